"""The export stage: the baked USD bundle (root layer, payload, maps) and report.json.

report.json holds what the bake computed, a function of the source and the settings only:
a rerun, a farm run and a run that survived faults write it byte for byte the same. What
varies from run to run (stage seconds, the cost model's estimate and ETA, the host, the
process, the date) goes to `run.json` (`write_run`), which is never part of the result
archive: a local bake writes it beside report.json, the farm beside the job's result zip.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from texelbake.cpm.assemble import assemble_level, fitted_shares
from texelbake.cpm.level import direction_sets, texel_ids
from texelbake.estimate.costmodel import atlas_trade
from texelbake.geometry.build import geometry_chunk, lod_meshes, lod_report
from texelbake.geometry.lodnormals import lod_corner_normals
from texelbake.io.atomic import atomic_json
from texelbake.io.chunks import chunk_ranges, sample_rows
from texelbake.stages.avis import avis_level_chunks, avis_rays, avis_tile_meta
from texelbake.stages.btf import export_btf
from texelbake.stages.context import StageContext
from texelbake.stages.cpm import cpm_levels
from texelbake.stages.fallback import fitted_inputs
from texelbake.stages.filtered import fallback_maps, filtered_levels, lod1_frames
from texelbake.stages.quality import quality_gate
from texelbake.stages.srf import export_srf
from texelbake.usd.baked import BakedAsset
from texelbake.usd.lodmesh import LodMesh
from texelbake.usd.package import copy_source
from texelbake.usd.write import write_baked_asset


def lod_animation(asset, meshes) -> tuple[str, list[str]]:
    """The LOD meshes follow M_org (`texelbake.deform.skinbind`): skin bindings transferred
    from a skinned asset (their points in bind space), else time samples of an animated one.
    The LOD vertices are taken as the payload will store them (float32), so that the renderer,
    which reads them back, deforms the same points. Returns the skeleton's path ("" when not
    bound) and the warnings of a skinned asset whose LODs could not be bound."""
    from texelbake.deform.skinbind import lod_bind_points, lod_skin, lod_time_samples

    warnings: list[str] = []
    if asset.skin is not None:
        bound = []
        for i, m in enumerate(meshes, start=1):
            v32 = m.vertices.astype(np.float32).astype(np.float64)
            idx, wgt = lod_skin(asset.skin, asset.points, asset.faces, v32)
            pts, valid = lod_bind_points(asset.skin, idx, wgt.astype(np.float64), v32)
            if not valid.all():
                warnings.append(
                    f"lod: UsdSkel skinning not transferred to the LOD meshes (LOD{i}: "
                    f"{int((~valid).sum())} vertices' blended rest transform is near-singular)"
                    "; they carry time samples of the skinned points instead")
                break
            bound.append({"indices": idx, "weights": wgt, "bind": np.eye(4), "points": pts,
                          "xform": asset.skin.placement})
        else:
            for m, skin in zip(meshes, bound, strict=True):
                m.skin = skin
            return asset.skin.skeleton, warnings
    if asset.has_deformation:
        for m in meshes:
            v32 = m.vertices.astype(np.float32).astype(np.float64)
            m.time_codes = np.asarray(asset.time_codes, dtype=np.float64)
            m.points_over_time = lod_time_samples(asset, v32)
    return "", warnings


def export_to(ctx: StageContext, out_dir: Path, *, plan=None, source: str = "copy") -> Path:
    """Write the baked USD bundle and report.json into out_dir (the export stage).
    source : "copy" (the source and its files under out_dir/source: the farm's downloadable
    result) or "reference" (the source referenced where it lies)."""
    if source not in ("copy", "reference"):
        from texelbake.errors import SettingsError

        raise SettingsError(f"field 'source': expected 'copy' or 'reference', got {source!r}")
    from texelbake.asset import check_asset_paths
    from texelbake.baselines.normal_maps import PreviewSums

    s = ctx.settings
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    geo = ctx.geometry()
    asset = ctx.asset()
    cpm_lv = cpm_levels(ctx)
    levels, level_reports = [], []
    avis_meta = avis_tile_meta(ctx)
    for lvl in range(ctx.n_levels):
        arrays, rep = assemble_level(geo, s.atlas_resolution, s.avis_keep_fraction, lvl, cpm_lv[lvl],
                                     avis_level_chunks(ctx, lvl, avis_meta), s.avis_selection)
        levels.append(arrays)
        level_reports.append(rep)
    dirs = direction_sets(s)
    # shading normals of each LOD's own surface for the tools that shade the LOD meshes
    # themselves (M_org's detail is in the normal maps, baked in these normals' frames)
    meshes = [LodMesh(v, f, uv, corner_normals=lod_corner_normals(
        v, f, asset.corner_normals, ctx.caster()))
              for v, f, uv in lod_meshes(geo)]
    # the normal map is in the tangent frames of the mesh that carries it, LOD1
    frames1, prim_of = lod1_frames(geo)
    preview = PreviewSums(s.atlas_resolution)
    for a, b in chunk_ranges(len(geo["sample_area"]), geometry_chunk(s)):  # memory bound
        r = sample_rows(geo, ("sample_row", "sample_col", "sample_area", "sample_nrm",
                              "sample_uv", "sample_mat"), a, b)
        preview.add(texel_ids(r, s.atlas_resolution, 0), r["sample_area"], r["sample_nrm"],
                    r["sample_uv"], r["sample_mat"], asset.materials, frames1, prim_of(a, b))
    albedo, normal, _ = preview.maps()
    extra_arrays = {}
    if not bool(geo["lod_exact"]):  # the CPM's atlas mesh M_T is not LOD1: the renderer needs it
        extra_arrays = {"atlas_vertices": geo["m1_vertices"], "atlas_faces": geo["m1_faces"],
                        "atlas_corner_uvs": geo["m1_corner_uvs"]}
    filtered = filtered_levels(ctx)  # the filtered baseline maps of every level
    fallback = fallback_maps(ctx, filtered)
    if s.fallback == "fitted":
        fallback = fitted_inputs(ctx, fallback)
    from texelbake.deform.impostor import impostor_params

    for m in meshes:  # seed 002 Table 1 on every vertex of M1..Mn
        m.impostor = impostor_params(m.vertices, m.faces, m.corner_uvs).as_arrays()
    skeleton, lod_warnings = lod_animation(asset, meshes)
    name = ctx.asset_path.stem
    skipped = list(plan.skipped) if plan is not None else []
    lods = lod_report(geo)
    report = {
        "texelbake_version": __import__("texelbake").__version__,
        "source": ctx.asset_path.name,
        "source_hash": ctx.asset_hash,
        "settings": s.model_dump(),
        "levels": level_reports,
        "samples": int(len(geo["sample_area"])),
        "rays": {"cpm": int(sum(r["rays"] for r in level_reports)), "avis": avis_rays(ctx, avis_meta)},
        "surface_area": float(geo["sample_area"].sum()),
        "lods": lods,
        # where the CPM maps apply, and what the atlas LOD1 asks for would cost (the
        # projection from this run's measured seconds is a run fact: `write_run`)
        "cpm_atlas": _without(atlas_trade(s, lods, fitted=fitted_shares(cpm_lv)),
                              "projected_seconds_for_lod1"),
        # how the LOD meshes follow M_org's animation (texelbake.deform.skinbind)
        "lod_animation": ("usdskel" if skeleton else "time_samples" if asset.has_deformation
                          else "static"),
        "skipped": [{"stage": a, "reason": b} for a, b in skipped],
        "fallback_levels": fallback["levels"],
        "fallback_resolution": fallback["resolution"],
        # paths only unselected variants name (never read) and textures missing from the asset
        "unreachable_paths": list(asset.unreachable_paths),
        "missing_paths": list(asset.missing_paths),
        "fallback": {"mode": s.fallback, **({"fit": fallback["fit"]} if "fit" in fallback
                                            else {})},
        "warnings": [f"asset: {w}" for w in dict.fromkeys(asset.warnings)] + [
            f"level {r['level']}: {r['avis']['texels_above_tolerance']} of "
            f"{r['avis']['ray_texels']} ray-traced texels have a compressed a_vis table more "
            f"than {r['avis']['tolerance']:.0%} (relative L2) from their uncompressed maps"
            for r in level_reports if r["avis"].get("texels_above_tolerance")] + lod_warnings,
    }
    l0 = level_reports[0]
    metadata = {
        "version": report["texelbake_version"],
        "source_hash": ctx.asset_hash,
        "settings": s.model_dump(),
        "materials": [m.path for m in asset.materials],
        "errors": {
            "snr_insample_db_mean": l0["snr_insample_db"].get("mean"),
            "snr_heldout_db_mean": l0["snr_heldout_db"].get("mean"),
            "snr_heldout_db_p5": l0["snr_heldout_db"].get("p5"),
            "avis_rel_error": l0["avis"]["rel_error"],
        },
    }
    baked = BakedAsset(
        name=name, levels=levels,
        arrays={"dirs_i": dirs["dirs_i"], "dirs_o": dirs["dirs_o"],
                "heldout_i": dirs["held_i"], "heldout_o": dirs["held_o"],
                "material_model": np.array(
                    [["lambert", "preview", "phong", "merl", "cellular"].index(m.model)
                     for m in asset.materials], np.int32), **extra_arrays},
        meshes=meshes, albedo=albedo, normal=normal, metadata=metadata,
        filtered=filtered, fallback=fallback, skeleton=skeleton,
    )
    author_extra = None
    if s.btf:
        author_extra = export_btf(ctx, out_dir, report)
    if s.srf:
        export_srf(ctx, out_dir, report)
    if source == "copy":
        source_copy = copy_source(
            ctx.asset_path, check_asset_paths(ctx.asset_path), out_dir / "source"
        )
    else:
        source_copy = ctx.asset_path
    root = write_baked_asset(out_dir, source_copy, baked, list(asset.mesh_paths),
                                     author_extra=author_extra)
    report["quality"] = quality_gate(report, s)
    atomic_json(out_dir / "report.json", report)
    return root


def _without(d: dict, key: str) -> dict:
    return {k: v for k, v in d.items() if k != key}


def run_facts(seconds: dict[str, float], cpm_atlas: dict,
              estimate: dict | None = None) -> dict:
    """What varies between two runs of the same bake (`write_run`): stage seconds and their
    sum, the projection of the atlas LOD1's cost from them (the report's `cpm_atlas`
    cost ratio, `estimate.costmodel.atlas_trade`, times the measured seconds), the cost
    model's prediction (`estimate`), the host, process and time that wrote it."""
    import datetime
    import os
    import socket

    total = float(sum(seconds.values()))
    ratio = cpm_atlas.get("cost_ratio")
    facts = {
        "stage_seconds": {k: round(v, 3) for k, v in seconds.items()},
        "total_seconds": round(total, 3),
        "cpm_atlas_projected_seconds_for_lod1": total * ratio if total and ratio else None,
        "host": socket.gethostname(),
        "pid": os.getpid(),
        "written_at": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    if estimate is not None:
        facts["estimate"] = estimate
    return facts


def write_run(path: Path, result_dir: Path, seconds: dict[str, float],
              estimate: dict | None = None, **extra) -> Path:
    """`run.json` at `path`: this run's facts (`run_facts`, and `extra`), documented as
    differing between runs; never a member of the result archive. result_dir : where
    `export_to` wrote report.json (its `cpm_atlas` projects the seconds)."""
    report = json.loads((Path(result_dir) / "report.json").read_text())
    atomic_json(Path(path), {**run_facts(seconds, report["cpm_atlas"], estimate), **extra})
    return Path(path)


def run_export(ctx: StageContext, shard: int = 0) -> str:
    """The farm's export: write the bundle under the store (`result/`) and return its key."""
    key = ctx.key("export", "result")
    out = ctx.store.path(key)
    if (out / "report.json").is_file():  # the same bake: only the gate's targets may differ

        report = json.loads((out / "report.json").read_text())
        report["quality"] = quality_gate(report, ctx.settings)
        atomic_json(out / "report.json", report)
        return key
    export_to(ctx, out)
    return key
