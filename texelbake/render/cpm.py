"""``cpm``: characteristic point maps, Eq. 12 of seed 000 (see `texelbake.render.frame`),
per-frame texel radiance, trilinear look-ups at each eye ray's footprint, the outline from
M_org, and the fall-back to M_org closer than the finest level."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from texelbake.errors import SettingsError
from texelbake.geometry.texels import bilinear_texels
from texelbake.render.scene import RenderScene, atlas_uv_prim, ray_atlas_uv
from texelbake.render.texel_radiance import texel_radiance
from texelbake.trace.camera import PinholeCamera
from texelbake.trace.org import shade_org
from texelbake.trace.shade import light_at
from texelbake.trace.tracer import enters_box, eye_passes, frame_pixels, ray_slices


def choose_mesh(scene: RenderScene, cam: PinholeCamera, max_error_px: float = 1.0) -> int:
    """Index i (0 = M1) of the coarsest M_i whose distance to M_org (vertex Hausdorff
    estimate) projects to at most `max_error_px` pixels at the bounding box's nearest point;
    M1 when none does (seed 000 §4.2: level chosen by projected size)."""
    lo, hi = scene.asset.bounds
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo))
    dist = max(float(np.linalg.norm(centre - cam.position)) - radius, 1e-9 * scene.diag)
    for i in range(len(scene.lods) - 1, 0, -1):
        if scene.lod_error[i] / (dist * cam.pixel_angle) <= max_error_px:
            return i
    return 0


class CpmFrame:
    """Per-frame data of the cpm mode: the texel radiance of each level, computed the first
    time a sample needs that texel (a frame touches the texels it sees, on the levels its
    footprints select: far views only coarse levels, and never the back of the object)."""

    def __init__(self, scene: RenderScene, cam: PinholeCamera, mesh: int) -> None:
        self.scene = scene
        self.cam_pos = np.asarray(cam.position, dtype=np.float64)
        self.mesh = mesh
        self.n_levels = len(scene.baked.levels)
        # per level: radiance, a_vis, exists, computed, requested
        self._levels: dict[int, tuple[np.ndarray, ...]] = {}
        self.rays = 0

    def _arrays(self, j: int) -> tuple[np.ndarray, ...]:
        if j not in self._levels:
            n = self.scene.baked.levels[j]["texel_offsets"].shape[0] - 1
            self._levels[j] = (np.zeros((n, 3)), np.zeros(n), np.zeros(n, bool),
                               np.zeros(n, bool), np.zeros(n, bool))
        return self._levels[j]

    def request(self, j: int, texels: np.ndarray) -> None:
        """Mark texels (ids, any shape) of level j as needed by the next `flush`."""
        self._arrays(j)[4][np.asarray(texels).ravel()] = True

    def flush(self) -> None:
        """Compute every requested texel not yet computed: one `texel_radiance` call per
        level (each call has a fixed cost; a frame's look-ups would otherwise make dozens)."""
        for j in sorted(self._levels):
            wanted, done = self._levels[j][4], self._levels[j][3]
            self._compute(j, np.flatnonzero(wanted & ~done))

    def _compute(self, j: int, todo: np.ndarray) -> None:
        if todo.size:
            rad, avis, ex, done, _ = self._arrays(j)
            r, a, e, n_rays = texel_radiance(self.scene, j, self.cam_pos, todo)
            rad[todo], avis[todo], ex[todo], done[todo] = r, a, e, True
            self.rays += n_rays

    def level(self, j: int, texels: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(radiance (n_j², 3), a_vis (n_j²,), exists (n_j²,) bool) of level j, computed
        for `texels` (ids, any shape) if not yet; other entries may be unset."""
        rad, avis, ex, done, _ = self._arrays(j)
        want = np.unique(texels)
        self._compute(j, want[~done[want]])
        return rad, avis, ex


def cpm_frame(scene: RenderScene, cam: PinholeCamera, max_error_px: float = 1.0) -> CpmFrame:
    """The per-frame state of the cpm mode (mesh M_i chosen, texel radiance on demand)."""
    return CpmFrame(scene, cam, choose_mesh(scene, cam, max_error_px))


def _lookup_level(frame: CpmFrame, level: int, idx: np.ndarray, w: np.ndarray,
                  filtering: str = "projected") -> tuple[np.ndarray, np.ndarray]:
    """Bilinear texel radiance at one level; weights of texels without points are dropped.

    idx, w : (n, 4) the bilinear texels and weights (`geometry.texels.bilinear_texels`)
    filtering : "projected" — each texel weighted by its bilinear weight times its visible
        projected area a_vis toward the viewer, L = Σ w a L / Σ w a = Σ w num / Σ w a (the
        pixel integrates radiance over the visible projected area, and a_vis is exactly that
        per texel; a masked texel adds nothing instead of darkening its neighbours, and the
        a_vis -> 0 limit needs no special case); "radiance" — plain bilinear of L (what a
        texture unit does); checked by `_check_cpm_options`.
    returns : (radiance (n, 3), weight sum (n,) — 0 where no texel around uv exists)"""
    radiance, avis, exists = frame.level(level, idx)
    w = w * exists[idx]
    s = w.sum(axis=1)
    if filtering == "projected":
        wa = w * avis[idx]
        sa = wa.sum(axis=1)
        rad = np.einsum("nk,nkc->nc", wa, radiance[idx])
        return np.divide(rad, sa[:, None], out=np.zeros_like(rad), where=sa[:, None] > 0), s
    rad = np.einsum("nk,nkc->nc", w, radiance[idx])
    return np.divide(rad, s[:, None], out=np.zeros_like(rad), where=s[:, None] > 0), s


def footprint_level(scene: RenderScene, cam: PinholeCamera, mesh: int, prim: np.ndarray,
                    p: np.ndarray, o: np.ndarray, d: np.ndarray,
                    ratio: np.ndarray | None = None, normal: np.ndarray | None = None
                    ) -> np.ndarray:
    """Mip level λ (unclipped, finest = 0) of eye-ray hits on M_i from the ray differential:
    the pixel's footprint on the hit triangle (screen-space derivatives, seed 000 §4.2; the
    footprint of the pixel, not of the sample, as texture hardware does under multi-sampling),
    mapped into the atlas by the uv density of the triangle the uv was read from. Used by the
    cpm and btf modes.

    prim (k,) hit triangles of M_{mesh+1}; p (k, 3) hit points; o, d (k, 3) their eye rays;
    ratio (k,) atlas uv area per world area and normal (k, 3) the unit normal of the surface
    the hits read the atlas on (default: the hit triangle's own, `RenderScene.lod_uv_ratio`,
    `lod_face_normals`)"""
    t = np.linalg.norm(p - o, axis=1)
    if normal is None:
        normal = scene.lod_face_normals[mesh][prim]
    cos_t = np.maximum(np.abs(np.einsum("ij,ij->i", normal, d)), 1e-3)
    cos_p = np.clip(d @ cam.forward, 1e-3, 1.0)
    area_world = (t * cam.pixel_angle) ** 2 * cos_p ** 3 / cos_t
    if ratio is None:
        ratio = scene.lod_uv_ratio[mesh][prim]
    return 0.5 * np.log2(np.maximum(area_world * ratio, 1e-300)) + math.log2(scene.n0)


#: where a hit on a coarser M_i reads the atlas: "ray" (default) — where the eye ray, carried
#: on, meets the atlas mesh (LOD1 or M_T) inside M_i; "closest" — seed 000 §4.1's composite
#: map T(T_i(·)), M_i's own uvs or the closest atlas-mesh point (the rays that miss the atlas
#: mesh, under M_i's rim, take it with either)
UV_FROM = ("ray", "closest")


def _check_cpm_options(filtering: str, footprint: str, uv_from: str = "ray") -> None:
    """The cpm mode's string options, checked before any ray is cast."""
    if filtering not in ("projected", "radiance"):
        raise SettingsError(f"field 'filtering': 'projected' or 'radiance', got {filtering!r}")
    if footprint not in ("sample", "pixel"):
        raise SettingsError(f"field 'footprint': 'sample' or 'pixel', got {footprint!r}")
    if uv_from not in UV_FROM:
        raise SettingsError(f"field 'uv_from': one of {UV_FROM}, got {uv_from!r}")


def _cpm_prepare(scene: RenderScene, frame: CpmFrame, cam: PinholeCamera, o: np.ndarray,
                 d: np.ndarray, *, lod_bias: float = 0.0, local_light_ratio: float = 8.0,
                 spp: int = 1, footprint: str = "sample", coverage: bool = True,
                 uv_from: str = "ray") -> dict[str, Any]:
    """First half of `shade_cpm`: eye rays against M_i, atlas uv, mip level λ of every hit;
    the texels the look-ups will read are requested from `frame` (computed in one batch by
    `CpmFrame.flush`).

    footprint : "sample" (default) — each of the `spp` stratified eye rays of a pixel looks
        up the maps at its own footprint, a 1/spp share of the pixel's (λ lower by
        ½ log2 spp, at least the finest level), and the box filter over the samples does the
        rest, as texture look-ups under supersampling do; "pixel" — every sample at the
        pixel's footprint (the level a single-sample renderer would use: under
        supersampling it blurs twice; on the full wall at 4 spp it cost 0.7 dB). Either
        way M_org is used where the *pixel's* footprint is below the finest level.
    coverage : an eye ray that hits M_i but misses M_org sees the background (one any-hit
        ray against M_org per hit; applied in `_cpm_finish`). M_i lies a little outside M_org
        (it encloses it, and a wrap is rounded at its rim), and without this test the rim it
        adds around the outline shows the full radiance of the sliver of surface inside its
        texels (the full wall: 8 % too much light, 43 % of its error at the outline). The
        texels still give the radiance: the test only decides whether the ray is covered,
        which is what M_org's outline does in gt. The other way round, an eye ray that misses
        M_i but meets M_org (an open surface's edge under the rim of an enclosing M_i: 473 of
        a grazing view's 6,720 object pixels on a bumpy open field) is shaded from M_org
        (`_outline_misses`; `_cpm_finish` treats it as a fallback ray).
    uv_from : UV_FROM. A coarser M_i lies up to its error outside the atlas mesh, and a point
        of M_i maps (by its own uvs, or by the closest point, seed 000 §4.1) to the atlas-mesh
        point under it, not to the one the eye ray would meet behind it: at grazing angles,
        i.e. along the outline, the two are h / tan θ apart — a parallax of texels. On the
        full cylinder at its lod view (72 object pixels, 64² atlas, M2 chosen at 0.19 px of
        Hausdorff error) that cost 3 dB: 19.6–20.8 dB against 22.7–25.2 with the ray's own
        atlas point, the same as rendering M1 (docs/decisions.md).
        "ray" casts each M_i hit's eye ray on against the atlas mesh (one more ray per hit,
        M_i ≠ the atlas mesh only)."""
    i = frame.mesh
    mesh = scene.baked.meshes[i]
    hits = scene.lods[i].cast(o, d)
    idx = np.flatnonzero(hits.hit)
    h: dict[str, Any] = {"n": o.shape[0], "idx": idx, "rays": o.shape[0],
                         "outline": np.zeros(0, np.int64)}
    if coverage:  # the other half of M_org's outline: rays that miss M_i but meet M_org
        h["outline"], traced = _outline_misses(scene, cam, d, hits.hit)
        h["rays"] += traced
    if idx.size == 0:
        return h
    prim = hits.prim[idx]
    b = hits.bary3()[idx]
    p = np.einsum("nk,nkj->nj", b, mesh.vertices[mesh.faces[prim]])
    uv = np.einsum("nk,nkj->nj", b, mesh.corner_uvs[prim])
    inexact = ~scene.lod_uv_exact[i][prim]
    # the footprint is taken where the uv is read: on M_i's own triangle, or on the
    # atlas-mesh triangle the look-up maps to, with its uv density and slope (a coarse or a
    # deformed-and-refined M_i's own uv density says nothing about the atlas: a refined M2
    # of the 2:1-stretched full cylinder put λ 1.1 levels low, and 80 % of the eye rays
    # fell back to M_org)
    ratio = scene.lod_uv_ratio[i][prim].copy()
    normal = scene.lod_face_normals[i][prim].copy()
    if uv_from == "ray" and (i > 0 or scene.atlas_separate):  # the ray's own atlas point
        # an atlas-mesh hit deeper than twice M_i's distance to M_org (+ the atlas mesh's
        # own) below the M_i hit is another part of the object, reached under M_i's rim
        depth = 2.0 * (scene.lod_error[i] + scene.lod_error[0]) + 1e-6 * scene.diag
        ruv, met, tri = ray_atlas_uv(scene, o[idx], d[idx], p, normal, depth)
        h["rays"] += idx.size
        uv[met] = ruv[met]
        ratio[met] = scene.atlas_uv_ratio[tri[met]]
        normal[met] = scene.atlas_face_normals[tri[met]]
        inexact &= ~met
    if inexact.any():  # the exact composite map: closest point on M1, its atlas uv
        uv[inexact], tri = atlas_uv_prim(scene, p[inexact])
        ratio[inexact] = scene.atlas_uv_ratio[tri]
        normal[inexact] = scene.atlas_face_normals[tri]
    lam = footprint_level(scene, cam, i, prim, p, o[idx], d[idx], ratio, normal) + lod_bias
    s0 = 1.0 / (scene.n0 * np.sqrt(ratio))  # world size of a finest texel
    for light in scene.lights:  # local lights: keep ωi about constant across a texel
        if light.kind != "distant":
            _, _, dist = light_at(light, p)
            lam = np.minimum(lam, np.log2(np.maximum(dist / (local_light_ratio * s0),
                                                     1e-300)))
    n_lv = frame.n_levels
    use = lam >= 0.0
    covered = None
    if coverage:  # does the eye ray meet M_org at all (any hit)
        covered = scene.org.occluded(o[idx], d[idx])
        h["rays"] += idx.size
    if footprint == "sample":
        lam = lam - 0.5 * math.log2(max(int(spp), 1))
    lam_c = np.clip(lam, 0.0, n_lv - 1.0)
    j0 = np.floor(lam_c).astype(np.int64)
    fr = lam_c - j0
    # per level, the samples reading it (weight 1 - fr at j0, fr at j0 + 1) and their texels
    reads = []
    for j in range(n_lv):  # a loop over the few levels; each sample touches two
        for sel, up in ((np.flatnonzero(use & (j0 == j)), False),
                        (np.flatnonzero(use & (j0 + 1 == j) & (fr > 0)), True)):
            if sel.size:
                tex, w = bilinear_texels(uv[sel], max(scene.n0 >> j, 1))
                frame.request(j, tex)
                reads.append((j, sel, up, tex, w))
    h.update(use=use, lam_c=lam_c, fr=fr, reads=reads, covered=covered)
    return h


def _cpm_finish(scene: RenderScene, frame: CpmFrame, o: np.ndarray, d: np.ndarray,
                h: dict[str, Any], filtering: str = "projected"
                ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """Second half of `shade_cpm`: trilinear look-ups of the texel radiance, M_org where the
    maps do not apply; rays that miss M_org are background when `_cpm_prepare` tested
    coverage. returns (radiance (n, 3), level (n,), rays cast, hit (n,) bool: the ray sees
    the object)"""
    n, idx, rays = h["n"], h["idx"], h["rays"]
    out = np.zeros((n, 3))
    level = np.full(n, np.nan)
    hit = np.zeros(n, dtype=bool)
    edge = h["outline"]
    if edge.size:  # missed M_i, met M_org: shaded from M_org
        out[edge], r_edge, hit[edge] = shade_org(scene, o[edge], d[edge])
        rays += r_edge
        level[edge] = -1.0
    if idx.size == 0:
        return out, level, rays, hit
    use, lam_c, fr = h["use"], h["lam_c"], h["fr"]
    rad = np.zeros((idx.size, 3))
    wsum = np.zeros(idx.size)
    for j, sel, up, tex, w in h["reads"]:
        r, s = _lookup_level(frame, j, tex, w, filtering)
        weight = (fr[sel] if up else 1.0 - fr[sel]) * (s > 0)
        rad[sel] += weight[:, None] * r
        wsum[sel] += weight
    ok = use & (wsum > 0)
    out[idx[ok]] = rad[ok] / wsum[ok, None]
    hit[idx[ok]] = True
    if h["covered"] is not None:
        out[idx[ok & ~h["covered"]]] = 0.0
        hit[idx[ok & ~h["covered"]]] = False
    level[idx[ok]] = lam_c[ok]
    # closer than the finest level (or no texel there): multi-sample M_org
    fb = idx[~ok]
    if fb.size:
        out[fb], r_fb, hit[fb] = shade_org(scene, o[fb], d[fb])
        rays += r_fb
        level[fb] = -1.0
    return out, level, rays, hit


def _outline_misses(scene: RenderScene, cam: PinholeCamera, d: np.ndarray,
                    hit_mi: np.ndarray) -> tuple[np.ndarray, int]:
    """(indices of the eye rays that miss M_i but meet M_org, rays traced). Eye rays start at
    the camera, so a ray can meet M_org only if it passes within M_org's bounding sphere
    (one mat-vec over the directions); only those are traced, one any-hit ray each. Measured
    on the full wall at 512², 4 spp: a per-ray slab test cost 0.1-0.2 s per frame, this
    ~3 ms."""
    lo, hi = np.asarray(scene.asset.bounds, dtype=np.float64)
    centre = 0.5 * (lo + hi)
    radius = 0.5 * float(np.linalg.norm(hi - lo)) + scene.ray_eps
    v = centre - cam.position
    t = d @ v  # distance along each unit direction to the point nearest the centre
    near = np.flatnonzero(~hit_mi & (float(v @ v) - t * t <= radius * radius) & (t > -radius))
    if near.size == 0:
        return near, 0
    o = np.broadcast_to(cam.position, (near.size, 3))
    return near[scene.org.occluded(o, d[near])], int(near.size)


def shade_cpm(scene: RenderScene, frame: CpmFrame, cam: PinholeCamera, o: np.ndarray,
              d: np.ndarray, spp: int, *, lod_bias: float = 0.0,
              local_light_ratio: float = 8.0, filtering: str = "projected",
              footprint: str = "sample", coverage: bool = True, uv_from: str = "ray"
              ) -> tuple[np.ndarray, np.ndarray, int, np.ndarray]:
    """Radiance along eye rays from the characteristic point maps (module docstring).

    returns : (radiance (n, 3), level (n,) float64 — the fractional mip level used, -1 where
        M_org was used, NaN for misses; rays cast; hit (n,) bool — the ray sees the object)
    """
    _check_cpm_options(filtering, footprint, uv_from)
    h = _cpm_prepare(scene, frame, cam, o, d, lod_bias=lod_bias,
                     local_light_ratio=local_light_ratio, spp=spp, footprint=footprint,
                     coverage=coverage, uv_from=uv_from)
    frame.flush()
    return _cpm_finish(scene, frame, o, d, h, filtering)


def render_cpm(scene: RenderScene, cam: PinholeCamera, spp: int, seed: int, **kw):
    max_error_px = kw.pop("max_error_px", 1.0)
    filtering = kw.pop("filtering", "projected")
    _check_cpm_options(filtering, kw.get("footprint", "sample"), kw.get("uv_from", "ray"))
    # a caller's CpmFrame (the deformed modes: `texelbake.render.deformed`) or this frame's
    frame_given = kw.pop("frame", None)
    frame = frame_given or cpm_frame(scene, cam, max_error_px)
    n_pix = cam.height * cam.width
    acc = np.zeros((n_pix, 3))
    lvl_sum = np.zeros(n_pix)
    lvl_cnt = np.zeros(n_pix)
    cov = np.zeros(n_pix)
    fallback = 0
    rays = 0
    # two phases, so that the texel radiance of the whole frame is computed in one batch per
    # level (`CpmFrame.flush`): every eye ray first, then every look-up
    # eye rays that miss every mesh's box are background (`tracer.culled`): not traced
    box = getattr(scene, "eye_box", None) if frame_given is None else None
    pixels = frame_pixels(cam, box)  # eye rays only where the box projects
    n_eff = n_pix if pixels is None else pixels.size
    at = slice(None) if pixels is None else pixels
    passes = []
    for _, o, d in eye_passes(cam, spp, seed, pixels):
        parts = []
        for sl in ray_slices(o.shape[0]):  # slices of many rays
            idx = np.arange(sl.start, sl.stop)
            if box is not None:
                idx = idx[enters_box(o[sl], d[sl], box)]
                rays += sl.stop - sl.start - idx.size
            if idx.size:
                parts.append((idx, _cpm_prepare(scene, frame, cam, o[idx], d[idx], spp=spp,
                                                **kw)))
        passes.append((o, d, parts))
    frame.flush()
    for o, d, prepared in passes:
        rad = np.zeros_like(o)
        lvl = np.full(o.shape[0], np.nan)
        hit = np.zeros(o.shape[0], dtype=bool)
        for idx, h in prepared:
            rad[idx], lvl[idx], r, hit[idx] = _cpm_finish(scene, frame, o[idx], d[idx], h,
                                                          filtering)
            rays += r
        if not n_eff:
            continue
        rays += (n_pix - n_eff) * (o.shape[0] // n_eff)  # the other pixels' eye rays
        acc[at] += rad.reshape(-1, n_eff, 3).sum(axis=0)
        cov[at] += hit.reshape(-1, n_eff).sum(axis=0)
        lv = lvl.reshape(-1, n_eff)
        hit = np.isfinite(lv)
        lvl_sum[at] += np.where(hit, lv, 0.0).sum(axis=0)
        lvl_cnt[at] += hit.sum(axis=0)
        fallback += int(np.sum(lv == -1.0))
    rays += frame.rays
    level_img = np.divide(lvl_sum, lvl_cnt, out=np.full(n_pix, np.nan), where=lvl_cnt > 0)
    extras = {
        "level": level_img.reshape(cam.height, cam.width).astype(np.float32),
        "mesh": f"M{frame.mesh + 1}",
        "fallback_fraction": fallback / max(float(lvl_cnt.sum()), 1.0),
        "frame_rays": frame.rays,
    }
    return ((acc / spp).reshape(cam.height, cam.width, 3), rays,
            (cov / spp).reshape(cam.height, cam.width), extras)
