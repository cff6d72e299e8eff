"""UsdLux lights and USD cameras -> Light, Camera."""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.asset.values import usd_matrix, warn
from texelbake.errors import AssetError
from texelbake.model import (
    Camera,
    Light,
)


def read_light(prim: Any, time: Any, xcache: Any, warns: list[str]) -> Light | None:
    from pxr import UsdLux

    path = str(prim.GetPath())
    if prim.IsA(UsdLux.DistantLight):
        light: Any = UsdLux.DistantLight(prim)
        kind = "distant"
    elif prim.IsA(UsdLux.SphereLight):
        light = UsdLux.SphereLight(prim)
        kind = "sphere"
    else:
        warn(warns, f"light {path}: unsupported light type {prim.GetTypeName()}; ignored")
        return None
    api = UsdLux.LightAPI(prim)
    normalize = bool(api.GetNormalizeAttr().Get(time))
    scale = light_luminance(
        float(api.GetIntensityAttr().Get(time)), float(api.GetExposureAttr().Get(time)),
        api.GetColorAttr().Get(time),
        float(api.GetColorTemperatureAttr().Get(time))
        if api.GetEnableColorTemperatureAttr().Get(time) else None)
    world = usd_matrix(xcache.GetLocalToWorldTransform(prim))
    lin = world[:3, :3]
    position = world[3, :3].copy()
    if kind == "distant":
        angle = float(light.GetAngleAttr().Get(time))
        if angle > HARD_SHADOW_ANGLE_DEGREES:
            warn(warns, f"light {path}: inputs:angle {angle:g} degrees; texelbake renders "
                        "its shadows as from one direction (hard edges)")
        scale = scale * distant_irradiance_factor(angle, normalize)
        toward = np.array([0.0, 0.0, 1.0]) @ lin  # the light shines along its local -Z
        norm = float(np.linalg.norm(toward))
        if not np.isfinite(norm) or norm == 0.0:
            raise AssetError(f"distant light {path} has a singular transform", prim=path)
        return Light(path=path, kind=kind, direction=toward / norm, position=position,
                     radius=0.0, radiance_scale=scale)
    radius = float(light.GetRadiusAttr().Get(time)) * float(abs(np.linalg.det(lin))) ** (1 / 3)
    treat_as_point = bool(light.GetTreatAsPointAttr().Get(time))
    if treat_as_point or radius == 0.0:
        radiance = scale
    elif normalize:
        # normalize divides the radiance by the surface area 4 pi r^2: pi r^2 / (4 pi r^2)
        radiance = scale * 0.25
    else:
        radiance = scale * np.pi * radius ** 2
    return Light(path=path, kind=kind, direction=np.zeros(3), position=position,
                 radius=0.0 if treat_as_point else radius, radiance_scale=radiance)


#: distant lights wider than this (degrees) get a warning: texelbake shades them as one
#: direction, so their penumbrae are missing
HARD_SHADOW_ANGLE_DEGREES = 2.0


def light_luminance(intensity: float, exposure: float, color, temperature: float | None
                    ) -> np.ndarray:
    """UsdLux LightAPI: L = color * intensity * 2**exposure, times the D65-normalised
    blackbody colour of `temperature` (K) when colour temperature is enabled (None: off).

    returns : (3,) float64 linear RGB luminance
    """
    from pxr import UsdLux

    lum = np.asarray(color, dtype=np.float64) * float(intensity) * 2.0 ** float(exposure)
    if temperature is not None:
        lum = lum * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(float(temperature)),
                               dtype=np.float64)
    return lum


def distant_irradiance_factor(angle_degrees: float, normalize: bool) -> float:
    """Irradiance at normal incidence per unit luminance of a UsdLux DistantLight.

    Normalized (`inputs:normalize` on), the light's luminance is divided by its solid angle,
    so its intensity is the irradiance itself: factor 1. Otherwise the disk of angular
    diameter θ (`inputs:angle`, clipped to [0, 360)) has solid angle
    ω = 2π (1 − cos(θ/2)) and delivers E = L ω (the sun's 0.53° gives ω = 6.72e-5 sr, so
    UsdLux's fallback intensity 50000 is an irradiance of 3.36). θ = 0 is a delta light with
    no solid angle; it is read as normalized (factor 1), which is the limit of L ω with the
    power held fixed.
    """
    if normalize:
        return 1.0
    theta = np.radians(min(max(float(angle_degrees), 0.0), 360.0 - 1e-9))
    if theta == 0.0:
        return 1.0
    return float(2.0 * np.pi * (1.0 - np.cos(0.5 * theta)))


def read_camera(prim: Any, time: Any, xcache: Any, warns: list[str]) -> Camera:
    from pxr import UsdGeom

    cam = UsdGeom.Camera(prim)
    if cam.GetProjectionAttr().Get(time) != UsdGeom.Tokens.perspective:
        warn(warns, f"camera {prim.GetPath()}: projection is "
                     f"{cam.GetProjectionAttr().Get(time)}; read as perspective")
    world = usd_matrix(xcache.GetLocalToWorldTransform(prim))
    return Camera(
        path=str(prim.GetPath()),
        world_from_camera=world.T,
        focal_length=float(cam.GetFocalLengthAttr().Get(time)),
        horizontal_aperture=float(cam.GetHorizontalApertureAttr().Get(time)),
        vertical_aperture=float(cam.GetVerticalApertureAttr().Get(time)),
        clipping=np.asarray(cam.GetClippingRangeAttr().Get(time), dtype=np.float64),
    )


#: irradiance of the default rig's key and fill lights (normal incidence): the key as the
#: generated scenes' suns, the fill a third of it so that the key's shadows stay readable
DEFAULT_KEY_IRRADIANCE = 3.0
DEFAULT_FILL_IRRADIANCE = 1.0


def default_light_rig(view_dir: np.ndarray, up_axis: str = "Y") -> tuple[Light, Light]:
    """The lights a render uses when the asset has none (a studio's "lightless" asset is lit
    by its look-dev scene): a key distant light from above and to one side of the viewer and
    a fill from the other side, both white; named `/texelbake:defaultRig/Key` and `/Fill`
    so that reports say which lights they used.

    view_dir : (3,) direction from the object toward the viewer (the camera);
    up_axis : the stage's up axis ("Y" or "Z")
    """
    v = np.asarray(view_dir, dtype=np.float64)
    norm = float(np.linalg.norm(v))
    if not np.isfinite(norm) or norm == 0.0:
        raise AssetError("default light rig: the view direction is zero or not finite")
    v = v / norm
    up = np.array([0.0, 0.0, 1.0]) if str(up_axis).upper() == "Z" else np.array([0.0, 1.0, 0.0])
    side = np.cross(up, v)
    if float(np.linalg.norm(side)) < 1e-6:  # looking straight down the up axis
        side = np.cross(np.array([1.0, 0.0, 0.0]), v)
    side /= np.linalg.norm(side)
    key = v + 0.8 * up + 0.6 * side
    fill = v + 0.2 * up - 0.9 * side
    white = np.ones(3)
    return (
        Light(path="/texelbake:defaultRig/Key", kind="distant",
              direction=key / np.linalg.norm(key), position=np.zeros(3), radius=0.0,
              radiance_scale=DEFAULT_KEY_IRRADIANCE * white),
        Light(path="/texelbake:defaultRig/Fill", kind="distant",
              direction=fill / np.linalg.norm(fill), position=np.zeros(3), radius=0.0,
              radiance_scale=DEFAULT_FILL_IRRADIANCE * white),
    )
