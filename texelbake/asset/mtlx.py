"""MaterialX surface shaders authored in USD (`outputs:mtlx:surface`), read as UsdPreviewSurface.

usd-core's wheel has no UsdMtlx (no `.mtlx` file format, no MaterialX nodes in Sdr), so a
MaterialX network cannot be evaluated through pxr here. What DCCs write most is a
`ND_standard_surface_surfaceshader` (Autodesk Standard Surface) or MaterialX's own
`ND_UsdPreviewSurface_surfaceshader` as ordinary UsdShade.Shader prims; their *constant* inputs
map onto UsdPreviewSurface parameters (texelbake's "preview" BRDF), which is the fallback:

| Standard Surface              | UsdPreviewSurface                                   |
|-------------------------------|-----------------------------------------------------|
| base × base_color             | diffuseColor                                        |
| metalness                     | metallic                                            |
| specular_roughness            | roughness                                           |
| specular_IOR                  | ior                                                 |
| coat, coat_roughness          | clearcoat, clearcoatRoughness                       |
| mean of opacity (color3)      | opacity                                             |
| emission × emission_color     | emissiveColor                                       |

Lobes UsdPreviewSurface lacks (sheen, subsurface, transmission, thin film, specular
anisotropy) are dropped, and an input driven by a node (a texture, a math graph) keeps the
shader's constant or the Standard Surface default; each case is warned, naming the input.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

STANDARD_SURFACE = "ND_standard_surface_surfaceshader"
MTLX_PREVIEW_SURFACE = "ND_UsdPreviewSurface_surfaceshader"
MTLX_SURFACES = (STANDARD_SURFACE, MTLX_PREVIEW_SURFACE)

#: Standard Surface inputs and their specification defaults (Autodesk Standard Surface 1.0.1)
STANDARD_DEFAULTS: dict[str, Any] = {
    "base": 1.0, "base_color": (0.8, 0.8, 0.8), "metalness": 0.0,
    "specular_roughness": 0.2, "specular_IOR": 1.5, "coat": 0.0, "coat_roughness": 0.1,
    "opacity": (1.0, 1.0, 1.0), "emission": 0.0, "emission_color": (1.0, 1.0, 1.0),
}
#: inputs whose lobes UsdPreviewSurface cannot show (warned when non-zero)
DROPPED_LOBES = ("sheen", "subsurface", "transmission", "thin_film_thickness",
                 "specular_anisotropy")


def preview_params(shader_id: str, value: Callable[[str], Any], driven: Callable[[str], bool],
                   warn: Callable[[str], None]) -> dict[str, Any]:
    """UsdPreviewSurface parameters from a MaterialX surface shader's inputs.

    value(name) : the input's constant (None when unauthored); driven(name) : True when a node
        drives it; warn(text) : report a loss
    returns : {preview input name: value} for the inputs the shader determines
    """
    if shader_id == MTLX_PREVIEW_SURFACE:  # the same names as UsdPreviewSurface
        names = ("diffuseColor", "emissiveColor", "useSpecularWorkflow", "specularColor",
                 "metallic", "roughness", "clearcoat", "clearcoatRoughness", "opacity",
                 "opacityThreshold", "ior")
        out = {}
        for name in names:
            if driven(name):
                warn(f"input {name} is driven by a node; using its constant")
            v = value(name)
            if v is not None:
                out[name] = v
        return out

    def get(name: str) -> Any:
        if driven(name):
            warn(f"input {name} is driven by a node; using its constant")
        v = value(name)
        return STANDARD_DEFAULTS[name] if v is None else v

    for lobe in DROPPED_LOBES:
        v = value(lobe)
        if driven(lobe) or (v is not None and np.any(np.asarray(v, np.float64) != 0.0)):
            warn(f"input {lobe}: UsdPreviewSurface has no such lobe; dropped")
    return {
        "diffuseColor": tuple(float(get("base")) * np.asarray(get("base_color"), np.float64)),
        "metallic": float(get("metalness")),
        "roughness": float(get("specular_roughness")),
        "ior": float(get("specular_IOR")),
        "clearcoat": float(get("coat")),
        "clearcoatRoughness": float(get("coat_roughness")),
        "opacity": float(np.mean(np.asarray(get("opacity"), np.float64))),
        "emissiveColor": tuple(float(get("emission"))
                               * np.asarray(get("emission_color"), np.float64)),
    }
