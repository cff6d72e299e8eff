"""The btf stage (seed 001): the BTF level of detail of the finest CPM level's filtered
reflectance; the science is `texelbake.btf`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from texelbake.cpm.level import direction_sets
from texelbake.errors import StageError
from texelbake.stages.context import StageContext
from texelbake.stages.cpm import cpm_levels


def btf_key(ctx: StageContext) -> str:
    return ctx.key("btf", "btf")


def run_btf(ctx: StageContext, shard: int = 0) -> str:
    """BTF level of detail (seed 001) from the finest level's filtered reflectance: exactly the
    Eq. 7 values the CPM stage measured against (f_bar on the N_i x N_o grid), one BTF image per
    direction pair over the atlas; EXR maps and a report under the store."""
    from texelbake.btf import BTFSettings, bake_btf, btf_from_texels
    from texelbake.btf.bake import narrow_lobes

    key = btf_key(ctx)
    out = ctx.store.path(key)
    if (out / "report.json").is_file():
        return key
    level0 = cpm_levels(ctx)[0]
    if "fbar" not in level0:
        raise StageError("the CPM artifacts of this bake carry no f_bar (settings.btf was off)")
    ok = level0["valid"]
    n = ctx.settings.atlas_resolution
    btf, covered = btf_from_texels(level0["fbar"][ok], level0["texel"][ok], n)
    dirs = direction_sets(ctx.settings)
    n_o = len(dirs["dirs_o"])
    di = np.repeat(dirs["dirs_i"], n_o, axis=0)  # row r = i * n_o + o
    do = np.tile(dirs["dirs_o"], (len(dirs["dirs_i"]), 1))
    out.mkdir(parents=True, exist_ok=True)
    _, report = bake_btf(btf, di, do, out, BTFSettings(), covered=covered)
    report["btf_table"] = ctx.settings.btf_table
    report["warnings"] = narrow_lobes(ctx.asset().materials, dirs["dirs_i"], dirs["dirs_o"])
    ctx.store.write_json(f"{key}/report.json", report)
    return key


def export_btf(ctx: StageContext, out_dir: Path, report: dict):
    """Copy the BTF maps beside the baked layer, add their report, and return the callback that
    authors texelbake's Laplacian BTF shader in the preview material of the payload."""
    import shutil

    from texelbake.btf import author_btf_shader, read_btf_maps

    src = ctx.store.path(btf_key(ctx))
    btf_report = ctx.store.read_json(f"{btf_key(ctx)}/report.json")
    for name in sorted(btf_report["files"].values()):
        shutil.copyfile(src / name, out_dir / name)
    report["btf"] = btf_report
    report["warnings"] = list(report.get("warnings", [])) + list(btf_report.get("warnings", []))
    maps = read_btf_maps(out_dir, "btf")
    files = {part: f"./{name}" for part, name in btf_report["files"].items()}

    def author(stage) -> None:
        author_btf_shader(stage, "/Baked/Looks/BakedPreview", files, maps)

    return author
