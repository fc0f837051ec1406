"""Arrays kept from frame to frame by the CPU backend.

Fresh arrays of tens of MB are mapped anew by the allocator (above its reuse threshold, 32 MB with glibc) and
page-fault on every frame: on the 1.22 M Gaussian biker8 at 1280x720 the projected rows, the tile lists and the
attribute rows made about 63,000 minor faults a frame (250 MB), a fifth of a frame's time. A :class:`Kept` holds
them between frames; what is taken from it is valid until its next :meth:`Kept.take`.
"""
from __future__ import annotations

from typing import Callable, Hashable

import numpy as np

#: Extra capacity when a kept buffer grows: the visible count changes a little from frame to frame.
HEADROOM = 0.25


class Kept:
    """Arrays sharing a leading length, made by ``make(length, *key)`` and reused while they are long enough and
    ``key`` (e.g. the class count) is unchanged. Pages past what a frame writes are never touched, so the headroom
    costs address space, not memory. One per thread of use."""

    def __init__(self, make: Callable[..., tuple[np.ndarray, ...]]) -> None:
        self._make = make
        self._key: Hashable = None
        self._arrays: tuple[np.ndarray, ...] = ()

    def take(self, length: int, *key: Hashable) -> tuple[np.ndarray, ...]:
        """Views of the first ``length`` rows of each array (uninitialised or left from an earlier frame)."""
        if not self._arrays or self._arrays[0].shape[0] < length or key != self._key:
            self._arrays = self._make(length + int(length * HEADROOM), *key)
            self._key = key
        return tuple(a[:length] for a in self._arrays)
