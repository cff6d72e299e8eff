"""The artifact store's `.npz` files: streamed writes give the bytes of the in-memory zip they
replaced, and a mapped read gives the arrays a plain read gives (issue 15, memory)."""

from __future__ import annotations

import io
import subprocess
import sys
import zipfile

import numpy as np
import pytest

from texelbake.errors import ShapeError, StageError
from texelbake.io.archive import zip_bytes
from texelbake.io.spool import FileSpool, spooled_file
from texelbake.io.store import MMAP_MIN_BYTES, ArtifactStore, read_npz, write_npz


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(4)
    return {
        "pos": rng.random((70_000, 3)),  # 1.7 MB: mapped
        "fortran": np.asfortranarray(rng.random((400, 500))),  # 1.6 MB, F order: mapped
        "ids": np.arange(300_000, dtype=np.int32),  # 1.2 MB: mapped
        "small": np.arange(10, dtype=np.int64),  # read
        "empty": np.zeros((0, 3)),
        "flag": np.array(True),
        "text": np.array('{"a": 1}'),
    }


def _zip_of_members(arrays: dict[str, np.ndarray]) -> bytes:
    """The artifacts' bytes before they were streamed: every member's `.npy` bytes in memory,
    then one zip (texelbake.io.archive.zip_bytes, stored, no permissions, sorted by name)."""
    members = []
    for name in sorted(arrays):
        buf = io.BytesIO()
        np.lib.format.write_array(buf, np.asanyarray(arrays[name]), allow_pickle=False)
        members.append((f"{name}.npy", buf.getvalue()))
    return zip_bytes(members, deflate=False, mode=None, sort=False)


def test_streamed_npz_has_the_bytes_of_the_in_memory_zip(tmp_path):
    arrays = _arrays()
    expect = _zip_of_members(arrays)
    buf = io.BytesIO()
    write_npz(buf, arrays)
    assert buf.getvalue() == expect
    store = ArtifactStore(tmp_path)
    store.write_arrays("a/b.npz", arrays)
    assert store.path("a/b.npz").read_bytes() == expect
    with np.load(store.path("a/b.npz")) as z:  # numpy reads it as its own
        for name, arr in arrays.items():
            np.testing.assert_array_equal(z[name], arr)


@pytest.mark.parametrize("mmap", [False, True])
def test_read_gives_the_arrays_written(tmp_path, mmap):
    arrays = _arrays()
    store = ArtifactStore(tmp_path)
    store.write_arrays("k.npz", arrays)
    got = store.read_arrays("k.npz", mmap=mmap)
    assert sorted(got) == sorted(arrays)
    for name, arr in arrays.items():
        assert got[name].dtype == arr.dtype and got[name].shape == arr.shape, name
        np.testing.assert_array_equal(got[name], arr)
        assert type(got[name]) is np.ndarray
        mapped = mmap and arr.nbytes >= MMAP_MIN_BYTES
        assert got[name].flags.writeable is not mapped, name  # a mapped array is read-only
    assert got["fortran"].flags.f_contiguous
    only = store.read_arrays("k.npz", lambda n: n in ("pos", "flag"), mmap=mmap)
    assert sorted(only) == ["flag", "pos"]


def test_a_mapped_read_pays_for_the_pages_it_touches(tmp_path):
    """A 400 MB member read mapped, one row of it touched, in a fresh process: its peak
    resident set grows by far less than the member (read whole, it would grow by all of it)."""
    store = ArtifactStore(tmp_path)
    big = np.ones((50_000_000,))  # 400 MB
    store.write_arrays("big.npz", {"big": big})
    del big
    # VmHWM, not ru_maxrss: Linux carries ru_maxrss over from the (large) parent across exec
    code = (
        "import sys; from pathlib import Path; from texelbake.io.store import read_npz\n"
        "def hwm():\n"
        "    line = next(x for x in open('/proc/self/status') if x.startswith('VmHWM'))\n"
        "    return int(line.split()[1])\n"
        "before = hwm()\n"
        "a = read_npz(Path(sys.argv[1]), mmap=sys.argv[2] == '1')['big']\n"
        "assert a[12_345_678] == 1.0\n"
        "print((hwm() - before) / 1024)\n"
    )
    grow = {m: float(subprocess.run([sys.executable, "-c", code, str(store.path("big.npz")), m],
                                    check=True, capture_output=True, text=True).stdout)
            for m in ("1", "0")}
    assert grow["1"] < 40.0  # MiB: a few pages and the interpreter's own noise
    assert grow["0"] > 300.0  # the same read without the map holds the member


def test_a_damaged_member_header_is_named(tmp_path):
    store = ArtifactStore(tmp_path)
    store.write_arrays("d.npz", {"pos": np.zeros((200_000, 3))})
    p = store.path("d.npz")
    with zipfile.ZipFile(p) as zf:
        offset = zf.getinfo("pos.npy").header_offset
    data = bytearray(p.read_bytes())
    data[offset:offset + 4] = b"XXXX"
    p.write_bytes(bytes(data))
    with pytest.raises(StageError, match="pos.npy"):
        read_npz(p, mmap=True)


def test_a_spooled_array_is_copied_with_the_bytes_of_the_array(tmp_path):
    """A `FileSpool` array (the geometry stage's samples, filled a block of rows at a time)
    goes into an `.npz` with the bytes the same array in memory gives; a view of its file
    under another shape, a slice or a reversed view is written as an ordinary array."""
    rng = np.random.default_rng(7)
    arrays = {"pos": rng.random((5_000, 3)), "ids": np.arange(7_001, dtype=np.int32)}
    spool = FileSpool(tmp_path / "spool")
    for name, arr in arrays.items():
        spool.allocate(name, arr.dtype, arr.shape)
        for a in range(0, len(arr), 999):
            spool.write(name, a, arr[a:a + 999])
        np.testing.assert_array_equal(spool.read(name, 1000, 3000), arr[1000:3000])
    got = spool.arrays()
    assert all(spooled_file(v) is not None for v in got.values())
    buf = io.BytesIO()
    write_npz(buf, got)
    assert buf.getvalue() == _zip_of_members(arrays)
    views = {"flat": got["pos"].reshape(-1), "half": got["pos"][:2500],
             "back": got["ids"][::-1]}
    assert all(spooled_file(v) is None for v in views.values())
    buf = io.BytesIO()
    write_npz(buf, views)
    assert buf.getvalue() == _zip_of_members({k: np.array(v) for k, v in views.items()})
    with pytest.raises(ShapeError, match="pos"):
        spool.write("pos", 4_999, arrays["pos"][:2])
    spool.close()
    assert not (tmp_path / "spool").exists() or not any((tmp_path / "spool").iterdir())


def test_mapped_arrays_author_into_usd(tmp_path):
    """Arrays mapped from an artifact lie where their zip member does, unaligned; numpy then
    exports them with the buffer format '=d', which Vt.FromNumpy refuses. The baked USD's
    writers take aligned copies (a 256² bake's export failed on its mapped frames)."""
    from pxr import Usd

    from texelbake.usd.lodmesh import LodMesh, author_mesh
    from texelbake.usd.write import author_array

    rng = np.random.default_rng(1)
    arrays = {"frames": rng.random((50_000, 3, 3)), "ids": np.arange(300_001, dtype=np.int32),
              "vertices": rng.random((100_000, 3)),
              "faces": rng.integers(0, 100_000, (100_000, 3)).astype(np.int32)}
    store = ArtifactStore(tmp_path)
    store.write_arrays("k.npz", arrays)
    got = store.read_arrays("k.npz", mmap=True)
    assert not all(got[k].flags.aligned for k in got)  # the case this test is about
    stage = Usd.Stage.CreateInMemory()
    prim = stage.DefinePrim("/A")
    for name in ("frames", "ids"):
        author_array(prim, name, got[name])
        np.testing.assert_array_equal(np.array(prim.GetAttribute(f"texelbake:{name}").Get()),
                                      arrays[name].reshape(-1))
    corner_uvs = np.zeros((100_000, 3, 2))
    geom = author_mesh(stage, "/M", LodMesh(got["vertices"], got["faces"], corner_uvs))
    np.testing.assert_array_equal(np.array(geom.GetFaceVertexIndicesAttr().Get()),
                                  arrays["faces"].reshape(-1))
