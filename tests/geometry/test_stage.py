"""The geometry stage's samples made a chunk at a time on disk (issue 15, memory bounded per
worker whatever the atlas size): the artifact does not depend on the chunk or the spool, the
spool is removed, a killed worker's spool is swept by the next run."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from schemas.settings import BakeSettings
from texelbake import stages
from texelbake.cpm.level import samples_in, texel_ids
from texelbake.geometry import build as build_mod
from texelbake.geometry.build import build_geometry, geometry_chunk
from texelbake.geometry.texels import morton
from texelbake.io.spool import FileSpool, MemorySpool
from texelbake.testscenes import write_scene


@pytest.fixture(scope="module")
def wall_ctx(tmp_path_factory):
    """The wall: a wrapped M1, so the bent-normal rule (M_org as occluder) runs in the pass."""
    d = tmp_path_factory.mktemp("geostage")
    scene = write_scene("wall", d / "wall.usda", "small")
    s = BakeSettings(atlas_resolution=32, samples_per_texel=16, mesh_levels=2)
    ctx = stages.StageContext.create(d / "work", scene, s)
    stages.run_ingest(ctx, 0)
    return ctx


def test_chunks_and_spools_give_the_same_arrays(wall_ctx, tmp_path, monkeypatch):
    ctx = wall_ctx
    one = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels, MemorySpool())
    assert len(one["sample_pos"]) > 3 * 1000
    monkeypatch.setattr(build_mod, "geometry_chunk", lambda s: 1000)
    spool = FileSpool(tmp_path)
    parts = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels, spool)
    assert sorted(parts) == sorted(one)
    for name, arr in one.items():
        assert parts[name].dtype == arr.dtype and parts[name].shape == arr.shape, name
        assert np.array(parts[name]).tobytes() == arr.tobytes(), name
    assert isinstance(parts["sample_row"], np.memmap)  # on disk, not in the process
    spool.close()
    assert list(tmp_path.iterdir()) == []


def test_the_stage_writes_the_in_memory_arrays_and_leaves_no_spool(wall_ctx):
    ctx = wall_ctx
    key = stages.run_geometry(ctx, 0)
    folder = ctx.store.path(key).parent
    assert [p.name for p in folder.iterdir()] == [ctx.store.path(key).name]
    got = ctx.store.read_arrays(key)
    one = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels)
    assert sorted(got) == sorted(one)
    for name, arr in one.items():
        assert got[name].tobytes() == np.asarray(arr).tobytes(), name


def test_a_dead_workers_spool_is_swept(tmp_path):
    """A spool whose process is gone is removed by the next sweep; a live one is kept."""
    child = subprocess.run(
        [sys.executable, "-c", "import sys; from texelbake.io.spool import FileSpool; "
         "s = FileSpool(sys.argv[1]); s.allocate('a', 'f8', (10,)); print(s.dir)",
         str(tmp_path)], check=True, capture_output=True, text=True)
    dead = tmp_path / os.path.basename(child.stdout.strip())
    assert dead.is_dir()  # the child exited without closing it
    live = FileSpool(tmp_path)
    assert FileSpool.sweep(tmp_path) == [dead]
    assert not dead.exists() and live.dir.is_dir()
    live.close()


def test_a_killed_workers_spool_is_swept_before_it_is_reaped(tmp_path):
    """A worker killed mid-stage is a zombie until its parent reaps it, and its shard is taken
    over at once (`farm.ledger.start_shard`): the rerun's sweep must count it as gone."""
    import time

    from texelbake.io.spool import pid_alive

    child = subprocess.Popen(
        [sys.executable, "-c", "import sys, time; from texelbake.io.spool import FileSpool; "
         "s = FileSpool(sys.argv[1]); s.allocate('a', 'f8', (10,)); print(s.dir, flush=True); "
         "time.sleep(60)", str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        dead = tmp_path / os.path.basename(child.stdout.readline().strip())
        assert dead.is_dir() and pid_alive(child.pid)
        child.kill()  # not reaped (no wait yet): a zombie
        deadline = time.monotonic() + 10
        while b") Z " not in open(f"/proc/{child.pid}/stat", "rb").read():
            assert time.monotonic() < deadline
            time.sleep(0.01)
        assert not pid_alive(child.pid)
        assert FileSpool.sweep(tmp_path) == [dead]
    finally:
        child.kill()
        child.wait()
        child.stdout.close()


def test_chunk_follows_the_worker_memory_setting():
    small, big = (geometry_chunk(BakeSettings(worker_memory_mb=mb)) for mb in (64, 4096))
    assert small == 1 << 14 and big == 4096 * 2**20 // 4 // build_mod.GEOMETRY_BYTES_PER_SAMPLE


def test_morton_codes_make_every_level_texel_one_run():
    """`morton` against its definition: bits interleaved (row's odd), and an aligned block of
    2^l x 2^l texels is the 4^l codes from its first."""
    rng = np.random.default_rng(2)
    r, c = rng.integers(0, 1 << 20, 500), rng.integers(0, 1 << 20, 500)
    want = [sum((((int(a) >> k) & 1) << (2 * k + 1)) | (((int(b) >> k) & 1) << (2 * k))
                for k in range(20)) for a, b in zip(r, c, strict=True)]
    assert morton(r, c).tolist() == want
    n, level = 32, 3
    rows, cols = np.divmod(np.arange(n * n), n)
    code = morton(rows, cols)
    assert np.array_equal(np.sort(code), np.arange(n * n))  # a permutation
    block = (rows >> level) * (n >> level) + (cols >> level)
    for t in range((n >> level) ** 2):
        got = np.sort(code[block == t])
        assert got[0] == morton(np.array([t // (n >> level) << level]),
                                np.array([t % (n >> level) << level]))[0]
        assert np.array_equal(got, np.arange(got[0], got[0] + 4 ** level))


def test_zorder_index_lists_the_samples_a_scan_finds(wall_ctx, monkeypatch):
    """`samples_in` (the Z-order index) against the scan of every sample's texel, at every
    level, for single texels, tiles and scattered sets; the index is the same for any chunk
    (the bucket sort's buckets follow the chunk)."""
    ctx = wall_ctx
    geo = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels)
    monkeypatch.setattr(build_mod, "geometry_chunk", lambda s: 777)
    small = build_geometry(ctx.asset(), ctx.settings, ctx.caster(), ctx.n_levels)
    assert np.array_equal(geo["sample_zorder"], small["sample_zorder"])
    n = ctx.settings.atlas_resolution
    m = len(geo["sample_pos"])
    assert np.array_equal(np.sort(geo["sample_zorder"]), np.arange(m))
    scan = {k: v for k, v in geo.items() if k not in ("sample_zorder", "texel_zoffsets")}
    rng = np.random.default_rng(0)
    for level in range(ctx.n_levels):
        n_l = n >> level
        tex = texel_ids(geo, n, level)
        for texels in (np.array([int(tex[0])]), np.arange(n_l * n_l),
                       rng.choice(n_l * n_l, max(1, n_l * n_l // 5), replace=False)):
            want = np.flatnonzero(np.isin(tex, texels))
            assert np.array_equal(samples_in(geo, n, level, texels), want), level
            assert np.array_equal(samples_in(scan, n, level, texels), want), level
