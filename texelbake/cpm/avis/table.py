"""The compressed a_vis table the renderer reads (Haar per cube face) and its look-up."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.cpm.avis.closed_form import ClosedForm, closed_form_maps, eval_closed_form
from texelbake.cpm.avis.cube import FACE_BASIS, dirs_to_cube
from texelbake.cpm.avis.levels import AvisLevel
from texelbake.cpm.haar import HaarCoeffs, compress_haar, eval_haar_point
from texelbake.errors import SettingsError, ShapeError
from texelbake.frames import to_world
from texelbake.tol import TOL

# --------------------------------------------------------------------------------------------
# compressed table and look-up


@dataclass(frozen=True)
class AvisTable:
    """Compressed a_vis of one level, ready for look-ups.

    res : cube face side
    frames : (n_texels, 3, 3) float64 texel frames, rows (t, b, n)
    texel_area : (n_texels,) float64
    closed : (n_texels,) bool; cf : ClosedForm (exact, any direction, for closed texels;
        the unoccluded upper bound for the other `bounded` texels)
    bounded : (n_texels,) bool
    ray_row : (n_texels,) int64 row of the texel in `haar` (-1 for closed-form texels)
    haar : HaarCoeffs of the (n_ray, 6, res, res) world-direction cube maps: for a bounded
        ray texel the *visible fraction* F = a_vis / U (U the unoccluded projected area, its
        closed form; F in [0, 1]), otherwise a_vis itself. Look-up: U F at the taps (U exact
        at each tap direction), interpolated, then min(., U(w)) with U exact at w: the
        horizon is exact and compression only touches the smoother masking fraction
        (about 4x lower error at the seed's kept fraction, benchmarks/avis_methods.py)
    """

    res: int
    frames: np.ndarray
    texel_area: np.ndarray
    closed: np.ndarray
    bounded: np.ndarray
    cf: ClosedForm
    ray_row: np.ndarray
    haar: HaarCoeffs

    @property
    def n_texels(self) -> int:
        return int(self.closed.shape[0])

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Named arrays (what the payload writer stores; float32 Haar values)."""
        return {
            "meta": np.array([self.res, self.haar.res], dtype=np.int64),
            "frames": self.frames, "texel_area": self.texel_area, "closed": self.closed,
            "bounded": self.bounded, "cf_offsets": self.cf.offsets,
            "cf_normals": self.cf.normals, "cf_areas": self.cf.areas, "ray_row": self.ray_row,
            "haar_offsets": self.haar.offsets, "haar_indices": self.haar.indices,
            "haar_values": self.haar.values,
        }

    @classmethod
    def from_arrays(cls, arrays) -> AvisTable:
        """Inverse of `to_arrays` (any mapping of name -> array)."""
        need = ("meta", "frames", "texel_area", "closed", "bounded", "cf_offsets", "cf_normals",
                "cf_areas", "ray_row", "haar_offsets", "haar_indices", "haar_values")
        missing = [k for k in need if k not in arrays]
        if missing:
            raise ShapeError(f"a_vis table arrays are missing {missing}")
        res = int(np.asarray(arrays["meta"])[0])
        ray_row = np.asarray(arrays["ray_row"], np.int64)
        n_ray = int(ray_row.max()) + 1 if ray_row.size else 0
        haar = HaarCoeffs(res, (n_ray, 6), np.asarray(arrays["haar_offsets"], np.int64),
                          np.asarray(arrays["haar_indices"], np.int32),
                          np.asarray(arrays["haar_values"]))
        if haar.n_maps != n_ray * 6:
            raise ShapeError(f"haar_offsets describe {haar.n_maps} maps, ray_row needs "
                             f"{n_ray * 6}")
        cf = ClosedForm(np.asarray(arrays["cf_offsets"], np.int64),
                        np.asarray(arrays["cf_normals"], np.float64),
                        np.asarray(arrays["cf_areas"], np.float64))
        return cls(res, np.asarray(arrays["frames"], np.float64),
                   np.asarray(arrays["texel_area"], np.float64),
                   np.asarray(arrays["closed"], bool), np.asarray(arrays["bounded"], bool), cf,
                   ray_row, haar)

    def evaluate(self, texels: np.ndarray, dirs_texel: np.ndarray, *,
                 interp: str = "bilinear",
                 floor: float = TOL.avis_floor) -> tuple[np.ndarray, np.ndarray]:
        """a_vis at view directions given in each texel's frame.

        texels : (n,) int in [0, n_texels)
        dirs_texel : (n, 3) float64 directions in the texel frame (t, b, n); need not be unit
        interp : "bilinear" (continuous across cube edges) or "nearest" cube-map texel
        floor : relative floor; see returns
        returns : (a (n,) float64 >= 0, valid (n,) bool). valid is False where
            a <= floor * texel_area (grazing or fully masked: the a_vis -> 0 limit), where the
            direction is zero or non-finite, and for empty texels; there a = 0 and the
            renderer must use zero radiance for the texel instead of dividing by a_vis.
        """
        t = np.asarray(texels, dtype=np.int64).ravel()
        d = np.asarray(dirs_texel, dtype=np.float64)
        n = t.shape[0]
        if d.shape != (n, 3):
            raise ShapeError(f"dirs_texel must be ({n}, 3), got {d.shape}")
        if n and (t.min() < 0 or t.max() >= self.n_texels):
            raise ShapeError(f"texels must be in [0, {self.n_texels}), got "
                             f"[{t.min()}, {t.max()}]")
        if interp not in ("bilinear", "nearest"):
            raise SettingsError(f"interp must be 'bilinear' or 'nearest', got {interp!r}")
        length = np.linalg.norm(d, axis=1)
        dir_ok = np.isfinite(length) & (length > 0)
        d = np.divide(d, length[:, None], out=np.zeros_like(d), where=dir_ok[:, None])
        w = to_world(self.frames[t], d)  # (n, 3)
        a = np.zeros(n, dtype=np.float64)
        cl = self.closed[t]
        if cl.any():
            a[cl] = eval_closed_form(self.cf, t[cl], w[cl])
        rq = np.flatnonzero(~cl)
        if rq.size:
            bnd = self.bounded[t[rq]]
            a[rq] = self._eval_maps(self.ray_row[t[rq]], w[rq], interp, t[rq], bnd)
            bq = rq[bnd]
            if bq.size:  # a_vis <= U, exact at w (a_vis -> 0 at the horizon with U)
                a[bq] = np.minimum(a[bq], eval_closed_form(self.cf, t[bq], w[bq]))
        a = np.maximum(a, 0.0)
        valid = dir_ok & (a > floor * self.texel_area[t]) & (self.texel_area[t] > 0)
        return np.where(valid, a, 0.0), valid

    def _eval_maps(self, rows: np.ndarray, w: np.ndarray, interp: str, texels: np.ndarray,
                   bounded: np.ndarray) -> np.ndarray:
        """a_vis from the Haar maps. For bounded texels the maps hold F = a_vis / U: nearest
        returns U(w) F(texel); bilinear interpolates the products U(tap) F(tap) over the four
        taps (so a lossless table interpolates a_vis itself, and compression only touches F)."""
        res = self.res
        face, iu, iv, fu, fv = dirs_to_cube(w, res)
        if interp == "nearest":
            val = eval_haar_point(self.haar, rows * 6 + face, iu, iv)
            if bounded.any():
                val[bounded] = (np.clip(val[bounded], 0.0, 1.0)
                                * eval_closed_form(self.cf, texels[bounded], w[bounded]))
            return val
        # Seamless bilinear: the four taps are texel centres of the face's plane extended by
        # one texel. A tap inside the face is read directly; a tap beyond an edge is turned
        # back into a direction and read by a bilinear look-up (clamped to that face) on the
        # face it falls on, so the result is continuous across cube edges and corners.
        u0 = np.floor(fu)
        v0 = np.floor(fv)
        au, av = fu - u0, fv - v0
        tu = np.concatenate([u0, u0 + 1, u0, u0 + 1])  # (4n,)
        tv = np.concatenate([v0, v0, v0 + 1, v0 + 1])
        f4 = np.tile(face, 4)
        r4 = np.tile(rows, 4)
        taps = np.empty(tu.shape[0], dtype=np.float64)
        inside = (tu >= 0) & (tu <= res - 1) & (tv >= 0) & (tv <= res - 1)
        taps[inside] = eval_haar_point(self.haar, r4[inside] * 6 + f4[inside],
                                       tu[inside].astype(np.int64), tv[inside].astype(np.int64))
        sc = 2.0 * (tu + 0.5) / res - 1.0
        tc = 2.0 * (tv + 0.5) / res - 1.0
        basis = FACE_BASIS[f4]  # (4n, 3, 3)
        tap_dirs = basis[:, 0] + sc[:, None] * basis[:, 1] + tc[:, None] * basis[:, 2]
        out = ~inside
        if out.any():
            tf, _, _, tfu, tfv = dirs_to_cube(tap_dirs[out], res)
            taps[out] = self._bilinear_in_face(r4[out], tf, tfu, tfv)
        b4 = np.tile(bounded, 4)
        if b4.any():  # F at the taps times U exactly at the tap directions
            td = tap_dirs[b4] / np.linalg.norm(tap_dirs[b4], axis=1, keepdims=True)
            taps[b4] = np.clip(taps[b4], 0.0, 1.0) * eval_closed_form(
                self.cf, np.tile(texels, 4)[b4], td)
        wts = np.concatenate([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum((taps * wts).reshape(4, -1), axis=0)

    def _bilinear_in_face(self, rows: np.ndarray, face: np.ndarray, fu: np.ndarray,
                          fv: np.ndarray) -> np.ndarray:
        """Bilinear look-up with coordinates clamped to the face's texel centres."""
        res = self.res
        fu = np.clip(fu, 0.0, res - 1.0)
        fv = np.clip(fv, 0.0, res - 1.0)
        u0 = np.minimum(np.floor(fu).astype(np.int64), max(res - 2, 0))
        v0 = np.minimum(np.floor(fv).astype(np.int64), max(res - 2, 0))
        u1, v1 = np.minimum(u0 + 1, res - 1), np.minimum(v0 + 1, res - 1)
        au, av = fu - u0, fv - v0
        mi = np.tile(rows * 6 + face, 4)
        taps = eval_haar_point(self.haar, mi, np.concatenate([u0, u1, u0, u1]),
                               np.concatenate([v0, v0, v1, v1])).reshape(4, -1)
        wts = np.stack([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum(taps * wts, axis=0)


def _fill_along(f: np.ndarray, ok: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill undefined entries with the nearest defined entry along one axis (ties: lower
    index). Vectorized: forward and backward running maxima of the defined indices."""
    n = f.shape[axis]
    shape = [1] * f.ndim
    shape[axis] = n
    pos = np.arange(n).reshape(shape)
    prev = np.maximum.accumulate(np.where(ok, pos, -1), axis=axis)
    nxt = n - 1 - np.maximum.accumulate(np.flip(np.where(ok, n - 1 - pos, -1), axis=axis),
                                        axis=axis)
    nxt = np.flip(nxt, axis=axis)  # index of the next defined entry, n when none
    d_prev = np.where(prev >= 0, pos - prev, n + 1)
    d_next = np.where(nxt < n, nxt - pos, n + 1)
    src = np.where(d_prev <= d_next, prev, nxt)
    found = np.minimum(d_prev, d_next) <= n
    filled = np.take_along_axis(f, np.clip(src, 0, n - 1), axis=axis)
    return np.where(ok, f, np.where(found, filled, 0.0)), ok | found


def visible_fraction(maps: np.ndarray, unoccluded: np.ndarray) -> np.ndarray:
    """F = a_vis / U on cube maps. Where U = 0 (F undefined) F takes the value of the nearest
    defined texel of the same face along its column, else along its row, so that bilinear
    look-ups just above the horizon and the Haar transform see a piecewise-constant extension
    rather than a jump to 0; faces with no defined texel are 0.

    maps, unoccluded : (r, 6, res, res) float64 a_vis and its unoccluded bound U >= a_vis
    returns : (r, 6, res, res) float64 in [0, 1]
    """
    a = np.asarray(maps, dtype=np.float64)
    u = np.asarray(unoccluded, dtype=np.float64)
    if a.shape != u.shape or a.ndim < 2:
        raise ShapeError(f"maps and unoccluded must share a (..., res, res) shape, got "
                         f"{a.shape} and {u.shape}")
    defined = u > 0
    f = np.clip(np.divide(a, u, out=np.zeros_like(a), where=defined), 0.0, 1.0)
    f, defined = _fill_along(f, defined, axis=-2)  # along columns (iv)
    f, _ = _fill_along(f, defined, axis=-1)  # then rows (iu), for columns without values
    return f


def compress_level(level: AvisLevel, frames: np.ndarray, keep_fraction: float) -> AvisTable:
    """AvisTable of a level: closed-form terms as they are, Haar for the ray-based texels.

    frames : (N*N, 3, 3) float64 texel frames of this level (rows t, b, n)
    keep_fraction : Haar coefficients kept per cube face (texelbake.haar.compress_haar)
    """
    n = level.n_side * level.n_side
    frames = np.asarray(frames, dtype=np.float64)
    if frames.shape != (n, 3, 3):
        raise ShapeError(f"frames must be ({n}, 3, 3), got {frames.shape}")
    ray_row = np.full(n, -1, dtype=np.int64)
    ray_row[level.ray_texels] = np.arange(level.ray_texels.shape[0])
    maps = level.ray_maps.copy()  # (n_ray, 6, res, res)
    frac = level.bounded[level.ray_texels]
    if frac.any():
        unocc = closed_form_maps(level.cf, level.res, level.ray_texels[frac])
        maps[frac] = visible_fraction(maps[frac], unocc)
    haar = compress_haar(maps, keep_fraction)
    return AvisTable(level.res, frames, level.texel_area, level.closed, level.bounded, level.cf,
                     ray_row, haar)


def avis_table_arrays(table: AvisTable) -> dict[str, np.ndarray]:
    """An AvisTable as payload arrays (`avis:` namespace)."""
    return {f"avis:{k}": v for k, v in table.to_arrays().items()}


def avis_table_from(arrays: dict[str, np.ndarray]) -> AvisTable:
    """Inverse of `avis_table_arrays` (used by the renderer on `read_baked` output)."""
    return AvisTable.from_arrays(
        {k[5:]: v for k, v in arrays.items() if k.startswith("avis:")}
    )
