"""The common result of every pose importer: one posed pinhole view per image (frames: SPEC §2)."""
from __future__ import annotations

import math
from collections import Counter
from dataclasses import dataclass
from pathlib import PurePath
from typing import Any

import numpy as np

from ..engine.camera import matrix_to_quaternion_xyzw
from ..errors import InputError
from ..io.frames import FrameRejected, validate_intrinsics

#: Largest accepted deviation of an imported rotation from orthonormality (|R^T R - I|, max abs entry).
ROTATION_TOLERANCE = 1e-4


class ImportFormatError(InputError):
    """A camera/pose/label file that cannot be imported (message names the file and the problem)."""


@dataclass(frozen=True)
class PosedView:
    """One image with its camera.

    Attributes:
        name: image file name as given by the pose file (e.g. ``00001.jpg`` or ``images/frame_001.png``).
        K: (3, 3) float64 pinhole intrinsics [px], principal point in the pixel-centres-at-integers
            convention of SPEC §2 (the centre of the top-left pixel is (0, 0)).
        width, height: image size [px].
        T_map_cam: (4, 4) float64 camera-to-world pose of the OpenCV optical frame (x right, y down,
            z forward) in the frame of the splat model [m].
    """

    name: str
    K: np.ndarray
    width: int
    height: int
    T_map_cam: np.ndarray

    @property
    def stem(self) -> str:
        """File name without folders and extension: the key that matches label/GT/confidence files."""
        return PurePath(self.name.replace("\\", "/")).stem

    @property
    def position(self) -> np.ndarray:
        """(3,) camera centre in the map frame [m]."""
        return self.T_map_cam[:3, 3].copy()

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """(4,) orientation of the optical frame in the map (x, y, z, w)."""
        return matrix_to_quaternion_xyzw(self.T_map_cam[:3, :3])


def pinhole_K(fx: float, fy: float, cx: float, cy: float) -> np.ndarray:
    """(3, 3) intrinsics [px] from focal lengths and principal point (pixel centres at integers)."""
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=np.float64)


def make_pose(R_map_cam: np.ndarray, t_map_cam: np.ndarray, where: str) -> np.ndarray:
    """(4, 4) camera-to-world transform from a rotation (3, 3) and a camera centre (3,).

    Raises:
        ImportFormatError: non-finite values or a rotation that is not orthonormal with det +1 (``where`` names
            the file and entry in the message).
    """
    R = np.asarray(R_map_cam, dtype=np.float64)
    t = np.asarray(t_map_cam, dtype=np.float64).reshape(-1)
    if R.shape != (3, 3) or t.shape != (3,):
        raise ImportFormatError(f"{where}: rotation must be 3x3 and position 3 values, got {R.shape} and {t.shape}")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(t))):
        raise ImportFormatError(f"{where}: non-finite pose values")
    err = float(np.max(np.abs(R.T @ R - np.eye(3))))
    if err > ROTATION_TOLERANCE or np.linalg.det(R) < 0:
        raise ImportFormatError(f"{where}: not a rotation matrix (|R^T R - I| = {err:.2g}, det = {np.linalg.det(R):.3g})")
    T = np.eye(4)
    T[:3, :3] = R
    T[:3, 3] = t
    return T


def checked_K(fx: float, fy: float, cx: float, cy: float, width: int, height: int, where: str) -> np.ndarray:
    """(3, 3) pinhole K [px] (principal point already in SPEC §2's convention), checked with the bounds
    css_node and css_replay apply to camera_info (:func:`css_ros.io.frames.validate_intrinsics`): a camera
    they would refuse is refused here, naming ``where``."""
    try:
        K = pinhole_K(float(fx), float(fy), float(cx), float(cy))
        validate_intrinsics(K, width, height)
    except (TypeError, ValueError, OverflowError) as exc:
        raise ImportFormatError(f"{where}: intrinsics must be numbers ({exc})") from None
    except FrameRejected as exc:
        raise ImportFormatError(f"{where}: {exc.reason}: {exc} (css_node and css_replay refuse this camera)") \
            from None
    return K


def image_size(value: Any, key: str, where: str) -> int:
    """An image width/height [px] read from a pose file: a positive integer (an integral float such as
    640.0 is accepted; 256.9, 1e999, NaN, booleans, strings and null are an ImportFormatError naming ``where``)."""
    ok = isinstance(value, int) and not isinstance(value, bool) or \
        isinstance(value, float) and math.isfinite(value) and value.is_integer()
    if not ok or int(value) < 1:
        raise ImportFormatError(f"{where}: {key} must be a positive integer number of pixels, got {value!r}")
    return int(value)


def image_name(value: Any, key: str, where: str) -> str:
    """An image file name read from a pose file: a non-empty string (else ImportFormatError naming ``where``)."""
    if not isinstance(value, str) or not value.strip():
        raise ImportFormatError(f"{where}: {key} must be a non-empty file name, got {value!r}")
    return value


def sorted_views(views: list[PosedView]) -> list[PosedView]:
    """Views ordered by image name (the capture order of numbered image files); names must be unique."""
    dup = sorted(n for n, k in Counter(v.name for v in views).items() if k > 1)
    if dup:
        raise ImportFormatError(f"image names occur more than once: {', '.join(dup[:5])}")
    dup = sorted(n for n, k in Counter(v.stem for v in views).items() if k > 1)
    if dup:
        raise ImportFormatError(f"image names differ only in folder or extension (labels are matched by stem): "
                           f"{', '.join(dup[:5])}")
    return sorted(views, key=lambda v: v.name)
