"""The wavefront loop: passes of stratified eye rays over every pixel, slices that bound
memory, the box filter (`accumulate`), and the result of a frame (`RenderResult`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from texelbake.render import camera as cam_mod
from texelbake.render.camera import PinholeCamera

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


# --------------------------------------------------------------------------- wavefront loop


def eye_passes(cam: PinholeCamera, spp: int, seed: int):
    """Yield (sample start, origins, dirs) of passes of whole samples (every pixel)."""
    n_pix = cam.width * cam.height
    per_pass = max(1, PASS_RAYS // n_pix)
    for start in range(0, spp, per_pass):  # a loop over passes of many rays
        stop = min(spp, start + per_pass)
        off = cam_mod.sample_offsets(spp, n_pix, seed, start, stop)
        o, d = cam_mod.eye_rays(cam, off)
        yield start, o, d


def ray_slices(n: int):
    for a in range(0, n, PASS_RAYS):
        yield slice(a, min(n, a + PASS_RAYS))


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


def accumulate(cam: PinholeCamera, spp: int, seed: int, shade) -> tuple[np.ndarray, int]:
    """Box-filtered image of `shade(o, d) -> (radiance (n, 3), rays)` over the stratified eye
    rays of every pass, in slices (no loop per pixel)."""
    acc = np.zeros((cam.height * cam.width, 3))
    rays = 0
    for _, o, d in eye_passes(cam, spp, seed):
        rad = np.zeros_like(o)
        for sl in ray_slices(o.shape[0]):
            rad[sl], r = shade(o[sl], d[sl])
            rays += r
        acc += rad.reshape(-1, cam.height * cam.width, 3).sum(axis=0)
    return (acc / spp).reshape(cam.height, cam.width, 3), rays
