"""Triangle meshes as two arrays, input checks, and welding of triangle soups.

Ingest hands over M_org as a triangle soup (vertices may be duplicated per face corner to
carry per-corner normals and UVs). Quadric simplification needs a connected mesh, so
`weld` merges vertices closer than `TOL.merge * bbox_diag` and keeps the map from the old
vertices to the new ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from texelbake.errors import NumericalError, ShapeError
from texelbake.tol import TOL


def check_points(points: object, name: str = "points") -> np.ndarray:
    """Coerce to (n, 3) float64 and require finite values.

    raises ShapeError (wrong shape) or NumericalError (NaN / Inf, naming the first bad row).
    """
    arr = np.asarray(points, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError(f"{name} must have shape (n, 3), got {arr.shape}")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise NumericalError(
            f"{name} must be finite; {int(bad.sum())} rows hold NaN/Inf (first: row {row})"
        )
    return arr


def check_faces(faces: object, n_vertices: int, name: str = "faces") -> np.ndarray:
    """Coerce to (f, 3) int64 and require indices in [0, n_vertices).

    raises ShapeError naming the first bad face and the valid range.
    """
    arr = np.asarray(faces)
    if arr.size == 0:
        return np.zeros((0, 3), dtype=np.int64)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ShapeError(f"{name} must have shape (f, 3), got {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise ShapeError(f"{name} must hold integers, got dtype {arr.dtype}")
    arr = arr.astype(np.int64, copy=False)
    bad = ((arr < 0) | (arr >= n_vertices)).any(axis=1)
    if bad.any():
        row = int(np.flatnonzero(bad)[0])
        raise ShapeError(f"{name}[{row}] = {arr[row].tolist()} indexes outside [0, {n_vertices})")
    return arr


def triangle_areas(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f,) float64 areas of the triangles `points[faces]`."""
    tri = points[faces]  # (f, 3, 3)
    return 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)


def face_normals(points: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(f, 3) float64 unit geometric normals of the triangles `points[faces]`, counter-
    clockwise winding, zero rows for degenerate triangles (no NaN). The one face-normal
    function of texelbake (model, meshes, renderer, a_vis)."""
    tri = points[faces]  # (f, 3, 3)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)


def bbox_diagonal(points: np.ndarray) -> float:
    """Length of the bounding-box diagonal of (n, 3) points (0.0 when empty)."""
    if points.shape[0] == 0:
        return 0.0
    return float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))


@dataclass(frozen=True, eq=False)
class Mesh:
    """An indexed triangle mesh.

    vertices : (n, 3) float64
    faces : (f, 3) int64, counter-clockwise seen from the front
    """

    vertices: np.ndarray
    faces: np.ndarray

    def __post_init__(self) -> None:
        v = check_points(self.vertices, "Mesh.vertices")
        f = check_faces(self.faces, v.shape[0], "Mesh.faces")
        v = np.array(v, dtype=np.float64, copy=True)
        f = np.array(f, dtype=np.int64, copy=True)
        v.flags.writeable = False
        f.flags.writeable = False
        object.__setattr__(self, "vertices", v)
        object.__setattr__(self, "faces", f)

    @property
    def num_faces(self) -> int:
        return int(self.faces.shape[0])

    @property
    def num_vertices(self) -> int:
        return int(self.vertices.shape[0])

    @property
    def bbox_diag(self) -> float:
        return bbox_diagonal(self.vertices)

    def triangles(self) -> np.ndarray:
        """(f, 3, 3) float64 corner positions."""
        return self.vertices[self.faces]

    def areas(self) -> np.ndarray:
        """(f,) float64 triangle areas."""
        return triangle_areas(self.vertices, self.faces)

    def area(self) -> float:
        return float(self.areas().sum())

    def face_normals(self) -> np.ndarray:
        """(f, 3) float64 unit geometric normals (zero rows for degenerate faces)."""
        return face_normals(self.vertices, self.faces)

    def degenerate_faces(self, eps: float = TOL.zero_area) -> np.ndarray:
        """(f,) bool: faces whose area is below eps * bbox_diag**2 or that repeat a vertex."""
        f = self.faces
        repeated = (f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 0] == f[:, 2])
        return repeated | (self.areas() <= eps * self.bbox_diag**2)


def weld(
    points: object, faces: object, eps: float = TOL.merge
) -> tuple[Mesh, np.ndarray, np.ndarray]:
    """Merge vertices closer than eps * bbox_diag; drop faces that collapse.

    Vertices within the distance are joined transitively (connected components of the
    "closer than" graph), so the result does not depend on a grid's cell boundaries as
    quantization would. A merged vertex takes the position of the lowest-indexed member.

    points : (n, 3) float64
    faces : (f, 3) int64
    returns : (mesh, vertex_map (n,) int64 old vertex -> new vertex,
               kept_faces (f,) bool, True where the face survives (no repeated vertex))
    """
    pts = check_points(points)
    fcs = check_faces(faces, pts.shape[0])
    n = pts.shape[0]
    if n == 0:
        return (
            Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.int64)),
            np.zeros(0, np.int64),
            np.zeros(fcs.shape[0], bool),
        )
    radius = eps * bbox_diagonal(pts)
    pairs = cKDTree(pts).query_pairs(r=radius, output_type="ndarray")  # (k, 2)
    graph = coo_matrix(
        (np.ones(pairs.shape[0], dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n)
    )
    _, labels = connected_components(graph, directed=False)
    # renumber components by their lowest vertex index so the output order is stable
    first = np.full(labels.max() + 1, n, dtype=np.int64)
    np.minimum.at(first, labels, np.arange(n, dtype=np.int64))
    rank = np.empty_like(first)
    rank[np.argsort(first, kind="stable")] = np.arange(first.shape[0], dtype=np.int64)
    vertex_map = rank[labels].astype(np.int64)
    new_vertices = pts[np.sort(first)]
    new_faces = vertex_map[fcs]
    kept = (
        (new_faces[:, 0] != new_faces[:, 1])
        & (new_faces[:, 1] != new_faces[:, 2])
        & (new_faces[:, 0] != new_faces[:, 2])
    )
    return Mesh(new_vertices, new_faces[kept]), vertex_map, kept


def compact(mesh: Mesh) -> tuple[Mesh, np.ndarray]:
    """Drop unreferenced vertices.

    returns : (mesh, old_index (n_new,) int64, the original vertex of each kept vertex)
    """
    used = np.unique(mesh.faces.ravel())
    remap = np.full(mesh.num_vertices, -1, dtype=np.int64)
    remap[used] = np.arange(used.shape[0], dtype=np.int64)
    return Mesh(mesh.vertices[used], remap[mesh.faces]), used.astype(np.int64)


def face_components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """(f,) int64 connected-component label of each face (faces sharing a vertex connect).

    Labels are numbered in order of each component's first face.
    """
    faces = np.asarray(faces, dtype=np.int64)
    f = faces.shape[0]
    if f == 0:
        return np.zeros(0, dtype=np.int64)
    # bipartite face-vertex graph: nodes 0..f-1 faces, f..f+n-1 vertices
    rows = np.repeat(np.arange(f, dtype=np.int64), 3)
    cols = f + faces.ravel()
    size = f + n_vertices
    graph = coo_matrix((np.ones(rows.shape[0], dtype=np.int8), (rows, cols)), shape=(size, size))
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[:f]
    _, first_idx, inverse = np.unique(face_labels, return_index=True, return_inverse=True)
    order = np.argsort(first_idx, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(order.shape[0])
    return rank[inverse].astype(np.int64)


def plane_bary(tri: np.ndarray, q: np.ndarray) -> np.ndarray:
    """(u, v) (m, 2) of points q (m, 3) projected on the planes of triangles tri (m, 3, 3)
    (point = (1 − u − v) p0 + u p1 + v p2; outside the triangle when q projects outside)."""
    e1, e2, d = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0], q - tri[:, 0]
    g11, g12, g22 = (np.einsum("mj,mj->m", a, b) for a, b in ((e1, e1), (e1, e2), (e2, e2)))
    r1, r2 = np.einsum("mj,mj->m", d, e1), np.einsum("mj,mj->m", d, e2)
    det = g11 * g22 - g12 * g12
    safe = np.where(np.abs(det) > 0, det, 1.0)
    return np.column_stack([(r1 * g22 - r2 * g12) / safe, (r2 * g11 - r1 * g12) / safe])
