"""The cost model's CPM fit seconds against a measured fit, with the classes priced at the shares
the fit really had: each `benchmarks/cpm_cpu.py --json` run's geometry is rebuilt (cached in
--workdir), its sample histogram priced by `costmodel.estimate` on this machine with `fitted` =
each classed level's share of texels the classes left to the fit (from the run's skip counts:
exact and grouped texels are stored, the rest fitted), and printed per level beside the run's
CPU seconds; the same without the classes (every texel priced as fitted) beside it. cpm_cpu
casts every coarse level's a_vis from its samples, so runs are priced with
avis_coarse="dense". The implied `classify` coefficient per classed level is what would make
that level exact.

    python benchmarks/costmodel_classes.py benchmarks/results/cpm_cpu_cylinder_128_heldout_samples_16384.json
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bake import scene_file  # noqa: E402

from schemas.settings import BakeSettings  # noqa: E402
from texelbake import stages  # noqa: E402
from texelbake.cpm.level_by_need import EXACT_SKIP, GROUPED_SKIP  # noqa: E402
from texelbake.estimate import costmodel, machinespeed  # noqa: E402


def price(run: dict, work: Path, speed: machinespeed.MachineSpeed) -> dict:
    """Per level: the run's CPU seconds, the model's with and without the classes."""
    s = BakeSettings(**{**run["settings"], "avis_coarse": "dense"})
    work.mkdir(parents=True, exist_ok=True)
    scene = scene_file(run["scene"], run["size"], work)
    ctx = stages.StageContext.create(work / "w", scene, s)
    stages.run_ingest(ctx, 0)
    stages.run_geometry(ctx, 0)
    geo = ctx.geometry()
    fitted = []
    for lv in run["levels"][:s.classed_levels]:
        sk = lv["skip_counts"]
        stored = sk.get(str(EXACT_SKIP), 0) + sk.get(str(GROUPED_SKIP), 0)
        fitted.append((lv["texels"] - stored) / max(lv["texels"], 1))
    counts = costmodel.sample_counts(geo, s.atlas_resolution)
    kw = {"ggx_fraction": costmodel.ggx_fraction_of(geo, ctx.asset().materials), "speed": speed}
    with_classes = costmodel.estimate(s, 1, counts, fitted=fitted, **kw)
    without = costmodel.estimate(s.model_copy(update={"texel_classes": "points"}), 1, counts,
                                 **kw)
    sizes = costmodel.level_sizes(counts.astype(float), s.c_max)
    per_dir = speed.factor("classify") * (s.n_light_dirs + s.n_view_dirs)
    rows = []
    for a, b, lv, (_, dense) in zip(with_classes.per_level, without.per_level, run["levels"],
                                    sizes, strict=False):
        row = {"level": a["level"], "texels": lv["texels"], "measured": lv["cpu_seconds"],
               "model": a["seconds"], "model_without_classes": b["seconds"]}
        if a["level"] < s.classed_levels:
            rest = lv["cpu_seconds"] - a["seconds"] + costmodel.Coefficients().classify \
                * per_dir * float(dense.sum())
            row["implied_classify"] = rest / (per_dir * float(dense.sum()))
        rows.append(row)
    return {"scene": run["scene"], "atlas": s.atlas_resolution, "fitted": fitted, "levels": rows,
            "measured": sum(r["measured"] for r in rows), "model": sum(r["model"] for r in rows),
            "model_without_classes": sum(r["model_without_classes"] for r in rows)}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    work = args.workdir or Path(tempfile.mkdtemp(prefix="costmodel-classes-"))
    speed = machinespeed.this_machine()
    out = []
    for i, path in enumerate(args.runs):
        r = price(json.loads(path.read_text()), work / str(i), speed)
        out.append(r)
        print(f"\n{r['scene']} {r['atlas']}^2 ({path.name}); fitted shares "
              + ", ".join(f"{f:.3f}" for f in r["fitted"]))
        print(f"{'lvl':>3} {'texels':>6} {'measured':>9} {'model':>8} {'ratio':>6} "
              f"{'no classes':>10} {'ratio':>6} {'implied classify':>16}")
        for row in r["levels"]:
            imp = f"{row['implied_classify']:.3g}" if "implied_classify" in row else ""
            print(f"{row['level']:>3} {row['texels']:>6} {row['measured']:>9.1f} "
                  f"{row['model']:>8.1f} {row['model'] / row['measured']:>6.2f} "
                  f"{row['model_without_classes']:>10.1f} "
                  f"{row['model_without_classes'] / row['measured']:>6.2f} {imp:>16}")
        print(f"all {r['measured']:.1f} s measured, model {r['model']:.1f} "
              f"({r['model'] / r['measured']:.2f}), without classes "
              f"{r['model_without_classes']:.1f} ({r['model_without_classes'] / r['measured']:.2f})")
    if args.json:
        args.json.write_text(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
