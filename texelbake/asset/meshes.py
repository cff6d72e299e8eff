"""Meshes: points in world space (transforms, UsdSkel skinning), catmullClark surfaces refined
(`texelbake.geometry.subdivision`), fan triangulation, normals (authored or computed), UVs."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from texelbake.asset.values import usd_matrix, warn
from texelbake.errors import AssetError
from texelbake.geometry.subdivision import Refinement, catmull_clark, refinement_levels


@dataclass
class MeshData:
    path: str
    points: np.ndarray  # (n, 3) float64 world
    tris: np.ndarray  # (t, 3) int64 local vertex ids, counter-clockwise
    tri_face: np.ndarray  # (t,) int64 source polygon
    corner_normals: np.ndarray | None  # (t, 3, 3) float64 world unit, None = compute
    corner_uvs: np.ndarray  # (t, 3, 2) float64
    has_uvs: bool
    tri_material: np.ndarray  # (t,) int32
    bad_polygons: int  # polygons with < 3 vertices
    # (n, n_cage) sparse: points = refine @ the cage's world points (a subdivision surface);
    # None: the points are the prim's own
    refine: Any = None


def _fan(counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fan triangulation of polygons given their vertex counts, without a loop per face.

    counts : (F,) int64 faceVertexCounts
    returns : tri_fv (T, 3) int64 face-varying corner indices (into faceVertexIndices),
        tri_face (T,) int64 the polygon of each triangle; polygon i with c_i >= 3 corners yields
        (s, s + k, s + k + 1) for k = 1 .. c_i - 2, s its first corner.
    """
    counts = np.asarray(counts, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    n_tri = np.maximum(counts - 2, 0)  # (F,)
    tri_face = np.repeat(np.arange(counts.shape[0], dtype=np.int64), n_tri)  # (T,)
    first_tri = np.concatenate([[0], np.cumsum(n_tri)[:-1]]).astype(np.int64)
    k = np.arange(tri_face.shape[0], dtype=np.int64) - first_tri[tri_face] + 1  # (T,)
    s = starts[tri_face]
    return np.stack([s, s + k, s + k + 1], axis=1), tri_face


def fan_triangles(counts: np.ndarray, indices: np.ndarray) -> np.ndarray:
    """(T, 3) int64 vertex ids of the fan triangulation of polygons (counts (F,), indices
    (C,) faceVertexIndices), as `read_mesh` triangulates them."""
    tri_fv, _ = _fan(np.asarray(counts, dtype=np.int64))
    return np.asarray(indices, dtype=np.int64)[tri_fv]


def _expand(values: np.ndarray, interp: str, tri_fv: np.ndarray, tri_vid: np.ndarray,
            tri_face: np.ndarray, n_points: int, n_faces: int, n_fv: int) -> np.ndarray | None:
    """Primvar values of any interpolation -> (T, 3, k) per triangle corner; None on mismatch."""
    n = values.shape[0]
    if interp == "constant":
        if n < 1:
            return None
        return np.broadcast_to(values[0], (tri_fv.shape[0], 3, values.shape[1])).copy()
    if interp == "uniform":
        return np.repeat(values[tri_face][:, None, :], 3, axis=1) if n == n_faces else None
    if interp in ("vertex", "varying"):
        return values[tri_vid] if n == n_points else None
    if interp == "faceVarying":
        return values[tri_fv] if n == n_fv else None
    return None


def _primvar_values(primvar: Any, time: Any, width: int) -> np.ndarray | None:
    """(k, width) float64 primvar values with indices applied; None when not authored / bad."""
    raw = primvar.Get(time)
    if raw is None:
        return None
    values = np.asarray(raw, dtype=np.float64)
    if values.ndim != 2 or values.shape[1] != width:
        return None
    if primvar.IsIndexed():
        idx = np.asarray(primvar.GetIndices(time), dtype=np.int64)
        if idx.size and (idx.min() < 0 or idx.max() >= values.shape[0]):
            return None
        values = values[idx]
    return values


def tri_cross(points: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(t, 3) float64 cross products (p1 - p0) x (p2 - p0): twice the area times the unit
    normal. Written per component: several times faster than np.cross on (t, 3) arrays."""
    p0, p1, p2 = points[tris[:, 0]], points[tris[:, 1]], points[tris[:, 2]]
    e1, e2 = p1 - p0, p2 - p0
    return np.stack([e1[:, 1] * e2[:, 2] - e1[:, 2] * e2[:, 1],
                     e1[:, 2] * e2[:, 0] - e1[:, 0] * e2[:, 2],
                     e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]], axis=1)


def row_norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt(np.einsum("...j,...j->...", v, v))


def area_weighted_normals(points: np.ndarray, tris: np.ndarray,
                           cross: np.ndarray | None = None) -> np.ndarray:
    """(t, 3, 3) corner normals: per vertex, the sum of incident triangle cross products.

    points : (n, 3) float64; tris : (t, 3) int64; cross : (t, 3) float64 `tri_cross` if known
    The cross product is twice the area times the unit normal, so the sum is area-weighted.
    A vertex whose sum vanishes (an isolated degenerate fan, opposite faces) takes the normal
    of each triangle it is a corner of (zero for a degenerate triangle).
    """
    if cross is None:
        cross = tri_cross(points, tris)
    n = points.shape[0]
    flat = tris.reshape(-1)  # (3t,) every corner adds its triangle's cross product
    acc = np.stack([np.bincount(flat, weights=np.repeat(cross[:, k], 3), minlength=n)
                    for k in range(3)], axis=1)  # (n, 3)
    length = row_norm(acc)  # (n,)
    ok = length > 0
    vertex_unit = np.zeros_like(acc)
    vertex_unit[ok] = acc[ok] / length[ok, None]
    corner = vertex_unit[tris]  # (t, 3, 3)
    bad_t, bad_c = np.nonzero(~ok[tris])
    if bad_t.size:
        face = cross[bad_t]
        face_len = row_norm(face)[:, None]
        corner[bad_t, bad_c] = np.divide(face, face_len, out=np.zeros_like(face),
                                         where=face_len > 0)
    return corner


def skinning_queries(stage: Any, warns: list[str]) -> dict[str, tuple[Any, Any]]:
    """mesh prim path -> (UsdSkel.SkinningQuery, UsdSkel.SkeletonQuery) for skinned meshes.

    Linear-blend (and dual-quaternion) skinning of points is evaluated by UsdSkel itself
    (`SkinningQuery.ComputeSkinnedPoints`); blend shapes are not applied (warning).
    """
    from pxr import Usd, UsdSkel

    out: dict[str, tuple[Any, Any]] = {}
    roots = [p for p in stage.Traverse(Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate))
             if p.IsA(UsdSkel.Root)]
    if not roots:
        return out
    cache = UsdSkel.Cache()
    for prim in roots:
        root = UsdSkel.Root(prim)
        cache.Populate(root, Usd.PrimDefaultPredicate)
        for binding in cache.ComputeSkelBindings(root, Usd.PrimDefaultPredicate):
            skel_query = cache.GetSkelQuery(binding.GetSkeleton())
            if not skel_query:
                warn(warns, f"skeleton {binding.GetSkeleton().GetPath()}: invalid; its "
                             "meshes are read unskinned")
                continue
            for sq in binding.GetSkinningTargets():
                path = str(sq.GetPrim().GetPath())
                if not sq.HasJointInfluences():
                    continue
                if sq.HasBlendShapes():
                    warn(warns, f"mesh {path}: UsdSkel blend shapes are not applied")
                out[path] = (sq, skel_query)
    return out


def world_points(prim: Any, points: np.ndarray, time: Any, xcache: Any,
                  skin: tuple[Any, Any] | None, source: str) -> tuple[np.ndarray, np.ndarray]:
    """Mesh points (n, 3) float64 in local space -> world (n, 3) float64, and the (3, 3) linear
    part of the frame that took them there.

    Unskinned: the prim's local-to-world transform. Skinned: UsdSkel's skinned points (skel
    space) times the Skeleton's local-to-world (the mesh's own transform does not apply).
    """
    from pxr import Vt

    if skin is None:
        world = usd_matrix(xcache.GetLocalToWorldTransform(prim))
    else:
        sq, skel_query = skin
        xforms = skel_query.ComputeSkinningTransforms(time)
        skinned = Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(points, dtype=np.float32))
        if xforms is None or not sq.ComputeSkinnedPoints(xforms, skinned, time):
            raise AssetError(f"mesh {prim.GetPath()}: UsdSkel could not skin its points "
                             f"with skeleton {skel_query.GetPrim().GetPath()}",
                             path=source, prim=str(prim.GetPath()))
        points = np.array(skinned, dtype=np.float64).reshape(-1, 3)
        world = usd_matrix(xcache.GetLocalToWorldTransform(skel_query.GetPrim()))
    return points @ world[:3, :3] + world[3, :3], world[:3, :3]


def read_mesh(prim: Any, time: Any, xcache: Any, face_materials: np.ndarray | None,
               uv_names: list[str], warns: list[str], source: str,
               skin: tuple[Any, Any] | None = None) -> MeshData:
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    path = str(prim.GetPath())
    pts_raw = mesh.GetPointsAttr().Get(time)
    points = np.asarray(pts_raw if pts_raw is not None else [], dtype=np.float64).reshape(-1, 3)
    bad = ~np.isfinite(points).all(axis=1)
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        raise AssetError(f"mesh {path} has NaN/Inf points ({int(bad.sum())} bad, first at "
                         f"index {first}: {points[first].tolist()})", path=source, prim=path)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    if (counts < 0).any():
        raise AssetError(f"mesh {path} has negative faceVertexCounts", path=source, prim=path)
    if int(counts.sum()) != fvi.shape[0]:
        raise AssetError(f"mesh {path}: faceVertexCounts sum to {int(counts.sum())} but there are "
                         f"{fvi.shape[0]} faceVertexIndices", path=source, prim=path)
    n_points = points.shape[0]
    out_of_range = (fvi < 0) | (fvi >= n_points)
    if out_of_range.any():
        first = int(np.flatnonzero(out_of_range)[0])
        raise AssetError(
            f"mesh {path}: faceVertexIndices[{first}] = {int(fvi[first])} is out of range for "
            f"{n_points} points", path=source, prim=path)
    n_faces = counts.shape[0]
    bad_polygons = int((counts < 3).sum())
    if bad_polygons:
        warn(warns, f"mesh {path}: dropped {bad_polygons} polygon(s) with fewer than 3 vertices")
    refinement = _refinement(mesh, path, counts, fvi, n_points, time, skin, warns)
    if refinement is not None:
        counts, fvi = refinement.counts, refinement.indices
        n_points = refinement.num_points  # n_faces stays the cage's: tri_face is its polygons
    tri_fv, tri_face = _fan(counts)  # (T, 3), (T,)
    if refinement is not None:  # the cage's polygon each refined face lies in
        tri_face = refinement.face_parent[tri_face]
    holes = np.asarray(mesh.GetHoleIndicesAttr().Get(time) or [], dtype=np.int64)
    if holes.size:
        keep = ~np.isin(tri_face, holes)
        tri_fv, tri_face = tri_fv[keep], tri_face[keep]

    points_w, lin = world_points(prim, points, time, xcache, skin, source)  # (n, 3), (3, 3)
    if refinement is not None:
        points_w = refinement.vertex_matrix @ points_w  # (n', 3) on the limit surface
    det = float(np.linalg.det(lin))
    left = mesh.GetOrientationAttr().Get(time) == UsdGeom.Tokens.leftHanded
    if left != (det < 0):  # either flips the winding; both cancel
        tri_fv = tri_fv[:, [0, 2, 1]]
    tri_vid = fvi[tri_fv]  # (T, 3)

    # normals: primvars:normals wins over the normals attribute (UsdGeomPointBased docs)
    corner_normals = None
    pv_api = UsdGeom.PrimvarsAPI(prim)
    nrm_pv = pv_api.GetPrimvar("normals")
    if refinement is not None:
        # UsdGeomMesh: normals are not authored on subdivision surfaces, a renderer computes
        # them from the limit surface; the refined mesh's area-weighted normals are that
        if (nrm_pv and nrm_pv.HasAuthoredValue()) or mesh.GetNormalsAttr().HasAuthoredValue():
            warn(warns, f"mesh {path}: authored normals ignored on a subdivision surface; "
                         "computed from its limit surface")
        values, interp, label = None, "", ""
    elif skin is not None:
        # UsdSkel in Python skins points only: normals are computed from the skinned surface
        if (nrm_pv and nrm_pv.HasAuthoredValue()) or mesh.GetNormalsAttr().HasAuthoredValue():
            warn(warns, f"mesh {path}: skinned by UsdSkel; its authored (rest-pose) normals are "
                         "replaced by normals computed from the skinned points")
        values, interp, label = None, "", ""
    elif nrm_pv and nrm_pv.HasAuthoredValue():
        values, interp, label = _primvar_values(nrm_pv, time, 3), nrm_pv.GetInterpolation(), \
            "primvars:normals"
    elif mesh.GetNormalsAttr().HasAuthoredValue():
        raw = mesh.GetNormalsAttr().Get(time)
        values = None if raw is None else np.asarray(raw, dtype=np.float64).reshape(-1, 3)
        interp, label = mesh.GetNormalsInterpolation(), "normals"
    else:
        values, interp, label = None, "", ""
    if label:
        expanded = None if values is None else _expand(
            values, interp, tri_fv, tri_vid, tri_face, n_points, n_faces, fvi.shape[0])
        if expanded is None:
            n_vals = -1 if values is None else values.shape[0]
            warn(warns, f"mesh {path}: {label} ({interp}, {n_vals} values) does not match the "
                         f"topology ({n_points} points, {n_faces} faces, {fvi.shape[0]} corners); "
                         "computing normals")
        else:
            normal_xf = np.linalg.inv(lin).T  # row vectors: n' = n @ inv(A).T
            nw = expanded @ normal_xf
            length = np.linalg.norm(nw, axis=2, keepdims=True)
            ok = np.isfinite(length) & (length > 0)
            corner_normals = np.divide(nw, length, out=np.zeros_like(nw), where=ok)
            if not ok.all():
                warn(warns, f"mesh {path}: {int((~ok).sum())} authored normal(s) are zero or "
                             "not finite; those corners use computed normals")
                computed = area_weighted_normals(points_w, tri_vid)  # (T, 3, 3)
                corner_normals = np.where(ok, corner_normals, computed)

    # UVs: the primvar the mesh's textures read (one set per mesh: texelbake carries one UV
    # set per face; textures reading different sets on one mesh all use the first, warned),
    # else primvars:st, else any texCoord2f
    if len(uv_names) > 1:
        warn(warns, f"mesh {path}: its textures read UV sets {uv_names}; texelbake carries "
                    f"one set per mesh and uses primvars:{uv_names[0]} for all of them")
    names = [*uv_names[:1], *(["st"] if "st" not in uv_names[:1] else [])]
    candidates = [pv_api.GetPrimvar(n) for n in names]
    chosen = next((pv for pv in candidates if pv and pv.HasAuthoredValue()), None)
    if chosen is None:
        tex_coords = sorted(
            (pv for pv in pv_api.GetPrimvarsWithAuthoredValues()
             if pv.GetTypeName().role == "TextureCoordinate"),
            key=lambda pv: pv.GetPrimvarName())
        chosen = tex_coords[0] if tex_coords else None
    corner_uvs = np.zeros((tri_fv.shape[0], 3, 2))
    has_uvs = False
    if chosen is not None:
        values = _primvar_values(chosen, time, 2)
        interp = chosen.GetInterpolation()
        if refinement is not None and values is not None:
            values = refine_primvar(refinement, values, interp)
        expanded = None if values is None else _expand(
            values, interp, tri_fv, tri_vid, tri_face, n_points, n_faces, fvi.shape[0])
        if expanded is None:
            n_vals = -1 if values is None else values.shape[0]
            warn(warns, f"mesh {path}: primvars:{chosen.GetPrimvarName()} ({interp}, {n_vals} "
                         f"values) does not match the topology; ignoring UVs")
        else:
            corner_uvs, has_uvs = expanded, True
            if chosen.GetPrimvarName() not in ("st", *uv_names[:1]):
                warn(warns, f"mesh {path}: no primvars:st; using primvars:"
                             f"{chosen.GetPrimvarName()} as UVs")

    tri_material = (np.zeros(tri_face.shape[0], np.int32) if face_materials is None
                    else face_materials[tri_face].astype(np.int32))
    return MeshData(path, points_w, tri_vid, tri_face, corner_normals, corner_uvs, has_uvs,
                     tri_material, bad_polygons,
                     None if refinement is None else refinement.vertex_matrix)


def _refinement(mesh: Any, path: str, counts: np.ndarray, fvi: np.ndarray, n_points: int,
                time: Any, skin: tuple[Any, Any] | None, warns: list[str]
                ) -> Refinement | None:
    """The Catmull–Clark refinement a subdivision mesh is baked from, or None (the points as
    authored): `subdivisionScheme` none, bilinear or not authored (flat polygons,
    fan-triangulated), loop
    (not refined: warned), a skinned mesh (its joint influences belong to the cage's points:
    warned) or a cage with a polygon of fewer than 3 vertices (warned with it)."""
    attr = mesh.GetSubdivisionSchemeAttr()
    scheme = str(attr.Get(time) or "none")
    if scheme in ("none", "bilinear") or counts.shape[0] == 0:
        return None
    if not attr.HasAuthoredValue():
        # UsdGeom's fallback is catmullClark, but meshes converted from polygon formats
        # (glTF, OBJ) leave it unauthored and mean their polygons, which is what Blender's
        # importer and usdview show at their defaults: only an authored scheme is refined
        warn(warns, f"mesh {path}: subdivisionScheme not authored (UsdGeom's fallback is "
                    "catmullClark); baked as its polygons, as Blender and usdview show it by "
                    "default; author catmullClark to bake its limit surface")
        return None
    if scheme != "catmullClark":
        warn(warns, f"mesh {path}: subdivisionScheme is {scheme!r}; baked as its control "
                    "cage, not refined (texelbake refines catmullClark)")
        return None
    if skin is not None:
        warn(warns, f"mesh {path}: a skinned catmullClark surface; baked as its control "
                    "cage, which its joint influences are authored on")
        return None
    if (counts < 3).any():
        warn(warns, f"mesh {path}: a catmullClark cage with polygons of fewer than 3 "
                    "vertices; baked as its control cage")
        return None
    for attr, what in ((mesh.GetCreaseIndicesAttr(), "creases"),
                       (mesh.GetCornerIndicesAttr(), "corners")):
        if len(attr.Get(time) or []):
            warn(warns, f"mesh {path}: its authored {what} are not applied (refined smooth)")
    boundary = str(mesh.GetInterpolateBoundaryAttr().Get(time) or "edgeAndCorner")
    if boundary not in ("edgeAndCorner", "edgeOnly"):
        warn(warns, f"mesh {path}: interpolateBoundary {boundary!r} refined as 'edgeOnly' "
                    "(its boundary faces are kept)")
        boundary = "edgeOnly"
    # face-varying values (UVs) are refined bilinearly whatever faceVaryingLinearInterpolation
    # says (texelbake.geometry.subdivision: why)
    return catmull_clark(counts, fvi, n_points, refinement_levels(counts), boundary=boundary)


def refine_primvar(refinement: Refinement, values: np.ndarray, interp: str) -> np.ndarray:
    """Cage primvar values (k, w) of `interp` -> the refined mesh's values of the same
    interpolation: vertex/varying smooth (the points' matrix), faceVarying bilinear; uniform
    and constant as they are (the refined triangles keep their cage polygon). Values whose count does not match the cage are
    returned unchanged (the caller's topology check then rejects them)."""
    mats = {"vertex": refinement.vertex_matrix, "varying": refinement.vertex_matrix,
            "faceVarying": refinement.fv_matrix}
    if interp in mats and values.shape[0] == mats[interp].shape[1]:
        return np.asarray(mats[interp] @ values)
    return values


def is_rendered(prim: Any, time: Any) -> bool:
    from pxr import UsdGeom

    img = UsdGeom.Imageable(prim)
    if img.ComputeVisibility(time) == UsdGeom.Tokens.invisible:
        return False
    return img.ComputePurpose() != UsdGeom.Tokens.guide
