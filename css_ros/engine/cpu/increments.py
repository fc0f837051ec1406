"""The update's per-thread increments of the concentrations, and their addition into the map.

Each work chunk of the update kernel adds its votes into a Gaussian-major (M, C) float64 array of its own, for the M
projected Gaussians. A frame's votes reach few of those entries: about 1.1 classes of a row on the 500k room (28
classes), 1.5 on biker (20), and a row can be reached by one chunk only. Reading and zeroing every chunk's whole
array (2 x 22 MB on the room, 2 x 160 MB on the 1.22 M Gaussian biker8 at 1280x720) cost more than the votes' own
part of the update; so the flush marks, per chunk and Gaussian, the classes it wrote (one bit of a uint64 per block
of ``classes_per_mark(C)`` classes: one class per bit up to 64 classes), and the add reads and zeroes only marked
entries. The marks are conservative (a marked entry may hold zero); an unmarked entry is always zero.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .composite import cttz
from .prefetch import prefetch_ahead
from ..kernel_cache import bind_sources

#: Bits of a mark word: blocks of classes a chunk's row can flag.
MARK_BITS = 8


class Increments(NamedTuple):
    """A frame's per-chunk increments (:func:`~css_ros.engine.cpu.raster.accumulate_update`), for the ``ids`` rows
    of the concentrations; all zero again after :func:`add_increments`."""

    acc: np.ndarray    #: (chunks, M, C) float64: sum of kappa * weight of the chunk's votes per Gaussian and class
    base: np.ndarray   #: (chunks, M) float64 added to every class (a sensor model's common part), or (0, 0)
    marks: np.ndarray  #: (chunks, M) uint64: bit b set where classes [b*k, (b+1)*k) may be non-zero, k = classes_per_mark


@njit(inline="always")
def classes_per_mark(num_classes):  # pragma: no cover
    """Classes one bit of a mark word stands for: 1 up to 64 classes, then blocks of ceil(C / 64)."""
    return max(1, (num_classes + MARK_BITS - 1) // MARK_BITS)


@njit(inline="always")
def class_mark(c, per_mark):  # pragma: no cover
    """The mark bit of class ``c`` (:func:`classes_per_mark` classes a bit)."""
    return np.uint64(1) << np.uint64(c // per_mark)


def all_marked(nchunks: int, m: int) -> np.ndarray:
    """Marks that flag every entry: increments made outside the update kernel (tests, other producers) are added
    whole."""
    return np.full((nchunks, m), np.iinfo(np.uint8).max, dtype=np.uint8)


class UpdateWorkspace:
    """The update's per-thread accumulators, kept from frame to frame: fresh arrays of tens of MB page-fault on
    every frame (~6 ms for the 45 MB of two threads at 141k visible Gaussians and 20 classes). They are zero between
    updates: :func:`add_increments` zeroes what it reads; one handed out and not given back by :meth:`done` (an
    exception between the two) is zeroed before its next use. One per thread of use."""

    def __init__(self) -> None:
        self._acc = np.zeros(0)
        self._base = np.zeros(0)
        self._marks = np.zeros(0, dtype=np.uint8)
        self._pending = False

    def take(self, nchunks: int, num_classes: int, m: int, with_base: bool) -> Increments:
        """Zero (nchunks, m, num_classes) and (nchunks, m) (or (0, 0)) float64 accumulators, and zero marks."""
        if self._pending:
            self._acc[:] = 0.0
            self._base[:] = 0.0
            self._marks[:] = 0
        size = nchunks * num_classes * m
        if self._acc.size < size:
            self._acc = np.zeros(size)
        if with_base and self._base.size < nchunks * m:
            self._base = np.zeros(nchunks * m)
        if self._marks.size < nchunks * m:
            self._marks = np.zeros(nchunks * m, dtype=np.uint8)
        self._pending = True
        base = self._base[:nchunks * m].reshape(nchunks, m) if with_base else _NO_BASE
        return Increments(self._acc[:size].reshape(nchunks, m, num_classes), base,
                          self._marks[:nchunks * m].reshape(nchunks, m))

    def done(self) -> None:
        """The accumulators handed out are zero again (:func:`add_increments` ran)."""
        self._pending = False


_NO_BASE = np.zeros((0, 0))


@njit(inline="always")
def add_increment_row(concentrations, row, j, acc, acc_base, marks, decay, prior):  # pragma: no cover
    """Row ``row`` of the concentrations += the chunks' increments of projected Gaussian j (:func:`add_increments`):
    only the marked entries are read (and zeroed), and only their classes of the row written, unless a common part
    or the decay touches every class."""
    num_classes = acc.shape[2]
    nch = acc.shape[0]
    per_mark = classes_per_mark(num_classes)
    common = 0.0
    if acc_base.shape[0] > 0:
        for ch in range(acc_base.shape[0]):
            common += acc_base[ch, j]
            acc_base[ch, j] = 0.0
    union = np.uint64(0)
    for ch in range(nch):
        union |= np.uint64(marks[ch, j])
    if decay != 1.0:
        received = common != 0.0
        for c in range(num_classes):
            if union & class_mark(c, per_mark):
                for ch in range(nch):
                    received |= acc[ch, j, c] != 0.0
        if received:
            for c in range(num_classes):
                concentrations[row, c] = prior + (concentrations[row, c] - prior) * decay
    if common != 0.0:
        for c in range(num_classes):
            concentrations[row, c] += common
    while union != 0:   # the marked blocks of classes (a bit mask is mostly empty: branch per set bit only)
        b = cttz(union)
        bit = np.uint64(1) << b
        union &= ~bit
        b = np.int64(b)
        c0 = b * per_mark
        for c in range(c0, min(num_classes, c0 + per_mark)):
            total = 0.0
            for ch in range(nch):
                if marks[ch, j] & bit:   # not read otherwise: an unmarked chunk's entry is another cache line
                    total += acc[ch, j, c]
                    acc[ch, j, c] = 0.0
            concentrations[row, c] += total
    for ch in range(nch):
        marks[ch, j] = 0


@njit(parallel=True, cache=True)
def _add_kernel(concentrations, ids, acc, acc_base, marks, decay, prior):  # pragma: no cover
    for j in prange(acc.shape[1]):
        prefetch_ahead(concentrations, ids, j)
        add_increment_row(concentrations, ids[j], j, acc, acc_base, marks, decay, prior)


def add_increments(concentrations: np.ndarray, ids: np.ndarray, inc: Increments, decay: float = 1.0,
                   prior: float = 1.0) -> None:
    """concentrations[ids[j], c] += sum over chunks of acc[chunk, j, c] (+ base[chunk, j] for every class when base
    is not empty) (ids are unique); the increments are left zero (:class:`UpdateWorkspace`). With ``decay`` < 1
    (forgetting, :mod:`css_ros.engine.change_rules`), a row whose increment is non-zero in some class is first set
    to prior + (alpha - prior) * decay."""
    _add_kernel(concentrations, ids, inc.acc, inc.base, inc.marks, float(decay), float(prior))


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
