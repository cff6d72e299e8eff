"""Runs inside Blender (headless bpy, tests/helpers/dcc.run_blender) for tests/dcc/test_addon.py:
install the add-on's extension zip, open a generated scene, submit it with the add-on's
operator to a real stack, drive the add-on's timer until the job is done, import LOD1 (and all
LODs), render the imported LOD, then submit with a wrong token; last, import LOD1 of BAKED_ROOT
(a bake of the generated Y-up, centimetre scene as uploaded, not through Blender) with the
add-on's import. Prints one JSON line.

Arguments after `--`: ZIP SCENE SERVER TOKEN OUT_DIR SETTINGS_JSON SHOTS_DIR BAKED_ROOT
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import bpy
import numpy as np

ZIP, SCENE, SERVER, TOKEN, OUT, SETTINGS, SHOTS, BAKED_ROOT = sys.argv[
    sys.argv.index("--") + 1:][:8]
OUT_DIR = Path(OUT)
TERMINAL = ("done", "error", "failed", "cancelled")


def drive(mod, props, timeout: float) -> dict:
    """Call the add-on's timer callback until the submission ends; returns what the panel
    showed on the way (distinct (state, progress) pairs), the seconds taken and the longest
    tick before the end (main-thread time: the UI's stall).

    Blender's timers (bpy.app.timers) fire from the window manager's event loop, which does
    not run in background mode (no windows are drawn): nothing would ever call `poll_step`
    here. So this loop stands in for Blender's timer and calls it every TICK_SECONDS, as
    Blender does in the UI; the HTTP meanwhile runs in the add-on's own background thread
    (time.sleep releases the GIL to it)."""
    t0 = time.monotonic()
    seen: list = []
    longest = 0.0
    panel_running: list = []  # what the panel draws the first time the job is running
    while True:
        t = time.monotonic()
        nxt = mod.poll_step()
        dt = time.monotonic() - t
        shown = [props.state, round(props.progress, 3)]
        if props.state and (not seen or seen[-1] != shown):
            seen.append(shown)
        if props.state == "running" and not panel_running:
            panel_running = panel_text(mod)
        if props.state in TERMINAL and nxt is None:
            return {"seconds": time.monotonic() - t0, "seen": seen, "longest_tick_s": longest,
                    "panel_running": panel_running}
        longest = max(longest, dt)
        if time.monotonic() - t0 > timeout:
            raise SystemExit(f"the job did not finish in {timeout} s: {props.state} "
                             f"{props.message} (seen {seen})")
        time.sleep(mod.TICK_SECONDS)


class PanelText:
    """Stands in for the UILayout Blender hands a panel's draw() (headless Blender has none:
    no window is drawn), recording what would be shown as text lines, and failing like
    Blender on a property the data does not have or an operator that is not registered."""

    def __init__(self, lines: list, depth: int = 0):
        self.lines, self.depth = lines, depth

    def _sub(self, *_a, **_k) -> PanelText:
        return PanelText(self.lines, self.depth + 1)

    row = column = box = _sub

    def label(self, text: str = "", icon: str = "NONE") -> None:
        self.lines.append("  " * self.depth + (f"[{icon}] " if icon != "NONE" else "") + text)

    def prop(self, data, name: str, text: str | None = None, slider: bool = False,
             **_k) -> None:
        if name not in data.bl_rna.properties:
            raise AttributeError(f"panel draws a missing property {name!r}")
        value = getattr(data, name)
        label = text if text is not None else data.bl_rna.properties[name].name
        shown = f"{100.0 * value:.0f}%" if slider else value  # a slider shows its fraction
        self.lines.append("  " * self.depth + f"{label}: {shown}")

    def operator(self, idname: str, text: str | None = None, icon: str = "NONE",
                 **_k) -> None:
        group, name = idname.split(".")
        op = getattr(getattr(bpy.ops, group), name)
        rna = op.get_rna_type()  # raises KeyError when not registered
        shown = text if text is not None else rna.name  # Blender shows the operator's label
        icon_tag = f"[{icon}] " if icon != "NONE" else ""
        self.lines.append("  " * self.depth + f"<{icon_tag}{shown}>")


def panel_text(mod) -> list:
    lines: list = []
    panel = mod.VIEW3D_PT_texelbake
    panel.draw(type("P", (), {"layout": PanelText(lines)})(), bpy.context)
    return lines


def mesh_info(obj) -> dict:
    me = obj.data
    co = np.empty(len(me.vertices) * 3, np.float32)
    me.vertices.foreach_get("co", co)
    co = co.reshape(-1, 3).astype(np.float64)
    mw = np.array(obj.matrix_world, np.float64)  # (4, 4)
    world = co @ mw[:3, :3].T + mw[:3, 3]  # (n, 3)
    mats = []
    for mat in me.materials:
        entry = {"name": mat.name, "base_color_image": None, "images": []}
        if mat.node_tree is not None:
            for node in mat.node_tree.nodes:
                if node.bl_idname == "ShaderNodeTexImage" and node.image is not None:
                    entry["images"].append(bpy.path.abspath(node.image.filepath))
                if node.bl_idname == "ShaderNodeBsdfPrincipled":
                    links = node.inputs["Base Color"].links
                    if links and links[0].from_node.bl_idname == "ShaderNodeTexImage":
                        img = links[0].from_node.image
                        entry["base_color_image"] = bpy.path.abspath(img.filepath)
                        entry["base_color_size"] = list(img.size)
        mats.append(entry)
    return {"name": obj.name, "n_vertices": len(me.vertices), "n_faces": len(me.polygons),
            "face_sizes": sorted({len(p.vertices) for p in me.polygons}),
            "world_min": world.min(axis=0).tolist(), "world_max": world.max(axis=0).tolist(),
            "materials": mats}


def render(objects, path: Path) -> None:
    """Cycles on the CPU (headless bpy has no GPU context for EEVEE/Workbench, nor for the UI)."""
    lo = np.min([o["world_min"] for o in objects], axis=0)
    hi = np.max([o["world_max"] for o in objects], axis=0)
    centre, size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
    scene = bpy.context.scene
    cam = bpy.data.objects.new("TestCamera", bpy.data.cameras.new("TestCamera"))
    scene.collection.objects.link(cam)
    cam.location = centre + np.array([0.9, -1.6, 0.8]) * size
    direction = centre - np.array(cam.location)
    cam.rotation_euler = __import__("mathutils").Vector(direction).to_track_quat(
        "-Z", "Y").to_euler()
    cam.data.clip_start, cam.data.clip_end = size * 0.01, size * 100
    scene.camera = cam
    sun = bpy.data.objects.new("TestSun", bpy.data.lights.new("TestSun", "SUN"))
    sun.data.energy = 3.0
    sun.rotation_euler = (0.6, 0.2, 0.8)
    scene.collection.objects.link(sun)
    if scene.world is None:
        scene.world = bpy.data.worlds.new("TestWorld")
    scene.world.color = (0.05, 0.05, 0.06)
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = 16
    scene.render.resolution_x, scene.render.resolution_y = 320, 240
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)


def main() -> None:
    bpy.ops.wm.read_factory_settings(use_empty=True)
    r = bpy.ops.extensions.package_install_files(filepath=ZIP, repo="user_default",
                                                 enable_on_install=True)
    assert "FINISHED" in r, r
    mod = sys.modules["bl_ext.user_default.texelbake_submit"]
    prefs = bpy.context.preferences.addons["bl_ext.user_default.texelbake_submit"].preferences
    prefs.server_url, prefs.token = SERVER, TOKEN
    prefs.result_dir = str(OUT_DIR / "results")

    # the artist's scene: a generated texelbake scene, opened with Blender's USD importer at
    # its size in scene units (2), not in metres (2 cm: at that size the farm's LOD chain keeps
    # the original mesh as LOD1: docs/decisions.md, 2026-11-25, the add-on's test scene)
    assert "FINISHED" in bpy.ops.wm.usd_import(filepath=SCENE, apply_unit_conversion_scale=False)
    scene = bpy.context.scene
    props = scene.texelbake
    out: dict = {"addon_module": mod.__name__}

    # nothing selected: refused before any upload, with a message
    bpy.ops.object.select_all(action="DESELECT")
    props.source = "SELECTED"
    try:
        bpy.ops.texelbake.submit()
        out["empty_selection"] = "accepted"
    except RuntimeError as e:  # an operator's ERROR report raises in background mode
        out["empty_selection"] = str(e)

    for obj in scene.objects:
        obj.select_set(obj.type in ("MESH", "LIGHT", "CAMERA"))
    settings = json.loads(SETTINGS)
    props.atlas_resolution = str(settings.pop("atlas_resolution"))
    props.extra_settings = json.dumps(settings)
    props.import_lod, props.import_mode, props.auto_import = 1, "ONE", True
    t = time.monotonic()
    assert "FINISHED" in bpy.ops.texelbake.submit()
    out["submit_op_s"] = time.monotonic() - t  # export + zip; the upload is the thread's
    out["drive"] = drive(mod, props, timeout=400)
    out["state"], out["message"], out["error"] = props.state, props.message, props.error
    out["job_id"], out["result_root"], out["lods"] = props.job_id, props.result_root, props.lods
    if props.state != "done":
        print(json.dumps(out))
        return

    out["panel_done"] = panel_text(mod)
    (Path(SHOTS) / "addon_panel_done.txt").write_text("\n".join(out["panel_done"]) + "\n")
    coll = next(c for c in bpy.data.collections if c.name.endswith(" LOD1"))
    out["lod1"] = [mesh_info(o) for o in coll.all_objects if o.type == "MESH"]
    out["lod1_collection"] = coll.name
    out["lod1_other_objects"] = sorted(o.type for o in coll.all_objects if o.type != "MESH")
    render(out["lod1"], Path(SHOTS) / "addon_lod1.png")

    # every LOD, switchable: only the shown one is visible
    coll.hide_viewport = coll.hide_render = True
    assert "FINISHED" in bpy.ops.texelbake.import_lod(mode="ALL", lod=1)
    parent = bpy.data.collections[props.lod_collection]
    shown = {}
    for lod in range(len(parent.children)):
        props.shown_lod = lod
        shown[lod] = sorted(c["texelbake_lod"] for c in parent.children if not c.hide_viewport
                            and not c.hide_render)
    out["all_lods"] = {"children": sorted(c.name for c in parent.children), "shown": shown,
                       "meshes": {c.name: sum(o.type == "MESH" for o in c.all_objects)
                                  for c in parent.children},
                       "faces": {c["texelbake_lod"]: sum(len(o.data.polygons) for o in
                                                         c.all_objects if o.type == "MESH")
                                 for c in parent.children}}

    # cancel: a second submission cancelled from the panel while it runs
    prefs.token = TOKEN
    props.auto_import = False
    assert "FINISHED" in bpy.ops.texelbake.submit()
    while not props.job_id:  # the thread has created the job
        mod.poll_step()
        time.sleep(0.1)
    assert "FINISHED" in bpy.ops.texelbake.cancel()
    drive(mod, props, timeout=60)
    out["cancelled"] = {"state": props.state, "error": props.error}

    # a wrong token: the server's words in the panel's error and the info report
    prefs.token = "not-the-token"
    assert "FINISHED" in bpy.ops.texelbake.submit()
    drive(mod, props, timeout=60)
    out["wrong_token"] = {"state": props.state, "error": props.error, "message": props.message,
                          "panel": panel_text(mod)}
    (Path(SHOTS) / "addon_panel_wrong_token.txt").write_text("\n".join(out["wrong_token"][
        "panel"]) + "\n")
    # a bake of the scene as texelbake generated it (Y-up, metersPerUnit 0.01): Blender's
    # importer turns it Z-up and scales it to metres
    props.result_root = BAKED_ROOT
    coll = mod.import_result(scene, 1, "ONE")
    out["yup_lod1"] = [mesh_info(o) for o in coll.all_objects if o.type == "MESH"]

    # the scene with the imports, to open in Blender and look at the panel there
    bpy.ops.wm.save_as_mainfile(filepath=str(OUT_DIR / "addon_scene.blend"))
    print(json.dumps(out))


main()
