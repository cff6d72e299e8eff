"""The cpm stages: every level inside one tile of finest texels (`run_cpm_tile`, the farm's
shard), then the levels coarser than a tile (`run_cpm_top`); the science is
`texelbake.cpm.level`."""

from __future__ import annotations

import numpy as np

from texelbake.cpm.level import (
    concat_levels,
    level_candidates,
    sort_by_texel,
    tile_texels,
)
from texelbake.cpm.level_batched import fit_level
from texelbake.cpm.refit import refit_to_dense
from texelbake.stages.context import StageContext


def level_key(ctx: StageContext, level: int, tile: int | None) -> str:
    """Key of one level's fit within one tile (or the top shard)."""
    name = f"L{level:02d}-tile{tile:05d}-s{ctx.settings.shard_texels}.npz" if tile is not None \
        else f"L{level:02d}-top.npz"
    return ctx.key("cpm", name)


def run_cpm_tile(ctx: StageContext, shard: int) -> str:
    """Every level inside one tile, finest first (coarser levels select from their children)."""
    s = ctx.settings
    last = level_key(ctx, ctx.tile_levels - 1, shard)
    if ctx.store.exists(last):
        return last
    children = None
    for level in range(ctx.tile_levels):
        key = level_key(ctx, level, shard)
        if ctx.store.exists(key):
            children = ctx.store.read_arrays(key)
            continue
        texels = tile_texels(s.atlas_resolution, s.shard_texels, shard, level)
        cands = level_candidates(ctx.fit_inputs(), level, texels, children)
        children = refit_coarse(ctx, level, fit_level(ctx.fit_inputs(), level, texels, cands))
        ctx.store.write_arrays(key, children)
    return last


def refit_coarse(ctx: StageContext, level: int, out: dict[str, np.ndarray]
                 ) -> dict[str, np.ndarray]:
    """A coarse level's fit with its weights refitted to the dense Eq. 7 when the settings ask
    for it (`coarse_target="dense"` with `hierarchy="children"`; issue 11, item 3)."""
    s = ctx.settings
    if level == 0 or s.hierarchy != "children" or s.coarse_target != "dense":
        return out
    return refit_to_dense(ctx.fit_inputs(), level, out)


def run_cpm_top(ctx: StageContext, shard: int = 0) -> str:
    """Levels coarser than a tile, from the tiles' coarsest level."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    last = level_key(ctx, ctx.n_levels - 1, None)
    if ctx.store.exists(last):
        return last
    lvl = ctx.tile_levels - 1
    children = concat_levels(
        [ctx.store.read_arrays(level_key(ctx, lvl, t)) for t in range(n_tiles)]
    )
    for level in range(ctx.tile_levels, ctx.n_levels):
        key = level_key(ctx, level, None)
        if ctx.store.exists(key):
            children = ctx.store.read_arrays(key)
            continue
        n_l = s.atlas_resolution >> level
        texels = np.arange(n_l * n_l, dtype=np.int64)
        cands = level_candidates(ctx.fit_inputs(), level, texels, children)
        children = refit_coarse(ctx, level, fit_level(ctx.fit_inputs(), level, texels, cands))
        ctx.store.write_arrays(key, children)
    return last


def cpm_levels(ctx: StageContext) -> list[dict[str, np.ndarray]]:
    """All levels of the finished CPM, each sorted by texel id (for export and reports)."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    levels = []
    for level in range(ctx.n_levels):
        if level < ctx.tile_levels:
            parts = [ctx.store.read_arrays(level_key(ctx, level, t)) for t in range(n_tiles)]
            data = concat_levels(parts)
        else:
            data = ctx.store.read_arrays(level_key(ctx, level, None))
        levels.append(sort_by_texel(data))
    return levels
