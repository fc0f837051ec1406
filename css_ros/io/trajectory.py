"""The observed camera trajectory of a replay (``trajectory.npz``): poses, fields of view and U_var per frame."""
from __future__ import annotations

import zipfile
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ..engine.camera import quaternion_xyzw_to_matrix
from ..errors import CssError

if TYPE_CHECKING:
    from ..engine.similarity import Similarity

#: (T_map_cam (4, 4), vertical field of view [rad], aspect width/height, U_var or NaN)
Frustum = tuple[np.ndarray, float, float, float]
MAX_FRAMES = 100_000


def save_trajectory(path: Path, poses: np.ndarray, fov_y: np.ndarray, aspect: np.ndarray, u_var: np.ndarray) -> None:
    """Write (F, 4, 4) poses T_map_cam, (F,) fov_y [rad], (F,) aspect and (F,) U_var (NaN when unknown)."""
    np.savez(path, poses=np.asarray(poses, np.float64), fov_y=np.asarray(fov_y, np.float64),
             aspect=np.asarray(aspect, np.float64), u_var=np.asarray(u_var, np.float64))


def load_trajectory(path: Path) -> list[Frustum]:
    """Read :func:`save_trajectory`'s file (no pickles; at most MAX_FRAMES frames)."""
    try:
        with np.load(path, allow_pickle=False) as d:
            poses, fov, aspect, u = (np.asarray(d[k], np.float64) for k in ("poses", "fov_y", "aspect", "u_var"))
    except (OSError, ValueError, KeyError, zipfile.BadZipFile) as exc:
        raise CssError(f"cannot read trajectory {path}: {exc}") from None
    f = len(fov)
    if poses.shape != (f, 4, 4) or aspect.shape != (f,) or u.shape != (f,) or f > MAX_FRAMES:
        raise CssError(f"trajectory {path}: inconsistent shapes")
    return [(poses[i], float(fov[i]), float(aspect[i]), float(u[i])) for i in range(f)]


def write_replay_trajectory(path: Path, frames: list, splat_to_map: "Similarity | None" = None) -> None:
    """Write the fused frames' cameras (``(camera, u_var or None)`` pairs, :class:`css_ros.Camera`, poses in the
    splat frame as the engine sees them) as a trajectory file in the map frame (moved by ``splat_to_map``, which
    turns the camera axes by its rotation and carries the centre along; the scale moves the centre only);
    nothing when ``frames`` is empty."""
    if not frames:
        return
    poses = np.stack([cam.T_map_cam for cam, _ in frames])
    if splat_to_map is not None and not splat_to_map.is_identity:
        pos, quat = splat_to_map.apply_poses(np.stack([cam.position for cam, _ in frames]),
                                             np.stack([cam.quaternion_xyzw for cam, _ in frames]))
        poses[:, :3, :3] = quaternion_xyzw_to_matrix(quat)
        poses[:, :3, 3] = pos
    fov = np.array([2.0 * np.arctan(cam.height / (2.0 * cam.fy)) for cam, _ in frames])
    aspect = np.array([(cam.width / cam.fx) / (cam.height / cam.fy) for cam, _ in frames])
    u = np.array([np.nan if uv is None else float(uv) for _, uv in frames])
    save_trajectory(path, poses, fov, aspect, u)
