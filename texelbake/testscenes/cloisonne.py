"""A bumpy blob with the cellular (cloisonné-like) multi-material shader."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from texelbake.model import SHADER_CELLULAR
from texelbake.testscenes.params import CELLULAR_INPUTS, CLOISONNE, CLOISONNE_SCALE
from texelbake.testscenes.spec import (
    LightSpec,
    MaterialSpec,
    MeshSpec,
    SceneSpec,
    unit,
    vertex_normals,
)


def _icosphere(levels: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit icosphere: points (n, 3) float64, tris (20 * 4**levels, 3) int64, outward CCW.

    Hand-written (midpoint subdivision, vectorized per level): open3d has it, but importing
    open3d alone takes longer than the 1 s budget of writing a small scene.
    """
    g = (1.0 + math.sqrt(5.0)) / 2.0
    pts = unit([[-1, g, 0], [1, g, 0], [-1, -g, 0], [1, -g, 0], [0, -1, g], [0, 1, g],
                 [0, -1, -g], [0, 1, -g], [g, 0, -1], [g, 0, 1], [-g, 0, -1], [-g, 0, 1]])
    tris = np.array([[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11],
                     [1, 5, 9], [5, 11, 4], [11, 10, 2], [10, 7, 6], [7, 1, 8],
                     [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9],
                     [4, 9, 5], [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]], np.int64)
    for _ in range(levels):  # a handful of levels
        edges = np.sort(np.stack([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]], 1), -1)
        uniq, inv = np.unique(edges.reshape(-1, 2), axis=0, return_inverse=True)
        mids = unit(pts[uniq[:, 0]] + pts[uniq[:, 1]])
        m = len(pts) + inv.reshape(-1, 3)  # (f, 3) midpoint ids of edges 01, 12, 20
        a, b, c = tris[:, 0], tris[:, 1], tris[:, 2]
        tris = np.concatenate([np.stack([a, m[:, 0], m[:, 2]], 1),
                               np.stack([b, m[:, 1], m[:, 0]], 1),
                               np.stack([c, m[:, 2], m[:, 1]], 1),
                               np.stack([m[:, 0], m[:, 1], m[:, 2]], 1)])
        pts = np.concatenate([pts, mids])
    return pts, tris


def build_cloisonne(p: Mapping[str, int], rng: np.random.Generator) -> SceneSpec:
    dirs, tris = _icosphere(p["subdiv"])
    centres = unit(rng.standard_normal((p["bumps"], 3)))  # (k, 3)
    heights = rng.uniform(0.4, 1.0, p["bumps"]) * CLOISONNE["amplitude"]
    width = CLOISONNE["bump_width"] * (24.0 / p["bumps"]) ** 0.25  # more, finer bumps
    ang2 = 2.0 * (1.0 - dirs @ centres.T)  # (n, k) squared chord length
    radius = 1.0 + (heights[None, :] * np.exp(-ang2 / width ** 2)).sum(axis=1)
    points = dirs * radius[:, None] * np.asarray(CLOISONNE_SCALE)
    normals = vertex_normals(points, tris)
    # st: spherical, faceVarying so faces across the u seam do not wrap backwards
    corner = dirs[tris.ravel()]
    u = (np.arctan2(corner[:, 2], corner[:, 0]) / (2 * math.pi) + 0.5).reshape(-1, 3)
    wraps = (u.max(axis=1) - u.min(axis=1)) > 0.5
    u = np.where(wraps[:, None] & (u < 0.5), u + 1.0, u)
    v = 0.5 + np.arcsin(np.clip(corner[:, 1], -1.0, 1.0)) / math.pi
    st = np.stack([u.ravel(), v], axis=1)
    mesh = MeshSpec("Blob", points, np.full(len(tris), 3, np.int32),
                     tris.ravel().astype(np.int32), normals, "vertex", st, "faceVarying",
                     material="Cloisonne")
    inputs = dict(CELLULAR_INPUTS)
    avg = tuple(0.5 * (a + b) for a, b in zip(inputs["cellColorA"], inputs["cellColorB"],
                                              strict=True))
    material = MaterialSpec(
        name="Cloisonne",
        preview={"diffuseColor": avg, "roughness": 0.4},  # a flat stand-in for viewers
        texelbake_id=SHADER_CELLULAR, texelbake_inputs=inputs,
    )
    lights = (
        LightSpec("Sun", "distant", 2.5, (1.0, 0.98, 0.95), toward=unit([0.5, 0.7, 0.8])),
        LightSpec("Fill", "sphere", 400.0, (0.85, 0.9, 1.0),
                   position=np.array([-2.6, 1.0, 2.2]), radius=0.15),
    )
    return SceneSpec("Cloisonne", (mesh,), (material,), lights, unit([0.35, 0.3, 1.0]), {})
