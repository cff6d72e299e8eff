"""Materials: UsdPreviewSurface and texelbake shader networks (with their textures) -> Material,
and the material of every face (bindings, GeomSubsets)."""

from __future__ import annotations

from typing import Any

import numpy as np

from texelbake.asset.files import load_merl
from texelbake.asset.mtlx import MTLX_SURFACES, preview_params
from texelbake.asset.primvars import READER_WIDTH, face_values, group_faces
from texelbake.asset.uvtexture import read_uv_texture
from texelbake.asset.values import coerce_like, default_param, warn
from texelbake.errors import AssetError, AssetPathError
from texelbake.model import (
    PREVIEW_DEFAULTS,
    SHADER_MEASURED,
    SHADER_MODELS,
    SHADER_PREVIEW,
    Material,
    Texture,
)
from texelbake.usd.shaderdefs import SHADER_INPUTS, shader_id

#: defaults for unauthored inputs of texelbake's own shader ids: the Sdr definitions'
#: defaults (texelbake.usd.shaderdefs.SHADER_INPUTS), colours as tuples
TEXELBAKE_DEFAULTS: dict[str, dict[str, Any]] = {
    sid: {name: ("" if type_name == "asset" else default)
          for name, type_name, default in inputs}
    for sid, inputs in SHADER_INPUTS.items()
}

#: the fallback for faces with no bound material: grey Lambert, path ""
def _readonly(params: dict[str, Any]) -> dict[str, Any]:
    """Arrays in material params made read-only (Materials are shared, immutable values)."""
    for value in params.values():
        if isinstance(value, np.ndarray):
            value.flags.writeable = False
    return params


DEFAULT_MATERIAL = Material(path="", model="lambert",
                            params=_readonly({"diffuseColor": np.full(3, 0.18)}))

class MaterialReader:
    """Reads UsdShade materials into model.Material, caching textures per load."""

    def __init__(self, time: Any, warns: list[str]):
        self.time = time
        self.warns = warns
        self._images: dict[str, tuple[np.ndarray, bool, str]] = {}
        #: material path -> {input name: (primvar name, width, fallback (width,))} for inputs
        #: driven by a UsdPrimvarReader (texelbake.asset.primvars)
        self.primvar_inputs: dict[str, dict[str, tuple[str, int, np.ndarray]]] = {}

    def specialize(self, material: Material, prim: Any, faces: np.ndarray
                   ) -> tuple[list[tuple[bytes, Material]], np.ndarray]:
        """The material as faces `faces` of mesh `prim` see it: its primvar-driven inputs
        evaluated on the mesh (texelbake.asset.primvars).

        returns : ([(key, Material) per distinct value; key b"" when nothing is driven],
                   (len(faces),) int64 index into that list per face)
        """
        inputs = self.primvar_inputs.get(material.path)
        faces = np.asarray(faces, dtype=np.int64)
        if not inputs:
            return [(b"", material)], np.zeros(faces.shape[0], np.int64)
        names = sorted(inputs)
        cols = []
        for name in names:
            varname, width, fallback = inputs[name]
            vals, interp = face_values(prim, varname, width, self.time)
            if vals is None:
                vals = np.broadcast_to(fallback, (int(faces.max(initial=-1)) + 1, width))
            elif interp in ("vertex", "varying", "faceVarying"):
                warn(self.warns, f"material {material.path} on mesh {prim.GetPath()}: primvar "
                                 f"{varname} ({interp}) drives input {name}; texelbake's "
                                 "inputs are per face, so each face takes its corners' mean")
            cols.append(vals[faces])
        distinct, group = group_faces(np.concatenate(cols, axis=1), self.warns,
                                      f"material {material.path} on mesh {prim.GetPath()}")
        out = []
        for row in distinct:
            params = dict(material.params)
            at = 0
            for name in names:
                width = inputs[name][1]
                part = row[at:at + width]
                at += width
                current = params[name]
                if isinstance(current, np.ndarray):
                    params[name] = np.resize(part, current.shape).astype(np.float64)
                elif isinstance(current, int) and not isinstance(current, bool):
                    params[name] = int(part[0])
                else:
                    params[name] = float(part[0])
            key = np.ascontiguousarray(row, dtype=np.float64).tobytes()
            out.append((key, Material(path=material.path, model=material.model,
                                      params=_readonly(params), textures=material.textures)))
        return out, group

    # ---- network helpers -------------------------------------------------------------------
    @staticmethod
    def _source(inp_or_out: Any) -> Any:
        """The attribute that produces this input's / output's value (through node graphs)."""
        attrs = inp_or_out.GetValueProducingAttributes()
        return attrs[0] if attrs else None

    @staticmethod
    def _shader_id(prim: Any) -> str | None:
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        if not shader:
            return None
        return shader_id(shader)

    def _surface(self, material: Any, context: str) -> tuple[Any, str | None] | None:
        """(shader prim, shader id) feeding the material's surface output for a context."""
        out = material.GetSurfaceOutput(context) if context else material.GetSurfaceOutput()
        if not out or not out.HasConnectedSource():
            return None
        src = self._source(out)
        if src is None:
            return None
        prim = src.GetPrim()
        return prim, self._shader_id(prim)

    # ---- entry -----------------------------------------------------------------------------
    def read(self, material: Any) -> Material:
        mat_path = str(material.GetPath())
        found = self._surface(material, "texelbake")
        if found is not None:
            prim, sid = found
            if sid is not None and sid in SHADER_MODELS:
                return self._read_shader(mat_path, prim, sid)
            warn(self.warns,
                  f"material {mat_path}: unsupported shader id {sid!r} on "
                  f"outputs:texelbake:surface (shader {prim.GetPath()}); using outputs:surface")
        found = self._surface(material, "")
        if found is None or found[1] not in SHADER_MODELS:
            mtlx = self._surface(material, "mtlx")
            if mtlx is not None and mtlx[1] in MTLX_SURFACES:
                return self._read_mtlx(mat_path, *mtlx)
        if found is None:
            warn(self.warns, f"material {mat_path}: no surface shader connected; "
                              "using UsdPreviewSurface defaults")
            return self._constant_preview(mat_path, None)
        prim, sid = found
        if sid is not None and sid in SHADER_MODELS:
            return self._read_shader(mat_path, prim, sid)
        if sid in MTLX_SURFACES:
            return self._read_mtlx(mat_path, prim, sid)
        warn(self.warns,
              f"material {mat_path}: unsupported shader network (shader {prim.GetPath()}, id "
              f"{sid!r}); falling back to its constant values")
        return self._constant_preview(mat_path, prim)

    def _read_mtlx(self, mat_path: str, prim: Any, sid: str | None) -> Material:
        """A MaterialX surface shader as UsdPreviewSurface parameters (texelbake.asset.mtlx)."""
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)

        def value(name: str) -> Any:
            inp = shader.GetInput(name)
            src = self._source(inp) if inp else None
            if src is None or UsdShade.Output.IsOutput(src):
                own = inp.GetAttr() if inp else None
                return own.Get(self.time) if own is not None and own.HasAuthoredValue() else None
            return src.Get(self.time)  # an interface input's value

        def driven(name: str) -> bool:
            inp = shader.GetInput(name)
            src = self._source(inp) if inp else None
            return src is not None and UsdShade.Output.IsOutput(src)

        def lost(text: str) -> None:
            warn(self.warns, f"material {mat_path}: MaterialX shader {prim.GetPath()} "
                             f"({sid}): {text}")

        params = {k: default_param(v) for k, v in PREVIEW_DEFAULTS.items()}
        for name, v in preview_params(str(sid), value, driven, lost).items():
            params[name] = coerce_like(v, PREVIEW_DEFAULTS[name])
        return Material(path=mat_path, model="preview", params=_readonly(params))

    def _constant_preview(self, mat_path: str, prim: Any) -> Material:
        """UsdPreviewSurface defaults overlaid by a foreign shader's constant preview inputs."""
        from pxr import UsdShade

        params = {k: default_param(v) for k, v in PREVIEW_DEFAULTS.items()}
        if prim is not None:
            shader = UsdShade.Shader(prim)
            for name, default in PREVIEW_DEFAULTS.items():
                inp = shader.GetInput(name) if shader else None
                if inp and inp.GetAttr().HasAuthoredValue():
                    value = inp.GetAttr().Get(self.time)
                    if value is not None:
                        params[name] = coerce_like(value, default)
        return Material(path=mat_path, model="preview", params=_readonly(params))

    def _read_shader(self, mat_path: str, prim: Any, sid: str) -> Material:
        from pxr import UsdShade

        shader = UsdShade.Shader(prim)
        defaults = PREVIEW_DEFAULTS if sid == SHADER_PREVIEW else TEXELBAKE_DEFAULTS[sid]
        params: dict[str, Any] = {}
        textures: dict[str, Texture] = {}
        for name, default in defaults.items():
            params[name] = default_param(default)
            inp = shader.GetInput(name)
            if not inp:
                continue
            own = inp.GetAttr().Get(self.time) if inp.GetAttr().HasAuthoredValue() else None
            if own is not None:
                params[name] = coerce_like(own, default)
            src = self._source(inp)
            if src is None:
                continue
            if UsdShade.Output.IsOutput(src):
                src_prim = src.GetPrim()
                src_id = self._shader_id(src_prim)
                if src_id == "UsdUVTexture":
                    out_name = UsdShade.Output(src).GetBaseName()
                    texture, fallback = read_uv_texture(
                        src_prim, out_name, name, mat_path, self._input_value, self._images,
                        self.warns)
                    if texture is not None:
                        textures[name] = texture
                    elif fallback is not None:
                        params[name] = coerce_like(fallback, default)
                elif src_id in READER_WIDTH:  # evaluated on the bound gprim (`specialize`)
                    reader = UsdShade.Shader(src_prim)
                    width = READER_WIDTH[src_id]
                    varname = str(self._input_value(reader, "varname", "") or "")
                    fallback = self._input_value(reader, "fallback", None)
                    fb = (np.zeros(width) if fallback is None else
                          np.resize(np.asarray(fallback, np.float64).reshape(-1), width))
                    self.primvar_inputs.setdefault(mat_path, {})[name] = (varname, width, fb)
                else:
                    warn(self.warns,
                          f"material {mat_path}: input {name} of shader {prim.GetPath()} is "
                          f"driven by an unsupported node {src_prim.GetPath()} (id {src_id!r}); "
                          "using its constant value")
            else:  # a value from an interface input (material or node graph)
                value = src.Get(self.time)
                if value is not None:
                    params[name] = coerce_like(value, default)
        if sid == SHADER_MEASURED:
            file_inp = shader.GetInput("file")
            src = self._source(file_inp) if file_inp else None
            asset = src.Get(self.time) if src is not None and not src.GetName().startswith(
                "outputs:") else None
            resolved = asset.resolvedPath if asset is not None else ""
            if not resolved:
                shown = asset.path if asset is not None else ""
                raise AssetPathError(
                    f"measured BRDF file '{shown}' of material {mat_path} does not exist "
                    "(a measured BRDF has no fallback)",
                    path=shown, prim=str(prim.GetPath()))
            params["file"] = resolved
            params["table"] = load_merl(resolved, str(prim.GetPath()))
        return Material(path=mat_path, model=SHADER_MODELS[sid], params=_readonly(params),
                        textures=textures)

    def _input_value(self, shader: Any, name: str, default: Any) -> Any:
        inp = shader.GetInput(name)
        if not inp:
            return default
        src = self._source(inp)
        if src is None or src.GetName().startswith("outputs:"):
            return default
        value = src.Get(self.time)
        return default if value is None else value


def _bound(prim: Any, warns: list[str]) -> Any:
    from pxr import UsdShade

    material, _ = UsdShade.MaterialBindingAPI(prim).ComputeBoundMaterial()
    if material:
        return material
    rel = prim.GetRelationship("material:binding")
    if rel and rel.GetTargets() and not prim.HasAPI(UsdShade.MaterialBindingAPI):
        warn(warns, f"prim {prim.GetPath()}: material:binding is authored but "
                     "MaterialBindingAPI is not applied, so USD ignores it")
    return None


def face_materials(prim: Any, n_faces: int, time: Any, index_of: Any, warns: list[str],
                    source: str) -> np.ndarray:
    """(F,) int32 material index per source polygon: GeomSubsets (familyName materialBind),
    then the mesh's own binding (or the default material) for faces no subset covers.

    index_of(material prim or None, mesh prim, face indices (n,)) -> (n,) int material index
    of each of those faces (a material with primvar-driven inputs differs per face)."""
    from pxr import UsdGeom, UsdShade

    path = str(prim.GetPath())
    face_mat = np.full(n_faces, -1, dtype=np.int32)  # -1: not (yet) bound by a subset
    for subset in UsdShade.MaterialBindingAPI(prim).GetMaterialBindSubsets():
        sub_path = str(subset.GetPath())
        if subset.GetElementTypeAttr().Get() != UsdGeom.Tokens.face:
            warn(warns, f"subset {sub_path}: elementType is not face; ignored")
            continue
        idx = np.asarray(subset.GetIndicesAttr().Get(time) or [], dtype=np.int64)
        bad = (idx < 0) | (idx >= n_faces)
        if bad.any():
            first = int(idx[np.flatnonzero(bad)[0]])
            raise AssetError(f"GeomSubset {sub_path}: face index {first} is out of range for "
                             f"{n_faces} faces of mesh {path}", path=source, prim=sub_path)
        if idx.size:
            face_mat[idx] = index_of(_bound(subset.GetPrim(), warns), prim, idx)
    rest = np.flatnonzero(face_mat < 0)
    if rest.size:  # only materials some face uses enter the list
        face_mat[rest] = index_of(_bound(prim, warns), prim, rest)
    return face_mat
