"""What a frame costs the CUDA backend on paper: bytes moved, instructions issued and the expected
milliseconds per kernel, from counts measured on the real scene (``benchmarks/cuda_estimate.py``).

No numba import: the counts come from the CPU engine (the same projection and tile lists as the
GPU's, :func:`frame_counts`), the formulas below from what each kernel of :mod:`.kernels` reads,
writes and executes per item. The estimate is a roofline floor with stated efficiencies, not a
simulation: a kernel takes max(bytes / (DRAM bandwidth x MEM_EFFICIENCY), instructions / (issue
rate x ISSUE_EFFICIENCY)) plus the host's cost of issuing it (numba-cuda launches as measured on the H200,
array-library calls, the synchronisations and the host's work on the frame's copy), the radix sorts are scaled
from a sort timed on the lent H100 (torch.sort, 5M int64 keys: 0.83 ms), transfers cross PCIe. ``docs/cuda.md``
holds the table and says how it compares with gsplat's measured times on the same scenes.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from ..spec import RENDER_CLASS_CHUNK, TILE_SIZE

if TYPE_CHECKING:
    from ..camera import Camera
    from ..cpu.projection import GaussianGeometry


@dataclass(frozen=True)
class GpuSpec:
    """Peak rates of one GPU (vendor figures)."""

    name: str
    dram_gbs: float          # DRAM bandwidth [GB/s]
    thread_instr_t: float    # thread instructions issued per second [1e12/s]: SMs x 4 schedulers x 32 x clock
    pcie_gbs: float          # host <-> device copies of pinned memory [GB/s]


H100_SXM = GpuSpec("H100 SXM5 (132 SMs, 1.98 GHz, HBM3 3.35 TB/s, PCIe 5)", 3350.0,
                   132 * 4 * 32 * 1.98e9 / 1e12, 50.0)
MEM_EFFICIENCY = 0.7      # fraction of peak DRAM bandwidth a streaming kernel reaches
ISSUE_EFFICIENCY = 0.35   # fraction of peak issue the compositing walks reach (25-66 % occupancy, divergence,
#                           barriers between batches, shared-memory atomics)
NUMBA_LAUNCH_MS = 0.2     # per numba-cuda kernel launch, host side: its argument handling in Python (~0.2 ms a
#                           launch in the H200 profile of 2026-11-26, torch.profiler + cProfile)
LAUNCH_MS = 0.015         # per array-library call issued from Python (torch's dispatch: allocation from its
#                           caching allocator, a sort, a scan, a copy), host side
SYNC_MS = 0.02            # one device -> host synchronisation
HOST_VIEW_MS = 0.1        # the host's work on a frame's copy: numpy views into it (benchmarks/bench_host.py: 0.05-0.08 ms)
#: bytes per pixel of a view's outputs in final form: int32 label, five float32 images (E, Var, kappa_b, evidence,
#: depth), the float32 confidence, uint8 colour (css_ros.engine.cuda.layout)
OUTPUT_BYTES_PER_PIXEL = 4 + 5 * 4 + 4 + 3
# torch.sort on the lent H100: 5M int64 keys (with their int64 indices) in 0.83 ms, i.e. 8 radix passes reading
# and writing 16 B per element. The backend sorts int32 keys (4 passes of 12 B): 4 x 12 / (8 x 16) of that.
SORT_MS_PER_KEY = 0.83 / 5e6 * (4 * 12) / (8 * 16)
SORT_MIN_MS = 0.03

# Per-item instruction counts of the kernels (read off kernels.py; a thread instruction is one lane's)
INSTR_PROJECT_ALL = 30        # per (view, Gaussian): loads, transform, near-plane and early cull
INSTR_PROJECT_KEPT = 220      # per kept pair: EWA (float64: 2 issue slots per op on H100), box, atomic, stores
INSTR_SH_PER_COEFF = 3 * 2 * 2  # per kept pair and SH coefficient: 3 channels x FMA + load, float64
INSTR_WALK = 16               # per (pixel, walked Gaussian): q, exp, tests, transmittance (float32)
INSTR_UPDATE_REDUCE = 10      # per (pixel, walked Gaussian) in the update: ballot, shuffles, shared atomic
INSTR_RENDER_PER_CLASS = 6    # per (pixel, contribution, class): 2 L1 loads, 2 FMAs, shared load/store
INSTR_TABLE_PER_CLASS = 4     # sensor-model flush, per (list entry, label, class): shared + table load, test, FMA
SENSOR_MODELS = ("none", "weights", "confusion")   # the update's kinds (bench_frame.py --sensor-model)


@dataclass(frozen=True)
class FrameCounts:
    """Sizes of one batch of views, measured on the scene (one view for observe / render).

    Attributes:
        gaussians: N; views: V; width, height [px]; classes: C; sh_coeffs: K (1, 4, 9, 16).
        kept: (view, Gaussian) pairs that reach the image (M).
        keys: (pair, 8x8 tile) entries of the tile lists (P): the sort's keys.
        walked: sum over tiles of 64 x list length: (pixel, Gaussian) alpha evaluations when no pixel
            stops early (an upper bound: early termination only shortens it).
        contributions: (pixel, Gaussian) pairs with kappa > 0 (what the render accumulates).
        label_sums: sum over tiles of list length x distinct labels in the tile (the update's float64
            atomics into the map, at most).
    """

    gaussians: int
    views: int
    width: int
    height: int
    classes: int
    sh_coeffs: int
    kept: int
    keys: int
    walked: int
    contributions: int
    label_sums: int

    def __add__(self, other: "FrameCounts") -> "FrameCounts":
        """Counts of two batches of the same model and image size taken together (views add up)."""
        return FrameCounts(self.gaussians, self.views + other.views, self.width, self.height, self.classes,
                           self.sh_coeffs, self.kept + other.kept, self.keys + other.keys,
                           self.walked + other.walked, self.contributions + other.contributions,
                           self.label_sums + other.label_sums)


@dataclass(frozen=True)
class KernelCost:
    """One stage of the frame: DRAM bytes, thread instructions and the expected time."""

    stage: str
    bytes: float
    instructions: float
    ms: float


def _kernel(stage: str, nbytes: float, instr: float, gpu: GpuSpec, launches: int = 0,
            kernels: int = 1) -> KernelCost:
    """A stage of ``kernels`` numba-cuda launches and ``launches`` array-library calls: device roofline plus the
    host's cost of issuing them (the host and the device do not overlap within a frame: every stage is issued
    from one Python thread and the frame ends in a synchronisation)."""
    mem_ms = nbytes / (gpu.dram_gbs * 1e9 * MEM_EFFICIENCY) * 1e3
    issue_ms = instr / (gpu.thread_instr_t * 1e12 * ISSUE_EFFICIENCY) * 1e3
    return KernelCost(stage, nbytes, instr, max(mem_ms, issue_ms) + kernels * NUMBA_LAUNCH_MS + launches * LAUNCH_MS)


def observe_costs(c: FrameCounts, gpu: GpuSpec = H100_SXM, color: bool = True,
                  sensor_model: str = "none") -> list[KernelCost]:
    """Per-stage costs of ``SemanticMap.observe`` (update then render at one pose) for counts ``c``; with a
    ``sensor_model`` ("weights": per label and depth bin weights; "confusion": a dense confusion model too), the
    update's variant with its depth walk."""
    pixels = c.width * c.height * c.views
    costs = [_project(c, gpu, color), _order(c, gpu), _moments(c, gpu), _update(c, gpu, sensor_model),
             _render(c, gpu, score=False)]
    # syncs: the pair count after the projection, the frame's copy (and with a sensor model the no-depth count)
    sync = 2 * SYNC_MS if sensor_model == "none" else 3 * SYNC_MS
    nbytes = pixels * (8 + OUTPUT_BYTES_PER_PIXEL)   # labels + weights in; every image out, final dtypes
    costs.append(KernelCost("transfers + sync", nbytes, 0.0, nbytes / (gpu.pcie_gbs * 1e9) * 1e3 + sync
                            + 4 * LAUNCH_MS + HOST_VIEW_MS))
    return costs



#: How bench_frame.py --backend cuda splits the observe cycle (it synchronises after each of these), in terms of the
#: stages priced here: prepare = projection + ordering, render = moments + render kernel + the transfers and sync.
BENCH_STAGES = {"prepare": ("project", "order"), "update": ("update",),
                "render": ("moments", "render", "transfers + sync")}


def bench_stages(costs: list[KernelCost]) -> dict[str, float]:
    """Expected ms per stage of ``bench_frame.py --backend cuda`` (:data:`BENCH_STAGES`) from observe costs."""
    ms = {c.stage: c.ms for c in costs}
    return {name: sum(ms[s] for s in parts) for name, parts in BENCH_STAGES.items()}


def score_costs(c: FrameCounts, gpu: GpuSpec = H100_SXM) -> list[KernelCost]:
    """Per-stage costs of ``score_views`` over ``c.views`` candidate views (one batch)."""
    return [_project(c, gpu, False), _order(c, gpu), _moments(c, gpu), _render(c, gpu, score=True),
            KernelCost("transfers + sync", c.views * 16, 0.0, 2 * SYNC_MS + 2 * LAUNCH_MS)]


def _project(c: FrameCounts, gpu: GpuSpec, color: bool) -> KernelCost:
    pairs = c.views * c.gaussians
    # the views of one Gaussian run on neighbouring lanes: its 88 B (means, cov3d, opacity, std) come from
    # DRAM once; the camera rows (152 B each) stay in L1
    nbytes = c.gaussians * 88 + c.kept * 104 + (c.kept * c.sh_coeffs * 12 if color else 0)
    instr = (pairs * INSTR_PROJECT_ALL + c.kept * INSTR_PROJECT_KEPT
             + (c.kept * c.sh_coeffs * INSTR_SH_PER_COEFF if color else 0))
    return _kernel("project", nbytes, instr, gpu, launches=10)   # buffers, cumsum, the count's copy


def _order(c: FrameCounts, gpu: GpuSpec) -> KernelCost:
    """Depth sort of the kept pairs, prefix sum of their tile counts, key emission in depth order, the
    stable sort of the 32-bit (view, tile) keys, the gather of the pair order, searchsorted."""
    nbytes = c.kept * (4 + 8 + 12 + 8 + 36) + c.keys * (8 + 16)
    emit = _kernel("order", nbytes, c.keys * 12, gpu, launches=12)
    sort_bytes = (c.kept + c.keys) * 4 * 2 * 12   # 4 digit passes, each reading and writing key + index
    sort_ms = 2 * SORT_MIN_MS + (c.kept + c.keys) * SORT_MS_PER_KEY
    return KernelCost("order", nbytes + sort_bytes, emit.instructions, emit.ms + sort_ms)


def _moments(c: FrameCounts, gpu: GpuSpec) -> KernelCost:
    rows = min(c.kept, c.gaussians)   # distinct Gaussians of the batch, at most
    return _kernel("moments", rows * (c.classes * 8 + (2 * c.classes + 1) * 4), rows * c.classes * 8, gpu,
                   launches=1)


def _update(c: FrameCounts, gpu: GpuSpec, sensor_model: str) -> KernelCost:
    """The update kernel: list staged (order, 7 f64 geometry, id), every labelled pixel walked, per (Gaussian,
    label) of each tile one float64 atomic. With a sensor model, the depth walk first (the list staged again with
    the depth column, every labelled pixel walked again) and the flush through the table (per list entry and class,
    a sum over the tile's rows); a dense confusion gives every class of every list entry a nonzero sum: C atomics
    per list entry instead of one per label present."""
    if sensor_model not in SENSOR_MODELS:
        raise ValueError(f"sensor_model must be one of {SENSOR_MODELS}, got {sensor_model!r}")
    pixels = c.width * c.height * c.views
    nbytes = c.keys * 64 + pixels * 8 + c.label_sums * 16
    instr = c.walked * (INSTR_WALK + INSTR_UPDATE_REDUCE)
    if sensor_model != "none":
        nbytes += c.keys * 68
        instr += c.walked * INSTR_WALK + c.label_sums * c.classes * INSTR_TABLE_PER_CLASS
    if sensor_model == "confusion":
        nbytes += max(c.keys * c.classes - c.label_sums, 0) * 16
    return _kernel("update", nbytes, instr, gpu, launches=2)   # the labels and weights uploads


def _render(c: FrameCounts, gpu: GpuSpec, score: bool) -> KernelCost:
    pixels = c.width * c.height * c.views
    passes = -(-c.classes // RENDER_CLASS_CHUNK)
    out = c.views * 16 if score else pixels * OUTPUT_BYTES_PER_PIXEL
    nbytes = passes * c.keys * (56 + 4 + 4 + 12 + 4 + (0 if score else 8)) + c.keys * (2 * c.classes + 1) * 4 + out
    instr = passes * c.walked * INSTR_WALK + c.contributions * c.classes * INSTR_RENDER_PER_CLASS
    return _kernel("score" if score else "render", nbytes, instr, gpu, launches=1)


def frame_counts(geometry: "GaussianGeometry", cameras: "list[Camera]", classes: int,
                 labels: "list[np.ndarray] | None" = None, tile: int = TILE_SIZE) -> FrameCounts:
    """Counts of a batch of views of one image size, measured with the CPU engine (same culls, same
    alpha boxes, same 8 x 8 tile lists as the GPU; contributions from the exact compositing walk).

    Args:
        labels: per view (H, W) int labels (-1 = none) for the update's atomics; None counts one
            label per tile.
        tile: tile edge [px] (the backend's is 8; other sizes show what a tile size would cost).
    """
    from ..cpu.projection import project
    from ..cpu.raster import bin_tiles, kappa_lists

    width, height = int(cameras[0].width), int(cameras[0].height)
    kept = keys = walked = contributions = label_sums = 0
    for v, cam in enumerate(cameras):
        proj = project(geometry, cam, view_colors=False)
        bins = bin_tiles(proj, width, height, tile)
        lengths = np.diff(bins.offsets)
        kept += proj.count
        keys += int(bins.offsets[-1])
        walked += int(lengths.sum()) * tile * tile
        contributions += int(kappa_lists(proj, bins, width, height).kappa.size)
        distinct = np.ones_like(lengths)
        if labels is not None:
            distinct = _labels_per_tile(np.asarray(labels[v]), bins.tiles_x, bins.tiles_y, tile)
        label_sums += int((lengths * distinct).sum())
    return FrameCounts(geometry.num_gaussians, len(cameras), width, height, classes, int(geometry.sh.shape[1]),
                       kept, keys, walked, contributions, label_sums)


def _labels_per_tile(labels: np.ndarray, tiles_x: int, tiles_y: int, tile: int) -> np.ndarray:
    """(tiles,) number of distinct valid labels (>= 0) per tile, row-major tile order."""
    h, w = labels.shape
    pad = np.full((tiles_y * tile, tiles_x * tile), -1, dtype=np.int64)
    pad[:h, :w] = labels
    blocks = pad.reshape(tiles_y, tile, tiles_x, tile).transpose(0, 2, 1, 3).reshape(tiles_y * tiles_x, -1)
    srt = np.sort(blocks, axis=1)
    new = np.concatenate([srt[:, :1] >= 0, (srt[:, 1:] != srt[:, :-1]) & (srt[:, 1:] >= 0)], axis=1)
    return new.sum(axis=1)
