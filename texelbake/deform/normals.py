"""Normals carried by a warp: the cofactor of its Jacobian maps a surface's normals to the
deformed surface's, defined where the Jacobian is singular."""

from __future__ import annotations

import numpy as np


def cofactor(jac: np.ndarray) -> np.ndarray:
    """cof(J) = det(J) J⁻ᵀ, columns (j2 × j3, j3 × j1, j1 × j2): maps normals to the deformed
    surface's normals without inverting J (defined where J is singular). (n, 3, 3)"""
    j1, j2, j3 = jac[:, :, 0], jac[:, :, 1], jac[:, :, 2]
    return np.stack([np.cross(j2, j3), np.cross(j3, j1), np.cross(j1, j2)], axis=2)


def deform_normals(jac: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Unit normals carried by Ψ: cof(J) n / |cof(J) n| (zero where that vanishes)."""
    n = np.einsum("nij,nj->ni", cofactor(jac), normals)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    return np.divide(n, length, out=np.zeros_like(n), where=length > 0)
