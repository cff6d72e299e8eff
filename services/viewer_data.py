"""What the dashboard's 3-D viewer and texel inspector read, extracted from a finished bake.

Run as a subprocess by the API (`python -m services.viewer_data BAKED_ROOT OUT_DIR`), as
`services.validate` is: pxr and the core stay out of the API process. Reads the baked USD with
`texelbake.usd.read.read_baked` (and the BTF maps with `read_btf_maps`) and writes into OUT_DIR
(atomically: a temporary folder renamed into place):

* `manifest.json` — atlas size, the LOD meshes (vertex counts, bounds), the texel arrays'
  layout, the a_vis polar grid, the BTF layout when the bake has BTF maps;
* `lod<i>.bin` — M_i unindexed, float32 per corner: position (3), atlas uv (2), then the
  face's tangent space (`normalmap.face_tangent_space`): normal (3), tangent (3), bitangent (3);
* `texels.json` — per finest texel (row-major, row 0 at v = 1): characteristic points, rank k,
  held-out and in-sample SNR (dB; null where undefined), valid;
* `avis.bin` — float32 (N*N, n_theta, n_phi): a_vis / texel area of every finest texel over a
  polar grid of view directions in its texel frame (`AvisTable.evaluate`, seed 000 §3.4);
* `frames.bin` — float32 (N*N, 3, 3) texel frames, rows (t, b, n): world -> texel frame;
* `albedo.png`, `normal.png` — the UsdPreviewSurface fallback maps (copies);
* with BTF maps (seed 001 §3.3): `btf_weights.bin` float32 (canvas_h, canvas_w, C) — every
  level's PCA weights packed as in `btf_weights.exr`; `btf_eigen.bin` float32 (L, d, C);
  `btf_lut.bin` float32 (R, R, 2) light/view nearest-direction tables; `btf_pair_index.bin`
  float32 (n_l, n_v); `btf_mean_table.bin` float32 (d, 3).

Prints one JSON object: `{"manifest": ...}` or `{"error": "..."}` (exit 1).
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

#: floats per corner of `lod<i>.bin`: position 3, atlas uv 2, face normal 3, tangent 3,
#: bitangent 3 (the normal map's tangent space, `texelbake.baselines.normal_maps.face_tangent_space`)
CORNER_FLOATS = 14
#: the a_vis polar grid: theta from the normal (cell centres over [0, 90) degrees), phi
AVIS_THETA = 9
AVIS_PHI = 24


def _f32(path: Path, arr: np.ndarray) -> list[int]:
    a = np.ascontiguousarray(np.asarray(arr, dtype="<f4"))
    path.write_bytes(a.tobytes())
    return list(a.shape)


def _finite_or_none(a: np.ndarray) -> list:
    return [None if not math.isfinite(float(v)) else round(float(v), 4) for v in a]


def polar_dirs(n_theta: int = AVIS_THETA, n_phi: int = AVIS_PHI) -> np.ndarray:
    """(n_theta, n_phi, 3) unit directions in a texel frame: cell centres of the polar grid."""
    th = (np.arange(n_theta) + 0.5) / n_theta * (np.pi / 2)
    ph = (np.arange(n_phi) + 0.5) / n_phi * (2 * np.pi)
    t, p = np.meshgrid(th, ph, indexing="ij")
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def extract(baked_root: Path, out: Path) -> dict:
    from texelbake.baselines.normal_maps import face_tangent_space
    from texelbake.cpm.avis.table import avis_table_from
    from texelbake.usd.read import read_baked

    baked = read_baked(baked_root)
    lvl = baked.levels[0]
    n_tex = int(lvl["texel_offsets"].shape[0] - 1)
    n = int(round(math.sqrt(n_tex)))
    lods = []
    for i, m in enumerate(baked.meshes):
        tri = m.vertices[m.faces]  # (f, 3, 3)
        tbn = face_tangent_space(m.vertices, m.faces, m.corner_uvs)  # rows (t, b, n)
        per_face = np.concatenate([tbn[:, 2], tbn[:, 0], tbn[:, 1]], axis=1)  # n, t, b
        corner = np.concatenate(
            [tri[:, :, :], m.corner_uvs, np.repeat(per_face[:, None], 3, axis=1)], axis=2
        )  # (f, 3, 14): position, uv, normal, tangent, bitangent
        _f32(out / f"lod{i + 1}.bin", corner.reshape(-1, CORNER_FLOATS))
        lo, hi = m.vertices.min(axis=0), m.vertices.max(axis=0)
        lods.append({"file": f"lod{i + 1}.bin", "faces": int(m.faces.shape[0]),
                     "vertices": int(m.faces.shape[0] * 3),
                     "bounds": [lo.tolist(), hi.tolist()]})  # fmt: skip
    points = np.diff(lvl["texel_offsets"]).astype(np.int64)
    texels = {
        "n": n,
        "points": points.tolist(),
        "k": lvl["texel_k"].astype(int).tolist(),
        "snr_heldout_db": _finite_or_none(lvl["texel_snr_heldout"]),
        "snr_insample_db": _finite_or_none(lvl["texel_snr_insample"]),
        "valid": lvl["texel_valid"].astype(bool).tolist(),
    }
    (out / "texels.json").write_text(json.dumps(texels))
    table = avis_table_from(lvl)
    dirs = polar_dirs().reshape(-1, 3)
    t_idx = np.repeat(np.arange(n_tex), dirs.shape[0])
    a, _ = table.evaluate(t_idx, np.tile(dirs, (n_tex, 1)))
    area = np.maximum(table.texel_area, 1e-30)
    avis = (a.reshape(n_tex, -1) / area[:, None]).reshape(n_tex, AVIS_THETA, AVIS_PHI)
    avis[table.texel_area <= 0] = 0.0
    _f32(out / "avis.bin", avis)
    _f32(out / "frames.bin", lvl["frames"])
    root = Path(baked.root_layer).parent
    for part in ("albedo", "normal"):
        shutil.copyfile(root / f"{baked.name}_{part}.png", out / f"{part}.png")
    manifest = {
        "name": baked.name,
        "atlas": n,
        "levels": len(baked.levels),
        "lods": lods,
        "avis": {
            "file": "avis.bin",
            "n_theta": AVIS_THETA,
            "n_phi": AVIS_PHI,
            "theta_max_deg": 90.0,
            "unit": "a_vis / texel area",
        },  # fmt: skip
        "frames": "frames.bin",
        "btf": _btf(root, out, n),
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _btf(folder: Path, out: Path, n: int) -> dict | None:
    if not (folder / "btf_eigen.exr").is_file():
        return None
    from texelbake.btf import read_btf_maps
    from texelbake.btf.color import RGB_FROM_YCBCR
    from texelbake.tol import TOL

    maps = read_btf_maps(folder, "btf")
    if tuple(maps.shape) != (n, n):
        raise ValueError(f"{folder}/btf_weights.exr: BTF map is {maps.shape}, atlas is {n}")
    shapes = [(int(w.shape[0]), int(w.shape[1])) for w in maps.weights]
    offsets = [(0, 0)]
    y = 0
    for hk, _ in shapes[1:]:  # the packing of btf_weights.exr (maps_io._weight_layout)
        offsets.append((y, shapes[0][1]))
        y += hk
    ch = max(shapes[0][0], y)
    cw = shapes[0][1] + (shapes[1][1] if len(shapes) > 1 else 0)
    c = sum(maps.n_components)
    canvas = np.zeros((ch, cw, c), np.float32)
    for w, (oy, ox) in zip(maps.weights, offsets, strict=True):
        canvas[oy : oy + w.shape[0], ox : ox + w.shape[1]] = w
    return {
        "n_components": list(maps.n_components),
        "channels": c,
        "top_level": maps.top_level,
        "levels": shapes,
        "weight_offsets": offsets,
        "weights": {"file": "btf_weights.bin", "shape": _f32(out / "btf_weights.bin", canvas)},
        "eigen": {"file": "btf_eigen.bin", "shape": _f32(out / "btf_eigen.bin", maps.eigen)},
        "lut": {"file": "btf_lut.bin", "shape": _f32(out / "btf_lut.bin", np.stack(
            [maps.lut.light_table, maps.lut.view_table], axis=-1))},
        "pair_index": {"file": "btf_pair_index.bin",
                       "shape": _f32(out / "btf_pair_index.bin", maps.lut.pair_index)},
        "mean_table": {"file": "btf_mean_table.bin",
                       "shape": _f32(out / "btf_mean_table.bin", maps.mean_table.T)},
        "num_pairs": maps.num_pairs,
        "mean_models": list(maps.mean_models),
        "mean_params": np.asarray(maps.mean_params, np.float64).tolist(),
        "rgb_from_ycbcr": RGB_FROM_YCBCR.tolist(),
        "grazing_cos": TOL.grazing_cos,
    }  # fmt: skip


def main(argv: list[str]) -> int:
    if len(argv) != 2:
        print(json.dumps({"error": "usage: viewer_data BAKED_ROOT OUT_DIR"}))
        return 2
    baked_root, out = Path(argv[0]), Path(argv[1])
    tmp = Path(tempfile.mkdtemp(prefix=".viewer-", dir=out.parent))
    try:
        manifest = extract(baked_root, tmp)
        if out.exists():  # another request finished first: keep its (identical) output
            shutil.rmtree(tmp)
        else:
            tmp.rename(out)
    except Exception as exc:  # noqa: BLE001 - reported to the API, which names the file
        shutil.rmtree(tmp, ignore_errors=True)
        print(json.dumps({"error": f"{type(exc).__name__}: {exc}"}))
        return 1
    print(json.dumps({"manifest": manifest}))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
