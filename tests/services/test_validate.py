"""The upload check (`services.validate.check_bundle`, run here in-process on an unpacked
bundle) refuses exactly what the bake would read from outside the bundle: not paths that only
unselected variants name, not a texture missing from the download; a selected variant's escape
and a missing layer still are. The API's own hostile-upload tests (tests/services/test_api.py)
cover sublayers, references, payloads, textures, `..`, URLs and packages through HTTP."""

from __future__ import annotations

import shutil

import pytest
from pxr import Usd

from services.validate import ESCAPES, MISSING, check_bundle
from tests.helpers.studio_assets import mtlx_asset, textured_box, wheel_variants_asset


def _bundle_of(tmp_path):
    """The car's folder copied as an upload would unpack it (the outside file is not in it)."""
    root, _ = wheel_variants_asset(tmp_path / "src")
    bundle = tmp_path / "bundle"
    shutil.copytree(root.parent, bundle)
    return bundle


def test_unselected_variant_escape_and_missing_file_are_accepted(tmp_path):
    bundle = _bundle_of(tmp_path)
    assert check_bundle(bundle, "root.usda") == []


@pytest.mark.parametrize(("variant", "problem"), [
    ("sport", ("../../../wheels/wheelVariants.usda (in root.usda)", ESCAPES)),
    ("racing", ("./parts/racing_wheels.usda (in root.usda)", MISSING)),
], ids=["escape", "missing_layer"])
def test_a_selected_variant_reading_outside_or_missing_is_refused(tmp_path, variant, problem):
    bundle = _bundle_of(tmp_path)
    stage = Usd.Stage.Open(str(bundle / "root.usda"))
    stage.GetPrimAtPath("/Root").GetVariantSet("wheels").SetVariantSelection(variant)
    stage.Save()
    del stage
    problems = check_bundle(bundle, "root.usda")
    assert problem in problems


def test_missing_texture_is_accepted_and_an_escaping_one_refused(tmp_path):
    textured_box(tmp_path / "a", "./gone.png")
    assert check_bundle(tmp_path / "a", "box.usda") == []
    textured_box(tmp_path / "b", "../gone.png")
    assert ("../gone.png (in box.usda)", ESCAPES) in check_bundle(tmp_path / "b", "box.usda")


def test_materialx_document_and_its_texture(tmp_path):
    mtlx_asset(tmp_path / "ok")
    assert check_bundle(tmp_path / "ok", "rook.usda") == []
    mtlx_asset(tmp_path / "bad", texture="../../outside.png")
    problems = check_bundle(tmp_path / "bad", "rook.usda")
    assert len(problems) == 1 and "escapes" in problems[0][1], problems
