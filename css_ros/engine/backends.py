"""Rasteriser backends behind one small protocol; adding a backend is adding a registry entry."""
from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, Any, Callable, Iterator, Sequence

import numpy as np

from ..errors import CssError

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel
    from .buffers import RenderBuffers
    from .sensor_model import SoftLabels


class RasterBackend(ABC):
    """What SemanticMap needs from a rasteriser (the backend contract). ``frame`` is the backend's own
    per-view state (projection + tile bins), computed once by :meth:`prepare` and reused by update and
    render. The concentrations are SemanticMap's host array (N, C) float64; a backend that keeps a copy
    on a device (cuda) overrides :meth:`host_read` / :meth:`host_write` to keep the two coherent;
    :meth:`score_views` defaults to reducing :meth:`score_images`."""

    @abstractmethod
    def prepare(self, camera: "Camera") -> Any: ...

    @abstractmethod

    def update(self, frame: Any, labels: np.ndarray, weights: np.ndarray, concentrations: np.ndarray,
               soft: "SoftLabels | None" = None) -> int:
        """concentrations[n, c] += sum_i kappa_in y_i^c (labels (H, W) int32, -1 = none; weights (H, W)).

        With ``soft`` (a sensor model, docs/spec.md "Sensor model"), y_i^c = weight_i * table[label_i * B + b_i, c]
        with b_i the depth bin of the pixel's expected depth sum kappa z / sum kappa. Returns the labelled pixels
        without any contribution (no depth) when ``soft`` is given, else 0."""

    @abstractmethod

    def render(self, frame: Any, concentrations: np.ndarray, e_bg: float, v_bg: float, s_bg: float,
               bg_rgb: np.ndarray, want_probs: bool) -> "RenderBuffers":
        """Composite colour, E, Var (argmax class), kappa_b, evidence and the expected depth from the current
        concentrations."""

    @abstractmethod

    def score_images(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                     s_bg: float, mass_weights: "tuple[np.ndarray, np.ndarray] | None" = None
                     ) -> Iterator[tuple[np.ndarray, np.ndarray, "tuple[np.ndarray, np.ndarray] | None"]]:
        """(expectation, variance, mass) of several query views of one map state, in order: the inputs of U_var,
        U_exp and the info gain. E and Var are exactly what ``render`` gives for them, possibly computed faster.
        With ``mass_weights`` (depth-bin edges in splat units (B + 1,), net vote weight per (label, bin) (C * B,)),
        mass = (model ids (M,), evidence (M,)): what observing the view would add to each visible Gaussian,
        sum_i kappa_in * weight[label_i * B + bin_i] with label_i the rendered argmax; else None."""

    #: whether :meth:`score_images` returns the evidence mass (the info gain); a backend without it gets NaN gains
    scores_mass = True

    def score_views(self, cameras: Sequence["Camera"], concentrations: np.ndarray, e_bg: float, v_bg: float,
                    s_bg: float) -> np.ndarray:
        """(V, 2) float64 (U_var, U_exp) of SPEC §6 per view, from :meth:`score_images`."""
        from .semantic_map import image_uncertainty  # the one definition of U_var / U_exp

        scores = np.empty((len(cameras), 2))
        for i, (expectation, variance, _) in enumerate(self.score_images(cameras, concentrations, e_bg, v_bg,
                                                                          s_bg)):
            scores[i] = image_uncertainty(expectation, variance)
        return scores

    def host_read(self, host: np.ndarray) -> np.ndarray:
        """``host`` up to date, for reading only (reading never forces a re-upload). Host-resident
        backends hand out the array itself (a read-only view would make numba compile a second
        specialisation of every kernel it reaches)."""
        return host

    def host_write(self, host: np.ndarray) -> np.ndarray:
        """``host`` up to date and writable; a device copy is refreshed from it before the next kernel."""
        return host


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
