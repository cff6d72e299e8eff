"""The Celery app: `celery -A workers.celery_app worker -Q cpm -c 1 --prefetch-multiplier 1`.

Importing this module does not import torch or pxr (the API imports it to enqueue by name);
the tasks module is loaded by workers only (`include`).
"""

from __future__ import annotations

import os

from celery import Celery
from celery.signals import worker_init, worker_process_init

from farm.celeryconfig import celery_config

app = Celery("texelbake", include=["workers.tasks"])
app.conf.update(celery_config())


def _warm() -> bool:
    return os.environ.get("TEXELBAKE_WARM_IMPORT", "1") != "0"


@worker_init.connect
def _init_worker(**_kwargs) -> None:
    """The worker's parent imports the core pipeline (torch, open3d, pxr) once, before its
    prefork pool forks: every pool child, the first and the one that replaces a child lost
    mid-shard, starts warm in the time of a fork instead of re-importing (seconds, and tens of
    seconds on a loaded machine) before the shard it should run again. Importing starts no
    computation (no thread pool of BLAS, OpenMP or TBB is up yet), so forking after it is safe."""
    if _warm():
        import texelbake.pipeline.run  # noqa: F401


@worker_process_init.connect
def _init_pool_child(**_kwargs) -> None:
    """A forked pool child must not share the parent's pooled DB connections; the core
    pipeline is already imported (`_init_worker`), or is imported here, not inside its first
    shard's time."""
    from farm.db import dispose_engines

    dispose_engines()
    if _warm():
        import texelbake.pipeline.run  # noqa: F401
