"""The one frame decoder of the package: message -> validated arrays, used by css_node and css_replay.

Each ``decode_*`` function takes a message (rclpy or rosbags; duck-typed on field names) and returns
plain arrays, or raises :class:`FrameRejected` whose ``reason`` is a short, stable drop reason (the
key of the warnings and counters of the node and of ``frames.skipped`` in css_replay's metrics) and
whose message says what was wrong. Node and replay therefore accept and refuse exactly the same
frames.

Policies (documented in the README's reliability section):

- **Confidence**: non-finite confidence values (NaN, ±inf) count as 0 (that pixel adds nothing) and
  the rest of the frame is used; values are clipped to [0, 1]. ``SemanticMap.update`` applies the
  same rule, so feeding it directly gives the same result.
- **camera_info**: an invalid one (K not 3x3, zero/non-finite/negative focal length, principal point
  or focal length outside :data:`INTRINSICS_BOUND`, size 0 or above ``max_image_pixels``) is refused
  and the previous valid one stays in use; frames before the first valid camera_info are dropped.
- **Pose**: non-finite or out-of-bounds positions (|x| > :data:`POSITION_BOUND_M`) and quaternions
  whose norm is outside ``QUATERNION_NORM_TOLERANCE`` are refused; others are normalised.
- **Images** (segmentation, confidence, colour, GT, depth): unsupported encodings, truncated data and a
  size different from the camera_info's are refused.
- **Depth** (REP 118): 16UC1 in millimetres (0: no measurement) or 32FC1 in metres (NaN, inf, 0 or negative: no
  measurement); every "no measurement" becomes NaN. A depth at another resolution than its segmentation (same
  field of view) is brought to it by the nearest pixel, never interpolated across edges (:func:`depth_for`).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..engine.camera import QUATERNION_NORM_TOLERANCE
from ..errors import InputError
from .messages import (COLOR_ENCODINGS, CONFIDENCE_ENCODINGS, DEPTH_ENCODINGS, LABEL_ENCODINGS,
                       camera_info_to_intrinsics, image_to_array, pose_to_arrays)

#: Largest image accepted by default [pixels] (4096 x 4096); node parameter / replay option ``max_image_pixels``.
DEFAULT_MAX_IMAGE_PIXELS = 4096 * 4096
#: Focal lengths and principal points beyond this [px] are refused as an upstream bug.
INTRINSICS_BOUND = 1e7
#: Positions beyond this [m] from the map origin are refused (a planet-sized map is an upstream bug).
POSITION_BOUND_M = 1e6


class FrameRejected(InputError):
    """A message cannot be used. ``reason`` is the stable drop reason; ``str(exc)`` the detail."""

    def __init__(self, reason: str, detail: str) -> None:
        super().__init__(detail)
        self.reason = reason


@dataclass(frozen=True)
class Intrinsics:
    """A validated rectified pinhole: K (3, 3) float64 [px], image width and height [px]."""

    K: np.ndarray
    width: int
    height: int

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width), the shape of every image of a frame."""
        return self.height, self.width


def decode_camera_info(msg: Any, max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> Intrinsics:
    """Validate a sensor_msgs/CameraInfo (distortion is ignored: images are rectified)."""
    try:
        K, width, height = camera_info_to_intrinsics(msg)
    except (InputError, AttributeError, TypeError, ValueError) as exc:
        raise FrameRejected("invalid camera_info", f"cannot read K/width/height: {exc}") from None
    return validate_intrinsics(K, width, height, max_image_pixels)


def validate_intrinsics(K: np.ndarray, width: int, height: int,
                        max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS) -> Intrinsics:
    """The one camera check of css_node, css_replay and css_import: K (3, 3) [px] an upper-triangular
    pinhole with finite, positive focal lengths and entries within :data:`INTRINSICS_BOUND`, and
    0 < width x height <= ``max_image_pixels``. Raises FrameRejected (reason ``invalid camera_info`` or
    ``image too large``)."""
    K = np.asarray(K, dtype=np.float64)
    if width <= 0 or height <= 0:
        raise FrameRejected("invalid camera_info", f"image size {width}x{height}")
    if width * height > max_image_pixels:
        raise FrameRejected("image too large", f"{width}x{height} = {width * height} pixels > max_image_pixels "
                                               f"{max_image_pixels}")
    if not np.all(np.isfinite(K)):
        raise FrameRejected("invalid camera_info", "K holds non-finite values")
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    if not (fx > 0 and fy > 0):
        raise FrameRejected("invalid camera_info", f"focal lengths must be > 0 (fx={fx:g}, fy={fy:g})")
    if max(fx, fy, abs(cx), abs(cy), abs(K[0, 1])) > INTRINSICS_BOUND:
        raise FrameRejected("invalid camera_info", f"intrinsics beyond {INTRINSICS_BOUND:g} px: {K.ravel().tolist()}")
    if np.any(K[2] != (0.0, 0.0, 1.0)) or K[1, 0] != 0.0:
        raise FrameRejected("invalid camera_info", f"K is not an upper-triangular pinhole matrix: {K.ravel().tolist()}")
    return Intrinsics(K, int(width), int(height))


def _image(msg: Any, allowed: tuple[str, ...], reason: str) -> np.ndarray:
    try:
        return image_to_array(msg, allowed=allowed)
    except (InputError, AttributeError, TypeError, ValueError) as exc:
        raise FrameRejected(reason, str(exc)) from None


def check_size(array: np.ndarray, intrinsics: Intrinsics, what: str) -> None:
    """Refuse an image whose size differs from the camera_info's."""
    if array.shape[:2] != intrinsics.shape:
        raise FrameRejected("size mismatch with camera_info",
                            f"{what} {array.shape[1]}x{array.shape[0]}, camera_info "
                            f"{intrinsics.width}x{intrinsics.height}")


def decode_labels(msg: Any, what: str = "segmentation") -> np.ndarray:
    """Label image (mono8/8UC1/mono16/16UC1) -> (H, W) int32 class ids."""
    return _image(msg, LABEL_ENCODINGS, f"bad {what}").astype(np.int32)


def decode_confidence(msg: Any) -> tuple[np.ndarray, int]:
    """32FC1 confidence -> ((H, W) float32 in [0, 1], number of non-finite values set to 0)."""
    conf = _image(msg, CONFIDENCE_ENCODINGS, "bad confidence").astype(np.float32)
    finite = np.isfinite(conf)
    bad = int(conf.size - np.count_nonzero(finite))
    if bad:
        conf = np.where(finite, conf, np.float32(0.0))
    return np.clip(conf, 0.0, 1.0), bad


#: units per metre of each depth encoding (REP 118)
DEPTH_UNITS_PER_METRE = {"16UC1": 1000.0, "32FC1": 1.0}


@dataclass(frozen=True)
class RawDepth:
    """A depth image as received: ``values`` (H, W) uint16 or float32, ``per_metre`` of them a metre. Kept so until a
    frame takes it (:meth:`metres`): most depth images of a camera faster than its segmentation are never used."""

    values: np.ndarray
    per_metre: float

    @property
    def shape(self) -> tuple[int, int]:
        return self.values.shape[0], self.values.shape[1]

    def metres(self) -> np.ndarray:
        """(H, W) float32 depth [m] along the optical axis; NaN where there is no measurement (0, NaN, inf, < 0)."""
        d = self.values.astype(np.float32)
        if self.per_metre != 1.0:
            d /= np.float32(self.per_metre)   # a division: 1500 mm is 1.5 m exactly (x 0.001 rounds it)
        return np.where(np.isfinite(d) & (d > 0), d, np.float32(np.nan)).astype(np.float32, copy=False)


def decode_depth(msg: Any) -> RawDepth:
    """A depth image (16UC1 millimetres or 32FC1 metres) -> :class:`RawDepth`; FrameRejected ``bad depth``."""
    values = _image(msg, DEPTH_ENCODINGS, "bad depth")
    return RawDepth(values, DEPTH_UNITS_PER_METRE[str(msg.encoding)])


def decode_image(msg: Any) -> np.ndarray:
    """Colour camera image -> (H, W, 3) uint8 RGB (mono8 repeated over the channels)."""
    rgb = _image(msg, COLOR_ENCODINGS, "bad image")
    if rgb.ndim == 2:
        rgb = np.repeat(rgb[:, :, None], 3, axis=2)
    return rgb


def decode_pose(msg: Any) -> tuple[np.ndarray, np.ndarray]:
    """geometry_msgs/PoseStamped -> (position (3,) [m], unit quaternion (4,) x, y, z, w)."""
    try:
        position, quat = pose_to_arrays(msg.pose)
    except (AttributeError, TypeError, ValueError) as exc:
        raise FrameRejected("invalid pose", f"cannot read the pose: {exc}") from None
    if not np.all(np.isfinite(position)):
        raise FrameRejected("invalid pose", f"non-finite position {position.tolist()}")
    if np.max(np.abs(position)) > POSITION_BOUND_M:
        raise FrameRejected("invalid pose", f"position {position.tolist()} beyond {POSITION_BOUND_M:g} m")
    if not np.all(np.isfinite(quat)):
        raise FrameRejected("invalid pose", f"non-finite quaternion {quat.tolist()}")
    norm = float(np.linalg.norm(quat))
    lo, hi = QUATERNION_NORM_TOLERANCE
    if not lo <= norm <= hi:
        raise FrameRejected("invalid pose", f"quaternion {quat.tolist()} has norm {norm:.4g} outside [{lo}, {hi}]")
    return position, quat / norm


def depth_for(depth: RawDepth, labels_shape: tuple[int, int], tolerance_px: float) -> np.ndarray:
    """The depth [m] (H, W) float32 at the segmentation's resolution ``labels_shape`` (NaN: no measurement).

    Another resolution with the same field of view (one scale factor for x and y, within ``tolerance_px`` of
    rounding) takes the nearest source pixel (:func:`resample_to` with ``labels``): depth is never interpolated
    across an edge (a value between a person and the wall behind is neither). Raises FrameRejected ``depth size
    mismatch`` for another aspect ratio."""
    h, w = labels_shape
    H, W = depth.shape
    if (H, W) == (h, w):
        return depth.metres()
    if abs(H * w / W - h) > tolerance_px or abs(W * h / H - w) > tolerance_px:
        raise FrameRejected("depth size mismatch", f"depth {W}x{H} is not the segmentation's {w}x{h} scaled by one "
                            "factor in x and y (is it registered to the segmentation's camera?)")
    return RawDepth(resample_to(depth.values, (h, w), labels=True), depth.per_metre).metres()


def resample_to(image: np.ndarray, shape: tuple[int, int], labels: bool = False) -> np.ndarray:
    """``image`` (H, W[, 3]) resampled to ``shape`` (h, w), same field of view (pixel centres at integers).

    Integer down-sampling factors average blocks (colour images) or take each block's centre-most pixel (labels);
    other factors take the nearest source pixel centre. Used where a segmentation runs at another resolution
    than the camera: the colour image (PSNR) and css_replay's GT are brought to the segmentation's resolution.
    """
    h, w = shape
    H, W = image.shape[:2]
    if (H, W) == (h, w):
        return image
    if not labels and H % h == 0 and W % w == 0:
        fy, fx = H // h, W // w
        blocks = image.reshape(h, fy, w, fx, *image.shape[2:]).astype(np.float64)
        return np.round(blocks.mean(axis=(1, 3))).astype(image.dtype)
    ys = np.clip(np.floor((np.arange(h) + 0.5) * H / h).astype(np.int64), 0, H - 1)
    xs = np.clip(np.floor((np.arange(w) + 0.5) * W / w).astype(np.int64), 0, W - 1)
    return image[ys[:, None], xs[None, :]]
