"""a_vis rays from at most k samples per texel and triangle (`facet_subsample`,
`avis_level(per_facet=k)`) against a brute-force selection, the closed form and the dense
rays."""

import numpy as np
import pytest

from tests.helpers.avis_scenes import (
    grid_mesh,
    periodic_height,
    sample_faces,
    texel_of_latlong,
    texel_of_xy,
    tile3x3,
    uv_sphere,
)
from texelbake.cpm.avis import avis_level, cube_directions, default_eps, unoccluded_samples
from texelbake.cpm.avis.subsample import facet_subsample
from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.raycast import RayCaster
from texelbake.tol import TOL


def _brute(tex, face, area, k, cast):
    """One group at a time: centred, evenly spaced ranks floor((i + 1/2) n / k) in id order,
    carrying the group's area in proportion to their own."""
    out = area.copy()
    live = np.flatnonzero((area > 0) & cast)
    for key in sorted({(int(tex[j]), int(face[j])) for j in live}):  # loop over groups
        ids = np.array([j for j in live if (tex[j], face[j]) == key])  # ascending
        n = len(ids)
        kk = min(n, k)
        ranks = {int(np.floor((i + 0.5) * n / kk)) for i in range(kk)}
        chosen = np.array([r in ranks for r in range(n)])
        scale = area[ids].sum() / area[ids[chosen]].sum()
        out[ids] = np.where(chosen, area[ids] * scale, 0.0)
    return out


@pytest.mark.parametrize("k", [1, 2, 3, 7])
def test_facet_subsample_brute_force(rng, k):
    m = 400
    tex = rng.integers(0, 5, m)
    face = rng.integers(0, 7, m)
    area = rng.random(m) * (rng.random(m) > 0.1)  # some samples on cut-outs (no area)
    cast = rng.random(m) > 0.2
    got = facet_subsample(tex, face, area, k, cast=cast)
    want = _brute(tex, face, area, k, cast)
    assert got.shape == (m,) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=0)
    # each group keeps its area and at most k weighted samples; samples not cast keep theirs
    grp = tex * 7 + face
    live = (area > 0) & cast
    np.testing.assert_allclose(np.bincount(grp[live], got[live], 35),
                               np.bincount(grp[live], area[live], 35), rtol=1e-12)
    assert np.bincount(grp[live & (got > 0)], minlength=35).max() <= k
    assert np.array_equal(got[~cast], area[~cast])


def test_facet_subsample_zero_keeps_all_and_errors(rng):
    tex, face, area = rng.integers(0, 3, 50), rng.integers(0, 3, 50), rng.random(50)
    assert np.array_equal(facet_subsample(tex, face, area, 0), area)
    assert np.array_equal(facet_subsample(tex, face, area, 10_000), area)  # k >= every group
    assert facet_subsample(tex[:0], face[:0], area[:0], 4).shape == (0,)
    with pytest.raises(SettingsError):
        facet_subsample(tex, face, area, -1)
    with pytest.raises(ShapeError):
        facet_subsample(tex, face[:3], area, 2)
    with pytest.raises(ShapeError):
        facet_subsample(tex, face, area, 2, cast=np.ones(3, bool))


def test_per_facet_equals_closed_form_where_unoccluded():
    """A convex sphere: V = 1, so a_vis is sum_k A_k (n_k . w)^+ however few samples cast
    rays (rays forced: closed_form=False)."""
    pts, faces = uv_sphere(8, 16)
    pos, nrm, ar, fid = sample_faces(pts, faces, 4, seed=3)
    tex = texel_of_latlong(pos, 4)
    caster = RayCaster(pts, faces)
    lv = avis_level(pos, nrm, ar, tex, 4, 8, caster.occluded, pts, closed_form=False,
                    faces=fid, per_facet=2)
    cos = nrm @ cube_directions(8).reshape(-1, 3).T  # (m, d)
    want = np.stack([np.bincount(tex, ar * np.where(cos[:, i] > TOL.grazing_cos, cos[:, i], 0),
                                 16) for i in range(cos.shape[1])], axis=1)  # loop over dirs
    got = lv.dense_maps().reshape(16, -1)
    np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-14)


def _field(q=4):
    h = periodic_height(0.05, seed=1)
    pts, faces = grid_mesh(16, h)
    tp, tf = tile3x3(pts, faces)
    pos, nrm, ar, fid = sample_faces(pts, faces, q, seed=2)
    return pos, nrm, ar, fid, texel_of_xy(pos, 2), RayCaster(tp, tf), tp


def test_per_facet_converges_to_the_dense_rays_and_casts_fewer():
    """A bumpy height field (masking varies within triangles): the maps from k samples per
    (texel, triangle) approach the dense ones as k grows, are bit-identical once k covers
    every group, and cast at most k samples' rays per group."""
    pos, nrm, ar, fid, tex, caster, tp = _field()
    eps = TOL.ray_offset * float(np.linalg.norm(np.ptp(tp, axis=0)))
    counts = []

    def counting(o, d):
        counts.append(len(o))
        return caster.occluded(o, d)

    def maps(k):
        counts.clear()
        lv = avis_level(pos, nrm, ar, tex, 2, 8, counting, tp, ray_eps=eps, faces=fid,
                        per_facet=k)
        return lv.dense_maps().reshape(4, -1), sum(counts)

    dense, rays0 = maps(0)
    errs = []
    for k in (1, 4, 16):  # 16 = q^2: every group whole
        got, rays = maps(k)
        errs.append(float(np.max(np.linalg.norm(got - dense, axis=1)
                                 / np.linalg.norm(dense, axis=1))))
        assert rays <= rays0 * min(k, 16) / 16 + 1e-9
    assert errs[0] > errs[1] > 0 and errs[2] == 0.0
    # masking on this field is a few percent of a_vis: one sample per triangle is within it
    assert errs[0] < 0.05


def test_per_facet_free_samples_keep_their_area():
    """Samples proven free count their own area (no rays): the subsample is drawn among the
    others only, so a texel of free samples is the closed form whatever k."""
    pos, nrm, ar, fid, tex, caster, tp = _field()
    eps = TOL.ray_offset * float(np.linalg.norm(np.ptp(tp, axis=0)))
    free = unoccluded_samples(pos, nrm, tp, eps=eps)
    a = facet_subsample(tex, fid, ar, 2, cast=~free)
    assert np.array_equal(a[free], ar[free])
    assert default_eps(pos) > 0
    with pytest.raises(SettingsError):
        avis_level(pos, nrm, ar, tex, 2, 8, caster.occluded, tp, per_facet=2)
