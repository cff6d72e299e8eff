"""The cost model against the bake (issue 15, item 4): full bakes of the cylinder and the bolt at
several atlas sizes at `texelbake bake`'s defaults, each in a fresh process (`bake.run_child`),
with the cost model's prediction (made by the bake itself after its geometry stage, the figure
`texelbake bake` prints and the job API returns) beside the measured wall time, per stage and
in total, and texels/s and held-out SNR (median, p5) per level.

    python benchmarks/costmodel_check.py --scenes cylinder,bolt --atlas 32,64,128 \
        --json benchmarks/results/costmodel_check.json

The bar (issue 15): the prediction within +-30 % of the measured total on every bake. The
prediction `texelbake bake` makes after its geometry stage knows the samples per texel and that
stage's seconds; the job API's, before anything runs, knows the settings only (printed beside). Peak
memory: the largest resident set of any process of the bake so far (`RUSAGE_CHILDREN`, the
kernel's maximum over the process tree; sizes run in increasing order, so a rise is this bake's).
Both predictions are priced on this machine (`texelbake.estimate.machinespeed`: a reference workload's
seconds here against the machine the coefficients were fitted on), printed first;
`TEXELBAKE_MACHINE_SPEED=1` prices on the fitted machine instead (the model without the term).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from bake import JOBS, run_child, write_scene  # noqa: E402

from schemas.settings import BakeSettings  # noqa: E402
from texelbake.estimate import costmodel, machinespeed  # noqa: E402


def recheck(args: argparse.Namespace) -> None:
    from texelbake import stages
    from texelbake.pipeline.estimate import _other_runnable, bake_estimate

    data = json.loads(args.recheck.read_text())
    work = args.workdir
    print(f"this tree's estimate on the stored geometry of {args.recheck} (other runnable now: "
          f"{_other_runnable():.1f})")
    print(f"{'scene':<9} {'atlas':>5} {'measured s':>10} {'printed':>8} {'ratio':>6} "
          f"{'now':>8} {'ratio':>6} {'before run':>10} {'ratio':>6}  bar 0.70-1.30")
    for row in data["rows"]:
        n, name = row["atlas"], row["scene"]
        ctx = stages.StageContext.create(work / f"{name}{n}" / "work",
                                         work / f"{name}_{row['size']}.usda",
                                         BakeSettings(atlas_resolution=n))
        st = row["stage_seconds"]
        est = bake_estimate(ctx, row["jobs"], elapsed=st.get("ingest", 0.0) + st["geometry"])
        pre = costmodel.estimate(BakeSettings(atlas_resolution=n), row["jobs"],
                                 cores=os.cpu_count(), speed=machinespeed.this_machine()).seconds
        row["predicted_seconds_recheck"] = est["seconds"]
        row["predicted_stage_seconds_recheck"] = est["stage_seconds"]
        row["predicted_before_run_seconds_recheck"] = pre
        t = row["total_seconds"]
        r = t / est["seconds"]
        print(f"{name:<9} {n:>5} {t:>10.1f} {row['predicted_seconds']:>8.1f} "
              f"{t / row['predicted_seconds']:>6.2f} {est['seconds']:>8.1f} {r:>6.2f} "
              f"{pre:>10.1f} {t / pre:>6.2f}  {'holds' if 0.7 <= r <= 1.3 else 'DOES NOT HOLD'}")
    if args.json:
        args.json.write_text(json.dumps(data, indent=1))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="cylinder,bolt")
    ap.add_argument("--atlas", default="32,64,128")
    ap.add_argument("--size", default="full", choices=["small", "full"])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--workdir", type=Path, default=None)
    ap.add_argument("--recheck", type=Path, default=None,
                    help="a JSON of an earlier run whose --workdir still holds the bakes: the "
                         "estimate of this tree's cost model from their geometry (the bake's "
                         "own call, `pipeline.estimate.bake_estimate`, with their measured ingest and "
                         "geometry seconds), beside what was measured; no bake is rerun")
    args = ap.parse_args()
    if args.recheck:
        recheck(args)
        return
    speed = machinespeed.this_machine()
    print("this machine against the cost model's (seconds ratio, > 1 slower): "
          + ", ".join(f"{k} {v:.2f}" for k, v in speed.factors.items()), flush=True)
    work = args.workdir or Path(tempfile.mkdtemp(prefix="texelbake-costmodel-"))
    here = Path(__file__).resolve().parents[1]
    rows = []
    for name in args.scenes.split(","):
        scene = write_scene(name, work / f"{name}_{args.size}.usda", args.size)
        for n in (int(a) for a in args.atlas.split(",")):
            r = run_child(here, scene, work / f"{name}{n}", {"atlas_resolution": n}, JOBS)
            # what the job API says before anything runs (settings only: uniform fill, half
            # the samples on GGX materials, the model's geometry term)
            pre = costmodel.estimate(BakeSettings(atlas_resolution=n), JOBS,
                                     cores=os.cpu_count(), speed=speed).seconds
            est = r["estimate"] or {}
            st = r["stage_seconds"] or {}
            rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024.0  # MiB
            texels = sum(lv["texels"] for lv in r["levels"])
            fit_wall = sum(lv["fit_wall_seconds"] for lv in r["levels"])
            row = {"scene": name, "size": args.size, "atlas": n, "jobs": JOBS,
                   "total_seconds": r["total_seconds"], "stage_seconds": st,
                   "predicted_seconds": est.get("seconds"),
                   "predicted_stage_seconds": est.get("stage_seconds"),
                   "predicted_before_run_seconds": pre,
                   "machine_speed": est.get("machine_speed"),
                   "ratio": (r["total_seconds"] / est["seconds"]) if est.get("seconds") else None,
                   "load_before": r["load_before"], "load_after": r["load_after"],
                   "peak_rss_mib_so_far": rss, "texels": texels,
                   "texels_per_second": texels / max(fit_wall, 1e-9) * JOBS,
                   "levels": r["levels"]}
            rows.append(row)
            print(f"\n{name} {args.size} {n}^2, {JOBS} processes, load {r['load_before']} -> "
                  f"{r['load_after']}: measured {r['total_seconds']:.1f} s, predicted "
                  f"{est.get('seconds', float('nan')):.1f} s (measured/predicted "
                  f"{row['ratio'] or float('nan'):.2f}, bar 0.70-1.30: "
                  f"{'holds' if row['ratio'] and 0.7 <= row['ratio'] <= 1.3 else 'DOES NOT HOLD'})"
                  f"; before the run (settings only, the job API) {pre:.1f} s "
                  f"({r['total_seconds'] / pre:.2f}); peak RSS so far {rss:.0f} MiB", flush=True)
            pst = est.get("stage_seconds") or {}
            print("  stages (s): " + ", ".join(f"{k} {v:.1f}" for k, v in st.items())
                  + f"; predicted cpm {pst.get('cpm', float('nan')):.1f}, "
                    f"avis {pst.get('avis', float('nan')):.1f}")
            print(f"  {'lvl':>3} {'texels':>6} {'tex/s':>8} {'ho med':>7} {'ho p5':>7}")
            for lv in r["levels"]:
                tps = lv["texels"] / max(lv["fit_wall_seconds"], 1e-9)
                med = lv["heldout_db_median"]
                p5 = lv["heldout_db_p5"]
                print(f"  {lv['level']:>3} {lv['texels']:>6} {tps:>8.2f} "
                      f"{med if med is not None else float('nan'):>7.2f} "
                      f"{p5 if p5 is not None else float('nan'):>7.2f}")
            if args.json:  # written after every bake: a long run keeps what it measured
                args.json.write_text(json.dumps({"rows": rows}, indent=1))


if __name__ == "__main__":
    main()
