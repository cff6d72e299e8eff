"""The BTF stage's report (seed 001, §4.2, Table 1 and Fig. 6).

* compression ratio: raw BTF bytes (d x h x w x 3 at 8 bits, the seed's accounting, which gives
  its 80,621,568 bytes for 81 x 81 pairs of 64 x 64 texels) over the bytes of the two float32
  maps plus the mean parameters (`BTFMaps.compressed_bytes`); also against a float32 raw BTF.
* per-channel MSE with the seed's averaging: for each direction image, the mean squared YCbCr
  error over its texels; then the average, minimum and maximum over direction images (pairs at
  or below the horizon are not images and are left out). Values are first scaled to [0, 1] as
  8-bit images are: multiplied by `value_scale`, by default 1 / the 99.9th percentile of the
  input's RGB values (the white point of an 8-bit exposure; see `default_value_scale`).
* error against the number of Y components (Fig. 6), with seconds per build, and its plot.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from texelbake.btf.color import CHANNELS
from texelbake.btf.compress import BTFMaps, BTFSettings, build_btf_maps, to_ycbcr_planes
from texelbake.btf.laplacian import top_level_for
from texelbake.btf.lod import reconstruct_channel
from texelbake.btf.phong import above_horizon
from texelbake.errors import ShapeError


def compression_stats(maps: BTFMaps) -> dict[str, float]:
    """Sizes in bytes and ratios of the representation of a d x h x w BTF."""
    h, w = maps.shape
    raw8 = maps.num_pairs * h * w * 3
    comp = maps.compressed_bytes()
    return {
        "raw_bytes_8bit": int(raw8),
        "raw_bytes_float32": int(raw8 * 4),
        "compressed_bytes": int(comp),
        "lut_bytes": int(maps.lut_bytes()),
        "compression_ratio": raw8 / comp,
        "compression_ratio_float32": 4 * raw8 / comp,
    }


def default_value_scale(btf: np.ndarray, texel_mask: np.ndarray | None = None) -> float:
    """1 / the 99.9th percentile of the RGB values (over the masked texels): the white point an
    8-bit capture would be exposed to (a few highlight texels clip, as in a photograph).

    The maximum would let one specular spike (a baked BTF reaches 100x its 99.9th percentile)
    shrink every error by its square. The percentile is taken on a fixed stride of the values
    (deterministic, ~10^6 samples for the 64 x 64 x 6561 BTF). Returns 1 for an all-zero BTF.
    """
    btf = np.asarray(btf)
    vals = btf[:, texel_mask] if texel_mask is not None else btf
    flat = vals.reshape(-1)
    stride = max(1, flat.size // 1_000_000)
    white = float(np.quantile(flat[::stride], 0.999)) if flat.size else 0.0
    if white <= 0:
        white = float(flat.max()) if flat.size else 0.0
    return 1.0 / white if white > 0 else 1.0


def btf_errors(
    btf: np.ndarray,
    maps: BTFMaps,
    *,
    value_scale: float | None = None,
    lod: float = 0.0,
    texel_mask: np.ndarray | None = None,
) -> dict[str, dict[str, float]]:
    """Per-channel MSE of the reconstruction (seed's Table 1 averaging, see module docstring).

    btf : (d, h, w, 3) the input the maps were built from; value_scale : multiplier to [0, 1]
        (default `default_value_scale`: 1 / the 99.9th percentile of the RGB values)
    texel_mask : optional (h, w) bool, the texels that count (e.g. atlas texels with data)
    returns : {"Y": {"avg", "min", "max"}, "Cb": ..., "Cr": ...}
    """
    btf = np.asarray(btf)
    d, h, w, _ = btf.shape
    if (h, w) != maps.shape or d != maps.num_pairs:
        raise ShapeError(f"btf {btf.shape} does not match the maps ({d} pairs of {maps.shape})")
    mask = np.ones((h, w), bool) if texel_mask is None else np.asarray(texel_mask, dtype=bool)
    if mask.shape != (h, w):
        raise ShapeError(f"texel_mask must be {(h, w)}, got {mask.shape}")
    n_tex = int(mask.sum())
    if value_scale is None:
        value_scale = default_value_scale(btf, mask)
    valid = above_horizon(maps.dirs_i.astype(np.float64), maps.dirs_o.astype(np.float64))
    truth = to_ycbcr_planes(btf)  # (3, h, w, d)
    out: dict[str, dict[str, float]] = {}
    for c, name in enumerate(CHANNELS):
        diff = reconstruct_channel(maps, c, lod)  # (h, w, d)
        diff -= truth[c]
        diff = diff[mask] if n_tex < h * w else diff.reshape(h * w, -1)  # (n_tex, d)
        sq = np.einsum("td,td->d", diff, diff, dtype=np.float64)
        per_image = sq / max(n_tex, 1)
        per_image = per_image[valid] * value_scale**2
        if per_image.size == 0:
            out[name] = {"avg": 0.0, "min": 0.0, "max": 0.0}
        else:
            out[name] = {"avg": float(per_image.mean()), "min": float(per_image.min()),
                         "max": float(per_image.max())}
    return out


def btf_report(
    btf: np.ndarray,
    dirs_i: np.ndarray,
    dirs_o: np.ndarray,
    settings: BTFSettings | None = None,
    *,
    value_scale: float | None = None,
    texel_mask: np.ndarray | None = None,
) -> tuple[BTFMaps, dict]:
    """Build the maps and measure them: compression, MSE per channel, seconds per stage.
    texel_mask : optional (h, w) bool texels counted in the errors (see `btf_errors`)

    returns : (maps, report dict with compression_ratio, mse {Y, Cb, Cr: {avg, min, max}},
        seconds {stage: s, total: s}, cpu_seconds, top_level, pca_methods, mean_models, notes)
    """
    settings = settings or BTFSettings()
    t0, c0 = time.perf_counter(), time.process_time()
    maps, info = build_btf_maps(btf, dirs_i, dirs_o, settings)
    build_s, build_cpu = time.perf_counter() - t0, time.process_time() - c0
    t0 = time.perf_counter()
    mse = btf_errors(btf, maps, value_scale=value_scale, texel_mask=texel_mask)
    err_s = time.perf_counter() - t0
    report = {
        **compression_stats(maps),
        "mse": mse,
        "seconds": {**{k: float(v) for k, v in info.seconds.items()}, "build_total": build_s,
                    "error_measurement": err_s},
        "cpu_seconds_build": build_cpu,
        "cpu_seconds": {k: float(v) for k, v in info.cpu_seconds.items()},
        "top_level": maps.top_level,
        "n_components": list(maps.n_components),
        "pca_methods": list(info.pca_methods),
        "mean_models": list(maps.mean_models),
        "phong_params": maps.mean_params[0].tolist(),
        "fit_message": info.fit_message,
        "notes": list(info.notes),
    }
    return maps, report


def error_vs_components(
    btf: np.ndarray,
    dirs_i: np.ndarray,
    dirs_o: np.ndarray,
    n_values: Sequence[int] = (2, 4, 8, 16),
    settings: BTFSettings | None = None,
    *,
    value_scale: float | None = None,
    texel_mask: np.ndarray | None = None,
) -> list[dict]:
    """The seed's Fig. 6: Y error against the number of Y components, each a full build.

    The pyramid depth is fixed to the one `settings` gives, so only n varies.
    returns : one dict per n: n, seconds (build), cpu_seconds, mse (per channel), ratio
    """
    settings = settings or BTFSettings()
    d, h, w, _ = np.asarray(btf).shape
    top = settings.top_level
    if top is None:
        top = top_level_for(h, w, int(np.ceil(settings.stop_factor * max(settings.n_components))))
    rows = []
    for n in n_values:  # a handful of builds
        s = replace(settings, n_components=(int(n), *settings.n_components[1:]), top_level=top)
        t0, c0 = time.perf_counter(), time.process_time()
        maps, _ = build_btf_maps(btf, dirs_i, dirs_o, s)
        secs, cpu = time.perf_counter() - t0, time.process_time() - c0
        mse = btf_errors(btf, maps, value_scale=value_scale, texel_mask=texel_mask)
        rows.append({"n": int(n), "seconds": secs, "cpu_seconds": cpu, "mse": mse,
                     "compression_ratio": compression_stats(maps)["compression_ratio"]})
        del maps
    return rows


def plot_error_vs_components(rows: Sequence[dict], path: str | Path, title: str = "") -> Path:
    """Fig. 6-style plot: Y MSE (avg with min-max band) and build seconds against n."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    n = [r["n"] for r in rows]
    avg = [r["mse"]["Y"]["avg"] for r in rows]
    lo = [r["mse"]["Y"]["min"] for r in rows]
    hi = [r["mse"]["Y"]["max"] for r in rows]
    fig, ax = plt.subplots(figsize=(5, 3.5), dpi=100)
    ax.plot(n, avg, "o-", label="Y MSE (avg over images)")
    ax.fill_between(n, lo, hi, alpha=0.25, label="min-max over images")
    ax.set_xlabel("principal components (Y)")
    ax.set_ylabel("MSE (values in [0, 1])")
    ax.set_yscale("log")
    ax2 = ax.twinx()
    ax2.plot(n, [r["seconds"] for r in rows], "s--", color="tab:red", label="build seconds")
    ax2.set_ylabel("build seconds")
    ax.set_title(title or "BTF error against the number of components")
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={"Software": None})
    plt.close(fig)
    return path
