"""The project's four test scenes (texelbake.testscenes) read back by the ingest: counts against
`expected_counts` (computed from the parameter table, independently of the reader), the
models the texelbake render context selects, and what `describe` prints."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from texelbake.asset import check_asset_paths, describe, load_asset
from texelbake.testscenes import expected_counts, write_scene

SCENES = ("cylinder", "wall", "bolt", "cloisonne")
#: texelbake shader ids win over the UsdPreviewSurface approximation (scenes' convention)
MODELS = {
    "cylinder": {"lambert", "phong"},
    "wall": {"preview"},
    "bolt": {"preview"},
    "cloisonne": {"cellular"},
}


@pytest.mark.parametrize("size", ["small", "full"])
@pytest.mark.parametrize("name", SCENES)
def test_scene_counts_and_describe(tmp_path, name, size):
    path = write_scene(name, tmp_path / f"{name}.usda", size)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a generated scene must ingest without any warning
        asset = load_asset(path)
    textures = {t.path for m in asset.materials for t in m.textures.values()}
    got = {
        "meshes": len(asset.mesh_paths),
        "faces": asset.num_faces,
        "materials": len(asset.materials),
        "lights": len(asset.lights),
        "cameras": len(asset.cameras),
        "textures": len(textures),
    }
    assert got == expected_counts(name, size)
    assert asset.dropped_faces == 0 and asset.warnings == ()
    assert {m.model for m in asset.materials} == MODELS[name]
    assert all(m.path for m in asset.materials)  # every face is bound: no default material
    assert asset.has_uvs.all()
    np.testing.assert_allclose(np.linalg.norm(asset.corner_normals, axis=2), 1.0, atol=1e-9)

    bundle = check_asset_paths(path)
    # the layer, its textures and the texelbake shaders' definitions (texelbake.usd.shaderdefs)
    own = any(m.model != "preview" for m in asset.materials)  # a texelbake shader is authored
    defs = [str((path.parent / "texelbake_shaders.usda").resolve())] if own else []
    assert bundle == sorted([str(path.resolve()), *textures, *defs])

    text = describe(asset)
    assert f"meshes: {got['meshes']} ({got['faces']} triangles" in text
    for key in ("materials", "textures", "lights", "cameras"):
        assert f"{key}: {got[key]}" in text
    for mesh_path in asset.mesh_paths:
        assert mesh_path in text
    for material in asset.materials:
        assert f"{material.path}: {material.model}" in text
    assert "deformation: no" in text
