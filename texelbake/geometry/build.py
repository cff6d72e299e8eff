"""The geometry stage's science in one call (DESIGN.md "Geometry"): the mesh hierarchy M1..Mn
(QEM, or a wrap for assets of many parts), enclosing M_org's outline, the UV atlas on M1 (M1
halved until its charts fit one page), dense samples on M_org, their texel assignment and the
texel frames of every mip level."""

from __future__ import annotations

import numpy as np

from schemas.settings import BakeSettings
from texelbake.errors import StageError
from texelbake.geometry.atlas import build_atlas, map_into_atlas
from texelbake.geometry.hierarchy import enclose, n_parts, needs_wrap, simplify_hierarchy
from texelbake.geometry.mesh import Mesh, bbox_diagonal
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import sample_surface
from texelbake.geometry.texels import assign_texels, texel_frames
from texelbake.model import AssetModel


def build_geometry(asset: AssetModel, settings: BakeSettings, caster: RayCaster,
                   n_levels: int) -> dict[str, np.ndarray]:
    """The geometry stage's arrays: M1..Mn, M1's atlas, dense samples on M_org with their
    texel (row, col) at the finest level, and the texel frames of every mip level.

    asset : M_org; caster : a ray caster over M_org (the bent-normal rule on wraps);
    n_levels : mip levels (log2 N + 1). returns : sample_* (m, ...) arrays, m1_* and m{i}_*
    meshes with corner uvs, frames_L{l} (N_l^2, 3, 3) and frames_valid_L{l}.
    """
    s = settings
    n = s.atlas_resolution
    target = m1_target_faces(asset.num_faces, s)
    samples = sample_surface(
        asset.points, asset.faces, n * n * s.samples_per_texel, s.seed,
        corner_normals=asset.corner_normals, corner_uvs=asset.corner_uvs,
        face_material=asset.face_material,
    )
    wrap_offset = m1_wrap_offset(asset.points, asset.faces, target, s)
    for attempt in range(4):  # a few halvings of M1 until its charts fit one page
        meshes = simplify_hierarchy(
            asset.points, asset.faces, s.mesh_levels, s.simplify_ratio, target_faces=target,
            wrap_offset=wrap_offset,
        )
        if s.enclose_meshes:  # every M_i covers M_org's outline (geometry.hierarchy.enclose)
            probe = samples.positions[:: max(1, samples.positions.shape[0] // 200_000)]
            meshes = [enclose(m, probe, tighten=wrap_offset is not None)[0] for m in meshes]
        try:
            atlas = _build_atlas_fitting(meshes[0], n)
            break
        except StageError:
            # xatlas makes about one chart per M1 face on assets of separate parts (the wall's
            # blocks); fewer faces means fewer charts. An explicit m1_faces is not second-guessed.
            if s.m1_faces or attempt == 3 or target // 2 < 8:
                raise
            target //= 2
    gnrm = asset.face_normals()[samples.face]
    # a wrap has a sheet on each side of thin parts: samples take the one they are seen
    # through (the bent-normal rule); QEM meshes keep the seed's closest point
    occluder = caster if wrap_offset is not None else None
    assignment = assign_texels(samples.positions, atlas.mesh, atlas, n_levels,
                               normals=gnrm, occluder=occluder)
    out: dict[str, np.ndarray] = {
        "sample_pos": samples.positions,
        "sample_nrm": samples.normals,
        "sample_gnrm": gnrm,
        "sample_face": samples.face,
        "sample_uv": samples.uv,
        "sample_mat": samples.material.astype(np.int32),
        "sample_area": samples.area,
        "sample_row": assignment.row,
        "sample_col": assignment.col,
        "sample_atlas_uv": assignment.uv,
        "sample_m1_prim": assignment.prim,
        "m1_vertices": atlas.mesh.vertices,
        "m1_faces": atlas.mesh.faces,
        "m1_corner_uvs": atlas.corner_uvs,
        "m1_wrap_offset": np.array(wrap_offset or 0.0),
    }
    for level in range(n_levels):
        frames, valid = texel_frames(
            assignment, samples.normals, samples.area, atlas.mesh, atlas, level
        )
        out[f"frames_L{level}"] = frames
        out[f"frames_valid_L{level}"] = valid
    for i, mesh in enumerate(meshes[1:], start=2):
        out[f"m{i}_vertices"] = mesh.vertices
        out[f"m{i}_faces"] = mesh.faces
        out[f"m{i}_corner_uvs"], out[f"m{i}_one_chart"] = map_into_atlas(mesh, atlas.mesh, atlas)
    return out


def m1_wrap_offset(points: np.ndarray, faces: np.ndarray, target: int,
                   settings: BakeSettings) -> float | None:
    """The offset of M1's wrap (`geometry.hierarchy.wrap`), None for the seed's QEM of M_org:
    settings.m1_method 'wrap', or 'auto' on an asset of many parts (`needs_wrap`). The
    offset is about a finest texel (bounding-box diagonal / N): detail below a texel lives
    in the maps, and parts closer than two texels merge into one sheet."""
    if settings.m1_method == "qem":
        return None
    if settings.m1_method == "auto" and not needs_wrap(n_parts(points, faces), target):
        return None
    return bbox_diagonal(points) / settings.atlas_resolution


def m1_target_faces(n_faces: int, settings: BakeSettings) -> int:
    """Faces of M1: settings.m1_faces, or simplify_ratio x the original but at most N^2 / 8
    (about eight finest texels per M1 triangle), so the atlas charts fit one N x N page with
    padding (a ridged cylinder keeps a chart per ridge until its ridges are simplified away)."""
    if settings.m1_faces:
        return int(settings.m1_faces)
    cap = max(8, settings.atlas_resolution ** 2 // 8)
    return int(min(max(8, round(settings.simplify_ratio * n_faces)), cap))


def _build_atlas_fitting(m1: Mesh, n: int):
    """The atlas of M1 with one texel of chart padding (bilinear look-ups stay inside a chart;
    the preview maps are dilated into the padding). Measured on the full cylinder's M1 at
    N = 32: padding 2 covers 100 texel centres and needs two pages, padding 1 covers 200."""
    return build_atlas(m1, n, padding_texels=1)
