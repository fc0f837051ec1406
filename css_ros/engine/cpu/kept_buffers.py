"""Per-frame work arrays of the numba backend kept from one observe to the next.

Arrays of megabytes taken fresh every frame cost their first touch: glibc serves them from fresh pages whenever
other work in the process (a node's messages, a second map, a benchmark's other code) handed its freed memory back
to the system in between, and each 4 KiB page then faults (measured on the real biker splat after other work in the
same process: about 3,800 faults and 12 ms of system time in the render's raw planes, 1,000 in the attribute rows).
Kept buffers fault once. Like :class:`~css_ros.engine.cpu.raster.UpdateWorkspace`, one per thread of use: a
``SemanticMap`` is used from one thread at a time, and what these hand out is valid until the next ``take``.
"""
from __future__ import annotations

import numpy as np


class RenderPlanes:
    """The render's raw (H, W) planes (label int32; E, Var, kappa_b, evidence, depth float64; (H, W, 3) colour
    float64), for renders whose planes are turned into the view's own arrays before the next one (the final form)."""

    def __init__(self) -> None:
        self._shape: tuple[int, int] = (-1, -1)
        self._planes: tuple[np.ndarray, ...] = ()

    def take(self, height: int, width: int) -> tuple[np.ndarray, ...]:
        """(label, E, Var, kappa_b, evidence, rgb, depth), uninitialised."""
        if self._shape != (height, width):
            hw = (height, width)
            self._planes = (np.empty(hw, np.int32), np.empty(hw), np.empty(hw), np.empty(hw), np.empty(hw),
                            np.empty((height, width, 3)), np.empty(hw))
            self._shape = hw
        return self._planes


class RowBuffers:
    """Flat float32 storage for a frame's per-Gaussian attribute rows (M rows of ``cols`` columns and of ``short``
    columns), grown to the largest M met (by a quarter more, so that a slowly growing view does not reallocate every
    frame)."""

    def __init__(self) -> None:
        self._full = np.empty(0, np.float32)
        self._short = np.empty(0, np.float32)

    def take(self, m: int, cols: int, short: int) -> tuple[np.ndarray, np.ndarray]:
        """Uninitialised (m, cols) and (m, short) C-contiguous float32 arrays."""
        if self._full.size < m * cols or self._short.size < m * short:
            grown = m + m // 4
            self._full = np.empty(grown * cols, np.float32)
            self._short = np.empty(grown * short, np.float32)
        return self._full[:m * cols].reshape(m, cols), self._short[:m * short].reshape(m, short)
