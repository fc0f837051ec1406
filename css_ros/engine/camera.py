"""Pinhole camera (intrinsics + optical-frame pose in the map) and quaternion helpers (SPEC section 2)."""
from __future__ import annotations

import math
import numbers
import reprlib
from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import CameraError
from .real_array import check_real_array

__all__ = [
    "Camera",
    "MAX_CAMERA_PIXELS",
    "QUATERNION_NORM_TOLERANCE",
    "MATRIX_TO_QUATERNION_TOLERANCE",
    "body_to_optical_rotation",
    "intrinsics_from_fov",
    "matrix_to_quaternion_xyzw",
    "quaternion_xyzw_to_matrix",
]

#: Accepted range of the norm of an incoming quaternion before it is normalised.
QUATERNION_NORM_TOLERANCE = (0.9, 1.1)
_ORTHO_TOL = 1e-5
#: Largest |R^T R - I| and |det R - 1| :func:`matrix_to_quaternion_xyzw` accepts. Wider than a Camera's pose check
#: (1e-5) and the importers' (1e-4, rotations read from text files), so every rotation those accept converts; a
#: matrix further off (a reflection, a scaled or zero matrix) is not a rotation and is refused.
MATRIX_TO_QUATERNION_TOLERANCE = 1e-3
#: Largest image (width x height, pixels) a Camera describes: 8192 x 8192 = 2**26. Every buffer of a render or a
#: scored view is allocated per pixel (a render takes ~95 bytes per pixel with 4 classes, numba backend; more with
#: probabilities), so this bounds a call's memory (~6.4 GB at the bound) instead of a MemoryError / OOM. It admits
#: the node's inputs at its default ``max_image_pixels`` (4096 x 4096, css_ros.io.frames.DEFAULT_MAX_IMAGE_PIXELS,
#: with 4x to spare for a raised parameter) and offline renders up to 8K (7680 x 4320 and 8192 x 4320, ~35 MP). The
#: engine keeps its own bound because it never imports ``io``; io's default must stay <= this (test_camera_args
#: checks it).
MAX_CAMERA_PIXELS = 8192 * 8192
#: Quaternions with a norm below this (after scaling by the largest component it cannot underflow) are "zero".
_ZERO_QUATERNION = 1e-12


def _unit_rows(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v / |v| along the last axis, |v| (..., 1)) without overflow or underflow: rows whose largest |component|
    lies outside [1e-100, 1e100] are divided by it before the norm (the others exactly as v / |v|).

    All-zero rows get norm 0 and zeros as direction; the norm of a row near the float maximum may be inf."""
    m = np.max(np.abs(v), axis=-1, keepdims=True)
    scale = np.where((m >= 1e-100) & (m <= 1e100), 1.0, np.where(m > 0, m, 1.0))
    w = v / scale
    n = np.linalg.norm(w, axis=-1, keepdims=True)
    with np.errstate(over="ignore"):
        return w / np.where(n > 0, n, 1.0), n * scale


def quaternion_xyzw_to_matrix(q: Sequence[float] | np.ndarray) -> np.ndarray:
    """Rotation matrix (..., 3, 3) float64 from quaternion(s) (..., 4) in (x, y, z, w) order (normalised here;
    scaled by the largest component first, so any finite magnitude works).

    Raises CameraError for non-numeric, complex, non-finite or zero (norm < 1e-12) quaternions.
    """
    q = check_real_array(q, "quaternion", CameraError)
    if q.shape[-1:] != (4,):
        raise CameraError(f"quaternion must have 4 components (x, y, z, w), got shape {q.shape}")
    if not np.all(np.isfinite(q)):
        raise CameraError("quaternion holds non-finite values")
    unit, norm = _unit_rows(q)
    if np.any(norm < _ZERO_QUATERNION):
        raise CameraError("zero quaternion")
    x, y, z, w = np.moveaxis(unit, -1, 0)
    R = np.empty(q.shape[:-1] + (3, 3))
    R[..., 0, 0] = 1 - 2 * (y * y + z * z)
    R[..., 0, 1] = 2 * (x * y - w * z)
    R[..., 0, 2] = 2 * (x * z + w * y)
    R[..., 1, 0] = 2 * (x * y + w * z)
    R[..., 1, 1] = 1 - 2 * (x * x + z * z)
    R[..., 1, 2] = 2 * (y * z - w * x)
    R[..., 2, 0] = 2 * (x * z - w * y)
    R[..., 2, 1] = 2 * (y * z + w * x)
    R[..., 2, 2] = 1 - 2 * (x * x + y * y)
    return R


def matrix_to_quaternion_xyzw(R: np.ndarray) -> np.ndarray:
    """Unit quaternion(s) (..., 4) in (x, y, z, w) order, w >= 0, from rotation matrices (..., 3, 3).

    Shepperd's method: the component with the largest magnitude is computed from the diagonal, the others
    from off-diagonal sums, so it is accurate for every rotation (including 180 degrees).

    Raises CameraError unless every matrix is finite and a rotation within :data:`MATRIX_TO_QUATERNION_TOLERANCE`
    (max |R^T R - I| and |det R - 1|).
    """
    R = check_real_array(R, "rotation matrix", CameraError)
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise CameraError(f"rotation matrix must be (..., 3, 3), got {R.shape}")
    if not np.all(np.isfinite(R)):
        raise CameraError("rotation matrix holds non-finite values")
    r00, r01, r02 = R[..., 0, 0], R[..., 0, 1], R[..., 0, 2]
    r10, r11, r12 = R[..., 1, 0], R[..., 1, 1], R[..., 1, 2]
    r20, r21, r22 = R[..., 2, 0], R[..., 2, 1], R[..., 2, 2]
    if R.size:
        ortho_err = float(np.max(np.abs(np.swapaxes(R, -1, -2) @ R - np.eye(3))))
        if ortho_err > MATRIX_TO_QUATERNION_TOLERANCE:
            raise CameraError(f"not a rotation matrix: max |R^T R - I| = {ortho_err:.3g} "
                              f"> {MATRIX_TO_QUATERNION_TOLERANCE:g}")
        det = r00 * (r11 * r22 - r12 * r21) - r01 * (r10 * r22 - r12 * r20) + r02 * (r10 * r21 - r11 * r20)
        worst = float(np.ravel(det)[np.argmax(np.abs(det - 1.0))])
        if abs(worst - 1.0) > MATRIX_TO_QUATERNION_TOLERANCE:
            raise CameraError(f"not a rotation matrix: determinant {worst:.3g}, expected +1 (a reflection?)")
    t = np.stack([1 + r00 + r11 + r22,   # 4 w^2
                  1 + r00 - r11 - r22,   # 4 x^2
                  1 - r00 + r11 - r22,   # 4 y^2
                  1 - r00 - r11 + r22],  # 4 z^2
                 axis=-1)
    s = 2.0 * np.sqrt(np.maximum(t, 1e-300))  # = 4 * |component|
    cand = np.stack([
        # (x, y, z, w) for each pivot
        np.stack([(r21 - r12) / s[..., 0], (r02 - r20) / s[..., 0], (r10 - r01) / s[..., 0], s[..., 0] / 4], -1),
        np.stack([s[..., 1] / 4, (r01 + r10) / s[..., 1], (r02 + r20) / s[..., 1], (r21 - r12) / s[..., 1]], -1),
        np.stack([(r01 + r10) / s[..., 2], s[..., 2] / 4, (r12 + r21) / s[..., 2], (r02 - r20) / s[..., 2]], -1),
        np.stack([(r02 + r20) / s[..., 3], (r12 + r21) / s[..., 3], s[..., 3] / 4, (r10 - r01) / s[..., 3]], -1),
    ], axis=-2)  # (..., 4 pivots, 4)
    pivot = np.argmax(t, axis=-1)
    q = np.take_along_axis(cand, pivot[..., None, None], axis=-2)[..., 0, :]
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., 3:4] < 0, -q, q)


def body_to_optical_rotation() -> np.ndarray:
    """R_body_optical (3, 3): optical axes (z fwd, x right, y down) expressed in a REP-103 body frame (x fwd, y left, z up).

    T_map_optical = T_map_body @ [[R_body_optical, 0], [0, 1]]. Equals quaternion (x, y, z, w) = (-0.5, 0.5, -0.5, 0.5).
    """
    return np.array([[0.0, 0.0, 1.0],
                     [-1.0, 0.0, 0.0],
                     [0.0, -1.0, 0.0]])


def intrinsics_from_fov(width: int, height: int, fov_x_deg: float) -> np.ndarray:
    """Pinhole K (3, 3) with square pixels, horizontal field of view ``fov_x_deg`` and the principal point at the
    image centre ((W - 1) / 2, (H - 1) / 2) in the pixel-centres-at-integers convention.

    Raises CameraError for an image size a Camera refuses, or ``fov_x_deg`` not a real number in (0, 180)
    degrees (exclusive) or so small that the focal length is not finite.
    """
    width, height = _image_size(width, height)
    fov = _real_number("fov_x_deg", fov_x_deg)
    if not (0.0 < fov < 180.0):
        raise CameraError(f"fov_x_deg must be in (0, 180) degrees, got {fov_x_deg!r}")
    f = width / (2.0 * math.tan(math.radians(fov) / 2.0))
    if not (math.isfinite(f) and f > 0):
        raise CameraError(f"fov_x_deg {fov_x_deg!r} gives focal length {f!r} px (not finite and > 0)")
    return np.array([[f, 0.0, (width - 1) / 2.0], [0.0, f, (height - 1) / 2.0], [0.0, 0.0, 1.0]])


def _as_K(K: np.ndarray | Sequence[float]) -> np.ndarray:
    k = check_real_array(K, "intrinsics K", CameraError, copy=True)
    if k.shape == (9,):
        k = k.reshape(3, 3)
    if k.shape != (3, 3):
        raise CameraError(f"intrinsics K must be (3, 3) or 9 row-major values, got shape {k.shape}")
    return k


def _as_int(name: str, v: object) -> int:
    if isinstance(v, (bool, np.bool_)):
        raise CameraError(f"{name} must be an integer, got {v!r}")
    if isinstance(v, (int, np.integer)):
        return int(v)
    if isinstance(v, (float, np.floating)) and math.isfinite(v) and float(v).is_integer():
        return int(v)
    raise CameraError(f"{name} must be an integer, got {reprlib.repr(v)}")


def _image_size(width: object, height: object) -> tuple[int, int]:
    """(width, height) as ints >= 1 with width x height <= :data:`MAX_CAMERA_PIXELS`; CameraError naming the size."""
    w, h = _as_int("width", width), _as_int("height", height)
    if w <= 0 or h <= 0:
        raise CameraError(f"image size must be positive, got width={reprlib.repr(w)} height={reprlib.repr(h)}")
    if w * h > MAX_CAMERA_PIXELS:
        raise CameraError(f"image size {reprlib.repr(w)}x{reprlib.repr(h)} exceeds MAX_CAMERA_PIXELS = "
                          f"{MAX_CAMERA_PIXELS} (8192 x 8192) pixels")
    return w, h


def _real_number(name: str, v: object) -> float:
    """``v`` as a float: a real number (int, float or numpy scalar; not bool, str or complex), else CameraError."""
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, numbers.Real):
        raise CameraError(f"{name} must be a real number, got {reprlib.repr(v)}")
    try:
        return float(v)
    except OverflowError:  # an int beyond float range
        return math.inf if v > 0 else -math.inf


def _vector3(name: str, v: object) -> np.ndarray:
    """``v`` as a finite (3,) float64 vector, else CameraError naming ``name``."""
    a = check_real_array(v, name, CameraError)
    if a.size != 3:
        raise CameraError(f"{name} must have 3 components, got shape {a.shape}")
    a = a.reshape(3)
    if not np.all(np.isfinite(a)):
        raise CameraError(f"{name} holds non-finite values: {a.tolist()}")
    return a


@dataclass(frozen=True, eq=False)
class Camera:
    """Pinhole camera without distortion (rectified images), pixel centres at integer coordinates.

    Attributes:
        K: (3, 3) float64 intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in pixels (no skew).
        width, height: image size in pixels.
        T_map_cam: (4, 4) float64 rigid pose of the camera OPTICAL frame (z forward, x right, y down) in the map
            frame; maps optical-frame points to map points. World-to-camera is its inverse (``world_to_cam``).

    The arrays are read-only copies.
    """

    K: np.ndarray
    width: int
    height: int
    T_map_cam: np.ndarray

    def __post_init__(self) -> None:
        K = _as_K(self.K)
        width, height = _image_size(self.width, self.height)
        if not np.all(np.isfinite(K)):
            raise CameraError(f"intrinsics K hold non-finite values: {K.tolist()}")
        if not (K[0, 0] > 0 and K[1, 1] > 0):
            raise CameraError(f"intrinsics need fx > 0 and fy > 0, got fx={K[0, 0]} fy={K[1, 1]}")
        if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
            raise CameraError(f"intrinsics K must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew), "
                              f"got {K.tolist()}")
        T = check_real_array(self.T_map_cam, "T_map_cam", CameraError, copy=True)
        if T.shape != (4, 4):
            raise CameraError(f"T_map_cam must be (4, 4), got {T.shape}")
        if not np.all(np.isfinite(T)):
            raise CameraError("T_map_cam holds non-finite values")
        if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=1e-9):
            raise CameraError(f"T_map_cam last row must be [0, 0, 0, 1], got {T[3].tolist()}")
        R = T[:3, :3]
        ortho_err = float(np.max(np.abs(R.T @ R - np.eye(3))))
        if ortho_err > _ORTHO_TOL:
            raise CameraError(f"T_map_cam rotation is not orthonormal (max |R^T R - I| = {ortho_err:.3g})")
        det = float(np.linalg.det(R))
        if abs(det - 1.0) > _ORTHO_TOL:
            raise CameraError(f"T_map_cam rotation has determinant {det:.6g}, expected +1 (a reflection?)")
        K.setflags(write=False)
        T.setflags(write=False)
        object.__setattr__(self, "K", K)
        object.__setattr__(self, "T_map_cam", T)
        object.__setattr__(self, "width", width)
        object.__setattr__(self, "height", height)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_pose(cls, K: np.ndarray | Sequence[float], width: int, height: int,
                  position_xyz: Sequence[float] | np.ndarray,
                  quaternion_xyzw: Sequence[float] | np.ndarray) -> "Camera":
        """Camera from intrinsics and the optical-frame pose in the map (geometry_msgs/Pose convention).

        Args:
            K: (3, 3) intrinsics or the 9 row-major values of ``sensor_msgs/CameraInfo.k``.
            width, height: image size in pixels.
            position_xyz: (3,) optical-frame origin in the map frame, metres.
            quaternion_xyzw: (4,) orientation of the optical frame in the map, (x, y, z, w) order as in
                geometry_msgs/Quaternion.

        The quaternion is normalised. Its norm must lie in [0.9, 1.1] (``QUATERNION_NORM_TOLERANCE``): messages
        round quaternions (float32 storage, text formats) so small deviations are expected and normalised away,
        while a larger deviation (e.g. a zero quaternion from an uninitialised message, or xyzw/wxyz mix-ups
        with scaled values) means a bug upstream and is rejected with CameraError.
        """
        pos = check_real_array(position_xyz, "position", CameraError).reshape(-1)
        q = check_real_array(quaternion_xyzw, "quaternion", CameraError).reshape(-1)
        if pos.shape != (3,):
            raise CameraError(f"position must have 3 components, got {pos.shape}")
        if q.shape != (4,):
            raise CameraError(f"quaternion must have 4 components (x, y, z, w), got {q.shape}")
        if not np.all(np.isfinite(pos)):
            raise CameraError(f"position holds non-finite values: {pos.tolist()}")
        if not np.all(np.isfinite(q)):
            raise CameraError(f"quaternion holds non-finite values: {q.tolist()}")
        norm = float(np.linalg.norm(q))
        lo, hi = QUATERNION_NORM_TOLERANCE
        if not (lo <= norm <= hi):
            raise CameraError(f"not a unit quaternion: {q.tolist()} has norm {norm:.6g} "
                              f"(accepted [{lo}, {hi}] before normalisation)")
        T = np.eye(4)
        T[:3, :3] = quaternion_xyzw_to_matrix(q / norm)
        T[:3, 3] = pos
        return cls(K=_as_K(K), width=width, height=height, T_map_cam=T)

    @classmethod
    def from_camera_info_k(cls, k9: Sequence[float] | np.ndarray, width: int, height: int,
                           position_xyz: Sequence[float] | np.ndarray,
                           quaternion_xyzw: Sequence[float] | np.ndarray) -> "Camera":
        """Alias of :meth:`from_pose` taking ``CameraInfo.k`` (9 row-major values)."""
        return cls.from_pose(k9, width, height, position_xyz, quaternion_xyzw)

    @classmethod
    def look_at(cls, position: Sequence[float] | np.ndarray, target: Sequence[float] | np.ndarray,
                K: np.ndarray | Sequence[float], width: int, height: int,
                up: Sequence[float] | np.ndarray = (0.0, 0.0, 1.0)) -> "Camera":
        """Optical-frame camera at ``position`` (map, metres) whose optical axis (+z) points at ``target``.

        Image "up" (-y optical) is aligned as closely as possible with the map direction ``up``. CameraError if an
        argument is not a finite 3-vector, ``up`` is zero, position == target, or the viewing direction is parallel
        to ``up`` (pass another ``up`` then). Directions are scaled by their largest component before any norm, so
        coordinates up to the float range work.
        """
        pos = _vector3("look_at: position", position)
        tgt = _vector3("look_at: target", target)
        upv = _vector3("look_at: up", up)
        with np.errstate(over="ignore"):
            d = tgt - pos
        if not np.all(np.isfinite(d)):  # beyond the float range: the halves cannot overflow
            d = tgt * 0.5 - pos * 0.5
        z, dist = _unit_rows(d)
        if float(dist[0]) < 1e-12:
            raise CameraError("look_at: position and target coincide")
        u, up_norm = _unit_rows(upv)
        if float(up_norm[0]) == 0.0:
            raise CameraError("look_at: up must be a non-zero vector")
        x = np.cross(z, u)
        nx = np.linalg.norm(x)
        if nx < 1e-9:
            raise CameraError("look_at: viewing direction is parallel to 'up'; pass a different up vector")
        x /= nx
        y = np.cross(z, x)
        T = np.eye(4)
        T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = x, y, z, pos
        return cls(K=_as_K(K), width=width, height=height, T_map_cam=T)

    # ------------------------------------------------------------------ properties
    @property
    def fx(self) -> float:
        """Focal length along x, pixels."""
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        """Focal length along y, pixels."""
        return float(self.K[1, 1])

    @property
    def cx(self) -> float:
        """Principal point x, pixels (pixel centres at integers)."""
        return float(self.K[0, 2])

    @property
    def cy(self) -> float:
        """Principal point y, pixels (pixel centres at integers)."""
        return float(self.K[1, 2])

    @property
    def position(self) -> np.ndarray:
        """(3,) float64 optical-frame origin in the map, metres."""
        return self.T_map_cam[:3, 3].copy()

    @property
    def R_map_cam(self) -> np.ndarray:
        """(3, 3) float64 rotation of the optical frame in the map (columns = optical axes in map coordinates)."""
        return self.T_map_cam[:3, :3].copy()

    @property
    def quaternion_xyzw(self) -> np.ndarray:
        """(4,) float64 orientation of the optical frame in the map, (x, y, z, w), w >= 0."""
        return matrix_to_quaternion_xyzw(self.T_map_cam[:3, :3])

    @property
    def R_cam_map(self) -> np.ndarray:
        """(3, 3) float64 world-to-camera rotation (R_map_cam transposed)."""
        return self.T_map_cam[:3, :3].T.copy()

    @property
    def t_cam_map(self) -> np.ndarray:
        """(3,) float64 world-to-camera translation: p_cam = R_cam_map @ p_map + t_cam_map."""
        return -self.T_map_cam[:3, :3].T @ self.T_map_cam[:3, 3]

    @property
    def world_to_cam(self) -> np.ndarray:
        """(4, 4) float64 T_cam_map = inverse(T_map_cam) (rigid inverse)."""
        out = np.eye(4)
        out[:3, :3] = self.R_cam_map
        out[:3, 3] = self.t_cam_map
        return out

    # ------------------------------------------------------------------ operations
    def project(self, points_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project map points (M, 3) -> (pixels (M, 2) float64 (u, v), depth z (M,) metres along the optical axis).

        No culling: points with z <= 0 get meaningless pixel coordinates (check ``depth``).
        """
        p = np.asarray(points_map, dtype=np.float64).reshape(-1, 3)
        pc = p @ self.R_cam_map.T + self.t_cam_map
        z = pc[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            uvw = pc @ self.K.T
            uv = uvw[:, :2] / z[:, None]
        return uv, z

    def scaled(self, factor: float) -> "Camera":
        """Camera for the image resized by ``factor`` (same pose): :meth:`resized` to
        (max(1, round(width * factor)), max(1, round(height * factor)))."""
        f = _real_number("scale factor", factor)
        if not (math.isfinite(f) and f > 0):
            raise CameraError(f"scale factor must be finite and > 0, got {reprlib.repr(factor)}")
        wf, hf = max(1.0, self.width * f), max(1.0, self.height * f)  # Python floats: inf at worst, no warning
        # the first test keeps round() away from inf
        if wf * hf > 2 * MAX_CAMERA_PIXELS or max(1, round(wf)) * max(1, round(hf)) > MAX_CAMERA_PIXELS:
            raise CameraError(f"scale factor {reprlib.repr(factor)} gives a {wf:.6g}x{hf:.6g} image, above "
                              f"MAX_CAMERA_PIXELS = {MAX_CAMERA_PIXELS} (8192 x 8192) pixels")
        return self.resized(max(1, round(wf)), max(1, round(hf)))

    def resized(self, width: int, height: int) -> "Camera":
        """Camera for the image resampled to ``width`` x ``height`` pixels (same pose, same field of view).

        With s_x = width' / width and s_y = height' / height: fx' = fx s_x, cx' = (cx + 0.5) s_x - 0.5 (likewise
        y), which keeps the pixel-centres-at-integers convention (the image edge -0.5 maps to -0.5). CameraError for
        a size a Camera refuses (not integers >= 1, or above :data:`MAX_CAMERA_PIXELS`).
        """
        w2, h2 = _image_size(width, height)
        sx, sy = w2 / self.width, h2 / self.height
        K = np.array(self.K)
        K[0, 0] *= sx
        K[0, 2] = (K[0, 2] + 0.5) * sx - 0.5
        K[1, 1] *= sy
        K[1, 2] = (K[1, 2] + 0.5) * sy - 0.5
        return Camera(K=K, width=w2, height=h2, T_map_cam=np.array(self.T_map_cam))
