"""UsdSkel skinning of an asset as arrays (`texelbake.model.SkinData`): per-vertex joint weights
of the flattened points and, per time code, each joint's transform from the skeleton's bind
space to the world, with the same at the rest time. The LOD meshes of a bake get skin bindings
transferred from these (`texelbake.deform.skinbind`); ingest itself skins points with UsdSkel
(`scene.meshes`).

A rest point p with weights w is at M_t M_r⁻¹ p (`deform.lbs.skin_blend`): exact for linear
blend skinning whatever the rest pose is (an animation's first frame, restTransforms other than
the bind pose), wherever M_r = Σ_j w_j B_j is invertible. Meshes no skeleton skins (props under
the SkelRoot or beside it, instanced copies) are bound rigidly, weight 1, to the first joint
(the skeleton's order) whose motion from the rest time is theirs at every time code — a static
mesh to a joint that does not move. The asset is described this way when one skeleton skins
it by classic linear blending without blend shapes, every skinned vertex has an influence,
every unskinned mesh moves with some joint, every rest blend is invertible, and the result
reproduces UsdSkel's own skinned points. Otherwise `skin_data` returns None with a warning
naming the reason, and the LOD meshes carry time samples instead.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.asset.values import usd_matrix, warn
from texelbake.deform.lbs import apply_affine, blend_affine, rest_inverse
from texelbake.model import SkinData
from texelbake.tol import TOL


def skin_data(mesh_prims: list[Any | None], n_points: list[int], skins: dict[str, tuple[Any, Any]],
              rest_time: Any, time_codes: np.ndarray, rest_points: np.ndarray,
              points_over_time: np.ndarray, warns: list[str]) -> SkinData | None:
    """mesh_prims : per flattened mesh its prim (None for an instanced copy); n_points : its
    vertex count; skins : `scene.meshes.skinning_queries`; rest_time : the Usd.TimeCode the rest
    points were read at. Returns None (module docstring) when the skinning is not one blend."""
    from pxr import Usd, UsdGeom

    if not skins or time_codes.shape[0] <= 1:
        return None

    def unsupported(why: str) -> SkinData | None:
        warn(warns, f"UsdSkel skinning not transferred to the LOD meshes ({why}); they carry "
                    "time samples of the skinned points instead")
        return None

    paths = [None if p is None else str(p.GetPath()) for p in mesh_prims]
    skel_paths = sorted({str(skins[p][1].GetPrim().GetPath()) for p in paths
                         if p is not None and p in skins})
    if len(skel_paths) != 1:
        return unsupported(f"{len(skel_paths)} skeletons: {skel_paths}")
    skel_query = next(skins[p][1] for p in paths if p is not None and p in skins)
    skel_prim = skel_query.GetPrim()
    joints = tuple(str(j) for j in skel_query.GetJointOrder())

    def joint_xforms(tc: Any) -> np.ndarray | None:
        """(j, 4, 4) column convention: bind space -> world at tc (None: UsdSkel has none)."""
        xf = skel_query.ComputeSkinningTransforms(tc)
        if xf is None:
            return None
        world = usd_matrix(UsdGeom.XformCache(tc).GetLocalToWorldTransform(skel_prim))
        s = np.stack([usd_matrix(m) for m in xf])  # (j, 4, 4) row convention
        return np.transpose(s @ world[None], (0, 2, 1))

    rest = joint_xforms(rest_time)
    if rest is None:
        return unsupported(f"skeleton {skel_prim.GetPath()}: no skinning transforms at rest")
    mats = []
    for t in time_codes.tolist():  # a loop over time codes
        x = joint_xforms(Usd.TimeCode(t))
        if x is None:
            return unsupported(f"skeleton {skel_prim.GetPath()}: no skinning transforms at "
                               f"{t:g}")
        mats.append(x)
    transforms = np.stack(mats)  # (t, j, 4, 4)
    size = max(1.0, float(np.abs(rest_points).max()) if rest_points.size else 1.0)
    rows = []
    for prim, path, n in zip(mesh_prims, paths, n_points, strict=True):
        got = (_skinned_rows(skins[path][0], path, n, joints, rest_time)
               if path is not None and path in skins
               else _rigid_rows(prim, n, rest_time, time_codes, rest, transforms, size))
        if isinstance(got, str):
            return unsupported(got)
        rows.append(got)
    weights = np.concatenate(rows, axis=0)
    total = weights.sum(axis=1, keepdims=True)
    if not (total > 0).all():
        return unsupported(f"{int((total <= 0).sum())} vertices have no joint influence")
    weights = weights / total  # UsdSkel normalises on read; this is exact to rounding
    inv, valid = rest_inverse(rest, weights)
    if not valid.all():
        return unsupported(f"{int((~valid).sum())} vertices' blended rest transform is "
                           f"near-singular (σ_min < {TOL.skin_blend_cond:g} σ_max)")
    bind_pts = apply_affine(inv, rest_points)  # (n, 3) skeleton bind space
    # the blend must reproduce UsdSkel's own skinned points (float32 there)
    err = 0.0
    for k in range(transforms.shape[0]):  # a loop over time codes
        lbs = apply_affine(blend_affine(transforms[k], weights), bind_pts)
        err = max(err, float(np.abs(lbs - points_over_time[k]).max()))
    if err > 1e-5 * size:
        return unsupported(f"the linear blend is {err:.3g} from UsdSkel's skinned points")
    xcache = UsdGeom.XformCache(rest_time)
    w_rest = usd_matrix(xcache.GetLocalToWorldTransform(skel_prim))
    root = skel_prim.GetStage().GetDefaultPrim()
    r_rest = usd_matrix(xcache.GetLocalToWorldTransform(root)) if root else np.eye(4)
    return SkinData(str(skel_prim.GetPath()), joints, weights, transforms, rest,
                    w_rest @ np.linalg.inv(r_rest))


def _skinned_rows(sq: Any, path: str, n: int, joints: tuple[str, ...], rest_time: Any
                  ) -> np.ndarray | str:
    """(n, j) float64 weights of a skinned mesh in the skeleton's joint order, or the reason
    the mesh cannot be described as one linear blend."""
    from pxr import UsdSkel

    if sq.GetSkinningMethod() != UsdSkel.Tokens.classicLinear:
        return f"mesh {path} uses {sq.GetSkinningMethod()} skinning"
    if sq.HasBlendShapes():
        return f"mesh {path} has blend shapes"
    inf = sq.ComputeVaryingJointInfluences(n, rest_time)
    if inf is None:
        return f"mesh {path}: UsdSkel cannot read its joint influences"
    idx = np.asarray(inf[0], dtype=np.int64).reshape(n, -1)
    wgt = np.asarray(inf[1], dtype=np.float64).reshape(n, -1)
    order = sq.GetJointOrder()
    if order is not None:  # the mesh's own joint order (skel:joints) -> the skeleton's
        jindex = {j: k for k, j in enumerate(joints)}
        names = [str(j) for j in order]
        missing = [j for j in names if j not in jindex]
        if missing:
            return f"mesh {path} names joints {missing} the skeleton lacks"
        idx = np.asarray([jindex[j] for j in names], dtype=np.int64)[idx]
    w = np.zeros((n, len(joints)))
    np.add.at(w, (np.repeat(np.arange(n), idx.shape[1]), idx.reshape(-1)), wgt.reshape(-1))
    return w


def _rigid_rows(prim: Any, n: int, rest_time: Any, time_codes: np.ndarray, rest: np.ndarray,
                transforms: np.ndarray, size: float) -> np.ndarray | str:
    """A mesh no skeleton skins, bound with weight 1 to the first joint whose motion from the
    rest time, T_j(t) T_j(r)⁻¹, is the mesh's own, X(t) X(r)⁻¹ (its local-to-world; an
    instanced copy (prim None) is static), at every time code: (n, j) one-hot rows, or the
    reason no joint does. Points time-sampled on the mesh itself are caught by `skin_data`'s
    final comparison with UsdSkel's points."""
    from pxr import Usd, UsdGeom

    n_t = time_codes.shape[0]
    motion = np.broadcast_to(np.eye(4), (n_t, 4, 4))
    if prim is not None:
        x_rest = usd_matrix(UsdGeom.XformCache(rest_time).GetLocalToWorldTransform(prim))
        inv_rest = np.linalg.inv(x_rest)
        motion = np.stack([  # (t, 4, 4) column convention
            (inv_rest @ usd_matrix(UsdGeom.XformCache(Usd.TimeCode(t))
                                   .GetLocalToWorldTransform(prim))).T
            for t in time_codes.tolist()])  # a loop over time codes
    joint_motion = transforms @ np.linalg.inv(rest)[None]  # (t, j, 4, 4)
    scale = np.ones((4, 4))
    scale[:3, 3] = 1.0 / size  # translations relative to the asset's size
    dev = (np.abs(joint_motion - motion[:, None]) * scale).max(axis=(0, 2, 3))  # (j,)
    match = np.flatnonzero(dev <= TOL.skin_match)
    path = "an instanced copy" if prim is None else f"mesh {prim.GetPath()}"
    if match.size == 0:
        return (f"{path} is not skinned and moves with no joint (closest: "
                f"{float(dev.min()):.3g} of the asset's size)")
    w = np.zeros((n, rest.shape[0]))
    w[:, int(match[0])] = 1.0
    return w
