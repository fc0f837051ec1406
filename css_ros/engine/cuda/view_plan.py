"""The single-view plan of the CUDA backend: an observe or a query render with one synchronisation (the view's one
copy out) and launches bound once.

A plan belongs to one image size and colour mode. It owns every device buffer a view's projection, depth sort,
key emission, update and render touch, sized by capacities (pairs P, keys K) rather than by the frame's own counts,
so that the host never waits for the counts before sorting (the batched path of :meth:`CudaBackend.prepare_views`
reads them: one synchronisation more). Rows past the frame's count sort last (depth +inf, no tiles; keys
INT32_MAX), so sorting the whole buffers gives the frame's order. The kernels read the counts on the device; if the
frame needs more room than the capacities give, the update adds nothing (``kernels.overflowed``), the view's copy
says so (its header holds the counts) and the backend grows the plan and does the frame again. Capacities follow the
frames seen: :data:`HEADROOM` above the largest recent need, shrunk when they exceed it :data:`SHRINK` times.

Every buffer keeps its address from frame to frame, so each launch is bound once (:mod:`.launch`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from ..splat_math import CAM_COLS, camera_row

if TYPE_CHECKING:
    from ..camera import Camera

#: capacity above the need that set it (pairs and keys)
HEADROOM = 1.25
#: a capacity more than this many times the need of the recent frames is shrunk
SHRINK = 2.0
#: the largest int32 key: rows past the frame's keys sort after every (view, tile) key
KEY_SENTINEL = np.iinfo(np.int32).max


@dataclass
class PlanBuffers:
    """The plan's device buffers for capacities P pairs and K keys (shapes in the comments)."""

    pairs: int
    keys: int
    sizes: Any      # (2,) i64: kept pairs (projection), keys (key emission)
    packed: Any     # (P, 8) f64
    bbox: Any       # (P, 4) i32
    ids: Any        # (P,) i32 model rows; also the moments' rows (one view: a pair's row is its index)
    views: Any      # (P,) i32
    ntiles: Any     # (P,) i32 (0 past the count)
    colors: Any     # (P, 3) f32
    depth: Any      # (P,) f32 (+inf past the count)
    depth_sorted: Any  # (P,) f32
    by_depth: Any   # (P,) i64
    nt_depth: Any   # (P,) i32
    ends: Any       # (P,) i64
    keys_raw: Any   # (K,) i32 (KEY_SENTINEL past the count)
    pairs_raw: Any  # (K,) i32
    keys_sorted: Any  # (K,) i32
    perm: Any       # (K,) i64
    order: Any      # (K,) i32
    offsets: Any    # (T + 1,) i64
    tile_ids: Any   # (T + 1,) i32: 0..T
    pair_row: Any   # (P,) i32: 0..P-1
    mom: Any        # (P, 2C + 1) f32, allocated by the backend per class count
    cam: Any        # (1, CAM_COLS) f64


class ViewPlan:
    """Buffers and capacities of single views of one size (``width`` x ``height``, colour or not).

    Args:
        ops: the backend's array operations. num_gaussians: N. tiles_x, tiles_per_view: the tile grid.
        pairs, keys: initial capacities.
    """

    def __init__(self, ops: Any, width: int, height: int, tiles_x: int, tiles_per_view: int, pairs: int,
                 keys: int) -> None:
        self.ops = ops
        self.width, self.height = int(width), int(height)
        self.tiles_x, self.tiles_per_view = int(tiles_x), int(tiles_per_view)
        self._cam_host = np.zeros((1, CAM_COLS))
        self._recent: list[tuple[int, int]] = []
        self.moments: dict[int, Any] = {}
        self.increments: dict[int, Any] = {}
        self.buffers = self._allocate(max(1, int(pairs)), max(1, int(keys)))

    def _allocate(self, pairs: int, keys: int) -> PlanBuffers:
        ops = self.ops
        t = self.tiles_per_view
        self.moments = {}
        self.increments = {}
        return PlanBuffers(
            pairs, keys, ops.zeros(2, np.int64), ops.zeros((pairs, 8), np.float64), ops.zeros((pairs, 4), np.int32),
            ops.zeros(pairs, np.int32), ops.zeros(pairs, np.int32), ops.zeros(pairs, np.int32),
            ops.zeros((pairs, 3), np.float32), ops.zeros(pairs, np.float32), ops.zeros(pairs, np.float32),
            ops.zeros(pairs, np.int64), ops.zeros(pairs, np.int32), ops.zeros(pairs, np.int64),
            ops.zeros(keys, np.int32), ops.zeros(keys, np.int32), ops.zeros(keys, np.int32), ops.zeros(keys, np.int64),
            ops.zeros(keys, np.int32), ops.zeros(t + 1, np.int64), ops.arange(t + 1, np.int32),
            ops.arange(pairs, np.int32), None, ops.zeros((1, CAM_COLS), np.float64))

    def moment_buffer(self, num_classes: int) -> Any:
        """(P, 2C + 1) f32 moments of the plan's pairs, one buffer per class count."""
        buf = self.moments.get(num_classes)
        if buf is None:
            buf = self.moments[num_classes] = self.ops.empty((self.buffers.pairs, 2 * num_classes + 1), np.float32)
        return buf

    def increment_buffer(self, num_classes: int) -> Any:
        """(P, C) f64 per-pair increments of an update with forgetting, zeros (the apply kernel zeroes the rows it
        consumed: :func:`~css_ros.engine.cuda.kernels.apply_increments_kernel`); one buffer per class count, made on
        first use (maps without forgetting never have one)."""
        buf = self.increments.get(num_classes)
        if buf is None:
            buf = self.increments[num_classes] = self.ops.zeros((self.buffers.pairs, num_classes), np.float64)
        return buf

    def start(self, camera: "Camera") -> PlanBuffers:
        """Reset the per-frame buffers and upload the camera (asynchronous)."""
        b, ops = self.buffers, self.ops
        camera_row(camera, self._cam_host[0])
        ops.host_to_device(b.cam, self._cam_host, "plan_camera")
        ops.fill(b.sizes, 0)
        ops.fill(b.ntiles, 0)
        ops.fill(b.depth, np.inf)
        ops.fill(b.keys_raw, KEY_SENTINEL)
        return b

    def sort_pairs(self) -> None:
        """Depth order of the pairs, then the inclusive prefix sum of their tile counts in that order."""
        b, ops = self.buffers, self.ops
        ops.sort_into(b.depth, b.depth_sorted, b.by_depth)
        ops.take_into(b.ntiles, b.by_depth, b.nt_depth)
        ops.cumsum_into(b.nt_depth, b.ends)

    def sort_keys(self) -> None:
        """Every tile's front-to-back list: the keys sorted stably, the pairs in that order, each tile's range."""
        b, ops = self.buffers, self.ops
        ops.sort_into(b.keys_raw, b.keys_sorted, b.perm)
        ops.take_into(b.pairs_raw, b.perm, b.order)
        ops.searchsorted_into(b.keys_sorted, b.tile_ids, b.offsets)

    def fits(self, pairs: int, keys: int) -> bool:
        """Whether a frame of ``pairs`` kept pairs and ``keys`` keys fitted; records its need. False: the plan has
        grown (new buffers) and the frame must be done again."""
        self._recent = (self._recent + [(pairs, keys)])[-8:]
        b = self.buffers
        if pairs <= b.pairs and keys <= b.keys:
            need_p = max(p for p, _ in self._recent)
            need_k = max(k for _, k in self._recent)
            if len(self._recent) >= 8 and (b.pairs > SHRINK * HEADROOM * max(need_p, 1)
                                           or b.keys > SHRINK * HEADROOM * max(need_k, 1)):
                self.buffers = self._allocate(int(HEADROOM * need_p) + 1, int(HEADROOM * need_k) + 1)
            return True
        self.buffers = self._allocate(max(b.pairs, int(HEADROOM * pairs) + 1), max(b.keys, int(HEADROOM * keys) + 1))
        return False
