"""The 3D view sidebar panel."""

from __future__ import annotations

import bpy

from .operators import TEXELBAKE_OT_cancel, TEXELBAKE_OT_import, TEXELBAKE_OT_submit
from .prefs import prefs


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
