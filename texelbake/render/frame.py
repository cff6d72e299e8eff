"""The renderer: a wavefront ray tracer over open3d/Embree and its modes (seed 000 §4.2, §5).

Every mode traces all eye rays of a pass at once (`camera.eye_rays`), shades the hits with
whole-array numpy and sums the samples of each pixel with a box filter; loops run over sample
passes, lights, levels and materials only.

Modes (all read the baked USD through `texelbake.usd.read.read_baked` and the copied source):

- ``gt`` — M_org, stratified eye rays, direct light with shadow rays against M_org
  (`shade.direct_radiance`).
- ``cpm`` — characteristic point maps, Eq. 12 of seed 000:
  f̄_r(p; ωi, ωo) = 1/a_vis(p, ωo) Σ_k V(x̂k, ωi) V(x̂k, ωo) f_r(x̂k, ωi, ωo) (n_k·ωi)⁺
  (n_gk·ωo)⁺ w_k, radiance L = Σ_l E_l f̄_r (the weights w_k include α_k and ΔA, so E_l times
  the sum is already the radiance; cos_i on the shading normal, cos_o on the geometric normal,
  as `texelbake.cpm.level.fit_level` built R). The mesh M_i is picked per frame by projected size
  (`choose_mesh`), the texel and mip level j per eye ray from its ray differential (pixel
  footprint → atlas footprint, each of the spp stratified eye rays at its 1/spp share of
  it: `footprint`), trilinear across texels and levels; where the pixel's footprint is
  below the finest level (the viewer is closer) the ray falls back to M_org. The outline is
  M_org's: an eye ray that hits M_i (which encloses M_org) but misses M_org sees the
  background (`coverage`, one any-hit ray per hit).
  *Per-frame texel radiance.* Seed 000 §3.1 assumes a distant viewer and distant lights per
  texel: ωo is one direction per texel. texelbake takes it from the texel's weighted
  characteristic-point centroid toward the camera position, and per light ωi from each point
  (exact for point lights). With that, Eq. 12 for every texel of every level depends on the
  frame but not on the pixel: it is evaluated once per frame for all texels (one shadow ray
  per point and light, one view ray per point toward the camera, a segment sum over the CSR
  and one a_vis look-up per texel), and the eye rays only fetch and blend texel radiances —
  the hint of the issue, carried to the view term. The cost per pixel is then an eye ray on
  M_i, which is what makes CPM many times faster than multi-sampling M_org.
  Inter-object shadows: the seed tests a shadow ray on the other objects' M_i; here every
  characteristic point's shadow ray is cast against the whole M_org (all objects of the
  asset), which covers both that test and intra-object shadowing V(x̂k, ωi) (docs/decisions.md).
  Local lights (§4.2): the mip level is also capped so that the distance to each point
  light is at least `local_light_ratio` texel sizes (ωi about constant across the texel).
- ``normalmap`` — the baseline studios bake today: M1 with the baked albedo and tangent-space
  normal maps, multi-sampled, the material's BRDF with its Lambertian part replaced by the
  albedo map (`normalmap_brdf`), shadows on M1.
- ``btf`` — the real-time target (seed 001 §3.4): M1 with the baked BTF maps
  (`btf_eigen.exr`, `btf_weights.exr`, `btf_lut.exr`, `btf_pairs.exr` beside the baked USD,
  written when `BakeSettings.btf` is on). Per light L = E_l V(p, ωi) f̄(ωi, ωo) with f̄ from
  `texelbake.btf.btf_lookup` (Eq. 7 of seed 001, continuous LOD): f̄ is the filtered
  reflectance of seed 000 Eq. 7, (Σ f V V cos_i cos_o ΔA)/a_vis, which already carries both
  cosines, so it is multiplied by the irradiance E_l only. ωi, ωo are expressed in the texel
  frame of the finest texel under the hit (`levels[0]["frames"]`, rows t, b, n), shadows are
  traced on M1 (as ``normalmap``), and λ comes from the pixel footprint exactly as in ``cpm``
  (clamped to [0, λ_max] by the look-up). Not in `MODES` (previews and reports iterate MODES
  and most bakes carry no BTF maps); `render_frame` accepts it through `EXTRA_MODES`.
- ``toksvig``, ``leadr`` (each also ``+ao``), ``preview-surface`` — the filtered baselines
  studios ship: the mip-mapped normal map with Toksvig's widened lobe
  (`render.toksvig`), LEAN/LEADR from the baked slope moments (`render.leadr`), the baked AO
  multiplied into the albedo term, and each LOD's UsdPreviewSurface fallback evaluated as
  authored (`render.preview_surface`); the level from the pixel footprint as ``cpm``. In
  `EXTRA_MODES` (older bakes have no filtered maps).
- ``equal-time`` — M_org shaded as ``gt`` for exactly the time budget (by default the time
  of the ``cpm`` image at the given spp, measured in this call): `tracer.progressive` adds
  samples in chunks, each half the time left at the measured cost per sample, so its
  measured time lands within a few percent of the budget whatever a sample costs (the sample count per
  pixel need not be a square, nor the same in every pixel: `extras["mean_spp"]`). A stratified
  count floored from a pilot's cost would give 0.70-0.75 of cpm's time.

Timing: `RenderResult.seconds` counts the rendering of one frame (rays, shading, per-frame
precomputation), not reading the USD files and building the ray-tracing structures and the
maps' float64 arrays and search keys, which a renderer does once per scene
(`RenderScene.setup_seconds`). `report.compare_modes` times each mode's second frame (a warm
renderer, as a previewer between frames).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from texelbake.errors import SettingsError
from texelbake.render.btf import render_btf
from texelbake.render.cpm import choose_mesh, render_cpm
from texelbake.render.deformed import DEFAULT_LOOKUP, DeformedCpmFrame, vertex_lookup
from texelbake.render.leadr import render_leadr
from texelbake.render.normalmap import render_normalmap
from texelbake.render.preview_surface import render_preview_surface
from texelbake.render.scene import RenderScene
from texelbake.render.toksvig import render_toksvig
from texelbake.trace import camera as cam_mod
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.org import render_org, shade_org
from texelbake.trace.tracer import RenderResult, progressive


def _gt(scene, cam, spp, seed, **kw):
    return (*render_org(scene, cam, spp, seed), {})


def _normalmap(scene, cam, spp, seed, **kw):
    return (*render_normalmap(scene, cam, spp, seed), {})


def _baked_only(mode: str, fn, takes_kw: bool = False, **mode_kw):
    """A mode that needs a baked asset's maps (a RenderScene), not M_org alone; the caller's
    keywords reach `fn` only when it `takes_kw` (the filtered baselines take none)."""

    def run(scene, cam, spp, seed, **kw):
        if not isinstance(scene, RenderScene):
            raise SettingsError(f"field 'mode': {mode!r} needs a baked asset (RenderScene)")
        return (*fn(scene, cam, spp, seed, **mode_kw, **(kw if takes_kw else {})), {})

    return run


def _srf(scene, cam, spp, seed, **kw):  # seed 002 §3, §5 (texelbake.srf)
    from texelbake.srf.mode import render_srf_mode

    return render_srf_mode(scene, cam, **kw)


def _cpm_deformed(naive: bool):
    def run(d, cam, spp, seed, **kw):
        lookup = kw.pop("lookup", DEFAULT_LOOKUP)
        frame = DeformedCpmFrame(d, cam, choose_mesh(d, cam, kw.pop("max_error_px", 1.0)),
                                 lookup="none" if naive else lookup)
        return render_cpm(d, cam, spp, seed, frame=frame, **kw)

    return run


def _btf_deformed(naive: bool):  # seed 001's maps through the seed's L, or without
    def run(d, cam, spp, seed, **kw):
        return (*render_btf(d, cam, spp, seed, lookup=None if naive else vertex_lookup, **kw),
                {})

    return run


def _srf_deformed(naive: bool):  # the reflectance field through L, or without it
    def run(d, cam, spp, seed, **kw):
        from texelbake.srf.mode import render_srf_mode

        return render_srf_mode(d.rest, cam, warp=d.warp, use_lookup=not naive, **kw)

    return run


@dataclass(frozen=True)
class Mode:
    """How a mode renders a frame at rest and a deformed frame (`deform_scene`); None where
    it does not. Each is (scene, cam, spp, seed, **kw) -> (image, rays, coverage, extras);
    ``equal-time`` is `render_frame`'s own (it times another mode)."""

    rest: Callable[..., tuple] | None
    deformed: Callable[..., tuple] | None
    #: "main": every preview and report renders it; "extra": on request, it needs optional
    #: bake outputs; "": deformed frames only
    listed: str


#: the filtered baselines: mode -> (renderer, its keywords)
_FILTERED: dict[str, tuple[Callable[..., tuple], dict[str, Any]]] = {
    "toksvig": (render_toksvig, {}), "toksvig+ao": (render_toksvig, {"ao": True}),
    "leadr": (render_leadr, {}), "leadr+ao": (render_leadr, {"ao": True}),
    "preview-surface": (render_preview_surface, {}),
}

#: the one table of render modes, in the order reports list them
MODE_TABLE: dict[str, Mode] = {
    "gt": Mode(_gt, _gt, "main"),
    "cpm": Mode(render_cpm, _cpm_deformed(naive=False), "main"),
    "cpm-naive": Mode(None, _cpm_deformed(naive=True), ""),
    "normalmap": Mode(_normalmap, _normalmap, "main"),
    "equal-time": Mode(None, None, "main"),
    "srf": Mode(_srf, _srf_deformed(naive=False), "extra"),
    "srf-naive": Mode(None, _srf_deformed(naive=True), ""),
    "btf": Mode(_baked_only("btf", render_btf, takes_kw=True), _btf_deformed(naive=False),
                "extra"),
    "btf-naive": Mode(None, _btf_deformed(naive=True), ""),
    # the filtered-normal-map baselines studios ship; they need a bake's filtered maps
    **{m: Mode(_baked_only(m, fn, **kw), None, "extra") for m, (fn, kw) in _FILTERED.items()},
}
MODES = tuple(m for m, e in MODE_TABLE.items() if e.listed == "main")
#: modes `render_frame` accepts beyond MODES (they need optional bake outputs; ``srf``: a
#: reflectance field captured beside the bake, `texelbake.srf.mode`)
EXTRA_MODES = tuple(m for m, e in MODE_TABLE.items() if e.listed == "extra")
FILTERED_MODES = tuple(_FILTERED)
DEFORMED_MODES = tuple(m for m, e in MODE_TABLE.items()
                       if e.deformed is not None or m == "equal-time")


def render_frame(scene: RenderScene, mode: str, cam: PinholeCamera, spp: int, seed: int = 0,
                 *, budget_seconds: float | None = None, **kw) -> RenderResult:
    """Render one image of `scene` (already loaded; a frame at rest, or a deformed frame from
    `deform_scene`) in `mode` (see module docstring)."""
    deformed = hasattr(scene, "warp")
    entry = MODE_TABLE.get(mode)
    if deformed and mode not in DEFORMED_MODES:
        raise SettingsError(f"field 'mode': a deformed frame renders one of {DEFORMED_MODES}, "
                            f"got {mode!r}")
    if entry is None or (not deformed and entry.rest is None and mode != "equal-time"):
        raise SettingsError(f"field 'mode': expected one of {MODES + EXTRA_MODES}, got "
                            f"{mode!r}")
    spp = int(spp)
    cam_mod.strata(spp)  # validates spp
    t0 = time.perf_counter()
    if mode == "equal-time":
        if budget_seconds is None:
            budget_seconds = render_frame(scene, "cpm", cam, spp, seed, **kw).seconds
        if not budget_seconds >= 0:  # 0: the first pass only (one sample per pixel)
            raise SettingsError(f"field 'budget_seconds': must be >= 0, got {budget_seconds}")
        img, rays, cov, mean_spp, seconds = progressive(
            cam, seed, lambda o, d: shade_org(scene, o, d), float(budget_seconds),
            None if deformed else scene.eye_box)
        extras = {"budget_seconds": float(budget_seconds), "mean_spp": float(mean_spp)}
        return RenderResult(img.astype(np.float32), seconds, int(rays), int(mean_spp), mode,
                            extras, cov.astype(np.float32))
    fn = entry.deformed if deformed else entry.rest
    assert fn is not None  # checked above: the mode renders this kind of frame
    img, rays, cov, extras = fn(scene, cam, spp, seed, **kw)
    seconds = time.perf_counter() - t0
    return RenderResult(img.astype(np.float32), seconds, int(rays), spp, mode, extras,
                        cov.astype(np.float32))


def render_deformed(d: RenderScene, mode: str, cam: PinholeCamera, spp: int, seed: int = 0,
                    *, budget_seconds: float | None = None, **kw: Any) -> RenderResult:
    """One image of a deformed scene (`deform_scene`) in `mode` (DEFORMED_MODES)."""
    if not hasattr(d, "warp"):
        raise SettingsError("render_deformed needs a scene from deform_scene()")
    return render_frame(d, mode, cam, spp, seed, budget_seconds=budget_seconds, **kw)
