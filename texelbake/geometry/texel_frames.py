"""Texel frames: each texel's tangent frame from the area-weighted normal of its M1 region and the
atlas's UV tangent, summed a chunk of samples at a time."""

from __future__ import annotations

import numpy as np

from texelbake.errors import ShapeError
from texelbake.geometry.atlas import Atlas, rasterize_atlas
from texelbake.geometry.basis import tangent_frames
from texelbake.geometry.mesh import Mesh, check_points
from texelbake.geometry.texels import TexelAssignment, texel_centers_uv
from texelbake.io.chunks import bincount_continued
from texelbake.tol import TOL


def face_uv_tangents(atlas: Atlas) -> tuple[np.ndarray, np.ndarray]:
    """d position / d u of every atlas triangle (the UV tangent), unit length.

    Solves [e1 e2] = [dP/du dP/dv] [[du1 du2], [dv1 dv2]] per triangle.
    returns : (tangent (f, 3) float64, valid (f,) bool — False where the uv triangle is
        degenerate; those rows are zero)
    """
    tri = atlas.mesh.triangles()  # (f, 3, 3)
    cuv = atlas.corner_uvs
    e1 = tri[:, 1] - tri[:, 0]
    e2 = tri[:, 2] - tri[:, 0]
    d1 = cuv[:, 1] - cuv[:, 0]
    d2 = cuv[:, 2] - cuv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]  # (f,)
    scale = float(np.abs(cuv).max()) if cuv.size else 1.0
    ok = np.abs(det) > TOL.zero_area * scale * scale
    safe = np.where(ok, det, 1.0)
    dpdu = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe[:, None]
    length = np.linalg.norm(dpdu, axis=1)
    ok &= length > 0
    tangent = np.divide(dpdu, length[:, None], out=np.zeros_like(dpdu), where=ok[:, None])
    return tangent, ok


def texel_frames(
    assignment: TexelAssignment,
    normals: object,
    areas: object,
    m1: Mesh,
    atlas: Atlas,
    level: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Tangent frame (rows t, b, n) of every texel at `level`.

    n = Σ ΔA_j n_j / |Σ ΔA_j n_j| over the texel's samples (area-weighted mean normal);
    t = the UV tangent dP/du of the M1 triangle under the texel centre (when the centre is
    outside every chart, of the triangle under the texel's sample nearest the centre in uv),
    made orthogonal to n; b = n × t (right-handed; on a mirrored chart b = -dP/dv).
    Texels with no samples, or whose normals cancel, get a frame from the M1 triangle under
    their centre (or the default frame of `texelbake.geometry.basis.tangent_frames`) and valid False.

    normals : (m, 3) float64 sample shading normals; areas : (m,) float64 ΔA
    returns : (frames (N_ℓ², 3, 3) float64, valid (N_ℓ²,) bool)
    """
    nrm = check_points(normals, "normals")
    w = np.asarray(areas, dtype=np.float64)
    m = assignment.prim.shape[0]
    if nrm.shape[0] != m or w.shape != (m,):
        raise ShapeError(
            f"normals (m, 3) and areas (m,) must match the {m} assigned samples, "
            f"got {nrm.shape} and {w.shape}"
        )
    if m1.num_faces != atlas.mesh.num_faces:
        raise ShapeError(
            f"m1 has {m1.num_faces} faces but the atlas mesh has {atlas.mesh.num_faces}"
        )
    acc = FrameSums(atlas, assignment.resolution_at(level))
    acc.add(assignment.row >> level, assignment.col >> level, nrm, w, assignment.uv,
            assignment.prim)
    return acc.frames(atlas)


class FrameSums:
    """`texel_frames` of one level, accumulated over consecutive chunks of samples (the
    geometry stage's pass over a spooled 512² sample set). Sums over a texel's samples are
    continued across chunks in sample order (`chunks.bincount_continued`), so any chunking
    gives the one-pass result bit for bit."""

    def __init__(self, atlas: Atlas, n_l: int) -> None:
        self.n_l = int(n_l)
        n_tex = self.n_l * self.n_l
        self.nsum = np.zeros((n_tex, 3))
        self.wsum = np.zeros(n_tex)
        self.counts = np.zeros(n_tex, np.int64)
        self.under, _, _ = rasterize_atlas(atlas.corner_uvs, self.n_l)  # M1 face under centre
        self.centres = texel_centers_uv(self.n_l)
        # fallback where no face lies under the centre: of the texel's samples, the one
        # nearest the centre in uv (ties: the lowest sample id); only those texels' samples
        # are looked at (sorting all 16.8 M at 512² was the geometry stage's peak)
        self.best_dist = np.full(n_tex, np.inf)
        self.nearest_face = np.full(n_tex, -1, dtype=np.int64)

    def add(self, row: np.ndarray, col: np.ndarray, nrm: np.ndarray, w: np.ndarray,
            uv: np.ndarray, prim: np.ndarray) -> None:
        """The next chunk of samples (chunks come in sample order): their texel row, col at
        this level, shading normals, ΔA, atlas uv and M1 triangle."""
        n_tex = self.n_l * self.n_l
        idx = row * self.n_l + col
        for k in range(3):  # x, y, z
            self.nsum[:, k] = bincount_continued(self.nsum[:, k], idx, w * nrm[:, k])
        self.wsum[:] = bincount_continued(self.wsum, idx, np.abs(w))
        self.counts += np.bincount(idx, minlength=n_tex)
        sel = np.flatnonzero(self.under[idx] < 0)  # ascending in the chunk
        if sel.size:
            isel = idx[sel]
            dist = np.linalg.norm(uv[sel] - self.centres[isel], axis=1)
            order = np.lexsort((sel, dist, isel))
            head = np.ones(sel.size, dtype=bool)
            head[1:] = isel[order][1:] != isel[order][:-1]
            t, d = isel[order][head], dist[order][head]
            # an earlier chunk's sample keeps a tie: its id is lower
            better = d < self.best_dist[t]
            self.best_dist[t[better]] = d[better]
            self.nearest_face[t[better]] = prim[sel][order][head][better]

    def frames(self, atlas: Atlas) -> tuple[np.ndarray, np.ndarray]:
        nsum = self.nsum
        length = np.linalg.norm(nsum, axis=1)
        valid = (self.counts > 0) & (length > TOL.grazing_cos * self.wsum) & (length > 0)
        face_tangent, tangent_ok = face_uv_tangents(atlas)
        face_normal = atlas.mesh.face_normals()
        face = np.where(self.under >= 0, self.under, self.nearest_face)  # (N_ℓ²,)
        has_face = face >= 0
        safe_face = np.where(has_face, face, 0)
        n_out = np.where(
            valid[:, None],
            np.divide(nsum, length[:, None], out=np.zeros_like(nsum),
                      where=length[:, None] > 0),
            np.where(has_face[:, None], face_normal[safe_face], 0.0),
        )
        t_in = np.where((has_face & tangent_ok[safe_face])[:, None], face_tangent[safe_face],
                        0.0)
        return tangent_frames(n_out, t_in), valid
