"""The fitted UsdPreviewSurface fallback of every LOD: per texel of the LOD's own level
(`lod_texture_levels`) the roughness and diffuseColor whose preview surface on the texel's mean
normal reproduces the filtered reflectance of M_org (shadowing and masking included) over
lights and views drawn by projected solid angle, least squares, regularised toward the
averaged inputs (`baselines.texel_fit`).

The rows: each dense sample of the fallback page (`filtered.fallback_samples`) takes N_LIGHTS
lights and N_VIEWS views cosine distributed about its LOD1 face (a fixed lattice shifted per
sample, seeded), shadowing and masking by rays against M_org; every (light, view) pair is a row.
Per LOD the rows are grouped by the texel of its level; the fit's prior weight λ is chosen on
held-out views (fit on the views of one half, judged on the other half's rows, both ways;
λ = ∞ is the averaged fallback, kept bit for bit). The diffuse texture is the level-0 base
colour plus the fit's change at the LOD's level (so a LOD keeps the page's detail), the
roughness texture the fit at the LOD's level. The workflow, metallic, normal maps, occlusion
and constants stay the averaged fallback's: Blender's importer maps the metallic workflow to
Principled BSDF's Metallic and Base Color, but a specular workflow's specularColor to Specular
Tint of an IOR-1.5 dielectric, so the fit never changes the workflow. Kept in the artifact
store (the rays are the cost); deterministic (seeded directions, no iteration)."""

from __future__ import annotations

import numpy as np

from texelbake.baselines.texel_fit import (
    FIT_LAMBDAS,
    ROUGHNESS_GRID,
    affine_terms,
    choose_lambda,
    pick,
    residual,
    row_sums,
    shifted_dirs,
)
from texelbake.brdf.evaluate import evaluate_by_face
from texelbake.geometry.basis import tangent_frames
from texelbake.stages.context import GEOMETRY_FIELDS, StageContext
from texelbake.tol import TOL

#: samples per chunk of the targets (L·V BRDF rows and L + V rays per sample)
SAMPLE_CHUNK = 8192


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


def _pair_samples(ctx: StageContext, fs: dict, res: int) -> dict:
    """Every dense sample's rows of the fit (`baselines.texel_fit`): N_LIGHTS lights and
    N_VIEWS views per sample, cosine distributed about its LOD1 face (a fixed lattice shifted per
    sample, seeded), shadowing and masking by rays against M_org. Returns {"y" (m, L, V, 3)
    float32 targets f_s V (n_s·l)⁺, "w" (m, V) float32 view weights A V (n_g·v)⁺ / (n_face·v)
    (the ratio capped at VIEW_RATIO_CAP), "dl" (m, L, 3), "dv" (m, V, 3) float32 world
    directions, "t0" (m,) level-0 texel, "normal" (m, 3) shading normals, "area" (m,)}."""
    smp = fs["smp"]
    n_l, n_v = N_LIGHTS, N_VIEWS
    t0 = fs["row"].astype(np.int64) * res + fs["col"]
    m_all = t0.size
    caster = ctx.caster()
    mats = ctx.asset().materials
    eps = TOL.ray_offset * caster.bbox_diag
    shift = np.random.default_rng([ctx.settings.seed, _TAG_PAIRS]).random((m_all, 2, 2))
    g = TOL.grazing_cos
    out = {"y": np.zeros((m_all, n_l, n_v, 3), np.float32), "w": np.zeros((m_all, n_v),
                                                                           np.float32),
           "dl": np.zeros((m_all, n_l, 3), np.float32), "dv": np.zeros((m_all, n_v, 3),
                                                                       np.float32)}
    for a in range(0, m_all, SAMPLE_CHUNK):  # chunks of samples (memory bound)
        sel = np.arange(a, min(a + SAMPLE_CHUNK, m_all))
        m = sel.size
        fr = fs["frames"][fs["prim"][sel]]  # (m, 3, 3) rows (t, b, n) of LOD1's face
        loc_l, loc_v = shifted_dirs(shift[sel, 0], n_l), shifted_dirs(shift[sel, 1], n_v)
        dl = np.einsum("mji,mkj->mki", fr, loc_l)  # (m, L, 3) world
        dv = np.einsum("mji,mkj->mki", fr, loc_v)  # (m, V, 3) world
        nrm, gn = smp.normals[sel], fs["gnrm"][sel]
        origins = smp.positions[sel] + eps * gn
        vis = []
        for dw in (dl, dv):  # lights, then views
            k = dw.shape[1]
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
        sl = np.einsum("mij,mkj->mki", sf, dl)
        sv = np.einsum("mij,mkj->mki", sf, dv)
        s_i, i_i, o_i = np.nonzero((vis_l[:, :, None] > 0) & (vis_v[:, None, :] > 0))
        f = np.zeros((m, n_l, n_v, 3))
        if s_i.size:
            f[s_i, i_i, o_i] = evaluate_by_face(
                mats, smp.material[sel][s_i].astype(np.int64), sl[s_i, i_i], sv[s_i, o_i],
                smp.uv[sel], sample_index=s_i)
        ratio = np.minimum(vis_v / np.maximum(loc_v[..., 2], 1e-12), VIEW_RATIO_CAP)
        out["y"][sel] = f * vis_l[:, :, None, None]
        out["w"][sel] = smp.area[sel][:, None] * ratio
        out["dl"][sel], out["dv"][sel] = dl, dv
    out.update(t0=t0, normal=smp.normals, area=smp.area)
    return out


#: lights and views per dense sample of the fit; a view's masking ratio cap
N_LIGHTS = 6
N_VIEWS = 6
VIEW_RATIO_CAP = 4.0
#: rows per chunk of the fit (one row a (sample, light, view) pair)
ROW_CHUNK = 1 << 19
_TAG_PAIRS = 0x70


def _lod_fit(lvl: int, res: int, rows: dict, base0: np.ndarray, rough: np.ndarray,
             const: dict) -> tuple[np.ndarray, np.ndarray, dict]:
    """One LOD's fitted (diffuse (res, res, 3), roughness (n, n) at its level's side n) and
    its report: per texel of level lvl its roughness and diffuseColor (`texel_fit`), λ chosen
    on held-out views (the fit on views of one half judged on the other's rows, both ways)."""
    n = res >> lvl
    t_lvl = (rows["t0"] // res >> lvl) * n + (rows["t0"] % res >> lvl)
    uniq, inv = np.unique(t_lvl, return_inverse=True)
    t = uniq.size
    # each row's shading normal: its level-0 texel's mean normal, what the normal map a viewer
    # decodes holds there (a LOD's coarse texel is seen through the page's level-0 normals, so
    # its fitted roughness must not absorb their spread a second time)
    u0, inv0 = np.unique(rows["t0"], return_inverse=True)
    nsum = np.stack([np.bincount(inv0, weights=rows["normal"][:, c] * rows["area"],
                                 minlength=u0.size) for c in range(3)], axis=1)
    length = np.linalg.norm(nsum, axis=1, keepdims=True)
    frames = tangent_frames(np.where(length > 0, nsum / np.maximum(length, 1e-300),
                                     [0.0, 0.0, 1.0]))  # (t0, 3, 3) rows (t, b, n)
    d0 = _to_side(base0, n).reshape(-1, 3)[uniq].astype(np.float64)
    r0 = _to_side(rough, n).reshape(-1)[uniq].astype(np.float64)
    grid = np.asarray(ROUGHNESS_GRID)
    n_l, n_v = N_LIGHTS, N_VIEWS
    order = np.argsort(inv, kind="stable")
    n_samp = np.bincount(inv, minlength=t)  # samples a texel
    bounds = np.searchsorted(inv[order], np.arange(t + 1))
    per = max(1, ROW_CHUNK // (n_l * n_v))  # samples per chunk
    half = (np.arange(n_v) % 2)[None, None]  # the views' lattice interleaved in elevation
    cv = np.zeros(len(FIT_LAMBDAS))
    fits = [(np.zeros(t), np.zeros((t, 3)), np.zeros(t)) for _ in FIT_LAMBDAS]
    energy = np.zeros(t)
    a = 0
    while a < t:  # chunks of texels holding about `per` samples
        b = int(np.searchsorted(bounds, bounds[a] + per, side="right")) - 1
        b = max(b, a + 1)
        smp = order[bounds[a]:bounds[b]]
        loc = inv[smp] - a  # (s,) texel within the chunk
        tc = b - a
        fr = frames[inv0[smp]]
        wi = np.einsum("sij,slj->sli", fr, rows["dl"][smp].astype(np.float64))
        wo = np.einsum("sij,svj->svi", fr, rows["dv"][smp].astype(np.float64))
        wi = np.broadcast_to(wi[:, :, None], (smp.size, n_l, n_v, 3)).reshape(-1, 3)
        wo = np.broadcast_to(wo[:, None], (smp.size, n_l, n_v, 3)).reshape(-1, 3)
        y = rows["y"][smp].reshape(-1, 3).astype(np.float64)
        w = np.broadcast_to(rows["w"][smp][:, None, :], (smp.size, n_l, n_v)).reshape(-1)
        w = w.astype(np.float64)
        grp = (2 * loc[:, None, None] + np.broadcast_to(half, (smp.size, n_l, n_v))).reshape(-1)
        row_tex = np.repeat(inv[smp], n_l * n_v)
        d0r, r0r = d0[row_tex], r0[row_tex]
        a0, b0 = affine_terms(const, r0r, wi, wo)
        l0 = a0 + d0r * b0
        sums = np.zeros((len(grid) + 1, 2 * tc, 4, 3))
        for j, r in enumerate([None, *grid]):  # the few roughness candidates
            ac, bc = (a0, b0) if r is None else affine_terms(const, np.full(w.size, r), wi, wo)
            sums[j] = row_sums(ac, bc, y, w, l0, d0r, grp, 2 * tc)
        wy2 = (w[:, None] * y * y).sum(axis=1).reshape(smp.size, -1).sum(axis=1)
        energy[a:b] = np.bincount(loc, weights=wy2, minlength=tc)
        halves = sums.reshape(len(grid) + 1, tc, 2, 4, 3).transpose(2, 0, 1, 3, 4)
        n_full = n_samp[a:b] * (n_l * n_v)
        cv += choose_lambda(halves, d0[a:b], r0[a:b], grid, np.stack([n_full // 2] * 2))
        full = halves[0] + halves[1]
        for i, lam in enumerate(FIT_LAMBDAS):  # the few λ
            r_fit, d_fit, best = pick(full, d0[a:b], r0[a:b], grid, lam, n_full)
            fits[i][0][a:b], fits[i][1][a:b] = r_fit, d_fit
            fits[i][2][a:b] = residual(full, d_fit, best)
        a = b
    k = int(np.argmin(cv))
    r_fit, d_fit, res_fit = fits[k]
    res_avg = fits[-1][2]
    rel = res_fit / np.maximum(energy, 1e-300)
    info = {"level": int(lvl), "lambda": FIT_LAMBDAS[k],
            "heldout_vs_averaged": round(float(cv[k] / cv[-1]), 4) if cv[-1] > 0 else None,
            "residual_rel_median": round(float(np.median(rel)), 4) if t else None,
            "residual_rel_p95": round(float(np.percentile(rel, 95)), 4) if t else None,
            "residual_vs_averaged": round(float(res_fit.sum() / max(res_avg.sum(), 1e-300)), 4)}
    if not np.isfinite(FIT_LAMBDAS[k]):
        return np.asarray(base0, np.float64), np.asarray(rough, np.float64), info
    delta = np.zeros((n * n, 3))
    delta[uniq] = d_fit - d0
    r_img = _to_side(rough, n).reshape(-1).astype(np.float64)
    r_img[uniq] = r_fit
    f = res // n
    diffuse = np.clip(base0 + np.repeat(np.repeat(delta.reshape(n, n, 3), f, 0), f, 1), 0, 1)
    return diffuse, r_img.reshape(n, n), info


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


FIT_VERSION = "texelfit-v4"


def fitted_inputs(ctx: StageContext, averaged: dict) -> dict:
    """The averaged fallback with each LOD's roughness and diffuseColor fitted per texel of its
    level (module docstring): per LOD its own diffuse texture (res, res, 3) and roughness
    (its level's side); workflow, metallic, normal maps, occlusion and constants the averaged
    one's. Kept in the artifact store (the rays are the cost)."""
    res = int(averaged["resolution"])
    n_lods = len(averaged["roughness"])
    levels = lod_texture_levels(ctx, res, n_lods)
    from texelbake.stages.filtered import FALLBACK_VERSION

    key = ctx.key("filtered", f"{FIT_VERSION}-{FALLBACK_VERSION}-{res}-s"
                  f"{'-'.join(map(str, levels))}.npz", GEOMETRY_FIELDS)
    const = {k: v for k, v in averaged["constants"].items()
             if k not in ("opacity", "emissiveColor")}
    base0 = np.asarray(averaged["base"], dtype=np.float64)
    if not ctx.store.exists(key):
        from texelbake.stages.filtered import fallback_samples

        rows = _pair_samples(ctx, fallback_samples(ctx, res), res)
        arrays: dict[str, np.ndarray] = {}
        for i, lvl in enumerate(levels):  # a loop over the few LODs
            diffuse, rough, info = _lod_fit(lvl, res, rows, base0,
                                            np.asarray(averaged["roughness"][i]), const)
            arrays[f"diffuse{i}"] = diffuse.astype(np.float32)
            arrays[f"roughness{i}"] = rough.astype(np.float32)
            arrays[f"info{i}"] = np.array([info[k] if info[k] is not None else np.nan
                                           for k in _INFO], dtype=np.float64)
        ctx.store.write_arrays(key, arrays)
    d = ctx.store.read_arrays(key)
    fit = []
    for i in range(n_lods):  # a loop over the few LODs
        vals = d[f"info{i}"]
        fit.append({k: (None if not np.isfinite(x) else int(x) if k == "level"
                        else round(float(x), 4)) for k, x in zip(_INFO, vals, strict=True)})
    keep = [f["lambda"] is None for f in fit]  # λ = ∞: the averaged maps themselves
    diffuse = [base0.astype(np.float32) if keep[i] else d[f"diffuse{i}"] for i in range(n_lods)]
    rough = [averaged["roughness"][i] if keep[i] else d[f"roughness{i}"] for i in range(n_lods)]
    return {**averaged, "diffuse": diffuse, "roughness": rough, "fit": {"texel": fit}}


#: the fit's report fields per LOD (stored as numbers, NaN for None)
_INFO = ("level", "lambda", "heldout_vs_averaged", "residual_vs_averaged",
         "residual_rel_median", "residual_rel_p95")
