"""The layout's rules (DESIGN.md "Layout"): no import cycles anywhere in texelbake, schemas,
farm, texelbake_client, services and workers (every module imports alone; the static import
graph, function-level imports included, has no cycle); the packages import downwards only
(schemas < the texelbake core < farm, texelbake_client < services, workers, texelbake.cli),
services and workers do not import each other, no private name crosses a package; inside the
core, its packages in layers (CORE_LAYERS); and the core package imports neither FastAPI, Celery
nor Redis."""

from __future__ import annotations

import ast
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("texelbake", "schemas", "farm", "texelbake_client", "services", "workers")
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
    bad = {m: sorted(t for t in ts
                     if t.split(".")[0] in ("farm", "texelbake_client", "services", "workers"))
           for m, ts in graph.items() if m.split(".")[0] == "texelbake"}
    # the CLI's `texelbake stack up` is the one door into the farm's process launcher, and
    # `texelbake submit` the one into the HTTP clients
    assert {m: ts for m, ts in bad.items() if ts} == {
        "texelbake.cli.farm": ["farm.stack", "texelbake_client.batch", "texelbake_client.submit"]}


#: each package's layer: a module imports from lower layers, and within its layer only from
#: its own package (farm and the clients do not import each other, nor services and workers)
LAYERS = {"schemas": 0, "texelbake": 1, "farm": 2, "texelbake_client": 2, "services": 3,
          "workers": 3}
#: packages that sit above their top package: the command line starts the stack and submits jobs
MODULE_LAYERS = {"texelbake.cli": 3}


def _layer(mod: str) -> int:
    for prefix, layer in MODULE_LAYERS.items():
        if mod == prefix or mod.startswith(prefix + "."):
            return layer
    return LAYERS[mod.split(".")[0]]


def layer_violations(graph: dict[str, set[str]]) -> list[str]:
    bad = []
    for mod, targets in sorted(graph.items()):
        for t in sorted(targets):
            up = _layer(t) > _layer(mod)
            sideways = _layer(t) == _layer(mod) and t.split(".")[0] != mod.split(".")[0]
            if up or sideways:
                bad.append(f"{mod} -> {t}")
    return bad


def test_layer_check_finds_violations():
    g = {"schemas.job": {"texelbake.errors"}, "texelbake.pipeline": {"schemas.job"},
         "farm.db": {"services.deps"}, "services.main": {"workers.tasks", "farm.db"},
         "workers.tasks": {"farm.db"}, "texelbake.cli": {"farm.stack"},
         "texelbake.errors": set(), "services.deps": set(), "farm.stack": set()}
    assert layer_violations(g) == ["farm.db -> services.deps", "schemas.job -> texelbake.errors",
                                   "services.main -> workers.tasks"]


def test_packages_import_downwards_only():
    graph = import_graph(_modules())
    assert layer_violations(graph) == []


#: the core's layers, lowest first: a module imports only from its own package or from a
#: package of a lower layer (two packages of one layer do not import each other)
CORE_LAYERS: tuple[tuple[str, ...], ...] = (
    ("schemas",),
    ("texelbake", "texelbake.arrays", "texelbake.errors", "texelbake.tol"),
    ("texelbake.model", "texelbake.io"),
    ("texelbake.brdf", "texelbake.geometry", "texelbake.estimate"),
    ("texelbake.baselines", "texelbake.cpm", "texelbake.deform"),
    ("texelbake.usd",),
    ("texelbake.asset", "texelbake.btf", "texelbake.testscenes"),
    ("texelbake.trace",),
    ("texelbake.srf",),
    ("texelbake.render",),
    ("texelbake.stages",),
    ("texelbake.pipeline",),
    ("texelbake.cli",),
)


def core_package(module: str) -> str:
    """The unit a core layer names: `texelbake.<package>` for the core's packages and its
    loose modules, the top-level package otherwise."""
    parts = module.split(".")
    return ".".join(parts[:2]) if parts[0] == "texelbake" and len(parts) > 1 else parts[0]


def core_layer_violations(graph: dict[str, set[str]], layers=CORE_LAYERS) -> list[str]:
    rank = {p: i for i, layer in enumerate(layers) for p in layer}
    out = []
    for mod in sorted(graph):
        a = core_package(mod)
        if a not in rank:
            continue
        for t in sorted(graph[mod]):
            b = core_package(t)
            if b != a and b in rank and rank[b] >= rank[a]:
                out.append(f"{mod} -> {t}")
    return out


def test_core_layer_check_finds_an_upward_import():
    g = {"texelbake.io.store": {"texelbake.cpm.fit"}, "texelbake.cpm.fit": {"texelbake.io.store"},
         "texelbake.cpm.level": {"texelbake.deform.warps"}}
    assert core_layer_violations(g) == ["texelbake.cpm.level -> texelbake.deform.warps",
                                        "texelbake.io.store -> texelbake.cpm.fit"]


def test_every_core_package_has_a_layer():
    """A new package of the core must be placed in CORE_LAYERS."""
    known = {p for layer in CORE_LAYERS for p in layer}
    core = {core_package(m) for m in _modules(("texelbake", "schemas"))}
    assert sorted(core - known) == []


def test_no_import_runs_up_the_core_layers():
    assert core_layer_violations(import_graph(_modules())) == []


def private_imports(modules: dict[str, Path]) -> list[str]:
    """`from X import _name` where X is a module of another package than the importer's
    (its parent package; `from pkg import _mod` of a private module counts too)."""
    bad = []
    for mod, path in modules.items():
        is_pkg = path.name == "__init__.py"
        own = mod if is_pkg else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.ImportFrom) or node.level:
                continue
            base = node.module or ""
            if base.split(".")[0] not in PACKAGES:
                continue  # not one of ours
            src_pkg = base if (ROOT / base.replace(".", "/")).is_dir() else base.rpartition(".")[0]
            for a in node.names:
                if a.name.startswith("_") and not a.name.startswith("__") and src_pkg != own:
                    bad.append(f"{mod}: from {base} import {a.name}")
    return bad


def test_no_private_name_crosses_a_package():
    assert private_imports(_modules()) == []


def test_one_queue_table():
    """The queues, their worker families and the stage -> queue map live in schemas.queues
    only: no other module spells a family's queue list or a stage's queue."""
    from schemas.queues import PLAN_QUEUE, QUEUE_FAMILIES, QUEUES, STAGE_QUEUES

    assert sorted(q for qs in QUEUE_FAMILIES.values() for q in qs) == sorted(QUEUES)
    assert set(STAGE_QUEUES.values()) <= set(QUEUES) and PLAN_QUEUE in QUEUES
    spelled = ('("ingest", "geometry", "export")', '("cpm", "avis", "btf")', '"ingest", "ingest"',
               '"cpm", "cpm"', '"geometry", "geometry"', 'PLAN_QUEUE = "')
    found = [f"{m}: {lit}" for m, path in _modules().items() if m != "schemas.queues"
             for lit in spelled if lit in path.read_text()]
    assert found == []


_PROBE = r"""
import importlib, json, sys
mods = json.loads(sys.argv[1])
ours = ("texelbake", "schemas", "farm", "texelbake_client", "services", "workers")
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


@pytest.mark.slow  # two fresh interpreters importing every module (~30 s): `make test` runs them
def test_every_module_imports_alone(tmp_path):
    mods = sorted(_modules())
    assert _probe(mods, "alone", tmp_path)["failed"] == {}


@pytest.mark.slow
def test_core_imports_neither_fastapi_celery_nor_redis(tmp_path):
    mods = sorted(_modules(("texelbake", "schemas")))
    loaded = _probe(mods, "core", tmp_path)["loaded"]
    assert "texelbake" in loaded and "torch" in loaded  # the probe did import the core
    assert [lib for lib in SERVICE_LIBS if lib in loaded] == []
