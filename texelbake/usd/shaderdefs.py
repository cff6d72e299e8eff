"""Sdr shader definitions for texelbake's own shader ids, so USD knows their inputs.

texelbake authors shaders of its own (`texelbake:lambert`, `texelbake:phong`,
`texelbake:measured`, `texelbake:cellular` in scenes — the table in `texelbake.model` — and
`texelbake:cpm`, `texelbake:btf_laplacian` in baked results). A stock USD tool knows none of
them: a shader whose `info:id` is not in its Sdr registry fails pxr's validator
`usdShadeValidators:ShaderSdrCompliance` (`MissingShaderIdInRegistry`).

How they are authored so that any tool opens them silently and without a validation error
(`author_shader`): the shader carries no `info:id` and leaves `info:implementationSource` at
its fallback (`id`), so no tool asks Sdr for a node, and it names its definition in
texelbake's own source-type attributes — `info:texelbake:sourceAsset =
@./texelbake_shaders.usda@` and `info:texelbake:sourceAsset:subIdentifier =
"texelbake_lambert"` — with the definitions file (`DEFINITIONS_FILE`, `write_definitions`)
written beside the layer. Why not `implementationSource = "sourceAsset"` (which made a stock
pxr type-check the inputs): Sdr names an asset-based node `<hash><subIdentifier><sourceType>`,
and usdShade's `usda` parser first looks that identifier up as a prim name, so every stock
process that resolves such a shader (UsdValidation's `ShaderSdrCompliance`, a Hydra material
network) prints one "Invalid prim name" warning per shader id; there is no spelling of an
asset-based node that avoids it. A tool that wants the inputs' types opts in by authoring
`info:implementationSource = "sourceAsset"` over the shader (the definitions resolve as
before; a test does exactly that). (A `plugInfo.json` plug-in would need
`PXR_PLUGINPATH_NAME` in every studio tool's environment; an id with a colon cannot be found
by Sdr's file-system discovery either, since a definition's identifier comes from its file or
prim name.) `shader_id` reads a shader's texelbake id back from any form: files written with
`info:id = "texelbake:…"` or with `implementationSource = "sourceAsset"` still read, and
`register_shader_definitions()` adds the ids to a process's own registry so that the
`info:id` form validates there too.

The definitions are UsdShade.Shader prims (the convention of usd-core's
`usdShaders/shaderDefs.usda`), one per id, named with the colon replaced by an underscore
(`texelbake_cellular`) because a colon is not allowed in a prim name.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

from pxr import Gf, Sdf, Sdr, Usd, UsdShade

from texelbake.errors import SettingsError
from texelbake.io.atomic import atomic_write_bytes
from texelbake.model import (
    SHADER_BTF,
    SHADER_CELLULAR,
    SHADER_CPM,
    SHADER_LAMBERT,
    SHADER_MEASURED,
    SHADER_PHONG,
)

#: the source type under which texelbake's definitions are registered and authored
SOURCE_TYPE = "texelbake"
#: the definitions file written beside every layer that authors a texelbake shader
DEFINITIONS_FILE = "texelbake_shaders.usda"

#: shader id -> ((input name, Sdf type name, default), ...): names and types as in
#: texelbake.model's table, defaults as texelbake.brdf's *_DEFAULTS (a test checks both)
SHADER_INPUTS: Mapping[str, tuple[tuple[str, str, object], ...]] = MappingProxyType(
    {
        SHADER_LAMBERT: (("diffuseColor", "color3f", (0.18, 0.18, 0.18)),),
        SHADER_PHONG: (
            ("diffuseColor", "color3f", (0.18, 0.18, 0.18)),
            ("specularColor", "color3f", (0.0, 0.0, 0.0)),
            ("exponent", "float", 32.0),
        ),
        SHADER_MEASURED: (
            ("file", "asset", Sdf.AssetPath("")),
            ("scale", "float", 1.0),
        ),
        SHADER_CELLULAR: (
            ("cellScale", "float", 8.0),
            ("seed", "int", 0),
            ("borderWidth", "float", 0.08),
            ("borderColor", "color3f", (1.0, 0.78, 0.34)),
            ("borderRoughness", "float", 0.25),
            ("cellColorA", "color3f", (0.70, 0.08, 0.06)),
            ("cellColorB", "color3f", (0.05, 0.20, 0.65)),
        ),
    }
)

#: the baked material's shaders (the payload's CPM marker, whose data is the
#: `texelbake:levels` relationship, and texelbake.btf's Laplacian BTF): id -> inputs as above
BAKED_SHADER_INPUTS: Mapping[str, tuple[tuple[str, str, object], ...]] = MappingProxyType(
    {
        SHADER_CPM: (),
        SHADER_BTF: (
            ("eigenMap", "asset", Sdf.AssetPath("")),
            ("weightsMap", "asset", Sdf.AssetPath("")),
            ("lutMap", "asset", Sdf.AssetPath("")),
            ("pairsMap", "asset", Sdf.AssetPath("")),
            ("topLevel", "int", 0),
            ("numComponents", "int3", Gf.Vec3i(8, 2, 2)),
            ("meanModels", "token[]", []),
            ("resolution", "int2", Gf.Vec2i(0, 0)),
        ),
    }
)

#: every texelbake shader id -> its inputs
ALL_SHADER_INPUTS: Mapping[str, tuple[tuple[str, str, object], ...]] = MappingProxyType(
    {**SHADER_INPUTS, **BAKED_SHADER_INPUTS})

_LOCK = threading.Lock()
_LAYER: list[Sdf.Layer] = []  # keeps the anonymous definitions layer alive for the parser


def definition_prim_name(shader_id: str) -> str:
    """The prim name of a definition: `texelbake:cellular` -> `texelbake_cellular`."""
    return shader_id.replace(":", "_")


_ID_OF_PRIM_NAME: Mapping[str, str] = MappingProxyType(
    {definition_prim_name(sid): sid for sid in ALL_SHADER_INPUTS})
#: the attributes a texelbake shader names its definition by (UsdShade's source-asset names)
_ASSET_ATTR = f"info:{SOURCE_TYPE}:sourceAsset"
_SUB_ATTR = f"info:{SOURCE_TYPE}:sourceAsset:subIdentifier"


def build_definitions_layer(source_asset: str = f"./{DEFINITIONS_FILE}") -> Sdf.Layer:
    """An anonymous layer with one UsdShade.Shader definition prim per texelbake shader id.

    source_asset : the implementation each definition names for the `texelbake` source type:
        the definitions file itself (relative) when written to disk, an absolute path for
        the in-process registry (an anonymous layer cannot anchor a relative path)

    Each prim carries `info:id` (the texelbake id), `sdrMetadata` role "surface", its typed
    inputs with defaults and a token `outputs:surface`. Prims are sorted by name; the layer's
    text (`definitions_text`) is the same on every machine.
    """
    layer = Sdf.Layer.CreateAnonymous("texelbake_shaderDefs.usda")
    stage = Usd.Stage.Open(layer)
    for sid in sorted(ALL_SHADER_INPUTS):  # (Usd-level Define is not safe in a ChangeBlock)
        shader = UsdShade.Shader.Define(stage, f"/{definition_prim_name(sid)}")
        shader.CreateIdAttr(sid)
        # usdShade's parser takes a definition's implementation from its source asset for
        # the source type; without one the node it returns has no inputs. The definitions
        # file names itself (relative, so the file is the same on every machine).
        shader.SetSourceAsset(Sdf.AssetPath(source_asset), SOURCE_TYPE)
        shader.SetSdrMetadataByKey("role", "surface")
        for name, type_name, default in ALL_SHADER_INPUTS[sid]:
            shader.CreateInput(name, Sdf.ValueTypeNames.Find(type_name)).Set(default)
        shader.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    layer.documentation = ("texelbake's shader definitions (texelbake.usd.shaderdefs): texelbake "
                           "shaders name one of these prims as their source asset")
    return layer


def definitions_text() -> str:
    """The usda text of the definitions file (deterministic)."""
    return build_definitions_layer().ExportToString()


def write_definitions(folder: str | Path) -> Path:
    """Write `DEFINITIONS_FILE` into `folder` (atomically; unchanged bytes when it exists);
    return its path."""
    path = Path(folder) / DEFINITIONS_FILE
    data = definitions_text().encode()
    if not (path.is_file() and path.read_bytes() == data):
        atomic_write_bytes(path, data)
    return path


def author_shader(stage: Usd.Stage, path: str, shader_id: str) -> UsdShade.Shader:
    """Define a texelbake shader at `path` that names its definition in texelbake's
    source-type attributes (`./texelbake_shaders.usda`, relative to the layer being authored;
    the file is written beside that layer when it is on disk, else by the caller with
    `write_definitions`), with no `info:id` and no authored implementation source (module
    docstring). Raises SettingsError for an id texelbake does not define."""
    if shader_id not in ALL_SHADER_INPUTS:
        raise SettingsError(f"field 'shader_id': {shader_id!r} is not a texelbake shader id "
                            f"(expected one of {sorted(ALL_SHADER_INPUTS)})")
    shader = UsdShade.Shader.Define(stage, path)
    layer = stage.GetEditTarget().GetLayer()
    if layer.realPath:  # a layer on disk: its definitions beside it (in-memory: the caller's)
        write_definitions(Path(layer.realPath).parent)
    prim = shader.GetPrim()
    prim.CreateAttribute(_ASSET_ATTR, Sdf.ValueTypeNames.Asset, custom=False,
                         variability=Sdf.VariabilityUniform).Set(
        Sdf.AssetPath(f"./{DEFINITIONS_FILE}"))
    prim.CreateAttribute(_SUB_ATTR, Sdf.ValueTypeNames.Token, custom=False,
                         variability=Sdf.VariabilityUniform).Set(definition_prim_name(shader_id))
    return shader


def shader_id(shader: UsdShade.Shader) -> str | None:
    """A shader's id: `info:id` when authored, else the texelbake id its `texelbake`
    source-asset sub-identifier names (`author_shader`, whatever its implementation source);
    None when it has neither."""
    sid = shader.GetShaderId()
    if sid:
        return str(sid)
    sub = shader.GetPrim().GetAttribute(_SUB_ATTR)
    value = sub.Get() if sub else None
    if value:
        return _ID_OF_PRIM_NAME.get(str(value), str(value))
    return None


def input_type(shader_id: str, input_name: str) -> Sdf.ValueTypeName:
    """The Sdf type texelbake's definition declares for an input of a texelbake shader;
    raises SettingsError naming the input when there is none."""
    for name, type_name, _ in ALL_SHADER_INPUTS.get(shader_id, ()):
        if name == input_name:
            return Sdf.ValueTypeNames.Find(type_name)
    raise SettingsError(f"shader {shader_id!r} has no input {input_name!r}")


def register_shader_definitions() -> None:
    """Add texelbake's shader ids to this process's Sdr registry (idempotent).

    Raises nothing on a second call. After it,
    `Sdr.Registry().GetShaderNodeByIdentifier("texelbake:cellular")` is a node whose inputs are
    `SHADER_INPUTS["texelbake:cellular"]`. Needed only to validate files that name the ids by
    `info:id` (written before `author_shader`); files written now validate anywhere.
    """
    with _LOCK:
        if _LAYER:
            return
        layer = build_definitions_layer(str((Path(__file__).parents[1] / "model.py").resolve()))
        _LAYER.append(layer)
        registry = Sdr.Registry()
        for sid in sorted(ALL_SHADER_INPUTS):
            name = definition_prim_name(sid)
            result = Sdr.NodeDiscoveryResult(
                sid,  # identifier: what `info:id` says
                Sdr.Version().GetAsDefault(),
                name,  # name
                SOURCE_TYPE,  # family
                "usda",  # discovery type: parsed by usdShade's shader-def parser
                SOURCE_TYPE,  # source type
                layer.identifier,  # uri
                layer.identifier,  # resolved uri (the parser re-finds the live layer)
                "",  # source code
                {},  # metadata
                "",  # blind data
                name,  # sub-identifier: the definition prim's name
            )
            registry.AddDiscoveryResult(result)
