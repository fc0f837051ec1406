"""Argument checks of the view-scoring API (``SemanticMap.score_views``, ``select_views``, ``task_importance``,
``class_importance``): each returns the validated value or raises a CssError naming the argument.

Bounds: ``importance`` <= MAX_IMPORTANCE per Gaussian and ``pixel_scale`` in (0, MAX_PIXEL_SCALE] keep every gain a
finite float64 (a gain sums importance x variance drop over the Gaussians; larger factors overflow to inf / NaN);
``select_views`` takes at most MAX_SELECT_CANDIDATES cameras per call (it keeps each candidate's visible Gaussians
and their evidence for the greedy re-scoring: memory grows with the candidates).
"""
from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import CameraError, MapError
from .map_args import check_integer, check_real, check_real_array

if TYPE_CHECKING:
    from .camera import Camera

__all__ = ["MAX_IMPORTANCE", "MAX_PIXEL_SCALE", "MAX_SELECT_CANDIDATES", "check_k", "check_importance",
           "check_pixel_scale", "check_cameras", "check_class_id"]

#: Largest importance of one Gaussian (relative weights: scale them down).
MAX_IMPORTANCE = 1e15
#: Largest pixel_scale: pixels observed per scored pixel (1 / f**2 for candidates rendered at scale f >= 1e-3).
MAX_PIXEL_SCALE = 1e6
#: Most candidate cameras of one select_views call (8 bytes of evidence and 8 of id per visible Gaussian are kept
#: per candidate; rank larger sets in batches, or prefilter them with score_views, which keeps nothing per view).
MAX_SELECT_CANDIDATES = 1024


def check_k(k: Any) -> int:
    """The number of views to select: an integer >= 1."""
    value = check_integer(k, "k")
    if value < 1:
        raise MapError(f"k must be >= 1 (the number of views to select), got {value}")
    return value


def check_class_id(class_id: Any, num_classes: int) -> int:
    """A class id in 0..C-1."""
    value = check_integer(class_id, "class_id")
    if not 0 <= value < num_classes:
        raise MapError(f"class_id {value} outside 0..{num_classes - 1}")
    return value


def check_importance(importance: Any, num_gaussians: int) -> np.ndarray | None:
    """(N,) float64 per-Gaussian weights, finite, in [0, MAX_IMPORTANCE] (None: uniform, returned as None)."""
    if importance is None:
        return None
    imp = check_real_array(importance, "importance", MapError)
    if imp.shape != (num_gaussians,):
        raise MapError(f"importance must have shape ({num_gaussians},) (one weight per Gaussian), got {imp.shape}")
    finite = np.isfinite(imp)
    bad = ~finite | (imp < 0) | (imp > MAX_IMPORTANCE)
    if np.any(bad):
        first = int(np.flatnonzero(bad)[0])
        raise MapError(f"importance must be finite and in [0, {MAX_IMPORTANCE:g}] (relative weights): {int(bad.sum())} "
                       f"of {imp.size} values are not, the first importance[{first}] = {imp[first]:g}")
    return imp


def check_pixel_scale(pixel_scale: Any) -> float:
    """Pixels observed per scored pixel: a real number in (0, MAX_PIXEL_SCALE]."""
    value = check_real(pixel_scale, "pixel_scale")
    if not 0.0 < value <= MAX_PIXEL_SCALE:
        raise MapError(f"pixel_scale must be finite and in (0, {MAX_PIXEL_SCALE:g}], got {pixel_scale}")
    return value


def check_cameras(cameras: Any, what: str, max_count: int | None = None) -> list["Camera"]:
    """The cameras of a call as a list: an iterable of :class:`~css_ros.engine.camera.Camera` (not one camera, not a
    string), at most ``max_count`` of them."""
    from .camera import Camera

    name = "task_cameras" if what == "task_importance" else "cameras"
    if isinstance(cameras, (Camera, str, bytes)) or not hasattr(cameras, "__iter__"):
        raise CameraError(f"{what}: {name} must be a sequence of Camera, got {type(cameras).__name__}")
    cams = []
    for i, cam in enumerate(cameras):
        if not isinstance(cam, Camera):
            raise CameraError(f"{what}: {name}[{i}] is a {type(cam).__name__}, not a Camera")
        if max_count is not None and i >= max_count:
            raise CameraError(f"{what}: more than {max_count} {name} in one call (MAX_SELECT_CANDIDATES: the "
                              "candidates' evidence is kept in memory); split them into batches")
        cams.append(cam)
    return cams
