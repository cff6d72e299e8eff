"""The USD LOD schema on a baked root (`UsdLod`), beside the `LOD` variant set older importers
read.

- LOD root: `<root>/Baked` carries `LODRootAPI`. Its children are the LOD items in index
  order, `LOD0, LOD1, ..., LODn` (a `primOrder` in the root layer puts them first): `LOD1..n`
  are the payload's meshes M_i; `LOD0` is an empty Xform defined in the root layer that
  stands for the asset as authored, whose meshes are the source's, beside `Baked` (they cannot
  be re-parented without changing every path a studio has bound to). The payload's `CPM` and
  `Looks` scopes follow the items: no heuristic threshold selects an index past `n`.
- Heuristic: `<root>/LODHeuristic`, a `LODScreenSizeHeuristic` of domain `imaging`, outside
  the payload (present when it is unloaded), `projectionMethod = projectedSphere`, `extent` the
  root's `extentsHint` (every LOD inside it) in the root's space, which is `Baked`'s (a Scope,
  no transform). Its `thresholds` are the bake's `lod_switch_px`: LOD i switches in when the
  bounding-box diagonal covers `lod_switch_px[i-1]` pixels. UsdLod measures screen size as the
  fraction of the viewport's *area* the extent's bounding sphere covers (the sphere's diameter
  is the diagonal), so a size of p pixels on a reference viewport of W x H pixels is
  `pi (p / 2)^2 / (W H)`; the reference (`REFERENCE_VIEWPORT_PX`, 1920 x 1080) and the pixel
  sizes are recorded on the heuristic (`texelbake:referenceViewportPx`,
  `texelbake:switchPx`). Levels beyond the given sizes (an 'atlas'-mode chain longer than
  `lod_switch_px`) continue its last ratio (a quarter when one size is given).
- The variant set: variant `LOD<k>` shows item k and authors `lod:default:index = k`, so a
  client that reads neither the variants nor the heuristic shows what the selection shows, and
  `ComputeLOD` on the heuristic at a screen size gives the index of the variant the bake meant
  for that size (a test checks both against the switch distances).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from pxr import Gf, Sdf, Usd, UsdGeom, UsdLod, Vt

from texelbake.errors import SettingsError

#: the viewport (width, height) in pixels on which `lod_switch_px` become area fractions
REFERENCE_VIEWPORT_PX = (1920, 1080)
#: the heuristic prim's name under the baked root (outside the payload)
HEURISTIC_NAME = "LODHeuristic"


def switch_sizes(lod_switch_px: Sequence[float], n_lod: int) -> list[float]:
    """The switch size in pixels of LOD1..LOD`n_lod`: `lod_switch_px`, continued by its last
    ratio (a quarter after a single size) when the chain is longer."""
    px = [float(p) for p in lod_switch_px]
    if not px or any(not p > 0 for p in px):
        raise SettingsError(f"field 'lod_switch_px': positive pixel sizes expected, got {px}")
    ratio = px[-1] / px[-2] if len(px) > 1 else 0.25
    while len(px) < n_lod:
        px.append(px[-1] * ratio)
    return px[:n_lod]


def area_fraction(px: float | np.ndarray,
                  viewport: tuple[int, int] = REFERENCE_VIEWPORT_PX) -> np.ndarray:
    """UsdLod's screen size (fraction of the viewport's area) of a bounding sphere whose
    diameter covers `px` pixels on a `viewport` of (width, height) pixels."""
    return math.pi * (np.asarray(px, dtype=np.float64) / 2.0) ** 2 / float(viewport[0] *
                                                                             viewport[1])


def author_lod_root(stage: Usd.Stage, root: Usd.Prim, n_lod: int,
                    lod_switch_px: Sequence[float], extent: np.ndarray) -> UsdLod.ScreenSizeHeuristic:
    """Apply `LODRootAPI` to `<root>/Baked`, define its `LOD0` item and the screen-size
    heuristic (module docstring) in the root layer of `stage`. extent : (2, 3) lo, hi of every
    LOD in the root's space. Call with the `LOD` variant selection cleared or at LOD0 (this
    authors outside the variants); `author_variant_index` authors the default index inside each
    variant."""
    baked = root.GetChild("Baked")
    if not baked:
        raise SettingsError(f"the baked root {root.GetPath()} has no Baked prim to carry the "
                            "LOD schema")
    px = switch_sizes(lod_switch_px, n_lod)
    UsdGeom.Xform.Define(stage, baked.GetPath().AppendChild("LOD0"))
    items = [f"LOD{i}" for i in range(n_lod + 1)]
    others = [c for c in baked.GetAllChildrenNames() if c not in items]
    baked.SetChildrenReorder(items + sorted(others, key=str))
    # (no lod:default:index here: a local opinion would be stronger than the variants'; the
    # schema's fallback is 0, the `LOD0` variant's too)
    api = UsdLod.RootAPI.Apply(baked)
    heur = UsdLod.ScreenSizeHeuristic.Define(stage, root.GetPath().AppendChild(HEURISTIC_NAME))
    heur.CreateLodDomainAttr(UsdLod.Tokens.imaging)
    heur.CreateProjectionMethodAttr(UsdLod.Tokens.projectedSphere)
    lo, hi = np.asarray(extent, dtype=np.float32)
    heur.CreateExtentAttr(Vt.Vec3fArray.FromNumpy(np.stack([lo, hi])))
    heur.CreateThresholdsAttr(Vt.FloatArray([float(f) for f in area_fraction(np.asarray(px))]))
    prim = heur.GetPrim()
    prim.CreateAttribute("texelbake:switchPx", Sdf.ValueTypeNames.FloatArray, custom=True,
                         variability=Sdf.VariabilityUniform).Set(Vt.FloatArray(px))
    prim.CreateAttribute("texelbake:referenceViewportPx", Sdf.ValueTypeNames.Int2, custom=True,
                         variability=Sdf.VariabilityUniform).Set(Gf.Vec2i(*REFERENCE_VIEWPORT_PX))
    api.CreateLodHeuristicsRel().SetTargets([heur.GetPath()])
    return heur


def author_variant_index(stage: Usd.Stage, baked_path: Sdf.Path, index: int) -> None:
    """Inside the current variant edit context: `lod:default:index = index` on the LOD root."""
    over = stage.OverridePrim(baked_path)
    UsdLod.RootAPI(over).CreateLodDefaultIndexAttr(index)
