"""Refining a LOD mesh so that it can follow a warp: 1 → 4 subdivision of every triangle
(edge midpoints shared, so the refined mesh is as watertight as the input), atlas uvs split
with each face (exact: uvs are linear on a triangle), per-vertex arrays interpolated.

A QEM-simplified M_i of a straight limb keeps no edge loops along it (they are redundant at
rest): deformed vertex by vertex it stays a chord of the bent M_org — 0.8 (in units where
the radius is 1) from the arm bent 90°, against 0.2 at rest. Refining it at render time does
not change the rest surface nor the atlas map, only how finely Ψ is sampled on it.
"""

from __future__ import annotations

import math

import numpy as np

from texelbake.errors import ShapeError


def subdivide(vertices: np.ndarray, faces: np.ndarray, corner_uvs: np.ndarray,
              extra: tuple[np.ndarray, ...] = ()
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[np.ndarray, ...],
                         np.ndarray]:
    """One 1 → 4 subdivision.

    vertices (n, 3), faces (f, 3), corner_uvs (f, 3, 2), extra: per-vertex arrays (n, k)
    (midpoints: the mean of the edge's ends)
    returns (vertices (n + e, 3), faces (4f, 3), corner_uvs (4f, 3, 2), extra, parent (4f,)
    the input face of each output face)"""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    cuv = np.asarray(corner_uvs, dtype=np.float64)
    if cuv.shape != (f.shape[0], 3, 2):
        raise ShapeError(f"corner_uvs must be ({f.shape[0]}, 3, 2), got {cuv.shape}")
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    uniq, inv = np.unique(edges, axis=0, return_inverse=True)
    mid = v.shape[0] + inv.reshape(3, -1)  # (3, f): midpoints of edges 01, 12, 20
    v_out = np.concatenate([v, 0.5 * (v[uniq[:, 0]] + v[uniq[:, 1]])])
    extra_out = tuple(np.concatenate([np.asarray(x, np.float64),
                                      0.5 * (np.asarray(x, np.float64)[uniq[:, 0]]
                                             + np.asarray(x, np.float64)[uniq[:, 1]])])
                      for x in extra)
    a, b, c = f.T
    m01, m12, m20 = mid
    f_out = np.concatenate([np.stack([a, m01, m20], 1), np.stack([m01, b, m12], 1),
                            np.stack([m20, m12, c], 1), np.stack([m01, m12, m20], 1)])
    u0, u1, u2 = cuv[:, 0], cuv[:, 1], cuv[:, 2]
    w01, w12, w20 = 0.5 * (u0 + u1), 0.5 * (u1 + u2), 0.5 * (u2 + u0)
    cuv_out = np.concatenate([np.stack([u0, w01, w20], 1), np.stack([w01, u1, w12], 1),
                              np.stack([w20, w12, u2], 1), np.stack([w01, w12, w20], 1)])
    parent = np.tile(np.arange(f.shape[0]), 4)
    return v_out, f_out, cuv_out, extra_out, parent


def refine_levels(vertices: np.ndarray, faces: np.ndarray, max_edge: float,
                  max_levels: int = 4) -> int:
    """Subdivisions that bring the longest edge to at most `max_edge` (each halves it),
    capped at `max_levels` (4: 256 faces per face)."""
    t = np.asarray(vertices, dtype=np.float64)[np.asarray(faces, dtype=np.int64)]
    if t.shape[0] == 0 or not max_edge > 0:
        return 0
    longest = float(np.linalg.norm(t - np.roll(t, 1, axis=1), axis=2).max())
    if longest <= max_edge:
        return 0
    return int(min(max_levels, math.ceil(math.log2(longest / max_edge))))
