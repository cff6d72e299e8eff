"""texelbake submitter: send the selected objects (or the scene) to a texelbake farm from
Blender's 3D view sidebar, follow the bake, import a baked LOD (or all LODs, switchable).

Blender's side only: the export (Blender's USD exporter), the panel, the operators and a timer.
HTTP runs in a background thread (`client.Submission`, standard library only, no `bpy`), so the
UI never waits on the network; `poll_step` (a `bpy.app.timers` callback on the main thread)
copies the thread's snapshot into the scene's properties and redraws the panel.
"""

from __future__ import annotations

import json
import re
import tempfile
from pathlib import Path
from typing import Any

import bpy
from bpy.props import (
    BoolProperty,
    EnumProperty,
    FloatProperty,
    IntProperty,
    PointerProperty,
    StringProperty,
)

from . import client

#: seconds between two timer ticks (the thread polls the server on its own clock)
TICK_SECONDS = 0.5
#: the running submission, by scene name (one at a time per scene)
_active: dict[str, client.Submission] = {}


def prefs() -> Any:
    return bpy.context.preferences.addons[__package__].preferences


class TEXELBAKE_AP_preferences(bpy.types.AddonPreferences):
    bl_idname = __package__

    server_url: StringProperty(  # type: ignore[valid-type]
        name="Server URL", default="http://127.0.0.1:8000",
        description="Base URL of the texelbake API (texelbake stack up prints it)")
    token: StringProperty(  # type: ignore[valid-type]
        name="Token", subtype="PASSWORD", default="",
        description="Bearer token of your studio's tenant")
    result_dir: StringProperty(  # type: ignore[valid-type]
        name="Result folder", subtype="DIR_PATH", default="",
        description="Where baked results are unpacked (one folder per job); empty: "
        "'texelbake_results' beside the .blend, or in the system's temporary folder when the "
        "file is not saved")

    def draw(self, context: bpy.types.Context) -> None:
        col = self.layout.column()
        col.prop(self, "server_url")
        col.prop(self, "token")
        col.prop(self, "result_dir")


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
        sub = _active.get(context.scene.name)
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
        _active[context.scene.name] = sub.start()
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
        sub = _active.get(context.scene.name)
        return sub is not None and not sub.finished

    def execute(self, context: bpy.types.Context) -> set[str]:
        _active[context.scene.name].cancel()
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


def _report(message: str, level: str) -> None:
    """A report in Blender's status bar and info log from the timer (no operator is running
    there, so it goes through TEXELBAKE_OT_report). Called from Python, an ERROR report also
    raises RuntimeError carrying the same words: caught, the report is made."""
    try:
        bpy.ops.texelbake.report(message=message, level=level)
    except RuntimeError:
        pass


def _redraw() -> None:
    wm = bpy.context.window_manager
    for window in wm.windows if wm else []:
        for area in window.screen.areas:
            if area.type == "VIEW_3D":
                area.tag_redraw()


def _popup(message: str) -> None:
    """The server's words in a popup where there is a UI (not in background mode: its window
    manager still lists a window, and drawing a popup there crashes Blender 5.0.1)."""
    wm = bpy.context.window_manager
    if bpy.app.background or wm is None or not wm.windows:
        return

    def draw(menu: Any, _context: Any) -> None:
        menu.layout.label(text=message)

    wm.popup_menu(draw, title="texelbake", icon="ERROR")


def poll_step() -> float | None:
    """The timer: copy every running submission's snapshot into its scene's properties, report
    errors, import the result when asked. Returns the next interval, None when nothing runs.

    Blender runs it on the main thread every TICK_SECONDS; it never waits on the network."""
    for scene_name, sub in list(_active.items()):
        scene = bpy.data.scenes.get(scene_name)
        snap = sub.snapshot()
        if scene is None:  # the scene was deleted: stop following its job
            sub.detach()
            del _active[scene_name]
            continue
        props = scene.texelbake
        if props.message != snap["message"] or props.state != snap["phase"]:
            props.state, props.message = snap["phase"], snap["message"]
        props.progress = snap["progress"]
        props.job_id = snap["job_id"]
        if not sub.finished:
            continue
        del _active[scene_name]
        if snap["phase"] == "done":
            props.result_root, props.lods = snap["root"], ",".join(snap["lods"])
            props.import_lod = min(props.import_lod, len(snap["lods"]) - 1)
            _report(f"texelbake: {snap['message']}", "INFO")
            if props.auto_import and scene != bpy.context.scene:
                # the importer writes into the context's view layer: not another scene's
                _report(f"texelbake: the bake of scene {scene.name!r} is done; import it "
                        "from the panel there", "WARNING")
            elif props.auto_import:
                try:
                    import_result(scene, props.import_lod, props.import_mode)
                except Exception as e:  # noqa: BLE001 - a raising timer is unregistered
                    props.error = str(e)
                    _report(f"texelbake: {e}", "ERROR")
        else:
            props.error = snap["error"]
            _report(f"texelbake: {snap['error']}", "ERROR")
            _popup(snap["error"])
    _redraw()
    return TICK_SECONDS if _active else None


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


class VIEW3D_PT_texelbake(bpy.types.Panel):
    bl_label = "texelbake"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "texelbake"

    def draw(self, context: bpy.types.Context) -> None:
        props = context.scene.texelbake
        layout = self.layout
        p = prefs()
        layout.label(text=p.server_url or "set the server in the preferences", icon="URL")
        col = layout.column(align=True)
        col.prop(props, "source", expand=True)
        col.prop(props, "atlas_resolution")
        col.prop(props, "mesh_levels")
        col.prop(props, "lod_error_px")
        col.prop(props, "previews")
        col.prop(props, "extra_settings")
        row = layout.row(align=True)
        row.operator(TEXELBAKE_OT_submit.bl_idname, icon="EXPORT")
        row.operator(TEXELBAKE_OT_cancel.bl_idname, icon="CANCEL", text="")
        if props.state:
            box = layout.box()
            if props.error:  # the server's words, wrapped to the sidebar's width
                for i, line in enumerate(_wrap(props.error, 48)):
                    box.label(text=line, icon="ERROR" if i == 0 else "BLANK1")
            else:
                box.label(text=props.message, icon="INFO")
            if props.state not in ("done", "error", "failed", "cancelled"):
                box.prop(props, "progress", text=props.state, slider=True)
        col = layout.column(align=True)
        col.prop(props, "auto_import")
        col.prop(props, "import_lod")
        col.prop(props, "import_mode", expand=True)
        if props.lods:
            col.label(text=f"result: {props.lods}")
        col.operator(TEXELBAKE_OT_import.bl_idname, icon="IMPORT")
        if props.lod_collection:
            layout.prop(props, "shown_lod")


def _wrap(text: str, width: int) -> list[str]:
    words, lines, line = text.split(), [], ""
    for w in words:
        if line and len(line) + 1 + len(w) > width:
            lines.append(line)
            line = w
        else:
            line = f"{line} {w}".strip()
    return lines + ([line] if line else [])


CLASSES = (TEXELBAKE_AP_preferences, TexelbakeSceneProps, TEXELBAKE_OT_submit,
           TEXELBAKE_OT_cancel, TEXELBAKE_OT_report, TEXELBAKE_OT_import, VIEW3D_PT_texelbake)


@bpy.app.handlers.persistent
def _forget_submissions(*_args: Any) -> None:
    """Another .blend is loading: its scenes are not the ones that submitted. The jobs keep
    running on the farm; this Blender stops following them."""
    for sub in _active.values():
        sub.detach()
    _active.clear()


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.texelbake = PointerProperty(type=TexelbakeSceneProps)
    bpy.app.handlers.load_pre.append(_forget_submissions)


def unregister() -> None:
    if _forget_submissions in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(_forget_submissions)
    if bpy.app.timers.is_registered(poll_step):
        bpy.app.timers.unregister(poll_step)
    _forget_submissions()
    del bpy.types.Scene.texelbake
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)


__all__ = ["register", "unregister", "poll_step", "import_result", "show_lod"]
