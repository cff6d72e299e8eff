"""The BTF's cell-averaged tables (`BakeSettings.btf_table="cell"`, `texelbake.cpm.cell_table`):
the draws lie in their cells, the table read at the nearest pair is closer to the truth than
the point table on a lobe narrower than a cell (against the lobe itself at independent random
pairs), and with every draw at its cell's centre the bake's cell table is the point table on
both fit paths (the wiring: visibility, weights, a_vis)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.btf.lut import build_lut, lookup_pairs
from texelbake.cpm import level_batched, level_per_texel
from texelbake.cpm.level import direction_sets, level_candidates, tile_texels
from texelbake.errors import SettingsError
from texelbake.geometry.directions import cell_directions, hemisphere_directions, product_pairs
from texelbake.stages.cpm import fit_level
from texelbake.testscenes import write_scene


def test_cell_directions_lie_in_their_cells_and_repeat():
    dirs = hemisphere_directions(64, seed=5)
    cells = cell_directions(dirs, 8, seed=1)
    assert cells.shape == (8, 64, 3)
    np.testing.assert_allclose(np.linalg.norm(cells, axis=-1), 1.0, atol=1e-12)
    assert np.all(cells[..., 2] > 0)
    owner = np.argmax(cells.reshape(-1, 3) @ dirs.T, axis=1).reshape(8, 64)
    np.testing.assert_array_equal(owner, np.broadcast_to(np.arange(64), (8, 64)))
    # spread over the cell, not piled on the centre: most draws are off it by degrees
    off = np.degrees(np.arccos(np.clip(np.sum(cells * dirs[None], axis=-1), -1, 1)))
    assert np.median(off) > 3.0
    np.testing.assert_array_equal(cell_directions(dirs, 8, seed=1), cells)


def test_an_empty_cell_holds_its_own_direction():
    """A direction repeated: one copy takes every tie, the other's cell is empty."""
    dirs = hemisphere_directions(16, seed=2)
    dup = np.concatenate([dirs, dirs[3:4]])
    cells = cell_directions(dup, 4)
    at_centre = [bool(np.all(cells[:, j] == dup[3])) for j in (3, 16)]
    assert sorted(at_centre) == [False, True]
    with pytest.raises(SettingsError, match="k >= 1"):
        cell_directions(dirs, 0)


def _lobe(wi, wo, sigma_deg=2.0):
    """A mirror lobe about +z much narrower than a cell of 64 directions, times cos(l)."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=-1, keepdims=True)
    ang = np.arccos(np.clip(h[..., 2], -1, 1))
    return np.exp(-0.5 * (ang / np.radians(sigma_deg)) ** 2) / np.radians(sigma_deg) ** 2 \
        * np.clip(wi[..., 2], 0, None)


def test_the_cell_table_is_nearer_the_lobe_than_the_point_table():
    """Read at the nearest pair (the BTF's look-up), the cell means' squared error over 400,000
    random pairs is a quarter below the point samples' (measured: 341 against 518; the cell
    mean is the least-squares constant over its cell, so only the draws' noise keeps it from
    the best a nearest look-up can do), and their mean (the lobe's energy) is within 5 % of
    the truth's (measured 3.6 %)."""
    di, do = hemisphere_directions(64, seed=11), hemisphere_directions(64, seed=12)
    ri, ro = product_pairs(64, 64)
    point = _lobe(di[ri], do[ro])
    k = 64
    ci, co = cell_directions(di, k, seed=3), cell_directions(do, k, seed=4)
    cell = np.mean([_lobe(ci[a][ri], co[a][ro]) for a in range(k)], axis=0)
    rng = np.random.default_rng(0)
    u = rng.random((400000, 4))
    wi = _hemi(u[:, :2])
    wo = _hemi(u[:, 2:])
    truth = _lobe(wi, wo)
    lut = build_lut(di[ri], do[ro])
    cols, _ = lookup_pairs(lut, wi, wo, interpolate=False)
    err_point = np.mean((point[cols[:, 0]] - truth) ** 2)
    err_cell = np.mean((cell[cols[:, 0]] - truth) ** 2)
    assert err_cell < 0.75 * err_point
    assert abs(cell[cols[:, 0]].mean() / truth.mean() - 1) < 0.05


def _hemi(u):
    c = 1 - u[:, 0]
    s = np.sqrt(1 - c * c)
    p = 2 * np.pi * u[:, 1]
    return np.stack([s * np.cos(p), s * np.sin(p), c], axis=1)


@pytest.fixture(scope="module")
def btf_scene(tmp_path_factory):
    d = tmp_path_factory.mktemp("cells")
    scene = write_scene("bolt", d / "bolt.usda", "small")
    s = BakeSettings(atlas_resolution=16, shard_texels=8, samples_per_texel=16, n_light_dirs=16,
                     n_view_dirs=16, n_heldout=16, c_max=12, n_trials=2, mesh_levels=1,
                     btf=True, btf_cell_draws=3)
    ctx = stages.StageContext.create(d / "work", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    return ctx


@pytest.mark.parametrize("method", ["batched", "per_texel"])
def test_draws_at_the_centres_give_the_point_table(btf_scene, monkeypatch, method):
    src = btf_scene.fit_inputs()
    texels = tile_texels(16, 8, 0, 0)
    cands = level_candidates(src, 0, texels, None)

    def at(table):
        s = src.settings.model_copy(update={"btf_table": table, "fit_method": method})
        return fit_level(dataclasses.replace(src, settings=s), 0, texels, cands)

    point = at("point")["fbar"]
    assert point.max() > 0
    drawn = at("cell")["fbar"]
    assert not np.allclose(drawn, point, rtol=1e-3)  # the draws move the table

    def centres(settings, dirs):
        k = settings.btf_cell_draws
        return np.repeat(dirs["dirs_i"][None], k, 0), np.repeat(dirs["dirs_o"][None], k, 0)

    for mod in (level_batched, level_per_texel):  # the cell table's two callers
        monkeypatch.setattr(mod, "direction_cells", centres)
    np.testing.assert_allclose(at("cell")["fbar"], point, rtol=1e-5, atol=1e-7)
    assert direction_sets(src.settings)["dirs_i"].shape == (16, 3)


@pytest.mark.parametrize("model,params", [
    ("phong", {"diffuseColor": (0.2, 0.2, 0.2), "specularColor": (0.4, 0.4, 0.4),
               "exponent": 60.0}),
    ("preview", {"metallic": 1.0, "roughness": 0.15}),
    ("preview", {"metallic": 1.0, "roughness": 0.4}),
])
def test_lobe_half_width_against_the_brdf_itself(model, params):
    """The closed forms against the BRDF evaluated at normal incidence, the view turned away
    from the mirror direction in 0.005° steps: where it first falls to half its peak (within
    6 %: GGX's Fresnel, masking and 1/cos terms move the half point a little)."""
    from texelbake.brdf import evaluate
    from texelbake.btf.bake import lobe_half_width
    from texelbake.model import Material

    m = Material("/M", model, params)
    beta = np.radians(np.arange(0.0, 40.0, 0.005))
    wi = np.tile([0.0, 0.0, 1.0], (beta.size, 1))
    wo = np.stack([np.sin(beta), np.zeros_like(beta), np.cos(beta)], axis=1)
    f = evaluate(m, wi, wo)[:, 0]
    if model == "phong":  # the diffuse floor is not the lobe
        f = f - f[-1]
    half = beta[np.argmax(f < 0.5 * f[0])]
    assert lobe_half_width(m) == pytest.approx(half, rel=0.06)


def test_the_btf_warns_of_a_lobe_narrower_than_its_directions():
    from texelbake.btf.bake import narrow_lobes
    from texelbake.model import Material

    dirs = direction_sets(BakeSettings())
    sharp = Material("/Looks/Steel", "preview", {"metallic": 1.0, "roughness": 0.15})
    broad = Material("/Looks/Plastic", "phong", {"exponent": 60.0})
    flat = Material("/Looks/Paper", "lambert", {})
    got = narrow_lobes([sharp, broad, flat], dirs["dirs_i"], dirs["dirs_o"])
    assert len(got) == 1 and "/Looks/Steel" in got[0] and "1.7°" in got[0]
    many = direction_sets(BakeSettings(n_light_dirs=4096, n_view_dirs=4096))
    assert narrow_lobes([sharp], many["dirs_i"], many["dirs_o"]) == []


def test_the_render_table_repeats_the_bakes_btf_warnings(tmp_path, capsys):
    """`texelbake render` with a btf mode prints the bake's btf warnings under its table (read
    from the report.json beside the baked USD); without a btf mode, or without the file, none."""
    from texelbake.cli.render import print_btf_warnings

    baked = tmp_path / "a_baked.usda"
    warn = "btf: material /M has a specular lobe 1.7° wide to half height, ..."
    (tmp_path / "report.json").write_text(
        json.dumps({"warnings": ["level 0: 3 of 9 ray-traced texels ...", warn]}))
    print_btf_warnings(baked, {"modes": {"gt": {}, "btf": {}}})
    assert capsys.readouterr().out == f"note (from the bake): {warn}\n"
    print_btf_warnings(baked, {"modes": {"gt": {}, "cpm": {}}})
    print_btf_warnings(tmp_path / "elsewhere" / "b.usda", {"modes": {"btf-naive": {}}})
    assert capsys.readouterr().out == ""
