"""Fixtures of the service tests: the small cylinder and its in-process bake, the truth every
farm result must equal (one bake per session, shared by the farm and fair-share tests)."""

from __future__ import annotations

from pathlib import Path

import pytest

from schemas.settings import BakeSettings
from tests.helpers.service import CHEAP_SETTINGS


@pytest.fixture(scope="session")
def cylinder(tmp_path_factory) -> Path:
    from texelbake.testscenes import write_scene

    return write_scene("cylinder", tmp_path_factory.mktemp("scene") / "cylinder.usda", "small")


@pytest.fixture(scope="session")
def reference(cylinder, tmp_path_factory) -> Path:
    """The in-process bake: the truth every farm result must equal."""
    from texelbake.pipeline.run import bake

    out = tmp_path_factory.mktemp("reference")
    return bake(cylinder, out, BakeSettings(**CHEAP_SETTINGS), progress=False)
