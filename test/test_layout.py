"""The package layout's dependency rule, checked on the code's own imports, and the longest function allowed.

Layers, lowest first: ``engine`` (and ``errors``) <- ``io`` <- ``evaluation`` / ``export`` /
``importers`` <- ``ros`` <- ``demo`` / ``clients``. A module may import its own layer and the
layers below it, never above; the ROS-free layers never import rclpy.
"""
from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "css_ros"

#: subpackage -> subpackages it may import (besides itself and ``errors``).
ALLOWED: dict[str, set[str]] = {
    "engine": set(),
    "io": {"engine"},
    "evaluation": {"engine", "io", "export"},
    "export": {"engine", "io"},
    "importers": {"engine", "io"},
    "maps": {"engine", "io"},
    "ros": {"engine", "io", "export"},
    "demo": {"engine", "io", "evaluation", "ros"},
    "clients": {"engine", "io", "ros"},
    "view": {"engine", "io", "export", "ros", "clients"},
    "calibration": {"engine", "io", "evaluation", "export"},
}
ROS_FREE = ("engine", "io", "evaluation", "export", "importers", "maps", "calibration")
#: Root modules of layer 0, importable from every layer (they import nothing of the package but errors).
BASE = ("errors", "console")
ROS_MODULES = ("rclpy", "std_msgs", "sensor_msgs", "geometry_msgs", "std_srvs", "diagnostic_msgs",
               "builtin_interfaces", "rcl_interfaces")


def _modules() -> list[Path]:
    return sorted(p for p in PKG.rglob("*.py") if "__pycache__" not in p.parts)


def _imports(path: Path) -> list[tuple[str, int]]:
    """(absolute dotted module, line) of every import in ``path`` (relative imports resolved)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    pkg_parts = ["css_ros", *path.relative_to(PKG).parts[:-1]]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = pkg_parts[: len(pkg_parts) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
                if node.module is None:  # from . import x
                    out += [(f"{mod}.{a.name}", node.lineno) for a in node.names]
                    continue
            else:
                mod = node.module or ""
            out.append((mod, node.lineno))
    return out


def _layer(path: Path) -> str | None:
    rel = path.relative_to(PKG).parts
    return rel[0] if len(rel) > 1 else None


#: Longest function or method [lines, decorators excluded, docstring included]: longer ones are split into named steps.
MAX_FUNCTION_LINES = 150


def test_functions_are_at_most_150_lines():
    long = []
    for path in _modules():
        for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = (node.end_lineno or node.lineno) - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long.append(f"{path.relative_to(PKG)}:{node.lineno} {node.name} is {n} lines")
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines:\n" + "\n".join(long)


def test_every_subpackage_has_a_rule():
    subpackages = {p.name for p in PKG.iterdir() if p.is_dir() and (p / "__init__.py").exists()}
    assert subpackages <= set(ALLOWED), f"add a layer rule for {subpackages - set(ALLOWED)}"


def test_imports_follow_the_layers():
    bad = []
    for path in _modules():
        layer = _layer(path)
        if layer is None:
            continue  # the package root (public API, errors, the `python -m css_ros.node` shim)
        for mod, line in _imports(path):
            parts = mod.split(".")
            if parts[0] in ROS_MODULES and layer in ROS_FREE:
                bad.append(f"{path.relative_to(PKG)}:{line} imports {mod} (a ROS-free layer)")
            if parts[0] != "css_ros" or len(parts) < 2:
                continue
            target = parts[1]
            if target in BASE or target == layer or target in ALLOWED[layer]:
                continue
            bad.append(f"{path.relative_to(PKG)}:{line} imports {mod} ({layer} may not import {target})")
    assert not bad, "\n".join(bad)


def test_base_modules_import_nothing_above_them():
    for name in BASE:
        for mod, line in _imports(PKG / f"{name}.py"):
            assert not mod.startswith("css_ros.") or mod == "css_ros.errors", f"{name}.py:{line} imports {mod}"


def test_torch_twin_imports_no_numba_code():
    for path in (PKG / "engine" / "torch").rglob("*.py"):
        for mod, line in _imports(path):
            assert not mod.startswith(("numba", "css_ros.engine.cpu")), f"{path.name}:{line} imports {mod}"


@pytest.mark.parametrize("modules", [
    "css_ros",
    "css_ros.engine",
    "css_ros.io, css_ros.io.bag, css_ros.io.frames, css_ros.io.frame_gate, css_ros.io.topics, css_ros.io.outputs",
    "css_ros.evaluation, css_ros.evaluation.cli, css_ros.evaluation.replay",
])
def test_ros_free_layers_do_not_import_rclpy_or_torch(modules):
    code = (f"import sys\nimport {modules}\n"
            "bad = sorted(m for m in ('rclpy', 'torch') if m in sys.modules)\n"
            "print(','.join(bad))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "", f"importing {modules} imported {out.stdout.strip()}"


def test_engine_imports_torch_only_for_the_torch_backend():
    code = ("import sys, numpy as np\n"
            "from css_ros import Camera, GaussianModel, SemanticMap\n"
            "from css_ros.engine.camera import intrinsics_from_fov\n"
            "n = 50\n"
            "rng = np.random.default_rng(0)\n"
            "m = GaussianModel(means=rng.normal(0, 1, (n, 3)) + [0, 0, 5], log_scales=np.full((n, 3), -2.0),\n"
            "                  rotations=np.tile([1.0, 0, 0, 0], (n, 1)), opacity_logits=np.zeros(n),\n"
            "                  sh=np.zeros((n, 1, 3), np.float32))\n"
            "cam = Camera(intrinsics_from_fov(16, 12, 60.0), 16, 12, np.eye(4))\n"
            "SemanticMap(m, 3).observe(cam, np.zeros((12, 16), np.int32))\n"
            "print('torch' in sys.modules)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "False"


BACKEND_PACKAGES = ("cpu", "cuda", "torch")
#: modules inside a backend's folder that are tools about it, not part of it: the CUDA cost model counts a frame's
#: sizes with the CPU engine (the same culls and tile lists)
BACKEND_TOOLS = {("engine", "cuda", "cost_model.py")}


def test_backends_know_only_the_contract_and_the_registry_knows_them():
    """Each rasteriser backend imports the backend contract (engine/raster_backend.py), never another backend or the
    registry; engine/backends.py is the only module of the package that imports a backend's entry module."""
    bad = []
    for path in _modules():
        rel = path.relative_to(PKG).parts
        own = rel[1] if len(rel) > 2 and rel[0] == "engine" and rel[1] in BACKEND_PACKAGES else None
        if rel in BACKEND_TOOLS:
            continue
        for mod, line in _imports(path):
            parts = mod.split(".")
            if own is not None:
                other = len(parts) > 2 and parts[1] == "engine" and parts[2] in BACKEND_PACKAGES and parts[2] != own
                if other or mod in ("css_ros.engine.backends", "css_ros.engine.semantic_map"):
                    bad.append(f"{path.relative_to(PKG)}:{line} imports {mod}")
            elif (mod in {f"css_ros.engine.{b}.backend" for b in ("cpu", "cuda")} or mod == "css_ros.engine.torch.raster") \
                    and rel != ("engine", "backends.py"):
                bad.append(f"{path.relative_to(PKG)}:{line} imports backend {mod} (only engine/backends.py may)")
    assert not bad, "\n".join(bad)


def test_module_imports_have_no_cycles():
    """The package's module imports (module level and deferred) form no cycle."""
    graph: dict[str, set[str]] = {}
    for path in _modules():
        name = "css_ros." + ".".join(path.relative_to(PKG).with_suffix("").parts)
        name = name.removesuffix(".__init__")
        graph[name] = {m for m, _ in _imports(path) if m.startswith("css_ros.")}
    graph = {k: {m for m in v if m in graph and m != k and not k.startswith(m + ".")} for k, v in graph.items()}
    seen: dict[str, int] = {}
    stack: list[str] = []

    def visit(node: str) -> None:
        seen[node] = 1
        stack.append(node)
        for nxt in sorted(graph[node]):
            if seen.get(nxt) == 1:
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(nxt):] + [nxt]))
            if nxt not in seen:
                visit(nxt)
        stack.pop()
        seen[node] = 2

    for node in sorted(graph):
        if node not in seen:
            visit(node)
