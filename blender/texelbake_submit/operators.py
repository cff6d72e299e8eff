"""The operators: submit (export and bake on the farm), cancel, report a message, import."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path

import bpy
from bpy.props import EnumProperty, IntProperty, StringProperty

from . import client
from .lod_import import import_result
from .prefs import prefs
from .props import bake_settings
from .timer import SUBMISSIONS, TICK_SECONDS, poll_step


def result_dir() -> Path:
    chosen = prefs().result_dir
    if chosen:
        return Path(bpy.path.abspath(chosen))
    if bpy.data.filepath:
        return Path(bpy.path.abspath("//texelbake_results"))
    return Path(tempfile.gettempdir()) / "texelbake_results"


def asset_name() -> str:
    stem = Path(bpy.data.filepath).stem if bpy.data.filepath else "untitled"
    return re.sub(r"[^A-Za-z0-9_]+", "_", stem).strip("_") or "untitled"


def export_usd(context: bpy.types.Context, source: str, folder: Path) -> Path:
    """Blender's USD exporter into `folder` (its textures in `folder/textures`)."""
    path = folder / f"{asset_name()}.usdc"
    result = bpy.ops.wm.usd_export(
        filepath=str(path), selected_objects_only=(source == "SELECTED"),
        export_animation=False, export_materials=True, generate_preview_surface=True,
        export_textures_mode="NEW", relative_paths=True, export_lights=True,
        export_cameras=True, evaluation_mode="RENDER")
    if "FINISHED" not in result or not path.is_file():
        raise RuntimeError(f"Blender's USD export did not write {path}")
    return path


class TEXELBAKE_OT_submit(bpy.types.Operator):
    """Export the selected objects (or the scene) as USD and bake them on the farm"""

    bl_idname = "texelbake.submit"
    bl_label = "Bake on farm"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        sub = SUBMISSIONS.get(context.scene.name)
        return sub is None or sub.finished

    def execute(self, context: bpy.types.Context) -> set[str]:
        props = context.scene.texelbake
        if props.source == "SELECTED" and not context.selected_objects:
            self.report({"ERROR"}, "Nothing selected: select objects or send the scene")
            return {"CANCELLED"}
        try:
            settings = bake_settings(props)
        except ValueError as e:
            self.report({"ERROR"}, f"More settings: {e}")
            return {"CANCELLED"}
        p = prefs()
        try:
            api = client.Client(p.server_url, p.token)
        except client.ApiError as e:
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        with tempfile.TemporaryDirectory(prefix="texelbake_export_") as tmp:
            try:
                layer = export_usd(context, props.source, Path(tmp))
            except RuntimeError as e:
                self.report({"ERROR"}, str(e))
                return {"CANCELLED"}
            data = client.zip_folder(tmp)
        sub = client.Submission(api, f"{layer.stem}.zip", data, settings, result_dir())
        SUBMISSIONS[context.scene.name] = sub.start()
        props.state, props.progress, props.error = "uploading", 0.0, ""
        props.message, props.job_id, props.result_root, props.lods = (
            f"uploading {layer.stem}.zip ({len(data) // 1024} KiB)", "", "", "")
        if not bpy.app.timers.is_registered(poll_step):
            bpy.app.timers.register(poll_step, first_interval=TICK_SECONDS)
        return {"FINISHED"}


class TEXELBAKE_OT_cancel(bpy.types.Operator):
    """Cancel the running bake job"""

    bl_idname = "texelbake.cancel"
    bl_label = "Cancel"

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        sub = SUBMISSIONS.get(context.scene.name)
        return sub is not None and not sub.finished

    def execute(self, context: bpy.types.Context) -> set[str]:
        SUBMISSIONS[context.scene.name].cancel()
        return {"FINISHED"}


class TEXELBAKE_OT_report(bpy.types.Operator):
    """Show a message of the texelbake submitter in Blender's status bar and info log"""

    bl_idname = "texelbake.report"
    bl_label = "texelbake message"
    bl_options = {"INTERNAL"}

    message: StringProperty()  # type: ignore[valid-type]
    level: StringProperty(default="INFO")  # type: ignore[valid-type]

    def execute(self, context: bpy.types.Context) -> set[str]:
        self.report({self.level}, self.message)
        return {"FINISHED"}


class TEXELBAKE_OT_import(bpy.types.Operator):
    """Import the finished bake: the chosen LOD, or every LOD as switchable collections"""

    bl_idname = "texelbake.import_lod"
    bl_label = "Import LOD"
    bl_options = {"REGISTER", "UNDO"}

    lod: IntProperty(name="LOD", default=-1, min=-1, max=8)  # type: ignore[valid-type]
    mode: EnumProperty(  # type: ignore[valid-type]
        name="Import", items=[("PANEL", "As in the panel", ""), ("ONE", "One LOD", ""),
                              ("ALL", "All LODs", "")], default="PANEL")

    @classmethod
    def poll(cls, context: bpy.types.Context) -> bool:
        return bool(context.scene.texelbake.result_root)

    def execute(self, context: bpy.types.Context) -> set[str]:
        props = context.scene.texelbake
        lod = props.import_lod if self.lod < 0 else self.lod
        mode = props.import_mode if self.mode == "PANEL" else self.mode
        try:
            coll = import_result(context.scene, lod, mode)
        except (client.ApiError, RuntimeError) as e:
            props.error = str(e)
            self.report({"ERROR"}, str(e))
            return {"CANCELLED"}
        self.report({"INFO"}, f"imported {coll.name}")
        return {"FINISHED"}
