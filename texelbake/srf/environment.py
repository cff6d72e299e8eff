"""An environment map as lights (seed 002 §4.3): the map is subsampled once into a dense set
of directions, each a light at infinity coloured by its share of the environment, so a
deformed field is lit by it without refiltering the map per point (L rotates each light's
direction; ULR over the capture lights reconstructs between them).

The map is a latitude-longitude image, radiance per pixel, +Y up (USD's default; `up="Z"`
for Z-up assets): row 0 looks up, column 0 looks down −Z, longitude grows toward +X. Each
pixel is assigned to its nearest light direction (a spherical Voronoi cell) and the light's
irradiance at normal incidence is the cell's Σ L ΔΩ — energy-conserving, so a constant
environment L gives Σ E = 4π L whatever the number of lights (to the lat-long quadrature).
"""

from __future__ import annotations

import math

import numpy as np

from texelbake.errors import SettingsError, ShapeError
from texelbake.model import Light
from texelbake.srf.rig import sphere_directions


def latlong_directions(height: int, width: int, up: str = "Y"
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Pixel-centre directions (h · w, 3) of a lat-long map and their solid angles (h · w,)."""
    theta = (np.arange(height) + 0.5) * math.pi / height  # from the up pole
    phi = (np.arange(width) + 0.5) * 2.0 * math.pi / width
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    s = np.sin(th)
    d = np.stack([s * np.sin(ph), np.cos(th), -s * np.cos(ph)], axis=-1).reshape(-1, 3)
    if up.upper() == "Z":
        d = d[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])
    elif up.upper() != "Y":
        raise SettingsError(f"field 'up': 'Y' or 'Z', got {up!r}")
    dw = (math.pi / height) * (2.0 * math.pi / width) * s.reshape(-1)
    return d, dw


def environment_lights(env: object, n: int, up: str = "Y") -> list[Light]:
    """n distant lights carrying a lat-long environment's radiance (module docstring).
    env : (h, w, 3) float linear radiance"""
    img = np.asarray(env, dtype=np.float64)
    if img.ndim != 3 or img.shape[2] != 3 or img.shape[0] < 1 or img.shape[1] < 1:
        raise ShapeError(f"environment map must be (h, w, 3), got {img.shape}")
    if not np.isfinite(img).all():
        raise ShapeError("environment map contains NaN or Inf")
    dirs = sphere_directions(n)
    pix_dir, dw = latlong_directions(img.shape[0], img.shape[1], up)
    cell = np.argmax(pix_dir @ dirs.T, axis=1)  # nearest light per pixel
    rad = img.reshape(-1, 3) * dw[:, None]
    irr = np.stack([np.bincount(cell, rad[:, c], dirs.shape[0]) for c in range(3)], axis=1)
    return [Light(path=f"/Environment/Light{j:04d}", kind="distant", direction=dirs[j],
                  position=np.zeros(3), radius=0.0, radiance_scale=irr[j])
            for j in range(dirs.shape[0]) if irr[j].max() > 0]
