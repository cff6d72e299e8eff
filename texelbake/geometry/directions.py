"""Direction sets on the texel-frame upper hemisphere (seed 000, §3.2 and §4.1).

The characteristic-point matrix R is tabulated on d direction pairs (seed 000, Eq. 9). texelbake
uses a *product grid*: N_i light directions x N_o view directions, both drawn from the same
low-discrepancy hemisphere set (with different seeds), so visibility costs m * (N_i + N_o) rays
instead of 2 * m * d (DESIGN.md "Characteristic points"). A separate, independently drawn set of
pairs measures how the fit generalizes to directions that were not sampled.

Directions are unit vectors in the texel frame (t, b, n): +z is the texel normal.

Sampling choice: *uniform in solid angle* (cos(theta) uniform on (0, 1], phi uniform), as the seed
does ("a dense sampling of incident and view directions"). A cosine-weighted set would
under-sample the grazing directions, exactly where shadowing and masking of the fine geometry
matter most, so it is not used.
"""

from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial import cKDTree
from scipy.stats import qmc

from texelbake.errors import SettingsError

# Fixed stream tags, so that the light grid, the view grid and the held-out pairs are three
# independent sequences even when the caller passes the same seed to each.
_TAG_HELDOUT = 0x4E1D
_TAG_BALANCED = 0xBA1A
_TAG_CELLS = 0xCE11
#: dense points drawn per (cell x draw) to find k uniform points in each direction's cell
_CELL_OVERSAMPLE = 4


def _check_count(name: str, n: int) -> int:
    n_int = int(n)
    if n_int != n or n_int < 0:
        raise SettingsError(f"{name} must be a non-negative integer, got {n!r}")
    return n_int


def _uniform_hemisphere(u: np.ndarray) -> np.ndarray:
    """Map (n, 2) points of the unit square to (n, 3) unit vectors, uniform in solid angle.

    u[:, 0] -> cos(theta) (uniform in solid angle because d omega = d cos(theta) d phi),
    u[:, 1] -> phi / (2 pi). cos(theta) = 1 - u0 lies in (0, 1] for u0 in [0, 1).
    """
    cos_t = 1.0 - u[:, 0]
    sin_t = np.sqrt(np.clip(1.0 - cos_t * cos_t, 0.0, None))
    phi = 2.0 * np.pi * u[:, 1]
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)


def hemisphere_directions(n: int, seed: int = 0) -> np.ndarray:
    """Low-discrepancy directions on the upper hemisphere (z > 0), uniform in solid angle.

    A scrambled Sobol' sequence (scipy.stats.qmc, Owen scrambling seeded by `seed`) in the unit
    square, mapped by (cos theta, phi) = (1 - u0, 2 pi u1). When n is not a power of two the
    first n points of the next power-of-two block are returned (a prefix of a Sobol' sequence
    is still low-discrepancy; scipy's balance warning is about the full block).

    n : number of directions, >= 0
    seed : scrambling seed; equal seeds give byte-identical output
    returns : (n, 3) float64 unit vectors with z in (0, 1]
    """
    n = _check_count("n", n)
    if n == 0:
        return np.zeros((0, 3), dtype=np.float64)
    m = max(int(np.ceil(np.log2(n))), 0)
    sobol = qmc.Sobol(d=2, scramble=True, seed=np.random.default_rng(seed))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        u = sobol.random_base2(m)[:n]  # (n, 2)
    return _uniform_hemisphere(u)


def product_pairs(n_i: int, n_o: int) -> tuple[np.ndarray, np.ndarray]:
    """Row index convention of R on a product grid: row r = i * n_o + o.

    n_i, n_o : numbers of light and view directions
    returns : (row_i (n_i * n_o,) int64, row_o (n_i * n_o,) int64): the light and view direction
        index of every row of R.
    """
    n_i = _check_count("n_i", n_i)
    n_o = _check_count("n_o", n_o)
    row_i = np.repeat(np.arange(n_i, dtype=np.int64), n_o)
    row_o = np.tile(np.arange(n_o, dtype=np.int64), n_i)
    return row_i, row_o


def balanced_pairs(n_i: int, n_o: int, d: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A subset of d rows of the n_i x n_o product grid, every direction used equally often.

    Visibility stays separable (m * (n_i + n_o) rays) but the d rows see n_i light and n_o view
    directions instead of sqrt(d) each: with n_i = n_o = 256 and d = 4096 every direction appears
    16 times. Construction (cyclic, no duplicate pair): with r = d / n_i views per light, light
    pi[a] gets the views po[(a r + k) mod n_o], k < r, for seeded random permutations pi, po;
    a r + k runs over d consecutive integers, so every view appears exactly d / n_o times.
    Rows are sorted by (i, o).

    n_i, n_o : grid sizes; d : number of rows, a multiple of n_i and of n_o, <= n_i * n_o
    returns : (row_i (d,) int64, row_o (d,) int64), index pairs into the two direction sets
    """
    n_i, n_o, d = _check_count("n_i", n_i), _check_count("n_o", n_o), _check_count("d", d)
    if d == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    if n_i == 0 or n_o == 0 or d % n_i or d % n_o or d > n_i * n_o:
        raise SettingsError(
            f"d ({d}) must be a multiple of n_i ({n_i}) and n_o ({n_o}) and <= n_i * n_o"
        )
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _TAG_BALANCED]))
    perm_i, perm_o = rng.permutation(n_i), rng.permutation(n_o)
    r = d // n_i
    a = np.repeat(np.arange(n_i, dtype=np.int64), r)  # (d,)
    k = np.tile(np.arange(r, dtype=np.int64), n_i)  # (d,)
    key = np.sort(perm_i[a] * n_o + perm_o[(a * r + k) % n_o])
    return key // n_o, key % n_o


def cell_directions(dirs: np.ndarray, k: int, seed: int = 0) -> np.ndarray:
    """k directions spread uniformly over each direction's cell: the part of the hemisphere
    nearer to it than to any other direction of `dirs` (chord distance, the cells the BTF's
    nearest-direction look-up reads, `texelbake.btf.lut`).

    A table read at the nearest sampled pair returns the pair's value for every direction in its
    cell; averaging f̄ over the cell's directions instead of taking it at the centre keeps a lobe
    narrower than the cell from being spread over the whole cell (docs/decisions.md). The draws: a scrambled Sobol' set of ~4 k n points uniform in solid angle,
    each given to its nearest direction; a cell keeps its first k points in sequence order (a
    prefix of a Sobol' set stays well spread), cycling through them when it caught fewer, and
    holds its own direction k times when it caught none (a cell smaller than the set's spacing).

    dirs : (n, 3) unit directions with z > 0; k : draws per cell, >= 1
    returns : (k, n, 3) float64 unit vectors, draw-major: [a] is one direction of every cell
    """
    dirs = np.asarray(dirs, dtype=np.float64)
    k = _check_count("k", k)
    if dirs.ndim != 2 or dirs.shape[1] != 3:
        raise SettingsError(f"dirs must be (n, 3), got {dirs.shape}")
    n = dirs.shape[0]
    if k == 0 or n == 0:
        raise SettingsError(f"cell_directions needs k >= 1 and directions, got k={k}, n={n}")
    dense = hemisphere_directions(_CELL_OVERSAMPLE * k * n, seed=seed * 65536 + _TAG_CELLS)
    owner = cKDTree(dirs).query(dense)[1].astype(np.int64)  # (M,) nearest direction
    order = np.argsort(owner, kind="stable")  # per cell, its points in sequence order
    count = np.bincount(owner, minlength=n)
    start = np.r_[0, np.cumsum(count)[:-1]]
    out = np.repeat(dirs[None], k, axis=0)  # empty cells hold their own direction
    has = count > 0
    for a in range(k):  # loop over the k draws (k is small)
        pick = order[start[has] + a % count[has]]
        out[a, has] = dense[pick]
    return out


def heldout_pairs(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Independent random (light, view) pairs for measuring generalization.

    Pseudo-random (numpy PCG64 seeded by (seed, tag)), uniform in solid angle on the upper
    hemisphere, light and view drawn independently: a different sequence from the Sobol' grid,
    so held-out pairs do not coincide with grid pairs.

    n : number of pairs, >= 0
    returns : (wi (n, 3) float64, wo (n, 3) float64) unit vectors with z in (0, 1]
    """
    n = _check_count("n", n)
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), _TAG_HELDOUT]))
    u = rng.random((n, 4))  # (n, 4)
    return _uniform_hemisphere(u[:, 0:2]), _uniform_hemisphere(u[:, 2:4])
