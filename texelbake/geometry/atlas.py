"""The UV atlas T on M1 and the composite map T(T_i(·)) of the coarser meshes into it
(seed 000, §4.1).

Texel convention (shared by every stage): an atlas of resolution N is an N × N image, row 0
at the top. uv = (u, v) in [0, 1]²; texel (row, col) = (floor((1 - v) N), floor(u N)), flat
index row * N + col. `texelbake.geometry.texels` holds the conversions.

Backend: xatlas. Measured on a 5120-triangle icosphere at N = 256 (2 shared cores):
xatlas ~0.02–0.1 s per generate (2–3 generates to fit N exactly; 7–9 charts; padding in
exact texels; deterministic); open3d `compute_uvatlas` ~0.11–0.15 s with
parallel_partitions (also deterministic here) but takes a gutter, not texel padding, and
does not fill the square (v max 0.89). xatlas is used for the exact texel padding.
Charts cover ~40–45 % of the page with 2 texels of padding (more charts, less cover: the
full-size wall, 1753 charts at N = 512, ~13 %). xatlas returns float32 uvs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from texelbake.errors import SettingsError, ShapeError, StageError
from texelbake.geometry.closest import closest_point_on_triangles
from texelbake.geometry.mesh import Mesh, face_components, triangle_areas
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.xatlas_child import Packed, xatlas_pack

#: xatlas packing is retried with a texel density shrunk by _STEP until one N × N page holds
#: all charts, then bisected between the last density that did not fit and the first that did
#: until they are within 1 / _SHRINK; below _MIN_DENSITY of the first guess it gives up
_SHRINK = 0.96
_STEP = 0.8
_MIN_DENSITY = _SHRINK ** 60
#: an atlas is refused when more than MAX_COLLAPSED_AREA of M1's area lies on faces whose UV
#: area per 3D area is under COLLAPSED_RATIO of the median face's (`collapsed_area_fraction`)
MAX_COLLAPSED_AREA = 0.01
COLLAPSED_RATIO = 0.01
#: fraction of the way from a corner of M_i to its face's centroid used to pick its chart
SEAM_PULL = 1e-3
#: a coarser mesh's face never takes an atlas triangle more than 120° from its own normal
#: (`map_into_atlas`): where M_T's sheet on one side of a thin part is the nearer to the
#: other side's faces, closest point alone gives both sides one uv chart
FACING_MIN_COS = -0.5
#: point-triangle pairs per chunk of the facing-restricted closest-point search
_FACING_PAIRS = 1 << 18
#: assumed fraction of the square the packed charts cover, for the first density guess
_FIRST_UTILIZATION = 0.8


@dataclass(frozen=True, eq=False)
class Atlas:
    """A UV atlas on M1.

    mesh : M1 with vertices split along chart seams; same faces in the same order as the
        M1 it was built from (so triangle ids agree)
    corner_uvs : (f, 3, 2) float64 in [0, 1]
    resolution : N, texels per side at level 0
    vertex_map : (n_split,) int64, the M1 vertex each split vertex copies
    face_chart : (f,) int64 chart id of each face
    padding_texels : gap kept around charts at level 0
    """

    mesh: Mesh
    corner_uvs: np.ndarray
    resolution: int
    vertex_map: np.ndarray
    face_chart: np.ndarray
    padding_texels: int = 2

    @property
    def num_charts(self) -> int:
        return int(self.face_chart.max()) + 1 if self.face_chart.shape[0] else 0

    def vertex_uvs(self) -> np.ndarray:
        """(n_split, 2) float64 uv per split vertex (each split vertex has one uv)."""
        uv = np.zeros((self.mesh.num_vertices, 2))
        uv[self.mesh.faces.ravel()] = self.corner_uvs.reshape(-1, 2)
        return uv

    def uv_areas(self) -> np.ndarray:
        """(f,) float64 signed uv-space areas (positive = counter-clockwise in (u, v))."""
        return corner_uv_areas(self.corner_uvs)


def corner_uv_areas(corner_uvs: np.ndarray) -> np.ndarray:
    """(f,) float64 signed areas of triangles given by their corner uvs (f, 3, 2)."""
    e1 = corner_uvs[:, 1] - corner_uvs[:, 0]
    e2 = corner_uvs[:, 2] - corner_uvs[:, 0]
    return 0.5 * (e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])


def _xatlas_pack(
    vertices: np.ndarray, faces: np.ndarray, resolution: int, padding: int, tpu: float
) -> Packed:
    """One xatlas pack, in a child process (`geometry.xatlas_child`: xatlas can hang)."""
    return xatlas_pack(vertices, faces, resolution, padding, tpu)


def collapsed_area_fraction(vertices: np.ndarray, faces: np.ndarray,
                            corner_uvs: np.ndarray) -> float:
    """Fraction of a mesh's 3D area on faces that the UV map all but collapses: UV area per 3D
    area under COLLAPSED_RATIO of the (area-weighted) median face's. xatlas packs every chart
    at one texel density, so a sound atlas has ratios within its charts' conformal distortion
    (a few x); measured on the full bolt's LOD1 at 64², 332 of 8,124 faces (a strip along the
    shaft) had UV areas of 1e-5 texels and their 6,162 dense samples fell in one texel (the
    median texel: 13), which both misrepresents that strip and holds one texel's R at 0.6 GB.

    vertices : (v, 3); faces : (f, 3); corner_uvs : (f, 3, 2); returns a fraction in [0, 1]"""
    a3 = triangle_areas(np.asarray(vertices, np.float64), np.asarray(faces, np.int64))
    a2 = np.abs(corner_uv_areas(np.asarray(corner_uvs, np.float64)))
    ok = a3 > 0
    total = float(a3.sum())
    if not ok.any() or total <= 0:
        return 0.0
    ratio = a2[ok] / a3[ok]
    order = np.argsort(ratio)
    w = np.cumsum(a3[ok][order])
    median = ratio[order][np.searchsorted(w, 0.5 * w[-1])]  # area-weighted median
    return float(a3[ok][ratio < COLLAPSED_RATIO * median].sum() / total)


def build_atlas(mesh: Mesh, resolution: int, padding_texels: int = 2) -> Atlas:
    """UV-parameterize M1 into one N × N page with xatlas.

    xatlas packs at a texel density (texels per scene unit): one unconstrained pack gives
    the page size at a first-guess density, the density is scaled so that size becomes N,
    then shrunk by 20 % steps until every chart fits one page of exactly N × N texels and
    bisected (geometric mean) between the last density that did not fit and the first that
    did until they are within 4 %; the densest fitting pack is kept. Each pack recomputes the
    charts (the binding has no separate pack step): on the full bolt's LOD1 at 64^2 a pack
    is 2.9 s, and 4 % steps all the way would take 27 packs (77 s) to fit, and 60 (39 s at
    32^2) to give up on a mesh whose padded charts never fit one page.
    mesh : M1; resolution : N (>= 8); padding_texels : >= 0
    returns : Atlas
    raises SettingsError for bad arguments, StageError when packing does not converge or
    collapses charts (`collapsed_area_fraction` over MAX_COLLAPSED_AREA; the geometry stage
    then falls back to the atlas chain's smaller M1, as when LOD1 does not fit).
    """
    n = int(resolution)
    if n < 8:
        raise SettingsError(f"atlas resolution must be >= 8, got {resolution}")
    if int(padding_texels) < 0:
        raise SettingsError(f"padding_texels must be >= 0, got {padding_texels}")
    if mesh.num_faces == 0:
        raise StageError("geometry: cannot build an atlas on M1 with 0 faces")
    area = mesh.area()
    if not area > 0:
        raise StageError(f"geometry: M1 has surface area {area}; expected > 0")

    def fits(candidate: Packed) -> bool:
        return candidate.atlas_count == 1 and candidate.width == n and candidate.height == n

    # 1) pack at a first-guess density with no page limit; 2) scale the density so the
    # larger side becomes N; 3) shrink by small steps until one N x N page holds it all
    # (padding is in absolute texels, so the scaling is close but not exact).
    tpu = math.sqrt(_FIRST_UTILIZATION * n * n / area)
    free = _xatlas_pack(mesh.vertices, mesh.faces, 0, padding_texels, tpu)
    side = max(free.width, free.height)
    if side > 0:
        tpu *= (n - padding_texels) / side
    floor = tpu * _MIN_DENSITY
    # the search's lowest density: the last of its steps down that is not under the floor
    lowest = tpu * _STEP ** math.floor(math.log(_MIN_DENSITY) / math.log(_STEP) + 1e-9)
    best: Packed | None = None
    too_dense = None  # the lowest density seen that did not fit
    probed = False
    while True:  # packing attempts (~10), each over all charts at once
        xa = _xatlas_pack(mesh.vertices, mesh.faces, n, padding_texels, tpu)
        if fits(xa):
            best, fit_tpu = xa, tpu
        else:
            too_dense = tpu
        if best is None and not probed and tpu > lowest:
            # the first density did not fit: before stepping down, one pack at the lowest
            # density the search would reach. Charts shrink with the density down to their
            # padded minimum, so a mesh that fails there is taken to fail at every step above
            # it (an assumption on xatlas's packer, a heuristic: smaller charts never needing
            # more pages; the full bolt's LOD1 at 32^2 needs 3 pages at every density, and the
            # steps took 11 packs, 11 s, to learn it). A probe that fits is only a probe: the
            # steps go on as before, so every atlas found is the one found without it.
            probed = True
            low = _xatlas_pack(mesh.vertices, mesh.faces, n, padding_texels, lowest)
            if not fits(low):
                xa, tpu = low, lowest
        if best is None:  # no fit yet: step down
            if tpu * _STEP < floor:
                raise StageError(
                    f"geometry: xatlas could not pack M1 ({mesh.num_faces} faces) into one "
                    f"{n} x {n} page (last: {xa.atlas_count} pages of {xa.width} x "
                    f"{xa.height}); raise atlas_resolution or lower m1_faces")
            tpu *= _STEP
            continue
        if too_dense is None or too_dense * _SHRINK <= fit_tpu:
            break  # the densest fit so far is within 4 % of a density that did not fit
        tpu = math.sqrt(fit_tpu * too_dense)  # bisect
    xa = best
    vmap, indices, uvs = xa[0]
    vmap = vmap.astype(np.int64)
    indices = indices.astype(np.int64)
    if indices.shape != mesh.faces.shape or not np.array_equal(vmap[indices], mesh.faces):
        raise StageError("geometry: xatlas changed the face order of M1; cannot keep triangle ids")
    # xatlas uv = (x / width, y / height) with y the image row (down); texelbake's v is up
    uv = np.column_stack([uvs[:, 0].astype(np.float64), 1.0 - uvs[:, 1].astype(np.float64)])
    uv = np.clip(uv, 0.0, 1.0)
    split = Mesh(mesh.vertices[vmap], indices)
    lost = collapsed_area_fraction(split.vertices, indices, uv[indices])
    if lost > MAX_COLLAPSED_AREA:
        raise StageError(
            f"geometry: xatlas collapsed charts of M1 ({mesh.num_faces} faces): {lost:.1%} of "
            f"its area has under {COLLAPSED_RATIO:.0%} of the median texels per area, so its "
            f"samples would crowd into a few texels")
    return Atlas(
        mesh=split,
        corner_uvs=uv[indices],
        resolution=n,
        vertex_map=vmap,
        face_chart=face_components(indices, split.num_vertices),
        padding_texels=int(padding_texels),
    )


def _interp_uv(atlas: Atlas, prim: np.ndarray, bary2: np.ndarray) -> np.ndarray:
    """(n, 2) uv at barycentrics (u, v) (open3d convention) of atlas triangles `prim`."""
    w = np.column_stack([1.0 - bary2[:, 0] - bary2[:, 1], bary2])  # (n, 3)
    return np.einsum("nk,nkd->nd", w, atlas.corner_uvs[prim])


def atlas_uv_of_points(
    points: object, atlas: Atlas, caster: RayCaster | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The composite map evaluated exactly at arbitrary points (e.g. ray hits on M_i):
    closest point on M1, then its atlas uv.

    points : (n, 3) float64
    caster : a RayCaster over atlas.mesh (built when None; pass one to reuse it)
    returns : (uv (n, 2) float64, prim (n,) int64 M1 triangle, distance (n,) float64)
    """
    pts = np.asarray(points, dtype=np.float64)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ShapeError(f"points must have shape (n, 3), got {pts.shape}")
    if caster is None:
        caster = RayCaster(atlas.mesh.vertices, atlas.mesh.faces)
    elif caster.num_faces != atlas.mesh.num_faces:
        raise ShapeError(
            f"caster has {caster.num_faces} faces, the atlas mesh {atlas.mesh.num_faces}"
        )
    if pts.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros(0)
    closest, prim, bary = caster.closest_points(pts)
    return _interp_uv(atlas, prim, bary), prim, np.linalg.norm(closest - pts, axis=1)


def _closest_facing(caster: RayCaster, mesh: Mesh, points: np.ndarray, normals: np.ndarray
                    ) -> np.ndarray:
    """(n,) int64 closest triangle of `mesh` to each point among those facing its normal
    (cos >= FACING_MIN_COS): the caster's closest triangle, re-searched exhaustively (in
    chunks of point-triangle pairs) where that one faces away. Points whose normal no
    triangle faces keep the caster's.

    points, normals : (n, 3) float64 (unit normals)
    """
    _, prim, _ = caster.closest_points(points)
    prim = np.array(prim, dtype=np.int64)
    fn = mesh.face_normals()  # (F, 3)
    away = np.flatnonzero(np.einsum("nd,nd->n", fn[prim], normals) < FACING_MIN_COS)
    if away.shape[0] == 0:
        return prim
    tri = mesh.triangles()  # (F, 3, 3)
    nf = tri.shape[0]
    step = max(1, _FACING_PAIRS // nf)
    for s in range(0, away.shape[0], step):
        idx = away[s: s + step]
        ok = normals[idx] @ fn.T >= FACING_MIN_COS  # (k, F)
        pi, ti = np.nonzero(ok)  # only the facing pairs are measured
        p = points[idx][pi]
        q, _ = closest_point_on_triangles(p, tri[ti, 0], tri[ti, 1], tri[ti, 2])
        d2 = np.full(ok.shape, np.inf)
        d2[pi, ti] = np.einsum("nd,nd->n", q - p, q - p)
        best = d2.argmin(axis=1)
        prim[idx] = np.where(ok.any(axis=1), best, prim[idx])
    return prim


def map_into_atlas(
    mesh_i: Mesh, m1: Mesh, atlas: Atlas, caster: RayCaster | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """Atlas uvs for the corners of a coarser mesh M_i: the composite T(T_i(·)) of seed 000
    §4.1, sampled at M_i's vertices by closest point onto M1.

    Corners of one M_i face can land in different charts of T (near a seam); interpolating
    across charts would smear the face over the atlas. For such faces, every corner is
    re-expressed in the chart of the face's centroid by extending the affine uv map of the
    centroid's M1 triangle to the corner (plane projection, unclamped barycentrics), and the
    face is flagged. Rendering that needs exact uvs at hit points uses `atlas_uv_of_points`.

    mesh_i : M_i; m1 : M1 (same faces as atlas.mesh); atlas : from build_atlas(m1, ...)
    returns : (corner_uvs (f_i, 3, 2) float64, one_chart (f_i,) bool — True where the three
        corners' closest points fall in one chart, so the uvs are the plain closest-point map)
    """
    if m1.num_faces != atlas.mesh.num_faces:
        raise ShapeError(
            f"m1 has {m1.num_faces} faces but the atlas mesh has {atlas.mesh.num_faces}"
        )
    f_i = mesh_i.num_faces
    if f_i == 0:
        return np.zeros((0, 3, 2)), np.zeros(0, dtype=bool)
    if caster is None:
        caster = RayCaster(atlas.mesh.vertices, atlas.mesh.faces)
    corners3 = mesh_i.triangles()  # (f_i, 3, 3)
    corners = corners3.reshape(-1, 3)  # (3 f_i, 3)
    centroids = corners3.mean(axis=1)  # (f_i, 3)
    # A corner of M_i often sits on a seam of T (QEM keeps vertices near M1's), where the
    # closest triangle is a tie between charts. Query a point pulled slightly toward the
    # face's centroid to break the tie toward the face's interior, then project the corner
    # itself onto the chosen triangle in float64 (so the pull does not move the uv).
    pulled = corners3 + SEAM_PULL * (centroids[:, None, :] - corners3)
    fnorm = mesh_i.face_normals()  # (f_i, 3)
    prim = _closest_facing(caster, atlas.mesh, pulled.reshape(-1, 3), np.repeat(fnorm, 3, axis=0))
    tri_all = atlas.mesh.triangles()[prim]  # (3 f_i, 3, 3)
    _, w = closest_point_on_triangles(corners, tri_all[:, 0], tri_all[:, 1], tri_all[:, 2])
    uv = np.einsum("nk,nkd->nd", w, atlas.corner_uvs[prim]).reshape(f_i, 3, 2)
    chart = atlas.face_chart[prim].reshape(f_i, 3)
    cprim = _closest_facing(caster, atlas.mesh, centroids, fnorm)
    cchart = atlas.face_chart[cprim]
    one_chart = (chart == cchart[:, None]).all(axis=1)
    fix = np.flatnonzero(~one_chart)
    if fix.shape[0]:
        tri = atlas.mesh.triangles()[cprim[fix]]  # (k, 3, 3)
        e1 = tri[:, 1] - tri[:, 0]
        e2 = tri[:, 2] - tri[:, 0]
        # barycentrics of the corner's projection onto the triangle's plane (least squares)
        g11 = np.einsum("kd,kd->k", e1, e1)
        g12 = np.einsum("kd,kd->k", e1, e2)
        g22 = np.einsum("kd,kd->k", e2, e2)
        det = g11 * g22 - g12 * g12
        det = np.where(np.abs(det) > 0, det, 1.0)
        rel = corners3[fix] - tri[:, None, 0]  # (k, 3, 3)
        r1 = np.einsum("kcd,kd->kc", rel, e1)
        r2 = np.einsum("kcd,kd->kc", rel, e2)
        b1 = (g22[:, None] * r1 - g12[:, None] * r2) / det[:, None]  # (k, 3)
        b2 = (g11[:, None] * r2 - g12[:, None] * r1) / det[:, None]
        tuv = atlas.corner_uvs[cprim[fix]]  # (k, 3, 2)
        ext = (
            tuv[:, None, 0]
            + b1[..., None] * (tuv[:, None, 1] - tuv[:, None, 0])
            + b2[..., None] * (tuv[:, None, 2] - tuv[:, None, 0])
        )  # (k, 3, 2)
        off = chart[fix] != cchart[fix, None]  # (k, 3) corners in another chart
        uv[fix] = np.where(off[..., None], np.clip(ext, 0.0, 1.0), uv[fix])
    return uv, one_chart


def rasterize_atlas(
    corner_uvs: object, resolution: int, eps: float = 1e-12
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which triangle covers each texel centre of an N × N atlas.

    Candidates (triangle, texel) come from each triangle's uv bounding box (np.repeat, no
    loop per triangle); a centre is inside when all three barycentrics are >= -eps (pass a
    negative eps for a strict test).
    corner_uvs : (f, 3, 2) float64; resolution : N
    returns : (face (N*N,) int64, lowest covering triangle or -1; bary (N*N, 3) float64 in
        that triangle; count (N*N,) int64 number of covering triangles)
    """
    cuv = np.asarray(corner_uvs, dtype=np.float64)
    if cuv.ndim != 3 or cuv.shape[1:] != (3, 2):
        raise ShapeError(f"corner_uvs must have shape (f, 3, 2), got {cuv.shape}")
    n = int(resolution)
    n_tex = n * n
    face = np.full(n_tex, -1, dtype=np.int64)
    bary = np.zeros((n_tex, 3))
    count = np.zeros(n_tex, dtype=np.int64)
    if cuv.shape[0] == 0:
        return face, bary, count
    # texel space: x = u N (columns), y = (1 - v) N (rows); centres at integer + 0.5
    xy = np.stack([cuv[..., 0] * n, (1.0 - cuv[..., 1]) * n], axis=-1)  # (f, 3, 2)
    lo = np.clip(np.ceil(xy.min(axis=1) - 0.5), 0, n).astype(np.int64)  # (f, 2)
    hi = np.clip(np.floor(xy.max(axis=1) - 0.5), -1, n - 1).astype(np.int64)
    width = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0)
    height = np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    per = width * height  # (f,)
    tri = np.repeat(np.arange(cuv.shape[0], dtype=np.int64), per)  # (k,)
    k = np.arange(tri.shape[0], dtype=np.int64) - np.repeat(np.cumsum(per) - per, per)
    col = lo[tri, 0] + k % width[tri]
    row = lo[tri, 1] + k // width[tri]
    p = np.column_stack([col + 0.5, row + 0.5])  # (k, 2)
    a, b, c = xy[tri, 0], xy[tri, 1], xy[tri, 2]
    v0 = b - a
    v1 = c - a
    v2 = p - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    ok = np.abs(den) > 0
    den = np.where(ok, den, 1.0)
    w1 = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
    w2 = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    w0 = 1.0 - w1 - w2
    inside = ok & (w0 >= -eps) & (w1 >= -eps) & (w2 >= -eps)
    tex = (row * n + col)[inside]
    tri_in = tri[inside]
    count = np.bincount(tex, minlength=n_tex).astype(np.int64)
    # lowest triangle id per texel: sort by (texel, triangle), keep first of each texel
    order = np.lexsort((tri_in, tex))
    tex_s = tex[order]
    first = np.ones(tex_s.shape[0], dtype=bool)
    first[1:] = tex_s[1:] != tex_s[:-1]
    sel = order[first]
    face[tex[sel]] = tri_in[sel]
    bary[tex[sel]] = np.column_stack([w0, w1, w2])[inside][sel]
    return face, bary, count
