"""The scenes' parameter table (everything that changes with the size) and what a reader must
find in each scene (`expected_counts`)."""

from __future__ import annotations

from collections.abc import Mapping
from types import MappingProxyType
from typing import Any

from texelbake.errors import SettingsError

SCENE_NAMES = ("cylinder", "wall", "bolt", "cloisonne")
SIZES = ("small", "full")
LAYER_SUFFIXES = (".usda", ".usdc", ".usd")

# ------------------------------------------------------------------------------------------
# Parameter table: everything that changes with the size, at a glance. Triangle counts are
# what `expected_counts` derives from these numbers.
#
#   cylinder  ridges around the axis, rings of quads along it; triangles 4*ridges*(rings+1)
#             (small 480; full 3072 = the seed's cylinder, Table 3)
#   wall      blocks per even row (odd rows: one more, halved at the ends), rows, quads per
#             side of a block's jittered front grid, texture width in pixels
#             (small 360 triangles, 256 px; full 29568 triangles, 1024 px)
#   bolt      bump cells around and along the shaft (8 triangles each), texture size
#             (small 812 triangles, 128 px; full 10784, ~ the seed's 10496, 1024 px)
#   cloisonne icosphere subdivision levels (20*4**levels triangles), number of bumps
#             (small 1280 triangles; full 20480)
# ------------------------------------------------------------------------------------------
SCENE_PARAMS: Mapping[str, Mapping[str, Mapping[str, int]]] = MappingProxyType(
    {
        "cylinder": {
            "small": {"ridges": 24, "rings": 4},
            "full": {"ridges": 64, "rings": 11},
        },
        "wall": {
            "small": {"cols": 4, "rows": 3, "front_cells": 2, "tex_res": 256},
            "full": {"cols": 12, "rows": 16, "front_cells": 8, "tex_res": 1024},
        },
        "bolt": {
            "small": {"around": 12, "along": 8, "tex_res": 128},
            "full": {"around": 46, "along": 29, "tex_res": 1024},
        },
        "cloisonne": {
            "small": {"subdiv": 3, "bumps": 24},
            "full": {"subdiv": 5, "bumps": 160},
        },
    }
)

# Size-independent shape constants (scene units).
CYLINDER: Mapping[str, float] = MappingProxyType({"radius": 1.0, "height": 2.0, "ridge_slope_deg": 50.0})
WALL: Mapping[str, float] = MappingProxyType(
    {"block_w": 0.4, "block_h": 0.2, "gap": 0.03, "depth": 0.06, "bevel": 0.015,
     "jitter": 0.005}
)
BOLT: Mapping[str, float] = MappingProxyType(
    {"radius": 0.4, "length": 1.6, "bump_ratio": 0.45, "head_radius": 0.7,
     "head_height": 0.35}
)
CLOISONNE: Mapping[str, float] = MappingProxyType({"amplitude": 0.07, "bump_width": 0.22})
CLOISONNE_SCALE = (1.0, 1.25, 0.9)  # the blob is a bumpy ellipsoid
METERS_PER_UNIT = MappingProxyType(
    {"cylinder": 0.01, "wall": 1.0, "bolt": 0.01, "cloisonne": 0.01}
)
SEEDS = MappingProxyType({"cylinder": 1000, "wall": 2000, "bolt": 3000, "cloisonne": 4000})

#: the cloisonné shader's inputs (names and types: texelbake.model's table)
CELLULAR_INPUTS: Mapping[str, Any] = MappingProxyType(
    {
        "cellScale": 16.0,
        "seed": 7,
        "borderWidth": 0.08,
        "borderColor": (1.0, 0.78, 0.34),
        "borderRoughness": 0.12,
        "cellColorA": (0.08, 0.22, 0.62),
        "cellColorB": (0.78, 0.16, 0.12),
    }
)


def check_scene(name: str, size: str) -> None:
    if name not in SCENE_NAMES:
        raise SettingsError(
            f"field 'name': unknown scene {name!r}; expected one of {', '.join(SCENE_NAMES)}"
        )
    if size not in SIZES:
        raise SettingsError(f"field 'size': unknown size {size!r}; expected one of small, full")


def expected_counts(name: str, size: str) -> dict[str, int]:
    """What a reader must find in `write_scene(name, ..., size)`, from the parameter table.

    Returns {"meshes", "faces", "materials", "lights", "cameras", "textures"}: faces are
    triangles after triangulation (an n-gon counts n - 2), materials the distinct bound
    UsdShade.Material prims, textures the distinct UsdUVTexture image files.
    Raises SettingsError for an unknown name or size.
    """
    check_scene(name, size)
    p = SCENE_PARAMS[name][size]
    if name == "cylinder":
        # 2 facets per ridge and 2 triangles per quad on each ring; two caps fanned over
        # the 2*ridges profile vertices
        faces = 4 * p["ridges"] * p["rings"] + 2 * (2 * p["ridges"])
        return _counts(1, faces, 2, 1, 1, 0)
    if name == "wall":
        n_even, n_odd = (p["rows"] + 1) // 2, p["rows"] // 2
        blocks = n_even * p["cols"] + n_odd * (p["cols"] + 1)
        per_block = 2 * p["front_cells"] ** 2 + 8 * 2  # front grid + 4 chamfers + 4 sides
        mortar = 2 * (2 * p["cols"]) * p["rows"]
        return _counts(2, blocks * per_block + mortar, 1, 1, 1, 1)
    if name == "bolt":
        shaft = 8 * p["around"] * p["along"] + 2 * p["around"]  # bumps + bottom cap fan
        head = 6 * 2 + 2 * (6 - 2)  # 6 side quads, 2 hexagons
        return _counts(2, shaft + head, 1, 2, 1, 1)
    return _counts(1, 20 * 4 ** p["subdiv"], 1, 2, 1, 0)


def _counts(meshes: int, faces: int, materials: int, lights: int, cameras: int,
            textures: int) -> dict[str, int]:
    return {"meshes": meshes, "faces": faces, "materials": materials, "lights": lights,
            "cameras": cameras, "textures": textures}
