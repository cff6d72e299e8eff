"""The layout's rules (DESIGN.md "Layout"): no import cycles anywhere in texelbake, schemas,
services and workers (every module imports alone; the static import graph, function-level
imports included, has no cycle), and the core package imports neither FastAPI, Celery nor
Redis."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("texelbake", "schemas", "farm", "services", "workers")
SERVICE_LIBS = ("fastapi", "starlette", "celery", "kombu", "redis", "uvicorn")


def _modules(packages=PACKAGES) -> dict[str, Path]:
    out = {}
    for pkg in packages:
        for path in sorted((ROOT / pkg).rglob("*.py")):
            rel = path.relative_to(ROOT).with_suffix("")
            parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
            out[".".join(parts)] = path
    return out


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """module -> the project modules it imports (at any depth of its code). `from pkg import
    name` is an edge to `pkg.name` when that is a module, else to `pkg` (its __init__)."""
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative import
                    anchor = mod.split(".") if is_pkg else mod.split(".")[:-1]
                    anchor = anchor[: len(anchor) - (node.level - 1)]
                    base = ".".join(anchor + ([base] if base else []))
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            for t in targets:
                while t and t not in modules:  # `import a.b.c` of a non-module name
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    graph[mod].add(t)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on, stack, out, counter = set(), [], [], [0]
    for root in sorted(graph):
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_cycle_finder_finds_a_cycle():
    g = {"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}
    assert cycles(g) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycles_in_the_static_graph():
    graph = import_graph(_modules())
    assert len(graph) > 80
    assert cycles(graph) == []


def test_core_does_not_import_the_service_packages_statically():
    graph = import_graph(_modules())
    bad = {m: sorted(t for t in ts if t.split(".")[0] in ("farm", "services", "workers"))
           for m, ts in graph.items() if m.startswith("texelbake")}
    # the CLI's `texelbake stack up` is the one door into the service's process launcher
    assert {m: ts for m, ts in bad.items() if ts} == {"texelbake.cli": ["farm.stack"]}


_PROBE = r"""
import importlib, json, sys
mods = json.loads(sys.argv[1])
ours = ("texelbake", "schemas", "farm", "services", "workers")
failed = {}
for m in mods:
    for k in [k for k in sys.modules if k.split(".")[0] in ours]:
        del sys.modules[k]
    try:
        importlib.import_module(m)
    except Exception as exc:  # noqa: BLE001
        failed[m] = f"{type(exc).__name__}: {exc}"
if sys.argv[2] == "core":
    for k in [k for k in sys.modules if k.split(".")[0] in ours]:
        del sys.modules[k]
    for m in mods:
        importlib.import_module(m)
print(json.dumps({"failed": failed, "loaded": sorted({k.split(".")[0] for k in sys.modules})}))
"""


def _probe(mods: list[str], mode: str, tmp_path: Path) -> dict:
    # the worker modules read the service settings at import: give them what they require
    env = {**os.environ, "TEXELBAKE_SECRET_KEY": "layout-test-secret",
           "TEXELBAKE_REDIS_URL": "redis://127.0.0.1:1/0",
           "TEXELBAKE_ARTIFACT_ROOT": str(tmp_path)}
    r = subprocess.run([sys.executable, "-c", _PROBE, json.dumps(mods), mode], cwd=ROOT,
                       capture_output=True, text=True, timeout=600, env=env)
    assert r.returncode == 0, r.stderr[-2000:]
    return json.loads(r.stdout.strip().splitlines()[-1])


def test_every_module_imports_alone(tmp_path):
    mods = sorted(_modules())
    assert _probe(mods, "alone", tmp_path)["failed"] == {}


def test_core_imports_neither_fastapi_celery_nor_redis(tmp_path):
    mods = sorted(_modules(("texelbake", "schemas")))
    loaded = _probe(mods, "core", tmp_path)["loaded"]
    assert "texelbake" in loaded and "torch" in loaded  # the probe did import the core
    assert [lib for lib in SERVICE_LIBS if lib in loaded] == []
