"""The mesh hierarchy M1 ⊃ M2 ⊃ … by quadric-error simplification (seed 000, §4.1, which
uses Garland–Heckbert [GH97]); pymeshlab's quadric edge collapse does the work."""

from __future__ import annotations

import math

import numpy as np
import pymeshlab

from texelbake.errors import SettingsError, StageError
from texelbake.geometry.mesh import Mesh, compact, face_components, weld

#: a level below this many faces is not a useful LOD mesh; simplification stops with an error
MIN_FACES = 4
#: with boundaries locked, a level above this multiple of its target is redone unlocked
BOUNDARY_FALLBACK = 1.5
#: boundary quadric weight of the unlocked redo (meshlab's boundaryweight; > 1 keeps borders
#: in place). On the small wall's M1: Hausdorff 0.033 at 10 vs 0.046 at 1 (bbox diag ~1.8).
BOUNDARY_WEIGHT = 10.0
#: `wrap` is used for M1 when QEM would leave fewer faces than this per connected part
#: (`needs_wrap`): the full wall's ~200 blocks at 1023 faces kept 1-6 faces each (441 parts,
#: half of them slanted slivers) and its 128² atlas mapped rays to the wrong blocks
FACES_PER_PART = 16
#: ... and only for assets of at least this many parts (a plane and the quad that shadows
#: it simplify well enough separately)
WRAP_MIN_PARTS = 8
#: the bounding-box diagonal every quadric collapse runs at (`_unit_frame`). Measured on
#: an icosphere and a bumpy sphere simplified at diagonals 0.035 ... 350: the two-sided
#: distance is 2-4x worse at diagonals <= 0.35 and flat (within run-to-run noise) from 3.5 up;
#: 4 sits in the flat part, near the generated scenes' own size
COLLAPSE_DIAG = 4.0
#: the wrap's marching-cubes grid: at most this many cells along the longest side
WRAP_MAX_CELLS = 400


def _unit_frame(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """Centre and scale that map the mesh's bounding box to a diagonal of COLLAPSE_DIAG.
    meshlab's quadric collapse is not scale-invariant (absolute epsilons in vcg's quadrics):
    the same 480 -> 200 collapse of a cylinder landed 1.2e-5 of the diagonal from the
    original at diagonal 3.8 but 4.0e-2 at diagonal 0.038 (a Blender export in metres), so
    every collapse runs on the mesh scaled to that diagonal and is scaled back."""
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    scale = diag / COLLAPSE_DIAG if diag > 0.0 and math.isfinite(diag) else 1.0
    return 0.5 * (lo + hi), scale


def _collapse(mesh: Mesh, target: int, level: int, preserve_boundary: bool) -> pymeshlab.MeshSet:
    """Quadric edge collapse of `mesh` to `target` faces, on the mesh in its collapse frame
    (`_unit_frame`; the caller scales the result back)."""
    centre, scale = _unit_frame(mesh.vertices)
    ms = pymeshlab.MeshSet()
    ms.add_mesh(
        pymeshlab.Mesh(
            vertex_matrix=np.ascontiguousarray((mesh.vertices - centre) / scale),
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
    centre, scale = _unit_frame(mesh.vertices)
    vertices = np.asarray(out.vertex_matrix(), dtype=np.float64) * scale + centre
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
    wrap_offset: float | None = None,
) -> list[Mesh]:
    """Meshes M1..Mn, each simplified from the previous one by quadric edge collapse.

    The input (M_org, possibly a triangle soup) is welded first (`weld`, TOL.merge).
    M1 has `target_faces` faces (default ceil(ratio * f_org)); M(i+1) has
    ceil(ratio * f(i)). Boundaries and normals are preserved (pymeshlab's preserveboundary,
    preservenormal; planarquadric keeps flat regions well shaped); when locked boundaries
    keep a level above BOUNDARY_FALLBACK x its target (many small open pieces), that level
    is redone with boundaries unlocked. With `wrap_offset`, M1 is simplified from
    `wrap(M_org, wrap_offset)` instead of M_org (assets of many parts, `needs_wrap`).

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
    if wrap_offset is not None:
        current = wrap(current.vertices, current.faces, wrap_offset)
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


def n_parts(vertices: object, faces: object) -> int:
    """Connected parts of a mesh after welding (`weld`): what QEM simplifies separately."""
    welded, _, _ = weld(vertices, faces)
    labels = face_components(welded.faces, welded.num_vertices)
    return int(labels.max()) + 1 if labels.size else 0


def needs_wrap(parts: int, target_faces: int) -> bool:
    """Whether M1 should be a wrap: QEM collapses edges and never joins parts, so an asset of
    many separate parts (blocks on a wall, scales, leaves) keeps a few faces per part and its
    atlas a chart per face; with WRAP_MIN_PARTS parts or more and fewer than FACES_PER_PART
    faces per part, wrap instead (a small target on a few parts is what QEM is for)."""
    return parts >= WRAP_MIN_PARTS and parts * FACES_PER_PART > int(target_faces)


def wrap(vertices: object, faces: object, offset: float, max_cells: int = WRAP_MAX_CELLS
         ) -> Mesh:
    """One connected surface around M_org at distance `offset`: the `offset` level set of
    M_org's unsigned distance field, by marching cubes (pymeshlab's uniform mesh resampling,
    `absdist`). Parts closer than 2 x offset merge into one sheet, so a wall of blocks
    becomes a slab whose front sheet lies `offset` above the blocks; the decimation that
    follows (`simplify_hierarchy`, QEM) has one connected surface to work on, and the atlas
    a few large charts (a departure from seed 000, which simplifies M_org itself;
    docs/decisions.md). Thin parts get two sheets, one per side; `assign_texels` keeps each
    sample on the sheet on its own side.

    offset : > 0, world units (the stage uses about a finest texel); the grid cell is
        offset / 2, coarsened to at most `max_cells` (WRAP_MAX_CELLS) along the longest side
    raises SettingsError for offset <= 0, StageError when the filter fails or returns
    fewer than MIN_FACES faces"""
    off = float(offset)
    if not off > 0.0:
        raise SettingsError(f"wrap offset must be > 0, got {offset}")
    # an unsigned distance needs no welding: a triangle soup gives the same field
    org = Mesh(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    extent = float(np.ptp(org.vertices, axis=0).max()) + 2.0 * off
    cell = max(0.5 * off, extent / int(max_cells))
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.ascontiguousarray(org.vertices),
                               face_matrix=np.ascontiguousarray(org.faces, dtype=np.int32)))
    try:
        ms.apply_filter("generate_resampled_uniform_mesh",
                        cellsize=pymeshlab.PureValue(cell), offset=pymeshlab.PureValue(off),
                        absdist=True, mergeclosevert=True)
        ms.apply_filter("meshing_remove_unreferenced_vertices")
    except (pymeshlab.PyMeshLabException, ValueError) as exc:  # pragma: no cover - defensive
        raise StageError(f"geometry: wrapping M_org at offset {off:g} failed: {exc}") from exc
    out = ms.current_mesh()
    v = np.asarray(out.vertex_matrix(), dtype=np.float64)
    f = np.asarray(out.face_matrix(), dtype=np.int64)
    if f.shape[0] < MIN_FACES or not np.isfinite(v).all():
        raise StageError(f"geometry: wrapping M_org at offset {off:g} gave {f.shape[0]} faces "
                         f"(expected >= {MIN_FACES}, finite)")
    mesh, _ = compact(Mesh(v, f[~Mesh(v, f).degenerate_faces()]))
    return _outer_sheets(mesh)


def _outer_sheets(mesh: Mesh) -> Mesh:
    """The parts of a marching-cubes surface that no other part encloses. The level set of
    an unsigned distance also runs *inside* closed parts thicker than twice the offset (12
    inner boxes in 12 unit boxes); those are never seen and would take atlas space. A part is
    inside another when a ray from its extreme vertex (largest x, going +x) crosses the
    other parts an odd number of times (the surface is closed: a padded grid)."""
    from texelbake.geometry.raycast import RayCaster

    labels = face_components(mesh.faces, mesh.num_vertices)
    n = int(labels.max()) + 1
    if n == 1:
        return mesh
    vert_label = np.full(mesh.num_vertices, -1)
    vert_label[mesh.faces.ravel()] = np.repeat(labels, 3)
    order = np.lexsort((mesh.vertices[:, 0], vert_label))  # by part, then x
    last = np.flatnonzero(np.r_[vert_label[order][1:] != vert_label[order][:-1], True])
    ext = order[last][vert_label[order][last] >= 0]  # one extreme vertex per part
    part = vert_label[ext]
    eps = 1e-6 * max(float(np.ptp(mesh.vertices, axis=0).max()), 1e-300)
    o = mesh.vertices[ext] + [eps, 0.0, 0.0]
    d = np.tile([1.0, 0.0, 0.0], (ext.size, 1))
    crossings = np.zeros(ext.size, np.int64)
    live = np.arange(ext.size)
    caster = RayCaster(mesh.vertices, mesh.faces)
    for _ in range(4 * n + 8):  # a loop over successive crossings, all rays at once
        if live.size == 0:
            break
        hits = caster.cast(o[live], d[live])
        hit = hits.hit
        crossings[live[hit]] += labels[hits.prim[hit]] != part[live[hit]]
        o[live[hit], 0] += hits.t[hit] + eps
        live = live[hit]
    inner = set(part[crossings % 2 == 1].tolist())
    keep = ~np.isin(labels, list(inner))
    out, _ = compact(Mesh(mesh.vertices, mesh.faces[keep]))
    return out


def enclose(mesh: Mesh, points: np.ndarray, *, tighten: bool = False) -> tuple[Mesh, float]:
    """`mesh` moved outward until it covers `points` (dense samples of M_org), face by face.

    A QEM mesh cuts through fine relief (ridges, bumps), so its silhouette lies inside M_org's
    and the renderer's coarse meshes lose a rim of pixels; the enclosing mesh keeps M_org's
    outline while the maps carry the relief (a departure from seed 000, which renders the QEM
    meshes as they are; docs/decisions.md). Each face f should move out along its normal n_f
    by o_f = the largest distance outside it of the samples closest to it (0 if none is
    outside); each vertex takes the displacement x that best meets the planes of its faces,
    min_x Σ_f A_f (n_f·x - o_f)² (area-weighted normal equations, pseudo-inverse: on a flat
    region x = o n, at a crease each side keeps its own offset, so a flat cap stays where it
    is while the ridged side beside it moves out). Vertices of faces that would fold stay put.

    With `tighten`, a face whose closest samples all lie inside it moves *in* to the
    outermost of them (o_f < 0): a wrap (`wrap`) lies an offset outside M_org, and its
    silhouette and parallax shrink back to M_org's.

    points : (m, 3) float64; returns (the moved mesh, the largest vertex displacement)"""
    from texelbake.geometry.raycast import RayCaster

    pts = np.asarray(points, dtype=np.float64)
    if pts.shape[0] == 0:
        return mesh, 0.0
    cp, prim, _ = RayCaster(mesh.vertices, mesh.faces).closest_points(pts)
    fn = mesh.face_normals()
    d = np.einsum("ij,ij->i", pts - cp, fn[prim])
    o = np.full(mesh.num_faces, -np.inf if tighten else 0.0)
    np.maximum.at(o, prim, d)
    o[~np.isfinite(o)] = 0.0  # faces no sample is closest to stay put
    if not (o != 0).any():
        return mesh, 0.0
    area = mesh.areas()
    nn = area[:, None, None] * fn[:, :, None] * fn[:, None, :]  # (f, 3, 3)
    nb = (area * o)[:, None] * fn  # (f, 3)
    a_mat = np.zeros((mesh.num_vertices, 3, 3))
    b_vec = np.zeros((mesh.num_vertices, 3))
    for k in range(3):  # a loop over the three corners
        np.add.at(a_mat, mesh.faces[:, k], nn)
        np.add.at(b_vec, mesh.faces[:, k], nb)
    # Pseudo-inverse with a relative cut-off of 0.1: a direction the faces constrain less than
    # a tenth as strongly as the best one does not move. Across a crease (normals >= ~18 deg
    # apart) every direction counts and each face keeps its own offset; across the slightly
    # bent faces of a smooth region the tangential directions are nearly unconstrained and a
    # difference of offsets would shear the vertex sideways by Δo / sin(angle), so the vertex
    # moves along the mean normal only. Bounded by the largest face offset, as a last guard.
    w, v = np.linalg.eigh(a_mat)
    inv = np.where(w > 0.1 * w[:, -1:], 1.0 / np.where(w > 0, w, 1.0), 0.0)
    x = np.einsum("nij,nj,nkj,nk->ni", v, inv, v, b_vec)
    length = np.linalg.norm(x, axis=1, keepdims=True)
    cap = float(np.abs(o).max())
    x = np.where(length > cap, x * (cap / np.maximum(length, 1e-300)), x)
    # QEM leaves slivers whose planes disagree with their neighbours'; where a face would fold
    # (turn by more than 60 degrees or keep less than a fifth of its area) its vertices stay
    # put, repeated until no face folds (the small cylinder's M1: 4 of 120 faces)
    for _ in range(8):  # a few rounds; each only pins vertices
        tri = (mesh.vertices + x)[mesh.faces]
        n1 = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        a1 = 0.5 * np.linalg.norm(n1, axis=1)
        turned = np.einsum("ij,ij->i", n1, fn) < 0.5 * 2.0 * a1
        folded = (turned | (a1 < 0.2 * area)) & (area > 0)
        if not folded.any():
            break
        x[mesh.faces[folded].ravel()] = 0.0
    else:
        return mesh, 0.0
    step = float(np.linalg.norm(x, axis=1).max())
    return Mesh(mesh.vertices + x, mesh.faces), step
