"""Is a deformed frame's cpm error the characteristic points and L, or the texels themselves?
(issue 12; docs/deformation.md "Measured", the arm bent 90°.)

    .venv/bin/python benchmarks/deform_texels.py BAKED_ROOT --json out.json
        [--warps "time:0;time:12;time:24"] [--ref-spp 1024] [--spp 256] [--samples 4000000]
        [--size 512]

Per deformed frame (a `time:T` of the asset's own animation, or a procedural warp spec;
`scale:s=1` is the rest frame of an asset without animation) at the
`lod` view of the deformed object, against `gt` of the deformed M_org at `--ref-spp`:
- `cpm`: the renderer's default (Eq. 12 of seed 000 at rest through L, seed 002 Eq. 10);
- `texel-exact`: the same renderer, mesh, mip levels and trilinear look-ups, but each texel's
  radiance replaced by the brute-force average radiance over the texel's visible projected
  area on the *deformed* M_org — what Eq. 12 approximates. `--samples` points on the rest
  M_org (the bake's own stratified sampler, `geometry.sampling.sample_surface`) are assigned
  to texels by the closest atlas-mesh point (the bake's assignment,
  `render.scene.atlas_uv_prim`), moved by Ψ, weighted by their ΔA times their triangle's
  deformed / rest area and |cos| toward the camera, kept where the eye ray to them meets their own triangle
  first, and shaded by `gt`'s own `shade_org` (lights, shadows on the deformed geometry, the
  BRDF at the deformed shading normal). The arm at 64² gets ~3,000 samples per finest
  texel (4 M over 1,344), so the average's standard error is ~2 % where a texel's radiance
  varies by its whole value across it (1/√3000; more where part of the texel is hidden).
- `normalmap` and `gt` at `--spp`.
`texel-exact` scoring like `cpm` says the error is the texel average itself (the atlas's
resolution at that view: a highlight narrower than a texel is spread over it), not the
characteristic points or L; `texel-exact` far above `cpm` would say the opposite. Both are
also compared with each other (`cpm_vs_texel_exact_db`, PSNR with the reference's peak).

JSON: {"settings", "cases": {spec: {"object_pixels", "reference_seconds", "modes": {mode:
{"seconds", "psnr_db", "flux_ratio", "top4_error_share", "fallback_fraction"?}},
"cpm_vs_texel_exact_db"}}}; `top4_error_share` is the share of the squared error in the
mode's four worst pixels.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from texelbake.deform.warps import parse_warp  # noqa: E402
from texelbake.geometry.mesh import triangle_areas  # noqa: E402
from texelbake.geometry.sampling import sample_surface  # noqa: E402
from texelbake.geometry.texels import uv_to_texel  # noqa: E402
from texelbake.io.atomic import atomic_json  # noqa: E402
from texelbake.render import metrics  # noqa: E402
from texelbake.render.cpm import choose_mesh, render_cpm  # noqa: E402
from texelbake.render.deformed import DeformedCpmFrame, deform_scene  # noqa: E402
from texelbake.render.deformed_report import warp_at_time  # noqa: E402
from texelbake.render.frame import render_deformed  # noqa: E402
from texelbake.render.scene import atlas_uv_prim, load_scene, lod_camera  # noqa: E402
from texelbake.trace.org import shade_org  # noqa: E402


class ExactTexelFrame(DeformedCpmFrame):
    """A deformed cpm frame whose texel radiance is the brute-force average over the texel's
    visible projected area on the deformed M_org (module docstring)."""

    def __init__(self, d, cam, mesh: int, n_samples: int, seed: int = 1) -> None:
        super().__init__(d, cam, mesh, "point")
        a = d.rest.asset
        f = a.faces
        smp = sample_surface(a.points, f, n_samples, seed)  # the bake's own sampler
        self.tri = smp.face
        self.uv, _ = atlas_uv_prim(d.rest, smp.positions)
        self.p_def = np.einsum("nk,nkj->nj", smp.bary, d.asset.points[f[self.tri]])
        stretch = (triangle_areas(d.asset.points, f)
                   / np.maximum(triangle_areas(a.points, f), 1e-300))
        self.w_area = smp.area * stretch[self.tri]  # the sample's deformed ΔA
        self.ng = d.org_face_normals[self.tri]

    def _compute(self, j: int, todo: np.ndarray) -> None:
        if not todo.size:
            return
        rad, avis, ex, done, _ = self._arrays(j)
        n = max(self.scene.n0 >> j, 1)
        row, col = uv_to_texel(self.uv, n)
        tid = row * n + col
        wanted = np.zeros(n * n, dtype=bool)
        wanted[todo] = True
        sel = np.flatnonzero(wanted[tid])
        d = self.p_def[sel] - self.cam_pos
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        o = np.broadcast_to(self.cam_pos, d.shape).copy()
        hits = self.scene.org.cast(o, d)
        seen = np.flatnonzero(hits.hit & (hits.prim == self.tri[sel]))
        lum = np.zeros((sel.size, 3))
        lum[seen], rays, _ = shade_org(self.scene, o[seen], d[seen])
        self.rays += sel.size + rays
        w = np.zeros(sel.size)
        w[seen] = self.w_area[sel[seen]] * np.abs(np.einsum("ij,ij->i", self.ng[sel[seen]],
                                                            d[seen]))
        t = tid[sel]
        num = np.stack([np.bincount(t, w * lum[:, c], n * n) for c in range(3)], axis=1)
        den = np.bincount(t, w, n * n)
        cnt = np.bincount(t, minlength=n * n)
        rad[todo] = np.divide(num[todo], den[todo, None], out=np.zeros((todo.size, 3)),
                              where=den[todo, None] > 0)
        # the look-up weighs texels by a_vis ("projected" filtering): the weight sum is the
        # texel's visible projected area on the deformed surface
        avis[todo] = den[todo]
        ex[todo] = cnt[todo] > 0
        done[todo] = True


def _errors(img: np.ndarray, ref: np.ndarray, mask: np.ndarray) -> dict:
    a, b = img.astype(np.float64)[mask], ref.astype(np.float64)[mask]
    err = np.sort(((a - b) ** 2).sum(axis=1))[::-1]
    return {"psnr_db": round(float(metrics.psnr_db(a, b, b.max())), 2),
            "flux_ratio": round(float(a.sum() / b.sum()), 3),
            "top4_error_share": round(float(err[:4].sum() / max(err.sum(), 1e-300)), 3)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("baked")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--warps", default="time:0;time:12;time:24")
    ap.add_argument("--ref-spp", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--samples", type=int, default=4_000_000)
    ap.add_argument("--size", type=int, default=512)
    args = ap.parse_args(argv)
    scene = load_scene(args.baked)
    cases = {}
    for spec in [w for w in args.warps.split(";") if w]:
        t0 = time.perf_counter()
        warp = (warp_at_time(scene.asset, float(spec[5:])) if spec.startswith("time:")
                else parse_warp(spec, scene.asset.bounds))
        d = deform_scene(scene, warp)
        cam = lod_camera(d, args.size, args.size)
        ref = render_deformed(d, "gt", cam, args.ref_spp, 100)
        mask = metrics.object_mask(ref.coverage, ref.coverage)
        case: dict = {"object_pixels": int(mask.sum()),
                      "reference_seconds": round(ref.seconds, 1), "modes": {}}
        images = {}
        for mode in ("cpm", "texel-exact", "normalmap", "gt"):  # a loop over the few modes
            t1 = time.perf_counter()
            if mode == "texel-exact":
                frame = ExactTexelFrame(d, cam, choose_mesh(d, cam, 1.0), args.samples)
                img, _, _, extras = render_cpm(d, cam, args.spp, 7, frame=frame)
            else:
                r = render_deformed(d, mode, cam, args.spp, 7)
                img, extras = r.image, r.extras
            images[mode] = img
            case["modes"][mode] = {"seconds": round(time.perf_counter() - t1, 1),
                                   **_errors(img, ref.image, mask)}
            if "fallback_fraction" in extras:
                case["modes"][mode]["fallback_fraction"] = round(extras["fallback_fraction"], 3)
        peak = float(ref.image[mask].max())
        case["cpm_vs_texel_exact_db"] = round(float(metrics.psnr_db(
            images["cpm"][mask].astype(np.float64),
            images["texel-exact"][mask].astype(np.float64), peak)), 2)
        cases[spec] = case
        print(f"{spec} ({time.perf_counter() - t0:.0f} s): object {case['object_pixels']} px, "
              f"reference {args.ref_spp} spp; cpm against texel-exact "
              f"{case['cpm_vs_texel_exact_db']} dB", flush=True)
        print(f"  {'mode':<12}{'s':>7}{'PSNR':>8}{'light':>8}{'top-4':>8}{'fallback':>10}")
        for mode, e in case["modes"].items():
            fb = e.get("fallback_fraction")
            print(f"  {mode:<12}{e['seconds']:>7.1f}{e['psnr_db']:>8.2f}{e['flux_ratio']:>8.3f}"
                  f"{e['top4_error_share']:>8.2f}{'' if fb is None else f'{fb:>10.1%}'}")
    out = {"settings": vars(args), "cases": cases}
    atomic_json(args.json, out)  # sorted, indented; the Path settings as strings
    return out


if __name__ == "__main__":
    main()
