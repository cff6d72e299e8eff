"""Fit the cost model's per-unit CPU costs (`texelbake.estimate.costmodel.Coefficients`) to measured
per-level CPU seconds of the CPM fit (`benchmarks/cpm_cpu.py --json`), and print prediction
against measurement per (scene, level) and summed.

    python benchmarks/calibrate_costmodel.py RUN.json [RUN.json ...] [--scale-only | --parts]

Each run's levels carry the sizes the model uses (candidates m and dense samples per texel on
cheap (Lambert / Phong) and costly materials, m^2, texels); the direction pairs d and the
held-out pairs H come from the run's settings. Non-negative least squares on relative
residuals (each level weighted by 1 / its measured seconds), so small and large levels count
alike. The fitted values are printed as a `Coefficients(...)` line to paste into
texelbake/estimate/costmodel.py; the table then shows the current model's prediction too. Runs that
record the machine they were made on (`machine_speed`, `texelbake.estimate.machinespeed`) are priced on
it, so the fitted coefficients stay the reference machine's seconds.

`--parts` scales each group of the model's terms as it stands (`GROUPS` of
`costmodel.TERMS`: the fitted texels' fit, the held-out truth, the classing, the coarse fit's
a_vis rays, the lobe class's tries) to its own measured seconds, from whole-atlas
`cpm_cpu.py --breakdown` runs: each level's prediction split by term is recorded by
cpm_cpu.py (`model_terms`, priced as the bake prices them, with the sampled classes and the
capped a_vis samples), and the held-out truth, the classing, the coarse a_vis and the lobe
tries are timed functions (`PARTS`; the fit is the rest of each level). Fitting the groups to the level totals instead cannot tell them apart: the fit and
the coarse a_vis grow together (an NNLS over four runs put the coarse a_vis at 0 where it
measured 64 s, docs/decisions.md).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import scipy.optimize

from texelbake.estimate.costmodel import TERMS, Coefficients
from texelbake.estimate.machinespeed import REFERENCE_SPEED, MachineSpeed

#: the coefficient each column of `design` is priced by (its kind of work's machine factor)
COLUMNS = ("r_entry", "r_entry", "gram", "held", "held", "texel")


def design(run: dict) -> tuple[np.ndarray, np.ndarray, list[str]]:
    s = run["settings"]
    d = s["n_light_dirs"] * s["n_view_dirs"]
    h = int(round(np.sqrt(s["n_heldout"]))) ** 2 if s["n_heldout"] else 0
    # the run's machine against the coefficients' (`texelbake.estimate.machinespeed`, recorded by
    # cpm_cpu.py since 2026-11-28; older runs: the coefficients' machine): each column is
    # priced at its kind of work's factor, so the fitted coefficients are the reference
    # machine's seconds wherever the runs were made
    f = (run.get("machine_speed") or {}).get("factors")
    speed = MachineSpeed(factors=f, seconds={}) if f else REFERENCE_SPEED
    rows, y, names = [], [], []
    for lv in run["levels"]:
        z = lv["sizes"]
        rows.append([z["m_cheap"] * d, z["m_costly"] * d, z["m2"] * d,
                     z["dense_cheap"] * h, z["dense_costly"] * h, z["texels"]])
        y.append(lv["cpu_seconds"])
        names.append(f"{run['scene']} L{lv['level']}")
    scale = [speed.factor(c) for c in COLUMNS]  # each column at its coefficient's factor
    return np.array(rows, float) * scale, np.array(y, float), names


def predict(coef: Coefficients, X: np.ndarray) -> np.ndarray:
    return (coef.r_entry * X[:, 0] + coef.r_entry * coef.brdf_ggx * X[:, 1] + coef.gram * X[:, 2]
            + coef.held * X[:, 3] + coef.held * coef.held_ggx * X[:, 4] + coef.texel * X[:, 5])


#: the groups a factor is fitted per (`--parts`): the fitted texels' fit (its terms' ratios
#: are the full fit's, over many runs), the held-out truth, the classing, the coarse fit's
#: a_vis rays and the lobe class's tries. One factor per group, not per term: R entries,
#: Gram and texel terms all grow with the fitted texels and are timed together
GROUPS = {"fit": ("r_entry", "gram", "eigh", "texel", "btf_cell"), "held": ("held",),
          "classify": ("classify",), "fit_avis": ("fit_avis",), "lobe": ("lobe",)}
#: a term priced by another coefficient's kind of work (btf_cell is a multiple of r_entry)
PRICED_BY = {"btf_cell": "r_entry"}


def term_design(run: dict) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Per level of a cpm_cpu.py run: the model's seconds by group (`GROUPS`) on the run's
    machine (`model_terms` at the coefficients' prices times the machine's factor of each),
    the measured CPU seconds and the level's name."""
    f = (run.get("machine_speed") or {}).get("factors")
    speed = MachineSpeed(factors=f, seconds={}) if f else REFERENCE_SPEED
    rows, y, names = [], [], []
    for lv in run["levels"]:
        if "model_terms" not in lv:
            raise SystemExit(f"{run['scene']} level {lv['level']}: no model_terms (a run of "
                             "every tile by this cpm_cpu.py records them)")
        terms = lv["model_terms"]
        rows.append([sum(terms.get(t, 0.0) * speed.factor(PRICED_BY.get(t, t)) for t in group)
                     for group in GROUPS.values()])
        y.append(lv["cpu_seconds"])
        names.append(f"{run['scene']} {run['settings']['atlas_resolution']} L{lv['level']}")
    return np.array(rows, float), np.array(y, float), names


#: the functions `cpm_cpu.py --breakdown` times that are each group's measured seconds (the
#: fit's group is the rest of the level); avis_sums is the coarse fit's a_vis only where it
#: casts rays (avis_coarse "dense"), else it reads maps and counts with the fit
PARTS = {"held": ("heldout_from_samples", "texelbake.cpm.level_by_need.heldout_from_samples"),
         "classify": ("classes_bounded",), "fit_avis": ("avis_sums",),
         "lobe": ("lobes_bounded",)}


def part_seconds(run: dict) -> tuple[np.ndarray, np.ndarray]:
    """A --breakdown run's measured CPU seconds per group (`GROUPS` order, summed over its
    levels) and the model's (its `model_terms` on the run's machine)."""
    if "breakdown_by_level" not in run:
        raise SystemExit(f"{run['scene']}: no breakdown (run cpm_cpu.py with --breakdown)")
    X, y, _ = term_design(run)
    model = X.sum(axis=0)
    names = list(GROUPS)
    measured = np.zeros(len(names))
    dense_avis = run["settings"].get("avis_coarse") == "dense"
    for parts in run["breakdown_by_level"].values():
        for group, funcs in PARTS.items():
            if group == "fit_avis" and not dense_avis:
                continue
            measured[names.index(group)] += sum(parts.get(f, 0.0) for f in funcs)
    measured[names.index("fit")] = y.sum() - measured.sum()
    return measured, model


def recorded_coefficients(paths: list[Path]) -> Coefficients:
    """The coefficients the runs' `model_terms` were priced with (one set for all: the
    factors scale them); the current ones for runs that did not record theirs."""
    sets = {json.dumps(json.loads(p.read_text()).get("model_coefficients"), sort_keys=True)
            for p in paths}
    if len(sets) > 1:
        raise SystemExit("the runs' model terms were priced with different coefficients: "
                         "re-run them with one tree")
    rec = json.loads(sets.pop())
    return Coefficients(**rec) if rec else Coefficients()


def fit_parts(paths: list[Path]) -> None:
    """--parts: each group's factor from its own measured seconds (`PARTS`), every run
    weighted alike (its seconds over its measured total): sum(measured) / sum(model)."""
    names = list(GROUPS)
    rows = [(p, *part_seconds(json.loads(p.read_text()))) for p in paths]
    num, den = np.zeros(len(names)), np.zeros(len(names))
    print(f"{'run':<32} " + " ".join(f"{g + ' meas/model':>22}" for g in names))
    for path, meas, model in rows:
        total = max(float(meas.sum()), 1e-9)
        num += meas / total
        den += model / total
        print(f"{path.name:<32} " + " ".join(
            f"{m:>9.1f} /{p:>8.1f} {m / p if p else float('nan'):>4.2f}"
            for m, p in zip(meas, model, strict=True)))
    k = np.where(den > 0, num / np.where(den > 0, den, 1.0), 1.0)
    now = recorded_coefficients(paths)
    for path, meas, model in rows:
        print(f"{path.name:<32} total measured {meas.sum():.1f} s, model now {model.sum():.1f} "
              f"({model.sum() / meas.sum():.2f}x), refitted {(model * k).sum():.1f} "
              f"({(model * k).sum() / meas.sum():.2f}x)")
    print("factors: " + ", ".join(f"{g} {k[i]:.3f}" for i, g in enumerate(names)))
    fitted = dataclasses.replace(now, **{t: getattr(now, t) * k[i]
                                         for i, group in enumerate(GROUPS.values())
                                         for t in group if t != "btf_cell"})
    print("Coefficients(" + ", ".join(f"{t}={getattr(fitted, t):.3g}" for t in TERMS
                                      if getattr(now, t) and t != "btf_cell") + ")")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--scale-only", action="store_true",
                    help="keep the current terms' ratios and fit one factor on them (few runs: "
                         "the full fit is underdetermined)")
    ap.add_argument("--parts", action="store_true",
                    help="each group's factor from its own measured seconds (runs made with "
                         "cpm_cpu.py --breakdown)")
    args = ap.parse_args()
    if args.parts:
        fit_parts(args.runs)
        return
    parts = [design(json.loads(p.read_text())) for p in args.runs]
    X = np.vstack([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    names = [n for p in parts for n in p[2]]
    w = 1.0 / np.maximum(y, 1e-3)
    now = Coefficients()
    if args.scale_only:
        fit_terms = predict(now, X)
        k = float((fit_terms * w) @ (y * w) / max(float((fit_terms * w) @ (fit_terms * w)),
                                                  1e-30))
        print(f"fit terms x {k:.3f}")
        fitted = dataclasses.replace(
            now, r_entry=now.r_entry * k, gram=now.gram * k, eigh=now.eigh * k,
            held=now.held * k, texel=now.texel * k)
    else:
        scale = np.maximum(np.abs(X).max(axis=0), 1e-30)
        sol, _ = scipy.optimize.nnls((X * w[:, None]) / scale, y * w)
        c = sol / scale
        r_entry = c[0] if c[0] > 0 else 1e-12
        held = c[3] if c[3] > 0 else 1e-12
        fitted = Coefficients(r_entry=float(c[0]), brdf_ggx=float(c[1] / r_entry),
                              gram=float(c[2]), held=float(c[3]), held_ggx=float(c[4] / held),
                              texel=float(c[5]))
    p_fit, p_now = predict(fitted, X), predict(now, X)
    print(f"{'level':<14} {'measured s':>10} {'fitted':>8} {'ratio':>6} {'current':>8} {'ratio':>6}")
    for n, a, b, e in zip(names, y, p_fit, p_now, strict=True):
        print(f"{n:<14} {a:>10.2f} {b:>8.2f} {b / a:>6.2f} {e:>8.2f} {e / a:>6.2f}")
    start = 0
    for run_names, (_, yy, _) in zip(args.runs, parts, strict=True):
        sel = slice(start, start + yy.size)  # this run's rows (two runs may share a scene)
        start += yy.size
        print(f"{run_names.name:<30} summed: measured {yy.sum():.2f} s, fitted "
              f"{p_fit[sel].sum():.2f} ({p_fit[sel].sum() / yy.sum():.2f}x), current "
              f"{p_now[sel].sum():.2f} ({p_now[sel].sum() / yy.sum():.2f}x)")
    print("Coefficients(" + ", ".join(
        f"{k}={getattr(fitted, k):.3g}" for k in ("r_entry", "brdf_ggx", "gram", "held",
                                                    "held_ggx", "texel")) + ")")


if __name__ == "__main__":
    main()
