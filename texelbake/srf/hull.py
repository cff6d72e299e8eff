"""The visual hull of a captured field (seed 002 §3: the impostor "can easily be determined
from observed silhouette images"): a voxel grid over the object's bounds is carved by every
camera's silhouette and the kept voxels' outer faces become a closed, outward-facing
triangle mesh (a cuberille), which `surfels.surfels_from_mesh` samples.

Carving is conservative: a voxel goes only where a camera sees its centre outside the
silhouette dilated by `DILATE_PX` pixels and the voxel's projected half-diagonal, so a voxel
the object touches is never removed; cameras that do not see a voxel (outside the image,
behind) do not carve it. The mesh follows the kept cubes' faces, so it encloses every kept
voxel (blocky at the grid's resolution; finer grids cost r³ projections per camera).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.ndimage import maximum_filter

from texelbake.errors import SettingsError
from texelbake.srf.rig import project
from texelbake.srf.store import SrfStore

#: silhouettes are dilated by this many pixels beyond each voxel's own projected size
DILATE_PX = 1
DEFAULT_RESOLUTION = 40


def carve(store: SrfStore, resolution: int = DEFAULT_RESOLUTION,
          bounds: object | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Voxels kept by every silhouette.

    bounds : (2, 3) region to carve (default: the store's `bounds`, padded by two voxels)
    returns (occupancy (r, r, r) bool indexed [x, y, z], lower corner (3,), voxel edge)"""
    r = int(resolution)
    if r < 2:
        raise SettingsError(f"field 'resolution': at least 2 voxels per side, got {r}")
    if bounds is None:
        if "bounds" not in store.meta:
            raise SettingsError(f"store {store.path}: no 'bounds' to carve in; pass bounds")
        bounds = store.meta["bounds"]
    b = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    edge = float((b[1] - b[0]).max()) / (r - 4)
    lo = 0.5 * (b[0] + b[1]) - 0.5 * r * edge
    idx = np.stack(np.meshgrid(*(np.arange(r),) * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    centres = lo + (idx + 0.5) * edge
    keep = np.ones(centres.shape[0], bool)
    half_diag = 0.5 * math.sqrt(3.0) * edge
    for c, cam in enumerate(store.cameras):  # a loop over the cameras, vectorised over voxels
        sil = store.silhouette(c) > 0
        xy, front = project(cam, centres)
        inside = front & (xy[:, 0] >= 0) & (xy[:, 0] < cam.width) & (xy[:, 1] >= 0) & (
            xy[:, 1] < cam.height)
        if not inside.any():
            continue
        depth = (centres[inside] - cam.position) @ cam.forward
        reach_px = half_diag / (depth.min() * cam.pixel_angle) + DILATE_PX  # projected size
        size = int(2 * min(math.ceil(reach_px), max(cam.width, cam.height)) + 1)
        grown = maximum_filter(sil, size=size, mode="constant", cval=False)
        ix = np.clip(xy[:, 0].astype(np.int64), 0, cam.width - 1)
        iy = np.clip(xy[:, 1].astype(np.int64), 0, cam.height - 1)
        keep &= ~(inside & ~grown[iy, ix])
    return keep.reshape(r, r, r), lo, edge


_QUAD = np.array([[0, 0], [1, 0], [1, 1], [0, 1]])


def cuberille(occ: np.ndarray, lo: object, edge: float) -> tuple[np.ndarray, np.ndarray]:
    """The outer faces of the occupied voxels as a triangle mesh, counter-clockwise seen from
    outside. returns (vertices (v, 3) float64, faces (f, 3) int64)"""
    occ = np.asarray(occ, dtype=bool)
    pad = np.pad(occ, 1)
    corners: list[np.ndarray] = []
    for a in range(3):  # six face orientations
        b_ax, c_ax = (a + 1) % 3, (a + 2) % 3
        for side in (1, -1):
            nb = np.roll(pad, -side, axis=a)[1:-1, 1:-1, 1:-1]
            vox = np.argwhere(occ & ~nb)  # (m, 3)
            if vox.size == 0:
                continue
            quad = _QUAD if side == 1 else _QUAD[::-1]
            q = np.repeat(vox[:, None, :], 4, axis=1)
            q[:, :, a] += 1 if side == 1 else 0
            q[:, :, b_ax] += quad[:, 0]
            q[:, :, c_ax] += quad[:, 1]
            corners.append(q)
    if not corners:
        return np.zeros((0, 3)), np.zeros((0, 3), np.int64)
    allc = np.concatenate(corners)  # (m, 4, 3) lattice points
    uniq, inv = np.unique(allc.reshape(-1, 3), axis=0, return_inverse=True)
    quads = inv.reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
    return np.asarray(lo, dtype=np.float64) + uniq * float(edge), faces.astype(np.int64)


def visual_hull(store: SrfStore, resolution: int = DEFAULT_RESOLUTION,
                bounds: object | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The carved visual hull as a mesh (vertices (v, 3), faces (f, 3))."""
    occ, lo, edge = carve(store, resolution, bounds)
    if not occ.any():
        raise SettingsError(f"store {store.path}: the silhouettes carve every voxel away "
                            f"(cameras disagree, or the bounds miss the object)")
    return cuberille(occ, lo, edge)
