"""The look-up rotation of seed 002 §4.2: the deformed tangents (u, v) = J (u0, v0) (Eq. 6 or
the exact Jacobian), their orthogonalized frame n̄, b̄, ū, v̄ (Eqs. 7–9) and
L = R0 (ū, v̄, n̄)ᵀ (Eq. 10), which maps deformed-world directions (l*, v*) to the rest
frame where the baked tables are evaluated.

Singular Jacobians. Where u × v vanishes (|u × v| ≤ SINGULAR_SIN |u| |v|: the warp folds the
surface, or squeezes a direction to nothing), Eq. 7 has no normal. Fallback, stated and
tested: n̄ is the given `fallback_normal` (the deformed surface's own normal at the point)
and b̄ is the bisector of whichever of u, v is non-zero, projected onto its plane (else the
default tangent of `frames.tangent_frames`); where no fallback normal is given (or it is
zero) the frame is R0 itself, i.e. L = I: directions are looked up unrotated, as `cpm-naive`
does. `valid` reports which points took Eqs. 7–9; no NaN is produced anywhere.

Folds. Where a fallback normal is given and u × v points against it, Ψ reverses the
orientation at the point (det J < 0: a bend whose centre of curvature lies inside the
impostor, so that M_i's vertices outside M_org are carried past it): the same fallback
applies. Without it, L turned such frames by ~180° (the 90° bend of the cylinder: 9 dB
against cpm-naive's 26 dB).
"""

from __future__ import annotations

import numpy as np

from texelbake.deform.warps import Warp, central_jacobian
from texelbake.errors import SettingsError, ShapeError
from texelbake.geometry.basis import tangent_frames

#: |u × v| / (|u| |v|) at or below this: the tangent plane is degenerate (a 1e-9 rad angle
#: between u and v is far below any real surface's shear; float64 cross products of unit
#: vectors are exact to ~1e-16)
SINGULAR_SIN = 1e-9


def _vec(x: object, name: str) -> np.ndarray:
    a = np.asarray(x, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != 3:
        raise ShapeError(f"{name} must be (n, 3), got {a.shape}")
    return a


def _unit(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    ln = np.linalg.norm(x, axis=1, keepdims=True)
    return np.divide(x, ln, out=np.zeros_like(x), where=ln > 0), ln[:, 0]


def orthogonalize(u: np.ndarray, v: np.ndarray, fallback_normal: np.ndarray | None = None,
                  eps: float = SINGULAR_SIN
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Eqs. 7–9: n̄ = u × v / |u × v|, b̄ = (u/|u| + v/|v|) / |·|,
    ū = (b̄ + b̄ × n̄)/√2, v̄ = (b̄ + n̄ × b̄)/√2 — the orthonormal pair that minimises the
    summed squared angles to (u, v).

    u, v : (n, 3) float64; fallback_normal : (n, 3) or None (module docstring)
    returns (ū, v̄, n̄ (n, 3) each, valid (n,) bool — Eqs. 7–9 applied; elsewhere n̄ is the
    fallback normal, or all three are zero when there is none)"""
    u, v = _vec(u, "u"), _vec(v, "v")
    if u.shape != v.shape:
        raise ShapeError(f"u {u.shape} and v {v.shape} must match")
    uh, lu = _unit(u)
    vh, lv = _unit(v)
    cross = np.cross(u, v)
    nbar, lc = _unit(cross)
    valid = (lu > 0) & (lv > 0) & (lc > eps * lu * lv)
    b = uh + vh
    if fallback_normal is not None:
        fb, lf = _unit(_vec(fallback_normal, "fallback_normal"))
        valid &= ~(np.einsum("ij,ij->i", nbar, fb) < 0.0)  # a fold: u × v against the surface
        nbar = np.where(valid[:, None], nbar, fb)
        has = valid | (lf > 0)
        # the bisector projected onto the fallback plane; if that vanishes, a default tangent
        bp = b - np.einsum("ij,ij->i", b, nbar)[:, None] * nbar
        bp, lb = _unit(bp)
        default = tangent_frames(np.where(has[:, None], nbar, [0.0, 0.0, 1.0]))[:, 0]
        b = np.where((lb > 1e-12)[:, None], bp, default)
    else:
        has = valid
    bbar, _ = _unit(b)
    bbar = np.where(has[:, None], bbar, 0.0)
    nbar = np.where(has[:, None], nbar, 0.0)
    s = 1.0 / np.sqrt(2.0)
    ubar = s * (bbar + np.cross(bbar, nbar))
    vbar = s * (bbar + np.cross(nbar, bbar))
    return ubar, vbar, nbar, valid


def lookup_rotation(rest_frames: np.ndarray, u: np.ndarray, v: np.ndarray,
                    fallback_normal: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 10: L = R0 (ū, v̄, n̄)ᵀ (deformed world → rest world).

    rest_frames : (n, 3, 3) R0 with columns (u0, v0, n0); u, v : (n, 3) deformed tangents
    returns (L (n, 3, 3) float64, valid (n,) bool); where no frame exists L = I"""
    r0 = np.asarray(rest_frames, dtype=np.float64)
    ubar, vbar, nbar, valid = orthogonalize(u, v, fallback_normal)
    if r0.shape != (ubar.shape[0], 3, 3):
        raise ShapeError(f"rest_frames must be ({ubar.shape[0]}, 3, 3), got {r0.shape}")
    deformed = np.stack([ubar, vbar, nbar], axis=2)  # columns
    none = ~np.any(nbar != 0.0, axis=1)
    deformed[none] = r0[none]  # no frame at all: L = I (module docstring)
    return r0 @ np.transpose(deformed, (0, 2, 1)), valid


def deformed_tangents(warp: Warp, p0: np.ndarray, u0: np.ndarray, v0: np.ndarray,
                      method: str = "exact") -> tuple[np.ndarray, np.ndarray]:
    """(u, v) = Ψ carried on (u0, v0) at p0: J u0, J v0 with the warp's Jacobian ("exact")
    or Eq. 6's central differences ("central"). All (n, 3) float64."""
    p0, u0, v0 = _vec(p0, "p0"), _vec(u0, "u0"), _vec(v0, "v0")
    if method == "exact":
        jac = warp.jacobian(p0)
        return np.einsum("nij,nj->ni", jac, u0), np.einsum("nij,nj->ni", jac, v0)
    if method == "central":
        return central_jacobian(warp, p0, u0), central_jacobian(warp, p0, v0)
    raise SettingsError(f"field 'jacobian': 'exact' or 'central', got {method!r}")


def rest_frames_at(u0: np.ndarray, v0: np.ndarray) -> np.ndarray:
    """R0 at points inside triangles from interpolated rest tangents (n, 3): the same
    orthogonalization (Eqs. 7–9), which leaves an orthonormal (u0, v0) unchanged, so at a
    vertex it is exactly R0. Rigid motions commute with it (L = Qᵀ everywhere)."""
    ub, vb, nb, _ = orthogonalize(u0, v0)
    return np.stack([ub, vb, nb], axis=2)


def interpolate(values: np.ndarray, faces: np.ndarray, prim: np.ndarray, bary: np.ndarray
                ) -> np.ndarray:
    """Barycentric interpolation of per-vertex values (v, k) at (prim (n,), bary (n, 3))."""
    f = np.asarray(faces, dtype=np.int64)[np.asarray(prim, dtype=np.int64)]
    return np.einsum("nk,nkj->nj", np.asarray(bary, dtype=np.float64),
                     np.asarray(values, dtype=np.float64)[f])


def align_quarter_turns(u0: np.ndarray, v0: np.ndarray, u: np.ndarray, v: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Per-vertex frames of one triangle made consistent before they are interpolated.

    Each vertex chose (u0, v0) among the four quarter turns about its normal (the choice that
    keeps its Rodrigues angle small, `impostor`), so neighbours may disagree by 90° or 180°
    and their average can vanish. Corners 1 and 2 are turned, (u0, v0) → (v0, −u0) and the
    same for (u, v), by the quarter turn that best aligns their u0 with corner 0's; L of a
    vertex does not depend on the turn (Eq. 9 commutes with it).

    all arguments (n, 3, 3): [point, corner, xyz]; returns the four arrays turned"""
    u0, v0, u, v = (np.array(x, dtype=np.float64) for x in (u0, v0, u, v))
    ref = u0[:, 0]
    for c in (1, 2):
        cands = [(u0[:, c], v0[:, c], u[:, c], v[:, c]),
                 (v0[:, c], -u0[:, c], v[:, c], -u[:, c]),
                 (-u0[:, c], -v0[:, c], -u[:, c], -v[:, c]),
                 (-v0[:, c], u0[:, c], -v[:, c], u[:, c])]
        score = np.stack([np.einsum("ij,ij->i", k[0], ref) for k in cands], axis=1)
        best = np.argmax(score, axis=1)
        for arr, j in ((u0, 0), (v0, 1), (u, 2), (v, 3)):
            arr[:, c] = np.choose(best[:, None], [k[j] for k in cands])
    return u0, v0, u, v
