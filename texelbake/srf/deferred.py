"""One frame of a surface reflectance field (seed 002 §3-§5): the impostor's surfels, warped
by Ψ when given (positions Ψ(p0), footprints (u, v) = J (u_rest, v_rest): Eq. 6 or the exact
Jacobian), are EWA-splatted (`splat`); every covered pixel is a shading point with its
deformed point p*, its rest point p (Eq. 3, through the splat's first-order inverse) and the
look-up rotation L (Eq. 10, `texelbake.deform.lookup`). The viewing direction v* = p* → eye
and each scene light's direction l* at p* are carried to the acquisition frame, v = L v*,
l = L l*; ULR picks the k cameras (visibility against the rest impostor) and the k capture
lights (`ulr`); each (point, scene light, camera, capture light) is a shading operation
(Table 2, `ops`) with colour weights w_c w_l E A(d) — Eq. 11: a distant light's irradiance,
a point light's intensity / d² from p* — executed sorted or naive against the block cache
(`cache`). Shadows and interreflections are the captured images' (§5.2: no light
visibility is traced).

Shading per pixel, not per surfel: the seed accumulates surfel colours and splats them; a
pixel's blended rest point lies on the eye ray through its centre (whatever the blend), so
in a capture camera's own view it projects onto that camera's pixel centre and the frame
reproduces the captured image exactly (the issue's ≥ 40 dB acceptance), where surfel
colours would be low-passed by the splat kernel. `use_lookup=False` is `srf` without L
(directions looked up unrotated, as `cpm-naive`).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from texelbake.deform.impostor import decode_frames
from texelbake.deform.lookup import deformed_tangents, lookup_rotation, orthogonalize
from texelbake.deform.warps import Warp
from texelbake.errors import SettingsError
from texelbake.geometry.raycast import RayCaster
from texelbake.model import Light
from texelbake.srf.cache import DEFAULT_CAPACITY, shade
from texelbake.srf.ops import ShadingOps, build_ops
from texelbake.srf.splat import SplatFrame, splat
from texelbake.srf.store import SrfStore
from texelbake.srf.surfels import Surfels
from texelbake.srf.ulr import camera_weights, light_weights
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.shade import light_at
from texelbake.trace.tracer import RenderResult

#: ULR's k (the seed's and Buehler's usual 3-4)
K_CAMERAS = 3
K_LIGHTS = 3
#: visibility rays start (and stop) this many median footprint radii from their ends
VIS_OFFSET = 0.5


def _unit(x: np.ndarray) -> np.ndarray:
    ln = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, ln, out=np.zeros_like(x), where=ln > 0)


def splat_surfels(surfels: Surfels, cam: PinholeCamera, warp: Warp | None = None, *,
                  use_lookup: bool = True, circular: bool = False,
                  jacobian: str = "exact") -> SplatFrame:
    """The G-buffer of the (warped) surfels seen by `cam` (module docstring). circular :
    discs of radius max(s_u, s_v) perpendicular to the deformed normal (Fig. 8a)."""
    s = surfels
    ru, rv = s.u, s.v
    if warp is None:
        pos, u, v = s.p0, ru, rv
    else:
        pos = warp.positions(s.p0)
        u, v = deformed_tangents(warp, s.p0, ru, rv, jacobian)
    lk = None
    if warp is not None and use_lookup:
        lk, _ = lookup_rotation(decode_frames(s.r0, s.u0, s.v0), u, v)
    if circular:
        ub, vb, _, _ = orthogonalize(u, v)
        r = np.maximum(s.su, s.sv)[:, None]
        u, v, ru, rv = r * ub, r * vb, r * s.u0, r * s.v0
    return splat(cam, pos, u, v, rest_centers=s.p0, rest_u=ru, rest_v=rv, lookup=lk)


def frame_ops(store: SrfStore, g: SplatFrame, cam: PinholeCamera, lights: Sequence[Light],
              occluder: RayCaster | None, vis_offset: float, k_cameras: int = K_CAMERAS,
              k_lights: int = K_LIGHTS) -> tuple[np.ndarray, ShadingOps, dict[str, Any]]:
    """Shading operations of the covered pixels. returns (pixel index (p,), ops, extras)"""
    pix = np.flatnonzero(g.covered)
    p_star, p_rest, lk = g.p_star[pix], g.p_rest[pix], g.lookup[pix]
    v_rest = np.einsum("nij,nj->ni", lk, _unit(cam.position[None] - p_star))
    cam_i, cam_w, cam_xy, ok_c = camera_weights(store.cameras, p_rest, v_rest, k_cameras,
                                                occluder, vis_offset)
    li, lw, rad = [], [], []
    for light in lights:  # a loop over the few scene lights
        wi, e, _ = light_at(light, p_star)  # Eq. 11: E, or I / d² from p*
        j, w, _ = light_weights(np.einsum("nij,nj->ni", lk, wi), store.light_dirs, k_lights)
        li.append(j)
        lw.append(w)
        rad.append(e)
    if not lights:
        raise SettingsError("field 'lights': a reflectance field is rendered under lights")
    ops = build_ops(cam_i, cam_w, cam_xy, np.stack(li), np.stack(lw), np.stack(rad))
    return pix, ops, {"no_camera_fraction": float(np.mean(~ok_c)) if pix.size else 0.0}


def render_srf(store: SrfStore, surfels: Surfels, cam: PinholeCamera,
               lights: Sequence[Light], *, warp: Warp | None = None,
               use_lookup: bool = True, circular: bool = False, executor: str = "sorted",
               cache_blocks: int = DEFAULT_CAPACITY, k_cameras: int = K_CAMERAS,
               k_lights: int = K_LIGHTS, jacobian: str = "exact") -> RenderResult:
    """One `srf` frame (module docstring). Pixels with no usable capture camera stay black
    (`extras["no_camera_fraction"]`)."""
    t0 = time.perf_counter()
    g = splat_surfels(surfels, cam, warp, use_lookup=use_lookup, circular=circular,
                      jacobian=jacobian)
    occluder = RayCaster(surfels.mesh_vertices, surfels.mesh_faces)
    vis = VIS_OFFSET * float(np.median(np.maximum(surfels.su, surfels.sv)))
    pix, ops, extras = frame_ops(store, g, cam, lights, occluder, vis, k_cameras, k_lights)
    colours, stats = shade(store, ops, pix.size, executor, cache_blocks)
    img = np.zeros((cam.height * cam.width, 3))
    img[pix] = colours
    extras.update({"executor": executor, "block_reads": stats.block_reads,
                   "operations": len(ops), "shading_seconds": stats.seconds,
                   "fragments": g.fragments, "surfels": len(surfels)})
    return RenderResult(img.reshape(cam.height, cam.width, 3).astype(np.float32),
                        time.perf_counter() - t0, int(occluder.rays_cast), 1, "srf", extras,
                        g.coverage(cam))
