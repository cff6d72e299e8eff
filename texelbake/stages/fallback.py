"""The fitted UsdPreviewSurface fallback of every LOD: the averaged fallback
(`filtered.fallback_maps`) with its diffuseColor times a smooth per-LOD gain, so that its
preview surface on the LOD reproduces the filtered reflectance of M_org (shadowing and masking
included) over the direction set of `baselines.fitted_fallback`, least squares.

The targets: the fallback page's dense samples (`filtered.fallback_samples`) over the direction
set, shadowing and masking by rays against M_org, summed per texel of level 0 in two disjoint
halves of the samples. The model: the averaged inputs' preview surface, L(g) = L0 + g ΔL per
pair and channel for diffuseColor g·base (`_model_terms`). The gain per channel is estimated
on a coarse level c (many samples a texel), shrunk toward 1 with weight λ
(argmin Σ(L0 + g ΔL − T)² + λ Σ ΔL² (g − 1)²), magnified bilinearly to the page and multiplied
into the level-0 base colour; c and λ (λ = ∞: the averaged inputs unchanged) are chosen per LOD
on held-out samples: the gain of one half judged against the other half's targets on texels
of the LOD's own level (`lod_texture_levels`), both ways. The workflow, roughness, normal and
constants stay the averaged fallback's (a renderer maps them as it maps the averaged ones:
Blender's importer turns a specular workflow's specularColor into Principled BSDF's Specular
Tint of an IOR-1.5 dielectric, not into F0); with a metallic map the model takes each
texel's metallic (`_model_terms`). What the fit leaves is reported per texel of the gain's
level (`residual_summary`: the fitted and the averaged inputs' relative residual beside the
targets' own noise; the report and `<name>_fit_residual_lod<i>.exr`). Kept in the artifact
store (the rays are the cost); deterministic (fixed directions, seeded views, no iteration)."""

from __future__ import annotations

import numpy as np

from texelbake.baselines.fitted_fallback import (
    cell_views,
    fit_directions,
    gain_residual,
    gain_sums,
    model_cells,
    sample_terms,
    shrunk_gain,
    targets,
)
from texelbake.brdf.evaluate import evaluate_by_face
from texelbake.cpm.level import segment_sum
from texelbake.geometry.basis import tangent_frames
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.tol import TOL

#: samples per chunk of the target sums (k² = 81 BRDF rows and k rays per sample)
SAMPLE_CHUNK = 8192
#: texels per chunk of the fit (81 pairs x 16 views x 3 BRDF evaluations each)
TEXEL_CHUNK = 1024
_TAG_VIEWS = 0x6F


def lod_texture_levels(ctx: StageContext, res: int, n_lods: int) -> list[int]:
    """The level of the res² page whose texels each LOD's fitted textures carry: the side at
    which a texel is at most a pixel where LOD i switches in (`lod_switch_px[i - 1]`, the
    rule of `filtered.fallback_resolution` for LOD1), as a power of two ≤ res; a LOD past the
    switch sizes (or 'atlas' mode) takes the last one's level."""
    n_levels = int(np.log2(res)) + 1
    px = list(ctx.settings.lod_switch_px) if ctx.settings.lod_mode == "error" else []
    out = []
    for i in range(n_lods):  # a loop over the few LODs
        if not px:
            out.append(0)
            continue
        sw = float(px[min(i, len(px) - 1)])
        lvl = int(np.floor(np.log2(float(px[0]) / sw)))  # the page is sized for LOD1
        out.append(int(np.clip(lvl, 0, n_levels - 1)))
    return out


def _sample_sums(ctx: StageContext, fs: dict, res: int, dirs: np.ndarray):
    """Level-0 sums over the page's covered texels: (covered (c,) texel ids, num (c, k·k·3),
    den (c, k), normal sums (c, 3) in the LOD1 tangent frame, area (c,))."""
    smp = fs["smp"]
    k = dirs.shape[0]
    t0 = fs["row"].astype(np.int64) * res + fs["col"]
    half = np.arange(t0.size) % 2  # two disjoint halves of the samples (held-out checks)
    order = np.lexsort((half, t0))
    covered = np.unique(t0)
    caster = ctx.caster()
    mats = ctx.asset().materials
    eps = TOL.ray_offset * caster.bbox_diag
    # each sample's view in each cell, seeded (the same draws whatever the chunking)
    u_view = np.random.default_rng([ctx.settings.seed, _TAG_VIEWS]).random((t0.size, k, 2))
    g = TOL.grazing_cos
    kk = k * k * 3
    total = np.zeros((2 * covered.size, kk + k + 4))
    for a in range(0, order.size, SAMPLE_CHUNK):  # chunks of samples (memory bound)
        sel = order[a:a + SAMPLE_CHUNK]
        m = sel.size
        fr = fs["frames"][fs["prim"][sel]]  # (m, 3, 3) rows (t, b, n) of LOD1's face
        dl = np.einsum("mji,kj->mki", fr, dirs)  # (m, k, 3) world lights
        dv = np.einsum("mji,mkj->mki", fr, cell_views(u_view[sel]))  # a view in each cell
        nrm, gn = smp.normals[sel], fs["gnrm"][sel]
        origins = smp.positions[sel] + eps * gn
        vis = []
        for dw in (dl, dv):  # lights, then views
            cos_s = np.einsum("mj,mkj->mk", nrm, dw)
            cos_g = np.einsum("mj,mkj->mk", gn, dw)
            live = (cos_s > g) & (cos_g > g)
            pi, di = np.nonzero(live)
            occ = caster.occluded_pairs(origins, dw.reshape(-1, 3), pi, pi * k + di)
            v = live.astype(np.float64)
            v[pi[occ], di[occ]] = 0.0
            vis.append(v * (cos_s if dw is dl else cos_g))
        vis_l, vis_v = vis
        sf = tangent_frames(nrm)  # each sample's shading frame
        loc_l = np.einsum("mij,mkj->mki", sf, dl)
        loc_v = np.einsum("mij,mkj->mki", sf, dv)
        s_i, i_i, o_i = np.nonzero((vis_l[:, :, None] > 0) & (vis_v[:, None, :] > 0))
        f = np.zeros((m, k, k, 3))
        if s_i.size:
            f[s_i, i_i, o_i] = evaluate_by_face(
                mats, smp.material[sel][s_i].astype(np.int64), loc_l[s_i, i_i], loc_v[s_i, o_i],
                smp.uv[sel], sample_index=s_i)
        num, den = sample_terms(f, vis_l, vis_v, smp.area[sel])
        n_loc = np.einsum("mij,mj->mi", fr, nrm) * smp.area[sel][:, None]
        # ascending: the samples are in (texel, half) order
        rows = 2 * np.searchsorted(covered, t0[sel]) + half[sel]
        starts = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
        total[rows[starts]] += np.add.reduceat(
            np.concatenate([num, den, n_loc, smp.area[sel][:, None]], axis=1), starts, axis=0)
    total = total.reshape(covered.size, 2, -1).transpose(1, 0, 2)  # (half, texel, ...)
    return covered, total[..., :kk], total[..., kk:kk + k], total[..., kk + k:kk + k + 3], \
        total[..., -1]



#: coarse levels above a LOD's own where its gain may be estimated, and the gain's shrinkage
#: weights toward 1 (inf: the averaged inputs unchanged); both chosen on held-out samples
GAIN_LEVELS = (1, 2, 3, 4)
GAIN_LAMBDAS = (0.0, 0.25, 1.0, 4.0, float("inf"))
#: covered texels of a LOD's own level the held-out choice evaluates (an even subset)
CV_TEXELS = 8192


def _to_side(img: np.ndarray, n: int) -> np.ndarray:
    """An (m, m, ...) map box-averaged (m > n) or repeated (m < n) to (n, n, ...)."""
    m = img.shape[0]
    if m > n:
        f = m // n
        return img.reshape(n, f, n, f, *img.shape[2:]).mean(axis=(1, 3))
    if m < n:
        f = n // m
        return np.repeat(np.repeat(img, f, axis=0), f, axis=1)
    return img


def _level(covered: np.ndarray, res: int, lvl: int, arrays: list[np.ndarray]):
    """Box sums of per-level-0-texel rows `arrays` at level lvl: (texel ids, sums)."""
    n_l = res >> lvl
    ids = (covered // res >> lvl) * n_l + (covered % res >> lvl)
    order = np.argsort(ids, kind="stable")
    uniq = np.unique(ids)
    seg = np.searchsorted(uniq, ids[order])
    return uniq, [segment_sum(a[order], seg, uniq.size, 0) for a in arrays]


def _model_terms(const: dict, metal: bool | np.ndarray, base: np.ndarray, rough: np.ndarray,
                 nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(L0, ΔL) (t, k, k, 3): each pair's cell mean of the averaged inputs' preview surface
    with diffuseColor 0 and its growth from 0 to `base`, L(g) = L0 + g ΔL for diffuseColor
    g·base (exact for the specular workflow and metallic 0 or 1; the base colour's part is the
    lobe on a metal, the diffuse elsewhere). `metal` : the constants' (bool), or (t,) each
    texel's metallic m (a metallic map): ΔL = (1 − m) ΔL_dielectric + m ΔL_metal, each part
    estimated as above (Schlick's F is affine in F0 = mix(0.04, g·base, m), the diffuse
    term is scaled by 1 − m), L0 the lobe at the texel's m."""
    per_texel = not isinstance(metal, bool)
    l0s, dls = [], []
    for a in range(0, nrm.shape[0], TEXEL_CHUNK):  # chunks of texels (memory bound)
        sl = slice(a, a + TEXEL_CHUNK)
        p1 = {"diffuseColor": base[sl], "roughness": rough[sl]}
        p0 = {"diffuseColor": np.zeros_like(base[sl]), "roughness": rough[sl]}
        if per_texel:
            m = np.asarray(metal, dtype=np.float64)[sl]
            l0 = model_cells(const, {**p0, "metallic": m}, nrm[sl], lobe=True)
            ones, zeros = np.ones_like(m), np.zeros_like(m)
            d = (model_cells(const, {**p1, "metallic": ones}, nrm[sl], lobe=True)
                 - model_cells(const, {**p0, "metallic": ones}, nrm[sl], lobe=True)
                 ) * m[:, None, None, None]
            d += (model_cells(const, {**p1, "metallic": zeros}, nrm[sl], lobe=False)
                  - model_cells(const, {**p0, "metallic": zeros}, nrm[sl], lobe=False)
                  ) * (1.0 - m)[:, None, None, None]
            l0s.append(l0)
            dls.append(d)
            continue
        l0 = model_cells(const, p0, nrm[sl], lobe=True)
        if metal:
            d = model_cells(const, p1, nrm[sl], lobe=True) - l0
        else:
            d = model_cells(const, p1, nrm[sl], lobe=False) - model_cells(const, p0, nrm[sl],
                                                                         lobe=False)
        l0s.append(l0)
        dls.append(d)
    k = fit_directions().shape[0]
    empty = np.zeros((0, k, k, 3))
    return (np.concatenate(l0s) if l0s else empty), (np.concatenate(dls) if dls else empty)


def _gain_image(g: np.ndarray, uniq: np.ndarray, n_c: int, n: int) -> np.ndarray:
    """Coarse per-texel gains (t, 3) at texels `uniq` of an n_c² level -> (n, n, 3) by
    nearest fill and bilinear magnification (no seams between coarse texels)."""
    from scipy.ndimage import zoom

    from texelbake.stages.filtered import nearest_fill

    img = np.ones((n_c * n_c, 3))
    img[uniq] = g
    filled = np.zeros(n_c * n_c, bool)
    filled[uniq] = True
    img = nearest_fill(img.reshape(n_c, n_c, 3), filled.reshape(n_c, n_c))
    if n == n_c:
        return img
    return zoom(img, (n / n_c, n / n_c, 1), order=1, mode="nearest", grid_mode=True)


def _lod_gain(lvl: int, res: int, sums: tuple, base0: np.ndarray, rough: np.ndarray,
              const: dict, metal: bool | np.ndarray) -> tuple[np.ndarray, dict]:
    """One LOD's diffuseColor gain (res, res, 3) and its choice (`corrected_inputs`)."""
    covered, num, den, nsum = sums
    k = fit_directions().shape[0]
    n_levels = int(np.log2(res)) + 1

    def at(level: int, pick: int = 1):
        uniq, (n0, n1, d0, d1, ns) = _level(covered, res, level,
                                            [num[0], num[1], den[0], den[1], nsum])
        sel = np.arange(0, uniq.size, pick)
        ok = (np.linalg.norm(ns, axis=1) > 0) & (ns[:, 2] > 0)
        nrm = np.where(ok[:, None], ns, [0.0, 0.0, 1.0])[sel]
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        n_l = res >> level
        b = _to_side(base0, n_l).reshape(-1, 3)[uniq[sel]].astype(np.float64)
        r = _to_side(rough, n_l).reshape(-1)[uniq[sel]].astype(np.float64)
        met = (metal if isinstance(metal, bool)
               else _to_side(metal, n_l).reshape(-1)[uniq[sel]].astype(np.float64))
        l0, dl = _model_terms(const, met, b, r, nrm)
        tg = [targets(nn[sel], dd[sel], k) for nn, dd in ((n0, d0), (n1, d1), (n0 + n1, d0 + d1))]
        return uniq, sel, l0, dl, tg

    n_fine = max(covered.size >> (2 * lvl), 1)  # about the LOD level's covered texels
    f_uniq, f_sel, f_l0, f_dl, f_tg = at(lvl, max(1, -(-n_fine // CV_TEXELS)))
    n_f = res >> lvl
    best = (np.inf, float("inf"), lvl)
    base_err = None
    for off in GAIN_LEVELS:  # the few coarse levels
        c = lvl + off
        if c > n_levels - 1:
            break
        c_uniq, _, l0, dl, tg = at(c)
        stats = [gain_sums(l0, dl, *tg[h]) for h in (0, 1)]
        for lam in GAIN_LAMBDAS:  # the few shrinkage weights
            err = 0.0
            for h in (0, 1):  # fit on one half, judge on the other
                g = _gain_image(shrunk_gain(stats[h][0], stats[h][1], lam), c_uniq, res >> c, n_f)
                g = g.reshape(-1, 3)[f_uniq[f_sel]]
                t_o, v_o = f_tg[1 - h]
                r = (f_l0 + g[:, None, None, :] * f_dl - t_o) * v_o[..., None]
                err += float(np.einsum("tijc,tijc->", r, r))
            if not np.isfinite(lam):
                base_err = err
            if err < best[0]:
                best = (err, lam, c)
    _, lam, c = best
    c_uniq, _, l0, dl, tg = at(c)
    t_c, v_c = tg[2]  # every sample's targets at the gain's level
    if np.isfinite(lam):
        sdd, sdr = gain_sums(l0, dl, t_c, v_c)
        g_c = shrunk_gain(sdd, sdr, lam)
        g = _gain_image(g_c, c_uniq, res >> c, res)
    else:
        g_c, g = np.ones((c_uniq.size, 3)), np.ones((res, res, 3))
    # what the fit leaves, per texel of the level its gain is fitted on, against every
    # sample's targets: the fitted model's and the averaged inputs' (NaN: nothing to fit),
    # and the targets' own sampling noise on the same scale (half the two halves' difference
    # has the variance of the whole's mean): a residual near it is noise, not the model
    resid = np.full((3, (res >> c) ** 2), np.nan)
    resid[0, c_uniq] = gain_residual(l0, dl, t_c, v_c, g_c)
    resid[1, c_uniq] = gain_residual(l0, dl, t_c, v_c, np.ones_like(g_c))
    half_d = 0.5 * (tg[0][0] - tg[1][0]) * (tg[0][1] & tg[1][1])[..., None]
    t_all = t_c * v_c[..., None]
    n2 = np.einsum("tijc,tijc->t", t_all, t_all)
    resid[2, c_uniq] = np.sqrt(np.divide(np.einsum("tijc,tijc->t", half_d, half_d), n2,
                                         out=np.full(n2.shape, np.nan), where=n2 > 0))
    info = {"level": int(c), "lambda": lam, "heldout_vs_averaged": round(
        best[0] / base_err, 4) if base_err else None,
        "residual": resid.reshape(3, res >> c, res >> c)}
    return g, info


GAIN_VERSION = "gain-v3"


def fitted_inputs(ctx: StageContext, averaged: dict) -> dict:
    """The averaged fallback with each LOD's diffuseColor times a smooth gain (module
    docstring): per LOD its own level-0 diffuse texture, everything else the averaged one's.
    Kept in the artifact store (the rays are the cost)."""
    res = int(averaged["resolution"])
    n_lods = len(averaged["roughness"])
    levels = lod_texture_levels(ctx, res, n_lods)
    from texelbake.stages.filtered import FALLBACK_VERSION

    key = ctx.key("filtered", f"{GAIN_VERSION}-{FALLBACK_VERSION}-{res}-s"
                  f"{'-'.join(map(str, levels))}.npz", GEOMETRY_FIELDS)
    const = {k: v for k, v in averaged["constants"].items()
             if k not in ("opacity", "emissiveColor")}
    metal: bool | np.ndarray = (int(const.get("useSpecularWorkflow", 0)) == 0
                                and float(np.asarray(const.get("metallic", 0.0))) >= 0.5)
    if averaged.get("metallic") is not None:  # a metallic map: each texel its own
        metal = np.asarray(averaged["metallic"], dtype=np.float64)
    base0 = np.asarray(averaged["base"], dtype=np.float64)
    if not ctx.store.exists(key):
        from texelbake.stages.filtered import fallback_samples

        covered, num, den, nsum, _ = _sample_sums(ctx, fallback_samples(ctx, res), res,
                                                  fit_directions())
        sums = (covered, num, den, nsum.sum(axis=0))
        arrays: dict[str, np.ndarray] = {}
        for i, lvl in enumerate(levels):  # a loop over the few LODs
            g, info = _lod_gain(lvl, res, sums, base0, np.asarray(averaged["roughness"][i]),
                                const, metal)
            arrays[f"gain{i}"] = g.astype(np.float32)
            arrays[f"choice{i}"] = np.array([info["level"], info["lambda"],
                                             info["heldout_vs_averaged"] or np.nan])
            arrays[f"residual{i}"] = info["residual"]
        ctx.store.write_arrays(key, arrays)
    d = ctx.store.read_arrays(key)
    diffuse = [np.clip(base0 * d[f"gain{i}"], 0.0, 1.0).astype(np.float32)
               for i in range(n_lods)]
    fit = [{"gain_level": int(d[f"choice{i}"][0]),
            "lambda": (float(d[f"choice{i}"][1]) if np.isfinite(d[f"choice{i}"][1]) else None),
            "heldout_vs_averaged": (None if np.isnan(d[f"choice{i}"][2])
                                    else round(float(d[f"choice{i}"][2]), 4)),
            "residual": residual_summary(d[f"residual{i}"])}
           for i in range(n_lods)]
    return {**averaged, "diffuse": diffuse, "fit": {"gain": fit},
            "residual": [d[f"residual{i}"][0].astype(np.float32) for i in range(n_lods)]}


#: a texel whose relative residual exceeds this is one the preview surface cannot reproduce
#: (its residual energy is more than a quarter of its targets')
RESIDUAL_FLAG = 0.5


def residual_summary(resid: np.ndarray) -> dict:
    """The report's view of one LOD's per-texel residual maps (3, n, n): the fitted model's
    and the averaged inputs' relative residual (`gain_residual`) and the targets' sampling
    noise on the same scale, over the texels with targets: their percentiles, and the texels
    above `RESIDUAL_FLAG` with the worst of them."""
    fit, avg, noise = (r.reshape(-1) for r in resid)
    ok = np.isfinite(fit)
    n = int(resid.shape[-1])

    def pct(x: np.ndarray) -> dict:
        if not x.size:
            return {}
        q = np.percentile(x, [50, 95, 100])
        return {"p50": round(float(q[0]), 4), "p95": round(float(q[1]), 4),
                "max": round(float(q[2]), 4)}

    ids = np.flatnonzero(ok)
    worst = ids[np.argsort(-fit[ids], kind="stable")[:5]]
    return {"texels": int(ok.sum()), "side": n, "fitted": pct(fit[ok]),
            "averaged": pct(avg[ok]), "target_noise": pct(noise[ok & np.isfinite(noise)]),
            "flag": RESIDUAL_FLAG,
            "texels_above_flag": int(np.sum(fit[ok] > RESIDUAL_FLAG)),
            "worst": [{"row": int(t // n), "col": int(t % n),
                       "residual": round(float(fit[t]), 4)} for t in worst]}
