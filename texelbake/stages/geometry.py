"""The geometry stage: the mesh hierarchy M1..Mn, the UV atlas on M1, dense samples on M_org,
their texel assignment at every mip level and the texel frames (`texelbake.geometry.build`)."""

from __future__ import annotations

from texelbake.geometry.build import build_geometry
from texelbake.io.spool import FileSpool
from texelbake.stages.context import StageContext


def run_geometry(ctx: StageContext, shard: int = 0) -> str:
    """Mesh hierarchy, atlas on M1, dense samples on M_org, texel assignment and frames."""
    key = ctx.geometry_key()
    if ctx.store.exists(key):
        return key
    # the per-sample arrays (2.5 GB at 512²) go to disk a chunk at a time, beside the
    # artifact, and are copied into it from there: the stage holds one chunk
    folder = ctx.store.path(key).parent
    FileSpool.sweep(folder)  # a killed worker's spool (its pid is gone)
    spool = FileSpool(folder)
    try:
        out = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels, spool,
                             normal_input=ctx.normal_input())
        key = ctx.store.write_arrays(key, out)
        del out
    finally:
        spool.close()
    return key
