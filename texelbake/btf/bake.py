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

from texelbake.btf.compress import BTFMaps, BTFSettings, direction_step
from texelbake.btf.maps_io import PARTS, SHADER_BTF, write_btf_maps
from texelbake.btf.report import btf_report
from texelbake.errors import ShapeError
from texelbake.usd.shaderdefs import author_shader


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


def fill_uncovered(btf: np.ndarray, covered: np.ndarray) -> np.ndarray:
    """Pull-push fill of texels without data (atlas gutters), so the Laplacian pyramid does not
    see artificial edges at chart borders (zeros next to data are high-frequency energy the
    PCA would spend components on, for texels that are never rendered).

    Pull: 2 x 2 sums of (value * mask, mask) up to 1 x 1; push: each uncovered texel takes the
    mask-weighted average of the finest coarser level that has data. Covered texels are
    unchanged. btf : (d, h, w, 3); covered : (h, w) bool -> (d, h, w, 3) same dtype.
    """
    btf = np.asarray(btf)
    covered = np.asarray(covered, dtype=bool)
    if covered.shape != btf.shape[1:3]:
        raise ShapeError(f"covered must be {btf.shape[1:3]}, got {covered.shape}")
    if covered.all() or not covered.any():
        return btf.copy()
    vals = [np.moveaxis(btf * covered[None, :, :, None], 0, 2)]  # (h, w, d, 3)
    masks = [covered.astype(btf.dtype)]
    while vals[-1].shape[0] > 1 or vals[-1].shape[1] > 1:  # pull: a handful of levels
        v, m = vals[-1], masks[-1]
        ph, pw = v.shape[0] % 2, v.shape[1] % 2
        v = np.pad(v, ((0, ph), (0, pw), (0, 0), (0, 0)))
        m = np.pad(m, ((0, ph), (0, pw)))
        vals.append(v[0::2, 0::2] + v[1::2, 0::2] + v[0::2, 1::2] + v[1::2, 1::2])
        masks.append(m[0::2, 0::2] + m[1::2, 0::2] + m[0::2, 1::2] + m[1::2, 1::2])
    filled = vals[-1] / masks[-1][:, :, None, None]
    for v, m in zip(reversed(vals[:-1]), reversed(masks[:-1]), strict=True):  # push
        up = filled[np.arange(v.shape[0]) // 2][:, np.arange(v.shape[1]) // 2]
        avg = v / np.maximum(m, 1e-30)[:, :, None, None]
        filled = np.where((m > 0)[:, :, None, None], avg, up)
    out = np.moveaxis(filled, 2, 0).astype(btf.dtype)
    out[:, covered] = btf[:, covered]  # exact, not v / 1
    return out


def bake_btf(
    btf: np.ndarray,
    dirs_i: np.ndarray,
    dirs_o: np.ndarray,
    out_dir: str | os.PathLike,
    settings: BTFSettings | None = None,
    *,
    stem: str = "btf",
    value_scale: float | None = None,
    covered: np.ndarray | None = None,
) -> tuple[BTFMaps, dict]:
    """Build the Laplacian BTF, write its EXR maps to `out_dir`, return (maps, report).

    btf : (d, h, w, 3) float32 linear RGB; dirs_i, dirs_o : (d, 3) unit, texel frame
    covered : optional (h, w) bool texels with data; the others are pull-push filled before
        the build and left out of the error statistics
    report : compression ratio, MSE per channel (avg/min/max), seconds per stage, plus
        "files": part -> file name relative to out_dir
    """
    if covered is not None:
        btf = fill_uncovered(btf, covered)
    maps, report = btf_report(btf, dirs_i, dirs_o, settings, value_scale=value_scale,
                              texel_mask=covered)
    paths = write_btf_maps(maps, out_dir, stem)
    report["files"] = {part: p.name for part, p in paths.items()}
    return maps, report


#: a lobe narrower (to half height) than this fraction of the direction step is flagged
NARROW_LOBE_FRACTION = 0.25


def lobe_half_width(material) -> float | None:
    """Half width at half maximum (radians, in the reflected direction) of a material's
    specular lobe, for the analytic families with a constant lobe parameter; None otherwise
    (Lambert: no lobe; textured roughness, cellular, MERL: not one width).

    phong (Lafortune's cos^e of the angle to the mirror direction): cos^e a = 1/2.
    preview (GGX, alpha = roughness^2 as `brdf.analytic.preview_surface`): D falls to half at
    tan^2 theta_h = alpha^2 (sqrt 2 - 1); the reflected direction turns by 2 theta_h."""
    from texelbake.brdf.analytic import PREVIEW_MIN_ROUGHNESS

    p = material.params
    if material.model == "phong" and "exponent" not in material.textures:
        e = float(p.get("exponent", 0.0))
        return float(np.arccos(0.5 ** (1.0 / e))) if e > 0 else None
    if material.model == "preview" and "roughness" not in material.textures:
        alpha = float(np.clip(p.get("roughness", 0.5), PREVIEW_MIN_ROUGHNESS, 1.0)) ** 2
        return float(2.0 * np.arctan(alpha * np.sqrt(np.sqrt(2.0) - 1.0)))
    return None


def narrow_lobes(materials, dirs_i: np.ndarray, dirs_o: np.ndarray) -> list[str]:
    """A warning per material whose specular lobe is narrower than the BTF's direction
    sampling resolves (half width < NARROW_LOBE_FRACTION x `direction_step`): its table holds
    the lobe averaged over a cell (btf_table "cell") or aliased (at "point"), so a
    look-up shows its highlights blurred and where they are not (measured on the bolt, GGX
    alpha 0.0225 on 64 x 64 directions: the btf image 5x gt's light, docs/decisions.md)."""
    step = direction_step(dirs_i, dirs_o)
    if step is None:
        return []
    out = []
    for m in materials:  # loop over the asset's few materials
        w = lobe_half_width(m)
        if w is not None and w < NARROW_LOBE_FRACTION * step:
            out.append(f"btf: material {m.path or '(default)'} has a specular lobe "
                       f"{np.degrees(w):.1f}° wide to half height, under a quarter of the BTF's "
                       f"direction step ({np.degrees(step):.1f}°): its highlights are averaged "
                       f"over the step and the btf mode shows them blurred and too bright; "
                       f"render cpm, or raise n_light_dirs and n_view_dirs")
    return out


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
    shader = author_shader(stage, f"{material_path}/LaplacianBTF", SHADER_BTF)
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
