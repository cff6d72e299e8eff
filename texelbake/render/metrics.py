"""Image error metrics against a reference (DESIGN.md "Measuring"): RMSE, PSNR and SNR in dB,
a perceptual difference map (CIE ΔE*ab per pixel) written as an image, NVIDIA's FLIP, and
the errors over the object's pixels (`object_mask`, `object_errors`).

Conventions (stated once, used by every report):
- images are linear radiance, (h, w, 3) (or any shape that matches the reference);
- RMSE is over every pixel and channel given; the reports measure over the *object's*
  pixels (`object_mask`: where the reference or the image saw the object, dilated by one
  pixel) — over a whole frame the exactly-black background lifts PSNR by 20-30 dB when the
  object covers 1 % of it; whole-frame PSNR stays in the reports, labelled;
- PSNR uses the peak of the *reference* (its largest value over pixels and channels), so a
  brighter scene does not look better; PSNR = 20 log10(peak / RMSE);
- SNR = 10 log10(Σ ref² / Σ (img - ref)²), the energy ratio seed 000 uses for its ε (§3.3);
- an exact match gives +inf dB, never a division error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texelbake.errors import ShapeError


def _pair(image: object, reference: object) -> tuple[np.ndarray, np.ndarray]:
    img = np.asarray(image, dtype=np.float64)
    ref = np.asarray(reference, dtype=np.float64)
    if img.shape != ref.shape:
        raise ShapeError(f"image shape {img.shape} does not match the reference {ref.shape}")
    if img.size == 0:
        raise ShapeError("images are empty")
    if not (np.isfinite(img).all() and np.isfinite(ref).all()):
        raise ShapeError("images contain NaN or Inf")
    return img, ref


def rmse(image: object, reference: object) -> float:
    """Root mean square error over all pixels and channels.

    image, reference : (h, w, c) float (any equal shapes)
    """
    img, ref = _pair(image, reference)
    return float(np.sqrt(np.mean((img - ref) ** 2)))


def psnr_db(image: object, reference: object, peak: float | None = None) -> float:
    """Peak signal-to-noise ratio in dB: 20 log10(peak / RMSE); peak = max(reference) unless
    given. +inf for an exact match."""
    img, ref = _pair(image, reference)
    peak = float(ref.max()) if peak is None else float(peak)
    if peak <= 0.0:
        raise ShapeError(f"PSNR needs a positive peak, got {peak} (all-black reference?)")
    e = rmse(img, ref)
    return float("inf") if e == 0.0 else float(20.0 * np.log10(peak / e))


def snr_db(image: object, reference: object) -> float:
    """Signal-to-noise ratio in dB: 10 log10(Σ ref² / Σ (image - ref)²). +inf for an exact
    match; raises ShapeError for an all-zero reference."""
    img, ref = _pair(image, reference)
    signal = float(np.sum(ref * ref))
    if signal <= 0.0:
        raise ShapeError("SNR needs a reference with energy (all-zero reference)")
    noise = float(np.sum((img - ref) ** 2))
    return float("inf") if noise == 0.0 else float(10.0 * np.log10(signal / noise))


# sRGB (D65) linear RGB -> XYZ, IEC 61966-2-1
_RGB_TO_XYZ = np.array([
    [0.4124564, 0.3575761, 0.1804375],
    [0.2126729, 0.7151522, 0.0721750],
    [0.0193339, 0.1191920, 0.9503041],
])
_WHITE = _RGB_TO_XYZ.sum(axis=1)  # XYZ of linear RGB (1, 1, 1)


def linear_to_lab(rgb: object, white: float = 1.0) -> np.ndarray:
    """CIE L*a*b* of linear sRGB radiance scaled so that `white` maps to L* = 100.

    rgb : (..., 3) float64; returns (..., 3) float64
    """
    x = np.asarray(rgb, dtype=np.float64)
    if x.shape[-1] != 3:
        raise ShapeError(f"colour images must end in 3 channels, got {x.shape}")
    xyz = (x / float(white)) @ _RGB_TO_XYZ.T / _WHITE
    d = 6.0 / 29.0
    f = np.where(xyz > d ** 3, np.cbrt(np.maximum(xyz, 0.0)), xyz / (3 * d * d) + 4.0 / 29.0)
    return np.stack([116.0 * f[..., 1] - 16.0, 500.0 * (f[..., 0] - f[..., 1]),
                     200.0 * (f[..., 1] - f[..., 2])], axis=-1)


def difference_map(image: object, reference: object, white: float | None = None) -> np.ndarray:
    """Perceptual difference per pixel: CIE ΔE*ab (1976) between the two images in L*a*b*,
    both scaled by the same white (default: the 99.5th percentile luminance of the
    reference's non-black pixels, the exposure a viewer would pick). ΔE ≈ 2.3 is a just-noticeable difference.

    image, reference : (h, w, 3) float; returns (h, w) float64 >= 0
    """
    img, ref = _pair(image, reference)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ShapeError(f"difference_map needs (h, w, 3) images, got {ref.shape}")
    if white is None:
        white = _white(ref)
    return np.linalg.norm(linear_to_lab(img, white) - linear_to_lab(ref, white), axis=-1)


def write_difference_map(path: str | Path, dmap: object, vmax: float = 10.0) -> Path:
    """Write a ΔE map as a colour-mapped PNG (magma, 0 .. vmax ΔE). Returns the path."""
    from matplotlib import colormaps

    from texelbake.io.images import write_png

    d = np.asarray(dmap, dtype=np.float64)
    if d.ndim != 2:
        raise ShapeError(f"dmap must be (h, w), got {d.shape}")
    rgb = colormaps["magma"](np.clip(d / float(vmax), 0.0, 1.0))[..., :3]
    return write_png(path, rgb, srgb=False)


def _white(reference: np.ndarray) -> float:
    """The exposure a viewer would pick: the 99.5th percentile luminance of the reference's
    non-black pixels (1 for an all-black reference)."""
    lum = reference @ _RGB_TO_XYZ[1]
    lum = lum[lum > 0]
    white = float(np.percentile(lum, 99.5)) if lum.size else 1.0
    return white if white > 0 else 1.0


def object_mask(*coverages: object) -> np.ndarray:
    """Pixels where the object is: the union of the given coverage maps ((h, w), > 0 where
    an eye ray saw the object; e.g. the reference's and the compared image's), dilated by one
    pixel (3 x 3) so that a silhouette one image has and the other lacks is counted.
    returns (h, w) bool"""
    from scipy.ndimage import binary_dilation

    if not coverages:
        raise ShapeError("object_mask needs at least one coverage map")
    maps = [np.asarray(c) for c in coverages]
    if any(m.ndim != 2 or m.shape != maps[0].shape for m in maps):
        raise ShapeError(f"coverage maps must be (h, w) of one shape, got "
                         f"{[m.shape for m in maps]}")
    union = np.logical_or.reduce([m > 0 for m in maps])
    return binary_dilation(union, structure=np.ones((3, 3), dtype=bool))


def flip_map(image: object, reference: object, white: float | None = None) -> np.ndarray:
    """NVIDIA FLIP error per pixel (the `flip-evaluator` package, LDR-FLIP, 67 pixels per
    degree) of the two linear images exposed by the same white (default: as
    `difference_map`) and clipped to [0, 1]. returns (h, w) float in [0, 1]"""
    import flip_evaluator

    img, ref = _pair(image, reference)
    if ref.ndim != 3 or ref.shape[2] != 3:
        raise ShapeError(f"flip_map needs (h, w, 3) images, got {ref.shape}")
    w = _white(ref) if white is None else float(white)
    a = np.clip(ref / w, 0.0, 1.0).astype(np.float32)
    b = np.clip(img / w, 0.0, 1.0).astype(np.float32)
    fmap, _, _ = flip_evaluator.evaluate(a, b, "LDR", inputsRGB=False, applyMagma=False,
                                         computeMeanError=False)
    return np.asarray(fmap, dtype=np.float64).reshape(ref.shape[:2])


def object_errors(image: object, reference: object, mask: object) -> dict[str, float | int]:
    """Errors of `image` against `reference` where the object is (`object_mask`), and FLIP.

    returns {"object_pixels", "psnr_db_object" (peak: the reference's over those pixels),
    "delta_e_mean", "delta_e_p95" (CIE ΔE*ab over those pixels, `difference_map`'s
    exposure), "flip_mean" (over the frame, as FLIP is defined), "flip_mean_object"}; with
    no object pixels the per-object figures are NaN (there is nothing to compare).
    """
    img, ref = _pair(image, reference)
    m = np.asarray(mask, dtype=bool)
    if m.shape != ref.shape[:2]:
        raise ShapeError(f"mask {m.shape} does not match the image {ref.shape[:2]}")
    white = _white(ref)
    fmap = flip_map(img, ref, white)
    out: dict[str, float | int] = {"object_pixels": int(m.sum()),
                                   "flip_mean": float(fmap.mean())}
    if not m.any():
        return {**out, "psnr_db_object": float("nan"), "delta_e_mean": float("nan"),
                "delta_e_p95": float("nan"), "flip_mean_object": float("nan")}
    peak = float(ref[m].max())
    de = difference_map(img, ref, white)[m]
    out.update(psnr_db_object=psnr_db(img[m], ref[m], peak) if peak > 0 else float("nan"),
               delta_e_mean=float(de.mean()), delta_e_p95=float(np.percentile(de, 95)),
               flip_mean_object=float(fmap[m].mean()))
    return out
