"""The CUDA backend: :class:`CudaBackend` implements the RasterBackend protocol with the numba-cuda
kernels of :mod:`.kernels`; device-wide sorts and scans come from the array library of
:mod:`.arrays` (torch.cuda on a GPU, numpy under the simulator).

State on the device: the model (means, 3D covariances, opacities, largest std, SH) and the
concentrations (N, C) float64. SemanticMap's host array is kept coherent lazily: the backend
uploads it when the host side may have changed (first use, after ``host_view`` handed it out, or a
different array) and downloads the device copy when the host asks for it (``host_view``). Per
observed frame the only transfers are the labels/weights in and one (H, W, 9) float32 array out (with a
sensor model, also its tables once and the update's no-depth count: one more synchronisation).
"""
from __future__ import annotations

import threading
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from ...errors import CssError
from ..backends import RasterBackend
from ..buffers import RenderBuffers
from ..spec import TILE_SIZE
from ..splat_math import CAM_COLS, camera_row
from .arrays import import_cuda, make_ops, simulator_enabled

if TYPE_CHECKING:
    from ..camera import Camera
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
        the render needs (each once).
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
    pair_row: Any
    rows: Any


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
        self.means = ops.upload(model.means, np.float64)
        self.cov3d = ops.upload(cov6, np.float64)
        self.opacities = ops.upload(model.opacities, np.float64)
        self.max_std = ops.upload(scales.max(axis=1) if len(scales) else np.zeros(0), np.float64)
        self.sh = ops.upload(model.sh, np.float32)
        self._capacity = {1: max(1, self.num_gaussians)}  # projection rows per batch size (grown on demand)
        self._conc: Any = None
        self._host: np.ndarray | None = None
        self._host_dirty = True
        self._device_newer = False
        self._soft: tuple[Any, Any, Any] | None = None  # (SoftLabels, edges, table on the device)

    def _probe(self) -> None:
        """Compile and run the smallest kernel once, so that a broken stack (numba-cuda vs numpy,
        driver, toolkit) fails here, at start, as one CssError naming cause and fix, not as a
        traceback at the first frame."""
        try:
            conc = self.ops.upload(np.ones((1, 2)), np.float64)
            out = self.ops.empty((1, 5), np.float32)
            self.k.moments_kernel[1, 1](conc, self.ops.upload(np.zeros(1, np.int32)), out)
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
            self._device_newer = False
        elif self._host_dirty or host is not self._host:
            self.ops.copy_into(self._conc, host)
            self._device_newer = False
        self._host, self._host_dirty = host, False
        return self._conc

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
            counter = ops.zeros(1, np.int64)  # int64: cannot wrap (V N < 2^63)
            packed = ops.empty((cap, k.PACK_COLS), np.float64)
            bbox = ops.empty((cap, 4), np.int32)
            ids = ops.zeros(cap, np.int32)       # rows past the count: valid model rows ...
            views = ops.zeros(cap, np.int32)
            ntiles = ops.zeros(cap, np.int32)    # ... that emit no keys
            colors = ops.empty((cap, 3), np.float32)
            blocks, threads = self._launch_1d(n_views * n)
            if n_views * n:
                k.project_kernel[blocks, threads](self.means, self.cov3d, self.opacities, self.max_std, self.sh,
                                                  cam_dev, float(width), float(height), self.tile, bool(want_color),
                                                  cap, counter, packed, bbox, ids, views, ntiles, colors)
            ends = ops.cumsum(ntiles)
            m, total = ops.scalars(counter[0], ends[cap - 1])  # the frame's one device -> host sync
            if m <= cap:
                break
            cap = m
        self._capacity[n_views] = cap
        keys = ops.empty(max(total, 1), np.int32)
        order = ops.empty(max(total, 1), np.int32)
        if m:
            # depth order of the pairs (positive float32 depths order as their int32 bit patterns), then the
            # tile keys emitted front to back and sorted stably by (view, tile) alone: two 32-bit radix sorts
            _, by_depth = ops.sort_stable(ops.float32_bits(packed[:m, 7]))
            nt_depth = ntiles[by_depth]
            first = ops.cumsum(nt_depth) - nt_depth
            blocks, threads = self._launch_1d(m)
            k.emit_keys_kernel[blocks, threads](bbox, views, by_depth, first, m, self.tile, tiles_x, tiles_per_view,
                                                keys, order)
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
        return CudaFrame(cams, width, height, tiles_x, tiles_per_view, m, offsets, order, packed, colors,
                         ids, pair_row, rows)

    # ------------------------------------------------------------------ update
    def update(self, frame: CudaFrame, labels: np.ndarray, weights: np.ndarray, concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> int:
        """concentrations[n, c] += sum_i kappa_in y_i^c on the device (labels (H, W) int32, -1 = none;
        weights (H, W) float32). The host array is brought up to date lazily (``host_view``).

        With ``soft`` (a sensor model's tables), the kernel variant of
        :func:`~css_ros.engine.cuda.kernels.make_update_kernel` with ``with_model`` runs instead (one more walk
        per labelled pixel for its expected depth); returns the labelled pixels without any contribution (one
        device -> host transfer), else 0."""
        self._bind()
        conc = self._device_concentrations(concentrations)
        num_classes = int(conc.shape[1])
        if soft is not None and tuple(soft.table.shape) != (num_classes * soft.num_bins, num_classes):
            raise ValueError(f"sensor-model table of shape {tuple(soft.table.shape)} for {num_classes} classes and "
                             f"{soft.num_bins} depth bins")
        if frame.num_pairs == 0:  # nothing is seen: every labelled pixel is without depth
            return 0 if soft is None else int(np.count_nonzero((labels >= 0) & (weights > 0)))
        ops = self.ops
        lab = ops.upload_frame("labels", labels, np.int32)
        wts = ops.upload_frame("weights", weights, np.float32)
        launch = (frame.tiles_per_view, self.tile * self.tile)
        if soft is None:
            kernel = self.k.make_update_kernel(num_classes, self.tile)
            kernel[launch](frame.offsets, frame.order, frame.packed, frame.ids, lab, wts, frame.tiles_x, conc)
            self._device_newer = True
            return 0
        edges, table = self._soft_tables(soft)
        no_depth = ops.zeros(1, np.int64)
        kernel = self.k.make_update_kernel(num_classes, self.tile, True, soft.num_bins)
        kernel[launch](frame.offsets, frame.order, frame.packed, frame.ids, lab, wts, frame.tiles_x, conc,
                       edges, table, no_depth)
        self._device_newer = True
        return ops.scalars(no_depth[0])[0]

    def _soft_tables(self, soft: "SoftLabels") -> tuple[Any, Any]:
        """The sensor model's edges and table on the device, uploaded once per SoftLabels object (SemanticMap
        keeps one until its sensor model changes; the table is C B x C float64)."""
        if self._soft is None or self._soft[0] is not soft:
            self._soft = (soft, self.ops.upload(soft.edges, np.float64), self.ops.upload(soft.table, np.float64))
        return self._soft[1], self._soft[2]

    # ------------------------------------------------------------------ render
    def _moments(self, frame: CudaFrame, conc: Any) -> Any:
        ops = self.ops
        r = int(frame.rows.shape[0])
        mom = ops.empty((max(r, 1), 2 * int(conc.shape[1]) + 1), np.float32)
        if r:
            blocks, threads = self._launch_1d(r)
            self.k.moments_kernel[blocks, threads](conc, frame.rows, mom)
        return mom

    def _render(self, frame: CudaFrame, conc: Any, e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
                score: bool, want_probs: bool) -> tuple[Any, Any, Any]:
        self._bind()
        ops = self.ops
        num_classes = int(conc.shape[1])
        n_views = len(frame.cameras)
        mom = self._moments(frame, conc)
        cols = self.k.RENDER_OUT_COLS
        if score:
            out = ops.empty((1, 1, 1, cols), np.float32)
            scores = ops.zeros((n_views, 2), np.float64)
        else:
            out = ops.empty((n_views, frame.height, frame.width, cols), np.float32)
            scores = ops.zeros((1, 2), np.float64)
        probs = ops.empty((n_views, frame.height, frame.width, num_classes) if want_probs else (1, 1, 1, 1),
                          np.float32)
        kernel = self.k.make_render_kernel(num_classes, self.tile, bool(score), bool(want_probs),
                                           self.k.RENDER_CLASS_CHUNK)
        kernel[n_views * frame.tiles_per_view, self.tile * self.tile](
            frame.offsets, frame.order, frame.packed, frame.colors, frame.pair_row, mom,
            float(e_bg), float(v_bg), float(s_bg), ops.upload(np.asarray(bg_rgb, dtype=np.float64)),
            frame.width, frame.height, frame.tiles_x, frame.tiles_per_view, out, probs, scores)
        return out, probs, scores

    def render(self, frame: CudaFrame, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> RenderBuffers:
        """Composite colour, E, Var (argmax class), kappa_b, evidence and the expected depth (splat units, NaN
        where nothing is rendered); one transfer of (H, W, 9) f32."""
        conc = self._device_concentrations_for_read(concentrations)
        out, probs, _ = self._render(frame, conc, e_bg, v_bg, s_bg, bg_rgb, False, want_probs)
        host = self.ops.download_frame("render", out)[0]
        f64 = lambda a: np.ascontiguousarray(a, dtype=np.float64)  # noqa: E731
        return RenderBuffers(
            labels=np.ascontiguousarray(host[..., 0], dtype=np.int32),
            expectation=f64(host[..., 1]), variance=f64(host[..., 2]), background=f64(host[..., 3]),
            evidence=f64(host[..., 4]), rgb=f64(host[..., 5:8]),
            probabilities=f64(self.ops.download(probs)[0]) if want_probs else None, depth=f64(host[..., 8]))

    def _device_concentrations_for_read(self, host: np.ndarray) -> Any:
        """Like _device_concentrations, but keeps a newer device state (a render after an update)."""
        if self._device_newer and host is self._host and self._conc is not None:
            return self._conc
        return self._device_concentrations(host)

    # ------------------------------------------------------------------ query views
    def _groups(self, cameras: Sequence["Camera"]) -> dict[tuple[int, int], list[int]]:
        groups: dict[tuple[int, int], list[int]] = {}
        for i, cam in enumerate(cameras):
            groups.setdefault((int(cam.width), int(cam.height)), []).append(i)
        return groups

    #: the info gain's evidence mass is not computed on the GPU yet (score_views gives NaN gains)
    scores_mass = False

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, None]]:
        """(expectation, variance, None) of the views, rendered in one batch per image size (no evidence mass)."""
        cams = list(cameras)
        if not cams:
            return
        conc = self._device_concentrations_for_read(concentrations)
        images: list[Any] = [None] * len(cams)
        for idx in self._groups(cams).values():
            frame = self.prepare_views([cams[i] for i in idx], want_color=False)
            out, _, _ = self._render(frame, conc, e_bg, v_bg, s_bg, np.zeros(3), False, False)
            host = self.ops.download(out)
            for row, i in enumerate(idx):
                images[i] = (host[row, ..., 1].astype(np.float64), host[row, ..., 2].astype(np.float64), None)
        yield from images

    def score_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float) -> np.ndarray:
        """(V, 2) float64 (U_var, U_exp) of SPEC §6 per view: all views of one size projected, sorted
        and rendered in one launch per stage; the per-view sums are reduced on the device, so only
        2 V numbers come back."""
        cams = list(cameras)
        result = np.empty((len(cams), 2))
        if not cams:
            return result
        conc = self._device_concentrations_for_read(concentrations)
        for (width, height), idx in self._groups(cams).items():
            frame = self.prepare_views([cams[i] for i in idx], want_color=False)
            _, _, scores = self._render(frame, conc, e_bg, v_bg, s_bg, np.zeros(3), True, False)
            sums = self.ops.download(scores)
            npix = float(width * height)
            result[idx, 0] = np.exp(sums[:, 0] / npix)
            result[idx, 1] = 1.0 - sums[:, 1] / npix
        return result
