"""The a_vis hierarchy: one level of a tile, coarsening by exact additivity, tiles stacked."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from texelbake.cpm.avis.by_need import K_SAMPLES, by_need_maps
from texelbake.cpm.avis.closed_form import (
    ClosedForm,
    closed_form_maps,
    closed_form_terms,
    merge_terms,
    unoccluded_samples,
)
from texelbake.cpm.avis.cube import OccludedFn
from texelbake.cpm.avis.maps import avis_cube_maps, coerce_samples, default_eps
from texelbake.errors import SettingsError, ShapeError

# --------------------------------------------------------------------------------------------
# hierarchy


def coarsen_maps(maps: np.ndarray) -> np.ndarray:
    """Sum 2 x 2 children into their parent (a_vis is additive over disjoint sample sets).

    maps : (N * N, ...) texels of an N x N atlas level in row-major order (texel = iy * N + ix)
    returns : (N/2 * N/2, ...) same dtype; exact in a shared (world) direction frame
    """
    a = np.asarray(maps)
    n = a.shape[0]
    side = int(round(np.sqrt(n)))
    if side * side != n or side % 2 or side == 0:
        raise ShapeError(f"maps must hold N*N texels with N even, got {n} texels")
    h = side // 2
    b = a.reshape(h, 2, h, 2, *a.shape[1:])
    return b.sum(axis=(1, 3)).reshape(h * h, *a.shape[1:])


def _children(n_side: int) -> np.ndarray:
    """(N/2 * N/2, 4) int64 child texel ids of each parent, row-major."""
    h = n_side // 2
    py, px = np.meshgrid(np.arange(h), np.arange(h), indexing="ij")
    kids = [(2 * py + dy) * n_side + (2 * px + dx) for dy in (0, 1) for dx in (0, 1)]
    return np.stack([k.ravel() for k in kids], axis=1)


@dataclass(frozen=True)
class AvisLevel:
    """Uncompressed a_vis of one mip level (N x N texels, row-major ids iy * N + ix).

    n_side : N; res : cube face side
    closed : (N*N,) bool, texels in closed form (their terms in `cf`)
    bounded : (N*N,) bool, texels whose terms are in `cf`: every closed texel, and ray texels
        with at most `max_terms` distinct normals. For a ray texel the terms give the
        unoccluded projected area, a hard upper bound a_vis(w) <= sum_k A_k (n_k . w)^+ that
        the look-up applies (exact horizon: a_vis -> 0 as w -> grazing for a flat texel, which
        a cube map only resolves to one cube texel)
    cf : ClosedForm over the N*N texels (terms only for bounded texels)
    ray_texels : (r,) int64 ascending, the texels not in closed form
    ray_maps : (r, 6, res, res) float64 world-direction cube maps of those texels
    texel_area : (N*N,) float64 sum of dA_j (for the a_vis -> 0 floor)
    """

    n_side: int
    res: int
    closed: np.ndarray
    bounded: np.ndarray
    cf: ClosedForm
    ray_texels: np.ndarray
    ray_maps: np.ndarray
    texel_area: np.ndarray
    max_terms: int = 256

    def dense_maps(self) -> np.ndarray:
        """(N*N, 6, res, res) float64 maps of every texel (closed form evaluated at the cube
        directions)."""
        n = self.n_side * self.n_side
        out = np.zeros((n, 6, self.res, self.res), dtype=np.float64)
        closed_ids = np.flatnonzero(self.closed)
        out[closed_ids] = closed_form_maps(self.cf, self.res, closed_ids)
        out[self.ray_texels] = self.ray_maps
        return out


_LEVEL_ARRAYS = ("closed", "bounded", "cf_offsets", "cf_normals", "cf_areas", "ray_texels",
                 "ray_maps", "texel_area")


def level_to_arrays(level: AvisLevel) -> dict[str, np.ndarray]:
    """Named arrays of an AvisLevel (for np.savez in the artifact store between the per-tile
    and the top stages); inverse of `level_from_arrays`."""
    return {
        "meta": np.array([level.n_side, level.res, level.max_terms], dtype=np.int64),
        "closed": level.closed, "bounded": level.bounded, "cf_offsets": level.cf.offsets,
        "cf_normals": level.cf.normals, "cf_areas": level.cf.areas,
        "ray_texels": level.ray_texels, "ray_maps": level.ray_maps,
        "texel_area": level.texel_area,
    }


def level_from_arrays(arrays, *, maps: bool = True) -> AvisLevel:
    """AvisLevel from `level_to_arrays` output (any mapping of name -> array, e.g. an NpzFile).
    maps=False: without its ray maps (`ray_maps` need not be present and is left with no
    rows: the per-texel arrays of a level whose maps are read a chunk at a time)."""
    need = ("meta", *_LEVEL_ARRAYS) if maps else ("meta", *(k for k in _LEVEL_ARRAYS
                                                             if k != "ray_maps"))
    missing = [k for k in need if k not in arrays]
    if missing:
        raise ShapeError(f"a_vis level arrays are missing {missing}")
    n_side, res, max_terms = (int(x) for x in np.asarray(arrays["meta"]))
    ray_maps = (np.asarray(arrays["ray_maps"], np.float64) if maps
                else np.zeros((0, 6, res, res)))
    level = AvisLevel(
        n_side, res, np.asarray(arrays["closed"], bool), np.asarray(arrays["bounded"], bool),
        ClosedForm(np.asarray(arrays["cf_offsets"], np.int64),
                   np.asarray(arrays["cf_normals"], np.float64),
                   np.asarray(arrays["cf_areas"], np.float64)),
        np.asarray(arrays["ray_texels"], np.int64), ray_maps,
        np.asarray(arrays["texel_area"], np.float64), max_terms)
    n = n_side * n_side
    if (level.closed.shape != (n,) or level.cf.n_texels != n
            or (maps and level.ray_maps.shape != (level.ray_texels.shape[0], 6, res, res))):
        raise ShapeError(f"a_vis level arrays are inconsistent with n_side={n_side}, res={res}")
    return level


def stack_tiles(tiles: list[AvisLevel], tiles_per_side: int) -> AvisLevel:
    """One level from a row-major grid of equally sized tiles (the farm's per-tile results).

    tiles : T * T AvisLevels of side n (tile (ty, tx) at index ty * T + tx, local texel ids
        iy * n + ix), all with one res and max_terms
    returns : AvisLevel of side T * n with texel id (ty n + iy) (T n) + tx n + ix
    """
    level, ids = tile_layout(tiles, tiles_per_side)  # level.ray_texels: ids sorted
    order = np.argsort(np.concatenate(ids), kind="stable")
    maps = (np.concatenate([t.ray_maps for t in tiles])[order] if order.size
            else np.zeros((0, 6, level.res, level.res)))
    return dataclasses.replace(level, ray_maps=maps)


def tile_layout(tiles: list[AvisLevel], tiles_per_side: int
                ) -> tuple[AvisLevel, list[np.ndarray]]:
    """`stack_tiles` without the ray maps: the stacked level's per-texel arrays (its
    `ray_texels` ascending, `ray_maps` with no rows), and every tile's ray texels as ids of
    the stacked level, in the tile's own order (the order a reader of tile after tile meets
    them). The tiles' ray maps are not read."""
    t_side = int(tiles_per_side)
    if t_side < 1 or len(tiles) != t_side * t_side:
        raise ShapeError(f"expected {t_side}^2 tiles, got {len(tiles)}")
    n, res, max_terms = tiles[0].n_side, tiles[0].res, tiles[0].max_terms
    if any((t.n_side, t.res, t.max_terms) != (n, res, max_terms) for t in tiles):
        raise ShapeError("tiles must share n_side, res and max_terms")
    side = t_side * n
    iy, ix = np.divmod(np.arange(n * n), n)
    closed = np.zeros(side * side, dtype=bool)
    bounded = np.zeros(side * side, dtype=bool)
    area = np.zeros(side * side)
    owners, normals, areas, ray_ids = [], [], [], []
    for k, tile in enumerate(tiles):  # a loop over tiles
        ty, tx = divmod(k, t_side)
        gid = (ty * n + iy) * side + tx * n + ix  # (n*n,) local -> global
        closed[gid], bounded[gid], area[gid] = tile.closed, tile.bounded, tile.texel_area
        owners.append(gid[np.repeat(np.arange(n * n), np.diff(tile.cf.offsets))])
        normals.append(tile.cf.normals)
        areas.append(tile.cf.areas)
        ray_ids.append(gid[tile.ray_texels])
    cf = merge_terms(np.concatenate(owners), np.concatenate(normals), np.concatenate(areas),
                     side * side)
    return (AvisLevel(side, res, closed, bounded, cf, np.sort(np.concatenate(ray_ids)),
                      np.zeros((0, 6, res, res)), area, max_terms), ray_ids)


def avis_level(positions: np.ndarray, normals: np.ndarray, areas: np.ndarray,
               texel_of_sample: np.ndarray, n_side: int, res: int, occluded_fn: OccludedFn,
               mesh_points: np.ndarray, *, closed_form: bool = True, max_terms: int = 256,
               ray_eps: float | None = None, max_rays: int = 1 << 21,
               samples: str = "dense", k_samples: int = K_SAMPLES) -> AvisLevel:
    """a_vis of one atlas level: closed form where `unoccluded_samples` proves every sample of
    a texel free, rays (avis_cube_maps, world directions) elsewhere, none from a free sample.

    positions, normals : (m, 3) float64 samples and geometric normals; areas : (m,) float64
    texel_of_sample : (m,) int in [0, n_side^2); mesh_points : (v, 3) float64 M_org vertices
    closed_form : False forces rays for every texel (for measuring what the skip saves)
    max_terms : ray texels with at most this many distinct normals keep their unoccluded
        upper bound (see AvisLevel.bounded); closed texels always keep all their terms
    ray_eps : ray-origin offset and closed-form detection slack; default
        `default_eps(positions)`. When a level is computed in tiles (texel ids local to the
        tile, see `stack_tiles`), pass one scene-wide value so that every tile casts the rays
        the whole level would.
    samples : "dense" casts every sample's rays; "by_need" a texel's from one sample when its
        ray-casting samples are one facet and one visibility pattern, else from `k_samples`
        strata, each weighted by its area (`texelbake.cpm.avis.by_need`)
    returns : AvisLevel
    """
    pos, nrm, ar, tex, n_texels = coerce_samples(normals, areas, texel_of_sample,
                                                  int(n_side) ** 2, positions)
    eps = default_eps(pos) if ray_eps is None else float(ray_eps)
    if closed_form:
        # a texel is closed when all its samples are free; the free samples of the others
        # cast no rays either (theirs would all escape: `unoccluded_samples`)
        free = unoccluded_samples(pos, nrm, mesh_points, eps=eps)
        closed = np.bincount(tex[~free], minlength=n_texels) == 0
    else:
        free = None
        closed = np.zeros(n_texels, dtype=bool)
    cf, bounded = _bounded_terms(closed_form_terms(nrm, ar, tex, n_texels), closed,
                                 int(max_terms))
    ray_texels = np.flatnonzero(~closed)
    area = np.bincount(tex, weights=ar, minlength=n_texels)
    if samples == "by_need":
        maps = by_need_maps(pos, nrm, ar, tex, n_texels, res, occluded_fn, closed, free, cf,
                            bounded, eps=eps, max_rays=max_rays, k=k_samples)
    elif samples == "dense":
        maps = avis_cube_maps(pos, nrm, ar, tex, n_texels, None, res, occluded_fn,
                              skip_texels=closed, free_samples=free, ray_eps=eps,
                              max_rays=max_rays, dtype=np.float64)
    else:
        raise SettingsError(f"samples must be 'dense' or 'by_need', got {samples!r}")
    return AvisLevel(int(n_side), int(res), closed, bounded, cf, ray_texels, maps[ray_texels],
                     area, int(max_terms))


def _bounded_terms(cf: ClosedForm, closed: np.ndarray,
                   max_terms: int) -> tuple[ClosedForm, np.ndarray]:
    """Keep the terms of closed texels and of texels with <= max_terms terms."""
    counts = np.diff(cf.offsets)
    bounded = closed | (counts <= max_terms)
    owner = np.repeat(np.arange(cf.n_texels), counts)
    keep = bounded[owner]
    return merge_terms(owner[keep], cf.normals[keep], cf.areas[keep], cf.n_texels), bounded


def coarsen_level(level: AvisLevel) -> AvisLevel:
    """The parent level (N/2 x N/2) by exact additivity in world directions.

    A parent is in closed form iff its four children are (the union of sample sets that are
    each unoccluded in their hemispheres is unoccluded; terms concatenated, equal normals
    merged). Otherwise its map is the sum of the children's maps, closed-form children
    evaluated at the cube directions. The parents' texel frames are only needed at look-up.
    """
    n = level.n_side
    if n % 2 or n == 0:
        raise ShapeError(f"level n_side must be even to coarsen, got {n}")
    kids = _children(n)  # (P, 4)
    n_par = kids.shape[0]
    closed = level.closed[kids].all(axis=1)
    # terms of parents whose four children are bounded: children's terms re-owned, merged
    parent_of = np.empty(n * n, dtype=np.int64)
    parent_of[kids.ravel()] = np.repeat(np.arange(n_par), 4)
    owner_child = np.repeat(np.arange(n * n), np.diff(level.cf.offsets))
    owner = parent_of[owner_child]
    keep = level.bounded[kids].all(axis=1)[owner]
    cf, bounded = _bounded_terms(
        merge_terms(owner[keep], level.cf.normals[keep], level.cf.areas[keep], n_par),
        closed, level.max_terms)
    bounded &= level.bounded[kids].all(axis=1)
    ray_par = np.flatnonzero(~closed)
    row_of = np.full(n * n, -1, dtype=np.int64)
    row_of[level.ray_texels] = np.arange(level.ray_texels.shape[0])
    maps = np.zeros((ray_par.shape[0], 6, level.res, level.res), dtype=np.float64)
    for c in range(4):  # the four children
        kid = kids[ray_par, c]
        is_ray = row_of[kid] >= 0
        maps[is_ray] += level.ray_maps[row_of[kid[is_ray]]]
        if (~is_ray).any():
            maps[~is_ray] += closed_form_maps(level.cf, level.res, kid[~is_ray])
    area = level.texel_area[kids].sum(axis=1)
    return AvisLevel(n // 2, level.res, closed, bounded, cf, ray_par, maps, area,
                     level.max_terms)
