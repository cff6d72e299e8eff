"""The render stage: previews of the finished bake, rendered from the written USD."""

from __future__ import annotations

from pathlib import Path

from texelbake.errors import StageError
from texelbake.stages.context import StageContext


def baked_root(out_dir: Path | None, stage: str) -> Path:
    """The written bake's root layer in out_dir (StageError naming the stage when absent)."""
    if out_dir is None:
        raise StageError(f"the {stage} stage needs the folder of the written bake")
    roots = sorted(Path(out_dir).glob("*_baked.usda"))
    if not roots:
        raise StageError(f"{stage}: no baked USD in {out_dir} to render previews from (export "
                         "has not run)")
    return roots[0]


def run_render(ctx: StageContext, shard: int = 0, out_dir: Path | None = None) -> list[Path]:
    """Previews of the finished bake, rendered from the written USD (texelbake.render)."""
    from texelbake.render import render_previews

    root = baked_root(out_dir, "render")
    return render_previews(root, root.parent / "previews", size="small")


def run_deformed(ctx: StageContext, shard: int = 0, out_dir: Path | None = None) -> list[Path]:
    """Deformed frames of the finished bake (seed 002 §4), rendered from the written USD: the
    asset's own animation, or the sweep of `settings.warp` from the identity, as
    `previews/animation.gif`, `error_per_frame.png` and `animation.json`
    (`texelbake.render.deformed_anim`; the same as `texelbake render BAKED --animate N`)."""
    from texelbake.render.deformed_anim import render_animation

    root = baked_root(out_dir, "deformed")
    report = render_animation(root, root.parent / "previews", warp=ctx.settings.warp or None,
                              frames=ctx.settings.deform_frames, seed=ctx.settings.seed)
    return [report.parent / "animation.gif", report.parent / "error_per_frame.png", report]
