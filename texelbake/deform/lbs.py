"""Linear-blend skinning as a warp (seed 002 Eq. 1 for a UsdSkel asset).

- `skin_blend`: p' = M_t(w) M_r(w)⁺ p, M the weight-blended joint transforms now (t) and at
  the rest pose (r): each point goes back to the skeleton's bind space through the blend of its
  own weights at rest and is skinned from there, as UsdSkel skins a mesh whose points are in
  bind space; exact Jacobian with the weights held fixed;
- `SkinWarp`: that map on arbitrary rest points, their weights transferred by closest point
  from the skinned mesh (`transfer_weights`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from texelbake.deform.warps import Warp, _points, bind_to_mesh
from texelbake.errors import ShapeError
from texelbake.tol import TOL

#: at most this many joints influence a point after weight transfer (UsdSkel's usual bound)
MAX_INFLUENCES = 4


def transfer_weights(points: np.ndarray, rest_vertices: np.ndarray, faces: np.ndarray,
                     weights: np.ndarray, max_influences: int = MAX_INFLUENCES) -> np.ndarray:
    """Skin weights of arbitrary points from a skinned mesh: closest point, barycentric blend
    of the triangle's vertex weights, the `max_influences` largest kept, renormalised (rows
    that sum to 0 stay 0: no influence).

    weights : (v, j) float64 per vertex; returns (n, j) float64"""
    w = np.asarray(weights, dtype=np.float64)
    prim, bary, _ = bind_to_mesh(points, rest_vertices, faces)
    out = np.einsum("nk,nkj->nj", bary, w[np.asarray(faces)[prim]])
    if out.shape[1] > max_influences:
        drop = np.argsort(-out, axis=1, kind="stable")[:, max_influences:]
        np.put_along_axis(out, drop, 0.0, axis=1)
    s = out.sum(axis=1, keepdims=True)
    return np.divide(out, s, out=np.zeros_like(out), where=s > 0)


def blend_affine(transforms: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Σ_j w_j X_j per point: transforms (j, 4, 4) column convention, weights (n, j) dense
    -> (n, 3, 4) float64 (the affine rows)."""
    x = np.asarray(transforms, dtype=np.float64)
    w = np.asarray(weights, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (4, 4) or w.ndim != 2 or w.shape[1] != x.shape[0]:
        raise ShapeError(f"weights (n, {x.shape[0] if x.ndim == 3 else '?'}) and transforms "
                         f"(j, 4, 4) expected, got {w.shape} and {x.shape}")
    return (w @ x[:, :3, :].reshape(x.shape[0], 12)).reshape(w.shape[0], 3, 4)


def apply_affine(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(n, 3, 4) affine per point applied to (n, 3) points -> (n, 3)."""
    return np.einsum("nij,nj->ni", m[:, :, :3], points) + m[:, :, 3]


def rest_inverse(rest_transforms: np.ndarray | None, weights: np.ndarray,
                 eps: float = TOL.skin_blend_cond) -> tuple[np.ndarray, np.ndarray]:
    """M_r⁺ of `skin_blend` per point: (n, 3, 4) affine (rest -> bind space) and valid (n,)
    bool; None rest transforms: the identity. Rows of weights summing to 0 are valid and
    map to the origin (their points have no bind-space position)."""
    w = np.asarray(weights, dtype=np.float64)
    n = w.shape[0]
    if rest_transforms is None:
        inv = np.zeros((n, 3, 4))
        inv[:, :, :3] = np.eye(3)
        return inv, np.ones(n, dtype=bool)
    blend = blend_affine(rest_transforms, w)
    free = w.sum(axis=1) <= 0
    blend[free, :, :3] = np.eye(3)
    sv = np.linalg.svd(blend[:, :, :3], compute_uv=False)  # (n, 3) descending
    valid = sv[:, 2] >= eps * sv[:, 0]
    a_inv = np.linalg.pinv(blend[:, :, :3], rcond=eps)  # (n, 3, 3) float64 (SVD cut at eps)
    inv = np.concatenate([a_inv, -np.einsum("nij,nj->ni", a_inv, blend[:, :, 3])[:, :, None]],
                         axis=2)
    inv[free] = 0.0
    return inv, valid


def bind_points(rest_transforms: np.ndarray, weights: np.ndarray, points: np.ndarray,
                eps: float = TOL.skin_blend_cond) -> tuple[np.ndarray, np.ndarray]:
    """The skeleton bind-space points q = M_r⁻¹ p of rest points p (n, 3) with dense weights
    (n, j) and rest transforms B_j (j, 4, 4): UsdSkel skinning q with the weights reproduces p
    at the rest time. returns q (n, 3) float64, valid (n,) bool (`rest_inverse`)."""
    inv, valid = rest_inverse(rest_transforms, weights, eps)
    return apply_affine(inv, _points(points)), valid


def skin_blend(transforms: np.ndarray, weights: np.ndarray, points: np.ndarray,
               rest_transforms: np.ndarray | None = None, eps: float = TOL.skin_blend_cond
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Linear-blend skinning of points given where they are in a rest pose:
    p' = M_t M_r⁺ p with M_t = Σ_j w_j T_j, M_r = Σ_j w_j B_j (affine, per point), i.e. the
    point's bind-space position M_r⁺ p skinned by UsdSkel's blend (exact for linear blend
    skinning at those weights: p = M_r q ⇒ p' = M_t q). J = A_t A_r⁺ (weights held fixed).

    transforms : (j, 4, 4) T_j, rest_transforms : (j, 4, 4) B_j (None: the identity, T_j then
    maps rest to deformed directly), column-vector convention; weights : (n, j) dense, rows
    summing to 1 or 0 (a row of 0: no influence, p' = p, J = I); points : (n, 3).
    M_r⁺ is the pseudo-inverse cut at `eps` σ_max (`rest_inverse`: rows where it cuts come
    back invalid).
    returns positions (n, 3), jacobians (n, 3, 3) float64, valid (n,) bool"""
    p = _points(points)
    w = np.asarray(weights, dtype=np.float64)
    if w.shape[0] != p.shape[0]:
        raise ShapeError(f"weights must have {p.shape[0]} rows, got {w.shape}")
    blend_t = blend_affine(transforms, w)  # (n, 3, 4)
    inv, valid = rest_inverse(rest_transforms, w, eps)
    pos = apply_affine(blend_t, apply_affine(inv, p))
    jac = np.einsum("nij,njk->nik", blend_t[:, :, :3], inv[:, :, :3])  # (n, 3, 3)
    free = w.sum(axis=1) <= 0
    pos[free] = p[free]
    jac[free] = np.eye(3)
    return pos, jac, valid


@dataclass
class SkinWarp(Warp):
    """Linear-blend skinning (`skin_blend`): p' = (Σ_j w_j T_j)(Σ_j w_j B_j)⁺ p, with the exact
    Jacobian (weights held fixed).

    transforms : (j, 4, 4) float64 T_j per joint, bind space -> deformed (UsdSkel's skinning
    transform with the skeleton's world transform), column-vector convention;
    rest_transforms : (j, 4, 4) B_j, the same at the rest pose (None: T_j maps rest to deformed
    directly); rest_vertices, faces, weights (v, j): the skinned mesh at rest, whose weights
    are transferred to other points (`transfer_weights`). A point without influence (all
    weights 0) stays at rest: p' = p, J = I."""

    transforms: np.ndarray
    rest_vertices: np.ndarray
    faces: np.ndarray
    weights: np.ndarray
    name: str = "skin"
    scale: float = 1.0
    rest_transforms: np.ndarray | None = None

    def _weights(self, p: np.ndarray) -> np.ndarray:
        rv = np.asarray(self.rest_vertices)
        if p.shape == rv.shape and np.array_equal(p, rv):
            w = np.asarray(self.weights, dtype=np.float64)
            s = w.sum(axis=1, keepdims=True)
            return np.divide(w, s, out=np.zeros_like(w), where=s > 0)
        return transfer_weights(p, rv, self.faces, self.weights)

    def positions(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        return skin_blend(self.transforms, self._weights(p), p, self.rest_transforms)[0]

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        return skin_blend(self.transforms, self._weights(p), p, self.rest_transforms)[1]
