"""The LOD meshes of the baked USD (DESIGN.md "The baked USD"): M_i with its atlas uvs, shading
normals, the impostor parameterization (seed 002 Table 1) and how it follows M_org's animation
(UsdSkel influences or time samples), authored on and read from one `UsdGeom.Mesh` each.
`texelbake.usd.write` and `texelbake.usd.read` write and read the rest of the bundle around them."""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdSkel, Vt

from texelbake.errors import AssetError

_NS = "texelbake:"


@dataclass
class LodMesh:
    """M_i with its atlas uvs. vertices (n, 3) float64, faces (f, 3) int64, corner_uvs (f, 3, 2);
    impostor: the local impostor parameterization of seed 002 Table 1 (`IMPOSTOR_PRIMVARS`,
    each (n, 3) float64 per vertex; empty when the bake wrote none); corner_normals: (f, 3, 3)
    shading normals per face corner, authored as faceVarying `normals` for other tools
    (`lodnormals.lod_corner_normals`; None: none authored, as in bakes before it).
    skin: the UsdSkel binding transferred from M_org (`texelbake.deform.skinbind`):
    "indices" (n, k) int32 and "weights" (n, k) float32 per vertex, "bind" (4, 4) float64
    the geomBindTransform (row-vector convention), "points" (n, 3) float64 the points the
    mesh carries for UsdSkel (its bind pose; `vertices` stay the rest positions, which the
    payload holds as the impostor's p0), "xform" (4, 4) float64 the transform of `Baked`, the
    LODs' SkelRoot (row-vector convention; `model.SkinData.placement`: UsdSkel ignores it,
    other tools place the bind pose with it); empty when the asset is not skinned.
    time_codes, points_over_time: (t,) and (t, n, 3) float64 time samples of the vertices
    (an animated asset without one skeleton); empty otherwise."""

    vertices: np.ndarray
    faces: np.ndarray
    corner_uvs: np.ndarray
    impostor: dict[str, np.ndarray] = field(default_factory=dict)
    corner_normals: np.ndarray | None = None
    skin: dict[str, np.ndarray] = field(default_factory=dict)
    time_codes: np.ndarray = field(default_factory=lambda: np.zeros(0))
    points_over_time: np.ndarray = field(default_factory=lambda: np.zeros((0, 0, 3)))



def author_mesh(stage: Usd.Stage, path: str, mesh: LodMesh) -> UsdGeom.Mesh:
    geom = UsdGeom.Mesh.Define(stage, path)
    # aligned copies where needed: a mapped artifact's arrays may be unaligned, which
    # Vt.*.FromNumpy refuses (see usd.write.author_array)
    v = np.require(mesh.skin.get("points", mesh.vertices), dtype=np.float32,
                   requirements=["C", "A"])
    f = np.require(mesh.faces, dtype=np.int32, requirements=["C", "A"])
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(f)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(f.reshape(-1)))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    lo, hi = (v.min(axis=0), v.max(axis=0)) if len(v) else (np.zeros(3), np.zeros(3))
    geom.CreateExtentAttr(Vt.Vec3fArray([Gf.Vec3f(float(lo[0]), float(lo[1]), float(lo[2])),
                                         Gf.Vec3f(float(hi[0]), float(hi[1]), float(hi[2]))]))
    st = UsdGeom.PrimvarsAPI(geom).CreatePrimvar(
        "st", Sdf.ValueTypeNames.TexCoord2fArray, UsdGeom.Tokens.faceVarying
    )
    st.Set(Vt.Vec2fArray.FromNumpy(
        np.ascontiguousarray(mesh.corner_uvs.reshape(-1, 2), dtype=np.float32)))
    if mesh.corner_normals is not None:
        geom.CreateNormalsAttr(Vt.Vec3fArray.FromNumpy(
            np.ascontiguousarray(mesh.corner_normals.reshape(-1, 3), dtype=np.float32)))
        geom.SetNormalsInterpolation(UsdGeom.Tokens.faceVarying)
    _author_impostor(geom, mesh.impostor)
    _author_animation(geom, mesh)
    return geom


def _author_animation(geom: UsdGeom.Mesh, mesh: LodMesh) -> None:
    """The LOD follows M_org (`texelbake.deform.skinbind`): UsdSkel influences (the skeleton
    relationship is authored in the root layer, where the skeleton's path is in namespace) or
    time samples of its points."""
    if mesh.skin:
        api = UsdSkel.BindingAPI.Apply(geom.GetPrim())
        idx = np.ascontiguousarray(mesh.skin["indices"], dtype=np.int32)
        wgt = np.ascontiguousarray(mesh.skin["weights"], dtype=np.float32)
        k = int(idx.shape[1])
        api.CreateJointIndicesPrimvar(False, k).Set(Vt.IntArray.FromNumpy(idx.reshape(-1)))
        api.CreateJointWeightsPrimvar(False, k).Set(Vt.FloatArray.FromNumpy(wgt.reshape(-1)))
        api.CreateGeomBindTransformAttr(Gf.Matrix4d(np.asarray(mesh.skin["bind"],
                                                               np.float64).tolist()))
    if mesh.time_codes.shape[0] > 1:
        author_point_samples(geom, zip(mesh.time_codes.tolist(), mesh.points_over_time,
                                       strict=True))


def extent_of(points: np.ndarray) -> Vt.Vec3fArray:
    """A mesh's `extent`: the (2,) float3 bounds of its (n, 3) points."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    return Vt.Vec3fArray([Gf.Vec3f(*map(float, lo)), Gf.Vec3f(*map(float, hi))])


def author_point_samples(geom: UsdGeom.Mesh, samples: Iterable[tuple[float, np.ndarray]]
                         ) -> None:
    """Time samples of a mesh's points and extent: one per (time code, (n, 3) points), the
    points as float32 (a LOD that follows time-sampled points, the animated proxy)."""
    attr = geom.GetPointsAttr()
    ext = geom.GetExtentAttr()
    for t, pts in samples:  # a loop over time codes
        p32 = np.ascontiguousarray(pts, dtype=np.float32)
        attr.Set(Vt.Vec3fArray.FromNumpy(p32), Usd.TimeCode(t))
        ext.Set(extent_of(p32), Usd.TimeCode(t))


#: the impostor parameterization's primvars (seed 002 Table 1): `primvars:texelbake:<name>`,
#: float3[] per vertex: p0 rest position, r0 Rodrigues vector of R0, u0 and v0 rest tangents
IMPOSTOR_PRIMVARS = ("p0", "r0", "u0", "v0")


def _author_impostor(geom: UsdGeom.Mesh, impostor: dict[str, np.ndarray]) -> None:
    api = UsdGeom.PrimvarsAPI(geom)
    for name in IMPOSTOR_PRIMVARS if impostor else ():
        pv = api.CreatePrimvar(f"{_NS}{name}", Sdf.ValueTypeNames.Float3Array,
                               UsdGeom.Tokens.vertex)
        pv.Set(Vt.Vec3fArray.FromNumpy(np.ascontiguousarray(impostor[name], dtype=np.float32)))


def read_impostor(geom: UsdGeom.Mesh, n_points: int) -> dict[str, np.ndarray]:
    api = UsdGeom.PrimvarsAPI(geom)
    out: dict[str, np.ndarray] = {}
    for name in IMPOSTOR_PRIMVARS:
        pv = api.GetPrimvar(f"{_NS}{name}")
        value = pv.Get() if pv else None
        if value is None:
            return {}
        arr = np.array(value, dtype=np.float32).astype(np.float64).reshape(-1, 3)
        if arr.shape[0] != n_points:
            raise AssetError(f"primvar {_NS}{name} has {arr.shape[0]} values for "
                             f"{n_points} points", prim=str(geom.GetPath()))
        out[name] = arr
    return out



def read_animation(geom: UsdGeom.Mesh, mesh: LodMesh, skeleton: str) -> str:
    """Fill mesh.skin / mesh.time_codes from the LOD prim (`_author_animation`); returns the
    bound skeleton's path on the baked stage (or `skeleton` unchanged when unskinned). A bound
    LOD's `points` are its bind pose: mesh.vertices become its rest positions, the impostor's
    p0 (AssetError when it has none)."""
    prim = geom.GetPrim()
    n = mesh.vertices.shape[0]
    if prim.HasAPI(UsdSkel.BindingAPI):
        api = UsdSkel.BindingAPI(prim)
        ipv, wpv = api.GetJointIndicesPrimvar(), api.GetJointWeightsPrimvar()
        k = int(ipv.GetElementSize()) if ipv else 0
        idx = np.array(ipv.Get() if ipv else [], dtype=np.int32)
        wgt = np.array(wpv.Get() if wpv else [], dtype=np.float32)
        if k <= 0 or idx.shape[0] != n * k or wgt.shape[0] != n * k:
            raise AssetError(f"primvars:skel:jointIndices/jointWeights hold {idx.shape[0]} / "
                             f"{wgt.shape[0]} values for {n} points (element size {k})",
                             prim=str(prim.GetPath()))
        bind = api.GetGeomBindTransformAttr().Get()
        targets = api.GetSkeletonRel().GetTargets()
        if not targets:
            raise AssetError("skinned LOD has no skel:skeleton target", prim=str(prim.GetPath()))
        if "p0" not in mesh.impostor:
            raise AssetError("skinned LOD has no primvars:texelbake:p0 (its rest positions)",
                             prim=str(prim.GetPath()))
        mesh.skin = {"indices": idx.reshape(n, k), "weights": wgt.reshape(n, k),
                     "bind": np.array(bind if bind is not None else Gf.Matrix4d(1.0),
                                      dtype=np.float64).reshape(4, 4),
                     "points": mesh.vertices,
                     "xform": np.array(UsdGeom.Xformable(prim.GetParent()).GetLocalTransformation(
                         Usd.TimeCode.Default()), dtype=np.float64).reshape(4, 4)}
        mesh.vertices = mesh.impostor["p0"].copy()
        skeleton = str(targets[0])
    times = geom.GetPointsAttr().GetTimeSamples()
    if len(times) > 1:
        mesh.time_codes = np.asarray(times, dtype=np.float64)
        mesh.points_over_time = np.stack([
            np.array(geom.GetPointsAttr().Get(Usd.TimeCode(t)), dtype=np.float32)
            .astype(np.float64).reshape(n, 3) for t in times])
    return skeleton
