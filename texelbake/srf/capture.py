"""Synthetic capture of a surface reflectance field (seed 002 §3) from any asset: M_org
rendered by the project's `gt` renderer (`render.gt.shade_org`: stratified eye rays, direct
light, shadow rays against M_org) from N cameras on a sphere, once per directional light of
unit irradiance among M on a sphere — so a pixel holds the reflectance value SRF(p, l, v)
of the field (radiance per unit irradiance), written block by block to a store.

The loop runs over images (camera × light), each rendered whole-array. `capture_cameras`
writes the blocks and silhouettes of some cameras of a rig (the farm's shard,
`texelbake.stages.srf`); `capture` runs every camera and closes the store.
"""

from __future__ import annotations

import copy
from collections.abc import Iterable, Sequence
from pathlib import Path

import numpy as np

from texelbake.errors import SettingsError
from texelbake.model import AssetModel, Light
from texelbake.srf.rig import (
    DEFAULT_CAMERAS,
    DEFAULT_LIGHTS,
    DEFAULT_SIZE,
    DEFAULT_SPP,
    sphere_cameras,
    sphere_directions,
)
from texelbake.srf.store import SrfStore, SrfWriter
from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.org import OrgScene, shade_org
from texelbake.trace.tracer import accumulate


def unit_light(direction: np.ndarray, index: int) -> Light:
    """A distant light of unit irradiance toward `direction` (the capture's light l)."""
    return Light(path=f"/SrfCapture/Light{index:03d}", kind="distant",
                 direction=np.asarray(direction, dtype=np.float64), position=np.zeros(3),
                 radius=0.0, radiance_scale=np.ones(3))


def capture_image(scene: OrgScene, cam: PinholeCamera, light: Light, spp: int, seed: int
                  ) -> tuple[np.ndarray, np.ndarray]:
    """One reflectance image: `gt` of M_org under this light only.
    returns (image (h, w, 3) float64, coverage (h, w) float64)"""
    lit = copy.copy(scene)
    lit.lights = (light,)
    img, _, cov = accumulate(cam, int(spp), int(seed), lambda o, d: shade_org(lit, o, d))
    return img, cov


def capture(asset: AssetModel, out: str | Path, *, n_cameras: int = DEFAULT_CAMERAS,
            n_lights: int = DEFAULT_LIGHTS, size: int = DEFAULT_SIZE, spp: int = DEFAULT_SPP,
            seed: int = 0, fov_deg: float = 30.0, encoding: str = "raw", tile: int = 4,
            components: int = 6, cameras: Sequence[PinholeCamera] | None = None,
            light_dirs: np.ndarray | None = None) -> SrfStore:
    """Capture the field of `asset` into the store folder `out` (module docstring).
    cameras / light_dirs override the sphere rig (n_cameras, n_lights, size, fov_deg)."""
    cam_mod.strata(int(spp))
    if cameras is None:
        if int(size) < 2:
            raise SettingsError(f"field 'size': capture images need >= 2 pixels, got {size}")
        cameras = sphere_cameras(asset.bounds, n_cameras, int(size), fov_deg=fov_deg)
    dirs = sphere_directions(n_lights) if light_dirs is None else np.asarray(light_dirs,
                                                                              np.float64)
    writer = SrfWriter(out, list(cameras), dirs, encoding=encoding, tile=tile,
                       components=components, source=str(asset.source))
    capture_cameras(asset, writer, range(len(writer.cameras)), spp, seed)
    bounds = np.asarray(asset.bounds, dtype=np.float64)
    return writer.close({"capture": {"renderer": "gt", "spp": int(spp), "seed": int(seed)},
                         "bounds": bounds.tolist()})


def capture_cameras(asset: AssetModel, writer: SrfWriter, cameras: Iterable[int], spp: int,
                    seed: int) -> int:
    """Render and write the blocks (every light) and silhouette of the given cameras of the
    writer's rig — one shard of a capture; `writer.close()` once every shard is done.
    Returns the images written."""
    scene = OrgScene(asset)
    lights = [unit_light(d, j) for j, d in enumerate(writer.light_dirs)]
    n = 0
    for c in cameras:  # a loop over images, each rendered whole
        cam = writer.cameras[int(c)]
        for j, light in enumerate(lights):
            img, cov = capture_image(scene, cam, light, spp, seed)
            writer.write(int(c), j, img)
            if j == 0:  # coverage does not depend on the light
                writer.write_silhouette(int(c), cov)
            n += 1
    return n
