"""The import rules of the layout (docs/architecture.md, "may import"), enforced on the source: every import
statement of every module, at top level or inside a function."""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PROJECT = ("schemas", "tasks", "data_catalog", "flows", "simulator")

# package -> (allowed project packages, forbidden third-party top-level names; None: only these)
RULES = {
    "schemas": ({"schemas"}, {"pydantic", "typing_extensions"}),
    "tasks": ({"tasks", "schemas"}, {"numpy", "scipy", "cv2", "open3d", "pymeshlab", "numba", "threadpoolctl",
                                     "gmsh", "matplotlib"}),
    "data_catalog": ({"data_catalog", "schemas"}, {"numpy", "zarr", "numcodecs", "yaml", "pydantic", "plyfile",
                                                   "pypcd4", "pye57", "laspy", "scipy", "meshio"}),
    "simulator": ({"simulator", "schemas", "data_catalog", "tasks"}, {"numpy", "scipy", "open3d", "cv2", "pydantic",
                                                                     "yaml", "zarr"}),
}
# flows may import anything; only these functions of flows/cli/simulate.py may touch the simulator
# (the `simulate` command is the simulator's own command line; `demo` simulates the demo sample;
# `export-cell` writes a sample as a cell's logs, for trying `import` on known data; `plan` plans a scan
# with the simulated cell's models)
SIMULATOR_IN_FLOWS = {("flows/cli/simulate.py", "_simulation_config"), ("flows/cli/simulate.py", "_cmd_simulate"),
                      ("flows/cli/simulate.py", "_cmd_demo"), ("flows/cli/simulate.py", "_cmd_export_cell"),
                      ("flows/cli/simulate.py", "_cmd_plan")}


def _imports(path: Path):
    """(line, top-level name, enclosing function or None) of every import in a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found = []

    def visit(node, function):
        for child in ast.iter_child_nodes(node):
            inner = child.name if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)) else function
            if isinstance(child, ast.Import):
                found.extend((child.lineno, a.name.split(".")[0], function) for a in child.names)
            elif isinstance(child, ast.ImportFrom) and child.level == 0 and child.module:
                found.append((child.lineno, child.module.split(".")[0], function))
            visit(child, inner)

    visit(tree, None)
    return found


def _files(package: str):
    return sorted((REPO / package).rglob("*.py"))


@pytest.mark.parametrize("package", sorted(RULES))
def test_package_imports_follow_the_layout(package):
    allowed_project, allowed_libraries = RULES[package]
    problems = []
    for path in _files(package):
        for line, name, _ in _imports(path):
            rel = path.relative_to(REPO).as_posix()
            if name in PROJECT and name not in allowed_project:
                problems.append(f"{rel}:{line} imports {name} ({package} may import {sorted(allowed_project)})")
            elif (name not in PROJECT and name not in sys.stdlib_module_names and name != "__future__"
                  and name not in allowed_libraries):
                problems.append(f"{rel}:{line} imports {name} (not a library {package} may use)")
    assert not problems, "\n".join(problems)


def test_only_the_simulate_and_demo_commands_touch_the_simulator():
    problems = [f"{path.relative_to(REPO).as_posix()}:{line} imports simulator (in {function})"
                for path in _files("flows") for line, name, function in _imports(path)
                if name == "simulator" and (path.relative_to(REPO).as_posix(), function) not in SIMULATOR_IN_FLOWS]
    assert not problems, "\n".join(problems)


def test_nothing_imports_prefect_outside_flows():
    problems = [f"{path.relative_to(REPO).as_posix()}:{line} imports {name}"
                for package in RULES for path in _files(package) for line, name, _ in _imports(path)
                if name in ("prefect", "prefect_dask", "distributed")]
    assert not problems, "\n".join(problems)


def test_a_stage_that_reads_its_inputs_figures_says_so():
    """Stage keys hash the inputs' files; a stage whose body reads its inputs' metrics as well (the
    report) declares it (``Stage.reads_input_metrics``), so that they go into its key too: without,
    a run whose inputs wrote the same files with other figures took the other run's report from the
    stage cache (issue 28). Checked on the source of every stage's body module."""
    from flows.stages import STAGES

    for stage in STAGES:
        for at in filter(None, (stage.body_at, stage.surfaces_body_at)):
            module = at.split(":")[0]
            source = (REPO / (module.replace(".", "/") + ".py")).read_text(encoding="utf-8")
            reads = any(isinstance(node, ast.Attribute) and node.attr == "metrics" for node in ast.walk(ast.parse(source)))
            assert reads <= stage.reads_input_metrics, f"{stage.name} ({module}) reads .metrics; set reads_input_metrics"
