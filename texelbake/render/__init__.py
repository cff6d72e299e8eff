"""The renderer (issue 4): baked USD -> images, and the speed-against-error report.

    render(baked_root, mode, *, width, height, spp, camera=None, out_dir=None, seed=0)
    render_previews(baked_root, out_dir, *, size="small")
    render_report(baked_root, out_dir, *, modes=..., width, height, spp, ref_spp, camera)
    write_report_plot(report_dir)

See `texelbake.render.core` for the modes and `texelbake.render.api` for the report.
"""

from texelbake.render.api import (
    PREVIEW_SIZES,
    compare_modes,
    render,
    render_previews,
    render_report,
    write_report_plot,
)
from texelbake.render.camera import PinholeCamera, auto_frame, from_usd, look_at
from texelbake.render.core import (
    EXTRA_MODES,
    MODES,
    RenderResult,
    RenderScene,
    load_scene,
    render_frame,
)

__all__ = [
    "EXTRA_MODES", "MODES", "PREVIEW_SIZES", "PinholeCamera", "RenderResult", "RenderScene", "auto_frame",
    "compare_modes", "from_usd", "load_scene", "look_at", "render", "render_frame",
    "render_previews", "render_report", "write_report_plot",
]
