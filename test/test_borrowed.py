"""Borrowed arrays of the CPU kernels (engine/cpu/borrowed.py): the same memory, shape and strides as the array
they borrow from, for single arrays and tuples of them, through every view the kernels take."""
from __future__ import annotations

import numpy as np
from numba import njit, prange

from css_ros.engine.cpu.borrowed import borrow, keep_alive


@njit
def _row_sums_through_views(a):
    """Row sums of ``a`` read through row views and slices of its borrowed copy; then 1 added through them."""
    b = borrow(a)
    out = np.zeros(a.shape[0])
    for i in range(b.shape[0]):
        row = b[i]
        for x in row[: row.shape[0] // 2]:
            out[i] += x
        for x in row[row.shape[0] // 2:]:
            out[i] += x
        row[:] += 1.0
    return out


@njit
def _scratch_in_the_kernel(n, reps):
    """Arrays allocated here, borrowed as a tuple, grown mid-loop, kept alive to the end; returns what the
    borrowed copies wrote, read back through the owned arrays."""
    owned = (np.zeros(4), np.zeros((2, 4), dtype=np.int64))
    a, b = borrow(owned)
    total = 0.0
    for r in range(reps):
        if r == reps // 2:          # grow: new owned arrays, then their borrowed copies
            owned = (np.zeros(n), np.zeros((2, n), dtype=np.int64))
            a, b = borrow(owned)
        for k in range(a.shape[0]):
            a[k] += 1.0
            b[1, k] += k
        total += a[a.shape[0] // 2 - 1:].sum()
    result = (owned[0].copy(), owned[1].copy(), total)
    keep_alive(owned)
    return result


@njit(parallel=True)
def _per_thread(arr, chunks):
    """Each chunk sums its borrowed rows of a shared argument and of a chunk-local array."""
    out = np.zeros(chunks)
    shared = borrow(arr)
    for ch in prange(chunks):
        local = np.full(3, ch + 1.0)
        mine = borrow(local)
        for i in range(ch, shared.shape[0], chunks):
            out[ch] += shared[i][0] + mine[1:][0]
        keep_alive(local)
    return out


def test_views_of_a_borrowed_array_read_and_write_the_original() -> None:
    a = np.arange(24, dtype=np.float64).reshape(4, 6)
    expected = a.sum(axis=1)
    np.testing.assert_array_equal(_row_sums_through_views(a), expected)
    np.testing.assert_array_equal(a, np.arange(24).reshape(4, 6) + 1.0)   # written through the borrowed copy


def test_a_borrowed_tuple_follows_its_owner_when_it_grows() -> None:
    first, second, total = _scratch_in_the_kernel(10, 6)
    np.testing.assert_array_equal(first, np.full(10, 3.0))            # the grown arrays took the last 3 passes
    np.testing.assert_array_equal(second, np.stack([np.zeros(10), 3.0 * np.arange(10)]))
    # a[k] counts the passes since the last allocation: passes 0-2 sum a[1:] (3 entries of 4), 3-5 a[4:] (6 of 10)
    assert total == sum(3 * (r + 1) for r in range(3)) + sum(6 * (r + 1) for r in range(3))


def test_borrowed_arrays_across_threads() -> None:
    arr = np.arange(40, dtype=np.float64).reshape(20, 2)
    out = _per_thread(arr, 2)
    np.testing.assert_array_equal(out, [arr[0::2, 0].sum() + 10 * 1.0, arr[1::2, 0].sum() + 10 * 2.0])
