"""The packages depend on one another one way (ARCHITECTURE.md, "What is in the box"): every
import of every module, those inside functions included, read from its source, names a package
its own may use. The command line (``jamnav``) wires them all together and is not held. Nor do
any modules import one another round a cycle, not even through an import deferred into a
function: the order a reader finds in the imports is the order they load in."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
PROJECT = ("shared", "planning", "world_sim", "uav_agent", "cloud_service", "jamnav",
           "benchmarks", "tests")
MAY_IMPORT = {
    "shared": {"shared"},
    "planning": {"planning", "shared"},
    # The world knows no planner: what it shows each UAV is shared.observation's.
    "world_sim": {"world_sim", "shared"},
    # An agent flies alone: it neither runs the world nor learns.
    "uav_agent": {"uav_agent", "planning", "shared"},
    # The in-process flights of training and evaluation run the world themselves.
    "cloud_service": {"cloud_service", "planning", "shared", "world_sim"},
}


def project_imports(path: Path) -> set[str]:
    """The project's modules that ``path`` imports, wherever in it."""
    names = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.level == 0:
            names.add(node.module)
    return {name for name in names if name.split(".")[0] in PROJECT}


@pytest.mark.parametrize("package", sorted(MAY_IMPORT))
def test_a_package_imports_only_what_it_may(package):
    allowed = MAY_IMPORT[package]
    crossing = [f"{path.relative_to(ROOT)} imports {name}"
                for path in sorted((ROOT / package).rglob("*.py"))
                for name in sorted(project_imports(path)) if name.split(".")[0] not in allowed]
    assert crossing == []


def test_the_rules_read_imports_inside_functions_too(tmp_path):
    module = tmp_path / "deferred.py"
    module.write_text("def later():\n    from planning.reference import LookaheadPolicy\n"
                      "    import world_sim.core\n", encoding="utf-8")
    assert project_imports(module) == {"planning.reference", "world_sim.core"}


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _run_time_imports(node: ast.AST):
    """The import statements under ``node`` that can run, those inside functions included:
    an import under ``if TYPE_CHECKING:`` names a type for the annotations and never loads."""
    if isinstance(node, ast.If) and _is_type_checking(node.test):
        children = node.orelse
    else:
        children = list(ast.iter_child_nodes(node))
    for child in children:
        if isinstance(child, ast.Import | ast.ImportFrom):
            yield child
        yield from _run_time_imports(child)


def _module_name(path: Path, root: Path) -> str:
    parts = path.relative_to(root).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def import_graph(root: Path, packages: tuple[str, ...]) -> dict[str, set[str]]:
    """Each module of ``packages`` under ``root`` and the modules of theirs it imports. A
    compiled module (its ``.pyx`` source) is a module that imports none of them. ``from p
    import m`` imports the module ``p.m`` where there is one, else the package ``p``; the
    packages a module sits in, which Python loads first, are not counted as its imports."""
    paths = {_module_name(path, root): path for package in packages
             for path in sorted((root / package).rglob("*")) if path.suffix in (".py", ".pyx")}
    graph = {}
    for name, path in paths.items():
        imported = set()
        if path.suffix == ".py":
            tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
            for node in _run_time_imports(tree):
                if isinstance(node, ast.Import):
                    imported.update(alias.name for alias in node.names)
                    continue
                base = node.module
                if node.level:
                    here = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
                    base = ".".join(here[: len(here) - node.level + 1] + ([base] if base else []))
                imported.update(f"{base}.{alias.name}" if f"{base}.{alias.name}" in paths
                                else base for alias in node.names)
        graph[name] = {other for other in imported if other in paths and other != name}
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """One cycle through each strongly connected component of ``graph`` that holds more than
    one module: ``[a, b, ..., a]``, each module importing the next."""
    index: dict[str, int] = {}
    lowest: dict[str, int] = {}
    stack: list[str] = []
    components = []

    def visit(module: str) -> None:  # Tarjan's algorithm
        index[module] = lowest[module] = len(index)
        stack.append(module)
        for other in sorted(graph[module]):
            if other not in index:
                visit(other)
                lowest[module] = min(lowest[module], lowest[other])
            elif other in stack:
                lowest[module] = min(lowest[module], index[other])
        if lowest[module] == index[module]:  # the root of a component: pop all of it
            component = {stack.pop()}
            while module not in component:
                component.add(stack.pop())
            if len(component) > 1:
                components.append(component)

    for module in sorted(graph):
        if module not in index:
            visit(module)
    return [_cycle_in(component, graph) for component in components]


def _cycle_in(component: set[str], graph: dict[str, set[str]]) -> list[str]:
    """The shortest cycle through the first module of ``component``, found breadth first."""
    start = min(component)
    came_from: dict[str, str] = {}
    frontier = [start]
    while start not in came_from:
        reached = []
        for module in frontier:
            for other in sorted(graph[module] & component):
                if other not in came_from:
                    came_from[other] = module
                    reached.append(other)
        frontier = reached
    path = [start]
    while len(path) == 1 or path[-1] != start:
        path.append(came_from[path[-1]])
    return path[::-1]


def test_no_modules_import_each_other_round_a_cycle():
    """Not even through imports deferred into functions: each module can be read, and
    loaded, after the ones it imports."""
    found = cycles(import_graph(ROOT, PROJECT))
    assert not found, "import cycles: " + "; ".join(" -> ".join(cycle) for cycle in found)


def test_a_deferred_import_cycle_is_found_and_named(tmp_path):
    package = tmp_path / "loop"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "first.py").write_text("from loop.second import later\n", encoding="utf-8")
    (package / "second.py").write_text("def later():\n    from . import third\n",
                                       encoding="utf-8")
    (package / "third.py").write_text("import loop.first\n", encoding="utf-8")
    (package / "typed.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                                      "    from loop.first import x\nimport loop.first\n",
                                      encoding="utf-8")
    graph = import_graph(tmp_path, ("loop",))
    assert graph["loop.typed"] == {"loop.first"}
    assert cycles(graph) == [["loop.first", "loop.second", "loop.third", "loop.first"]]
