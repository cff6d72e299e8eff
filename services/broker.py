"""Sending by task name, and the broker's identity (a restarted Redis has a new run id)."""

from __future__ import annotations

import redis

from services.ledger import Sender


def broker_run_id(redis_url: str, timeout: float = 2.0) -> str | None:
    """Redis `run_id` (changes on every restart: queued messages were lost), None if down."""
    try:
        r = redis.Redis.from_url(redis_url, socket_timeout=timeout, socket_connect_timeout=timeout)
        try:
            return str(r.info("server")["run_id"])
        finally:
            r.close()
    except (redis.RedisError, OSError):
        return None


def celery_sender(app) -> Sender:  # noqa: ANN001
    def send(task: str, args: tuple, queue: str, task_id: str) -> None:
        app.send_task(
            task,
            args=list(args),
            queue=queue,
            routing_key=queue,
            task_id=task_id,
            retry=True,
            retry_policy={"max_retries": 2, "interval_start": 0.2, "interval_step": 0.5},
        )

    return send
