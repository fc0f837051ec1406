"""The backend registry: the one place that knows every rasteriser backend (the contract they implement is
:class:`~css_ros.engine.raster_backend.RasterBackend`); adding a backend is adding an entry here."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Callable

from ..errors import CssError

if TYPE_CHECKING:
    from .gaussians import GaussianModel
    from .raster_backend import RasterBackend


def _numba_backend(model: "GaussianModel") -> "RasterBackend":
    from .cpu.backend import NumbaBackend  # numba is imported only when this backend is asked for

    return NumbaBackend(model)


def _torch_backend(model: "GaussianModel") -> "RasterBackend":
    from .torch.raster import TorchBackend  # torch is imported only when this backend is asked for

    return TorchBackend(model)


def _cuda_backend(model: "GaussianModel", device: int | None = None) -> "RasterBackend":
    from .cuda.backend import CudaBackend  # numba.cuda is imported only when this backend is asked for

    return CudaBackend(model, device=device)


BACKENDS: dict[str, Callable[..., "RasterBackend"]] = {
    "numba": _numba_backend,
    "torch": _torch_backend,
    "cuda": _cuda_backend,
}


def make_backend(name: str, model: "GaussianModel", **options: Any) -> "RasterBackend":
    """Instantiate the backend registered under ``name`` for ``model`` (``options``, e.g. ``device``,
    go to its factory)."""
    try:
        factory = BACKENDS[name]
    except KeyError:
        raise CssError(f"unknown backend '{name}' (choose from {', '.join(BACKENDS)})") from None
    return factory(model, **options)
