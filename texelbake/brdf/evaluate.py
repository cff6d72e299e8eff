"""The dispatcher: a `texelbake.model.Material` (textured inputs resolved) -> f_r, per face;
the diffuse albedo and shading normal a material shows at uv."""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from texelbake import model
from texelbake.brdf.albedo import cosine_hemisphere
from texelbake.brdf.analytic import lambert, phong, preview_surface
from texelbake.brdf.cellular_shader import (
    cellular_color,
    cellular_params,
    cellular_shade,
    cellular_split,
)
from texelbake.brdf.common import (
    CELLULAR_DEFAULTS,
    LAMBERT_DEFAULTS,
    MERL_DEFAULTS,
    PHONG_DEFAULTS,
    as_color,
    as_dirs,
    as_scalar,
    as_uv,
)
from texelbake.brdf.merl import merl_lookup, merl_table_from_file
from texelbake.brdf.textures import sample_texture
from texelbake.brdf.widened import widen_inputs
from texelbake.errors import SettingsError, ShapeError
from texelbake.tol import TOL

_COLOR_INPUTS = frozenset(
    {"diffuseColor", "specularColor", "borderColor", "cellColorA", "cellColorB", "normal"}
)
_MODELS = ("lambert", "phong", "preview", "merl", "cellular")
_DEFAULTS: Mapping[str, Mapping[str, Any]] = {
    "lambert": LAMBERT_DEFAULTS,
    "phong": PHONG_DEFAULTS,
    "preview": model.PREVIEW_DEFAULTS,
    "cellular": CELLULAR_DEFAULTS,
    "merl": MERL_DEFAULTS,
}
#: inputs that only make sense as constants (never sampled from a texture)
_CONSTANT_INPUTS = frozenset({"seed", "cellScale", "useSpecularWorkflow", "file", "table"})


def _input(
    material: model.Material, name: str, n: int, uv: np.ndarray | None
) -> tuple[Any, bool]:
    """A material input: (value, textured). The texture sampled at uv ((n, 3) colour or (n,)
    scalar, textured=True) when the input is textured, else the constant, else the model's
    default (textured=False, the raw value)."""
    tex = material.textures.get(name)
    if tex is not None and name not in _CONSTANT_INPUTS:
        if uv is None:
            raise ShapeError(
                f"material {material.path!r}: input {name!r} is textured ({tex.path}); "
                f"uv (n, 2) is required, got None"
            )
        v = sample_texture(tex, uv)  # (n, c)
        if name in _COLOR_INPUTS:
            return (v[:, :3] if v.shape[1] >= 3 else np.repeat(v[:, :1], 3, axis=1)), True
        return v[:, 0], True
    if name in material.params:
        return material.params[name], False
    return _DEFAULTS[material.model][name], False


def material_inputs(
    material: model.Material,
    names: Sequence[str],
    uv: np.ndarray | None,
    rows: np.ndarray | None,
) -> dict[str, Any]:
    """Resolve inputs once per uv row (textures sampled at uv (m, 2)), then gather the
    textured ones to the evaluation rows (rows (n,) int into uv, or None for rows = uv rows)."""
    m = 1 if uv is None else uv.shape[0]
    out = {}
    for name in names:
        v, textured = _input(material, name, m, uv)
        out[name] = np.take(v, rows, axis=0) if (textured and rows is not None) else v
    return out


def _check_model(material: model.Material) -> None:
    if material.model not in _MODELS:
        raise SettingsError(
            f"material {material.path!r}: unknown BRDF model {material.model!r}, expected one "
            f"of {list(_MODELS)}"
        )


def _merl_table(material: model.Material) -> np.ndarray:
    if "table" in material.params:
        return np.asarray(material.params["table"], dtype=np.float64)
    if "file" in material.params:
        return merl_table_from_file(os.fspath(material.params["file"]))
    raise SettingsError(
        f"material {material.path!r}: merl model needs params 'table' or 'file', got "
        f"{sorted(material.params)}"
    )


def evaluate(
    material: model.Material,
    wi: Any,
    wo: Any,
    uv: Any = None,
    *,
    sample_index: Any = None,
    eps: float = TOL.grazing_cos,
    var: np.ndarray | None = None,
) -> np.ndarray:
    """Evaluate a material's BRDF.

    Picks the model from ``material.model``; each input comes from
    ``material.textures[name]`` sampled at uv (bilinear, :func:`sample_texture`), else from
    ``material.params[name]``, else from the model's defaults. Colour inputs take the first 3
    texture channels (a 1- or 2-channel texture is read as grey), scalar inputs the first.

    material : model.Material; wi, wo : (n, 3) float64 local-frame unit vectors
    uv : (n, 2) float64 or None (required for textured inputs and the cellular model); with
        ``sample_index`` it is (m, 2), one row per surface sample
    sample_index : (n,) int into uv, or None. The CPM layout (many direction pairs per sample):
        textures and the cellular pattern are then evaluated once per sample (m rows) and
        gathered, instead of once per (sample, direction pair) row.
    var : (n,) each row's lobe widened by this slope variance per axis
        (`texelbake.brdf.widened.widen_inputs`, textured inputs included), None for none
    returns : (n, 3) float64, 1/sr
    raises SettingsError (naming material.path) for an unknown model, ShapeError for bad shapes
    """
    _check_model(material)
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    uv_a = None if uv is None else as_uv(uv)
    rows = _rows_index(sample_index, n, uv_a)
    if uv_a is not None and rows is None and uv_a.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv_a.shape}")
    kind = material.model
    if kind == "lambert":
        p = material_inputs(material, ("diffuseColor",), uv_a, rows)
        return lambert(p["diffuseColor"], wi, wo, eps=eps)
    if kind == "phong":
        p = material_inputs(material, ("diffuseColor", "specularColor", "exponent"), uv_a, rows)
        if var is not None:
            p = widen_inputs(kind, p, var)
        return phong(p["diffuseColor"], p["specularColor"], p["exponent"], wi, wo, eps=eps)
    if kind == "preview":
        p = material_inputs(material, PREVIEW_BRDF_INPUTS, uv_a, rows)
        if var is not None:
            p = widen_inputs(kind, p, var)
        return preview_surface(p, wi, wo, eps=eps)
    if kind == "merl":
        scale = as_scalar(material_inputs(material, ("scale",), uv_a, rows)["scale"], n, "scale")
        return merl_lookup(_merl_table(material), wi, wo, eps=eps) * scale[:, None]
    # cellular: the pattern once per uv row, the shading per evaluation row
    if uv_a is None:
        raise ShapeError(f"material {material.path!r}: the cellular model needs uv (n, 2)")
    m = uv_a.shape[0]
    p = cellular_params(material_inputs(material, tuple(CELLULAR_DEFAULTS), uv_a, None), m)
    border, color, finite = cellular_split(p, uv_a)
    bc, br = p["borderColor"], p["borderRoughness"]
    if rows is not None:
        border, color, finite = border[rows], color[rows], finite[rows]
        bc = bc if bc.shape[0] == 1 else bc[rows]
        br = br if br.shape[0] == 1 else br[rows]
    return cellular_shade(border, color, finite, bc, br, wi, wo, eps)


def _used_rows(rows: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    """(sorted distinct values of rows, index of each row's value in them): np.unique's
    (values, inverse) for indices into m rows, in O(len(rows) + m) without sorting."""
    seen = np.zeros(m, dtype=bool)
    seen[rows] = True
    used = np.flatnonzero(seen)
    position = np.cumsum(seen) - 1
    return used, position[rows]


def _rows_index(sample_index: Any, n: int, uv: np.ndarray | None) -> np.ndarray | None:
    if sample_index is None:
        return None
    rows = np.asarray(sample_index)
    if rows.shape != (n,) or not (np.issubdtype(rows.dtype, np.integer) or n == 0):
        raise ShapeError(f"sample_index must be ({n},) int, got {rows.shape} {rows.dtype}")
    if uv is None:  # no per-sample inputs to gather: every row uses the constants
        return None
    rows = rows.astype(np.int64)
    m = uv.shape[0]
    if n and (rows.min() < 0 or rows.max() >= m):
        raise ShapeError(
            f"sample_index must lie in [0, {m - 1}] (uv has {m} rows), got "
            f"[{rows.min()}, {rows.max()}]"
        )
    return rows


PREVIEW_BRDF_INPUTS = (
    "diffuseColor",
    "specularColor",
    "useSpecularWorkflow",
    "metallic",
    "roughness",
    "clearcoat",
    "clearcoatRoughness",
    "ior",
)

#: stratified cosine-weighted directions for the MERL normal-incidence albedo (deterministic)
_ALBEDO_GRID = 128


def diffuse_albedo(material: model.Material, uv: Any = None) -> np.ndarray:
    """The albedo a normal-map baker bakes for this material (what Blender / Substance /
    xNormal put in an albedo map next to the normal map; DESIGN.md "Rendering").

    preview: diffuseColor * (1 - metallic) (metallic workflow) or diffuseColor (specular);
    lambert, phong: diffuseColor (kd); cellular: the cell colour under uv; merl: the
    directional albedo at normal incidence, integral f_r(wi, n) (n.wi) dwi (stratified
    128 x 128 cosine-weighted quadrature), i.e. the Lambertian rho with the same normal-incidence
    reflectance, times ``scale``.

    material : model.Material; uv : (n, 2) float64 or None (then n = 1)
    returns : (n, 3) float64
    """
    _check_model(material)
    uv_a = None if uv is None else as_uv(uv)
    n = 1 if uv_a is None else uv_a.shape[0]
    kind = material.model
    if kind in ("lambert", "phong"):
        d = material_inputs(material, ("diffuseColor",), uv_a, None)["diffuseColor"]
        return np.broadcast_to(as_color(d, n, "diffuseColor"), (n, 3)).copy()
    if kind == "preview":
        p = material_inputs(material, ("diffuseColor", "metallic", "useSpecularWorkflow"), uv_a, None)
        d = as_color(p["diffuseColor"], n, "diffuseColor")
        m = np.clip(as_scalar(p["metallic"], n, "metallic"), 0.0, 1.0)
        wf = as_scalar(p["useSpecularWorkflow"], n, "useSpecularWorkflow")
        out = np.where(wf[:, None] != 0.0, d, d * (1.0 - m[:, None]))
        return np.broadcast_to(out, (n, 3)).copy()
    if kind == "cellular":
        if uv_a is None:
            raise ShapeError(f"material {material.path!r}: the cellular model needs uv (n, 2)")
        return cellular_color(material_inputs(material, tuple(CELLULAR_DEFAULTS), uv_a, None), uv_a)
    # merl
    g = (np.arange(_ALBEDO_GRID) + 0.5) / _ALBEDO_GRID
    u = np.stack(np.meshgrid(g, g, indexing="ij"), axis=-1).reshape(-1, 2)
    wi = cosine_hemisphere(u)
    wo = np.broadcast_to(np.array([0.0, 0.0, 1.0]), wi.shape)
    rho = np.pi * merl_lookup(_merl_table(material), wi, wo).mean(axis=0)
    scale = as_scalar(material_inputs(material, ("scale",), uv_a, None)["scale"], n, "scale")[:, None]
    return np.broadcast_to(rho[None, :] * scale, (n, 3)).copy()


def shading_normal(material: model.Material, uv: Any = None) -> np.ndarray:
    """Tangent-space shading normal of a material: UsdPreviewSurface's ``normal`` input
    ("Expects normal in tangent space [(-1,-1,-1), (1,1,1)]"; a normal map is connected
    through a UsdUVTexture whose scale (2, 2, 2, 1) and bias (-1, -1, -1, 0) do the remapping,
    so the sampled value is used as is), normalised. (0, 0, 1) for the other models, and where
    the value is not finite, has zero length or points below the tangent plane (z <= 0).

    :func:`evaluate` does not apply it: the caller owns the shading frame (build it with
    ``frames.tangent_frames(normal_world, tangent_world)`` and pass directions in it), so that
    the cosine terms and the BRDF use the same normal.

    material : model.Material; uv : (n, 2) float64 or None (then n = 1)
    returns : (n, 3) float64 unit vectors in the (t, b, n) frame of the surface
    """
    _check_model(material)
    uv_a = None if uv is None else as_uv(uv)
    n = 1 if uv_a is None else uv_a.shape[0]
    up = np.zeros((n, 3))
    up[:, 2] = 1.0
    if material.model != "preview":
        return up
    v = np.broadcast_to(as_color(_input(material, "normal", n, uv_a)[0], n, "normal"), (n, 3))
    length = np.linalg.norm(v, axis=1, keepdims=True)
    ok = np.isfinite(length[:, 0]) & (length[:, 0] > TOL.brdf_eps) & (v[:, 2] > 0.0)
    return np.where(ok[:, None], v / np.where(ok[:, None], length, 1.0), up)


def evaluate_by_face(
    materials: Sequence[model.Material],
    material_index: Any,
    wi: Any,
    wo: Any,
    uv: Any = None,
    *,
    sample_index: Any = None,
    eps: float = TOL.grazing_cos,
    var: np.ndarray | None = None,
) -> np.ndarray:
    """Evaluate many (sample, direction-pair) entries with a material per entry: groups by
    material index (a loop over the few materials present, vectorized within each).
    var : (n,) each entry's lobe widened by this slope variance per axis
        (`texelbake.brdf.widened.widen_inputs`), None for none

    materials : sequence of model.Material; material_index : (n,) int
    wi, wo : (n, 3) float64; uv : (n, 2) float64 or None
    sample_index : (n,) int or None; when given, uv is (m, 2) per surface sample and
        textures / the cellular pattern are evaluated once per sample (see :func:`evaluate`)
    returns : (n, 3) float64
    """
    wi, wo = as_dirs(wi, wo)
    n = wi.shape[0]
    idx = np.asarray(material_index)
    if idx.shape != (n,) or not (np.issubdtype(idx.dtype, np.integer) or idx.size == 0):
        raise ShapeError(f"material_index must be ({n},) int, got {idx.shape} {idx.dtype}")
    idx = idx.astype(np.int64)
    uv_a = None if uv is None else as_uv(uv)
    rows = _rows_index(sample_index, n, uv_a)
    if uv_a is not None and rows is None and uv_a.shape[0] != n:
        raise ShapeError(f"uv must be ({n}, 2) to match wi, got {uv_a.shape}")
    out = np.zeros((n, 3), dtype=np.float64)
    if n == 0:
        return out
    lo, hi = int(idx.min()), int(idx.max())
    if lo < 0 or hi >= len(materials):
        raise ShapeError(
            f"material_index must lie in [0, {len(materials) - 1}], got [{lo}, {hi}]"
        )
    # one group per material present, entries in ascending order (what a stable sort by
    # material gives, without sorting n entries: a mask per material, O(n) each; a bake
    # spent 3 s of 46 in that argsort)
    present = np.flatnonzero(np.bincount(idx, minlength=hi + 1))
    for m_i in present:  # a loop over the few materials
        group = np.flatnonzero(idx == m_i) if present.size > 1 else np.arange(n)
        mat = materials[int(m_i)]
        vg = None if var is None else np.asarray(var, np.float64)[group]
        if rows is None:
            out[group] = evaluate(
                mat, wi[group], wo[group], None if uv_a is None else uv_a[group], eps=eps,
                var=vg,
            )
            continue
        # only the samples this material uses: resolve inputs on them, then gather (what
        # np.unique(..., return_inverse=True) gives, by a presence mask instead of a sort)
        used, local = _used_rows(rows[group], uv_a.shape[0] if uv_a is not None else 0)
        out[group] = evaluate(
            mat, wi[group], wo[group], None if uv_a is None else uv_a[used],
            sample_index=local, eps=eps, var=vg,
        )
    return out
