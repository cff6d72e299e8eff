"""Warps Ψ: R³ → R³ (seed 002 Eq. 1), each giving the warped positions and the Jacobian.

A warp maps rest points (the acquisition frame, where the bake happened) to deformed points.
Every warp here is defined on arbitrary rest points, so that M_org, every M_i and the
characteristic points all follow the same Ψ:

- procedural warps, named in a spec string (`parse_warp`): `sine` (the seed's Fig. 13: a
  sinusoidal displacement across an axis), `twist`, `bend`, `stretch` (anisotropic scale),
  `scale` (uniform), `rigid` (rotation + translation). Their Jacobian is exact (closed form);
  `central_jacobian` is Eq. 6 for any warp and tests check the two agree;
- `MeshWarp`: time-sampled points of a mesh; each rest point is bound to its closest rest
  triangle (barycentrics and a normal offset) and follows it; the Jacobian is the triangle's
  affine deformation gradient;
- linear-blend skinning (`SkinWarp`, `transfer_weights`) lives in `texelbake.deform.lbs`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

from schemas import warp as warp_grammar
from texelbake.errors import SettingsError, ShapeError

#: Eq. 6 step, relative to the bounding-box diagonal of the warp's domain. Central
#: differences have truncation error O(ε² |Ψ'''|) and rounding error O(δ |Ψ| / ε) with
#: δ = 2.2e-16 (float64); both balance at ε ~ δ^(1/3) ≈ 6e-6 of the length scale over which
#: Ψ varies (for our procedural warps, the object's size), giving ~δ^(2/3) ≈ 4e-11 relative
#: error in u, v — far below what the float32 geometry can show. 1e-5 sits at that optimum.
CD_STEP = 1e-5


def _points(x: object, name: str = "points") -> np.ndarray:
    p = np.asarray(x, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ShapeError(f"{name} must be (n, 3), got {p.shape}")
    return p


class Warp(ABC):
    """Ψ on rest points. `scale` is the length over which the warp varies (for Eq. 6)."""

    name: str = "warp"
    scale: float = 1.0

    @abstractmethod
    def positions(self, points: np.ndarray) -> np.ndarray:
        """points : (n, 3) float64 rest → (n, 3) float64 deformed."""

    @abstractmethod
    def jacobian(self, points: np.ndarray) -> np.ndarray:
        """points : (n, 3) float64 rest → (n, 3, 3) float64 dΨ/dp (exact where known)."""


def central_jacobian(warp: Warp, points: np.ndarray, dirs: np.ndarray,
                     eps: float | None = None) -> np.ndarray:
    """Directional derivative of Ψ by central differences, Eq. 6:
    (Ψ(p + ε d) − Ψ(p − ε d)) / 2ε.

    points, dirs : (n, 3) float64 (dirs need not be unit); eps : absolute step, default
    `CD_STEP * warp.scale` (see CD_STEP). returns (n, 3) float64"""
    p = _points(points)
    d = _points(dirs, "dirs")
    e = CD_STEP * warp.scale if eps is None else float(eps)
    if not e > 0:
        raise SettingsError(f"field 'eps': must be > 0, got {eps}")
    return (warp.positions(p + e * d) - warp.positions(p - e * d)) / (2.0 * e)


# --------------------------------------------------------------------------- procedural


@dataclass
class AffineWarp(Warp):
    """p' = A p + t (stretch, uniform scale, rigid motion, shear): J = A everywhere."""

    matrix: np.ndarray
    offset: np.ndarray
    name: str = "affine"
    scale: float = 1.0

    def positions(self, points: np.ndarray) -> np.ndarray:
        return _points(points) @ np.asarray(self.matrix).T + np.asarray(self.offset)

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        n = _points(points).shape[0]
        return np.broadcast_to(np.asarray(self.matrix, np.float64), (n, 3, 3)).copy()


@dataclass
class AxisWarp(Warp):
    """Procedural warps along an axis a through `origin` (the bounding box's centre, at the
    low end of the axis), with s = (p − origin)·a ∈ [0, length]. kind:

    - "twist": rotation about a by φ = angle · s / length;
    - "bend": the axis bent into a circular arc of total angle `angle` toward b (Barr's bend):
      R = length / angle, φ = s / R,
      p' = o + b (R − (R − d) cos φ) + a (R − d) sin φ + c e, with d = (p − o)·b,
      e = (p − o)·c, c = a × b. Singular where d = R (the centre of curvature);
    - "sine": p' = p + b A sin(2π k s / length + phase) (the seed's Fig. 13), A = amplitude ·
      length: a shear whose amount varies along a.
    """

    kind: str
    axis: np.ndarray
    direction: np.ndarray
    origin: np.ndarray
    length: float
    angle: float = 0.0
    amplitude: float = 0.0
    periods: float = 1.0
    phase: float = 0.0
    name: str = "axis"
    scale: float = 1.0

    def _local(self, p: np.ndarray):
        a, b = self.axis, self.direction
        c = np.cross(a, b)
        q = p - self.origin
        return a, b, c, q @ a, q @ b, q @ c

    def positions(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        a, b, c, s, d, e = self._local(p)
        if self.kind == "sine":
            k = 2.0 * math.pi * self.periods / self.length
            return p + np.outer(self.amplitude * self.length * np.sin(k * s + self.phase), b)
        if self.kind == "twist":
            phi = self.angle * s / self.length
            cos, sin = np.cos(phi)[:, None], np.sin(phi)[:, None]
            # rotate (d, e) in the (b, c) plane
            return (self.origin + np.outer(s, a) + (cos * d[:, None] - sin * e[:, None]) * b
                    + (sin * d[:, None] + cos * e[:, None]) * c)
        # bend
        r = self.length / self.angle
        phi = s / r
        return (self.origin + np.outer(r - (r - d) * np.cos(phi), b)
                + np.outer((r - d) * np.sin(phi), a) + np.outer(e, c))

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        a, b, c, s, d, e = self._local(p)
        n = p.shape[0]
        if self.kind == "sine":
            k = 2.0 * math.pi * self.periods / self.length
            ds = self.amplitude * self.length * k * np.cos(k * s + self.phase)
            return np.eye(3)[None] + ds[:, None, None] * np.outer(b, a)[None]
        if self.kind == "twist":
            phi = self.angle * s / self.length
            cos, sin = np.cos(phi), np.sin(phi)
            rot = (np.outer(a, a)[None] + cos[:, None, None] * (np.outer(b, b) + np.outer(c, c))
                   + sin[:, None, None] * (np.outer(c, b) - np.outer(b, c)))  # (n, 3, 3)
            # d/dφ of the rotated (d, e) part, times dφ/ds
            dperp = ((-sin * d - cos * e)[:, None] * b + (cos * d - sin * e)[:, None] * c)
            return rot + (self.angle / self.length) * np.einsum("ni,j->nij", dperp, a)
        r = self.length / self.angle
        phi = s / r
        cos, sin = np.cos(phi), np.sin(phi)
        d_s = ((r - d) / r)[:, None] * (sin[:, None] * b + cos[:, None] * a)
        d_d = cos[:, None] * b - sin[:, None] * a
        return (np.einsum("ni,j->nij", d_s, a) + np.einsum("ni,j->nij", d_d, b)
                + np.broadcast_to(np.outer(c, c), (n, 3, 3)))


# --------------------------------------------------------------------------- from the asset


def bind_to_mesh(points: np.ndarray, rest_vertices: np.ndarray, faces: np.ndarray,
                 caster: object = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest rest triangle of each point: (prim (n,) int64, bary (n, 3) float64,
    normal offset (n,) float64 along the triangle's unit normal). caster : a RayCaster of
    the rest mesh to reuse (built when None)."""
    from texelbake.geometry.raycast import RayCaster

    p = _points(points)
    v = _points(rest_vertices, "rest_vertices")
    f = np.asarray(faces, dtype=np.int64)
    rc = caster if caster is not None else RayCaster(v, f)
    cp, prim, b2 = rc.closest_points(p)  # type: ignore[attr-defined]
    bary = np.column_stack([1.0 - b2[:, 0] - b2[:, 1], b2])
    nrm, _ = _unit(_face_normals(v, f)[prim])
    return prim, bary, np.einsum("ij,ij->i", p - cp, nrm)


def _face_normals(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    t = v[f]
    return np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0])


def _unit(x: np.ndarray, eps: float = 1e-300) -> tuple[np.ndarray, np.ndarray]:
    n = np.linalg.norm(x, axis=-1, keepdims=True)
    return np.divide(x, n, out=np.zeros_like(x), where=n > eps), n[..., 0] > eps


def triangle_jacobians(rest: np.ndarray, deformed: np.ndarray, faces: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray]:
    """Per-triangle affine deformation gradient: J [e1 e2 n] = [e1' e2' n'] with edges
    e1 = p1 − p0, e2 = p2 − p0, n the unit rest normal and n' the deformed unit normal times
    sqrt(area' / area) (as deformation transfer scales it: exact for similarities, so a
    uniform scale s gives J = s I and a rigid motion J = Q).

    returns (J (f, 3, 3) float64, valid (f,) bool — rest triangle not degenerate; J = I
    where invalid)"""
    f = np.asarray(faces, dtype=np.int64)
    r, d = _points(rest, "rest")[f], _points(deformed, "deformed")[f]
    n0, ok0 = _unit(np.cross(r[:, 1] - r[:, 0], r[:, 2] - r[:, 0]))
    c0 = np.linalg.norm(np.cross(r[:, 1] - r[:, 0], r[:, 2] - r[:, 0]), axis=1)
    c1 = np.cross(d[:, 1] - d[:, 0], d[:, 2] - d[:, 0])
    scale = np.sqrt(np.linalg.norm(c1, axis=1) * c0)
    n1 = np.divide(c1, scale[:, None], out=np.zeros_like(c1),
                   where=(scale > 0)[:, None])  # unit · sqrt(area ratio); 0 if collapsed
    src = np.stack([r[:, 1] - r[:, 0], r[:, 2] - r[:, 0], n0], axis=2)  # columns
    dst = np.stack([d[:, 1] - d[:, 0], d[:, 2] - d[:, 0], n1], axis=2)
    det = np.linalg.det(src)
    ok = ok0 & (np.abs(det) > 0)
    jac = np.broadcast_to(np.eye(3), (len(f), 3, 3)).copy()
    if ok.any():
        jac[ok] = dst[ok] @ np.linalg.inv(src[ok])
    return jac, ok


@dataclass
class MeshWarp(Warp):
    """Time-sampled points: a mesh at rest and deformed; any point follows its closest rest
    triangle's affine map: p' = q0' + J (p − q0) with q0, q0' the triangle's first corner at
    rest and deformed and J its `triangle_jacobians` (barycentrics in the plane, the normal
    offset along the deformed normal; the full offset, also where the closest point is on an
    edge or corner, so that affine warps are reproduced exactly).

    vertex_jacobians : (v, 3, 3) float64 or None — when given (a warp Ψ whose own Jacobian is
    known at the rest vertices), `jacobian` is their barycentric interpolation on the closest
    rest triangle instead of the triangle's constant affine map: the field the deformed
    M_org's shading normals cof(J) n come from (`render.deformed.deform_scene`), continuous
    across triangles. Positions are unchanged (the triangle's affine map)."""

    rest: np.ndarray
    deformed: np.ndarray
    faces: np.ndarray
    name: str = "mesh"
    scale: float = 1.0
    vertex_jacobians: np.ndarray | None = None

    def __post_init__(self) -> None:
        if np.shape(self.rest) != np.shape(self.deformed):
            raise ShapeError(f"deformed points {np.shape(self.deformed)} must match the rest "
                             f"points {np.shape(self.rest)}")
        from texelbake.geometry.raycast import RayCaster

        self._jac, _ = triangle_jacobians(self.rest, self.deformed, self.faces)
        self._caster = RayCaster(self.rest, self.faces)
        if self.vertex_jacobians is not None:
            vj = np.asarray(self.vertex_jacobians, dtype=np.float64)
            if vj.shape != (np.shape(self.rest)[0], 3, 3):
                raise ShapeError(f"vertex_jacobians must be ({np.shape(self.rest)[0]}, 3, 3), "
                                 f"got {vj.shape}")
            self.vertex_jacobians = vj

    def positions(self, points: np.ndarray) -> np.ndarray:
        p = _points(points)
        prim, _, _ = bind_to_mesh(p, self.rest, self.faces, self._caster)
        corner = np.asarray(self.faces)[prim, 0]
        q0, q1 = np.asarray(self.rest)[corner], np.asarray(self.deformed)[corner]
        return q1 + np.einsum("nij,nj->ni", self._jac[prim], p - q0)

    def jacobian(self, points: np.ndarray) -> np.ndarray:
        prim, bary, _ = bind_to_mesh(points, self.rest, self.faces, self._caster)
        if self.vertex_jacobians is None:
            return self._jac[prim].copy()
        corners = np.asarray(self.faces, dtype=np.int64)[prim]  # (n, 3)
        return np.einsum("nk,nkij->nij", bary, self.vertex_jacobians[corners])


@dataclass
class SkinnedMeshWarp(MeshWarp):
    """A skinned asset's time samples at one time (`MeshWarp`) with its skin's joint transforms
    (`model.SkinData`): `transforms` (j, 4, 4) float64 bind space -> world at that time and
    `rest_transforms` (j, 4, 4) the same at the rest time. The deformed frame moves M_org and
    the characteristic points by the samples, and LOD meshes bound to the skeleton by their own
    weights (`lbs.SkinWarp`, `render.deformed.deform_scene`)."""

    transforms: np.ndarray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    rest_transforms: np.ndarray | None = None


# --------------------------------------------------------------------------- spec strings

_AXES = {"x": np.array([1.0, 0, 0]), "y": np.array([0, 1.0, 0]), "z": np.array([0, 0, 1.0])}
#: name -> {parameter: default}
WARP_PARAMS = warp_grammar.WARP_PARAMS


def parse_warp_fields(spec: str) -> tuple[str, dict[str, object]]:
    try:
        return warp_grammar.parse_warp_fields(spec)
    except ValueError as exc:
        raise SettingsError(str(exc)) from None


def check_warp_spec(spec: str) -> str:
    """`schemas.warp.check_warp_spec` with a SettingsError (exit status 2 on the CLI)."""
    try:
        return warp_grammar.check_warp_spec(spec)
    except ValueError as exc:
        raise SettingsError(str(exc)) from None


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1.0 - math.cos(angle)) * (k @ k)


def parse_warp(spec: str, bounds: np.ndarray) -> Warp:
    """A procedural warp from a spec `name:key=value,...` (WARP_PARAMS lists names, fields
    and defaults; angles in degrees, sine amplitude as a fraction of the axis length),
    placed on the rest bounding box `bounds` (2, 3): the axis runs through the box's centre
    from its low end, over its extent along the axis."""
    name, prm = parse_warp_fields(spec)
    lo, hi = np.asarray(bounds, dtype=np.float64).reshape(2, 3)
    centre = 0.5 * (lo + hi)
    diag = float(np.linalg.norm(hi - lo)) or 1.0
    if name in ("stretch", "scale", "rigid"):
        if name == "rigid":
            m = _rotation(_AXES[str(prm["axis"])], math.radians(float(prm["angle"])))  # type: ignore[arg-type]
            t = np.array([prm["tx"], prm["ty"], prm["tz"]], dtype=np.float64)
        else:
            s = ([prm["x"], prm["y"], prm["z"]] if name == "stretch" else [prm["s"]] * 3)
            m = np.diag(np.asarray(s, dtype=np.float64))
            t = np.zeros(3)
        # about the box's centre: p' = m (p − c) + c + t
        return AffineWarp(m, centre - m @ centre + t, name=spec, scale=diag)
    a = _AXES[str(prm["axis"])]
    b = _AXES[str(prm.get("toward", "x"))] if name != "twist" else _AXES[
        "x" if prm["axis"] != "x" else "y"]
    if abs(float(a @ b)) > 0.5:
        raise SettingsError(f"field 'warp.toward': must differ from the axis "
                            f"{prm['axis']!r}, got {prm.get('toward')!r}")
    length = float((hi - lo) @ a)
    if not length > 0:
        raise SettingsError(f"field 'warp.axis': the asset is flat along {prm['axis']!r}")
    origin = centre - a * float((centre - lo) @ a)
    angle = math.radians(float(prm.get("angle", 0.0)))  # type: ignore[arg-type]
    if name == "bend" and abs(angle) < 1e-9:
        return AffineWarp(np.eye(3), np.zeros(3), name=spec, scale=diag)
    return AxisWarp(name, a, b, origin, length, angle=angle,
                    amplitude=float(prm.get("amplitude", 0.0)),  # type: ignore[arg-type]
                    periods=float(prm.get("periods", 1.0)),  # type: ignore[arg-type]
                    phase=math.radians(float(prm.get("phase", 0.0))),  # type: ignore[arg-type]
                    name=spec, scale=diag)
