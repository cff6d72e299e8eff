"""UsdLux DomeLight -> environment lighting, as distant lights drawn by importance sampling.

Every renderer of texelbake (gt, cpm, the baselines, the previews) sums over `Light`s. A dome
of radiance L(ω) (a lat-long texture times the light's colour, intensity and exposure, or the
constant alone) enters that sum as `DOME_SAMPLES` distant lights ω_k drawn once from a
density p(ω) ∝ luminance × (the lat-long map's solid angle per pixel, ∝ sin θ): each carries
the irradiance L(ω_k) / (p(ω_k) K). The sum over them is an unbiased estimate of the dome's
direct light, ∫ L(ω) V f_r cos dω, in every renderer alike (the same directions for every
pixel and texel: its error is a fixed pattern, not noise, and reruns are identical). The draw
is stratified — one uniform point per cell of a √K × √K grid, mapped through the map's 2-D
CDF (the rows' marginal, then the chosen row's columns) — so bright regions get their share
of directions and the estimate of a smooth integrand converges faster than 1/√K.

Lat-long layout (UsdLux, the OpenEXR convention): pixel column x ↦ longitude +π … −π, row y
(top first) ↦ latitude +π/2 … −π/2; latitude 0, longitude 0 is +Z, longitude π/2 is +X, and
+Y is the top pole, in the light's own frame (its transform applies; DomeLight_1's poleAxis
"scene" on a Z-up stage turns +Y onto +Z).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.asset.files import load_image
from texelbake.asset.lights import light_luminance
from texelbake.asset.values import usd_matrix, warn
from texelbake.errors import AssetError, ShapeError
from texelbake.model import Light

#: distant lights a dome becomes (a 16 x 16 stratified draw). With 256 an unoccluded
#: Lambertian plane under a constant dome gets pi L within 1 % (tests/asset/test_dome.py),
#: and a frame's shading costs 256 shadow rays per point
DOME_SAMPLES = 256
#: rows x columns of the map standing for a constant dome (sin θ weighting alone)
CONSTANT_MAP = (32, 64)
#: the seed of the stratified draw (every bake and render of an asset draws the same)
DOME_SEED = 0


def latlong_directions(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Directions (n, 3) float64 of lat-long coordinates u (column / width, 0 at the left)
    and v (row / height, 0 at the top), in the dome's frame."""
    lon = np.pi * (1.0 - 2.0 * np.asarray(u, dtype=np.float64))
    lat = np.pi * (0.5 - np.asarray(v, dtype=np.float64))
    c = np.cos(lat)
    return np.stack([c * np.sin(lon), np.sin(lat), c * np.cos(lon)], axis=1)


def sample_latlong(radiance: np.ndarray, n: int, seed: int = DOME_SEED
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Draw n directions from a lat-long radiance map by luminance × sin θ (stratified).

    radiance : (h, w, 3) float64 linear RGB, row 0 the top (latitude +π/2)
    n : directions, rounded down to a square (at least 1)
    returns : (dirs (m, 3) unit in the dome's frame, radiance (m, 3) at them, pdf (m,) per
        steradian), m = ⌊√n⌋²
    """
    rad = np.asarray(radiance, dtype=np.float64)
    if rad.ndim != 3 or rad.shape[2] != 3 or rad.shape[0] == 0 or rad.shape[1] == 0:
        raise ShapeError(f"radiance must be (h, w, 3), got {rad.shape}")
    h, w, _ = rad.shape
    lum = np.maximum(rad @ np.array([0.2126, 0.7152, 0.0722]), 0.0)  # (h, w) Rec. 709
    sin_row = np.sin(np.pi * (np.arange(h) + 0.5) / h)  # (h,)
    weight = lum * sin_row[:, None]  # (h, w)
    if not np.isfinite(weight).all():
        raise ShapeError("radiance has non-finite values")
    if weight.sum() <= 0.0:  # a black dome: uniform over the map, every light carries 0
        weight = np.broadcast_to(sin_row[:, None], (h, w)).copy()
    row_w = weight.sum(axis=1)  # (h,)
    row_cdf = np.cumsum(row_w) / row_w.sum()
    col_cdf = np.cumsum(weight, axis=1) / np.maximum(row_w, 1e-300)[:, None]  # (h, w)
    side = max(int(np.floor(np.sqrt(max(int(n), 1)))), 1)
    rng = np.random.default_rng(seed)
    gi, gj = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    xi = (np.stack([gi.ravel(), gj.ravel()], axis=1) + rng.random((side * side, 2))) / side
    row = np.minimum(np.searchsorted(row_cdf, xi[:, 0], side="right"), h - 1)  # (m,)
    col = np.empty_like(row)
    # columns of each drawn row: a search per distinct row (at most h, vectorized within)
    for r in np.unique(row).tolist():
        sel = row == r
        col[sel] = np.minimum(np.searchsorted(col_cdf[r], xi[sel, 1], side="right"), w - 1)
    # the position inside the pixel, uniform (the density is constant over the pixel in u, v)
    jitter = rng.random((row.shape[0], 2))
    u = (col + jitter[:, 0]) / w
    v = (row + jitter[:, 1]) / h
    p_uv = weight[row, col] / weight.sum() * (h * w)  # density over [0, 1]^2
    sin_theta = np.sin(np.pi * v)
    # dω = 2π · π · sin θ du dv
    pdf = np.divide(p_uv, 2.0 * np.pi * np.pi * sin_theta, out=np.zeros_like(p_uv),
                    where=sin_theta > 0)
    return latlong_directions(u, v), rad[row, col], pdf


def dome_lights(path: str, radiance: np.ndarray, world_from_dome: np.ndarray,
                n: int = DOME_SAMPLES, seed: int = DOME_SEED) -> list[Light]:
    """A dome as distant lights (module docstring).

    radiance : (h, w, 3) float64 lat-long radiance (already times colour and intensity)
    world_from_dome : (3, 3) float64 rotation taking the dome's frame to world (row vectors:
        d_world = d_dome @ world_from_dome)
    returns : ⌊√n⌋² lights named `{path}/sample{k}`, kind "distant", `direction` toward the
        dome, `radiance_scale` L / (p K)
    """
    dirs, rad, pdf = sample_latlong(radiance, n, seed)
    m = dirs.shape[0]
    world = dirs @ np.asarray(world_from_dome, dtype=np.float64)
    world /= np.linalg.norm(world, axis=1, keepdims=True)
    scale = np.divide(rad, (pdf * m)[:, None], out=np.zeros_like(rad), where=pdf[:, None] > 0)
    return [Light(path=f"{path}/sample{k}", kind="distant", direction=world[k],
                  position=np.zeros(3), radius=0.0, radiance_scale=scale[k])
            for k in range(m)]  # the lights are the renderers' interface: one per direction


def read_dome(prim: Any, time: Any, xcache: Any, up_axis: str, warns: list[str]
              ) -> list[Light]:
    """A UsdLux DomeLight (or DomeLight_1) prim -> `dome_lights`. A texture that does not
    resolve or is not lat-long is warned of and the dome's constant colour used."""
    from pxr import UsdLux

    from texelbake.io.images import srgb_to_linear

    path = str(prim.GetPath())
    api = UsdLux.LightAPI(prim)
    scale = light_luminance(
        float(api.GetIntensityAttr().Get(time)), float(api.GetExposureAttr().Get(time)),
        api.GetColorAttr().Get(time),
        float(api.GetColorTemperatureAttr().Get(time))
        if api.GetEnableColorTemperatureAttr().Get(time) else None)
    dome: Any = UsdLux.DomeLight_1(prim) if prim.IsA(UsdLux.DomeLight_1) else \
        UsdLux.DomeLight(prim)
    radiance = np.ones((*CONSTANT_MAP, 3))
    asset = dome.GetTextureFileAttr().Get(time)
    fmt = str(dome.GetTextureFormatAttr().Get(time) or "automatic")
    if asset is not None and asset.path:
        if fmt not in ("automatic", "latlong"):
            warn(warns, f"dome light {path}: texture:format {fmt!r} is not read (lat-long "
                        "only); lit by its constant colour")
        elif not asset.resolvedPath:
            warn(warns, f"dome light {path}: texture '{asset.path}' does not resolve; lit by "
                        "its constant colour")
        else:
            pixels, is_8bit, _ = load_image(asset.resolvedPath, path)
            rgb = np.asarray(pixels, dtype=np.float64)
            rgb = (np.repeat(rgb[..., :1], 3, axis=2) if rgb.shape[2] < 3 else rgb[..., :3])
            radiance = srgb_to_linear(rgb) if is_8bit else rgb
    world = usd_matrix(xcache.GetLocalToWorldTransform(prim))[:3, :3]
    norms = np.linalg.norm(world, axis=1, keepdims=True)
    if not np.isfinite(norms).all() or (norms == 0).any():
        raise AssetError(f"dome light {path} has a singular transform", prim=path)
    rot = world / norms  # the dome's orientation; its scale does not matter at infinity
    pole = str(dome.GetPoleAxisAttr().Get(time)) if prim.IsA(UsdLux.DomeLight_1) else "Y"
    if pole == "Z" or (pole == "scene" and str(up_axis).upper() == "Z"):
        rot = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]) @ rot  # +Y -> +Z
    return dome_lights(path, radiance * scale[None, None, :], rot)
