"""Priorities and fair share on a real farm (issue 16, item 2): 50 small jobs from two tenants,
one of them at high priority, under three admission policies of the shard ledger.

    .venv/bin/python benchmarks/fairshare.py --json bench_out/fairshare.json [--jobs 50]

Workload (the same under every policy): tenant `lo` submits one job at the default priority
(50); right after it, tenant `hi` submits a batch of `--jobs - 1` jobs at priority 90. All are
real jobs over HTTP (individual `POST /jobs`) on a real stack (`farm.stack.stack_up`:
uvicorn, redis-server, `--workers` Celery worker processes serving every queue, SQLite). They
bake the same small cylinder with the same settings, and the artifacts of a first, untimed
job are kept: an existing artifact key is success, so each job's shards cost the farm's
per-shard work (claim, load, key check, record, dispatch) and its own export. What is measured
is the queue discipline, not the numerics.

Policies (`Settings.queue_backlog`, `Settings.tenant_max_running_shards`):
- `fifo`: no backlog limit, no tenant limit: every ready shard goes to the broker at once and
  Redis' FIFO decides (the farm before issue 16);
- `priority`: backlog 1, no tenant limit: the ledger admits by priority (one queue group of
  every queue, as the workers serve them all: `Settings.queue_groups`);
- `fair`: backlog 1, and each tenant holds at most `--workers - 1` shards (admitted or
  running): one tenant can never take every worker.
From the ledger (job created/finished, first shard start) it prints per policy: the batch's
makespan and median job time, the single job's wait (created -> first shard start) and
turnaround (created -> finished), its finish rank among all jobs, and the most shards each
tenant held at once. Claims, each printed as holding or not:
- priority is honoured: under `priority`, every `hi` job finishes before the earlier `lo` job
  (under `fifo` the earlier job goes first);
- the single job is never starved: under `fair`, its turnaround is at most a quarter of the
  batch's makespan (under `priority` it waits for the whole batch);
- the limit holds: under `fair`, no tenant ever held more than its limit.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import httpx
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from sqlalchemy import func, select  # noqa: E402

from farm.db import Job, Shard, session_factory  # noqa: E402
from farm.stack import free_port, stack_down, stack_up  # noqa: E402
from schemas.queues import QUEUES  # noqa: E402

TOKENS = {"fair-token-hi-0123456789abcdef": "hi", "fair-token-lo-0123456789abcdef": "lo"}
HI, LO = list(TOKENS)
#: the cheapest bake that still has several shards per stage (4 cpm tiles and a top level)
SETTINGS = {"atlas_resolution": 16, "shard_texels": 8, "n_light_dirs": 8, "n_view_dirs": 8,
            "samples_per_texel": 4, "n_heldout": 8, "c_max": 8, "n_trials": 1,
            "avis_resolution": 4}
POLICIES = ("fifo", "priority", "fair")


def policy_env(name: str, workers: int) -> dict[str, str]:
    backlog, cap = {"fifo": (0, 0), "priority": (1, 0), "fair": (1, workers - 1)}[name]
    return {"TEXELBAKE_QUEUE_BACKLOG": str(backlog),
            "TEXELBAKE_TENANT_MAX_RUNNING_SHARDS": str(cap)}


def wait_all(sm, ids: list[str], timeout: float) -> None:  # noqa: ANN001
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        with sm() as s:
            states = dict(s.execute(select(Job.id, Job.state).where(Job.id.in_(ids))).all())
        bad = {j: st for j, st in states.items() if st in ("failed", "cancelled")}
        if bad:
            raise RuntimeError(f"jobs ended badly: {bad}")
        if len(states) == len(ids) and all(st == "succeeded" for st in states.values()):
            return
        time.sleep(0.5)
    raise TimeoutError(f"{len(ids)} jobs not done within {timeout} s")


def peak_held(sm, ids: list[str]) -> dict[str, int]:  # noqa: ANN001
    """The most shards each tenant ran at once (from the shards' start/finish times)."""
    with sm() as s:
        rows = s.execute(
            select(Job.tenant, Shard.started_at, Shard.finished_at)
            .select_from(Shard).join(Job, Job.id == Shard.job_id)
            .where(Job.id.in_(ids))
        ).all()
    out: dict[str, int] = {}
    for tenant in {r[0] for r in rows}:
        ev = sorted([(r[1], 1) for r in rows if r[0] == tenant]
                    + [(r[2], -1) for r in rows if r[0] == tenant], key=lambda e: (e[0], e[1]))
        n = best = 0
        for _t, d in ev:
            n += d
            best = max(best, n)
        out[tenant] = best
    return out


def run(policy: str, n_jobs: int, workers: int, work: Path, artifacts: Path,
        scene: Path, timeout: float) -> dict:
    stack_dir = work / f"stack-{policy}"
    db = f"sqlite:///{work / f'{policy}.db'}"
    stack = stack_up(stack_dir, redis_url=f"redis://127.0.0.1:{free_port()}/0", database_url=db,
                     tokens=TOKENS, environment="test", artifact_root=artifacts,
                     workers={"all": workers}, queues={"all": QUEUES},
                     extra_env={"TEXELBAKE_SWEEP_INTERVAL": "1",
                                "TEXELBAKE_QUEUE_GROUPS": json.dumps({"all": list(QUEUES)}),
                                **policy_env(policy, workers)})
    api = stack.api_url + "/api/v1"
    from texelbake_client.submit import package

    try:
        clients = {t: httpx.Client(base_url=api, headers={"Authorization": f"Bearer {t}"},
                                   timeout=120) for t in TOKENS}
        assets = {}
        for t, c in clients.items():
            r = c.post("/assets", files={"file": package(scene)})
            r.raise_for_status()
            assets[t] = r.json()["id"]
        sm = session_factory(db)
        # warm-up (untimed): one job computes the shared artifacts
        warm = clients[LO].post("/jobs", json={"asset_id": assets[LO], "settings": SETTINGS})
        warm.raise_for_status()
        wait_all(sm, [warm.json()["id"]], timeout)
        order: list[tuple[str, int]] = [(LO, 50)] + [(HI, 90)] * (n_jobs - 1)
        ids: list[str] = []
        t_submit = time.time()
        for token, prio in order:
            r = clients[token].post("/jobs", json={"asset_id": assets[token],
                                                   "settings": SETTINGS, "priority": prio})
            r.raise_for_status()
            ids.append(r.json()["id"])
        submit_seconds = time.time() - t_submit
        wait_all(sm, ids, timeout)
        with sm() as s:
            first = dict(s.execute(select(Shard.job_id, func.min(Shard.started_at))
                                   .where(Shard.job_id.in_(ids)).group_by(Shard.job_id)).all())
            jobs = {j.id: j for j in s.scalars(select(Job).where(Job.id.in_(ids)))}
        peaks = peak_held(sm, ids)
        for c in clients.values():
            c.close()
    finally:
        stack_down(stack_dir)
    t0 = min(j.created_at for j in jobs.values())
    rows = []
    for k, jid in enumerate(ids):
        j = jobs[jid]
        rows.append({"k": k, "tenant": j.tenant, "priority": j.priority,
                     "created_s": (j.created_at - t0).total_seconds(),
                     "first_start_s": (first[jid] - t0).total_seconds(),
                     "finished_s": (j.finished_at - t0).total_seconds()})
    fin = sorted(r["finished_s"] for r in rows)
    lo = rows[0]
    hi = rows[1:]
    return {
        "policy": policy, "env": policy_env(policy, workers), "workers": workers,
        "submit_seconds": submit_seconds, "jobs": rows, "peak_shards_held": peaks,
        "batch_makespan_s": max(r["finished_s"] for r in hi) - min(r["created_s"] for r in hi),
        "batch_median_s": float(np.median([r["finished_s"] - r["created_s"] for r in hi])),
        "single_wait_s": lo["first_start_s"] - lo["created_s"],
        "single_turnaround_s": lo["finished_s"] - lo["created_s"],
        "single_finish_rank": 1 + fin.index(lo["finished_s"]),
        "hi_finished_before_single": sum(r["finished_s"] < lo["finished_s"] for r in hi),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--jobs", type=int, default=50, help="jobs in all: 1 of `lo`, the rest `hi`")
    ap.add_argument("--workers", type=int, default=3, help="worker processes (all queues)")
    ap.add_argument("--policies", default=",".join(POLICIES))
    ap.add_argument("--timeout", type=float, default=1800.0)
    args = ap.parse_args(argv)
    policies = [p for p in args.policies.split(",") if p]
    with tempfile.TemporaryDirectory(prefix="texelbake-fair-") as tmp:
        work = Path(tmp)
        from texelbake.testscenes import write_scene

        scene = write_scene("cylinder", work / "scene" / "cylinder.usda", "small")
        load0 = os.getloadavg()
        results = [run(p, args.jobs, args.workers, work, work / "artifacts", scene, args.timeout)
                   for p in policies]
        load1 = os.getloadavg()
    print(f"{'policy':>9} {'batch makespan s':>17} {'batch median s':>15} {'single wait s':>14} "
          f"{'single turnaround s':>20} {'single rank':>12} {'peak held':>22}")
    for r in results:
        print(f"{r['policy']:>9} {r['batch_makespan_s']:>17.1f} {r['batch_median_s']:>15.1f} "
              f"{r['single_wait_s']:>14.1f} {r['single_turnaround_s']:>20.1f} "
              f"{r['single_finish_rank']:>8}/{args.jobs:<3} {json.dumps(r['peak_shards_held']):>22}")
    by = {r["policy"]: r for r in results}
    claims = {}
    if "priority" in by:
        p = by["priority"]
        claims["priority honoured: every hi job finishes before the earlier lo job"] = (
            p["hi_finished_before_single"] == args.jobs - 1,
            f"{p['hi_finished_before_single']}/{args.jobs - 1} hi jobs finished first")
    if "fair" in by:
        f = by["fair"]
        claims["single job never starved: turnaround <= 1/4 of the batch makespan"] = (
            f["single_turnaround_s"] <= 0.25 * f["batch_makespan_s"],
            f"{f['single_turnaround_s']:.1f} s vs {f['batch_makespan_s']:.1f} s")
        cap = args.workers - 1
        claims[f"tenant limit holds: no tenant ran more than {cap} shards at once"] = (
            max(f["peak_shards_held"].values()) <= cap, json.dumps(f["peak_shards_held"]))
    for text, (ok, why) in claims.items():
        print(f"{'holds' if ok else 'does NOT hold'}: {text} ({why})")
    print(f"load average {load0[0]:.1f} -> {load1[0]:.1f} on {os.cpu_count()} CPUs")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({
            "runs": results, "claims": {k: {"holds": v[0], "measured": v[1]}
                                        for k, v in claims.items()},
            "loadavg_before": list(load0), "loadavg_after": list(load1),
            "cpus": os.cpu_count(), "settings": SETTINGS}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
