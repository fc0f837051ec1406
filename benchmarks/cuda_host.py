"""Host time of the CUDA backend per observe and per query render, measured on the CPU with a stub device.

The stub device keeps the backend's Python exactly as it runs on a GPU (SemanticMap.observe, the label checks, the
single-view plan, the bound launches, the output layout and the view's images) and replaces what the GPU does by
nothing: arrays are shape-only placeholders, kernels record their launches, the view's copy hands back a host buffer
of the right size (its header says the frame fitted). What it measures is therefore the host's own work per frame,
the part the device cannot hide, plus a count of launches, host -> device copies and synchronisations. What it
leaves out: the driver's cost per launch and per copy (a few microseconds each on a GPU, cuda.core's launch call)
and the array library's per-call overhead (torch's dispatcher, ~5-10 µs per call): the counts below say how many of
those a frame makes.

    python benchmarks/cuda_host.py --scene 1M            # the 1M KITTI-like scene (1241 x 376, 19 classes)
    python benchmarks/cuda_host.py --scene 100k --scene biker --frames 200

Runs with NUMBA_ENABLE_CUDASIM=1 set by itself (only to import numba.cuda without a GPU: no kernel runs).
"""
from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


class StubArray:
    """A device array of the stub device: shape and dtype only."""

    def __init__(self, shape: Any, dtype: Any) -> None:
        self.shape = (int(shape),) if np.isscalar(shape) else tuple(int(s) for s in shape)
        self.dtype = np.dtype(dtype)

    def view(self, dtype: Any) -> "StubArray":
        dtype = np.dtype(dtype)
        last = self.shape[-1] * self.dtype.itemsize // dtype.itemsize if self.shape else 1
        return StubArray(self.shape[:-1] + (last,), dtype)

    def reshape(self, *shape: Any) -> "StubArray":
        return StubArray(shape[0] if len(shape) == 1 else shape, self.dtype)

    def __getitem__(self, idx: Any) -> "StubArray":
        return StubArray(np.empty(self.shape, dtype=np.bool_)[idx].shape if self.shape else (), self.dtype)


class StubOps:
    """The array operations of the stub device. ``calls`` counts them by name; host -> device copies still copy
    into a host buffer (the real path copies into a page-locked one), the view's copy returns a reused buffer whose
    header says the frame fitted."""

    name = "stub"

    def __init__(self) -> None:
        self.calls: dict[str, int] = {}
        self._pinned: dict[tuple, np.ndarray] = {}
        self._words: np.ndarray = np.zeros(0, dtype=np.int32)

    def _count(self, name: str) -> None:
        self.calls[name] = self.calls.get(name, 0) + 1

    def empty(self, shape: Any, dtype: Any) -> StubArray:
        self._count("alloc")
        return StubArray(shape, dtype)

    zeros = empty

    def arange(self, n: int, dtype: Any = np.int64) -> StubArray:
        self._count("alloc")
        return StubArray(n, dtype)

    def upload(self, host: np.ndarray, dtype: Any = None) -> StubArray:
        self._count("upload")
        host = np.asarray(host)
        return StubArray(host.shape, host.dtype if dtype is None else dtype)

    def host_to_device(self, dev: Any, host: np.ndarray, name: str) -> None:
        self._count("host_to_device")
        key = (name, host.shape, host.dtype.str)
        buf = self._pinned.get(key)
        if buf is None:
            buf = self._pinned[key] = np.empty_like(host)
        buf[...] = host   # the host's share of the copy: into the page-locked staging buffer

    def kernel_array(self, x: Any) -> Any:
        return x

    def view_as(self, dev: Any, dtype: Any) -> Any:
        return dev.view(dtype)

    def download(self, dev: Any) -> np.ndarray:
        self._count("download")
        return np.zeros(dev.shape, dtype=dev.dtype)

    def download_words(self, dev: Any, n: int) -> np.ndarray:
        self._count("download_words")
        if self._words.shape[0] < n:
            self._words = np.zeros(n, dtype=np.int32)
        return self._words[:n]   # header zeros: no counts, 0 pairs and keys (the frame fitted)

    def scalars(self, *xs: Any) -> list[int]:
        self._count("scalars")
        return [0 for _ in xs]

    def synchronize(self) -> None:
        self._count("synchronize")

    def __getattr__(self, name: str) -> Any:
        """Every other operation (fill, sort_into, take_into, cumsum_into, searchsorted_into, zero_words,
        copy_words, ...): recorded, no work."""
        if name.startswith("__"):
            raise AttributeError(name)

        def op(*args: Any, **kwargs: Any) -> None:
            self._count(name)
        return op


class StubKernel:
    """A kernel of the stub device: ``kernel[grid, block](*args)`` records the launch."""

    def __init__(self, name: str, record: dict[str, int]) -> None:
        self.name, self.record = name, record

    def __getitem__(self, config: Any) -> Any:
        def launch(*args: Any) -> None:
            self.record[self.name] = self.record.get(self.name, 0) + 1
        return launch


class StubKernels:
    """The kernels module of the stub device: its constants, and kernels (one object each, as the real module's
    cached ones) that record their launches."""

    def __init__(self, real: Any) -> None:
        self._real = real
        self.launches: dict[str, int] = {}
        self._kernels: dict[str, StubKernel] = {}

    def _kernel(self, name: str) -> StubKernel:
        if name not in self._kernels:
            self._kernels[name] = StubKernel(name, self.launches)
        return self._kernels[name]

    def __getattr__(self, name: str) -> Any:
        if name.endswith("_kernel"):
            return self._kernel(name)
        return getattr(self._real, name)

    def make_update_kernel(self, *args: Any) -> StubKernel:
        return self._kernel("update")

    def make_render_kernel(self, *args: Any, **kwargs: Any) -> StubKernel:
        return self._kernel("render")


def stub_map(model: Any, num_classes: int) -> Any:
    """A SemanticMap on backend "cuda" whose device is the stub device."""
    from css_ros import SemanticMap
    from css_ros.engine.label_input import NUM_COUNTS

    smap = SemanticMap(model, num_classes, backend="cuda")
    backend: Any = smap._backend
    backend.ops = ops = StubOps()
    backend.k = StubKernels(backend.k)
    for name in ("means", "cov3d", "opacities", "max_std", "sh"):
        real = getattr(backend, name)
        setattr(backend, name, StubArray(real.shape, real.dtype))
    backend._empty_f64 = ops.zeros(0, np.float64)
    backend._empty_views = backend._word_views(ops.zeros(16, np.int32))
    backend._empty_scores = ops.zeros((1, 2), np.float64)
    backend._no_confidence = ops.zeros((1, 1), np.float32)
    backend._no_image = ops.zeros((1, 1), np.float32)
    backend._no_transient = ops.zeros(1, np.bool_)
    backend._transient = (b"", backend._no_transient)
    backend._counts_dev = ops.zeros(NUM_COUNTS, np.int32)
    backend._conc = None
    backend._plans.clear()
    backend._out = None
    backend._params_key = None
    backend._planes_dev.clear()
    return smap


def measure(model: Any, cams: list, labels: list, num_classes: int, frames: int) -> dict:
    """Host ms per observe and per query render (median over ``frames`` after 10 warm-up frames: the plan settles its
    capacities over its first 8 frames, as on a GPU), and per frame: the launches, host -> device copies, device ->
    host copies and synchronisations, and launches bound after the warm-up."""
    smap = stub_map(model, num_classes)
    backend = smap._backend
    ops, kern = backend.ops, backend.k
    n = len(cams)
    for i in range(10):
        smap.observe(cams[i % n], labels[i % n])
        smap.render(cams[i % n])
    ops.calls.clear()
    kern.launches.clear()
    bindings = backend.launches.bindings
    observe, query = [], []
    for i in range(frames):
        cam, lab = cams[i % n], labels[i % n]
        t = time.perf_counter()
        smap.observe(cam, lab)
        observe.append(time.perf_counter() - t)
    per_observe = {k: v / frames for k, v in ops.calls.items()}
    launches_observe = sum(kern.launches.values()) / frames
    ops.calls.clear()
    kern.launches.clear()
    for i in range(frames):
        t = time.perf_counter()
        smap.render(cams[i % n])
        query.append(time.perf_counter() - t)
    per_query = {k: v / frames for k, v in ops.calls.items()}
    syncs = ("download", "download_words", "scalars", "synchronize")
    return dict(observe_ms=1e3 * statistics.median(observe), observe_p90_ms=1e3 * float(np.percentile(observe, 90)),
                query_ms=1e3 * statistics.median(query), launches_per_observe=launches_observe,
                launches_per_query=sum(kern.launches.values()) / frames,
                syncs_per_observe=sum(per_observe.get(k, 0) for k in syncs),
                syncs_per_query=sum(per_query.get(k, 0) for k in syncs),
                uploads_per_observe=per_observe.get("host_to_device", 0) + per_observe.get("upload", 0),
                array_ops_per_observe=sum(v for k, v in per_observe.items() if k not in syncs),
                new_bindings=backend.launches.bindings - bindings)


def main(argv: list[str] | None = None) -> int:
    import bench_frame as bf

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", choices=sorted(bf.SCENES), action="append", help="scene(s) (default: 1M)")
    p.add_argument("--frames", type=int, default=100, help="timed frames per measurement (default 100)")
    args = p.parse_args(argv)
    print(f"{'scene':8} {'observe ms':>10} {'p90':>6} {'query ms':>9} {'launches':>8} {'syncs':>5} {'H2D':>4} "
          f"{'array ops':>9} {'new bindings':>12}")
    for name in args.scene or ["1M"]:
        cfg = dict(bf.SCENES[name])
        model, gt, cams = bf.build_scene(cfg, 12)
        rng = np.random.default_rng(0)
        labels = [rng.integers(0, cfg["classes"], (cfg["height"], cfg["width"])).astype(np.uint8) for _ in cams]
        r = measure(model, cams, labels, cfg["classes"], args.frames)
        print(f"{name:8} {r['observe_ms']:10.3f} {r['observe_p90_ms']:6.3f} {r['query_ms']:9.3f} "
              f"{r['launches_per_observe']:8.1f} {r['syncs_per_observe']:5.1f} {r['uploads_per_observe']:4.1f} "
              f"{r['array_ops_per_observe']:9.1f} {r['new_bindings']:12d}")
    print(f"machine: {os.cpu_count()} cores, {bf.cpu_model()}; stub device (no kernel runs; labels uint8 as mono8)")
    return 0


if __name__ == "__main__":
    os.environ.setdefault("NUMBA_ENABLE_CUDASIM", "1")   # numba.cuda importable without a GPU; no kernel runs
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    sys.exit(main())
