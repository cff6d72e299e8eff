"""Cut-outs: UsdPreviewSurface's `opacity` with `opacityThreshold` > 0.

The UsdPreviewSurface spec: with a threshold above 0, a point whose opacity is below it is
not there at all (a cut-out: no shading, no shadow, no hit), and one at or above it is fully
opaque. texelbake has no partial transparency: with threshold 0 the opacity is not read (an
opaque surface). `opacity` comes from a texture's channel (e.g. the `a` output of a
UsdUVTexture) or a constant.

`Cutout` is what every ray cast against M_org asks (`texelbake.geometry.raycast.RayCaster`
takes it as its `cutout`): which faces can be cut at all, and whether a point on them is.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from texelbake import model
from texelbake.brdf.textures import sample_texture
from texelbake.errors import ShapeError


def _threshold(material: model.Material) -> float:
    if material.model != "preview":
        return 0.0
    return float(material.params.get("opacityThreshold", 0.0))


def _constant_opacity(material: model.Material) -> float:
    return float(material.params.get("opacity", 1.0))


def can_cut(material: model.Material) -> bool:
    """The material may cut its surface: a threshold above 0 and a textured opacity or a
    constant one below the threshold."""
    t = _threshold(material)
    if t <= 0.0:
        return False
    return "opacity" in material.textures or _constant_opacity(material) < t


@dataclass(frozen=True, eq=False)
class Cutout:
    """The cut-out test of one mesh.

    materials : the asset's materials; face_material : (f,) int32; corner_uvs : (f, 3, 2)
    float64; faces : (f,) bool, the faces whose material can cut (`can_cut`)
    """

    materials: tuple[model.Material, ...]
    face_material: np.ndarray
    corner_uvs: np.ndarray
    faces: np.ndarray

    def cut_uv(self, prim: Any, uv: Any) -> np.ndarray:
        """(k,) bool: the point at `uv` (k, 2) float64 on face `prim` (k,) int64 is cut."""
        prim = np.asarray(prim, dtype=np.int64)
        uv = np.asarray(uv, dtype=np.float64)
        if uv.shape != (prim.shape[0], 2):
            raise ShapeError(f"uv must be ({prim.shape[0]}, 2), got {uv.shape}")
        out = np.zeros(prim.shape[0], dtype=bool)
        sel = np.flatnonzero(self.faces[prim])
        if sel.size == 0:
            return out
        mat = self.face_material[prim[sel]]
        for m in np.unique(mat).tolist():  # a loop over the few cutting materials
            rows = sel[mat == m]
            material = self.materials[m]
            tex = material.textures.get("opacity")
            opacity = (sample_texture(tex, uv[rows])[:, 0] if tex is not None
                       else np.full(rows.shape[0], _constant_opacity(material)))
            out[rows] = opacity < _threshold(material)
        return out

    def cut(self, prim: Any, bary: Any) -> np.ndarray:
        """(k,) bool: the hit at barycentrics `bary` (k, 2) float64 (open3d's (u, v), weights
        (1 - u - v, u, v)) of face `prim` (k,) int64 is cut."""
        prim = np.asarray(prim, dtype=np.int64)
        return self.cut_uv(prim, hit_uv(self.corner_uvs, prim, bary))


def hit_uv(corner_uvs: np.ndarray, prim: np.ndarray, bary: Any) -> np.ndarray:
    """(k, 2) uv of ray hits at barycentrics `bary` (k, 2) (open3d's (u, v), weights
    (1 - u - v, u, v)) of faces `prim` (k,) int64, from the mesh's (f, 3, 2) corner uvs: what
    every cut-out test (`geometry.raycast.CutoutTest.cut`) looks its opacity up at."""
    b = np.asarray(bary, dtype=np.float64)
    if b.shape != (prim.shape[0], 2):
        raise ShapeError(f"bary must be ({prim.shape[0]}, 2), got {b.shape}")
    w = np.column_stack([1.0 - b[:, 0] - b[:, 1], b])  # (k, 3)
    return np.einsum("nk,nkj->nj", w, corner_uvs[prim])


def asset_cutout(asset: model.AssetModel) -> Cutout | None:
    """`cutout_of` the asset's faces (M_org)."""
    return cutout_of(asset.materials, asset.face_material, asset.corner_uvs)


def cutout_of(materials: tuple[model.Material, ...], face_material: np.ndarray,
              corner_uvs: np.ndarray) -> Cutout | None:
    """The mesh's Cutout, or None when no face's material can cut (every ray then takes the
    opaque path, bit for bit as without cut-outs).

    face_material : (f,) int; corner_uvs : (f, 3, 2) float64
    """
    cutting = np.array([can_cut(m) for m in materials], dtype=bool)
    if not cutting.any():
        return None
    fm = np.asarray(face_material, dtype=np.int32)
    faces = cutting[fm]
    if not faces.any():
        return None
    return Cutout(tuple(materials), fm, np.asarray(corner_uvs, dtype=np.float64), faces)
