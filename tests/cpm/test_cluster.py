"""A fitted finest texel's candidates as groups of its samples (`texelbake.cpm.cluster`,
BakeSettings.level0_candidates = "clustered"): the grouping against a loop over its rule, the
closed forms of a flat texel, the hard cases (a steep sample, a single sample, two
materials, a texture, a shadowed texel), the groups' sum against every sample's on the
held-out pairs, and the fit on them (single-sample groups as the seed's, bit for bit).

The scenes are `test_classify`'s: the unit square z = 0 on a 2 x 2 atlas, 16 or 64 samples
per texel on a regular grid, the normals set per case."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from tests.cpm.test_classify import SETTINGS, _grid_samples, _inputs, _ramp, _up, _walled
from texelbake.brdf import evaluate
from texelbake.cpm.classify import open_texels, visibility_patterns
from texelbake.cpm.cluster import (
    CLUSTER_SLOPE,
    POSITION_CELLS,
    RESPONSE_FLOOR,
    RESPONSE_PAIRS,
    RESPONSE_STEP,
    STEEP_COS,
    TIE_DIGITS,
    cluster_candidates,
)
from texelbake.cpm.dense import HELD_KEYS, LevelPass, dense_of, points_on
from texelbake.cpm.level import FitInputs, level_candidates
from texelbake.cpm.level_batched import fit_level_batched
from texelbake.cpm.level_by_need import classes_bounded, fit_level_by_need
from texelbake.cpm.lobe import slope_variance
from texelbake.model import Material

TEXELS = np.arange(4, dtype=np.int64)
GLOSSY = Material("/m/glossy", "preview", {"diffuseColor": (0.2, 0.2, 0.2), "roughness": 0.3})


def _tilted(pos: np.ndarray, deg: float, seed: int = 0) -> np.ndarray:
    """Unit normals about +z, each tilted by up to `deg` degrees in a random direction."""
    rng = np.random.default_rng(seed)
    th = np.radians(deg) * np.sqrt(rng.random(len(pos)))
    ph = 2 * np.pi * rng.random(len(pos))
    return np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=1)


def _clusters(src: FitInputs):
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    return lp, dense, dseg, cluster_candidates(lp, TEXELS, dense, dseg)


def _brute_force(lp: LevelPass, dense: np.ndarray, dseg: np.ndarray) -> list[tuple]:
    """The module's rule sample by sample: (texel, sample, weight, var) per group, sorted."""
    geo = lp.src.geo
    shut = ~open_texels(lp, dense, dseg, np.arange(dense.size), len(TEXELS))
    groups: dict[tuple, list[int]] = {}
    for r in range(dense.size):  # loop over samples: the test's brute force
        t, j = int(dseg[r]), int(dense[r])
        fr = lp.frames[TEXELS[t]]
        key: list = [t, int(geo["sample_mat"][j])]
        steep = False
        for n in (geo["sample_nrm"][j], geo["sample_gnrm"][j]):
            loc = fr @ n
            steep |= loc[2] <= STEEP_COS
            z = max(loc[2], STEEP_COS)
            key += [int(np.floor(loc[0] / z / CLUSTER_SLOPE)),
                    int(np.floor(loc[1] / z / CLUSTER_SLOPE))]
        if shut[t]:
            rows = np.flatnonzero(dseg == t)
            a = geo["sample_area"][dense[rows]]
            cen = (geo["sample_pos"][dense[rows]] * a[:, None]).sum(0) / a.sum()
            cell = np.sqrt(a.sum()) / POSITION_CELLS
            uv = fr[:2] @ (geo["sample_pos"][j] - cen) / cell
            key += [int(np.floor(uv[0])), int(np.floor(uv[1]))]
        m = lp.src.materials[int(geo["sample_mat"][j])]
        for wi, wo in RESPONSE_PAIRS:  # the sample's own response, per pair and channel
            f = evaluate(m, wi[None], wo[None], geo["sample_uv"][j][None])[0]
            key += [int(np.floor(np.log(max(v, RESPONSE_FLOOR)) / np.log1p(RESPONSE_STEP)))
                    for v in f]
        key.append(r if steep else -1)
        groups.setdefault(tuple(key), []).append(r)
    out = []
    for rows in groups.values():
        a = geo["sample_area"][dense[rows]]
        n = geo["sample_nrm"][dense[rows]]
        mean = (n * a[:, None]).sum(0)
        mean /= np.linalg.norm(mean)
        best = max(rows, key=lambda r: (round(float(geo["sample_nrm"][dense[r]] @ mean),
                                              TIE_DIGITS), -dense[r]))
        cos = n @ mean  # the spread about the group's mean normal
        out.append((int(dseg[rows[0]]), int(dense[best]), float(a.sum()),
                    float((a * slope_variance(cos)).sum() / a.sum())))
    return sorted(out)


@pytest.mark.parametrize("shadowed", [False, True])
def test_groups_equal_a_loop_over_the_rule(shadowed):
    """Shading normals tilted up to 12 degrees, two materials (by column, one with an albedo
    texture rising along x), on the open square or beside a wall (then the texels by it are
    grouped by position too): the groups, their points, areas and slope variances equal the
    rule applied sample by sample."""
    pos = _grid_samples(8)
    mat = (pos[:, 0] * 4).astype(np.int64) % 2
    mesh = _walled(0.5, 0.0, 1.0) if shadowed else None
    src = _inputs(pos, _tilted(pos, 12.0),
                  materials=(Material("/m/a", "lambert", {}, {"diffuseColor": _ramp(3)}),
                             Material("/m/b", "lambert", {})),
                  mat=mat, **({"mesh": mesh} if mesh else {}))
    src.geo["sample_gnrm"] = _up(len(pos))  # flat facets, smooth shading normals
    lp, dense, dseg, got = _clusters(src)
    if shadowed:
        assert not open_texels(lp, dense, dseg, np.arange(dense.size), 4).all()
    want = _brute_force(lp, dense, dseg)
    pos_t = np.searchsorted(TEXELS, got.texel)
    have = sorted(zip(pos_t.tolist(), got.sample.tolist(), got.weight[:, 0].tolist(),
                      got.var.tolist(), strict=True))
    assert len(have) == len(want) < dense.size  # grouped, and fewer than the samples
    for h, w in zip(have, want, strict=True):
        assert h[:2] == w[:2]
        np.testing.assert_allclose(h[2:], w[2:], rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(got.weight[:, 0], got.weight[:, 2])


def test_a_shadowed_texel_is_grouped_by_its_visibility_patterns():
    """A wall across texels 0 and 2 (`test_classify`'s): with c_max = 1 their two patterns
    send them to the fit, and the classes' own rays group them: two candidates each, one per
    side of the wall, each of the side's area (8 samples of 1/64), every sample of a group of
    one pattern on every training direction (a second cast, brute force) where the position
    grid alone would make 16 of 16 samples."""
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)), mesh=_walled(100.0, -100.0, 100.0))
    src = dataclasses.replace(src, settings=src.settings.model_copy(update={"c_max": 1}))
    lp = LevelPass.of(src, 0)
    dense, dseg = dense_of(lp, TEXELS)
    cls = classes_bounded(lp, TEXELS, dense, dseg)
    fitted = np.flatnonzero(~(cls.exact | cls.grouped))
    assert fitted.tolist() == [0, 2] and np.all(cls.pattern[np.isin(dseg, fitted)] >= 0)
    rows = np.flatnonzero(np.isin(dseg, fitted))
    seg = np.searchsorted(fitted, dseg[rows])
    got = cluster_candidates(lp, TEXELS[fitted], dense[rows], seg, cls.pattern[rows])
    assert np.bincount(np.searchsorted(TEXELS, got.texel)).tolist() == [2, 0, 2]
    np.testing.assert_allclose(got.weight, 0.125, rtol=1e-12)
    vis, _ = visibility_patterns(lp, TEXELS, dense, dseg, rows)
    for p in got.sample.tolist():  # loop over the four groups: their members' patterns
        side = pos[p, 0] < 0.3
        members = rows[(pos[dense[rows], 0] < 0.3) == side]
        members = members[dseg[members] == dseg[np.flatnonzero(dense == p)[0]]]
        assert (vis[np.searchsorted(rows, members)] == vis[np.searchsorted(rows, members)][0]
                ).all()
    assert len(cluster_candidates(lp, TEXELS[fitted], dense[rows], seg).sample) == 32


def test_a_texture_splits_the_groups_by_its_values():
    """A flat texel of one Lambertian material whose albedo ramps along x: its samples fall
    into several groups (a group per 2 % of albedo), whose points reproduce the sum over
    every sample on the held-out pairs to better than the step (34 dB); the texel's area is
    shared out whole; the same texel untextured is one group."""
    pos = _grid_samples(8)
    tex = Material("/m/tex", "lambert", {}, {"diffuseColor": _ramp(3)})
    src = _inputs(pos, _up(len(pos)), materials=(tex,))
    _, _, _, got = _clusters(src)
    per = np.searchsorted(TEXELS, got.texel)
    assert np.all(np.bincount(per) > 1)
    np.testing.assert_allclose(np.bincount(per, weights=got.weight[:, 0]), 0.25, rtol=1e-12)
    snr, _ = _grouped_snr(src, widen=True)
    assert np.all(snr >= 20 * np.log10(1.0 / RESPONSE_STEP)), snr
    assert len(_clusters(_inputs(pos, _up(len(pos))))[3].sample) == 4


def test_one_normal_is_one_candidate_of_the_texels_area():
    """A flat texel of one material (the open square): one candidate per texel, weight its
    area 1/4 (closed form), no widening (exactly 0), its point the lowest sample id (every
    normal equal: a tie)."""
    pos = _grid_samples()
    src = _inputs(pos, _up(len(pos)))
    _, dense, dseg, got = _clusters(src)
    assert len(got.sample) == 4
    np.testing.assert_allclose(got.weight, 0.25, rtol=1e-12)
    assert np.all(got.var == 0.0)
    first = [int(dense[np.flatnonzero(dseg == t)].min()) for t in range(4)]
    assert got.sample.tolist() == first


def test_steep_samples_and_a_single_sample_stay_apart():
    """A sample more than acos(STEEP_COS) from its texel's frame (a fold) is its own candidate
    whatever its neighbours; a texel of one sample is one candidate of its area."""
    pos = _grid_samples()
    nrm = _up(len(pos))
    t0 = np.flatnonzero((pos[:, 0] < 0.5) & (pos[:, 1] < 0.5))
    steep = np.array([np.sin(np.radians(80)), 0.0, np.cos(np.radians(80))])
    nrm[t0[:3]] = steep  # three samples of one steep normal: three candidates
    keep = np.ones(len(pos), bool)
    t3 = np.flatnonzero((pos[:, 0] > 0.5) & (pos[:, 1] > 0.5))
    keep[t3[1:]] = False  # texel 3 keeps one sample
    src = _inputs(pos[keep], nrm[keep], area=np.full(int(keep.sum()), 0.01))
    src.geo["sample_gnrm"] = _up(int(keep.sum()))  # a steep shading normal on a flat facet
    _, _, _, got = _clusters(src)
    per = np.bincount(got.texel, minlength=4)
    assert per[0] == 4 and per[3] == 1  # 3 steep + the flat rest; the single sample
    assert got.weight[got.texel == 3, 0] == pytest.approx(0.01)


def _sphere(pos: np.ndarray, deg: float) -> np.ndarray:
    """A sphere cap's unit normals over the square: the tilt grows linearly from its centre
    to `deg` degrees at the middle of each edge."""
    k = np.tan(np.radians(deg)) / 0.5
    n = np.stack([-(pos[:, 0] - 0.5) * k, -(pos[:, 1] - 0.5) * k, np.ones(len(pos))], axis=1)
    return n / np.linalg.norm(n, axis=1)[:, None]


def _grouped_snr(src: FitInputs, widen: bool) -> tuple[np.ndarray, int]:
    """Per texel the SNR (dB) of the groups' points (weights their areas, lobes widened by
    their spread when `widen`) against Eq. 7's numerator summed over every sample, on the
    held-out pairs; and the number of groups."""
    lp, dense, dseg, got = _clusters(src)
    every = points_on(lp, TEXELS, dense, dseg,
                      np.repeat(src.geo["sample_area"][dense][:, None], 3, axis=1), None,
                      HELD_KEYS)
    pts = points_on(lp, TEXELS, got.sample, np.searchsorted(TEXELS, got.texel), got.weight,
                    got.var if widen else None, HELD_KEYS)
    err = ((every - pts) ** 2).sum(axis=(1, 2, 3))
    with np.errstate(divide="ignore"):  # +inf: exact
        return 10 * np.log10((every ** 2).sum(axis=(1, 2, 3)) / err), len(got.sample)


@pytest.mark.parametrize("roughness", [0.2, 0.4])
def test_groups_stand_for_every_sample_of_a_curved_glossy_texel(roughness):
    """A glossy sphere cap (normals up to 5 degrees off, 64 samples per texel): the groups'
    points, far fewer than the samples, reproduce the sum over every sample on the held-out
    pairs (directions between the training grid's) to 35 dB or better. With 30 degrees of
    spread the samples are further apart than a cell: every one is its own group, exact (the
    candidates follow the detail)."""
    pos = _grid_samples(8)
    glossy = Material("/m/glossy", "preview", {"diffuseColor": (0.2, 0.2, 0.2),
                                               "roughness": roughness})
    src = _inputs(pos, _sphere(pos, 5.0), materials=(glossy,))
    src.geo["sample_gnrm"] = _up(len(pos))  # flat facets, smooth shading normals
    snr, n_groups = _grouped_snr(src, widen=True)
    assert n_groups <= len(pos) // 8
    assert np.all(snr >= 35.0), snr
    wide = _inputs(pos, _sphere(pos, 30.0), materials=(glossy,))
    wide.geo["sample_gnrm"] = _up(len(pos))
    snr_wide, n_wide = _grouped_snr(wide, widen=True)
    assert n_wide == len(pos) and np.all(snr_wide == np.inf)


def test_a_fitted_texel_chooses_among_its_groups():
    """The level's fit under "clustered": a curved texel is fitted (skip code 0, no texel
    keeps every group as a texel keeps every sample), its points are groups' points with
    their spread as lobe variance, and the held-out SNR is measured for every texel."""
    pos = _grid_samples(8)
    src = _inputs(pos, _sphere(pos, 5.0), materials=(GLOSSY,))
    src.geo["sample_gnrm"] = _up(len(pos))
    s = BakeSettings.model_validate({**SETTINGS.model_dump(),
                                     "level0_candidates": "clustered"})
    sub = FitInputs(s, src.geo, src.caster, src.materials)
    out = fit_level_by_need(sub, 0, TEXELS, level_candidates(sub, 0, TEXELS, None),
                            lambda t, c: fit_level_batched(sub, 0, t, c))
    _, _, _, got = _clusters(src)
    assert np.all(out["skip"] == 0) and np.all(np.isfinite(out["snr_ho"]))
    assert set(out["point_sample"].tolist()) <= set(got.sample.tolist())
    var = dict(zip(got.sample.tolist(), got.var.tolist(), strict=True))
    own = np.array([var[p] for p in out["point_sample"].tolist()])
    assert np.all(out["point_var"] >= own.astype(np.float32) - 1e-7)


def test_a_texel_of_single_sample_groups_is_fitted_as_the_seed():
    """Normals up to 30 degrees apart, 16 samples a texel (more facets than c_max 8: the
    classes send it to the fit): every sample is its own group, so the texel is fitted on
    its samples exactly as under "dense" (the same arrays, bit for bit; a texel of at most
    c_max samples would keep them all, as the seed's path does)."""
    pos = _grid_samples()
    src = _inputs(pos, _sphere(pos, 30.0), materials=(GLOSSY,))
    src.geo["sample_gnrm"] = _up(len(pos))

    def run(mode: str) -> dict:
        s = BakeSettings.model_validate({**SETTINGS.model_dump(), "level0_candidates": mode})
        sub = FitInputs(s, src.geo, src.caster, src.materials)
        return fit_level_by_need(sub, 0, TEXELS, level_candidates(sub, 0, TEXELS, None),
                                 lambda t, c: fit_level_batched(sub, 0, t, c))

    dense, clus = run("dense"), run("clustered")
    assert np.all(clus["skip"] == 0)  # fitted
    assert dense.keys() == clus.keys()
    for k in dense:
        np.testing.assert_array_equal(dense[k], clus[k], err_msg=k)


def test_clustered_needs_lobes_that_carry_the_spread():
    """The setting is refused where a group's widening cannot be stored (narrow lobes, no lobe
    class), on the seed's loop and without classes; left unset there it is 'dense'."""
    for bad in ({"point_lobe": "narrow"}, {"fit_method": "per_texel"},
                {"texel_classes": "points"}):
        with pytest.raises(ValueError, match="level0_candidates"):
            BakeSettings(level0_candidates="clustered", **bad)
        assert BakeSettings(**bad).level0_candidates == "dense"
    assert BakeSettings(point_lobe="narrow", lobe_class="validated",
                        level0_candidates="clustered").level0_candidates == "clustered"
