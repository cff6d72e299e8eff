"""What every stage shares: where a bake's artifacts live and what they are derived from
(`StageContext`), the content-derived artifact keys, and per-process caches of the asset, the
geometry arrays and the ray caster over M_org."""

from __future__ import annotations

import functools
import hashlib
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.settings import BakeSettings
from texelbake.brdf.evaluate import shading_normal
from texelbake.brdf.opacity import asset_cutout
from texelbake.cpm.level import FitInputs
from texelbake.errors import StageError
from texelbake.geometry.normal_input import NormalInput, mapped_normals
from texelbake.geometry.raycast import RayCaster
from texelbake.io.store import ArtifactStore, file_sha256
from texelbake.model import AssetModel

#: settings that change no stage output (farm layout and optional downstream stages)
#: (shard_texels changes no result but does name the tile artifacts: it is part of their key,
#: so bakes of one asset with different tilings can share a store, the default store;
#: worker_memory_mb changes how a worker chunks its texels, never a result)
LAYOUT_ONLY = {"previews", "warp", "deform_frames", "worker_memory_mb", "gate_snr_median_db",
               "gate_snr_p5_db", "gate_avis_rel_error"}  # the gate's targets are re-checked on
# every export; warp and deform_frames change the deformed previews only
#: settings only the export reads (the fallback material): no other stage's key holds them, so
#: exports that differ in them share every other artifact
EXPORT_ONLY = {"fallback"}
GEOMETRY_FIELDS = (
    "seed", "atlas_resolution", "mesh_levels", "simplify_ratio", "m1_faces", "samples_per_texel",
    "enclose_meshes", "m1_method", "lod_mode", "lod_switch_px", "lod_error_px", "sample_density",
)
_TAG_LIGHT, _TAG_VIEW, _TAG_HELD_I, _TAG_HELD_O = 0x11, 0x22, 0x33, 0x44


@dataclass(frozen=True)
class StageContext:
    """Where a bake's artifacts live and what they are derived from."""

    store: ArtifactStore
    asset_path: Path
    settings: BakeSettings
    asset_hash: str

    @classmethod
    def create(cls, workdir: Path, asset_path: Path, settings: BakeSettings) -> StageContext:
        asset_path = Path(asset_path).resolve()
        if not asset_path.is_file():
            raise StageError(f"asset file {asset_path} does not exist")
        return cls(ArtifactStore(Path(workdir) / "artifacts"), asset_path, settings,
                   _asset_digest(str(asset_path), asset_path.stat().st_mtime_ns))

    @property
    def n_levels(self) -> int:
        return int(self.settings.atlas_resolution).bit_length()  # log2 N + 1

    @property
    def tile_levels(self) -> int:
        """Levels 0..tile_levels-1 live inside one shard's tile."""
        return int(self.settings.shard_texels).bit_length()

    def key(self, stage: str, name: str, fields: tuple[str, ...] | None = None) -> str:
        if fields is None:
            skip = LAYOUT_ONLY | (set() if stage == "export" else EXPORT_ONLY)
            fields = tuple(sorted(set(BakeSettings.model_fields) - skip))
        return f"{self.asset_hash[:16]}/{stage}-{self.settings.digest(*fields)}/{name}"

    def geometry_key(self) -> str:
        return self.key("geometry", "geometry.npz", GEOMETRY_FIELDS)

    def asset(self) -> AssetModel:
        return _load_asset_cached(str(self.asset_path), self.asset_hash)

    def geometry(self) -> dict[str, np.ndarray]:
        return _read_cached(str(self.store.root), self.geometry_key())

    def caster(self) -> RayCaster:
        a = self.asset()
        return _caster_cached(self.asset_hash, a)

    def normal_input(self) -> NormalInput | None:
        """The materials' normal maps on M_org (`geometry.normal_input`), None when no
        material has one; made once per asset in a process (M_org's MikkTSpace frames)."""
        a = self.asset()
        if self.asset_hash not in _NORMAL_INPUTS:
            _NORMAL_INPUTS.clear()
            _NORMAL_INPUTS[self.asset_hash] = mapped_normals(a, shading_normal)
        return _NORMAL_INPUTS[self.asset_hash]

    def fit_inputs(self) -> FitInputs:
        """What `texelbake.cpm.level` reads to fit a level."""
        return FitInputs(self.settings, self.geometry(), self.caster(), self.asset().materials)


@functools.lru_cache(maxsize=8)
def _asset_digest(path: str, mtime_ns: int) -> str:
    # The root layer's bytes plus every file it references (textures, sublayers): a texture
    # edit must change the key.
    h = hashlib.sha256(file_sha256(path).encode())
    from texelbake.asset import check_asset_paths

    for dep in sorted(check_asset_paths(path)):
        if Path(dep).resolve() != Path(path).resolve():
            h.update(file_sha256(dep).encode())
    return h.hexdigest()


def asset_of(asset_path: Path) -> AssetModel:
    """The asset at `asset_path` as every stage reads it (cached per file and mtime)."""
    path = Path(asset_path).resolve()
    if not path.is_file():
        raise StageError(f"asset file {path} does not exist")
    return _load_asset_cached(str(path), _asset_digest(str(path), path.stat().st_mtime_ns))


@functools.lru_cache(maxsize=2)
def _load_asset_cached(path: str, digest: str) -> AssetModel:
    """The asset as every stage reads it, its warnings kept in `AssetModel.warnings` and not
    shown: the ingest stage shows them once (`run_ingest`), the report lists them, and a
    shard process that reads the asset again does not repeat them."""
    from texelbake.asset import load_asset
    from texelbake.asset.values import AssetWarning

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", AssetWarning)
        return load_asset(path)


@functools.lru_cache(maxsize=4)
def _read_cached(root: str, key: str) -> dict[str, np.ndarray]:
    # mapped, not read: a shard touches its tile's samples only (memory)
    return ArtifactStore(root).read_arrays(key, mmap=True)


_CASTERS: dict[str, RayCaster] = {}
_NORMAL_INPUTS: dict[str, NormalInput | None] = {}


def _caster_cached(digest: str, asset: AssetModel) -> RayCaster:
    if digest not in _CASTERS:
        _CASTERS.clear()
        # M_org's visibility rays (a_vis, the fit's R) pass through cut-outs
        _CASTERS[digest] = RayCaster(asset.points, asset.faces, cutout=asset_cutout(asset))
    return _CASTERS[digest]
