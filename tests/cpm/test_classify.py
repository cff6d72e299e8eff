"""Texels classed by need (`texelbake.cpm.classify`, `texelbake.cpm.level_by_need`): the exact
class on small hand-built scenes whose truth is known, and each hard case's behaviour.

The scenes: the unit square z = 0 (two coplanar triangles, one chart), a 2 x 2 atlas (texel
(r, c) is the quadrant floor(2y), floor(2x)), 16 samples per texel on a regular grid."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake.brdf.evaluate import diffuse_albedo
from texelbake.cpm.classify import REASONS, _pattern_groups, classify_texels
from texelbake.cpm.dense import LevelPass, dense_of
from texelbake.cpm.level import FitInputs, level_candidates
from texelbake.cpm.level_batched import fit_level_batched
from texelbake.cpm.level_by_need import EXACT_SKIP, GROUPED_SKIP, fit_level_by_need
from texelbake.geometry.basis import tangent_frames
from texelbake.geometry.raycast import RayCaster
from texelbake.model import Material, Texture
from texelbake.tol import TOL

SQUARE = (np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float),
          np.array([[0, 1, 2], [0, 2, 3]]))
LAMBERT = Material("/m/lambert", "lambert", {"diffuseColor": (0.5, 0.3, 0.2)})
SETTINGS = BakeSettings(atlas_resolution=2, shard_texels=2, n_light_dirs=16, n_view_dirs=16,
                        n_heldout=64, c_max=8, n_trials=2, mesh_levels=1)


def _grid_samples(k: int = 4) -> np.ndarray:
    """(4 k^2, 3) sample positions: k x k per quadrant, cell centres."""
    t = (np.arange(2 * k) + 0.5) / (2 * k)
    x, y = np.meshgrid(t, t, indexing="xy")
    return np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], axis=1)


def _inputs(pos: np.ndarray, nrm: np.ndarray, mesh=SQUARE, materials=(LAMBERT,),
            mat: np.ndarray | None = None, area: np.ndarray | None = None) -> FitInputs:
    """FitInputs of samples at `pos` (m, 3) with normals `nrm` (m, 3) (geometric = shading), uv
    = (x, y), on the 2 x 2 atlas; texel frames about +z; a caster over `mesh`."""
    m = len(pos)
    row = np.clip((pos[:, 1] * 2).astype(np.int64), 0, 1)
    col = np.clip((pos[:, 0] * 2).astype(np.int64), 0, 1)
    geo = {
        "sample_pos": pos, "sample_gnrm": nrm, "sample_nrm": nrm.copy(),
        "sample_mat": np.zeros(m, np.int64) if mat is None else mat,
        "sample_uv": pos[:, :2].copy(),
        "sample_area": np.full(m, 1.0 / m) if area is None else area,
        "sample_row": row, "sample_col": col,
        "frames_L0": tangent_frames(np.tile([[0.0, 0.0, 1.0]], (4, 1))),
        "frames_L1": tangent_frames(np.array([[0.0, 0.0, 1.0]])),
    }
    return FitInputs(SETTINGS, geo, RayCaster(*mesh), list(materials))


def _up(m: int) -> np.ndarray:
    return np.tile([[0.0, 0.0, 1.0]], (m, 1))


def _classes(src: FitInputs):
    lp = LevelPass.of(src, 0)
    texels = np.arange(4, dtype=np.int64)
    dense, dseg = dense_of(lp, texels)
    return classify_texels(lp, texels, dense, dseg)


def _by_need(src: FitInputs) -> dict[str, np.ndarray]:
    texels = np.arange(4, dtype=np.int64)
    cands = level_candidates(src, 0, texels, None)
    return fit_level_by_need(src, 0, texels, cands,
                             lambda t, c: fit_level_batched(src, 0, t, c))


def test_flat_square_every_texel_exact_by_the_geometric_bound():
    """One facet (two coplanar triangles: the diagonal is a chart-internal border crossing
    texels 0 and 3), one material, nothing above the plane: every texel is one point of
    weight its area (0.25, closed form), no ray cast (bounded from the geometry), and the
    held-out Eq. 7 measures it exact (>= TOL.exact_fit_db)."""
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)))
    cls = _classes(src)
    assert cls.exact.all() and cls.rays == 0
    np.testing.assert_allclose(cls.weight, 0.25, rtol=1e-12)
    out = _by_need(src)
    assert np.all(out["skip"] == EXACT_SKIP) and np.all(np.diff(out["offsets"]) == 1)
    assert np.all(out["snr_ho"] >= TOL.exact_fit_db)


def test_seam_of_two_facets_is_a_point_per_facet():
    """A texel on a fold (two facets of one chart, normals 30 degrees apart) holds samples of
    both facets: stored as one point per facet, each weighing its half's area (8 samples of
    1/64: 0.125), exact on the held-out pairs (nothing occludes, each facet's samples answer
    alike); the flat texels beside it stay one point. With c_max = 1 the fold is fitted."""
    pos = _grid_samples()
    nrm = _up(len(pos))
    tilt = np.array([np.sin(np.radians(30)), 0.0, np.cos(np.radians(30))])
    # texel 0 (x, y < 0.5): its half x > 0.25 is the second facet
    second = (pos[:, 0] > 0.25) & (pos[:, 0] < 0.5) & (pos[:, 1] < 0.5)
    nrm[second] = tilt
    src = _inputs(pos, nrm)
    cls = _classes(src)
    assert cls.grouped[0] and cls.exact[1:].all()
    assert cls.offsets[1] == 2
    np.testing.assert_allclose(cls.weights[:2], 0.125, rtol=1e-12)
    assert {bool(second[p]) for p in cls.points[:2]} == {True, False}
    out = _by_need(src)
    assert out["skip"][0] == GROUPED_SKIP and np.all(out["snr_ho"] >= TOL.exact_fit_db)
    assert _classes(_with(src, c_max=1)).reason[0] == REASONS["facets"]


def test_thin_sheet_seen_from_both_sides():
    """A two-sided sheet (the square and its back, 1e-4 below): a texel whose samples are one
    side is exact and measures so; a texel holding samples of both sides (opposite normals)
    has a facet black on every check pair (below the texel's horizon), whose factor cannot
    be found: fitted."""
    top, back = SQUARE
    pts = np.concatenate([top, top - [0, 0, 1e-4]])
    faces = np.concatenate([back, back[:, ::-1] + 4])
    pos = _grid_samples()
    nrm = _up(len(pos))
    # texel 3 (x, y > 0.5): every other sample on the back side, facing down
    t3 = np.flatnonzero((pos[:, 0] > 0.5) & (pos[:, 1] > 0.5))[::2]
    pos[t3, 2] = -1e-4
    nrm[t3] = [0.0, 0.0, -1.0]
    src = _inputs(pos, nrm, mesh=(pts, faces))
    cls = _classes(src)
    assert cls.reason[3] == REASONS["inputs"]
    assert cls.exact[:3].all()
    out = _by_need(src)
    ex = out["skip"] == EXACT_SKIP
    assert list(ex) == [True, True, True, False]
    assert np.all(out["snr_ho"][ex] >= TOL.exact_fit_db)


def _walled(height: float, y0: float, y1: float) -> tuple[np.ndarray, np.ndarray]:
    """The square with a wall standing on it at x = 0.3, from y0 to y1, `height` high."""
    p, f = SQUARE
    wall = np.array([[0.3, y0, 0], [0.3, y1, 0], [0.3, y1, height], [0.3, y0, height]], float)
    return np.concatenate([p, wall]), np.concatenate([f, [[4, 5, 6], [4, 6, 7]]])


def _with(src: FitInputs, **update) -> FitInputs:
    return dataclasses.replace(src, settings=src.settings.model_copy(update=update))


def test_partly_shadowed_flat_texel_is_grouped_by_pattern():
    """A wall taller and longer than the scene stands across texels 0 and 2 (x = 0.3): a
    sample left of it sees only directions with x <= 0, one right of it only x >= 0, so those
    texels hold two visibility patterns (found by their own rays) and are stored as two
    points, each its half's sample nearest the half's centroid, weight the half's area (8 of
    the texel's 16 samples of area 1/64: 0.125, closed form); the open texels 1 and 3 stay
    one point. Both halves see exactly their half-spaces on the held-out pairs too, so every
    texel measures exact. With c_max = 1 the two-pattern texels go to the fit."""
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)), mesh=_walled(100.0, -100.0, 100.0))
    cls = _classes(src)
    assert list(cls.grouped) == [True, False, True, False]
    assert list(cls.exact) == [False, True, False, True] and cls.rays > 0
    assert list(np.diff(cls.offsets)) == [2, 1, 2, 1]
    tex = src.geo["sample_row"] * 2 + src.geo["sample_col"]
    for t in (0, 2):
        pts = cls.points[cls.offsets[t]:cls.offsets[t + 1]]
        np.testing.assert_allclose(cls.weights[cls.offsets[t]:cls.offsets[t + 1]], 0.125,
                                   rtol=1e-12)
        for side in (pos[:, 0] < 0.3, pos[:, 0] > 0.3):  # each half: its nearest-centroid
            own = np.flatnonzero(side & (tex == t))
            d = np.linalg.norm(pos[own] - pos[own].mean(axis=0), axis=1)
            assert own[np.argmin(d)] in pts
    out = _by_need(src)
    assert list(out["skip"]) == [GROUPED_SKIP, EXACT_SKIP, GROUPED_SKIP, EXACT_SKIP]
    assert list(out["c"]) == [2, 1, 2, 1]
    assert np.all(out["snr_ho"] >= TOL.exact_fit_db)
    capped = _classes(_with(src, c_max=1))
    assert list(capped.reason) == [REASONS["visibility"], 0, REASONS["visibility"], 0]
    assert not capped.grouped.any()


def test_the_report_counts_each_class():
    """The level's report entry (`assemble._classes`) counts the exact, grouped and fitted
    texels with their mean stored points: the tall wall's scene has two one-point texels and
    two of two points; with c_max = 1 those two are fitted."""
    from texelbake.cpm.assemble import _classes as report_classes

    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)), mesh=_walled(100.0, -100.0, 100.0))
    for c_max, grouped in ((8, 2), (1, 0)):
        out = _by_need(_with(src, c_max=c_max))
        rep = report_classes(out, out["valid"].astype(bool))
        assert (rep["exact"]["texels"], rep["grouped"]["texels"], rep["points"]["texels"]) \
            == (2, grouped, 2 - grouped)
        assert rep["exact"]["points_mean"] == 1.0
        assert rep["grouped"]["points_mean"] == (2.0 if grouped else 0.0)


def test_grouped_texel_matches_the_brute_force_on_the_grid():
    """A short wall (0.4 high) on texel 0 splits texels into many visibility patterns: with
    c_max at least their count each texel stores a point per pattern, and on the training
    grid the points' Eq. 7 is the brute-force sum over the texel's samples (the grouping is
    lossless there, relative residual < 1e-6); with c_max = 8 the texels with more
    patterns are fitted."""
    from texelbake.cpm.dense import held_pass

    pos = _grid_samples()
    src = _with(_inputs(pos, _up(len(pos)), mesh=_walled(0.4, 0.0, 0.5)), c_max=64)
    cls = _classes(src)
    assert cls.grouped.all() and np.all(np.diff(cls.offsets) > 8)
    # the training grid as the "held-out" pairs: Eq. 7 of the samples against the points'
    lp = LevelPass.of(src, 0)
    lp = dataclasses.replace(lp, dirs=lp.dirs | {"held_i": lp.dirs["dirs_i"],
                                                 "held_o": lp.dirs["dirs_o"]})
    texels = np.arange(4, dtype=np.int64)
    dense, dseg = dense_of(lp, texels)
    pseg = np.repeat(np.arange(4), np.diff(cls.offsets))
    at = np.searchsorted(dseg * (len(pos) + 1) + dense, pseg * (len(pos) + 1) + cls.points)
    ref, apx, _ = held_pass(lp, texels, dense, dseg, at, pseg, cls.weights, want_ref=True)
    assert np.abs(ref).max() > 0
    np.testing.assert_allclose(apx, ref, rtol=0, atol=1e-6 * np.abs(ref).max())
    fitted = _classes(_with(src, c_max=8)).reason
    assert np.all(fitted[np.diff(cls.offsets) > 8] == REASONS["visibility"])


def _ramp(channels: int) -> Texture:
    """An 8 x 8 texture rising along x (row 0 the top of the image)."""
    ramp = np.linspace(0.1, 0.9, 8, dtype=np.float32)
    px = np.broadcast_to(ramp[None, :, None], (8, 8, channels)).copy()
    if channels == 3:
        px *= np.array([1.0, 0.7, 0.4], np.float32)
    return Texture("ramp.png", px, source_color_space="raw")


def test_varying_albedo_is_exact_with_the_mean_albedo():
    """A Lambert albedo texture varying inside each texel: f_r is linear in the albedo, so one
    point holds the texel with weight A mean(rho) / rho_ref per channel (closed form from the
    albedo at the samples) and measures exact on the held-out pairs."""
    mat = Material("/m/tex", "lambert", {}, {"diffuseColor": _ramp(3)})
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)), materials=(mat,))
    cls = _classes(src)
    assert cls.exact.all()
    rho = diffuse_albedo(mat, pos[:, :2])  # (m, 3)
    assert np.ptp(rho[:, 0]) > 0.1  # the texture does vary inside a texel
    tex = src.geo["sample_row"] * 2 + src.geo["sample_col"]
    for t in range(4):  # four texels
        own = tex == t
        expect = src.geo["sample_area"][own] @ rho[own] / rho[cls.point[t]]
        np.testing.assert_allclose(cls.weight[t], expect, rtol=1e-6)
    out = _by_need(src)
    assert np.all(out["skip"] == EXACT_SKIP)
    assert np.all(out["snr_ho"] >= TOL.exact_fit_db)


def test_varying_roughness_is_not_exact():
    """A UsdPreviewSurface whose roughness (an input f_r is not linear in) varies inside the
    texels: not one point, so fitted; the same material with a constant roughness is exact."""
    tex = Material("/m/rough", "preview", {"diffuseColor": (0.4, 0.4, 0.4)},
                   {"roughness": _ramp(1)})
    const = Material("/m/const", "preview", {"diffuseColor": (0.4, 0.4, 0.4),
                                             "roughness": 0.3})
    pos = _grid_samples()
    assert np.all(_classes(_inputs(pos, _up(len(pos)), materials=(tex,))).reason
                  == REASONS["inputs"])
    src = _inputs(pos, _up(len(pos)), materials=(const,))
    assert _classes(src).exact.all()
    assert np.all(_by_need(src)["snr_ho"] >= TOL.exact_fit_db)


def test_two_materials_and_a_single_sample():
    """Texel 0 holds two materials: a point per material, each weighing its area (8 samples
    of 1/64); texel 1 holds one sample (exact: that sample, its area); texels 2 and 3 stay
    exact; all measure exact held out; an empty texel is none."""
    red = Material("/m/red", "lambert", {"diffuseColor": (0.8, 0.1, 0.1)})
    pos = _grid_samples()
    in1 = np.flatnonzero((pos[:, 0] > 0.5) & (pos[:, 1] < 0.5))
    keep = np.ones(len(pos), bool)
    keep[in1[1:]] = False  # texel 1 keeps its first sample only
    pos = pos[keep]
    mat = np.zeros(len(pos), np.int64)
    mat[(pos[:, 0] < 0.25) & (pos[:, 1] < 0.5)] = 1
    area = np.full(len(pos), 1.0 / 64)
    src = _inputs(pos, _up(len(pos)), materials=(LAMBERT, red), mat=mat, area=area)
    cls = _classes(src)
    assert cls.grouped[0] and cls.exact[1:].all()
    assert sorted(mat[cls.points[:2]]) == [0, 1]
    np.testing.assert_allclose(cls.weights[:2], 8 / 64, rtol=1e-12)
    one = np.flatnonzero((pos[:, 0] > 0.5) & (pos[:, 1] < 0.5))
    assert cls.point[1] == one[0]
    np.testing.assert_allclose(cls.weight[1], 1.0 / 64)
    out = _by_need(src)
    assert out["skip"][0] == GROUPED_SKIP and np.all(out["skip"][1:] == EXACT_SKIP)
    assert np.all(out["snr_ho"] >= TOL.exact_fit_db)
    empty = _inputs(pos[pos[:, 1] < 0.5], _up(int(np.sum(pos[:, 1] < 0.5))),
                    materials=(LAMBERT, red), mat=mat[pos[:, 1] < 0.5])
    assert np.all(_classes(empty).reason[2:] == REASONS["empty"])


@pytest.mark.parametrize("mode", ["points", "by_need"])
def test_setting_chooses_the_path(mode, tmp_path):
    """`texel_classes="points"` is the seed's fit for every texel (no exact texel stored)."""
    from texelbake.stages.cpm import fit_level

    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)))
    src = dataclasses.replace(src, settings=SETTINGS.model_copy(update={"texel_classes": mode}))
    texels = np.arange(4, dtype=np.int64)
    out = fit_level(src, 0, texels, level_candidates(src, 0, texels, None))
    assert np.any(out["skip"] == EXACT_SKIP) == (mode == "by_need")
    assert out["valid"].all()
    # the report's classes are read where the level says it was classed
    assert ("classed" in out) == (mode == "by_need")

    # the coarse level (the flat square's one texel: one facet, one material, nothing above)
    # is classed while classed_levels holds it, and fitted from its children's points beyond
    one = np.zeros(1, np.int64)
    for classed, stored in ((2, mode == "by_need"), (1, False)):
        src_c = dataclasses.replace(src, settings=src.settings.model_copy(
            update={"classed_levels": classed}))
        coarse = fit_level(src_c, 1, one, level_candidates(src_c, 1, one, out))
        assert bool(np.any(coarse["skip"] == EXACT_SKIP)) == stored, classed
        assert coarse["valid"].all()
        if stored:  # one point of weight the whole square's area
            assert coarse["c"][0] == 1
            assert np.allclose(coarse["point_weight"], 1.0, rtol=1e-6)
            assert coarse["snr_ho"][0] >= TOL.exact_fit_db


def test_a_classed_level_must_lie_inside_the_tiles():
    """A top level is fitted from the tiles' sums without its samples: settings that would class
    one are refused with the fields named; 'points' or a small atlas need no such tile."""
    with pytest.raises(ValueError, match="shard_texels .* classed_levels 3"):
        BakeSettings(atlas_resolution=16, shard_texels=2, classed_levels=3)
    BakeSettings(atlas_resolution=16, shard_texels=4, classed_levels=3)
    BakeSettings(atlas_resolution=16, shard_texels=2, classed_levels=3, texel_classes="points")
    BakeSettings(atlas_resolution=2, shard_texels=2, classed_levels=5)


def test_classes_do_not_depend_on_the_memory_chunks(monkeypatch):
    """`classes_bounded` with one texel per chunk (a huge per-entry size) gives the classes,
    points and weights of one chunk (the whole scene: two texels split by a wall, an exact
    one and a folded one)."""
    from texelbake.cpm import level_by_need

    pos = _grid_samples()
    nrm = _up(len(pos))
    nrm[(pos[:, 0] > 0.75) & (pos[:, 1] > 0.5)] = [0.0, np.sin(0.3), np.cos(0.3)]
    src = _inputs(pos, nrm, mesh=_walled(100.0, -100.0, 100.0))
    lp = LevelPass.of(src, 0)
    texels = np.arange(4, dtype=np.int64)
    dense, dseg = dense_of(lp, texels)
    whole = level_by_need.classes_bounded(lp, texels, dense, dseg)
    monkeypatch.setattr(level_by_need, "BYTES_PER_CLASS_ENTRY", 10**12)
    parts = level_by_need.classes_bounded(lp, texels, dense, dseg)
    for f in dataclasses.fields(whole):
        np.testing.assert_array_equal(getattr(whole, f.name), getattr(parts, f.name))
    assert list(whole.grouped) == [True, False, True, True]
    assert list(whole.exact) == [False, True, False, False]


def test_pattern_groups_number_the_pairs_in_byte_order():
    """A row's (facet, pattern) group is its rank among the distinct pairs in the order of
    their bytes (the facet's big-endian two's complement, then the packed pattern): the same
    numbering as `np.unique(axis=0)` on those bytes, for patterns of 0 to 130 directions
    (padding at every byte boundary), negative facets and no rows."""
    rng = np.random.default_rng(5)
    for n_dirs in (0, 1, 7, 8, 9, 64, 65, 130):
        fac = rng.integers(-3, 5, 3000)
        vis = rng.random((3000, n_dirs)) < 0.9
        vis[rng.random(3000) < 0.3] = True  # many equal patterns
        key = np.concatenate([fac.astype(">i8").view(np.uint8).reshape(-1, 8),
                              np.packbits(vis, axis=1)], axis=1)
        want = np.unique(key, axis=0, return_inverse=True)[1].ravel()
        assert np.array_equal(_pattern_groups(fac, vis), want)
    assert _pattern_groups(np.zeros(0, np.int64), np.zeros((0, 4), bool)).shape == (0,)
