"""Argument checks of :class:`~css_ros.engine.semantic_map.SemanticMap`'s constructor, frame inputs, point queries
and persistence: each returns the validated value or raises a CssError naming the argument.

The bounds are those :meth:`SemanticMap.load` applies to a file, so a map the API accepts is a map it can save and
load again (a prior of 1e300 was once accepted, gave NaN gains and wrote checkpoints no node could resume).
"""
from __future__ import annotations

import math
import os
import stat
from numbers import Integral, Real
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ..errors import CameraError, InputError, MapError
from .real_array import check_real_array

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel

__all__ = ["MAX_CONCENTRATION", "MIN_CONCENTRATION", "MAX_CLASSES", "MAX_QUERY_VALUES", "check_model",
           "check_integer", "check_num_classes", "check_real", "check_concentration", "check_unknown_threshold",
           "check_ignore_label", "check_background_rgb", "check_depth_scale", "check_camera", "check_real_array",
           "check_query_points", "check_background_weight", "check_map_path", "shown"]

#: Largest concentration / prior / background of a map (beyond: a crafted or broken file, or a typo).
MAX_CONCENTRATION = 1e15
#: Smallest prior / background of a map: far below any useful prior (the default is 1e-3), and far above the
#: subnormal range, where a prior of 1e-310 made the numba render's expectation +inf and U_exp -inf.
MIN_CONCENTRATION = 1e-12
#: Largest number of classes of a map.
MAX_CLASSES = 65536
#: Most (point, class) values one ``query_points`` call returns: its expectation and variance are 8 bytes per
#: value (float32 each), so 2^27 values are 1 GiB; query larger sets in slices.
MAX_QUERY_VALUES = 2**27
_INT32 = (-(2**31), 2**31 - 1)


def _scalar(value: Any) -> Any:
    """A 0-d numpy array of numbers as its scalar (what ``np.load(...)["prior"]`` gives); anything else as is."""
    if isinstance(value, np.ndarray) and value.ndim == 0 and value.dtype.kind in "biuf":
        return value[()]
    return value


def check_real(value: Any, name: str) -> float:
    """``value`` as a float: a real number or a 0-d array of one (bools, strings, complex and other arrays refused),
    finite and within float64 (an integer of 400 digits is refused, not an OverflowError)."""
    value = _scalar(value)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Real):
        raise MapError(f"{name} must be a real number, got {type(value).__name__} {_short(value)}")
    try:
        with np.errstate(over="ignore"):
            f = float(value)
    except OverflowError:
        f = math.inf
    if not math.isfinite(f):
        raise MapError(f"{name} must be finite, got {_short(value)}")
    return f


def _short(value: Any, limit: int = 60) -> str:
    """``repr(value)`` cut to ``limit`` characters (error messages never echo a huge argument)."""
    return shown(repr(value), limit)


def shown(text: str, limit: int = 200) -> str:
    """``text`` cut to ``limit`` characters; quoted when it holds a newline or other unprintable character (a message
    stays one line)."""
    text = text if text.isprintable() else repr(text)
    return text if len(text) <= limit else text[:limit] + "…"


def check_model(model: Any) -> "GaussianModel":
    """A :class:`~css_ros.engine.gaussians.GaussianModel`."""
    from .gaussians import GaussianModel

    if not isinstance(model, GaussianModel):
        raise MapError(f"model must be a GaussianModel (GaussianModel.from_ply), got {type(model).__name__}")
    return model


def check_integer(value: Any, name: str) -> int:
    """``value`` as an int: an integer, a float holding one or a 0-d array of either (bools, NaN, fractions, numbers
    beyond float64 and other types refused, MapError naming ``name``)."""
    value = _scalar(value)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (Integral, Real)):
        raise MapError(f"{name} must be an integer, got {type(value).__name__} {_short(value)}")
    if isinstance(value, Integral):
        return int(value)
    try:
        f = float(value)
    except OverflowError:
        f = math.inf
    if not (math.isfinite(f) and f.is_integer()):
        raise MapError(f"{name} must be an integer, got {_short(value)}")
    return int(f)


def check_num_classes(value: Any, name: str = "num_classes") -> int:
    """C: an integer in 1..MAX_CLASSES (an integral float such as 4.0 or a 0-d array counts; 2.7, True, "4" do not)."""
    c = check_integer(value, name)
    if not 1 <= c <= MAX_CLASSES:
        raise MapError(f"{name} must be in 1..{MAX_CLASSES}, got {c}")
    return c


def check_concentration(value: Any, name: str) -> float:
    """A prior or background concentration: a real number in [MIN_CONCENTRATION, MAX_CONCENTRATION]."""
    f = check_real(value, name)
    if not MIN_CONCENTRATION <= f <= MAX_CONCENTRATION:
        raise MapError(f"{name} must be in [{MIN_CONCENTRATION:g}, {MAX_CONCENTRATION:g}], got {f:g}")
    return f


def check_unknown_threshold(value: Any) -> float:
    """kappa_b above which a rendered pixel is "unknown": a real number in [0, 1] (1: never)."""
    f = check_real(value, "unknown_threshold")
    if not 0.0 <= f <= 1.0:
        raise MapError(f"unknown_threshold must be in [0, 1] (a background weight), got {f:g}")
    return f


def check_ignore_label(value: Any) -> int:
    """The "no label" value: an integer (or a 0-d integer array) that fits the int32 label images."""
    value = _scalar(value)
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, Integral):
        raise MapError(f"ignore_label must be an integer, got {type(value).__name__} {_short(value)}")
    v = int(value)
    if not _INT32[0] <= v <= _INT32[1]:
        raise MapError(f"ignore_label must fit int32 (the rendered label images), got {v}")
    return v


def check_background_rgb(value: Any) -> np.ndarray:
    """(3,) float64 colour behind all Gaussians, each channel a real number in [0, 1]."""
    arr = check_real_array(value, "background_rgb", MapError)
    if arr.shape != (3,):
        raise MapError(f"background_rgb must be 3 numbers (R, G, B), got shape {arr.shape}")
    if not (np.all(np.isfinite(arr)) and np.all((arr >= 0.0) & (arr <= 1.0))):
        raise MapError(f"background_rgb must be finite, each channel in [0, 1], got {arr.tolist()}")
    return arr


def check_depth_scale(value: Any) -> float:
    """Metres per splat unit: a positive finite real number."""
    f = check_real(value, "depth_scale")
    if not f > 0.0:
        raise MapError(f"depth_scale must be a positive finite number, got {f:g}")
    return f


def check_camera(camera: Any, what: str) -> "Camera":
    """A :class:`~css_ros.engine.camera.Camera` (``what``: the call, for the message)."""
    from .camera import Camera

    if not isinstance(camera, Camera):
        raise CameraError(f"{what}: camera must be a Camera, got {type(camera).__name__}")
    return camera


def check_query_points(points: Any, num_classes: int) -> np.ndarray:
    """(M, 3) real query points, M x C at most MAX_QUERY_VALUES (checked before anything of that size is made)."""
    if isinstance(points, np.ma.MaskedArray):
        raise InputError("points is a masked array: give a plain (M, 3) array")
    pts = np.asarray(points)
    if pts.dtype.kind not in "biuf":
        raise InputError(f"points must be an (M, 3) array of real numbers, got dtype {pts.dtype}")
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise InputError(f"points must be an (M, 3) array of numbers, got shape {pts.shape}")
    if pts.shape[0] * num_classes > MAX_QUERY_VALUES:
        raise InputError(f"{pts.shape[0]} points x {num_classes} classes is more than {MAX_QUERY_VALUES} values in one "
                         f"query (MAX_QUERY_VALUES, {MAX_QUERY_VALUES * 8 >> 20} MiB of results): query in slices")
    return pts


def check_background_weight(value: Any) -> float:
    """w_b of the continuous field: a positive finite real number."""
    try:
        f = check_real(value, "background_weight")
    except MapError as exc:
        raise InputError(str(exc)) from None
    if not f > 0.0:
        raise InputError(f"background_weight must be a positive finite number, got {f:g}")
    return f


def check_map_path(path: Any, reading: bool) -> Path:
    """A map file's path: a str or PathLike without NUL characters. When ``reading``, it must exist and be a regular
    file (a FIFO would block, a device be read without end); when writing, it must not be an existing directory (its
    folder is made when missing, as css_node's default checkpoint folder is). MapError naming the path otherwise."""
    if not isinstance(path, (str, os.PathLike)):
        raise MapError(f"map path must be a str or os.PathLike, got {type(path).__name__}")
    try:
        raw = os.fspath(path)
        p = Path(raw)
    except Exception as exc:  # noqa: BLE001 - a PathLike's __fspath__ may raise anything, or return bytes
        raise MapError(f"map path {type(path).__name__} gives no str path ({type(exc).__name__}: {shown(str(exc))})") \
            from None
    text = os.fspath(p)
    if "\0" in text or not text:
        raise MapError(f"map path {_short(text)} is empty or holds a NUL character")
    if not reading and raw.endswith(os.sep):
        raise MapError(f"cannot save the map to {shown(text)}{os.sep}: the path names a folder, give a file name")
    try:
        st = os.stat(p)
    except FileNotFoundError:
        if reading:
            raise MapError(f"map file {shown(text)} does not exist") from None
        st = None
    except OSError as exc:
        raise MapError(f"map file {shown(text)}: {exc.strerror or exc}") from None
    if reading and st is not None and not stat.S_ISREG(st.st_mode):
        raise MapError(f"map file {shown(text)} is not a regular file")
    if not reading:
        if st is not None and stat.S_ISDIR(st.st_mode):
            raise MapError(f"cannot save the map to {shown(text)}: it is a directory")
    return p
