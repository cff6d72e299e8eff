"""The real DCC for the `dcc` tests: Blender (the `bpy` module, pinned in scripts/dcc-venv.sh)
runs in its own virtualenv, always in a subprocess, never imported into the test process."""

from __future__ import annotations

import json
import os
import subprocess
from pathlib import Path

import pytest

from tests.helpers.service import backend_missing

ROOT = Path(__file__).resolve().parents[2]
VENV_SCRIPT = ROOT / "scripts" / "dcc-venv.sh"
IMPORT_RENDER = ROOT / "tests" / "blender" / "import_render.py"
#: where the renders are kept besides the test's tmp folder, when set (a folder)
ARTIFACTS_ENV = "TEXELBAKE_TEST_ARTIFACTS"


def bpy_python() -> Path:
    """The Python of the bpy virtualenv that `scripts/dcc-venv.sh` made (`make setup` and
    `.ci/run` make it). Skips when it is missing (fails under CI: `backend_missing`)."""
    venv = os.environ.get("TEXELBAKE_DCC_VENV") or str(
        Path.home() / ".cache" / "texelbake" / "dcc-venv-bpy5.0.1")
    exe = Path(venv) / "bin" / "python"
    if not (Path(venv) / ".installed").exists() or not exe.exists():
        backend_missing(f"no bpy virtualenv at {venv}: run scripts/dcc-venv.sh")
    return exe


def run_blender(script: Path | str, *args: str, timeout: float = 600.0) -> dict:
    """Run a Python script inside Blender (headless bpy) with `args` after `--`; the script
    prints one JSON object on its last stdout line, which is returned."""
    exe = bpy_python()
    proc = subprocess.run([str(exe), str(script), "--", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=str(ROOT))
    if proc.returncode != 0:
        pytest.fail(f"Blender script {script} failed ({proc.returncode}):\n"
                    f"{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}", pytrace=False)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if not lines:
        pytest.fail(f"Blender script {script} printed no JSON:\n{proc.stdout[-3000:]}",
                    pytrace=False)
    return json.loads(lines[-1])


def import_and_render(files: dict[str, Path], out_dir: Path, *, frame=None,
                      resolution: int = 160, samples: int = 32, timeout: float = 600.0,
                      diag_px: float | None = None,
                      options: dict[str, dict] | None = None,
                      scene_frames: dict[str, int] | None = None,
                      keep: dict[str, tuple[str, ...]] | None = None,
                      seeds: dict[str, int] | None = None) -> dict:
    """Import each of `files` ({name: USD path}) into an empty Blender scene with the USD
    importer at its defaults (or `options[name]`, keywords of `bpy.ops.wm.usd_import` such as
    {"import_subdivision": True}) and render it (tests/blender/import_render.py), at the scene
    frame `scene_frames[name]` if given (else the animation's start), from one camera
    and sun, placed from `frame` ([lo, hi] in Blender's world space) or, when None, from the
    first file's imported bounds; with `diag_px` the camera is where the frame box's diagonal
    covers that many pixels (a LOD's switch distance). `keep[name]` keeps what the file carries
    instead: "lights" (its lights, its DomeLight as the world; Cycles direct light only, as
    texelbake's gt) and/or "camera" (its first camera). Returns {"frame", "files": {name: what
    Blender made, "png"}}. `seeds[name]` is Cycles' seed for that file (default 0): one file
    under two names and seeds measures the render's noise.
    """
    out_dir.mkdir(parents=True, exist_ok=True)
    spec = out_dir / "dcc_spec.json"
    opts, kept = options or {}, keep or {}
    frames = scene_frames or {}
    bad = {k: v for k, v in kept.items() if set(v) - {"lights", "camera"}}
    if bad:
        raise ValueError(f"keep takes 'lights' and 'camera', got {bad}")
    spec.write_text(json.dumps({"files": [{"name": k, "path": str(v), "options": opts.get(k, {}),
                                           "keep": list(kept.get(k, ())),
                                           **({"scene_frame": frames[k]} if k in frames else {}),
                                           **({"seed": int(seeds[k])} if seeds and k in seeds
                                              else {})}
                                          for k, v in files.items()],
                                "out_dir": str(out_dir), "frame": frame,
                                "resolution": resolution, "samples": samples,
                                "diag_px": diag_px}))
    got = run_blender(IMPORT_RENDER, str(spec), timeout=timeout)
    return {"frame": got["frame"], "files": {f["name"]: f for f in got["files"]}}


def compare_renders(reference_png: Path | str, png: Path | str) -> dict[str, float]:
    """Object-pixel mean absolute difference and silhouette IoU of two RGBA renders of one view
    (8-bit sRGB as displayed, alpha = coverage, film transparent).

    - `mad`: |a - b| averaged over RGB and over the object's pixels, both images composited
      over black, in display values [0, 1]; the object's pixels are `metrics.object_mask` of
      the two alphas (their union, dilated by one pixel), as every render figure of the
      project, so a part one image has and the other lacks counts with its full colour.
    - `iou`: |A & B| / |A | B| of the silhouettes A, B = alpha >= 0.5.
    """
    import numpy as np

    from texelbake.io.images import read_pixels
    from texelbake.render.metrics import object_mask

    ref = read_pixels(reference_png)[0].astype(np.float64)
    img = read_pixels(png)[0].astype(np.float64)
    if ref.shape != img.shape or ref.shape[2] != 4:
        raise ValueError(f"renders must be RGBA of one size: {ref.shape} vs {img.shape}")
    a_ref, a_img = ref[..., 3], img[..., 3]
    mask = object_mask(a_ref, a_img)
    # OpenImageIO hands PNG pixels with associated alpha: colour over black already
    diff = np.abs(img[..., :3] - ref[..., :3]).mean(axis=2)
    sil_ref, sil_img = a_ref >= 0.5, a_img >= 0.5
    union = int(np.logical_or(sil_ref, sil_img).sum())
    inter = int(np.logical_and(sil_ref, sil_img).sum())
    return {"mad": float(diff[mask].mean()) if mask.any() else 0.0,
            "iou": inter / union if union else 1.0,
            "object_pixels": int(mask.sum())}


def write_render_png(path: Path, image, coverage) -> Path:
    """A texelbake render as Blender writes its transparent film: 8-bit sRGB RGBA, the colour
    straight (divided by the coverage), alpha = coverage; `compare_renders` reads both alike.

    image : (h, w, 3) linear, averaged over the pixel's samples with misses black (colour
    over black); coverage : (h, w) fraction of the pixel's samples that met the object
    """
    import numpy as np

    from texelbake.io.images import linear_to_srgb, write_pixels

    cov = np.asarray(coverage, dtype=np.float64)
    rgb = np.asarray(image, dtype=np.float64) / np.maximum(cov, 1e-12)[..., None]
    rgba = np.concatenate([linear_to_srgb(rgb), np.clip(cov, 0.0, 1.0)[..., None]], axis=2)
    return write_pixels(path, np.round(rgba * 255.0).astype(np.uint8), "uint8")


def side_by_side(pngs: list[Path], out: Path) -> Path:
    """One PNG of the renders in a row over a grey background, for a person to look at."""
    import numpy as np

    from texelbake.io.images import read_pixels, write_pixels

    tiles = []
    for p in pngs:
        px = read_pixels(p)[0].astype(np.float64)
        tiles.append(px[..., :3] + 0.2 * (1.0 - px[..., 3:]))  # associated alpha
    row = np.concatenate(tiles, axis=1)
    return write_pixels(out, np.round(np.clip(row, 0, 1) * 255).astype(np.uint8), "uint8")


def without_twin_triangles(src: Path, dest: Path) -> tuple[Path, int]:
    """The asset with its coplanar overlapping twin triangles removed, for Blender's reference.

    A twin is a triangle that shares an edge with another, lies in its plane and on the same
    side of that edge (the two overlap). Cycles keeps a ray from re-hitting the triangle it
    leaves but not its twin, so a shadow or bounce ray from one stops on the other at distance
    ~0 and the overlap renders black (or, without shadows, too bright): BoxAnimated's every
    quad is three such triangles. Keeping, in face order, each triangle that overlaps no kept
    one leaves the covered surface as it was. Returns (`src`, 0) when no all-triangle mesh has
    a twin, else (`dest`, the number removed): the flattened stage with those meshes cut to
    the kept faces (`_keep_faces`), the twins found at the stage's earliest time."""
    import numpy as np
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(src))
    flat = Usd.Stage.Open(stage.Flatten())
    removed = 0
    for prim in flat.Traverse():
        if not prim.IsA(UsdGeom.Mesh):
            continue
        mesh = UsdGeom.Mesh(prim)
        counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get() or [], dtype=np.int64)
        if not counts.size or np.any(counts != 3):
            continue
        tri = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64).reshape(-1, 3)
        pts = np.asarray(mesh.GetPointsAttr().Get(Usd.TimeCode.EarliestTime()), dtype=np.float64)
        nrm = np.cross(pts[tri[:, 1]] - pts[tri[:, 0]], pts[tri[:, 2]] - pts[tri[:, 0]])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        by_edge: dict[tuple[int, int], list[int]] = {}
        kept: list[int] = []
        for f, t in enumerate(tri.tolist()):  # a loop over the asset's triangles
            twin = False
            for a, b, c in ((t[0], t[1], t[2]), (t[1], t[2], t[0]), (t[2], t[0], t[1])):
                edge = (min(a, b), max(a, b))
                for g in by_edge.get(edge, ()):
                    if abs(float(nrm[f] @ nrm[g])) < 0.999:
                        continue
                    other = next(v for v in tri[g].tolist() if v not in edge)
                    side = np.cross(pts[b] - pts[a], pts[c] - pts[a]) @ nrm[f]
                    if side * (np.cross(pts[b] - pts[a], pts[other] - pts[a]) @ nrm[f]) > 0:
                        twin = True
            if twin:
                continue
            kept.append(f)
            for a, b in ((t[0], t[1]), (t[1], t[2]), (t[2], t[0])):
                by_edge.setdefault((min(a, b), max(a, b)), []).append(f)
        if len(kept) < len(tri):
            removed += len(tri) - len(kept)
            _keep_faces(mesh, np.asarray(kept, dtype=np.int64), len(tri))
    if not removed:
        return src, 0
    dest.parent.mkdir(parents=True, exist_ok=True)
    flat.GetRootLayer().Export(str(dest))
    return dest, removed


def _keep_faces(mesh, kept, n_faces: int) -> None:
    """Cut an all-triangle UsdGeom.Mesh to its faces `kept` ((k,) int64, ascending): the
    topology, per-face (uniform) and per-corner (faceVarying) primvars and normals, their
    indices where indexed, and GeomSubsets' face indices."""
    import numpy as np
    from pxr import UsdGeom, Vt

    corners = (kept[:, None] * 3 + np.arange(3)).ravel()  # (3 k,) the kept corners
    tri = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(), dtype=np.int64)
    mesh.GetFaceVertexCountsAttr().Set(Vt.IntArray([3] * len(kept)))
    mesh.GetFaceVertexIndicesAttr().Set(Vt.IntArray(tri[corners].tolist()))
    rows = {UsdGeom.Tokens.uniform: kept, UsdGeom.Tokens.faceVarying: corners}
    for pv in UsdGeom.PrimvarsAPI(mesh).GetPrimvars():
        sel = rows.get(pv.GetInterpolation())
        if sel is None:
            continue
        if pv.IsIndexed():
            pv.SetIndices(Vt.IntArray(np.asarray(pv.GetIndices())[sel].tolist()))
        else:
            attr = pv.GetAttr()
            values = attr.Get()
            attr.Set(type(values).FromNumpy(np.ascontiguousarray(np.asarray(values)[sel])))
    normals = mesh.GetNormalsAttr()
    sel = rows.get(mesh.GetNormalsInterpolation())
    if normals.HasAuthoredValue() and sel is not None:
        normals.Set(Vt.Vec3fArray.FromNumpy(
            np.ascontiguousarray(np.asarray(normals.Get(), dtype=np.float32)[sel])))
    new_index = np.full(n_faces, -1, dtype=np.int64)
    new_index[kept] = np.arange(len(kept))
    for subset in UsdGeom.Subset.GetAllGeomSubsets(mesh):
        faces = new_index[np.asarray(subset.GetIndicesAttr().Get(), dtype=np.int64)]
        subset.GetIndicesAttr().Set(Vt.IntArray(faces[faces >= 0].tolist()))


def keep_artifacts(paths: list[Path], subdir: str) -> Path | None:
    """Copy `paths` to $TEXELBAKE_TEST_ARTIFACTS/<subdir>/ when that variable is set."""
    import shutil

    root = os.environ.get(ARTIFACTS_ENV)
    if not root:
        return None
    dest = Path(root) / subdir
    dest.mkdir(parents=True, exist_ok=True)
    for p in paths:
        shutil.copyfile(p, dest / Path(p).name)
    return dest


__all__ = ["ARTIFACTS_ENV", "bpy_python", "compare_renders", "import_and_render",
           "keep_artifacts", "run_blender", "side_by_side", "without_twin_triangles",
           "write_render_png"]
