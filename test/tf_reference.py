"""The TF brute force of the tests: 4x4 matrices composed edge by edge, each dynamic edge interpolated linearly
(position) and with scipy's Slerp (rotation), exact at a sample; independent of css_ros.io.pose_history."""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy.spatial.transform import Rotation, Slerp

#: (stamp [ns], translation (3,), quaternion xyzw (4,)) samples of one edge, in time order.
Samples = Sequence[tuple[int, Sequence[float], Sequence[float]]]


def mat(xyz: Sequence[float], q: Sequence[float]) -> np.ndarray:
    """4x4 rigid transform from a translation and an xyzw quaternion."""
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(q).as_matrix()
    T[:3, 3] = xyz
    return T


def brute_edge(samples: Samples, t: int) -> np.ndarray:
    """T_parent_child at stamp ``t`` [ns] from time-ordered samples (``t`` within their span)."""
    times = np.array([s[0] for s in samples], dtype=np.int64)
    i = int(np.searchsorted(times, t))
    if i < len(times) and times[i] == t:
        return mat(samples[i][1], samples[i][2])
    (t0, p0, q0), (t1, p1, q1) = samples[i - 1], samples[i]
    u = (t - t0) / (t1 - t0)
    T = np.eye(4)
    T[:3, :3] = Slerp([0.0, 1.0], Rotation.from_quat([q0, q1]))([u])[0].as_matrix()
    T[:3, 3] = np.asarray(p0) + u * (np.asarray(p1) - np.asarray(p0))
    return T


def brute_chain(frame: str, root: str, t: int, parents: dict[str, str], dynamic: dict[str, Samples],
                static: dict[str, np.ndarray]) -> np.ndarray:
    """T_root_frame at ``t``: the edges from ``frame`` up to ``root`` composed (``parents[child]`` = its parent)."""
    T = np.eye(4)
    while frame != root:
        E = static[frame] if frame in static else brute_edge(dynamic[frame], t)
        T = E @ T
        frame = parents[frame]
    return T


def pose_errors(position: np.ndarray, quat: np.ndarray, T: np.ndarray) -> tuple[float, float]:
    """(position error [m], rotation angle error [rad]) of a pose (xyzw quaternion) against a 4x4 transform."""
    R = Rotation.from_quat(quat).as_matrix()
    return (float(np.linalg.norm(np.asarray(position) - T[:3, 3])),
            float(Rotation.from_matrix(R.T @ T[:3, :3]).magnitude()))
