"""Check an unpacked upload with pxr: every asset path resolves inside the bundle.

The API runs `check_bundle` in a checker forked per upload from its warm check server
(`services.checkserver`), so that pxr is never imported into the API process and a hostile
file that crashes or exhausts pxr takes down only that checker (it runs under a CPU rlimit).
`python -m services.validate BUNDLE_DIR ROOT_REL` does the same check in a fresh interpreter
and prints one JSON object: `{"problems": [[path, reason], ...]}` (empty list: accepted).

What is refused is what the bake would read from outside the bundle, and nothing else: paths
that only unselected variants name are never read (the core's `scan_asset_paths` composes the
stage with their targets muted and says which), so they are left alone, and a missing texture
is not refused (the bake warns and uses its fallback); a missing *layer* the stage composes
is.

Reasons (stable strings; the API puts them in the 4xx `detail`):
"""

from __future__ import annotations

import json
import os
import re
import sys
from pathlib import Path

CANNOT_OPEN = "pxr cannot open"
ABSOLUTE = "absolute asset path"
URL = "URL asset path"
ESCAPES = "asset path escapes the bundle"
LINK = "asset path is a link"
MISSING = "asset path does not exist"
BAD_PATH = "asset path is not allowed"
UNREADABLE = "pxr cannot read a value"

USD_SUFFIXES = (".usd", ".usda", ".usdc", ".usdz")
#: what composition opens as a layer (a MaterialX document through its translation)
LAYER_SUFFIXES = (*USD_SUFFIXES, ".mtlx")
_SCHEME = re.compile(r"^[A-Za-z][A-Za-z0-9+.\-]*:")
_DRIVE = re.compile(r"^[A-Za-z]:[\\/]")


def _classify(raw: str, layer: Path, bundle: Path) -> tuple[str | None, Path | None]:
    """(reason or None, resolved path or None) for one authored asset path."""
    path = raw
    if path.endswith("]") and "[" in path:  # package-relative: pkg.usdz[member]
        path = path[: path.index("[")]
    if not path:
        return None, None
    if "\x00" in path:
        return BAD_PATH, None
    if path.startswith(("/", "\\")) or _DRIVE.match(path):
        return ABSOLUTE, None
    if _SCHEME.match(path):
        return URL, None
    rel = path.replace("\\", "/")
    target = Path(os.path.normpath(layer.parent / rel))
    try:
        target.relative_to(bundle)
    except ValueError:
        return ESCAPES, None
    # a link anywhere on the way is refused, even one pointing back inside
    probe = bundle
    for part in target.relative_to(bundle).parts:
        probe = probe / part
        if probe.is_symlink():
            return LINK, None
    if "<UDIM>" in rel:
        pattern = target.name.replace("<UDIM>", "[0-9][0-9][0-9][0-9]")
        if not any(target.parent.glob(pattern)):
            return MISSING, None
        return None, None
    if not target.exists():
        return MISSING, None
    return None, target


def check_bundle(bundle: Path, root_rel: str) -> list[tuple[str, str]]:
    """All problems of an unpacked upload, as (path, reason), sorted; [] when accepted.

    bundle : the unpacked upload; root_rel : the root layer, relative to `bundle`. Sublayers, references, payloads and
    asset-valued attributes (including time samples and arrays) of every reachable layer are
    checked; USD layers found on the way are followed.
    """
    from pxr import Sdf, Tf, Usd, UsdUtils

    bundle = Path(os.path.realpath(bundle))
    root_layer = bundle / root_rel
    unreached = _unreachable_only(root_layer)
    problems: set[tuple[str, str]] = set()
    seen: set[Path] = set()
    todo = [root_layer]
    while todo:
        layer_path = todo.pop()
        if layer_path in seen:
            continue
        seen.add(layer_path)
        rel_layer = str(layer_path.relative_to(bundle))
        try:
            layer = Sdf.Layer.FindOrOpen(str(layer_path))
        except Tf.ErrorException:
            layer = None
        if layer is None:
            problems.add((rel_layer, CANNOT_OPEN))
            continue
        try:
            subs, refs, payloads = UsdUtils.ExtractExternalReferences(str(layer_path))
        except Tf.ErrorException:
            problems.add((rel_layer, CANNOT_OPEN))
            continue
        if (bad := unreadable_value(layer)) is not None:
            problems.add((f"{rel_layer} at {bad[0]}", f"{UNREADABLE} ({bad[1]})"))
            continue
        for raw in sorted(set(subs) | set(refs) | set(payloads)):
            if (os.path.realpath(layer_path), raw) in unreached:
                continue  # only unselected variants name it: never read
            reason, target = _classify(raw, layer_path, bundle)
            if reason == MISSING and not _is_layer(raw) and raw not in set(subs):
                continue  # a missing texture: the bake warns and takes its fallback
            if reason is not None:
                problems.add((f"{raw} (in {rel_layer})", reason))
            elif target is not None and target.suffix.lower() in USD_SUFFIXES:
                if target.suffix.lower() == ".usdz":
                    problems.add((f"{raw} (in {rel_layer})", "nested .usdz is not supported"))
                else:
                    todo.append(target)
    if not problems:
        try:
            stage = Usd.Stage.Open(str(root_layer))
        except Tf.ErrorException:
            stage = None
        if stage is None:
            problems.add((str(root_layer.relative_to(bundle)), CANNOT_OPEN))
    if not problems:
        problems.update(_core_check(root_layer, bundle))
    return sorted(problems)


def _is_layer(raw: str) -> bool:
    return raw.split("[", 1)[0].lower().endswith(LAYER_SUFFIXES)


def _unreachable_only(root_layer: Path) -> set[tuple[str, str]]:
    """(layer real path, authored asset path) pairs only unselected variants name, from the
    core's scan; empty when the core refuses the asset (the walk then names the problems)."""
    try:
        from texelbake.asset.paths import scan_asset_paths
        from texelbake.errors import AssetError
    except ImportError:
        return set()
    try:
        return set(scan_asset_paths(root_layer).unreachable_only)
    except AssetError:
        return set()


def pxr_reason(exc: BaseException) -> str:
    """The commentary of a pxr error without its C++ function, line and build path."""
    found = re.findall(r" : '(.*?)'\s*$", str(exc), flags=re.MULTILINE)
    return (found[-1] if found else f"{exc}".strip().splitlines()[-1])[:200]


def unreadable_value(layer) -> tuple[str, str] | None:  # noqa: ANN001 - an Sdf.Layer
    """(spec path, pxr's reason) of the first field or time sample of a binary (crate) layer
    that pxr cannot read, or None. A crate layer opens without reading its values, so a
    truncated or corrupted one (an array range out of bounds, a bad compressed block) would
    otherwise pass the check and fail the bake; a text layer is parsed whole on open."""
    from pxr import Sdf, Tf

    if layer.GetFileFormat().formatId == "usda":
        return None
    paths: list = []
    layer.Traverse(Sdf.Path.absoluteRootPath, paths.append)
    for path in sorted(paths):
        try:
            spec = layer.GetObjectAtPath(path)
            if spec is None:
                continue
            for key in spec.ListInfoKeys():
                spec.GetInfo(key)
            if path.IsPropertyPath():
                for t in layer.ListTimeSamplesForPath(path):
                    layer.QueryTimeSample(path, t)
        except (Tf.ErrorException, RuntimeError, ValueError) as exc:
            return str(path), pxr_reason(exc)
    return None


def _core_check(root_layer: Path, bundle: Path) -> list[tuple[str, str]]:
    """The ingest engineer's own check, when it exists (it raises AssetPathError naming the path)."""
    try:
        from texelbake.asset import check_asset_paths  # type: ignore[attr-defined]
    except ImportError:
        return []
    from texelbake.errors import AssetError

    try:
        check_asset_paths(root_layer)
    except AssetError as exc:
        return [(str(root_layer.relative_to(bundle)), str(exc))]
    return []


def main(argv: list[str]) -> int:
    """argv: BUNDLE_DIR ROOT_REL [CPU_SECONDS]."""
    import resource

    bundle, root_rel = Path(argv[0]), argv[1]
    cpu = int(float(argv[2])) if len(argv) > 2 else 120
    # CPU only: an address-space limit breaks torch/open3d imports of the core check; the
    # unpacked size is already capped by the upload handler
    resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu))
    problems = check_bundle(bundle, root_rel)
    sys.stdout.write(json.dumps({"problems": [list(p) for p in problems]}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
