"""Uploads checked in a bounded place, against a real uvicorn and real checkers: hostile
archives are 422s naming the member (never a 500), a tiny zip whose header under-states its
size leaves the API's memory and a parallel health check alone, a check past its memory cap
fails alone, an unauthenticated or over-long body is refused before it is read, a corrupted
crate layer is a 422 naming the file and the value, no message holds a server path."""

from __future__ import annotations

import socket
import threading
import time
from pathlib import Path

import httpx
import numpy as np
import pytest

from farm.stack import OWN_REDIS, stack_down, stack_up
from services import uploads
from tests.helpers.hostile_zips import cases, understated
from tests.helpers.service import dir_listing, usda

pytestmark = [pytest.mark.service, pytest.mark.timeout(180)]

TOK = "token-bounds-0123456789abcdef"
MAX_UPLOAD = 8 << 20


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    work = tmp_path_factory.mktemp("stack")
    stack = stack_up(
        work, redis_url=OWN_REDIS, workers={}, tokens={TOK: "t"},
        environment="test", extra_env={"TEXELBAKE_MAX_UPLOAD_BYTES": str(MAX_UPLOAD)},
    )  # fmt: skip
    try:
        yield stack
    finally:
        stack_down(work)


@pytest.fixture
def c(api):
    with httpx.Client(base_url=api.api_url + "/api/v1", timeout=60,
                      headers={"Authorization": f"Bearer {TOK}"}) as client:  # fmt: skip
        yield client


def stored(api) -> list[str]:
    root = api.workdir / "artifacts"
    return [p for p in dir_listing(root) if p.startswith(("assets", "tmp"))]


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def no_server_path(text: str, api) -> None:  # noqa: ANN001
    for path in (str(api.workdir), "/tmp/", "/opt/", "/work/", "/home/"):
        assert path not in text, text


@pytest.mark.parametrize("case", sorted(cases()))
def test_hostile_zip_is_422_naming_the_member(api, c, case):
    data, member = cases()[case]
    before = stored(api)
    r = c.post("/assets", files={"file": ("scene.zip", data)})
    assert r.status_code == 422, r.text
    assert member in r.json()["detail"], r.text
    no_server_path(r.text, api)
    assert stored(api) == before


def test_understated_zip_leaves_the_api_alone(api, c):
    """512 MiB of zeros in a 0.5 MB zip whose headers say 100 bytes: inflated (and stopped)
    in a checker, while the API's resident memory stays flat and a health check stays fast."""
    data = understated(512)
    assert len(data) < MAX_UPLOAD
    pid = api.pids["api"]
    c.get("/assets")
    rss0 = rss_mib(pid)
    worst, stop = [0.0], threading.Event()

    def health() -> None:
        while not stop.is_set():
            t0 = time.perf_counter()
            httpx.get(api.api_url + "/api/v1/utils/health-check/", timeout=30)
            worst[0] = max(worst[0], time.perf_counter() - t0)
            time.sleep(0.02)

    probe = threading.Thread(target=health)
    probe.start()
    try:
        r = c.post("/assets", files={"file": ("bomb.zip", data)})
    finally:
        stop.set()
        probe.join()
    assert r.status_code in (413, 422) and "pad.bin" in r.json()["detail"], r.text
    # the upload is spooled and streamed through the API (~4 MB); 50 MiB is room for the
    # allocator's arenas, far below the gigabytes an inflation in this process would take
    assert rss_mib(pid) - rss0 < 50
    assert worst[0] < 2.0


def test_a_check_past_its_memory_cap_fails_alone(tmp_path):
    """The checker's RLIMIT_AS: a layer whose parse needs more than the cap fails the check
    with a 422, the warm server lives on and the next check passes."""
    bundle = tmp_path / "bundle"
    bundle.mkdir()
    floats = ",".join(["1.5"] * 3_000_000)  # ~12 MB of text, well over 48 MiB to parse
    (bundle / "big.usda").write_text(f'#usda 1.0\ndef "X" {{\n float[] a = [{floats}]\n}}\n')
    (bundle / "ok.usda").write_bytes(usda())
    req = {"staging": str(tmp_path), "bundle": str(bundle), "kind": "usda", "root": "big.usda",
           "filename": "big.usda"}  # fmt: skip
    with pytest.raises(uploads.UploadRejected) as exc:
        uploads.run_check(req, 60, memory=48 << 20)
    assert exc.value.status == 422 and exc.value.detail.startswith(uploads.VALIDATE_FAILED)
    assert "big.usda" in exc.value.detail and str(tmp_path) not in exc.value.detail
    assert uploads.run_validator(bundle, "ok.usda", 60) == []


def _raw(api, head: bytes, body: bytes = b"") -> tuple[bytes, float]:  # noqa: ANN001
    """Send `head` (and `body`) on a raw connection; the first bytes answered and the time."""
    port = int(api.api_url.rsplit(":", 1)[1])
    with socket.create_connection(("127.0.0.1", port), timeout=3) as s:
        t0 = time.perf_counter()
        s.sendall(head)
        if body:
            try:
                s.sendall(body)
            except OSError:  # the server answered and closed while the body was on its way
                pass
        return s.recv(200), time.perf_counter() - t0


def _post(auth: str, length: int, extra: str = "") -> bytes:
    return (f"POST /api/v1/assets HTTP/1.1\r\nHost: x\r\n{auth}{extra}"
            f"Content-Type: multipart/form-data; boundary=x\r\nContent-Length: {length}\r\n\r\n"
            ).encode()  # fmt: skip


def test_unauthenticated_body_is_refused_before_it_is_read(api):
    """50 MB declared, 1 MB sent: the 401 comes at once (the server never read on); with
    `Expect: 100-continue` the answer is the 401, not `100 Continue`; a wrong token alike."""
    head, seconds = _raw(api, _post("", 50 << 20), b"x" * (1 << 20))
    assert head.startswith(b"HTTP/1.1 401") and seconds < 3
    head, _ = _raw(api, _post("", 50 << 20, "Expect: 100-continue\r\n"))
    assert head.startswith(b"HTTP/1.1 401")
    head, _ = _raw(api, _post("Authorization: Bearer wrong\r\n", 50 << 20,
                              "Expect: 100-continue\r\n"))  # fmt: skip
    assert head.startswith(b"HTTP/1.1 401")


def test_declared_length_over_the_cap_is_413_unread(api):
    head, seconds = _raw(api, _post(f"Authorization: Bearer {TOK}\r\n", MAX_UPLOAD * 4))
    assert head.startswith(b"HTTP/1.1 413") and seconds < 3


def test_lower_case_bearer_is_the_same_scheme_for_every_method(api, c):
    """RFC 7235: the scheme is case-insensitive, so `bearer` authenticates reads, uploads,
    jobs and their DELETE alike; another scheme is a 401."""
    for scheme in ("bearer", "BEARER"):
        h = {"Authorization": f"{scheme} {TOK}"}
        with httpx.Client(base_url=api.api_url + "/api/v1", headers=h, timeout=60) as lc:
            asset = lc.post("/assets", files={"file": ("low.usda", usda())})
            assert asset.status_code in (200, 201), asset.text
            job = lc.post("/jobs", json={"asset_id": asset.json()["id"], "settings": {}})
            assert job.status_code == 201, job.text
            r = lc.delete(f"/jobs/{job.json()['id']}")
            assert r.status_code in (200, 202, 204), r.text
            assert c.get(f"/jobs/{job.json()['id']}").json()["state"] in ("cancelled",
                                                                          "canceled")
    r = httpx.delete(f"{api.api_url}/api/v1/jobs/x", headers={"Authorization": f"Basic {TOK}"})
    assert r.status_code == 401


def test_corrupt_crate_is_422_naming_the_file_and_value(api, c, tmp_path):
    """A crate layer whose array count points past the file: pxr opens it and fails only
    when the value is read ("Zero-copy data range out-of-bounds"); the check reads every
    value, so the upload is a 422 naming the layer and the attribute, not a job failure."""
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(tmp_path / "m.usdc"))
    pts = np.arange(9000, dtype=np.float32).reshape(3000, 3)
    UsdGeom.Mesh.Define(stage, "/Root/M").CreatePointsAttr(Vt.Vec3fArray.FromNumpy(pts))
    stage.Save()
    data = bytearray((tmp_path / "m.usdc").read_bytes())
    at = data.find(pts.tobytes()[:64])
    assert int.from_bytes(data[at - 8 : at], "little") == 3000  # the array's element count
    data[at - 8 : at] = (3000 * 100_000).to_bytes(8, "little")
    before = stored(api)
    r = c.post("/assets", files={"file": ("broken.usdc", bytes(data))})
    assert r.status_code == 422, r.text
    detail = r.json()["detail"]
    assert "broken.usdc at /Root/M.points" in detail and "out-of-bounds" in detail, detail
    assert "Error in" not in detail
    no_server_path(r.text, api)
    assert stored(api) == before
