"""Stage bodies: pure functions from artifacts to artifacts (DESIGN.md "The data flow").

Each `run_*` takes a StageContext and a shard index, writes its output atomically under a
content-derived key and returns that key; when the key already exists it returns at once
("already there" is success), so a retried or duplicated task is harmless.

Per-texel randomness is seeded by (settings.seed, level, texel), never by shard, so the result
does not depend on how texels are sharded: the farm and the in-process bake write the same arrays.
"""

from __future__ import annotations

import functools
import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from schemas.settings import BakeSettings
from texelbake import avis as avis_mod
from texelbake import brdf as brdf_mod
from texelbake import cpm, directions
from texelbake.errors import StageError
from texelbake.frames import tangent_frames
from texelbake.geometry.atlas import build_atlas, map_into_atlas
from texelbake.geometry.hierarchy import enclose, n_parts, needs_wrap, simplify_hierarchy
from texelbake.geometry.mesh import Mesh, bbox_diagonal
from texelbake.geometry.raycast import RayCaster
from texelbake.geometry.sampling import sample_surface
from texelbake.geometry.texels import assign_texels, texel_frames
from texelbake.model import AssetModel
from texelbake.store import ArtifactStore, file_sha256
from texelbake.tol import TOL

#: settings that change no stage output (farm layout and optional downstream stages)
_LAYOUT_ONLY = {"shard_texels", "previews"}
_GEOMETRY_FIELDS = (
    "seed", "atlas_resolution", "mesh_levels", "simplify_ratio", "m1_faces", "samples_per_texel",
)
_TAG_LIGHT, _TAG_VIEW, _TAG_HELD_I, _TAG_HELD_O = 0x11, 0x22, 0x33, 0x44


# --------------------------------------------------------------------------- context


@dataclass(frozen=True)
class StageContext:
    """Where a bake's artifacts live and what they are derived from."""

    store: ArtifactStore
    asset_path: Path
    settings: BakeSettings
    asset_hash: str

    @classmethod
    def create(cls, workdir: Path, asset_path: Path, settings: BakeSettings) -> StageContext:
        asset_path = Path(asset_path).resolve()
        if not asset_path.is_file():
            raise StageError(f"asset file {asset_path} does not exist")
        return cls(ArtifactStore(Path(workdir) / "artifacts"), asset_path, settings,
                   _asset_digest(str(asset_path), asset_path.stat().st_mtime_ns))

    @property
    def n_levels(self) -> int:
        return int(self.settings.atlas_resolution).bit_length()  # log2 N + 1

    @property
    def tile_levels(self) -> int:
        """Levels 0..tile_levels-1 live inside one shard's tile."""
        return int(self.settings.shard_texels).bit_length()

    def key(self, stage: str, name: str, fields: tuple[str, ...] | None = None) -> str:
        if fields is None:
            fields = tuple(sorted(set(BakeSettings.model_fields) - _LAYOUT_ONLY))
        return f"{self.asset_hash[:16]}/{stage}-{self.settings.digest(*fields)}/{name}"

    def geometry_key(self) -> str:
        return self.key("geometry", "geometry.npz", _GEOMETRY_FIELDS)

    def asset(self) -> AssetModel:
        return _load_asset_cached(str(self.asset_path), self.asset_hash)

    def geometry(self) -> dict[str, np.ndarray]:
        return _read_cached(str(self.store.root), self.geometry_key())

    def caster(self) -> RayCaster:
        a = self.asset()
        return _caster_cached(self.asset_hash, a.points, a.faces)


@functools.lru_cache(maxsize=8)
def _asset_digest(path: str, mtime_ns: int) -> str:
    # The root layer's bytes plus every file it references (textures, sublayers): a texture
    # edit must change the key.
    h = hashlib.sha256(file_sha256(path).encode())
    from texelbake.scene import check_asset_paths

    for dep in sorted(check_asset_paths(path)):
        if Path(dep).resolve() != Path(path).resolve():
            h.update(file_sha256(dep).encode())
    return h.hexdigest()


@functools.lru_cache(maxsize=2)
def _load_asset_cached(path: str, digest: str) -> AssetModel:
    from texelbake.scene import load_asset

    return load_asset(path)


@functools.lru_cache(maxsize=4)
def _read_cached(root: str, key: str) -> dict[str, np.ndarray]:
    return ArtifactStore(root).read_arrays(key)


_CASTERS: dict[str, RayCaster] = {}


def _caster_cached(digest: str, points: np.ndarray, faces: np.ndarray) -> RayCaster:
    if digest not in _CASTERS:
        _CASTERS.clear()
        _CASTERS[digest] = RayCaster(points, faces)
    return _CASTERS[digest]


# --------------------------------------------------------------------------- ingest, geometry


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


def run_geometry(ctx: StageContext, shard: int = 0) -> str:
    """Mesh hierarchy, atlas on M1, dense samples on M_org, texel assignment and frames."""
    key = ctx.geometry_key()
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    asset = ctx.asset()
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
    occluder = ctx.caster() if wrap_offset is not None else None
    assignment = assign_texels(samples.positions, atlas.mesh, atlas, ctx.n_levels,
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
    for level in range(ctx.n_levels):
        frames, valid = texel_frames(
            assignment, samples.normals, samples.area, atlas.mesh, atlas, level
        )
        out[f"frames_L{level}"] = frames
        out[f"frames_valid_L{level}"] = valid
    for i, mesh in enumerate(meshes[1:], start=2):
        out[f"m{i}_vertices"] = mesh.vertices
        out[f"m{i}_faces"] = mesh.faces
        out[f"m{i}_corner_uvs"], out[f"m{i}_one_chart"] = map_into_atlas(mesh, atlas.mesh, atlas)
    return ctx.store.write_arrays(key, out)


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


# --------------------------------------------------------------------------- texel bookkeeping


def texel_ids(geo: dict[str, np.ndarray], n: int, level: int) -> np.ndarray:
    """(m,) int64 flat texel id of every sample at `level` (row * N_l + col)."""
    n_l = n >> level
    return (geo["sample_row"] >> level) * n_l + (geo["sample_col"] >> level)


def tile_texels(n: int, s: int, tile: int, level: int) -> np.ndarray:
    """Flat ids at `level` of the texels inside tile `tile` (tiles of s x s finest texels)."""
    tiles_per_row = n // s
    tr, tc = divmod(int(tile), tiles_per_row)
    side = s >> level
    n_l = n >> level
    rows = tr * side + np.arange(side)
    cols = tc * side + np.arange(side)
    return (rows[:, None] * n_l + cols[None, :]).ravel().astype(np.int64)


def direction_sets(settings: BakeSettings) -> dict[str, np.ndarray]:
    """The texel-frame direction sets of the bake: the N_i x N_o training grid and a held-out
    product grid of independent directions (16 x 16 by default: n_heldout pairs)."""
    s = settings
    n_h = max(1, int(round(np.sqrt(s.n_heldout)))) if s.n_heldout else 0
    return {
        "dirs_i": directions.hemisphere_directions(s.n_light_dirs, seed=s.seed * 1000 + _TAG_LIGHT),
        "dirs_o": directions.hemisphere_directions(s.n_view_dirs, seed=s.seed * 1000 + _TAG_VIEW),
        "held_i": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_I)[0],
        "held_o": directions.heldout_pairs(n_h, seed=s.seed * 1000 + _TAG_HELD_O)[1],
    }


@dataclass
class PointSet:
    """Candidate (or characteristic) points: samples of M_org with per-channel weights."""

    sample: np.ndarray  # (p,) int64 index into the geometry samples
    weight: np.ndarray  # (p, 3) float64 area-like weight per channel
    texel: np.ndarray  # (p,) int64 texel id (at the level being fitted)

    def take(self, idx: np.ndarray) -> PointSet:
        return PointSet(self.sample[idx], self.weight[idx], self.texel[idx])


def _visibility_cos(
    ctx: StageContext,
    geo: dict[str, np.ndarray],
    sample: np.ndarray,
    dirs_world: np.ndarray,
    cosine: str = "shading",
) -> np.ndarray:
    """V(x, w) (n . w)+ for samples x and per-sample world directions.

    sample : (p,) int64; dirs_world : (p, D, 3) float64
    cosine : "shading" — (n_s . w)+ with the interpolated shading normal, for light directions
        (irradiance, as the `gt` renderer shades); "geometric" — (n_g . w)+ with the triangle's
        normal, for view directions (projected area, Eq. 3, as avis.py defines a_vis), so that
        R's view factor and a_vis agree and a flat Lambertian texel is reproduced exactly.
    returns : (p, D) float64 — visibility by rays against M_org times the clamped cosine; zero
        below the geometric or the shading horizon.
    """
    p, n_dirs = dirs_world.shape[:2]
    if p == 0 or n_dirs == 0:
        return np.zeros((p, n_dirs))
    pos = geo["sample_pos"][sample]
    gn = geo["sample_gnrm"][sample]
    sn = geo["sample_nrm"][sample]
    cos_g = np.einsum("pk,pdk->pd", gn, dirs_world)  # (p, D)
    cos_s = np.einsum("pk,pdk->pd", sn, dirs_world)
    caster = ctx.caster()
    live = (cos_g > TOL.grazing_cos) & (cos_s > TOL.grazing_cos)
    pi, di = np.nonzero(live)
    origins = pos[pi] + (TOL.ray_offset * caster.bbox_diag) * gn[pi]
    occ = caster.occluded(origins, dirs_world[pi, di])
    out = np.zeros((p, n_dirs))
    cos = cos_s if cosine == "shading" else cos_g
    out[pi, di] = np.where(occ, 0.0, cos[pi, di])
    return out


def _world_dirs(frames: np.ndarray, texel: np.ndarray, dirs_local: np.ndarray) -> np.ndarray:
    """(p, D, 3) world directions of texel-frame `dirs_local` (D, 3) for points in `texel`."""
    return np.einsum("dk,pkl->pdl", dirs_local, frames[texel])


def _brdf_grid(
    ctx: StageContext,
    geo: dict[str, np.ndarray],
    sample: np.ndarray,
    wi_world: np.ndarray,
    wo_world: np.ndarray,
    live: np.ndarray,
) -> np.ndarray:
    """f_r(x_j, wi, wo) in each sample's own shading frame, on a product of direction sets.

    sample : (p,); wi_world : (p, A, 3); wo_world : (p, B, 3); live : (A, B, p) bool — entries
    whose visibility-cosine product is zero are not evaluated.
    returns : (A, B, p, 3) float64
    """
    asset = ctx.asset()
    frames = tangent_frames(geo["sample_nrm"][sample])  # (p, 3, 3)
    wi_loc = np.einsum("pkl,pal->apk", frames, wi_world)  # (A, p, 3)
    wo_loc = np.einsum("pkl,pbl->bpk", frames, wo_world)  # (B, p, 3)
    a_idx, b_idx, p_idx = np.nonzero(live)
    out = np.zeros(live.shape + (3,))
    if a_idx.size:
        out[a_idx, b_idx, p_idx] = brdf_mod.evaluate_by_face(
            asset.materials,
            geo["sample_mat"][sample][p_idx],
            wi_loc[a_idx, p_idx],
            wo_loc[b_idx, p_idx],
            geo["sample_uv"][sample],
            sample_index=p_idx,
        )
    return out


def _texel_seed(seed: int, level: int, texel: int) -> int:
    return int.from_bytes(
        hashlib.sha256(f"{seed}/{level}/{texel}".encode()).digest()[:4], "little"
    )


# --------------------------------------------------------------------------- characteristic points


def fit_level(
    ctx: StageContext,
    level: int,
    texels: np.ndarray,
    candidates: PointSet,
) -> dict[str, np.ndarray]:
    """Characteristic points of `texels` at `level` chosen among `candidates` (seed 000 §3.3).

    The reference of each texel is its candidates' summation term (Eq. 9 with the candidates'
    per-channel weights); a_vis(w_o) comes from *all* dense samples of the texel (Eq. 3 on the
    same visibility); held-out SNR compares against the brute-force Eq. 7 over all samples.
    returns : arrays for this level: texel (t,), offsets (t+1,), point sample ids (p,), point
        weights (p, 3) float32, k, c, snr_in, snr_ho (t,), mode (t,) int8, valid (t,) bool,
        and when settings.btf, fbar (t, d, 3) float32 (Eq. 7 on the training grid).
    """
    # Per-texel matrices are small (d x m, m ~ tens to hundreds): BLAS and torch thread pools
    # only add contention (measured on a loaded 2-core machine: a 1024 x 16 SVD takes 1.5 ms on
    # 1 torch thread and 78 ms on 2; a 4096 x 256 QR went from milliseconds to minutes with
    # multi-threaded OpenBLAS). Parallelism comes from shards / worker processes instead.
    torch.set_num_threads(1)
    caster = ctx.caster()
    rays0 = caster.rays_cast
    with threadpool_limits(limits=1):
        out = _fit_level(ctx, level, texels, candidates)
    out["rays"] = np.array([caster.rays_cast - rays0], np.int64)  # work done, for rays/s
    return out


def _fit_level(
    ctx: StageContext,
    level: int,
    texels: np.ndarray,
    candidates: PointSet,
) -> dict[str, np.ndarray]:
    s = ctx.settings
    geo = ctx.geometry()
    n = s.atlas_resolution
    dirs = direction_sets(s)
    frames = geo[f"frames_L{level}"]
    tex_of_sample = texel_ids(geo, n, level)
    # all dense samples of these texels (for a_vis and the held-out truth)
    in_set = np.isin(tex_of_sample, texels)
    samp_all = np.nonzero(in_set)[0]
    tex_all = tex_of_sample[samp_all]
    n_i, n_o = len(dirs["dirs_i"]), len(dirs["dirs_o"])
    n_hi = len(dirs["held_i"])
    # one batch of rays per direction set for the whole tile
    view_vc = _visibility_cos(
        ctx, geo, samp_all, _world_dirs(frames, tex_all, dirs["dirs_o"]), "geometric"
    )
    held_vc = np.concatenate([
        _visibility_cos(ctx, geo, samp_all, _world_dirs(frames, tex_all, dirs["held_i"])),
        _visibility_cos(
            ctx, geo, samp_all, _world_dirs(frames, tex_all, dirs["held_o"]), "geometric"
        ),
    ], axis=1)
    cand_light_vc = _visibility_cos(
        ctx, geo, candidates.sample, _world_dirs(frames, candidates.texel, dirs["dirs_i"])
    )
    # candidates are dense samples of these texels; samp_all is sorted (np.nonzero)
    cand_rows = np.searchsorted(samp_all, candidates.sample)
    cand_view_vc = view_vc[cand_rows]
    area_all = geo["sample_area"][samp_all]

    # group samples and candidates by texel (stable order)
    order_all = np.argsort(tex_all, kind="stable")
    order_cand = np.argsort(candidates.texel, kind="stable")
    bounds_all = np.searchsorted(tex_all[order_all], np.stack([texels, texels + 1]))
    bounds_cand = np.searchsorted(candidates.texel[order_cand], np.stack([texels, texels + 1]))

    out_pts: list[np.ndarray] = []
    out_w: list[np.ndarray] = []
    offsets = [0]
    stats = {k: np.zeros(len(texels)) for k in ("k", "c", "snr_in", "snr_ho")}
    mode = np.zeros(len(texels), np.int8)
    valid = np.zeros(len(texels), bool)
    fbar_all = np.zeros((len(texels), n_i * n_o, 3), np.float32) if s.btf else None
    for t, texel in enumerate(texels):  # one SVD/bisection per texel: inherent to the method
        rows_all = order_all[bounds_all[0, t]:bounds_all[1, t]]
        rows_c = order_cand[bounds_cand[0, t]:bounds_cand[1, t]]
        if rows_all.size == 0 or rows_c.size == 0:
            offsets.append(offsets[-1])
            stats["snr_in"][t] = stats["snr_ho"][t] = np.nan
            continue
        cset = candidates.take(rows_c)
        vi = cand_light_vc[rows_c]  # (m, n_i)
        vo = cand_view_vc[rows_c]  # (m, n_o)
        live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)  # (n_i, n_o, m)
        wi_w = _world_dirs(frames, cset.texel, dirs["dirs_i"])
        wo_w = _world_dirs(frames, cset.texel, dirs["dirs_o"])
        f = _brdf_grid(ctx, geo, cset.sample, wi_w, wo_w, live)  # (n_i, n_o, m, 3)
        R = (f * (vi.T[:, None, :, None] * vo.T[None, :, :, None])
             * cset.weight[None, None, :, :]).reshape(n_i * n_o, -1, 3)
        avis_o = view_vc[rows_all].T @ area_all[rows_all]  # (n_o,)
        avis_rows = np.tile(avis_o, n_i)
        texel_area = float(area_all[rows_all].sum())
        fit = cpm.fit_texel(
            R, avis_rows, psi=s.psi, eps_db=s.eps_db, c_max=s.c_max, n_trials=s.n_trials,
            weights=s.weights, colour=s.colour, decorrelation_threshold=s.decorrelation_threshold,
            seed=_texel_seed(s.seed, level, int(texel)), n_batch=s.n_batch, texel_area=texel_area,
        )
        # effective weight of a point: alpha times its candidate weight (Eq. 10 with dA folded in)
        w_eff = fit.weights.astype(np.float64) * cset.weight[fit.columns]
        out_pts.append(cset.sample[fit.columns])
        out_w.append(w_eff)
        offsets.append(offsets[-1] + len(fit.columns))
        stats["k"][t], stats["c"][t] = fit.k, fit.c
        stats["snr_in"][t] = fit.snr_db_insample
        mode[t] = 1 if fit.colour_mode == "per_channel" else 0
        valid[t] = fit.valid
        if fbar_all is not None:
            fbar, _ = cpm.filtered_reflectance(
                R.sum(axis=1), avis_rows, cpm.avis_floor(texel_area)
            )
            fbar_all[t] = fbar
        # held-out: brute force over all samples vs the characteristic points
        if n_hi and fit.valid:
            stats["snr_ho"][t] = _heldout_snr(
                ctx, geo, dirs, frames, int(texel), samp_all[rows_all], held_vc[rows_all],
                area_all[rows_all], cset.sample[fit.columns], w_eff,
                held_vc[np.searchsorted(samp_all, cset.sample[fit.columns])],
                texel_area,
            )
        else:
            stats["snr_ho"][t] = np.nan
    out = {
        "texel": texels.astype(np.int64),
        "offsets": np.asarray(offsets, np.int64),
        "point_sample": np.concatenate(out_pts) if out_pts else np.zeros(0, np.int64),
        "point_weight": (np.concatenate(out_w) if out_w else np.zeros((0, 3))).astype(np.float32),
        "k": stats["k"].astype(np.int32),
        "c": stats["c"].astype(np.int32),
        "snr_in": stats["snr_in"].astype(np.float32),
        "snr_ho": stats["snr_ho"].astype(np.float32),
        "mode": mode,
        "valid": valid,
    }
    if fbar_all is not None:
        out["fbar"] = fbar_all
    return out


def _heldout_snr(
    ctx, geo, dirs, frames, texel, samples, held_vc, area, pts, w_eff, pts_held_vc, texel_area
) -> float:
    """SNR (dB) of Eq. 7 on the held-out product grid: brute force over all `samples` of the
    texel (weights ΔA) against the characteristic points `pts` (weights w_eff)."""
    n_hi = len(dirs["held_i"])
    tex = np.full(len(samples), texel)
    wi_w = _world_dirs(frames, tex, dirs["held_i"])
    wo_w = _world_dirs(frames, tex, dirs["held_o"])
    vi, vo = held_vc[:, :n_hi], held_vc[:, n_hi:]
    live = (vi.T[:, None, :] > 0) & (vo.T[None, :, :] > 0)
    f = _brdf_grid(ctx, geo, samples, wi_w, wo_w, live)  # (h_i, h_o, m, 3)
    ref = np.einsum("abmc,am,bm,m->abc", f, vi.T, vo.T, area)
    # the characteristic points are samples too: reuse their rows of f
    pos = np.searchsorted(samples, pts)
    approx = np.einsum("abmc,am,bm,mc->abc", f[:, :, pos], pts_held_vc[:, :n_hi].T,
                       pts_held_vc[:, n_hi:].T, w_eff)
    avis_o = vo.T @ area  # (h_o,)
    eps = cpm.avis_floor(texel_area)
    d = ref.shape[0] * ref.shape[1]
    avis_rows = np.tile(avis_o, ref.shape[0])
    f_ref, valid = cpm.filtered_reflectance(ref.reshape(d, 3), avis_rows, eps)
    f_apx, _ = cpm.filtered_reflectance(approx.reshape(d, 3), avis_rows, eps)
    return float(cpm.snr_db(f_ref, f_apx, valid))


def _level_candidates(
    ctx: StageContext, level: int, texels: np.ndarray, children: dict[str, np.ndarray] | None
) -> PointSet:
    """Candidates of `texels` at `level`: all dense samples (level 0, or hierarchy="dense"), or
    the union of the children's weighted characteristic points (hierarchy="children")."""
    geo = ctx.geometry()
    n = ctx.settings.atlas_resolution
    if level == 0 or ctx.settings.hierarchy == "dense" or children is None:
        tex = texel_ids(geo, n, level)
        idx = np.nonzero(np.isin(tex, texels))[0]
        area = geo["sample_area"][idx]
        return PointSet(idx.astype(np.int64), np.repeat(area[:, None], 3, axis=1), tex[idx])
    counts = np.diff(children["offsets"])
    child_tex = np.repeat(children["texel"], counts)  # (p,) child texel ids at level-1
    n_c = n >> (level - 1)
    r, c = np.divmod(child_tex, n_c)
    parent = (r >> 1) * (n_c >> 1) + (c >> 1)
    return PointSet(
        children["point_sample"].astype(np.int64),
        children["point_weight"].astype(np.float64),
        parent.astype(np.int64),
    )


def _level_key(ctx: StageContext, level: int, tile: int | None) -> str:
    """Key of one level's fit within one tile (or the top shard)."""
    name = f"L{level:02d}-tile{tile:05d}-s{ctx.settings.shard_texels}.npz" if tile is not None \
        else f"L{level:02d}-top.npz"
    return ctx.key("cpm", name)


def run_cpm_tile(ctx: StageContext, shard: int) -> str:
    """Every level inside one tile, finest first (coarser levels select from their children)."""
    s = ctx.settings
    last = _level_key(ctx, ctx.tile_levels - 1, shard)
    if ctx.store.exists(last):
        return last
    children = None
    for level in range(ctx.tile_levels):
        key = _level_key(ctx, level, shard)
        if ctx.store.exists(key):
            children = ctx.store.read_arrays(key)
            continue
        texels = tile_texels(s.atlas_resolution, s.shard_texels, shard, level)
        cands = _level_candidates(ctx, level, texels, children)
        children = fit_level(ctx, level, texels, cands)
        ctx.store.write_arrays(key, children)
    return last


def _concat_levels(parts: list[dict[str, np.ndarray]]) -> dict[str, np.ndarray]:
    """Concatenate per-tile results of one level (CSR offsets re-based)."""
    out: dict[str, np.ndarray] = {}
    base = 0
    offs = [np.zeros(1, np.int64)]
    for p in parts:
        offs.append(p["offsets"][1:] + base)
        base += int(p["offsets"][-1])
    out["offsets"] = np.concatenate(offs)
    for k in parts[0]:
        if k == "rays":
            out[k] = np.array([sum(int(p[k].sum()) for p in parts if k in p)], np.int64)
        elif k != "offsets":
            out[k] = np.concatenate([p[k] for p in parts])
    return out


def run_cpm_top(ctx: StageContext, shard: int = 0) -> str:
    """Levels coarser than a tile, from the tiles' coarsest level."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    last = _level_key(ctx, ctx.n_levels - 1, None)
    if ctx.store.exists(last):
        return last
    lvl = ctx.tile_levels - 1
    children = _concat_levels(
        [ctx.store.read_arrays(_level_key(ctx, lvl, t)) for t in range(n_tiles)]
    )
    for level in range(ctx.tile_levels, ctx.n_levels):
        key = _level_key(ctx, level, None)
        if ctx.store.exists(key):
            children = ctx.store.read_arrays(key)
            continue
        n_l = s.atlas_resolution >> level
        texels = np.arange(n_l * n_l, dtype=np.int64)
        cands = _level_candidates(ctx, level, texels, children)
        children = fit_level(ctx, level, texels, cands)
        ctx.store.write_arrays(key, children)
    return last


def cpm_levels(ctx: StageContext) -> list[dict[str, np.ndarray]]:
    """All levels of the finished CPM, each sorted by texel id (for export and reports)."""
    s = ctx.settings
    n_tiles = (s.atlas_resolution // s.shard_texels) ** 2
    levels = []
    for level in range(ctx.n_levels):
        if level < ctx.tile_levels:
            parts = [ctx.store.read_arrays(_level_key(ctx, level, t)) for t in range(n_tiles)]
            data = _concat_levels(parts)
        else:
            data = ctx.store.read_arrays(_level_key(ctx, level, None))
        levels.append(_sort_by_texel(data))
    return levels


def _sort_by_texel(data: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    order = np.argsort(data["texel"], kind="stable")
    counts = np.diff(data["offsets"])[order]
    starts = data["offsets"][:-1][order]
    # the CSR ranges in the new texel order, gathered without a loop per texel
    base = np.cumsum(counts) - counts
    point_idx = (np.arange(int(counts.sum())) - np.repeat(base, counts)
                 + np.repeat(starts, counts))
    out = {k: v[order] for k, v in data.items()
           if k not in ("offsets", "point_sample", "point_weight", "rays")}
    if "rays" in data:
        out["rays"] = data["rays"]
    out["offsets"] = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
    out["point_sample"] = data["point_sample"][point_idx.astype(np.int64)]
    out["point_weight"] = data["point_weight"][point_idx.astype(np.int64)]
    return out



# --------------------------------------------------------------------------- visible projected area


def _avis_level_arrays(level: avis_mod.AvisLevel, prefix: str) -> dict[str, np.ndarray]:
    return {f"{prefix}{k}": v for k, v in avis_mod.level_to_arrays(level).items()}


def _avis_level_from(data: dict[str, np.ndarray], prefix: str) -> avis_mod.AvisLevel:
    return avis_mod.level_from_arrays(
        {k[len(prefix):]: v for k, v in data.items() if k.startswith(prefix)}
    )


def _avis_key(ctx: StageContext, tile: int | None) -> str:
    fields = _GEOMETRY_FIELDS + ("avis_resolution",)
    name = f"tile{tile:05d}-s{ctx.settings.shard_texels}.npz" if tile is not None else "top.npz"
    return ctx.key("avis", name, fields)


def run_avis_tile(ctx: StageContext, shard: int) -> str:
    """a_vis cube maps of every level inside one tile (seed 000 §3.4): closed form where it is
    provably exact, rays elsewhere; coarser levels by exact additivity over children."""
    key = _avis_key(ctx, shard)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    geo = ctx.geometry()
    n, side = s.atlas_resolution, s.shard_texels
    tr, tc = divmod(shard, n // side)
    row, col = geo["sample_row"], geo["sample_col"]
    inside = (row // side == tr) & (col // side == tc)
    idx = np.nonzero(inside)[0]
    local = (row[idx] - tr * side) * side + (col[idx] - tc * side)
    caster = ctx.caster()
    rays0 = caster.rays_cast
    level = avis_mod.avis_level(
        geo["sample_pos"][idx], geo["sample_gnrm"][idx], geo["sample_area"][idx], local, side,
        s.avis_resolution, caster.occluded, ctx.asset().points,
        ray_eps=TOL.ray_offset * caster.bbox_diag,
    )
    out = _avis_level_arrays(level, "L00_")
    out["rays"] = np.array([caster.rays_cast - rays0], np.int64)
    for lvl in range(1, ctx.tile_levels):
        level = avis_mod.coarsen_level(level)
        out.update(_avis_level_arrays(level, f"L{lvl:02d}_"))
    return ctx.store.write_arrays(key, out)


def avis_rays(ctx: StageContext) -> int:
    """Rays the a_vis tiles cast (closed-form texels cast none)."""
    per_row = ctx.settings.atlas_resolution // ctx.settings.shard_texels
    return int(sum(int(ctx.store.read_arrays(_avis_key(ctx, t)).get("rays", np.zeros(1)).sum())
                   for t in range(per_row * per_row)))


def run_avis_top(ctx: StageContext, shard: int = 0) -> str:
    """Levels coarser than a tile: the tiles' coarsest maps placed side by side, then summed."""
    key = _avis_key(ctx, None)
    if ctx.store.exists(key):
        return key
    s = ctx.settings
    per_row = s.atlas_resolution // s.shard_texels
    top = f"L{ctx.tile_levels - 1:02d}_"
    parts = [_avis_level_from(ctx.store.read_arrays(_avis_key(ctx, t)), top)
             for t in range(per_row * per_row)]
    level = avis_mod.stack_tiles(parts, per_row)
    out = {}
    for lvl in range(ctx.tile_levels, ctx.n_levels):
        level = avis_mod.coarsen_level(level)
        out.update(_avis_level_arrays(level, f"L{lvl:02d}_"))
    return ctx.store.write_arrays(key, out)


def avis_levels(ctx: StageContext) -> list[avis_mod.AvisLevel]:
    """Every level's a_vis over the whole atlas (tiles assembled)."""
    s = ctx.settings
    n, side = s.atlas_resolution, s.shard_texels
    per_row = n // side
    tiles = [ctx.store.read_arrays(_avis_key(ctx, t)) for t in range(per_row * per_row)]
    top = ctx.store.read_arrays(_avis_key(ctx, None)) if ctx.tile_levels < ctx.n_levels else {}
    levels = []
    for lvl in range(ctx.n_levels):
        if lvl < ctx.tile_levels:
            parts = [_avis_level_from(d, f"L{lvl:02d}_") for d in tiles]
            levels.append(avis_mod.stack_tiles(parts, per_row))
        else:
            levels.append(_avis_level_from(top, f"L{lvl:02d}_"))
    return levels


def avis_table_arrays(table: avis_mod.AvisTable) -> dict[str, np.ndarray]:
    """An AvisTable as payload arrays (`avis:` namespace)."""
    return {f"avis:{k}": v for k, v in table.to_arrays().items()}


def avis_table_from(arrays: dict[str, np.ndarray]) -> avis_mod.AvisTable:
    """Inverse of `avis_table_arrays` (used by the renderer on `read_baked` output)."""
    return avis_mod.AvisTable.from_arrays(
        {k[5:]: v for k, v in arrays.items() if k.startswith("avis:")}
    )


# --------------------------------------------------------------------------- btf, render


def _btf_key(ctx: StageContext) -> str:
    return ctx.key("btf", "btf")


def run_btf(ctx: StageContext, shard: int = 0) -> str:
    """BTF level of detail (seed 001) from the finest level's filtered reflectance: exactly the
    Eq. 7 values the CPM stage measured against (f_bar on the N_i x N_o grid), one BTF image per
    direction pair over the atlas; EXR maps and a report under the store."""
    from texelbake.btf import BTFSettings, bake_btf, btf_from_texels

    key = _btf_key(ctx)
    out = ctx.store.path(key)
    if (out / "report.json").is_file():
        return key
    level0 = cpm_levels(ctx)[0]
    if "fbar" not in level0:
        raise StageError("the CPM artifacts of this bake carry no f_bar (settings.btf was off)")
    ok = level0["valid"]
    n = ctx.settings.atlas_resolution
    btf, covered = btf_from_texels(level0["fbar"][ok], level0["texel"][ok], n)
    dirs = direction_sets(ctx.settings)
    n_o = len(dirs["dirs_o"])
    di = np.repeat(dirs["dirs_i"], n_o, axis=0)  # row r = i * n_o + o
    do = np.tile(dirs["dirs_o"], (len(dirs["dirs_i"]), 1))
    out.mkdir(parents=True, exist_ok=True)
    _, report = bake_btf(btf, di, do, out, BTFSettings(), covered=covered)
    ctx.store.write_json(f"{key}/report.json", report)
    return key


def run_render(ctx: StageContext, shard: int = 0, out_dir: Path | None = None) -> list[Path]:
    """Previews of the finished bake, rendered from the written USD (texelbake.render)."""
    from texelbake.render import render_previews

    if out_dir is None:
        raise StageError("the render stage needs the folder of the written bake")
    roots = sorted(Path(out_dir).glob("*_baked.usda"))
    if not roots:
        raise StageError(f"no baked USD in {out_dir} to render previews from")
    return render_previews(roots[0], Path(out_dir) / "previews", size="small")


# --------------------------------------------------------------------------- export


def _percentiles(x: np.ndarray) -> dict[str, float]:
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"n": 0}
    return {"n": int(x.size), "mean": float(x.mean()), "p5": float(np.percentile(x, 5)),
            "p50": float(np.median(x)), "p95": float(np.percentile(x, 95)),
            "min": float(x.min()), "max": float(x.max())}


def assemble_level(ctx: StageContext, level: int, data: dict[str, np.ndarray],
                   avis_level: avis_mod.AvisLevel) -> tuple[dict[str, np.ndarray], dict]:
    """One CPM level as dense per-texel payload arrays, and its report entry."""
    s = ctx.settings
    geo = ctx.geometry()
    n_l = s.atlas_resolution >> level
    n_tex = n_l * n_l
    counts = np.zeros(n_tex, np.int64)
    counts[data["texel"]] = np.diff(data["offsets"])
    # data is sorted by texel id, so its points are already in dense-CSR order
    pts = data["point_sample"]

    def dense(name: str, fill, dtype) -> np.ndarray:
        out = np.full(n_tex, fill, dtype=dtype)
        out[data["texel"]] = data[name]
        return out

    frames = geo[f"frames_L{level}"]
    table = avis_mod.compress_level(avis_level, frames, s.avis_keep_fraction)
    arrays = {
        "texel_offsets": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "point_sample": pts.astype(np.int64),
        "point_position": geo["sample_pos"][pts].astype(np.float32),
        "point_normal": geo["sample_nrm"][pts].astype(np.float32),
        "point_geom_normal": geo["sample_gnrm"][pts].astype(np.float32),
        "point_material": geo["sample_mat"][pts].astype(np.int32),
        "point_uv": geo["sample_uv"][pts].astype(np.float32),
        "point_weight": data["point_weight"].astype(np.float32),
        "texel_k": dense("k", 0, np.int32),
        "texel_c": dense("c", 0, np.int32),
        "texel_snr_insample": dense("snr_in", np.nan, np.float32),
        "texel_snr_heldout": dense("snr_ho", np.nan, np.float32),
        "texel_valid": dense("valid", False, bool),
        "texel_mode": dense("mode", 0, np.uint8),
        "frames": frames.astype(np.float64),
    }
    arrays.update(avis_table_arrays(table))
    # a_vis compression error (relative L2 over the ray-based maps, the seed's measure)
    err = 0.0
    if len(avis_level.ray_texels):
        from texelbake.haar import decompress_haar

        table_maps = decompress_haar(table.haar).reshape(-1, 6, avis_level.res, avis_level.res)
        frac = avis_level.bounded[avis_level.ray_texels]
        ref = avis_level.ray_maps.copy()
        if frac.any():
            unocc = avis_mod.closed_form_maps(avis_level.cf, avis_level.res,
                                              avis_level.ray_texels[frac])
            ref[frac] = avis_mod.visible_fraction(ref[frac], unocc)
        err = float(np.linalg.norm(table_maps - ref)) / max(float(np.linalg.norm(ref)), 1e-300)
    valid = data["valid"]
    report = {
        "level": level,
        "resolution": n_l,
        "texels": n_tex,
        "texels_with_samples": int(len(data["texel"]) - np.sum(np.isnan(data["snr_in"]))),
        "texels_valid": int(valid.sum()),
        "k": _percentiles(data["k"][valid]),
        "c": _percentiles(data["c"][valid]),
        "snr_insample_db": _percentiles(data["snr_in"][valid]),
        "snr_heldout_db": _percentiles(data["snr_ho"][valid]),
        "per_channel_texels": int(np.sum(data["mode"][valid] == 1)),
        "points": int(len(pts)),
        "rays": int(data["rays"].sum()) if "rays" in data else 0,
        "bytes": int(sum(a.nbytes for a in arrays.values())),
        "avis": {
            "closed_form_texels": int(avis_level.closed.sum()),
            "ray_texels": int(len(avis_level.ray_texels)),
            "kept_fraction": float(table.haar.kept_fraction),
            "rel_error": err,
        },
    }
    return arrays, report


def export_to(ctx: StageContext, out_dir: Path, *, stage_seconds: dict | None = None,
              plan=None) -> Path:
    """Write the baked USD bundle and report.json into out_dir (the export stage)."""
    from texelbake import payload
    from texelbake.normalmap import bake_preview_maps, face_tangent_space
    from texelbake.scene import check_asset_paths

    s = ctx.settings
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    geo = ctx.geometry()
    asset = ctx.asset()
    cpm_lv = cpm_levels(ctx)
    avis_lv = avis_levels(ctx)
    levels, level_reports = [], []
    for lvl in range(ctx.n_levels):
        arrays, rep = assemble_level(ctx, lvl, cpm_lv[lvl], avis_lv[lvl])
        levels.append(arrays)
        level_reports.append(rep)
    dirs = direction_sets(s)
    m1_frames = face_tangent_space(geo["m1_vertices"], geo["m1_faces"], geo["m1_corner_uvs"])
    albedo, normal, _ = bake_preview_maps(
        s.atlas_resolution, texel_ids(geo, s.atlas_resolution, 0), geo["sample_area"],
        geo["sample_nrm"], geo["sample_uv"], geo["sample_mat"], asset.materials, m1_frames,
        geo["sample_m1_prim"],
    )
    meshes = [payload.LodMesh(geo["m1_vertices"], geo["m1_faces"], geo["m1_corner_uvs"])]
    i = 2
    while f"m{i}_vertices" in geo:
        meshes.append(payload.LodMesh(geo[f"m{i}_vertices"], geo[f"m{i}_faces"],
                                      geo[f"m{i}_corner_uvs"]))
        i += 1
    name = ctx.asset_path.stem
    skipped = list(plan.skipped) if plan is not None else []
    report = {
        "texelbake_version": __import__("texelbake").__version__,
        "source": ctx.asset_path.name,
        "source_hash": ctx.asset_hash,
        "settings": s.model_dump(),
        "levels": level_reports,
        "samples": int(len(geo["sample_area"])),
        "rays": {"cpm": int(sum(r["rays"] for r in level_reports)), "avis": avis_rays(ctx)},
        "surface_area": float(geo["sample_area"].sum()),
        "skipped": [{"stage": a, "reason": b} for a, b in skipped],
        "stage_seconds": dict(stage_seconds or {}),
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
    baked = payload.BakedAsset(
        name=name, levels=levels,
        arrays={"dirs_i": dirs["dirs_i"], "dirs_o": dirs["dirs_o"],
                "heldout_i": dirs["held_i"], "heldout_o": dirs["held_o"],
                "material_model": np.array(
                    [["lambert", "preview", "phong", "merl", "cellular"].index(m.model)
                     for m in asset.materials], np.int32)},
        meshes=meshes, albedo=albedo, normal=normal, metadata=metadata,
    )
    author_extra = None
    if s.btf:
        author_extra = _export_btf(ctx, out_dir, report)
    source_copy = payload.copy_source(
        ctx.asset_path, check_asset_paths(ctx.asset_path), out_dir / "source"
    )
    root = payload.write_baked_asset(out_dir, source_copy, baked, list(asset.mesh_paths),
                                     author_extra=author_extra)
    payload.atomic_json(out_dir / "report.json", report)
    return root


def _export_btf(ctx: StageContext, out_dir: Path, report: dict):
    """Copy the BTF maps beside the baked layer, add their report, and return the callback that
    authors texelbake's Laplacian BTF shader in the preview material of the payload."""
    import shutil

    from texelbake.btf import author_btf_shader, read_btf_maps

    src = ctx.store.path(_btf_key(ctx))
    btf_report = ctx.store.read_json(f"{_btf_key(ctx)}/report.json")
    for name in sorted(btf_report["files"].values()):
        shutil.copyfile(src / name, out_dir / name)
    report["btf"] = btf_report
    maps = read_btf_maps(out_dir, "btf")
    files = {part: f"./{name}" for part, name in btf_report["files"].items()}

    def author(stage) -> None:
        author_btf_shader(stage, "/Baked/Looks/BakedPreview", files, maps)

    return author


def update_report_seconds(out_dir: Path, seconds: dict[str, float]) -> None:
    from texelbake import payload

    path = Path(out_dir) / "report.json"
    report = json.loads(path.read_text())
    report["stage_seconds"] = {k: round(v, 3) for k, v in seconds.items()}
    report["total_seconds"] = round(sum(seconds.values()), 3)
    payload.atomic_json(path, report)


def run_export(ctx: StageContext, shard: int = 0) -> str:
    """The farm's export: write the bundle under the store (`result/`) and return its key."""
    key = ctx.key("export", "result")
    out = ctx.store.path(key)
    if (out / "report.json").is_file():
        return key
    export_to(ctx, out)
    return key
