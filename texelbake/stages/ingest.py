"""The ingest stage: read and check the asset, record what was found (`ingest.json`)."""

from __future__ import annotations

from texelbake.stages.context import StageContext


def run_ingest(ctx: StageContext, shard: int = 0) -> str:
    """Read and check the asset; record what was found (`ingest.json`)."""
    key = ctx.key("ingest", "ingest.json", ())
    if ctx.store.exists(key):
        return key
    asset = ctx.asset()
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
