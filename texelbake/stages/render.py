"""The render stage: previews of the finished bake, rendered from the written USD."""

from __future__ import annotations

from pathlib import Path

from texelbake.errors import StageError
from texelbake.stages.context import StageContext


def run_render(ctx: StageContext, shard: int = 0, out_dir: Path | None = None) -> list[Path]:
    """Previews of the finished bake, rendered from the written USD (texelbake.render)."""
    from texelbake.render import render_previews

    if out_dir is None:
        raise StageError("the render stage needs the folder of the written bake")
    roots = sorted(Path(out_dir).glob("*_baked.usda"))
    if not roots:
        raise StageError(f"no baked USD in {out_dir} to render previews from")
    return render_previews(roots[0], Path(out_dir) / "previews", size="small")
