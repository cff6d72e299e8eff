"""The one way of each piece of plumbing (issue 19): atomic writes, deterministic archives and
image headers, the sRGB pair."""

from __future__ import annotations

import zipfile

import numpy as np
import pytest

from texelbake.io.archive import zip_bytes
from texelbake.io.atomic import atomic_path, atomic_write_bytes
from texelbake.io.images import linear_to_srgb, read_pixels, srgb_to_linear, write_exr


def test_a_failing_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = tmp_path / "sub" / "data.bin"
    atomic_write_bytes(target, b"old")
    with pytest.raises(RuntimeError, match="disk on fire"), atomic_path(target) as tmp:
        tmp.write_bytes(b"half of the new")
        raise RuntimeError("disk on fire")
    assert target.read_bytes() == b"old"
    assert sorted(p.name for p in target.parent.iterdir()) == ["data.bin"]  # no leftovers
    atomic_write_bytes(target, b"new")
    assert target.read_bytes() == b"new" and oct(target.stat().st_mode & 0o777) == "0o644"


def test_zip_bytes_is_deterministic_and_sorted():
    a = zip_bytes([("b.txt", b"2"), ("a.txt", b"1")])
    b = zip_bytes([("a.txt", b"1"), ("b.txt", b"2")])
    assert a == b
    import io

    with zipfile.ZipFile(io.BytesIO(a)) as zf:
        assert zf.namelist() == ["a.txt", "b.txt"]
        assert {i.date_time for i in zf.infolist()} == {(1980, 1, 1, 0, 0, 0)}


def test_exr_rewrites_are_byte_identical(tmp_path):
    """OpenEXR stamps the current time unless told otherwise; ours carry a fixed DateTime."""
    img = np.random.default_rng(0).random((4, 5, 3))
    p1 = write_exr(tmp_path / "a.exr", img)
    first = p1.read_bytes()
    import time

    time.sleep(1.1)  # the DateTime field has one-second resolution
    assert write_exr(tmp_path / "a.exr", img).read_bytes() == first
    px, info = read_pixels(p1)
    np.testing.assert_array_equal(px, img.astype(np.float32))
    assert info.attributes["DateTime"] == "1970:01:01 00:00:00" and info.is_float


def test_srgb_pair_round_trips_and_matches_the_standard():
    x = np.linspace(0.0, 1.0, 1001)
    np.testing.assert_allclose(srgb_to_linear(linear_to_srgb(x)), x, atol=2e-6)
    # IEC 61966-2-1 fixed points: 0 -> 0, 1 -> 1, the linear segment below 0.0031308
    np.testing.assert_allclose(linear_to_srgb([0.0, 1.0, 0.001]), [0.0, 1.0, 0.01292])
