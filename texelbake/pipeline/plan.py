"""Which stages an asset needs: the plan of a bake.

A bake is a plan of stages; some are sharded by texel tile. Every shard is a pure function from
files in the artifact store to files in the artifact store (`texelbake.stages`), so the same code
runs in one process (`pipeline.run.bake`) or as Celery tasks (`pipeline.run.run_shard`).

Tiles: the finest CPM level has N x N texels (N = settings.atlas_resolution); a shard owns an
S x S tile (S = settings.shard_texels) and every coarser level's texels inside it (levels
0..log2 S). Levels coarser than a tile (log2 S + 1 .. log2 N) are one `*_top` shard.
"""

from __future__ import annotations

import functools
import warnings
from dataclasses import dataclass
from pathlib import Path

from schemas.queues import STAGE_QUEUES
from schemas.settings import BakeSettings
from texelbake.errors import AssetError, StageError
from texelbake.geometry.build import lod1_atlas
from texelbake.stages.context import asset_of
from texelbake.stages.srf import n_srf_shards


@dataclass(frozen=True)
class StagePlan:
    name: str
    queue: str
    n_shards: int
    depends_on: tuple[str, ...] = ()


@dataclass(frozen=True)
class Plan:
    stages: tuple[StagePlan, ...]
    skipped: tuple[tuple[str, str], ...] = ()

    def stage(self, name: str) -> StagePlan:
        for s in self.stages:
            if s.name == name:
                return s
        raise StageError(f"stage {name!r} is not in this plan ({[s.name for s in self.stages]})")


def n_tiles(settings: BakeSettings) -> int:
    side = settings.atlas_resolution // settings.shard_texels
    return side * side


def resolve_settings(asset_path: Path, settings: BakeSettings) -> BakeSettings:
    """The settings a bake runs with: atlas_mode "lod1" replaced by its atlas side (the size
    at which a finest texel is at most one pixel where LOD1 switches in, capped at atlas_cap;
    `texelbake.geometry.build.lod1_atlas`), shard_texels kept within it; other settings as
    given. A deterministic function of the asset and the settings, so every process of a bake
    (the CLI's, the farm's workers) resolves the same."""
    if settings.atlas_mode != "lod1":
        return settings
    asset = asset_of(asset_path)
    n, _need = lod1_atlas(asset.points, asset.faces, settings.lod_switch_px[0],
                          settings.atlas_cap)
    return BakeSettings.model_validate(settings.model_dump() | {
        "atlas_resolution": n, "shard_texels": min(settings.shard_texels, n)})


def atlas_note(asset_path: Path, settings: BakeSettings) -> str:
    """One line on the atlas a bake runs with: its side, how it was chosen, whether the cap
    was reached (atlas_mode "lod1": serving the largest size the cap allows)."""
    n = resolve_settings(asset_path, settings).atlas_resolution
    if settings.atlas_mode != "lod1":
        return f"atlas: {n}x{n} (atlas_mode fixed)"
    asset = asset_of(asset_path)
    _n, need = lod1_atlas(asset.points, asset.faces, settings.lod_switch_px[0],
                          settings.atlas_cap)
    text = (f"atlas: {n}x{n} (atlas_mode lod1: {need}x{need} puts a finest texel at one pixel "
            f"at LOD1's switch size, {settings.lod_switch_px[0]:g} px; cap {settings.atlas_cap})")
    if need is not None and need > n:
        text += (f"; the cap is reached: serving {n}x{n}, the largest size the cap allows, "
                 f"which serves LOD1 up to {settings.lod_switch_px[0] * n / need:g} px")
    return text


def plan_bake(asset_path: Path, settings: BakeSettings) -> Plan:
    """The stages this asset and these settings (`resolve_settings`) need, in execution
    order, with what is skipped."""
    settings = resolve_settings(asset_path, settings)
    tiles = n_tiles(settings)
    has_top = settings.shard_texels < settings.atlas_resolution
    plan = [
        StagePlan("ingest", STAGE_QUEUES["ingest"], 1),
        StagePlan("geometry", STAGE_QUEUES["geometry"], 1, ("ingest",)),
        StagePlan("avis", STAGE_QUEUES["avis"], tiles, ("geometry",)),
    ]
    skipped: list[tuple[str, str]] = []
    if has_top:
        plan.append(StagePlan("avis_top", STAGE_QUEUES["avis_top"], 1, ("avis",)))
    # a coarse level's fit reads its a_vis from the a_vis stage's maps (the children's summed)
    children = settings.avis_coarse == "children" and settings.fit_method == "batched"
    plan.append(StagePlan("cpm", STAGE_QUEUES["cpm"], tiles,
                          ("geometry", "avis") if children else ("geometry",)))
    if has_top:
        plan.append(StagePlan("cpm_top", STAGE_QUEUES["cpm_top"], 1,
                              ("cpm", "avis_top") if children else ("cpm",)))
    cpm_deps = ("cpm_top",) if has_top else ("cpm",)
    avis_deps = ("avis_top",) if has_top else ("avis",)
    if settings.btf:
        plan.append(StagePlan("btf", STAGE_QUEUES["btf"], 1, cpm_deps))
    else:
        skipped.append(("btf", "no real-time target requested (settings.btf is false)"))
    if settings.srf:  # seed 002 §3: captured with gt, sharded by camera (render workers)
        plan.append(StagePlan("srf", STAGE_QUEUES["srf"], n_srf_shards(settings), ("ingest",)))
        plan.append(StagePlan("srf_top", STAGE_QUEUES["srf_top"], 1, ("srf",)))
    export_deps = (cpm_deps + avis_deps + (("btf",) if settings.btf else ())
                   + (("srf_top",) if settings.srf else ()))
    plan.append(StagePlan("export", STAGE_QUEUES["export"], 1, export_deps))
    if settings.previews:
        plan.append(StagePlan("render", STAGE_QUEUES["render"], 1, ("export",)))
        # seed 002 §4: an animated preview of deformed frames, only when there is motion
        if settings.warp or asset_deforms(asset_path):
            plan.append(StagePlan("deformed", STAGE_QUEUES["deformed"], 1, ("export",)))
        else:
            skipped.append(("deformed", "the asset has no animation (at most one time sample) "
                                        "and no warp was asked (settings.warp)"))
    else:
        skipped.append(("render", "previews not requested (settings.previews is false)"))
        skipped.append(("deformed", "previews not requested (settings.previews is false)"))
    if not settings.srf:
        skipped.append(
            ("srf", "no reflectance field requested (settings.srf is false; the impostor "
                    "parameterization is on every LOD mesh for deformed frames)")
        )
    return Plan(tuple(plan), tuple(skipped))


def asset_deforms(asset_path: Path) -> bool:
    """Whether the asset's points move over its time samples (`AssetModel.has_deformation`,
    the ingest's own reading), read once per file version and process: the plan is made
    again by every shard."""
    path = Path(asset_path)
    try:
        st = path.stat()
    except OSError as exc:
        raise AssetError(f"the asset cannot be read ({exc.strerror})", path=str(path)) from None
    return _deforms(str(path.resolve()), st.st_mtime_ns, st.st_size)


@functools.lru_cache(maxsize=16)
def _deforms(path: str, mtime_ns: int, size: int) -> bool:
    from texelbake.asset.load import load_asset

    with warnings.catch_warnings():  # the ingest stage reports the asset's warnings
        warnings.simplefilter("ignore")
        return load_asset(path).has_deformation
