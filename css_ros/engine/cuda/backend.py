"""The CUDA backend: :class:`CudaBackend` implements the RasterBackend protocol with the numba-cuda
kernels of :mod:`.kernels`; device-wide sorts and scans come from the array library of
:mod:`.arrays` (torch.cuda on a GPU, numpy under the simulator).

State on the device: the model (means, 3D covariances, opacities, largest std, SH) and the
concentrations (N, C) float64. SemanticMap's host array is kept coherent lazily: the backend
uploads it when the host side may have changed (first use, after ``host_view`` handed it out, or a
different array) and downloads the device copy when the host asks for it (``host_view``). Per
observed frame the only transfers are the labels/weights in, the pair and key counts of the projection (the sizes of
the sorts: one synchronisation) and one copy out of the requested images in final form (:mod:`.layout`'s planes and
header; with a sensor model, also its tables once and the update's no-depth count: one more synchronisation).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from ...errors import CssError
from ..label_input import NUM_COUNTS
from ..raster_backend import RasterBackend, UpdateCounts
from ..buffers import RenderBuffers
from ..final_form import IMAGE_OUTPUTS, FrameImages, RenderSettings, uncertainty_from_sums
from ..info_gain import SelectedViews
from ..spec import INFO_GAIN_PRIOR
from ..spec import TILE_SIZE
from ..splat_math import CAM_COLS, camera_row
from .arrays import import_cuda, make_ops, simulator_enabled
from .launch import Launches
from .layout import COUNT_WORDS, HEADER_WORDS, NUM_PLANES, SIZE_WORDS, PlaneLayout, plane_layout
from .view_plan import HEADROOM, ViewPlan

if TYPE_CHECKING:
    from ..camera import Camera
    from ..label_input import FrameLabels
    from ..sensor_model import SoftLabels
    from ..gaussians import GaussianModel


@dataclass
class CudaFrame:
    """Per-batch view state on the device (V views of one size; M kept (view, Gaussian) pairs in
    (view, depth, id) order; P (pair, tile) keys).

    Attributes:
        cameras: the V cameras. width, height: image size [px]. tiles_x, tiles_per_view: tile grid.
        num_pairs: M. offsets: (V T + 1,) i64 ranges of each (view, tile) in ``order``.
        order: (max(P, 1),) i32 pair index of each key, keys sorted by (view * T + tile) << 32 | depth32.
        packed: (>= M, 8) f64 rows
        (u, v, a, b, c, opacity, qmax, depth). colors: (M, 3) f32. ids: (M,) i32 model rows.
        pair_row: (M,) i32 row of each pair in ``rows``. rows: (R,) i32 model rows whose moments
        the render needs (each once). sizes: (2,) i64 on the device, (kept pairs, keys) as the kernels counted
        them. row_count: (1,) i64 on the device, the rows' count. plan: the single-view plan whose buffers these
        are (:mod:`.view_plan`; its counts are known on the host only after the view's copy: ``num_pairs`` -1),
        or None (a batch sized on the host).
    """

    cameras: list
    width: int
    height: int
    tiles_x: int
    tiles_per_view: int
    num_pairs: int
    offsets: Any
    order: Any
    packed: Any
    colors: Any
    ids: Any
    views: Any
    pair_row: Any
    rows: Any
    sizes: Any
    row_count: Any
    plan: "ViewPlan | None" = None


#: (view, Gaussian) pairs one scoring batch may hold: its buffers take ~250 bytes per pair (projection rows 108,
#: depth sort 24, tile keys and their sort ~24 per key, evidence mass 8, ...), so ~2 GiB at this bound, which keeps
#: a 256-candidate scoring of a 1M splat within 4 GiB of GPU memory with the model and the map
SCORE_BATCH_PAIRS = 8_000_000
#: attempts of a single view in its plan before it takes the batched path (each attempt grows the plan to its need:
#: the pairs first, then the keys of all of them; two suffice)
PLAN_ATTEMPTS = 4


@dataclass
class PairMasses:
    """What the info gain needs of a scoring batch, kept after its frame is gone: the batch's view indices, its M
    pairs' view rows (M,) i32, model ids (M,) i32 and evidence mass (M,) f64 on the device (None when M = 0)."""

    idx: list[int]
    num_pairs: int
    views: Any
    ids: Any
    mass: Any


class DeviceCounts(UpdateCounts):
    """An update's pixel counts (NUM_COUNTS,) int32 on the device and, when it made one, its (H, W) float32 surprise
    image on the device (``surprise_device``): the next view's one copy brings them (:meth:`arrived`), else
    :meth:`get` / :meth:`surprise` download them."""

    def __init__(self, ops: Any, device: Any, surprise_device: Any = None) -> None:
        super().__init__()
        self.ops = ops
        self.device = device
        self.surprise_device = surprise_device
        self.ready = False

    @property
    def surprise_shape(self) -> tuple[int, int]:
        """(H, W) of the surprise image ((0, 0) without one)."""
        if self.surprise_device is None:
            return (0, 0)
        return int(self.surprise_device.shape[0]), int(self.surprise_device.shape[1])

    def arrived(self, counts: np.ndarray, surprise: "np.ndarray | None" = None) -> None:
        """The counts (and the surprise image), copied to the host with a view's output."""
        self._counts = tuple(int(v) for v in counts[:NUM_COUNTS])
        self._surprise = surprise
        self.ready = True

    def _fetch(self) -> None:
        if not self.ready:
            surprise = None if self.surprise_device is None else self.ops.download(self.surprise_device)
            self.arrived(self.ops.download(self.device), surprise)

    def get(self) -> tuple[int, int, int, int, int, int]:
        self._fetch()
        return super().get()

    def surprise(self) -> "np.ndarray | None":
        self._fetch()
        return super().surprise()


class CudaBackend(RasterBackend):
    """numba-cuda rasteriser (SPEC §3-6) with the model and the concentrations on the GPU.

    Args:
        model: the splat model (map frame).
        device: CUDA device index (default: the current device, normally 0).
        tile_size: tile edge [px]; one block of tile_size^2 threads per tile.
    Raises:
        CssError: numba-cuda missing, or neither a GPU nor the simulator.
    """

    def __init__(self, model: "GaussianModel", device: int | None = None, tile_size: int = TILE_SIZE) -> None:
        self.cuda = import_cuda()
        self.simulated = simulator_enabled()
        self.device = None if device is None else int(device)
        self._thread = threading.local()
        self._bind()
        self.ops = make_ops(device)
        from . import kernels  # compiles lazily, at the first launch

        self.k = kernels
        self._probe()
        self.tile = int(tile_size)
        ops = self.ops
        scales = np.asarray(model.scales, dtype=np.float64)
        cov = model.covariances()
        cov6 = np.stack([cov[:, 0, 0], cov[:, 0, 1], cov[:, 0, 2], cov[:, 1, 1], cov[:, 1, 2], cov[:, 2, 2]], axis=1)
        self.num_gaussians = int(model.num_gaussians)
        # arrays that live as long as the backend go to the kernels as numba device arrays, converted once
        # (a torch tensor passed to a launch is converted through __cuda_array_interface__ at every launch)
        karr = ops.kernel_array
        self.means = karr(ops.upload(model.means, np.float64))
        self.cov3d = karr(ops.upload(cov6, np.float64))
        self.opacities = karr(ops.upload(model.opacities, np.float64))
        self.max_std = karr(ops.upload(scales.max(axis=1) if len(scales) else np.zeros(0), np.float64))
        self.sh = karr(ops.upload(model.sh, np.float32))
        self._capacity = {1: max(1, self.num_gaussians)}  # projection rows per batch size (grown on demand)
        self._conc: Any = None       # the concentrations on the device (array library) ...
        self._conc_k: Any = None     # ... and as a kernel argument
        self._host: np.ndarray | None = None
        self._host_dirty = True
        self._device_newer = False
        self._soft: tuple[Any, Any, Any] | None = None  # (SoftLabels, edges, table on the device)
        self._out: Any = None                                 # the reused output buffer (int32 words)
        self._params_key: tuple[bytes, bytes] | None = None
        self._params_dev: tuple[Any, Any] = (None, None)
        self._planes_dev: dict[bytes, Any] = {}
        self._out_views: tuple[Any, ...] = ()
        self._empty_f64 = karr(ops.zeros(0, np.float64))
        self._empty_views = self._word_views(ops.zeros(HEADER_WORDS, np.int32))
        self._empty_scores = karr(ops.zeros((1, 2), np.float64))
        self._no_confidence = ops.zeros((1, 1), np.float32)  # the confidence argument of a frame without one
        self._no_image = ops.zeros((1, 1), np.float32)        # an image argument of a rule the frame does not use
        self._no_transient = ops.zeros(1, np.bool_)            # the transient mask of a map without transient classes
        self._transient: tuple[bytes, Any] = (b"", self._no_transient)  # the map's mask on the device (bytes, array)
        self._counts_dev = ops.zeros(NUM_COUNTS, np.int32)    # the update's pixel counts (DeviceCounts)
        self._inputs: dict[tuple, Any] = {}                   # per-frame input buffers (_frame_input)
        self._plans: dict[tuple[int, int], ViewPlan] = {}     # single-view plans per image size
        self.launches = Launches(self.simulated)
        self._pairs_per_view: dict[tuple[int, int], float] = {}  # scoring batches' pairs per view, per size
        self._pending_counts: DeviceCounts | None = None      # the last update's counts, still on the device

    def _probe(self) -> None:
        """Compile and run the smallest kernel once, so that a broken stack (numba-cuda vs numpy,
        driver, toolkit) fails here, at start, as one CssError naming cause and fix, not as a
        traceback at the first frame."""
        try:
            conc = self.ops.upload(np.ones((1, 2)), np.float64)
            out = self.ops.empty((1, 5), np.float32)
            self.k.moments_kernel[1, 2](conc, self.ops.upload(np.zeros(1, np.int32)),
                                        self.ops.upload(np.ones(1, np.int64)), out)
            got = self.ops.download(out)
        except Exception as exc:  # any failure of the CUDA stack: reported in one line
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else ""
            raise CssError(f"backend 'cuda' cannot run kernels ({type(exc).__name__}: {first[:200]}); fix: "
                           "numba-cuda 0.30.4 with numpy<2.4 and a CUDA build of torch or cupy "
                           "(pip install -e '.[cuda]', docs/cuda.md), or use backend 'numba'") from exc
        if not np.allclose(got[0], [0.5, 0.5, 1 / 12, 1 / 12, 2.0]):
            raise CssError(f"backend 'cuda': the probe kernel returned {got[0].tolist()} instead of the Dirichlet "
                           "moments of (1, 1); the GPU stack is broken: use backend 'numba'")

    def _bind(self) -> None:
        """Make ``device`` current in the calling thread (numba's CUDA context is per thread: a node
        that launches from an executor thread must select it there too); once per thread."""
        if self.device is None or self.simulated or getattr(self._thread, "bound", False):
            return
        self.cuda.select_device(self.device)  # pragma: no cover - GPU only
        self._thread.bound = True  # pragma: no cover - GPU only

    # ------------------------------------------------------------------ concentrations
    def _device_concentrations(self, host: np.ndarray) -> Any:
        """The device copy of the concentrations, uploaded first if the host array may differ."""
        if self._conc is None or tuple(self._conc.shape) != host.shape:
            self._conc = self.ops.upload(host, np.float64)
            self._conc_k = self.ops.kernel_array(self._conc)
            self._device_newer = False
        elif self._host_dirty or host is not self._host:
            self.ops.copy_into(self._conc, host)
            self._device_newer = False
        self._host, self._host_dirty = host, False
        return self._conc_k

    def _download_if_newer(self, host: np.ndarray) -> None:
        if self._device_newer and host is self._host and self._conc is not None:
            host[...] = self.ops.download(self._conc)
        self._device_newer = False

    def host_read(self, host: np.ndarray) -> np.ndarray:
        """``host`` brought up to date with the device (one download if an update happened since), as a
        read-only view: the device copy stays valid, nothing is uploaded again."""
        self._download_if_newer(host)
        view = host.view()
        view.flags.writeable = False  # a write through it would silently miss the device copy
        return view

    def host_write(self, host: np.ndarray) -> np.ndarray:
        """``host`` brought up to date and handed out for writing: the next kernel that needs the
        concentrations uploads it again (the whole (N, C) array: writes are rare, e.g. load / reset)."""
        self._download_if_newer(host)
        self._host_dirty = True
        return host

    # ------------------------------------------------------------------ projection + binning
    def _launch_1d(self, total: int) -> tuple[int, int]:
        return self.k.launch_1d(total, self.simulated)

    def prepare(self, camera: "Camera") -> CudaFrame:
        return self.prepare_views([camera], want_color=True)

    def prepare_views(self, cameras: Sequence["Camera"], want_color: bool) -> CudaFrame:
        """Project, depth-sort and tile-bin V views of one image size in a fixed number of launches."""
        self._bind()
        ops, k = self.ops, self.k
        cams = list(cameras)
        width, height = int(cams[0].width), int(cams[0].height)
        if any((int(c.width), int(c.height)) != (width, height) for c in cams):
            raise ValueError("prepare_views needs views of one image size")
        n_views, n = len(cams), self.num_gaussians
        tiles_x = (width + self.tile - 1) // self.tile
        tiles_y = (height + self.tile - 1) // self.tile
        tiles_per_view = tiles_x * tiles_y
        if n_views * tiles_per_view >= 2 ** 31:
            raise CssError(f"{n_views} views x {tiles_per_view} tiles do not fit the 32-bit tile keys: score fewer "
                           "views per call")
        cam_rows = np.empty((n_views, CAM_COLS))
        for v, cam in enumerate(cams):
            camera_row(cam, cam_rows[v])
        cam_dev = ops.upload(cam_rows)
        cap = self._capacity.get(n_views, max(1, min(n_views * n, 4 * n)))
        while True:
            counter = ops.zeros(2, np.int64)  # int64: cannot wrap (V N < 2^63); [1]: the keys, set below
            packed = ops.empty((cap, k.PACK_COLS), np.float64)
            bbox = ops.empty((cap, 4), np.int32)
            ids = ops.zeros(cap, np.int32)       # rows past the count: valid model rows ...
            views = ops.zeros(cap, np.int32)
            ntiles = ops.zeros(cap, np.int32)    # ... that emit no keys
            colors = ops.empty((cap, 3), np.float32)
            depth = ops.empty(cap, np.float32)
            blocks, threads = self._launch_1d(n_views * n)
            if n_views * n:
                k.project_kernel[blocks, threads](self.means, self.cov3d, self.opacities, self.max_std, self.sh,
                                                  cam_dev, float(width), float(height), self.tile, bool(want_color),
                                                  cap, counter, packed, bbox, ids, views, ntiles, colors, depth)
            ends = ops.cumsum(ntiles)
            m, total = ops.scalars(counter[0], ends[cap - 1])  # the batch's device -> host sync
            if m <= cap:
                break
            cap = m
        self._capacity[n_views] = cap
        keys = ops.empty(max(total, 1), np.int32)
        order = ops.empty(max(total, 1), np.int32)
        if m:
            # depth order of the pairs (stable radix sort of their float32 depths), then the tile keys emitted front
            # to back and sorted stably by (view, tile) alone: two 32-bit radix sorts
            _, by_depth = ops.sort_stable(depth[:m])
            ends = ops.cumsum(ntiles[by_depth])
            blocks, threads = self._launch_1d(m)
            k.emit_keys_kernel[blocks, threads](bbox, views, by_depth, ends, counter, self.tile, tiles_x,
                                                tiles_per_view, keys, order)
            sorted_keys, perm = ops.sort_stable(keys[:total])
            order = order[perm]
            offsets = ops.searchsorted(sorted_keys, ops.arange(n_views * tiles_per_view + 1, np.int32))
        else:
            offsets = ops.zeros(n_views * tiles_per_view + 1, np.int64)
        ids = ids[:max(m, 1)]
        if n_views == 1:
            rows, pair_row = ids, ops.arange(max(m, 1), np.int32)
        else:
            flag = ops.zeros(n, np.int32)
            flag[ids] = 1
            rows = ops.nonzero(flag)
            row_of = ops.zeros(n, np.int32)
            row_of[rows] = ops.arange(rows.shape[0], np.int32)
            pair_row = row_of[ids]
            rows = rows.to(ids.dtype) if hasattr(rows, "to") else rows.astype(np.int32)
        if m == 0:
            rows = rows[:0]
        row_count = ops.upload(np.array([int(rows.shape[0])], dtype=np.int64))
        return CudaFrame(cams, width, height, tiles_x, tiles_per_view, m, offsets, order, packed, colors,
                         ids, views, pair_row, rows, counter, row_count)

    # ------------------------------------------------------------------ single views: one synchronisation
    def _plan(self, width: int, height: int) -> ViewPlan:
        """The single-view plan of this image size (capacities start at every Gaussian kept, 4 tiles each)."""
        key = (int(width), int(height))
        plan = self._plans.get(key)
        if plan is None:
            if len(self._plans) >= 8:  # image sizes of a long-lived process: bounded
                self._plans.clear()
                self.launches.clear()
            tiles_x = (width + self.tile - 1) // self.tile
            tiles_per_view = tiles_x * ((height + self.tile - 1) // self.tile)
            n = max(1, self.num_gaussians)
            plan = self._plans[key] = ViewPlan(self.ops, width, height, tiles_x, tiles_per_view, n, 4 * n)
        return plan

    def _plan_frame(self, camera: "Camera", want_color: bool) -> CudaFrame:
        """Project, sort and bin one view into its plan's buffers without waiting for the device: sizes stay on the
        device (the kernels read them), launches are bound once per plan."""
        self._bind()
        plan = self._plan(int(camera.width), int(camera.height))
        b = plan.start(camera)
        k, go = self.k, self.launches.launch
        blocks, threads = self._launch_1d(self.num_gaussians)
        if self.num_gaussians:
            go(k.project_kernel, blocks, threads, self.means, self.cov3d, self.opacities, self.max_std, self.sh,
               b.cam, float(plan.width), float(plan.height), self.tile, bool(want_color), b.pairs, b.sizes, b.packed,
               b.bbox, b.ids, b.views, b.ntiles, b.colors, b.depth)
        plan.sort_pairs()
        blocks, threads = self._launch_1d(b.pairs)
        go(k.emit_keys_kernel, blocks, threads, b.bbox, b.views, b.by_depth, b.ends, b.sizes, self.tile,
           plan.tiles_x, plan.tiles_per_view, b.keys_raw, b.pairs_raw)
        plan.sort_keys()
        return CudaFrame([camera], plan.width, plan.height, plan.tiles_x, plan.tiles_per_view, -1, b.offsets,
                         b.order, b.packed, b.colors, b.ids, b.views, b.pair_row, b.ids, b.sizes, b.sizes, plan)

    def _plan_done(self, frame: CudaFrame, host: np.ndarray) -> bool:
        """After a plan frame's copy: whether its pairs and keys fitted (else the plan has grown: do it again)."""
        assert frame.plan is not None
        pairs, keys = (int(v) for v in host[SIZE_WORDS:SIZE_WORDS + 4].view(np.int64))
        before = frame.plan.buffers
        fitted = frame.plan.fits(pairs, keys)
        if frame.plan.buffers is not before:
            self.launches.clear()  # the old buffers' bindings go with them
        return fitted

    def observe_view(self, camera: "Camera", inputs: "FrameLabels", concentrations: np.ndarray,
                     soft: "SoftLabels | None", settings: RenderSettings) -> tuple[FrameImages, UpdateCounts]:
        """One observed frame with one synchronisation: project, sort, update and render in bound launches, then one
        copy of the outputs (with the update's counts and the frame's sizes). A frame that did not fit the plan's
        buffers added nothing; it is done again with larger ones (each attempt grows the plan to the need it saw;
        after PLAN_ATTEMPTS the frame takes the path that sizes its sorts on the host)."""
        for _ in range(PLAN_ATTEMPTS):
            frame = self._plan_frame(camera, settings.wants("rgb"))
            counts = self.update(frame, inputs, concentrations, soft)
            out = self._render_host(frame, concentrations, settings)
            if self._plan_done(frame, out[0]):
                return self._images(frame, *out), counts
        return super().observe_view(camera, inputs, concentrations, soft, settings)

    def render_query(self, camera: "Camera", concentrations: np.ndarray, settings: RenderSettings) -> FrameImages:
        """A query view with one synchronisation (as :meth:`observe_view`, without the update)."""
        for _ in range(PLAN_ATTEMPTS):
            frame = self._plan_frame(camera, settings.wants("rgb"))
            out = self._render_host(frame, concentrations, settings)
            if self._plan_done(frame, out[0]):
                return self._images(frame, *out)
        return super().render_query(camera, concentrations, settings)

    # ------------------------------------------------------------------ update
    def update(self, frame: CudaFrame, inputs: "FrameLabels", concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> UpdateCounts:
        """concentrations[n, c] += sum_i kappa_in y_i^c on the device. The labels and the confidence go to the device
        as they came in (one copy each; no confidence: none) and the update kernel applies the label rule and counts
        the pixels there (:func:`~css_ros.engine.cuda.kernels.pixel_input`). The host array is brought up to date
        lazily (``host_view``).

        With ``soft`` (a sensor model's tables), the kernel variant of
        :func:`~css_ros.engine.cuda.kernels.make_update_kernel` with ``with_model`` runs instead (one more walk
        per labelled pixel for its expected depth) and also counts the labelled pixels without any contribution.
        The rules of a changing world (:mod:`css_ros.engine.change_rules`) cost only the frames that use them: a
        measured depth image (one more copy in; the kernel variant's extra walk), transient classes, the surprise
        image (the moments before the update: one more launch; the image rides along with the view's copy) and
        forgetting (the increments into a per-pair scratch, then one more launch applies them).
        The counts stay on the device: the next :meth:`render_view` brings them with its one copy, else
        :meth:`DeviceCounts.get` fetches them."""
        self._bind()
        conc = self._device_concentrations(concentrations)
        num_classes = int(conc.shape[1])
        if soft is not None and tuple(soft.table.shape) != (num_classes * soft.num_bins, num_classes):
            raise ValueError(f"sensor-model table of shape {tuple(soft.table.shape)} for {num_classes} classes and "
                             f"{soft.num_bins} depth bins")
        lab = self._frame_input("labels", inputs.labels)
        has_conf = inputs.confidence is not None
        conf = self._no_confidence if inputs.confidence is None else self._frame_input("confidence", inputs.confidence)
        counts = self._counts_dev
        self.ops.fill(counts, 0)
        rules = inputs.rules
        forgets = rules.decay != 1.0
        target, target_ids = conc, frame.ids
        if forgets:  # the frame's increments apart first: forgetting applies to the Gaussians they touch
            target, target_ids = self._increments(frame, num_classes), frame.pair_row
        rule_args, surprise = self._rule_args(frame, inputs, conc)
        args: tuple[Any, ...] = (frame.offsets, frame.order, frame.packed, target_ids, lab, conf, has_conf,
                                 int(inputs.ignore_label), frame.tiles_x, target, counts, frame.sizes, *rule_args)
        flags = (inputs.depth is not None, surprise is not None, rules.any_transient)
        if soft is None:
            kernel = self.k.make_update_kernel(num_classes, self.tile, False, 1, *flags)
        else:
            kernel = self.k.make_update_kernel(num_classes, self.tile, True, soft.num_bins, *flags)
            args = (*args, *self._soft_tables(soft))
        self._go(frame, kernel, frame.tiles_per_view, self.tile * self.tile, args)
        if forgets:
            blocks, threads = self._launch_1d(int(target.shape[0]))
            self._go(frame, self.k.apply_increments_kernel, blocks, threads,
                     (target, frame.ids, frame.sizes, frame.packed, frame.order, float(rules.decay),
                      float(rules.prior), conc))
        self._device_newer = True
        pending = DeviceCounts(self.ops, counts, surprise)
        self._pending_counts = pending
        return pending

    def _rule_args(self, frame: CudaFrame, inputs: "FrameLabels", conc: Any) -> tuple[tuple[Any, ...], Any]:
        """The update kernel's arguments of the changing world's rules (transient mask, measured depth, tolerances,
        depth scale, pair rows, moments before the update, surprise image) and the surprise image on the device
        (None when not asked for). A rule the frame does not use gets a placeholder; the surprise's moments are
        made here, before the update changes the map (one launch)."""
        rules = inputs.rules
        transient = self._no_transient
        if rules.any_transient:
            key = np.ascontiguousarray(rules.transient, dtype=np.bool_).tobytes()
            if self._transient[0] != key:
                self._transient = (key, self.ops.kernel_array(self.ops.upload(rules.transient, np.bool_)))
            transient = self._transient[1]
        depth = self._no_image if inputs.depth is None else self._frame_input("depth", inputs.depth)
        mom = surprise = None
        if inputs.want_surprise:
            mom = self._moments(frame, conc)
            surprise = self._frame_buffer("surprise", inputs.labels.shape, np.float32)
        return ((transient, depth, float(rules.tol_abs), float(rules.tol_rel), float(rules.depth_scale),
                 frame.pair_row, self._no_image if mom is None else mom,
                 self._no_image if surprise is None else surprise), surprise)

    def _increments(self, frame: CudaFrame, num_classes: int) -> Any:
        """The (pairs, C) f64 zeroed scratch of an update with forgetting (the plan's, kept; a batch's, made)."""
        if frame.plan is not None:
            return frame.plan.increment_buffer(num_classes)
        return self.ops.zeros((max(frame.num_pairs, 1), num_classes), np.float64)

    def _frame_buffer(self, name: str, shape: tuple[int, ...], dtype: Any) -> Any:
        """A device buffer per (name, shape, dtype) that a kernel fills (the same address every frame of that size:
        the launch stays bound)."""
        key = (name, tuple(shape), np.dtype(dtype).str)
        dev = self._inputs.get(key)
        if dev is None:
            if len(self._inputs) >= 16:  # image sizes and dtypes of a long-lived process: bounded
                self._inputs.clear()
                self.launches.clear()
            dev = self._inputs[key] = self.ops.empty(shape, dtype)
        return dev

    def _frame_input(self, name: str, host: np.ndarray) -> Any:
        """A device buffer per (name, shape, dtype) holding ``host`` (copied asynchronously): the same address every
        frame of that size, so the update's launch stays bound."""
        dev = self._frame_buffer(name, host.shape, host.dtype)
        self.ops.host_to_device(dev, host, name)
        return dev

    def _go(self, frame: CudaFrame, kernel: Any, grid: int, block: int, args: tuple[Any, ...]) -> None:
        """Launch ``kernel``: bound once for a plan frame (its buffers keep their addresses), plainly for a batch."""
        if frame.plan is not None:
            self.launches.launch(kernel, grid, block, *args)
        else:
            kernel[grid, block](*args)

    def _soft_tables(self, soft: "SoftLabels") -> tuple[Any, Any]:
        """The sensor model's edges and table on the device, uploaded once per SoftLabels object (SemanticMap
        keeps one until its sensor model changes; the table is C B x C float64)."""
        if self._soft is None or self._soft[0] is not soft:
            self._soft = (soft, self.ops.upload(soft.edges, np.float64), self.ops.upload(soft.table, np.float64))
        return self._soft[1], self._soft[2]

    # ------------------------------------------------------------------ render
    def _moments(self, frame: CudaFrame, conc: Any) -> Any:
        num_classes = int(conc.shape[1])
        r = int(frame.rows.shape[0])
        if frame.plan is not None:
            mom = frame.plan.moment_buffer(num_classes)
        else:
            mom = self.ops.empty((max(r, 1), 2 * num_classes + 1), np.float32)
        if r:
            blocks, threads = self._launch_1d(r * num_classes)  # a thread per (row, class)
            self._go(frame, self.k.moments_kernel, blocks, threads, (conc, frame.rows, frame.row_count, mom))
        return mom

    def _params(self, settings: "RenderSettings") -> tuple[Any, Any]:
        """(params (RENDER_PARAMS,) f64, knots (2, K) f64) on the device, uploaded again only when they change."""
        k = self.k
        cmap = settings.confidence
        host = np.zeros(k.RENDER_PARAMS)
        host[k.P_EBG], host[k.P_VBG], host[k.P_SBG] = settings.e_bg, settings.v_bg, settings.s_bg
        host[k.P_RGB:k.P_RGB + 3] = settings.bg_rgb
        host[k.P_THRESHOLD], host[k.P_DEPTH_SCALE] = settings.unknown_threshold, settings.depth_scale
        host[k.P_IGNORE] = settings.ignore_label
        knots = np.zeros((2, 1))
        if cmap is not None:
            host[k.P_COEF:k.P_COEF + 3] = cmap.coef
            knots = np.stack([np.asarray(cmap.knots_x, dtype=np.float64), np.asarray(cmap.knots_y, dtype=np.float64)])
        key = (host.tobytes(), knots.tobytes())
        if self._params_key != key:
            self._params_dev = (self.ops.kernel_array(self.ops.upload(host, np.float64)),
                                self.ops.kernel_array(self.ops.upload(knots, np.float64)))
            self._params_key = key
        return self._params_dev

    def _planes(self, planes: np.ndarray) -> Any:
        """The plane offsets on the device, uploaded once per layout (a frame of the same size and outputs reuses
        them)."""
        key = planes.tobytes()
        dev = self._planes_dev.get(key)
        if dev is None:
            if len(self._planes_dev) > 64:  # sizes and output sets of a long-lived process: bounded
                self._planes_dev.clear()
            dev = self._planes_dev[key] = self.ops.kernel_array(self.ops.upload(planes, np.int64))
        return dev

    def _word_views(self, words: Any) -> tuple[Any, ...]:
        """The int32, float32, uint8 and float64 views of an output buffer, as kernel arguments."""
        return tuple(self.ops.view_as(words, dt) for dt in (np.int32, np.float32, np.uint8, np.float64))

    def _output_buffer(self, words: int) -> tuple[Any, tuple[Any, ...]]:
        """The device output buffer (int32 words) and its kernel views, grown when a frame needs more, kept
        between frames."""
        if self._out is None or int(self._out.shape[0]) < words:
            self._out = self.ops.empty(words + (words % 2), np.int32)  # even: the header is read as float64
            self._out_views = self._word_views(self._out)
        return self._out, self._out_views

    def _launch_render(self, frame: CudaFrame, conc: Any, settings: "RenderSettings", planes: np.ndarray,
                       out_views: tuple[Any, ...], scores: Any, score: bool,
                       mass: tuple[Any, Any, Any] | None = None) -> None:
        """One launch of the render kernel over all views x tiles of ``frame``."""
        self._bind()
        k = self.k
        num_classes = int(conc.shape[1])
        mom = self._moments(frame, conc)
        params, knots = self._params(settings)
        kernel = k.make_render_kernel(num_classes, self.tile, bool(score), bool(settings.probabilities and not score),
                                      k.RENDER_CLASS_CHUNK, mass is not None)
        mass_w, mass_edges, mass_out = mass if mass is not None else (self._empty_f64, self._empty_f64,
                                                                     self._empty_f64)
        self._go(frame, kernel, len(frame.cameras) * frame.tiles_per_view, self.tile * self.tile,
                 (frame.offsets, frame.order, frame.packed, frame.colors, frame.pair_row, mom, params, knots,
                  self._planes(planes), frame.width, frame.height, frame.tiles_x, frame.tiles_per_view,
                  *out_views, scores, mass_w, mass_edges, mass_out))

    def render_view(self, frame: CudaFrame, concentrations: np.ndarray, settings: "RenderSettings") -> FrameImages:
        """The view's requested outputs made on the device in final form (:mod:`css_ros.engine.final_form`): the
        render kernel writes each requested plane, packed, into one reused device buffer and reduces U_var / U_exp
        there; one copy brings exactly those bytes to the host, and the images are views into that copy."""
        if frame.plan is not None:
            raise ValueError("a plan frame is rendered by observe_view / render_query (it may need doing again)")
        return self._images(frame, *self._render_host(frame, concentrations, settings))

    def _render_host(self, frame: CudaFrame, concentrations: np.ndarray,
                     settings: "RenderSettings") -> tuple[np.ndarray, PlaneLayout, int]:
        """Render ``frame`` into the output buffer and copy it to the host (the one synchronisation): the header
        brings the U sums, the pending update's counts and the frame's sizes."""
        conc = self._device_concentrations_for_read(concentrations)
        num_classes = int(conc.shape[1])
        pending, self._pending_counts = self._pending_counts, None
        if pending is not None and pending.ready:
            pending = None
        shape = (0, 0) if pending is None else pending.surprise_shape
        layout = plane_layout(frame.height, frame.width, num_classes, settings, shape[0] * shape[1])
        out, views = self._output_buffer(layout.words)
        self.ops.zero_words(out, HEADER_WORDS)
        if pending is not None:  # an update's counts ride along in the header, its surprise after the planes
            self.ops.copy_words(out, COUNT_WORDS, pending.device)
            if pending.surprise_device is not None:
                self.ops.copy_words(out, layout.surprise, pending.surprise_device)
        self.ops.copy_words(out, SIZE_WORDS, frame.sizes)
        self._launch_render(frame, conc, settings, layout.planes, views, self._empty_scores, False)
        host = self.ops.download_words(out, layout.words)  # the frame's one copy (and synchronisation)
        if pending is not None:
            pending.arrived(host[COUNT_WORDS:COUNT_WORDS + NUM_COUNTS], layout.surprise_image(host, shape))
        return host, layout, num_classes

    @staticmethod
    def _images(frame: CudaFrame, host: np.ndarray, layout: PlaneLayout, num_classes: int) -> FrameImages:
        """The view's images: numpy views into the copied words."""
        return layout.images(host, frame.height, frame.width, num_classes)

    def render(self, frame: CudaFrame, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> RenderBuffers:
        """The contract's raw buffers, from :meth:`render_view` (float32 precision; labels without the unknown
        threshold; colour quantised to 1/255): for callers of the raw form only, the map renders through
        ``render_view``."""
        settings = RenderSettings(e_bg, v_bg, s_bg, (float(bg_rgb[0]), float(bg_rgb[1]), float(bg_rgb[2])),
                                  float("inf"), -1, 1.0, None, frozenset(IMAGE_OUTPUTS), bool(want_probs))
        img = self.render_view(frame, concentrations, settings)
        f64 = lambda a: np.asarray(a, dtype=np.float64)  # noqa: E731
        assert img.labels is not None and img.rgb is not None
        return RenderBuffers(labels=img.labels, expectation=f64(img.expectation), variance=f64(img.variance),
                             background=f64(img.background), evidence=f64(img.evidence), rgb=img.rgb / 255.0,
                             probabilities=None if img.probabilities is None else f64(img.probabilities),
                             depth=f64(img.depth))

    def _device_concentrations_for_read(self, host: np.ndarray) -> Any:
        """Like _device_concentrations, but keeps a newer device state (a render after an update)."""
        if self._device_newer and host is self._host and self._conc is not None:
            return self._conc_k
        return self._device_concentrations(host)

    # ------------------------------------------------------------------ query views
    def _groups(self, cameras: Sequence["Camera"]) -> dict[tuple[int, int], list[int]]:
        groups: dict[tuple[int, int], list[int]] = {}
        for i, cam in enumerate(cameras):
            groups.setdefault((int(cam.width), int(cam.height)), []).append(i)
        return groups

    def _score_settings(self, e_bg: float, v_bg: float, s_bg: float,
                        outputs: frozenset[str] = frozenset()) -> "RenderSettings":
        """Settings of a scored view: no colour, no threshold, no confidence; ``outputs`` the images wanted."""
        return RenderSettings(e_bg, v_bg, s_bg, (0.0, 0.0, 0.0), float("inf"), -1, 1.0, None, outputs, False)

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]]:
        """(expectation, variance, mass) of the views one by one (the contract's image form; the batched device
        paths are :meth:`score_views`, :meth:`view_masses` and :meth:`select_views`)."""
        settings = self._score_settings(e_bg, v_bg, s_bg, frozenset({"expectation", "variance"}))
        cams = list(cameras)
        masses = list(self.view_masses(cams, concentrations, e_bg, v_bg, s_bg, mass_weights)) \
            if mass_weights is not None else [None] * len(cams)
        for cam, mass in zip(cams, masses):
            img = self.render_view(self.prepare_views([cam], want_color=False), concentrations, settings)
            assert img.expectation is not None and img.variance is not None
            yield img.expectation.astype(np.float64), img.variance.astype(np.float64), mass

    def _score_chunks(self, idx: list[int], width: int, height: int) -> list[list[int]]:
        """``idx`` (views of one size) cut into batches whose (view, Gaussian) pairs should fit
        :data:`SCORE_BATCH_PAIRS` (the pairs per view of this size measured at the last batch, :data:`HEADROOM`
        above; a quarter of the model before any), so that a batch's buffers stay within a bounded memory whatever
        the number of candidates."""
        per_view = self._pairs_per_view.get((width, height), max(1.0, self.num_gaussians / 4))
        size = max(1, int(SCORE_BATCH_PAIRS // max(1.0, HEADROOM * per_view)))
        return [idx[i:i + size] for i in range(0, len(idx), size)]

    def _scored_groups(self, cameras: list["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                       s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None"
                       ) -> Iterator[tuple[list[int], CudaFrame, Any, Any]]:
        """Per batch of views of one size (:meth:`_score_chunks`): (indices into ``cameras``, the batch's frame, its
        (V, 2) f64 score sums on the device, the (M,) f64 evidence mass per pair on the device or None), every stage
        one launch for the batch. Callers keep of a batch only what they need and drop its frame and mass before
        asking for the next (the frame's buffers are the largest part of a scoring's memory: with the previous batch
        still referenced, two batches' buffers were alive at the peak)."""
        conc = self._device_concentrations_for_read(concentrations)
        settings = self._score_settings(e_bg, v_bg, s_bg)
        no_planes = np.full(NUM_PLANES, -1, dtype=np.int64)
        weights_dev = edges_dev = None
        if mass_weights is not None:
            edges_dev = self.ops.upload(mass_weights[0], np.float64)
            weights_dev = self.ops.upload(mass_weights[1], np.float64)
        for (width, height), same_size in self._groups(cameras).items():
            for idx in self._score_chunks(same_size, width, height):
                frame = self.prepare_views([cameras[i] for i in idx], want_color=False)
                self._pairs_per_view[(width, height)] = max(1.0, frame.num_pairs / len(idx))
                scores = self.ops.zeros((len(idx), 2), np.float64)
                mass = None
                if weights_dev is not None:
                    mass = self.ops.zeros(max(frame.num_pairs, 1), np.float64)
                    self._launch_render(frame, conc, settings, no_planes, self._empty_views, scores, True,
                                        (weights_dev, edges_dev, mass))
                else:
                    self._launch_render(frame, conc, settings, no_planes, self._empty_views, scores, True)
                yield idx, frame, scores, mass
                del frame, scores, mass    # the next batch's buffers are made with this one's gone

    def _pair_masses(self, idx: list[int], frame: CudaFrame, mass: Any) -> "PairMasses":
        """What the gains need of a batch, copied out of its frame so that the frame's buffers can go."""
        m = frame.num_pairs
        if m == 0 or mass is None:
            return PairMasses(idx, 0, None, None, None)
        return PairMasses(idx, m, self.ops.copy(frame.views[:m]), self.ops.copy(frame.ids[:m]),
                          self.ops.copy(mass[:m]))

    def _moment_sums(self, concentrations: np.ndarray) -> Any:
        """(N, 2) f64 (S, Q) of every Gaussian with the scoring prior (info_gain.MomentSums.of), on the device."""
        conc = self._device_concentrations_for_read(concentrations)
        sq = self.ops.empty((max(self.num_gaussians, 1), 2), np.float64)
        if self.num_gaussians:
            blocks, threads = self._launch_1d(self.num_gaussians)
            self.k.moment_sums_kernel[blocks, threads](conc, float(INFO_GAIN_PRIOR), sq)
        return sq

    def _gains(self, batches: list["PairMasses"], sq: Any, importance: Any, scale: float, num_views: int,
               gains: Any = None) -> Any:
        """(V,) f64 info gain of every view on the device (added to ``gains`` when given): one launch per batch over
        its pairs."""
        if gains is None:
            gains = self.ops.zeros(max(num_views, 1), np.float64)
        for pm in batches:
            self._add_gains(pm.idx, pm.num_pairs, pm.views, pm.ids, pm.mass, sq, importance, scale, gains)
        return gains

    def _add_gains(self, idx: list[int], num_pairs: int, views: Any, ids: Any, mass: Any, sq: Any, importance: Any,
                   scale: float, gains: Any) -> None:
        """gains[idx[view]] += each pair's drop of the expected variance (one launch over the batch's pairs)."""
        if num_pairs == 0 or mass is None:
            return
        slot = self.ops.upload(np.asarray(idx, dtype=np.int32))[views[:num_pairs]]
        blocks, threads = self._launch_1d(num_pairs)
        self.k.view_gain_kernel[blocks, threads](mass, slot, ids[:num_pairs], sq, importance, float(scale), gains)

    def score_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None",
                    importance: np.ndarray | None, pixel_scale: float) -> np.ndarray:
        """(V, 3) float64 (U_var, U_exp, info_gain) per view: the views of one size projected, sorted and rendered
        in one launch per stage per batch (:meth:`_score_chunks`); the U sums and each pair's evidence mass are
        reduced on the device, the gains by one more launch per batch before its buffers go; 3 V numbers come
        back."""
        cams = list(cameras)
        result = np.full((len(cams), 3), np.nan)
        if not cams:
            return result
        gains = sq = imp = None
        if mass_weights is not None:
            imp = self._empty_f64 if importance is None else self.ops.upload(importance, np.float64)
            sq = self._moment_sums(concentrations)
            gains = self.ops.zeros(len(cams), np.float64)
        sums: list[tuple[list[int], int, Any]] = []
        for idx, frame, scores, mass in self._scored_groups(cams, concentrations, e_bg, v_bg, s_bg, mass_weights):
            sums.append((idx, frame.width * frame.height, scores))
            if gains is not None:
                self._add_gains(idx, frame.num_pairs, frame.views, frame.ids, mass, sq, imp, pixel_scale, gains)
            del frame, mass
        for idx, pixels, scores in sums:
            values = self.ops.download(scores)
            for row, i in enumerate(idx):
                result[i, :2] = uncertainty_from_sums(float(values[row, 0]), float(values[row, 1]), pixels)
        if gains is not None:
            result[:, 2] = self.ops.download(gains)[:len(cams)]
        return result

    def view_masses(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray]"
                    ) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """Per view, (model ids, evidence mass) of its visible Gaussians, from the batched device walk."""
        cams = list(cameras)
        out: list[tuple[np.ndarray, np.ndarray]] = [(np.zeros(0, np.int64), np.zeros(0))] * len(cams)
        for idx, frame, _, mass in self._scored_groups(cams, concentrations, e_bg, v_bg, s_bg, mass_weights):
            m = frame.num_pairs
            if m == 0 or mass is None:
                del frame, mass
                continue
            views = self.ops.download(frame.views[:m])
            ids = self.ops.download(frame.ids[:m]).astype(np.int64)
            values = self.ops.download(mass[:m])
            del frame, mass
            for row, i in enumerate(idx):
                sel = views == row
                order = np.argsort(ids[sel], kind="stable")
                out[i] = (ids[sel][order], values[sel][order])
        yield from out

    def select_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray]", importance: np.ndarray | None,
                     pixel_scale: float, k: int) -> SelectedViews:
        """The greedy batch on the device: the pairs' evidence mass once, then per pick one gain launch per image
        size, V gains back, and one launch moving the chosen view's Gaussians' (S, Q) as its expected observation
        would (the numba path's result within float32 rounding of the mass)."""
        cams = list(cameras)
        groups: list[PairMasses] = []
        for idx, frame, _, mass in self._scored_groups(cams, concentrations, e_bg, v_bg, s_bg, mass_weights):
            groups.append(self._pair_masses(idx, frame, mass))
            del frame, mass
        sq = self._moment_sums(concentrations)
        imp = self._empty_f64 if importance is None else self.ops.upload(importance, np.float64)
        chosen: list[int] = []
        gains: list[float] = []
        for _ in range(min(int(k), len(cams))):
            scores = self.ops.download(self._gains(groups, sq, imp, pixel_scale, len(cams)))[:len(cams)]
            scores[chosen] = -np.inf
            best = int(np.argmax(scores))
            chosen.append(best)
            gains.append(float(scores[best]))
            for pm in groups:
                if best in pm.idx and pm.num_pairs:
                    blocks, threads = self._launch_1d(pm.num_pairs)
                    self.k.observe_expected_kernel[blocks, threads](pm.mass, pm.views, pm.ids, pm.idx.index(best),
                                                                    float(pixel_scale), sq)
        return SelectedViews(np.array(chosen, dtype=np.int64), np.array(gains))
