"""Bake settings: the one validated description of what a bake does.

Shared by the CLI, the in-process pipeline, the API (request body) and the workers. Every field has
a default so `BakeSettings()` is the embedded default bake. The JSON Schema is exported from here.
"""

from __future__ import annotations

import hashlib
import json
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.warp import check_warp_spec

#: quality-gate defaults (texelbake.stages.quality; measured in docs/decisions.md, 2026-11-25)
GATE_SNR_MEDIAN_DB = 0.0
GATE_SNR_P5_DB = -6.0
GATE_AVIS_REL_ERROR = 0.15


class BakeSettings(BaseModel):
    """Settings of one bake. Field docs cite the seed each knob comes from."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    seed: int = Field(0, ge=0, description="Seed of every random choice; reruns are byte-identical.")
    # geometry
    atlas_resolution: int = Field(
        16, ge=2, le=4096, description="Finest CPM level: N x N texels over M1's atlas (power of two)."
    )
    lod_mode: Literal["error", "atlas"] = Field(
        "error",
        description="'error': each LOD is the smallest QEM mesh within lod_error_px pixels of "
        "M_org at its switch size (lod_switch_px), independent of the atlas; 'atlas': the "
        "pre-issue-22 chain (M1 capped by the atlas, then simplify_ratio per level).",
    )
    lod_switch_px: tuple[float, ...] = Field(
        (256.0, 64.0),
        description="Screen size (pixels covered by the bounding-box diagonal) at which LOD1, "
        "LOD2, ... switch in; decreasing. 'error' mode: one LOD per entry up to mesh_levels "
        "(fewer when a level would not reduce the triangle count meaningfully).",
    )
    lod_error_px: float = Field(
        1.0, gt=0.0, le=64.0,
        description="Largest deviation (two-sided Hausdorff distance to M_org) a LOD may show, "
        "in pixels at its switch size.",
    )
    mesh_levels: int = Field(
        2, ge=1, le=8, description="Simplified meshes M1..Mn: 'atlas' mode's count, 'error' "
        "mode's most (the first mesh_levels switch sizes).",
    )
    simplify_ratio: float = Field(0.25, gt=0.0, lt=1.0, description="Face ratio M_{i+1}/M_i.")
    enclose_meshes: bool = Field(
        True,
        description="Move M1..Mn outward until they cover M_org's outline (each face's plane to "
        "its farthest sample outside); false: the seed's QEM meshes as they are.",
    )
    m1_method: Literal["auto", "qem", "wrap"] = Field(
        "auto",
        description="How M1 is made: 'qem' simplifies M_org (the seed); 'wrap' simplifies a "
        "connected surface about a texel outside M_org (assets of many separate parts); "
        "'auto' wraps assets of 8 or more parts when QEM would keep fewer than 16 faces per part.",
    )
    m1_faces: int = Field(
        0, ge=0, description="Target faces of M1; 0 = simplify_ratio x the original face count."
    )
    samples_per_texel: int = Field(
        64, ge=1, le=65536, description="Dense samples X on M_org per finest texel (on average)."
    )
    # characteristic points (seed 000 §3)
    n_light_dirs: int = Field(64, ge=1, le=4096, description="N_i light directions (texel frame).")
    n_view_dirs: int = Field(64, ge=1, le=4096, description="N_o view directions (texel frame).")
    n_heldout: int = Field(256, ge=0, le=65536, description="Held-out direction pairs per texel.")
    psi: float = Field(0.97, gt=0.0, le=1.0, description="Energy fraction that fixes the rank k.")
    eps_db: float = Field(30.0, gt=0.0, le=200.0, description="Target SNR (dB) for the bisection on c.")
    c_max: int = Field(64, ge=1, le=4096, description="Maximum characteristic points per texel.")
    n_trials: int = Field(4, ge=1, le=64, description="Random column draws per c; best kept.")
    small_texels: Literal["all", "fit"] = Field(
        "all",
        description="all: a texel with at most c_max candidates keeps every one of them (its "
        "Eq. 7 exact at every direction) unless its fit is already exact on the grid (rank 1: "
        "one point); fit: the seed's bisection on c, which stops at the smallest c reaching "
        "eps_db on the direction grid and generalizes worse off it (docs/decisions.md "
        "2026-11-27).",
    )
    weights: Literal["nnls", "clamp"] = Field(
        "nnls", description="nnls: exact non-negative LS; clamp: the seed's C+R1 with negatives to 0."
    )
    colour: Literal["auto", "luminance", "per_channel"] = "auto"
    decorrelation_threshold: float = Field(
        0.9, ge=-1.0, le=1.0, description="Channels correlated below this are selected per channel."
    )
    n_batch: int = Field(1024, ge=16, description="Max columns of one R; bigger texels go in batches.")
    hierarchy: Literal["children", "dense"] = Field(
        "children",
        description="children: coarse texels select from their children's weighted points; "
        "dense: from all dense samples, as the seed.",
    )
    coarse_target: Literal["children", "dense"] = Field(
        "children",
        description="With hierarchy='children', what a coarse texel's point weights are fitted "
        "to: 'children': the children's weighted sum, as the fit selects them (compounds "
        "errors); 'dense' refits them by NNLS to the texel's Eq. 7 over all its dense samples "
        "(texelbake.cpm.refit; measured: higher held-out medians at the coarse levels, e.g. the "
        "full cylinder 16² L1-L4 23.7/22.0/16.8/11.2 -> 28.5/25.9/20.9/17.8 dB, but lower tails, "
        "the cloisonne's L3 p5 -1.9 -> -7.7 dB, under the quality gate's floor, and twice the "
        "fit's time; not the default since 2026-11-26, docs/decisions.md).",
    )
    refit_validation: bool = Field(
        False,
        description="With coarse_target='dense', accept a texel's refit only if it beats the "
        "fit's weights in a 4-fold cross-validation over the grid's light directions (the "
        "held-out pairs stay unseen). Off by default: measured 2026-11-26 it keeps the "
        "cloisonne's level-3 held-out p5 at -1.9 dB (-7.7 without) but refuses most refits, so "
        "the full cylinder's coarse medians fall 2-6 dB (docs/decisions.md).",
    )
    refit_shrink: bool = Field(
        False,
        description="With coarse_target='dense', shrink the refitted weights towards the fit's: "
        "NNLS of |A w - f|^2 + lam |w - w_fit|^2, lam from five strengths or the fit's own "
        "weights, chosen once per pool of texels (a tile's level, or 256 texels of a top level) "
        "by an 8-fold cross-validation over the grid's light directions "
        "(texelbake.cpm.refit). Measured at 16², 3 seeds: the cylinder's coarse held-out "
        "medians and tails rise at every level (L3 19.5 -> 23.3 dB, p5 13.8 -> 20.4), the "
        "cloisonne's and the Teapot's tails stay where 'children' has them (the plain refit "
        "lowers them; with c_max 256 the Teapot's coarse tails move with the seed both ways); "
        "costs what the refit costs; off (docs/decisions.md 2026-11-29).",
    )
    fit_method: Literal["batched", "per_texel"] = Field(
        "batched",
        description="batched: R, Grams and eigendecompositions for many texels at once "
        "(issue 15); per_texel: one texel at a time on R itself (the seed's loop).",
    )
    trial_stop: Literal["all", "target"] = Field(
        "all",
        description="all: every one of n_trials draws per probed c, the best kept (the seed); "
        "target: a probe stops drawing at the first draw that reaches eps_db (batched fit "
        "only; issue 15).",
    )
    c_start: Literal["interval", "spectrum"] = Field(
        "interval",
        description="interval: the bisection on c probes the middle of [k, c_max] first (the "
        "seed); spectrum: it probes first the smallest c whose Eckart-Young tail of the "
        "selection matrix is eps_db below its energy, then brackets outward from it (batched "
        "fit only; issue 15).",
    )
    selection_columns: int = Field(
        0, ge=0, le=65536,
        description="0: a texel's points are drawn from all its candidates (the seed); s > 0: "
        "a texel of more than s candidates draws them from s of its candidates (a uniform "
        "subset, seeded by the texel), its weights still fitted to Eq. 7 over all of them "
        "(Grams s^2 d instead of m^2 d; batched fit only; issue 15).",
    )
    identical_columns: Literal["keep", "merge"] = Field(
        "merge",
        description="merge: candidates whose columns of F are identical (flat, unoccluded, "
        "single-material samples) are fitted as one column of weight sqrt(k), which leaves the "
        "fit's distribution the seed's and stores no point twice (Grams u^2 d for u distinct "
        "columns; batched fit only; issue 15); keep: every candidate is a column of the fit "
        "(the seed).",
    )
    closed_form: bool = Field(
        False, description="A texel whose R is numerically rank 1 gets its point in closed form, "
        "without draws or trials (batched fit only). Off by default: measured, the one column it "
        "picks (the largest-energy sample) generalizes worse than the randomized draw (inter-"
        "object shadow test: cpm 23.8 dB against 25.3 dB).",
    )
    # visible projected area (seed 000 §3.4)
    avis_resolution: int = Field(
        32, ge=2, le=256, description="Cube-map face resolution (32: every texel within 2 % of "
        "its uncompressed maps at 3.8 % storage on height fields; 16 keeps too few "
        "coefficients per texel, 3.2 %).")
    avis_keep_fraction: float = Field(
        0.03, gt=0.0, le=1.0, description="Haar coefficients kept, a fraction of the level's "
        "dense cube pixels (4 bytes each with avis_selection='texel': 0.03 stores 4.0 % of the "
        "dense float32 maps with the counts, scales and sum corrections).")
    avis_selection: Literal["texel", "face"] = Field(
        "texel", description="How the a_vis Haar coefficients are chosen: 'texel' spends one "
        "budget per level so that every texel's relative error is about equal (U^2-weighted, "
        "float16 values); 'face' is the seed's per-face top fraction with float32 values.")
    # quality gate (issue 22, item 2; texelbake.stages.quality): targets, not inputs of any stage
    gate_snr_median_db: float = Field(
        GATE_SNR_MEDIAN_DB, ge=-200.0, le=200.0,
        description="Each CPM level's held-out SNR median (dB) must reach this.",
    )
    gate_snr_p5_db: float = Field(
        GATE_SNR_P5_DB, ge=-200.0, le=200.0,
        description="Each CPM level's held-out SNR 5th percentile (dB) must reach this.",
    )
    gate_avis_rel_error: float = Field(
        GATE_AVIS_REL_ERROR, gt=0.0, le=10.0,
        description="Each CPM level's a_vis relative L2 error (compressed) must stay below this.",
    )
    # farm
    shard_texels: int = Field(8, ge=1, le=4096, description="Tile side (finest texels) of a shard.")
    worker_memory_mb: int = Field(
        512, ge=64, le=1 << 20,
        description="Working-memory bound of one worker's CPM fit (MiB): texels and samples are "
        "processed in chunks that fit, whatever the atlas size; the result does not depend on it.",
    )
    # optional stages
    btf: bool = Field(False, description="Run the BTF stage (real-time target).")
    btf_table: Literal["point", "cell"] = Field(
        "point",
        description="What the BTF stores per direction pair: 'point', Eq. 7 at the pair itself "
        "(seed 001's tables of point samples); 'cell', the BRDF averaged over the pair's cell "
        "(the directions its nearest look-up answers for), so a lobe narrower than a cell is "
        "not aliased: 5.3 dB better on the bolt's polished metal, 0.3 dB worse on the cylinder's "
        "Phong, 1.7-1.9x the cpm stage's time (benchmarks/btf_tables.py).",
    )
    btf_cell_draws: int = Field(
        4, ge=1, le=256,
        description="Draws per direction cell for btf_table='cell', besides the pair itself "
        "(the BRDF is evaluated 1 + this many times per pair; visibility stays at the pair).",
    )
    previews: bool = Field(False, description="Render previews after export.")
    # deformed frames (seed 002 §4): an animated preview after export, when there is motion
    warp: str = Field(
        "", max_length=200,
        description="A procedural warp whose sweep from the identity the deformed previews show, "
        "e.g. 'bend:angle=90' (texelbake.deform.warps); empty: the asset's own animation, if "
        "it has one. Only with previews.",
    )
    deform_frames: int = Field(9, ge=2, le=240, description="Frames of the deformed preview.")
    # surface reflectance field (seed 002 §3, §5): captured with gt, sharded by camera
    srf: bool = Field(False, description="Capture a surface reflectance field of M_org beside "
                      "the bake (render mode srf).")
    srf_cameras: int = Field(216, ge=1, le=4096, description="Capture cameras on a sphere "
                             "(seed 002: 216-432).")
    srf_lights: int = Field(44, ge=1, le=1024, description="Directional capture lights on a "
                            "sphere (seed 002: 44-60).")
    srf_size: int = Field(48, ge=2, le=4096, description="Capture image side (pixels).")
    srf_spp: int = Field(16, ge=1, le=4096, description="Eye rays per pixel of a capture image.")
    srf_shard_cameras: int = Field(24, ge=1, le=4096, description="Cameras per srf shard.")

    @model_validator(mode="after")
    def _check(self) -> BakeSettings:
        for name in ("atlas_resolution", "avis_resolution", "shard_texels"):
            v = getattr(self, name)
            if v & (v - 1):
                raise ValueError(f"{name} must be a power of two, got {v}")
        px = self.lod_switch_px
        if not px or len(px) > 8 or any(not p > 0 for p in px) or any(
                b >= a for a, b in zip(px, px[1:], strict=False)):
            raise ValueError(f"lod_switch_px must be 1 to 8 decreasing positive sizes, got {px}")
        if self.warp:
            check_warp_spec(self.warp)
        if self.refit_shrink and self.refit_validation:
            raise ValueError("refit_shrink and refit_validation are two rules for the same "
                             "refit (shrink towards the fit's weights, or all or nothing): "
                             "choose one")
        if self.shard_texels > self.atlas_resolution:
            raise ValueError(
                f"shard_texels ({self.shard_texels}) must not exceed atlas_resolution "
                f"({self.atlas_resolution})"
            )
        return self

    def digest(self, *fields: str) -> str:
        """Hex digest of the given fields (all when none): content-derived artifact names."""
        data = self.model_dump()
        if fields:
            data = {k: data[k] for k in fields}
        return hashlib.sha256(json.dumps(data, sort_keys=True).encode()).hexdigest()[:16]
