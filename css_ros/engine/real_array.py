"""The one conversion of "an array of real numbers" that the engine's argument checks share (camera poses and
intrinsics, frame confidences, importance weights, image_uncertainty's images)."""
from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from ..errors import InputError

__all__ = ["check_real_array"]


def _all_real(a: np.ndarray) -> bool:
    """Whether every element of an object array is a real number (bools are not)."""
    return all(isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_)) for v in a.flat)


def check_real_array(value: Any, name: str, error: type[Exception] = InputError, *, copy: bool = False) -> np.ndarray:
    """``value`` as a float64 array of real numbers, else ``error`` naming ``name``.

    Accepted: bool, integer and float arrays (and sequences of them), and object arrays holding real numbers only.
    Refused, because numpy would silently do something else: masked arrays (their mask would be ignored), complex
    arrays (the imaginary part would be dropped with only a warning), strings (they would be parsed), other
    objects, ragged sequences and numbers beyond float64 in an object array. A long double beyond float64 becomes
    inf (the callers check finiteness where they need it).

    Args:
        value: the array-like.
        name: how the message names it (it starts every message).
        error: the exception type to raise (the caller's: CameraError, InputError, MapError).
        copy: return a new array even when ``value`` already is a float64 array (for callers that keep it).
    Returns:
        float64 array of ``value``'s shape (``value`` itself when it is one and ``copy`` is False).
    """
    if isinstance(value, np.ma.MaskedArray):
        raise error(f"{name} is a masked array: give a plain array (mask the values out another way, e.g. NaN or 0)")
    try:
        arr = value if isinstance(value, np.ndarray) else np.asarray(value)
    except (TypeError, ValueError) as exc:
        raise error(f"{name} is not an array of numbers ({exc})") from None
    kind = arr.dtype.kind
    if kind not in "biuf" and not (kind == "O" and _all_real(arr)):
        what = {"c": " (complex values)", "O": " (it holds text or other objects)"}.get(kind, "")
        raise error(f"{name} must hold real numbers, got dtype {arr.dtype}{what}")
    try:
        with np.errstate(over="ignore"):
            return np.array(arr, dtype=np.float64) if copy else np.asarray(arr, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as exc:   # an object array holding an int beyond float64
        raise error(f"{name} must hold real numbers within float64 ({exc})") from None
