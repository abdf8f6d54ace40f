"""The packages depend on one another one way (README, "What is in the box"): every import of
every module, those inside functions included, read from its source, names a package its own
may use. The command line (``jamnav``) wires them all together and is not held."""

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
