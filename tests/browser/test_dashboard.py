"""The dashboard in a real browser (Playwright driving Debian's Chromium) against a real stack
(redis-server, uvicorn serving web/dist and /api/v1, Celery workers), the way a person uses it:
log in (a wrong token first), drop the small cylinder on the upload form and set its settings
in the generated fields, watch the job's shards reach done, open the previews (synchronised
zoom, swipe, difference), hover the speed-against-error plot, download the result, cancel a
second job, look at the farm; another tenant's job is neither listed nor readable. No console
error beyond the expected 401/404 answers. Screenshots go to build/browser-screenshots/."""

from __future__ import annotations

import base64
import io
import json
import re
import shutil
import time
import zipfile
from pathlib import Path

import httpx
import pytest

from farm.stack import OWN_REDIS, stack_down, stack_up
from schemas.queues import QUEUE_FAMILIES
from tests.helpers.service import CHEAP_SETTINGS, backend_missing, make_zip, usda

pytestmark = [pytest.mark.browser, pytest.mark.service, pytest.mark.timeout(900)]
TOKEN_A = "browser-token-a-0123456789"
TOKEN_B = "browser-token-b-0123456789"
REPO = Path(__file__).resolve().parents[2]
SHOTS = REPO / "build" / "browser-screenshots"
#: a bake of the small cylinder in about a minute of worker time, with previews and BTF maps
#: two LODs (switch sizes 32 and 8 px: the small cylinder's chain keeps M1 and M2), so the
#: viewer's distance switch is exercised; typed as the form takes a list
SETTINGS = {**CHEAP_SETTINGS, "previews": True, "btf": True, "lod_switch_px": "32,8",
            "warp": "bend:angle=45", "deform_frames": 2}  # a warp: the deformed frames too
#: the decode check: GL float32 against the CPU's float64 on the same float32 maps; a texel
#: sums at most L x C = 4 x 12 products, so the difference is float32 rounding (~1e-7
#: relative; measured below 1e-6): 1e-5 absolute plus 1e-4 relative leaves room, and a wrong
#: texel, level, pair or channel is off by far more (the maps' values are 1e-2 .. 1)
DECODE_ATOL, DECODE_RTOL = 1e-5, 1e-4


@pytest.fixture(scope="module")
def chromium_path() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        backend_missing("Debian's chromium is not installed (make setup installs it)")
    return exe


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    if not (REPO / "web" / "dist" / "index.html").is_file():
        backend_missing("web/dist is not built (make setup runs npm ci && npm run build)")
    work = tmp_path_factory.mktemp("stack")
    st = stack_up(
        work,
        redis_url=OWN_REDIS,
        tokens={TOKEN_A: "studio-a", TOKEN_B: "studio-b"},
        workers={"prep": 1, "numeric": 1, "render": 1},
        environment="test",
        extra_env={"TEXELBAKE_SSE_MAX_SECONDS": "20"},
    )
    try:
        yield st
    finally:
        stack_down(work)


@pytest.fixture(scope="module")
def cylinder(tmp_path_factory) -> Path:
    """The small cylinder as a studio ships it: a .zip of its layer and the files beside it
    (the scene writer puts texelbake_shaders.usda next to the layer)."""
    from texelbake.testscenes import write_scene

    folder = tmp_path_factory.mktemp("scene")
    write_scene("cylinder", folder / "cylinder.usda", "small")
    members = {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.is_file()}
    out = tmp_path_factory.mktemp("upload") / "cylinder.zip"
    out.write_bytes(make_zip(members))
    return out


@pytest.fixture(scope="module")
def browser(chromium_path):
    sync_api = pytest.importorskip("playwright.sync_api")
    with sync_api.sync_playwright() as p:
        b = p.chromium.launch(executable_path=chromium_path, args=["--no-sandbox"])
        try:
            yield b
        finally:
            b.close()


class Console:
    """Console errors and uncaught page errors, less the ones a step expects."""

    def __init__(self, page):  # noqa: ANN001
        self.errors: list[str] = []
        self.allowed: list[re.Pattern] = []
        page.on("console", lambda m: m.type == "error" and self.errors.append(self._fmt(m)))
        page.on("pageerror", lambda e: self.errors.append(f"pageerror: {e}"))

    @staticmethod
    def _fmt(m) -> str:  # noqa: ANN001
        loc = m.location or {}
        return f"{m.text} @ {loc.get('url', '')}"

    def allow(self, pattern: str) -> None:
        self.allowed.append(re.compile(pattern))

    def unexpected(self) -> list[str]:
        return [e for e in self.errors if not any(p.search(e) for p in self.allowed)]


def shot(page, name: str) -> Path:  # noqa: ANN001
    SHOTS.mkdir(parents=True, exist_ok=True)
    path = SHOTS / f"{name}.png"
    page.screenshot(path=str(path), full_page=True)
    return path


def api(stack, token: str) -> httpx.Client:  # noqa: ANN001
    return httpx.Client(
        base_url=stack.api_url, headers={"Authorization": f"Bearer {token}"}, timeout=60
    )


def drop_file(page, selector: str, name: str, data: bytes) -> None:  # noqa: ANN001
    """Drop a file on an element as a person dragging it from the desktop would."""
    dt = page.evaluate_handle(
        "([name, b64]) => { const dt = new DataTransfer();"
        " const bytes = Uint8Array.from(atob(b64), c => c.charCodeAt(0));"
        " dt.items.add(new File([bytes], name, {type: 'application/zip'}));"
        " return dt; }",
        [name, base64.b64encode(data).decode()],
    )
    page.dispatch_event(selector, "dragover", {"dataTransfer": dt})
    page.dispatch_event(selector, "drop", {"dataTransfer": dt})


def fill_settings(page, settings: dict) -> None:  # noqa: ANN001
    for key, value in settings.items():
        field = page.locator(f"#setting-{key}")
        if isinstance(value, bool):
            field.set_checked(value)
        else:
            field.fill(str(value))


def upload_and_bake(page, cylinder: Path, settings: dict, screenshot: str = "") -> str:  # noqa: ANN001
    page.click("text=New bake")
    page.wait_for_selector("[data-testid=settings-form]")
    drop_file(page, "[data-testid=dropzone]", cylinder.name, cylinder.read_bytes())
    assert page.inner_text("[data-testid=file-name]") == cylinder.name
    fill_settings(page, settings)
    if screenshot:
        shot(page, screenshot)
    page.click("[data-testid=submit]")
    page.wait_for_selector("[data-testid=job-page]", timeout=120_000)
    return page.get_attribute("[data-testid=job-page]", "data-job-id")


def test_dashboard_end_to_end(stack, browser, cylinder):
    ctx = browser.new_context(viewport={"width": 1280, "height": 900}, accept_downloads=True)
    page = ctx.new_page()
    console = Console(page)
    page.set_default_timeout(30_000)

    # --- another tenant's job, made through the API: studio-a must never see it
    with api(stack, TOKEN_B) as b:
        r = b.post("/api/v1/assets", files={"file": (cylinder.name, cylinder.read_bytes())})
        assert r.status_code in (200, 201), r.text
        r = b.post("/api/v1/jobs", json={"asset_id": r.json()["id"], "settings": CHEAP_SETTINGS})
        assert r.status_code == 201, r.text
        other = r.json()
        b.delete(f"/api/v1/jobs/{other['id']}")

    # --- login: a wrong token is refused with the API's message, the right one lets us in
    page.goto(stack.api_url + "/")
    page.wait_for_selector("#token")
    shot(page, "01-login")
    console.allow(r"status of 401 .*@ .*/api/v1/jobs\?limit=1")
    page.fill("#token", "not-a-token")
    page.click("button[type=submit]")
    assert "invalid token" in page.inner_text("[data-testid=login-error]")
    page.fill("#token", TOKEN_A)
    page.click("button[type=submit]")
    page.wait_for_selector("[data-testid=no-jobs]")

    # --- upload form: fields generated from the BakeSettings schema, defaults and descriptions
    page.click("text=New bake")
    page.wait_for_selector("[data-testid=settings-form]")
    schema = httpx.get(stack.api_url + "/api/v1/openapi.json").json()
    props = schema["components"]["schemas"]["BakeSettings"]["properties"]
    assert page.locator("[data-testid=settings-form] .field").count() == len(props)
    groups = {p.get("group") for p in props.values()}
    assert page.locator("[data-testid=settings-form] fieldset[data-group]").count() == len(groups)
    res = page.locator("[data-field=atlas_resolution]")
    assert props["atlas_resolution"]["description"] in res.inner_text()
    assert f"default {props['atlas_resolution']['default']}" in res.inner_text()
    assert page.input_value("#setting-atlas_resolution") == str(
        props["atlas_resolution"]["default"]
    )
    assert page.locator("#setting-weights option").all_inner_texts() == props["weights"]["enum"]

    # a rejected upload: the API's message, with the file it names set off
    console.allow(r"status of 422 .*@ .*/api/v1/assets")
    bad = usda(header="    subLayers = [@./missing_layer.usda@]")
    drop_file(page, "[data-testid=dropzone]", "broken.usda", bad)
    page.click("[data-testid=submit]")
    page.wait_for_selector("[data-testid=upload-error]")
    named = page.locator("[data-testid=error-named]").all_inner_texts()
    assert any("missing_layer.usda" in t for t in named), named
    shot(page, "02-upload-rejected")

    job_id = upload_and_bake(page, cylinder, SETTINGS, "03-upload-form")
    shot(page, "04-job-queued")

    # --- live progress: the page follows the events stream to done
    t0 = time.monotonic()
    page.wait_for_selector("[data-testid=shard-grid] .shard", timeout=180_000)
    saw_partial = False
    while True:
        state = page.get_attribute("[data-testid=job-page]", "data-state")
        if state in ("succeeded", "failed", "cancelled"):
            break
        assert time.monotonic() - t0 < 600, "the job did not finish in 10 minutes"
        cells = page.locator(".shard").evaluate_all("els => els.map(e => e.dataset.state)")
        if not saw_partial and "done" in cells and set(cells) != {"done"}:
            saw_partial = True
            shot(page, "05-job-running")
        time.sleep(0.5)
    assert state == "succeeded", page.inner_text("[data-testid=job-page]")
    cells = page.locator(".shard").evaluate_all("els => els.map(e => e.dataset.state)")
    assert cells and set(cells) == {"done"}
    stages = page.locator("[data-testid=stage-row]").evaluate_all(
        "els => els.map(e => [e.dataset.stage, e.dataset.state])"
    )
    assert {"ingest", "geometry", "cpm", "avis", "export", "render", "deformed"} <= {
        s for s, _ in stages}
    assert all(st == "done" for _, st in stages), stages
    assert page.get_attribute("[role=progressbar]", "aria-valuenow") == "100"
    # the settings the bake changed come first, the defaults folded away by group
    changed = page.inner_text("[data-testid=settings-changed]")
    assert "atlas_resolution" in changed
    assert "seed" not in changed.split()  # at its default
    page.click("[data-testid=settings-defaults] summary")
    assert page.locator("[data-testid=settings-defaults] [data-group]").count() >= 2
    shot(page, "06-job-done")

    # --- download: the result zip, through the page
    with page.expect_download() as dl:
        page.click("[data-testid=download]")
    with zipfile.ZipFile(io.BytesIO(Path(dl.value.path()).read_bytes())) as zf:
        assert "report.json" in zf.namelist()

    # --- previews: every mode side by side; zoom moves all panels together
    page.click("[data-testid=tab-previews]")
    page.wait_for_function(
        "document.querySelectorAll('[data-testid=preview] img').length >= 5 && "
        "[...document.querySelectorAll('[data-testid=preview] img')]"
        ".every(i => i.complete && i.naturalWidth > 0)"
    )
    modes = page.locator("[data-testid=preview]").evaluate_all(
        "els => els.map(e => e.dataset.mode)"
    )
    assert {"gt_reference", "gt", "cpm", "normalmap", "equal-time"} <= set(modes), modes
    first = page.locator("[data-testid=preview] .zoompan").first
    box = first.bounding_box()
    page.mouse.move(box["x"] + box["width"] * 0.5, box["y"] + box["height"] * 0.4)
    for _ in range(3):
        page.mouse.wheel(0, -100)
        page.wait_for_timeout(50)
    renders = page.locator(
        "[data-testid=preview] .zoompan-inner, [data-testid=compare-view] .zoompan-inner"
    ).evaluate_all("els => els.map(e => e.style.transform)")
    assert len(renders) >= 6 and len(set(renders)) == 1, renders
    assert "scale(1.953" in renders[0], renders
    # the diagnostics (the atlas is another space) keep their own view
    diags = page.locator("[data-testid=diagnostic] .zoompan-inner").evaluate_all(
        "els => els.map(e => e.style.transform)"
    )
    assert diags and set(diags) == {"translate(0%, 0%) scale(1)"}, diags
    shot(page, "07-previews-zoomed")
    page.dblclick("[data-testid=preview] .zoompan >> nth=0")
    shot(page, "08-previews-swipe")
    page.check("[data-testid=compare-difference]")
    # cpm against the reference: a bake is never exact, so the difference is not all black
    nonzero = page.wait_for_function(
        "() => { const c = document.querySelector('[data-testid=diff-canvas]');"
        " if (!c || !c.width) return false;"
        " const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data;"
        " let n = 0; for (let i = 0; i < d.length; i += 4) n += (d[i] + d[i+1] + d[i+2]) > 0;"
        " return n; }"
    ).json_value()
    assert nonzero > 0
    shot(page, "09-previews-difference")
    # the deformed frames (settings.warp): the animation and its error plot, decoded
    page.wait_for_function(
        "[...document.querySelectorAll('[data-testid=deformed] img')]"
        ".filter(i => i.complete && i.naturalWidth > 0).length == 2"
    )
    alts = page.locator("[data-testid=deformed] img").evaluate_all("els => els.map(e => e.alt)")
    assert alts == ["animation.gif", "error_per_frame.png"], alts
    page.locator("[data-testid=deformed]").first.scroll_into_view_if_needed()
    shot(page, "09b-previews-deformed")

    # --- the plot: one point per finite sweep entry; hover names mode, spp, seconds, dB
    with api(stack, TOKEN_A) as a:
        report = a.get(f"/api/v1/jobs/{job_id}/previews/render_report.json").json()
    finite = [
        e for e in report["sweep"]
        if isinstance(e.get("psnr_db_object"), float | int) and e["seconds"] > 0
    ]  # fmt: skip
    page.click("[data-testid=tab-plot]")
    page.wait_for_selector("[data-testid=plot-point]")
    assert page.locator("[data-testid=plot-point]").count() == len(finite)
    cpm = next(e for e in finite if e["mode"] == "cpm")
    idx = finite.index(cpm)
    # the pointer's entering the cpm point (its onMouseEnter): equal-time is drawn at cpm's
    # time by design and, at a close PSNR, over it, where a real pointer would reach the
    # equal-time point instead
    page.locator("[data-testid=plot-point]").nth(idx).dispatch_event("mouseenter")
    tip = page.inner_text("[data-testid=plot-tooltip]")
    assert tip.startswith("cpm") and f"{cpm['spp']} spp" in tip, tip
    assert f"{cpm['seconds']:.4f} s" in tip and f"{cpm['psnr_db_object']:.2f} dB" in tip, tip
    shot(page, "10-plot-hover")

    check_inspector(page, stack, job_id)
    check_viewer(page, stack, job_id)

    # --- a second job, cancelled from its page before it finishes
    second = upload_and_bake(page, cylinder, {})
    assert second != job_id
    page.click("[data-testid=cancel]")
    page.wait_for_selector("[data-testid=job-page][data-state=cancelled]")
    assert page.is_disabled("[data-testid=cancel]") and page.is_disabled("[data-testid=download]")
    shot(page, "14-job-cancelled")

    # --- the list: ours with live states, filters; never the other tenant's job
    page.click("text=Jobs")
    page.wait_for_selector(f"[data-testid=job-row][data-job-id='{second}']")
    rows = page.locator("[data-testid=job-row]").evaluate_all(
        "els => els.map(e => [e.dataset.jobId, e.dataset.state])"
    )
    assert dict(rows) == {job_id: "succeeded", second: "cancelled"}, rows
    assert other["id"] not in page.content()
    page.select_option("[data-testid=filter-state]", "cancelled")
    page.wait_for_function("document.querySelectorAll('[data-testid=job-row]').length === 1")
    assert page.get_attribute("[data-testid=job-row]", "data-job-id") == second
    page.select_option("[data-testid=filter-state]", "")
    page.wait_for_function("document.querySelectorAll('[data-testid=job-row]').length === 2")
    # live list: a job started elsewhere (the API) appears and runs to done on the open page,
    # through the tenant's one events stream (no reload, no polling)
    with api(stack, TOKEN_A) as a:
        aid = a.get(f"/api/v1/jobs/{job_id}").json()["asset_id"]
        third = a.post("/api/v1/jobs", json={"asset_id": aid, "settings": CHEAP_SETTINGS}).json()
    row = f"[data-testid=job-row][data-job-id='{third['id']}']"
    page.wait_for_selector(row, timeout=30_000)
    page.wait_for_selector(f"{row}[data-state=succeeded]", timeout=300_000)
    assert page.get_attribute(f"{row} [role=progressbar]", "aria-valuenow") == "100"
    shot(page, "15-jobs-list")
    # another tenant's job by its address: the API's 404, shown as such
    console.allow(rf"status of 404 .*@ .*/api/v1/jobs/{other['id']}")
    page.goto(f"{stack.api_url}/#/jobs/{other['id']}")
    page.wait_for_selector(".error-box")
    assert "job not found" in page.inner_text(".error-box")
    shot(page, "16-other-tenant-404")

    # --- the farm: the three workers, their queues, the queue table
    page.goto(f"{stack.api_url}/#/farm")
    page.wait_for_selector("[data-testid=worker-row]", timeout=30_000)
    page.wait_for_function("document.querySelectorAll('[data-testid=worker-row]').length >= 3")
    workers = page.inner_text("[data-testid=workers]")
    for family, queues in QUEUE_FAMILIES.items():
        assert re.search(rf"{family}\S*@\S+\t{', '.join(sorted(queues))}\t", workers), workers
    assert page.locator("[data-testid=queue-row]").count() == 7
    shot(page, "17-farm")

    assert console.unexpected() == [], json.dumps(console.errors, indent=1)
    ctx.close()


def check_inspector(page, stack, job_id: str) -> None:  # noqa: ANN001
    """Click a texel of the atlas: its numbers are the baked ones, its a_vis plot the grid."""
    import numpy as np

    page.click("[data-testid=tab-inspector]")
    page.wait_for_selector("[data-testid=atlas]", timeout=120_000)
    with api(stack, TOKEN_A) as a:
        man = a.get(f"/api/v1/jobs/{job_id}/viewer").json()
        tex = a.get(f"/api/v1/jobs/{job_id}/viewer/texels.json").json()
        avis = np.frombuffer(a.get(f"/api/v1/jobs/{job_id}/viewer/avis.bin").content, "<f4")
    n = man["atlas"]
    # the texel with the most points: click its centre
    t = int(np.argmax(tex["points"]))
    row, col = divmod(t, n)
    box = page.locator("[data-testid=atlas]").bounding_box()
    page.mouse.click(
        box["x"] + (col + 0.5) / n * box["width"], box["y"] + (row + 0.5) / n * box["height"]
    )
    info = page.locator("[data-testid=texel-info]")
    assert info.get_attribute("data-row") == str(row) and info.get_attribute("data-col") == str(col)
    assert page.inner_text("[data-testid=texel-points]") == str(tex["points"][t])
    snr = tex["snr_heldout_db"][t]
    assert page.inner_text("[data-testid=texel-snr]") == ("—" if snr is None else f"{snr:.2f} dB")
    cells = page.locator("[data-testid=avis-polar] path").evaluate_all(
        "els => els.map(e => Number(e.dataset.value))"
    )
    k = man["avis"]["n_theta"] * man["avis"]["n_phi"]
    np.testing.assert_allclose(cells, avis[t * k : (t + 1) * k], rtol=1e-6)
    assert max(cells) > 0
    shot(page, "11-texel-inspector")


def canvas_coverage(page, at_least: float = 0.05, timeout: float = 30.0) -> float:  # noqa: ANN001
    """Fraction of the viewer canvas not at the clear colour, polled until it reaches
    `at_least` (software GL draws a frame in a few hundred ms on a loaded machine)."""
    t_end = time.monotonic() + timeout
    while True:
        cover = page.evaluate(
            "() => { const g = document.querySelector('[data-testid=viewer-canvas]');"
            " const c = document.createElement('canvas'); c.width = g.width;"
            " c.height = g.height; const x = c.getContext('2d'); x.drawImage(g, 0, 0);"
            " const d = x.getImageData(0, 0, c.width, c.height).data; let n = 0;"
            " for (let i = 0; i < d.length; i += 4)"
            "   n += Math.abs(d[i] - 15) + Math.abs(d[i+1] - 18) + Math.abs(d[i+2] - 23) > 6;"
            " return n / (c.width * c.height); }"
        )
        if cover >= at_least or time.monotonic() > t_end:
            return cover
        time.sleep(0.25)


def check_viewer(page, stack, job_id: str) -> None:  # noqa: ANN001
    """The WebGL2 viewer draws the asset with the BTF maps and with the fallback; its BTF
    decode (the fragment shader, Eq. 7) matches the CPU's `btf_lookup_texels` on the same
    maps at every texel for several direction pairs and λ."""
    import numpy as np

    from texelbake.btf import btf_lookup_texels, read_btf_maps

    page.click("[data-testid=tab-viewer]")
    page.wait_for_selector("[data-testid=viewer][data-ready='1']", timeout=120_000)
    assert "BTF:" in page.inner_text("[data-testid=viewer-status]")
    btf_cover = canvas_coverage(page)
    assert btf_cover > 0.05, btf_cover
    shot(page, "12-viewer-btf")

    out = Path(stack.env["TEXELBAKE_ARTIFACT_ROOT"]) / "jobs" / job_id / "out"
    maps = read_btf_maps(out, "btf")
    n = maps.shape[0]
    rows, cols = np.divmod(np.arange(n * n), n)
    rng = np.random.default_rng(7)
    worst = 0.0
    for lam in (0.0, 0.6, 1.5, float(maps.top_level)):
        for _ in range(3):
            th = rng.uniform(0.05, 1.3, 2)
            ph = rng.uniform(0, 2 * np.pi, 2)
            w = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], 1)
            w = w.astype(np.float32).astype(np.float64)  # what the shader gets
            gl = np.array(page.evaluate("a => window.texelbakeDecode(a[0], a[1], a[2])",
                                        [w[0].tolist(), w[1].tolist(), lam]))  # fmt: skip
            gl = gl.reshape(n * n, 4)[:, :3]
            cpu = btf_lookup_texels(maps, rows, cols, np.repeat(w[:1], n * n, 0),
                                    np.repeat(w[1:], n * n, 0), np.full(n * n, lam))  # fmt: skip
            assert np.abs(cpu).max() > 1e-3  # a lit, non-trivial pair
            err = np.abs(gl - cpu)
            assert np.all(err <= DECODE_ATOL + DECODE_RTOL * np.abs(cpu)), (lam, err.max())
            worst = max(worst, float(err.max()))
    print(f"GL decode vs CPU btf_lookup_texels: max abs difference {worst:.3g}")
    check_view_against_cpu(page, out, maps)

    # the fallback draws a different image of the same asset
    url = "() => document.querySelector('[data-testid=viewer-canvas]').toDataURL()"
    before = page.evaluate(url)
    page.select_option("[data-testid=viewer-mode]", "preview")
    page.wait_for_function(f"u => ({url})() !== u", arg=before, timeout=30_000)
    assert canvas_coverage(page) > 0.05
    shot(page, "13-viewer-fallback")
    page.select_option("[data-testid=viewer-mode]", "btf")
    # the LOD mesh follows the distance: M1 near, the coarser M2 from 8 radii on
    hud = "[data-testid=viewer-hud]"
    assert "LOD M1" in page.inner_text(hud)
    box = page.locator("[data-testid=viewer-canvas]").bounding_box()
    page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    for _ in range(8):  # x 1.15 each: 3.2 -> 9.8 radii
        page.mouse.wheel(0, 100)
        page.wait_for_timeout(60)
    page.wait_for_function(f"document.querySelector('{hud}').textContent.includes('LOD M2')")
    assert canvas_coverage(page, 0.005) > 0.005
    shot(page, "13b-viewer-far-lod2")
    page.select_option("[data-testid=viewer-lod]", "0")  # M1 at any distance, when asked
    page.wait_for_function(f"document.querySelector('{hud}').textContent.includes('LOD M1')")
    page.select_option("[data-testid=viewer-lod]", "-1")
    page.check("[data-testid=viewer-spin]")
    page.wait_for_function(
        "/[0-9.]+ fps/.test(document.querySelector('[data-testid=viewer-hud]').textContent)"
        " && parseFloat(document.querySelector('[data-testid=viewer-hud]').textContent) > 0",
        timeout=15_000,
    )
    page.uncheck("[data-testid=viewer-spin]")


#: the view check: pixels whose GL value is within 1e-4 + 1e-3 relative of the CPU's; the
#: rest sit where float32 (GL) and float64 (CPU) put a direction in neighbouring cells of the
#: nearest-direction table, or a uv on the other side of a texel edge (a different sampled
#: pair or texel: a jump, not noise)
VIEW_ATOL, VIEW_RTOL, VIEW_MIN_AGREE = 1e-4, 1e-3, 0.98


def check_view_against_cpu(page, out: Path, maps) -> None:  # noqa: ANN001
    """The viewer's frame, shaded on the CPU: for every covered pixel of the GL's view (its
    atlas uv, λ and view direction read back from float framebuffers), the CPU takes the
    texel (`texel_of_uv`), its frame from the baked USD, the light and view directions in
    that frame, and evaluates `btf_lookup_texels` (clamped at 0, as the renderer does)."""
    import numpy as np

    from texelbake.btf import btf_lookup_texels
    from texelbake.btf.render import texel_of_uv
    from texelbake.usd.read import read_baked

    w, h = 160, 120
    cap = page.evaluate(f"() => window.texelbakeCapture({w}, {h})")
    f = np.array(cap["f"]).reshape(-1, 4)
    uvl = np.array(cap["uvl"]).reshape(-1, 4)
    wo = np.array(cap["wo"]).reshape(-1, 4)[:, :3]
    cov = f[:, 3] > 0.5
    assert cov.sum() > 0.1 * w * h, cov.sum()
    frames = read_baked(next(out.glob("*_baked.usda"))).levels[0]["frames"]
    rows, cols = texel_of_uv(uvl[cov, :2], maps.shape)
    fr = frames[rows * maps.shape[1] + cols]
    wi = np.asarray(cap["light"], np.float64)
    wi /= np.linalg.norm(wi)
    wo_c = wo[cov] / np.linalg.norm(wo[cov], axis=1, keepdims=True)
    wi_l = np.einsum("nij,j->ni", fr, wi)
    wo_l = np.einsum("nij,nj->ni", fr, wo_c)
    cpu = np.maximum(btf_lookup_texels(maps, rows, cols, wi_l, wo_l, uvl[cov, 2]), 0.0)
    gl = f[cov, :3]
    assert cpu.max() > 1e-2  # the view is lit
    agree = np.all(np.abs(gl - cpu) <= VIEW_ATOL + VIEW_RTOL * np.abs(cpu), axis=1)
    print(
        f"GL view vs CPU at {int(cov.sum())} pixels: {agree.mean():.4f} agree, median abs "
        f"difference {np.median(np.abs(gl - cpu)):.3g}"
    )
    assert agree.mean() >= VIEW_MIN_AGREE, agree.mean()
