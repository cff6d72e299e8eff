"""The Laplacian BTF level-of-detail representation: build, store in memory, reconstruct
(seed 001, §3.1-3.3).

A BTF here is `btf : (d, h, w, 3)` linear RGB, one image per direction pair, with the pairs'
directions `dirs_i, dirs_o : (d, 3)` in the texel frame (+z the normal). Either the bake's
filtered reflectance f_r(p, wi, wo) of every finest texel on the direction grid, or an imported
measured BTF (`texelbake.btf.measured`).

build_btf_maps:
1. RGB -> YCbCr (§3.1), transposed to one (h, w, d) array per channel, so a texel's BRDF is a
   contiguous row and the pyramid filters every direction image at once.
2. Per channel a Laplacian pyramid L_0 .. L_{top-1}, F_top (Eqs. 2-3), `top` from the stop rule
   (first level with at most `stop_factor * max(n)` texels) unless given.
3. Top-level mean mu(wi, wo) over texels: Phong by Levenberg-Marquardt for Y (Eq. 5), the
   constant average for Cb and Cr (Eq. 6); a rejected Phong fit keeps the tabulated mean.
4. PCA per (level, channel) with n = (8, 2, 2) components (Eq. 4); the three channels of a
   level are one batched torch call. The top level is centred on the *fitted* mean mu' the
   renderer will use, not on the data mean: the PCA then also absorbs the fit residual
   mu - mu' (the seed leaves it as error), and with all components kept the reconstruction is
   exact. Laplacian levels are not centred (mu_k = 0, §3.2).
5. Packing (§3.3): eigen Laplacian BRDFs `eigen : (L, d, C)` and PCA weights per level
   `(h_k, w_k, C)`, C = nY + nCb + nCr channels in that order, float32.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import torch

from texelbake.btf.color import CHANNELS, YCBCR_FROM_RGB
from texelbake.btf.laplacian import FILTERS, build_pyramid, top_level_for
from texelbake.btf.lut import DirectionLUT, build_lut
from texelbake.btf.pca import METHODS, pca_batched
from texelbake.btf.phong import above_horizon, fit_phong, phong_eval
from texelbake.errors import NumericalError, SettingsError, ShapeError
from texelbake.tol import TOL

MEAN_MODELS = ("phong", "constant", "table")
#: storage precision of the two maps -> bytes per value
STORAGE_BYTES = {"float32": 4, "float16": 2}


@dataclass(frozen=True)
class BTFSettings:
    """Settings of the BTF stage.

    n_components : PCA components for (Y, Cb, Cr) at every level (seed: 8, 2, 2)
    top_level : lambda_max; None = stop rule (first level with <= stop_factor * max(n) texels)
    pyramid_filter : "box3" (the seed) | "gauss5" (Burt & Adelson, for comparison)
    pca_method : "auto" | "exact" | "randomized"; pca_oversample, pca_power_iters: randomized
        sketch; pca_exact_max: "auto" solves exactly when min(texels, pairs) <= this
    fit_phong : False keeps the tabulated Y mean (d floats) instead of Eq. 5
    lut_resolution : R of the R x R nearest-direction tables
    storage : "float32" (the seed's 128-bit RGBA textures) | "float16" (half-float maps, what a
        GPU samples natively today: half the bytes; components and weights rounded to half)
    seed : randomized PCA seed
    """

    n_components: tuple[int, int, int] = (8, 2, 2)
    top_level: int | None = None
    stop_factor: float = 2.0
    pyramid_filter: str = "box3"
    pca_method: str = "auto"
    pca_oversample: int = 8
    pca_power_iters: int = 3
    pca_exact_max: int = 512
    fit_phong: bool = True
    lut_resolution: int = 64
    storage: str = "float32"
    seed: int = 0

    def __post_init__(self) -> None:
        n = tuple(int(v) for v in self.n_components)
        if len(n) != 3 or min(n) < 0 or max(n) < 1:
            raise SettingsError(
                f"n_components must be 3 non-negative ints (Y, Cb, Cr), not all 0; got "
                f"{self.n_components!r}"
            )
        object.__setattr__(self, "n_components", n)
        if self.top_level is not None and int(self.top_level) < 0:
            raise SettingsError(f"top_level must be >= 0 or None, got {self.top_level}")
        if not self.stop_factor > 0:
            raise SettingsError(f"stop_factor must be > 0, got {self.stop_factor}")
        if self.pyramid_filter not in FILTERS:
            raise SettingsError(
                f"pyramid_filter must be one of {sorted(FILTERS)}, got {self.pyramid_filter!r}"
            )
        if self.pca_method not in METHODS:
            raise SettingsError(f"pca_method must be one of {METHODS}, got {self.pca_method!r}")
        for name in ("pca_oversample", "pca_power_iters", "pca_exact_max"):
            if int(getattr(self, name)) < 0:
                raise SettingsError(f"{name} must be >= 0, got {getattr(self, name)}")
        if self.storage not in STORAGE_BYTES:
            raise SettingsError(f"storage must be one of {sorted(STORAGE_BYTES)}, got "
                                f"{self.storage!r}")
        if int(self.lut_resolution) < 1:
            raise SettingsError(f"lut_resolution must be >= 1, got {self.lut_resolution}")


@dataclass(frozen=True, eq=False)
class BTFMaps:
    """The packed representation (what the EXR files hold).

    eigen : (L, d, C) float32 eigen Laplacian BRDFs, L = top_level + 1 levels, C channels
        (Y components, then Cb, then Cr)
    weights : L arrays (h_k, w_k, C) float32 PCA weights d_kj(p)
    n_components : (nY, nCb, nCr)
    mean_models : per channel "phong" | "constant" | "table"
    mean_params : (3, 4) float64: (ka, kd, ks, alpha) for "phong", (c, 0, 0, 0) for "constant"
    mean_table : (3, d) float32 tabulated top-level mean, used for "table" rows (else zero)
    dirs_i, dirs_o : (d, 3) float32 directions of the pairs (texel frame)
    lut : DirectionLUT; pyramid_filter : filter used; notes : what happened (fallbacks, ...)
    storage : "float32" | "float16" precision of `eigen` and `weights` in the files (the arrays
        are float32 holding values representable at that precision)
    """

    eigen: np.ndarray
    weights: tuple[np.ndarray, ...]
    n_components: tuple[int, int, int]
    mean_models: tuple[str, str, str]
    mean_params: np.ndarray
    mean_table: np.ndarray
    dirs_i: np.ndarray
    dirs_o: np.ndarray
    lut: DirectionLUT
    pyramid_filter: str = "box3"
    notes: tuple[str, ...] = ()
    storage: str = "float32"

    @property
    def top_level(self) -> int:
        return len(self.weights) - 1

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.weights[0].shape[0]), int(self.weights[0].shape[1])

    @property
    def num_pairs(self) -> int:
        return int(self.eigen.shape[1])

    def channel_slices(self) -> tuple[slice, slice, slice]:
        a, b, _ = self.n_components
        return slice(0, a), slice(a, a + b), slice(a + b, sum(self.n_components))

    def compressed_bytes(self) -> int:
        """Bytes of the two maps at their storage precision plus the float32 mean parameters
        (the seed's §3.3 count; the direction tables are reported separately)."""
        mean = sum(
            {"phong": 4, "constant": 1, "table": self.num_pairs}[m] for m in self.mean_models
        )
        maps = self.eigen.size + sum(w.size for w in self.weights)
        return STORAGE_BYTES[self.storage] * maps + 4 * mean

    def lut_bytes(self) -> int:
        lut = self.lut
        return 4 * (lut.light_table.size + lut.view_table.size + self.dirs_i.size * 2)


@dataclass(frozen=True)
class BuildInfo:
    """seconds : stage -> wall seconds; pca_methods : per level; fit_message : Phong fit message;
    notes : fallbacks and degenerate cases; cpu_seconds : stage -> process CPU seconds (all
    threads; on a shared machine the honest measure of work next to wall time)."""

    seconds: dict[str, float] = field(default_factory=dict)
    pca_methods: tuple[str, ...] = ()
    fit_message: str = ""
    notes: tuple[str, ...] = ()
    cpu_seconds: dict[str, float] = field(default_factory=dict)


def direction_step(wi: np.ndarray, wo: np.ndarray) -> float | None:
    """The sampling's step: the median angle (radians) between a sampled direction and its
    nearest neighbour, light and view directions alike, the larger; None for single directions.

    wi, wo : (d, 3) float64 unit"""
    steps = []
    for dirs in (wi, wo):
        u = np.unique(np.round(np.asarray(dirs, dtype=np.float64), 9), axis=0)
        if u.shape[0] < 2:
            continue
        cos = np.clip(u @ u.T, -1.0, 1.0)
        np.fill_diagonal(cos, -1.0)
        steps.append(float(np.median(np.arccos(cos.max(axis=1)))))
    return max(steps) if steps else None


def resolvable_alpha(wi: np.ndarray, wo: np.ndarray) -> float:
    """The sharpest Phong exponent the direction sampling can see: a lobe (N·H)^alpha still at
    half height half a sampling step from its peak, (cos(δ/2))^alpha = 1/2, with δ the
    `direction_step`. A fit wanting a sharper lobe is chasing a few spiking pairs; evaluated
    between the pairs (the renderer's look-ups) it would invent highlights hundreds of times
    the data (measured on the bolt: alpha 4122 on a ~20 degree grid, btf image 13x too
    bright), so `fit_phong` falls back to the tabulated mean instead.

    wi, wo : (d, 3) float64 unit; returns float (TOL.phong_alpha_max for a single direction)"""
    step = direction_step(wi, wo)
    if step is None:
        return float(TOL.phong_alpha_max)
    half = 0.5 * step
    return float(min(TOL.phong_alpha_max, np.log(0.5) / np.log(np.cos(half))))


def mean_on_pairs(
    models, params: np.ndarray, table: np.ndarray, wi: np.ndarray, wo: np.ndarray,
    cols: np.ndarray | None = None, col_weights: np.ndarray | None = None,
) -> np.ndarray:
    """Top-level mean mu' (Eqs. 5-6) of the three channels at direction pairs.

    wi, wo : (n, 3) float64; for "table" channels, `cols`/`col_weights` (n, m) select and blend
        table columns (default: the pairs are the table's own columns, n == d)
    returns : (n, 3) float64, zero where a direction is at or below the horizon
    """
    wi = np.asarray(wi, dtype=np.float64)
    wo = np.asarray(wo, dtype=np.float64)
    valid = above_horizon(wi, wo)
    out = np.zeros((wi.shape[0], 3))
    for c, model in enumerate(models):
        if model == "phong":
            out[:, c] = phong_eval(params[c], wi, wo)
        elif model == "constant":
            out[:, c] = np.where(valid, params[c, 0], 0.0)
        else:
            tab = np.asarray(table[c], dtype=np.float64)
            if cols is None:
                vals = tab
            else:
                vals = np.sum(tab[cols] * col_weights, axis=1)
            out[:, c] = np.where(valid, vals, 0.0)
    return out


def _check_btf(btf: np.ndarray, dirs_i: np.ndarray, dirs_o: np.ndarray):
    btf = np.asarray(btf)
    if btf.ndim != 4 or btf.shape[3] != 3:
        raise ShapeError(f"btf must be (d, h, w, 3), got shape {btf.shape}")
    if btf.shape[0] == 0 or btf.shape[1] == 0 or btf.shape[2] == 0:
        raise ShapeError(f"btf must have at least one pair and one texel, got shape {btf.shape}")
    if btf.dtype not in (np.float32, np.float64):
        btf = btf.astype(np.float32)
    dirs_i = np.asarray(dirs_i, dtype=np.float64)
    dirs_o = np.asarray(dirs_o, dtype=np.float64)
    d = btf.shape[0]
    if dirs_i.shape != (d, 3) or dirs_o.shape != (d, 3):
        raise ShapeError(
            f"dirs_i and dirs_o must be ({d}, 3) to match btf, got {dirs_i.shape} and "
            f"{dirs_o.shape}"
        )
    for name, arr in (("btf", btf), ("dirs_i", dirs_i), ("dirs_o", dirs_o)):
        if not np.isfinite(arr).all():
            raise NumericalError(f"{name} contains NaN or Inf (expected finite values)")
    norms = np.linalg.norm(np.concatenate([dirs_i, dirs_o]), axis=1)
    if np.any(np.abs(norms - 1.0) > 1e-4):
        raise ShapeError(
            f"dirs_i/dirs_o must be unit vectors, found norms in [{norms.min():.6g}, "
            f"{norms.max():.6g}]"
        )
    return btf, dirs_i, dirs_o


def to_ycbcr_planes(btf: np.ndarray) -> np.ndarray:
    """(d, h, w, 3) RGB -> (3, h, w, d) YCbCr, same float dtype (texel-major per channel).

    One blocked, threaded transpose (torch) of the whole array to (texel, rgb, d), then three
    contiguous multiply-adds per channel: measured 0.5 s CPU for the 64 x 64 x 6561 BTF against
    1.4-2.3 s for per-channel weighted sums followed by per-channel transposes. Costs one
    transient input-sized buffer.
    """
    d, h, w, _ = btf.shape
    out = np.empty((3, h, w, d), dtype=btf.dtype)
    src = torch.from_numpy(np.ascontiguousarray(btf)).reshape(d, h * w * 3)
    dst = torch.from_numpy(out).reshape(3, h * w, d)
    m = YCBCR_FROM_RGB
    with torch.no_grad():
        texel_rgb = src.T.contiguous().reshape(h * w, 3, d)
        for c in range(3):
            torch.mul(texel_rgb[:, 0], float(m[c, 0]), out=dst[c])
            dst[c].add_(texel_rgb[:, 1], alpha=float(m[c, 1]))
            dst[c].add_(texel_rgb[:, 2], alpha=float(m[c, 2]))
    return out


def build_btf_maps(
    btf: np.ndarray,
    dirs_i: np.ndarray,
    dirs_o: np.ndarray,
    settings: BTFSettings | None = None,
) -> tuple[BTFMaps, BuildInfo]:
    """Build the Laplacian BTF LOD representation (see module docstring).

    btf : (d, h, w, 3) float32|float64 linear RGB; dirs_i, dirs_o : (d, 3) unit, texel frame
    returns : (BTFMaps, BuildInfo)
    """
    settings = settings or BTFSettings()
    seconds: dict[str, float] = {}
    cpu: dict[str, float] = {}
    t0, c0 = time.perf_counter(), time.process_time()
    btf, dirs_i, dirs_o = _check_btf(btf, dirs_i, dirs_o)
    d, h, w, _ = btf.shape
    # Directions are stored as float32; every computation uses the stored values so the maps
    # read back from disk reproduce the build exactly.
    di32 = dirs_i.astype(np.float32)
    do32 = dirs_o.astype(np.float32)
    wi, wo = di32.astype(np.float64), do32.astype(np.float64)
    lut = build_lut(wi, wo, settings.lut_resolution)
    valid = above_horizon(wi, wo)  # (d,)
    notes: list[str] = []
    if not valid.all():
        notes.append(f"{int((~valid).sum())} of {d} direction pairs at or below the horizon: "
                     "excluded from the mean fit, mean defined as 0 there")
    seconds["validate"] = time.perf_counter() - t0
    cpu["validate"] = time.process_time() - c0

    t0, c0 = time.perf_counter(), time.process_time()
    planes = to_ycbcr_planes(btf)  # (3, h, w, d)
    seconds["ycbcr"] = time.perf_counter() - t0
    cpu["ycbcr"] = time.process_time() - c0

    t0, c0 = time.perf_counter(), time.process_time()
    n_max = max(settings.n_components)
    top = (
        int(settings.top_level)
        if settings.top_level is not None
        else top_level_for(h, w, int(np.ceil(settings.stop_factor * n_max)))
    )
    per_channel = [
        build_pyramid(planes[c], top, settings.pyramid_filter, overwrite=True) for c in range(3)
    ]
    # level 0 lives in `planes` (overwritten in place); coarser levels are stacked per level
    levels = [planes] + [np.stack([per_channel[c][k] for c in range(3)]) for k in range(1, top + 1)]
    del per_channel
    seconds["pyramid"] = time.perf_counter() - t0
    cpu["pyramid"] = time.process_time() - c0

    t0, c0 = time.perf_counter(), time.process_time()
    x_top = levels[top]  # (3, h_top, w_top, d)
    mu = x_top.reshape(3, -1, d).mean(axis=1, dtype=np.float64)  # (3, d)
    models = ["phong", "constant", "constant"]
    params = np.zeros((3, 4))
    table = np.zeros((3, d), np.float32)
    fit_message = ""
    if settings.fit_phong:
        fit = fit_phong(mu[0], wi, wo, alpha_max=resolvable_alpha(wi, wo))
        fit_message = fit.message
        if fit.model == "phong":
            params[0] = fit.params
        else:
            models[0] = "table"
            notes.append(f"Y top-level mean: {fit.message}")
    else:
        models[0] = "table"
        fit_message = "Phong fit disabled: kept the tabulated mean"
    for c in (1, 2):
        params[c, 0] = float(mu[c][valid].mean()) if valid.any() else 0.0
    table[0] = mu[0].astype(np.float32) if models[0] == "table" else 0.0
    mean_grid = mean_on_pairs(models, params, table, wi, wo)  # (3, d) after .T
    x_top -= mean_grid.T[:, None, None, :].astype(x_top.dtype)
    seconds["mean_fit"] = time.perf_counter() - t0
    cpu["mean_fit"] = time.process_time() - c0

    t0, c0 = time.perf_counter(), time.process_time()
    n_tot = sum(settings.n_components)
    eigen = np.zeros((top + 1, d, n_tot), np.float32)
    weights: list[np.ndarray] = []
    methods: list[str] = []
    offsets = np.cumsum([0, *settings.n_components])
    for k, lev in enumerate(levels):
        _, hk, wk, _ = lev.shape
        res = pca_batched(
            lev.reshape(3, hk * wk, d),
            settings.n_components,
            method=settings.pca_method,
            oversample=settings.pca_oversample,
            power_iters=settings.pca_power_iters,
            exact_max=settings.pca_exact_max,
            seed=settings.seed + k,
            store_dtype=settings.storage,
        )
        methods.append(res.method)
        wmap = np.zeros((hk, wk, n_tot), np.float32)
        for c in range(3):
            nc = settings.n_components[c]
            sl = slice(offsets[c], offsets[c + 1])
            eigen[k, :, sl] = res.components[c, :nc].T
            wmap[:, :, sl] = res.weights[c, :, :nc].reshape(hk, wk, nc)
            if res.n_effective[c] < nc:
                notes.append(
                    f"level {k} {CHANNELS[c]}: {res.n_effective[c]} of {nc} components "
                    f"non-zero ({hk * wk} texels, rank-deficient or constant)"
                )
        weights.append(wmap)
    storage = settings.storage
    if storage == "float16":
        peak = max(float(np.abs(w).max()) for w in weights)
        if peak > float(np.finfo(np.float16).max):
            storage = "float32"  # components are half-rounded, weights stay exact float32
            notes.append(f"weights reach {peak:.4g} > float16 max: weight map kept as float32 "
                         "(storage float32)")
        else:
            weights = [w.astype(np.float16).astype(np.float32) for w in weights]
    seconds["pca"] = time.perf_counter() - t0
    cpu["pca"] = time.process_time() - c0
    del levels, planes

    maps = BTFMaps(
        eigen=eigen,
        weights=tuple(weights),
        n_components=settings.n_components,
        mean_models=(models[0], models[1], models[2]),
        mean_params=params,
        mean_table=table,
        dirs_i=di32,
        dirs_o=do32,
        lut=lut,
        pyramid_filter=settings.pyramid_filter,
        notes=tuple(notes),
        storage=storage,
    )
    return maps, BuildInfo(seconds, tuple(methods), fit_message, tuple(notes), cpu)
