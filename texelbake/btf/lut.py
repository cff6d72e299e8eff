"""Direction sets of a BTF and the direction look-up table (seed 001, §3.3-3.4).

A BTF is sampled on d (light, view) pairs. The pairs are split into their distinct light
directions (n_l) and view directions (n_v) and a pair table `pair_index[l, v]` (-1 where a
combination was not sampled): on a product grid (the Bonn 81 x 81, or texelbake's CPM grid)
every entry is set. The seed's "lookup table [that] stores the sequence number of the closest
direction for many directions" is, per direction set, an R x R table over the hemisphere in the
equal-area (Lambert azimuthal) disk

    (x, y) = (w_x, w_y) / sqrt(1 + w_z),     w_z = 1 - (x^2 + y^2)

holding the nearest sampled direction of every cell centre (and, so that a sampled direction
always finds itself, the cell containing each sample holds that sample).

Interpolated look-up ("an interpolated option") blends the 3 nearest sampled directions with
modified-Shepard weights w_j = 1/d_j - 1/d_4 (d = chord distance, d_4 the 4th nearest): the
weights reach zero before a neighbour leaves the set, so the blend is continuous, and a query on
a sample returns that sample exactly. Pairs blend with the product of light and view weights.

Bonn UBO2003 sampling: 81 directions per hemisphere, theta in 0, 15, 30, 45, 60, 75 degrees
with 1, 6, 12, 18, 20, 24 equally spaced phi samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from texelbake.errors import ShapeError
from texelbake.tol import TOL

BONN_THETAS = (0.0, 15.0, 30.0, 45.0, 60.0, 75.0)
BONN_PHI_COUNTS = (1, 6, 12, 18, 20, 24)


def dirs_from_degrees(theta_deg, phi_deg) -> np.ndarray:
    """(n,) polar angle from +z and azimuth from +x, degrees -> (n, 3) float64 unit vectors."""
    t = np.radians(np.asarray(theta_deg, dtype=np.float64))
    p = np.radians(np.asarray(phi_deg, dtype=np.float64))
    if t.shape != p.shape:
        raise ShapeError(f"theta and phi must have the same shape, got {t.shape} and {p.shape}")
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def bonn_angles() -> tuple[np.ndarray, np.ndarray]:
    """The 81 (theta, phi) of the Bonn UBO2003 sampling, degrees, in ring order: (81,) x 2."""
    rings = zip(BONN_THETAS, BONN_PHI_COUNTS, strict=True)
    theta = np.concatenate([np.full(c, t) for t, c in rings])
    phi = np.concatenate([np.arange(c) * (360.0 / c) for c in BONN_PHI_COUNTS])
    return theta, phi


def bonn_directions() -> np.ndarray:
    """(81, 3) float64 unit vectors of the Bonn sampling."""
    return dirs_from_degrees(*bonn_angles())


def to_disk(w: np.ndarray) -> np.ndarray:
    """(n, 3) unit directions -> (n, 2) equal-area disk coordinates (z clamped to >= 0)."""
    w = np.asarray(w, dtype=np.float64)
    z = np.clip(w[..., 2], 0.0, 1.0)
    return w[..., :2] / np.sqrt(1.0 + z)[..., None]


def from_disk(xy: np.ndarray) -> np.ndarray:
    """(n, 2) disk coordinates (radius > 1 is pulled onto the horizon) -> (n, 3) unit vectors."""
    xy = np.asarray(xy, dtype=np.float64)
    r2 = np.sum(xy * xy, axis=-1)
    scale = np.where(r2 > 1.0, 1.0 / np.sqrt(np.maximum(r2, 1.0)), 1.0)
    xy = xy * scale[..., None]
    z = 1.0 - np.minimum(r2, 1.0)
    w = np.concatenate([xy * np.sqrt(1.0 + z)[..., None], z[..., None]], axis=-1)
    return w / np.linalg.norm(w, axis=-1, keepdims=True)


def unique_directions(dirs: np.ndarray, *, eps: float = TOL.dir_match):
    """Distinct directions in order of first occurrence.

    dirs : (d, 3) -> (unique (u, 3) float64, inverse (d,) int64 with dirs ~ unique[inverse])
    Directions are identified after quantisation to `eps`.
    """
    dirs = np.asarray(dirs, dtype=np.float64)
    if dirs.size == 0:
        return np.zeros((0, 3)), np.zeros(0, np.int64)
    keys = np.round(dirs / eps).astype(np.int64)
    _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first, kind="stable")  # unique ids sorted by first occurrence
    rank = np.empty_like(order)
    rank[order] = np.arange(order.size)
    return dirs[first[order]], rank[inverse.reshape(-1)].astype(np.int64)


def _nearest_table(dirs: np.ndarray, resolution: int) -> np.ndarray:
    """(R, R) int32: nearest of `dirs` (by angle) to every cell centre of the disk."""
    c = (np.arange(resolution) + 0.5) / resolution * 2.0 - 1.0  # cell centres in [-1, 1]
    xx, yy = np.meshgrid(c, c)  # row = y, column = x
    centres = from_disk(np.stack([xx.ravel(), yy.ravel()], axis=1))  # (R*R, 3)
    table = np.argmax(centres @ dirs.T, axis=1).astype(np.int32)
    cell = _cells(dirs, resolution)  # stamp the samples' own cells
    table.reshape(resolution, resolution)[cell[:, 0], cell[:, 1]] = np.arange(dirs.shape[0])
    return table.reshape(resolution, resolution)


def _cells(w: np.ndarray, resolution: int) -> np.ndarray:
    """(n, 3) directions -> (n, 2) int64 (row, col) of their table cell."""
    xy = to_disk(w)
    ij = np.floor((xy + 1.0) * 0.5 * resolution).astype(np.int64)
    ij = np.clip(ij, 0, resolution - 1)
    return np.stack([ij[:, 1], ij[:, 0]], axis=1)


@dataclass(frozen=True, eq=False)
class DirectionLUT:
    """light_dirs : (n_l, 3) float32; view_dirs : (n_v, 3) float32;
    pair_index : (n_l, n_v) int32 column of each (light, view) pair, -1 if not sampled;
    light_table, view_table : (R, R) int32 nearest-direction tables over the disk."""

    light_dirs: np.ndarray
    view_dirs: np.ndarray
    pair_index: np.ndarray
    light_table: np.ndarray
    view_table: np.ndarray

    @property
    def resolution(self) -> int:
        return int(self.light_table.shape[0])

    @property
    def is_product(self) -> bool:
        return bool(np.all(self.pair_index >= 0))

    def pair_dirs(self) -> tuple[np.ndarray, np.ndarray]:
        """(dirs_i (d, 3), dirs_o (d, 3)) float64 of the columns, in column order."""
        li, vi = np.nonzero(self.pair_index >= 0)
        cols = self.pair_index[li, vi]
        d = int(cols.max()) + 1 if cols.size else 0
        wi = np.zeros((d, 3))
        wo = np.zeros((d, 3))
        wi[cols] = self.light_dirs[li]
        wo[cols] = self.view_dirs[vi]
        return wi, wo


def build_lut(dirs_i: np.ndarray, dirs_o: np.ndarray, resolution: int = 64) -> DirectionLUT:
    """Split d pairs into light and view sets and tabulate nearest directions.

    dirs_i, dirs_o : (d, 3) unit directions of the pairs (texel frame); each pair must be
        distinct. resolution : R of the R x R tables. Directions are stored as float32.
    """
    dirs_i = np.asarray(dirs_i, dtype=np.float32).astype(np.float64)
    dirs_o = np.asarray(dirs_o, dtype=np.float32).astype(np.float64)
    if dirs_i.ndim != 2 or dirs_i.shape[1] != 3 or dirs_o.shape != dirs_i.shape:
        raise ShapeError(
            f"dirs_i and dirs_o must both be (d, 3), got {dirs_i.shape} and {dirs_o.shape}"
        )
    if resolution < 1:
        raise ShapeError(f"LUT resolution must be >= 1, got {resolution}")
    lights, li = unique_directions(dirs_i)
    views, vi = unique_directions(dirs_o)
    pair = np.full((lights.shape[0], views.shape[0]), -1, np.int32)
    pair[li, vi] = np.arange(dirs_i.shape[0], dtype=np.int32)
    if np.count_nonzero(pair >= 0) != dirs_i.shape[0]:
        raise ShapeError("BTF direction pairs (dirs_i, dirs_o) contain duplicates")
    if lights.shape[0] == 0:
        empty = np.zeros((resolution, resolution), np.int32)
        return DirectionLUT(lights.astype(np.float32), views.astype(np.float32), pair, empty,
                            empty.copy())
    return DirectionLUT(
        lights.astype(np.float32),
        views.astype(np.float32),
        pair,
        _nearest_table(lights, resolution),
        _nearest_table(views, resolution),
    )


def _shepard(dirs: np.ndarray, query: np.ndarray, k: int = 3, eps: float = TOL.dir_match):
    """(n, k) indices and weights (rows sum to 1) of the modified-Shepard blend."""
    n_dirs = dirs.shape[0]
    kk = min(k + 1, n_dirs)
    dist, idx = cKDTree(dirs).query(query, k=kk)
    dist = np.asarray(dist, dtype=np.float64).reshape(query.shape[0], kk)
    idx = np.asarray(idx, dtype=np.int64).reshape(query.shape[0], kk)
    if kk <= k:  # too few samples for a vanishing rim: plain inverse distance
        inv = 1.0 / np.maximum(dist, eps)
        w = inv
    else:
        inv = 1.0 / np.maximum(dist, eps)
        w = np.clip(inv[:, :k] - inv[:, k:k + 1], 0.0, None)
        idx = idx[:, :k]
        dist = dist[:, :k]
    snap = dist[:, 0] < eps
    w[snap] = 0.0
    w[snap, 0] = 1.0
    total = w.sum(axis=1, keepdims=True)
    degenerate = total[:, 0] <= 0.0  # equidistant rim: fall back to the nearest
    w[degenerate] = 0.0
    w[degenerate, 0] = 1.0
    return idx, w / w.sum(axis=1, keepdims=True)


def lookup_pairs(
    lut: DirectionLUT, wi: np.ndarray, wo: np.ndarray, *, interpolate: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Columns and weights to evaluate a tabulated function at arbitrary direction pairs.

    wi, wo : (n, 3) float64 unit, texel frame
    returns : (cols (n, m) int64, weights (n, m) float64 rows summing to 1); m = 1 for the
        nearest look-up through the tables, up to 9 when interpolating. Unsampled pairs of a
        non-product set fall back to the nearest sampled pair (6-D chord distance).
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    n = wi.shape[0]
    if wi.shape != (n, 3) or wo.shape != (n, 3):
        raise ShapeError(f"wi and wo must both be (n, 3), got {wi.shape} and {wo.shape}")
    if n == 0 or lut.pair_index.size == 0:
        return np.zeros((n, 1), np.int64), np.zeros((n, 1))
    if interpolate:
        li, lw = _shepard(lut.light_dirs.astype(np.float64), wi)
        vi, vw = _shepard(lut.view_dirs.astype(np.float64), wo)
        cols = lut.pair_index[li[:, :, None], vi[:, None, :]].reshape(n, -1).astype(np.int64)
        w = (lw[:, :, None] * vw[:, None, :]).reshape(n, -1)
        w = np.where(cols >= 0, w, 0.0)
        total = w.sum(axis=1, keepdims=True)
        ok = total[:, 0] > 0.0
        w = np.divide(w, total, out=np.zeros_like(w), where=total > 0)
        cols = np.where(cols >= 0, cols, 0)
    else:
        r = lut.resolution
        lc = _cells(wi, r)
        vc = _cells(wo, r)
        li = lut.light_table[lc[:, 0], lc[:, 1]]
        vi = lut.view_table[vc[:, 0], vc[:, 1]]
        cols = lut.pair_index[li, vi].astype(np.int64)[:, None]
        ok = cols[:, 0] >= 0
        w = ok[:, None].astype(np.float64)
        cols = np.where(cols >= 0, cols, 0)
    if not np.all(ok):  # unsampled combinations: nearest sampled pair in 6-D
        pi, po = lut.pair_dirs()
        tree = cKDTree(np.concatenate([pi, po], axis=1))
        _, near = tree.query(np.concatenate([wi[~ok], wo[~ok]], axis=1), k=1)
        cols[~ok] = 0
        w[~ok] = 0.0
        cols[~ok, 0] = near
        w[~ok, 0] = 1.0
    return cols, w
