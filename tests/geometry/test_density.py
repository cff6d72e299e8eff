"""Samples where the detail is (`geometry.density`, `sample_density="detail"`): which faces are
simple, the counts the sampler gives them, and that every area-weighted sum stays the area."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from schemas.settings import BakeSettings
from tests.helpers.render import lambert, model, quad
from texelbake.errors import ShapeError
from texelbake.geometry.build import CHART_COVER, _spool_samples, sample_density
from texelbake.geometry.density import SIMPLE_DENSITY, face_density, simple_faces
from texelbake.geometry.mesh import triangle_areas
from texelbake.geometry.sampling import sample_surface, surface_sampler
from texelbake.io.spool import MemorySpool
from texelbake.io.store import ArtifactStore
from texelbake.model import Material, Texture
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.stages.filtered import filtered_key


def _scene():
    """Four 2 x 1 quads side by side (eight triangles of area 1) and a fan of eight small
    triangles (area 1/128 each): quad 0 flat Lambert (simple), quad 1 textured, quad 2 the
    cellular shader, quad 3 flat Lambert whose shading normals tilt at one corner; the fan flat
    Lambert but smaller than a texel."""
    parts = [quad(3.0 * i, 3.0 * i + 2.0, 0.0, 1.0, 0.0) for i in range(4)]
    pts = np.concatenate([p for p, _ in parts])
    faces = np.concatenate([f + 4 * i for i, (_, f) in enumerate(parts)])
    ang = np.linspace(0.0, 2.0 * np.pi, 9)[:-1]
    r = np.sqrt(2.0 / 128.0 / np.sin(2.0 * np.pi / 8))  # 8 triangles of area 1/128
    fan = np.c_[r * np.cos(ang), r * np.sin(ang) - 2.0, np.zeros(8)]
    centre = len(pts) + 8
    pts = np.concatenate([pts, fan, [[0.0, -2.0, 0.0]]])
    fan_faces = np.stack([np.full(8, centre), len(pts) - 9 + np.arange(8),
                          len(pts) - 9 + (np.arange(8) + 1) % 8], axis=1)
    faces = np.concatenate([faces, fan_faces])
    asset = model(pts, faces)
    cn = asset.corner_normals.copy()
    cn[6, 0] = [0.0, 0.6, 0.8]  # quad 3's first triangle: a tilted corner normal
    tex = Texture(path="albedo.png", pixels=np.full((2, 2, 3), 0.5, np.float32))
    mats = (lambert(), Material("/Looks/Tex", "lambert", {"diffuseColor": np.full(3, 0.5)},
                                {"diffuseColor": tex}),
            Material("/Looks/Cells", "cellular", {}))
    fm = np.zeros(len(faces), np.int32)
    fm[2:4], fm[4:6] = 1, 2
    return dataclasses.replace(asset, corner_normals=cn, face_material=fm, materials=mats)


def test_simple_faces_are_flat_constant_and_at_least_a_texel():
    asset = _scene()
    got = simple_faces(asset, texel_area=0.5)
    want = np.zeros(len(asset.faces), bool)
    want[[0, 1, 7]] = True  # quad 0; quad 3's untilted triangle; not textured, cellular, fan
    assert got.tolist() == want.tolist()
    # the fan's triangles become simple once a texel is smaller than they are
    assert simple_faces(asset, texel_area=1.0 / 256).tolist() == [
        True, True, False, False, False, False, False, True] + [True] * 8
    np.testing.assert_array_equal(face_density(asset, 0.5),
                                  np.where(want, SIMPLE_DENSITY, 1.0))


def test_density_splits_counts_by_weighted_area_and_keeps_every_area():
    asset = _scene()
    d = face_density(asset, 0.5)
    areas = triangle_areas(asset.points, asset.faces)
    m = 4000
    smp = sample_surface(asset.points, asset.faces, m, seed=3, face_density=d)
    counts = np.bincount(smp.face, minlength=len(areas))
    # m · Σ d a / Σ a samples: one a face, the rest split by d · a up to the largest
    # remainder's one sample
    total = round(m * (d * areas).sum() / areas.sum())
    assert counts.sum() == total
    want = 1 + (total - len(areas)) * (d * areas) / (d * areas).sum()
    assert np.all(np.abs(counts - want) <= 1.0)
    # density per unit area on a simple face is SIMPLE_DENSITY of an ordinary one's
    assert counts[0] / counts[2] == pytest.approx(SIMPLE_DENSITY, abs=2e-3)
    # a face's samples share its area, so ΣΔA is the surface area and each face's is its own
    np.testing.assert_allclose(np.bincount(smp.face, smp.area, len(areas)), areas, rtol=1e-12)
    assert smp.area.sum() == pytest.approx(areas.sum(), rel=1e-12)


def test_unit_density_is_the_seeds_allocation():
    asset = _scene()
    a = surface_sampler(asset.points, asset.faces, 3000, seed=5)
    b = surface_sampler(asset.points, asset.faces, 3000, seed=5,
                        face_density=np.ones(len(asset.faces)))
    np.testing.assert_array_equal(a.counts, b.counts)


@pytest.mark.parametrize("bad", [np.zeros(16), np.full(16, 1.5), np.ones(3)])
def test_a_bad_density_names_the_field(bad):
    asset = _scene()
    with pytest.raises(ShapeError, match="face_density"):
        surface_sampler(asset.points, asset.faces, 100, seed=0, face_density=bad)


def test_the_setting_sizes_a_texel_by_the_atlas():
    asset = _scene()
    area = triangle_areas(asset.points, asset.faces).sum()
    assert sample_density(asset, BakeSettings(sample_density="area")) is None  # the seed's
    s = BakeSettings(sample_density="detail", atlas_resolution=16, shard_texels=4)
    np.testing.assert_array_equal(sample_density(asset, s),
                                  face_density(asset, area / (16 * 16 * CHART_COVER)))
    # at 4² a texel (~1.26) is larger than every face: nothing is simple, and the sampler is
    # the seed's (None: its probes too); at 16² quad 0 is simple
    assert sample_density(asset, BakeSettings(sample_density="detail", atlas_resolution=4,
                                              shard_texels=4)) is None
    assert sample_density(asset, BakeSettings(sample_density="detail",
                                              atlas_resolution=16))[0] == SIMPLE_DENSITY


def test_the_density_keys_the_geometry_and_what_reads_its_samples(tmp_path):
    ctx = [StageContext(ArtifactStore(tmp_path), tmp_path / "a.usda",
                        BakeSettings(sample_density=d), "0" * 64) for d in ("area", "detail")]
    assert ctx[0].geometry_key() != ctx[1].geometry_key()
    assert filtered_key(ctx[0]) != filtered_key(ctx[1])
    assert ctx[0].key("avis", "top.npz", GEOMETRY_FIELDS) != ctx[1].key("avis", "top.npz",
                                                                         GEOMETRY_FIELDS)


def test_probes_follow_the_area_whatever_the_density():
    """The LOD chain and the atlas search measure on probes; with a density they are the
    samples at equal steps of cumulative area, so each face holds its area's share of them."""
    asset = _scene()
    areas = triangle_areas(asset.points, asset.faces)
    sampler = surface_sampler(asset.points, asset.faces, 40_000, seed=2,
                              corner_normals=asset.corner_normals,
                              face_density=face_density(asset, 0.5))
    probes = _spool_samples(sampler, asset, MemorySpool(), 7_000, (2_000,))[2_000]
    assert abs(len(probes) - 2_000) <= 1
    quad0 = (probes[:, 0] <= 2.0) & (probes[:, 1] >= 0.0)
    share = areas[:2].sum() / areas.sum()  # quad 0: simple, sampled at a quarter
    assert abs(quad0.sum() - 2_000 * share) <= 2  # a systematic sample: within a step or two
    smp = sample_surface(asset.points, asset.faces, 40_000, seed=2,
                         face_density=face_density(asset, 0.5))
    assert np.isin(smp.face, [0, 1]).mean() < 0.5 * share
