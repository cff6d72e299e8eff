"""The BTF maps as float EXR files, written and read with OpenImageIO (seed 001, §3.3).

Four files next to each other, `<stem>_<part>.exr`:

* `eigen`   — eigen Laplacian BRDF map: an image L (levels) high and d (pairs) wide, one float
              channel per component, named `Y00 .. Y07, Cb00, Cb01, Cr00, Cr01` (FLOAT, or
              HALF when the maps' storage is float16; the LUT and pairs files are always FLOAT).
* `weights` — PCA weight map: every level's (h_k, w_k, C) weights packed into one image, level 0
              at (0, 0), levels >= 1 stacked in a column to its right (offsets in the metadata),
              same channel names.
* `lut`     — the direction look-up tables: an R x R image with channels `light` and `view`
              (indices into the distinct light / view directions, exact in float32 below 2^24).
* `pairs`   — per direction pair: `ix iy iz ox oy oz` (the pair's directions, float32) and
              `meanY meanCb meanCr` (the tabulated top-level mean, zero unless a channel's mean
              model is "table").

The eigen map's header holds a JSON string attribute `texelbake:btf` with the layout, the
component counts, the mean models and their parameters (JSON floats round-trip exactly) and the
notes. EXR channels come back sorted by name, so every read maps channels by name. Files are
written to a temporary name and renamed into place; the same maps write byte-identical files.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from texelbake.btf.compress import MEAN_MODELS, BTFMaps
from texelbake.btf.lut import DirectionLUT, build_lut
from texelbake.errors import AssetError
from texelbake.io.images import ImageInfo, read_pixels, write_pixels
from texelbake.model import SHADER_BTF  # noqa: F401  (re-exported: the BTF material's shader id)

FORMAT_VERSION = 1
META_KEY = "texelbake:btf"
PARTS = ("eigen", "weights", "lut", "pairs")


def channel_names(n_components: tuple[int, int, int]) -> list[str]:
    """['Y00', ..., 'Cb00', ..., 'Cr00', ...] in storage order."""
    return [f"{ch}{j:02d}" for ch, n in zip(("Y", "Cb", "Cr"), n_components, strict=True)
            for j in range(n)]


def _write_exr(path: Path, pixels: np.ndarray, names: list[str], meta: str | None = None,
               half: bool = False) -> None:
    attrs: dict[str, str] = {"compression": "zip"}
    if meta is not None:
        attrs[META_KEY] = meta
    write_pixels(path, np.asarray(pixels, dtype=np.float32), "half" if half else "float",
                 channel_names=names, attributes=attrs)


def read_float_pixels(path: str | Path) -> tuple[np.ndarray, ImageInfo]:
    """Any image OpenImageIO reads, as (h, w, c) float32 pixels and its `ImageInfo`;
    AssetError naming the file when it cannot be opened or read."""
    return read_pixels(path)


def _read_exr(path: Path, names: list[str]) -> tuple[np.ndarray, str | None]:
    pixels, info = read_float_pixels(path)
    have = list(info.channel_names)
    missing = [n for n in names if n not in have]
    if missing:
        raise AssetError(f"EXR lacks channels {missing} (has {have})", path=str(path))
    meta = info.attributes.get(META_KEY)
    return pixels[:, :, [have.index(n) for n in names]], meta


def _weight_layout(shapes: list[tuple[int, int]]) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """Canvas (height, width) and per-level (y, x) offsets of the packed weight map."""
    h0, w0 = shapes[0]
    offsets = [(0, 0)]
    y = 0
    for hk, _ in shapes[1:]:
        offsets.append((y, w0))
        y += hk
    width = w0 + (shapes[1][1] if len(shapes) > 1 else 0)
    return (max(h0, y), width), offsets


def write_btf_maps(maps: BTFMaps, folder: str | os.PathLike, stem: str = "btf") -> dict[str, Path]:
    """Write the four EXR files. folder : existing or new directory. returns : part -> path."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    names = channel_names(maps.n_components)
    shapes = [(int(w.shape[0]), int(w.shape[1])) for w in maps.weights]
    (ch, cw), offsets = _weight_layout(shapes)
    n_ch = len(names)
    canvas = np.zeros((ch, cw, n_ch), np.float32)
    for wmap, (y, x) in zip(maps.weights, offsets, strict=True):
        canvas[y:y + wmap.shape[0], x:x + wmap.shape[1]] = wmap
    meta = {
        "version": FORMAT_VERSION,
        "shader": SHADER_BTF,
        "n_components": list(maps.n_components),
        "levels": shapes,
        "weight_offsets": offsets,
        "num_pairs": maps.num_pairs,
        "mean_models": list(maps.mean_models),
        "mean_params": maps.mean_params.tolist(),
        "pyramid_filter": maps.pyramid_filter,
        "lut_resolution": maps.lut.resolution,
        "notes": list(maps.notes),
        "storage": maps.storage,
        "files": {p: f"{stem}_{p}.exr" for p in PARTS},
    }
    paths = {p: folder / f"{stem}_{p}.exr" for p in PARTS}
    half = maps.storage == "float16"
    _write_exr(paths["eigen"], maps.eigen, names, json.dumps(meta, sort_keys=True), half)
    _write_exr(paths["weights"], canvas, names, half=half)
    lut_px = np.stack([maps.lut.light_table, maps.lut.view_table], axis=-1).astype(np.float32)
    _write_exr(paths["lut"], lut_px, ["light", "view"])
    pairs = np.concatenate(
        [maps.dirs_i, maps.dirs_o, maps.mean_table.T], axis=1
    )[None]  # (1, d, 9)
    _write_exr(paths["pairs"], pairs, ["ix", "iy", "iz", "ox", "oy", "oz",
                                       "meanY", "meanCb", "meanCr"])
    return paths


def read_btf_maps(folder: str | os.PathLike, stem: str = "btf") -> BTFMaps:
    """Read the four EXR files written by `write_btf_maps` back into identical BTFMaps."""
    folder = Path(folder)
    eigen_path = folder / f"{stem}_eigen.exr"
    if not eigen_path.exists():
        raise AssetError("BTF eigen map not found", path=str(eigen_path))
    raw = read_float_pixels(eigen_path)[1].attributes.get(META_KEY)
    try:
        meta = json.loads(raw if isinstance(raw, str) else "")
        version = int(meta["version"])
    except (TypeError, ValueError, KeyError) as exc:
        raise AssetError(f"missing or bad '{META_KEY}' metadata ({exc})",
                         path=str(eigen_path)) from exc
    if version != FORMAT_VERSION:
        raise AssetError(f"BTF map format version {version}, expected {FORMAT_VERSION}",
                         path=str(eigen_path))
    n_comp = tuple(int(v) for v in meta["n_components"])
    models = tuple(meta["mean_models"])
    if len(n_comp) != 3 or any(m not in MEAN_MODELS for m in models):
        raise AssetError(f"bad n_components {n_comp} or mean_models {models}",
                         path=str(eigen_path))
    names = channel_names(n_comp)
    eigen, _ = _read_exr(eigen_path, names)
    canvas, _ = _read_exr(folder / f"{stem}_weights.exr", names)
    weights = tuple(
        np.ascontiguousarray(canvas[y:y + h, x:x + w])
        for (h, w), (y, x) in zip(meta["levels"], meta["weight_offsets"], strict=True)
    )
    lut_px, _ = _read_exr(folder / f"{stem}_lut.exr", ["light", "view"])
    pairs, _ = _read_exr(folder / f"{stem}_pairs.exr", ["ix", "iy", "iz", "ox", "oy", "oz",
                                                         "meanY", "meanCb", "meanCr"])
    pairs = pairs[0]  # (d, 9)
    dirs_i = np.ascontiguousarray(pairs[:, 0:3])
    dirs_o = np.ascontiguousarray(pairs[:, 3:6])
    derived = build_lut(dirs_i, dirs_o, resolution=1)  # light/view split and pair table
    lut = DirectionLUT(
        derived.light_dirs,
        derived.view_dirs,
        derived.pair_index,
        lut_px[:, :, 0].astype(np.int32),
        lut_px[:, :, 1].astype(np.int32),
    )
    if eigen.shape[1] != int(meta["num_pairs"]) or dirs_i.shape[0] != eigen.shape[1]:
        raise AssetError(
            f"eigen map has {eigen.shape[1]} pairs, pairs file {dirs_i.shape[0]}, metadata "
            f"{meta['num_pairs']}", path=str(eigen_path))
    return BTFMaps(
        eigen=np.ascontiguousarray(eigen),
        weights=weights,
        n_components=n_comp,
        mean_models=models,
        mean_params=np.asarray(meta["mean_params"], dtype=np.float64).reshape(3, 4),
        mean_table=np.ascontiguousarray(pairs[:, 6:9].T),
        dirs_i=dirs_i,
        dirs_o=dirs_o,
        lut=lut,
        pyramid_filter=str(meta["pyramid_filter"]),
        notes=tuple(meta["notes"]),
        storage=str(meta.get("storage", "float32")),
    )
