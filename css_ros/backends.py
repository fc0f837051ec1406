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
        """Views are projected SCORE_CHUNK at a time; the Dirichlet moments of the union of their
        visible Gaussians are computed once per chunk (one table, rows looked up per view) instead
        of once per view. Colour is not rendered."""
        from .raster import dirichlet_attributes, render_semantic

        n = concentrations.shape[0]
        no_rgb = np.zeros(3)
        for first in range(0, len(cameras), SCORE_CHUNK):
            frames = [self.prepare(cam) for cam in cameras[first:first + SCORE_CHUNK]]
            seen = np.zeros(n, dtype=np.bool_)
            for proj, _, _ in frames:
                seen[proj.ids] = True
            union = np.flatnonzero(seen)
            table_row = np.empty(n, dtype=np.int32)
            table_row[union] = np.arange(len(union), dtype=np.int32)
            table = dirichlet_attributes(concentrations, union, np.empty((0, 3)))
            for proj, bins, cam in frames:
                buf = render_semantic(proj, bins, cam.width, cam.height, table, e_bg, v_bg, s_bg, no_rgb, False,
                                      None, attr_rows=table_row[proj.ids])
                yield buf.expectation, buf.variance


SCORE_CHUNK = 16  # candidate views projected (and held in memory) together by NumbaBackend.score_images


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
