"""Small generated scenes for the a_vis tests and benchmarks (seeded, deterministic)."""

from __future__ import annotations

import numpy as np


def grid_mesh(k: int, height) -> tuple[np.ndarray, np.ndarray]:
    """(k+1)^2 vertices on [0, 1]^2 with z = height(x, y), 2 k^2 triangles facing +z."""
    e = np.linspace(0.0, 1.0, k + 1)
    y, x = np.meshgrid(e, e, indexing="ij")
    pts = np.column_stack([x.ravel(), y.ravel(), height(x.ravel(), y.ravel())])
    i = np.arange(k)
    iy, ix = np.meshgrid(i, i, indexing="ij")
    v00 = (iy * (k + 1) + ix).ravel()
    v01, v10, v11 = v00 + 1, v00 + (k + 1), v00 + (k + 2)
    faces = np.concatenate([np.column_stack([v00, v01, v11]), np.column_stack([v00, v11, v10])])
    return pts, faces.astype(np.int64)


def periodic_height(amp: float = 0.04, seed: int = 0, n_waves: int = 4):
    """A smooth height field with period 1 in x and y (integer wave numbers)."""
    rng = np.random.default_rng(seed)
    kx = rng.integers(1, 4, n_waves)
    ky = rng.integers(-3, 4, n_waves)
    ph = rng.random(n_waves) * 2 * np.pi
    a = amp * (0.5 + rng.random(n_waves)) / n_waves

    def h(x, y):
        arg = 2 * np.pi * (np.outer(x, kx) + np.outer(y, ky)) + ph
        return np.sin(arg) @ a

    return h


def tile3x3(pts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh and its 8 neighbours shifted by +-1 in x and y (periodic occluders)."""
    all_p, all_f = [], []
    for c, (dx, dy) in enumerate((a, b) for a in (-1, 0, 1) for b in (-1, 0, 1)):
        all_p.append(pts + np.array([dx, dy, 0.0]))
        all_f.append(faces + c * pts.shape[0])
    return np.concatenate(all_p), np.concatenate(all_f)


def face_normals_areas(pts: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cr = np.cross(pts[faces[:, 1]] - pts[faces[:, 0]], pts[faces[:, 2]] - pts[faces[:, 0]])
    a2 = np.linalg.norm(cr, axis=1)
    return cr / np.where(a2 > 0, a2, 1.0)[:, None], 0.5 * a2


def sample_faces(pts: np.ndarray, faces: np.ndarray, q: int, seed: int = 0):
    """q^2 stratified jittered samples per triangle (area-preserving square->triangle map).

    returns positions (m, 3), geometric normals (m, 3), areas (m,), face id (m,)
    """
    rng = np.random.default_rng(seed)
    nf = faces.shape[0]
    s = q * q
    g = np.arange(q)
    gy, gx = np.meshgrid(g, g, indexing="ij")
    u = (gx.ravel()[None, :] + rng.random((nf, s))) / q
    v = (gy.ravel()[None, :] + rng.random((nf, s))) / q
    su = np.sqrt(u)
    b0, b1 = 1 - su, su * (1 - v)
    b2 = su * v
    p0, p1, p2 = (pts[faces[:, i]][:, None, :] for i in range(3))
    pos = b0[..., None] * p0 + b1[..., None] * p1 + b2[..., None] * p2
    nrm, area = face_normals_areas(pts, faces)
    fid = np.repeat(np.arange(nf), s)
    return (pos.reshape(-1, 3), nrm[fid], np.repeat(area / s, s), fid)


def texel_of_xy(pos: np.ndarray, n_side: int) -> np.ndarray:
    """Row-major texel id iy * N + ix of the xy position on [0, 1)^2."""
    ix = np.clip(np.floor(pos[:, 0] * n_side), 0, n_side - 1).astype(np.int64)
    iy = np.clip(np.floor(pos[:, 1] * n_side), 0, n_side - 1).astype(np.int64)
    return iy * n_side + ix


def uv_sphere(n_lat: int, n_lon: int, radius=1.0, bump=None):
    """A closed UV sphere, outward faces; optional radial bump(theta, phi) (relative)."""
    th = np.linspace(0, np.pi, n_lat + 1)[1:-1]
    ph = np.linspace(0, 2 * np.pi, n_lon, endpoint=False)
    T, P = np.meshgrid(th, ph, indexing="ij")
    r = radius * (1.0 + (bump(T, P) if bump is not None else 0.0))
    ring = np.stack([r * np.sin(T) * np.cos(P), r * np.sin(T) * np.sin(P), r * np.cos(T)], -1)
    pts = np.concatenate([[[0, 0, radius]], ring.reshape(-1, 3), [[0, 0, -radius]]])
    faces = []
    j = np.arange(n_lon)
    jn = (j + 1) % n_lon
    faces.append(np.column_stack([np.zeros(n_lon, int), 1 + j, 1 + jn]))
    for i in range(n_lat - 2):
        a, b = 1 + i * n_lon, 1 + (i + 1) * n_lon
        faces.append(np.column_stack([a + j, b + j, b + jn]))
        faces.append(np.column_stack([a + j, b + jn, a + jn]))
    last = pts.shape[0] - 1
    base = 1 + (n_lat - 2) * n_lon
    faces.append(np.column_stack([base + j, np.full(n_lon, last), base + jn]))
    return pts, np.concatenate(faces).astype(np.int64)


def texel_of_latlong(pos: np.ndarray, n_side: int) -> np.ndarray:
    """Texel id on an N x N (theta, phi) grid of a sphere-like object centred at 0."""
    r = np.linalg.norm(pos, axis=1)
    th = np.arccos(np.clip(pos[:, 2] / r, -1, 1))
    ph = np.mod(np.arctan2(pos[:, 1], pos[:, 0]), 2 * np.pi)
    iy = np.clip(np.floor(th / np.pi * n_side), 0, n_side - 1).astype(np.int64)
    ix = np.clip(np.floor(ph / (2 * np.pi) * n_side), 0, n_side - 1).astype(np.int64)
    return iy * n_side + ix
