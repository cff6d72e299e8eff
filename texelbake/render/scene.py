"""A baked asset ready to render (`RenderScene`: the baked arrays read through
`texelbake.usd.read`, M_org and every M_i with their ray casters), and the cameras a frame can
be seen from (`resolve_camera`, `lod_camera`)."""

from __future__ import annotations

import functools
import math
import time
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.brdf.opacity import hit_uv
from texelbake.cpm.avis.table import AvisTable, avis_table_from
from texelbake.errors import SettingsError, ShapeError, StageError
from texelbake.geometry.mesh import face_normals
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.texels import bilinear_texels, uv_to_texel
from texelbake.model import Camera
from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.org import OrgScene


class MapCutout:
    """The cut-out test of a LOD mesh from its fallback's opacity texture (`geometry.raycast.
    CutoutTest`): a point is cut where the texture, bilinearly filtered at its uv, is below
    the material's opacityThreshold, as a viewer's alpha test on the finest mip level.

    opacity : (n, n) float64 texel values; corner_uvs : (f, 3, 2); threshold in (0, 1]
    """

    def __init__(self, opacity: np.ndarray, corner_uvs: np.ndarray, threshold: float) -> None:
        op = np.asarray(opacity, dtype=np.float64)
        if op.ndim != 2 or op.shape[0] != op.shape[1]:
            raise ShapeError(f"opacity map must be square (n, n), got {op.shape}")
        self.opacity = op.reshape(-1)
        self.resolution = int(op.shape[0])
        self.corner_uvs = np.asarray(corner_uvs, dtype=np.float64)
        self.threshold = float(threshold)
        self.faces = np.ones(self.corner_uvs.shape[0], dtype=bool)

    def cut_uv(self, prim: np.ndarray, uv: np.ndarray) -> np.ndarray:
        tex, w = bilinear_texels(np.asarray(uv, dtype=np.float64), self.resolution)
        return np.einsum("nk,nk->n", w, self.opacity[tex]) < self.threshold

    def cut(self, prim: np.ndarray, bary: np.ndarray) -> np.ndarray:
        prim = np.asarray(prim, dtype=np.int64)
        return self.cut_uv(prim, hit_uv(self.corner_uvs, prim, bary))


def lod_cutout(baked: Any, lod: int) -> MapCutout | None:
    """LOD `lod`'s (0 = M1) cut-out test from its fallback material, or None when it does not
    cut (no opacity texture, or no threshold above 0: the spec's opaque surface)."""
    mats = baked.fallback.get("materials", [])
    mat = mats[lod] if lod < len(mats) else {}
    op = (mat.get("textures") or {}).get("opacity") if mat else None
    thr = (mat.get("constants") or {}).get("opacityThreshold") if mat else None
    if op is None or thr is None or not float(thr) > 0.0:
        return None
    return MapCutout(np.asarray(op)[..., 0], baked.meshes[lod].corner_uvs, float(thr))


class RenderScene(OrgScene):
    """A baked asset ready to render: the baked arrays, M_org with its materials and lights,
    and ray casters over M_org and every M_i (built once)."""

    #: per atlas-mesh triangle, uv area per world area and unit normal (`set_atlas_surface`)
    atlas_uv_ratio: np.ndarray
    atlas_face_normals: np.ndarray

    def __init__(self, baked_root: str | Path) -> None:
        from texelbake.asset import load_asset
        from texelbake.usd.read import read_baked

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
        # a LOD whose fallback cuts (an opacity texture under its opacityThreshold) is cut
        # for every ray cast against it, eye and shadow rays alike, as a viewer's alpha test
        self.lods = [RayCaster(m.vertices, m.faces, cutout=lod_cutout(self.baked, i))
                     for i, m in enumerate(self.baked.meshes)]
        self.lod_face_normals = [face_normals(m.vertices, m.faces) for m in self.baked.meshes]
        self.n0 = int(round(math.sqrt(len(self.baked.levels[0]["texel_offsets"]) - 1)))
        # the atlas mesh M_T: LOD1 itself, or (LOD1 too fine for the atlas) the
        # mesh the CPM maps are built on, stored beside them; LODs are mapped into it
        arr = self.baked.arrays
        self.atlas_separate = "atlas_vertices" in arr
        if self.atlas_separate:
            self.atlas_arrays = (arr["atlas_vertices"].astype(np.float64),
                                 arr["atlas_faces"].astype(np.int64),
                                 arr["atlas_corner_uvs"].astype(np.float64))
            self.atlas_caster = RayCaster(self.atlas_arrays[0], self.atlas_arrays[1])
        else:  # `atlas_uv` reads LOD1 itself
            m0 = self.baked.meshes[0]
            self.atlas_arrays = (m0.vertices, m0.faces, m0.corner_uvs)
            self.atlas_caster = self.lods[0]
        self.lod_uv_ratio, self.lod_uv_exact = zip(
            *(_uv_ratio(m.vertices, m.faces, m.corner_uvs, i == 0 and not self.atlas_separate)
              for i, m in enumerate(self.baked.meshes)),
            strict=True)
        set_atlas_surface(self)
        # eye rays meet M_org, or an M_i (moved outward to enclose M_org's outline)
        self.eye_box = self.box_around(self.asset.points, self.atlas_arrays[0],
                                       *(m.vertices for m in self.baked.meshes))
        self.lod_error = [_hausdorff(self.org, c, self.asset.points, m.vertices)
                          for c, m in zip(self.lods, self.baked.meshes, strict=True)]
        self._tables = [_avis_table(lv) for lv in self.baked.levels]
        self._points: dict[int, dict[str, Any]] = {}
        self._nm: dict[str, np.ndarray] | None = None
        self._btf: Any = None
        # the per-scene layout of the maps, like the ray-tracing structures: float64 points of
        # every level
        for j in range(len(self.baked.levels)):
            self.points(j)
        self.setup_seconds = time.perf_counter() - t0

    def avis_table(self, level: int):
        """The level's a_vis table (texelbake.cpm.avis.AvisTable), rebuilt once at load."""
        return self._tables[level]

    def points(self, level: int) -> dict[str, Any]:
        """The level's characteristic points in float64, unit normals (converted once):
        position, geom_normal, normal (P, 3); weight (P, 3); material (P,) int64; uv (P, 2);
        var (P,) their lobes' slope variance per axis (`texelbake.cpm.lobe`), None when the
        bake kept the narrow lobes (no `point_var`)."""
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
                "uv": lv["point_uv"].astype(np.float64),
                "var": lv["point_var"].astype(np.float64) if "point_var" in lv else None}
        return self._points[level]


def _avis_table(level: dict[str, np.ndarray]):
    """The level's AvisTable through `avis_table_from` (the payload contract). Bakes
    written before the flat `avis:<name>` layout stored the dataclass fields nested
    (`avis:cf:offsets`, `avis:haar:values`, ...): those are renamed and read the same way."""
    try:
        return avis_table_from(level)
    except ShapeError:
        if "avis:cf:offsets" not in level:
            raise
    old = {k[5:].replace(":", "_"): v for k, v in level.items() if k.startswith("avis:")}
    old["meta"] = np.array([int(old["res"]), int(old.get("haar_res", old["res"]))], np.int64)
    return AvisTable.from_arrays(old)


def set_atlas_surface(scene: RenderScene) -> None:
    """`scene.atlas_uv_ratio` (uv area per world area) and `atlas_face_normals` of each
    atlas-mesh triangle: the texel density and slope a look-up that reads the atlas mesh (by
    the eye ray or by closest point) sees. LOD1's own when it is the atlas mesh; called again
    by a deformed frame after it moves the meshes."""
    if scene.atlas_separate:
        v, f, cuv = scene.atlas_arrays
        scene.atlas_uv_ratio = _uv_ratio(v, f, cuv, first=True)[0]
        scene.atlas_face_normals = face_normals(v, f)
    else:
        scene.atlas_uv_ratio = scene.lod_uv_ratio[0]
        scene.atlas_face_normals = scene.lod_face_normals[0]


def _uv_ratio(v: np.ndarray, f: np.ndarray, cuv: np.ndarray, first: bool = False,
              exact: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per triangle of M_i: atlas uv area per world area (f,), and whether its interpolated
    uvs can be trusted (f,) bool. Triangles of a coarse M_i whose corners map into different
    charts (their uv density is far from the atlas' median) are looked up by closest point on
    M1 instead (the exact composite map T(T_i(·)) of seed 000 §4.1). `exact` (f,) bool: the
    trusted triangles are given (a deformed frame's refined M_i inherits its parents' flags:
    the median density of the refined faces is not the rest mesh's, and the rule would flag
    other faces)."""
    tri = v[f]
    a_w = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    d1, d2 = cuv[:, 1] - cuv[:, 0], cuv[:, 2] - cuv[:, 0]
    a_uv = 0.5 * np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0])
    ok = a_w > 0
    ratio = np.divide(a_uv, a_w, out=np.zeros_like(a_w), where=ok)
    if first:  # M1 carries the atlas itself: its interpolated uvs are exact
        med0 = float(np.median(ratio[ratio > 0])) if np.any(ratio > 0) else 1.0
        return np.where(ratio > 0, ratio, med0), np.ones(len(f), bool)
    if exact is None:
        med = float(np.median(ratio[ok & (ratio > 0)])) if np.any(ok & (ratio > 0)) else 1.0
        exact = ok & (ratio > 0.25 * med) & (ratio < 4.0 * med)
    else:
        exact = np.asarray(exact, dtype=bool) & ok & (ratio > 0)
        med = float(np.median(ratio[exact])) if exact.any() else 1.0
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


def describe_camera(scene: OrgScene, camera: object) -> str:
    """What `resolve_camera(scene, camera, ...)` looks through, in words for reports: the
    asset's camera (its prim path), the auto-framed view when the asset has none, the `lod`
    view, or a given camera."""
    if camera is None:
        cams = scene.asset.cameras
        return f"the asset's camera {cams[0].path}" if cams else "auto-framed (the asset has none)"
    if isinstance(camera, str):
        return "lod: the default view moved back until a finest texel spans ~0.7 pixel"
    if isinstance(camera, (int, float)):
        return f"auto-framed at {float(camera):g}x the fitting distance"
    return "given by the caller"


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


def m1_arrays(scene: RenderScene) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m = scene.baked.meshes[0]
    return m.vertices, m.faces, m.corner_uvs


def hit_m1(scene: RenderScene, o: np.ndarray, d: np.ndarray):
    """Eye rays against M1: (hit (n,) bool, idx (k,) rays that hit, prim (k,), p (k, 3),
    uv (k, 2) atlas uv, row (k,), col (k,) finest texel under the hit, bary (k, 3) the hit's
    barycentrics on its triangle)."""
    v, f, cuv = m1_arrays(scene)
    hits = scene.lods[0].cast(o, d)
    idx = np.flatnonzero(hits.hit)
    prim = hits.prim[idx]
    b = hits.bary3()[idx]
    p = np.einsum("nk,nkj->nj", b, v[f[prim]])
    uv = np.einsum("nk,nkj->nj", b, cuv[prim])
    inexact = ~scene.lod_uv_exact[0][prim]
    if inexact.any():
        uv[inexact] = atlas_uv(scene, p[inexact])
    row, col = uv_to_texel(uv, scene.n0)
    return hits.hit, idx, prim, p, uv, row, col, b


def _atlas_mesh(scene: RenderScene) -> tuple[np.ndarray, RayCaster]:
    """The atlas mesh's corner uvs (f, 3, 2) and its ray caster: LOD1, or the separate M_T
    (a deformed frame replaces either with its warped copy)."""
    if scene.atlas_separate:
        return scene.atlas_arrays[2], scene.atlas_caster
    return scene.baked.meshes[0].corner_uvs, scene.lods[0]


def ray_atlas_uv(scene: RenderScene, o: np.ndarray, d: np.ndarray,
                 near: np.ndarray | None = None, normal: np.ndarray | None = None,
                 max_depth: float = math.inf) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The atlas uv where eye rays (o, d) (n, 3) meet the atlas mesh (LOD1 or M_T), which lies
    inside every coarser M_i: the texel the ray would read had it been traced against the
    atlas mesh. near, normal (n, 3): the rays' hits on M_i and M_i's unit normals there; an
    atlas-mesh hit farther than `max_depth` from near along the normal is not the surface
    under M_i but another part (a ray that slips under M_i's rim and goes on) and counts as a
    miss. returns (uv (n, 2) float64, met (n,) bool, the atlas-mesh triangle (n,) int64;
    uv 0 and triangle -1 where not met)"""
    c1, caster = _atlas_mesh(scene)
    hits = caster.cast(o, d)
    uv = np.zeros((o.shape[0], 2))
    met = hits.hit.copy()
    if near is not None and normal is not None:
        dn = d / np.linalg.norm(d, axis=1, keepdims=True)  # t is along the unit direction
        p1 = o + np.where(met, hits.t, 0.0)[:, None] * dn
        depth = np.abs(np.einsum("ij,ij->i", np.where(met[:, None], p1 - near, 0.0), normal))
        met &= depth <= max_depth
    uv[met] = np.einsum("nk,nkj->nj", hits.bary3()[met], c1[hits.prim[met]])
    return uv, met, np.where(met, hits.prim, -1).astype(np.int64)


def atlas_uv_prim(scene: RenderScene, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The exact composite map T(T_i(·)) of seed 000 §4.1: the atlas uv (n, 2) of the closest
    point on the atlas mesh (LOD1, or the separate M_T) to points p (n, 3) on any LOD, and
    that atlas-mesh triangle (n,) int64."""
    c1, caster = _atlas_mesh(scene)
    _, p1, b1 = caster.closest_points(p)
    w1 = np.column_stack([1.0 - b1[:, 0] - b1[:, 1], b1])
    return np.einsum("nk,nkj->nj", w1, c1[p1]), np.asarray(p1, dtype=np.int64)


def atlas_uv(scene: RenderScene, p: np.ndarray) -> np.ndarray:
    """`atlas_uv_prim`'s uv alone."""
    return atlas_uv_prim(scene, p)[0]
