"""Warp intrinsics for numba-cuda's simulator, which has none (``shfl_*_sync``, ``ballot_sync``,
``all_sync`` are missing from it; the real ones compile to ``shfl.sync`` / ``vote.sync`` on a GPU).

Each intrinsic is an exchange within the warp (32 consecutive linear thread ids): every lane posts
its value, waits at its warp's barrier, reads the warp's values, waits again. That is exactly the
full-mask semantics the kernels use, provided all 32 lanes reach the call, which the kernels
guarantee (their warp calls sit in warp-uniform control flow). Installed by :mod:`.kernels` only when the simulator is on.
"""
from __future__ import annotations

import threading
from typing import Any

import numpy as np

WARP = 32
_LOCK = threading.Lock()
_TIMEOUT_S = 120.0  # a lane that never arrives (an exception in another lane) breaks the barrier


def _warp_values(value: Any) -> tuple[int, list[Any]]:
    """(lane, the values posted by the calling thread's warp) after an exchange within the warp
    (two waits on a 32-thread barrier of that warp: other warps of the block are not involved, as
    on a GPU where a warp-uniform branch may skip the call in other warps)."""
    thread = threading.current_thread()
    manager = thread._manager  # type: ignore[attr-defined]
    tid = thread.thread_id  # type: ignore[attr-defined]
    base = tid - tid % WARP
    with _LOCK:
        warps = manager.__dict__.setdefault("_css_warps", {})
        if base not in warps:
            size = min(WARP, int(np.prod(manager._block_dim)) - base)
            warps[base] = (threading.Barrier(size, timeout=_TIMEOUT_S), {})
        barrier, store = warps[base]
    store[tid - base] = value
    barrier.wait()
    values = [store[lane] for lane in range(len(store))]
    barrier.wait()
    return tid - base, values


def shfl_sync(mask: int, value: Any, src_lane: int) -> Any:
    return _warp_values(value)[1][int(src_lane) % WARP]


def shfl_xor_sync(mask: int, value: Any, lane_mask: int) -> Any:
    lane, values = _warp_values(value)
    return values[(lane ^ int(lane_mask)) % WARP]


def shfl_down_sync(mask: int, value: Any, delta: int) -> Any:
    lane, values = _warp_values(value)
    src = lane + int(delta)
    return values[src] if src < WARP else value


def ballot_sync(mask: int, predicate: Any) -> int:
    _, values = _warp_values(bool(predicate))
    return sum(1 << lane for lane, p in enumerate(values) if p)


def all_sync(mask: int, predicate: Any) -> bool:
    return all(_warp_values(bool(predicate))[1])


def any_sync(mask: int, predicate: Any) -> bool:
    return any(_warp_values(bool(predicate))[1])


def warp_xor_sum(x: Any) -> Any:
    """``kernels.warp_sum`` in one exchange instead of five: the same xor butterfly (offsets 16, 8, 4, 2, 1,
    ``v[l] + v[l ^ off]`` in the values' own type), evaluated on the 32 posted values, so every lane gets
    the bit-identical sum that the five shuffles give."""
    lane, values = _warp_values(x)
    size = len(values)
    off = WARP // 2
    while off > 0:
        values = [values[i] + values[(i ^ off) % size] for i in range(size)]
        off //= 2
    return values[lane]


def install() -> None:
    """Add the missing warp intrinsics to the simulator's fake ``cuda`` module, and make its shared arrays one per
    block and line even when the block's threads reach the line together (idempotent)."""
    from numba.cuda.simulator.kernelapi import FakeCUDAModule, FakeCUDAShared

    for fn in (shfl_sync, shfl_xor_sync, shfl_down_sync, ballot_sync, all_sync, any_sync):
        if not hasattr(FakeCUDAModule, fn.__name__):
            setattr(FakeCUDAModule, fn.__name__, staticmethod(fn))
    if not getattr(FakeCUDAShared, "_css_locked", False):
        FakeCUDAShared.array = _locked_shared_array(FakeCUDAShared.array)  # type: ignore[method-assign]
        FakeCUDAShared._css_locked = True  # type: ignore[attr-defined]


def _locked_shared_array(make: Any) -> Any:
    """The simulator's ``cuda.shared.array`` under one lock: it looks a block's array up by the calling line and
    makes it when missing, without a lock, so threads released together by a barrier could each make their own
    array and never see each other's writes (seen as garbage staged rows under load). The lookup is by the caller's
    frame, which this wrapper adds to the stack: the wrapped call sees its caller one frame further up, so the
    wrapper passes through the same key the original would compute."""
    import sys
    import traceback

    lock = threading.Lock()

    def array(self: Any, shape: Any, dtype: Any, alignment: Any = None) -> Any:
        if shape == 0 or alignment is not None:
            return make(self, shape, dtype, alignment)
        from numba.cuda import types  # what the simulator's own array() uses
        from numba.cuda.np import numpy_support

        if isinstance(dtype, types.Type):  # type: ignore[attr-defined]
            dtype = numpy_support.as_dtype(dtype)
        caller = traceback.extract_stack(sys._getframe(1), limit=1)[-1][0:2]
        with lock:
            res = self._allocations.get(caller)
            if res is None:
                res = self._allocations[caller] = np.empty(shape, dtype)
        return res
    return array
