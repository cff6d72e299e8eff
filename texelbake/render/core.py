"""The renderer: a wavefront ray tracer over open3d/Embree and its modes (seed 000 §4.2, §5).

Every mode traces all eye rays of a pass at once (`camera.eye_rays`), shades the hits with
whole-array numpy and sums the samples of each pixel with a box filter; loops run over sample
passes, lights, levels and materials only.

Modes (all read the baked USD through `texelbake.payload.read_baked` and the copied source):

- ``gt`` — M_org, stratified eye rays, direct light with shadow rays against M_org
  (`shade.direct_radiance`).
- ``cpm`` — characteristic point maps, Eq. 12 of seed 000:
  f̄_r(p; ωi, ωo) = 1/a_vis(p, ωo) Σ_k V(x̂k, ωi) V(x̂k, ωo) f_r(x̂k, ωi, ωo) (n_k·ωi)⁺
  (n_gk·ωo)⁺ w_k, radiance L = Σ_l E_l f̄_r (the weights w_k include α_k and ΔA, so E_l times
  the sum is already the radiance; cos_i on the shading normal, cos_o on the geometric normal,
  as `texelbake.stages.fit_level` built R). The mesh M_i is picked per frame by projected size
  (`choose_mesh`), the texel and mip level j per eye ray from its ray differential (pixel
  footprint → atlas footprint, each of the spp stratified eye rays at its 1/spp share of
  it: `footprint`), trilinear across texels and levels; where the pixel's footprint is
  below the finest level (the viewer is closer) the ray falls back to M_org. The outline is
  M_org's: an eye ray that hits M_i (which encloses M_org) but misses M_org sees the
  background (`coverage`, one any-hit ray per hit).
  *Per-frame texel radiance.* Seed 000 §3.1 assumes a distant viewer and distant lights per
  texel: ωo is one direction per texel. texelbake takes it from the texel's weighted
  characteristic-point centroid toward the camera position, and per light ωi from each point
  (exact for point lights). With that, Eq. 12 for every texel of every level depends on the
  frame but not on the pixel: it is evaluated once per frame for all texels (one shadow ray
  per point and light, one view ray per point toward the camera, a segment sum over the CSR
  and one a_vis look-up per texel), and the eye rays only fetch and blend texel radiances —
  the hint of the issue, carried to the view term. The cost per pixel is then an eye ray on
  M_i, which is what makes CPM many times faster than multi-sampling M_org.
  Inter-object shadows: the seed tests a shadow ray on the other objects' M_i; here every
  characteristic point's shadow ray is cast against the whole M_org (all objects of the
  asset), which covers both that test and intra-object shadowing V(x̂k, ωi) (docs/decisions.md).
  Local lights (§4.2): the mip level is also capped so that the distance to each point
  light is at least `local_light_ratio` texel sizes (ωi about constant across the texel).
- ``normalmap`` — the baseline studios bake today: M1 with the baked albedo and tangent-space
  normal maps, multi-sampled, the material's BRDF with its Lambertian part replaced by the
  albedo map (`normalmap_brdf`), shadows on M1.
- ``btf`` — the real-time target (seed 001 §3.4): M1 with the baked BTF maps
  (`btf_eigen.exr`, `btf_weights.exr`, `btf_lut.exr`, `btf_pairs.exr` beside the baked USD,
  written when `BakeSettings.btf` is on). Per light L = E_l V(p, ωi) f̄(ωi, ωo) with f̄ from
  `texelbake.btf.btf_lookup` (Eq. 7 of seed 001, continuous LOD): f̄ is the filtered
  reflectance of seed 000 Eq. 7, (Σ f V V cos_i cos_o ΔA)/a_vis, which already carries both
  cosines, so it is multiplied by the irradiance E_l only. ωi, ωo are expressed in the texel
  frame of the finest texel under the hit (`levels[0]["frames"]`, rows t, b, n), shadows are
  traced on M1 (as ``normalmap``), and λ comes from the pixel footprint exactly as in ``cpm``
  (clamped to [0, λ_max] by the look-up). Not in `MODES` (previews and reports iterate MODES
  and most bakes carry no BTF maps); `render_frame` accepts it through `EXTRA_MODES`.
- ``equal-time`` — M_org with as many eye rays per pixel as fit in the time budget (by
  default the time of the ``cpm`` image at the given spp, measured in this call).

Timing: `RenderResult.seconds` counts the rendering of one frame (rays, shading, per-frame
precomputation), not reading the USD files and building the ray-tracing structures and the
maps' float64 arrays and search keys, which a renderer does once per scene
(`RenderScene.setup_seconds`). `api.compare_modes` times each mode's second frame (a warm
renderer, as a previewer between frames).
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.errors import SettingsError, StageError
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.texels import bilinear_texels, uv_to_texel
from texelbake.model import AssetModel, Camera
from texelbake.normalmap import face_tangent_space
from texelbake.render import camera as cam_mod
from texelbake.render.camera import PinholeCamera
from texelbake.render.shade import direct_radiance, light_at, lit_points
from texelbake.tol import TOL

MODES = ("gt", "cpm", "normalmap", "equal-time")
#: modes `render_frame` accepts beyond MODES (they need optional bake outputs)
EXTRA_MODES = ("btf",)

#: rays per wavefront pass (bounds memory: ~1 kB of temporaries per ray)
PASS_RAYS = 1 << 17


@dataclass
class RenderResult:
    """One rendered image.

    image : (h, w, 3) float32 linear radiance
    seconds : wall time of the frame (see module docstring)
    rays_cast : every ray traced (eye, shadow, view and fallback rays)
    spp : eye rays per pixel
    extras : per-mode diagnostics (cpm: `level` (h, w) float32 mean mip level of the samples,
        -1 where M_org was used, NaN on background; `mesh` the M_i used; fallback fraction)
    """

    image: np.ndarray
    seconds: float
    rays_cast: int
    spp: int
    mode: str = ""
    extras: dict[str, Any] = field(default_factory=dict)


# --------------------------------------------------------------------------- the scene


class OrgScene:
    """M_org ready to render: an AssetModel with its ray caster (what `gt` traces). Also
    usable without a bake (`render_model`)."""

    def __init__(self, asset: AssetModel) -> None:
        self.asset = asset
        self.materials = asset.materials
        self.lights = asset.lights
        self.org = RayCaster(asset.points, asset.faces)
        self.org_face_normals = asset.face_normals()
        self.diag = self.org.bbox_diag
        self.ray_eps = TOL.ray_offset * self.diag

    def default_camera(self, width: int, height: int) -> PinholeCamera:
        if self.asset.cameras:
            return cam_mod.from_usd(self.asset.cameras[0], width, height)
        return cam_mod.auto_frame(self.asset.bounds, width, height)


class RenderScene(OrgScene):
    """A baked asset ready to render: the baked arrays, M_org with its materials and lights,
    and ray casters over M_org and every M_i (built once)."""

    def __init__(self, baked_root: str | Path) -> None:
        from texelbake.payload import read_baked
        from texelbake.scene import load_asset

        t0 = time.perf_counter()
        self.root = Path(baked_root)
        self.baked = read_baked(self.root)
        if not self.baked.source_layer:
            raise StageError(f"baked asset {self.root} names no source layer")
        if not self.baked.meshes:
            raise StageError(f"baked asset {self.root} has no LOD meshes")
        if not self.baked.levels:
            raise StageError(f"baked asset {self.root} has no CPM levels")
        super().__init__(load_asset(self.baked.source_layer))
        self.lods = [RayCaster(m.vertices, m.faces) for m in self.baked.meshes]
        self.lod_face_normals = [_face_normals(m.vertices, m.faces) for m in self.baked.meshes]
        self.n0 = int(round(math.sqrt(len(self.baked.levels[0]["texel_offsets"]) - 1)))
        self.lod_uv_ratio, self.lod_uv_exact = zip(
            *(_uv_ratio(m.vertices, m.faces, m.corner_uvs, i == 0)
              for i, m in enumerate(self.baked.meshes)),
            strict=True)
        self.lod_error = [_hausdorff(self.org, c, self.asset.points, m.vertices)
                          for c, m in zip(self.lods, self.baked.meshes, strict=True)]
        self._tables = [_avis_table(lv) for lv in self.baked.levels]
        self._points: dict[int, dict[str, np.ndarray]] = {}
        self._nm: dict[str, np.ndarray] | None = None
        self._btf: Any = None
        # the per-scene layout of the maps, like the ray-tracing structures: float64 points of
        # every level and the a_vis tables' search keys (0.13 s of the full wall's first cpm
        # frame when left to it)
        for j in range(len(self.baked.levels)):
            self.points(j)
        for table in self._tables:
            _ = table.haar.sorted_keys
        self.setup_seconds = time.perf_counter() - t0

    def avis_table(self, level: int):
        """The level's a_vis table (texelbake.avis.AvisTable), rebuilt once at load."""
        return self._tables[level]

    def points(self, level: int) -> dict[str, np.ndarray]:
        """The level's characteristic points in float64, unit normals (converted once):
        position, geom_normal, normal (P, 3); weight (P, 3); material (P,) int64; uv (P, 2)."""
        if level not in self._points:
            lv = self.baked.levels[level]
            ng = lv["point_geom_normal"].astype(np.float64)
            ns = lv["point_normal"].astype(np.float64)
            ng /= np.maximum(np.linalg.norm(ng, axis=1, keepdims=True), 1e-300)
            ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-300)
            self._points[level] = {
                "position": lv["point_position"].astype(np.float64), "geom_normal": ng,
                "normal": ns, "weight": lv["point_weight"].astype(np.float64),
                "material": lv["point_material"].astype(np.int64),
                "uv": lv["point_uv"].astype(np.float64)}
        return self._points[level]


def _avis_table(level: dict[str, np.ndarray]):
    """The level's AvisTable through `stages.avis_table_from` (the payload contract). Bakes
    written before the flat `avis:<name>` layout stored the dataclass fields nested
    (`avis:cf:offsets`, `avis:haar:values`, ...): those are renamed and read the same way."""
    from texelbake.avis import AvisTable
    from texelbake.errors import ShapeError
    from texelbake.stages import avis_table_from

    try:
        return avis_table_from(level)
    except ShapeError:
        if "avis:cf:offsets" not in level:
            raise
    old = {k[5:].replace(":", "_"): v for k, v in level.items() if k.startswith("avis:")}
    old["meta"] = np.array([int(old["res"]), int(old.get("haar_res", old["res"]))], np.int64)
    return AvisTable.from_arrays(old)


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def _uv_ratio(v: np.ndarray, f: np.ndarray, cuv: np.ndarray, first: bool = False
              ) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle of M_i: atlas uv area per world area (f,), and whether its interpolated
    uvs can be trusted (f,) bool. Triangles of a coarse M_i whose corners map into different
    charts (their uv density is far from the atlas' median) are looked up by closest point on
    M1 instead (the exact composite map T(T_i(·)) of seed 000 §4.1)."""
    tri = v[f]
    if first:  # M1 carries the atlas itself: its interpolated uvs are exact
        a_w0 = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                    axis=1)
        d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
        a_uv0 = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
        r = np.divide(a_uv0, a_w0, out=np.zeros_like(a_w0), where=a_w0 > 0)
        med0 = float(np.median(r[r > 0])) if np.any(r > 0) else 1.0
        return np.where(r > 0, r, med0), np.ones(len(f), bool)
    a_w = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    a_uv = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ok = a_w > 0
    ratio = np.divide(a_uv, a_w, out=np.zeros_like(a_w), where=ok)
    med = float(np.median(ratio[ok & (ratio > 0)])) if np.any(ok & (ratio > 0)) else 1.0
    exact = ok & (ratio > 0.25 * med) & (ratio < 4.0 * med)
    return np.where(exact, ratio, med), exact


def _hausdorff(org: RayCaster, lod: RayCaster, org_points: np.ndarray,
               lod_points: np.ndarray) -> float:
    """Symmetric vertex-to-surface distance between M_org and M_i (an estimate of their
    Hausdorff distance from the vertices of each side)."""
    a, _, _ = org.closest_points(lod_points)
    b, _, _ = lod.closest_points(org_points)
    return float(max(np.linalg.norm(a - lod_points, axis=1).max(initial=0.0),
                     np.linalg.norm(b - org_points, axis=1).max(initial=0.0)))


@functools.lru_cache(maxsize=2)
def _scene_cached(path: str, mtime_ns: int) -> RenderScene:
    return RenderScene(path)


def load_scene(baked_root: str | Path) -> RenderScene:
    """A RenderScene, cached per file (path and modification time)."""
    p = Path(baked_root).resolve()
    if not p.is_file():
        raise StageError(f"baked USD {p} does not exist")
    return _scene_cached(str(p), p.stat().st_mtime_ns)


def texel_size(scene: RenderScene) -> float:
    """World size of a finest CPM texel on M1 (median over M1's triangles)."""
    return 1.0 / (scene.n0 * math.sqrt(float(np.median(scene.lod_uv_ratio[0]))))


def lod_camera(scene: RenderScene, width: int, height: int, texel_px: float = 0.7
               ) -> PinholeCamera:
    """The asset's camera (else auto-framed) moved back along its axis until a finest CPM
    texel at the bounding box centre projects to `texel_px` pixels — the distance from which
    the characteristic point maps apply (closer, the renderer falls back to M_org); never
    moved closer than the asset's camera."""
    cam = scene.default_camera(width, height)
    centre = scene.asset.bounds.mean(axis=0)
    depth = float(np.dot(centre - cam.position, cam.forward))
    far = texel_size(scene) / (texel_px * cam.pixel_angle)
    return cam_mod.dolly(cam, centre, far) if far > depth else cam


def resolve_camera(scene: OrgScene, camera: object, width: int, height: int) -> PinholeCamera:
    """camera : None (the asset's, else auto-framed), "lod" (`lod_camera`), a PinholeCamera,
    a model.Camera, or a number = auto-frame distance factor (`camera.auto_frame`)."""
    if camera is None:
        return scene.default_camera(width, height)
    if isinstance(camera, str):
        if camera != "lod" or not isinstance(scene, RenderScene):
            raise SettingsError(f"field 'camera': the only named camera is 'lod', got "
                                f"{camera!r}")
        return lod_camera(scene, width, height)
    if isinstance(camera, PinholeCamera):
        if (camera.width, camera.height) != (width, height):
            return PinholeCamera(camera.position, camera.rotation, camera.tan_half_x, width,
                                 height)
        return camera
    if isinstance(camera, Camera):
        return cam_mod.from_usd(camera, width, height)
    if isinstance(camera, (int, float)):
        return cam_mod.auto_frame(scene.asset.bounds, width, height, distance=float(camera))
    raise SettingsError(f"field 'camera': expected None, PinholeCamera, Camera or a distance, "
                        f"got {type(camera).__name__}")


# --------------------------------------------------------------------------- wavefront loop


def _passes(cam: PinholeCamera, spp: int, seed: int):
    """Yield (sample start, origins, dirs) of passes of whole samples (every pixel)."""
    n_pix = cam.width * cam.height
    per_pass = max(1, PASS_RAYS // n_pix)
    for start in range(0, spp, per_pass):  # a loop over passes of many rays
        stop = min(spp, start + per_pass)
        off = cam_mod.sample_offsets(spp, n_pix, seed, start, stop)
        o, d = cam_mod.eye_rays(cam, off)
        yield start, o, d


def _slices(n: int):
    for a in range(0, n, PASS_RAYS):
        yield slice(a, min(n, a + PASS_RAYS))


# --------------------------------------------------------------------------- gt


def shade_org(scene: OrgScene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, int]:
    """Radiance along eye rays traced against M_org. o, d : (n, 3); returns ((n, 3), rays)."""
    a = scene.asset
    hits = scene.org.cast(o, d)
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    idx = np.flatnonzero(hits.hit)
    if idx.size == 0:
        return out, rays
    prim = hits.prim[idx]
    b = hits.bary3()[idx]  # (k, 3)
    p = np.einsum("nk,nkj->nj", b, a.points[a.faces[prim]])
    ns = np.einsum("nk,nkj->nj", b, a.corner_normals[prim])
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-300)
    uv = np.einsum("nk,nkj->nj", b, a.corner_uvs[prim])
    mat = a.face_material[prim]

    def brdf(sel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        return brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi, wo, uv[sel])

    rad, shadow = direct_radiance(p, scene.org_face_normals[prim], ns, -d[idx], scene.lights,
                                  brdf, scene.org, scene.ray_eps)
    out[idx] = rad
    return out, rays + shadow


def well_stratified(n: int) -> int:
    """The largest count <= n whose stratification grid (`camera.strata`) is no more than
    twice as long as wide (a prime count would give a 1 x n grid, stratified on one axis only).
    """
    m = max(int(n), 1)
    while m > 1:
        nx, ny = cam_mod.strata(m)
        if ny <= 2 * nx:
            return m
        m -= 1
    return 1


def _accumulate(cam: PinholeCamera, spp: int, seed: int, shade) -> tuple[np.ndarray, int]:
    """Box-filtered image of `shade(o, d) -> (radiance (n, 3), rays)` over the stratified eye
    rays of every pass, in slices (no loop per pixel)."""
    acc = np.zeros((cam.height * cam.width, 3))
    rays = 0
    for _, o, d in _passes(cam, spp, seed):
        rad = np.zeros_like(o)
        for sl in _slices(o.shape[0]):
            rad[sl], r = shade(o[sl], d[sl])
            rays += r
        acc += rad.reshape(-1, cam.height * cam.width, 3).sum(axis=0)
    return (acc / spp).reshape(cam.height, cam.width, 3), rays


def _render_org(scene: OrgScene, cam: PinholeCamera, spp: int, seed: int
                ) -> tuple[np.ndarray, int]:
    return _accumulate(cam, spp, seed, lambda o, d: shade_org(scene, o, d))


# --------------------------------------------------------------------------- normal map


def _normalmap_tables(scene: RenderScene) -> dict[str, np.ndarray]:
    """Per finest texel: material and texture uv of its heaviest characteristic point (the
    material id map a baker writes beside the albedo and normal maps), filled in empty texels
    from the nearest filled one; the material's own diffuse albedo there."""
    if scene._nm is not None:
        return scene._nm
    from scipy.spatial import cKDTree

    lv = scene.baked.levels[0]
    n = scene.n0
    counts = np.diff(lv["texel_offsets"])
    tex = np.repeat(np.arange(n * n), counts)
    w = lv["point_weight"].astype(np.float64).sum(axis=1)
    # heaviest point per texel: sort by (texel, weight)
    order = np.lexsort((w, tex))
    last = np.flatnonzero(np.r_[tex[order][1:] != tex[order][:-1], True])
    best = order[last]  # one point per filled texel
    filled = tex[best]
    if filled.size == 0:
        raise StageError(f"{scene.root}: the finest CPM level has no points")
    rc = np.stack(np.divmod(np.arange(n * n), n), axis=1)
    _, near = cKDTree(rc[filled]).query(rc)
    src = best[near]
    mat = lv["point_material"][src].astype(np.int64)
    uv = lv["point_uv"][src].astype(np.float64)
    kd = np.zeros((n * n, 3))
    for m in np.unique(mat):  # the few materials
        sel = mat == m
        kd[sel] = brdf_mod.diffuse_albedo(scene.materials[int(m)], uv[sel])
    scene._nm = {"material": mat, "uv": uv, "kd": kd,
                 "frames": face_tangent_space(*_m1(scene))}
    return scene._nm


def _m1(scene: RenderScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = scene.baked.meshes[0]
    return m.vertices, m.faces, m.corner_uvs


def _bilinear_map(img: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear look-up of an (N, N, c) atlas map at uv (n, 2) (row = (1 - v) N)."""
    n = img.shape[0]
    idx, w = bilinear_texels(uv, n)
    flat = img.reshape(n * n, -1).astype(np.float64)
    return np.einsum("nk,nkc->nc", w, flat[idx])


def normalmap_brdf(scene: RenderScene, texel: np.ndarray, albedo: np.ndarray):
    """The baseline's BRDF at hits on M1: the texel's material (nearest texel of the material
    map) with its Lambertian part replaced by the albedo map,
    f = max(f_mat − kd_mat/π + albedo/π, 0): what a look-dev artist gets by plugging the baked
    albedo into the material's diffuse colour (exact for Lambertian materials)."""
    nm = _normalmap_tables(scene)
    mat = nm["material"][texel]

    def brdf(sel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        t = texel[sel]
        f = brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi, wo, nm["uv"],
                                      sample_index=t)
        lam = (wi[:, 2] > TOL.grazing_cos) & (wo[:, 2] > TOL.grazing_cos)
        f += lam[:, None] * (albedo[sel] - nm["kd"][t]) / np.pi
        return np.maximum(f, 0.0)

    return brdf


def _hit_m1(scene: RenderScene, o: np.ndarray, d: np.ndarray):
    """Eye rays against M1: (idx (k,) rays that hit, prim (k,), p (k, 3), uv (k, 2) atlas uv,
    row (k,), col (k,) finest texel under the hit)."""
    v, f, cuv = _m1(scene)
    hits = scene.lods[0].cast(o, d)
    idx = np.flatnonzero(hits.hit)
    prim = hits.prim[idx]
    b = hits.bary3()[idx]
    p = np.einsum("nk,nkj->nj", b, v[f[prim]])
    uv = np.einsum("nk,nkj->nj", b, cuv[prim])
    row, col = uv_to_texel(uv, scene.n0)
    return idx, prim, p, uv, row, col


def shade_normalmap(scene: RenderScene, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, int]:
    """Radiance along eye rays traced against M1 with the baked normal and albedo maps."""
    nm = _normalmap_tables(scene)
    caster = scene.lods[0]
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    idx, prim, p, uv, row, col = _hit_m1(scene, o, d)
    if idx.size == 0:
        return out, rays
    albedo = _bilinear_map(scene.baked.albedo, uv)
    local = _bilinear_map(scene.baked.normal, uv)
    ns = np.einsum("nji,nj->ni", nm["frames"][prim], local)  # tangent space -> world
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-300)
    texel = row * scene.n0 + col
    rad, shadow = direct_radiance(p, scene.lod_face_normals[0][prim], ns, -d[idx], scene.lights,
                                  normalmap_brdf(scene, texel, albedo), caster, scene.ray_eps)
    out[idx] = rad
    return out, rays + shadow


def _render_normalmap(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int):
    return _accumulate(cam, spp, seed, lambda o, d: shade_normalmap(scene, o, d))


# --------------------------------------------------------------------------- btf


def _btf_files(scene: RenderScene) -> list[Path]:
    return [scene.root.parent / f"btf_{p}.exr" for p in ("eigen", "weights", "lut", "pairs")]


def has_btf_maps(scene: RenderScene) -> bool:
    """Whether the bake wrote BTF maps beside its USD (`BakeSettings.btf`)."""
    return all(f.is_file() for f in _btf_files(scene))


def btf_maps(scene: RenderScene):
    """The bake's BTF maps (texelbake.btf.BTFMaps), read once from beside the baked USD."""
    if scene._btf is None:
        from texelbake.btf import read_btf_maps

        folder = scene.root.parent
        missing = [str(f) for f in _btf_files(scene) if not f.is_file()]
        if missing:
            raise StageError(f"baked asset {scene.root}: mode 'btf' needs the BTF maps "
                             f"(bake with settings.btf on); missing {missing}")
        maps = read_btf_maps(folder, "btf")
        if tuple(maps.shape) != (scene.n0, scene.n0):
            raise StageError(f"{folder}/btf_weights.exr: BTF map is {tuple(maps.shape)}, "
                             f"expected the atlas resolution ({scene.n0}, {scene.n0})")
        scene._btf = maps
    return scene._btf


def shade_btf(scene: RenderScene, cam: PinholeCamera, o: np.ndarray, d: np.ndarray,
              *, lod_bias: float = 0.0, interpolate: bool = False) -> tuple[np.ndarray, int]:
    """Radiance along eye rays traced against M1 with the BTF maps (module docstring).

    o, d : (n, 3) float64 eye rays; returns (radiance (n, 3) float64, rays cast)
    """
    from texelbake.btf import btf_lookup_texels

    maps = btf_maps(scene)
    caster = scene.lods[0]
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    idx, prim, p, _, row, col = _hit_m1(scene, o, d)
    if idx.size == 0:
        return out, rays
    n = scene.n0
    frames = scene.baked.levels[0]["frames"][row * n + col].astype(np.float64)  # (k, 3, 3)
    ng = scene.lod_face_normals[0][prim]
    wo = -d[idx]
    lam = footprint_level(scene, cam, 0, prim, p, o[idx], d[idx]) + lod_bias
    lam = np.clip(lam, 0.0, float(maps.top_level))
    view_ok = np.einsum("ij,ij->i", ng, wo) > TOL.grazing_cos
    wo_l = np.einsum("nij,nj->ni", frames, wo)
    for light in scene.lights:  # a loop over the few lights
        live, wi, e, r = lit_points(light, p, ng, view_ok, caster, scene.ray_eps)
        rays += r
        if live.size == 0:
            continue
        wi_l = np.einsum("nij,nj->ni", frames[live], wi[live])
        fbar = btf_lookup_texels(maps, row[live], col[live], wi_l, wo_l[live], lam[live],
                                 interpolate)
        # a truncated PCA can undershoot zero where f̄ is near zero (measured: -0.06 in the
        # demo's cylinder at 16²); reflectance is not negative, so neither is the radiance
        fbar = np.maximum(fbar, 0.0)
        out[idx[live]] += e[live] * fbar  # f̄ carries cos_i cos_o already: E_l only
    return out, rays


def _render_btf(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, **kw):
    return _accumulate(cam, spp, seed, lambda o, d: shade_btf(scene, cam, o, d, **kw))


# --------------------------------------------------------------------------- cpm


def choose_mesh(scene: RenderScene, cam: PinholeCamera, max_error_px: float = 1.0) -> int:
    """Index i (0 = M1) of the coarsest M_i whose distance to M_org (vertex Hausdorff
    estimate) projects to at most `max_error_px` pixels at the bounding box's nearest point;
    M1 when none does (seed 000 §4.2: level chosen by projected size)."""
    lo, hi = scene.asset.bounds
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    dist = max(float(np.linalg.norm(centre - cam.position)) - radius, 1e-9 * scene.diag)
    for i in range(len(scene.lods) - 1, 0, -1):
        if scene.lod_error[i] / (dist * cam.pixel_angle) <= max_error_px:
            return i
    return 0


def texel_radiance(scene: RenderScene, level: int, cam_pos: np.ndarray,
                   texels: np.ndarray | None = None
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """Eq. 12 for the texels of one level (all, or the ids in `texels`), for this frame
    (module docstring). Each texel's value depends only on its own points, so computing a
    subset gives the same values as computing all.

    cam_pos : (3,) float64; texels : (t,) int64 distinct texel ids, None = every texel
    returns : (radiance (t, 3) float64, a_vis (t,) float64 toward the camera (0 where
        invalid: the a_vis -> 0 limit), exists (t,) bool — the texel has characteristic
        points, rays cast)
    """
    lv = scene.baked.levels[level]
    offsets = lv["texel_offsets"]
    if texels is None:
        texels = np.arange(offsets.shape[0] - 1)
    texels = np.asarray(texels, dtype=np.int64)
    n_tex = texels.shape[0]
    counts = offsets[texels + 1] - offsets[texels]
    exists = counts > 0
    radiance = np.zeros((n_tex, 3))
    avis = np.zeros(n_tex)
    n_pts = int(counts.sum())
    if n_pts == 0:
        return radiance, avis, exists, 0
    tex = np.repeat(np.arange(n_tex), counts)  # (P,) local texel of each point
    # the points of the chosen texels: each texel's CSR range, concatenated
    first = np.cumsum(counts) - counts
    pt = offsets[texels][tex] + (np.arange(n_pts) - first[tex])
    cp = scene.points(level)
    pos, ng, ns, w = cp["position"][pt], cp["geom_normal"][pt], cp["normal"][pt], cp["weight"][pt]
    # one view direction per texel: weighted centroid -> camera
    ws = np.abs(w).sum(axis=1)
    ws = np.where(np.bincount(tex, ws, n_tex)[tex] > 0, ws, 1.0)
    wsum = np.bincount(tex, ws, n_tex)
    cen = np.stack([np.bincount(tex, ws * pos[:, c], n_tex) for c in range(3)], axis=1)
    cen = np.divide(cen, wsum[:, None], out=np.zeros_like(cen), where=wsum[:, None] > 0)
    wo_tex = np.asarray(cam_pos[None, :] - cen, dtype=np.float64)
    wo_tex = wo_tex / np.maximum(np.linalg.norm(wo_tex, axis=1, keepdims=True), 1e-300)
    wo = wo_tex[tex]
    g = TOL.grazing_cos
    cos_go = np.einsum("ij,ij->i", ng, wo)
    view = (cos_go > g) & (np.einsum("ij,ij->i", ns, wo) > g)
    rays = 0
    vi = np.flatnonzero(view)
    if vi.size:  # V(x̂k, ωo): a ray from the point toward the camera
        tmax = np.linalg.norm(cam_pos[None, :] - pos[vi], axis=1)
        occ = scene.org.occluded(pos[vi] + scene.ray_eps * ng[vi], wo[vi], tmax=tmax)
        rays += vi.size
        view[vi[occ]] = False
    mat, uv = cp["material"][pt], cp["uv"][pt]

    def brdf(sel: np.ndarray, wi_l: np.ndarray, wo_l: np.ndarray) -> np.ndarray:
        return brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi_l, wo_l, uv[sel])

    # Σ_l E_l V_i f_r cos_i (the shading of `direct_radiance`, at the points, toward ωo),
    # for the points that see the camera (the others add nothing)
    lit = np.zeros((n_pts, 3))
    seen = np.flatnonzero(view)
    if seen.size:
        lit[seen], r = direct_radiance(pos[seen], ng[seen], ns[seen], wo[seen], scene.lights,
                                       lambda sel, wi_l, wo_l: brdf(seen[sel], wi_l, wo_l),
                                       scene.org, scene.ray_eps)
        rays += r
    contrib = np.where(view[:, None], lit * w * cos_go[:, None], 0.0)  # (P, 3)
    num = np.stack([np.bincount(tex, contrib[:, c], n_tex) for c in range(3)], axis=1)
    live = np.flatnonzero(exists)
    frames = lv["frames"][texels[live]]
    wo_local = np.einsum("nij,nj->ni", frames, wo_tex[live])
    a, valid = scene.avis_table(level).evaluate(texels[live], wo_local)
    radiance[live] = np.where(valid[:, None], num[live] / np.where(valid, a, 1.0)[:, None], 0.0)
    avis[live] = np.where(valid, a, 0.0)
    return radiance, avis, exists, rays


class CpmFrame:
    """Per-frame data of the cpm mode: the texel radiance of each level, computed the first
    time a sample needs that texel (a frame touches the texels it sees, on the levels its
    footprints select: far views only coarse levels, and never the back of the object)."""

    def __init__(self, scene: RenderScene, cam: PinholeCamera, mesh: int) -> None:
        self.scene = scene
        self.cam_pos = np.asarray(cam.position, dtype=np.float64)
        self.mesh = mesh
        self.n_levels = len(scene.baked.levels)
        # per level: radiance, a_vis, exists, computed, requested
        self._levels: dict[int, tuple[np.ndarray, ...]] = {}
        self.rays = 0

    def _arrays(self, j: int) -> tuple[np.ndarray, ...]:
        if j not in self._levels:
            n = self.scene.baked.levels[j]["texel_offsets"].shape[0] - 1
            self._levels[j] = (np.zeros((n, 3)), np.zeros(n), np.zeros(n, bool),
                               np.zeros(n, bool), np.zeros(n, bool))
        return self._levels[j]

    def request(self, j: int, texels: np.ndarray) -> None:
        """Mark texels (ids, any shape) of level j as needed by the next `flush`."""
        self._arrays(j)[4][np.asarray(texels).ravel()] = True

    def flush(self) -> None:
        """Compute every requested texel not yet computed: one `texel_radiance` call per
        level (each call has a fixed cost; a frame's look-ups would otherwise make dozens)."""
        for j in sorted(self._levels):
            wanted, done = self._levels[j][4], self._levels[j][3]
            self._compute(j, np.flatnonzero(wanted & ~done))

    def _compute(self, j: int, todo: np.ndarray) -> None:
        if todo.size:
            rad, avis, ex, done, _ = self._arrays(j)
            r, a, e, n_rays = texel_radiance(self.scene, j, self.cam_pos, todo)
            rad[todo], avis[todo], ex[todo], done[todo] = r, a, e, True
            self.rays += n_rays

    def level(self, j: int, texels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(radiance (n_j², 3), a_vis (n_j²,), exists (n_j²,) bool) of level j, computed
        for `texels` (ids, any shape) if not yet; other entries may be unset."""
        rad, avis, ex, done, _ = self._arrays(j)
        want = np.unique(texels)
        self._compute(j, want[~done[want]])
        return rad, avis, ex


def cpm_frame(scene: RenderScene, cam: PinholeCamera, max_error_px: float = 1.0) -> CpmFrame:
    """The per-frame state of the cpm mode (mesh M_i chosen, texel radiance on demand)."""
    return CpmFrame(scene, cam, choose_mesh(scene, cam, max_error_px))


def _lookup_level(frame: CpmFrame, level: int, idx: np.ndarray, w: np.ndarray,
                  filtering: str = "projected") -> tuple[np.ndarray, np.ndarray]:
    """Bilinear texel radiance at one level; weights of texels without points are dropped.

    idx, w : (n, 4) the bilinear texels and weights (`geometry.texels.bilinear_texels`)
    filtering : "projected" — each texel weighted by its bilinear weight times its visible
        projected area a_vis toward the viewer, L = Σ w a L / Σ w a = Σ w num / Σ w a (the
        pixel integrates radiance over the visible projected area, and a_vis is exactly that
        per texel; a masked texel adds nothing instead of darkening its neighbours, and the
        a_vis -> 0 limit needs no special case); "radiance" — plain bilinear of L (what a
        texture unit does); checked by `_check_cpm_options`.
    returns : (radiance (n, 3), weight sum (n,) — 0 where no texel around uv exists)"""
    radiance, avis, exists = frame.level(level, idx)
    w = w * exists[idx]
    s = w.sum(axis=1)
    if filtering == "projected":
        wa = w * avis[idx]
        sa = wa.sum(axis=1)
        rad = np.einsum("nk,nkc->nc", wa, radiance[idx])
        return np.divide(rad, sa[:, None], out=np.zeros_like(rad), where=sa[:, None] > 0), s
    rad = np.einsum("nk,nkc->nc", w, radiance[idx])
    return np.divide(rad, s[:, None], out=np.zeros_like(rad), where=s[:, None] > 0), s


def footprint_level(scene: RenderScene, cam: PinholeCamera, mesh: int, prim: np.ndarray,
                    p: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Mip level λ (unclipped, finest = 0) of eye-ray hits on M_i from the ray differential:
    the pixel's footprint on the hit triangle (screen-space derivatives, seed 000 §4.2; the
    footprint of the pixel, not of the sample, as texture hardware does under multi-sampling),
    mapped into the atlas by the triangle's uv density. Used by the cpm and btf modes.

    prim (k,) hit triangles of M_{mesh+1}; p (k, 3) hit points; o, d (k, 3) their eye rays"""
    t = np.linalg.norm(p - o, axis=1)
    cos_t = np.maximum(np.abs(np.einsum("ij,ij->i", scene.lod_face_normals[mesh][prim], d)),
                       1e-3)
    cos_p = np.clip(d @ cam.forward, 1e-3, 1.0)
    area_world = (t * cam.pixel_angle) ** 2 * cos_p ** 3 / cos_t
    ratio = scene.lod_uv_ratio[mesh][prim]
    return 0.5 * np.log2(np.maximum(area_world * ratio, 1e-300)) + math.log2(scene.n0)


def _check_cpm_options(filtering: str, footprint: str) -> None:
    """The cpm mode's string options, checked before any ray is cast."""
    if filtering not in ("projected", "radiance"):
        raise SettingsError(f"field 'filtering': 'projected' or 'radiance', got {filtering!r}")
    if footprint not in ("sample", "pixel"):
        raise SettingsError(f"field 'footprint': 'sample' or 'pixel', got {footprint!r}")


def _cpm_prepare(scene: RenderScene, frame: CpmFrame, cam: PinholeCamera, o: np.ndarray,
                 d: np.ndarray, *, lod_bias: float = 0.0, local_light_ratio: float = 8.0,
                 spp: int = 1, footprint: str = "sample", coverage: bool = True
                 ) -> dict[str, Any]:
    """First half of `shade_cpm`: eye rays against M_i, atlas uv, mip level λ of every hit;
    the texels the look-ups will read are requested from `frame` (computed in one batch by
    `CpmFrame.flush`).

    footprint : "sample" (default) — each of the `spp` stratified eye rays of a pixel looks
        up the maps at its own footprint, a 1/spp share of the pixel's (λ lower by
        ½ log2 spp, at least the finest level), and the box filter over the samples does the
        rest, as texture look-ups under supersampling do; "pixel" — every sample at the
        pixel's footprint (the level a single-sample renderer would use: under
        supersampling it blurs twice; on the full wall at 4 spp it cost 0.7 dB). Either
        way M_org is used where the *pixel's* footprint is below the finest level.
    coverage : an eye ray that hits M_i but misses M_org sees the background (one any-hit
        ray against M_org per hit; applied in `_cpm_finish`). M_i lies a little outside M_org
        (it encloses it, and a wrap is rounded at its rim), and without this test the rim it
        adds around the outline shows the full radiance of the sliver of surface inside its
        texels (the full wall: 8 % too much light, 43 % of its error at the outline). The
        texels still give the radiance: the test only decides whether the ray is covered,
        which is what M_org's outline does in gt."""
    i = frame.mesh
    mesh = scene.baked.meshes[i]
    hits = scene.lods[i].cast(o, d)
    idx = np.flatnonzero(hits.hit)
    h: dict[str, Any] = {"n": o.shape[0], "idx": idx, "rays": o.shape[0]}
    if idx.size == 0:
        return h
    prim = hits.prim[idx]
    b = hits.bary3()[idx]
    p = np.einsum("nk,nkj->nj", b, mesh.vertices[mesh.faces[prim]])
    uv = np.einsum("nk,nkj->nj", b, mesh.corner_uvs[prim])
    inexact = ~scene.lod_uv_exact[i][prim]
    if inexact.any():  # the exact composite map: closest point on M1, its atlas uv
        v1, f1, c1 = _m1(scene)
        _, p1, b1 = scene.lods[0].closest_points(p[inexact])
        w1 = np.column_stack([1.0 - b1[:, 0] - b1[:, 1], b1])
        uv[inexact] = np.einsum("nk,nkj->nj", w1, c1[p1])
    lam = footprint_level(scene, cam, i, prim, p, o[idx], d[idx]) + lod_bias
    s0 = 1.0 / (scene.n0 * np.sqrt(scene.lod_uv_ratio[i][prim]))  # world size of a finest texel
    for light in scene.lights:  # local lights: keep ωi about constant across a texel
        if light.kind != "distant":
            _, _, dist = light_at(light, p)
            lam = np.minimum(lam, np.log2(np.maximum(dist / (local_light_ratio * s0),
                                                     1e-300)))
    n_lv = frame.n_levels
    use = lam >= 0.0
    covered = None
    if coverage:  # does the eye ray meet M_org at all (any hit)
        covered = scene.org.occluded(o[idx], d[idx])
        h["rays"] += idx.size
    if footprint == "sample":
        lam = lam - 0.5 * math.log2(max(int(spp), 1))
    lam_c = np.clip(lam, 0.0, n_lv - 1.0)
    j0 = np.floor(lam_c).astype(np.int64)
    fr = lam_c - j0
    # per level, the samples reading it (weight 1 - fr at j0, fr at j0 + 1) and their texels
    reads = []
    for j in range(n_lv):  # a loop over the few levels; each sample touches two
        for sel, up in ((np.flatnonzero(use & (j0 == j)), False),
                        (np.flatnonzero(use & (j0 + 1 == j) & (fr > 0)), True)):
            if sel.size:
                tex, w = bilinear_texels(uv[sel], max(scene.n0 >> j, 1))
                frame.request(j, tex)
                reads.append((j, sel, up, tex, w))
    h.update(use=use, lam_c=lam_c, fr=fr, reads=reads, covered=covered)
    return h


def _cpm_finish(scene: RenderScene, frame: CpmFrame, o: np.ndarray, d: np.ndarray,
                h: dict[str, Any], filtering: str = "projected"
                ) -> tuple[np.ndarray, np.ndarray, int]:
    """Second half of `shade_cpm`: trilinear look-ups of the texel radiance, M_org where the
    maps do not apply; rays that miss M_org are background when `_cpm_prepare` tested
    coverage. returns (radiance (n, 3), level (n,), rays cast)"""
    n, idx, rays = h["n"], h["idx"], h["rays"]
    out = np.zeros((n, 3))
    level = np.full(n, np.nan)
    if idx.size == 0:
        return out, level, rays
    use, lam_c, fr = h["use"], h["lam_c"], h["fr"]
    rad = np.zeros((idx.size, 3))
    wsum = np.zeros(idx.size)
    for j, sel, up, tex, w in h["reads"]:
        r, s = _lookup_level(frame, j, tex, w, filtering)
        weight = (fr[sel] if up else 1.0 - fr[sel]) * (s > 0)
        rad[sel] += weight[:, None] * r
        wsum[sel] += weight
    ok = use & (wsum > 0)
    out[idx[ok]] = rad[ok] / wsum[ok, None]
    if h["covered"] is not None:
        out[idx[ok & ~h["covered"]]] = 0.0
    level[idx[ok]] = lam_c[ok]
    # closer than the finest level (or no texel there): multi-sample M_org
    fb = idx[~ok]
    if fb.size:
        out[fb], r_fb = shade_org(scene, o[fb], d[fb])
        rays += r_fb
        level[fb] = -1.0
    return out, level, rays


def shade_cpm(scene: RenderScene, frame: CpmFrame, cam: PinholeCamera, o: np.ndarray,
              d: np.ndarray, spp: int, *, lod_bias: float = 0.0,
              local_light_ratio: float = 8.0, filtering: str = "projected",
              footprint: str = "sample", coverage: bool = True
              ) -> tuple[np.ndarray, np.ndarray, int]:
    """Radiance along eye rays from the characteristic point maps (module docstring).

    returns : (radiance (n, 3), level (n,) float64 — the fractional mip level used, -1 where
        M_org was used, NaN for misses; rays cast)
    """
    _check_cpm_options(filtering, footprint)
    h = _cpm_prepare(scene, frame, cam, o, d, lod_bias=lod_bias,
                     local_light_ratio=local_light_ratio, spp=spp, footprint=footprint,
                     coverage=coverage)
    frame.flush()
    return _cpm_finish(scene, frame, o, d, h, filtering)


def _render_cpm(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, **kw):
    max_error_px = kw.pop("max_error_px", 1.0)
    filtering = kw.pop("filtering", "projected")
    _check_cpm_options(filtering, kw.get("footprint", "sample"))
    frame = cpm_frame(scene, cam, max_error_px)
    n_pix = cam.height * cam.width
    acc = np.zeros((n_pix, 3))
    lvl_sum = np.zeros(n_pix)
    lvl_cnt = np.zeros(n_pix)
    fallback = 0
    rays = 0
    # two phases, so that the texel radiance of the whole frame is computed in one batch per
    # level (`CpmFrame.flush`): every eye ray first, then every look-up
    passes = []
    for _, o, d in _passes(cam, spp, seed):
        passes.append((o, d, [(sl, _cpm_prepare(scene, frame, cam, o[sl], d[sl], spp=spp,
                                                **kw))
                              for sl in _slices(o.shape[0])]))
    frame.flush()
    for o, d, prepared in passes:
        rad = np.zeros_like(o)
        lvl = np.full(o.shape[0], np.nan)
        for sl, h in prepared:
            rad[sl], lvl[sl], r = _cpm_finish(scene, frame, o[sl], d[sl], h, filtering)
            rays += r
        acc += rad.reshape(-1, n_pix, 3).sum(axis=0)
        lv = lvl.reshape(-1, n_pix)
        hit = np.isfinite(lv)
        lvl_sum += np.where(hit, lv, 0.0).sum(axis=0)
        lvl_cnt += hit.sum(axis=0)
        fallback += int(np.sum(lv == -1.0))
    rays += frame.rays
    level_img = np.divide(lvl_sum, lvl_cnt, out=np.full(n_pix, np.nan), where=lvl_cnt > 0)
    extras = {
        "level": level_img.reshape(cam.height, cam.width).astype(np.float32),
        "mesh": f"M{frame.mesh + 1}",
        "fallback_fraction": fallback / max(float(lvl_cnt.sum()), 1.0),
        "frame_rays": frame.rays,
    }
    return (acc / spp).reshape(cam.height, cam.width, 3), rays, extras


# --------------------------------------------------------------------------- entry points


def render_frame(scene: RenderScene, mode: str, cam: PinholeCamera, spp: int, seed: int = 0,
                 *, budget_seconds: float | None = None, **kw) -> RenderResult:
    """Render one image of `scene` (already loaded) in `mode` (see module docstring)."""
    if mode not in MODES + EXTRA_MODES:
        raise SettingsError(f"field 'mode': expected one of {MODES + EXTRA_MODES}, got "
                            f"{mode!r}")
    spp = int(spp)
    cam_mod.strata(spp)  # validates spp
    extras: dict[str, Any] = {}
    t0 = time.perf_counter()
    if mode == "gt":
        img, rays = _render_org(scene, cam, spp, seed)
    elif mode == "normalmap":
        img, rays = _render_normalmap(scene, cam, spp, seed)
    elif mode == "cpm":
        img, rays, extras = _render_cpm(scene, cam, spp, seed, **kw)
    elif mode == "btf":
        if not isinstance(scene, RenderScene):
            raise SettingsError("field 'mode': 'btf' needs a baked asset (RenderScene)")
        img, rays = _render_btf(scene, cam, spp, seed, **kw)
    else:  # equal-time
        if budget_seconds is None:
            budget_seconds = render_frame(scene, "cpm", cam, spp, seed, **kw).seconds
        # pilot at the cpm image's spp measures the cost of an eye ray per pixel on M_org
        # (one sample per pixel under-estimates it: fixed costs per pass dominate)
        t1 = time.perf_counter()
        img, rays = _render_org(scene, cam, spp, seed)
        pilot = time.perf_counter() - t1
        n_eq = well_stratified(max(1, int(budget_seconds / max(pilot / spp, 1e-9))))
        extras = {"budget_seconds": float(budget_seconds), "pilot_seconds": pilot,
                  "pilot_spp": spp}
        t0 = time.perf_counter()
        if n_eq != spp:
            img, rays = _render_org(scene, cam, n_eq, seed)
        else:
            t0 -= pilot
        spp = n_eq
    seconds = time.perf_counter() - t0
    return RenderResult(img.astype(np.float32), seconds, int(rays), spp, mode, extras)


def render_model(asset: AssetModel, cam: PinholeCamera, spp: int, seed: int = 0
                 ) -> RenderResult:
    """`gt` of an AssetModel directly (no bake): M_org, direct light, shadows."""
    scene = OrgScene(asset)
    cam_mod.strata(int(spp))
    t0 = time.perf_counter()
    img, rays = _render_org(scene, cam, int(spp), seed)
    return RenderResult(img.astype(np.float32), time.perf_counter() - t0, int(rays), int(spp),
                        "gt")
