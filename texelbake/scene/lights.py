"""UsdLux lights and USD cameras -> Light, Camera."""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.errors import AssetError
from texelbake.model import (
    Camera,
    Light,
)
from texelbake.scene.values import usd_matrix, warn


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
    intensity = float(api.GetIntensityAttr().Get(time))
    exposure = float(api.GetExposureAttr().Get(time))
    color = np.asarray(api.GetColorAttr().Get(time), dtype=np.float64)
    if api.GetEnableColorTemperatureAttr().Get(time):
        temp = float(api.GetColorTemperatureAttr().Get(time))
        color = color * np.asarray(UsdLux.BlackbodyTemperatureAsRgb(temp), dtype=np.float64)
    scale = color * intensity * 2.0 ** exposure
    world = usd_matrix(xcache.GetLocalToWorldTransform(prim))
    lin = world[:3, :3]
    position = world[3, :3].copy()
    if kind == "distant":
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
    elif api.GetNormalizeAttr().Get(time):
        # normalize divides the radiance by the surface area 4 pi r^2: pi r^2 / (4 pi r^2)
        radiance = scale * 0.25
    else:
        radiance = scale * np.pi * radius ** 2
    return Light(path=path, kind=kind, direction=np.zeros(3), position=position,
                 radius=0.0 if treat_as_point else radius, radiance_scale=radiance)


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
