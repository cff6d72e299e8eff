"""The avis stages: a_vis cube maps of every level inside one tile (`run_avis_tile`), then the
levels coarser than a tile (`run_avis_top`); the science is `texelbake.cpm.avis`."""

from __future__ import annotations

import threading

import numpy as np

from texelbake.cpm import avis as avis_mod
from texelbake.cpm.avis.by_need import strata_for
from texelbake.cpm.avis.compress import CHUNK_ROWS, LevelChunks, chunks_of
from texelbake.cpm.avis.resample import avis_at
from texelbake.cpm.level import direction_sets, samples_in
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.tol import TOL


def _avis_level_arrays(level: avis_mod.AvisLevel, prefix: str) -> dict[str, np.ndarray]:
    return {f"{prefix}{k}": v for k, v in avis_mod.level_to_arrays(level).items()}


def _avis_level_from(data: dict[str, np.ndarray], prefix: str, *, maps: bool = True
                     ) -> avis_mod.AvisLevel:
    return avis_mod.level_from_arrays(
        {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)}, maps=maps
    )


def _avis_key(ctx: StageContext, tile: int | None) -> str:
    # tiles named by layout
    fields = GEOMETRY_FIELDS + ("avis_resolution", "avis_level0", "shard_texels")
    name = f"tile{tile:05d}-s{ctx.settings.shard_texels}.npz" if tile is not None else "top.npz"
    return ctx.key("avis", name, fields)


def run_avis_tile(ctx: StageContext, shard: int) -> str:
    """a_vis cube maps of every level inside one tile (seed 000 §3.4): closed form where it is
    provably exact, rays elsewhere; coarser levels by exact additivity over children."""
    key = _avis_key(ctx, shard)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    geo = ctx.geometry()
    n, side = s.atlas_resolution, s.shard_texels
    tr, tc = divmod(shard, n // side)
    # the tile is one texel of level log2(side): its samples from the Z-order index
    idx = samples_in(geo, n, side.bit_length() - 1, np.array([shard]))
    row, col = geo["sample_row"][idx], geo["sample_col"][idx]
    local = (row - tr * side) * side + (col - tc * side)
    caster = ctx.caster()
    rays0 = caster.rays_cast
    level = avis_mod.avis_level(
        geo["sample_pos"][idx], geo["sample_gnrm"][idx], geo["sample_area"][idx], local, side,
        s.avis_resolution, caster.occluded, ctx.asset().points,
        ray_eps=TOL.ray_offset * caster.bbox_diag, samples=s.avis_level0,
        k_samples=strata_for(n),
    )
    out = _avis_level_arrays(level, "L00_")
    out["rays"] = np.array([caster.rays_cast - rays0], np.int64)
    for lvl in range(1, ctx.tile_levels):
        level = avis_mod.coarsen_level(level)
        out.update(_avis_level_arrays(level, f"L{lvl:02d}_"))
    return ctx.store.write_arrays(key, out)


def avis_tile_meta(ctx: StageContext) -> list[dict[str, np.ndarray]]:
    """Every tile's a_vis artifact without its maps (the per-texel arrays of all its levels and
    its ray count), one read per tile: what `avis_level_chunks` and `avis_rays` need of every
    tile, read once for all levels."""
    per_row = ctx.settings.atlas_resolution // ctx.settings.shard_texels
    return [ctx.store.read_arrays(_avis_key(ctx, t), lambda name: not name.endswith("ray_maps"))
            for t in range(per_row * per_row)]  # a loop over tiles


def avis_rays(ctx: StageContext, meta: list[dict[str, np.ndarray]] | None = None) -> int:
    """Rays the a_vis tiles cast (closed-form texels cast none). meta : `avis_tile_meta`, if
    already read."""
    meta = avis_tile_meta(ctx) if meta is None else meta
    return int(sum(int(d.get("rays", np.zeros(1)).sum()) for d in meta))


def run_avis_top(ctx: StageContext, shard: int = 0) -> str:
    """Levels coarser than a tile: the tiles' coarsest maps placed side by side, then summed."""
    key = _avis_key(ctx, None)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    per_row = s.atlas_resolution // s.shard_texels
    top = f"L{ctx.tile_levels - 1:02d}_"
    parts = [_avis_level_from(ctx.store.read_arrays(_avis_key(ctx, t)), top)
             for t in range(per_row * per_row)]
    level = avis_mod.stack_tiles(parts, per_row)
    out = {}
    for lvl in range(ctx.tile_levels, ctx.n_levels):
        level = avis_mod.coarsen_level(level)
        out.update(_avis_level_arrays(level, f"L{lvl:02d}_"))
    return ctx.store.write_arrays(key, out)


def avis_levels(ctx: StageContext) -> list[avis_mod.AvisLevel]:
    """Every level's a_vis over the whole atlas (tiles assembled)."""
    s = ctx.settings
    n, side = s.atlas_resolution, s.shard_texels
    per_row = n // side
    tiles = [ctx.store.read_arrays(_avis_key(ctx, t)) for t in range(per_row * per_row)]
    top = ctx.store.read_arrays(_avis_key(ctx, None)) if ctx.tile_levels < ctx.n_levels else {}
    levels = []
    for lvl in range(ctx.n_levels):
        if lvl < ctx.tile_levels:
            parts = [_avis_level_from(d, f"L{lvl:02d}_") for d in tiles]
            levels.append(avis_mod.stack_tiles(parts, per_row))
        else:
            levels.append(_avis_level_from(top, f"L{lvl:02d}_"))
    return levels


def avis_level_chunks(ctx: StageContext, lvl: int,
                      meta: list[dict[str, np.ndarray]] | None = None) -> LevelChunks:
    """One level's a_vis for the export's compression (`cpm.avis.compress`), its ray maps read
    a tile at a time (at most `CHUNK_ROWS` ray texels per chunk) instead of stacked: the
    per-texel arrays of every tile, each tile's maps only when its chunk is read (memory
    bounded whatever the atlas size). Levels coarser than a tile are one artifact, read whole.
    meta : `avis_tile_meta`, if already read (the export reads it once for every level)."""
    s = ctx.settings
    prefix = f"L{lvl:02d}_"
    if lvl >= ctx.tile_levels:
        return chunks_of(_avis_level_from(ctx.store.read_arrays(
            _avis_key(ctx, None), lambda name: name.startswith(prefix)), prefix))
    per_row = s.atlas_resolution // s.shard_texels
    keys = [_avis_key(ctx, t) for t in range(per_row * per_row)]
    maps_name = f"{prefix}ray_maps"
    meta = avis_tile_meta(ctx) if meta is None else meta
    metas = [_avis_level_from(d, prefix, maps=False) for d in meta]  # a loop over tiles
    level, ids = avis_mod.tile_layout(metas, per_row)
    pieces = [(t, a, min(a + CHUNK_ROWS, len(ids[t])))  # (tile, rows a..b of its maps)
              for t in range(len(ids)) for a in range(0, len(ids[t]), CHUNK_ROWS)]
    # consecutive pieces joined into chunks of at most CHUNK_ROWS rows: a level's tiles hold
    # few ray texels each (a level-3 tile of 8² texels one), and every pass over the chunks
    # pays a fixed cost per chunk
    groups: list[list[tuple[int, int, int]]] = []
    rows = CHUNK_ROWS
    for piece in pieces:  # a loop over tiles' pieces
        if rows + piece[2] - piece[1] > CHUNK_ROWS:
            groups.append([])
            rows = 0
        groups[-1].append(piece)
        rows += piece[2] - piece[1]
    bounds = np.zeros(len(groups) + 1, np.int64)
    np.cumsum([sum(b - a for _, a, b in g) for g in groups], out=bounds[1:])
    last: dict[int, np.ndarray] = {}  # the tile read last (its pieces come one after another)

    def tile_rows(t: int, a: int, b: int) -> np.ndarray:
        if t not in last:
            last.clear()
            last[t] = ctx.store.read_arrays(keys[t], lambda name: name == maps_name)[maps_name]
        return last[t][a:b]

    lock = threading.Lock()  # the passes read chunks from several threads

    def read(i: int) -> np.ndarray:
        with lock:
            parts = [tile_rows(t, a, b) for t, a, b in groups[i]]
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    return LevelChunks(level, np.concatenate(ids) if ids else np.zeros(0, np.int64), bounds,
                       read)


def fit_avis_o(ctx: StageContext, level: int, texels: np.ndarray, tile: int | None
               ) -> np.ndarray:
    """a_vis on the fit's view grid of `texels` (flat ids at `level`, all in tile `tile`, or
    None for the levels above a tile) from this stage's maps of that level, i.e. its children's
    summed (`cpm.avis.resample.avis_at`): what `BakeSettings.avis_coarse = "children"` hands
    the fit of a coarse level instead of recasting every dense sample's rays.

    returns : (t, n_o) float64, texel-frame directions `direction_sets(settings)["dirs_o"]`
    """
    s = ctx.settings
    texels = np.asarray(texels, np.int64)
    prefix = f"L{level:02d}_"
    if tile is None or level >= ctx.tile_levels:
        local = texels
        arrays = ctx.store.read_arrays(_avis_key(ctx, None), lambda k: k.startswith(prefix))
    else:
        n_l, side_l = s.atlas_resolution >> level, s.shard_texels >> level
        tr, tc = divmod(int(tile), s.atlas_resolution // s.shard_texels)
        row, col = np.divmod(texels, n_l)
        local = (row - tr * side_l) * side_l + (col - tc * side_l)
        arrays = ctx.store.read_arrays(_avis_key(ctx, tile), lambda k: k.startswith(prefix))
    frames = ctx.geometry()[f"frames_L{level}"][texels]
    return avis_at(_avis_level_from(arrays, prefix), local, frames,
                   direction_sets(s)["dirs_o"])
