"""The artifact write path's fault-injection point (`texelbake.io.atomic.failpoint`), the hook the
chaos suite uses to make a worker's disk full (ENOSPC) or read-only (EACCES) for a while."""

from __future__ import annotations

import errno

import pytest

from texelbake.io.atomic import FAILPOINT_ENV, atomic_path, atomic_write_bytes


def test_unset_or_empty_control_file_writes_normally(tmp_path, monkeypatch):
    monkeypatch.delenv(FAILPOINT_ENV, raising=False)
    assert atomic_write_bytes(tmp_path / "a.bin", b"1").read_bytes() == b"1"
    control = tmp_path / "control"
    monkeypatch.setenv(FAILPOINT_ENV, str(control))
    assert atomic_write_bytes(tmp_path / "b.bin", b"2").read_bytes() == b"2"  # no file yet
    control.write_text("")
    assert atomic_write_bytes(tmp_path / "c.bin", b"3").read_bytes() == b"3"  # empty file


@pytest.mark.parametrize("name", ["ENOSPC", "EACCES"])
def test_fault_fails_the_write_and_leaves_nothing(name, tmp_path, monkeypatch):
    control = tmp_path / "control"
    control.write_text(f"{name} /store/\n")
    monkeypatch.setenv(FAILPOINT_ENV, str(control))
    store = tmp_path / "store"
    store.mkdir()
    (store / "x.bin").write_bytes(b"old")
    with pytest.raises(OSError) as info:
        atomic_write_bytes(store / "x.bin", b"new")
    assert info.value.errno == getattr(errno, name)
    assert info.value.filename == str(store / "x.bin")  # the error names the path
    assert (store / "x.bin").read_bytes() == b"old"  # target untouched
    assert sorted(p.name for p in store.iterdir()) == ["x.bin"]  # no temporary file left
    with pytest.raises(OSError):  # the context manager form too
        with atomic_path(store / "y.npy") as tmp:
            tmp.write_bytes(b"y")
    assert sorted(p.name for p in store.iterdir()) == ["x.bin"]
    # a path without the fragment is not affected
    assert atomic_write_bytes(tmp_path / "other.bin", b"o").read_bytes() == b"o"
    # the fault clears when the control file is emptied or removed
    control.unlink()
    assert atomic_write_bytes(store / "x.bin", b"new").read_bytes() == b"new"


def test_bad_errno_name_is_a_clear_error(tmp_path, monkeypatch):
    control = tmp_path / "control"
    control.write_text("ENOTANERRNO")
    monkeypatch.setenv(FAILPOINT_ENV, str(control))
    with pytest.raises(ValueError, match="ENOTANERRNO"):
        atomic_write_bytes(tmp_path / "x.bin", b"x")
