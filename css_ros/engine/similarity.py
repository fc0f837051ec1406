"""Similarity transforms between the splat's frame and the robot's map frame, and rigid camera extrinsics.

A trained splat lives in its trainer's frame and scale; the robot localises in its map frame in metres.
``splat_to_map`` = (s, R, t) takes splat coordinates into the map: ``x_map = s R x_splat + t``. The engine
always works in the splat frame; everything a node or tool receives or publishes is in the map frame, converted
here (docs/spec.md, "The splat in the map").

Parameter layouts (node parameters, css_replay options, css_align's output):

- ``splat_to_map``: 8 numbers ``[s, x, y, z, qx, qy, qz, qw]`` (scale s > 0, translation [m], rotation as a
  unit quaternion in geometry_msgs order).
- camera extrinsics: 7 numbers ``[x, y, z, qx, qy, qz, qw]`` per camera, the camera's optical frame in the frame
  the pose describes (e.g. ``base_link``): ``T_map_optical = T_map_body @ T_body_optical``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Sequence

import numpy as np

from ..errors import ConfigError
from .camera import QUATERNION_NORM_TOLERANCE, matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix

if TYPE_CHECKING:
    from .gaussians import GaussianModel

#: Number of values of a ``splat_to_map`` parameter and of one camera's extrinsics.
SIMILARITY_VALUES = 8
EXTRINSICS_VALUES = 7
#: Identity ``splat_to_map``.
IDENTITY_SIMILARITY = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
#: Unit-quaternion tolerance of a configured rotation (tighter than for messages: a parameter is typed once).
CONFIG_QUATERNION_TOLERANCE = 1e-3


def _quaternion(values: Sequence[float], name: str) -> np.ndarray:
    q = np.asarray(values, dtype=np.float64)
    norm = float(np.linalg.norm(q))
    if not np.all(np.isfinite(q)) or abs(norm - 1.0) > CONFIG_QUATERNION_TOLERANCE:
        raise ConfigError(f"{name}: quaternion (qx, qy, qz, qw) = {q.tolist()} is not a unit quaternion "
                          f"(norm {norm:.6g}; allowed 1 +- {CONFIG_QUATERNION_TOLERANCE:g})")
    return q / norm


@dataclass(frozen=True)
class Similarity:
    """x_out = scale * R @ x_in + t: a uniform scale (> 0), a rotation (3, 3) and a translation (3,).

    Used for ``splat_to_map`` (in = splat frame, out = map frame [m]) and, with scale 1, for rigid transforms
    (camera extrinsics: in = optical frame, out = body frame).
    """

    scale: float
    R: np.ndarray
    t: np.ndarray

    def __post_init__(self) -> None:
        R = np.array(self.R, dtype=np.float64).reshape(3, 3)
        t = np.array(self.t, dtype=np.float64).reshape(3)
        R.setflags(write=False)
        t.setflags(write=False)
        object.__setattr__(self, "R", R)
        object.__setattr__(self, "t", t)
        object.__setattr__(self, "scale", float(self.scale))

    # ------------------------------------------------------------------ construction
    @classmethod
    def identity(cls) -> "Similarity":
        return cls(1.0, np.eye(3), np.zeros(3))

    @classmethod
    def from_params(cls, values: Sequence[float], name: str = "splat_to_map") -> "Similarity":
        """From ``[s, x, y, z, qx, qy, qz, qw]``; ConfigError naming ``name`` on a bad value."""
        try:
            v = [float(x) for x in values]
        except (TypeError, ValueError):
            raise ConfigError(f"{name}: expected {SIMILARITY_VALUES} numbers [s, x, y, z, qx, qy, qz, qw], "
                              f"got {list(values)!r}") from None
        if len(v) != SIMILARITY_VALUES:
            raise ConfigError(f"{name}: expected {SIMILARITY_VALUES} numbers [s, x, y, z, qx, qy, qz, qw], "
                              f"got {len(v)}")
        s = v[0]
        if not (math.isfinite(s) and MIN_SCALE <= s <= MAX_SCALE):
            raise ConfigError(f"{name}: scale must be finite and within {MIN_SCALE:g}..{MAX_SCALE:g}, got {s!r}")
        if not all(math.isfinite(x) and abs(x) <= MAX_TRANSLATION_M for x in v[1:4]):
            raise ConfigError(f"{name}: translation must be finite and within ±{MAX_TRANSLATION_M:g} m "
                              f"(poses are float32 in messages), got {v[1:4]}")
        q = _quaternion(v[4:8], name)
        return cls(s, quaternion_xyzw_to_matrix(q), np.array(v[1:4]))

    @classmethod
    def rigid_from_params(cls, values: Sequence[float], name: str = "camera_extrinsics") -> "Similarity":
        """A rigid transform from ``[x, y, z, qx, qy, qz, qw]``; ConfigError naming ``name`` on a bad value."""
        v = list(values)
        if len(v) != EXTRINSICS_VALUES:
            raise ConfigError(f"{name}: expected {EXTRINSICS_VALUES} numbers [x, y, z, qx, qy, qz, qw], got {len(v)}")
        return cls.from_params([1.0, *v], name)

    def to_params(self) -> list[float]:
        """``[s, x, y, z, qx, qy, qz, qw]`` (the inverse of :meth:`from_params`)."""
        q = matrix_to_quaternion_xyzw(self.R)
        return [self.scale, *(float(x) for x in self.t), *(float(x) for x in q)]

    # ------------------------------------------------------------------ algebra
    @property
    def is_identity(self) -> bool:
        return self.scale == 1.0 and bool(np.all(self.R == np.eye(3))) and bool(np.all(self.t == 0.0))

    def inverse(self) -> "Similarity":
        """x_in = (1/s) R^T (x_out - t)."""
        Rt = self.R.T
        return Similarity(1.0 / self.scale, Rt, -(Rt @ self.t) / self.scale)

    def __matmul__(self, other: "Similarity") -> "Similarity":
        """Composition: (self @ other)(x) = self(other(x))."""
        return Similarity(self.scale * other.scale, self.R @ other.R, self.scale * (self.R @ other.t) + self.t)

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform points (..., 3) -> (..., 3) float64."""
        p = np.asarray(points, dtype=np.float64)
        return self.scale * (p @ self.R.T) + self.t

    def matrix(self) -> np.ndarray:
        """(4, 4) homogeneous matrix [[s R, t], [0, 1]]."""
        T = np.eye(4)
        T[:3, :3] = self.scale * self.R
        T[:3, 3] = self.t
        return T

    # ------------------------------------------------------------------ poses
    def apply_pose(self, position: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pose (position (3,), orientation (4,) xyzw) of a frame given in the input frame -> in the output frame.

        The orientation is rotated by R; a frame's axes are not scaled (a camera stays a camera).
        """
        pos = self.apply(np.asarray(position, dtype=np.float64))
        R = self.R @ quaternion_xyzw_to_matrix(quat_xyzw)
        return pos, matrix_to_quaternion_xyzw(R)

    def apply_poses(self, positions: np.ndarray, quats_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Vectorised :meth:`apply_pose`: (M, 3), (M, 4) -> (M, 3), (M, 4); rows with NaN stay NaN."""
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        quats = np.asarray(quats_xyzw, dtype=np.float64).reshape(-1, 4)
        out_q = np.full_like(quats, np.nan)
        ok = np.all(np.isfinite(quats), axis=1) & (np.linalg.norm(np.nan_to_num(quats), axis=1) > 0)
        if np.any(ok):
            out_q[ok] = matrix_to_quaternion_xyzw(self.R @ quaternion_xyzw_to_matrix(quats[ok]))
        return self.apply(positions), out_q

    def compose_pose(self, position: np.ndarray, quat_xyzw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For a rigid ``self`` = T_body_child: pose of the child given the body's pose (position, xyzw) in a frame.

        T_frame_child = T_frame_body @ T_body_child (scale must be 1).
        """
        R_fb = quaternion_xyzw_to_matrix(quat_xyzw)
        pos = np.asarray(position, dtype=np.float64) + R_fb @ self.t
        return pos, matrix_to_quaternion_xyzw(R_fb @ self.R)

    def transform_model(self, model: "GaussianModel") -> "GaussianModel":
        """The splat moved by this similarity: means s R x + t, standard deviations x s, orientations R q.

        View-dependent colour (SH degree >= 1) is defined in the input frame; it is kept as is for a pure
        scale/translation and dropped (degree 0, the base colour stays) when R is not the identity, since
        rotating SH coefficients is not needed anywhere a transformed model is used (exports, viewers, tests).
        """
        from .gaussians import GaussianModel

        q_wxyz = model.rotations.astype(np.float64)
        q_wxyz = q_wxyz / np.linalg.norm(q_wxyz, axis=1, keepdims=True)
        R_g = quaternion_xyzw_to_matrix(q_wxyz[:, [1, 2, 3, 0]])
        q_new = matrix_to_quaternion_xyzw(self.R[None] @ R_g)[:, [3, 0, 1, 2]]
        rotated = not bool(np.all(self.R == np.eye(3)))
        sh = model.sh[:, :1] if rotated else model.sh
        return GaussianModel(means=self.apply(model.means).astype(np.float32), sh=sh,
                             opacity_logits=model.opacity_logits,
                             log_scales=(model.log_scales.astype(np.float64) + math.log(self.scale)).astype(np.float32),
                             rotations=q_new.astype(np.float32),
                             normals=None if model.normals is None else model.normals @ self.R.T.astype(np.float32))


def rotation_between(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation (3, 3) taking direction ``a`` to direction ``b`` (both (3,), any length > 0)."""
    a = np.asarray(a, dtype=np.float64) / np.linalg.norm(a)
    b = np.asarray(b, dtype=np.float64) / np.linalg.norm(b)
    v = np.cross(a, b)
    c = float(np.dot(a, b))
    if c < -1.0 + 1e-12:  # opposite: 180 degrees about any axis orthogonal to a
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        axis /= np.linalg.norm(axis)
        return 2.0 * np.outer(axis, axis) - np.eye(3)
    vx = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + vx + vx @ vx / (1.0 + c)


#: Bounds of a similarity's scale and translation [m]: beyond, positions stop being representable in the float32
#: of messages and clouds (1e7 m is 10 000 km; a float32 there resolves 1 m).
MIN_SCALE = 1e-6
MAX_SCALE = 1e6
MAX_TRANSLATION_M = 1e7


def parse_extrinsics(values: Sequence[float], num_cameras: int,
                     name: str = "camera_extrinsics") -> list[Similarity | None]:
    """Per-camera extrinsics from a flat list: empty -> ``[None] * num_cameras`` (the pose is the optical frame's);
    otherwise exactly 7 numbers per camera (ConfigError naming ``name`` and the camera index on a bad value)."""
    v = list(values)
    if not v:
        return [None] * num_cameras
    if len(v) != EXTRINSICS_VALUES * num_cameras:
        raise ConfigError(f"{name}: expected {EXTRINSICS_VALUES} numbers [x, y, z, qx, qy, qz, qw] per camera "
                          f"({num_cameras} camera(s): {EXTRINSICS_VALUES * num_cameras} numbers), got {len(v)}")
    return [Similarity.rigid_from_params(v[i * EXTRINSICS_VALUES:(i + 1) * EXTRINSICS_VALUES],
                                         f"{name} (camera {i})") for i in range(num_cameras)]


__all__ = ["EXTRINSICS_VALUES", "IDENTITY_SIMILARITY", "SIMILARITY_VALUES", "Similarity", "parse_extrinsics",
           "rotation_between", "QUATERNION_NORM_TOLERANCE"]
