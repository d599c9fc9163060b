"""The import graph shows the data flow: each package imports only the root package (`lightstage`, folder
core/) and the stages before it, and no module imports itself back through others (checked statically, imports
inside functions included, so a lazy import cannot hide a backward edge or a cycle)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# Package folder -> import name, in data-flow order. The simulator produces captures (only pipelines imports it).
LAYERS = (
    ("core", "lightstage"),
    ("capture", "lightstage.capture"),
    ("simulator", "lightstage.simulator"),
    ("preprocess", "lightstage.preprocess"),
    ("calibration", "lightstage.calibration"),
    ("dataset", "lightstage.dataset"),
    ("interop", "lightstage.interop"),
    ("training", "lightstage.training"),
    ("viewer", "lightstage.viewer"),
    ("pipelines", "lightstage.pipelines"),
)
# What each package may import besides itself and the root package (the stages before it in the data flow).
ALLOWED = {
    "lightstage": set(),
    "lightstage.capture": set(),
    "lightstage.simulator": {"lightstage.capture"},
    "lightstage.preprocess": {"lightstage.capture"},
    "lightstage.calibration": {"lightstage.capture", "lightstage.preprocess"},
    "lightstage.dataset": {"lightstage.capture", "lightstage.preprocess", "lightstage.calibration"},
    "lightstage.interop": {
        "lightstage.capture",
        "lightstage.preprocess",
        "lightstage.calibration",
        "lightstage.dataset",
    },
    "lightstage.training": {
        "lightstage.capture",
        "lightstage.preprocess",
        "lightstage.calibration",
        "lightstage.dataset",
    },
    # the viewer shows captures and trained models: every stage before it but the simulator
    "lightstage.viewer": {name for _, name in LAYERS[1:-2]} - {"lightstage.simulator"},
    "lightstage.pipelines": {name for _, name in LAYERS[1:-1]},
}


def module_name(path: Path) -> str:
    """Import name of a source file, e.g. core/records/shards.py -> lightstage.records.shards."""
    rel = path.relative_to(REPO)
    package = dict(LAYERS)[rel.parts[0]]
    parts = [*rel.parts[1:-1], rel.stem] if rel.stem != "__init__" else list(rel.parts[1:-1])
    return ".".join([package, *parts])


def package_of(module: str) -> str:
    """The layer a module belongs to: lightstage.capture.stage -> lightstage.capture; root modules -> lightstage."""
    for _, name in LAYERS[1:]:
        if module == name or module.startswith(name + "."):
            return name
    return "lightstage"


def _typing_only(tree: ast.AST) -> set[int]:
    """ids of the import nodes under `if TYPE_CHECKING:` (annotations only, never executed)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            out |= {id(n) for stmt in node.body for n in ast.walk(stmt)}
    return out


def first_party_imports(path: Path, modules: set[str], extra: str = "", typing: bool = True) -> set[str]:
    """Modules of the project `path` (plus `extra` source appended) imports anywhere in the file;
    `typing=False` leaves out imports under `if TYPE_CHECKING:`."""
    me = module_name(path)
    out: set[str] = set()
    tree = ast.parse(path.read_text() + extra, str(path))
    skip = set() if typing else _typing_only(tree)
    for node in ast.walk(tree):
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:  # relative import
                base = me.rsplit(".", node.level - (path.stem == "__init__"))[0]
                root = f"{base}.{node.module}" if node.module else base
            else:
                root = node.module or ""
            names = [f"{root}.{a.name}" for a in node.names] + [root]
        else:
            continue
        for n in names:
            while n and n not in modules:
                n = n.rpartition(".")[0]
            if n and n != me and n.startswith("lightstage"):
                out.add(n)
    return out


def import_graph(planted: dict[str, str] | None = None, typing: bool = True) -> dict[str, set[str]]:
    """module -> the project modules it imports; `planted`: {repo-relative file: source to append} (tests);
    `typing=False`: without the imports made for annotations only."""
    planted = planted or {}
    files = [p for folder, _ in LAYERS for p in (REPO / folder).rglob("*.py")]
    modules = {module_name(p) for p in files} | {name for _, name in LAYERS}
    return {
        module_name(p): first_party_imports(p, modules, planted.get(str(p.relative_to(REPO)), ""), typing)
        for p in files
    }


def backward_imports(graph: dict[str, set[str]]) -> list[str]:
    """'a -> b' for every import of a package neither the root nor an earlier stage of a's package."""
    bad = []
    for mod, targets in sorted(graph.items()):
        src = package_of(mod)
        for t in sorted(targets):
            dst = package_of(t)
            if dst != src and dst != "lightstage" and dst not in ALLOWED[src]:
                bad.append(f"{mod} -> {t}")
            if src == "lightstage" and dst != "lightstage":
                bad.append(f"{mod} -> {t}")
    return bad


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Import cycles between modules (Tarjan's strongly connected components of more than one module)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
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

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_no_backward_imports():
    bad = backward_imports(import_graph())
    assert not bad, "imports against the data flow (see docs/architecture.md):\n" + "\n".join(bad)


def test_no_import_cycles():
    """No cycles among the imports that run (a type hint under TYPE_CHECKING may name a module that imports
    this one; the layer check above still counts those)."""
    found = cycles(import_graph(typing=False))
    assert not found, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in found)


@pytest.mark.parametrize(
    "source, importer",
    [
        ("from lightstage.pipelines.cluster import dask_client\n", "core/atomic.py"),
        ("from lightstage.training.model import RelightModel\n", "dataset/split.py"),
        ("import lightstage.simulator.simulate\n", "training/metrics.py"),
    ],
)
def test_a_backward_import_is_caught(source, importer):
    """The check fails on a planted backward import (it would not pass vacuously)."""
    before = set(backward_imports(import_graph()))
    after = set(backward_imports(import_graph({importer: source})))
    assert after - before


def test_a_cycle_is_caught():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]


DASK_BACKEND = "core/dask_executor.py"  # the one module behind the executor interface that imports dask


def dask_importers(planted: dict[str, str] | None = None) -> list[str]:
    """Repo-relative files (other than the dask backend) that import `dask` or `distributed` anywhere."""
    planted = planted or {}
    out = []
    for folder, _ in LAYERS:
        for path in sorted((REPO / folder).rglob("*.py")):
            rel = str(path.relative_to(REPO))
            tree = ast.parse(path.read_text() + planted.get(rel, ""), rel)
            for node in ast.walk(tree):
                if isinstance(node, ast.Import):
                    roots = [a.name.split(".")[0] for a in node.names]
                elif isinstance(node, ast.ImportFrom) and not node.level:
                    roots = [(node.module or "").split(".")[0]]
                else:
                    continue
                if rel != DASK_BACKEND and {"dask", "distributed"} & set(roots):
                    out.append(rel)
                    break
    return out


def test_only_the_dask_backend_imports_dask():
    """Stages and pipelines reach dask only through lightstage.executor / lightstage.dask_executor."""
    found = dask_importers()
    assert not found, f"import dask outside {DASK_BACKEND}:\n" + "\n".join(found)
    assert dask_importers({"preprocess/jobs.py": "def f():\n    from distributed import get_worker\n"}) == [
        "preprocess/jobs.py"
    ]
