"""Dashboard first render (issue 13): how long the job list takes to show in a real browser
with 1,000 of this tenant's jobs (and 1,000 of another tenant's) in the database.

    .venv/bin/python benchmarks/dashboard.py --json PATH [--jobs 1000] [--runs 5]

Fills a fresh SQLite database with jobs planned as a real bake is (8 stages, 14 shards each,
states spread over queued/running/succeeded/failed/cancelled, shards done in proportion),
starts the API (no workers) serving the built dashboard (web/dist, `make setup`), and opens
the page in headless Chromium (Playwright, Debian's chromium) with the token in session
storage. Time to first render: from navigation start to the first page of rows (50, the
dashboard's page size; the server pages) in the DOM, `performance.now()` in the page; the
median of `--runs` fresh pages is `job_list_first_render_seconds` (bar: <= 1 s). Beside it
the API's own time for one page of 50 and for 1,000 rows at once (what an unpaged list
would fetch), and a check that every rendered row is this tenant's.

Then (unless `--no-viewer`) the WebGL2 viewer's frames per second: the small cylinder baked
with BTF maps by the stack's workers, its viewer tab opened, continuous rotation for
`--viewer-seconds`, the HUD's fps (frames counted per second of `requestAnimationFrame`)
averaged. Headless Chromium renders WebGL in software (SwiftShader) here: reported, no bar.
"""

from __future__ import annotations

import argparse
import io
import json
import shutil
import statistics
import sys
import tempfile
import time
import uuid
import zipfile
from datetime import timedelta
from pathlib import Path

import httpx

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from farm.db import Asset, Event, Job, Shard, Stage, session_factory, utcnow  # noqa: E402
from farm.stack import free_port, stack_down, stack_up  # noqa: E402

TOKEN = "bench-dashboard-token-0123456789"
OTHER = "bench-dashboard-other-0123456789"
PAGE_SIZE = 50  # web/src/screens/JobsList.tsx PAGE_SIZE
#: the small cylinder's cheap bake (as tests/helpers/service.CHEAP_SETTINGS) with BTF maps
VIEWER_BAKE = {"atlas_resolution": 32, "shard_texels": 16, "n_light_dirs": 8, "n_view_dirs": 8,
               "samples_per_texel": 8, "n_heldout": 8, "c_max": 8, "n_trials": 1,
               "avis_resolution": 4, "btf": True}  # fmt: skip
BAR_SECONDS = 1.0
#: a small bake's plan: (stage, queue, shards)
PLAN = [("ingest", "ingest", 1), ("geometry", "geometry", 1), ("cpm", "cpm", 4),
        ("cpm_top", "cpm", 1), ("avis", "avis", 4), ("avis_top", "avis", 1),
        ("export", "export", 1), ("render", "render", 1)]  # fmt: skip
TERMINAL = ("succeeded", "failed", "cancelled")
STATES = ("succeeded", "succeeded", "succeeded", "failed", "cancelled", "running", "queued")


def fill(db_url: str, tenant: str, n: int) -> None:
    """n planned jobs of one tenant, bulk-inserted (one transaction)."""
    sm = session_factory(db_url)
    now = utcnow()
    with sm.begin() as s:
        aid = "a" + uuid.uuid4().hex[:31]
        s.add(Asset(id=aid, tenant=tenant, sha256=uuid.uuid4().hex * 2, filename="cyl.usda",
                    kind="usda", root_layer="cyl.usda", size_bytes=1000, n_files=1))  # fmt: skip
        s.flush()
        jobs, stages, shards, events = [], [], [], []
        total = sum(k for _, _, k in PLAN)
        for i in range(n):
            jid = uuid.uuid4().hex
            state = STATES[i % len(STATES)]
            t0 = now - timedelta(seconds=60 * (n - i))
            done_n = {"succeeded": total, "queued": 0}.get(state, (i * 7) % total)
            finished = t0 + timedelta(seconds=40) if state in TERMINAL else None
            jobs.append({"id": jid, "tenant": tenant, "asset_id": aid, "settings_json": "{}",
                         "state": state, "error": "cpm/2: boom" if state == "failed" else None,
                         "created_at": t0, "started_at": t0 + timedelta(seconds=2),
                         "finished_at": finished})  # fmt: skip
            k = 0
            for pos, (name, queue, m) in enumerate(PLAN):
                stages.append({"job_id": jid, "name": name, "position": pos, "queue": queue,
                               "n_shards": m,
                               "state": "done" if k + m <= done_n else "queued"})  # fmt: skip
                for j in range(m):
                    shards.append({"job_id": jid, "stage": name, "shard": j, "queue": queue,
                                   "state": "done" if k < done_n else "queued",
                                   "attempts": 1, "seconds": 0.5})  # fmt: skip
                    k += 1
            events.append({"job_id": jid, "kind": "job",
                           "data_json": json.dumps({"state": state}), "at": t0})  # fmt: skip
        s.execute(Job.__table__.insert(), jobs)
        s.execute(Stage.__table__.insert(), stages)
        s.execute(Shard.__table__.insert(), shards)
        s.execute(Event.__table__.insert(), events)


def first_render(api_url: str, chromium: str, runs: int) -> list[dict]:
    from playwright.sync_api import sync_playwright

    out = []
    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        try:
            for _ in range(runs):
                ctx = browser.new_context(viewport={"width": 1280, "height": 900})
                ctx.add_init_script(f"sessionStorage.setItem('texelbake.token', {TOKEN!r})")
                page = ctx.new_page()
                errors: list[str] = []
                page.on("console", lambda m: m.type == "error" and errors.append(m.text))  # noqa: B023
                page.on("pageerror", lambda e: errors.append(str(e)))  # noqa: B023
                page.goto(api_url + "/#/jobs", wait_until="commit")
                ms = page.wait_for_function(
                    f"document.querySelectorAll('[data-testid=job-row]').length >= {PAGE_SIZE}"
                    " && performance.now()",
                    polling="raf",
                    timeout=30_000,
                ).json_value()
                ids = page.locator("[data-testid=job-row]").evaluate_all(
                    "els => els.map(e => e.dataset.jobId)"
                )
                out.append({"seconds": ms / 1000.0, "rows": len(ids), "ids": ids,
                            "console_errors": errors})  # fmt: skip
                ctx.close()
        finally:
            browser.close()
    return out


def bake_cylinder(client: httpx.Client, work: Path) -> str:
    """Upload the small cylinder, bake it with BTF maps, wait for success; the job id."""
    from texelbake.testscenes import write_scene

    folder = work / "scene"
    write_scene("cylinder", folder / "cylinder.usda", "small")
    buf = io.BytesIO()  # the layer and the files the writer put beside it, as a bundle
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(folder.iterdir()):
            zf.writestr(p.name, p.read_bytes())
    r = client.post("/api/v1/assets", files={"file": ("cylinder.zip", buf.getvalue())})
    if r.status_code not in (200, 201):
        sys.exit(f"upload of the cylinder: {r.status_code} {r.text}")
    aid = r.json()["id"]
    job = client.post("/api/v1/jobs", json={"asset_id": aid, "settings": VIEWER_BAKE}).json()
    deadline = time.monotonic() + 600
    while job["state"] not in ("succeeded", "failed", "cancelled"):
        if time.monotonic() > deadline:
            sys.exit(f"the viewer's bake did not finish in 10 minutes: {job['state']}")
        time.sleep(1.0)
        job = client.get(f"/api/v1/jobs/{job['id']}").json()
    if job["state"] != "succeeded":
        sys.exit(f"the viewer's bake {job['state']}: {job.get('error')}")
    return job["id"]


def viewer_fps(api_url: str, chromium: str, job_id: str, seconds: float) -> dict:
    from playwright.sync_api import sync_playwright

    with sync_playwright() as p:
        browser = p.chromium.launch(executable_path=chromium, args=["--no-sandbox"])
        try:
            ctx = browser.new_context(viewport={"width": 1280, "height": 900})
            ctx.add_init_script(f"sessionStorage.setItem('texelbake.token', {TOKEN!r})")
            page = ctx.new_page()
            page.goto(f"{api_url}/#/jobs/{job_id}/viewer")
            page.wait_for_selector("[data-testid=viewer][data-ready='1']", timeout=120_000)
            renderer = page.evaluate(
                "() => { const g = document.querySelector('[data-testid=viewer-canvas]')"
                ".getContext('webgl2'); const e = g.getExtension('WEBGL_debug_renderer_info');"
                " return e ? g.getParameter(e.UNMASKED_RENDERER_WEBGL) : g.getParameter(g.RENDERER); }"
            )
            page.check("[data-testid=viewer-spin]")
            page.wait_for_timeout(1500)  # warm-up: shader compile, first frames
            readings = []
            t_end = time.monotonic() + seconds
            while time.monotonic() < t_end:
                page.wait_for_timeout(1000)
                hud = page.inner_text("[data-testid=viewer-hud]")
                readings.append(float(hud.split(" fps")[0]))
            size = page.evaluate(
                "() => { const c = document.querySelector('[data-testid=viewer-canvas]');"
                " return [c.width, c.height]; }"
            )
        finally:
            browser.close()
    return {"fps": statistics.mean(readings), "readings": readings, "renderer": renderer,
            "canvas": size}  # fmt: skip


def api_seconds(client: httpx.Client, query: str, repeat: int = 5) -> tuple[float, int]:
    best = float("inf")
    rows = 0
    for _ in range(repeat):
        t = time.perf_counter()
        r = client.get(f"/api/v1/jobs?{query}")
        best = min(best, time.perf_counter() - t)
        r.raise_for_status()
        rows = len(r.json()["data"])
    return best, rows


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--json", required=True, help="write the results here")
    ap.add_argument("--jobs", type=int, default=1000, help="jobs of the measured tenant")
    ap.add_argument("--runs", type=int, default=5, help="fresh page loads")
    ap.add_argument("--no-viewer", action="store_true", help="skip the WebGL viewer's fps")
    ap.add_argument("--viewer-seconds", type=float, default=5.0)
    args = ap.parse_args()
    chromium = shutil.which("chromium") or shutil.which("chromium-browser")
    if chromium is None:
        sys.exit("chromium is not installed (make setup installs Debian's chromium)")
    if not (ROOT / "web" / "dist" / "index.html").is_file():
        sys.exit("web/dist is not built: run make setup (npm ci && npm run build in web/)")

    with tempfile.TemporaryDirectory(prefix="texelbake-dash-") as tmp:
        work = Path(tmp)
        art = work / "artifacts"
        art.mkdir()
        db_url = f"sqlite:///{(art / 'texelbake.db').resolve()}"
        t = time.perf_counter()
        fill(db_url, "bench", args.jobs)
        fill(db_url, "other", args.jobs)
        fill_s = time.perf_counter() - t
        # the list on an API alone (workers booting beside it would be measured too)
        stack = stack_up(work / "stack", redis_url=f"redis://127.0.0.1:{free_port()}/0",
                         workers={}, tokens={TOKEN: "bench", OTHER: "other"},
                         environment="test", artifact_root=art)  # fmt: skip
        try:
            with httpx.Client(base_url=stack.api_url, timeout=60,
                              headers={"Authorization": f"Bearer {TOKEN}"}) as c:  # fmt: skip
                page_s, page_rows = api_seconds(c, f"limit={PAGE_SIZE}")
                all_s, all_rows = api_seconds(c, "limit=1000")
                mine = {j["id"] for j in c.get("/api/v1/jobs?limit=1000").json()["data"]}
            runs = first_render(stack.api_url, chromium, args.runs)
        finally:
            stack_down(work / "stack")
        viewer = None
        if not args.no_viewer:  # then the whole stack, to bake the cylinder with BTF maps
            stack = stack_up(work / "stack2", redis_url=f"redis://127.0.0.1:{free_port()}/0",
                             workers={"prep": 1, "numeric": 1, "render": 1},
                             tokens={TOKEN: "bench", OTHER: "other"}, environment="test",
                             artifact_root=art)  # fmt: skip
            try:
                with httpx.Client(base_url=stack.api_url, timeout=60,
                                  headers={"Authorization": f"Bearer {TOKEN}"}) as c:  # fmt: skip
                    job_id = bake_cylinder(c, work)
                viewer = viewer_fps(stack.api_url, chromium, job_id, args.viewer_seconds)
            finally:
                stack_down(work / "stack2")

    secs = [r["seconds"] for r in runs]
    foreign = sum(1 for r in runs for i in r["ids"] if i not in mine)
    errors = [e for r in runs for e in r["console_errors"]]
    median = statistics.median(secs)
    result = {
        "job_list_first_render_seconds": round(median, 4),
        "first_render_seconds_runs": [round(s, 4) for s in secs],
        "first_render_seconds_max": round(max(secs), 4),
        "bar_seconds": BAR_SECONDS,
        "meets_bar": median <= BAR_SECONDS,
        "jobs_in_database": 2 * args.jobs,
        "jobs_of_tenant": args.jobs,
        "rows_rendered": runs[0]["rows"],
        "page_size": PAGE_SIZE,
        "api_page_seconds": round(page_s, 4),
        "api_page_rows": page_rows,
        "api_1000_rows_seconds": round(all_s, 4),
        "api_1000_rows": all_rows,
        "foreign_rows_rendered": foreign,
        "console_errors": errors,
        "fill_seconds": round(fill_s, 2),
        "viewer_fps": None if viewer is None else round(viewer["fps"], 2),
        "viewer_fps_readings": None if viewer is None else viewer["readings"],
        "viewer_renderer": None if viewer is None else viewer["renderer"],
        "viewer_canvas": None if viewer is None else viewer["canvas"],
    }
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(result, indent=1) + "\n")
    print(f"{'case':<44} {'seconds':>9} {'rows':>6} {'check':>28}")
    print(f"{'job list first render (median of ' + str(args.runs) + ')':<44} {median:>9.3f} "
          f"{runs[0]['rows']:>6} {'<= 1 s: ' + ('yes' if median <= BAR_SECONDS else 'NO'):>28}")
    print(f"{'job list first render (worst)':<44} {max(secs):>9.3f} {runs[0]['rows']:>6} "
          f"{'foreign rows: ' + str(foreign):>28}")
    print(f"{'API GET /jobs?limit=50 (best of 5)':<44} {page_s:>9.3f} {page_rows:>6} "
          f"{'console errors: ' + str(len(errors)):>28}")
    print(f"{'API GET /jobs?limit=1000 (best of 5)':<44} {all_s:>9.3f} {all_rows:>6} {'':>28}")
    if viewer is not None:
        w, h = viewer["canvas"]
        print(f"WebGL2 viewer, small cylinder BTF, {w}x{h}: {viewer['fps']:.1f} fps "
              f"(no bar; renderer: {viewer['renderer']})")
    return 0 if median <= BAR_SECONDS and not foreign and not errors else 1


if __name__ == "__main__":
    sys.exit(main())
