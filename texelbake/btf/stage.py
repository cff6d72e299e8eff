"""Glue between the bake and the BTF stage: texel arrays -> BTF images, build + write + report,
and the USD shader that references the maps (DESIGN.md "The baked USD").

The CPM stage computes, per finest texel, f_r on the N_i x N_o training grid (Eq. 7 of seed 000)
as `fbar : (t, d, 3)` with flat texel ids `row * N + col`; `btf_from_texels` scatters these into
the `(d, N, N, 3)` BTF array the Laplacian stage takes (texels without data stay zero and are
reported). `bake_btf` is the one call a pipeline stage needs.
"""

from __future__ import annotations

import os

import numpy as np

from texelbake.btf.compress import BTFMaps, BTFSettings
from texelbake.btf.maps_io import PARTS, SHADER_BTF, write_btf_maps
from texelbake.btf.report import btf_report
from texelbake.errors import ShapeError


def btf_from_texels(
    fbar: np.ndarray, texel_ids: np.ndarray, resolution: int
) -> tuple[np.ndarray, np.ndarray]:
    """Scatter per-texel reflectance tables into BTF images.

    fbar : (t, d, 3) float32 f_r of texel t on the d direction pairs
    texel_ids : (t,) int64 flat finest-level ids, row * resolution + col (unique)
    resolution : N, the atlas side
    returns : (btf (d, N, N, 3) float32, covered (N, N) bool)
    """
    fbar = np.asarray(fbar, dtype=np.float32)
    ids = np.asarray(texel_ids, dtype=np.int64)
    n = int(resolution)
    if fbar.ndim != 3 or fbar.shape[2] != 3 or ids.shape != (fbar.shape[0],):
        raise ShapeError(f"fbar must be (t, d, 3) with texel_ids (t,); got {fbar.shape}, "
                         f"{ids.shape}")
    if n < 1 or (ids.size and (ids.min() < 0 or ids.max() >= n * n)):
        raise ShapeError(f"texel ids must lie in [0, {n * n}) for resolution {n}")
    if np.unique(ids).size != ids.size:
        raise ShapeError("texel_ids contain duplicates")
    d = fbar.shape[1]
    flat = np.zeros((n * n, d, 3), np.float32)
    flat[ids] = fbar
    covered = np.zeros(n * n, bool)
    covered[ids] = True
    btf = np.ascontiguousarray(flat.reshape(n, n, d, 3).transpose(2, 0, 1, 3))
    return btf, covered.reshape(n, n)


def bake_btf(
    btf: np.ndarray,
    dirs_i: np.ndarray,
    dirs_o: np.ndarray,
    out_dir: str | os.PathLike,
    settings: BTFSettings | None = None,
    *,
    stem: str = "btf",
    value_scale: float | None = None,
) -> tuple[BTFMaps, dict]:
    """Build the Laplacian BTF, write its EXR maps to `out_dir`, return (maps, report).

    btf : (d, h, w, 3) float32 linear RGB; dirs_i, dirs_o : (d, 3) unit, texel frame
    report : compression ratio, MSE per channel (avg/min/max), seconds per stage, plus
        "files": part -> file name relative to out_dir
    """
    maps, report = btf_report(btf, dirs_i, dirs_o, settings, value_scale=value_scale)
    paths = write_btf_maps(maps, out_dir, stem)
    report["files"] = {part: p.name for part, p in paths.items()}
    return maps, report


def author_btf_shader(stage, material_path: str, files: dict[str, str], maps: BTFMaps,
                      *, render_context: str = "texelbake_btf"):
    """Author texelbake's Laplacian BTF shader in a material and connect it on its own render
    context (USD viewers keep using the UsdPreviewSurface on the universal context).

    stage : Usd.Stage; material_path : an existing or new UsdShade.Material path
    files : part ("eigen", "weights", "lut", "pairs") -> asset path as it should be authored
        (relative to the layer, e.g. the `report["files"]` of `bake_btf`)
    returns : the UsdShade.Shader
    """
    from pxr import Gf, Sdf, UsdShade

    missing = [p for p in PARTS if p not in files]
    if missing:
        raise ShapeError(f"files lacks BTF parts {missing} (expected {list(PARTS)})")
    mat = UsdShade.Material.Define(stage, material_path)
    shader = UsdShade.Shader.Define(stage, f"{material_path}/LaplacianBTF")
    shader.CreateIdAttr(SHADER_BTF)
    for part in PARTS:
        shader.CreateInput(f"{part}Map", Sdf.ValueTypeNames.Asset).Set(Sdf.AssetPath(files[part]))
    shader.CreateInput("topLevel", Sdf.ValueTypeNames.Int).Set(int(maps.top_level))
    shader.CreateInput("numComponents", Sdf.ValueTypeNames.Int3).Set(Gf.Vec3i(*maps.n_components))
    shader.CreateInput("meanModels", Sdf.ValueTypeNames.TokenArray).Set(list(maps.mean_models))
    shader.CreateInput("resolution", Sdf.ValueTypeNames.Int2).Set(
        Gf.Vec2i(int(maps.shape[1]), int(maps.shape[0])))
    mat.CreateSurfaceOutput(render_context).ConnectToSource(
        shader.CreateOutput("surface", Sdf.ValueTypeNames.Token))
    return shader
