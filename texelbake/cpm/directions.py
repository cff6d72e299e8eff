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
from scipy.stats import qmc

from texelbake.errors import SettingsError

# Fixed stream tags, so that the light grid, the view grid and the held-out pairs are three
# independent sequences even when the caller passes the same seed to each.
_TAG_HELDOUT = 0x4E1D
_TAG_BALANCED = 0xBA1A


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
