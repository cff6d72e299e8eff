"""The ingest stage: read and check the asset, record what was found (`ingest.json`)."""

from __future__ import annotations

import warnings

from texelbake.asset.values import AssetWarning
from texelbake.stages.context import StageContext


def run_ingest(ctx: StageContext, shard: int = 0) -> str:
    """Read and check the asset; record what was found (`ingest.json`)."""
    key = ctx.key("ingest", "ingest.json", ())
    if ctx.store.exists(key):
        return key
    asset = ctx.asset()
    for w in dict.fromkeys(asset.warnings):  # shown once, here (`context._load_asset_cached`)
        warnings.warn(w, AssetWarning, stacklevel=2)
    summary = {
        "source": str(ctx.asset_path),
        "asset_hash": ctx.asset_hash,
        "meshes": list(asset.mesh_paths),
        "faces": asset.num_faces,
        "materials": [{"path": m.path, "model": m.model} for m in asset.materials],
        "lights": len(asset.lights),
        "cameras": len(asset.cameras),
        "bounds": asset.bounds.tolist(),
        "deformation": bool(asset.has_deformation),
        "dropped_faces": int(asset.dropped_faces),
        "warnings": list(asset.warnings),
    }
    return ctx.store.write_json(key, summary)
