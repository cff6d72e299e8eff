"""The add-on's preferences: the server, the token, where results are unpacked."""

from __future__ import annotations

from typing import Any

import bpy
from bpy.props import StringProperty


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
