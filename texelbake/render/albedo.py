"""The albedo map the baseline modes (``normalmap``, ``toksvig``, ``leadr``) read.

A studio bakes its albedo at a texture's resolution, not at the CPM atlas's: at the default
16² atlas a printed texture averages to one colour per chart (the baselines showed a plain
body where the asset is printed). The bake already writes such a page, on the same atlas
layout: LOD1's UsdPreviewSurface fallback base colour (`stages.filtered.fallback_maps`, side
`fallback_resolution`, 512² at most). When that page is finer than the atlas, the baselines take
their albedo from it, diffuseColor × (1 − metallic) in the metallic workflow (the fallback's
metallic map or constant, `brdf.diffuse_albedo`'s rule), mip-mapped and looked up trilinearly at the level the
filtered maps use shifted by log2(page / atlas), so both address the same footprint; else they
keep the atlas-resolution albedo of the filtered maps.
"""

from __future__ import annotations

import math

import numpy as np

from texelbake.render.preview_surface import mip_chain, trilinear
from texelbake.render.scene import RenderScene


def albedo_chain(scene: RenderScene) -> list[np.ndarray] | None:
    """The finer albedo page as a mip chain ((n_l², 3) float64 per level, finest first), or
    None when the bake's fallback is no finer than the atlas (cached on the scene)."""
    cache = scene.__dict__.setdefault("_albedo_chain", [])
    if cache:
        return cache[0]
    mats = scene.baked.fallback.get("materials", [])
    mat = mats[0] if mats else {}
    base = (mat.get("textures") or {}).get("diffuseColor")
    chain = None
    if base is not None and base.shape[0] > scene.n0:
        consts = mat.get("constants") or {}
        metallic = (mat.get("textures") or {}).get("metallic")  # the page's map, or
        if metallic is None:  # the dominant material's constant
            metallic = float(consts.get("metallic") or 0.0)
        specular_workflow = bool(consts.get("useSpecularWorkflow") or 0)
        kd = 1.0 if specular_workflow else 1.0 - np.clip(metallic, 0.0, 1.0)
        chain = mip_chain(np.asarray(base, np.float64)[..., :3] * kd)
    cache.append(chain)
    return chain


def baseline_albedo(scene: RenderScene, uv: np.ndarray, lam: np.ndarray | None = None
                    ) -> np.ndarray | None:
    """The finer page's albedo at atlas uv (k, 2), (k, 3) float64; None when there is no finer
    page. lam (k,): the footprint's fractional level in atlas levels, unclipped (below 0 the
    footprint is finer than the atlas; the page serves it down to its own finest level);
    None: the page's finest level (``normalmap`` multi-samples the pixel itself)."""
    chain = albedo_chain(scene)
    if chain is None:
        return None
    if lam is None:
        return trilinear(chain, uv, np.zeros(uv.shape[0]))
    shift = math.log2(math.sqrt(chain[0].shape[0]) / scene.n0)
    return trilinear(chain, uv, np.asarray(lam, np.float64) + shift)
