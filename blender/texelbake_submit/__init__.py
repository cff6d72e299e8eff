"""texelbake submitter: send the selected objects (or the scene) to a texelbake farm from
Blender's 3D view sidebar, follow the bake, import a baked LOD (or all LODs, switchable).

Blender's side only: the export (Blender's USD exporter), the panel, the operators and a timer.
HTTP runs in a background thread (`client.Submission`, standard library only, no `bpy`), so the
UI never waits on the network; `poll_step` (a `bpy.app.timers` callback on the main thread)
copies the thread's snapshot into the scene's properties and redraws the panel.
"""

from __future__ import annotations

import bpy
from bpy.props import PointerProperty

from .lod_import import import_result, show_lod
from .operators import (
    TEXELBAKE_OT_cancel,
    TEXELBAKE_OT_import,
    TEXELBAKE_OT_report,
    TEXELBAKE_OT_submit,
)
from .panel import VIEW3D_PT_texelbake
from .prefs import TEXELBAKE_AP_preferences
from .props import TexelbakeSceneProps
from .timer import TICK_SECONDS, forget_submissions, poll_step

CLASSES = (TEXELBAKE_AP_preferences, TexelbakeSceneProps, TEXELBAKE_OT_submit,
           TEXELBAKE_OT_cancel, TEXELBAKE_OT_report, TEXELBAKE_OT_import, VIEW3D_PT_texelbake)


def register() -> None:
    for cls in CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.Scene.texelbake = PointerProperty(type=TexelbakeSceneProps)
    bpy.app.handlers.load_pre.append(forget_submissions)


def unregister() -> None:
    if forget_submissions in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(forget_submissions)
    if bpy.app.timers.is_registered(poll_step):
        bpy.app.timers.unregister(poll_step)
    forget_submissions()
    del bpy.types.Scene.texelbake
    for cls in reversed(CLASSES):
        bpy.utils.unregister_class(cls)


__all__ = ["register", "unregister", "poll_step", "import_result", "show_lod", "TICK_SECONDS",
           "VIEW3D_PT_texelbake"]
