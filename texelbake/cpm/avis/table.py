"""The compressed a_vis table the renderer reads (Haar per cube face) and its look-up."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np

from texelbake.cpm.avis.closed_form import ClosedForm, closed_form_maps, eval_closed_form
from texelbake.cpm.avis.correction import apply_correction
from texelbake.cpm.avis.cube import FACE_BASIS, dirs_to_cube
from texelbake.cpm.haar import (
    HaarCoeffs,
    decompress_haar,
    dequantize_values,
    eval_haar_point,
    map_range,
    quantize_values,
)
from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.basis import to_world
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
        at each tap direction), interpolated (linear in the taps: sums over texels survive):
        compression only touches the smoother masking fraction (about 4x lower error at the
        seed's kept fraction, benchmarks/avis_methods.py)
    correction : (k, 6, res, res) float16 sum-preserving corrections (`sum_correction`),
        one per group present in the level, (0,) when the table has none (the seed's plain
        Haar table, or a bake from before it); correction_groups : (k,) uint8, which group
        each map corrects: 0 the bounded texels' visible fractions, 1 the direct texels' a_vis
    haar_scale : (n_ray,) float32, per ray texel, when the Haar values are stored as float16
        relative to it (`selection="texel"`); (0,) for float32 values (the seed's table)
    """

    res: int
    frames: np.ndarray
    texel_area: np.ndarray
    closed: np.ndarray
    bounded: np.ndarray
    cf: ClosedForm
    ray_row: np.ndarray
    haar: HaarCoeffs
    correction: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float16))
    correction_groups: np.ndarray = field(default_factory=lambda: np.zeros(0, np.uint8))
    haar_scale: np.ndarray = field(default_factory=lambda: np.zeros(0, np.float32))

    @property
    def n_texels(self) -> int:
        return int(self.closed.shape[0])

    @functools.cached_property
    def row_texels(self) -> np.ndarray:
        """(n_ray,) int64 the texel of each row of `haar` (the inverse of `ray_row`), built
        once: `ray_texel_maps` is called a chunk of rows at a time."""
        out = np.empty(self.haar.n_maps // 6, np.int64)
        has = np.flatnonzero(self.ray_row >= 0)
        out[self.ray_row[has]] = has
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Named arrays (what the payload writer stores). USD has no 16-bit integer arrays, so
        per-map coefficient counts go two to a uint32 word (uint16 each; the maps come six to
        a texel; counts wider than 16 bits, res > 128, one to a word). With `haar_scale`
        (float16 values) each coefficient is its in-map index, one to a uint32 word
        (`haar_index`: ascending within a map, so USD's integer compression of deltas stores
        it in well under 16 bits), and its float16 value as half (`haar_half`); without it
        (the seed's table) int32 indices and float32 values. An index and its value's bits
        packed into one word (`haar_packed`, still read) defeat that compression: USD
        counted the random words' deltas and saved the 256² cylinder's level 0 in 4.5 s
        instead of 0.01 s, to a larger file. meta[2] = 2 marks this layout (1: packed;
        bakes before either store offsets)."""
        n_coef = self.haar.res * self.haar.res
        counts = np.diff(self.haar.offsets)
        out = {
            "meta": np.array([self.res, self.haar.res, 2], dtype=np.int64),
            "frames": self.frames, "texel_area": self.texel_area, "closed": self.closed,
            "bounded": self.bounded, "cf_offsets": self.cf.offsets,
            "cf_normals": self.cf.normals, "cf_areas": self.cf.areas, "ray_row": self.ray_row,
            "haar_counts": (counts.astype(np.uint16).view(np.uint32)
                            if n_coef <= 65535 and counts.size % 2 == 0
                            else counts.astype(np.uint32)),
            "haar_scale": self.haar_scale, "correction": self.correction,
            "correction_groups": self.correction_groups,
        }
        if self.haar_scale.size:
            out["haar_index"] = self.haar.indices.astype(np.uint32)
            out["haar_half"] = quantize_values(self.haar.values, self._entry_scale())[0]
        else:
            out["haar_indices"] = self.haar.indices.astype(np.int32)
            out["haar_values"] = self.haar.values.astype(np.float32)
        return out

    def _entry_scale(self) -> np.ndarray:
        """(nnz,) float32 scale of every stored Haar value (its texel's `haar_scale`)."""
        maps = np.repeat(np.arange(self.haar.n_maps), np.diff(self.haar.offsets))
        return self.haar_scale[maps // 6]

    def stored_bytes(self) -> int:
        """Bytes of the compressed maps as `to_arrays` stores them: Haar counts, indices,
        values, scales and the correction maps (the storage the benchmarks count), a
        `haar_index` entry at its 16-bit width (the payload's compressed uint[] takes
        fewer)."""
        a = self.to_arrays()
        n = sum(a[k].nbytes for k in ("haar_counts", "haar_indices", "haar_values",
                                      "haar_half", "haar_scale", "correction") if k in a)
        return int(n + 2 * a["haar_index"].size if "haar_index" in a else n)

    @classmethod
    def from_arrays(cls, arrays) -> AvisTable:
        """Inverse of `to_arrays` (any mapping of name -> array)."""
        need = ("meta", "frames", "texel_area", "closed", "bounded", "cf_offsets", "cf_normals",
                "cf_areas", "ray_row")
        missing = [k for k in need if k not in arrays]
        if "haar_counts" not in arrays and "haar_offsets" not in arrays:
            missing.append("haar_counts")
        if not (("haar_index" in arrays and "haar_half" in arrays) or "haar_packed" in arrays
                or ("haar_indices" in arrays and "haar_values" in arrays)):
            missing.append("haar_index and haar_half (or haar_packed, or haar_indices and "
                           "haar_values)")
        if missing:
            raise ShapeError(f"a_vis table arrays are missing {missing}")
        meta = np.asarray(arrays["meta"]).reshape(-1)
        res = int(meta[0])
        ray_row = np.asarray(arrays["ray_row"], np.int64)
        n_ray = int(ray_row.max()) + 1 if ray_row.size else 0
        n_maps = n_ray * 6
        if "haar_counts" in arrays:  # meta[2] >= 1: uint16 pairs in uint32 words
            raw = np.asarray(arrays["haar_counts"])
            counts = (raw.astype(np.uint32).view(np.uint16) if raw.size * 2 == n_maps
                      else raw).astype(np.int64)
            offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        else:  # bakes before the packed layout
            offsets = np.asarray(arrays["haar_offsets"], np.int64)
        scale = np.asarray(arrays.get("haar_scale", np.zeros(0)), np.float32).reshape(-1)
        if "haar_index" in arrays and "haar_half" in arrays:
            indices = np.asarray(arrays["haar_index"]).astype(np.int32)
            values = np.asarray(arrays["haar_half"], np.float16)
        elif "haar_packed" in arrays:  # bakes of the packed layout (meta[2] = 1)
            packed = np.asarray(arrays["haar_packed"]).astype(np.uint32)
            indices = (packed & 0xFFFF).astype(np.int32)
            values = (packed >> 16).astype(np.uint16).view(np.float16)
        else:
            indices = np.asarray(arrays["haar_indices"], np.int32)
            values = np.asarray(arrays["haar_values"])
        if scale.size:
            if scale.shape[0] != n_ray:
                raise ShapeError(f"haar_scale must have one entry per ray texel ({n_ray}), got "
                                 f"{scale.shape[0]}")
            maps = np.repeat(np.arange(offsets.shape[0] - 1), np.diff(offsets))
            values = dequantize_values(values, scale[maps // 6])
        haar = HaarCoeffs(res, (n_ray, 6), offsets, indices, values)
        if haar.n_maps != n_maps:
            raise ShapeError(f"haar counts describe {haar.n_maps} maps, ray_row needs "
                             f"{n_maps}")
        cf = ClosedForm(np.asarray(arrays["cf_offsets"], np.int64),
                        np.asarray(arrays["cf_normals"], np.float64),
                        np.asarray(arrays["cf_areas"], np.float64))
        corr = np.asarray(arrays.get("correction", np.zeros(0)), np.float16)
        groups = np.asarray(arrays.get("correction_groups", np.zeros(0)), np.uint8).reshape(-1)
        if corr.size and corr.shape != (groups.shape[0], 6, res, res):
            raise ShapeError(f"correction must be ({groups.shape[0]}, 6, {res}, {res}) for "
                             f"correction_groups {groups.tolist()}, got {corr.shape}")
        return cls(res, np.asarray(arrays["frames"], np.float64),
                   np.asarray(arrays["texel_area"], np.float64),
                   np.asarray(arrays["closed"], bool), np.asarray(arrays["bounded"], bool), cf,
                   ray_row, haar, corr, groups, scale)

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
            # No clamp to U(w) after the bilinear look-up: the look-up stays linear in the
            # stored tap values, so sums over texels are kept (the height-field identity, a
            # parent equal to its children, the renderer's a_vis-weighted pixel average). A
            # wall's tap overshoot past its horizon (within one cube pixel) balances the
            # undershoot of the wall it uncovers; clamping only the overshoot biased the
            # V-grooves' identity by 1.4 % (res 32) and 4 % (res 16) and won 0.02 % per texel
            # (docs/decisions.md). Below the horizon the texel's points have
            # (n . w)^+ = 0, so its radiance is 0 either way.
            a[rq] = self._eval_maps(self.ray_row[t[rq]], w[rq], interp, t[rq], bnd)
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
            val = self._pixels(eval_haar_point(self.haar, rows * 6 + face, iu, iv), face, iu,
                               iv, bounded)
            if bounded.any():
                val[bounded] *= eval_closed_form(self.cf, texels[bounded], w[bounded])
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
        b4 = np.tile(bounded, 4)
        iu_in, iv_in = tu[inside].astype(np.int64), tv[inside].astype(np.int64)
        taps[inside] = self._pixels(
            eval_haar_point(self.haar, r4[inside] * 6 + f4[inside], iu_in, iv_in),
            f4[inside], iu_in, iv_in, b4[inside])
        sc = 2.0 * (tu + 0.5) / res - 1.0
        tc = 2.0 * (tv + 0.5) / res - 1.0
        basis = FACE_BASIS[f4]  # (4n, 3, 3)
        tap_dirs = basis[:, 0] + sc[:, None] * basis[:, 1] + tc[:, None] * basis[:, 2]
        out = ~inside
        if out.any():
            tf, _, _, tfu, tfv = dirs_to_cube(tap_dirs[out], res)
            taps[out] = self._bilinear_in_face(r4[out], tf, tfu, tfv, b4[out])
        if b4.any():  # F at the taps (in [0, 1]) times U exactly at the tap directions
            td = tap_dirs[b4] / np.linalg.norm(tap_dirs[b4], axis=1, keepdims=True)
            taps[b4] = taps[b4] * eval_closed_form(self.cf, np.tile(texels, 4)[b4], td)
        wts = np.concatenate([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum((taps * wts).reshape(4, -1), axis=0)

    def ray_texel_maps(self, rows: slice | None = None) -> np.ndarray:
        """(n_ray, 6, res, res) float64 a_vis of the ray-based texels (of table rows `rows`,
        default all) at the cube pixels as this table reconstructs them (bounded texels: U
        times the corrected fraction): what a nearest look-up returns there. For measuring
        the table against its uncompressed maps; a full inverse transform, not for
        rendering."""
        res = self.res
        r = self.row_texels.shape[0]
        a, b, _ = (rows or slice(0, r)).indices(r)
        rec = decompress_haar(map_range(self.haar, a * 6, b * 6, (b - a, 6)))
        texels = self.row_texels[a:b]
        bnd = self.bounded[texels]
        face, iv, iu = np.meshgrid(np.arange(6), np.arange(res), np.arange(res), indexing="ij")
        n = rec.shape[0]
        face_k, iu_k, iv_k = (np.broadcast_to(a.ravel(), (n, a.size)).ravel()
                              for a in (face, iu, iv))
        rec = self._pixels(rec.reshape(-1), face_k, iu_k, iv_k,
                           np.repeat(bnd, face.size)).reshape(n, 6, res, res)
        if bnd.any():
            rec[bnd] *= closed_form_maps(self.cf, res, texels[bnd])
        return rec

    def _pixels(self, raw: np.ndarray, face: np.ndarray, iu: np.ndarray, iv: np.ndarray,
                bounded: np.ndarray) -> np.ndarray:
        """Table values at cube pixels: bounded texels' corrected fractions (`_fraction`),
        the other ray texels' corrected a_vis (`_direct`). All arrays (k,)."""
        out = np.empty(raw.shape[0], dtype=np.float64)
        out[bounded] = self._fraction(raw[bounded], face[bounded], iu[bounded], iv[bounded])
        d = ~bounded
        out[d] = self._direct(raw[d], face[d], iu[d], iv[d])
        return out

    def _fraction(self, raw: np.ndarray, face: np.ndarray, iu: np.ndarray, iv: np.ndarray
                  ) -> np.ndarray:
        """A bounded texel's visible fraction at cube pixels: the Haar value clipped to
        [0, 1], then the level's sum correction (`sum_correction`) at those pixels."""
        f = np.clip(raw, 0.0, 1.0)
        k = np.flatnonzero(self.correction_groups == 0)
        if k.size == 0:
            return f
        return apply_correction(f, self.correction[k[0], face, iv, iu], bounded=True)

    def _direct(self, raw: np.ndarray, face: np.ndarray, iu: np.ndarray, iv: np.ndarray
                ) -> np.ndarray:
        """A direct (unbounded) ray texel's a_vis at cube pixels: >= 0, then corrected."""
        a = np.maximum(raw, 0.0)
        k = np.flatnonzero(self.correction_groups == 1)
        if k.size == 0:
            return a
        return apply_correction(a, self.correction[k[0], face, iv, iu], bounded=False)

    def _bilinear_in_face(self, rows: np.ndarray, face: np.ndarray, fu: np.ndarray,
                          fv: np.ndarray, bounded: np.ndarray) -> np.ndarray:
        """Bilinear look-up with coordinates clamped to the face's texel centres (bounded
        rows: of their corrected fractions)."""
        res = self.res
        fu = np.clip(fu, 0.0, res - 1.0)
        fv = np.clip(fv, 0.0, res - 1.0)
        u0 = np.minimum(np.floor(fu).astype(np.int64), max(res - 2, 0))
        v0 = np.minimum(np.floor(fv).astype(np.int64), max(res - 2, 0))
        u1, v1 = np.minimum(u0 + 1, res - 1), np.minimum(v0 + 1, res - 1)
        au, av = fu - u0, fv - v0
        mi = np.tile(rows * 6 + face, 4)
        pu, pv = np.concatenate([u0, u1, u0, u1]), np.concatenate([v0, v0, v1, v1])
        taps = self._pixels(eval_haar_point(self.haar, mi, pu, pv), np.tile(face, 4), pu, pv,
                            np.tile(bounded, 4)).reshape(4, -1)
        wts = np.stack([(1 - au) * (1 - av), au * (1 - av), (1 - au) * av, au * av])
        return np.sum(taps * wts, axis=0)


def _fill_along(f: np.ndarray, ok: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    """Fill undefined entries with the nearest defined entry along one axis (ties: lower
    index). Vectorized: forward and backward running maxima of the defined indices, in int16
    (a cube face's side is far below 2^14), a quarter of int64's memory traffic."""
    n = f.shape[axis]
    it = np.dtype(np.int16 if n < (1 << 14) else np.int64)
    shape = [1] * f.ndim
    shape[axis] = n
    pos = np.arange(n, dtype=it).reshape(shape)
    # 0-d arrays of that type: they keep the arithmetic in it (a Python int is weak too, but
    # spelled so the type checker sees one dtype)
    none, last, far = (np.array(v, it) for v in (-1, n - 1, n + 1))
    prev = np.maximum.accumulate(np.where(ok, pos, none), axis=axis)
    back = np.flip(np.where(ok, last - pos, none), axis=axis)
    nxt = last - np.flip(np.maximum.accumulate(back, axis=axis), axis=axis)
    # nxt: index of the next defined entry, n when none
    d_prev = np.where(prev >= 0, pos - prev, far)
    d_next = np.where(nxt < n, nxt - pos, far)
    src = np.where(d_prev <= d_next, prev, nxt)
    found = np.minimum(d_prev, d_next) <= n
    filled = np.take_along_axis(f, np.clip(src, 0, n - 1).astype(np.intp), axis=axis)
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
    # only a partly defined face is filled: a face defined everywhere is F itself, one defined
    # nowhere stays 0 (np.divide's out); a cube's upper and lower faces are mostly one or the
    # other
    faces = f.reshape(-1, *f.shape[-2:])
    ok = defined.reshape(faces.shape)
    n_ok = ok.sum(axis=(1, 2))
    part = np.flatnonzero((n_ok > 0) & (n_ok < f.shape[-2] * f.shape[-1]))
    if part.size:
        g, ok_g = _fill_along(faces[part], ok[part], axis=-2)  # along columns (iv)
        rows = np.flatnonzero(~ok_g.all(axis=(1, 2)))  # faces with a column without values
        if rows.size:
            g[rows], _ = _fill_along(g[rows], ok_g[rows], axis=-1)  # then along rows (iu)
        faces[part] = g
    return f


def avis_table_arrays(table: AvisTable) -> dict[str, np.ndarray]:
    """An AvisTable as payload arrays (`avis:` namespace)."""
    return {f"avis:{k}": v for k, v in table.to_arrays().items()}


def avis_table_from(arrays: dict[str, np.ndarray]) -> AvisTable:
    """Inverse of `avis_table_arrays` (used by the renderer on `read_baked` output)."""
    return AvisTable.from_arrays(
        {k[5:]: v for k, v in arrays.items() if k.startswith("avis:")}
    )
