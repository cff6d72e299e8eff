"""MERL measured BRDFs: the binary format (MERL's BRDFRead.cpp), the half/difference angle
look-up, tabulation."""

from __future__ import annotations

import functools
import os
from collections.abc import Callable
from typing import Any

import numpy as np

from texelbake.brdf.common import CHUNK, as_dirs, valid_pairs
from texelbake.errors import AssetError, ShapeError
from texelbake.io.atomic import atomic_write_bytes
from texelbake.tol import TOL

#: (BRDFRead.cpp: RED_SCALE = 1/1500, GREEN_SCALE = 1.15/1500, BLUE_SCALE = 1.66/1500)
MERL_SHAPE = (90, 90, 180)
MERL_SCALE = np.array([1.0 / 1500.0, 1.15 / 1500.0, 1.66 / 1500.0])


def write_merl(path: str | os.PathLike[str], table: Any) -> None:
    """Write a BRDF table in the MERL binary format (Matusik et al. 2003, ``BRDFRead.cpp``):
    three little-endian int32 dims (n_theta_half, n_theta_diff, n_phi_diff), then
    3 * prod(dims) little-endian float64, channel-major (R, G, B), each channel C-ordered as
    [theta_half][theta_diff][phi_diff], divided by the channel scale (1, 1.15, 1.66) / 1500.
    Negative values mark invalid entries. Written atomically (temp file + rename).

    table : (3, n_th, n_td, n_pd) float64
    """
    tab = np.asarray(table, dtype=np.float64)
    if tab.ndim != 4 or tab.shape[0] != 3:
        raise ShapeError(f"MERL table must be (3, n_th, n_td, n_pd), got {tab.shape}")
    dims = np.asarray(tab.shape[1:], dtype="<i4")
    data = np.ascontiguousarray(tab / MERL_SCALE[:, None, None, None], dtype="<f8")
    atomic_write_bytes(os.fspath(path), dims.tobytes() + data.tobytes())


def read_merl(path: str | os.PathLike[str]) -> np.ndarray:
    """Read a MERL binary BRDF (layout in :func:`write_merl`).

    returns : (3, n_th, n_td, n_pd) float64 reflectance in 1/sr, channel scales applied,
        invalid (negative) entries set to 0. Standard files are (3, 90, 90, 180).
    raises AssetError (naming the file) when it is missing, truncated or has bad dims.
    """
    path = os.fspath(path)
    try:
        raw = np.fromfile(path, dtype=np.uint8)
    except OSError as exc:
        raise AssetError(f"cannot read MERL BRDF: {exc.strerror}", path=path) from exc
    if raw.size < 12:
        raise AssetError(f"MERL file too short: {raw.size} bytes, expected >= 12", path=path)
    dims = raw[:12].view("<i4").astype(np.int64)
    if np.any(dims <= 0) or np.any(dims > 4096):
        raise AssetError(f"MERL dims must be positive, got {dims.tolist()}", path=path)
    count = 3 * int(np.prod(dims))
    expected = 12 + 8 * count
    if raw.size != expected:
        raise AssetError(
            f"MERL file size {raw.size} bytes does not match dims {dims.tolist()} "
            f"(expected {expected})",
            path=path,
        )
    data = raw[12:].view("<f8").astype(np.float64).reshape(3, *dims.tolist())
    data *= MERL_SCALE[:, None, None, None]
    data[~(data >= 0.0)] = 0.0  # negative = invalid; NaN also dropped
    return data


@functools.lru_cache(maxsize=4)
def _read_merl_cached(path: str, mtime_ns: int, size: int) -> np.ndarray:
    table = read_merl(path)
    table.flags.writeable = False
    return table


def merl_table_from_file(path: str) -> np.ndarray:
    try:
        st = os.stat(path)
    except OSError as exc:
        raise AssetError(f"MERL BRDF file not found: {exc.strerror}", path=path) from exc
    return _read_merl_cached(os.path.abspath(path), st.st_mtime_ns, st.st_size)


def _merl_angles(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, ...]:
    """(theta_half, theta_diff, phi_diff in [0, pi)), each (n,) float64 (Rusinkiewicz 1998
    half/difference angles, as ``std_coords_to_half_diff_coords`` in ``BRDFRead.cpp``)."""
    h = wi + wo
    h /= np.maximum(np.linalg.norm(h, axis=1, keepdims=True), TOL.brdf_eps)
    # cos/sin of theta_half and phi_half straight from h (no trig round trip)
    ct = np.clip(h[:, 2], -1.0, 1.0)
    th = np.arccos(ct)
    st = np.hypot(h[:, 0], h[:, 1])
    pole = st <= TOL.brdf_eps  # h = n: phi_half undefined, take 0 (as atan2(0, 0) in MERL)
    inv = 1.0 / np.where(pole, 1.0, st)
    cp = np.where(pole, 1.0, h[:, 0] * inv)
    sp = np.where(pole, 0.0, h[:, 1] * inv)
    # rotate wi by -phi_half about the normal, then by -theta_half about the binormal
    x = cp * wi[:, 0] + sp * wi[:, 1]
    y = cp * wi[:, 1] - sp * wi[:, 0]
    z = wi[:, 2]
    dx = x * ct - z * st
    dz = x * st + z * ct
    td = np.arccos(np.clip(dz, -1.0, 1.0))
    pd = np.mod(np.arctan2(y, dx), np.pi)  # reciprocity: phi_diff and phi_diff + pi coincide
    return th, td, pd


def merl_lookup(
    table: Any, wi: Any, wo: Any, *, interpolate: bool = False, eps: float = TOL.grazing_cos
) -> np.ndarray:
    """Evaluate a tabulated BRDF in MERL layout.

    Bins as in MERL's ``BRDFRead.cpp``: theta_half index = floor(sqrt(theta_half / (pi/2)) n_th)
    (the non-linear mapping that puts more bins near the specular peak), theta_diff index =
    floor(theta_diff / (pi/2) n_td), phi_diff index = floor((phi_diff mod pi) / pi n_pd) (the
    table stores phi_diff in [0, pi) only, using reciprocity f(phi_d) = f(phi_d + pi)).
    ``interpolate=False`` returns the containing bin (the reference reader); ``True``
    interpolates trilinearly between bin centres in those index coordinates (clamped in the
    two theta axes, periodic in phi_diff).

    table : (3, n_th, n_td, n_pd) float64 (from :func:`read_merl` / :func:`tabulate_merl`)
    wi, wo : (n, 3) float64; returns : (n, 3) float64
    """
    tab = np.asarray(table, dtype=np.float64)
    if tab.ndim != 4 or tab.shape[0] != 3:
        raise ShapeError(f"MERL table must be (3, n_th, n_td, n_pd), got {tab.shape}")
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    n_th, n_td, n_pd = tab.shape[1:]
    flat = tab.reshape(3, -1)
    ok = valid_pairs(wi, wo, eps)
    out = np.zeros((n, 3), dtype=np.float64)
    up_z = np.array([0.0, 0.0, 1.0])
    for lo in range(0, n, CHUNK):
        hi = min(lo + CHUNK, n)
        okb = ok[lo:hi, None]  # invalid rows (zeroed below) get a harmless stand-in direction
        th, td, pd = _merl_angles(np.where(okb, wi[lo:hi], up_z), np.where(okb, wo[lo:hi], up_z))
        uh = np.sqrt(th * (2.0 / np.pi)) * n_th
        ud = td * (2.0 / np.pi) * n_td
        up = pd * (1.0 / np.pi) * n_pd
        if not interpolate:
            ih = np.clip(uh.astype(np.int64), 0, n_th - 1)
            i_d = np.clip(ud.astype(np.int64), 0, n_td - 1)
            ip = np.clip(up.astype(np.int64), 0, n_pd - 1)
            idx = (ih * n_td + i_d) * n_pd + ip
            for ch in range(3):  # np.take per channel: ~10x faster than flat[:, idx]
                out[lo:hi, ch] = np.take(flat[ch], idx)
            continue
        xh = np.clip(uh - 0.5, 0.0, n_th - 1.0)
        xd = np.clip(ud - 0.5, 0.0, n_td - 1.0)
        xp = np.mod(up - 0.5, n_pd)
        h0 = np.minimum(xh.astype(np.int64), n_th - 2) if n_th > 1 else np.zeros(hi - lo, int)
        d0 = np.minimum(xd.astype(np.int64), n_td - 2) if n_td > 1 else np.zeros(hi - lo, int)
        p0 = np.minimum(xp.astype(np.int64), n_pd - 1)
        fh, fd, fp = xh - h0, xd - d0, xp - p0
        h1 = np.minimum(h0 + 1, n_th - 1)
        d1 = np.minimum(d0 + 1, n_td - 1)
        p1 = (p0 + 1) % n_pd
        acc = np.zeros((hi - lo, 3))
        for ih, wh in ((h0, 1.0 - fh), (h1, fh)):  # 8 corners
            for i_d, wd in ((d0, 1.0 - fd), (d1, fd)):
                for ip, wp in ((p0, 1.0 - fp), (p1, fp)):
                    idx = (ih * n_td + i_d) * n_pd + ip
                    wgt = wh * wd * wp
                    for ch in range(3):
                        acc[:, ch] += np.take(flat[ch], idx) * wgt
        out[lo:hi] = acc
    out[~ok] = 0.0
    return out


def merl_bin_directions(shape: tuple[int, int, int] = MERL_SHAPE) -> tuple[np.ndarray, np.ndarray]:
    """The (wi, wo) pair at the centre of every MERL bin, with phi_half = 0.

    Bin centres: theta_half = ((i + 0.5) / n_th)^2 pi/2 (inverse of the sqrt mapping),
    theta_diff = (j + 0.5) / n_td pi/2, phi_diff = (k + 0.5) / n_pd pi. wi is the difference
    vector rotated back by theta_half about the binormal; wo is wi mirrored about h.
    returns : wi, wo each (n_th * n_td * n_pd, 3) float64, in the table's C order. Pairs with a
        direction below the horizon are included (a BRDF returns 0 there).
    """
    n_th, n_td, n_pd = (int(s) for s in shape)
    th = ((np.arange(n_th) + 0.5) / n_th) ** 2 * (0.5 * np.pi)
    td = (np.arange(n_td) + 0.5) / n_td * (0.5 * np.pi)
    pd = (np.arange(n_pd) + 0.5) / n_pd * np.pi
    th_g, td_g, pd_g = (g.ravel() for g in np.meshgrid(th, td, pd, indexing="ij"))
    d = np.stack([np.sin(td_g) * np.cos(pd_g), np.sin(td_g) * np.sin(pd_g), np.cos(td_g)], axis=1)
    ct, st = np.cos(th_g), np.sin(th_g)
    wi = np.stack([d[:, 0] * ct + d[:, 2] * st, d[:, 1], d[:, 2] * ct - d[:, 0] * st], axis=1)
    h = np.stack([st, np.zeros_like(st), ct], axis=1)
    wo = 2.0 * np.sum(h * wi, axis=1, keepdims=True) * h - wi
    return wi, wo


def tabulate_merl(
    fn: Callable[[np.ndarray, np.ndarray], np.ndarray],
    shape: tuple[int, int, int] = MERL_SHAPE,
) -> np.ndarray:
    """Tabulate an analytic BRDF ``fn(wi (m, 3), wo (m, 3)) -> (m, 3)`` at the MERL bin centres
    (:func:`merl_bin_directions`). returns : (3, n_th, n_td, n_pd) float64."""
    wi, wo = merl_bin_directions(shape)
    vals = np.empty((wi.shape[0], 3))
    step = 1 << 18
    for lo in range(0, wi.shape[0], step):  # bounded memory for fn's temporaries
        v = np.asarray(fn(wi[lo : lo + step], wo[lo : lo + step]), dtype=np.float64)
        if v.shape != (min(step, wi.shape[0] - lo), 3):
            raise ShapeError(f"fn must return (m, 3) values, got {v.shape}")
        vals[lo : lo + step] = v
    return np.ascontiguousarray(vals.T.reshape(3, *shape))
