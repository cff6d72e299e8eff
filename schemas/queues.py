"""The farm's queues: one per workload, the families of workers that serve them, and the queue
of every stage a plan can hold.

The one table of queues: the core's plan (`texelbake.pipeline.plan.plan_bake`) reads the stage
queues, the Celery configuration declares `QUEUES`, the local launcher and docker-compose.yml
start one kind of worker per family, and admission groups its backlog by family.
"""

from __future__ import annotations

#: one queue per workload, in the order the farm view lists them
QUEUES: tuple[str, ...] = ("ingest", "geometry", "cpm", "avis", "btf", "export", "render")

#: worker families: queues served by one kind of worker process (compose and `texelbake stack`)
QUEUE_FAMILIES: dict[str, tuple[str, ...]] = {
    "prep": ("ingest", "geometry", "export"),
    "numeric": ("cpm", "avis", "btf"),
    "render": ("render",),
}

#: the queue of the plan task (a job's first message) and Celery's default queue
PLAN_QUEUE = "ingest"

#: stage name -> the queue its shards go to
STAGE_QUEUES: dict[str, str] = {
    "ingest": "ingest",
    "geometry": "geometry",
    "cpm": "cpm",
    "cpm_top": "cpm",
    "avis": "avis",
    "avis_top": "avis",
    "btf": "btf",
    "srf": "render",  # captured with the renderer, sharded by camera
    "srf_top": "render",
    "export": "export",
    "render": "render",
    "deformed": "render",
}
