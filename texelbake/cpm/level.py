"""What fitting one CPM level over a set of texels reads (seed 000 §3.2–3.3): the fit's inputs,
texel ids and the samples of texels, the direction sets, visibility rays against M_org and the
BRDFs of the samples, and the candidates of a coarse level (its children's points, or all
dense samples). The fits themselves: `level_batched` (many texels at once) and
`level_per_texel` (the seed's loop); `texelbake.stages.cpm` chooses one by
`BakeSettings.fit_method`.

Inputs are the geometry stage's arrays (`FitInputs.geo`: samples, texel assignment, frames),
a ray caster over M_org and the asset's materials; outputs are plain arrays per level, CSR by
texel (`offsets`), which the cpm stage stores per tile.

Per-texel randomness is seeded by (settings.seed, level, texel), never by shard, so the result
does not depend on how texels are sharded.
"""

from __future__ import annotations

import functools
import hashlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp

from schemas.settings import BakeSettings
from texelbake import brdf as brdf_mod
from texelbake.arrays import concat_ranges
from texelbake.geometry import directions
from texelbake.geometry.basis import grid_to_local, grid_to_world, tangent_frames
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.texels import morton
from texelbake.model import Material
from texelbake.tol import TOL

_TAG_LIGHT, _TAG_VIEW, _TAG_HELD_I, _TAG_HELD_O = 0x11, 0x22, 0x33, 0x44
_TAG_VAL_I, _TAG_VAL_O = 0x55, 0x66
_TAG_LOBE_I, _TAG_LOBE_O = 0x77, 0x88

#: light and view directions of the validation pairs (VALIDATION x VALIDATION), on which
#: point_lobe="widened" chooses each texel's lobes (`texelbake.cpm.lobe`): independent of the
#: training grid and of the held-out pairs, which stay the measure; 8 x 8 chose the widened
#: lobes on the bolt's shadowing bumps where the held-out pairs did not (docs/decisions.md,
#: "A characteristic point carries the normal spread…")
VALIDATION = 16
#: light and view directions of the pairs on which BakeSettings.lobe_class keeps a texel's
#: lobes (`texelbake.cpm.lobe_class`): 8 x 8 let texels through whose held-out SNR was near
#: 0 dB (docs/decisions.md, "A curved texel of one material is a few lobes")
LOBE_VALIDATION = 16


@dataclass(frozen=True)
class FitInputs:
    """What fitting a level reads: the bake settings, the geometry stage's arrays, a ray caster
    over M_org (all objects of the asset) and the asset's materials."""

    settings: BakeSettings
    geo: Mapping[str, np.ndarray]
    caster: RayCaster
    materials: Sequence[Material]


def texel_ids(geo: Mapping[str, np.ndarray], n: int, level: int,
              samples: np.ndarray | None = None) -> np.ndarray:
    """(m,) int64 flat texel id of every sample at `level` (row * N_l + col); with `samples`,
    of those samples only."""
    n_l = n >> level
    row, col = geo["sample_row"], geo["sample_col"]
    if samples is not None:
        row, col = row[samples], col[samples]
    return (row >> level) * n_l + (col >> level)


def zorder_runs(geo: Mapping[str, np.ndarray], n: int, level: int,
                texels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lo, hi) (t,) int64: each of `texels` (flat ids at `level`) as its run
    sample_zorder[lo:hi] of the geometry stage's Z-order index (4^level finest codes)."""
    zoff = geo["texel_zoffsets"]
    r, c = np.divmod(texels, n >> level)
    first = morton(r << level, c << level)
    return (np.asarray(zoff[first], np.int64),
            np.asarray(zoff[first + (1 << (2 * level))], np.int64))


def texel_counts(geo: Mapping[str, np.ndarray], n: int, level: int,
                 texels: np.ndarray) -> np.ndarray:
    """(t,) int64 dense samples of each of `texels` (flat ids at `level`) in the whole atlas
    (a tile holds only its part of a top level's texel)."""
    texels = np.asarray(texels, np.int64)
    if "sample_zorder" not in geo:  # artifacts from before the Z-order index
        return np.bincount(texel_ids(geo, n, level), minlength=(n >> level) ** 2)[texels]
    lo, hi = zorder_runs(geo, n, level, texels)
    return hi - lo


def samples_in(geo: Mapping[str, np.ndarray], n: int, level: int,
               texels: np.ndarray) -> np.ndarray:
    """(k,) int64 ids of the samples of `texels` (flat ids at `level`), ascending, as
    `np.flatnonzero(np.isin(texel_ids(geo, n, level), texels))` gives them. Read from the
    geometry stage's Z-order index (`sample_zorder`, `texel_zoffsets`): a texel at level l is
    one run of 4^l finest codes, so only these texels' ids are read, not every sample's texel
    (artifacts from before the index: that scan)."""
    texels = np.unique(np.asarray(texels, dtype=np.int64))
    if "sample_zorder" not in geo:
        return np.flatnonzero(np.isin(texel_ids(geo, n, level), texels))
    lo, hi = zorder_runs(geo, n, level, texels)
    size = hi - lo
    if not size.sum():
        return np.zeros(0, np.int64)
    # the runs' positions in sample_zorder, concatenated: lo_j, lo_j + 1, ..., hi_j - 1
    pos = concat_ranges(lo, size)
    order = geo["sample_zorder"]
    # runs sorted by position: a mapped index is read front to back
    return np.sort(np.asarray(order[np.sort(pos)], dtype=np.int64))


def tile_texels(n: int, s: int, tile: int, level: int) -> np.ndarray:
    """Flat ids at `level` of the texels inside tile `tile` (tiles of s x s finest texels)."""
    tiles_per_row = n // s
    tr, tc = divmod(int(tile), tiles_per_row)
    side = s >> level
    n_l = n >> level
    rows = tr * side + np.arange(side)
    cols = tc * side + np.arange(side)
    return (rows[:, None] * n_l + cols[None, :]).ravel().astype(np.int64)


def carries_lobe_var(settings: BakeSettings) -> bool:
    """Whether a level's points carry their lobe's slope variance (`point_var`): widened
    points (point_lobe "widened") or lobe texels (lobe_class), and then every texel's, a
    stored or narrow point's at 0, so that every tile's level has the same arrays."""
    return settings.point_lobe == "widened" or settings.lobe_class != "off"


def clusters_level0(settings: BakeSettings) -> bool:
    """Whether a fitted finest texel's candidates are its samples' groups
    (`texelbake.cpm.cluster`): level0_candidates "clustered", on the batched fit of classed
    texels whose points carry their lobe's spread (the settings' check refuses the rest)."""
    return (settings.level0_candidates == "clustered" and settings.fit_method == "batched"
            and settings.texel_classes == "by_need" and carries_lobe_var(settings))


def direction_sets(settings: BakeSettings) -> dict[str, np.ndarray]:
    """The texel-frame direction sets of the bake: the N_i x N_o training grid and a held-out
    product grid of independent directions (16 x 16 by default: n_heldout pairs); with
    widened lobes a VALIDATION x VALIDATION product grid of others, and with the lobe class a
    LOBE_VALIDATION x LOBE_VALIDATION one of others again (else empty)."""
    s = settings
    n_h = max(1, int(round(np.sqrt(s.n_heldout)))) if s.n_heldout else 0
    n_v = VALIDATION if s.point_lobe == "widened" else 0
    n_l = LOBE_VALIDATION if s.lobe_class != "off" else 0
    return {
        "dirs_i": directions.hemisphere_directions(s.n_light_dirs, seed=s.seed * 1000 + _TAG_LIGHT),
        "dirs_o": directions.hemisphere_directions(s.n_view_dirs, seed=s.seed * 1000 + _TAG_VIEW),
        "held_i": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_I)[0],
        "held_o": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_O)[1],
        "val_i": directions.heldout_pairs(n_v, seed=s.seed * 1000 + _TAG_VAL_I)[0],
        "val_o": directions.heldout_pairs(n_v, seed=s.seed * 1000 + _TAG_VAL_O)[1],
        "lobe_i": directions.heldout_pairs(n_l, seed=s.seed * 1000 + _TAG_LOBE_I)[0],
        "lobe_o": directions.heldout_pairs(n_l, seed=s.seed * 1000 + _TAG_LOBE_O)[1],
    }


@dataclass
class PointSet:
    """Candidate (or characteristic) points: samples of M_org with per-channel weights."""

    sample: np.ndarray  # (p,) int64 index into the geometry samples
    weight: np.ndarray  # (p, 3) float64 area-like weight per channel
    texel: np.ndarray  # (p,) int64 texel id (at the level being fitted)
    # (p,) float64 the slope variance per axis each one's lobe is widened by (a child point's
    # `point_var`, `texelbake.cpm.lobe`); None: 0, every lobe a dense sample's own
    var: np.ndarray | None = None

    def take(self, idx: np.ndarray) -> PointSet:
        return PointSet(self.sample[idx], self.weight[idx], self.texel[idx],
                        None if self.var is None else self.var[idx])


def visibility_cos(
    src: FitInputs,
    sample: np.ndarray,
    dirs_world: np.ndarray | TexelDirs,
    cosine: str = "shading",
) -> np.ndarray:
    """V(x, w) (n . w)+ for samples x and per-sample world directions.

    sample : (p,) int64; dirs_world : (p, D, 3) float64, or `TexelDirs` (the samples of a
        texel share its directions: converted and checked once for the rays, not per sample)
    cosine : "shading" — (n_s . w)+ with the interpolated shading normal, for light directions
        (irradiance, as the `gt` renderer shades); "geometric" — (n_g . w)+ with the triangle's
        normal, for view directions (projected area, Eq. 3, as `texelbake.cpm.avis` defines a_vis), so that
        R's view factor and a_vis agree and a flat Lambertian texel is reproduced exactly.
    returns : (p, D) float64 — visibility by rays against M_org times the clamped cosine; zero
        below the geometric or the shading horizon.
    """
    # the rays' directions (a texel's shared rows, or each sample's own) and each sample's row
    if isinstance(dirs_world, TexelDirs):
        per, flat, rid = dirs_world.per_sample, dirs_world.rows, dirs_world.row
    else:
        per, flat, rid = dirs_world, dirs_world, None
    p, n_dirs = len(sample), flat.shape[1]
    if p == 0 or n_dirs == 0:
        return np.zeros((p, n_dirs))
    geo = src.geo
    pos = geo["sample_pos"][sample]
    gn = geo["sample_gnrm"][sample]
    sn = geo["sample_nrm"][sample]
    cos_g = np.einsum("pk,pdk->pd", gn, per)  # (p, D)
    cos_s = np.einsum("pk,pdk->pd", sn, per)
    caster = src.caster
    live = (cos_g > TOL.grazing_cos) & (cos_s > TOL.grazing_cos)
    pi, di = np.nonzero(live)
    # offset once per sample; the caster pairs origins and directions into its float32 rays
    origins = pos + (TOL.ray_offset * caster.bbox_diag) * gn
    occ = caster.occluded_pairs(origins, flat.reshape(-1, 3), pi,
                                (pi if rid is None else rid[pi]) * n_dirs + di)
    cos = cos_s if cosine == "shading" else cos_g
    # the live entries kept whole, only the occluded ones scattered (most rays escape)
    out = np.where(live, cos, 0.0)
    out[pi[occ], di[occ]] = 0.0
    return out


def segment_sum(values: np.ndarray, seg: np.ndarray, n_seg: int, axis: int) -> np.ndarray:
    """Sum `values` along `axis` by segment ids seg (n,) in [0, n_seg) -> n_seg rows, each
    row's terms added in their order (ascending ids need no sort). A sparse (n_seg x n)
    matrix of ones times the values (scipy's CSR product adds a row's terms one after the
    other): ~10x `np.add.reduceat` along a middle axis."""
    values = np.asarray(values, dtype=np.float64)
    shape = list(values.shape)
    n = shape[axis]
    shape[axis] = n_seg
    if seg.size == 0:
        return np.zeros(shape, dtype=np.float64)
    seg = np.asarray(seg, np.int64)
    ptr = np.zeros(n_seg + 1, np.int64)
    ptr[1:] = np.cumsum(np.bincount(seg, minlength=n_seg))
    cols = (np.argsort(seg, kind="stable") if np.any(seg[1:] < seg[:-1])
            else np.arange(n))
    ones = sp.csr_matrix((np.ones(n), cols, ptr), shape=(n_seg, n))
    lead = int(np.prod(values.shape[:axis], dtype=np.int64))
    rest = int(np.prod(values.shape[axis + 1:], dtype=np.int64))
    block = np.ascontiguousarray(values).reshape(lead, n, rest)
    out = np.empty((lead, n_seg, rest), dtype=np.float64)
    for i in range(lead):  # a loop over the few leading rows (channels), not over terms
        out[i] = ones @ block[i]
    return out.reshape(shape)


def world_dirs(frames: np.ndarray, texel: np.ndarray, dirs_local: np.ndarray) -> np.ndarray:
    """(p, D, 3) world directions of texel-frame `dirs_local` (D, 3) for points in `texel`."""
    return grid_to_world(frames[texel], dirs_local)


@dataclass
class TexelDirs:
    """World directions shared by runs of points of one texel: rows (u, D, 3) and each
    point's row (p,) (`texel_dirs`)."""

    rows: np.ndarray
    row: np.ndarray

    @functools.cached_property
    def per_sample(self) -> np.ndarray:
        """(p, D, 3) each point's directions, gathered once (the cosines and the BRDF read
        them)."""
        return self.rows[self.row]


def texel_dirs(frames: np.ndarray, texel: np.ndarray, dirs_local: np.ndarray) -> TexelDirs:
    """`world_dirs` once per run of equal texels (points grouped by texel), its `per_sample`
    equal to `world_dirs(frames, texel, dirs_local)` bit for bit (each frame's product is
    computed alone either way)."""
    texel = np.asarray(texel, np.int64)
    first = np.r_[True, texel[1:] != texel[:-1]] if texel.size else np.zeros(0, bool)
    return TexelDirs(grid_to_world(frames[texel[first]], dirs_local), np.cumsum(first) - 1)


def brdf_grid(
    src: FitInputs,
    sample: np.ndarray,
    wi_world: np.ndarray,
    wo_world: np.ndarray,
    live: np.ndarray,
) -> np.ndarray:
    """f_r(x_j, wi, wo) in each sample's own shading frame, on a product of direction sets.

    sample : (p,); wi_world : (p, A, 3); wo_world : (p, B, 3); live : (A, B, p) bool — entries
    whose visibility-cosine product is zero are not evaluated.
    returns : (A, B, p, 3) float64
    """
    geo = src.geo
    frames = tangent_frames(geo["sample_nrm"][sample])  # (p, 3, 3)
    wi_loc = grid_to_local(frames, wi_world)  # (A, p, 3)
    wo_loc = grid_to_local(frames, wo_world)  # (B, p, 3)
    a_idx, b_idx, p_idx = np.nonzero(live)
    out = np.zeros(live.shape + (3,))
    if a_idx.size:
        out[a_idx, b_idx, p_idx] = brdf_mod.evaluate_by_face(
            src.materials,
            geo["sample_mat"][sample][p_idx],
            wi_loc[a_idx, p_idx],
            wo_loc[b_idx, p_idx],
            geo["sample_uv"][sample],
            sample_index=p_idx,
        )
    return out


def texel_seed(seed: int, level: int, texel: int) -> int:
    return int.from_bytes(
        hashlib.sha256(f"{seed}/{level}/{texel}".encode()).digest()[:4], "little"
    )


def level_candidates(
    src: FitInputs, level: int, texels: np.ndarray, children: Mapping[str, np.ndarray] | None,
    grandchildren: Mapping[str, np.ndarray] | None = None,
) -> PointSet:
    """Candidates of `texels` at `level`: all dense samples (level 0, or hierarchy="dense"),
    the union of the children's weighted characteristic points (hierarchy="children"), or of
    the points two levels down (hierarchy="grandchildren", from level 2 on: `grandchildren`,
    the level - 2 fit of the same texels, by texel and sample id; level 1, or no grandchildren
    given, takes the children's). children, grandchildren : a level fit's arrays (`point_sample`,
    `point_weight`, CSR `offsets` by `texel`)."""
    geo = src.geo
    n = src.settings.atlas_resolution
    if level == 0 or src.settings.hierarchy == "dense" or children is None:
        idx = samples_in(geo, n, level, texels)
        area = geo["sample_area"][idx]
        return PointSet(idx, np.repeat(area[:, None], 3, axis=1),
                        texel_ids(geo, n, level, idx))
    if src.settings.hierarchy == "grandchildren" and level >= 2 and grandchildren is not None:
        pts = descendants_points(grandchildren, n, level, 2)
        # by texel, then sample id: grandchildren that kept every dense sample give the
        # dense candidates in their order, so the fit equals hierarchy="dense"'s
        return pts.take(np.lexsort((pts.sample, pts.texel)))
    return descendants_points(children, n, level, 1)


def descendants_points(fit: Mapping[str, np.ndarray], n: int, level: int, down: int
                       ) -> PointSet:
    """The characteristic points of a fit `down` levels below `level` (its arrays, CSR by
    texel) as candidates of the texels at `level` that hold them (n : atlas side)."""
    counts = np.diff(fit["offsets"])
    tex = np.repeat(np.asarray(fit["texel"], np.int64), counts)  # (p,) ids at level - down
    r, c = np.divmod(tex, n >> (level - down))
    return PointSet(
        np.asarray(fit["point_sample"]).astype(np.int64),
        np.asarray(fit["point_weight"]).astype(np.float64),
        ((r >> down) * (n >> level) + (c >> down)).astype(np.int64),
        np.asarray(fit["point_var"]).astype(np.float64) if "point_var" in fit else None,
    )


#: a level's per-point arrays (CSR rows by `offsets`); `point_var` (the lobe's variance) only
#: where lobes may be widened
POINT_KEYS = ("point_sample", "point_weight", "point_var")

#: a level's per-level totals (the rays its fit cast, the seconds per texel class of
#: `texelbake.cpm.level_by_need`): summed over tiles, never reordered by texel
LEVEL_TOTALS = ("rays", "classed")


def concat_levels(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate per-tile results of one level (CSR offsets re-based; `LEVEL_TOTALS`
    summed)."""
    out: dict[str, np.ndarray] = {}
    base = 0
    offs = [np.zeros(1, np.int64)]
    for p in parts:
        offs.append(p["offsets"][1:] + base)
        base += int(p["offsets"][-1])
    out["offsets"] = np.concatenate(offs)
    for k in parts[0]:
        if k == "rays":
            out[k] = np.array([sum(int(p[k].sum()) for p in parts if k in p)], np.int64)
        elif k in LEVEL_TOTALS:
            out[k] = np.sum([p[k] for p in parts if k in p], axis=0)
        elif k != "offsets":
            out[k] = np.concatenate([p[k] for p in parts])
    return out


def sort_by_texel(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.argsort(data["texel"], kind="stable")
    counts = np.diff(data["offsets"])[order]
    starts = data["offsets"][:-1][order]
    point_idx = concat_ranges(starts, counts)  # the CSR ranges in the new texel order
    out = {k: v[order] for k, v in data.items()
           if k not in ("offsets", *POINT_KEYS, *LEVEL_TOTALS)}
    out.update({k: data[k] for k in LEVEL_TOTALS if k in data})
    out["offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    for k in POINT_KEYS:
        if k in data:
            out[k] = data[k][point_idx.astype(np.int64)]
    return out
