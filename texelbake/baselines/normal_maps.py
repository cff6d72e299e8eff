"""The baseline studios bake today: albedo and tangent-space normal maps of M_org onto M1
(what Blender, Substance and xNormal produce), and the tangent space they are expressed in.

Tangent space convention (MikkTSpace-like, per M1 triangle): n = the M1 face normal,
t = dP/du made orthogonal to n, b = sign * (n x t) with sign = sign((n x t) . dP/dv) so
mirrored charts keep the map's green axis along +v. A sample's normal n_s is stored as
(t . n_s, b . n_s, n . n_s). The renderer's `normalmap` mode decodes with the same function.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from texelbake import brdf
from texelbake.errors import ShapeError
from texelbake.geometry.basis import tangent_frames
from texelbake.io.chunks import bincount_continued
from texelbake.model import Material
from texelbake.tol import TOL


def face_tangent_space(
    vertices: np.ndarray, faces: np.ndarray, corner_uvs: np.ndarray
) -> np.ndarray:
    """(f, 3, 3) float64 rows (t, b, n) per triangle (see module docstring).

    vertices : (n, 3) float64; faces : (f, 3) int64; corner_uvs : (f, 3, 2) float64.
    Triangles with degenerate uvs get the default frame of `frames.tangent_frames`.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cuv = np.asarray(corner_uvs, dtype=np.float64)
    if cuv.shape != (len(f), 3, 2):
        raise ShapeError(f"corner_uvs must be ({len(f)}, 3, 2), got {cuv.shape}")
    tri = v[f]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    ok = np.abs(det) > TOL.zero_area
    safe = np.where(ok, det, 1.0)[:, None]
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe
    dpdv = (e2 * d1[:, 0:1] - e1 * d2[:, 0:1]) / safe
    n = np.cross(e1, e2)
    frames = tangent_frames(n, np.where(ok[:, None], dpdu, 0.0))
    sign = np.where(np.sum(frames[:, 1] * dpdv, axis=1) < 0.0, -1.0, 1.0)
    frames[:, 1] *= sign[:, None]
    return frames


def dilate(values: np.ndarray, filled: np.ndarray, iterations: int = 8) -> np.ndarray:
    """Fill empty texels with the mean of their filled 4-neighbours, repeatedly, so bilinear
    look-ups at chart borders do not blend in zeros (the usual bake "padding").

    values : (N, N, c) float64; filled : (N, N) bool; returns (N, N, c) float64
    """
    out = np.array(values, dtype=np.float64, copy=True)
    have = np.array(filled, dtype=bool, copy=True)
    for _ in range(iterations):  # a few passes over the whole map, vectorized per pass
        if have.all():
            break
        acc = np.zeros_like(out)
        cnt = np.zeros(have.shape)
        for dy, dx in ((0, 1), (0, -1), (1, 0), (-1, 0)):
            acc += np.roll(np.where(have[..., None], out, 0.0), (dy, dx), axis=(0, 1))
            cnt += np.roll(have, (dy, dx), axis=(0, 1))
        new = (~have) & (cnt > 0)
        out[new] = acc[new] / cnt[new][:, None]
        have |= new
    return out


def bake_preview_maps(
    resolution: int,
    texel: np.ndarray,
    area: np.ndarray,
    sample_normals: np.ndarray,
    sample_uv: np.ndarray,
    sample_material: np.ndarray,
    materials: Sequence[Material],
    m1_frames: np.ndarray,
    sample_m1_face: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Area-weighted albedo and tangent-space normal per texel of M1's atlas (`PreviewSums`
    takes the samples a chunk at a time with the same result).

    texel : (m,) int64 flat texel ids at level 0; area : (m,) ΔA; sample_normals : (m, 3)
    sample_uv : (m, 2) the samples' own texture coordinates (for textured albedo)
    sample_material : (m,) int32; m1_frames : (f1, 3, 3) from `face_tangent_space`
    sample_m1_face : (m,) int64 M1 triangle under each sample (closest point)
    returns : (albedo (N, N, 3) float32, normal (N, N, 3) float32 unit, filled (N, N) bool)
    """
    sums = PreviewSums(resolution)
    sums.add(texel, area, sample_normals, sample_uv, sample_material, materials, m1_frames,
             sample_m1_face)
    return sums.maps()


class PreviewSums:
    """`bake_preview_maps` over chunks of samples given in order, the sums continued across
    chunks (`chunks.bincount_continued`): the one-pass maps bit for bit."""

    def __init__(self, resolution: int) -> None:
        self.resolution = int(resolution)
        n_tex = self.resolution * self.resolution
        self.wsum = np.zeros(n_tex)
        self.alb = np.zeros((3, n_tex))
        self.nrm = np.zeros((3, n_tex))

    def add(self, texel: np.ndarray, area: np.ndarray, sample_normals: np.ndarray,
            sample_uv: np.ndarray, sample_material: np.ndarray, materials: Sequence[Material],
            m1_frames: np.ndarray, sample_m1_face: np.ndarray) -> None:
        """The next chunk of samples (arguments as `bake_preview_maps`')."""
        albedo_s = np.zeros((len(texel), 3))
        for mi in np.unique(sample_material):  # a loop over the few materials
            sel = sample_material == mi
            albedo_s[sel] = brdf.diffuse_albedo(materials[int(mi)], sample_uv[sel])
        local = np.einsum("mij,mj->mi", m1_frames[sample_m1_face], sample_normals)
        self.wsum = bincount_continued(self.wsum, texel, area)
        for c in range(3):  # r, g, b / x, y, z
            self.alb[c] = bincount_continued(self.alb[c], texel, area * albedo_s[:, c])
            self.nrm[c] = bincount_continued(self.nrm[c], texel, area * local[:, c])

    def maps(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        resolution, n_tex = self.resolution, self.resolution * self.resolution
        wsum = self.wsum
        filled = wsum > 0
        alb = np.divide(np.ascontiguousarray(self.alb.T), wsum[:, None],
                        out=np.zeros((n_tex, 3)), where=filled[:, None])
        nrm = np.ascontiguousarray(self.nrm.T)  # (N², 3) as the one-pass stack
        length = np.linalg.norm(nrm, axis=1, keepdims=True)
        nrm = np.divide(nrm, length, out=np.tile([0.0, 0.0, 1.0], (n_tex, 1)),
                        where=length > 0)
        shape = (resolution, resolution, 3)
        f2 = filled.reshape(resolution, resolution)
        alb = dilate(alb.reshape(shape), f2)
        nrm = dilate(nrm.reshape(shape), f2)
        nrm = nrm / np.maximum(np.linalg.norm(nrm, axis=2, keepdims=True), 1e-12)
        return alb.astype(np.float32), nrm.astype(np.float32), f2
