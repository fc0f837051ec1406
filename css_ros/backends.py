"""Rasteriser backends behind one small protocol; adding a backend is adding a registry entry."""
from __future__ import annotations

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

        Measured alternatives that were not faster on 2 cores (benchmarks/README.md): one moments
        table for the union of a batch's visible Gaussians (its rows are scattered over a table
        much larger than the cache) and one view per thread with serial kernels."""
        from .projection import project
        from .raster import bin_tiles, dirichlet_attributes, render_semantic

        no_colors = np.empty((0, 3))
        for cam in cameras:
            proj = project(self.geometry, cam, self._scratch, view_colors=False)
            bins = bin_tiles(proj, cam.width, cam.height)
            attrs = dirichlet_attributes(concentrations, proj.ids, no_colors)
            buf = render_semantic(proj, bins, cam.width, cam.height, attrs, e_bg, v_bg, s_bg, np.zeros(3), False)
            yield buf.expectation, buf.variance


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
