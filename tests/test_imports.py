"""The package's import graph: no cycles between modules, and ``pipeline.job`` (read by the API, which has no
torch) imports no torch.

Every ``import`` statement counts, function-local ones included: a lazy import still ties two modules
together, it only hides the tie from the interpreter until the call. Imports under ``if TYPE_CHECKING:`` are
annotations only (they never run) and do not count.
"""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("pipeline", "service", "worker", "cli")


def _module_name(path: Path) -> str:
    parts = path.relative_to(REPO).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _modules() -> dict[str, Path]:
    return {_module_name(p): p for pkg in PACKAGES for p in (REPO / pkg).rglob("*.py")}


def _imports(path: Path, name: str, known: set[str]) -> set[str]:
    """The project modules ``name`` imports (``from a.b import c`` counts as a.b.c when that is a module)."""
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    out: set[str] = set()
    for node in _runtime_nodes(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in known else base for a in node.names]
        else:
            continue
        for t in targets:
            while t and t not in known:  # `import a.b.c` of a non-module attribute: its module
                t = t.rpartition(".")[0]
            if t and t != name:
                out.add(t)
    return out


def _runtime_nodes(tree: ast.AST):
    """Every node of ``tree`` except those under ``if TYPE_CHECKING:``."""
    todo = [tree]
    while todo:
        node = todo.pop()
        yield node
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            todo += node.orelse
            continue
        todo += list(ast.iter_child_nodes(node))


def _graph() -> dict[str, set[str]]:
    mods = _modules()
    known = set(mods)
    # A package's __init__ is a module of its own; importing a.b.c also runs a and a.b, but those edges are
    # the interpreter's, not the code's, so they are not counted.
    return {m: _imports(p, m, known) for m, p in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
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


def test_no_import_cycles():
    cycles = _cycles(_graph())
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_the_job_package_imports_no_torch():
    offenders = []
    for p in (REPO / "pipeline" / "job").rglob("*.py"):
        for node in _runtime_nodes(ast.parse(p.read_text())):
            names = ([a.name for a in node.names] if isinstance(node, ast.Import)
                     else [node.module or ""] if isinstance(node, ast.ImportFrom) else [])
            offenders += [f"{p.name}: {n}" for n in names if n.split(".")[0] in ("torch", "numpy", "numba")]
    assert not offenders, offenders


def test_no_module_shadows_the_standard_library_or_an_installed_package():
    """A module named like ``select``, ``types`` or ``lpips`` reads as the other one and breaks as soon as
    something runs with its folder on sys.path."""
    import importlib.metadata
    import sys

    installed = {name for name in importlib.metadata.packages_distributions() if not name.startswith("_")}
    taken = (set(sys.stdlib_module_names) | installed) - set(PACKAGES)
    bad = sorted(m for m in _modules() if m.rpartition(".")[2] in taken)
    assert not bad, f"modules named like a standard-library module or an installed package: {bad}"


# pipeline's packages (and top-level modules) from the bottom up: each may import only those in earlier layers or
# its own. The stages read the job contract and the libraries below them; evaluate scores a trained model; restore
# reads evaluate's results; survey maps a restored job; export reports all of it; cli (the `dualphys` command) sits
# above pipeline and service.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("config", "profiling", "cli_args"),
    ("job",),
    ("scene",),
    ("ingest",),
    ("synth", "sfm"),
    ("splat",),
    ("ops",),
    ("water",),
    ("medium",),
    ("train",),
    ("evaluate",),
    ("restore",),
    ("survey",),
    ("export",),
)
TOP = ("service", "worker", "cli")  # above pipeline, in this order


def _layer_of(module: str) -> tuple[int, str]:
    parts = module.split(".")
    if parts[0] != "pipeline":
        return len(LAYERS) + TOP.index(parts[0]), parts[0]
    if len(parts) == 1:  # pipeline/__init__.py
        return -1, "pipeline"
    name = parts[1]
    for i, layer in enumerate(LAYERS):
        if name in layer:
            return i, name
    raise AssertionError(f"{module}: package pipeline.{name} is in no layer of tests/test_imports.py LAYERS")


def test_packages_import_only_layers_below_them():
    graph = _graph()
    bad = []
    for mod, targets in graph.items():
        src, src_pkg = _layer_of(mod)
        for t in targets:
            dst, dst_pkg = _layer_of(t)
            if dst > src or (dst == src and dst_pkg != src_pkg and src >= 0):
                bad.append(f"{mod} -> {t}")
    assert not bad, "imports against the layer order (tests/test_imports.py LAYERS):\n" + "\n".join(sorted(bad))


def test_the_pipeline_imports_nothing_of_the_service():
    graph = _graph()
    bad = sorted(f"{m} -> {t}" for m, ts in graph.items() if m.startswith("pipeline") for t in ts
                 if t.split(".")[0] in TOP)
    assert not bad, bad


def test_the_object_store_layer_sits_between_the_job_store_and_the_composition_root():
    """``service.storage`` (the object store, issue 44) builds on ``service.jobs`` and the pipeline's job folder;
    only ``service.compose`` picks it, so with no object store configured nothing else depends on it."""
    graph = _graph()
    below = ("service.storage", "service.jobs", "service.core", "pipeline.job")
    up = sorted(f"{m} -> {t}" for m, ts in graph.items() if m.startswith("service.storage") for t in ts
                if not t.startswith(below))
    assert not up, up
    users = sorted(m for m, ts in graph.items() if not m.startswith("service.storage")
                   and any(t.startswith("service.storage") for t in ts))
    assert users == ["service.compose"], users
