"""`services.archive` (run in the upload checker) on hostile zips built at the byte level, and
`farm.storage.public_text` (what a client reads of an error): in process, no stack."""

from __future__ import annotations

import zipfile
from pathlib import Path

import pytest

from farm.storage import public_text
from services import archive
from tests.helpers.hostile_zips import cases, understated
from tests.helpers.service import make_zip, usda

LIMITS = {"max_unpacked": 1 << 30, "max_ratio": 100.0, "max_members": 4096}


def unpack(tmp_path: Path, data: bytes, name: str = "scene.zip") -> list[str]:
    (tmp_path / "up.zip").write_bytes(data)
    (tmp_path / "bundle").mkdir()
    return archive.unpack_zip(tmp_path / "up.zip", tmp_path / "bundle", display=name, **LIMITS)


@pytest.mark.parametrize("case", sorted(cases()))
def test_hostile_zip_is_refused_naming_the_member(tmp_path, case):
    data, member = cases()[case]
    with pytest.raises(archive.ArchiveRejected) as exc:
        unpack(tmp_path, data)
    assert exc.value.status == 422 and member in exc.value.detail
    assert str(tmp_path) not in exc.value.detail


def test_file_and_folder_is_named_for_either_order_and_explicit_folders(tmp_path):
    for members in ([("tex/", b""), ("tex", b"x")], [("tex", b"x"), ("tex/", b"")],
                    [("a/b/c.png", b"x"), ("a/b", b"y")]):  # fmt: skip
        sub = tmp_path / str(len(list(tmp_path.iterdir())))
        sub.mkdir()
        with zipfile.ZipFile(sub / "z.zip", "w") as zf:
            zf.writestr("scene.usda", usda())
            for name, data in members:
                zf.writestr(name, data)
        with pytest.raises(archive.ArchiveRejected, match=archive.FILE_AND_FOLDER):
            unpack(sub, (sub / "z.zip").read_bytes())


def test_understated_size_stops_at_the_declared_size(tmp_path):
    """512 MiB of zeros behind a header that says 100 bytes: refused after the first block,
    with nothing near the real size written."""
    with pytest.raises(archive.ArchiveRejected) as exc:
        unpack(tmp_path, understated(512))
    assert "pad.bin" in exc.value.detail
    written = sum(p.stat().st_size for p in (tmp_path / "bundle").rglob("*") if p.is_file())
    assert written < 1 << 20


def test_valid_bundle_unpacks_and_finds_its_root(tmp_path):
    files = unpack(tmp_path, make_zip({"scene.usda": usda(), "tex/a.png": b"png"}))
    assert files == ["scene.usda", "tex/a.png"]
    assert (tmp_path / "bundle" / "tex" / "a.png").read_bytes() == b"png"
    assert archive.root_layer(files, "scene.zip", usdz=False) == "scene.usda"
    with pytest.raises(archive.ArchiveRejected, match=archive.NO_ROOT):
        archive.root_layer(["tex/a.png", "scene.usda"], "m.usdz", usdz=True)


def test_public_text_drops_server_paths_but_not_prim_paths_or_member_names(tmp_path):
    root = tmp_path / "artifacts"
    bundle = root / "assets" / ("ab" * 32) / "bundle"
    code = Path(archive.__file__).resolve().parents[1]
    text = (f"ErrorException: Error in 'Sdf_CrateFile::_Unpack' at line 9 in file "
            f"/opt/USD/pxr/usd/sdf/crateFile.cpp : 'Corrupt asset <{bundle}/sub/m.usdc>' at "
            f"/World/Box; File \"{code}/workers/tasks.py\", line 3; {root}/jobs/j1/out; "
            f"member /tmp/evil.txt")  # fmt: skip
    out = public_text(text, root)
    assert "Corrupt asset <sub/m.usdc>" in out and "/World/Box" in out
    assert "jobs/j1/out" in out and "member /tmp/evil.txt" in out
    for server in (str(tmp_path), str(code), "/opt/USD", "Error in"):
        assert server not in out, out
