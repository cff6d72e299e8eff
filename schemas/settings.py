"""Bake settings: the one validated description of what a bake does.

Shared by the CLI, the in-process pipeline, the API (request body) and the workers. Every field has
a default so `BakeSettings()` is the embedded default bake. The JSON Schema is exported from here.
"""

from __future__ import annotations

import hashlib
import json
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from schemas.warp import check_warp_spec

#: quality-gate defaults (texelbake.stages.quality; measured in docs/decisions.md)
GATE_SNR_MEDIAN_DB = 0.0
GATE_SNR_P5_DB = -6.0
GATE_AVIS_REL_ERROR = 0.15

#: the settings' groups, in the order the API schema, `texelbake bake --help` and the dashboard
#: show them; every field names its group in the JSON Schema (`json_schema_extra["group"]`)
GROUPS = ("geometry", "fit", "a_vis", "quality gate", "farm", "optional stages")

#: largest LOD switch size in pixels (a screen is a few thousand)
MAX_SWITCH_PX = 1e6
#: largest seed: numpy's 32-bit seed range
MAX_SEED = 2**32 - 1
#: a LOD switch size: finite, positive, bounded
SwitchPx = Annotated[float, Field(gt=0.0, le=MAX_SWITCH_PX)]


def _field(default, group: str, description: str, **bounds):
    """A settings field of `group` (one of GROUPS) described in one sentence."""
    if group not in GROUPS:
        raise ValueError(f"settings group {group!r} is not one of {GROUPS}")
    return Field(default, description=description, json_schema_extra={"group": group}, **bounds)


class BakeSettings(BaseModel):
    """Settings of one bake, in the groups of GROUPS."""

    # NaN and Infinity (JSON extensions) are refused everywhere, list entries included: a
    # stored job must read back, and JSON has no spelling for them
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    # geometry
    seed: int = _field(
        0, "geometry", "Seed of every random choice of the bake, so reruns are byte-identical.",
        ge=0, le=MAX_SEED)
    atlas_resolution: int = _field(
        16, "geometry", "Side of the finest CPM level in texels over the atlas (a power of two), "
        "baked as given when atlas_mode is 'fixed'.",
        ge=2, le=4096)
    atlas_mode: Literal["fixed", "lod1"] = _field(
        "fixed", "geometry",
        "'fixed' bakes atlas_resolution, 'lod1' the smallest power of two at which a finest "
        "texel is at most one pixel where LOD1 switches in, up to atlas_cap.")
    atlas_cap: int = _field(
        1024, "geometry", "Largest atlas side atlas_mode 'lod1' may choose (a power of two).",
        ge=2, le=4096)
    lod_mode: Literal["error", "atlas"] = _field(
        "error", "geometry",
        "How the LOD meshes are sized: 'error' makes each the smallest mesh within lod_error_px "
        "of the original at its switch size, 'atlas' caps M1 by the atlas and simplifies each "
        "further level by simplify_ratio.")
    lod_switch_px: tuple[SwitchPx, ...] = _field(
        (256.0, 64.0), "geometry",
        "Decreasing screen sizes in pixels (bounding-box diagonal) at which LOD1, LOD2 and so "
        "on switch in.")
    lod_error_px: float = _field(
        1.0, "geometry",
        "Largest Hausdorff distance to the original mesh a LOD may show, in pixels at its "
        "switch size.", gt=0.0, le=64.0)
    mesh_levels: int = _field(
        2, "geometry", "Number of simplified meshes M1..Mn ('atlas' mode) or the most of them "
        "('error' mode).", ge=1, le=8)
    simplify_ratio: float = _field(
        0.25, "geometry", "Face ratio of each simplified mesh to the previous one.",
        gt=0.0, lt=1.0)
    enclose_meshes: bool = _field(
        True, "geometry",
        "Move the simplified meshes outward until they cover the original's outline; false "
        "keeps the seed's QEM meshes as they are.")
    m1_method: Literal["auto", "qem", "wrap"] = _field(
        "auto", "geometry",
        "How M1 is made: 'qem' simplifies the original (the seed), 'wrap' simplifies a surface "
        "wrapped around it, 'auto' wraps assets of many small separate parts.")
    m1_faces: int = _field(
        0, "geometry", "Target face count of M1, or 0 for simplify_ratio times the original's.",
        ge=0, le=1 << 30)
    samples_per_texel: int = _field(
        64, "geometry", "Average number of dense samples on the original mesh per finest texel.",
        ge=1, le=65536)
    sample_density: Literal["area", "detail"] = _field(
        "detail", "geometry",
        "'detail' samples a flat, constant-material face of at least a texel's area at a "
        "quarter of the density and every other face at samples_per_texel, 'area' samples "
        "every face at samples_per_texel as the seed.")
    # characteristic points (seed 000 §3)
    n_light_dirs: int = _field(
        64, "fit", "Number of light directions of the texel-frame grid.", ge=1, le=4096)
    n_view_dirs: int = _field(
        64, "fit", "Number of view directions of the texel-frame grid.", ge=1, le=4096)
    n_heldout: int = _field(
        256, "fit", "Number of held-out direction pairs per texel on which the fit is scored.",
        ge=0, le=65536)
    heldout_texels: int = _field(
        256, "fit",
        "Number of texels per level, a seeded sample, on which the held-out SNR is measured "
        "(every texel of a level that has fewer); 0 measures every texel.", ge=0, le=1 << 30)
    heldout_samples: int = _field(
        16384, "fit",
        "Dense samples per measured texel over which its held-out truth is summed: a texel "
        "with more sums a seeded subset of about this many, scaled by its area over theirs; "
        "0 sums every sample.", ge=0, le=1 << 30)
    psi: float = _field(
        0.97, "fit", "Energy fraction of the selection matrix that fixes its rank k.",
        gt=0.0, le=1.0)
    eps_db: float = _field(
        30.0, "fit", "Target in-sample SNR in dB of the bisection on the number of points.",
        gt=0.0, le=200.0)
    c_max: int = _field(
        64, "fit", "Largest number of characteristic points per texel.", ge=1, le=4096)
    n_trials: int = _field(
        4, "fit", "Random column draws per probed number of points, the best one kept.",
        ge=1, le=64)
    small_texels: Literal["all", "fit"] = _field(
        "all", "fit",
        "'all' lets a texel of at most c_max candidates keep every one unless one point is "
        "exact, 'fit' runs the seed's bisection on it too.")
    weights: Literal["nnls", "clamp"] = _field(
        "nnls", "fit",
        "How point weights are solved: 'nnls' by non-negative least squares, 'clamp' by the "
        "seed's least squares with negative weights set to zero.")
    colour: Literal["auto", "luminance", "per_channel"] = _field(
        "auto", "fit",
        "Whether points are selected on luminance or per colour channel ('auto' decides per "
        "texel by decorrelation_threshold).")
    decorrelation_threshold: float = _field(
        0.9, "fit", "Channel correlation below which colour='auto' selects points per channel.",
        ge=-1.0, le=1.0)
    n_batch: int = _field(
        1024, "fit", "Most candidate columns in one selection; wider texels are selected in "
        "batches.", ge=16, le=1 << 20)
    hierarchy: Literal["children", "grandchildren", "dense"] = _field(
        "children", "fit",
        "Where a coarse texel's candidates come from: 'children' its children's weighted "
        "points, 'grandchildren' the weighted points two levels down, 'dense' all its dense "
        "samples as the seed.")
    fit_method: Literal["batched", "per_texel"] = _field(
        "batched", "fit",
        "'batched' fits many texels at once from their Gram matrices, 'per_texel' fits one "
        "texel at a time on its matrix as the seed.")
    texel_classes: Literal["by_need", "points"] = _field(
        "by_need", "fit",
        "'by_need' stores a texel whose samples form at most c_max groups of one facet, one "
        "material response and one visibility pattern as a point per group before any fit "
        "(one exact point for one group); 'points' fits every texel as the seed.")
    classed_levels: int = _field(
        3, "fit",
        "Levels, from the finest, whose texels 'by_need' classes (the coarser ones are fitted); "
        "each must lie inside a shard's tile: shard_texels >= 2^(classed_levels - 1) or the "
        "atlas side.", ge=1, le=13)
    point_lobe: Literal["narrow", "widened"] = _field(
        "widened", "fit",
        "'widened' gives a fitted characteristic point the normal spread of the surface it "
        "stands for where validation pairs favour it (its GGX or Phong lobe widened by its "
        "cell's slope variance; fit_method 'batched' only, and 'narrow' when unset under "
        "'per_texel'), 'narrow' keeps the sample's own lobe as the seed.")
    lobe_class: Literal["off", "validated"] = _field(
        "off", "fit",
        "'validated' stores a finest texel of one material and one visibility pattern "
        "whose normals spread (a curved texel) as a few points about its mean normals, each "
        "GGX or Phong lobe widened by its cell's slope variance (LEADR), where they reach "
        "eps_db on validation pairs without the fit (fit_method 'batched' and texel_classes "
        "'by_need' only); 'off' gives such texels to the fit.")
    level0_candidates: Literal["dense", "clustered"] = _field(
        "clustered", "fit",
        "'clustered' offers a fitted finest texel one candidate per group of its dense samples "
        "of one material and normals within a few degrees (and, where the texel may be "
        "shadowed, one part of its extent; the group's area its weight, its normal spread its "
        "point's lobe widening; fit_method 'batched', texel_classes 'by_need' and lobe "
        "variances only, and 'dense' when unset without them), 'dense' every dense sample as "
        "the seed.")
    identical_columns: Literal["keep", "merge"] = _field(
        "merge", "fit",
        "'merge' fits candidates with identical columns as one weighted column, 'keep' fits "
        "every candidate as its own column as the seed.")
    # visible projected area (seed 000 §3.4)
    avis_resolution: int = _field(
        32, "a_vis", "Face resolution of the a_vis cube maps (a power of two).", ge=2, le=256)
    avis_keep_fraction: float = _field(
        0.03, "a_vis", "Fraction of a level's dense cube pixels kept as Haar coefficients.",
        gt=0.0, le=1.0)
    avis_coarse: Literal["children", "dense"] = _field(
        "children", "a_vis",
        "Where the fit of a coarse level gets its a_vis: 'children' from its children's summed "
        "cube maps read at its own directions, 'dense' from rays of every dense sample as the "
        "seed.")
    avis_fit_samples: int = _field(
        16384, "a_vis",
        "Dense samples per texel from which a coarse level's fit casts its a_vis rays "
        "(avis_coarse 'dense'): a texel with more casts from every k-th of its samples in "
        "Z-order, scaled by its area over theirs; 0 casts from every sample as the seed.",
        ge=0, le=1 << 30)
    avis_level0: Literal["dense", "by_need"] = _field(
        "dense", "a_vis",
        "Which samples cast the finest level's a_vis rays: 'dense' every dense sample, "
        "'by_need' one sample of a one-facet texel with one visibility pattern and 16 "
        "area-weighted samples of any other texel.")
    avis_selection: Literal["texel", "face"] = _field(
        "texel", "a_vis",
        "How the Haar coefficients are chosen: 'texel' evens the relative error over texels, "
        "'face' keeps the seed's top fraction per cube face.")
    # quality gate (texelbake.stages.quality): targets, not inputs of any stage
    gate_snr_median_db: float = _field(
        GATE_SNR_MEDIAN_DB, "quality gate",
        "Held-out SNR median in dB that each CPM level must reach.", ge=-200.0, le=200.0)
    gate_snr_p5_db: float = _field(
        GATE_SNR_P5_DB, "quality gate",
        "Held-out SNR 5th percentile in dB that each CPM level must reach.",
        ge=-200.0, le=200.0)
    gate_avis_rel_error: float = _field(
        GATE_AVIS_REL_ERROR, "quality gate",
        "Relative L2 error of the compressed a_vis that each CPM level must stay below.",
        gt=0.0, le=10.0)
    # farm
    shard_texels: int = _field(
        8, "farm", "Side in finest texels of the tile one shard fits (a power of two).",
        ge=1, le=4096)
    worker_memory_mb: int = _field(
        512, "farm",
        "Working memory in MiB of one worker's CPM fit, which never changes its result.",
        ge=64, le=1 << 20)
    # optional stages
    btf: bool = _field(False, "optional stages", "Run the BTF stage for real-time rendering.")
    btf_table: Literal["point", "cell"] = _field(
        "point", "optional stages",
        "What the BTF stores per direction pair: 'point' Eq. 7 at the pair itself (the seed's "
        "point samples), 'cell' the BRDF averaged over the pair's cell.")
    btf_cell_draws: int = _field(
        4, "optional stages",
        "Extra BRDF draws per direction cell when btf_table is 'cell'.", ge=1, le=256)
    previews: bool = _field(False, "optional stages", "Render previews after export.")
    fallback: Literal["averaged", "fitted"] = _field(
        "averaged", "optional stages",
        "How each LOD's UsdPreviewSurface fallback gets its inputs: 'averaged' from the area "
        "means of the source material's inputs with a widened roughness; 'fitted' the same "
        "with each LOD's diffuseColor times a smooth gain fitted to the texels' filtered "
        "reflectance (shadowing and masking), chosen on held-out samples.")
    # deformed frames (seed 002 §4): an animated preview after export, when there is motion
    warp: str = _field(
        "", "optional stages",
        "Procedural warp such as 'bend:angle=90' whose sweep the deformed previews show, or "
        "empty for the asset's own animation.", max_length=200)
    deform_frames: int = _field(
        9, "optional stages", "Number of frames of the deformed preview.", ge=2, le=240)
    # surface reflectance field (seed 002 §3, §5): captured with gt, sharded by camera
    srf: bool = _field(
        False, "optional stages",
        "Capture a surface reflectance field of the original mesh beside the bake.")
    srf_cameras: int = _field(
        216, "optional stages", "Number of capture cameras on a sphere.", ge=1, le=4096)
    srf_lights: int = _field(
        44, "optional stages", "Number of directional capture lights on a sphere.",
        ge=1, le=1024)
    srf_size: int = _field(
        48, "optional stages", "Side in pixels of a capture image.", ge=2, le=4096)
    srf_spp: int = _field(
        16, "optional stages", "Eye rays per pixel of a capture image.", ge=1, le=4096)
    srf_shard_cameras: int = _field(
        24, "optional stages", "Number of capture cameras per srf shard.", ge=1, le=4096)

    @model_validator(mode="before")
    @classmethod
    def _seed_lobe_with_seed_loop(cls, data: Any) -> Any:
        """point_lobe left unset takes 'narrow' under fit_method 'per_texel' (the seed's loop
        has no widened lobes), and level0_candidates left unset 'dense' where its groups'
        lobes cannot be carried (narrow lobes, no lobe class) or no texel is classed (the
        seed's path); set explicitly, the pairs are checked below."""
        if not isinstance(data, dict):
            return data
        if "point_lobe" not in data and data.get("fit_method") == "per_texel":
            data = {**data, "point_lobe": "narrow"}
        if "level0_candidates" not in data and (
                data.get("point_lobe") == "narrow" and data.get("lobe_class", "off") == "off"
                or data.get("texel_classes") == "points"
                or data.get("fit_method") == "per_texel"):
            data = {**data, "level0_candidates": "dense"}
        return data

    @model_validator(mode="after")
    def _check(self) -> BakeSettings:
        for name in ("atlas_resolution", "atlas_cap", "avis_resolution", "shard_texels"):
            v = getattr(self, name)
            if v & (v - 1):
                raise ValueError(f"{name} must be a power of two, got {v}")
        px = self.lod_switch_px
        if not px or len(px) > 8 or any(not p > 0 for p in px) or any(
                b >= a for a, b in zip(px, px[1:], strict=False)):
            raise ValueError(f"lod_switch_px must be 1 to 8 decreasing positive sizes, got {px}")
        if self.warp:
            check_warp_spec(self.warp)
        tile_needs = min(1 << (self.classed_levels - 1), self.atlas_resolution)
        if self.texel_classes == "by_need" and self.shard_texels < tile_needs:
            # a classed level must be inside the tiles: a top level is fitted from the tiles'
            # sums without its samples, so classing it would make the result depend on the
            # tiling
            raise ValueError(
                f"shard_texels ({self.shard_texels}) must be at least {tile_needs} for "
                f"classed_levels {self.classed_levels} (texel_classes 'by_need'): a classed "
                "level must lie inside a shard's tile")
        if self.point_lobe == "widened" and self.fit_method != "batched":
            raise ValueError("point_lobe 'widened' needs fit_method 'batched' (the seed's "
                             "per-texel loop keeps the narrow lobe)")
        if self.level0_candidates == "clustered" and (
                self.fit_method != "batched" or self.texel_classes != "by_need"
                or (self.point_lobe == "narrow" and self.lobe_class == "off")):
            raise ValueError("level0_candidates 'clustered' needs fit_method 'batched', "
                             "texel_classes 'by_need' and lobes that carry their spread "
                             "(point_lobe 'widened' or a lobe_class): a group's point is "
                             "widened by its normals' spread")
        if self.lobe_class != "off" and (self.fit_method != "batched"
                                         or self.texel_classes != "by_need"):
            raise ValueError("lobe_class 'validated' needs fit_method 'batched' and "
                             "texel_classes 'by_need' (it is a class of the classed texels)")
        # atlas_mode "lod1" chooses the atlas and keeps the tiles within it (resolve_settings)
        if self.atlas_mode == "fixed" and self.shard_texels > self.atlas_resolution:
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
