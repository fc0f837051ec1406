"""The compiled CPU backend: numba projection, tile binning and per-pixel kernels behind the
:class:`~css_ros.engine.raster_backend.RasterBackend` protocol."""
from __future__ import annotations

import queue
from typing import TYPE_CHECKING, Any, Iterator, Sequence

import numpy as np

from ..raster_backend import RasterBackend, UpdateCounts
from .finalize import finalize, uncertainty
from .projection import GaussianGeometry, ProjectionScratch, project
from .increments import UpdateWorkspace, add_increments
from .kept import Kept
from .raster import (AttributeRows, ContributionStore, accumulate_update, add_increments_and_attributes, bin_tiles,
                     dirichlet_attributes, new_attribute_rows, new_lists, render_semantic)

if TYPE_CHECKING:
    from ..buffers import RenderBuffers
    from ..camera import Camera
    from ..final_form import FrameImages, RenderSettings
    from ..gaussians import GaussianModel
    from ..label_input import FrameLabels
    from ..sensor_model import SoftLabels


class NumbaBackend(RasterBackend):
    """Compiled CPU path: numba projection, tile binning and per-pixel kernels. A frame is projected and binned once
    (:meth:`prepare`); ``update`` walks the voting pixels (:mod:`.composite`) and records their contributions, which a
    ``render`` of the same frame (as in ``SemanticMap.observe``) replays instead of walking a second time."""

    def __init__(self, model: "GaussianModel") -> None:
        self.geometry = GaussianGeometry.from_model(model)
        self._scratch = ProjectionScratch()
        self._workspace = UpdateWorkspace()
        self._store = ContributionStore()
        # kept between frames (engine/cpu/kept.py): the tile lists and attribute rows of observe and render (not of
        # the score workers); a frame is valid until the next prepare
        self._lists = Kept(new_lists)
        self._rows = Kept(new_attribute_rows)
        self._attrs: "tuple[Any, AttributeRows] | None" = None  # (frame, attribute rows) made by observe's update
        self._score_scratch: queue.SimpleQueue = queue.SimpleQueue()  # ProjectionScratch per score worker

    def prepare(self, camera: "Camera") -> Any:
        proj = project(self.geometry, camera, self._scratch)
        return proj, bin_tiles(proj, camera.width, camera.height, kept=self._lists), camera

    def update(self, frame: Any, inputs: "FrameLabels", concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> UpdateCounts:
        return self._update(frame, inputs, concentrations, soft, False)

    def _update(self, frame: Any, inputs: "FrameLabels", concentrations: np.ndarray, soft: "SoftLabels | None",
                with_attributes: bool) -> UpdateCounts:
        """The update; ``with_attributes``: also the render's attribute rows of the updated map, made in the same
        pass over the visible rows (kept for :meth:`render` of this frame)."""
        proj, bins, _ = frame
        self._store.owner = None
        self._attrs = None
        inc, counts, surprise = accumulate_update(proj, bins, inputs, soft, self._workspace, self._store,
                                                  concentrations)
        self._store.owner = frame
        rules = inputs.rules
        if with_attributes:
            self._attrs = (frame, add_increments_and_attributes(concentrations, proj.ids, inc, rules.decay, rules.prior,
                                                                proj.colors, proj.packed, self._rows))
        else:
            add_increments(concentrations, proj.ids, inc, rules.decay, rules.prior)
        self._workspace.done()
        return UpdateCounts(counts, surprise)

    def observe_view(self, camera: "Camera", inputs: "FrameLabels", concentrations: np.ndarray,
                     soft: "SoftLabels | None", settings: "RenderSettings") -> "tuple[FrameImages, UpdateCounts]":
        """Prepare, update (with the render's attribute rows in the same pass) and render the same frame."""
        frame = self.prepare(camera)
        counts = self._update(frame, inputs, concentrations, soft, True)
        return self.render_view(frame, concentrations, settings), counts

    def render(self, frame: Any, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> RenderBuffers:
        proj, bins, camera = frame
        kept, self._attrs = self._attrs, None
        attrs = kept[1] if kept is not None and kept[0] is frame else \
            dirichlet_attributes(concentrations, proj.ids, proj.colors, proj.packed, self._rows)
        store = self._store if self._store.owner is frame else None
        buffers = render_semantic(proj, bins, camera.width, camera.height, attrs, e_bg, v_bg, s_bg, bg_rgb,
                                  want_probs, store=store)
        if store is not None:
            # replayed once; the buffers are kept for the next frame: given back and taken again, their pages
            # faulted in on every frame (~10 % of a biker frame, benchmarks/README.md)
            store.owner = None
        return buffers

    def render_view(self, frame: Any, concentrations: np.ndarray, settings: "RenderSettings") -> "FrameImages":
        """The final outputs in one compiled pass after the render (:mod:`.finalize`)."""
        buf = self.render(frame, concentrations, settings.e_bg, settings.v_bg, settings.s_bg,
                          np.asarray(settings.bg_rgb, dtype=np.float64), settings.probabilities)
        return finalize(buf, settings)

    def uncertainty(self, expectation: np.ndarray, variance: np.ndarray) -> tuple[float, float]:
        return uncertainty(expectation, variance)

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]]:
        """Per view: project (no SH colour), bin, moments of the visible Gaussians, render.

        Small views split badly over the cores (short parallel regions, serial sorting), so views
        after the first are spread over a pool of worker threads, one whole view per thread at a
        time, each running the kernels single-threaded (numba's thread count is per thread; the
        kernels release the GIL). This needs a thread-safe numba threading layer (OpenMP or TBB);
        with the workqueue layer views are scored one after another. Each worker keeps its own
        projection buffers (N x 11 float64) between calls.
        """
        import numba
        from concurrent.futures import ThreadPoolExecutor


        no_colors = np.empty((0, 3))

        def score(cam: "Camera", scratch: "ProjectionScratch") -> tuple[np.ndarray, np.ndarray, Any]:
            proj = project(self.geometry, cam, scratch, view_colors=False)
            bins = bin_tiles(proj, cam.width, cam.height)
            attrs = dirichlet_attributes(concentrations, proj.ids, no_colors, proj.packed)
            buf = render_semantic(proj, bins, cam.width, cam.height, attrs, e_bg, v_bg, s_bg, np.zeros(3), False,
                                  mass_weights=mass_weights)
            mass = None if buf.mass is None else (np.array(proj.ids, dtype=np.int64), buf.mass)
            return buf.expectation, buf.variance, mass

        if not cameras:
            return
        yield score(cameras[0], self._scratch)  # also initialises numba's threading layer
        workers = min(numba.get_num_threads(), len(cameras) - 1)
        if workers < 2 or numba.threading_layer() not in ("omp", "tbb"):
            for cam in cameras[1:]:
                yield score(cam, self._scratch)
            return
        while self._score_scratch.qsize() < workers:
            self._score_scratch.put(ProjectionScratch())

        def work(cam: "Camera") -> tuple[np.ndarray, np.ndarray, Any]:
            numba.set_num_threads(1)
            scratch = self._score_scratch.get()
            try:
                return score(cam, scratch)
            finally:
                self._score_scratch.put(scratch)

        with ThreadPoolExecutor(workers, thread_name_prefix="css-score") as pool:
            yield from pool.map(work, cameras[1:])
