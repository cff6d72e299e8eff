"""Sdr shader definitions for texelbake's own shader ids, so USD knows their inputs.

texelbake authors shaders whose `info:id` is one of its own ids (`texelbake:lambert`,
`texelbake:phong`, `texelbake:measured`, `texelbake:cellular`; the table in
`texelbake.model`). Without a definition in the Sdr registry, pxr's validator
`usdShadeValidators:ShaderSdrCompliance` reports `MissingShaderIdInRegistry` for every such
shader, and no tool can check the input types. `register_shader_definitions()` adds one
definition per id to the process's Sdr registry; after it, the validator also checks that each
authored input has the declared type (`MismatchedPropertyType`).

How: the definitions are UsdShade.Shader prims in an anonymous USD layer built here from
`SHADER_INPUTS` (the same convention as usd-core's own `usdShaders/shaderDefs.usda`), handed
to `Sdr.Registry().AddDiscoveryResult` and parsed by usdShade's own `usda` parser plugin.
The discovery result's identifier is the shader id; the definition prim is named with the
colon replaced by an underscore (`texelbake_cellular`) because a colon is not allowed in a
prim name, and the parser falls back to the result's sub-identifier for it (usd-core prints
one harmless "Invalid prim name" warning per id when it first parses).

Why in code and not a plug-in folder: the registration must work from an installed wheel
without `PXR_PLUGINPATH_NAME` tricks; any process that validates texelbake assets (ingest,
the upload check of the API, the tests) calls `register_shader_definitions()` first.
It is idempotent and thread-safe.
"""

from __future__ import annotations

import threading
from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType

from pxr import Sdf, Sdr, Usd, UsdShade

from texelbake.model import SHADER_CELLULAR, SHADER_LAMBERT, SHADER_MEASURED, SHADER_PHONG

#: the source type under which texelbake's definitions are registered
SOURCE_TYPE = "texelbake"

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

_LOCK = threading.Lock()
_LAYER: list[Sdf.Layer] = []  # keeps the anonymous definitions layer alive for the parser


def definition_prim_name(shader_id: str) -> str:
    """The prim name of a definition: `texelbake:cellular` -> `texelbake_cellular`."""
    return shader_id.replace(":", "_")


def build_definitions_layer() -> Sdf.Layer:
    """An anonymous layer with one UsdShade.Shader definition prim per texelbake shader id.

    Each prim carries `info:id`, `info:implementationSource = "sourceAsset"`, an
    `info:texelbake:sourceAsset` pointing at `texelbake/model.py` (where the shader table and
    the models' meaning are documented), its typed inputs with defaults and a token
    `outputs:surface`.
    """
    layer = Sdf.Layer.CreateAnonymous("texelbake_shaderDefs.usda")
    stage = Usd.Stage.Open(layer)
    impl = Path(__file__).with_name("model.py").resolve()
    for shader_id in sorted(SHADER_INPUTS):
        shader = UsdShade.Shader.Define(stage, f"/{definition_prim_name(shader_id)}")
        shader.CreateIdAttr(shader_id)
        shader.SetSourceAsset(Sdf.AssetPath(str(impl)), SOURCE_TYPE)
        shader.SetSdrMetadataByKey("role", "surface")
        for name, type_name, default in SHADER_INPUTS[shader_id]:
            shader.CreateInput(name, Sdf.ValueTypeNames.Find(type_name)).Set(default)
        shader.CreateOutput("surface", Sdf.ValueTypeNames.Token)
    return layer


def register_shader_definitions() -> None:
    """Add texelbake's shader ids to this process's Sdr registry (idempotent).

    Raises nothing on a second call. After it,
    `Sdr.Registry().GetShaderNodeByIdentifier("texelbake:cellular")` is a node whose inputs are
    `SHADER_INPUTS["texelbake:cellular"]`.
    """
    with _LOCK:
        if _LAYER:
            return
        layer = build_definitions_layer()
        _LAYER.append(layer)
        registry = Sdr.Registry()
        for shader_id in sorted(SHADER_INPUTS):
            name = definition_prim_name(shader_id)
            result = Sdr.NodeDiscoveryResult(
                shader_id,  # identifier: what `info:id` says
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
