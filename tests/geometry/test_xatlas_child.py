"""xatlas packs in a child process (`texelbake.geometry.xatlas_child`): the answer equals the
library's own in this process, and a child that stops answering (SIGSTOP: what a hang inside
xatlas looks like from outside, 0 % CPU) or dies is replaced without losing the pack."""

from __future__ import annotations

import os
import signal

import numpy as np
import pytest
import xatlas

from texelbake.geometry import xatlas_child as xc


def _grid(n: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A bent n x n quad grid (two triangles per quad)."""
    t = np.linspace(0.0, 1.0, n + 1)
    x, y = np.meshgrid(t, t, indexing="xy")
    v = np.stack([x.ravel(), y.ravel(), 0.3 * np.sin(3.0 * x.ravel())], axis=1)
    i = np.arange(n * (n + 1)).reshape(n, n + 1)[:, :n].ravel()
    f = np.concatenate([np.stack([i, i + 1, i + n + 2], 1), np.stack([i, i + n + 2, i + n + 1], 1)])
    return v.astype(np.float32), f.astype(np.uint32)


def _direct(v, f, res, pad, tpu):
    atlas = xatlas.Atlas()
    atlas.add_mesh(v, f)
    pack = xatlas.PackOptions()
    pack.resolution, pack.padding, pack.bilinear, pack.texels_per_unit = res, pad, True, tpu
    atlas.generate(pack_options=pack)
    return atlas.atlas_count, atlas.width, atlas.height, atlas[0]


def _same(got: xc.Packed, ref) -> None:
    assert (got.atlas_count, got.width, got.height) == ref[:3]
    for a, b in zip(got[0], ref[3], strict=True):
        assert a.dtype == b.dtype
        np.testing.assert_array_equal(a, b)


def test_child_pack_equals_the_library_in_process():
    v, f = _grid()
    _same(xc.xatlas_pack(v, f, 64, 2, 40.0), _direct(v, f, 64, 2, 40.0))
    _same(xc.xatlas_pack(v, f, 0, 1, 25.0), _direct(v, f, 0, 1, 25.0))


@pytest.mark.parametrize("sig", [signal.SIGSTOP, signal.SIGKILL], ids=["hung", "dead"])
def test_a_hung_or_dead_child_is_replaced(monkeypatch, sig):
    """The child stopped (or killed) right after answering: the next pack waits at most
    DROP_SECONDS for its acknowledgement (or sees the pipe closed), kills it and answers from
    a new child."""
    monkeypatch.setattr(xc, "DROP_SECONDS", 0.5)
    monkeypatch.setattr(xc, "PACK_SECONDS", 5.0)
    v, f = _grid()
    ref = _direct(v, f, 64, 2, 40.0)
    _same(xc.xatlas_pack(v, f, 64, 2, 40.0), ref)
    old = xc._child
    assert old is not None
    os.kill(old.proc.pid, sig)
    _same(xc.xatlas_pack(v, f, 64, 2, 40.0), ref)
    assert xc._child is not old and old.proc.poll() is not None  # replaced, the old one gone


def test_a_child_that_never_answers_fails_the_stage(monkeypatch):
    """Every child hangs (stopped as soon as it starts): after PACK_TRIES children the pack is
    a StageError naming xatlas, not a hang."""
    monkeypatch.setattr(xc, "PACK_SECONDS", 0.5)
    monkeypatch.setattr(xc, "DROP_SECONDS", 0.5)
    started = []
    real = xc._Child.__init__

    def stopped(self) -> None:
        real(self)
        os.kill(self.proc.pid, signal.SIGSTOP)
        started.append(self.proc)

    monkeypatch.setattr(xc._Child, "__init__", stopped)
    monkeypatch.setattr(xc, "_child", None)
    v, f = _grid()
    with pytest.raises(xc.StageError, match="xatlas hung or died"):
        xc.xatlas_pack(v, f, 64, 2, 40.0)
    assert len(started) == xc.PACK_TRIES and all(p.poll() is not None for p in started)


def test_a_forked_process_starts_its_own_child():
    """A process forked after a pack (a bake's worker processes) never writes to its parent's
    child: it starts its own, and the parent's keeps answering."""
    v, f = _grid()
    ref = _direct(v, f, 64, 2, 40.0)
    _same(xc.xatlas_pack(v, f, 64, 2, 40.0), ref)
    parents = xc._child.proc.pid
    r, w = os.pipe()
    pid = os.fork()
    if pid == 0:  # the forked process: pack, report, leave without running pytest's teardown
        try:
            got = xc.xatlas_pack(v, f, 64, 2, 40.0)
            ok = xc._child.proc.pid != parents and got.width == ref[1]
            os.write(w, b"1" if ok else b"0")
        finally:
            os._exit(0)
    os.waitpid(pid, 0)
    assert os.read(r, 1) == b"1"
    _same(xc.xatlas_pack(v, f, 64, 2, 40.0), ref)
    assert xc._child.proc.pid == parents
