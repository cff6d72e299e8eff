"""The mesh hierarchy M1 ⊃ M2 ⊃ … by quadric-error simplification (seed 000, §4.1, which
uses Garland–Heckbert [GH97]); pymeshlab's quadric edge collapse does the work."""

from __future__ import annotations

import math

import numpy as np
import pymeshlab

from texelbake.errors import SettingsError, StageError
from texelbake.geometry.mesh import Mesh, compact, weld

#: a level below this many faces is not a useful LOD mesh; simplification stops with an error
MIN_FACES = 4
#: with boundaries locked, a level above this multiple of its target is redone unlocked
BOUNDARY_FALLBACK = 1.5
#: boundary quadric weight of the unlocked redo (meshlab's boundaryweight; > 1 keeps borders
#: in place). On the small wall's M1: Hausdorff 0.033 at 10 vs 0.046 at 1 (bbox diag ~1.8).
BOUNDARY_WEIGHT = 10.0


def _collapse(mesh: Mesh, target: int, level: int, preserve_boundary: bool) -> pymeshlab.MeshSet:
    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(
            vertex_matrix=np.ascontiguousarray(mesh.vertices),
            face_matrix=np.ascontiguousarray(mesh.faces, dtype=np.int32),
        )
    )
    try:
        ms.apply_filter(
            "meshing_decimation_quadric_edge_collapse",
            targetfacenum=int(target),
            preserveboundary=preserve_boundary,
            boundaryweight=1.0 if preserve_boundary else BOUNDARY_WEIGHT,
            preservenormal=True,
            preservetopology=False,
            optimalplacement=True,
            planarquadric=True,
            qualitythr=0.3,
            autoclean=True,
        )
        ms.apply_filter("meshing_remove_unreferenced_vertices")
    except (pymeshlab.PyMeshLabException, ValueError) as exc:  # pragma: no cover - defensive
        raise StageError(
            f"geometry: quadric simplification of level M{level} failed: {exc}"
        ) from exc
    return ms


def _decimate(mesh: Mesh, target: int, level: int) -> Mesh:
    # preserveboundary locks boundary vertices; a mesh made of many small open pieces (the
    # wall scene: 13 open blocks on a plane) then cannot get near the target, and the
    # collapse is redone with boundaries weighted instead of locked.
    ms = _collapse(mesh, target, level, preserve_boundary=True)
    if ms.current_mesh().face_number() > BOUNDARY_FALLBACK * target:
        ms = _collapse(mesh, target, level, preserve_boundary=False)
    out = ms.current_mesh()
    vertices = np.asarray(out.vertex_matrix(), dtype=np.float64)
    faces = np.asarray(out.face_matrix(), dtype=np.int64)
    if faces.shape[0] < MIN_FACES or not np.isfinite(vertices).all():
        raise StageError(
            f"geometry: simplification to level M{level} produced a degenerate mesh "
            f"(expected >= {MIN_FACES} faces and finite vertices, got {faces.shape[0]} faces, "
            f"finite={bool(np.isfinite(vertices).all())})"
        )
    try:
        result = Mesh(vertices, faces)
    except ValueError as exc:
        raise StageError(f"geometry: level M{level} is not a valid mesh: {exc}") from exc
    keep = ~result.degenerate_faces()
    if not keep.all():
        result, _ = compact(Mesh(result.vertices, result.faces[keep]))
    if result.num_faces < MIN_FACES:
        raise StageError(
            f"geometry: level M{level} has {result.num_faces} nondegenerate faces "
            f"(expected >= {MIN_FACES})"
        )
    return result


def simplify_hierarchy(
    vertices: object,
    faces: object,
    n_levels: int,
    ratio: float = 0.25,
    target_faces: int | None = None,
) -> list[Mesh]:
    """Meshes M1..Mn, each simplified from the previous one by quadric edge collapse.

    The input (M_org, possibly a triangle soup) is welded first (`weld`, TOL.merge).
    M1 has `target_faces` faces (default ceil(ratio * f_org)); M(i+1) has
    ceil(ratio * f(i)). Boundaries and normals are preserved (pymeshlab's preserveboundary,
    preservenormal; planarquadric keeps flat regions well shaped); when locked boundaries
    keep a level above BOUNDARY_FALLBACK x its target (many small open pieces), that level
    is redone with boundaries unlocked.

    vertices : (n, 3) float64; faces : (f, 3) int64
    returns : list of n_levels Mesh
    raises SettingsError for n_levels < 1, ratio outside (0, 1), target_faces < MIN_FACES;
        StageError naming the level when a level would drop below MIN_FACES faces, fails
        to shrink, or comes out degenerate.
    """
    if int(n_levels) < 1:
        raise SettingsError(f"n_levels must be >= 1, got {n_levels}")
    if not 0.0 < float(ratio) < 1.0:
        raise SettingsError(f"ratio must be in (0, 1), got {ratio}")
    if target_faces is not None and int(target_faces) < MIN_FACES:
        raise SettingsError(f"target_faces must be >= {MIN_FACES}, got {target_faces}")
    welded, _, _ = weld(vertices, faces)
    keep = ~welded.degenerate_faces()
    current, _ = compact(Mesh(welded.vertices, welded.faces[keep]))
    if current.num_faces < MIN_FACES:
        raise StageError(
            f"geometry: M_org has {current.num_faces} nondegenerate faces after welding "
            f"(expected >= {MIN_FACES})"
        )
    levels: list[Mesh] = []
    for level in range(1, int(n_levels) + 1):  # a loop over a handful of levels
        if level == 1 and target_faces is not None:
            target = int(target_faces)
        else:
            target = math.ceil(float(ratio) * current.num_faces)
        if target < MIN_FACES:
            raise StageError(
                f"geometry: level M{level} would have {target} faces "
                f"(ratio {ratio} of {current.num_faces}); expected >= {MIN_FACES}"
            )
        if target >= current.num_faces:
            if level == 1:
                # M_org is already at or below the requested size: M1 is M_org itself
                levels.append(current)
                continue
            raise StageError(
                f"geometry: level M{level} target {target} faces does not reduce "
                f"M{level - 1} ({current.num_faces} faces)"
            )
        nxt = _decimate(current, target, level)
        if nxt.num_faces >= current.num_faces:
            raise StageError(
                f"geometry: level M{level} did not shrink ({nxt.num_faces} faces from "
                f"{current.num_faces})"
            )
        levels.append(nxt)
        current = nxt
    return levels
