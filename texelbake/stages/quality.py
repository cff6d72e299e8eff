"""The quality gate of a bake: per LOD and per CPM level, pass or fail
against stated targets, written to report.json as `quality` and read by `texelbake bake` (exit
status QUALITY_EXIT naming what missed) and the job API ("completed with warnings").

Targets (schemas.settings.BakeSettings, `gate_*`):
- each LOD's two-sided Hausdorff distance to M_org within its bound (error_px pixels at its
  switch size, `geometry.lodchain`); LODs of `lod_mode="atlas"` have no bound and are not gated;
- each CPM level's held-out SNR (seed 000, Eq. 7 on held-out direction pairs) median and 5th
  percentile over its texels at or above `gate_snr_median_db` / `gate_snr_p5_db`. They are
  measured on a seeded sample of the level's texels (`BakeSettings.heldout_texels`; each
  texel's truth over at most ~`heldout_samples` of its samples, whose noise adds to the error
  read), so the check reads the upper end of each statistic's 95 % interval (`cpm.assemble.quantile_ci`):
  a level fails when its population median (p5) is below the target with at least 97.5 %
  confidence, so sampling alone fails a level that meets its target at most 2.5 % of the
  time. Where the sample is the whole level the interval is the value itself (the rule as
  it was). The point estimate is reported beside it (`value`, `ci`);
- each CPM level's a_vis relative L2 error (compressed against uncompressed, seed 000 §3.4)
  at most `gate_avis_rel_error`.
A level with no texel that has samples has nothing to measure and is not gated.
"""

from __future__ import annotations

import math

from schemas.settings import BakeSettings

#: `texelbake bake`'s exit status when the bake finished but missed a target (2 is an error)
QUALITY_EXIT = 3


def _check(what: str, value: float | None, target: float, higher_is_better: bool,
           ci: list | None = None) -> dict:
    """One check; with `ci` (low, high) the rule reads its upper end (module docstring)."""
    judged = ci[1] if ci else value
    ok = (value is not None and math.isfinite(value) and judged is not None
          and (judged >= target if higher_is_better else judged <= target))
    out: dict[str, object] = {"what": what, "value": value, "target": target,
                              "rule": ">=" if higher_is_better else "<=", "passed": bool(ok)}
    if ci:
        out["ci"] = list(ci)
        out["judged_on"] = "ci_high"
    return out


def quality_gate(report: dict, settings: BakeSettings) -> dict:
    """{"passed", "checks": [{what, value, target, rule, passed}], "missed": [str]} from a
    bake's report (its "lods" and "levels")."""
    s = settings
    checks: list[dict] = []
    for i, lod in enumerate(report.get("lods", {}).get("levels", []), start=1):
        if lod.get("bound") is None:
            continue
        checks.append(_check(f"LOD{i} Hausdorff distance", lod["hausdorff"], lod["bound"],
                             higher_is_better=False))
    for lv in report.get("levels", []):
        if not lv.get("texels_with_samples"):
            continue
        name = f"CPM level {lv['level']}"
        held = lv.get("snr_heldout_db", {})
        if held.get("n"):
            checks.append(_check(f"{name} held-out SNR median (dB)", held.get("p50"),
                                 s.gate_snr_median_db, True, held.get("p50_ci")))
            checks.append(_check(f"{name} held-out SNR p5 (dB)", held.get("p5"),
                                 s.gate_snr_p5_db, True, held.get("p5_ci")))
        avis = lv.get("avis", {})
        if "rel_error" in avis:
            checks.append(_check(f"{name} a_vis relative error", avis["rel_error"],
                                 s.gate_avis_rel_error, higher_is_better=False))
    missed = [_describe(c) for c in checks if not c["passed"]]
    return {"passed": not missed, "checks": checks, "missed": missed}


def _describe(c: dict) -> str:
    v = "n/a" if c["value"] is None else f"{c['value']:.4g}"
    want = "at least" if c["rule"] == ">=" else "at most"
    return f"{c['what']} is {v}, target {want} {c['target']:.4g}"
