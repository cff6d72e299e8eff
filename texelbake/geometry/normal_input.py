"""A material's `normal` input on M_org: UsdPreviewSurface's tangent-space normal (a normal
map through a UsdUVTexture, or a constant), decoded in the MikkTSpace frames of M_org's corner
normals and uvs (`geometry.mikktspace`: what Blender's, Cycles' and glTF viewers' normal-map
nodes build), so that the dense samples, the ground truth and every map baked from them see
the bumps an asset's normal maps draw. The tangent-space normals are read by the caller's
`local_normals` (`brdf.shading_normal`, which the layers above pass in: geometry does not
evaluate materials); a value it rejects (not finite, zero, at or below the tangent plane) is +z,
the interpolated corner normal."""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from texelbake.geometry.mesh import face_normals
from texelbake.geometry.mikktspace import decode, frames_at, mikk_tangents
from texelbake.model import AssetModel, Material

#: a material's tangent-space shading normals at uvs (m, 2) -> (m, 3) (`brdf.shading_normal`)
LocalNormals = Callable[[Material, np.ndarray], np.ndarray]


def normal_materials(materials: Sequence[Material]) -> np.ndarray:
    """(k,) bool: the materials whose shading normal is not the surface's own, a preview
    material whose `normal` input is read from a texture or is a constant other than +z."""
    out = np.zeros(len(materials), bool)
    for i, m in enumerate(materials):  # a loop over the few materials
        if m.model != "preview":
            continue
        v = m.params.get("normal")
        out[i] = "normal" in m.textures or (
            v is not None and not np.allclose(np.asarray(v, np.float64), (0.0, 0.0, 1.0)))
    return out


class NormalInput:
    """The normal inputs of an asset's materials on its surface (module docstring); `active`
    is False when no material has one, and `apply` then returns the normals it is given."""

    def __init__(self, asset: AssetModel, local_normals: LocalNormals) -> None:
        self.asset = asset
        self.local_normals = local_normals
        self.mapped = normal_materials(asset.materials)
        self.active = bool(self.mapped.any()) and asset.corner_uvs is not None
        self._tangents: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def _frames(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(tangent (f, 3, 3), sign (f,), corner normals (f, 3, 3)) of M_org, made once."""
        if self._tangents is None:
            a = self.asset
            cn = a.corner_normals
            if cn is None:  # none authored: the face normals, as a viewer derives them
                cn = np.repeat(face_normals(a.points, a.faces)[:, None], 3, axis=1)
            tangent, sign = mikk_tangents(a.points, a.faces, cn, a.corner_uvs)
            self._tangents = (tangent, sign, np.asarray(cn, np.float64))
        return self._tangents

    def apply(self, face: np.ndarray, bary: np.ndarray, normals: np.ndarray, uv: np.ndarray,
              material: np.ndarray) -> np.ndarray:
        """World shading normals (m, 3) at points of triangles `face` (m,) with barycentrics
        bary (m, 3), uv (m, 2) and material ids (m,): `normals` where the point's material
        has no normal input, its decoded normal input elsewhere."""
        if not self.active:
            return normals
        sel = np.flatnonzero(self.mapped[np.asarray(material)])
        if not sel.size:
            return normals
        tangent, sign, cn = self._frames()
        mats, uv_sel = np.asarray(material)[sel], np.asarray(uv)[sel]
        local = np.zeros((sel.size, 3))
        for mi in np.unique(mats):  # a loop over the few mapped materials
            k = mats == mi
            local[k] = self.local_normals(self.asset.materials[int(mi)], uv_sel[k])
        out = np.array(normals, dtype=np.float64, copy=True)
        out[sel] = decode(frames_at(tangent, sign, cn, np.asarray(face)[sel],
                                    np.asarray(bary, np.float64)[sel]), local)
        return out


def mapped_normals(asset: AssetModel, local_normals: LocalNormals) -> NormalInput | None:
    """The asset's `NormalInput` when one of its materials has a normal input, else None
    (nothing to apply)."""
    ni = NormalInput(asset, local_normals)
    return ni if ni.active else None
