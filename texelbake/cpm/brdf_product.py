"""f_r(x_j, w_i, w_o) on a product of direction sets for many samples at once: the
BRDF evaluation that builds R (seed 000 Eq. 9) for a whole chunk of texels.

`texelbake.cpm.level.brdf_grid` evaluates only the entries whose visibility-cosine product is
nonzero, gathering them with np.nonzero and scattering the result back: for a hemisphere of
directions about the texel normal nearly every entry is live, so the gathers cost more than
they save (profile: 21-23 % of a bake). Here, per material (a loop over the few present):

- Lambert: f = rho / pi wherever both local directions are above the horizon, a function of
  the sample alone: rho per sample from one evaluation at normal incidence (textures sampled
  once per sample), then broadcast over (w_i, w_o): A + B + p work instead of A B p;
- UsdPreviewSurface (`grid_kernel="product"`, the default): the model's formulas evaluated on
  the (w_i, w_o) grid itself with per-sample parameters broadcast (`preview_shape`,
  `preview_colour`): the same arithmetic in the same order as
  `brdf.analytic.preview_surface`, so equal to it bit for bit, without forming (A B p, 3)
  direction rows or gathering and scattering live entries; every entry is evaluated (dead ones
  are zeroed by the visibility product); Phong (`phong_shape`, `phong_colour`) likewise;
- the lobe's shape (the half-vector terms, D, G and Fresnel's weight; Phong's lobe), which
  costs most, is evaluated once per distinct shape (`shape_blocks`): samples of one flat
  facet of a texel share their local directions and, where only colours vary, their shape
  inputs, so a textured, faceted asset (the bolt: 997 samples of 64 x 64 pairs, 177 shapes)
  pays for its shapes once and for its colours per sample; equal inputs give equal bits;
- any other model (and preview with `grid_kernel="rows"`): `brdf.evaluate` on every (w_i, w_o, sample) entry of the material's samples
  (dense, no gather), textures once per sample through sample_index; when fewer than
  DENSE_FRACTION of the entries are live (occluded samples, e.g. a bolt's threads) only the
  live ones, gathered.

Entries that are not live are multiplied by a zero visibility-cosine product afterwards; a
non-finite value at a live entry is an error (NumericalError naming the material), a non-finite
value at a dead entry is set to 0.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from typing import NamedTuple

import numpy as np

from texelbake import brdf as brdf_mod
from texelbake.brdf.analytic import preview_surface_params, schlick_weight
from texelbake.brdf.common import INV_PI, as_color, as_scalar
from texelbake.brdf.evaluate import PREVIEW_BRDF_INPUTS, material_inputs
from texelbake.brdf.widened import widen_inputs
from texelbake.errors import NumericalError, SettingsError
from texelbake.geometry.basis import grid_to_local, tangent_frames
from texelbake.tol import TOL

#: the models whose lobe `widen_inputs` widens (per-sample inputs, read by the product
#: kernel's paths below); the others keep their own lobe
WIDENED_MODELS = ("preview", "phong")

#: below this fraction of live entries a material's samples are evaluated on the live entries
#: only (gathered, as `level.brdf_grid`); above it densely (no gather / scatter)
DENSE_FRACTION = 0.6


def _store_finite(out: np.ndarray, blk: np.ndarray, fg: np.ndarray, live: np.ndarray,
                  material) -> None:  # noqa: ANN001
    """out[:, blk] = fg, a block's BRDF grid (3, nb, A, B); a non-finite value where a pair is
    live raises (`_check_finite`), elsewhere it is stored as 0."""
    bad = ~np.isfinite(fg)
    if bad.any():
        _check_finite(np.where(live[:, :, blk].transpose(2, 0, 1)[None], fg, 0.0), material)
        fg[bad] = 0.0
    out[:, blk] = fg


def _check_finite(f: np.ndarray, material) -> None:
    if not np.all(np.isfinite(f)):
        raise NumericalError(
            f"material {material.path!r}: BRDF not finite at a visible direction pair"
        )


def brdf_product(
    geo: Mapping[str, np.ndarray],
    materials,
    sample: np.ndarray,
    wi_world: np.ndarray,
    wo_world: np.ndarray,
    live: np.ndarray,
    kernel: str = "product",
    var: np.ndarray | None = None,
) -> np.ndarray:
    """f_r in each sample's shading frame on a product of direction sets.

    sample : (p,) int64; wi_world : (p, A, 3); wo_world : (p, B, 3); live : (A, B, p) bool
    var : (p,) each sample's lobe widened by this slope variance per axis
        (`texelbake.brdf.widened.widen_inputs`), None for the samples' own lobes
    returns : (3, p, A, B) float64 (channel-major: a sample's rows are contiguous), equal to
        `level.brdf_grid` (A, B, p, 3) on live entries (0 elsewhere up to the caller's
        visibility product)
    """
    p = len(sample)
    A, B = wi_world.shape[1], wo_world.shape[1]
    out = np.zeros((3, p, A, B))
    if p == 0 or A == 0 or B == 0:
        return out
    frames = tangent_frames(geo["sample_nrm"][sample])  # (p, 3, 3)
    wi_loc = grid_to_local(frames, wi_world)  # (A, p, 3)
    wo_loc = grid_to_local(frames, wo_world)  # (B, p, 3)
    mat = geo["sample_mat"][sample]
    uv = geo["sample_uv"][sample]
    eps = TOL.grazing_cos
    present = np.flatnonzero(np.bincount(mat))
    for m_i in present:  # a loop over the few materials
        material = materials[int(m_i)]
        sel = np.flatnonzero(mat == m_i)
        n_s = sel.size
        v_sel = var[sel] if var is not None and material.model in WIDENED_MODELS else None
        if v_sel is not None and kernel != "product":
            raise SettingsError("widened lobes are evaluated by the product kernel only")
        if material.model == "lambert":
            up = np.zeros((n_s, 3))
            up[:, 2] = 1.0
            rho_pi = brdf_mod.evaluate(material, up, up, uv[sel], sample_index=np.arange(n_s))
            mi = wi_loc[:, sel, 2] > eps  # (A, n_s)
            mo = wo_loc[:, sel, 2] > eps  # (B, n_s)
            ok = (mi.T[:, :, None] & mo.T[:, None, :]).astype(np.float64)  # (n_s, A, B)
            for c in range(3):  # loop over colour channels
                out[c, sel] = ok * rho_pi[:, c, None, None]
            continue
        if material.model == "preview" and kernel == "product":
            inp = material_inputs(material, PREVIEW_BRDF_INPUTS, uv[sel], None)
            if v_sel is not None:  # per-sample inputs (n_s,), textured ones included
                inp = widen_inputs("preview", inp, v_sel)
            prm = preview_surface_params(inp, n_s)
            shp = {k: prm[k] for k in PREVIEW_SHAPE_INPUTS}
            for rows, reps in shape_blocks(wi_loc, wo_loc, sel, list(shp.values())):
                shape = preview_shape(_rows(shp, reps), _local(wi_loc, sel[reps]),
                                      _local(wo_loc, sel[reps]), eps)
                for mb, lb in rows:  # loop over blocks of the samples of these shapes
                    fg = preview_colour(_rows(prm, mb), shape, lb)  # (3, nb, A, B)
                    _store_finite(out, sel[mb], fg, live, material)
            continue
        if material.model == "phong" and kernel == "product":
            prm = material_inputs(material, ("diffuseColor", "specularColor", "exponent"), uv[sel], None)
            if v_sel is not None:
                prm = widen_inputs("phong", prm, v_sel)
            kd = as_color(prm["diffuseColor"], n_s, "diffuseColor")
            ks = as_color(prm["specularColor"], n_s, "specularColor")
            ex = as_scalar(prm["exponent"], n_s, "exponent")
            if np.any(ex < 0):
                raise SettingsError(f"material {material.path!r}: phong exponent must be >= 0")
            for rows, reps in shape_blocks(wi_loc, wo_loc, sel, [ex]):
                lobe, dead = phong_shape(_row(ex, reps), _local(wi_loc, sel[reps]),
                                         _local(wo_loc, sel[reps]), eps)
                for mb, lb in rows:  # loop over blocks of the samples of these shapes
                    fg = phong_colour(_row(kd, mb), _row(ks, mb), lobe, dead, lb)
                    _store_finite(out, sel[mb], fg, live, material)
            continue
        lv = live[:, :, sel].transpose(2, 0, 1)  # (n_s, A, B)
        if float(lv.mean()) < DENSE_FRACTION:  # mostly dead (occluded): gather the live ones
            j, ia, ib = np.nonzero(lv)
            f_live = brdf_mod.evaluate(material, wi_loc[ia, sel[j]], wo_loc[ib, sel[j]],
                                       uv[sel], sample_index=j)
            _check_finite(f_live, material)
            for c in range(3):  # loop over colour channels
                out[c, sel[j], ia, ib] = f_live[:, c]
            continue
        wi = np.broadcast_to(wi_loc[:, sel, :].transpose(1, 0, 2)[:, :, None, :],
                             (n_s, A, B, 3)).reshape(-1, 3)
        wo = np.broadcast_to(wo_loc[:, sel, :].transpose(1, 0, 2)[:, None, :, :],
                             (n_s, A, B, 3)).reshape(-1, 3)
        idx = np.repeat(np.arange(n_s), A * B)
        f = brdf_mod.evaluate(material, wi, wo, uv[sel], sample_index=idx).reshape(n_s, A, B, 3)
        bad = ~np.isfinite(f)
        if bad.any():
            _check_finite(np.where(lv[..., None], f, 0.0), material)
            f[bad] = 0.0
        out[:, sel] = f.transpose(3, 0, 1, 2)
    return out


#: sample x direction-pair entries per block of `preview_grid` / `phong_grid` (16 samples of
#: 64 x 64 pairs: temporaries of ~0.5 MB each; a block of the classes' 4 x 4 check pairs holds
#: 4,096 samples, where blocks of 16 spent most of their time in numpy's per-call overhead).
#: Every entry depends on its own sample only: the block changes no bit
GRID_ENTRIES = 16 * 64 * 64


def grid_block(A: int, B: int) -> int:
    """Samples per block of a grid kernel on A x B pairs (`GRID_ENTRIES`)."""
    return max(GRID_ENTRIES // max(A * B, 1), 1)


#: the UsdPreviewSurface inputs its lobe's shape on the grid depends on (besides the local
#: directions): `preview_shape`'s; the colours enter only `preview_colour`
PREVIEW_SHAPE_INPUTS = ("alpha", "alpha_c", "clearcoat", "ior")

#: above this share of distinct shapes among a material's samples, each sample's shape is
#: evaluated in its own block (no gathers)
SHAPE_SHARE = 0.75

#: a block's samples: (their positions in the material's samples, each one's row in the
#: block's shapes or None where the rows are the samples themselves)
Rows = list[tuple[np.ndarray, np.ndarray | None]]


def shape_blocks(wi_loc: np.ndarray, wo_loc: np.ndarray, sel: np.ndarray,
                 inputs: list[np.ndarray]) -> Iterator[tuple[Rows, np.ndarray]]:
    """The material's samples `sel` in blocks of shapes: (rows, reps) with reps the positions
    in `sel` of the samples whose lobe shapes a block evaluates and rows the samples that read
    them. Two samples whose local directions (wi_loc (A, p, 3), wo_loc (B, p, 3): their frame
    and their texel's directions) and shape inputs (`inputs`, (1 or n,) each) are equal byte
    for byte have the same shape, so it is evaluated once (the samples of one flat facet of
    a texel, whatever their colours) and every sample's value is the same bit for bit. Where
    nearly every sample's shape is its own (smooth normals), blocks of samples as they come."""
    n_s = sel.size
    nb = grid_block(wi_loc.shape[0], wo_loc.shape[0])
    scalars = [np.broadcast_to(v, (n_s,))[:, None] for v in inputs]
    # first on one light and one view direction: where that key is nearly all distinct, so is
    # the whole (it is a part of it), and the whole key is not built
    first = _distinct(np.concatenate([wi_loc[0, sel], wo_loc[0, sel]] + scalars, axis=1))[0]
    if first.size <= SHAPE_SHARE * n_s:
        first, inv = _distinct(np.concatenate(
            [_local(wi_loc, sel).reshape(n_s, -1), _local(wo_loc, sel).reshape(n_s, -1)]
            + scalars, axis=1))
    if first.size > SHAPE_SHARE * n_s:
        for b0 in range(0, n_s, nb):  # loop over sample blocks (cache-sized)
            blk = np.arange(b0, min(b0 + nb, n_s))
            yield [(blk, None)], blk
        return
    order = np.argsort(inv, kind="stable")
    edge = np.searchsorted(inv[order], np.arange(0, first.size + nb, nb).clip(max=first.size))
    for k, u0 in enumerate(range(0, first.size, nb)):  # loop over blocks of shapes
        members = order[edge[k]:edge[k + 1]]
        yield [(members[b:b + nb], inv[members[b:b + nb]] - u0)
               for b in range(0, members.size, nb)], first[u0:u0 + nb]


def _distinct(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The rows of `key` (n, k) float64 that differ byte for byte: (each one's first row, in
    the rows' byte order; each row's index into them)."""
    key = np.ascontiguousarray(key)
    row = key.view(np.dtype((np.void, key.dtype.itemsize * key.shape[1]))).ravel()
    _, first, inv = np.unique(row, return_index=True, return_inverse=True)
    return first, inv.ravel()


def _row(v: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """A parameter array at rows `idx` (one of a single row, shared, as it is)."""
    return v if v.shape[0] == 1 else v[idx]


def _rows(p: dict[str, np.ndarray], idx: np.ndarray) -> dict[str, np.ndarray]:
    """Every parameter array of `p` at rows `idx` (`_row`)."""
    return {k: _row(v, idx) for k, v in p.items()}


def _local(w_loc: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """(n, A, 3) the local directions w_loc (A, p, 3) of the samples `idx`, sample first."""
    return w_loc[:, idx].transpose(1, 0, 2)


def _at(a: np.ndarray, loc: np.ndarray | None) -> np.ndarray:
    return a if loc is None else a[loc]


class PreviewShape(NamedTuple):
    """`preview_shape`'s (n, A, B) terms."""

    fres: np.ndarray  # Schlick's weight
    dv: np.ndarray  # the GGX D V product
    fc: np.ndarray | None  # the clearcoat lobe (None where no sample has one)
    dead: np.ndarray  # either direction under the horizon (or not finite)


def preview_shape(p: dict[str, np.ndarray], wi: np.ndarray, wo: np.ndarray, eps: float
                  ) -> PreviewShape:
    """UsdPreviewSurface's terms on the product grid that do not depend on its colours:
    `brdf.analytic.preview_surface` (with `_half_terms`, `_ggx_dv`, `schlick_weight`) term by
    term, in the same order of operations, per-direction terms on (n, A) or (n, B) and
    per-sample parameters broadcast.

    p : the `PREVIEW_SHAPE_INPUTS` of `preview_surface_params`, arrays with leading dimension 1
    or n; wi (n, A, 3), wo (n, B, 3) local."""
    zi = np.maximum(wi[:, :, 2], 0.0)[:, :, None]  # (n, A, 1)
    zo = np.maximum(wo[:, :, 2], 0.0)[:, None, :]  # (n, 1, B)
    c = wi[:, :, None, 0] * wo[:, None, :, 0]
    c += wi[:, :, None, 1] * wo[:, None, :, 1]
    c += wi[:, :, None, 2] * wo[:, None, :, 2]
    c += 1.0
    np.maximum(c, TOL.brdf_eps, out=c)
    nh2 = zi + zo
    nh2 *= nh2
    nh2 /= 2.0 * c
    np.minimum(nh2, 1.0, out=nh2)
    c *= 0.5
    cos_d = np.sqrt(c, out=c)
    np.minimum(cos_d, 1.0, out=cos_d)
    fres = schlick_weight(cos_d)  # (n, A, B)

    def sca(v: np.ndarray) -> np.ndarray:  # (1 or n,) -> (1 or n, 1, 1)
        return v[:, None, None]

    dv = _ggx_dv_grid(nh2, zi, zo, sca(p["alpha"]))
    fc = None
    cc = p["clearcoat"]
    if np.any(cc > 0.0):
        r = (1.0 - p["ior"]) / (1.0 + p["ior"])
        r2c = sca(r * r)
        fc = (1.0 - r2c) * fres
        fc += r2c
        fc *= sca(cc)
        fc *= _ggx_dv_grid(nh2, zi, zo, sca(p["alpha_c"]))
    return PreviewShape(fres, dv, fc, _horizon_dead(wi, wo, eps))


def preview_colour(p: dict[str, np.ndarray], shape: PreviewShape,
                   loc: np.ndarray | None) -> np.ndarray:
    """UsdPreviewSurface on the product grid for n samples (`p` their parameters, leading
    dimension 1 or n) whose shapes are `shape`'s rows `loc` (None: its rows in order),
    `preview_surface`'s colour terms in its order of operations. Returns (3, n, A, B)
    float64, 0 where either direction is under the horizon."""
    fres, dv = _at(shape.fres, loc), _at(shape.dv, loc)

    def col(v: np.ndarray) -> np.ndarray:  # (1 or n, 3) -> (3, 1 or n, 1, 1)
        return v.T[:, :, None, None]

    diffuse = p["diffuseColor"]
    m = p["metallic"][:, None]
    spec_wf = p["useSpecularWorkflow"][:, None] != 0.0
    r = (1.0 - p["ior"]) / (1.0 + p["ior"])
    r2 = (r * r)[:, None]
    f0 = np.where(spec_wf, p["specularColor"], r2 * (1.0 - m) + diffuse * m)
    f90 = np.where(spec_wf, 1.0, (1.0 - m) + diffuse * m)
    dcol = np.where(spec_wf, diffuse, diffuse * (1.0 - m))
    f0g, dfg, dpi = col(f0), col(f90 - f0), col(dcol * INV_PI)
    out = np.empty((3, *fres.shape))
    for ch in range(3):  # loop over colour channels
        fr = dfg[ch] * fres
        fr += f0g[ch]  # f0 + (f90 - f0) w, as preview_surface (addition commutes exactly)
        o = out[ch]
        np.multiply(fr, dv, out=o)
        np.subtract(1.0, fr, out=fr)
        fr *= dpi[ch]
        o += fr
    if shape.fc is not None:
        out += _at(shape.fc, loc)[None]
    dead = _at(shape.dead, loc)
    if dead.any():
        out[:, dead] = 0.0
    return out


def _ggx_dv_grid(nh2: np.ndarray, zi: np.ndarray, zo: np.ndarray, alpha: np.ndarray
                 ) -> np.ndarray:
    """`brdf.analytic._ggx_dv` with zi (n, A, 1), zo (n, 1, B), alpha (n or 1, 1, 1)."""
    a2 = alpha * alpha
    d = nh2 * (a2 - 1.0)
    d += 1.0
    d *= d
    d *= np.pi
    k = 0.5 * alpha
    gi = zi * (1.0 - k)
    gi += k
    go = zo * (1.0 - k)
    go += k
    g = gi * go
    g *= 4.0
    d *= g
    return a2 / d


def _horizon_dead(wi: np.ndarray, wo: np.ndarray, eps: float) -> np.ndarray:
    """(n, A, B) bool: `brdf.common.valid_pairs` negated on the grid."""
    ok_i = (wi[:, :, 2] > eps) & np.isfinite(wi[:, :, 0] + wi[:, :, 1] + wi[:, :, 2])
    ok_o = (wo[:, :, 2] > eps) & np.isfinite(wo[:, :, 0] + wo[:, :, 1] + wo[:, :, 2])
    return ~(ok_i[:, :, None] & ok_o[:, None, :])


def phong_shape(e: np.ndarray, wi: np.ndarray, wo: np.ndarray, eps: float
                ) -> tuple[np.ndarray, np.ndarray]:
    """`brdf.analytic.phong`'s normalized lobe on the product grid, same operations in the
    same order: e (1 or n,), wi (n, A, 3), wo (n, B, 3) local; returns the lobe (n, A, B) and
    where either direction is under the horizon (n, A, B)."""
    cos_a = wi[:, :, None, 2] * wo[:, None, :, 2]
    cos_a -= wi[:, :, None, 0] * wo[:, None, :, 0]
    cos_a -= wi[:, :, None, 1] * wo[:, None, :, 1]
    np.maximum(cos_a, 0.0, out=cos_a)
    ee = np.broadcast_to(e[:, None, None], cos_a.shape)
    lobe = np.power(cos_a, ee)
    lobe *= ((e + 2.0) * (0.5 * INV_PI))[:, None, None]
    return lobe, _horizon_dead(wi, wo, eps)


def phong_colour(kd: np.ndarray, ks: np.ndarray, lobe: np.ndarray, dead: np.ndarray,
                 loc: np.ndarray | None) -> np.ndarray:
    """Phong on the grid for n samples (kd, ks (1 or n, 3)) whose lobes are `lobe`'s rows
    `loc` (None: its rows in order); returns (3, n, A, B), 0 under either horizon."""
    lobe, dead = _at(lobe, loc), _at(dead, loc)
    out = np.empty((3, *lobe.shape))
    for ch in range(3):  # loop over colour channels
        np.multiply(ks[:, ch, None, None], lobe, out=out[ch])
        out[ch] += (kd[:, ch] * INV_PI)[:, None, None]
    if dead.any():
        out[:, dead] = 0.0
    return out
