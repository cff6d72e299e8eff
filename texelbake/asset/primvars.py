"""Material inputs driven by `UsdPrimvarReader_*` nodes, evaluated on the bound geometry.

A UsdPreviewSurface input connected to a primvar reader (the Teapot's `diffuseColor` reads
`displayColor`) takes its value from the *gprim* the material is bound to, not from the
material: one material bound to two meshes with different `displayColor` shades them
differently. texelbake materials are per face (`AssetModel.face_material`), so ingest
specializes a material per distinct primvar value of the faces it is bound to:

* `constant` (also inherited from an ancestor, as UsdGeom's primvar inheritance says) and
  `uniform` primvars give each face its exact value;
* `vertex`, `varying` and `faceVarying` primvars vary inside a face; texelbake's BRDF inputs
  are per face, so each face takes the mean of its corners' values (a warning says so);
* a primvar the gprim does not have gives the reader's `inputs:fallback` (the UsdPreviewSurface
  spec's reader semantics; zeros when no fallback is authored);
* faces of one material are grouped by value; more than `MAX_VARIANTS` distinct values per
  (material, mesh) are quantized to 1/255 steps, and if still too many the mesh's area-blind
  mean is used, with a warning (a per-face specialisation is only worth it for a few values).
"""

from __future__ import annotations

from typing import Any

import numpy as np

#: UsdPrimvarReader id -> number of components of its output
READER_WIDTH = {
    "UsdPrimvarReader_float": 1, "UsdPrimvarReader_int": 1, "UsdPrimvarReader_float2": 2,
    "UsdPrimvarReader_float3": 3, "UsdPrimvarReader_normal": 3, "UsdPrimvarReader_point": 3,
    "UsdPrimvarReader_vector": 3, "UsdPrimvarReader_float4": 4,
}

#: distinct values per (material, mesh) before quantization
MAX_VARIANTS = 64


def face_values(prim: Any, name: str, width: int, time: Any
                ) -> tuple[np.ndarray | None, str]:
    """Per-face values of primvar `name` on mesh `prim`.

    returns : ((n_faces, width) float64 or None when the primvar is absent, not authored or
        does not match the topology, interpolation token ("" when absent))
    """
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(prim)
    counts = np.asarray(mesh.GetFaceVertexCountsAttr().Get(time) or [], dtype=np.int64)
    fvi = np.asarray(mesh.GetFaceVertexIndicesAttr().Get(time) or [], dtype=np.int64)
    n_faces = counts.shape[0]
    pv = UsdGeom.PrimvarsAPI(prim).FindPrimvarWithInheritance(name)
    if not pv or not pv.HasAuthoredValue():
        return None, ""
    raw = pv.ComputeFlattened(time)
    if raw is None:
        return None, ""
    values = np.asarray(raw, dtype=np.float64).reshape(len(raw), -1)
    if values.shape[1] == 1 and width > 1:
        values = np.repeat(values, width, axis=1)
    if values.shape[1] < width or values.shape[0] == 0:
        return None, str(pv.GetInterpolation())
    values = values[:, :width]
    interp = str(pv.GetInterpolation())
    if interp == "constant":
        return np.broadcast_to(values[0], (n_faces, width)).copy(), interp
    if interp == "uniform":
        return (values.copy() if values.shape[0] == n_faces else None), interp
    if interp in ("vertex", "varying", "faceVarying"):
        corner = values[fvi] if interp != "faceVarying" else values
        if corner.shape[0] != fvi.shape[0] or (interp != "faceVarying"
                                                and fvi.size and fvi.max() >= values.shape[0]):
            return None, interp
        if n_faces == 0:
            return np.zeros((0, width)), interp
        starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
        nonempty = counts > 0
        sums = np.zeros((n_faces, width))
        sums[nonempty] = np.add.reduceat(corner, starts[nonempty], axis=0)
        return sums / np.maximum(counts, 1)[:, None], interp
    return None, interp


def group_faces(values: np.ndarray, warns: list[str], where: str
                ) -> tuple[np.ndarray, np.ndarray]:
    """Group faces by value: (distinct (k, w) float64, (n,) int group of each face), with the
    MAX_VARIANTS rule of the module docstring."""
    from texelbake.asset.values import warn

    distinct, group = np.unique(values, axis=0, return_inverse=True)
    if distinct.shape[0] > MAX_VARIANTS:
        q = np.round(values * 255.0) / 255.0
        distinct, group = np.unique(q, axis=0, return_inverse=True)
        if distinct.shape[0] > MAX_VARIANTS:
            warn(warns, f"{where}: {distinct.shape[0]} distinct primvar values; using their mean")
            return values.mean(axis=0, keepdims=True), np.zeros(values.shape[0], np.int64)
        warn(warns, f"{where}: primvar values quantized to 1/255 ({distinct.shape[0]} distinct)")
    return distinct, group.reshape(-1)
