"""Celery configuration: queues per workload, late acks, prefetch 1, redelivery, retries.

Read by the workers' app (`workers.celery_app`) and by the API's sending app alike; the queues
are the one table (`schemas.queues`), the broker URL and the visibility timeout come from the
one settings class (`farm.config.Settings`).
"""

from __future__ import annotations

from kombu import Queue

from farm.config import Settings, get_settings
from schemas.queues import PLAN_QUEUE, QUEUES


def celery_config(settings: Settings | None = None) -> dict:
    st = settings or get_settings()
    return {
        "broker_url": st.redis_url,
        "result_backend": None,  # job state lives in the database, not in Redis
        "task_ignore_result": True,
        "task_queues": [Queue(q, routing_key=q) for q in QUEUES],
        "task_default_queue": PLAN_QUEUE,
        "task_create_missing_queues": False,
        # a message is acknowledged only after the task returns; a worker that dies (kill -9,
        # OOM) puts it back; the redelivery cap is counted in the shard ledger (max_attempts)
        "task_acks_late": True,
        "task_reject_on_worker_lost": True,
        "worker_prefetch_multiplier": 1,
        # a task past this is killed by its worker's parent process (SIGKILL of the pool child,
        # so a hang in C code that holds the GIL is ended too); its message is acked and the
        # ledger's sweeper re-queues the shard once its heartbeats are stale (ledger.sweep)
        "task_time_limit": st.task_hard_time_limit,
        "broker_transport_options": {
            # unacked messages come back after this long: above the longest shard
            "visibility_timeout": st.visibility_timeout,
        },
        "broker_connection_retry": True,
        "broker_connection_retry_on_startup": True,
        "broker_connection_max_retries": None,  # survive a Redis restart
        "worker_cancel_long_running_tasks_on_connection_loss": False,
        "task_serializer": "json",
        "accept_content": ["json"],
        "worker_send_task_events": False,
        "worker_hijack_root_logger": False,
        "worker_proc_alive_timeout": 120.0,  # a child imports torch/open3d/pxr when its parent did not
        "enable_utc": True,
    }
