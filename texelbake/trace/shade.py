"""Direct illumination from distant and point lights, with shadow rays (seed 000 §4.2: direct
illumination only, as the seed's renderer).

Radiance toward ωo of a surface point with geometric normal n_g and shading normal n_s:

    L(ωo) = Σ_lights E_l(x) V(x, ωi) f_r(x, ωi, ωo) (n_s · ωi)⁺

with the BRDF evaluated in the shading frame `frames.tangent_frames(n_s)` (as the bake does),
and zero wherever ωi or ωo lies below the geometric or the shading horizon (cosine below
TOL.grazing_cos), exactly the support `texelbake.cpm.level.visibility_cos` gives the bake, so
that the ground truth and the baked reflectance describe the same function. Surfaces are
one-sided (seen from behind they are black), as in the bake.

Lights (texelbake.model.Light): distant — ωi = `direction`, E = `radiance_scale`
(irradiance at normal incidence), shadow ray unbounded; sphere — treated as a point at
`position`: ωi toward it, E = radiant intensity / d², shadow ray up to the light.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.basis import tangent_frames
from texelbake.geometry.raycast import RayCaster
from texelbake.model import Light
from texelbake.tol import TOL

#: brdf(selection (k,) int64 row indices, wi_local (k, 3), wo_local (k, 3)) -> (k, 3) 1/sr
BrdfFn = Callable[[np.ndarray, np.ndarray, np.ndarray], np.ndarray]


def light_at(light: Light, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Incident direction, irradiance at normal incidence and shadow-ray length of one light.

    points : (n, 3) float64
    returns : (wi (n, 3) unit, E (n, 3), tmax (n,) float64 (inf for distant lights))
    """
    p = np.asarray(points, dtype=np.float64)
    n = p.shape[0]
    scale = np.asarray(light.radiance_scale, dtype=np.float64).reshape(3)
    if light.kind == "distant":
        d = np.asarray(light.direction, dtype=np.float64)
        d = d / np.linalg.norm(d)
        return np.broadcast_to(d, (n, 3)).copy(), np.broadcast_to(scale, (n, 3)).copy(), \
            np.full(n, np.inf)
    if light.kind == "sphere":
        v = np.asarray(light.position, dtype=np.float64)[None, :] - p
        dist = np.linalg.norm(v, axis=1)
        ok = dist > 0
        wi = np.divide(v, dist[:, None], out=np.zeros_like(v), where=ok[:, None])
        inv2 = np.divide(1.0, dist * dist, out=np.zeros_like(dist), where=ok)
        return wi, scale[None, :] * inv2[:, None], dist
    raise SettingsError(f"light {light.path}: kind must be 'distant' or 'sphere', got "
                        f"{light.kind!r}")


def lit_points(light: Light, p: np.ndarray, ng: np.ndarray, candidates: np.ndarray,
               occluder: RayCaster | None, ray_eps: float, ns: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """The points one light reaches: among `candidates` (n,) bool, those whose geometric
    (and, when given, shading) normal faces the light above TOL.grazing_cos, with some
    irradiance, and whose shadow ray (from p + ray_eps n_g, up to the light) is unoccluded.

    returns : (indices (k,) int64, wi (n, 3), E (n, 3) of every point, shadow rays cast)"""
    g = TOL.grazing_cos
    wi, e, tmax = light_at(light, p)
    live = candidates & (np.einsum("ij,ij->i", ng, wi) > g) & (e.max(axis=1) > 0)
    if ns is not None:
        live &= np.einsum("ij,ij->i", ns, wi) > g
    idx = np.flatnonzero(live)
    rays = 0
    if idx.size and occluder is not None:
        origins = p[idx] + ray_eps * ng[idx]
        tm = tmax[idx] if np.isfinite(tmax[idx]).any() else np.inf
        rays = int(idx.size)
        idx = idx[~occluder.occluded(origins, wi[idx], tmax=tm)]
    return idx, wi, e, rays


def direct_radiance(
    points: np.ndarray,
    geom_normals: np.ndarray,
    shading_normals: np.ndarray,
    wo: np.ndarray,
    lights: Sequence[Light],
    brdf: BrdfFn,
    occluder: RayCaster | None,
    ray_eps: float,
) -> tuple[np.ndarray, int]:
    """Outgoing radiance toward wo of surface points lit directly (module docstring).

    points, geom_normals, shading_normals, wo : (n, 3) float64 (normals unit, wo unit toward
        the viewer)
    occluder : the mesh shadow rays are tested against (None: no shadows)
    ray_eps : absolute offset of shadow-ray origins along the geometric normal
    returns : (radiance (n, 3) float64, shadow rays cast)
    """
    p = np.asarray(points, dtype=np.float64)
    ng = np.asarray(geom_normals, dtype=np.float64)
    ns = np.asarray(shading_normals, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    n = p.shape[0]
    for name, a in (("geom_normals", ng), ("shading_normals", ns), ("wo", wo)):
        if a.shape != (n, 3):
            raise ShapeError(f"{name} must be ({n}, 3) like points, got {a.shape}")
    out = np.zeros((n, 3))
    rays = 0
    if n == 0:
        return out, rays
    g = TOL.grazing_cos
    view_ok = (np.einsum("ij,ij->i", ng, wo) > g) & (np.einsum("ij,ij->i", ns, wo) > g)
    frames = tangent_frames(ns)  # (n, 3, 3) rows (t, b, n)
    for light in lights:  # a loop over the few lights
        idx, wi, e, r = lit_points(light, p, ng, view_ok, occluder, ray_eps, ns)
        rays += r
        if idx.size == 0:
            continue
        fr = frames[idx]
        wi_l = np.einsum("nij,nj->ni", fr, wi[idx])
        wo_l = np.einsum("nij,nj->ni", fr, wo[idx])
        cos_s = np.einsum("ij,ij->i", ns[idx], wi[idx])
        out[idx] += e[idx] * brdf(idx, wi_l, wo_l) * cos_s[:, None]
    return out, rays
