"""The LOD meshes follow M_org: what the baked USD authors on M1..Mn
so that any USD viewer animates every LOD, and what the renderer's deformed frame does with it.

- A skinned asset (`model.SkinData`): each LOD vertex gets joint weights transferred from
  M_org (`lbs.transfer_weights`: closest point, barycentric blend of the triangle's vertex
  weights, the `MAX_INFLUENCES` largest kept, renormalised), stored as UsdSkel
  `primvars:skel:jointIndices` / `jointWeights` (vertex interpolation, element size
  `MAX_INFLUENCES`, float32) with the skeleton's joint order. The LOD was built at the rest
  pose, which need not be the bind pose (an animation's first frame, restTransforms other than
  the bind pose): its points are authored in bind space, q = M_r⁻¹ p with M_r = Σ_j w_j B_j
  the vertex's own blend of the joints' rest transforms (`lod_bind_points`), with the identity
  geomBindTransform; the transform of their SkelRoot `Baked` (which UsdSkel ignores) puts that
  bind pose where the skeleton stands for tools that place a skinned mesh by its parent
  (`SkinData.placement`: Blender's importer). UsdSkel then poses
  the LOD at M_t q: p itself at the rest time (exact for linear blend skinning at those
  weights), the rig's motion at every other. The renderer deforms the LOD meshes with the same
  weights (as read back from the payload) and the same map (`lbs.skin_blend`). A vertex whose
  M_r is near-singular (`TOL.skin_blend_cond`) has no usable bind-space point: the export then
  gives every LOD time samples instead, and says so.
- Time-sampled points without one skeleton: each LOD vertex is bound to its closest rest
  triangle of M_org and follows that triangle's affine map (`warps.MeshWarp`: barycentrics and
  normal offset, the deformed normal scaled by sqrt(area ratio)); the LOD's `points` carry
  one time sample per time code of the asset (`lod_time_samples`).
"""

from __future__ import annotations

import numpy as np

from texelbake.deform.lbs import MAX_INFLUENCES, bind_points, transfer_weights
from texelbake.deform.warps import bind_to_mesh, triangle_jacobians
from texelbake.errors import SettingsError, ShapeError
from texelbake.model import AssetModel, SkinData


def lod_skin(skin: SkinData, rest_points: np.ndarray, faces: np.ndarray, vertices: np.ndarray,
             max_influences: int = MAX_INFLUENCES) -> tuple[np.ndarray, np.ndarray]:
    """Skin binding of LOD vertices (n, 3) from M_org's: (indices (n, k) int32 into the
    skeleton's joints, weights (n, k) float32), k = min(max_influences, joints); unused
    influences have weight 0 (index 0). Every row sums to 1 (M_org's rows all do)."""
    w = transfer_weights(vertices, rest_points, faces, skin.weights, max_influences)
    k = min(max_influences, w.shape[1])
    idx = np.argsort(-w, axis=1, kind="stable")[:, :k]
    wk = np.take_along_axis(w, idx, axis=1)
    idx = np.where(wk > 0, idx, 0)
    return idx.astype(np.int32), wk.astype(np.float32)


def dense_weights(indices: np.ndarray, weights: np.ndarray, n_joints: int) -> np.ndarray:
    """(n, k) joint indices and weights -> (n, j) float64 dense (repeated indices add)."""
    idx = np.asarray(indices, dtype=np.int64)
    wgt = np.asarray(weights, dtype=np.float64)
    if idx.shape != wgt.shape or idx.ndim != 2:
        raise ShapeError(f"joint indices {idx.shape} and weights {wgt.shape} must be (n, k)")
    if idx.size and (idx.min() < 0 or idx.max() >= n_joints):
        raise ShapeError(f"joint indices must lie in [0, {n_joints}), got "
                         f"[{idx.min()}, {idx.max()}]")
    out = np.zeros((idx.shape[0], n_joints))
    np.add.at(out, (np.repeat(np.arange(idx.shape[0]), idx.shape[1]), idx.reshape(-1)),
              wgt.reshape(-1))
    return out


def transforms_at(skin: SkinData, time_codes: np.ndarray, time: float) -> np.ndarray:
    """The skin's (j, 4, 4) rest -> deformed transforms at `time`: at a time code exactly
    UsdSkel's; between two codes the matrices are blended linearly (UsdSkel interpolates the
    joints' translations, rotations and scales instead, so there the two differ by O(Δangle²));
    clamped to the first / last code."""
    codes = np.asarray(time_codes, dtype=np.float64)
    if codes.shape[0] != skin.transforms.shape[0] or codes.shape[0] == 0:
        raise ShapeError(f"{codes.shape[0]} time codes for {skin.transforms.shape[0]} "
                         "skinning samples")
    if not np.isfinite(time):
        raise SettingsError(f"field 'time': must be finite, got {time}")
    t = float(np.clip(time, codes[0], codes[-1]))
    k = int(np.clip(np.searchsorted(codes, t, side="right") - 1, 0, max(codes.shape[0] - 2, 0)))
    if codes.shape[0] == 1:
        return skin.transforms[0].copy()
    a = (t - codes[k]) / (codes[k + 1] - codes[k])
    return (1.0 - a) * skin.transforms[k] + a * skin.transforms[k + 1]


def lod_bind_points(skin: SkinData, indices: np.ndarray, weights: np.ndarray,
                    vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The points a LOD mesh bound by (indices, weights) (n, k) carries (module docstring): its
    rest vertices (n, 3) taken to the skeleton's bind space by their own blended rest
    transform. returns points (n, 3) float64, valid (n,) bool (False: the blend is
    near-singular there, `lbs.rest_inverse`)."""
    return bind_points(skin.rest, dense_weights(indices, weights, len(skin.joints)), vertices)


def lod_time_samples(asset: AssetModel, vertices: np.ndarray) -> np.ndarray:
    """(t, n, 3) float64: LOD vertices following M_org's time samples (module docstring),
    one frame per `asset.time_codes`."""
    v = np.asarray(vertices, dtype=np.float64)
    prim, _, _ = bind_to_mesh(v, asset.points, asset.faces)
    corner = asset.faces[prim, 0]
    q0 = asset.points[corner]
    out = np.empty((asset.points_over_time.shape[0],) + v.shape)
    for k, pts in enumerate(asset.points_over_time):  # a loop over time codes
        jac, _ = triangle_jacobians(asset.points, pts, asset.faces)
        out[k] = pts[corner] + np.einsum("nij,nj->ni", jac[prim], v - q0)
    return out
