"""Fit the cost model's per-unit CPU costs (`texelbake.estimate.costmodel.Coefficients`) to measured
per-level CPU seconds of the CPM fit (`benchmarks/cpm_cpu.py --json`), and print prediction
against measurement per (scene, level) and summed.

    python benchmarks/calibrate_costmodel.py RUN.json [RUN.json ...] [--scale-only]

Each run's levels carry the sizes the model uses (candidates m and dense samples per texel on
cheap (Lambert / Phong) and costly materials, m^2, texels); the direction pairs d and the
held-out pairs H come from the run's settings. Non-negative least squares on relative
residuals (each level weighted by 1 / its measured seconds), so small and large levels count
alike. The fitted values are printed as a `Coefficients(...)` line to paste into
texelbake/estimate/costmodel.py; the table then shows the current model's prediction too. Runs that
record the machine they were made on (`machine_speed`, `texelbake.estimate.machinespeed`) are priced on
it, so the fitted coefficients stay the reference machine's seconds.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np
import scipy.optimize

from texelbake.estimate.costmodel import Coefficients
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


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--scale-only", action="store_true",
                    help="keep the current terms' ratios and fit one factor on them (few runs: "
                         "the full fit is underdetermined)")
    args = ap.parse_args()
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
