"""Dense samples where the detail is (`sample_density="detail"`).

Seed 000 §4.1 spreads the dense samples X by area, so every texel holds the same count
whatever it covers. Part of a texel over one flat face of one constant material needs few of
them: every sample there has the same normal and the same BRDF, so Eq. 7's sums over them are
the face's area times one sample's term wherever visibility is one pattern, and its samples
only place that pattern's edges (a shadow across the face). A face is *simple* when

* it is flat: each corner's shading normal is its geometric normal within `TOL.exact_normal`
  (the tolerance `cpm.classify` groups a facet by);
* its material is constant over it: no input read from a texture and not the cellular shader
  (primvar-driven inputs are per face after ingest);
* it is at least one finest texel's area (smaller faces are the detail a texel spans).

A simple face is sampled at `SIMPLE_DENSITY` of the requested density, every other face at
the requested one. The samples of a face share its area, so every area-weighted sum stays
unbiased; the sample count, and with it memory, sampling and every per-sample cost downstream,
follows the surface's detail rather than the atlas's area.
"""

from __future__ import annotations

import numpy as np

from texelbake.geometry.mesh import face_normals, triangle_areas
from texelbake.model import AssetModel
from texelbake.tol import TOL

#: a simple face's sample density relative to the request's (docs/decisions.md, "Dense samples
#: follow the detail": measured against 1/2 and 1/8)
SIMPLE_DENSITY = 0.25


def simple_faces(asset: AssetModel, texel_area: float) -> np.ndarray:
    """(f,) bool: the faces of `asset` that are flat, of a constant material and at least
    `texel_area` (a finest texel's area on the surface, world units²)."""
    areas = triangle_areas(asset.points, asset.faces)
    geo = face_normals(asset.points, asset.faces)
    flat = np.all(np.einsum("fck,fk->fc", asset.corner_normals, geo) >= 1.0 - TOL.exact_normal,
                  axis=1)
    constant = np.array([m.model != "cellular" and not m.textures for m in asset.materials],
                        bool)
    return flat & constant[asset.face_material] & (areas >= float(texel_area))


def face_density(asset: AssetModel, texel_area: float) -> np.ndarray:
    """(f,) float64: each face's sample density relative to the request's, `SIMPLE_DENSITY`
    on `simple_faces` and 1 elsewhere."""
    return np.where(simple_faces(asset, texel_area), SIMPLE_DENSITY, 1.0)
