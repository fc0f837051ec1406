"""Compiled kernel of :meth:`css_ros.engine.classes.ClassSet.colorize`: label ids -> palette colours in one pass."""
from __future__ import annotations

import numpy as np
from numba import njit
from .kernel_cache import bind_sources


@njit(cache=True, nogil=True)
def colorize_into(labels: np.ndarray, palette: np.ndarray, ignore_label: int, out: np.ndarray) -> None:
    """``out[i] = palette[labels[i]]`` for ids in [0, C) other than ``ignore_label``, black (0, 0, 0) otherwise.

    Args:
        labels: (P,) integer class ids.
        palette: (C, 3) uint8 RGB.
        ignore_label: id drawn black even when it is below C.
        out: (P, 3) uint8, written.
    """
    num_classes = palette.shape[0]
    for i in range(labels.shape[0]):
        k = labels[i]
        if k < 0 or k >= num_classes or k == ignore_label:
            out[i, 0] = 0
            out[i, 1] = 0
            out[i, 2] = 0
        else:
            out[i, 0] = palette[k, 0]
            out[i, 1] = palette[k, 1]
            out[i, 2] = palette[k, 2]


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
