"""The layers of DESIGN.md, enforced on the real import graph.

``core < io < runtime < nodes < sim_node, learner``: every module's imports (top-level and
inside functions) are read with :mod:`ast` from every file of the three packages, so a
wrong-way import added anywhere fails here. Two subprocess checks then import the core and
the I/O layer with the forbidden packages made unimportable.
"""

from __future__ import annotations

import ast
import functools
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("tpsr_ros", "sim_node", "learner")
NODE_MODULES = {
    "tpsr_ros.filter_node",
    "tpsr_ros.record",
    "tpsr_ros.play",
    "tpsr_ros.bag_info",
    "tpsr_ros.bag_recover",
    "sim_node.node",
    "sim_node.__main__",
}
MIDDLEWARE = ("rclpy", "cyclonedds", "rcl_interfaces", "rosidl_runtime_py")
BAG_LIBRARIES = ("rosbags", "mcap")


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _sources() -> dict[str, Path]:
    found = {}
    for package in PACKAGES:
        for path in sorted((ROOT / package).rglob("*.py")):
            found[_module_name(path)] = path
    return found


MODULES = _sources()


def _imports(name: str, path: Path) -> set[str]:
    """Every module ``name`` imports, anywhere in the file (resolved to project modules)."""
    is_package = path.name == "__init__.py"
    base = name.split(".") if is_package else name.split(".")[:-1]
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), str(path))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                stem = base[: len(base) - node.level + 1]
                module = ".".join(stem + ([node.module] if node.module else []))
            else:
                module = node.module or ""
            for alias in node.names:
                child = f"{module}.{alias.name}"
                found.add(child if child in MODULES else module)
    return found


@functools.cache
def _graph() -> dict[str, set[str]]:
    """Every project module's imports, parsed once per process when a test first asks (not
    at collection, which every test worker does)."""
    return {name: _imports(name, path) for name, path in MODULES.items()}


def _layer(module: str) -> str:
    if module in NODE_MODULES or any(module.startswith(n + ".") for n in NODE_MODULES):
        return "node"
    for prefix in ("tpsr_ros.core", "tpsr_ros.io", "tpsr_ros.runtime"):
        if module == prefix or module.startswith(prefix + "."):
            return prefix.rsplit(".", 1)[1]
    return module.split(".")[0]


def _hits(modules: set[str], prefixes: tuple[str, ...]) -> list[str]:
    return sorted(
        m
        for m in modules
        if m.split(".")[0] in prefixes
        or m in prefixes
        or any(m.startswith(p + ".") for p in prefixes)
    )


def _violations(layer: str, forbidden: tuple[str, ...]) -> dict[str, list[str]]:
    return {
        name: hits
        for name, imports in _graph().items()
        if _layer(name) == layer and (hits := _hits(imports, forbidden))
    }


def test_the_graph_covers_the_project() -> None:
    assert {"tpsr_ros.core.tpsr", "tpsr_ros.io.bag", "tpsr_ros.runtime.node"} <= set(_graph())
    assert "tpsr_ros.core.filtering" in _graph()["tpsr_ros.core.tpsr_model"]
    assert "learner.tune" in _graph()["learner.measures"]  # lazy imports count too


def test_core_imports_only_the_core() -> None:
    forbidden = (
        "tpsr_ros.io",
        "tpsr_ros.runtime",
        *NODE_MODULES,
        "sim_node",
        "learner",
        *BAG_LIBRARIES,
        *MIDDLEWARE,
        "yaml",
    )
    assert _violations("core", forbidden) == {}


def test_io_imports_no_middleware_runtime_or_nodes() -> None:
    forbidden = ("tpsr_ros.runtime", *NODE_MODULES, "sim_node", "learner", *MIDDLEWARE)
    assert _violations("io", forbidden) == {}


def test_runtime_imports_no_node_and_no_application() -> None:
    assert _violations("runtime", (*NODE_MODULES, "sim_node", "learner")) == {}


def test_no_tpsr_ros_module_imports_sim_node_or_learner() -> None:
    wrong = {
        name: hits
        for name, imports in _graph().items()
        if name.split(".")[0] == "tpsr_ros" and (hits := _hits(imports, ("sim_node", "learner")))
    }
    assert wrong == {}


def test_no_learner_module_imports_a_node_module() -> None:
    assert _violations("learner", tuple(NODE_MODULES)) == {}


def test_sim_node_imports_no_learner() -> None:
    assert _violations("sim_node", ("learner",)) == {}


def test_no_import_cycles_between_modules() -> None:
    """Strongly connected components of the module graph (a package's ``__init__`` importing
    its own submodules, and a submodule importing its parent package, are not cycles)."""
    edges = {
        name: {
            m
            for m in imports
            if m in MODULES
            and m != name
            and not m.startswith(name + ".")
            and not name.startswith(m + ".")
        }
        for name, imports in _graph().items()
    }
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    cycles: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in edges[v]:
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
                cycles.append(sorted(component))

    sys.setrecursionlimit(10_000)
    for v in sorted(edges):
        if v not in index:
            visit(v)
    assert cycles == []


_BLOCKER = """
import importlib.abc, sys
BLOCKED = {blocked!r}
class Blocker(importlib.abc.MetaPathFinder):
    def find_spec(self, name, path=None, target=None):
        if name.split(".")[0] in BLOCKED:
            raise ImportError(f"{{name}} is blocked by the layering test")
        return None
sys.meta_path.insert(0, Blocker())
for name in BLOCKED:
    assert name not in sys.modules, name
"""


def _import_with_blocked(modules: list[str], blocked: tuple[str, ...]) -> None:
    code = _BLOCKER.format(blocked=blocked) + textwrap.dedent(
        f"""
        import importlib
        for name in {modules!r}:
            importlib.import_module(name)
        leaked = sorted(m for m in sys.modules if m.split(".")[0] in BLOCKED)
        assert not leaked, leaked
        """
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr[-2000:]


def _layer_modules(layer: str) -> list[str]:
    return sorted(name for name in MODULES if _layer(name) == layer)


@pytest.mark.parametrize(
    ("layer", "blocked"),
    [
        ("core", (*BAG_LIBRARIES, *MIDDLEWARE, "sim_node", "learner", "yaml")),
        ("io", (*MIDDLEWARE, "sim_node", "learner")),
    ],
)
def test_a_layer_imports_with_the_layers_above_unimportable(
    layer: str, blocked: tuple[str, ...]
) -> None:
    _import_with_blocked([f"tpsr_ros.{layer}", *_layer_modules(layer)], blocked)


def test_the_array_api_needs_no_bag_library_or_middleware() -> None:
    _import_with_blocked(["tpsr_ros"], (*BAG_LIBRARIES, *MIDDLEWARE, "sim_node", "learner"))
    code = _BLOCKER.format(blocked=(*BAG_LIBRARIES, *MIDDLEWARE, "sim_node")) + (
        "from tpsr_ros import TPSRConfig, Trajectory, fit, load_model, save_model\n"
    )
    result = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True)
    assert result.returncode == 0, result.stderr[-2000:]


ROS_FREE_FILTER_PARTS = [
    "tpsr_ros.filter_node.inputs",
    "tpsr_ros.filter_node.health",
    "tpsr_ros.filter_node.stepping",
]


def test_the_filter_nodes_parts_import_without_ros_bag_libraries_or_middleware() -> None:
    assert set(ROS_FREE_FILTER_PARTS) <= set(MODULES)
    _import_with_blocked(
        ROS_FREE_FILTER_PARTS, (*BAG_LIBRARIES, *MIDDLEWARE, "sim_node", "learner", "yaml")
    )


def test_the_filter_nodes_health_levels_are_diagnostic_msgs_levels() -> None:
    from tpsr_ros.filter_node import health
    from tpsr_ros.runtime import diagnostics

    assert (health.OK, health.WARN, health.ERROR, health.STALE) == (
        diagnostics.OK,
        diagnostics.WARN,
        diagnostics.ERROR,
        diagnostics.STALE,
    )
