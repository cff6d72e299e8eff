"""The a_vis table compressed a chunk of texels at a time (issue 15 item 5,
`texelbake.cpm.avis.compress`): against the exact in-memory rules it replaced (the budget's
bisection `haar.budget_mask`, the correction's bisection `table.sum_correction`), invariant
to the chunking, read tile after tile by the export like the stacked level, and with a peak
memory that does not grow with the level."""

from __future__ import annotations

import tracemalloc

import numpy as np
import pytest

from tests.helpers.avis_scenes import grid_mesh, periodic_height, sample_faces, texel_of_xy, tile3x3
from texelbake.cpm.avis import AvisLevel, avis_level, compress_level
from texelbake.cpm.avis import compress as cz
from texelbake.cpm.avis.chunk_threads import compress_threads
from texelbake.cpm.avis.closed_form import ClosedForm
from texelbake.cpm.avis.correction import _power_and_scale, apply_correction, sum_correction
from texelbake.cpm.avis.correction_sums import CorrectionTerms
from texelbake.cpm.haar import budget_mask, decompress_haar
from texelbake.errors import SettingsError
from texelbake.geometry.raycast import RayCaster

KEEP = 0.03


@pytest.fixture(scope="module")
def bumpy() -> AvisLevel:
    """A random bumpy height field's finest level: 8 x 8 texels, res 16, every texel ray
    traced with its unoccluded bound (bounded)."""
    pts, faces = grid_mesh(48, periodic_height(0.05, seed=3))
    tp, tf = tile3x3(pts, faces)
    pos, nrm, ar, _ = sample_faces(pts, faces, 2, seed=4)
    return avis_level(pos, nrm, ar, texel_of_xy(pos, 8), 8, 16, RayCaster(tp, tf).occluded, tp,
                      max_terms=1024)


def _frames(level: AvisLevel) -> np.ndarray:
    return np.broadcast_to(np.eye(3), (level.n_side ** 2, 3, 3)).copy()


def _direct_level(n_side: int, res: int) -> AvisLevel:
    """A level of direct (unbounded) ray texels only, whose maps a reader makes on demand."""
    n = n_side * n_side
    return AvisLevel(n_side, res, np.zeros(n, bool), np.zeros(n, bool),
                     ClosedForm(np.zeros(n + 1, np.int64), np.zeros((0, 3)), np.zeros(0)),
                     np.arange(n, dtype=np.int64), np.zeros((0, 6, res, res)), np.ones(n))


def _maps(rows: np.ndarray, res: int) -> np.ndarray:
    """Smooth positive maps, a function of the texel id only (any chunking reads the same)."""
    t = rows[:, None, None, None].astype(np.float64)
    f = np.arange(6)[None, :, None, None]
    y, x = np.meshgrid(np.arange(res), np.arange(res), indexing="ij")
    return 1.0 + np.sin(0.3 * t + f + 0.4 * x[None, None] + 0.1 * t * y[None, None] / res) ** 2


def test_budget_within_a_grid_step_of_the_exact_bisection(bumpy):
    """The grid's tau keeps at most the budget, and every texel's dropped share is within one
    grid step (1.4 %) of the exact bisection's largest (`haar.budget_mask`, the rule before)."""
    src = cz.chunks_of(bumpy, 10 ** 6)
    c = cz._chunk(src, 0)
    _, share, _, tail, nonzero = cz._shares(c)
    r = bumpy.ray_texels.shape[0]
    budget = max(r, int(np.ceil(KEEP * r * 6 * bumpy.res ** 2)))
    exact = budget_mask(share, budget)
    tau = cz._level_tau(cz.chunks_of(bumpy, 7), KEEP)
    kept = np.clip((tail > tau).sum(axis=1), 1, np.maximum(nonzero, 1))
    dropped = np.take_along_axis(np.concatenate([tail, np.zeros((r, 1))], axis=1),
                                 kept[:, None], axis=1)[:, 0]
    dropped_exact = np.sum(np.where(exact, 0.0, share), axis=1)
    step = cz.TAU_GRID[1] / cz.TAU_GRID[0]
    assert kept.sum() <= budget
    assert kept.sum() >= 0.98 * exact.sum()
    assert dropped.max() <= step * dropped_exact.max() * (1 + 1e-12)
    assert np.all(dropped <= tau)


def test_sum_correction_as_good_as_the_bisection(bumpy):
    """The streamed correction restores the level's total at every cube pixel as well as the
    exact bisection does on the same reconstruction (both stored as float16)."""
    table = compress_level(bumpy, _frames(bumpy), KEEP)
    c = cz._chunk(cz.chunks_of(bumpy, 10 ** 6), 0)
    assert c.bounded.all()
    approx = np.clip(decompress_haar(table.haar), 0.0, 1.0)
    target = np.sum(c.unocc * c.stored, axis=0)
    exact = sum_correction(c.stored, approx, c.unocc, bounded=True).astype(np.float16)

    def total(g):
        fixed = apply_correction(approx, np.broadcast_to(g.astype(np.float64), approx.shape),
                                 bounded=True)
        return np.sum(c.unocc * fixed, axis=0)

    scale = np.abs(target).max()
    err_stream = np.abs(total(table.correction[0]) - target).max() / scale
    err_exact = np.abs(total(exact) - target).max() / scale
    plain = np.abs(np.sum(c.unocc * approx, axis=0) - target).max() / scale
    assert plain > 1e-3  # the correction has work to do here
    assert err_stream <= max(2.0 * err_exact, 2e-4)
    # (the parameters themselves may differ by several float16 steps where the total barely
    # depends on them: F~ near 0 or 1 at every texel of a pixel)


def test_chunking_does_not_change_the_table(bumpy):
    """Rows 1, 5 or all at a time: the same coefficients and scales (the budget is one integer
    histogram) and the same reconstruction to 1e-4 (the correction's float sums run in
    another order: where the total barely depends on c, c itself may move)."""
    tabs = [cz.compress_chunks(cz.chunks_of(bumpy, k), _frames(bumpy), KEEP)[0]
            for k in (1, 5, 10 ** 6)]
    for t in tabs[1:]:
        np.testing.assert_array_equal(t.haar.offsets, tabs[0].haar.offsets)
        np.testing.assert_array_equal(t.haar.indices, tabs[0].haar.indices)
        np.testing.assert_array_equal(t.haar.values, tabs[0].haar.values)
        np.testing.assert_array_equal(t.haar_scale, tabs[0].haar_scale)
        np.testing.assert_allclose(t.ray_texel_maps(), tabs[0].ray_texel_maps(), rtol=1e-4,
                                   atol=1e-6 * np.abs(bumpy.ray_maps).max())


def test_tile_order_reads_like_the_stacked_level():
    """Chunks in another row order (the export's, tile after tile) give a table whose
    look-ups equal the in-order table's, and the same per-texel errors."""
    n_side, res = 6, 8
    lv = _direct_level(n_side, res)
    lv_mem = AvisLevel(n_side, res, lv.closed, lv.bounded, lv.cf, lv.ray_texels,
                       _maps(lv.ray_texels, res), lv.texel_area)
    order = np.random.default_rng(0).permutation(n_side * n_side)
    bounds = np.array([0, 5, 17, 30, 36])
    src = cz.LevelChunks(lv, order, bounds, lambda i: _maps(order[bounds[i]:bounds[i + 1]], res))
    t_perm, e_perm = cz.compress_chunks(src, _frames(lv), 0.1, errors=True)
    t_mem, e_mem = cz.compress_chunks(cz.chunks_of(lv_mem, 4), _frames(lv), 0.1, errors=True)
    rng = np.random.default_rng(1)
    d = rng.normal(size=(400, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    for t in range(n_side * n_side):  # a loop over the level's texels
        a, _ = t_perm.evaluate(np.full(len(d), t), d)
        b, _ = t_mem.evaluate(np.full(len(d), t), d)
        np.testing.assert_allclose(a, b, rtol=2e-3, atol=1e-12)
    np.testing.assert_allclose(e_perm.per_texel, e_mem.per_texel[order], rtol=2e-3)
    assert e_perm.rel_error == pytest.approx(e_mem.rel_error, rel=2e-3)


def test_peak_memory_does_not_grow_with_the_level():
    """Levels of 1,024 and 4,096 texels (12.6 and 50 MB of float64 maps) read 16 rows at a
    time: the traced peak of the larger stays under a quarter of its maps, and grows by under
    15 % of the maps' growth: one chunk's temporaries are fixed, what grows is the table
    itself (3 % of the coefficients, 8 bytes each with its index) and its copy while the
    chunks' parts are joined. The in-memory compression before it held ~12 copies of the
    level (measured on the arm's 64² level 0: 1.1 GB for 92 MB of maps)."""
    res, rows = 16, 16

    def peak(n_side: int) -> tuple[int, int]:
        lv = _direct_level(n_side, res)
        bounds = np.arange(0, n_side * n_side + 1, rows)
        src = cz.LevelChunks(lv, lv.ray_texels, bounds,
                             lambda i: _maps(lv.ray_texels[bounds[i]:bounds[i + 1]], res))
        tracemalloc.start()
        try:
            table, errs = cz.compress_chunks(src, _frames(lv), KEEP, errors=True)
            _, top = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        assert table.haar.kept_fraction <= KEEP
        assert errs.per_texel.shape == (n_side * n_side,)
        return top, n_side * n_side * 6 * res * res * 8

    small, small_bytes = peak(32)
    big, big_bytes = peak(64)
    assert big < big_bytes / 4, (big, big_bytes)
    assert big - small < 0.15 * (big_bytes - small_bytes), (big, small)


def test_correction_terms_sum_like_the_dense_rule(bumpy):
    """The correction's totals from the gathered non-zero terms (`correction_sums.CorrectionTerms`) equal, bit
    for bit, the dense sum over every texel of U F~^exp(g(c)) (`apply_correction`'s bounded
    rule, its scale applied to the sum), at grid values below, at and above the power's cap
    and at a c that varies per pixel; and that rule to rounding. The bumpy field has every
    kind of term: U = 0 below a horizon, F~ = 0, F~ = 1 and between."""
    c = cz._chunk(cz.chunks_of(bumpy, 10 ** 6), 0)
    u = c.unocc[c.bounded]
    a = np.clip(c.stored[c.bounded] + 0.02 * np.sin(np.arange(c.stored[c.bounded].size)
                                                    ).reshape(u.shape), 0.0, 1.0)
    assert np.any(u == 0) and np.any((u > 0) & (a == 0)) and np.any((u > 0) & (a == 1))
    assert np.any((u > 0) & (a > 0) & (a < 1))
    terms = CorrectionTerms(u, a)
    rng = np.random.default_rng(5)
    for cv in (-8.0, -0.5, 0.0, 3.0, 8.0, 12.5, 16.0, rng.uniform(-8, 16, u.shape[1:])):
        cm = np.broadcast_to(cv, u.shape[1:])
        g, scale = _power_and_scale(cm)
        power = np.where(a > 0, np.exp(np.exp(g) * np.log(np.where(a > 0, a, 1.0))), 0.0)
        dense = np.sum(u * power, axis=0) * scale
        got = terms.total(np.array(cm))
        np.testing.assert_array_equal(got, dense)
        np.testing.assert_allclose(got, np.sum(u * apply_correction(a, cm, True), axis=0),
                                   rtol=1e-12, atol=1e-15)


def test_threads_do_not_change_the_table(bumpy, monkeypatch):
    """One thread or three over chunks of 5 rows: the same table and errors, bit for bit
    (each pass reduces its chunks' results in chunk order); a bad thread count is refused."""
    out = []
    for threads in ("1", "3"):
        monkeypatch.setenv("TEXELBAKE_COMPRESS_THREADS", threads)
        assert compress_threads() == int(threads)
        out.append(cz.compress_chunks(cz.chunks_of(bumpy, 5), _frames(bumpy), KEEP,
                                      errors=True))
    (t1, e1), (t3, e3) = out
    for name, arr in t1.to_arrays().items():
        np.testing.assert_array_equal(t3.to_arrays()[name], arr, err_msg=name)
    assert e1 is not None and e3 is not None
    assert e1.rel_error == e3.rel_error
    np.testing.assert_array_equal(e1.per_texel, e3.per_texel)
    for bad in ("0", "two"):
        monkeypatch.setenv("TEXELBAKE_COMPRESS_THREADS", bad)
        with pytest.raises(SettingsError, match="TEXELBAKE_COMPRESS_THREADS"):
            compress_threads()


def test_top_mask_keeps_a_stable_argsorts_first_entries():
    """Which coefficients a count keeps, from the sorted values alone, against the first `cnt`
    of a stable argsort of -share (the order the selection is defined by): rows with many
    ties (shares on a coarse grid, zeros), every count from 1 to n."""
    rng = np.random.default_rng(3)
    k, n = 64, 96
    share = rng.integers(0, 6, (k, n)).astype(np.float64) / 8.0  # ties in every row
    share[:4] = 0.0  # rows of zeros only
    share[4:8] = rng.random((4, n))  # rows without ties
    srt = np.sort(share, axis=1)[:, ::-1]
    order = np.argsort(-share, axis=1, kind="stable")
    for cnt in (np.ones(k, np.int64), np.full(k, n), rng.integers(1, n + 1, k)):
        want = np.zeros((k, n), bool)
        np.put_along_axis(want, order, np.arange(n)[None, :] < cnt[:, None], axis=1)
        got = cz._top_mask(share, srt, cnt)
        assert np.array_equal(got, want)
        assert np.array_equal(got.sum(axis=1), cnt)
