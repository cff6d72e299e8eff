"""a_vis: sample rays vs orthographic ray grids, Haar kept fraction vs error, closed-form savings.

Three measurements, time and error side by side (DESIGN.md "Measuring"):

1. Method choice (texelbake.cpm.avis module docstring). On a finite bumpy height field (flat texel
   frames) and on a bumpy sphere (curved: every texel frame differs; the maps are in world
   directions, so both methods are directly comparable), a_vis of every texel at every cube
   direction by
     - `avis_cube_maps` (one ray per facing (sample, direction) pair; q^2 samples per triangle),
     - `avis_ortho_grids` (G^2 parallel rays per direction, shared by all texels and levels,
       hits credited by the exact texel function of the scene, i.e. its best case),
   against a reference = the mean of the densest runs of both methods (their difference is
   reported, so the reference's own error is visible). Error per texel: relative L2 over
   directions; the median and 90th percentile over texels are printed, plus the error of the
   total over all texels.
2. Haar: kept fraction vs relative L2 error of the maps of the height field at res 32
   (the seed keeps 4-6.5 %).
3. Closed form: rays and time with and without the exact unoccluded-texel skip on a scene
   with a mix (ground + plate) and on the sphere.
4. Identity: storage against error of the table the renderer reads, the seed's plain Haar
   table against texelbake's sum-corrected one and against the per-level texel budget
   (`selection="texel"`, the default), on a bumpy field and V-grooves at every level
   (`identity_table`; the seed's 4-6.5 % storage marked; PASS/FAIL against issue 11's bar:
   every texel of every level within 2 % at <= 4 % storage, and the identity within 1 %).

    .venv/bin/python benchmarks/avis_methods.py --json avis.json [--quick] [--haar-res 64]
    .venv/bin/python benchmarks/avis_methods.py --identity-only --json avis_identity.json
    .venv/bin/python benchmarks/avis_methods.py --coarse cylinder:full:32 --json coarse.json

Measured 2026-11-25 (`--identity-only`; storage = bytes as the payload stores them
(`AvisTable.stored_bytes`): uint16 counts two to a uint32, int32 index + float32 value ('face')
or index and float16 value packed in one uint32 plus a float32 scale per texel ('texel'), the
float16 sum-correction maps; over the dense float32 maps of every level). Worst texel of any
level against the uncompressed maps; identity = worst |sum a_vis - cos| / cos over levels:

    field      res keep   table      storage  L0 med  worst texel  identity  bar
    bumpy       16 0.060  face+corr   11.4 %   2.1 %   3.8 %        0.9 %     FAIL
    bumpy       16 0.030  texel        4.0 %   2.0 %   3.2 %        0.8 %     FAIL
    bumpy       32 0.025  texel        3.3 %   0.9 %   1.6 %        0.2 %     PASS
    bumpy       32 0.030  texel        3.8 %   0.6 %   1.3 %                  (tests)
    v-grooves   16 0.060  face+corr   11.4 %           8.5 %        3.1 %     FAIL
    v-grooves   16 0.030  texel        4.0 %   0.4 %   1.2 %        3.1 %     FAIL (look-up)
    v-grooves   32 0.030  texel        3.8 %   0.1 %   1.4 %        1.2 %     FAIL (look-up, L0)

(the V-grooves' level-0 identity is the bilinear look-up's, lossless tables have it too:
docs/decisions.md). Rows measured with 6-byte face coefficients (before the uint32 packing; texel rows unchanged):
results/avis_identity_partial.txt (the run was stopped at res 32 on the V-grooves).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.helpers.avis_scenes import (  # noqa: E402
    grid_mesh,
    periodic_height,
    sample_faces,
    texel_of_latlong,
    texel_of_xy,
    tile3x3,
    uv_sphere,
)
from texelbake.cpm.avis import (  # noqa: E402
    AvisLevel,
    avis_cube_maps,
    avis_from_visibility,
    avis_level,
    avis_ortho_grids,
    closed_form_maps,
    closed_form_terms,
    compress_level,
    default_eps,
    visible_fraction,
)
from texelbake.cpm.haar import compress_haar, decompress_haar, eval_haar_point  # noqa: E402
from texelbake.geometry.raycast import RayCaster  # noqa: E402


class CountingCaster:
    """RayCaster wrapper counting rays (occluded and cast)."""

    def __init__(self, pts, faces):
        self.inner = RayCaster(pts, faces)
        self.points = self.inner.points
        self.rays = 0

    def occluded(self, o, d):
        self.rays += len(o)
        return self.inner.occluded(o, d)

    def cast(self, o, d):
        self.rays += len(o)
        return self.inner.cast(o, d)


def scene_heightfield(k=48):
    pts, faces = grid_mesh(k, periodic_height(0.05, seed=1))
    return pts, faces, lambda p: texel_of_xy(p, 8), 8


def scene_sphere():
    pts, faces = uv_sphere(24, 48, bump=lambda t, p: 0.08 * np.sin(5 * t) * np.cos(6 * p))
    return pts, faces, lambda p: texel_of_latlong(p, 8), 8


def per_texel_error(a, ref):
    a = a.reshape(a.shape[0], -1).astype(np.float64)
    ref = ref.reshape(ref.shape[0], -1)
    norm = np.linalg.norm(ref, axis=1)
    ok = norm > 0.05 * norm.max()
    rel = np.linalg.norm(a - ref, axis=1)[ok] / norm[ok]
    tot = np.abs(a.sum(0) - ref.sum(0)).max() / np.abs(ref.sum(0)).max()
    return float(np.median(rel)), float(np.percentile(rel, 90)), float(tot)


def method_table(name, scene, res, qs, grids, q_ref, g_ref):
    pts, faces, texel_fn, n_side = scene
    n_tex = n_side * n_side
    cc = CountingCaster(pts, faces)
    rows = []

    def run_samples(q):
        pos, nrm, ar, _ = sample_faces(pts, faces, q, seed=11)
        cc.rays = 0
        t0 = time.perf_counter()
        maps = avis_cube_maps(pos, nrm, ar, texel_fn(pos), n_tex, None, res, cc.occluded,
                              dtype=np.float64)
        return maps, time.perf_counter() - t0, cc.rays, pos.shape[0]

    def run_ortho(g):
        pos, _, _, _ = sample_faces(pts, faces, 1, seed=11)
        cc.rays = 0
        t0 = time.perf_counter()
        maps = avis_ortho_grids(cc, pos, texel_fn(pos), n_tex, res, grid_res=g,
                                texel_of_points=texel_fn, dtype=np.float64)
        return maps, time.perf_counter() - t0, cc.rays

    ref_s, t_rs, r_rs, m_rs = run_samples(q_ref)
    ref_o, t_ro, r_ro, = run_ortho(g_ref)
    ref = 0.5 * (ref_s + ref_o)
    agree = per_texel_error(ref_s, ref_o)
    print(f"\n[{name}] res {res} ({6 * res * res} directions), {n_tex} texels; reference = "
          f"mean of samples q={q_ref} ({m_rs} samples, {t_rs:.1f} s) and ortho G={g_ref} "
          f"({t_ro:.1f} s); their disagreement: median {agree[0]:.2%}, p90 {agree[1]:.2%}, "
          f"total {agree[2]:.3%}")
    print(f"{'method':>16} {'rays':>12} {'seconds':>8} {'median err':>11} {'p90 err':>9} "
          f"{'total err':>10}")
    for q in qs:
        maps, t, r, m = run_samples(q)
        e = per_texel_error(maps, ref)
        rows.append({"scene": name, "method": "samples", "param": q, "samples": m, "rays": r,
                     "seconds": t, "median": e[0], "p90": e[1], "total": e[2]})
        print(f"{'samples q=' + str(q):>16} {r:>12,} {t:>8.2f} {e[0]:>11.2%} {e[1]:>9.2%} "
              f"{e[2]:>10.3%}")
    for g in grids:
        maps, t, r = run_ortho(g)
        e = per_texel_error(maps, ref)
        rows.append({"scene": name, "method": "ortho", "param": g, "rays": r, "seconds": t,
                         "median": e[0], "p90": e[1], "total": e[2]})
        print(f"{'ortho G=' + str(g):>16} {r:>12,} {t:>8.2f} {e[0]:>11.2%} {e[1]:>9.2%} "
              f"{e[2]:>10.3%}")
    return rows, {"scene": name, "ref_disagreement": agree}


def haar_table(res, q, keeps):
    pts, faces, texel_fn, n_side = scene_heightfield(32)
    pos, nrm, ar, _ = sample_faces(pts, faces, q, seed=11)
    cc = CountingCaster(pts, faces)
    t0 = time.perf_counter()
    maps = avis_cube_maps(pos, nrm, ar, texel_fn(pos), n_side ** 2, None, res, cc.occluded,
                          dtype=np.float64)
    t_maps = time.perf_counter() - t0
    print(f"\n[haar] height field maps res {res}: {n_side ** 2} texels x 6 faces, "
          f"{cc.rays:,} rays in {t_maps:.1f} s")
    print("  direct = Haar of a_vis; fraction = Haar of F = a_vis / U, times the exact U")
    print(f"{'keep':>7} {'stored':>8} {'bytes(16b idx+f32)':>19} {'direct err':>11} "
          f"{'max err/area':>13} {'fraction err':>13} {'max err/area':>13} {'compress s':>11} "
          f"{'point evals/s':>14}")
    unocc = closed_form_maps(closed_form_terms(nrm, ar, texel_fn(pos), n_side ** 2), res)
    frac = visible_fraction(maps, unocc)
    area = np.bincount(texel_fn(pos), weights=ar, minlength=n_side ** 2)
    out = []
    rng = np.random.default_rng(0)
    nq = 200_000
    for keep in keeps:
        t0 = time.perf_counter()
        c = compress_haar(maps, keep)
        t_c = time.perf_counter() - t0
        rec = decompress_haar(c)
        rec = np.clip(rec, 0.0, unocc)
        rel = float(np.linalg.norm(rec - maps) / np.linalg.norm(maps))
        mx = float(np.max(np.abs(rec - maps).reshape(len(area), -1).max(1) / area))
        rec_f = unocc * np.clip(decompress_haar(compress_haar(frac, keep)), 0.0, 1.0)
        rel_f = float(np.linalg.norm(rec_f - maps) / np.linalg.norm(maps))
        mx_f = float(np.max(np.abs(rec_f - maps).reshape(len(area), -1).max(1) / area))
        mi = rng.integers(0, c.n_maps, nq)
        iu, iv = rng.integers(0, res, nq), rng.integers(0, res, nq)
        t0 = time.perf_counter()
        eval_haar_point(c, mi, iu, iv)
        eps = nq / (time.perf_counter() - t0)
        out.append({"keep": keep, "stored": c.kept_fraction,
                    "bytes_fraction": 1.5 * c.kept_fraction, "rel_l2": rel,
                    "max_err_over_area": mx, "fraction_rel_l2": rel_f,
                    "fraction_max_err_over_area": mx_f, "compress_s": t_c,
                    "point_evals_per_s": eps})
        print(f"{keep:>7.3f} {c.kept_fraction:>8.2%} {1.5 * c.kept_fraction:>19.2%} "
              f"{rel:>11.3%} {mx:>13.3%} {rel_f:>13.3%} {mx_f:>13.3%} {t_c:>11.3f} "
              f"{eps:>14,.0f}")
    return out


def lookup_table(res, keeps, n_dirs=400):
    """End to end: AvisTable.evaluate at random directions (theta < 85 deg) against a_vis
    from rays cast at exactly those directions, per texel; F-storage vs direct storage."""
    pts, faces, texel_fn, n_side = scene_heightfield(32)
    pos, nrm, ar, _ = sample_faces(pts, faces, 2, seed=11)
    tex = texel_fn(pos)
    nt = n_side ** 2
    caster = RayCaster(pts, faces)
    lvl = avis_level(pos, nrm, ar, tex, n_side, res, caster.occluded, pts, max_terms=4096)
    direct = AvisLevel(lvl.n_side, lvl.res, lvl.closed, np.zeros(nt, bool), lvl.cf,
                       lvl.ray_texels, lvl.ray_maps, lvl.texel_area)
    rng = np.random.default_rng(5)
    cos_t = rng.uniform(np.cos(np.radians(85)), 1, n_dirs)
    phi = rng.uniform(0, 2 * np.pi, n_dirs)
    sin_t = np.sqrt(1 - cos_t ** 2)
    w = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    m = pos.shape[0]
    vis = ~caster.occluded(np.repeat(pos + default_eps(pos) * nrm, n_dirs, axis=0),
                           np.tile(w, (m, 1))).reshape(m, n_dirs)
    truth = avis_from_visibility(vis, nrm, ar, tex, nt, w)  # (nt, n_dirs)
    frames = np.broadcast_to(np.eye(3), (nt, 3, 3)).copy()
    print(f"\n[look-up] res {res}, {nt} texels, {n_dirs} random directions (theta < 85 deg); "
          f"per-texel relative L2 error against rays at those directions")
    print(f"{'keep':>7} {'storage':>9} {'interp':>9} {'error':>8} {'look-ups/s':>11}")
    out = []
    for keep in keeps:
        for name, level in (("F = a/U", lvl), ("a_vis", direct)):
            table = compress_level(level, frames, keep)
            for interp in ("nearest", "bilinear"):
                t0 = time.perf_counter()  # one batched call, as a renderer would make
                a = table.evaluate(np.repeat(np.arange(nt), n_dirs), np.tile(w, (nt, 1)),
                                   interp=interp)[0].reshape(nt, n_dirs)
                rate = a.size / (time.perf_counter() - t0)
                err = float(np.linalg.norm(a - truth) / np.linalg.norm(truth))
                out.append({"keep": keep, "storage": name, "interp": interp, "rel_l2": err,
                            "lookups_per_s": rate})
                print(f"{keep:>7.3f} {name:>9} {interp:>9} {err:>8.2%} {rate:>11,.0f}")
    return out


def closed_form_table(res):
    out = []
    print(f"\n[closed form] res {res}")
    print(f"{'scene':>8} {'closed texels':>14} {'rays (skip)':>12} {'s (skip)':>9} "
          f"{'rays (all)':>12} {'s (all)':>8} {'max |diff| / area':>18}")
    ground, gf = grid_mesh(8, lambda x, y: 0.0 * x)
    keep = (np.arange(gf.shape[0]) % 64) != 9  # hole under the plate (cell (1, 1))
    plate = np.array([[0.125, 0.125, 0.3], [0.25, 0.125, 0.3], [0.25, 0.25, 0.3],
                      [0.125, 0.25, 0.3]])
    pts = np.concatenate([ground, plate])
    faces = np.concatenate([gf[keep], np.array([[0, 1, 2], [0, 2, 3]]) + ground.shape[0]])
    sph, sf = uv_sphere(24, 48)
    for name, (p, f, tfn) in {"plate": (pts, faces, lambda x: texel_of_xy(x, 8)),
                              "sphere": (sph, sf, lambda x: texel_of_latlong(x, 8))}.items():
        pos, nrm, ar, _ = sample_faces(p, f, 3, seed=11)
        cc = CountingCaster(p, f)
        t0 = time.perf_counter()
        a = avis_level(pos, nrm, ar, tfn(pos), 8, res, cc.occluded, p)
        t_a, r_a = time.perf_counter() - t0, cc.rays
        cc.rays = 0
        t0 = time.perf_counter()
        b = avis_level(pos, nrm, ar, tfn(pos), 8, res, cc.occluded, p, closed_form=False)
        t_b, r_b = time.perf_counter() - t0, cc.rays
        area = np.maximum(a.texel_area, 1e-300)
        diff = float(np.max(np.abs(a.dense_maps() - b.dense_maps()).reshape(64, -1).max(1)
                            / area))
        out.append({"scene": name, "closed": int(a.closed.sum()), "rays_skip": r_a, "s_skip": t_a,
                        "rays_all": r_b, "s_all": t_b, "max_diff_over_area": diff})
        print(f"{name:>8} {int(a.closed.sum()):>8} / 64 {r_a:>12,} {t_a:>9.2f} {r_b:>12,} "
              f"{t_b:>8.2f} {diff:>18.1e}")
    return out


def identity_table(res_keeps, k=64, n_side=16, n_dirs=300, tables=("seed", "face+corr", "texel")):
    """Storage against error of the table the renderer reads (issue 11): per-texel relative L2
    of a_vis at the cube pixels against the uncompressed maps (level 0: median, p95; the worst
    texel of any level), and the height-field identity sum_texels a_vis = cos(theta) through
    `AvisTable.evaluate` (bilinear, theta <= 75 deg), worst over every level, for the seed's
    plain per-face Haar table ("seed"), the per-face table with texelbake's sum correction
    ("face+corr") and the per-level texel budget with the correction ("texel", the default).
    Storage: `AvisTable.stored_bytes` (what the payload stores) over the dense float32 cube maps
    of every level. PASS: every texel within 2 % and the identity within 1 % at <= 4 %."""
    from texelbake.cpm.avis import coarsen_level
    from texelbake.cpm.avis.compress import texel_rel_errors

    period = 1.0 / 8
    fields = {"bumpy": periodic_height(0.05, seed=1),
              "v-grooves": lambda x, y: 0.06 * np.abs((x / period) % 1.0 - 0.5)}
    rng = np.random.default_rng(3)
    cos_t = rng.uniform(np.cos(np.radians(75)), 1.0, n_dirs)
    phi = rng.uniform(0, 2 * np.pi, n_dirs)
    sin_t = np.sqrt(1 - cos_t ** 2)
    w = np.column_stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t])
    print("\n[identity] storage against error of the compressed table (seed: 4-6.5 % stored); "
          "bar: every texel <= 2 %, identity <= 1 %, storage <= 4 %")
    print(f"{'field':>10} {'res':>4} {'keep':>6} {'table':>10} {'storage':>8} {'':>6} "
          f"{'L0 med':>7} {'p95':>7} {'max any':>8} {'identity max':>13} {'worst level':>11} "
          f"{'s':>6} {'bar':>5}")
    out = []
    variants = tuple(v for v in (("seed", "face", False), ("face+corr", "face", True),
                                 ("texel", "texel", True)) if v[0] in tables)
    for fname, h in fields.items():
        pts, faces = grid_mesh(k, h)
        tp, tf = tile3x3(pts, faces)
        pos, nrm, ar, _ = sample_faces(pts, faces, 2, seed=2)
        for res, keeps in res_keeps:
            lvl = avis_level(pos, nrm, ar, texel_of_xy(pos, n_side), n_side, res,
                             RayCaster(tp, tf).occluded, tp, max_terms=1024)
            levels = [lvl]
            while levels[-1].n_side > 1:
                levels.append(coarsen_level(levels[-1]))
            dense = sum(lv.n_side ** 2 for lv in levels) * 6 * res * res * 4.0
            for keep in keeps:
                for label, sel, corr in variants:
                    t0 = time.perf_counter()
                    nbytes, worst, worst_lv, per0, tex_max = 0.0, 0.0, 0, np.zeros(1), 0.0
                    for li, lv in enumerate(levels):
                        nt = lv.n_side ** 2
                        tab = compress_level(lv, np.broadcast_to(np.eye(3), (nt, 3, 3)).copy(),
                                             keep, correct_sum=corr, selection=sel)
                        nbytes += tab.stored_bytes()
                        tot = sum(tab.evaluate(np.full(n_dirs, t), w)[0] for t in range(nt))
                        e = float(np.max(np.abs(tot - cos_t) / cos_t))
                        if e > worst:
                            worst, worst_lv = e, li
                        if lv.ray_texels.size:
                            per = texel_rel_errors(tab.ray_texel_maps(), lv.ray_maps)
                            tex_max = max(tex_max, float(per.max()))
                            if li == 0:
                                per0 = per
                    dt = time.perf_counter() - t0
                    st = nbytes / dense
                    mark = "*seed*" if 0.04 <= st <= 0.065 else ""
                    ok = st <= 0.04 and tex_max <= 0.02 and worst <= 0.01
                    row = {"field": fname, "res": res, "keep": keep, "table": label,
                           "selection": sel, "corrected": corr, "storage": st,
                           "texel_median": float(np.median(per0)),
                           "texel_p95": float(np.percentile(per0, 95)),
                           "texel_max_level0": float(per0.max()),
                           "texel_max_any_level": tex_max, "identity_max": worst,
                           "identity_worst_level": worst_lv, "seconds": dt, "bar": ok}
                    out.append(row)
                    print(f"{fname:>10} {res:>4} {keep:>6.3f} {label:>10} {st:>8.2%} {mark:>6} "
                          f"{row['texel_median']:>7.2%} {row['texel_p95']:>7.2%} "
                          f"{tex_max:>8.2%} {worst:>13.2%} {worst_lv:>11} {dt:>6.1f} "
                          f"{'PASS' if ok else 'FAIL':>5}", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--json", type=Path)
    ap.add_argument("--quick", action="store_true", help="smaller sizes (about a minute)")
    ap.add_argument("--haar-res", type=int, default=None, help="cube face side for the Haar "
                    "table (default 32, 16 with --quick; the seed uses 64)")
    ap.add_argument("--identity-only", action="store_true",
                    help="only the identity / storage table (issue 11, item 1)")
    ap.add_argument("--res-keeps", default="16:0.03,0.06;32:0.025,0.03",
                    help="the identity table's face resolutions and keep fractions, "
                         "'RES:K,K;RES:K' (default %(default)s)")
    ap.add_argument("--tables", default="seed,face+corr,texel",
                    help="the identity table's variants (default %(default)s)")
    ap.add_argument("--coarse", default="",
                    help="only the coarse levels' a_vis for the fit, children's maps against "
                         "the seed's rebuild (BakeSettings.avis_coarse), on "
                         "'SCENE:SIZE:ATLAS[,...]' (benchmarks/avis_coarse.py)")
    ap.add_argument("--work", type=Path, default=Path("bench_out/avis_coarse"))
    args = ap.parse_args()
    quick = args.quick
    if args.coarse:
        from benchmarks.avis_coarse import coarse_table

        rows = coarse_table(args.coarse.split(","), args.work)
        if args.json:
            args.json.write_text(json.dumps({"coarse": rows}, indent=1))
        return
    if args.identity_only:
        res_keeps = [(int(r), tuple(float(k) for k in ks.split(",")))
                     for r, ks in (part.split(":") for part in args.res_keeps.split(";"))]
        rows = identity_table(res_keeps, tables=tuple(args.tables.split(",")))
        if args.json:
            args.json.write_text(json.dumps({"identity": rows}, indent=1))
        return
    results = {"methods": [], "references": []}
    for name, scene in (("heightfield", scene_heightfield()), ("bumpy sphere", scene_sphere())):
        rows, ref = method_table(name, scene, 4, (1, 2, 3) if quick else (1, 2, 4),
                                 (64, 128) if quick else (128, 256, 512),
                                 4 if quick else 8, 512 if quick else 1024)
        results["methods"] += rows
        results["references"].append(ref)
    haar_res = args.haar_res or (16 if quick else 32)
    results["haar"] = haar_table(haar_res, 2,
                                 (0.02, 0.04, 0.065, 0.1, 0.2, 1.0))
    results["lookup"] = lookup_table(16, (1.0, 0.065, 0.04))
    results["closed_form"] = closed_form_table(8)
    results["identity"] = identity_table(
        [(16, (0.03, 0.06))] if quick else [(16, (0.03, 0.06)), (32, (0.025, 0.03))])
    if args.json:
        args.json.write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
