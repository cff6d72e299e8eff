"""The cpm stages: every level inside one tile of finest texels (`run_cpm_tile`, the farm's
shard), then the levels coarser than a tile (`run_cpm_top`); the science is
`texelbake.cpm.level`.

A coarse texel's a_vis and held-out truth are sums over all its dense samples (a top level's
texels together hold every sample of the atlas), and they do not depend on the fit. Each tile
shard sums its own samples for the one texel above it at every top level (`top_sums`, an
artifact beside its levels), and the top shard adds the tiles' sums in tile order
(`gathered_sums`): the work is the same, but it is spread over the tile shards instead of
being one worker's serial pass over the whole atlas per top level. A store whose tiles
predate the sums (or lack one) has the top shard read the samples itself.

`fit_level` is where `BakeSettings.texel_classes` stores the exact texels as one point each
(`texelbake.cpm.level_by_need`) and `BakeSettings.fit_method` chooses the level fit of the rest: many texels at once from
their Gram matrices (`texelbake.cpm.level_batched`) or one texel at a time on its R, the
seed's loop (`texelbake.cpm.level_per_texel`); same arrays either way."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import torch
from threadpoolctl import ThreadpoolController

from texelbake.cpm.dense import DenseSums, dense_sums
from texelbake.cpm.level import (
    FitInputs,
    PointSet,
    concat_levels,
    direction_sets,
    level_candidates,
    samples_in,
    sort_by_texel,
    tile_texels,
)
from texelbake.cpm.level_batched import fit_level_batched
from texelbake.cpm.level_by_need import fit_level_by_need
from texelbake.cpm.level_per_texel import cell_fbar_per_texel, fit_level_per_texel
from texelbake.cpm.texel_fit import FitCounts
from texelbake.stages.avis import fit_avis_o
from texelbake.stages.context import StageContext


def fit_level(
    src: FitInputs, level: int, texels: np.ndarray, candidates: PointSet,
    sums: DenseSums | None = None, counts: FitCounts | None = None,
    avis_o: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """One level's fit of `texels` (flat ids at `level`) among `candidates`, by
    BakeSettings.fit_method: "batched" (`level_batched.fit_level_batched`) or "per_texel"
    (`level_per_texel.fit_level_per_texel`, the seed's loop). Same arrays either way, and
    `rays` (1,) int64: the rays the fit cast.

    sums : the texels' `DenseSums`, already summed (the top levels' from the tile shards):
        the batched fit then reads no dense sample; the per-texel loop computes its own.
    counts : `FitCounts` the batched fit adds its search's work to.
    avis_o : (t, n_o) the texels' a_vis on the view grid from the children's maps
        (`stages.avis.fit_avis_o`, BakeSettings.avis_coarse = "children"): the batched fit
        casts no a_vis ray; the per-texel loop (the seed's) ignores it."""
    s = src.settings
    # Per-texel matrices are small (d x m, m ~ tens to hundreds): BLAS and torch thread pools
    # only add contention (measured on a loaded 2-core machine: a 1024 x 16 SVD takes 1.5 ms on
    # 1 torch thread and 78 ms on 2; a 4096 x 256 QR went from milliseconds to minutes with
    # multi-threaded OpenBLAS). Parallelism comes from shards / worker processes instead.
    torch.set_num_threads(1)
    rays0 = src.caster.rays_cast
    def seed_fit(tex: np.ndarray, cands: PointSet) -> dict[str, np.ndarray]:
        if s.fit_method == "per_texel":
            return fit_level_per_texel(src, level, tex, cands)
        sub = avis_o
        if avis_o is not None and tex is not texels:  # a subset (the texels not exact)
            order = np.argsort(texels, kind="stable")
            sub = avis_o[order[np.searchsorted(texels, tex, sorter=order)]]
        return fit_level_batched(src, level, tex, cands, sums, counts, sub)

    with _blas_pools().limit(limits=1):
        # texels are classed at the finest `classed_levels` levels, which the settings keep
        # inside every tile (a top level is fitted from sums without its dense samples:
        # classing one would make the result depend on shard_texels); the coarser levels
        # choose among their children's points, an exact child's one point included.
        # No BTF table: an exact texel builds no F to sum
        if s.texel_classes == "by_need" and level < s.classed_levels and not s.btf:
            assert sums is None, "a classed level is inside the tiles (BakeSettings._check)"
            out = fit_level_by_need(src, level, texels, candidates, seed_fit)
        else:
            out = seed_fit(texels, candidates)
    out["rays"] = np.array([src.caster.rays_cast - rays0], np.int64)  # work done, for rays/s
    if s.fit_method == "per_texel" and "fbar" in out and level == 0 and s.btf_table == "cell":
        out["fbar"] = cell_fbar_per_texel(src, texels, candidates)
    return out


@functools.cache
def _blas_pools() -> ThreadpoolController:
    """The thread pools loaded in this process (numpy's BLAS, torch's), found once: a
    `threadpool_limits` per fit scans the process's libraries again each time."""
    return ThreadpoolController()


def level_key(ctx: StageContext, level: int, tile: int | None) -> str:
    """Key of one level's fit within one tile (or the top shard)."""
    name = f"L{level:02d}-tile{tile:05d}-s{ctx.settings.shard_texels}.npz" if tile is not None \
        else f"L{level:02d}-top.npz"
    return ctx.key("cpm", name)


def sums_key(ctx: StageContext, tile: int) -> str:
    """Key of one tile's `DenseSums` for the texels above it at every top level."""
    return ctx.key("cpm", f"sums-tile{tile:05d}-s{ctx.settings.shard_texels}.npz")


def has_top(ctx: StageContext) -> bool:
    """Whether the atlas has levels coarser than a tile (a `cpm_top` shard)."""
    return ctx.tile_levels < ctx.n_levels


def tile_ancestor(ctx: StageContext, tile: int, level: int) -> int:
    """Flat id at `level` (>= tile_levels - 1) of the one texel that holds tile `tile`."""
    s = ctx.settings
    per_row = s.atlas_resolution // s.shard_texels
    tr, tc = divmod(int(tile), per_row)
    up = level - (ctx.tile_levels - 1)
    return (tr >> up) * (s.atlas_resolution >> level) + (tc >> up)


def top_sums(ctx: StageContext, tile: int) -> dict[str, np.ndarray]:
    """The tile's samples summed for its ancestor texel at every top level (`DenseSums`,
    arrays prefixed `L{level}_`)."""
    s = ctx.settings
    src = ctx.fit_inputs()
    last = ctx.tile_levels - 1
    samples = samples_in(src.geo, s.atlas_resolution, last,
                         tile_texels(s.atlas_resolution, s.shard_texels, tile, last))
    out: dict[str, np.ndarray] = {}
    for level in range(ctx.tile_levels, ctx.n_levels):  # loop over top levels
        anc = np.array([tile_ancestor(ctx, tile, level)], np.int64)
        out.update(top_level_sums(src, level, anc, samples).to_arrays(f"L{level}_"))
    return out


def top_level_sums(src, level: int, texels: np.ndarray, samples: np.ndarray) -> DenseSums:
    """One top level's share of a tile's sums (its own function so that benchmarks time it
    as that level's work, `benchmarks/_bake_child.py`); without a_vis when the top levels take
    theirs from the children's maps (`coarse_avis`)."""
    return dense_sums(src, level, texels, samples, avis=not coarse_avis(src.settings))


def coarse_avis(settings) -> bool:
    """Whether coarse levels take their fit's a_vis from the a_vis stage's maps (the
    children's summed) rather than from rays of its dense samples (`cpm.dense.avis_sums`)."""
    return settings.avis_coarse == "children" and settings.fit_method == "batched"


def run_cpm_tile(ctx: StageContext, shard: int) -> str:
    """Every level inside one tile, finest first (coarser levels select from their children);
    with levels above the tile, first the tile's sums for them (`top_sums`)."""
    s = ctx.settings
    if has_top(ctx) and not ctx.store.exists(sums_key(ctx, shard)):
        ctx.store.write_arrays(sums_key(ctx, shard), top_sums(ctx, shard))
    last = level_key(ctx, ctx.tile_levels - 1, shard)
    if ctx.store.exists(last):
        return last
    children = grandchildren = None
    for level in range(ctx.tile_levels):
        key = level_key(ctx, level, shard)
        if ctx.store.exists(key):
            grandchildren, children = children, ctx.store.read_arrays(key)
            continue
        texels = tile_texels(s.atlas_resolution, s.shard_texels, shard, level)
        cands = level_candidates(ctx.fit_inputs(), level, texels, children, grandchildren)
        avis_o = (fit_avis_o(ctx, level, texels, shard)
                  if level > 0 and coarse_avis(s) else None)
        grandchildren = children
        children = fit_level(ctx.fit_inputs(), level, texels, cands, avis_o=avis_o)
        ctx.store.write_arrays(key, children)
    return last


def empty_top_sums(ctx: StageContext) -> dict[int, DenseSums]:
    """Zero `DenseSums` of every texel of every top level."""
    dirs = direction_sets(ctx.settings)
    return {lv: DenseSums.zeros((ctx.settings.atlas_resolution >> lv) ** 2, dirs)
            for lv in range(ctx.tile_levels, ctx.n_levels)}


def add_tile_sums(ctx: StageContext, acc: dict[int, DenseSums], tile: int,
                  arrays) -> None:
    """Add one tile's `top_sums` arrays into `acc` (`empty_top_sums`), in place."""
    for lv, sums in acc.items():  # loop over top levels
        sums.add_row(tile_ancestor(ctx, tile, lv), DenseSums.from_arrays(arrays, f"L{lv}_"))


def gathered_sums(ctx: StageContext) -> dict[int, DenseSums] | None:
    """Every top level's `DenseSums` of all its texels, the tiles' sums added in tile order
    (deterministic); None when a tile's sums are not in the store (tiles baked before they
    existed): the top shard then reads the samples itself."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    keys = [sums_key(ctx, t) for t in range(n_tiles)]
    if not all(ctx.store.exists(k) for k in keys):
        return None
    out = empty_top_sums(ctx)
    for t, key in enumerate(keys):  # loop over tiles, in order: the sums' order is fixed
        add_tile_sums(ctx, out, t, ctx.store.read_arrays(key))
    return out


def run_cpm_top(ctx: StageContext, shard: int = 0) -> str:
    """Levels coarser than a tile, from the tiles' coarsest level and the tiles' sums."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    last = level_key(ctx, ctx.n_levels - 1, None)
    if ctx.store.exists(last):
        return last
    lvl = ctx.tile_levels - 1
    children = concat_levels(
        [ctx.store.read_arrays(level_key(ctx, lvl, t)) for t in range(n_tiles)]
    )
    grandchildren = None
    if s.hierarchy == "grandchildren" and lvl >= 1:  # the tiles' level below their last
        grandchildren = concat_levels(
            [ctx.store.read_arrays(level_key(ctx, lvl - 1, t)) for t in range(n_tiles)])
    sums = gathered_sums(ctx)
    for level in range(ctx.tile_levels, ctx.n_levels):
        key = level_key(ctx, level, None)
        if ctx.store.exists(key):
            grandchildren, children = children, ctx.store.read_arrays(key)
            continue
        n_l = s.atlas_resolution >> level
        texels = np.arange(n_l * n_l, dtype=np.int64)
        cands = level_candidates(ctx.fit_inputs(), level, texels, children, grandchildren)
        grandchildren = children
        avis_o = fit_avis_o(ctx, level, texels, None) if coarse_avis(s) else None
        lsums = sums[level] if sums is not None else None
        if lsums is not None and avis_o is not None:
            lsums = dataclasses.replace(lsums, avis_o=avis_o, area_avis=lsums.area)
        children = fit_level(ctx.fit_inputs(), level, texels, cands, lsums, avis_o=avis_o)
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
