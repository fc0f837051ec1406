"""A view's outputs in their final form: what a caller asks for, and how every backend delivers it.

A backend's ``render_view`` returns :class:`FrameImages`: the requested images already in their final dtypes
(labels with the unknown threshold applied, float32 moments, uint8 colour, depth in metres, the calibrated
confidence) and U_var / U_exp reduced. The CUDA backend makes them on the device and copies only the requested
planes, once; the numba backend in one compiled pass; :func:`finalize_host` is the plain numpy form (the torch
backend's, and the reference the tests hold the others to).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

import numpy as np

from ..errors import InputError
from .camera import MAX_CAMERA_PIXELS
from .real_array import check_real_array
from .spec import VAR_FLOOR

if TYPE_CHECKING:
    from .buffers import RenderBuffers
    from .sensor_model import ConfidenceMap

#: The per-pixel images of a rendered view (RenderedView's fields); ``probabilities`` is asked for separately.
#: ``surprise`` is made by an observed frame's update (``SemanticMap.observe``); a query render has none.
IMAGE_OUTPUTS: tuple[str, ...] = ("labels", "expectation", "variance", "background", "evidence", "rgb", "depth",
                                  "confidence", "surprise")
#: The images made when ``outputs`` is None: all but the surprise, which is asked for by name (like the
#: probabilities): it costs the update a pass over the visible Gaussians and a gather per contribution, 5-8 % of a
#: CPU frame (benchmarks/README.md), and only change detection reads it (css_node and css_replay ask for it).
DEFAULT_OUTPUTS: tuple[str, ...] = tuple(n for n in IMAGE_OUTPUTS if n != "surprise")


def check_outputs(outputs: Iterable[str] | None) -> frozenset[str]:
    """The set of requested image names (None: :data:`DEFAULT_OUTPUTS`, every image but the surprise).

    Raises:
        InputError: an unknown name, a name that is no str, not a collection, or a plain string (a common slip for
            a one-element list).
    """
    if outputs is None:
        return frozenset(DEFAULT_OUTPUTS)
    if isinstance(outputs, str):
        raise InputError(f"outputs must be a collection of names, not the string {outputs!r} "
                         f"(e.g. outputs=({outputs!r},))")
    if not hasattr(outputs, "__iter__"):
        raise InputError(f"outputs must be a collection of names, got {type(outputs).__name__}")
    items = list(outputs)
    odd = [type(n).__name__ for n in items if not isinstance(n, str)]
    if odd:
        raise InputError(f"outputs must be names (str), got a {odd[0]} (choose from {', '.join(IMAGE_OUTPUTS)})")
    names = frozenset(items)
    unknown = sorted(str(n) for n in names - set(IMAGE_OUTPUTS))
    if unknown:
        raise InputError(f"unknown output(s) {', '.join(unknown)} (choose from {', '.join(IMAGE_OUTPUTS)})")
    return names


@dataclass(frozen=True)
class RenderSettings:
    """Everything a backend needs to turn a render into final outputs.

    Attributes:
        e_bg, v_bg, s_bg: background Dirichlet's E and Var per class and its total S_b.
        bg_rgb: colour behind all Gaussians, RGB in [0, 1].
        unknown_threshold: pixels whose kappa_b exceeds this get ``ignore_label``.
        ignore_label: the "unknown" label value.
        depth_scale: metres per splat unit (depth is returned in metres).
        confidence: the sensor model's calibrated confidence map, or None (no ``confidence`` image).
        outputs: the image names to deliver (:data:`IMAGE_OUTPUTS`); the others are None.
        probabilities: also deliver the (H, W, C) float32 E of every class.
    """

    e_bg: float
    v_bg: float
    s_bg: float
    bg_rgb: tuple[float, float, float]
    unknown_threshold: float
    ignore_label: int
    depth_scale: float
    confidence: "ConfidenceMap | None"
    outputs: frozenset[str]
    probabilities: bool

    def wants(self, name: str) -> bool:
        """Whether image ``name`` is delivered (``confidence`` only with a confidence map)."""
        return name in self.outputs and (name != "confidence" or self.confidence is not None)


@dataclass
class FrameImages:
    """A view's outputs in final form (H, W = the camera's image size); None where not requested.

    labels (H, W) int32 (``ignore_label`` where kappa_b > threshold); expectation, variance, background, evidence,
    depth [m], confidence (H, W) float32; rgb (H, W, 3) uint8; probabilities (H, W, C) float32; u_var, u_exp the
    SPEC §6 image uncertainties (float64 sums over all pixels)."""

    u_var: float
    u_exp: float
    labels: np.ndarray | None = None
    expectation: np.ndarray | None = None
    variance: np.ndarray | None = None
    background: np.ndarray | None = None
    evidence: np.ndarray | None = None
    rgb: np.ndarray | None = None
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None
    probabilities: np.ndarray | None = None


def uncertainty_from_sums(sum_log_var: float, sum_e: float, num_pixels: int) -> tuple[float, float]:
    """(U_var, U_exp) of SPEC §6 from sum_i log max(Var_i, VAR_FLOOR) and sum_i E_i over ``num_pixels`` pixels."""
    if num_pixels <= 0:
        return float("nan"), float("nan")
    return float(np.exp(sum_log_var / num_pixels)), float(1.0 - sum_e / num_pixels)


#: Rounding tolerance of :func:`image_uncertainty`'s range checks (E in [0, 1], Var >= 0).
_UNCERTAINTY_TOL = 1e-6


def _uncertainty_image(name: str, a: object) -> np.ndarray:
    """``a`` as a finite real float64 array of at most MAX_CAMERA_PIXELS values, else InputError naming ``name``."""
    what = f"image_uncertainty: {name}"
    arr = a if isinstance(a, np.ndarray) else check_real_array(a, what)   # an array is sized before any copy
    if arr.size > MAX_CAMERA_PIXELS:
        raise InputError(f"{what} has {arr.size} values, more than an image of the largest camera "
                         f"(MAX_CAMERA_PIXELS = {MAX_CAMERA_PIXELS})")
    arr = check_real_array(arr, what)
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{what} holds non-finite values")
    return arr


def image_uncertainty(expectation: np.ndarray, variance: np.ndarray) -> tuple[float, float]:
    """(U_var, U_exp) of SPEC §6 over all pixels of a view (float64 accumulation).

    Both arrays must be real (bool, integer or float; not complex), of the same non-empty shape of at most
    MAX_CAMERA_PIXELS values and finite, with
    E in [0, 1] and Var >= 0 up to a rounding tolerance of 1e-6 (float32 images of values computed in float64 are
    off by < 1e-7); values within it are used as given (Var floored at VAR_FLOOR before the log).

    Raises:
        InputError: naming the array and the problem.
    """
    e = _uncertainty_image("expectation", expectation)
    var = _uncertainty_image("variance", variance)
    if e.shape != var.shape:
        raise InputError(f"image_uncertainty: expectation {e.shape} and variance {var.shape} differ in shape")
    if e.size == 0:
        raise InputError(f"image_uncertainty: empty images (shape {e.shape})")
    if float(e.min()) < -_UNCERTAINTY_TOL or float(e.max()) > 1.0 + _UNCERTAINTY_TOL:
        raise InputError(f"image_uncertainty: expectation must be in [0, 1], got values in "
                         f"[{float(e.min()):.6g}, {float(e.max()):.6g}]")
    if float(var.min()) < -_UNCERTAINTY_TOL:
        raise InputError(f"image_uncertainty: variance must be >= 0, got a minimum of {float(var.min()):.6g}")
    u_var = float(np.exp(np.mean(np.log(np.maximum(var, VAR_FLOOR)))))
    u_exp = float(1.0 - np.mean(e))
    return u_var, u_exp


def to_bytes(rgb: np.ndarray) -> np.ndarray:
    """Colour in [0, 1] -> uint8 (round half to even, clipped): :func:`css_ros.engine.pixel_math.to_byte`."""
    return np.clip(np.rint(np.asarray(rgb) * 255.0), 0, 255).astype(np.uint8)


def finalize_host(buf: "RenderBuffers", settings: RenderSettings) -> FrameImages:
    """The final outputs from a backend's raw float64 buffers, in numpy (the reference form)."""
    s = settings
    unknown = buf.background > s.unknown_threshold
    labels = np.where(unknown, s.ignore_label, buf.labels).astype(np.int32)
    u_var, u_exp = image_uncertainty(buf.expectation, buf.variance)
    out = FrameImages(u_var=u_var, u_exp=u_exp)
    if s.wants("labels"):
        out.labels = labels
    for name in ("expectation", "variance", "background", "evidence"):
        if s.wants(name):
            setattr(out, name, getattr(buf, name).astype(np.float32))
    if s.wants("rgb"):
        out.rgb = to_bytes(buf.rgb)
    if s.wants("depth") and buf.depth is not None:
        out.depth = (buf.depth * s.depth_scale).astype(np.float32)
    if s.wants("confidence") and s.confidence is not None:
        conf = s.confidence(buf.expectation, buf.evidence)
        conf[labels == s.ignore_label] = 0.0
        out.confidence = conf
    if s.probabilities and buf.probabilities is not None:
        out.probabilities = buf.probabilities.astype(np.float32)
    return out
