"""The scene's submitter properties (what the panel shows and the job's settings)."""

from __future__ import annotations

import json
from typing import Any

import bpy
from bpy.props import BoolProperty, EnumProperty, FloatProperty, IntProperty, StringProperty

from .lod_import import show_lod

ATLAS_ITEMS = [(str(n), f"{n}²", f"{n} x {n} texels at the finest CPM level")
               for n in (16, 32, 64, 128, 256, 512, 1024)]


def _show_lod_update(self: Any, context: bpy.types.Context) -> None:
    show_lod(context.scene, self.shown_lod)


class TexelbakeSceneProps(bpy.types.PropertyGroup):
    source: EnumProperty(  # type: ignore[valid-type]
        name="Send", items=[("SELECTED", "Selected", "The selected objects"),
                            ("SCENE", "Scene", "Every object of the scene")],
        default="SELECTED")
    atlas_resolution: EnumProperty(  # type: ignore[valid-type]
        name="Atlas", items=ATLAS_ITEMS, default="64",
        description="Finest CPM level resolution (atlas_resolution)")
    mesh_levels: IntProperty(  # type: ignore[valid-type]
        name="LODs", default=2, min=1, max=8, description="Most simplified meshes (mesh_levels)")
    lod_error_px: FloatProperty(  # type: ignore[valid-type]
        name="LOD error (px)", default=1.0, min=0.01, max=64.0,
        description="Largest deviation a LOD may show at its switch size (lod_error_px)")
    previews: BoolProperty(  # type: ignore[valid-type]
        name="Previews", default=False, description="Render previews on the farm (previews)")
    extra_settings: StringProperty(  # type: ignore[valid-type]
        name="More settings", default="",
        description="A JSON object of further BakeSettings fields, e.g. {\"c_max\": 16}")
    auto_import: BoolProperty(  # type: ignore[valid-type]
        name="Import when done", default=True)
    import_lod: IntProperty(  # type: ignore[valid-type]
        name="LOD", default=1, min=0, max=8, description="The LOD to import")
    import_mode: EnumProperty(  # type: ignore[valid-type]
        name="Import", items=[("ONE", "One LOD", "Import the chosen LOD"),
                              ("ALL", "All LODs", "Every LOD in its own collection, one shown")],
        default="ONE")
    shown_lod: IntProperty(  # type: ignore[valid-type]
        name="Show LOD", default=1, min=0, max=8, update=_show_lod_update,
        description="Which LOD collection of an 'All LODs' import is visible")
    # the job, as the timer last saw it
    state: StringProperty(name="State", default="")  # type: ignore[valid-type]
    progress: FloatProperty(  # type: ignore[valid-type]
        name="Progress", default=0.0, min=0.0, max=1.0, subtype="FACTOR")
    message: StringProperty(name="Message", default="")  # type: ignore[valid-type]
    error: StringProperty(name="Error", default="")  # type: ignore[valid-type]
    job_id: StringProperty(name="Job", default="")  # type: ignore[valid-type]
    result_root: StringProperty(name="Result", default="")  # type: ignore[valid-type]
    lods: StringProperty(name="LODs", default="")  # type: ignore[valid-type]
    lod_collection: StringProperty(name="LOD collection", default="")  # type: ignore[valid-type]


def bake_settings(props: TexelbakeSceneProps) -> dict[str, Any]:
    """The job's BakeSettings fields from the panel (the extra JSON wins)."""
    settings: dict[str, Any] = {
        "atlas_resolution": int(props.atlas_resolution),
        "mesh_levels": int(props.mesh_levels),
        "lod_error_px": float(props.lod_error_px),
        "previews": bool(props.previews),
    }
    if props.extra_settings.strip():
        extra = json.loads(props.extra_settings)
        if not isinstance(extra, dict):
            raise ValueError("More settings must be a JSON object")
        settings.update(extra)
    return settings
