"""Kernel launches bound once: numba-cuda's per-launch argument handling (typing every argument, converting each
array through ``__cuda_array_interface__``, marshalling it to ctypes) done when a launch is first bound, not at
every frame.

A :class:`BoundLaunch` keeps a kernel's compiled overload, its launch configuration and its marshalled argument
list; calling it is one driver launch. It is valid as long as its arguments are: the single-view plan
(:mod:`.view_plan`) keeps every buffer it passes at a fixed address and scalars fixed, and :class:`Launches` binds
again when any argument is another object. Under the simulator (no driver) a bound launch is the plain
``kernel[grid, block](*args)`` call.
"""
from __future__ import annotations

from typing import Any, Callable

#: scalar argument types kept by value in a binding's key (arrays are kept by identity)
_SCALARS = (bool, int, float)


class BoundLaunch:
    """One kernel launch with its arguments fixed. Call it to launch (on the default stream, as numba-cuda's
    ``kernel[grid, block](*args)`` does).

    Args:
        kernel: a ``numba.cuda.jit`` kernel (dispatcher).
        grid, block: launch configuration (ints).
        args: the kernel's arguments: device arrays (kept alive by this object) and Python scalars.
        simulated: numba-cuda's simulator: launch through the dispatcher each time.
    """

    def __init__(self, kernel: Any, grid: int, block: int, args: tuple[Any, ...], simulated: bool) -> None:
        self.args = args  # keeps every array alive: the marshalled pointers stay valid
        self.grid, self.block = int(grid), int(block)
        self.bound = False
        self._call: Callable[[], Any] = lambda: kernel[self.grid, self.block](*args)
        if not simulated:  # pragma: no cover - needs a GPU and its driver
            self._call = _bind(kernel, self.grid, self.block, args) or self._call
            self.bound = True

    def __call__(self) -> None:
        self._call()


def _bind(kernel: Any, grid: int, block: int, args: tuple[Any, ...]) -> Callable[[], Any] | None:  # pragma: no cover
    """The driver launch of ``kernel`` with ``args`` marshalled once (numba-cuda 0.30's ``_Kernel.launch`` minus the
    per-launch work), or None where this numba-cuda differs (the caller then launches through the dispatcher)."""
    try:
        from numba.cuda._compat import CUDA_CORE_GE_1_0
        from numba.cuda.cudadrv import driver
        from numba.cuda.dispatcher import (LaunchConfig, launch,  # type: ignore[attr-defined]
                                           normalize_kernel_dimensions)

        argtypes = tuple(kernel.typeof_pyval(a) for a in args)
        compiled = kernel.compile(argtypes)
        if getattr(compiled, "debug", False) or getattr(compiled, "cooperative", False):
            return None
        retr: list[Any] = []
        kernelargs: list[Any] = []
        for t, v in zip(compiled.argument_types, args):
            compiled._prepare_args(t, v, 0, retr, kernelargs)
        if retr:  # a host array was copied in: its write-back would be lost; never bind that
            return None
        griddim, blockdim = normalize_kernel_dimensions(grid, block)
        opts = {"is_cooperative": False} if CUDA_CORE_GE_1_0 else {"cooperative_launch": False}
        config = LaunchConfig(grid=griddim, block=blockdim, shmem_size=0, **opts)
        cu_kernel = compiled._codelibrary.get_cufunc().kernel
        stream = driver._to_core_stream(0)  # type: ignore[attr-defined]  # the default stream, as kernel[grid, block](...) uses
    except (ImportError, AttributeError, TypeError):
        return None
    return lambda: launch(stream, config, cu_kernel, *kernelargs)


class Launches:
    """Bound launches, looked up by (kernel, configuration, argument identities): a frame whose buffers and scalars
    are those of an earlier frame reuses that frame's binding. ``count`` counts the launches made (a stub device in
    the benchmarks reads it)."""

    def __init__(self, simulated: bool, capacity: int = 64) -> None:
        self.simulated = simulated
        self.capacity = capacity
        self._bound: dict[tuple[Any, ...], BoundLaunch] = {}
        self.count = 0
        self.bindings = 0

    @staticmethod
    def _key(kernel: Any, grid: int, block: int, args: tuple[Any, ...]) -> tuple[Any, ...]:
        return (id(kernel), int(grid), int(block),
                *((type(a), a) if isinstance(a, _SCALARS) else id(a) for a in args))

    def launch(self, kernel: Any, grid: int, block: int, *args: Any) -> None:
        """Launch ``kernel[grid, block](*args)``, bound on first use of these arguments."""
        key = self._key(kernel, grid, block, args)
        bound = self._bound.get(key)
        if bound is None:
            if len(self._bound) >= self.capacity:  # sizes and settings of a long-lived process: bounded
                self._bound.clear()
            bound = self._bound[key] = BoundLaunch(kernel, grid, block, args, self.simulated)
            self.bindings += 1
        self.count += 1
        bound()

    def clear(self) -> None:
        """Forget every binding (their buffers are being replaced)."""
        self._bound.clear()
