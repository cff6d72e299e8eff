"""The geometry stage's science in one call (DESIGN.md "Geometry"): the LOD chain (each LOD
within its error bound at its switch size, `geometry.lodchain`, or the atlas-sized QEM/wrap
hierarchy), enclosing M_org's outline, the UV atlas on LOD1 or on an atlas-sized M_T, dense
samples on M_org, their texel assignment and the texel frames of every mip level."""

from __future__ import annotations

import json
import math

import numpy as np

from schemas.settings import BakeSettings
from texelbake.errors import StageError
from texelbake.geometry.atlas import build_atlas, map_into_atlas
from texelbake.geometry.density import face_density
from texelbake.geometry.hierarchy import enclose, n_parts, needs_wrap, simplify_hierarchy
from texelbake.geometry.lodchain import build_lod_chain, hausdorff
from texelbake.geometry.mesh import (
    Mesh,
    bbox_diagonal,
    compact,
    face_normals,
    triangle_areas,
    weld,
)
from texelbake.geometry.normal_input import NormalInput
from texelbake.geometry.raycast import CutoutTest, RayCaster
from texelbake.geometry.sampling import SurfaceSampler, surface_sampler
from texelbake.geometry.texel_frames import FrameSums
from texelbake.geometry.texels import assign_rows, morton, uv_to_texel
from texelbake.io.spool import FileSpool, MemorySpool
from texelbake.model import AssetModel


def build_geometry(asset: AssetModel, settings: BakeSettings, caster: RayCaster,
                   n_levels: int, spool: MemorySpool | FileSpool | None = None,
                   normal_input: NormalInput | None = None) -> dict[str, np.ndarray]:
    """The geometry stage's arrays: the LOD meshes, the atlas mesh M_T (the CPM's domain),
    dense samples on M_org with their texel (row, col) at the finest level, and the texel
    frames of every mip level.

    LODs (settings.lod_mode): 'error' sizes each LOD by its geometric error bound at its
    switch size (`geometry.lodchain`); the atlas is built on LOD1 when its charts fit one
    N x N page, else on the atlas-capped M1 of the 'atlas' mode, into which every LOD is mapped
    by closest point. 'atlas': M1 capped by the atlas is LOD1 and M_T.

    asset : M_org; caster : a ray caster over M_org (the bent-normal rule on wraps);
    n_levels : mip levels (log2 N + 1). returns : sample_* (m, ...) arrays, m1_* (M_T with
    corner uvs), lod{i}_* (LOD i: vertices, faces, corner_uvs, one_chart), lod_exact (LOD1 is
    M_T), lod_report (JSON), frames_L{l} (N_l^2, 3, 3) and frames_valid_L{l}, and the samples'
    Z-order index sample_zorder (m,) with texel_zoffsets (N^2 + 1,) (`_zorder_spooled`).
    normal_input : the materials' normal maps on M_org (`geometry.normal_input`), decoded
        into the samples' shading normals; None: the interpolated corner normals.
    spool : where the sample_* arrays are made, a chunk of samples at a time
    (`geometry_chunk`): a `FileSpool` keeps them on disk (the stage: memory bounded by
    settings.worker_memory_mb whatever the atlas size), None or a `MemorySpool` in memory.
    The arrays do not depend on the spool or the chunk.
    """
    s = settings
    n = s.atlas_resolution
    spool = MemorySpool() if spool is None else spool
    sampler = surface_sampler(
        asset.points, asset.faces, n * n * s.samples_per_texel, s.seed,
        corner_normals=asset.corner_normals, corner_uvs=asset.corner_uvs,
        face_material=asset.face_material, face_density=sample_density(asset, s),
        normal_input=normal_input,
    )
    chunk = geometry_chunk(s)
    probes = _spool_samples(sampler, asset, spool, chunk, (200_000, 20_000), caster.cutout)
    probe = probes[200_000]
    atlas = None
    wrap_offset = None
    lod_exact = True
    if s.lod_mode == "error":
        chain = build_lod_chain(
            asset.points, asset.faces, s.lod_switch_px[: s.mesh_levels], s.lod_error_px,
            enclose_meshes=s.enclose_meshes,
            probe=probes[20_000],
            seed=s.seed,
        )
        lods = [lv.mesh for lv in chain.levels]
        try:
            atlas = _build_atlas_fitting(lods[0], n)
        except StageError:
            atlas = None
        report = chain.report()
    if atlas is None:
        atlas, wrap_offset, meshes = _atlas_chain(asset, s, probe)
        if s.lod_mode == "atlas":
            lods = meshes
            report = _measured_report(asset, lods, s.seed)
        else:
            lod_exact = False
    report["atlas_mesh"] = {"triangles": int(atlas.mesh.num_faces), "is_lod1": bool(lod_exact),
                            "atlas_resolution": int(n),
                            "atlas_resolution_for_lod1": _resolution_needed(
                                sampler.total_area, bbox_diagonal(asset.points),
                                report["levels"][0].get("switch_px")),
                            "cpm_max_px": _cpm_max_px(sampler.total_area,
                                                      bbox_diagonal(asset.points), n)}
    if not lod_exact:
        report["notes"] = [*report.get("notes", []), (
            f"LOD1 ({lods[0].num_faces} triangles) does not fit a {n}x{n} atlas: the CPM "
            f"maps are built on a {atlas.mesh.num_faces}-triangle M_T and every LOD is mapped "
            f"into them by closest point")]
    # a wrap has a sheet on each side of thin parts: samples take the one they are seen
    # through (the bent-normal rule); QEM meshes keep the seed's closest point
    occluder = caster if wrap_offset is not None else None
    frame_sums = _assign_spooled(spool, sampler.m, atlas, n_levels, occluder, chunk)
    zoffsets = _zorder_spooled(spool, sampler.m, n, frame_sums[0].counts, chunk)
    out: dict[str, np.ndarray] = {
        **spool.arrays(),
        "texel_zoffsets": zoffsets,
        "m1_vertices": atlas.mesh.vertices,
        "m1_faces": atlas.mesh.faces,
        "m1_corner_uvs": atlas.corner_uvs,
        "m1_wrap_offset": np.array(wrap_offset or 0.0),
        "lod_exact": np.array(lod_exact),
        "lod_report": np.array(json.dumps(report, sort_keys=True)),
    }
    for level, sums in enumerate(frame_sums):
        out[f"frames_L{level}"], out[f"frames_valid_L{level}"] = sums.frames(atlas)
    for i, mesh in enumerate(lods, start=1):
        if i == 1 and lod_exact:
            mesh, uvs, one = atlas.mesh, atlas.corner_uvs, np.ones(atlas.mesh.num_faces, bool)
        else:
            uvs, one = map_into_atlas(mesh, atlas.mesh, atlas)
        out[f"lod{i}_vertices"] = mesh.vertices
        out[f"lod{i}_faces"] = mesh.faces
        out[f"lod{i}_corner_uvs"] = uvs
        out[f"lod{i}_one_chart"] = one
    return out


#: fraction of the page xatlas' charts cover (geometry.atlas: ~40-45 % measured)
CHART_COVER = 0.4


def sample_density(asset: AssetModel, s: BakeSettings) -> np.ndarray | None:
    """Each face's sample density relative to samples_per_texel (`geometry.density`), None
    for settings.sample_density 'area' and where no face is simple (the seed's samples, bit
    for bit). A finest texel's area on the surface is the surface's over the N² texels at
    CHART_COVER of the page."""
    if s.sample_density == "area":
        return None
    area = float(triangle_areas(asset.points, asset.faces).sum())
    density = face_density(asset, area / (s.atlas_resolution ** 2 * CHART_COVER))
    return None if bool((density == 1.0).all()) else density


#: the geometry stage's working bytes per sample in a chunk (the sample's attributes, the
#: closest-point and bent-normal temporaries of `assign_rows`, the frame sums' gathers)
GEOMETRY_BYTES_PER_SAMPLE = 1024


def geometry_chunk(s: BakeSettings) -> int:
    """Samples the geometry stage takes at a time under settings.worker_memory_mb."""
    return int(np.clip(int(s.worker_memory_mb) * 2**20 // 4 // GEOMETRY_BYTES_PER_SAMPLE,
                       1 << 14, 1 << 22))


#: the per-sample arrays of the geometry artifact, written by the first two passes below
_SAMPLE_ARRAYS = {
    "sample_pos": (np.float64, (3,)), "sample_nrm": (np.float64, (3,)),
    "sample_gnrm": (np.float64, (3,)), "sample_face": (np.int64, ()),
    "sample_uv": (np.float64, (2,)), "sample_mat": (np.int32, ()),
    "sample_area": (np.float64, ()),
}
_ASSIGN_ARRAYS = {
    "sample_row": (np.int64, ()), "sample_col": (np.int64, ()),
    "sample_atlas_uv": (np.float64, (2,)), "sample_m1_prim": (np.int64, ()),
}


def _spool_samples(sampler: SurfaceSampler, asset: AssetModel, spool, chunk: int,
                   probe_sizes: tuple[int, ...], cutout: CutoutTest | None = None
                   ) -> dict[int, np.ndarray]:
    """First pass: the samples into the spool, a chunk at a time; returns, per size p, every
    (m // p)-th sample position (the probes the LOD chain and the atlas search measure on), or,
    when the sampler's density varies over the faces, the sample in which each multiple of
    1/p of the cumulative area falls (area-uniform probes whatever the density).
    A sample on a cut-out (`cutout`) holds no surface: its area is 0, so it weighs nothing in
    the maps (R, a_vis, the baselines' sums)."""
    m = sampler.m
    for name, (dt, tail) in _SAMPLE_ARRAYS.items():
        spool.allocate(name, dt, (m, *tail))
    face_n = face_normals(asset.points, asset.faces)
    probes: dict[int, list[np.ndarray]] = {p: [] for p in probe_sizes}
    done = 0.0  # the samples' area before the chunk
    for a, smp in sampler.chunks(chunk):  # loop over chunks (memory bound)
        cum = None if sampler.uniform else done + np.cumsum(smp.area)
        for p in probe_sizes:
            if cum is None:  # global ids 0, st, 2 st, ... that fall in the chunk
                st = max(1, m // p)
                pick = smp.positions[(-a) % st::st].copy()  # not a view of the chunk
            else:  # the samples in which each multiple of the step falls
                step = sampler.total_area / min(p, m)
                k = np.floor(cum / step)
                pick = smp.positions[k > np.r_[np.floor(done / step), k[:-1]]]
            probes[p].append(pick)
        if cum is not None:
            done = float(cum[-1])
        area = smp.area
        if cutout is not None:
            area = np.where(cutout.cut_uv(smp.face, smp.uv), 0.0, area)
        for name, arr in (("sample_pos", smp.positions), ("sample_nrm", smp.normals),
                          ("sample_gnrm", face_n[smp.face]), ("sample_face", smp.face),
                          ("sample_uv", smp.uv), ("sample_mat", smp.material),
                          ("sample_area", area)):
            spool.write(name, a, arr)
    return {p: np.concatenate(v) if v else np.zeros((0, 3)) for p, v in probes.items()}


def _assign_spooled(spool, m: int, atlas, n_levels: int, occluder: RayCaster | None,
                    chunk: int) -> list[FrameSums]:
    """Second pass: each spooled sample's texel by `assign_rows` (seed 000 §4.1's closest
    point, with the own-side and bent-normal rules), written back to the spool, and the
    texel-frame sums of every level, a chunk at a time."""
    for name, (dt, tail) in _ASSIGN_ARRAYS.items():
        spool.allocate(name, dt, (m, *tail))
    n = int(atlas.resolution)
    m1_caster = RayCaster(atlas.mesh.vertices, atlas.mesh.faces)
    m1_normals = atlas.mesh.face_normals()
    sums = [FrameSums(atlas, n >> level) for level in range(n_levels)]
    for a in range(0, m, chunk):  # loop over chunks (memory bound)
        b = min(a + chunk, m)
        pts, gnrm = spool.read("sample_pos", a, b), spool.read("sample_gnrm", a, b)
        prim, _, uv, _ = assign_rows(pts, gnrm, atlas, m1_caster, occluder, m1_normals)
        row, col = uv_to_texel(uv, n)
        for name, arr in (("sample_row", row), ("sample_col", col), ("sample_atlas_uv", uv),
                          ("sample_m1_prim", prim)):
            spool.write(name, a, arr)
        nrm, area = spool.read("sample_nrm", a, b), spool.read("sample_area", a, b)
        for level, acc in enumerate(sums):  # a handful of mip levels
            acc.add(row >> level, col >> level, nrm, area, uv, prim)
    return sums


def _zorder_spooled(spool, m: int, n: int, counts: np.ndarray, chunk: int) -> np.ndarray:
    """Third pass: `sample_zorder` (m,), the sample ids ordered by the Z-order code of their
    finest texel (`morton`), ascending ids within a texel, and the offsets (n² + 1,) of each
    code's run in it: a texel of any level is one run, so a shard reads its tile's ids, not
    every sample's texel (at 1k² that scan was most of a shard's seconds and memory).

    A bucket sort bounded by the chunk: codes are cut into buckets of about `chunk` samples
    (a bucket is a range of codes, so its samples have one range of the result); each chunk's
    ids go to their buckets' next free places, then each bucket is sorted by code on its own.
    counts : (n²,) samples per finest texel, row-major."""
    rows, cols = np.divmod(np.arange(n * n, dtype=np.int64), n)
    per_code = np.zeros(n * n, np.int64)
    per_code[morton(rows, cols)] = counts
    zoff = np.r_[0, np.cumsum(per_code)].astype(np.int64)
    bucket_of_code = zoff[:-1] // max(chunk, 1)  # non-decreasing
    n_b = int(bucket_of_code[-1]) + 1 if n else 0
    bstart = zoff[np.searchsorted(bucket_of_code, np.arange(n_b + 1))]  # (n_b + 1,)
    cursor = bstart[:-1].copy()
    spool.allocate("_zorder_ids", np.int64, (m,))
    spool.allocate("_zorder_codes", np.int64, (m,))
    for a in range(0, m, chunk):  # loop over chunks (memory bound)
        b = min(a + chunk, m)
        code = morton(spool.read("sample_row", a, b), spool.read("sample_col", a, b))
        bk = bucket_of_code[code]
        order = np.argsort(bk, kind="stable")
        bks = bk[order]
        heads = np.flatnonzero(np.r_[True, bks[1:] != bks[:-1]])
        for h, e in zip(heads, np.r_[heads[1:], len(bks)], strict=True):  # chunk's buckets
            j = int(bks[h])
            spool.write("_zorder_ids", int(cursor[j]), a + order[h:e])
            spool.write("_zorder_codes", int(cursor[j]), code[order[h:e]])
            cursor[j] += e - h
    spool.allocate("sample_zorder", np.int64, (m,))
    for j in range(n_b):  # loop over buckets (each about a chunk)
        lo, hi = int(bstart[j]), int(bstart[j + 1])
        ids = spool.read("_zorder_ids", lo, hi)
        spool.write("sample_zorder", lo,
                    ids[np.argsort(spool.read("_zorder_codes", lo, hi), kind="stable")])
    spool.drop("_zorder_ids")
    spool.drop("_zorder_codes")
    return zoff


def _resolution_needed(area: float, diag: float, switch_px: float | None) -> int | None:
    """The atlas side at which a finest texel is at most one pixel where LOD1 switches in
    (its diagonal covers switch_px pixels): N >= switch_px sqrt(area / CHART_COVER) / diag,
    rounded up to a power of two. Applied by atlas_mode "lod1" (`lod1_atlas`), reported
    always."""
    if not switch_px or not diag > 0 or not area > 0:
        return None
    need = float(switch_px) * math.sqrt(area / CHART_COVER) / diag
    return int(2 ** math.ceil(math.log2(max(need, 2.0))))


def lod1_atlas(points: np.ndarray, faces: np.ndarray, switch_px: float, cap: int
               ) -> tuple[int, int | None]:
    """(n, need): the atlas side `need` at which a finest texel of M_org (points (v, 3),
    faces (f, 3)) is at most one pixel where LOD1 switches in (`_resolution_needed`, None for
    an empty or flat-to-a-point asset), and the side baked: need capped at `cap` (a power of
    two), the largest size the cap allows."""
    pts = np.asarray(points, dtype=np.float64)
    tri = pts[np.asarray(faces, dtype=np.int64)]  # (f, 3, 3)
    area = 0.5 * float(np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]),
                                      axis=1).sum()) if len(tri) else 0.0
    need = _resolution_needed(area, bbox_diagonal(pts) if len(pts) else 0.0, switch_px)
    if need is None:
        return int(cap), None
    return int(min(need, cap)), need


def _cpm_max_px(area: float, diag: float, n: int) -> float | None:
    """The inverse of `_resolution_needed`: the screen size (the diagonal in pixels) up to which
    a finest texel of an n x n atlas is at most one pixel. Larger on screen, texelbake's
    renderer shades from M_org (seed 000 §4.2: closer than the finest level, multi-sample the
    original), so the atlas decides where the CPM maps are used, not whether a view is right."""
    if not diag > 0 or not area > 0:
        return None
    return float(n) * diag / math.sqrt(area / CHART_COVER)


def lod_report(geo: dict[str, np.ndarray]) -> dict:
    """The geometry stage's LOD report (`build_geometry`): per LOD triangles, switch size,
    bound and two-sided Hausdorff distance to M_org, why the chain stopped, the atlas mesh."""
    return json.loads(str(geo["lod_report"])) if "lod_report" in geo else {}


def lod_meshes(geo: dict[str, np.ndarray]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(vertices, faces, corner_uvs) of LOD1, LOD2, ... as the geometry stage wrote them."""
    out = []
    i = 1
    while f"lod{i}_vertices" in geo:
        out.append((geo[f"lod{i}_vertices"], geo[f"lod{i}_faces"], geo[f"lod{i}_corner_uvs"]))
        i += 1
    return out


def _measured_report(asset: AssetModel, meshes: list[Mesh], seed: int) -> dict:
    """The 'atlas' mode's chain measured like the 'error' mode's (no switch sizes, no bound)."""
    welded, _, _ = weld(asset.points, asset.faces)
    org, _ = compact(Mesh(welded.vertices, welded.faces[~welded.degenerate_faces()]))
    diag = bbox_diagonal(org.vertices)
    levels = []
    for m in meshes:
        d_lo, d_ol = hausdorff(m, org, seed=seed)
        levels.append({"triangles": int(m.num_faces), "switch_px": None, "bound": None,
                       "bound_rel": None, "hausdorff": max(d_lo, d_ol),
                       "hausdorff_rel": max(d_lo, d_ol) / diag, "hausdorff_lod_to_org": d_lo,
                       "hausdorff_org_to_lod": d_ol, "within_bound": None, "method": "atlas",
                       "enclosed": None, "note": "sized by the atlas (lod_mode 'atlas')"})
    return {"diag": diag, "levels": levels, "stopped": "", "notes": []}


def _atlas_chain(asset: AssetModel, s: BakeSettings, probe: np.ndarray):
    """M1..Mn sized by the atlas (lod_mode 'atlas', and M_T when LOD1 does not fit): M1 is
    halved until its charts fit one N x N page. returns (atlas on M1, wrap offset, meshes)."""
    n = s.atlas_resolution
    target = m1_target_faces(asset.num_faces, s)
    wrap_offset = m1_wrap_offset(asset.points, asset.faces, target, s)
    levels = s.mesh_levels if s.lod_mode == "atlas" else 1
    for attempt in range(4):  # a few halvings of M1 until its charts fit one page
        meshes = simplify_hierarchy(
            asset.points, asset.faces, levels, s.simplify_ratio, target_faces=target,
            wrap_offset=wrap_offset,
        )
        if s.enclose_meshes:  # every M_i covers M_org's outline (geometry.hierarchy.enclose)
            meshes = [enclose(m, probe, tighten=wrap_offset is not None)[0] for m in meshes]
        try:
            return _build_atlas_fitting(meshes[0], n), wrap_offset, meshes
        except StageError:
            # xatlas makes about one chart per M1 face on assets of separate parts (the wall's
            # blocks); fewer faces means fewer charts. An explicit m1_faces is not second-guessed.
            if s.m1_faces or attempt == 3 or target // 2 < 8:
                raise
            target //= 2
    raise StageError("geometry: no atlas mesh fits")  # pragma: no cover - the loop returns


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
