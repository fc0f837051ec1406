"""Projection helpers: the exact stable depth sort."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.cpu.projection import _argsort_positive


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_depth_argsort_is_the_exact_stable_sort(seed):
    """Equal to numpy's stable argsort of the float64 values, including exact ties and values that
    differ below float32 resolution (where the float32 radix keys tie)."""
    rng = np.random.default_rng(seed)
    d = rng.uniform(0.05, 80.0, 20000)
    d[::7] = d[::7].astype(np.float32).astype(np.float64)                       # exact float32 values
    d[1::5] = d[0:-1:5]                                                         # exact duplicates
    d[2::9] = d[2::9].astype(np.float32).astype(np.float64) * (1.0 + 1e-12)     # float32 ties, float64 apart
    rng.shuffle(d)
    np.testing.assert_array_equal(_argsort_positive(d), np.argsort(d, kind="stable"))


def test_depth_argsort_small_inputs():
    for values in ([1.0], [2.0, 2.0, 1.0], [3.0, 1.0, 2.0, 1.0]):
        v = np.asarray(values)
        np.testing.assert_array_equal(_argsort_positive(v), np.argsort(v, kind="stable"))
