"""UsdSkel skinning of an asset as arrays (`texelbake.model.SkinData`): per-vertex joint weights
of the flattened points and, per time code, the linear-blend transforms from the rest points to
the skinned points. The LOD meshes of a bake get skin bindings transferred from these
(`texelbake.deform.skinbind`); ingest itself skins points with UsdSkel (`scene.meshes`).

An asset is described this way only when the map is one linear blend: one skeleton skins every
mesh (no instanced copies, no unskinned part), by classic linear blending, without blend shapes,
every vertex has an influence, and every joint's skinning transform at the rest time is the same
matrix C (the rest pose is a rigid image of the bind pose: then rest -> time t is
Σ w_j (W(r)⁻¹ C⁻¹ S_j(t) W(t)) for rest points too). Otherwise `skin_data` returns None with a
warning naming the reason, and the LOD meshes carry time samples instead.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.asset.values import usd_matrix, warn
from texelbake.model import SkinData


def skin_data(mesh_prims: list[Any | None], n_points: list[int], skins: dict[str, tuple[Any, Any]],
              rest_time: Any, time_codes: np.ndarray, rest_points: np.ndarray,
              points_over_time: np.ndarray, warns: list[str]) -> SkinData | None:
    """mesh_prims : per flattened mesh its prim (None for an instanced copy); n_points : its
    vertex count; skins : `scene.meshes.skinning_queries`; rest_time : the Usd.TimeCode the rest
    points were read at. Returns None (module docstring) when the skinning is not one blend."""
    from pxr import Usd, UsdGeom, UsdSkel

    if not skins or time_codes.shape[0] <= 1:
        return None

    def unsupported(why: str) -> SkinData | None:
        warn(warns, f"UsdSkel skinning not transferred to the LOD meshes ({why}); they carry "
                    "time samples of the skinned points instead")
        return None

    skel_paths = {str(skins[str(p.GetPath())][1].GetPrim().GetPath())
                  for p in mesh_prims if p is not None and str(p.GetPath()) in skins}
    if any(p is None or str(p.GetPath()) not in skins for p in mesh_prims):
        return unsupported("the asset has meshes no skeleton skins")
    if len(skel_paths) != 1:
        return unsupported(f"{len(skel_paths)} skeletons: {sorted(skel_paths)}")
    skel_query = skins[str(mesh_prims[0].GetPath())][1]  # type: ignore[union-attr]
    joints = tuple(str(j) for j in skel_query.GetJointOrder())
    jindex = {j: k for k, j in enumerate(joints)}
    rows = []
    for prim, n in zip(mesh_prims, n_points, strict=True):
        sq = skins[str(prim.GetPath())][0]  # type: ignore[union-attr]
        path = str(prim.GetPath())  # type: ignore[union-attr]
        if sq.GetSkinningMethod() != UsdSkel.Tokens.classicLinear:
            return unsupported(f"mesh {path} uses {sq.GetSkinningMethod()} skinning")
        if sq.HasBlendShapes():
            return unsupported(f"mesh {path} has blend shapes")
        inf = sq.ComputeVaryingJointInfluences(n, rest_time)
        if inf is None:
            return unsupported(f"mesh {path}: UsdSkel cannot read its joint influences")
        idx = np.asarray(inf[0], dtype=np.int64).reshape(n, -1)
        wgt = np.asarray(inf[1], dtype=np.float64).reshape(n, -1)
        order = sq.GetJointOrder()
        if order is not None:  # the mesh's own joint order (skel:joints) -> the skeleton's
            names = [str(j) for j in order]
            missing = [j for j in names if j not in jindex]
            if missing:
                return unsupported(f"mesh {path} names joints {missing} the skeleton lacks")
            idx = np.asarray([jindex[j] for j in names], dtype=np.int64)[idx]
        w = np.zeros((n, len(joints)))
        np.add.at(w, (np.repeat(np.arange(n), idx.shape[1]), idx.reshape(-1)), wgt.reshape(-1))
        rows.append(w)
    weights = np.concatenate(rows, axis=0)
    total = weights.sum(axis=1, keepdims=True)
    if not (total > 0).all():
        return unsupported(f"{int((total <= 0).sum())} vertices have no joint influence")
    weights = weights / total  # UsdSkel normalises on read; this is exact to rounding

    def skin_xforms(tc: Any) -> np.ndarray:
        xf = skel_query.ComputeSkinningTransforms(tc)
        if xf is None:
            raise ValueError
        return np.stack([usd_matrix(m) for m in xf])  # (j, 4, 4) row convention

    skel_prim = skel_query.GetPrim()
    try:
        c_all = skin_xforms(rest_time)
    except ValueError:
        return unsupported(f"skeleton {skel_prim.GetPath()}: no skinning transforms at rest")
    c = c_all[0]
    # float32 joint transforms in USD: a few 1e-8 apart when equal; 1e-6 of the asset's size
    # moves a point by less than the 1e-5 the blend is checked to below
    size = max(1.0, float(np.abs(rest_points).max()), float(np.abs(c).max()))
    if np.abs(c_all - c[None]).max() > 1e-6 * size:
        return unsupported("the rest pose is not a rigid image of the bind pose (joints' "
                           "skinning transforms differ at the rest time)")
    w_rest = usd_matrix(UsdGeom.XformCache(rest_time).GetLocalToWorldTransform(skel_prim))
    to_bind = np.linalg.inv(c @ w_rest)  # row convention: rest world -> skeleton bind space
    mats = []
    for t in time_codes.tolist():  # a loop over time codes
        tc = Usd.TimeCode(t)
        try:
            s = skin_xforms(tc)
        except ValueError:
            return unsupported(f"skeleton {skel_prim.GetPath()}: no skinning transforms at {t:g}")
        w_t = usd_matrix(UsdGeom.XformCache(tc).GetLocalToWorldTransform(skel_prim))
        mats.append(np.transpose(to_bind[None] @ s @ w_t[None], (0, 2, 1)))
    transforms = np.stack(mats)  # (t, j, 4, 4) column convention
    # the blend must reproduce UsdSkel's own skinned points (float32 there)
    hom = np.concatenate([rest_points, np.ones((rest_points.shape[0], 1))], axis=1)
    lbs = np.einsum("nj,tjab,nb->tna", weights, transforms[:, :, :3, :], hom)
    scale = max(1.0, float(np.abs(rest_points).max()))
    err = float(np.abs(lbs - points_over_time).max())
    if err > 1e-5 * scale:
        return unsupported(f"the linear blend is {err:.3g} from UsdSkel's skinned points")
    return SkinData(str(skel_prim.GetPath()), joints, weights, transforms, to_bind)
