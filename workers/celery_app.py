"""The Celery app: `celery -A workers.celery_app worker -Q cpm -c 1 --prefetch-multiplier 1`.

Importing this module does not import torch or pxr (the API imports it to enqueue by name);
the tasks module is loaded by workers only (`include`).
"""

from __future__ import annotations

from celery import Celery
from celery.signals import worker_process_init

from farm.celeryconfig import celery_config

app = Celery("texelbake", include=["workers.tasks"])
app.conf.update(celery_config())


@worker_process_init.connect
def _init_pool_child(**_kwargs) -> None:
    """A forked pool child must not share the parent's pooled DB connections; it imports the
    core pipeline (torch, open3d, pxr) once here, not inside its first shard's time."""
    import os

    from farm.db import dispose_engines

    dispose_engines()
    if os.environ.get("TEXELBAKE_WARM_IMPORT", "1") != "0":
        import texelbake.pipeline.run  # noqa: F401
