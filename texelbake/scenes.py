"""The project's own USD test scenes, modelled on the scenes of seed 000 (§1, §5, Table 3).

`write_scene(name, path, size)` writes one scene as a USD layer (and its PNG textures beside
it); `expected_counts(name, size)` says, from the parameter table alone, how many meshes,
triangles, materials, lights, cameras and textures a reader must find in it.

| scene     | geometry                                                  | appearance                     |
|-----------|-----------------------------------------------------------|--------------------------------|
| cylinder  | radius-1 cylinder of sharp ridges along its axis, each a  | facets alternate: a yellow     |
|           | triangular cross-section (seed 000 Fig. 1), closed by caps | Lambertian and a glossy blue   |
|           |                                                           | Phong, bound per face through  |
|           |                                                           | GeomSubsets (materialBind)     |
| wall      | running-bond blocks with chamfered edges and a jittered   | Lambertian UsdPreviewSurface   |
|           | front grid, standing proud of a mortar plane (2 meshes)   | with a PNG colour texture      |
| bolt      | shaft covered in diamond (pyramidal) bumps, a hex head    | metallic, low roughness, with  |
|           | (2 meshes)                                                | a PNG stain texture            |
| cloisonne | bumpy blob (displaced icosphere)                          | `texelbake:cellular`: a        |
|           |                                                           | Lambertian colour per Worley   |
|           |                                                           | cell, sharp metal on borders   |

Every scene has `upAxis = "Y"`, `metersPerUnit`, a `defaultPrim` (an Xform of kind
component), one UsdGeom.Camera framing the object, one UsdLux.DistantLight and, for the bolt
and the cloisonne, a UsdLux.SphereLight. Meshes use `subdivisionScheme = "none"`, authored
`normals` (faceVarying for the faceted cylinder and bolt, vertex for the wall and the
cloisonne) and `primvars:st` (texCoord2f[]); authored extents; MaterialBindingAPI applied
wherever a binding is authored.

Material convention (the ingest reads it this way): a material whose BRDF
UsdPreviewSurface cannot express carries a texelbake shader (`info:id` one of the ids in
`texelbake.model`, with exactly the input names of its table) on the `texelbake` render
context output, `outputs:texelbake:surface`, AND a UsdPreviewSurface approximation on the
universal `outputs:surface`, so any USD viewer shows something. The ingest reads
`outputs:texelbake:surface` first and falls back to `outputs:surface`. Materials that
UsdPreviewSurface expresses exactly (the wall's Lambertian: specular workflow with zero
specular colour; the bolt's metal) have only `outputs:surface`.

Meaning of the `texelbake:cellular` inputs (evaluated by `texelbake.brdf.cellular`): Worley
cells over `st * cellScale` (the cloisonne's st is a spherical map, so 16 gives 16 cells
around and 16 from pole to pole), `seed` the feature-point seed, `borderWidth` in cell
units (a point is on a border where F2 - F1 < borderWidth), `borderRoughness` the roughness
of the border metal, `cellColorA`/`cellColorB` the range of the Lambertian cell colours.

Textures are 8-bit sRGB PNGs named `{scene}_{size}_{role}.png`, written beside the layer and
referenced by a relative path (`./wall_small_albedo.png`), so both sizes of one scene can
share a folder. Everything is seeded (`_SEEDS`); rewriting a scene gives identical bytes.
Files are written atomically (temp file in the same folder, then rename).

texelbake's shader ids are unknown to a bare pxr: `texelbake.shaderdefs.
register_shader_definitions()` (called when this module is imported) adds them to the Sdr
registry, after which pxr's validators pass with no error on every scene.
"""

from __future__ import annotations

import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from types import MappingProxyType
from typing import Any

import numpy as np
import OpenImageIO as oiio
from pxr import Gf, Kind, Sdf, Sdr, Usd, UsdGeom, UsdLux, UsdShade, Vt

from texelbake.errors import SettingsError
from texelbake.model import SHADER_CELLULAR, SHADER_LAMBERT, SHADER_PHONG, SHADER_PREVIEW
from texelbake.shaderdefs import register_shader_definitions

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
_CYLINDER: Mapping[str, float] = MappingProxyType({"radius": 1.0, "height": 2.0, "ridge_slope_deg": 50.0})
_WALL: Mapping[str, float] = MappingProxyType(
    {"block_w": 0.4, "block_h": 0.2, "gap": 0.03, "depth": 0.06, "bevel": 0.015,
     "jitter": 0.005}
)
_BOLT: Mapping[str, float] = MappingProxyType(
    {"radius": 0.4, "length": 1.6, "bump_ratio": 0.45, "head_radius": 0.7,
     "head_height": 0.35}
)
_CLOISONNE: Mapping[str, float] = MappingProxyType({"amplitude": 0.07, "bump_width": 0.22})
_CLOISONNE_SCALE = (1.0, 1.25, 0.9)  # the blob is a bumpy ellipsoid
_METERS_PER_UNIT = MappingProxyType(
    {"cylinder": 0.01, "wall": 1.0, "bolt": 0.01, "cloisonne": 0.01}
)
_SEEDS = MappingProxyType({"cylinder": 1000, "wall": 2000, "bolt": 3000, "cloisonne": 4000})

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


def _check(name: str, size: str) -> None:
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
    _check(name, size)
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


# ------------------------------------------------------------------------------------------
# Scene descriptions: plain arrays, authored by `_author_*` below.
# ------------------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class _MeshSpec:
    """One mesh. counts : (f,) int32; indices : (sum(counts),) int32; points : (n, 3)
    float64; normals : (n, 3) for "vertex" or (sum(counts), 3) for "faceVarying"; st alike
    with (., 2); subsets: (subset name, face indices (k,) int32, material name)."""

    name: str
    points: np.ndarray
    counts: np.ndarray
    indices: np.ndarray
    normals: np.ndarray
    normals_interp: str
    st: np.ndarray
    st_interp: str
    material: str | None = None
    subsets: tuple[tuple[str, np.ndarray, str], ...] = ()


@dataclass(frozen=True, eq=False)
class _MaterialSpec:
    """preview: UsdPreviewSurface constant inputs; texture: (preview input, texture role)
    driven by a UsdUVTexture; texelbake_id/texelbake_inputs: the texelbake shader, if any."""

    name: str
    preview: Mapping[str, Any]
    texture: tuple[str, str] | None = None
    texelbake_id: str | None = None
    texelbake_inputs: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class _LightSpec:
    """kind "distant": `toward` (3,) unit, from the scene toward the light; kind "sphere":
    `position` (3,), `radius`."""

    name: str
    kind: str
    intensity: float
    color: tuple[float, float, float]
    toward: np.ndarray = field(default_factory=lambda: np.zeros(3))
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))
    radius: float = 0.0


@dataclass(frozen=True, eq=False)
class _SceneSpec:
    root: str
    meshes: tuple[_MeshSpec, ...]
    materials: tuple[_MaterialSpec, ...]
    lights: tuple[_LightSpec, ...]
    view_from: np.ndarray  # (3,) direction from the object's centre toward the camera
    textures: Mapping[str, np.ndarray]  # role -> (h, w, 3) uint8, row 0 = top (t = 1)


def _unit(v: Any) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _face_normals_fv(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(sum(counts), 3) float64 flat per-face normals repeated on every corner, from the
    first three corners of each (planar, convex) face."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p0, p1, p2 = (points[indices[starts + k]] for k in range(3))
    n = _unit(np.cross(p1 - p0, p2 - p0))  # (f, 3)
    return np.repeat(n, counts, axis=0)


def _vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(n, 3) float64 area-weighted vertex normals of a triangle mesh tris : (f, 3)."""
    tri = points[tris]  # (f, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    acc = np.zeros_like(points)
    for k in range(3):  # three corners, not a loop over faces
        np.add.at(acc, tris[:, k], fn)
    return _unit(acc)


# ---- cylinder (seed 000, Fig. 1) ---------------------------------------------------------


def _cylinder(p: Mapping[str, int], rng: np.random.Generator) -> _SceneSpec:
    del rng  # the cylinder is fully regular
    n_ridge, rings = p["ridges"], p["rings"]
    r0, height = _CYLINDER["radius"], _CYLINDER["height"]
    # ridge height: facets rise at ridge_slope_deg over half a ridge's arc
    h = r0 * (math.pi / n_ridge) * math.tan(math.radians(_CYLINDER["ridge_slope_deg"]))
    n_prof = 2 * n_ridge  # profile: valley, peak, valley, ...
    k = np.arange(n_prof)
    phi = k * (math.pi / n_ridge)
    rad = np.where(k % 2 == 0, r0, r0 + h)
    ys = np.linspace(-height / 2, height / 2, rings + 1)
    prof = np.stack([rad * np.cos(phi), rad * np.sin(phi)], axis=1)  # (2N, 2) x, z
    side = np.empty((rings + 1, n_prof, 3))
    side[..., 0], side[..., 1], side[..., 2] = prof[None, :, 0], ys[:, None], prof[None, :, 1]
    c_top, c_bot = (rings + 1) * n_prof, (rings + 1) * n_prof + 1
    points = np.concatenate([side.reshape(-1, 3), [[0, height / 2, 0], [0, -height / 2, 0]]])

    # side quads (ring i, facet k): up the axis first, then around -> outward normal
    i_idx, k_idx = np.meshgrid(np.arange(rings), k, indexing="ij")  # (rings, 2N)
    k_next = (k_idx + 1) % n_prof
    quads = np.stack([i_idx * n_prof + k_idx, (i_idx + 1) * n_prof + k_idx,
                      (i_idx + 1) * n_prof + k_next, i_idx * n_prof + k_next], axis=-1)
    quads = quads.reshape(-1, 4)
    top = np.stack([np.full(n_prof, c_top), rings * n_prof + (k + 1) % n_prof,
                    rings * n_prof + k], axis=1)
    bot = np.stack([np.full(n_prof, c_bot), k, (k + 1) % n_prof], axis=1)
    counts = np.concatenate([np.full(len(quads), 4), np.full(2 * n_prof, 3)]).astype(np.int32)
    indices = np.concatenate([quads.ravel(), top.ravel(), bot.ravel()]).astype(np.int32)

    # facet normals in closed form: the edge (ex, ez) of the profile has outward (ez, -ex)
    edge = np.roll(prof, -1, axis=0) - prof  # (2N, 2)
    facet_n = _unit(np.stack([edge[:, 1], np.zeros(n_prof), -edge[:, 0]], axis=1))
    quad_n = np.repeat(np.tile(facet_n, (rings, 1)), 4, axis=0)
    cap_n = np.repeat(np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]]), 3 * n_prof, axis=0)
    normals = np.concatenate([quad_n, cap_n])

    # st: u around (1 at the seam's far side), v along; caps: planar in x, z
    k_corner = np.stack([k_idx, k_idx, k_idx + 1, k_idx + 1], axis=-1).reshape(-1)
    i_corner = np.stack([i_idx, i_idx + 1, i_idx + 1, i_idx], axis=-1).reshape(-1)
    st_side = np.stack([k_corner / n_prof, i_corner / rings], axis=1)
    cap_pts = points[np.concatenate([top.ravel(), bot.ravel()])]
    st_cap = 0.5 + 0.5 * cap_pts[:, [0, 2]] / (r0 + h)
    st = np.concatenate([st_side, st_cap])

    # materials: facets rising from a valley with phi (even k; they face toward decreasing
    # phi, i.e. toward the camera on the left rim) are blue, so the left rim turns blue by
    # masking as in Fig. 1(d); the others and the caps are yellow. Face order: quads
    # (ring-major, facet-minor), then the caps.
    quad_k = np.tile(k, rings)
    face_ids = np.arange(len(counts), dtype=np.int32)
    is_yellow = np.concatenate([quad_k % 2 == 1, np.ones(2 * n_prof, bool)])
    mesh = _MeshSpec(
        name="RidgedCylinder", points=points, counts=counts, indices=indices,
        normals=normals, normals_interp="faceVarying", st=st, st_interp="faceVarying",
        subsets=(("YellowFacets", face_ids[is_yellow], "YellowLambert"),
                 ("BlueFacets", face_ids[~is_yellow], "BluePhong")),
    )
    exponent = 60.0
    materials = (
        _MaterialSpec(
            name="YellowLambert",
            # exact Lambertian in UsdPreviewSurface: specular workflow, zero specular
            preview={"diffuseColor": (0.85, 0.7, 0.08), "useSpecularWorkflow": 1,
                     "specularColor": (0.0, 0.0, 0.0), "roughness": 1.0},
            texelbake_id=SHADER_LAMBERT,
            texelbake_inputs={"diffuseColor": (0.85, 0.7, 0.08)},
        ),
        _MaterialSpec(
            name="BluePhong",
            # Phong exponent n ~ Beckmann/GGX alpha^2 = 2 / (n + 2); UsdPreviewSurface's
            # alpha = roughness^2, so roughness = (2 / (n + 2)) ** 0.25
            preview={"diffuseColor": (0.05, 0.12, 0.55), "useSpecularWorkflow": 1,
                     "specularColor": (0.4, 0.4, 0.4),
                     "roughness": (2.0 / (exponent + 2.0)) ** 0.25},
            texelbake_id=SHADER_PHONG,
            texelbake_inputs={"diffuseColor": (0.05, 0.12, 0.55),
                              "specularColor": (0.4, 0.4, 0.4), "exponent": exponent},
        ),
    )
    # as Fig. 1: seen from the side, lit from the upper front-left, so the left rim shows
    # masking and the right rim shadowing
    lights = (_LightSpec("Sun", "distant", 3.0, (1.0, 1.0, 1.0),
                         toward=_unit([-0.6, 0.5, 1.0])),)
    return _SceneSpec("Cylinder", (mesh,), materials, lights, _unit([0.0, 0.15, 1.0]), {})


# ---- wall ---------------------------------------------------------------------------------


def _wall_blocks(cols: int, rows: int) -> np.ndarray:
    """(nb, 4) float64 block footprints x0, x1, y0, y1 in running bond (odd rows shifted by
    half a block and clipped to the wall, so their end blocks are halves)."""
    bw, bh, gap = _WALL["block_w"], _WALL["block_h"], _WALL["gap"]
    px, py = bw + gap, bh + gap
    width = cols * px
    out = []
    for j in range(rows):  # a handful of rows
        odd = j % 2
        x0 = np.arange(cols + odd) * px + gap / 2 - odd * px / 2
        x1 = np.minimum(x0 + bw, width - gap / 2)
        x0 = np.maximum(x0, gap / 2)
        y0 = np.full_like(x0, j * py + gap / 2)
        out.append(np.stack([x0, x1, y0, y0 + bh], axis=1))
    return np.concatenate(out)


def _wall(p: Mapping[str, int], rng: np.random.Generator) -> _SceneSpec:
    cols, rows, s = p["cols"], p["rows"], p["front_cells"]
    bw, bh, gap = _WALL["block_w"], _WALL["block_h"], _WALL["gap"]
    depth, bevel, jitter = _WALL["depth"], _WALL["bevel"], _WALL["jitter"]
    width, height = cols * (bw + gap), rows * (bh + gap)
    fp = _wall_blocks(cols, rows)  # (nb, 4)
    nb = len(fp)

    # front grid of each block: (s+1)^2 vertices, interior ones jittered in depth
    t = np.linspace(0.0, 1.0, s + 1)
    gx, gy = np.meshgrid(t, t, indexing="xy")  # (s+1, s+1), row = y
    fx0, fx1 = fp[:, 0] + bevel, fp[:, 1] - bevel
    fy0, fy1 = fp[:, 2] + bevel, fp[:, 3] - bevel
    front = np.empty((nb, s + 1, s + 1, 3))
    front[..., 0] = fx0[:, None, None] + gx[None] * (fx1 - fx0)[:, None, None]
    front[..., 1] = fy0[:, None, None] + gy[None] * (fy1 - fy0)[:, None, None]
    interior = np.zeros((s + 1, s + 1), bool)
    interior[1:-1, 1:-1] = True
    front[..., 2] = depth + jitter * rng.uniform(-1.0, 1.0, (nb, s + 1, s + 1)) * interior
    a, b = np.meshgrid(np.arange(s), np.arange(s), indexing="xy")
    v00 = (b * (s + 1) + a).ravel()
    v10, v01, v11 = v00 + 1, v00 + s + 1, v00 + s + 2
    grid_tris = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    nfv = (s + 1) ** 2
    tris = grid_tris[None] + (np.arange(nb) * nfv)[:, None, None]  # (nb, 2s^2, 3)
    front_pts = front.reshape(-1, 3)  # (nb * (s+1)^2, 3), block-major
    front_tris = tris.reshape(-1, 3)
    front_n = _vertex_normals(front_pts, front_tris)

    # chamfers and sides: 8 planar quads per block, 4 own vertices each, CCW from outside
    rim_xy = np.stack([fp[:, [0, 2]], fp[:, [1, 2]], fp[:, [1, 3]], fp[:, [0, 3]]], 1)
    fr_xy = np.stack([np.stack([fx0, fy0], 1), np.stack([fx1, fy0], 1),
                      np.stack([fx1, fy1], 1), np.stack([fx0, fy1], 1)], 1)  # (nb, 4, 2)

    def at_z(xy: np.ndarray, z: float) -> np.ndarray:
        return np.concatenate([xy, np.full(xy.shape[:-1] + (1,), z)], axis=-1)

    rim, frt, base = at_z(rim_xy, depth - bevel), at_z(fr_xy, depth), at_z(rim_xy, 0.0)
    ca, cb = np.arange(4), (np.arange(4) + 1) % 4  # edge a -> b, CCW seen from +z
    chamfer = np.stack([rim[:, ca], rim[:, cb], frt[:, cb], frt[:, ca]], axis=2)
    sides = np.stack([base[:, ca], base[:, cb], rim[:, cb], rim[:, ca]], axis=2)
    quads = np.concatenate([chamfer, sides], axis=1).reshape(-1, 4, 3)  # (nb*8, 4, 3)
    quad_n = _unit(np.cross(quads[:, 1] - quads[:, 0], quads[:, 3] - quads[:, 0]))
    n_q = len(quads)
    q_base = len(front_pts)
    points = np.concatenate([front_pts, quads.reshape(-1, 3)])
    counts = np.concatenate([np.full(len(front_tris), 3), np.full(n_q, 4)]).astype(np.int32)
    indices = np.concatenate([front_tris.ravel(), q_base + np.arange(4 * n_q)]).astype(np.int32)
    normals = np.concatenate([front_n, np.repeat(quad_n, 4, axis=0)])
    st = points[:, :2] / np.array([width, height])
    blocks = _MeshSpec("Blocks", points, counts, indices, normals, "vertex", st, "vertex",
                       material="WallAlbedo")

    # mortar plane: (2 cols) x rows quads at z = 0
    mx, my = 2 * cols, rows
    xs, ys = np.linspace(0, width, mx + 1), np.linspace(0, height, my + 1)
    mgx, mgy = np.meshgrid(xs, ys, indexing="xy")
    m_pts = np.stack([mgx.ravel(), mgy.ravel(), np.zeros(mgx.size)], axis=1)
    a, b = np.meshgrid(np.arange(mx), np.arange(my), indexing="xy")
    m00 = (b * (mx + 1) + a).ravel()
    m_quads = np.stack([m00, m00 + 1, m00 + mx + 2, m00 + mx + 1], axis=1)
    mortar = _MeshSpec(
        "Mortar", m_pts, np.full(len(m_quads), 4, np.int32), m_quads.ravel().astype(np.int32),
        np.tile([0.0, 0.0, 1.0], (len(m_pts), 1)), "vertex",
        m_pts[:, :2] / np.array([width, height]), "vertex", material="WallAlbedo",
    )
    material = _MaterialSpec(
        name="WallAlbedo",
        preview={"useSpecularWorkflow": 1, "specularColor": (0.0, 0.0, 0.0), "roughness": 1.0},
        texture=("diffuseColor", "albedo"),
    )
    texture = _wall_texture(cols, rows, p["tex_res"], rng)
    lights = (_LightSpec("Sun", "distant", 3.0, (1.0, 0.97, 0.92),
                         toward=_unit([-0.55, 0.45, 0.7])),)
    return _SceneSpec("Wall", (blocks, mortar), (material,), lights,
                      _unit([0.25, 0.2, 1.0]), {"albedo": texture})


def _wall_texture(cols: int, rows: int, res: int, rng: np.random.Generator) -> np.ndarray:
    """(h, w, 3) uint8 sRGB albedo: a colour per block (one texel wider than its footprint,
    so bilinear look-ups at block edges stay on the block), speckle, grey mortar."""
    bw, bh, gap = _WALL["block_w"], _WALL["block_h"], _WALL["gap"]
    px, py = bw + gap, bh + gap
    width, height = cols * px, rows * py
    w_px, h_px = res, max(8, round(res * height / width))
    texel = width / w_px
    x = (np.arange(w_px) + 0.5) / w_px * width
    y = (1.0 - (np.arange(h_px) + 0.5) / h_px) * height  # row 0 is the top (t = 1)
    X, Y = np.meshgrid(x, y, indexing="xy")  # (h, w)
    row = np.clip(np.floor(Y / py).astype(int), 0, rows - 1)
    shift = (row % 2) * px / 2
    col = np.floor((X + shift) / px).astype(int)
    lx, ly = X + shift - col * px, Y - row * py
    lo, hi_x, hi_y = gap / 2 - texel, gap / 2 + bw + texel, gap / 2 + bh + texel
    on_block = ((lx >= lo) & (lx <= hi_x) & (ly >= lo) & (ly <= hi_y)
                & (X >= lo) & (X <= width - lo))
    stone = np.array([0.62, 0.50, 0.38])
    # per block: mostly a brightness change, a little hue
    block_rgb = np.clip(stone + rng.normal(0.0, 0.025, (rows, cols + 1, 3))
                        + rng.normal(0.0, 0.08, (rows, cols + 1, 1)), 0.05, 0.95)
    mortar_rgb = np.array([0.58, 0.57, 0.54])
    rgb = np.where(on_block[..., None], block_rgb[row, np.clip(col, 0, cols)], mortar_rgb)
    rgb = rgb + rng.normal(0.0, 0.03, (h_px, w_px, 1))  # speckle
    return _to_srgb8(rgb)


def _to_srgb8(linear: np.ndarray) -> np.ndarray:
    """(h, w, 3) float linear [0, 1] -> uint8 sRGB (the PNG is tagged sRGB)."""
    c = np.clip(linear, 0.0, 1.0)
    srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


# ---- bolt ---------------------------------------------------------------------------------


def _bolt(p: Mapping[str, int], rng: np.random.Generator) -> _SceneSpec:
    n_a, n_l = p["around"], p["along"]
    r, length = _BOLT["radius"], _BOLT["length"]
    cell_w = 2 * math.pi * r / n_a
    bump = _BOLT["bump_ratio"] * cell_w
    y0 = -length / 2
    # half-step lattice: corners (even, even), edge midpoints (mixed), apexes (odd, odd)
    n_p, n_q = 2 * n_a, 2 * n_l + 1
    pp, qq = np.meshgrid(np.arange(n_p), np.arange(n_q), indexing="xy")  # (n_q, n_p)
    theta = pp * (math.pi / n_a)
    rad = np.where((pp % 2 == 1) & (qq % 2 == 1), r + bump, r)
    lattice = np.stack([rad * np.cos(theta), y0 + qq * (length / (2 * n_l)),
                        rad * np.sin(theta)], axis=-1).reshape(-1, 3)
    c_bot = len(lattice)
    points = np.concatenate([lattice, [[0.0, y0, 0.0]]])

    # 8 triangles per cell; corners written with unwrapped p (for st), wrapped for indices.
    # Each triangle is clockwise in the (theta, y) plane, i.e. counter-clockwise seen from
    # outside (x = r cos theta, z = r sin theta).
    ii, jj = np.meshgrid(np.arange(n_a), np.arange(n_l), indexing="xy")
    pc, qc = (2 * ii + 1).ravel(), (2 * jj + 1).ravel()
    rel = {"C": (0, 0), "B": (0, -1), "T": (0, 1), "L": (-1, 0), "R": (1, 0),
           "C00": (-1, -1), "C10": (1, -1), "C11": (1, 1), "C01": (-1, 1)}
    tri_names = [("C", "B", "L"), ("C", "L", "T"), ("C", "T", "R"), ("C", "R", "B"),
                 ("C00", "L", "B"), ("C10", "B", "R"), ("C11", "R", "T"), ("C01", "T", "L")]
    tri_p = np.stack([np.stack([pc + rel[v][0] for v in t], 1) for t in tri_names], 1)
    tri_q = np.stack([np.stack([qc + rel[v][1] for v in t], 1) for t in tri_names], 1)
    tri_p, tri_q = tri_p.reshape(-1, 3), tri_q.reshape(-1, 3)  # (8 cells, 3) unwrapped
    shaft_tris = tri_q * n_p + tri_p % n_p
    k = np.arange(n_p)
    cap = np.stack([np.full(n_p, c_bot), k, (k + 1) % n_p], axis=1)
    tris = np.concatenate([shaft_tris, cap])
    counts = np.full(len(tris), 3, np.int32)
    indices = tris.ravel().astype(np.int32)
    normals = _face_normals_fv(points, counts, indices)
    st_shaft = np.stack([tri_p.ravel() / n_p, tri_q.ravel() / (n_q - 1)], axis=1)
    st_cap = 0.5 + 0.5 * points[cap.ravel()][:, [0, 2]] / (r + bump)
    shaft = _MeshSpec("Shaft", points, counts, indices, normals, "faceVarying",
                      np.concatenate([st_shaft, st_cap]), "faceVarying", material="StainedMetal")

    # hex head on top of the open upper end of the shaft
    rh, hh, y1 = _BOLT["head_radius"], _BOLT["head_height"], y0 + length
    ang = np.arange(6) * (math.pi / 3)
    ring = np.stack([rh * np.cos(ang), np.zeros(6), rh * np.sin(ang)], axis=1)
    h_pts = np.concatenate([ring + [0.0, y1, 0.0], ring + [0.0, y1 + hh, 0.0]])  # bot, top
    k6, k6n = np.arange(6), (np.arange(6) + 1) % 6
    h_quads = np.stack([k6, k6 + 6, k6n + 6, k6n], axis=1)
    h_counts = np.array([4] * 6 + [6, 6], np.int32)
    h_indices = np.concatenate([h_quads.ravel(), 6 + k6[::-1], k6]).astype(np.int32)
    h_normals = _face_normals_fv(h_pts, h_counts, h_indices)
    h_st_side = np.stack([np.stack([k6, k6, k6 + 1, k6 + 1], 1).ravel() / 6.0,
                          np.tile([0.0, 1.0, 1.0, 0.0], 6)], axis=1)
    h_st_caps = 0.5 + 0.5 * h_pts[np.concatenate([6 + k6[::-1], k6])][:, [0, 2]] / rh
    head = _MeshSpec("Head", h_pts, h_counts, h_indices, h_normals, "faceVarying",
                     np.concatenate([h_st_side, h_st_caps]), "faceVarying",
                     material="StainedMetal")
    material = _MaterialSpec(
        name="StainedMetal",
        preview={"metallic": 1.0, "roughness": 0.15},  # GGX alpha = 0.0225: a sharp lobe
        texture=("diffuseColor", "stain"),
    )
    lights = (
        _LightSpec("Sun", "distant", 2.5, (1.0, 1.0, 1.0), toward=_unit([-0.4, 0.6, 1.0])),
        # ~1 W/m^2 at the bolt: intensity * pi * r^2 / d^2 with d ~ 3.4
        _LightSpec("Fill", "sphere", 300.0, (0.9, 0.95, 1.0),
                   position=np.array([2.2, 1.4, 2.2]), radius=0.1),
    )
    stain = _stain_texture(p["tex_res"], rng)
    return _SceneSpec("Bolt", (shaft, head), (material,), lights, _unit([0.3, 0.35, 1.0]),
                      {"stain": stain})


def _periodic_noise(shape: tuple[int, int], sigma_px: float, rng: np.random.Generator
                    ) -> np.ndarray:
    """(h, w) float64 tileable smooth noise in [0, 1]: white noise low-passed by a Gaussian
    in the Fourier domain (periodic by construction, O(n log n) for any sigma)."""
    noise = rng.standard_normal(shape)
    fy = np.fft.fftfreq(shape[0])[:, None]
    fx = np.fft.rfftfreq(shape[1])[None, :]
    gain = np.exp(-2.0 * (math.pi * sigma_px) ** 2 * (fx ** 2 + fy ** 2))
    smooth = np.fft.irfft2(np.fft.rfft2(noise) * gain, s=shape)
    lo, hi = smooth.min(), smooth.max()
    return (smooth - lo) / (hi - lo) if hi > lo else np.zeros(shape)


def _stain_texture(res: int, rng: np.random.Generator) -> np.ndarray:
    """(res, res, 3) uint8 sRGB: silver with tileable rust-brown stains and fine grain."""
    big = _periodic_noise((res, res), res / 24.0, rng)
    grain = _periodic_noise((res, res), 1.0, rng)
    t = np.clip((big - 0.55) / 0.2, 0.0, 1.0)
    mask = (t * t * (3.0 - 2.0 * t))[..., None]  # smoothstep
    silver, stain = np.array([0.80, 0.80, 0.82]), np.array([0.42, 0.30, 0.18])
    rgb = (1.0 - mask) * silver + mask * stain + 0.06 * (grain[..., None] - 0.5)
    return _to_srgb8(rgb)


# ---- cloisonne ----------------------------------------------------------------------------


def _icosphere(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: points (n, 3) float64, tris (20 * 4**levels, 3) int64, outward CCW.

    Hand-written (midpoint subdivision, vectorized per level): open3d has it, but importing
    open3d alone takes longer than the 1 s budget of writing a small scene.
    """
    g = (1.0 + math.sqrt(5.0)) / 2.0
    pts = _unit([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                 [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]])
    tris = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                     [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                     [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                     [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)
    for _ in range(levels):  # a handful of levels
        edges = np.sort(np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], 1), -1)
        uniq, inv = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
        mids = _unit(pts[uniq[:, 0]] + pts[uniq[:, 1]])
        m = len(pts) + inv.reshape(-1, 3)  # (f, 3) midpoint ids of edges 01, 12, 20
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        tris = np.concatenate([np.stack([a, m[:, 0], m[:, 2]], 1),
                               np.stack([b, m[:, 1], m[:, 0]], 1),
                               np.stack([c, m[:, 2], m[:, 1]], 1),
                               np.stack([m[:, 0], m[:, 1], m[:, 2]], 1)])
        pts = np.concatenate([pts, mids])
    return pts, tris


def _cloisonne(p: Mapping[str, int], rng: np.random.Generator) -> _SceneSpec:
    dirs, tris = _icosphere(p["subdiv"])
    centres = _unit(rng.standard_normal((p["bumps"], 3)))  # (k, 3)
    heights = rng.uniform(0.4, 1.0, p["bumps"]) * _CLOISONNE["amplitude"]
    width = _CLOISONNE["bump_width"] * (24.0 / p["bumps"]) ** 0.25  # more, finer bumps
    ang2 = 2.0 * (1.0 - dirs @ centres.T)  # (n, k) squared chord length
    radius = 1.0 + (heights[None, :] * np.exp(-ang2 / width ** 2)).sum(axis=1)
    points = dirs * radius[:, None] * np.asarray(_CLOISONNE_SCALE)
    normals = _vertex_normals(points, tris)
    # st: spherical, faceVarying so faces across the u seam do not wrap backwards
    corner = dirs[tris.ravel()]
    u = (np.arctan2(corner[:, 2], corner[:, 0]) / (2 * math.pi) + 0.5).reshape(-1, 3)
    wraps = (u.max(axis=1) - u.min(axis=1)) > 0.5
    u = np.where(wraps[:, None] & (u < 0.5), u + 1.0, u)
    v = 0.5 + np.arcsin(np.clip(corner[:, 1], -1.0, 1.0)) / math.pi
    st = np.stack([u.ravel(), v], axis=1)
    mesh = _MeshSpec("Blob", points, np.full(len(tris), 3, np.int32),
                     tris.ravel().astype(np.int32), normals, "vertex", st, "faceVarying",
                     material="Cloisonne")
    inputs = dict(CELLULAR_INPUTS)
    avg = tuple(0.5 * (a + b) for a, b in zip(inputs["cellColorA"], inputs["cellColorB"],
                                              strict=True))
    material = _MaterialSpec(
        name="Cloisonne",
        preview={"diffuseColor": avg, "roughness": 0.4},  # a flat stand-in for viewers
        texelbake_id=SHADER_CELLULAR, texelbake_inputs=inputs,
    )
    lights = (
        _LightSpec("Sun", "distant", 2.5, (1.0, 0.98, 0.95), toward=_unit([0.5, 0.7, 0.8])),
        _LightSpec("Fill", "sphere", 400.0, (0.85, 0.9, 1.0),
                   position=np.array([-2.6, 1.0, 2.2]), radius=0.15),
    )
    return _SceneSpec("Cloisonne", (mesh,), (material,), lights, _unit([0.35, 0.3, 1.0]), {})


_BUILDERS = MappingProxyType(
    {"cylinder": _cylinder, "wall": _wall, "bolt": _bolt, "cloisonne": _cloisonne}
)


# ------------------------------------------------------------------------------------------
# Authoring
# ------------------------------------------------------------------------------------------


def _sdf_type(shader_id: str, input_name: str) -> Sdf.ValueTypeName:
    """The Sdf type Sdr declares for an input (so the validator's type check agrees)."""
    node = Sdr.Registry().GetShaderNodeByIdentifier(shader_id)
    prop = node.GetShaderInput(input_name) if node else None
    if prop is None:
        raise SettingsError(f"shader {shader_id!r} has no input {input_name!r} in Sdr")
    return prop.GetTypeAsSdfType().GetSdfType()


def _set_inputs(shader: UsdShade.Shader, shader_id: str, values: Mapping[str, Any]) -> None:
    for name in sorted(values):
        shader.CreateInput(name, _sdf_type(shader_id, name)).Set(values[name])


def _author_material(stage: Usd.Stage, path: str, spec: _MaterialSpec,
                     texture_files: Mapping[str, str]) -> UsdShade.Material:
    material = UsdShade.Material.Define(stage, path)
    preview = UsdShade.Shader.Define(stage, f"{path}/PreviewSurface")
    preview.CreateIdAttr(SHADER_PREVIEW)
    _set_inputs(preview, SHADER_PREVIEW, spec.preview)
    material.CreateSurfaceOutput().ConnectToSource(
        preview.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    if spec.texture is not None:
        input_name, role = spec.texture
        reader = UsdShade.Shader.Define(stage, f"{path}/StReader")
        reader.CreateIdAttr("UsdPrimvarReader_float2")
        _set_inputs(reader, "UsdPrimvarReader_float2", {"varname": "st"})
        tex = UsdShade.Shader.Define(stage, f"{path}/{role.capitalize()}Texture")
        tex.CreateIdAttr("UsdUVTexture")
        _set_inputs(tex, "UsdUVTexture", {
            "file": Sdf.AssetPath(f"./{texture_files[role]}"),
            "wrapS": "repeat", "wrapT": "repeat", "sourceColorSpace": "sRGB",
            "fallback": Gf.Vec4f(0.5, 0.5, 0.5, 1.0),
        })
        tex.CreateInput("st", _sdf_type("UsdUVTexture", "st")).ConnectToSource(
            reader.CreateOutput("result", Sdf.ValueTypeNames.Float2))
        preview.CreateInput(input_name, _sdf_type(SHADER_PREVIEW, input_name)).ConnectToSource(
            tex.CreateOutput("rgb", Sdf.ValueTypeNames.Float3))
    if spec.texelbake_id is not None:
        own = UsdShade.Shader.Define(stage, f"{path}/TexelbakeSurface")
        own.CreateIdAttr(spec.texelbake_id)
        _set_inputs(own, spec.texelbake_id, spec.texelbake_inputs)
        material.CreateSurfaceOutput("texelbake").ConnectToSource(
            own.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    return material


def _bind(prim: Usd.Prim, material: UsdShade.Material) -> None:
    UsdShade.MaterialBindingAPI.Apply(prim).Bind(material)


def _author_mesh(stage: Usd.Stage, path: str, spec: _MeshSpec,
                 materials: Mapping[str, UsdShade.Material]) -> UsdGeom.Mesh:
    mesh = UsdGeom.Mesh.Define(stage, path)
    mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    mesh.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(spec.points, np.float32)))
    mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(spec.counts)))
    mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(spec.indices)))
    mesh.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(spec.normals,
                                                                         np.float32)))
    mesh.SetNormalsInterpolation(spec.normals_interp)
    UsdGeom.PrimvarsAPI(mesh).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, spec.st_interp
    ).Set(Vt.Vec2fArray.FromNumpy(np.ascontiguousarray(spec.st, np.float32)))
    mesh.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(mesh,
                                                                     Usd.TimeCode.Default()))
    if spec.material is not None:
        _bind(mesh.GetPrim(), materials[spec.material])
    if spec.subsets:
        binding = UsdShade.MaterialBindingAPI.Apply(mesh.GetPrim())
        for name, faces, mat in spec.subsets:
            subset = binding.CreateMaterialBindSubset(
                name, Vt.IntArray.FromNumpy(np.ascontiguousarray(faces, np.int32)),
                UsdGeom.Tokens.face)
            _bind(subset.GetPrim(), materials[mat])
        binding.SetMaterialBindSubsetsFamilyType(UsdGeom.Tokens.partition)
    return mesh


def _look_at(eye: np.ndarray, target: np.ndarray, up: np.ndarray) -> Gf.Matrix4d:
    """USD (row-vector) transform of a camera or light at `eye` whose local -Z points at
    `target` and whose local +Y leans toward `up`."""
    z = _unit(eye - target)
    x = _unit(np.cross(up, z))
    y = np.cross(z, x)
    m = np.eye(4)
    m[0, :3], m[1, :3], m[2, :3], m[3, :3] = x, y, z, eye
    m = np.round(m, 12) + 0.0  # no -0.0 or 1e-17 noise in the written layer
    return Gf.Matrix4d(m.tolist())


def _author_camera(stage: Usd.Stage, path: str, centre: np.ndarray, radius: float,
                   view_from: np.ndarray) -> None:
    focal, aperture = 50.0, 24.0  # mm; a 27 degree square field of view
    half_fov = math.atan(0.5 * aperture / focal)
    dist = 1.1 * radius / math.sin(half_fov)
    cam = UsdGeom.Camera.Define(stage, path)
    cam.CreateFocalLengthAttr(focal)
    cam.CreateHorizontalApertureAttr(aperture)
    cam.CreateVerticalApertureAttr(aperture)
    cam.CreateClippingRangeAttr(Gf.Vec2f(max(dist - 2.0 * radius, 0.01 * dist),
                                         dist + 2.0 * radius))
    eye = centre + dist * view_from
    cam.AddTransformOp().Set(_look_at(eye, centre, np.array([0.0, 1.0, 0.0])))


def _author_light(stage: Usd.Stage, path: str, spec: _LightSpec, centre: np.ndarray,
                  radius: float) -> None:
    if spec.kind == "distant":
        light = UsdLux.DistantLight.Define(stage, path)
        # a distant light shines down its local -Z: put +Z on `toward`
        up = np.array([0.0, 1.0, 0.0]) if abs(spec.toward[1]) < 0.9 else np.array([1.0, 0, 0])
        eye = centre + 3.0 * radius * spec.toward
        UsdGeom.Xformable(light).AddTransformOp().Set(_look_at(eye, centre, up))
    else:
        light = UsdLux.SphereLight.Define(stage, path)
        light.CreateRadiusAttr(spec.radius)
        light.CreateTreatAsPointAttr(False)
        UsdGeom.Xformable(light).AddTranslateOp().Set(Gf.Vec3d(*spec.position.tolist()))
        light.CreateExtentAttr(UsdGeom.Boundable.ComputeExtentFromPlugins(
            UsdGeom.Boundable(light), Usd.TimeCode.Default()))
    light.CreateIntensityAttr(spec.intensity)
    light.CreateColorAttr(Gf.Vec3f(*spec.color))


def build_stage(name: str, size: str = "small") -> tuple[Usd.Stage, dict[str, np.ndarray]]:
    """The scene as an in-memory stage plus its textures {file name: (h, w, 3) uint8}.

    Texture file names are relative to the folder the layer will be written to. Raises
    SettingsError for an unknown name or size.
    """
    _check(name, size)
    register_shader_definitions()
    spec = _BUILDERS[name](SCENE_PARAMS[name][size], np.random.default_rng(_SEEDS[name]))
    tex_files = {role: f"{name}_{size}_{role}.png" for role in sorted(spec.textures)}

    stage = Usd.Stage.CreateInMemory(f"{name}_{size}.usda")
    UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y)
    UsdGeom.SetStageMetersPerUnit(stage, _METERS_PER_UNIT[name])
    layer = stage.GetRootLayer()
    layer.documentation = f"texelbake test scene '{name}' ({size}), written by texelbake.scenes"
    layer.customLayerData = {"texelbake": {"scene": name, "size": size, "seed": _SEEDS[name]}}
    root_path = f"/{spec.root}"
    root = UsdGeom.Xform.Define(stage, root_path)
    Usd.ModelAPI(root.GetPrim()).SetKind(Kind.Tokens.component)
    stage.SetDefaultPrim(root.GetPrim())

    UsdGeom.Scope.Define(stage, f"{root_path}/Looks")
    materials = {m.name: _author_material(stage, f"{root_path}/Looks/{m.name}", m, tex_files)
                 for m in spec.materials}
    UsdGeom.Xform.Define(stage, f"{root_path}/Geom")
    for m in spec.meshes:
        _author_mesh(stage, f"{root_path}/Geom/{m.name}", m, materials)

    pts = np.concatenate([m.points for m in spec.meshes])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    centre = 0.5 * (lo + hi)
    radius = float(np.linalg.norm(pts - centre, axis=1).max())
    UsdGeom.Xform.Define(stage, f"{root_path}/Lights")
    for light in spec.lights:
        _author_light(stage, f"{root_path}/Lights/{light.name}", light, centre, radius)
    _author_camera(stage, f"{root_path}/Camera", centre, radius, spec.view_from)
    hint = UsdGeom.BBoxCache(Usd.TimeCode.Default(), [UsdGeom.Tokens.default_])
    UsdGeom.ModelAPI(root.GetPrim()).SetExtentsHint(
        UsdGeom.ModelAPI(root.GetPrim()).ComputeExtentsHint(hint))
    return stage, {tex_files[role]: spec.textures[role] for role in tex_files}


def _atomic_target(final: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{final.stem}.", suffix=f".tmp{final.suffix}",
                               dir=final.parent)
    os.close(fd)
    os.chmod(tmp, 0o644)  # mkstemp makes 0600; these are shared, read-only assets
    return Path(tmp)


def _write_png(path: Path, pixels: np.ndarray) -> None:
    tmp = _atomic_target(path)
    try:
        h, w, c = pixels.shape
        out = oiio.ImageOutput.create(str(tmp))
        if out is None or not out.open(str(tmp), oiio.ImageSpec(w, h, c, "uint8")):
            raise OSError(f"cannot write {path}: {oiio.geterror()}")
        ok = out.write_image(np.ascontiguousarray(pixels))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {out.geterror()}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_scene(name: str, path: str | Path, size: str = "small") -> Path:
    """Write test scene `name` at `size` to `path` (.usda, .usdc or .usd) and its PNG
    textures beside it; return the layer's path.

    Deterministic: the same (name, size) gives byte-identical files. Every file is written
    to a temporary name in the target folder and renamed into place; the folder is created
    if missing. Raises SettingsError naming the field for an unknown name, size or suffix.
    """
    _check(name, size)
    path = Path(path)
    if path.suffix not in LAYER_SUFFIXES:
        raise SettingsError(
            f"field 'path': {str(path)!r} has suffix {path.suffix!r}; expected one of "
            f"{', '.join(LAYER_SUFFIXES)}"
        )
    stage, textures = build_stage(name, size)
    path.parent.mkdir(parents=True, exist_ok=True)
    for file_name in sorted(textures):  # textures first: the layer must resolve them
        _write_png(path.parent / file_name, textures[file_name])
    tmp = _atomic_target(path)
    try:
        if not stage.GetRootLayer().Export(str(tmp)):
            raise OSError(f"cannot write {path}")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)
    return path


register_shader_definitions()
