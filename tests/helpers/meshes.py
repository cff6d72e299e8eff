"""Small meshes built with numpy / open3d for the geometry tests (not a test module)."""

from __future__ import annotations

import numpy as np
import open3d as o3d


def plane_grid(nx: int, ny: int, size: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Grid on z = 0 over [0, size]^2, nx * ny quads split in two, normals +z.

    returns : (vertices ((nx+1)(ny+1), 3) float64, faces (2 nx ny, 3) int64)
    """
    xs = np.linspace(0.0, size, nx + 1)
    ys = np.linspace(0.0, size, ny + 1)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")  # (ny+1, nx+1)
    vertices = np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)])
    i, j = np.meshgrid(np.arange(nx), np.arange(ny), indexing="xy")
    v00 = (j * (nx + 1) + i).ravel()
    v10 = v00 + 1
    v01 = v00 + nx + 1
    v11 = v01 + 1
    faces = np.concatenate([np.stack([v00, v10, v11], 1), np.stack([v00, v11, v01], 1)])
    return vertices, faces.astype(np.int64)


def icosphere(subdivisions: int, radius: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Icosphere (open3d icosahedron, midpoint-subdivided, projected to the sphere)."""
    mesh = o3d.geometry.TriangleMesh.create_icosahedron(1.0)
    if subdivisions:
        mesh = mesh.subdivide_midpoint(subdivisions)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    v = radius * v / np.linalg.norm(v, axis=1, keepdims=True)
    return v, np.asarray(mesh.triangles, dtype=np.int64)


def bumpy_sphere(subdivisions: int, amplitude: float = 0.05, freq: int = 6):
    """Icosphere with radial bumps r = 1 + a sin(f x) sin(f y) sin(f z)."""
    v, f = icosphere(subdivisions)
    r = 1.0 + amplitude * np.sin(freq * v[:, 0]) * np.sin(freq * v[:, 1]) * np.sin(freq * v[:, 2])
    return v * r[:, None], f


def box(lo=(0.0, 0.0, 0.0), hi=(1.0, 1.0, 1.0)) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box, 12 outward-facing triangles."""
    mesh = o3d.geometry.TriangleMesh.create_box(1.0, 1.0, 1.0)
    v = np.asarray(mesh.vertices, dtype=np.float64)
    lo = np.asarray(lo, dtype=np.float64)
    hi = np.asarray(hi, dtype=np.float64)
    return lo + v * (hi - lo), np.asarray(mesh.triangles, dtype=np.int64)


def soup(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The same surface as a triangle soup (three fresh vertices per face)."""
    return vertices[faces].reshape(-1, 3), np.arange(faces.size, dtype=np.int64).reshape(-1, 3)


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """(3, 3) float64 rotation (QR of a Gaussian matrix, sign-fixed, det +1)."""
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    if np.linalg.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q
