"""Laplacian pyramids of BTF images (seed 001, §3.1, Eqs. 2-3).

    F_{k+1} = down(g * F_k)          (Eq. 2)
    L_k     = F_k - up(F_{k+1})      (Eq. 3)

with g the seed's 3 x 3 box filter (or, for comparison, Burt & Adelson's 5-tap binomial
[1, 4, 6, 4, 1] / 16), `down` keeping every other sample (even indices) and `up` nearest
neighbour. Any image size works: a level of size h has a parent of size ceil(h / 2), the filter
clamps at the border (edge replication), and `up` repeats each parent sample twice and crops,
so the collapse F_k = L_k + up(F_{k+1}) inverts Eq. 3 exactly (to one rounding of the dtype).

Arrays are images with the spatial axes first: `(h, w, ...)` with any trailing axes (the BTF
stage passes `(h, w, d)`, one column per direction pair), so one call filters every direction
image at once. The separable filter is applied only at the kept (even) output positions.
Hand-written because no maintained library builds Laplacian pyramids with arbitrary trailing
axes, odd sizes and the seed's box/nearest operators (scikit-image's `pyramid_laplacian`
uses Gaussian filtering and interpolating upsampling, which is a different transform).
"""

from __future__ import annotations

import numpy as np

from texelbake.errors import SettingsError, ShapeError

#: filter name -> (offsets, weights) of the separable 1-D kernel
FILTERS: dict[str, tuple[tuple[int, ...], tuple[float, ...]]] = {
    "box3": ((-1, 0, 1), (1.0 / 3.0, 1.0 / 3.0, 1.0 / 3.0)),
    "gauss5": ((-2, -1, 0, 1, 2), (1 / 16, 4 / 16, 6 / 16, 4 / 16, 1 / 16)),
}


def _kernel(filter_name: str) -> tuple[tuple[int, ...], tuple[float, ...]]:
    if filter_name not in FILTERS:
        raise SettingsError(f"pyramid filter must be one of {sorted(FILTERS)}, got {filter_name!r}")
    return FILTERS[filter_name]


def parent_size(n: int) -> int:
    """Size of the next coarser level along one axis: ceil(n / 2)."""
    return (int(n) + 1) // 2


def level_shapes(h: int, w: int, n_levels: int) -> list[tuple[int, int]]:
    """(h_k, w_k) for k = 0 .. n_levels - 1 (level 0 is the input)."""
    shapes = [(int(h), int(w))]
    for _ in range(n_levels - 1):
        hh, ww = shapes[-1]
        shapes.append((parent_size(hh), parent_size(ww)))
    return shapes


def top_level_for(h: int, w: int, stop_texels: int) -> int:
    """lambda_max: the first level whose texel count is <= `stop_texels` (or is 1 x 1).

    The seed stops "when the number of Laplacian BRDFs is close to n" (§3.2); with
    stop_texels = 2 n and a 64 x 64 BTF, n = 8 this is lambda_max = 4 (a 4 x 4 top), the seed's
    choice.
    """
    if h < 1 or w < 1:
        raise ShapeError(f"image size must be positive, got {(h, w)}")
    k = 0
    while h * w > max(int(stop_texels), 1) and (h > 1 or w > 1):
        h, w = parent_size(h), parent_size(w)
        k += 1
    return k


def _reduce_axis(img: np.ndarray, axis: int, offsets, weights) -> np.ndarray:
    n = img.shape[axis]
    keep = 2 * np.arange(parent_size(n))  # (n1,)
    terms = []
    for off, wt in zip(offsets, weights, strict=True):
        term = np.take(img, np.clip(keep + off, 0, n - 1), axis=axis)  # a copy
        term *= img.dtype.type(wt)
        terms.append(term)
    out = terms[0]
    for term in terms[1:]:
        out += term
    return out


def reduce(img: np.ndarray, filter_name: str = "box3") -> np.ndarray:
    """Eq. 2: filter with g and keep even samples.

    img : (h, w, ...) float32|float64 -> (ceil(h/2), ceil(w/2), ...) same dtype
    """
    img = np.asarray(img)
    if img.ndim < 2:
        raise ShapeError(f"image must be (h, w, ...), got shape {img.shape}")
    offsets, weights = _kernel(filter_name)
    out = _reduce_axis(img, 0, offsets, weights)
    return _reduce_axis(out, 1, offsets, weights)


def expand(img: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Nearest-neighbour upsampling (the seed's `up`): out[i, j] = img[i // 2, j // 2].

    img : (h1, w1, ...) -> (h, w, ...) with ceil(h / 2) == h1 and ceil(w / 2) == w1
    """
    img = np.asarray(img)
    h, w = int(shape[0]), int(shape[1])
    if parent_size(h) != img.shape[0] or parent_size(w) != img.shape[1]:
        raise ShapeError(
            f"cannot expand {img.shape[:2]} to {(h, w)}: expected parent "
            f"{(parent_size(h), parent_size(w))}"
        )
    rows = np.arange(h) // 2
    cols = np.arange(w) // 2
    return img[rows][:, cols]


def build_pyramid(
    img: np.ndarray, top_level: int, filter_name: str = "box3", *, overwrite: bool = False
) -> list[np.ndarray]:
    """Laplacian pyramid [L_0, ..., L_{top-1}, F_top] (Eqs. 2-3).

    img : (h, w, ...) float32|float64; with `overwrite=True` level 0 is computed in place in
        `img` (saves one full-size copy for the 64 x 64 x 6561 BTF)
    top_level : lambda_max >= 0; 0 returns [img] (a single top level)
    returns : list of top_level + 1 arrays, level k of shape (h_k, w_k, ...), same dtype
    """
    img = np.asarray(img)
    if img.ndim < 2:
        raise ShapeError(f"image must be (h, w, ...), got shape {img.shape}")
    if top_level < 0:
        raise SettingsError(f"top_level must be >= 0, got {top_level}")
    if not np.issubdtype(img.dtype, np.floating):
        img = img.astype(np.float64)
        overwrite = True
    current = img if overwrite else img.copy()
    levels: list[np.ndarray] = []
    for _ in range(top_level):
        parent = reduce(current, filter_name)
        current -= expand(parent, current.shape[:2])  # Eq. 3, in place
        levels.append(current)
        current = parent
    levels.append(current)
    return levels


def collapse(levels: list[np.ndarray], start: int = 0) -> np.ndarray:
    """Invert `build_pyramid`: F_start = L_start + up(L_{start+1} + up(... F_top)).

    levels : as returned by `build_pyramid`; start : level to stop at (0 = full resolution)
    returns : (h_start, w_start, ...) array
    """
    if not levels:
        raise ShapeError("cannot collapse an empty pyramid")
    out = np.array(levels[-1], copy=True)
    for lap in reversed(levels[start:-1]):
        out = lap + expand(out, lap.shape[:2])
    return out
