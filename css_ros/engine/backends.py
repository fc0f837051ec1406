"""Rasteriser backends behind one small protocol; adding a backend is adding a registry entry."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable, Iterator, Protocol, Sequence

import numpy as np

from ..errors import CssError

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel
    from .buffers import RenderBuffers


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


def _numba_backend(model: "GaussianModel") -> RasterBackend:
    from .cpu.backend import NumbaBackend  # numba is imported only when this backend is asked for

    return NumbaBackend(model)


def _torch_backend(model: "GaussianModel") -> RasterBackend:
    from .torch.raster import TorchBackend  # torch is imported only when this backend is asked for

    return TorchBackend(model)


def _cuda_backend(model: "GaussianModel", device: int | None = None) -> RasterBackend:
    from .cuda.backend import CudaBackend  # numba.cuda is imported only when this backend is asked for

    return CudaBackend(model, device=device)


BACKENDS: dict[str, Callable[..., RasterBackend]] = {
    "numba": _numba_backend,
    "torch": _torch_backend,
    "cuda": _cuda_backend,
}


def make_backend(name: str, model: "GaussianModel", **options: Any) -> RasterBackend:
    """Instantiate the backend registered under ``name`` for ``model`` (``options``, e.g. ``device``,
    go to its factory)."""
    try:
        factory = BACKENDS[name]
    except KeyError:
        raise CssError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})") from None
    return factory(model, **options)
