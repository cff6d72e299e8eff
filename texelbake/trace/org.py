"""M_org ready to trace (`OrgScene`) and its ground truth, ``gt``: stratified eye rays, direct
light with shadow rays against M_org."""

from __future__ import annotations

import time

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.brdf.evaluate import shading_normal
from texelbake.brdf.opacity import asset_cutout
from texelbake.geometry.mesh import face_normals
from texelbake.geometry.normal_input import mapped_normals
from texelbake.geometry.raycast import RayCaster
from texelbake.model import AssetModel
from texelbake.tol import TOL
from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import direct_radiance
from texelbake.trace.tracer import RenderResult, accumulate


class OrgScene:
    """M_org ready to render: an AssetModel with its ray caster (what `gt` traces). Also
    usable without a bake (`render_model`)."""

    def __init__(self, asset: AssetModel) -> None:
        self.asset = asset
        self.materials = asset.materials
        self.lights = asset.lights
        #: True when the asset has no lights and the renderer lights it with
        #: `scene.lights.default_light_rig` (reports name the rig's lights)
        self.default_lights = not asset.lights
        if self.default_lights:
            from texelbake.asset.lights import default_light_rig

            centre = np.asarray(asset.bounds, dtype=np.float64).mean(axis=0)
            view = self.default_camera(64, 64).position - centre
            self.lights = default_light_rig(view, asset.up_axis)
        # cut-outs (opacity below opacityThreshold) are passed through by every ray: eye,
        # shadow and coverage
        self.org = RayCaster(asset.points, asset.faces, cutout=asset_cutout(asset))
        self.org_face_normals = face_normals(asset.points, asset.faces)
        #: the materials' normal maps on M_org (None: no material has a normal input)
        self.normal_input = mapped_normals(asset, shading_normal)
        self.diag = self.org.bbox_diag
        self.ray_eps = TOL.ray_offset * self.diag
        self.eye_box: np.ndarray | None = self.box_around(np.asarray(asset.points, np.float64))

    def box_around(self, *points: np.ndarray) -> np.ndarray:
        """(2, 3) [lo, hi] around every point given, padded by 1e-3 of M_org's diagonal:
        what eye rays must enter to meet anything the frame shows (`tracer.culled`)."""
        pts = np.concatenate([np.asarray(p, np.float64).reshape(-1, 3) for p in points])
        pad = 1e-3 * self.diag
        return np.stack([pts.min(axis=0) - pad, pts.max(axis=0) + pad])

    def default_camera(self, width: int, height: int) -> PinholeCamera:
        if self.asset.cameras:
            return cam_mod.from_usd(self.asset.cameras[0], width, height)
        return cam_mod.auto_frame(self.asset.bounds, width, height)


def shade_org(scene: OrgScene, o: np.ndarray, d: np.ndarray
              ) -> tuple[np.ndarray, int, np.ndarray]:
    """Radiance along eye rays traced against M_org. o, d : (n, 3); returns ((n, 3), rays,
    hit (n,) bool: the ray met the object)."""
    a = scene.asset
    hits = scene.org.cast(o, d)
    rays = o.shape[0]
    out = np.zeros((o.shape[0], 3))
    idx = np.flatnonzero(hits.hit)
    if idx.size == 0:
        return out, rays, hits.hit
    prim = hits.prim[idx]
    b = hits.bary3()[idx]  # (k, 3)
    p = np.einsum("nk,nkj->nj", b, a.points[a.faces[prim]])
    ns = np.einsum("nk,nkj->nj", b, a.corner_normals[prim])
    ns /= np.maximum(np.linalg.norm(ns, axis=1, keepdims=True), 1e-300)
    uv = np.einsum("nk,nkj->nj", b, a.corner_uvs[prim])
    mat = a.face_material[prim]
    if scene.normal_input is not None:  # the materials' normal maps, as the samples see them
        ns = scene.normal_input.apply(prim, b, ns, uv, mat)

    def brdf(sel: np.ndarray, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
        return brdf_mod.evaluate_by_face(scene.materials, mat[sel], wi, wo, uv[sel])

    rad, shadow = direct_radiance(p, scene.org_face_normals[prim], ns, -d[idx], scene.lights,
                                  brdf, scene.org, scene.ray_eps)
    out[idx] = rad
    return out, rays + shadow, hits.hit


def render_org(scene: OrgScene, cam: PinholeCamera, spp: int, seed: int
               ) -> tuple[np.ndarray, int, np.ndarray]:
    return accumulate(cam, spp, seed, lambda o, d: shade_org(scene, o, d), scene.eye_box)


def render_model(asset: AssetModel, cam: PinholeCamera, spp: int, seed: int = 0
                 ) -> RenderResult:
    """`gt` of an AssetModel directly (no bake): M_org, direct light, shadows."""
    scene = OrgScene(asset)
    cam_mod.strata(int(spp))
    t0 = time.perf_counter()
    img, rays, cov = render_org(scene, cam, int(spp), seed)
    return RenderResult(img.astype(np.float32), time.perf_counter() - t0, int(rays), int(spp),
                        "gt", coverage=cov)
