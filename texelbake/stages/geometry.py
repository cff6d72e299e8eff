"""The geometry stage: the mesh hierarchy M1..Mn, the UV atlas on M1, dense samples on M_org,
their texel assignment at every mip level and the texel frames (`texelbake.geometry.build`)."""

from __future__ import annotations

from texelbake.geometry.build import build_geometry
from texelbake.stages.context import StageContext


def run_geometry(ctx: StageContext, shard: int = 0) -> str:
    """Mesh hierarchy, atlas on M1, dense samples on M_org, texel assignment and frames."""
    key = ctx.geometry_key()
    if ctx.store.exists(key):
        return key
    out = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels)
    return ctx.store.write_arrays(key, out)
