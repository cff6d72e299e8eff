"""The srf stage (seed 002 §3, §5): a surface reflectance field of M_org captured with `gt`
(`texelbake.srf.capture`), sharded by camera — shard i renders cameras
[i·k, (i+1)·k) of the rig (k = settings.srf_shard_cameras) under every light into one store
under the artifact store; `srf_top` checks every block is there and writes `srf.json`; the
export copies the store beside the baked USD (`srf/`), where `texelbake render --modes srf`
finds it. Blocks are written atomically, so a retried shard overwrites identical files."""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import numpy as np

from texelbake.stages.context import StageContext

#: the settings a capture depends on (its artifact key)
SRF_FIELDS = ("seed", "srf_cameras", "srf_lights", "srf_size", "srf_spp")


def n_srf_shards(settings) -> int:
    return math.ceil(settings.srf_cameras / settings.srf_shard_cameras)


def srf_key(ctx: StageContext) -> str:
    return ctx.key("srf", "store", SRF_FIELDS)


def _writer(ctx: StageContext):
    from texelbake.srf.rig import sphere_cameras, sphere_directions
    from texelbake.srf.store import SrfWriter

    s = ctx.settings
    cams = sphere_cameras(ctx.asset().bounds, s.srf_cameras, s.srf_size)
    return SrfWriter(ctx.store.path(srf_key(ctx)), cams, sphere_directions(s.srf_lights),
                     source=ctx.asset_path.name)


def run_srf_shard(ctx: StageContext, shard: int = 0) -> str:
    """Capture cameras [shard·k, (shard+1)·k) of the rig (module docstring)."""
    from texelbake.srf.capture import capture_cameras

    key = srf_key(ctx)
    if (ctx.store.path(key) / "srf.json").is_file():
        return key
    s = ctx.settings
    lo = int(shard) * s.srf_shard_cameras
    hi = min(lo + s.srf_shard_cameras, s.srf_cameras)
    capture_cameras(ctx.asset(), _writer(ctx), range(lo, hi), s.srf_spp, s.seed)
    return key


def run_srf_top(ctx: StageContext, shard: int = 0) -> str:
    """Every shard's blocks are there: write the store's `srf.json`."""
    key = srf_key(ctx)
    if not (ctx.store.path(key) / "srf.json").is_file():
        s = ctx.settings
        bounds = np.asarray(ctx.asset().bounds, dtype=np.float64)
        _writer(ctx).close({"capture": {"renderer": "gt", "spp": s.srf_spp, "seed": s.seed},
                            "bounds": bounds.tolist()})
    return key


def export_srf(ctx: StageContext, out_dir: Path, report: dict) -> None:
    """Copy the captured store beside the baked USD (`srf/`) and name it in the report."""
    src = ctx.store.path(srf_key(ctx))
    dst = Path(out_dir) / "srf"
    shutil.copytree(src, dst, dirs_exist_ok=True)
    s = ctx.settings
    report["srf"] = {"store": "srf", "cameras": s.srf_cameras, "lights": s.srf_lights,
                     "size": s.srf_size, "spp": s.srf_spp}
