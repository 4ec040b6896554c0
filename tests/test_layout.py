"""The import graph of ``server/`` and ``estimator/``, read from the source with ``ast``.

Dependencies point down: no import cycle between modules; the runtime (everything in
``server/`` outside ``server/tooling/``) never imports the tooling, except the ``slipfleet``
command line, which offers the tooling's commands and is imported by nothing; of the runtime
only the app (``server/app_main.py``) imports the API layer; ``estimator/`` never imports the
server. Every import counts, at module level or inside a function
(``TYPE_CHECKING`` blocks too), and so does ``importlib.import_module`` with a literal name or an
f-string's literal prefix.
"""

from __future__ import annotations

import ast
from collections.abc import Iterator, Mapping
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PACKAGES = ("server", "estimator")
TOOLING = "server.tooling"
#: The ``slipfleet`` console script (pyproject.toml): it offers serve and the tooling commands.
COMMAND_LINE = "server.cli"
#: The one runtime module that builds the REST app (the runtime hands the API what it serves).
APP = "server.app_main"

Graph = Mapping[str, frozenset[str]]


def _module_names(root: Path, packages: tuple[str, ...]) -> dict[str, Path]:
    """Dotted module name → file of every ``.py`` under ``packages`` (``__init__``: the package)."""
    names: dict[str, Path] = {}
    for package in packages:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            names[".".join(parts)] = path
    return names


def _imported_names(tree: ast.Module, module: str, is_package: bool) -> Iterator[str]:
    """Every dotted name ``module`` imports: ``a.b`` for ``import a.b``, ``a.b.c`` for ``from a.b
    import c`` (a module, or a name that resolves to ``a.b``), literal ``import_module`` names.

    A submodule's parent packages, which Python imports first, are not edges: a package whose
    ``__init__`` re-exports its submodules would otherwise close a cycle with each of them."""
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".") if is_package else module.split(".")[:-1]
                parts = parts[: len(parts) - node.level + 1]
                base = ".".join([*parts, base] if base else parts)
            yield from (f"{base}.{alias.name}" for alias in node.names)
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
        ):
            arg = node.args[0]
            if isinstance(arg, ast.Constant) and isinstance(arg.value, str):
                yield arg.value
            elif isinstance(arg, ast.JoinedStr) and isinstance(arg.values[0], ast.Constant):
                yield str(arg.values[0].value).rstrip(".")


def _resolve(name: str, modules: Mapping[str, Path]) -> str | None:
    """The module of ``modules`` that ``name`` is or lies in (longest prefix), else None."""
    while name:
        if name in modules:
            return name
        name = name.rpartition(".")[0]
    return None


def import_graph(root: Path, packages: tuple[str, ...] = PACKAGES) -> Graph:
    """Module → the modules of ``packages`` it imports (itself left out)."""
    modules = _module_names(root, packages)
    graph: dict[str, frozenset[str]] = {}
    for name, path in modules.items():
        tree = ast.parse(path.read_text(), filename=str(path))
        names = _imported_names(tree, name, is_package=path.stem == "__init__")
        targets = (_resolve(n, modules) for n in names)
        graph[name] = frozenset(t for t in targets if t is not None and t != name)
    return graph


def cycles(graph: Graph) -> list[list[str]]:
    """The import cycles: strongly connected components of more than one module (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def _in(module: str, package: str) -> bool:
    return module == package or module.startswith(package + ".")


def test_no_import_cycles() -> None:
    assert cycles(import_graph(REPO)) == []


def test_the_runtime_never_imports_the_tooling() -> None:
    graph = import_graph(REPO)
    offending = {
        m: sorted(t for t in targets if _in(t, TOOLING))
        for m, targets in graph.items()
        if _in(m, "server") and not _in(m, TOOLING) and m != COMMAND_LINE
    }
    assert {m: t for m, t in offending.items() if t} == {}
    assert sorted(m for m, targets in graph.items() if COMMAND_LINE in targets) == []


def test_the_api_layer_is_imported_by_the_app_only_and_imports_no_composition() -> None:
    graph = import_graph(REPO)
    importers = {
        m
        for m, targets in graph.items()
        if any(_in(t, "server.api") for t in targets)
        and not _in(m, "server.api")
        and not _in(m, TOOLING)
    }
    assert importers == {APP}
    composition = {"server.runtime", APP, COMMAND_LINE}
    api_imports = {t for m, targets in graph.items() if _in(m, "server.api") for t in targets}
    assert api_imports & composition == set()


def test_the_estimator_never_imports_the_server() -> None:
    graph = import_graph(REPO)
    offending = {
        m: sorted(t for t in targets if _in(t, "server"))
        for m, targets in graph.items()
        if _in(m, "estimator")
    }
    assert {m: t for m, t in offending.items() if t} == {}


def test_the_graph_sees_known_imports_of_every_kind() -> None:
    graph = import_graph(REPO)
    assert "server.live.hub" in graph["server.runtime"]  # module level
    assert "server.tooling.fleet_commands" in graph[COMMAND_LINE]  # inside a function
    assert "server.tooling.bench" in graph[COMMAND_LINE]  # import_module(f"…{name}")
    assert "server.api.app" in graph[APP]


def test_a_planted_cycle_and_a_relative_import_are_found(tmp_path: Path) -> None:
    package = tmp_path / "pkg"
    (package / "sub").mkdir(parents=True)
    (package / "__init__.py").write_text("")
    (package / "sub" / "__init__.py").write_text("from . import b\n")
    (package / "a.py").write_text("def f():\n    from pkg.sub.b import g\n")
    (package / "sub" / "b.py").write_text("from ..a import f\n\ndef g(): ...\n")
    (package / "c.py").write_text("import pkg.a\n")
    (package / "d.py").write_text("import importlib\n\nimportlib.import_module('pkg.c')\n")
    graph = import_graph(tmp_path, ("pkg",))
    assert graph["pkg.c"] == {"pkg.a"} and graph["pkg.d"] == {"pkg.c"}
    assert graph["pkg.sub"] == {"pkg.sub.b"}
    assert graph["pkg.sub.b"] == {"pkg.a"}
    assert cycles(graph) == [["pkg.a", "pkg.sub.b"]]
