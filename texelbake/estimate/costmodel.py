"""A bake's cost model: its time predicted from the texel count, the samples per
texel, the direction pairs and the worker count, before the CPM stages run.

The CPM fit of a texel with m candidate columns on d = N_i N_o direction pairs costs (batched
fit, `texelbake.cpm.level_batched`):

    r_entry m d    building R (BRDF evaluation, visibility products, F = R / a_vis)
    gram m^2 d     the Gram matrices (4 per texel in luminance mode)
    eigh m^3       their eigendecompositions
    held n H       the held-out truth over its n dense samples on H held-out pairs (a measured
                   texel's: `heldout_texels` of a level's, each over at most `heldout_samples`)
    texel          draws, bisection and NNLS on the reduced r x c systems

With texel_classes "by_need" every texel of the finest `classed_levels` levels is first classed
(its n dense samples' visibility on the N_i + N_o grid directions: `classify` n (N_i + N_o)),
and only the fraction the classes send to the fit (`fitted`, measured on a sample of texels by
the caller, `texelbake.pipeline.estimate`; 1 when not known) pays the fit's terms.

Level 0's m are the dense samples per texel (known exactly once the geometry stage has placed
them: `sample_counts`; before that the n^2 spt samples spread over an assumed atlas fill); a coarser
texel selects among its children's points, m = sum over its children of min(c_L, m_child) with
c_L the typical points per texel of a level (C_LEVEL, measured; a finest texel's fall with the
atlas's side, `finest_points`). The a_vis and geometry stages scale with the dense samples. Tile shards spread over the workers; the levels above a tile
are one shard (`run_cpm_top`), priced serially except for their dense samples' sums (the held
term), which the tile shards make; each process pool pays its start once.
Coefficients are seconds measured on one 2-core machine (benchmarks/costmodel_check.py compares
prediction and outcome); on another machine `estimate(speed=...)` scales them by a short
reference workload's time there against its time on that machine (`texelbake.estimate.machinespeed`,
per kind of work: elementwise grids, BLAS, rays, per-call Python), and `Coefficients` can be
re-fitted for another machine.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, fields, replace
from typing import TYPE_CHECKING

import numpy as np

from schemas.settings import BakeSettings
from texelbake.arrays import every_kth

if TYPE_CHECKING:
    from texelbake.estimate.machinespeed import MachineSpeed

#: occupied fraction of the atlas' finest texels when the geometry is not known yet (measured:
#: cylinder 0.37, bolt 0.4 at 32^2)
DEFAULT_FILL = 0.4


@dataclass(frozen=True)
class Coefficients:
    """Seconds per unit on the reference machine (`texelbake.estimate.machinespeed`: an estimate on
    another machine scales them by its reference workload's factors). The fit's groups (the
    fitted texels' fit: r_entry, gram, eigh, texel; the held-out truth: held; the classing:
    classify; the coarse fit's a_vis: fit_avis) are scaled each to its own measured CPU seconds
    in whole-atlas `benchmarks/cpm_cpu.py --breakdown` runs (`benchmarks/calibrate_costmodel.py
    --parts`: cylinder and bolt at 64^2 and 128^2 defaults and the cylinder at 512^2 with
    LOD1's settings, benchmarks/results/cpm_cpu_*_parts.json); the ratios within a group
    (brdf_ggx, held_ggx, gram and texel to r_entry) come from the earlier NNLS fit of every
    level's seconds; the a_vis, export, process and fixed terms to the stage seconds of
    `benchmarks/costmodel_check.py`, which also checks prediction against outcome out of
    sample (docs/profile.md)."""

    r_entry: float = 7.16e-8  # s per (candidate, direction pair), Lambert / Phong
    gram: float = 1.05e-10  # s per m^2 d
    eigh: float = 0.0  # s per m^3
    held: float = 1.65e-8  # s per (dense sample, held-out pair), Lambert / Phong (+ a_vis)
    texel: float = 4.79e-3  # s per fitted texel
    brdf_ggx: float = 1.25  # R cost of a GGX (preview, merl, cellular) material, x r_entry
    held_ggx: float = 1.43  # held-out cost of such a material, x held
    # classing a texel by need (`cpm.classify`): s per (dense sample, grid direction), its
    # visibility rays and pattern tests (`classes_bounded`'s seconds)
    classify: float = 7.09e-8
    # a coarse level's a_vis cast by the fit over its fitted texels' samples (avis_coarse
    # "dense"; "children" reads the a_vis stage's maps): s per (dense sample, grid view
    # direction) (`avis_sums`' seconds)
    fit_avis: float = 5.28e-8
    # trying level 0's lobe class (lobe_class "validated", `cpm.lobe_class`): s per dense
    # sample of a tried texel (its truth on the fit pairs, the lobes' columns and NNLS, and
    # for the texels that pass, their visibility rays and validation truth), x `widened`
    # like every term; `lobes_bounded`'s CPU seconds on the Teapot at 64^2 (whole atlas)
    # and 512^2 (16 tiles), 3.1e-5 and 3.5e-5 (docs/decisions.md)
    lobe: float = 3.3e-5
    # level 0's cell-averaged BTF table (btf_table "cell", `cpm.cell_table`): one BRDF grid per
    # draw and the pair's own, x r_entry per (sample, pair, grid); fitted to the cpm stage's
    # seconds cell / point (benchmarks/btf_tables.py)
    btf_cell: float = 0.39
    # point_lobe "widened" (`cpm.lobe`: the cells, the widened lobes' BRDF, the NNLS refit, the
    # 16 x 16 validation pairs): the whole fit's CPU seconds x narrow, the median of the
    # measured ratios 1.17-1.37 over five scenes and three seeds
    # (benchmarks/results/cpm_cpu_*_seeds_point_lobe_{narrow,widened}.json)
    widened: float = 1.24
    avis: float = 1.76e-4  # s per dense sample at 32^2 cube faces, x (res / 32)^2 (rays)
    # s per occupied finest texel at any face resolution (maps, coarsening); the residual of
    # the 512^2 cylinder's and bolt's a_vis stages (LOD1's settings) past their rays, which
    # match at the same texels and 4x the samples (docs/decisions.md)
    avis_fixed: float = 2.5e-4
    avis_stage: float = 4.8  # wall s of the a_vis stage on any atlas (each worker's set-up)
    # the export's a_vis tables (`cpm.avis.compress`, four passes over every level's ray
    # texels): wall s per occupied finest texel at 32^2 faces, x (res / 32)^2; and its
    # filtered maps (`stages.filtered.run_filtered`: AO rays and the LEADR, AO and base sums
    # of every dense sample), whatever the faces: wall s per dense sample. Fitted to the
    # export's seconds of the cylinder and bolt at 16^2, 64^2 (defaults) and 512^2 (LOD1's
    # settings), whose samples per texel differ 4x at the same texels (docs/decisions.md)
    export: float = 1.5e-3
    filtered: float = 4.85e-6
    geometry: float = 2.0e-5  # s per dense sample (sampling, texel assignment)
    process: float = 3.5  # s per process pool's start (imports, scene, ray caster)
    fixed: float = 2.0  # s (ingest, plan, the export's USD and LODs)

    def scaled(self, speed: MachineSpeed) -> Coefficients:
        """These coefficients on a machine of `speed` (every seconds field times its kind of
        work's factor, `MachineSpeed.factor`; the ratio fields unchanged)."""
        return replace(self, **{f.name: getattr(self, f.name) * speed.factor(f.name)
                                for f in fields(self)})


#: the coefficients a level's seconds are priced by (`Estimate.per_level`'s "terms")
TERMS = ("held", "r_entry", "gram", "eigh", "texel", "classify", "fit_avis", "btf_cell",
         "lobe")

#: typical characteristic points per texel at level L (children hierarchy), capped by c_max:
#: measured means at levels 0-4 at 32^2 (defaults): cylinder 32, 35, 42, 51, 82,
#: bolt 21, 19, 19, 21, 31; their mean
C_LEVEL = (27.0, 27.0, 31.0, 36.0, 56.0)
#: a fitted finest texel's points fall as the atlas grows (a smaller texel spans fewer
#: facets, shadows and normals): C_LEVEL[0] x (n / 32)^C0_SLOPE above 32^2; the fitted finest
#: texels' measured means, Teapot 64^2 / 128^2 / 512^2 21.8 / 20 / 12, bolt 64^2 / 128^2 19 /
#: 13 (`cpm_cpu.py`, docs/decisions.md)
C0_SLOPE = -0.29


def finest_points(n: int) -> float:
    """The typical points of a fitted finest texel of an n x n atlas (uncapped)."""
    return C_LEVEL[0] * min(1.0, (max(int(n), 1) / 32.0) ** C0_SLOPE)


def _level_points(level: int, n: int) -> float:
    """`finest_points` at level 0 of an n x n atlas, `C_LEVEL` above it."""
    return finest_points(n) if level == 0 else C_LEVEL[min(level, len(C_LEVEL) - 1)]


@dataclass
class Estimate:
    """Predicted seconds of a bake: total wall time on `workers` processes and its parts."""

    seconds: float
    workers: int
    cpm_seconds: float  # CPU seconds of the CPM fit (all levels), before dividing by workers
    avis_seconds: float
    geometry_seconds: float
    texels: int  # texels with samples, all levels
    stretch: float = 1.0  # wall / CPU slowdown from the machine's other load (>= 1)
    cpm_serial_seconds: float = 0.0  # of cpm_seconds, the levels above a tile (one shard)
    export_seconds: float = 0.0
    cpm_wall_seconds: float = 0.0  # the cpm stages' wall seconds on the workers (stretched)
    avis_wall_seconds: float = 0.0  # the avis stage's wall seconds on the workers (stretched)
    per_level: list[dict] = field(default_factory=list)
    speed: dict | None = None  # the machine's speed factors (`MachineSpeed.to_dict`), if used

    def to_dict(self) -> dict:
        return asdict(self)


def _pool2(a: np.ndarray) -> np.ndarray:
    n = a.shape[0] // 2
    return a.reshape(n, 2, n, 2).sum(axis=(1, 3))


def level_sizes(counts: np.ndarray, c_max: int, fitted: Sequence[float] | None = None,
                classed_points: Sequence[float] | None = None
                ) -> list[tuple[np.ndarray, np.ndarray]]:
    """(m (t,), n_dense (t,)) of the texels with samples at every level, from the finest
    level's dense sample counts (N, N). A texel's candidates are its children's points: a
    fitted child's `C_LEVEL` (`finest_points` at level 0), and at a classed level (`fitted`
    its fitted share, `classed_points` the points a classed texel stores, both per classed
    level) the mean of the fitted and the classed children's (a one-facet texel stores one
    point)."""
    out = []
    m = counts.astype(np.float64)
    dense = counts.astype(np.float64)
    level = 0
    while True:
        keep = dense > 0
        out.append((m[keep], dense[keep]))
        if dense.shape[0] == 1:
            return out
        c_l = min(float(c_max), _level_points(level, counts.shape[0]))
        if fitted is not None and classed_points is not None and level < min(
                len(fitted), len(classed_points)):
            phi = float(np.clip(fitted[level], 0.0, 1.0))
            c_l = phi * c_l + (1.0 - phi) * min(float(classed_points[level]), c_l)
        m = _pool2(np.minimum(m, c_l))
        dense = _pool2(dense)
        level += 1


def _uniform_sizes(n: int, spt: int, c_max: int) -> list[tuple[np.ndarray, np.ndarray, float]]:
    """`level_sizes` of the n^2 spt dense samples (the geometry stage places spt per atlas
    texel on average, `build_geometry`) spread evenly over DEFAULT_FILL n^2 occupied texels,
    in O(log n): at level L, t_L = max(t_0 / 4^L, 1) texels share the samples evenly (m,
    dense, multiplicity t_L). (Giving each occupied texel spt samples would be 1/fill too
    few: the job API's estimates were 2.3x short.)"""
    t = max(DEFAULT_FILL * n * n, 1.0)
    m = dense = float(spt) * n * n / t
    out = []
    for level in range(int(n).bit_length()):
        out.append((np.full(1, m), np.full(1, dense), t))
        t_next = max(t / 4.0, 1.0)
        c_l = min(float(c_max), _level_points(level, n))
        m = min(m, c_l) * t / t_next
        dense = dense * t / t_next
        t = t_next
    return out


def avis_cast(dense: np.ndarray, cap: int) -> np.ndarray:
    """The samples a fit casts a_vis rays from, per texel of `dense` samples: every
    ceil(dense / cap)-th (`texelbake.cpm.truth_sample.avis_samples`; cap 0: all)."""
    return every_kth(np.asarray(dense, np.float64), cap)[1]


def estimate(
    settings: BakeSettings,
    workers: int = 1,
    sample_counts: np.ndarray | None = None,
    coef: Coefficients | None = None,
    ggx_fraction: float = 0.5,
    load: float = 0.0,
    cores: int | None = None,
    speed: MachineSpeed | None = None,
    fitted: Sequence[float] | None = None,
    avis_ray_samples: float | None = None,
    level0_ratio: float | None = None,
    classed_points: Sequence[float] | None = None,
    lobe_tried: float | None = None,
) -> Estimate:
    """Predict a bake's seconds.

    settings : the bake's settings; workers : processes running shards (>= 1)
    ggx_fraction : fraction of the samples on materials costlier than Lambert / Phong
        (`ggx_fraction_of`); 0.5 when the asset is not known
    load, cores : other runnable processes on the machine (the 1-min load average without the
        bake's own) and its cores; when load + workers > cores each process gets
        cores / (load + workers) of a core and every term is stretched accordingly (default:
        a quiet machine)
    sample_counts : (N, N) int dense samples per finest texel (the geometry stage's
        `sample_row`/`sample_col` histogram, `sample_counts`); None: spt on DEFAULT_FILL of
        the atlas, spread evenly (a prediction before the geometry exists; O(log N) work)
    speed : this machine against the coefficients' (`texelbake.estimate.machinespeed.this_machine()`);
        None: the coefficients' machine (deterministic, for tests and ratios of estimates)
    fitted : per classed level, the fraction of its texels the classes leave to the fit
        (texel_classes "by_need"); None or a level beyond it: every texel (an upper bound)
    avis_ray_samples : the samples that cast level 0's a_vis rays (avis_level0 "by_need": a
        few strata per texel, `texelbake.pipeline.estimate`); None: every dense sample
    level0_ratio : a fitted finest texel's candidates over its dense samples (its groups,
        level0_candidates "clustered", measured on a sample by `texelbake.pipeline.estimate`);
        None: 1, every sample a candidate
    classed_points : per classed level, the mean points a texel the classes store holds
        (measured on the same sample); with `fitted` they set the next level's candidates
        (`level_sizes`); None: every child holds `C_LEVEL` points
    lobe_tried : the fraction of level 0's texels the lobe class tries (lobe_class
        "validated", measured on the same sample; its lobe texels are among the stored ones
        of `fitted` and `classed_points`); None: the class is not tried
    """
    coef = coef or Coefficients()
    if speed is not None:
        coef = coef.scaled(speed)
    s = settings
    n = s.atlas_resolution
    workers = max(int(workers), 1)
    sizes = ([(m, dn, 1.0) for m, dn in level_sizes(
        np.asarray(sample_counts, dtype=np.float64).reshape(n, n), s.c_max,
        fitted, classed_points)]
        if sample_counts is not None else _uniform_sizes(n, s.samples_per_texel, s.c_max))
    d = s.n_light_dirs * s.n_view_dirs
    n_h = int(round(np.sqrt(s.n_heldout))) ** 2 if s.n_heldout else 0
    g = float(np.clip(ggx_fraction, 0.0, 1.0))
    brdf = 1.0 + (coef.brdf_ggx - 1.0) * g
    brdf_h = 1.0 + (coef.held_ggx - 1.0) * g
    cell_grids = (1 + s.btf_cell_draws) if s.btf and s.btf_table == "cell" else 0
    per_level = []
    cpm = 0.0
    serial = 0.0  # levels above a tile: `run_cpm_top`, one shard on one worker
    tile_levels = int(s.shard_texels).bit_length()
    classed = s.classed_levels if s.texel_classes == "by_need" and not s.btf else 0
    n_dirs = s.n_light_dirs + s.n_view_dirs
    k_held = float(s.heldout_samples) if s.heldout_samples else np.inf
    texels = 0
    for level, (m, dense, mult) in enumerate(sizes):
        n_occ = mult * m.size
        measured = min(1.0, s.heldout_texels / max(n_occ, 1.0)) if s.heldout_texels else 1.0
        held = measured * mult * float(
            brdf_h * coef.held * (np.minimum(dense, k_held) * n_h).sum())
        phi = 1.0
        if level < classed and fitted is not None and level < len(fitted):
            phi = float(np.clip(fitted[level], 0.0, 1.0))
        if level == 0 and level0_ratio is not None:
            m = m * float(np.clip(level0_ratio, 0.0, 1.0))  # the fit's candidates, not samples
        # the level's seconds by the coefficient that prices them (`TERMS`), so that
        # benchmarks/calibrate_costmodel.py --parts can scale each group to its measured share
        terms = dict.fromkeys(TERMS, 0.0)
        terms["held"] = held
        terms["r_entry"] = phi * mult * float(brdf * coef.r_entry * (m * d).sum())
        terms["gram"] = phi * mult * float(coef.gram * (m * m * d).sum())
        terms["eigh"] = phi * mult * float(coef.eigh * (m ** 3).sum())
        terms["texel"] = phi * mult * float(coef.texel * m.size)
        if level < classed:
            terms["classify"] = mult * coef.classify * n_dirs * float(dense.sum())
        if level > 0 and s.avis_coarse == "dense":
            terms["fit_avis"] = phi * mult * coef.fit_avis * s.n_view_dirs * float(
                avis_cast(dense, s.avis_fit_samples).sum())
        if level == 0 and lobe_tried:
            terms["lobe"] = mult * coef.lobe * float(np.clip(lobe_tried, 0.0, 1.0)) * float(
                dense.sum())
        if level == 0 and cell_grids:
            terms["btf_cell"] = (mult * cell_grids * coef.btf_cell * brdf * coef.r_entry
                                 * float((m * d).sum()))
        if s.point_lobe == "widened":
            terms = {k: v * coef.widened for k, v in terms.items()}
        sec = sum(terms.values())
        n_tex = int(round(mult * m.size))
        per_level.append({"level": level, "texels": n_tex, "seconds": sec, "terms": terms})
        cpm += sec
        if level >= tile_levels:
            # a top level's dense sums (a_vis, held-out truth) are made by the tile shards
            # (`texelbake.stages.cpm.top_sums`); the top shard fits from them
            serial += sec - held
        texels += n_tex
    total_samples = float(sizes[0][1].sum() * sizes[0][2])
    finest_texels = float(sizes[0][0].size * sizes[0][2])  # occupied finest texels
    faces = (s.avis_resolution / 32.0) ** 2
    ray_samples = total_samples if avis_ray_samples is None else float(avis_ray_samples)
    avis = coef.avis * faces * ray_samples + coef.avis_fixed * finest_texels
    export = coef.export * faces * finest_texels + coef.filtered * total_samples
    geom = coef.geometry * total_samples
    par = min(workers, cores or workers)
    cpm_wall = (cpm - serial) / par + serial
    avis_wall = avis / par + coef.avis_stage
    seconds = coef.fixed + geom + export + coef.process + cpm_wall + avis_wall
    stretch = max(1.0, (max(load, 0.0) + par) / cores) if cores else 1.0
    return Estimate(seconds=seconds * stretch, workers=workers, cpm_seconds=cpm,
                    avis_seconds=avis, geometry_seconds=geom, texels=texels,
                    cpm_serial_seconds=serial, export_seconds=export,
                    cpm_wall_seconds=cpm_wall * stretch, avis_wall_seconds=avis_wall * stretch,
                    per_level=per_level, stretch=stretch,
                    speed=speed.to_dict() if speed is not None else None)


def atlas_trade(settings: BakeSettings, lod_report: dict,
                measured_seconds: float | None = None,
                fitted: Sequence[float] | None = None) -> dict:
    """What the CPM atlas covers and what the atlas LOD1 asks for would cost: the
    baked resolution, the largest screen size it serves (`max_px`, the bbox diagonal in pixels
    at which a finest texel is one pixel; larger on screen texelbake's renderer shades from
    M_org), the resolution at which a finest texel is one pixel where LOD1 switches in, the
    cost model's one-worker seconds of both (uniform fill, a quiet machine) and their ratio;
    with `measured_seconds` (this bake's stages), the projection measured x ratio. The ratio
    of one model's two predictions is what is trusted here, not its absolute seconds.

    fitted : this bake's classed levels' shares of texels left to the fit
        (`texelbake.cpm.assemble.fitted_shares`), priced for this atlas as they are; the
        larger atlas's classed level of the same texel size gets the same share, and a
        smaller texel than this bake's finest gets the finest's (a smaller texel spans fewer
        facets and patterns: an upper bound). None: every texel priced as fitted."""
    atlas = lod_report.get("atlas_mesh", {})
    need = atlas.get("atlas_resolution_for_lod1")
    n = settings.atlas_resolution
    est = estimate(settings, fitted=fitted).seconds
    # atlas_mode "lod1" bakes `for_lod1` up to the cap: the cap is reached when it bakes less
    out = {"resolution": n, "max_px": atlas.get("cpm_max_px"), "for_lod1": need,
           "mode": settings.atlas_mode, "cap": settings.atlas_cap,
           "cap_reached": bool(settings.atlas_mode == "lod1" and need and need > n),
           "estimated_seconds": est, "estimated_seconds_for_lod1": None, "cost_ratio": None,
           "projected_seconds_for_lod1": None,
           "fitted_shares": None if fitted is None else [round(float(f), 4) for f in fitted]}
    if need:
        shift = int(need).bit_length() - int(n).bit_length()  # levels between the two
        need_fitted = None if not fitted else [
            fitted[max(level - shift, 0)] if level - shift < len(fitted) else 1.0
            for level in range(settings.classed_levels)]
        est_need = est if need == n else estimate(
            settings.model_copy(update={"atlas_resolution": int(need)}),
            fitted=need_fitted).seconds
        out["estimated_seconds_for_lod1"] = est_need
        out["cost_ratio"] = est_need / est
        if measured_seconds:
            out["projected_seconds_for_lod1"] = float(measured_seconds) * est_need / est
    return out


def sample_counts(geo, n: int) -> np.ndarray:
    """(n, n) dense samples per finest texel from the geometry stage's arrays."""
    flat = geo["sample_row"].astype(np.int64) * n + geo["sample_col"].astype(np.int64)
    return np.bincount(flat, minlength=n * n).reshape(n, n)


def ggx_fraction_of(geo, materials) -> float:
    """Fraction of the dense samples whose material is not Lambert or Phong."""
    mat = np.asarray(geo["sample_mat"], dtype=np.int64)
    if mat.size == 0:
        return 0.0
    costly = np.array([m.model not in ("lambert", "phong") for m in materials], dtype=bool)
    return float(costly[mat].mean()) if costly.size else 0.0
