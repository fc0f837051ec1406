"""Rasteriser backends behind one small protocol; adding a backend is adding a registry entry."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Protocol

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

    def frame_ids(self, frame: Any) -> np.ndarray: ...

    def accumulate(self, frame: Any, labels: np.ndarray, weights: np.ndarray,
                   num_classes: int) -> tuple[np.ndarray, np.ndarray]: ...

    def render(self, frame: Any, expect: np.ndarray, var: np.ndarray, totals: np.ndarray,
               e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
               want_probs: bool) -> "RenderBuffers": ...


class NumbaBackend:
    """Compiled CPU path: numba projection, tile binning and per-pixel kernels.

    ``accumulate`` records each pixel's contributions; a ``render`` of the same frame (as in
    ``SemanticMap.observe``) replays them instead of compositing a second time.
    """

    def __init__(self, model: "GaussianModel") -> None:
        from .projection import GaussianGeometry
        from .raster import ContributionStore

        self.geometry = GaussianGeometry.from_model(model)
        self._store = ContributionStore()

    def prepare(self, camera: "Camera") -> Any:
        from .projection import project
        from .raster import bin_tiles

        proj = project(self.geometry, camera)
        return proj, bin_tiles(proj, camera.width, camera.height), camera

    def frame_ids(self, frame: Any) -> np.ndarray:
        return frame[0].ids

    def accumulate(self, frame: Any, labels: np.ndarray, weights: np.ndarray,
                   num_classes: int) -> tuple[np.ndarray, np.ndarray]:
        from .raster import accumulate_update

        proj, bins, _ = frame
        self._store.owner = None
        increments = accumulate_update(proj, bins, labels, weights, num_classes, self._store)
        self._store.owner = frame
        return proj.ids, increments

    def render(self, frame: Any, expect: np.ndarray, var: np.ndarray, totals: np.ndarray,
               e_bg: float, v_bg: float, s_bg: float, bg_rgb: np.ndarray,
               want_probs: bool) -> "RenderBuffers":
        from .raster import render_semantic

        proj, bins, camera = frame
        store = self._store if self._store.owner is frame else None
        return render_semantic(proj, bins, camera.width, camera.height, expect, var, totals,
                               e_bg, v_bg, s_bg, bg_rgb, want_probs, store)


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
