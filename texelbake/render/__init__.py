"""The renderer (seed 000 §4.2, §5): baked USD -> images, and the speed-against-error report.

    render(baked_root, mode, *, width, height, spp, camera=None, out_dir=None, seed=0)
    render_previews(baked_root, out_dir, *, size="small")
    render_report(baked_root, out_dir, *, modes=..., width, height, spp, ref_spp, camera)
    write_report_plot(report_dir)

Modules: `frame` (the modes and `render_frame`), `tracer` (the wavefront loop), `camera`,
`scene` (a baked asset ready to render), one module per mode (`gt`, `cpm`, `btf`,
`normalmap`, `toksvig`, `leadr`, `preview_surface`; `filtered`: the filtered maps' look-ups),
`shade` (direct light), `diagnostics` (mip-level and density images),
`images` (EXR/PNG), `report` (previews, the report and its plot).
"""

from texelbake.render.frame import EXTRA_MODES, MODES, render_frame
from texelbake.render.report import (
    PREVIEW_SIZES,
    compare_modes,
    render,
    render_previews,
    render_report,
    write_report_plot,
)
from texelbake.render.scene import RenderScene, load_scene
from texelbake.trace.camera import PinholeCamera, auto_frame, from_usd, look_at
from texelbake.trace.tracer import RenderResult

__all__ = [
    "EXTRA_MODES", "MODES", "PREVIEW_SIZES", "PinholeCamera", "RenderResult", "RenderScene", "auto_frame",
    "compare_modes", "from_usd", "load_scene", "look_at", "render", "render_frame",
    "render_previews", "render_report", "write_report_plot",
]
