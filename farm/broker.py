"""Sending by task name, and the broker's identity (a restarted Redis has a new run id)."""

from __future__ import annotations

import re
import threading

import redis

from farm.ledger import Sender

_RUN_ID = re.compile(rb"^run_id:([0-9A-Za-z]+)", re.M)
_clients: dict[tuple[str, float], redis.Redis] = {}
_clients_lock = threading.Lock()


def _client(redis_url: str, timeout: float) -> redis.Redis:
    """One pooled client per (URL, timeout) and process, its INFO reply left unparsed: a new
    connection and redis-py's parse of the whole section were 40 % of a POST /jobs' CPU."""
    with _clients_lock:
        r = _clients.get((redis_url, timeout))
        if r is None:
            r = redis.Redis.from_url(redis_url, socket_timeout=timeout,
                                     socket_connect_timeout=timeout)
            r.set_response_callback("INFO", lambda raw, **_: raw)
            _clients[(redis_url, timeout)] = r
        return r


def broker_run_id(redis_url: str, timeout: float = 2.0) -> str | None:
    """Redis `run_id` (changes on every restart: queued messages were lost), None if down."""
    try:
        raw = _client(redis_url, timeout).execute_command("INFO", "server")
    except (redis.RedisError, OSError):
        return None
    m = _RUN_ID.search(raw if isinstance(raw, bytes) else str(raw).encode())
    return m.group(1).decode() if m else None


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
