"""The update's per-thread increments of the concentrations, and their addition into the map.

Each work chunk of the update kernel adds its votes for the M projected Gaussians into increments of its own. A
frame's votes reach few classes of a Gaussian: of the (chunk, Gaussian) pairs a vote reaches, 87 % get one class and
0.3 % three or more on the 500k room (28 classes), 62 % and 11 % on biker (20). So each pair has two slots, (class,
value), filled in the order the classes come; a third class of the pair goes to a dense Gaussian-major (M, C) float64
array, where the flush also sets a mark bit of its class (one bit of a uint8 per block of ``classes_per_mark(C)``
classes: one class per bit up to 8 classes). The slots of a chunk (24 bytes a Gaussian: 2.3 MB at the room's 98k
visible Gaussians) stay in the core's cache, where a dense row of 28 classes is 224 bytes, and the add reads the
slots and only the marked entries of the dense array, where it read and zeroed the dense arrays whole (2 x 22 MB on
the room, 2 x 160 MB on the 1.22 M Gaussian biker8 at 1280x720: 4.3 and 54 ms; benchmarks/README.md).
The marks are conservative (a marked entry may hold zero); an unmarked dense entry is always zero.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit, prange

from .composite import cttz
from .prefetch import prefetch_ahead
from ..kernel_cache import bind_sources

#: Bits of a mark (its dtype, uint8): blocks of classes a chunk's dense row can flag.
MARK_BITS = 8
#: (class, value) slots per chunk and Gaussian before a class goes to the dense row.
SLOTS = 2
#: The class of an empty slot.
EMPTY = -1


class Increments(NamedTuple):
    """A frame's per-chunk increments (:func:`~css_ros.engine.cpu.raster.accumulate_update`), for the ``ids`` rows
    of the concentrations; all zero (slots empty) again after :func:`add_increments`. A chunk's increment of
    Gaussian j and class c is the value of j's slot holding c, if any, plus acc[chunk, j, c]."""

    acc: np.ndarray       #: (chunks, M, C) float64: the classes that found no free slot
    base: np.ndarray      #: (chunks, M) float64 added to every class (a sensor model's common part), or (0, 0)
    marks: np.ndarray     #: (chunks, M) uint8: bit b set where acc's classes [b*k, (b+1)*k) may be non-zero
    slot_class: np.ndarray  #: (chunks, M, SLOTS) int32: a slot's class, EMPTY when free
    slot_value: np.ndarray  #: (chunks, M, SLOTS) float64: a slot's increment

    @classmethod
    def dense(cls, acc: np.ndarray, base: np.ndarray) -> "Increments":
        """Increments held whole in ``acc`` (every entry marked, slots empty): made outside the update kernel
        (tests, other producers)."""
        nchunks, m = acc.shape[:2]
        return cls(acc, base, np.full((nchunks, m), np.iinfo(np.uint8).max, dtype=np.uint8),
                   np.full((nchunks, m, SLOTS), EMPTY, dtype=np.int32), np.zeros((nchunks, m, SLOTS)))


@njit(inline="always")
def classes_per_mark(num_classes):  # pragma: no cover
    """Classes one bit of a mark stands for: 1 up to 8 classes, then blocks of ceil(C / 8)."""
    return max(1, (num_classes + MARK_BITS - 1) // MARK_BITS)


@njit(inline="always")
def class_mark(c, per_mark):  # pragma: no cover
    """The mark bit of class ``c`` (:func:`classes_per_mark` classes a bit)."""
    return np.uint64(1) << np.uint64(c // per_mark)


@njit(inline="always")
def add_to(slot_class, slot_value, acc, marks, j, c, value, per_mark):  # pragma: no cover
    """One chunk's increment of Gaussian j, class c += value: into j's slot of class c, or a free one, else into
    the dense row (marked). ``slot_class``, ``slot_value``, ``acc``, ``marks``: the chunk's (M, ...) arrays."""
    sc = slot_class[j]
    for s in range(SLOTS):
        held = sc[s]
        if held == c:
            slot_value[j, s] += value
            return
        if held == EMPTY:
            sc[s] = c
            slot_value[j, s] = value
            return
    acc[j, c] += value
    marks[j] |= class_mark(c, per_mark)


class UpdateWorkspace:
    """The update's per-thread increments, kept from frame to frame: fresh arrays of tens of MB page-fault on every
    frame (~6 ms for the 45 MB of two threads at 141k visible Gaussians and 20 classes). They are zero (slots empty)
    between updates: :func:`add_increments` clears what it reads; one handed out and not given back by :meth:`done`
    (an exception between the two) is cleared whole before its next use. One per thread of use."""

    def __init__(self) -> None:
        self._acc = np.zeros(0)
        self._base = np.zeros(0)
        self._marks = np.zeros(0, dtype=np.uint8)
        self._slot_class = np.full(0, EMPTY, dtype=np.int32)
        self._slot_value = np.zeros(0)
        self._pending = False

    def take(self, nchunks: int, num_classes: int, m: int, with_base: bool) -> Increments:
        """Zero increments for ``nchunks`` chunks, ``m`` Gaussians and ``num_classes`` classes (base (0, 0) unless
        ``with_base``)."""
        if self._pending:
            self._acc[:] = 0.0
            self._base[:] = 0.0
            self._marks[:] = 0
            self._slot_class[:] = EMPTY
        size = nchunks * num_classes * m
        if self._acc.size < size:
            self._acc = np.zeros(size)
        if with_base and self._base.size < nchunks * m:
            self._base = np.zeros(nchunks * m)
        if self._marks.size < nchunks * m:
            self._marks = np.zeros(nchunks * m, dtype=np.uint8)
            self._slot_class = np.full(nchunks * m * SLOTS, EMPTY, dtype=np.int32)
            self._slot_value = np.zeros(nchunks * m * SLOTS)
        self._pending = True
        base = self._base[:nchunks * m].reshape(nchunks, m) if with_base else _NO_BASE
        pairs = nchunks * m * SLOTS
        return Increments(self._acc[:size].reshape(nchunks, m, num_classes), base,
                          self._marks[:nchunks * m].reshape(nchunks, m),
                          self._slot_class[:pairs].reshape(nchunks, m, SLOTS),
                          self._slot_value[:pairs].reshape(nchunks, m, SLOTS))

    def done(self) -> None:
        """The increments handed out are zero again (:func:`add_increments` ran)."""
        self._pending = False


_NO_BASE = np.zeros((0, 0))


@njit(inline="always")
def add_increment_row(concentrations, row, j, acc, acc_base, marks, slot_class, slot_value, decay,
                      prior):  # pragma: no cover
    """Row ``row`` of the concentrations += the chunks' increments of projected Gaussian j (:func:`add_increments`):
    the slots, then the marked dense entries, each read once and cleared; only their classes of the row are written,
    unless a common part or the decay touches every class. The order of the additions is fixed (chunk by chunk,
    slots before the dense row), so a frame's result does not depend on the threads' timing."""
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
        for ch in range(nch):
            for s in range(SLOTS):
                received |= slot_class[ch, j, s] != EMPTY and slot_value[ch, j, s] != 0.0
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
    for ch in range(nch):
        for s in range(SLOTS):
            c = slot_class[ch, j, s]
            if c == EMPTY:
                break   # slots fill in order
            concentrations[row, c] += slot_value[ch, j, s]
            slot_class[ch, j, s] = EMPTY
    if union == 0:
        return
    every = (np.uint64(1) << np.uint64((num_classes - 1) // per_mark + 1)) - np.uint64(1)
    for ch in range(nch):
        mark = np.uint64(marks[ch, j])
        if mark == 0:
            continue   # not read: an unmarked chunk's row is other cache lines
        if mark == every:   # a whole row (a confusion model's votes): one pass
            for c in range(num_classes):
                concentrations[row, c] += acc[ch, j, c]
                acc[ch, j, c] = 0.0
        while mark != every and mark != 0:   # the marked blocks of classes (a branch per set bit only)
            b = cttz(mark)
            mark &= mark - np.uint64(1)
            c0 = np.int64(b) * per_mark
            for c in range(c0, min(num_classes, c0 + per_mark)):
                concentrations[row, c] += acc[ch, j, c]
                acc[ch, j, c] = 0.0
        marks[ch, j] = 0


@njit(parallel=True, cache=True)
def _add_kernel(concentrations, ids, acc, acc_base, marks, slot_class, slot_value, decay, prior):  # pragma: no cover
    for j in prange(acc.shape[1]):
        prefetch_ahead(concentrations, ids, j)
        add_increment_row(concentrations, ids[j], j, acc, acc_base, marks, slot_class, slot_value, decay, prior)


def add_increments(concentrations: np.ndarray, ids: np.ndarray, inc: Increments, decay: float = 1.0,
                   prior: float = 1.0) -> None:
    """concentrations[ids[j], c] += the increments of Gaussian j and class c of every chunk (+ base[chunk, j] for
    every class when base is not empty) (ids are unique); the increments are left zero (:class:`UpdateWorkspace`).
    With ``decay`` < 1 (forgetting, :mod:`css_ros.engine.change_rules`), a row whose increment is non-zero in some
    class is first set to prior + (alpha - prior) * decay."""
    _add_kernel(concentrations, ids, inc.acc, inc.base, inc.marks, inc.slot_class, inc.slot_value, float(decay),
                float(prior))


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
