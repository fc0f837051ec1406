"""numba's on-disk kernel cache, made stale by an edit of any module a kernel is built from.

numba stamps a cached kernel with the modification time and size of the one file that defines it and with nothing
else, so a kernel that inlines functions of other modules (every kernel of this package does: ``cpu/composite.py``,
``cpu/row_vector.py``, ``spec.py``, ``splat_math.py`` ...) keeps running its old machine code after an edit of those
alone: a ``git pull`` of an editable install that changes only them leaves silently wrong kernels behind.
:func:`bind_sources` adds a fingerprint of every module of the package that the kernel's module imports, directly
or not, to the stamp numba compares, so that such an edit recompiles the kernel as an edit of its own file does.
numba then ignores the old entries and overwrites them; nothing else in its cache changes.
"""
from __future__ import annotations

import functools
import hashlib
import re
import sys
from pathlib import Path
from typing import Any, Mapping

#: Attribute set on a dispatcher whose cache stamp includes the fingerprint (binding twice changes nothing).
_BOUND = "_css_sources_bound"


def _module_file(name: str) -> Path | None:
    """The source file of module ``name`` of an imported top-level package (a package's ``__init__.py``), found by
    its path under the package (nothing is imported), or None if there is none."""
    parts = name.split(".")
    top = sys.modules.get(parts[0])
    top_file = getattr(top, "__file__", None)
    if not top_file:
        return None
    base = Path(top_file).parent.joinpath(*parts[1:])
    for path in (base.with_suffix(".py"), base / "__init__.py"):
        if path.is_file():
            return path
    return None


#: ``import a.b, c`` or ``from .a import (x, y`` at the start of a line (a parenthesised list may go on below).
_IMPORT = re.compile(r"^[ \t]*import[ \t]+([\w., \t]+)|^[ \t]*from[ \t]+(\.*)([\w.]*)[ \t]+import[ \t]+(\(?)([^#\n]*)",
                     re.MULTILINE)


@functools.lru_cache(maxsize=None)
def _imported(name: str, path: Path) -> tuple[str, ...]:
    """Names of the modules that module ``name`` (source ``path``) imports, relative imports resolved: for
    ``from X import y``, X and X.y (y may be a submodule). A line scan, not a parse (a kernel module's imports
    are statements at the start of a line; one inside a string only adds a file to the fingerprint)."""
    text = path.read_text(encoding="utf-8")
    is_package = path.name == "__init__.py"
    found: list[str] = []
    for m in _IMPORT.finditer(text):
        if m.group(1) is not None:
            found += [part.split()[0] for part in m.group(1).split(",") if part.strip()]
            continue
        dots, module, paren, names = m.group(2), m.group(3), m.group(4), m.group(5)
        if paren and ")" not in names:
            names += "," + text[m.end(5):text.index(")", m.end(5))].replace("\n", " ")
        if dots:
            parts = name.split(".")
            stem = ".".join(parts[:len(parts) - len(dots) + (1 if is_package else 0)] + ([module] if module else []))
        else:
            stem = module
        if module:
            found.append(stem)      # the module the names come from
        for alias in names.replace("(", " ").replace(")", " ").replace("\\", " ").split(","):
            if alias.split():
                found.append(f"{stem}.{alias.split()[0]}")      # a name that is itself a module
    return tuple(found)


@functools.lru_cache(maxsize=None)
def module_sources(name: str) -> tuple[Path, ...]:
    """The source files of module ``name`` and of every module of its top-level package that it imports, directly or
    through other modules of the package, sorted."""
    top = name.split(".")[0]
    seen: dict[str, Path] = {}
    todo = [name]
    while todo:
        mod = todo.pop()
        if mod in seen or mod.split(".")[0] != top:
            continue
        path = _module_file(mod)
        if path is None:
            continue
        seen[mod] = path
        todo.extend(_imported(mod, path))
    return tuple(sorted(set(seen.values())))


@functools.lru_cache(maxsize=None)
def sources_fingerprint(name: str) -> str:
    """SHA-256 (hex) of the contents of :func:`module_sources` of ``name``, each with its path relative to the
    package (so a checkout moved elsewhere keeps its cache)."""
    files = module_sources(name)
    root = _module_file(name.split(".")[0])
    base = root.parent if root is not None else Path("/")
    digest = hashlib.sha256()
    for path in files:
        rel = path.relative_to(base) if path.is_relative_to(base) else path
        data = path.read_bytes()
        digest.update(f"{rel.as_posix()}\0{len(data)}\0".encode())
        digest.update(data)
    return digest.hexdigest()


def bind_sources(namespace: Mapping[str, Any]) -> int:
    """Make the cached kernels of a module stale when any module they are built from changes.

    Call at the end of a module that defines ``cache=True`` kernels, with ``globals()``, before any of them runs:
    each dispatcher's cache stamp (numba's (mtime, size) of the module's own file) becomes (that stamp, the
    :func:`sources_fingerprint` of the module). Dispatchers without an on-disk cache are left alone. Returns how
    many dispatchers are bound (those bound before included).

    The stamp lives in numba's ``IndexDataCacheFile`` (``dispatcher._cache._cache_file._source_stamp``, as in numba
    0.68: test_kernel_cache.py checks it with the installed numba); if a numba version lacks it, the dispatcher's
    cache is turned off instead (correct, compiled in every process), never left stale.
    """
    fingerprint = sources_fingerprint(namespace["__name__"])
    bound = 0
    for obj in list(namespace.values()):
        cache = getattr(obj, "_cache", None)
        if cache is None or getattr(cache, "cache_path", None) is None:
            continue        # not a dispatcher, or one without an on-disk cache (numba's NullCache)
        if getattr(obj, _BOUND, False):
            bound += 1
            continue
        cache_file = getattr(cache, "_cache_file", None)
        if cache_file is not None and hasattr(cache_file, "_source_stamp"):
            cache_file._source_stamp = (cache_file._source_stamp, fingerprint)
        else:
            from numba.core.caching import NullCache
            obj._cache = NullCache()
        setattr(obj, _BOUND, True)
        bound += 1
    return bound
