"""The 8-wide row accumulation of the CPU kernels (engine/cpu/row_vector.py) against numpy's float64 sums, for every
index type the render gives it, and only the first 8 accumulator entries written."""
from __future__ import annotations

import numpy as np
import pytest
from numba import njit

from css_ros.engine.cpu.raster import SHORT_COLS
from css_ros.engine.cpu.row_vector import WIDTH, add_row, add_rows4


@njit
def _weighted_sum(acc, rows, ids, weights):
    """acc[:8] += sum_i weights[i] rows[ids[i], :8], four rows a step, the rest one by one."""
    i = 0
    n = ids.shape[0]
    while i + 4 <= n:
        add_rows4(acc, rows, ids[i], ids[i + 1], ids[i + 2], ids[i + 3], np.float32(weights[i]),
                  np.float32(weights[i + 1]), np.float32(weights[i + 2]), np.float32(weights[i + 3]))
        i += 4
    while i < n:
        add_row(acc, rows, ids[i], np.float32(weights[i]))
        i += 1


@pytest.mark.parametrize("id_dtype", [np.uint16, np.int32, np.int64])
@pytest.mark.parametrize("n", [0, 1, 3, 4, 7, 8, 33])
def test_weighted_row_sums_equal_numpys(id_dtype: type, n: int) -> None:
    rng = np.random.default_rng(n)
    rows = rng.uniform(-1.0, 1.0, size=(300, WIDTH)).astype(np.float32)
    ids = rng.integers(0, rows.shape[0], size=n).astype(id_dtype)
    weights = rng.uniform(0.0, 1.0, size=n).astype(np.float32)
    acc = np.full(WIDTH + 5, 7.0, dtype=np.float32)   # wider than a step, with a value to add to
    _weighted_sum(acc, rows, ids, weights)
    expected = 7.0 + (weights[:, None].astype(np.float64) * rows[ids.astype(np.int64)]).sum(axis=0)
    # float32 sums of n terms of magnitude <= 1 around 7: a few float32 ulps of the largest partial sum
    np.testing.assert_allclose(acc[:WIDTH], expected, rtol=0, atol=(n + 1) * 8 * 2.0 ** -23 * (7 + n))
    np.testing.assert_array_equal(acc[WIDTH:], np.float32(7.0))   # never written past the step


def test_rows_of_a_strided_array_and_float64_weights_do_not_compile() -> None:
    """Only C-contiguous float32 rows and accumulators, float32 weights: anything else is a typing error, not a
    wrong load."""
    acc = np.zeros(WIDTH, np.float32)
    rows = np.zeros((10, 2 * WIDTH), np.float32)[:, ::2]
    with pytest.raises(Exception, match="add_row"):
        _weighted_sum(acc, rows, np.zeros(1, np.int64), np.zeros(1, np.float32))

    @njit
    def f64(acc, rows):
        add_row(acc, rows, 0, 0.5)
    with pytest.raises(Exception, match="add_row"):
        f64(acc, np.zeros((10, WIDTH), np.float32))


def test_the_short_shading_row_is_one_vector_step() -> None:
    assert SHORT_COLS == WIDTH
