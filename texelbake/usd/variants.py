"""What a baked asset shows when it is not opened the way it was baked:
with payloads unloaded (a proxy), and under another asset variant (the selections the bake was
made for, and a guard).

- Proxy: `<root>/Proxy`, the coarsest LOD with `purpose = proxy`, defined in the root layer
  outside the payload prim (`Baked`; prims below an unloaded payload are not traversed), so a
  stage opened with payloads unloaded shows the asset. Its purpose keeps it out of renders
  (render/default purposes); a viewport that draws proxies (usdview's default) draws it beside
  the selected LOD, as with any proxy whose render geometry is not purpose `render`. When the
  source's default prim carries a payload itself (the Teapot), the baked root inherits it and is
  itself unloaded: no prim below it is traversed, and clients have its `extentsHint` (every LOD).
- Asset variants: the bake is made for the source's composed variant selections, recorded in
  `customLayerData["texelbake"]["variantSelections"]` ({prim path: {set: variant}}). For every
  variant set on the asset's default prim, each *other* variant gets, in the root layer, a
  variant of the same name (selections apply to every site of a set) whose opinions deactivate
  `Baked` and `Proxy` and show the original meshes again; these sets are placed before `LOD` so they are
  stronger. Selecting another asset variant shows that variant as authored, never a bake of a
  different one ("leave it at its original"; baking each combination would multiply the bake
  by the number of combinations: 12 for the Teapot). Variant sets below the default prim are
  recorded, not guarded (their variants cannot reach `Baked`).
- An animated asset's proxy moves with it: it carries one time sample of its points
  (and extent) per time code of the coarsest LOD's motion — that LOD's own time samples, or
  its UsdSkel skinning computed by UsdSkel on the written stage (`proxy_motion`) — since a
  proxy outside the payload cannot be bound to a skeleton inside it.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from pxr import Sdf, Usd, UsdGeom, UsdSkel, Vt

from texelbake.errors import AssetError, ShapeError
from texelbake.usd.lodmesh import author_point_samples, extent_of


def source_variant_selections(source_layer: Path) -> dict[str, dict[str, str]]:
    """{prim path: {variant set: selection}} of every prim with variant sets, payloads loaded
    (the stage the bake read)."""
    stage = Usd.Stage.Open(str(source_layer), Usd.Stage.LoadAll)
    if stage is None:
        raise AssetError("cannot open the source to read its variant selections",
                         path=str(source_layer))
    out: dict[str, dict[str, str]] = {}
    for prim in stage.TraverseAll():
        vsets = prim.GetVariantSets()
        names = vsets.GetNames()
        if names:
            out[str(prim.GetPath())] = {n: vsets.GetVariantSet(n).GetVariantSelection()
                                        for n in sorted(names)}
    return out


def variant_names(source_layer: Path, prim_path: str) -> dict[str, list[str]]:
    """Every variant of every set on one prim of the source."""
    stage = Usd.Stage.Open(str(source_layer), Usd.Stage.LoadAll)
    prim = stage.GetPrimAtPath(prim_path) if stage is not None else None
    if not prim:
        return {}
    vsets = prim.GetVariantSets()
    return {n: list(vsets.GetVariantSet(n).GetVariantNames()) for n in sorted(vsets.GetNames())}


def author_proxy(stage: Usd.Stage, root_name: str, vertices: np.ndarray, faces: np.ndarray,
                 motion: list[tuple[float, np.ndarray]] | None = None) -> UsdGeom.Mesh:
    """The proxy mesh in the root layer, beside the `Baked` scope that holds the payload.
    motion : [(time code, (n, 3) points)] of an animated asset (`proxy_motion`), authored as
        time samples of the points and extent beside their rest defaults."""
    path = f"/{root_name}/Proxy"
    geom = UsdGeom.Mesh.Define(stage, path)
    v = np.require(vertices, dtype=np.float32, requirements=["C", "A"])  # aligned (mapped inputs)
    f = np.require(faces, dtype=np.int32, requirements=["C", "A"])
    geom.CreatePointsAttr(Vt.Vec3fArray.FromNumpy(v))
    geom.CreateFaceVertexCountsAttr(Vt.IntArray([3] * len(f)))
    geom.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(f.reshape(-1)))
    geom.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
    geom.CreateExtentAttr(extent_of(v))
    bad = [t for t, pts in motion or () if np.shape(pts) != v.shape]
    if bad:
        raise ShapeError(f"proxy motion at time {bad[0]}: points are not the proxy's {v.shape}")
    author_point_samples(geom, motion or ())
    geom.CreatePurposeAttr(UsdGeom.Tokens.proxy)
    return geom


def proxy_motion(stage: Usd.Stage, lod_path: str, time_codes: np.ndarray,
                 points_over_time: np.ndarray, skinned: bool) -> list[tuple[float, np.ndarray]]:
    """[(time code, points)] of the LOD mesh at `lod_path` over its animation, in the space of
    the proxy's parent (the asset root: a time-sampled LOD's parent `Baked` carries no
    transform; a skinned one's may, which UsdSkel ignores): its time samples as given, or — bound
    to a skeleton — UsdSkel's skinning of it on `stage` (the payload loaded) at every time
    sample of the skeleton's animation, the way any USD tool will pose it. [] when static."""
    if time_codes.shape[0] > 1:
        return [(float(t), np.asarray(p)) for t, p in
                zip(time_codes.tolist(), points_over_time, strict=True)]
    if not skinned:
        return []
    prim = stage.GetPrimAtPath(lod_path)
    root = UsdSkel.Root.Find(prim)
    if not prim or not root:
        raise AssetError("a skinned LOD mesh is not below a SkelRoot", path=lod_path)
    cache = UsdSkel.Cache()
    cache.Populate(root, Usd.PrimDefaultPredicate)
    query = cache.GetSkinningQuery(prim)
    skel = cache.GetSkelQuery(UsdSkel.BindingAPI(prim).GetInheritedSkeleton())
    if not query or not skel:
        raise AssetError("the skinned LOD mesh has no valid skinning query or skeleton",
                         path=lod_path)
    anim = skel.GetAnimQuery()
    times = sorted(set(anim.GetJointTransformTimeSamples()) if anim else set())
    if len(times) < 2:
        return []
    rest = UsdGeom.Mesh(prim).GetPointsAttr().Get()
    out = []
    for t in times:  # a loop over the animation's time codes
        xc = UsdGeom.XformCache(t)
        pts = Vt.Vec3fArray(rest)
        if not query.ComputeSkinnedPoints(skel.ComputeSkinningTransforms(t), pts, t):
            raise AssetError(f"UsdSkel could not skin the LOD mesh at time {t}", path=lod_path)
        # skinned points are in the skeleton's space: to world, then to the SkelRoot's parent
        to_parent = (np.array(xc.GetLocalToWorldTransform(skel.GetPrim()))
                     @ np.linalg.inv(np.array(xc.GetParentToWorldTransform(root.GetPrim()))))
        a = np.array(pts, dtype=np.float64)
        out.append((float(t), a @ to_parent[:3, :3] + to_parent[3, :3]))
    return out


def author_variant_guard(stage: Usd.Stage, root: Usd.Prim, baked_for: dict[str, str],
                         names: dict[str, list[str]], original_targets: list[Sdf.Path]) -> int:
    """For every variant of the default prim's sets other than the one baked, deactivate
    `Baked` and show the original meshes (module docstring). Returns the variants guarded."""
    guarded = 0
    for set_name in sorted(names):
        others = [n for n in names[set_name] if n != baked_for.get(set_name)]
        if not others:
            continue
        vset = root.GetVariantSets().AddVariantSet(set_name)
        for name in others:  # a loop over the few variants of one set
            vset.AddVariant(name)
            vset.SetVariantSelection(name)
            with vset.GetVariantEditContext():
                for baked in ("Baked", "Proxy"):
                    stage.OverridePrim(root.GetPath().AppendChild(baked)).SetActive(False)
                for target in original_targets:
                    UsdGeom.Imageable(stage.OverridePrim(target)).CreateVisibilityAttr(
                        UsdGeom.Tokens.inherited)
            guarded += 1
        # the selection stays the source's: only a client's explicit choice switches it
        vset.ClearVariantSelection()
    if guarded:  # earlier variant sets are stronger: the guards before `LOD`
        spec = stage.GetRootLayer().GetPrimAtPath(root.GetPath())
        items = list(spec.variantSetNameList.prependedItems)
        first = [n for n in items if n in names]
        spec.variantSetNameList.prependedItems = first + [n for n in items if n not in names]
    return guarded
