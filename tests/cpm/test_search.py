"""The search on c (`texelbake.cpm.search`), the one both fitting paths use: the bisection on a
trial whose SNR is known in closed form (one dB per distinct column drawn), the cap, the draws
it solves, the batches of a wide selection, and the reduced trial against a direct residual."""

from __future__ import annotations

import math

import numpy as np
import pytest

from texelbake.cpm.column_sampling import fit_weights
from texelbake.cpm.search import reduced_trial, search_c, select_batched
from texelbake.cpm.texel_fit import FitCounts, FitParams, GroupFit


def _size_trial(snr_per_column: float):
    """A trial whose SNR is snr_per_column x the number of distinct columns drawn."""
    def trial(local):
        return np.ones((local.size, 1)), snr_per_column * local.size
    return trial


@pytest.mark.parametrize("eps_db", [3.0, 10.0, 25.0, 200.0])
def test_bisection_stops_at_the_smallest_c_reaching_eps(eps_db):
    """With distinct draws (uniform p over many columns, few repeats) the best draw of c has c
    columns or one fewer: the answer reaches eps_db with at most one column more than the
    smallest that can, or is c_max when eps_db is out of reach."""
    m, k, c_max = 5000, 2, 40
    p = np.full(m, 1.0 / m)
    params = FitParams(eps_db=eps_db, c_max=c_max, n_trials=3)
    counts = FitCounts()
    cols, alpha, capped = search_c(p, k, _size_trial(1.0), np.random.default_rng(0), c_max,
                                   params, counts)
    assert not capped and alpha.shape == (cols.size, 1)
    assert cols.dtype == np.int64 and np.all(np.diff(cols) > 0)
    if eps_db <= c_max:
        assert cols.size >= eps_db
        assert cols.size <= math.ceil(eps_db) + 1  # a repeat may cost one column
    else:
        assert cols.size >= c_max - 1  # eps not reached: c = c_max
    assert counts.probes >= 1 and counts.draws <= 3 * counts.probes


def test_c_max_below_k_caps_without_bisection():
    params = FitParams(c_max=4, n_trials=2)
    counts = FitCounts()
    cols, _, capped = search_c(np.ones(50), 9, _size_trial(1.0), np.random.default_rng(1), 4,
                               params, counts)
    assert capped and 1 <= cols.size <= 4 and counts.probes == 1


def test_a_repeated_draw_is_not_solved_again():
    """One column: every draw is the same, so a probe solves it once whatever n_trials."""
    counts = FitCounts()
    search_c(np.array([1.0]), 1, _size_trial(1.0), np.random.default_rng(2), 1,
             FitParams(n_trials=8, c_max=1), counts)
    assert counts.draws == counts.probes == 1


def test_reduced_trial_equals_the_direct_residual():
    """||A a - t||^2 + rest with A = M, rest = 0 is the direct residual: same weights (NNLS)
    and SNR = signal / noise in dB."""
    rng = np.random.default_rng(3)
    M = rng.random((30, 12))
    t = M @ rng.random(12)
    local = np.array([1, 4, 7])
    alpha, snr = reduced_trial([(M, t, 0.0)], float(t @ t), "nnls")(local)
    a = fit_weights(M[:, local], t, "nnls")
    np.testing.assert_array_equal(alpha[:, 0], a)
    r = M[:, local] @ a - t
    assert snr == pytest.approx(10.0 * math.log10(float(t @ t) / float(r @ r)), rel=1e-12)


def test_select_batched_fits_batches_then_their_pool():
    """Wider than n_batch: every direct selection holds at most n_batch columns, batches get
    c_max capped at n_batch // 2, and the last one selects among the pool for all of cand."""
    calls = []

    def direct(pool, whole, c_max):
        calls.append((pool.size, whole.size, c_max))
        keep = pool[: min(c_max, pool.size)]
        return GroupFit(keep, np.ones((keep.size, 1)), 1, False)

    params = FitParams(n_batch=10, c_max=8)
    got = select_batched(np.arange(35, dtype=np.int64), 8, params, direct)
    assert got is not None and got.cols.size <= 8
    assert all(n <= 10 for n, _, _ in calls)
    assert calls[-1][1] == 35 and calls[-1][2] == 8
    assert all(c == 5 for _, _, c in calls[:-1])
    assert select_batched(np.arange(35, dtype=np.int64), 8, params,
                          lambda pool, whole, c: None) is None
