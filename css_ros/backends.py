"""Rasteriser backends behind one small protocol; adding a backend is adding a registry entry."""
from __future__ import annotations

import queue
from typing import TYPE_CHECKING, Any, Callable, Iterator, Protocol, Sequence

import numpy as np

from .errors import CssError

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel
    from .raster import RenderBuffers


class RasterBackend(Protocol):
    """What SemanticMap needs from a rasteriser. ``frame`` is the backend's own per-view state
    (projection + tile bins), computed once by :meth:`prepare` and reused by update and render."""

    def prepare(self, camera: "Camera") -> Any: ...

    def update(self, frame: Any, labels: np.ndarray, weights: np.ndarray, concentrations: np.ndarray) -> None:
        """concentrations[n, c] += sum_i kappa_in y_i^c (labels (H, W) int32, -1 = none; weights (H, W))."""

    def render(self, frame: Any, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> "RenderBuffers":
        """Composite colour, E, Var (argmax class), kappa_b and evidence from the current concentrations."""

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float) -> Iterator[tuple[np.ndarray, np.ndarray]]:
        """(expectation, variance) images of several query views of one map state, in order: the
        inputs of U_var and U_exp. Exactly what ``render`` gives for them, possibly computed faster."""


class NumbaBackend:
    """Compiled CPU path: numba projection, tile binning and per-pixel kernels.

    ``update`` records each pixel's contributions; a ``render`` of the same frame (as in
    ``SemanticMap.observe``) replays them instead of compositing a second time.
    """

    def __init__(self, model: "GaussianModel") -> None:
        from .projection import GaussianGeometry, ProjectionScratch
        from .raster import ContributionStore

        self.geometry = GaussianGeometry.from_model(model)
        self._scratch = ProjectionScratch()
        self._store = ContributionStore()
        self._score_scratch: queue.SimpleQueue = queue.SimpleQueue()  # ProjectionScratch per score worker

    def prepare(self, camera: "Camera") -> Any:
        from .projection import project
        from .raster import bin_tiles

        proj = project(self.geometry, camera, self._scratch)
        return proj, bin_tiles(proj, camera.width, camera.height), camera

    def update(self, frame: Any, labels: np.ndarray, weights: np.ndarray, concentrations: np.ndarray) -> None:
        from .raster import accumulate_update, add_increments

        proj, bins, _ = frame
        self._store.owner = None
        acc = accumulate_update(proj, bins, labels, weights, concentrations.shape[1], self._store)
        self._store.owner = frame
        add_increments(concentrations, proj.ids, acc)

    def render(self, frame: Any, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> "RenderBuffers":
        from .raster import dirichlet_attributes, render_semantic

        proj, bins, camera = frame
        attrs = dirichlet_attributes(concentrations, proj.ids, proj.colors)
        store = self._store if self._store.owner is frame else None
        return render_semantic(proj, bins, camera.width, camera.height, attrs,
                               e_bg, v_bg, s_bg, bg_rgb, want_probs, store)

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float) -> Iterator[tuple[np.ndarray, np.ndarray]]:
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

        from .projection import ProjectionScratch, project
        from .raster import bin_tiles, dirichlet_attributes, render_semantic

        no_colors = np.empty((0, 3))

        def score(cam: "Camera", scratch: "ProjectionScratch") -> tuple[np.ndarray, np.ndarray]:
            proj = project(self.geometry, cam, scratch, view_colors=False)
            bins = bin_tiles(proj, cam.width, cam.height)
            attrs = dirichlet_attributes(concentrations, proj.ids, no_colors)
            buf = render_semantic(proj, bins, cam.width, cam.height, attrs, e_bg, v_bg, s_bg, np.zeros(3), False)
            return buf.expectation, buf.variance

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

        def work(cam: "Camera") -> tuple[np.ndarray, np.ndarray]:
            numba.set_num_threads(1)
            scratch = self._score_scratch.get()
            try:
                return score(cam, scratch)
            finally:
                self._score_scratch.put(scratch)

        with ThreadPoolExecutor(workers, thread_name_prefix="css-score") as pool:
            yield from pool.map(work, cameras[1:])


def _torch_backend(model: "GaussianModel") -> RasterBackend:
    from .raster_torch import TorchBackend

    return TorchBackend(model)


BACKENDS: dict[str, Callable[["GaussianModel"], RasterBackend]] = {
    "numba": NumbaBackend,
    "torch": _torch_backend,
}


def make_backend(name: str, model: "GaussianModel") -> RasterBackend:
    """Instantiate the backend registered under ``name`` for ``model``."""
    try:
        factory = BACKENDS[name]
    except KeyError:
        raise CssError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})") from None
    return factory(model)
