"""`describe(asset)`: the report `texelbake inspect FILE` prints."""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.model import (
    PREVIEW_DEFAULTS,
    AssetModel,
    Material,
)


def _fmt_vec(v: Any) -> str:
    return "(" + ", ".join(f"{float(x):.4g}" for x in np.asarray(v).reshape(-1)) + ")"


def _param_summary(mat: Material) -> str:
    """`name=value` for a material's constants (for "preview", only those off the spec
    defaults; never the MERL table or file, shown separately)."""
    parts = []
    for key in sorted(mat.params):
        if key in ("table", "file"):
            continue
        value = mat.params[key]
        if mat.model == "preview" and key in PREVIEW_DEFAULTS and np.allclose(
                np.asarray(value, dtype=np.float64), np.asarray(PREVIEW_DEFAULTS[key], np.float64)):
            continue
        text = (_fmt_vec(value) if isinstance(value, np.ndarray)
                else f"{value:.4g}" if isinstance(value, float) else str(value))
        parts.append(f"{key}={text}")
    return ", ".join(parts)


def describe(asset: AssetModel) -> str:
    """The human-readable summary `texelbake inspect FILE` prints.

    asset : an AssetModel from `load_asset`
    returns : multi-line text: meshes with face counts, materials with model and textures,
        lights, cameras, bounds and bbox diagonal, deformation, dropped faces, warnings.
    """
    lines = [f"asset: {asset.source}",
             f"up axis: {asset.up_axis}, meters per unit: {asset.meters_per_unit:g}"]
    counts = np.bincount(asset.face_mesh, minlength=len(asset.mesh_paths))
    lines.append(f"meshes: {len(asset.mesh_paths)} ({asset.num_faces} triangles, "
                 f"{asset.points.shape[0]} points)")
    for path, n in zip(asset.mesh_paths, counts.tolist(), strict=True):
        lines.append(f"  {path}: {n} triangles")
    n_tex = len({t.path for m in asset.materials for t in m.textures.values()})
    lines.append(f"materials: {len(asset.materials)}")
    used = np.bincount(asset.face_material, minlength=len(asset.materials))
    for i, mat in enumerate(asset.materials):
        name = mat.path or "<default grey lambert>"
        lines.append(f"  {name}: {mat.model}, {int(used[i])} triangles")
        shown = _param_summary(mat)
        if shown:
            lines.append(f"    {shown}")
        for inp, tex in sorted(mat.textures.items()):
            h, w, c = tex.pixels.shape
            lines.append(f"    {inp} <- texture {tex.path} ({w}x{h}, {c} ch, "
                         f"{tex.source_color_space}, st={tex.st_primvar})")
        if mat.model == "merl":
            lines.append(f"    measured BRDF {mat.params.get('file', '')}")
    lines.append(f"textures: {n_tex}")
    lines.append(f"lights: {len(asset.lights)}")
    for light in asset.lights:
        where = (f"toward {_fmt_vec(light.direction)}" if light.kind == "distant"
                 else f"at {_fmt_vec(light.position)}, radius {light.radius:.4g}")
        lines.append(f"  {light.path}: {light.kind} {where}, "
                     f"scale {_fmt_vec(light.radiance_scale)}")
    lines.append(f"cameras: {len(asset.cameras)}")
    for cam in asset.cameras:
        lines.append(f"  {cam.path}: at {_fmt_vec(cam.world_from_camera[:3, 3])}, focal "
                     f"{cam.focal_length:.4g} mm")
    lo, hi = asset.bounds
    lines.append(f"bounds: min {_fmt_vec(lo)} max {_fmt_vec(hi)}")
    lines.append(f"bbox diagonal: {asset.bbox_diag:.6g}")
    uv_faces = int(asset.has_uvs.sum())
    lines.append(f"uvs: {uv_faces} of {asset.num_faces} triangles")
    if asset.has_deformation:
        lines.append(f"deformation: yes ({asset.time_codes.shape[0]} time codes, "
                     f"{asset.time_codes[0]:g} .. {asset.time_codes[-1]:g})")
    else:
        lines.append(f"deformation: no ({asset.time_codes.shape[0]} time codes)")
    lines.append(f"dropped faces: {asset.dropped_faces}")
    lines.append(f"warnings: {len(asset.warnings)}")
    lines.extend(f"  - {w}" for w in asset.warnings)
    return "\n".join(lines)
