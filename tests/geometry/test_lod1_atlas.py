"""`lod1_atlas`: the atlas side at which a finest texel is one pixel where LOD1 switches in,
and the cap."""

from __future__ import annotations

import math

import numpy as np

from tests.helpers.meshes import plane_grid
from texelbake.geometry.build import CHART_COVER, lod1_atlas


def _need(area: float, diag: float, px: float) -> int:
    """The closed form, written out: N >= px sqrt(area / CHART_COVER) / diag, a power of two."""
    return 2 ** math.ceil(math.log2(px * math.sqrt(area / CHART_COVER) / diag))


def test_unit_square_against_the_closed_form_and_the_cap():
    pts, faces = plane_grid(3, 3, size=1.0)
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    area = float(np.prod((pts.max(0) - pts.min(0))[:2]))
    need = _need(area, diag, 256.0)
    assert need == 512  # 256 sqrt(2.5) / sqrt(2) = 286.2 -> 512
    assert lod1_atlas(pts, faces, 256.0, cap=1024) == (need, need)
    # the cap reached: the largest size it allows is baked, the need still reported
    assert lod1_atlas(pts, faces, 256.0, cap=128) == (128, need)
    # a smaller switch size asks for a smaller atlas
    assert lod1_atlas(pts, faces, 64.0, cap=1024) == (_need(area, diag, 64.0),) * 2


def test_an_empty_asset_bakes_the_cap_and_reports_no_need():
    assert lod1_atlas(np.zeros((0, 3)), np.zeros((0, 3), np.int64), 256.0, cap=64) == (64, None)
