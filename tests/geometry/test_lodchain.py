"""The LOD chain chosen by geometric error (issue 22, item 1; texelbake.geometry.lodchain):
each level within its bound, the bound measured by an independent distance, and the hard cases
(already coarse, a chain that stops, many parts, open surface, non-manifold input)."""

from __future__ import annotations

import numpy as np
import pytest

from tests.helpers.meshes import box, bumpy_sphere, plane_grid
from texelbake.errors import SettingsError
from texelbake.geometry.lodchain import KEEP_FRACTION, build_lod_chain, error_bounds, hausdorff
from texelbake.geometry.mesh import Mesh, bbox_diagonal
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import sample_surface


def _brute_hausdorff(a: Mesh, b: Mesh, n: int = 200_000) -> float:
    """Two-sided distance from 200k seeded samples (10x the chain's), by Embree's closest
    points: an independent estimate (other samples, other distance code)."""
    out = 0.0
    for x, y in ((a, b), (b, a)):
        pts = np.concatenate([x.vertices, sample_surface(x.vertices, x.faces, n, 7).positions])
        cp, _, _ = RayCaster(y.vertices, y.faces).closest_points(pts)
        out = max(out, float(np.linalg.norm(cp - pts, axis=1).max()))
    return out


def _boxes(k: int, size: float, gap: float):
    vs, fs, off = [], [], 0
    for i in range(k):
        for j in range(k):
            v, f = box((i * gap, j * gap, 0.0), (i * gap + size, j * gap + size, size))
            vs.append(v)
            fs.append(f + off)
            off += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def test_hausdorff_of_two_parallel_planes_is_their_distance():
    # closed form: a unit square and the same square 0.3 above it are 0.3 apart both ways
    v, f = plane_grid(4, 4)
    a = Mesh(v, f)
    b = Mesh(v + [0.0, 0.0, 0.3], f)
    d_ab, d_ba = hausdorff(a, b)
    assert d_ab == pytest.approx(0.3, rel=1e-6)
    assert d_ba == pytest.approx(0.3, rel=1e-6)


def test_hausdorff_matches_an_independent_closest_point_computation():
    v, f = bumpy_sphere(3)
    org = Mesh(v, f)
    coarse = build_lod_chain(v, f, (16.0,)).levels[0].mesh
    d = max(hausdorff(coarse, org))
    brute = _brute_hausdorff(coarse, org)
    # 20k samples vs 200k: the sparser set can only miss the farthest point by about its
    # sample spacing (sqrt(area / 20k) ~ 0.02 on this unit sphere); both are distances to a
    # triangle that Embree and pymeshlab choose in float32, exact to ~1e-7 of the diagonal
    # (measured: 4e-9 over on a 0.2 distance)
    assert d <= brute + 1e-6 * bbox_diagonal(org.vertices)
    assert d >= brute - 0.02


@pytest.fixture(scope="module")
def sphere_chain():
    v, f = bumpy_sphere(4)
    return Mesh(v, f), build_lod_chain(v, f, (256.0, 64.0, 16.0), 1.0)


def test_every_level_is_within_its_bound_and_smaller(sphere_chain):
    org, chain = sphere_chain
    diag = bbox_diagonal(org.vertices)
    assert [lv.bound for lv in chain.levels] == pytest.approx(
        [diag / 256.0, diag / 64.0, diag / 16.0])
    faces = [org.num_faces] + [lv.mesh.num_faces for lv in chain.levels]
    assert all(b <= KEEP_FRACTION * a for a, b in zip(faces, faces[1:], strict=False)), faces
    for lv in chain.levels:
        assert lv.hausdorff <= lv.bound
        # the independent, denser estimate: within the bound up to the chain's sample spacing
        # (sqrt(4 pi / 20k) ~ 0.025 on the unit sphere, ~1% of its diagonal)
        assert _brute_hausdorff(lv.mesh, org) <= lv.bound + 0.01 * diag
    rep = chain.report()
    assert [lv["within_bound"] for lv in rep["levels"]] == [True, True, True]
    assert rep["stopped"] == ""


def test_a_level_is_about_the_smallest_within_its_bound(sphere_chain):
    # the bisection's answer: a collapse to 2/3 of LOD1's faces leaves the bound
    from texelbake.geometry.hierarchy import _decimate

    org, chain = sphere_chain
    lv = chain.levels[0]
    smaller = _decimate(org, int(lv.mesh.num_faces * 2 / 3), 1)
    assert max(hausdorff(smaller, org)) > lv.bound


def test_a_mesh_already_coarser_than_the_bound_is_its_own_lod1():
    v, f = box()  # 12 triangles: no collapse keeps a cube within a pixel at 512 px
    chain = build_lod_chain(v, f, (512.0, 256.0))
    assert len(chain.levels) == 1
    lv = chain.levels[0]
    assert lv.method == "original" and lv.mesh.num_faces == 12 and lv.hausdorff == 0.0
    assert "original" in lv.note
    assert "stops" in chain.stopped and "LOD2" in chain.stopped


def test_the_chain_stops_when_a_level_would_barely_reduce():
    v, f = bumpy_sphere(3)
    chain = build_lod_chain(v, f, (128.0, 120.0, 16.0))
    # LOD2's bound is 7 % looser than LOD1's: no collapse to 80 % of LOD1 stays within it
    assert len(chain.levels) == 1
    assert "LOD2" in chain.stopped and "80%" in chain.stopped


def test_many_small_parts_are_merged_into_a_wrap_when_the_bound_allows():
    v, f = _boxes(6, 0.1, 0.102)  # 36 boxes 2 mm apart: a slab to the eye at 6 px
    org = Mesh(v, f)
    chain = build_lod_chain(v, f, (6.0,))
    lv = chain.levels[0]
    assert lv.method == "wrap" and "36 parts" in lv.note
    assert lv.mesh.num_faces < 36  # fewer triangles than parts: QEM alone cannot get there
    assert lv.hausdorff <= lv.bound
    assert _brute_hausdorff(lv.mesh, org) <= lv.bound * 1.05


def test_many_small_parts_at_a_tight_bound_are_kept():
    v, f = _boxes(6, 0.1, 0.15)
    chain = build_lod_chain(v, f, (64.0,))
    lv = chain.levels[0]
    assert lv.method == "original" and lv.mesh.num_faces == 432


def test_an_open_surface_keeps_its_boundary_within_the_bound():
    v, f = plane_grid(40, 40)
    v = v.copy()
    v[:, 2] = 0.05 * np.sin(6.0 * v[:, 0]) * np.cos(4.0 * v[:, 1])
    org = Mesh(v, f)
    chain = build_lod_chain(v, f, (128.0, 32.0))
    assert len(chain.levels) == 2
    boundary = v[(np.abs(v[:, 0] - v[:, 0].min()) < 1e-9) | (np.abs(v[:, 0] - v[:, 0].max())
                                                           < 1e-9)]
    for lv in chain.levels:
        assert lv.mesh.num_faces < org.num_faces
        cp, _, _ = RayCaster(lv.mesh.vertices, lv.mesh.faces).closest_points(boundary)
        assert np.linalg.norm(cp - boundary, axis=1).max() <= lv.bound


def test_non_manifold_input_is_simplified_within_the_bound():
    # three curved sheets sharing one edge (a non-manifold "book" of pages)
    v, f = plane_grid(20, 20)
    pages_v, pages_f = [], []
    for k, ang in enumerate((0.0, 2.1, 4.2)):
        rot = np.array([[np.cos(ang), 0.0, -np.sin(ang)], [0.0, 1.0, 0.0],
                        [np.sin(ang), 0.0, np.cos(ang)]])
        p = v.copy()
        p[:, 0] -= p[:, 0].min()  # the shared edge is x = 0
        p[:, 2] = 0.05 * np.sin(5.0 * p[:, 0])
        pages_v.append(p @ rot.T)
        pages_f.append(f + k * len(v))
    pv, pf = np.concatenate(pages_v), np.concatenate(pages_f)
    from texelbake.geometry.mesh import weld

    welded, _, _ = weld(pv, pf)
    edges = np.sort(welded.faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert counts.max() == 3  # the input really is non-manifold
    chain = build_lod_chain(pv, pf, (128.0,))
    lv = chain.levels[0]
    assert lv.mesh.num_faces < welded.num_faces
    assert lv.hausdorff <= lv.bound
    assert _brute_hausdorff(lv.mesh, welded) <= lv.bound * 1.05


def test_the_chain_is_deterministic():
    v, f = bumpy_sphere(3)
    a = build_lod_chain(v, f, (128.0, 32.0))
    b = build_lod_chain(v, f, (128.0, 32.0))
    for x, y in zip(a.levels, b.levels, strict=True):
        np.testing.assert_array_equal(x.mesh.vertices, y.mesh.vertices)
        np.testing.assert_array_equal(x.mesh.faces, y.mesh.faces)
        assert x.hausdorff == y.hausdorff


def test_bad_switch_sizes_are_named():
    with pytest.raises(SettingsError, match="decrease"):
        error_bounds(1.0, (64.0, 128.0), 1.0)
    with pytest.raises(SettingsError, match="positive"):
        error_bounds(1.0, (0.0,), 1.0)
    from pydantic import ValidationError

    from schemas.settings import BakeSettings

    with pytest.raises(ValidationError, match="lod_switch_px"):
        BakeSettings(lod_switch_px=(64.0, 64.0))


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    fn = np.cross(v[f][:, 1] - v[f][:, 0], v[f][:, 2] - v[f][:, 0])
    return fn / np.linalg.norm(fn, axis=1, keepdims=True)


def _prism(sides: int, rings: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """An open regular prism about z (radius 1, height 1), outward faces."""
    phi = 2.0 * np.pi * np.arange(sides) / sides
    z = np.linspace(0.0, 1.0, rings + 1)
    v = np.stack([np.tile(np.cos(phi), rings + 1), np.tile(np.sin(phi), rings + 1),
                  np.repeat(z, sides)], axis=1)
    i, k = np.meshgrid(np.arange(rings), np.arange(sides), indexing="ij")
    a, b = i * sides + k, i * sides + (k + 1) % sides
    c, d = a + sides, b + sides
    f = np.concatenate([np.stack([a, b, d], -1).reshape(-1, 3),
                        np.stack([a, d, c], -1).reshape(-1, 3)])
    return v, f.astype(np.int64)


def test_smooth_corner_normals_match_a_per_vertex_loop_and_split_at_the_crease(monkeypatch):
    # the vectorized pairs against a plain loop over each corner's vertex, on a bumpy sphere
    # whose vertices are also duplicated (a soup: vertices at one position are one); in
    # chunks of a few pairs the same
    import texelbake.geometry.lodnormals as lodnormals
    from tests.helpers.meshes import soup

    v, f = bumpy_sphere(2, amplitude=0.15, freq=5)
    fn = _face_normals(v, f)
    tri = v[f]
    want = np.zeros((len(f), 3, 3))
    for c in (20.0, 60.0):
        for fi in range(len(f)):  # the independent computation: one corner at a time
            for k in range(3):
                acc = np.zeros(3)
                for fj, kj in zip(*np.nonzero(f == f[fi, k]), strict=True):
                    if fn[fi] @ fn[fj] >= np.cos(np.radians(c)):
                        e1, e2 = tri[fj, (kj + 1) % 3] - tri[fj, kj], tri[fj, (kj + 2) % 3] - tri[fj, kj]
                        acc += np.arccos(e1 @ e2 / np.linalg.norm(e1) / np.linalg.norm(e2)) * fn[fj]
                want[fi, k] = acc / np.linalg.norm(acc)
        sv, sf = soup(v, f)
        got = lodnormals.smooth_corner_normals(sv, sf, crease_deg=c)
        np.testing.assert_allclose(got, want, atol=1e-12)
        monkeypatch.setattr(lodnormals, "PAIR_CHUNK", 7)
        np.testing.assert_array_equal(lodnormals.smooth_corner_normals(sv, sf, crease_deg=c), got)
        monkeypatch.undo()
    # a box's edges (90 degrees) are creases at 60: every corner keeps its face's normal
    bv, bf = box()
    np.testing.assert_array_equal(lodnormals.smooth_corner_normals(bv, bf),
                                  np.repeat(_face_normals(bv, bf)[:, None], 3, axis=1))
    assert lodnormals.smooth_corner_normals(bv, bf[:0]).shape == (0, 3, 3)
    with pytest.raises(SettingsError, match="crease_deg"):
        lodnormals.smooth_corner_normals(bv, bf, crease_deg=0.0)


def test_lod_corner_normals_keep_sharp_edges_sharp_and_smooth_surfaces_smooth():
    # issue 22: a DCC shades a LOD with the normals it carries. A box (M_org's corner normals
    # its face normals, sharp) onto a box LOD: every corner takes its own face's normal
    # exactly; a fine sphere with radial (smooth) corner normals onto a coarser sphere: each
    # corner's normal is the radial direction at its vertex within the coarse sphere's
    # asymmetry (its angle-weighted vertex normals: cos error < 1e-3), equal at a vertex
    from tests.helpers.meshes import icosphere
    from texelbake.geometry.lodnormals import lod_corner_normals

    v, f = box()
    fn = _face_normals(v, f)
    got = lod_corner_normals(v, f, np.repeat(fn[:, None], 3, axis=1), RayCaster(v, f))
    np.testing.assert_allclose(got, np.repeat(fn[:, None], 3, axis=1), atol=1e-9)

    fine_v, fine_f = icosphere(4)
    radial = fine_v[fine_f] / np.linalg.norm(fine_v[fine_f], axis=2, keepdims=True)
    lod_v, lod_f = icosphere(2)
    got = lod_corner_normals(lod_v, lod_f, radial, RayCaster(fine_v, fine_f))
    want = lod_v[lod_f] / np.linalg.norm(lod_v[lod_f], axis=2, keepdims=True)
    assert np.einsum("fkd,fkd->fk", got, want).min() > 0.999
    per_vertex = np.zeros((len(lod_v), 3))
    per_vertex[lod_f.ravel()] = got.reshape(-1, 3)  # the last corner's
    np.testing.assert_allclose(got, per_vertex[lod_f], atol=1e-12)


def test_lod_corner_normals_follow_the_lods_surface_not_m_orgs_bumps():
    # a bumpy plane (bumps sloped up to ~50 degrees, smooth-shaded by their analytic normals)
    # under a flat 4x4 LOD: the LOD's corners face +z (the bumps belong to the normal map);
    # M_org's normal at the corner, the old rule, is up to the bumps' slope off
    from texelbake.geometry.lodnormals import lod_corner_normals, org_corner_normals

    a, k = 0.02, 2.0 * np.pi * 9.5  # height a sin(kx) sin(ky): slope a k = 1.19
    v, f = plane_grid(120, 120)
    v[:, 2] = a * np.sin(k * v[:, 0]) * np.sin(k * v[:, 1])
    grad = np.stack([a * k * np.cos(k * v[:, 0]) * np.sin(k * v[:, 1]),
                     a * k * np.sin(k * v[:, 0]) * np.cos(k * v[:, 1])], axis=1)
    n_org = np.column_stack([-grad, np.ones(len(v))])
    n_org = (n_org / np.linalg.norm(n_org, axis=1, keepdims=True))[f]
    lod_v, lod_f = plane_grid(4, 4)
    caster = RayCaster(v, f)
    off = np.degrees(np.arccos(lod_corner_normals(lod_v, lod_f, n_org, caster)[..., 2]))
    assert off.max() < 1e-6
    old = np.degrees(np.arccos(org_corner_normals(lod_v, lod_f, n_org, caster)[..., 2]))
    assert np.median(old) > 10.0


@pytest.mark.parametrize("sides", [12, 64])
def test_a_prisms_edges_stay_sharp_where_m_org_is_flat_shaded(sides):
    # the same prism as M_org and as its LOD: flat-shaded (corner normals = face normals, the
    # cylinder's ridges, the bolt's bumps on LOD1) every corner keeps its face's normal even
    # where the edge (30 degrees at 12 sides, 5.6 at 64) is below the crease angle; smooth-
    # shaded (radial corner normals) the corners are the prism's vertex normals, radial
    from texelbake.geometry.lodnormals import lod_corner_normals

    v, f = _prism(sides)
    fn = _face_normals(v, f)
    flat = np.repeat(fn[:, None], 3, axis=1)
    caster = RayCaster(v, f)
    np.testing.assert_allclose(lod_corner_normals(v, f, flat, caster), flat, atol=1e-9)
    radial = v[f] * [1.0, 1.0, 0.0]
    got = lod_corner_normals(v, f, radial, caster)
    np.testing.assert_allclose(got, radial, atol=1e-9)


def _recorded_collapses(monkeypatch):
    """The face counts of the meshes `_decimate` starts from, in call order."""
    import texelbake.geometry.lodchain as lodchain

    seen: list[int] = []
    real = lodchain._decimate

    def recording(mesh, target, level):
        seen.append(mesh.num_faces)
        return real(mesh, target, level)

    monkeypatch.setattr(lodchain, "_decimate", recording)
    return seen


def test_a_large_mesh_is_searched_from_one_proxy_collapse_within_the_bound(monkeypatch):
    # a bumpy sphere of 20,480 faces stands in for a million-triangle asset: with the proxy at
    # 2,000 faces, one collapse starts from M_org and every other from the proxy, and the
    # level is still within its bound by the independent, denser distance
    import texelbake.geometry.lodchain as lodchain

    v, f = bumpy_sphere(5)
    org = Mesh(v, f)
    monkeypatch.setattr(lodchain, "PROXY_FACES", 2_000)
    seen = _recorded_collapses(monkeypatch)
    chain = build_lod_chain(v, f, (64.0,), 1.0)
    lv = chain.levels[0]
    assert seen.count(org.num_faces) == 1 and seen[0] == org.num_faces, seen
    assert len(seen) > 3 and all(n <= 2_000 for n in seen[1:]), seen
    assert lv.mesh.num_faces < 2_000
    assert lv.hausdorff <= lv.bound
    diag = bbox_diagonal(org.vertices)
    assert _brute_hausdorff(lv.mesh, org) <= lv.bound + 0.01 * diag


def test_a_proxy_too_far_from_the_original_is_not_searched_from(monkeypatch):
    # at a bound tighter than the proxy's own distance over PROXY_SHARE the search runs on
    # M_org as before: every collapse starts from its 20,480 faces
    import texelbake.geometry.lodchain as lodchain

    v, f = bumpy_sphere(5)
    monkeypatch.setattr(lodchain, "PROXY_FACES", 200)
    seen = _recorded_collapses(monkeypatch)
    chain = build_lod_chain(v, f, (256.0,), 1.0)
    assert seen[0] == len(f) and seen.count(len(f)) == len(seen), seen
    assert chain.levels[0].hausdorff <= chain.levels[0].bound
