"""The wavefront loop: passes of stratified eye rays over every pixel, slices that bound
memory, the box filter (`accumulate`), rendering to a time budget (`progressive`), and the
result of a frame (`RenderResult`)."""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera

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
        -1 where M_org was used, NaN on background; `mesh` the M_i used; fallback fraction;
        equal-time: `mean_spp`, `budget_seconds`)
    coverage : (h, w) float32 fraction of each pixel's eye rays that saw the object (what
        `texelbake.render.metrics.object_mask` measures errors over)
    """

    image: np.ndarray
    seconds: float
    rays_cast: int
    spp: int
    mode: str = ""
    extras: dict[str, Any] = field(default_factory=dict)
    coverage: np.ndarray | None = None


# --------------------------------------------------------------------------- wavefront loop


def eye_passes(cam: PinholeCamera, spp: int, seed: int, pixels: np.ndarray | None = None):
    """Yield (sample start, origins, dirs) of passes of whole samples (every pixel, or the
    row-major `pixels` (p,) only: the same rays those pixels get in the whole frame's passes,
    ordered [sample][pixel])."""
    n_pix = cam.width * cam.height
    per_pass = max(1, PASS_RAYS // n_pix)
    for start in range(0, spp, per_pass):  # a loop over passes of many rays
        stop = min(spp, start + per_pass)
        if pixels is None:
            o, d = cam_mod.eye_rays(cam, cam_mod.sample_offsets(spp, n_pix, seed, start, stop))
        else:
            sub = cam_mod.sample_offsets(spp, n_pix, seed, start, stop, pixels)  # (k, p, 2)
            pix = np.broadcast_to(pixels, sub.shape[:2]).reshape(-1)
            o, d = cam_mod.eye_rays_at(cam, pix, sub.reshape(-1, 2))
        yield start, o, d


def frame_pixels(cam: PinholeCamera, box: np.ndarray | None) -> np.ndarray | None:
    """The pixels whose eye rays can meet `box` (`camera.box_pixels`), None for all."""
    return None if box is None else cam_mod.box_pixels(cam, box)


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


def enters_box(o: np.ndarray, d: np.ndarray, box: np.ndarray) -> np.ndarray:
    """(n,) bool: the rays o + t d (t >= 0) meet the axis-aligned box (2, 3) [lo, hi]
    (the slab test; a zero direction component is inside its slab iff the origin is)."""
    lo, hi = box[0], box[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / d
        t0 = (lo - o) * inv
        t1 = (hi - o) * inv
    # 0 * inf (a zero component with the origin on a slab plane) is NaN: that slab is open
    near = np.where(np.isnan(t0) | np.isnan(t1), -np.inf, np.minimum(t0, t1)).max(axis=1)
    far = np.where(np.isnan(t0) | np.isnan(t1), np.inf, np.maximum(t0, t1)).min(axis=1)
    return (near <= far) & (far >= 0.0)


def culled(shade, box: np.ndarray | None):
    """`shade` on the eye rays that enter `box` (2, 3) only (everything the frame can show
    lies inside it): the others are background, radiance 0 and no hit, and count as one ray
    each (the eye ray) without being traced. At the sizes the maps serve most of a frame's
    eye rays miss the object (an object of 64 px in a 512² frame: ~1 % hit), and tracing and
    shading them was the frame's cost. box None: `shade` itself."""
    if box is None:
        return shade

    def inner(o: np.ndarray, d: np.ndarray):
        m = enters_box(o, d, box)
        rad = np.zeros((o.shape[0], 3))
        hit = np.zeros(o.shape[0], dtype=bool)
        rays = int(o.shape[0] - m.sum())
        if m.any():
            rad[m], r, hit[m] = shade(o[m], d[m])
            rays += r
        return rad, rays, hit

    return inner


def accumulate(cam: PinholeCamera, spp: int, seed: int, shade, box: np.ndarray | None = None
               ) -> tuple[np.ndarray, int, np.ndarray]:
    """Box-filtered image of `shade(o, d) -> (radiance (n, 3), rays, hit (n,) bool)` over the
    stratified eye rays of every pass, in slices (no loop per pixel); with `box` (2, 3) the
    eye rays that miss it are not shaded (`culled`).
    returns (image (h, w, 3), rays cast, coverage (h, w): fraction of eye rays that hit)"""
    shade = culled(shade, box)
    n_pix = cam.height * cam.width
    pixels = frame_pixels(cam, box)  # eye rays only where the box projects
    n_eff = n_pix if pixels is None else pixels.size
    at = slice(None) if pixels is None else pixels
    acc = np.zeros((n_pix, 3))
    cov = np.zeros(n_pix)
    rays = 0
    per_pass = max(1, PASS_RAYS // n_pix)  # eye_passes' samples per pass
    for start, o, d in eye_passes(cam, spp, seed, pixels):
        rad = np.zeros_like(o)
        hit = np.zeros(o.shape[0], dtype=bool)
        for sl in ray_slices(o.shape[0]):
            rad[sl], r, hit[sl] = shade(o[sl], d[sl])
            rays += r
        rays += (n_pix - n_eff) * (min(spp, start + per_pass) - start)  # the others' eye rays
        if n_eff:
            acc[at] += rad.reshape(-1, n_eff, 3).sum(axis=0)
            cov[at] += hit.reshape(-1, n_eff).sum(axis=0)
    return ((acc / spp).reshape(cam.height, cam.width, 3), rays,
            (cov / spp).reshape(cam.height, cam.width))


# --------------------------------------------------------------------------- time budget

#: Roberts' R2 sequence (the plastic number's reciprocal powers): a low-discrepancy sequence
#: in [0, 1)² whose every prefix is well spread, so a pixel may stop after any number of
#: samples — which a stratified grid (`camera.strata`, fixed spp) cannot offer.
R2 = np.array([0.7548776662466927, 0.5698402909980532])

#: each further chunk of a time-budgeted frame takes this fraction of the time left (by the
#: measured cost per sample), so the chunks shrink geometrically toward the budget: a chunk
#: overshoots the budget only if it runs 1 / BUDGET_STEP times slower than the samples before
#: it. 0.8 overshot by 5.3 % on a loaded 2-core machine (the full cylinder, 512²); 0.5 needs a
#: 2x slowdown within one chunk, for ~4 more chunks per frame (~1 ms each)
BUDGET_STEP = 0.5
#: samples of the smallest chunk; below it the frame stops (per-call overhead would dominate)
MIN_CHUNK_RAYS = 512


def progressive(cam: PinholeCamera, seed: int, shade, budget_seconds: float,
                box: np.ndarray | None = None
                ) -> tuple[np.ndarray, int, np.ndarray, float, float]:
    """Render until `budget_seconds` of wall time are spent: every pixel gets one sample, then
    further samples are added in chunks of pixels (whole rows in a seeded random order, so a
    partial pass is spread over the image), each `BUDGET_STEP` of the time left at the
    measured cost per sample (at most a pass), until less than `MIN_CHUNK_RAYS` samples'
    time (a quarter pass's, for frames smaller than that) is left. On frames of a few hundred
    pixels the per-call overhead makes the time only approximate (a 24² preview stopped at
    0.4 of its budget with a whole-pass threshold); the benchmark frames (512²) land within
    ±5 %. Each pixel's sample k sits at R2[k] shifted by a per-pixel random
    offset (Cranley–Patterson rotation), so every pixel's samples are well spread whatever
    their count; the pixel's value is the mean of its samples.

    The first pass (one sample per pixel) is always rendered, even when it alone exceeds the
    budget; the caller reports the measured time, not the budget.
    returns (image (h, w, 3), rays cast, coverage (h, w), mean samples per pixel, seconds)
    """
    t0 = time.perf_counter()
    shade = culled(shade, box)  # eye rays that miss `box` are not shaded
    full = cam.width * cam.height
    rng = np.random.default_rng([int(seed), 0x52])
    # a partial pass covers whole rows in a random order: spread over the image, and
    # neighbouring eye rays stay neighbours (coherent traversal). Everything below is kept
    # in that order (position i holds pixel order[i]), so a chunk is a slice, not a gather.
    # With `box`, only the rows and columns of the rectangle it projects to (`box_pixels`).
    pixels = frame_pixels(cam, box)
    rect = (np.arange(cam.height)[:, None] * cam.width + np.arange(cam.width)[None, :]
            if pixels is None or pixels.size == 0 else _as_rect(pixels, cam.width))
    order = rect[rng.permutation(rect.shape[0])].reshape(-1)
    n_pix = order.size
    shift = rng.random((n_pix, 2))
    acc = np.zeros((n_pix, 3))
    cov = np.zeros(n_pix)
    rays = 0
    k, pos = 0, 0  # the next sample is sample k of the pixel at position pos
    chunk = n_pix  # the first chunk is the whole first pass
    while True:
        sl = slice(pos, min(pos + chunk, n_pix))  # within one pass
        off = shift[sl] + k * R2
        off -= np.floor(off)
        o, d = cam_mod.eye_rays_at(cam, order[sl], off)
        for part in ray_slices(o.shape[0]):
            rad, r, hit = shade(o[part], d[part])
            at = slice(sl.start + part.start, sl.start + part.stop)
            acc[at] += rad
            cov[at] += hit
            rays += r
        pos = sl.stop
        if pos == n_pix:
            k, pos = k + 1, 0
        done = k * n_pix + pos
        elapsed = time.perf_counter() - t0
        per_sample = elapsed / done
        chunk = int(min(BUDGET_STEP * (budget_seconds - elapsed) / per_sample, n_pix))
        if chunk < min(MIN_CHUNK_RAYS, max(n_pix // 4, 1)):
            break
    count = np.full(n_pix, float(k))
    count[:pos] += 1.0
    img = np.zeros((full, 3))
    img[order] = acc / count[:, None]
    coverage = np.zeros(full)
    coverage[order] = cov / count
    return (img.reshape(cam.height, cam.width, 3), rays,
            coverage.reshape(cam.height, cam.width), done / n_pix,
            time.perf_counter() - t0)


def _as_rect(pixels: np.ndarray, width: int) -> np.ndarray:
    """(rows, cols) int64 the rectangle of row-major `pixels` (`box_pixels`: a rectangle,
    ascending) as a 2-D array of its pixel ids, one row per image row."""
    rows = np.unique(pixels // width)
    return pixels.reshape(rows.size, -1)
