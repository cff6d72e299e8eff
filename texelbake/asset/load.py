"""`load_asset`: a USD asset -> one immutable AssetModel (meshes, materials, lights, cameras,
time-sampled points)."""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np

from texelbake.asset.compose import read_composed
from texelbake.asset.dome import read_dome
from texelbake.asset.instancers import instancer_meshes
from texelbake.asset.lights import read_camera, read_light
from texelbake.asset.materials import DEFAULT_MATERIAL, MaterialReader, face_materials
from texelbake.asset.meshes import (
    MeshData,
    area_weighted_normals,
    is_rendered,
    read_mesh,
    row_norm,
    skinning_queries,
    tri_cross,
    world_points,
)
from texelbake.asset.paths import AssetScan, scan_asset_paths
from texelbake.asset.skin import skin_data
from texelbake.asset.values import warn
from texelbake.errors import AssetError
from texelbake.model import (
    AssetModel,
    Camera,
    Light,
    Material,
)
from texelbake.tol import TOL


def _ancestors(prim: Any) -> Iterable[Any]:
    while prim and not prim.IsPseudoRoot():
        yield prim
        prim = prim.GetParent()


def load_asset(path: str | Path, *, time_code: float | None = None) -> AssetModel:
    """Read a USD asset into one AssetModel (see `texelbake.model.AssetModel` for every field).

    path : `.usda` / `.usdc` / `.usd` / `.usdz`. `scan_asset_paths` runs first, before the stage
        is composed with its variant selections (`texelbake.asset.compose.read_composed`: MaterialX
        documents through their translation); paths only unselected variants name are never
        read and listed in `unreachable_paths`, missing textures in `missing_paths`.
    time_code : the time at which points, transforms, lights and cameras are read. None reads
        each attribute at its earliest time sample, or its default value when it has none
        (`Usd.TimeCode.EarliestTime()`).

    Meshes (visible, non-guide `UsdGeom.Mesh` prims, instance proxies included) are flattened to
    world space (normals by the inverse-transpose), fan-triangulated, and counter-clockwise
    (winding flipped for `orientation = "leftHanded"` and for mirroring transforms). Triangles
    with area below `TOL.zero_area * bbox_diag**2` are dropped and counted, with a warning.
    Time-sampled points or transforms (on the mesh or an ancestor) give `time_codes` and
    `points_over_time` (every mesh, same vertex order as `points`).

    Texture contract: `Texture.pixels` holds exactly the channels of the UsdUVTexture output
    that drives the input (`rgb` -> 3, `r`/`g`/`b`/`a` -> 1), linear; `scale`/`bias` are
    reordered to follow those channels. Colour space, wrap modes, the st primvar and a missing
    file (a warning and the node's `fallback`) follow `texelbake.asset.uvtexture`.
    A "merl" material holds the file's resolved path in params["file"], the table in
    params["table"] (`texelbake.brdf.read_merl`: MERL RGB scale applied, invalid entries 0)
    and the shader's `scale` input unapplied.

    raises : AssetPathError (unsafe / missing asset paths), AssetError (unreadable file, no mesh,
        NaN/Inf points, out-of-range indices, every face degenerate), each naming the prim/file.
    """
    src = Path(path)
    source = str(src)
    if not src.is_file():
        raise AssetError("asset file does not exist", path=source)
    scan = scan_asset_paths(src)
    warns: list[str] = []
    for item in scan.unreachable:
        warn(warns, f"asset path {item} is named only by unselected variants; not read")
    for item in scan.missing:
        warn(warns, f"asset path {item} does not exist; what reads it takes its fallback")
    return read_composed(source, scan.mtlx, warns,
                         lambda stage: _read_stage(stage, source, time_code, warns, scan))


def _read_stage(stage: Any, source: str, time_code: float | None, warns: list[str],
                scan: AssetScan) -> AssetModel:
    """`load_asset` once the stage is composed (see there)."""
    from pxr import Usd, UsdGeom

    time = Usd.TimeCode.EarliestTime() if time_code is None else Usd.TimeCode(float(time_code))
    xcache = UsdGeom.XformCache(time)
    reader = MaterialReader(time, warns)

    materials: list[Material] = []
    read_by_path: dict[str, Material] = {}
    index_by_key: dict[tuple[str, bytes], int] = {}

    def index_of(material: Any, prim: Any, faces: np.ndarray) -> np.ndarray:
        path = str(material.GetPath()) if material else ""
        if path not in read_by_path:
            read_by_path[path] = reader.read(material) if material else DEFAULT_MATERIAL
        variants, group = reader.specialize(read_by_path[path], prim, faces)
        index = np.empty(len(variants), dtype=np.int32)
        for i, (value_key, mat) in enumerate(variants):  # one per distinct primvar value
            key = (path, value_key)
            if key not in index_by_key:
                index_by_key[key] = len(materials)
                materials.append(mat)
            index[i] = index_by_key[key]
        return index[group]

    mesh_prims: list[Any] = []
    instancers: list[Any] = []
    lights: list[Light] = []
    cameras: list[Camera] = []
    prims = iter(Usd.PrimRange(stage.GetPseudoRoot(),
                               Usd.TraverseInstanceProxies(Usd.PrimDefaultPredicate)))
    for prim in prims:
        if prim.IsA(UsdGeom.PointInstancer):
            if is_rendered(prim, time):
                instancers.append(prim)
            prims.PruneChildren()  # prototypes are read per instance (scene.instancers)
        elif prim.IsA(UsdGeom.Mesh):
            if is_rendered(prim, time):
                mesh_prims.append(prim)
            else:
                warn(warns, f"mesh {prim.GetPath()}: invisible or guide purpose; skipped")
        elif prim.IsA(UsdGeom.Camera):
            cameras.append(read_camera(prim, time, xcache, warns))
        elif _is_dome(prim):  # environment light: importance-sampled distant lights
            lights.extend(read_dome(prim, time, xcache, str(UsdGeom.GetStageUpAxis(stage)),
                                    warns))
        elif _is_light(prim):
            light = read_light(prim, time, xcache, warns)
            if light is not None:
                lights.append(light)
        elif prim.IsA(UsdGeom.Gprim) and is_rendered(prim, time):
            warn(warns, f"prim {prim.GetPath()}: {prim.GetTypeName()} is not a UsdGeom.Mesh; "
                         "ignored")
    if not mesh_prims and not instancers:
        raise AssetError("the asset has no UsdGeom.Mesh prim (nothing to bake)", path=source,
                         prim=str(stage.GetDefaultPrim().GetPath()) if stage.GetDefaultPrim()
                         else "/")

    skins = skinning_queries(stage, warns)

    def read_one(prim: Any) -> MeshData:
        n_faces = len(UsdGeom.Mesh(prim).GetFaceVertexCountsAttr().Get(time) or [])
        face_mat = face_materials(prim, n_faces, time, index_of, warns, source)
        uv_names = sorted({
            tex.st_primvar for i in np.unique(face_mat).tolist()
            for tex in materials[i].textures.values()})
        return read_mesh(prim, time, xcache, face_mat, uv_names, warns, source,
                         skins.get(str(prim.GetPath())))

    meshes: list[MeshData] = [read_one(prim) for prim in mesh_prims]
    timed: list[Any] = list(mesh_prims)  # None: an instanced copy, static (scene.instancers)
    for prim in instancers:
        copies = instancer_meshes(prim, time, xcache, read_one, warns)
        meshes += copies
        timed += [None] * len(copies)
    if not meshes:
        raise AssetError("the asset's point instancers show no mesh (nothing to bake)",
                         path=source, prim=str(instancers[0].GetPath()))

    # ---- assemble, computing missing normals, dropping degenerate triangles ----------------
    all_points = np.concatenate([m.points for m in meshes], axis=0)  # (n, 3)
    diag = float(np.linalg.norm(all_points.max(0) - all_points.min(0))) if len(all_points) else 0.0
    min_area = TOL.zero_area * diag ** 2
    offsets = np.concatenate([[0], np.cumsum([m.points.shape[0] for m in meshes])[:-1]])
    parts: dict[str, list[np.ndarray]] = {k: [] for k in
                                          ("faces", "normals", "uvs", "has", "mat", "mesh")}
    dropped = sum(m.bad_polygons for m in meshes)
    for mi, m in enumerate(meshes):
        cross = tri_cross(m.points, m.tris)  # (t, 3)
        keep = 0.5 * row_norm(cross) > min_area
        n_drop = int((~keep).sum())
        if n_drop:
            dropped += n_drop
            warn(warns, f"mesh {m.path}: dropped {n_drop} zero-area / degenerate triangle(s) "
                         f"(area <= {min_area:.3g})")
        normals = (m.corner_normals if m.corner_normals is not None
                   else area_weighted_normals(m.points, m.tris, cross))
        sel = slice(None) if n_drop == 0 else keep  # no masked copies for clean meshes
        parts["faces"].append(m.tris[sel] + offsets[mi])
        parts["normals"].append(normals[sel])
        parts["uvs"].append(m.corner_uvs[sel])
        parts["has"].append(np.full(int(keep.sum()), m.has_uvs))
        parts["mat"].append(m.tri_material[sel])
        parts["mesh"].append(np.full(int(keep.sum()), mi, dtype=np.int32))
    faces = np.concatenate(parts["faces"]).astype(np.int64).reshape(-1, 3)
    if faces.shape[0] == 0 and dropped == 0:
        raise AssetError(
            f"the mesh(es) {', '.join(m.path for m in meshes)} have no faces", path=source,
            prim=meshes[0].path)
    if faces.shape[0] == 0:
        raise AssetError(
            f"every face is degenerate (zero area or fewer than 3 vertices; {dropped} dropped) in "
            f"mesh(es) {', '.join(m.path for m in meshes)}", path=source, prim=meshes[0].path)

    # materials used only by dropped faces stay in the list: indices are stable per binding
    time_codes, points_over_time = _time_samples(timed, meshes, skins, source)
    skin = skin_data(timed, [m.points.shape[0] for m in meshes], skins, time, time_codes,
                     all_points, points_over_time, warns)
    return AssetModel(
        source=source,
        points=all_points,
        faces=faces,
        corner_normals=np.concatenate(parts["normals"]).reshape(-1, 3, 3),
        corner_uvs=np.concatenate(parts["uvs"]).reshape(-1, 3, 2),
        has_uvs=np.concatenate(parts["has"]).astype(bool),
        face_material=np.concatenate(parts["mat"]).astype(np.int32),
        face_mesh=np.concatenate(parts["mesh"]).astype(np.int32),
        mesh_paths=tuple(m.path for m in meshes),
        materials=tuple(materials),
        lights=tuple(lights),
        cameras=tuple(cameras),
        up_axis=str(UsdGeom.GetStageUpAxis(stage)),
        meters_per_unit=float(UsdGeom.GetStageMetersPerUnit(stage)),
        time_codes=time_codes,
        points_over_time=points_over_time,
        dropped_faces=int(dropped),
        warnings=tuple(warns),
        skin=skin,
        unreachable_paths=scan.unreachable,
        missing_paths=scan.missing,
    )


def _is_dome(prim: Any) -> bool:
    from pxr import UsdLux

    return bool(prim.IsA(UsdLux.DomeLight) or prim.IsA(UsdLux.DomeLight_1))


def _is_light(prim: Any) -> bool:
    from pxr import UsdLux

    return bool(prim.HasAPI(UsdLux.LightAPI))


def _time_samples(mesh_prims: list[Any | None], meshes: list[MeshData],
                  skins: dict[str, tuple[Any, Any]], source: str) -> tuple[np.ndarray, np.ndarray]:
    """Union of the time samples of every mesh's points, of its (ancestors') transforms and,
    for skinned meshes, of the skeleton's animation, skinning primvars and transforms.

    returns : time_codes (t,) float64, points_over_time (t, n, 3) float64 (world, flattened,
        the vertex order of `points`)
    """
    from pxr import Usd, UsdGeom

    times: set[float] = set()

    def xform_samples(prim: Any) -> list[float]:
        found: list[float] = []
        for anc in _ancestors(prim):
            xf = UsdGeom.Xformable(anc)
            if xf:
                found.extend(xf.GetTimeSamples())
        return found

    varying: list[bool] = []  # per mesh: do its world points change at all?
    for prim in mesh_prims:
        if prim is None:  # an instanced copy: static
            varying.append(False)
            continue
        mesh_times = list(UsdGeom.Mesh(prim).GetPointsAttr().GetTimeSamples())
        skin = skins.get(str(prim.GetPath()))
        if skin is None:
            mesh_times += xform_samples(prim)
        else:
            sq, skel_query = skin
            mesh_times += list(sq.GetTimeSamples()) + xform_samples(skel_query.GetPrim())
            anim = skel_query.GetAnimQuery()
            if anim:
                mesh_times += list(anim.GetJointTransformTimeSamples())
        times.update(mesh_times)
        varying.append(len(set(mesh_times)) > 1)
    if not times:
        return np.zeros(0), np.zeros((0, sum(m.points.shape[0] for m in meshes), 3))
    codes = np.array(sorted(times), dtype=np.float64)
    frames = []
    for t in codes.tolist():  # a loop over time codes, each a whole-array evaluation
        tc = Usd.TimeCode(t)
        xcache = UsdGeom.XformCache(tc)
        per_mesh = []
        for prim, m, moves in zip(mesh_prims, meshes, varying, strict=True):
            if not moves:  # at most one sample: the same points at every time
                per_mesh.append(m.points)
                continue
            raw = UsdGeom.Mesh(prim).GetPointsAttr().Get(tc)
            pts = np.asarray(raw if raw is not None else [], dtype=np.float64).reshape(-1, 3)
            expected = m.points.shape[0] if m.refine is None else m.refine.shape[1]
            if pts.shape[0] != expected:
                raise AssetError(
                    f"mesh {m.path}: {pts.shape[0]} points at time {t:g}, expected "
                    f"{expected} (changing topology is not supported)",
                    path=source, prim=m.path)
            bad = ~np.isfinite(pts).all(axis=1)
            if bad.any():
                raise AssetError(
                    f"mesh {m.path} has NaN/Inf points at time {t:g} (first at index "
                    f"{int(np.flatnonzero(bad)[0])})", path=source, prim=m.path)
            world_pts, _ = world_points(prim, pts, tc, xcache, skins.get(m.path), source)
            if m.refine is not None:  # a subdivision surface: refined as at the rest time
                world_pts = m.refine @ world_pts
            per_mesh.append(world_pts)
        frames.append(np.concatenate(per_mesh, axis=0))
    return codes, np.stack(frames)
