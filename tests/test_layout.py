"""The package's shape: no import cycle among its modules, imports at the top of files, the manual's module map
(docs/concepts/data-flow.md) equal to the tree."""

from __future__ import annotations

import ast
import inspect
from pathlib import Path

import harness

PKG = Path(harness.__file__).parent
MODULE_MAP = PKG.parent / "docs" / "concepts" / "data-flow.md"  # the manual's page of the data flow


def _modules() -> dict[str, Path]:
    """Dotted name -> file of every module of the package (packages by their ``__init__``)."""
    out = {}
    for path in sorted(PKG.rglob("*.py")):
        rel = path.relative_to(PKG.parent).with_suffix("")
        parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
        if any(p.startswith("_") and p != "__init__" for p in parts[1:]):
            continue  # harness/_fmus, harness/_specs: package data
        out[".".join(parts)] = path
    return out


def _target(mods: dict[str, Path], name: str, alias: str | None) -> str:
    """The module an import binds: ``from pkg import sub`` is module pkg.sub when that is a module."""
    if alias is not None and f"{name}.{alias}" in mods:
        return f"{name}.{alias}"
    return name


def import_graph() -> dict[str, set[str]]:
    """Module -> the package's modules it imports (relative imports resolved)."""
    mods = _modules()
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        package = mod if path.name == "__init__.py" else mod.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [(a.name, None) for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    base = package.split(".")[: len(package.split(".")) - node.level + 1]
                    name = ".".join(base + ([node.module] if node.module else []))
                else:
                    name = node.module or ""
                names = [(name, a.name) for a in node.names]
            else:
                continue
            for name, alias in names:
                if name == "harness" or name.startswith("harness."):
                    target = _target(mods, name, alias)
                    if target in mods and target != mod:
                        graph[mod].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Every strongly connected component of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in graph[v]:
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


def test_cycle_finder_finds_a_cycle() -> None:
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle() -> None:
    graph = import_graph()
    assert len(graph) > 30
    assert "harness.diagnosis.diagnose" in graph["harness.cli"]
    assert cycles(graph) == []


LAZY = ("harness.cli", "harness.__main__")  # the command-line layer: a command imports what it runs when it runs


def test_imports_at_the_top_of_files() -> None:
    late = []
    for mod, path in _modules().items():
        if mod in LAZY:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
                late += [f"{mod}:{n.lineno}" for n in ast.walk(node) if isinstance(n, (ast.Import, ast.ImportFrom))]
    assert late == []


def module_map() -> set[str]:
    """The files the manual's module map lists (paths relative to the package's parent), read from its indented
    tree: a name ending in "/" opens a folder at that indentation."""
    text = MODULE_MAP.read_text(encoding="utf-8")
    block = text.split("<!-- module map", 1)[1].split("```text\n", 1)[1].split("```", 1)[0]
    out: set[str] = set()
    stack: list[tuple[int, str]] = []
    for line in block.splitlines():
        if not line.strip():
            continue
        indent = len(line) - len(line.lstrip())
        name = line.split()[0]
        while stack and stack[-1][0] >= indent:
            stack.pop()
        path = "/".join([p for _, p in stack] + [name.rstrip("/")])
        if name.endswith("/"):
            stack.append((indent, name.rstrip("/")))
        else:
            out.add(path)
    return out


def test_module_map_is_the_tree() -> None:
    tree = {
        str(p.relative_to(PKG.parent))
        for p in PKG.rglob("*.py")
        if p.name != "__init__.py" and not any(part.startswith("_") for part in p.relative_to(PKG).parts)
    }
    listed = module_map()
    assert "harness/diagnosis/diagnose.py" in listed and "harness/cli.py" in listed
    assert listed == tree, f"only in the module map: {sorted(listed - tree)}; only in the tree: {sorted(tree - listed)}"


def test_public_api_in_data_flow_order() -> None:
    assert all(hasattr(harness, name) for name in harness.__all__)
    order = [harness.__all__.index(n) for n in ("load_spec", "run_campaign", "calibrate_run", "estimate",
                                                "crossfit_run", "diagnose_run", "write_report")]  # fmt: skip
    assert order == sorted(order)


def test_public_functions_have_numpydoc_sections() -> None:
    """Every public function (``harness.__all__``) says what it takes and returns in numpydoc sections, which the
    manual's API page renders; the diagnosis's own follow with its rewrite (issue 34)."""
    bare = []
    for name in harness.__all__:
        obj = getattr(harness, name)
        if not inspect.isfunction(obj) or obj.__module__.startswith("harness.diagnosis"):
            continue
        doc = inspect.getdoc(obj) or ""
        if not ("Parameters\n----------" in doc and "Returns\n-------" in doc):
            bare.append(name)
    assert bare == []


def test_no_public_name_is_a_module_of_the_package() -> None:
    """A submodule ``harness.X`` becomes the package's attribute X when imported, hiding a public name X: a public
    name that is also a top-level module would change meaning with what was imported before."""
    top = {p.stem for p in PKG.glob("*.py")} | {p.parent.name for p in PKG.glob("*/__init__.py")}
    assert "prediction" in top and "predict" in harness.__all__
    assert sorted(top & set(harness.__all__)) == []
