"""numba's on-disk kernel cache goes stale with any module a kernel is built from (engine/kernel_cache.py)."""
from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from css_ros.engine.kernel_cache import module_sources, sources_fingerprint

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "css_ros"

KERNEL = '''from numba import njit

from .mid import (
    g,
)
from css_ros.engine.kernel_cache import bind_sources


@njit(cache=True)
def k(x):
    return g(x) * 10


bind_sources(globals())
'''
MID = '''from numba import njit

from . import leaf


@njit(inline="always")
def g(x):
    return leaf.f(x) + 100
'''
LEAF = '''from numba import njit


@njit(inline="always")
def f(x):
    return x + {step}
'''
RUN = ("import json, sys; from kcpkg.kern import k; "
       "print(json.dumps([int(k(1)), sum(k.stats.cache_hits.values()), sum(k.stats.cache_misses.values())]))")


def _package(root: Path, step: int) -> None:
    pkg = root / "kcpkg"
    pkg.mkdir(exist_ok=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "kern.py").write_text(KERNEL)
    (pkg / "mid.py").write_text(MID)
    (pkg / "leaf.py").write_text(LEAF.format(step=step))


def _run(root: Path) -> list[int]:
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(root), str(REPO)]))
    env.pop("NUMBA_CACHE_DIR", None)
    env.pop("NUMBA_DISABLE_JIT", None)
    out = subprocess.run([sys.executable, "-c", RUN], env=env, capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_an_edit_of_an_inlined_module_two_imports_away_recompiles_the_cached_kernel(tmp_path):
    """leaf.py (imported by mid.py through ``from . import leaf``, itself imported by the kernel's module through a
    parenthesised import) is edited, nothing else: the next process recompiles and runs the new code, the one after
    it loads that from the cache."""
    _package(tmp_path, step=1)
    assert _run(tmp_path) == [(1 + 1 + 100) * 10, 0, 1]        # compiled and saved
    assert _run(tmp_path) == [(1 + 1 + 100) * 10, 1, 0]        # loaded from the cache
    (tmp_path / "kcpkg" / "leaf.py").write_text(LEAF.format(step=2))
    assert _run(tmp_path) == [(1 + 2 + 100) * 10, 0, 1]        # stale: compiled again with the new leaf
    assert _run(tmp_path) == [(1 + 2 + 100) * 10, 1, 0]


def test_module_sources_follow_the_package_imports_only(tmp_path, monkeypatch):
    _package(tmp_path, step=1)
    monkeypatch.syspath_prepend(str(tmp_path))
    importlib.import_module("kcpkg")
    names = sorted(p.name for p in module_sources("kcpkg.kern"))
    assert names == ["kern.py", "leaf.py", "mid.py"]          # numba and css_ros are other packages
    assert [p.name for p in module_sources("kcpkg.leaf")] == ["leaf.py"]
    before = sources_fingerprint("kcpkg.kern")
    assert len(before) == 64 and before == sources_fingerprint("kcpkg.kern")
    # the engine's update kernel is built from the walk, the row sums, the borrowed views and the constants
    raster = {p.relative_to(PKG).as_posix() for p in module_sources("css_ros.engine.cpu.raster")}
    assert {"engine/cpu/composite.py", "engine/cpu/row_vector.py", "engine/cpu/borrowed.py", "engine/spec.py",
            "engine/label_input.py", "engine/cpu/raster.py"} <= raster
    assert not any(p.startswith(("ros/", "evaluation/", "engine/cuda/")) for p in raster)


CACHED = re.compile(r"^\s*@?(?:numba\.)?njit\(.*cache=True", re.MULTILINE)


def _kernel_modules() -> list[str]:
    """Every module of the package that defines numba kernels cached on disk."""
    found = []
    for path in sorted(PKG.rglob("*.py")):
        if "__pycache__" not in path.parts and CACHED.search(path.read_text(encoding="utf-8")):
            found.append(".".join(("css_ros",) + path.relative_to(PKG).with_suffix("").parts))
    return found


@pytest.mark.parametrize("name", _kernel_modules())
def test_every_cached_kernel_of_the_package_is_bound_to_its_sources(name):
    module = importlib.import_module(name)
    kernels = [obj for obj in vars(module).values()
               if getattr(getattr(obj, "_cache", None), "cache_path", None) is not None]
    assert kernels, f"{name} has no cached kernel"
    unbound = [k.__name__ for k in kernels if not getattr(k, "_css_sources_bound", False)]
    assert not unbound, f"{name}: call bind_sources(globals()) at the end of the module ({unbound})"
