"""The CPU kernels' software prefetch (engine/cpu/prefetch.py): a hint that compiles for every array type the kernels
give it and changes no result, also when it names a row past the end."""
from __future__ import annotations

import numpy as np
from numba import njit

from css_ros.engine.cpu.prefetch import prefetch, prefetch_ahead


@njit
def _gather_rows(arr, ids):
    """arr[ids] with a prefetch of the row AHEAD iterations on, and of one past the array's end."""
    m = ids.shape[0]
    out = np.empty((m, arr.shape[1]), arr.dtype)
    for j in range(m):
        prefetch_ahead(arr, ids, j)
        prefetch(arr, (arr.shape[0] + 1000, 0))  # never dereferenced
        for c in range(arr.shape[1]):
            out[j, c] = arr[ids[j], c]
    return out


@njit
def _first_of_blocks(sh, rows):
    out = np.empty(rows.shape[0], sh.dtype)
    for r in range(rows.shape[0]):
        prefetch(sh, (rows[r], 0, 0))
        out[r] = sh[rows[r], 0, 0]
    return out


def test_a_prefetching_gather_equals_numpys_fancy_index():
    rng = np.random.default_rng(0)
    for dtype, cols in ((np.float64, 28), (np.float32, 68), (np.int32, 4), (np.float64, 1)):
        arr = rng.normal(size=(5000, cols)).astype(dtype)
        ids = rng.permutation(5000)[:1200]
        before = arr.copy()
        np.testing.assert_array_equal(_gather_rows(arr, ids), arr[ids])
        np.testing.assert_array_equal(arr, before)
    sh = rng.normal(size=(300, 16, 3)).astype(np.float32)
    rows = rng.permutation(300)
    np.testing.assert_array_equal(_first_of_blocks(sh, rows), sh[rows, 0, 0])
