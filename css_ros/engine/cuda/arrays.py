"""Device array helpers: one small set of array operations that runs on a GPU (torch.cuda, or cupy)
and, under the numba-cuda simulator, on host numpy arrays.

The kernels only need arrays they can index; the device-wide steps between kernels (stable sorts,
prefix sums, compaction, searchsorted) come from the array library. Every array the backend keeps is
an array of that library: numpy in the simulator; a torch CUDA tensor (or cupy array) on a GPU, which
numba kernels read and write in place through ``__cuda_array_interface__`` (no copies).
"""
from __future__ import annotations

import os
import weakref
from typing import Any

import numpy as np

from ...errors import CssError


def simulator_enabled() -> bool:
    """True when numba-cuda runs kernels in its CPU simulator (``NUMBA_ENABLE_CUDASIM=1``)."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0")


def import_cuda() -> Any:
    """Import ``numba.cuda`` and check that kernels can run (a GPU, or the simulator).

    Raises:
        CssError: numba-cuda is not installed, or there is neither a CUDA GPU nor the simulator.
    """
    try:
        from numba import cuda
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise CssError("backend 'cuda' needs numba-cuda: pip install -e '.[cuda]' "
                       f"(on a machine with an NVIDIA GPU), or NUMBA_ENABLE_CUDASIM=1 to simulate ({exc})") from exc
    if getattr(cuda, "simulator", None) is None and not hasattr(cuda, "is_available"):  # pragma: no cover
        raise CssError("numba.cuda is not the numba-cuda package; pip install -e '.[cuda]'")
    try:
        available = cuda.is_available()
    except Exception:  # pragma: no cover - driver errors
        available = False
    if not available:
        raise CssError("backend 'cuda': no CUDA GPU found (numba.cuda.is_available() is False); "
                       "set NUMBA_ENABLE_CUDASIM=1 to run the kernels in the (slow) simulator")
    return cuda


class NumpyOps:
    """Array operations over a numpy-like module: numpy (simulator) or cupy (GPU)."""

    def __init__(self, xp: Any = np, device: int | None = None) -> None:
        self.xp = xp
        self.name = xp.__name__
        self.device = device

    def empty(self, shape: Any, dtype: Any) -> Any:
        return self.xp.empty(shape, dtype=dtype)

    def zeros(self, shape: Any, dtype: Any) -> Any:
        return self.xp.zeros(shape, dtype=dtype)

    def arange(self, n: int, dtype: Any = np.int64) -> Any:
        return self.xp.arange(n, dtype=dtype)

    def upload(self, host: np.ndarray, dtype: Any = None) -> Any:
        """Host array -> contiguous device array (of ``dtype`` if given)."""
        a = np.ascontiguousarray(host if dtype is None else np.asarray(host, dtype=dtype))
        return self.xp.asarray(a)

    def copy_into(self, dst: Any, host: np.ndarray) -> None:
        """dst[...] = host (host -> device, same shape)."""
        dst[...] = self.xp.asarray(np.ascontiguousarray(host, dtype=dst.dtype))

    def upload_frame(self, name: str, host: np.ndarray, dtype: Any) -> Any:
        """Per-frame input (labels, weights); pinned and asynchronous on torch (see TorchOps)."""
        return self.upload(host, dtype)

    def download_frame(self, name: str, dev: Any) -> np.ndarray:
        """The frame's result (one synchronising copy on a GPU)."""
        return np.array(self.download(dev))

    def download(self, dev: Any) -> np.ndarray:
        """Device array -> host numpy array (a copy on a GPU)."""
        get = getattr(dev, "get", None)
        return np.asarray(get() if get is not None and self.xp is not np else dev)

    def view_as(self, dev: Any, dtype: Any) -> Any:
        """The same memory as another dtype (1-D), as a kernel argument. Under the simulator a host array passed
        to a kernel is copied in and written back after it, so views of one buffer passed together would
        overwrite each other's writes: they go in as the simulator's device arrays instead (no copies)."""
        view = dev.view(dtype)
        if self.xp is np and simulator_enabled():
            from numba.cuda.simulator.cudadrv.devicearray import FakeCUDAArray

            return FakeCUDAArray(view)
        return view

    def zero_words(self, dev: Any, n: int) -> None:
        """dev[:n] = 0 (the output buffer's header)."""
        dev[:n] = 0

    def copy_words(self, dev: Any, offset: int, src: Any) -> None:
        """dev[offset:...] = the int32 words of ``src`` (device to device, no synchronisation)."""
        words = src.view(np.int32).reshape(-1)
        dev[offset:offset + words.shape[0]] = words

    def download_words(self, dev: Any, n: int) -> np.ndarray:
        """A fresh host copy of dev[:n] (the frame's one copy): the caller's images are views into it."""
        return np.array(self.download(dev[:n]))

    def argsort_stable(self, x: Any) -> Any:
        return self.xp.argsort(x, kind="stable")

    def sort(self, x: Any) -> Any:
        return self.xp.sort(x)

    def sort_stable(self, x: Any) -> tuple[Any, Any]:
        """(sorted x, the permutation), stable."""
        perm = self.xp.argsort(x, kind="stable")
        return x[perm], perm

    def copy(self, x: Any) -> Any:
        """A new device array with x's values (a slice's copy no longer holds its base's memory)."""
        return x.copy()

    # ---- into preallocated outputs (the single-view plan's buffers keep their addresses frame to frame)
    def fill(self, dev: Any, value: Any) -> None:
        """dev[...] = value."""
        dev[...] = value

    def sort_into(self, x: Any, values: Any, indices: Any) -> None:
        """values, indices = the stable sort of x and its permutation (int64)."""
        perm = self.xp.argsort(x, kind="stable")
        indices[...] = perm
        values[...] = x[perm]

    def take_into(self, x: Any, index: Any, out: Any) -> None:
        """out = x[index] (1-D)."""
        out[...] = x[index]

    def cumsum_into(self, x: Any, out: Any) -> None:
        """out (int64) = the inclusive prefix sum of x."""
        self.xp.cumsum(x, dtype=np.int64, out=out)

    def searchsorted_into(self, sorted_values: Any, values: Any, out: Any) -> None:
        out[...] = self.xp.searchsorted(sorted_values, values)

    def host_to_device(self, dev: Any, host: np.ndarray, name: str) -> None:
        """dev[...] = host (same shape and dtype; asynchronous through a pinned buffer on torch)."""
        dev[...] = host

    def scalars(self, *xs: Any) -> list[int]:
        """Several one-element device values -> Python ints in one transfer."""
        return [int(v) for v in self.download(self.xp.stack([self.xp.asarray(x) for x in xs]))]

    def cumsum(self, x: Any) -> Any:
        """Inclusive prefix sum, int64."""
        return self.xp.cumsum(x, dtype=np.int64)

    def searchsorted(self, sorted_values: Any, values: Any) -> Any:
        return self.xp.searchsorted(sorted_values, values)

    def nonzero(self, mask: Any) -> Any:
        return self.xp.flatnonzero(mask)

    def scalar(self, x: Any) -> int:
        """One element -> Python int (a device-to-host synchronisation on a GPU)."""
        return int(x)

    def kernel_arg(self, x: Any) -> Any:
        return x

    def kernel_array(self, x: Any) -> Any:
        """A long-lived array as a kernel argument (converted once); the array itself here."""
        return x

    def synchronize(self) -> None:
        if self.xp is not np:  # pragma: no cover - GPU only
            self.xp.cuda.Device().synchronize()


class _HostWords:
    """Owner of a frame's host copy: every numpy view of it refers to this object (its ``base``), so the copy's
    pinned buffer is free for reuse exactly when this object is garbage."""

    def __init__(self, storage: Any, words: np.ndarray) -> None:
        self.storage = storage  # keeps the page-locked memory alive as long as a view of it exists
        self.__array_interface__ = dict(words.__array_interface__)


class TorchOps:  # pragma: no cover - needs a CUDA build of torch and a GPU
    """Array operations over torch CUDA tensors (device-wide radix sort and scan)."""

    _DTYPES = {np.dtype(np.float64): "float64", np.dtype(np.float32): "float32", np.dtype(np.int64): "int64",
               np.dtype(np.int32): "int32", np.dtype(np.uint16): "uint16", np.dtype(np.uint8): "uint8",
               np.dtype(np.bool_): "bool"}

    def __init__(self, device: int | None = None) -> None:
        import torch

        self.torch = torch
        self.name = "torch"
        self.device = torch.device("cuda", 0 if device is None else int(device))
        self._pinned_cache: dict[tuple, Any] = {}
        self._word_pool: list[list[Any]] = []  # [pinned int32 buffer, weakref to the array handed out or None]
        #: page-locked buffers allocated for frame outputs so far (constant once warm unless views are kept)
        self.pinned_allocations = 0

    def _dt(self, dtype: Any) -> Any:
        return getattr(self.torch, self._DTYPES[np.dtype(dtype)])

    def empty(self, shape: Any, dtype: Any) -> Any:
        return self.torch.empty(shape, dtype=self._dt(dtype), device=self.device)

    def zeros(self, shape: Any, dtype: Any) -> Any:
        return self.torch.zeros(shape, dtype=self._dt(dtype), device=self.device)

    def arange(self, n: int, dtype: Any = np.int64) -> Any:
        return self.torch.arange(n, dtype=self._dt(dtype), device=self.device)

    def upload(self, host: np.ndarray, dtype: Any = None) -> Any:
        a = np.ascontiguousarray(host if dtype is None else np.asarray(host, dtype=dtype))
        return self.torch.from_numpy(a).to(self.device)

    def _pinned(self, name: str, shape: tuple, dtype: Any) -> Any:
        """A page-locked host buffer kept per (name, shape, dtype): DMA without a staging copy."""
        key = (name, tuple(shape), np.dtype(dtype))
        buf = self._pinned_cache.get(key)
        if buf is None:
            buf = self.torch.empty(tuple(shape), dtype=self._dt(dtype)).pin_memory()
            self._pinned_cache[key] = buf
        return buf

    def upload_frame(self, name: str, host: np.ndarray, dtype: Any) -> Any:
        """Per-frame input (labels, weights) through a pinned buffer, copied asynchronously (the
        frame's final download synchronises, so the buffer is free again by the next frame)."""
        buf = self._pinned(name, host.shape, dtype)
        buf.numpy()[...] = host
        return buf.to(self.device, non_blocking=True)

    def download_frame(self, name: str, dev: Any) -> np.ndarray:
        """The frame's result through a pinned buffer: one synchronising copy, returned as a fresh array."""
        buf = self._pinned(name, tuple(dev.shape), self._np_dtype(dev.dtype))
        buf.copy_(dev, non_blocking=True)
        self.torch.cuda.current_stream(self.device).synchronize()
        return buf.numpy().copy()

    def _np_dtype(self, tdtype: Any) -> Any:
        return next(k for k, v in self._DTYPES.items() if getattr(self.torch, v) == tdtype)

    def copy_into(self, dst: Any, host: np.ndarray) -> None:
        dst.copy_(self.torch.from_numpy(np.ascontiguousarray(host)).to(dst.dtype))

    def view_as(self, dev: Any, dtype: Any) -> Any:
        return self.kernel_array(dev.view(self._dt(dtype)))

    def zero_words(self, dev: Any, n: int) -> None:
        dev[:n].zero_()

    def copy_words(self, dev: Any, offset: int, src: Any) -> None:
        """dev[offset:...] = the int32 words of ``src`` (an asynchronous device-to-device copy)."""
        words = src.view(self.torch.int32).reshape(-1)
        dev[offset:offset + words.shape[0]].copy_(words, non_blocking=True)

    def download_words(self, dev: Any, n: int) -> np.ndarray:
        """dev[:n] into a page-locked host buffer in one asynchronous copy and one synchronisation; the returned
        array (the caller's images are views into it) owns that buffer until it is garbage: the pool hands a
        buffer out again only when no array of an earlier frame still refers to it, so a view stays valid after
        later frames and a caller that drops its views causes no allocation once warm."""
        buf = None
        for entry in self._word_pool:
            if entry[1] is None or entry[1]() is None:
                if int(entry[0].shape[0]) >= n:
                    buf = entry
                    break
        if buf is None:
            buf = [self.torch.empty(max(n, 1), dtype=self.torch.int32).pin_memory(), None]
            self._word_pool.append(buf)
            self.pinned_allocations += 1
        buf[0][:n].copy_(dev[:n], non_blocking=True)
        self.torch.cuda.current_stream(self.device).synchronize()
        owner = _HostWords(buf[0], buf[0].numpy()[:n])
        buf[1] = weakref.ref(owner)
        return np.asarray(owner)

    def download(self, dev: Any) -> np.ndarray:
        return dev.cpu().numpy()

    def argsort_stable(self, x: Any) -> Any:
        return self.torch.sort(x, stable=True).indices

    def sort(self, x: Any) -> Any:
        return self.torch.sort(x).values

    def sort_stable(self, x: Any) -> tuple[Any, Any]:
        res = self.torch.sort(x, stable=True)  # device-wide radix sort (CUB) for integer keys
        return res.values, res.indices

    def fill(self, dev: Any, value: Any) -> None:
        dev.fill_(value)

    def copy(self, x: Any) -> Any:
        return x.clone()

    def sort_into(self, x: Any, values: Any, indices: Any) -> None:
        self.torch.sort(x, stable=True, out=(values, indices))

    def take_into(self, x: Any, index: Any, out: Any) -> None:
        self.torch.index_select(x, 0, index, out=out)

    def cumsum_into(self, x: Any, out: Any) -> None:
        self.torch.cumsum(x, 0, dtype=self.torch.int64, out=out)

    def searchsorted_into(self, sorted_values: Any, values: Any, out: Any) -> None:
        self.torch.searchsorted(sorted_values, values, out=out)

    def host_to_device(self, dev: Any, host: np.ndarray, name: str) -> None:
        """dev[...] = host through a page-locked buffer kept per (name, shape, dtype), asynchronously (the frame's
        final download synchronises, so the buffer is free again by the next frame)."""
        buf = self._pinned(name, host.shape, host.dtype)
        buf.numpy()[...] = host
        dev.copy_(buf, non_blocking=True)

    def scalars(self, *xs: Any) -> list[int]:
        return [int(v) for v in self.torch.stack([x.reshape(()) for x in xs]).cpu().tolist()]

    def cumsum(self, x: Any) -> Any:
        return self.torch.cumsum(x, 0, dtype=self.torch.int64)

    def searchsorted(self, sorted_values: Any, values: Any) -> Any:
        return self.torch.searchsorted(sorted_values, values)

    def nonzero(self, mask: Any) -> Any:
        return self.torch.nonzero(mask.reshape(-1)).reshape(-1)

    def scalar(self, x: Any) -> int:
        return int(x.item()) if hasattr(x, "item") else int(x)

    def kernel_arg(self, x: Any) -> Any:
        return x  # torch CUDA tensors expose __cuda_array_interface__

    def kernel_array(self, x: Any) -> Any:
        """A numba device array viewing tensor ``x`` (no copy; it keeps ``x`` alive), made once: a launch then
        passes it without converting ``__cuda_array_interface__`` again."""
        from numba import cuda

        return cuda.as_cuda_array(x)

    def synchronize(self) -> None:
        self.torch.cuda.synchronize(self.device)


def make_ops(device: int | None = None) -> "NumpyOps | TorchOps":
    """The array operations for this process: numpy under the simulator, else torch.cuda, else cupy.

    Raises:
        CssError: on a GPU machine with neither a CUDA build of torch nor cupy.
    """
    if simulator_enabled():
        return NumpyOps(np, device)
    try:  # pragma: no cover - GPU only
        import torch

        if torch.cuda.is_available():
            return TorchOps(device)
    except ImportError:  # pragma: no cover
        pass
    try:  # pragma: no cover - GPU only
        import cupy

        if device is not None:
            cupy.cuda.Device(int(device)).use()
        return NumpyOps(cupy, device)
    except ImportError:  # pragma: no cover
        raise CssError("backend 'cuda' needs a CUDA build of torch (torch.cuda.is_available()) or cupy "
                       "for its device-wide sorts and scans; see docs/cuda.md") from None
