"""One frame's segmentation as it comes in, and the one rule that makes a pixel of it a vote (SPEC §4).

A label image goes to the backends in the dtype it came in (the segmentation topic's ``mono8`` / ``mono16`` /
``32SC1``: uint8, uint16, int32; int64 as numpy makes it), with the optional confidence in its own float dtype:
no int64 copy, no plane of ones, no numpy pass over the pixels. The backends apply :func:`pixel_vote` per pixel
inside their compiled update pass (numba on the CPU, numba-cuda on the GPU, vectorised in the torch twin) and count
the pixels there. Other integer dtypes (int8, int16, uint32, uint64) are converted once to int64, keeping every
value's meaning (the only host pass, for inputs no ROS encoding produces).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import InputError
from .change_rules import ChangeRules

#: label dtypes the compiled passes read directly (one kernel specialisation each)
KERNEL_LABEL_DTYPES = (np.dtype(np.uint8), np.dtype(np.uint16), np.dtype(np.int32), np.dtype(np.int64))
#: confidence dtypes the compiled passes read directly (others are converted to float64)
KERNEL_CONFIDENCE_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))

#: status of a pixel under :func:`pixel_vote` (indices of the counts the passes return)
USED, IGNORED, OUT_OF_RANGE = 0, 1, 2
#: length of the counts array a compiled pass fills: used, ignored, out of range, no depth (sensor model), transient
#: (a transient class: no evidence), occluded (measured depth nearer than the splat's: no evidence); see
#: :mod:`css_ros.engine.change_rules`
NUM_COUNTS = 6
NO_DEPTH = 3
TRANSIENT = 4
OCCLUDED = 5


def pixel_vote(label, conf, num_classes, ignore_label):  # type: ignore[no-untyped-def]
    """The vote of one pixel: (class c or -1, weight w, status), the one definition every backend compiles.

    ``label`` is the pixel's integer as it came; ``conf`` its confidence (1.0 without a confidence image), any
    float. ``ignore_label`` gives (-1, 0, IGNORED); a label < 0 or >= ``num_classes`` (OUT_OF_RANGE) adds nothing;
    a confidence that is NaN or <= 0 after the float32 cast is IGNORED; confidences above 1 (and +inf) count as 1.
    So the weight is numpy's ``float32(clip(nan_to_num(conf, nan=0, posinf=1, neginf=0), 0, 1))`` and a pixel is
    USED exactly when its class is valid and that weight is > 0. Plain scalar code: ``engine/cpu`` compiles it with
    ``numba.njit``, ``engine/cuda`` with ``numba.cuda.jit(device=True)``.
    """
    if label == ignore_label:
        return -1, np.float32(0.0), IGNORED
    if label < 0 or label >= num_classes:
        return -1, np.float32(0.0), OUT_OF_RANGE
    if conf > 1.0:
        conf = 1.0
    w = np.float32(conf)
    if not (w > np.float32(0.0)):
        return -1, np.float32(0.0), IGNORED
    return int(label), w, USED


def transient_status(c, status, transient):  # type: ignore[no-untyped-def]
    """TRANSIENT for a USED vote of a class marked in ``transient`` ((C,) bool; may be empty: none), else
    ``status`` (:mod:`css_ros.engine.change_rules`). Scalar code for numba / numba-cuda."""
    if status == USED and c < transient.shape[0] and transient[c]:
        return TRANSIENT
    return status


@dataclass(frozen=True)
class FrameLabels:
    """A frame's label input for a backend's update.

    Attributes:
        labels: (H, W) C-contiguous integer class ids in one of :data:`KERNEL_LABEL_DTYPES`, as the caller gave them.
        confidence: (H, W) C-contiguous float32 / float64 per-pixel weights as given (clipped by :func:`pixel_vote`),
            or None (every pixel weight 1).
        num_classes: C; labels outside 0..C-1 are out of range.
        ignore_label: the "no label" value.
        depth: (H, W) C-contiguous float32 measured depth in metres along the optical axis, registered to the labels
            (NaN, inf or <= 0: no measurement), or None (:mod:`css_ros.engine.change_rules`).
        rules: the map's rules for a changing world (transient classes, depth tolerance, forgetting).
        want_surprise: also make the (H, W) float32 surprise image (observe's ``surprise`` output).
    """

    labels: np.ndarray
    confidence: np.ndarray | None
    num_classes: int
    ignore_label: int
    depth: np.ndarray | None = None
    rules: ChangeRules = field(default_factory=ChangeRules)
    want_surprise: bool = False


def kernel_labels(labels: np.ndarray) -> np.ndarray:
    """``labels`` (an integer array) in a dtype of :data:`KERNEL_LABEL_DTYPES`, C-contiguous: the array itself when it
    already is; int8 / int16 / uint32 as int64 (lossless); uint64 clipped to 2^63 - 1 first (still out of range)."""
    if labels.dtype in KERNEL_LABEL_DTYPES:
        return np.ascontiguousarray(labels)
    if labels.dtype == np.uint64:
        labels = np.minimum(labels, np.uint64(2**63 - 1))
    return np.ascontiguousarray(labels, dtype=np.int64)


def kernel_confidence(confidence: np.ndarray) -> np.ndarray:
    """A real confidence image in a dtype of :data:`KERNEL_CONFIDENCE_DTYPES` (float32 / float64 kept as they are;
    others, e.g. bool, int, float16 or long double, as float64: a long double beyond float64 becomes inf, then 1)."""
    if confidence.dtype in KERNEL_CONFIDENCE_DTYPES:
        return np.ascontiguousarray(confidence)
    with np.errstate(over="ignore"):
        return np.ascontiguousarray(confidence, dtype=np.float64)


def count_votes(labels: np.ndarray, confidence: np.ndarray | None, num_classes: int,
                ignore_label: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vectorised :func:`pixel_vote` over a whole image (numpy; the torch twin and the tests' reference):
    (classes (H, W) int64, -1 where none; weights (H, W) float32, 0 where none; counts (3,) used, ignored, out of
    range). Transient classes and depth are applied after it (:mod:`css_ros.engine.change_rules`)."""
    lab = np.asarray(labels).astype(np.int64)
    if labels.dtype == np.uint64:
        lab = np.minimum(np.asarray(labels), np.uint64(2**63 - 1)).astype(np.int64)
    ignored = lab == ignore_label
    oor = ~ignored & ((lab < 0) | (lab >= num_classes))
    if confidence is None:
        w = np.ones(lab.shape, dtype=np.float32)
    else:
        with np.errstate(over="ignore", invalid="ignore"):
            c = np.asarray(confidence, dtype=np.float64)
            w = np.clip(np.nan_to_num(c, nan=0.0, posinf=1.0, neginf=0.0), 0.0, 1.0).astype(np.float32)
    used = ~ignored & ~oor & (w > 0)
    classes = np.where(used, lab, -1)
    weights = np.where(used, w, np.float32(0.0)).astype(np.float32)
    counts = np.array([int(used.sum()), int(lab.size - used.sum() - oor.sum()), int(oor.sum())], dtype=np.int64)
    return classes, weights, counts


def check_frame_labels(labels: object, confidence: object, shape: tuple[int, int], num_classes: int,
                       ignore_label: int, depth: object = None, rules: ChangeRules | None = None,
                       want_surprise: bool = False) -> FrameLabels:
    """Validate a frame's labels (and confidence, measured depth) for a camera of image ``shape`` (H, W) without
    touching pixels (a depth image that is not float32 is converted once).

    Raises:
        InputError: masked arrays, not 2-D, not integers, another size than the camera's, a confidence or depth that
            is not real numbers or of another shape.
    """
    from .map_args import check_real_array

    if isinstance(labels, np.ma.MaskedArray):
        raise InputError("labels is a masked array: give a plain array (ignore_label marks pixels without a label)")
    lab = np.asarray(labels)
    if lab.ndim != 2:
        raise InputError(f"labels must be an (H, W) array, got shape {lab.shape}")
    if not np.issubdtype(lab.dtype, np.integer):
        raise InputError(f"labels must be integers, got {lab.dtype}")
    if lab.shape[:2] != shape:
        raise InputError(f"label image is {lab.shape[1]}x{lab.shape[0]} but the camera is {shape[1]}x{shape[0]}")
    conf = None
    if confidence is not None:
        if type(confidence) is np.ndarray and confidence.dtype in KERNEL_CONFIDENCE_DTYPES:
            conf = confidence
        else:
            conf = check_real_array(confidence, "confidence")
        if conf.shape != lab.shape:
            raise InputError(f"confidence shape {conf.shape} differs from labels {lab.shape}")
        conf = kernel_confidence(conf)
    dep = None
    if depth is not None:
        if type(depth) is np.ndarray and depth.dtype == np.float32:
            dep = depth
        else:
            dep = check_real_array(depth, "depth")
        if dep.shape != lab.shape:
            raise InputError(f"depth shape {dep.shape} differs from labels {lab.shape}")
        with np.errstate(over="ignore", invalid="ignore"):
            dep = np.ascontiguousarray(dep, dtype=np.float32)
    return FrameLabels(kernel_labels(lab), conf, int(num_classes), int(ignore_label), dep,
                       rules if rules is not None else ChangeRules(), bool(want_surprise))
