"""The stages of a bake, each a thin function artifact store -> artifact store over the science
packages (DESIGN.md "The data flow"): `run_ingest`, `run_geometry`, `run_cpm_tile` /
`run_cpm_top`, `run_avis_tile` / `run_avis_top`, `run_btf`, `run_srf_shard` / `run_srf_top`, `run_export`,
`run_render` and `run_deformed` (previews, from the written USD).

Each `run_*` takes a StageContext and a shard index, writes its output atomically under a
content-derived key and returns that key; when the key already exists it returns at once
("already there" is success), so a retried or duplicated task is harmless. The same functions
run in-process (`texelbake.pipeline.run.bake`) and as Celery tasks (`workers.tasks`).
"""

from texelbake.stages.avis import avis_levels, run_avis_tile, run_avis_top
from texelbake.stages.btf import run_btf
from texelbake.stages.context import StageContext
from texelbake.stages.cpm import cpm_levels, run_cpm_tile, run_cpm_top
from texelbake.stages.export import export_to, run_export, write_run
from texelbake.stages.geometry import run_geometry
from texelbake.stages.ingest import run_ingest
from texelbake.stages.render import run_deformed, run_render
from texelbake.stages.srf import run_srf_shard, run_srf_top

__all__ = [
    "StageContext", "avis_levels", "cpm_levels", "export_to", "run_avis_tile", "run_avis_top",
    "run_btf", "run_cpm_tile", "run_cpm_top", "run_deformed", "run_export", "run_geometry", "run_ingest",
    "run_render", "run_srf_shard", "run_srf_top", "write_run",
]
