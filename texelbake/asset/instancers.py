"""UsdGeom.PointInstancer -> meshes: every instance of every prototype mesh, flattened.

A point instancer places prototypes (prims named by its `prototypes` relationship) at
per-instance positions, orientations and scales; `UsdGeom.PointInstancer.
ComputeInstanceTransformsAtTime` gives each instance's transform in the instancer's space
(honouring `invisibleIds` and inactive ids through its mask). A prototype mesh is read once
(`read_one`: points and normals as `read_mesh` returns them, in world space of the prototype
prim where it is authored) and copied to every instance with one batched transform:

    p_instance = p_proto_world · inv(W_proto) · R_mesh→root · T_instance · W_instancer

(USD's row-vector convention; W = local-to-world, R = the mesh's transform relative to its
prototype root). Normals take the inverse transpose; a mirroring transform (det < 0) reverses
the winding so faces keep pointing out. The copies of one prototype mesh form one MeshData
named `<instancer>[<prototype>/<mesh>]` (reports name the instancer). Instancers are read at the
asset's time code; their motion is not animated (a warning says so when they have samples).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from texelbake.asset.meshes import MeshData
from texelbake.asset.values import usd_matrix, warn


def _instance_transforms(instancer: Any, time: Any) -> tuple[np.ndarray, np.ndarray]:
    """((k, 4, 4) float64 instance transforms in the instancer's space, (k,) int proto index)
    of the visible instances."""
    mats = instancer.ComputeInstanceTransformsAtTime(time, time)
    proto = np.asarray(instancer.GetProtoIndicesAttr().Get(time) or [], dtype=np.int64)
    mask = instancer.ComputeMaskAtTime(time)
    keep = (np.ones(proto.shape[0], bool) if not mask
            else np.asarray(list(mask), dtype=bool))
    if mats is None or len(mats) != int(keep.sum()):  # pxr returns the masked instances
        return np.zeros((0, 4, 4)), np.zeros(0, np.int64)
    arr = np.asarray([usd_matrix(m) for m in mats], dtype=np.float64).reshape(-1, 4, 4)
    return arr, proto[keep]


def instancer_meshes(prim: Any, time: Any, xcache: Any,
                     read_one: Callable[[Any], MeshData], warns: list[str]) -> list[MeshData]:
    """Every instance of every prototype mesh of the point instancer `prim` (module doc)."""
    from pxr import Usd, UsdGeom

    path = str(prim.GetPath())
    instancer = UsdGeom.PointInstancer(prim)
    inst, proto_of = _instance_transforms(instancer, time)
    if any(a.GetNumTimeSamples() > 1 for a in (instancer.GetPositionsAttr(),
                                               instancer.GetOrientationsAttr(),
                                               instancer.GetScalesAttr())):
        warn(warns, f"point instancer {path}: animated instances are read at one time code")
    targets = instancer.GetPrototypesRel().GetTargets()
    stage = prim.GetStage()
    world_instancer = usd_matrix(xcache.GetLocalToWorldTransform(prim))
    out: list[MeshData] = []
    for p_idx, target in enumerate(targets):  # a loop over prototypes, not instances
        sel = inst[proto_of == p_idx]
        root = stage.GetPrimAtPath(target)
        if sel.shape[0] == 0 or not root:
            continue
        for mesh_prim in Usd.PrimRange(root):
            if not mesh_prim.IsA(UsdGeom.Mesh):
                continue
            base = read_one(mesh_prim)
            rel, _ = xcache.ComputeRelativeTransform(mesh_prim, root)
            w_proto = usd_matrix(xcache.GetLocalToWorldTransform(mesh_prim))
            # (k, 4, 4): proto world -> its local -> root -> instance -> world
            a = np.linalg.inv(w_proto) @ usd_matrix(rel) @ sel @ world_instancer
            rel_name = mesh_prim.GetPath().MakeRelativePath(root.GetPath().GetParentPath())
            out.append(_replicate(base, a, f"{path}[{rel_name}]"))
    if not out:
        warn(warns, f"point instancer {path}: no visible instance of a mesh prototype")
    return out


def _replicate(m: MeshData, a: np.ndarray, name: str) -> MeshData:
    """Copies of `m` under each (4, 4) row-vector transform of `a` (k, 4, 4)."""
    k, n = a.shape[0], m.points.shape[0]
    lin, off = a[:, :3, :3], a[:, 3, :3]  # (k, 3, 3), (k, 3)
    pts = np.einsum("nj,kji->kni", m.points, lin) + off[:, None, :]  # (k, n, 3)
    det = np.linalg.det(lin)  # (k,)
    tris = np.broadcast_to(m.tris, (k, *m.tris.shape)).copy()  # (k, t, 3)
    flip = det < 0
    tris[flip] = tris[flip][:, :, ::-1]
    tris += (np.arange(k) * n)[:, None, None]
    normals = None
    if m.corner_normals is not None:
        inv_t = np.linalg.inv(lin)  # normals: n' = n inv(L)^T in row form -> n @ inv(L).T
        nr = np.einsum("tcj,kij->ktci", m.corner_normals, inv_t)  # (k, t, 3, 3)
        nr /= np.maximum(np.linalg.norm(nr, axis=-1, keepdims=True), 1e-300)
        nr[flip] = nr[flip][:, :, ::-1]
        normals = nr.reshape(-1, 3, 3)
    uvs = np.broadcast_to(m.corner_uvs, (k, *m.corner_uvs.shape)).copy()
    uvs[flip] = uvs[flip][:, :, ::-1]
    return MeshData(
        path=name, points=pts.reshape(-1, 3), tris=tris.reshape(-1, 3),
        tri_face=np.tile(m.tri_face, k), corner_normals=normals,
        corner_uvs=uvs.reshape(-1, 3, 2), has_uvs=m.has_uvs,
        tri_material=np.tile(m.tri_material, k), bad_polygons=m.bad_polygons * k)
