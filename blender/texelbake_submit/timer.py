"""Following running submissions from Blender's main thread: `poll_step` (a `bpy.app.timers`
callback) copies each background thread's snapshot into its scene's properties, reports the
outcome and imports the result when asked. It never waits on the network."""

from __future__ import annotations

from typing import Any

import bpy

from . import client
from .lod_import import import_result

#: seconds between two timer ticks (the thread polls the server on its own clock)
TICK_SECONDS = 0.5
#: the running submission, by scene name (one at a time per scene)
SUBMISSIONS: dict[str, client.Submission] = {}


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
    for scene_name, sub in list(SUBMISSIONS.items()):
        scene = bpy.data.scenes.get(scene_name)
        snap = sub.snapshot()
        if scene is None:  # the scene was deleted: stop following its job
            sub.detach()
            del SUBMISSIONS[scene_name]
            continue
        props = scene.texelbake
        if props.message != snap["message"] or props.state != snap["phase"]:
            props.state, props.message = snap["phase"], snap["message"]
        props.progress = snap["progress"]
        props.job_id = snap["job_id"]
        if not sub.finished:
            continue
        del SUBMISSIONS[scene_name]
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
    return TICK_SECONDS if SUBMISSIONS else None


@bpy.app.handlers.persistent
def forget_submissions(*_args: Any) -> None:
    """Another .blend is loading: its scenes are not the ones that submitted. The jobs keep
    running on the farm; this Blender stops following them."""
    for sub in SUBMISSIONS.values():
        sub.detach()
    SUBMISSIONS.clear()
