"""The asset's stage composed as USD composes it, with what usd-core's wheel lacks: MaterialX
documents composed through their translation (`texelbake.asset.mtlx_document`).

`read_composed` swaps, for the life of the stage, each arc to a `.mtlx` document for one to the
document's in-memory translation: the layer holding the arc is edited in pxr's layer registry
(`UpdateExternalReference`) and reloaded from disk afterwards, so nothing is written and the
next open sees the file as authored. `reached_specs` composes with some layers muted (never
opened) and tells which specs the composed stage uses: what the variant selections reach.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

from texelbake.asset.mtlx_document import TRANSLATED_SUFFIX, translated_layer
from texelbake.asset.values import first_line
from texelbake.errors import AssetError

T = TypeVar("T")


def layer_key(layer: Any) -> str:
    """A layer's file as `scan_asset_paths` names it: the real path on disk, `pkg[member]` for
    a package member, the document's path for a translated MaterialX document."""
    from pxr import Ar, Sdf

    ident = Sdf.Layer.SplitIdentifier(layer.identifier)[0]
    if ident.endswith(TRANSLATED_SUFFIX):
        ident = ident[: -len(TRANSLATED_SUFFIX)]
    if Ar.IsPackageRelativePath(ident):
        outer, inner = Ar.SplitPackageRelativePathOuter(ident)
        return f"{os.path.realpath(outer)}[{inner}]"
    return os.path.realpath(ident)


def read_composed(root: str, mtlx: Sequence[tuple[str, str, str]], warns: list[str],
                  read: Callable[[Any], T], *, mute: Sequence[str] = ()) -> T:
    """`read(stage)` on the composed stage of `root`; the stage is released and the layers'
    edits undone before this returns.

    mtlx : (layer identifier holding the arc, the arc's asset path, the document's file), from
        `AssetScan.mtlx`; mute : layer identifiers composition must not open (the stage is
        opened with an empty population mask, muted, then populated)
    raises : AssetError when pxr cannot open the root
    """
    from pxr import Sdf, Tf, Usd

    keep: list[Any] = []
    edited: dict[str, Any] = {}
    try:
        for holder_id, asset, mtlx_file in mtlx:
            keep.append(translated_layer(mtlx_file, warns))
            holder = edited.get(holder_id) or Sdf.Layer.FindOrOpen(holder_id)
            edited[holder_id] = holder
            holder.UpdateExternalReference(asset, asset + TRANSLATED_SUFFIX)
        try:
            if mute:
                stage = Usd.Stage.OpenMasked(root, Usd.StagePopulationMask())
                stage.MuteAndUnmuteLayers(list(mute), [])
                stage.SetPopulationMask(Usd.StagePopulationMask.All())
            else:
                stage = Usd.Stage.Open(root)
        except Tf.ErrorException as exc:
            raise AssetError(f"pxr cannot open the file: {first_line(exc)}", path=root) from exc
        if stage is None:
            raise AssetError("pxr cannot open the file", path=root)
        try:
            return read(stage)
        finally:
            del stage  # released before the edits are undone: nothing recomposes
    finally:
        for layer in edited.values():
            layer.Reload(True)


def reached_specs(root: str, mtlx: Sequence[tuple[str, str, str]], mute: Sequence[str]
                  ) -> tuple[set[tuple[str, str]], set[str]]:
    """What the composed stage uses: ({(layer_key, prim spec path)} of every prim's prim stack,
    prototypes included; {layer_key} of its used layers). Variant contents appear under their
    variant paths (`/Asset{look=red}Body`), only for the selected variants."""
    from pxr import Usd

    def read(stage: Any) -> tuple[set[tuple[str, str]], set[str]]:
        layers = {layer_key(layer) for layer in stage.GetUsedLayers()}
        prims: set[tuple[str, str]] = set()
        for top in [stage.GetPseudoRoot(), *stage.GetPrototypes()]:
            for prim in Usd.PrimRange(top, Usd.PrimAllPrimsPredicate):
                for spec in prim.GetPrimStack():
                    prims.add((layer_key(spec.layer), str(spec.path)))
        return prims, layers

    return read_composed(root, mtlx, [], read, mute=mute)
