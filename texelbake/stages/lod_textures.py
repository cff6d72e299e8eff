"""Each LOD's fallback textures at its own size: the page is sized for LOD1
(`filtered.fallback_resolution`: a texel at most a pixel where LOD1 switches in); LOD i's
textures are that page's level l_i, where a texel is at most a pixel where LOD i switches in
(`lod_texture_levels`). A viewer that mip-maps builds its levels from the page as box means of
filled texels, so near a chart's border a coarse level mixes the page's padding and the
neighbouring chart in; a renderer that does not mip-map (Cycles) reads LOD1's texels on a LOD
drawn 4-16x smaller. The LOD's own texture is each level-l texel's mean over the covered
level-0 texels under it, weighted by their covered area (`box_down`), so neither happens at the
LOD's own distance. Only the inputs radiance is linear in are sized so (`per_lod`)."""

from __future__ import annotations

import numpy as np

from texelbake.stages.context import StageContext


def lod_texture_levels(ctx: StageContext, res: int, n_lods: int) -> list[int]:
    """The level of the res² page whose texels each LOD's textures carry: the side at which a
    texel is at most a pixel where LOD i switches in (`lod_switch_px[i - 1]`, the rule of
    `filtered.fallback_resolution` for LOD1), as a power of two ≤ res; a LOD past the switch
    sizes (or 'atlas' mode) takes the last one's level."""
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


def box_down(img: np.ndarray, area: np.ndarray, level: int) -> np.ndarray:
    """A level-0 map (n, n, c) at `level`: each coarse texel the mean of the level-0 texels
    under it weighted by their covered area (n, n), texels no area covers filled from the
    nearest covered one. Level 0 is the map itself, unchanged. float32."""
    from texelbake.stages.filtered import nearest_fill

    img = np.asarray(img)
    if level == 0:
        return img
    n = img.shape[0]
    f = 1 << level
    m = n // f
    w = np.asarray(area, dtype=np.float64).reshape(m, f, m, f)
    num = (img.astype(np.float64).reshape(m, f, m, f, -1) * w[..., None]).sum(axis=(1, 3))
    den = w.sum(axis=(1, 3))
    out = num / np.where(den > 0, den, 1.0)[..., None]
    out = nearest_fill(out, den > 0)
    return out.reshape(m, m, *img.shape[2:]).astype(np.float32)


def per_lod(fb: dict, levels: list[int]) -> dict:
    """The fallback's per-LOD textures (`box_down` of the page's at each LOD's level) of the
    inputs the preview surface's radiance is linear in: "lod_base" and, where the fallback has
    one, "lod_metallic", one entry per LOD. The normal maps stay at the page's size: radiance
    is not linear in the normal, and a mean normal loses the glints of what it averages
    (docs/decisions.md: "Each LOD's textures at its own size")."""
    area = fb["coverage"]
    out = {"lod_base": [box_down(fb["base"], area, lvl) for lvl in levels]}
    if fb.get("metallic") is not None:
        out["lod_metallic"] = [box_down(fb["metallic"][..., None], area, lvl)[..., 0]
                               for lvl in levels]
    return out
