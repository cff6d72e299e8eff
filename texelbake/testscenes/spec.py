"""Scene descriptions as plain arrays (meshes, materials, lights), authored by `author`."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np


@dataclass(frozen=True, eq=False)
class MeshSpec:
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
class MaterialSpec:
    """preview: UsdPreviewSurface constant inputs; texture: (preview input, texture role)
    driven by a UsdUVTexture; texelbake_id/texelbake_inputs: the texelbake shader, if any."""

    name: str
    preview: Mapping[str, Any]
    texture: tuple[str, str] | None = None
    texelbake_id: str | None = None
    texelbake_inputs: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True, eq=False)
class LightSpec:
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
class SceneSpec:
    root: str
    meshes: tuple[MeshSpec, ...]
    materials: tuple[MaterialSpec, ...]
    lights: tuple[LightSpec, ...]
    view_from: np.ndarray  # (3,) direction from the object's centre toward the camera
    textures: Mapping[str, np.ndarray]  # role -> (h, w, 3) uint8, row 0 = top (t = 1)


def unit(v: Any) -> np.ndarray:
    v = np.asarray(v, dtype=np.float64)
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def face_normals_fv(points: np.ndarray, counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(sum(counts), 3) float64 flat per-face normals repeated on every corner, from the
    first three corners of each (planar, convex) face."""
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    p0, p1, p2 = (points[indices[starts + k]] for k in range(3))
    n = unit(np.cross(p1 - p0, p2 - p0))  # (f, 3)
    return np.repeat(n, counts, axis=0)


def vertex_normals(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(n, 3) float64 area-weighted vertex normals of a triangle mesh tris : (f, 3)."""
    tri = points[tris]  # (f, 3, 3)
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    acc = np.zeros_like(points)
    for k in range(3):  # three corners, not a loop over faces
        np.add.at(acc, tris[:, k], fn)
    return unit(acc)


def to_srgb8(linear: np.ndarray) -> np.ndarray:
    """(h, w, 3) float linear [0, 1] -> uint8 sRGB (the PNG is tagged sRGB)."""
    from texelbake.io.images import to_uint8

    return to_uint8(linear)
