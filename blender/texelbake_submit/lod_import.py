"""Importing a baked result: one LOD into a collection, or every LOD as switchable
collections (Blender's USD importer reads a small layer that selects the LOD variant)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import bpy

from . import client


def _layer_collection(root: Any, coll: bpy.types.Collection) -> Any:
    if root.collection == coll:
        return root
    for child in root.children:
        found = _layer_collection(child, coll)
        if found is not None:
            return found
    return None


def _prune_empties(new: list[bpy.types.Object]) -> None:
    """Drop imported empties with no mesh below them (the CPM scopes, the Looks, lights' and
    cameras' parents): the importer makes an empty of every Xform and Scope."""
    keep = set()
    for obj in new:
        if obj.type == "MESH":
            o = obj
            while o is not None:
                keep.add(o.name)
                o = o.parent
    for obj in new:
        if obj.type == "EMPTY" and obj.name not in keep:
            bpy.data.objects.remove(obj, do_unlink=True)


def import_lod(scene: bpy.types.Scene, root: Path, lod: int,
               collection: bpy.types.Collection) -> list[bpy.types.Object]:
    """Import LOD `lod` of the baked root into `collection` with its UsdPreviewSurface
    fallback material; returns the imported mesh objects."""
    layer = client.write_lod_layer(root, lod)
    view_layer = bpy.context.view_layer
    saved = view_layer.active_layer_collection
    view_layer.active_layer_collection = _layer_collection(view_layer.layer_collection,
                                                           collection)
    before = set(bpy.data.objects)
    try:
        result = bpy.ops.wm.usd_import(
            filepath=str(layer), import_visible_only=True, import_proxy=False,
            import_guide=False, import_render=True, import_lights=False, import_cameras=False,
            import_materials=True, import_usd_preview=True, create_collection=False)
    finally:
        view_layer.active_layer_collection = saved
    if "FINISHED" not in result:
        raise RuntimeError(f"Blender's USD import of {layer} failed")
    new = [o for o in bpy.data.objects if o not in before]
    _prune_empties(new)
    return [o for o in bpy.data.objects if o not in before and o.type == "MESH"]


def import_result(scene: bpy.types.Scene, lod: int, mode: str) -> bpy.types.Collection:
    """Import the scene's finished result: LOD `lod` into a new collection (mode 'ONE'), or
    every LOD into child collections of one, only `lod` shown (mode 'ALL')."""
    props = scene.texelbake
    if not props.result_root:
        raise RuntimeError("no finished bake to import")
    root = Path(props.result_root)
    lods = client.read_root(root)["lods"]
    stem = root.stem.removesuffix("_baked")
    if mode == "ONE":
        coll = bpy.data.collections.new(f"{stem} LOD{lod}")
        scene.collection.children.link(coll)
        import_lod(scene, root, lod, coll)
        return coll
    parent = bpy.data.collections.new(f"{stem} LODs")
    scene.collection.children.link(parent)
    for name in lods:
        child = bpy.data.collections.new(f"{stem} {name}")
        child["texelbake_lod"] = int(name[3:])
        parent.children.link(child)
        import_lod(scene, root, int(name[3:]), child)
    props.lod_collection = parent.name
    props.shown_lod = lod  # its update shows that one
    show_lod(scene, lod)
    return parent


def show_lod(scene: bpy.types.Scene, lod: int) -> None:
    """Show only LOD `lod` of the last 'All LODs' import (viewport and render)."""
    parent = bpy.data.collections.get(scene.texelbake.lod_collection)
    if parent is None:
        return
    for child in parent.children:
        hidden = child.get("texelbake_lod") != lod
        child.hide_viewport = hidden
        child.hide_render = hidden
