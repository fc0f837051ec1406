"""Robot-like camera path through the demo room: smooth, at robot camera height, with revisits and a late part.

The path is a C1 monotone cubic (PCHIP) spline through hand-placed waypoints (x, y, camera height, yaw,
pitch) in the free space of :mod:`css_ros.demo_scene`'s room, timed like a slow mobile robot (0.5 m/s,
35 deg/s turns). Its three phases:

1. the east half and the north side (window, sofa corner with rug and coffee table, cabinet, north wall, door,
   dining table from the north) - the south-west corner (bookshelf, plant) stays out of view;
2. back east along the north side and to the sofa: *revisits* of places seen in phase 1 from new viewpoints;
3. (from waypoint ``LATE_PHASE_START``) west along the south corridor to the bookshelf and plant corner,
   *seen for the first time*, then a last look at the west wall and the dining table.

The studio layout (``layout="studio"``, a 9 m x 4.5 m flat) has its own path, :data:`STUDIO_WAYPOINTS`, along
the free corridor in the middle of the flat (~38 s), alternating close looks (< 1.5 m) with views along the long
axis (far walls 5-8 m away):

1. the living corner at the east end (sofa, rug, coffee table, window, lamp), then a long view west across the
   whole flat;
2. the dining table and the desk from close by;
3. (from waypoint ``late_phase_start("studio")``) the west end seen close for the first time (moving boxes,
   door, bookshelf, kitchen), a long view back east and the return to the middle.

Poses are T_map_cam of the camera OPTICAL frame (z forward, x right, y down) in the map frame (z up).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import PchipInterpolator

__all__ = ["LATE_PHASE_START", "STUDIO_WAYPOINTS", "Trajectory", "WAYPOINTS", "late_phase_start", "look_at_rotation",
           "robot_trajectory", "waypoint_spline"]

#: Waypoints (x [m], y [m], camera height [m], yaw [deg, 0 = +x, ccw], pitch [deg, negative = looking down]).
WAYPOINTS: tuple[tuple[float, float, float, float, float], ...] = (
    # phase 1: east half and north side
    (2.2, -0.4, 1.00, 0.0, 10.0),       # window (looking up a little: ceiling)
    (2.6, -0.9, 1.00, -60.0, -14.0),    # south-east corner: lamp, sofa
    (2.3, -0.5, 1.05, -110.0, -18.0),   # sofa, rug, coffee table
    (2.4, 0.5, 1.00, 40.0, 0.0),        # plant by the window, east wall outlet
    (1.6, 1.2, 1.00, 95.0, -10.0),      # cabinet, picture on the north wall
    (0.4, 1.7, 1.05, 125.0, 10.0),      # north wall, outlet, ceiling
    (-1.0, 1.9, 1.00, 160.0, 6.0),      # door, lamp in the north-west corner
    (-2.2, 1.9, 1.00, 110.0, -2.0),     # close to the door
    (-2.6, 1.9, 1.05, -45.0, -22.0),    # turn round (through north and east): dining table from the north-west
    # phase 2: revisits
    (-0.3, 1.8, 1.00, -85.0, -20.0),    # dining table from the north-east
    (1.4, 1.6, 1.00, -60.0, -15.0),     # across the room to the sofa
    (2.5, 0.2, 1.00, -115.0, -15.0),    # sofa again
    (2.3, -0.65, 1.00, -125.0, -10.0),  # rug and coffee table from close by
    # phase 3: the late part
    (0.4, -0.7, 1.00, -160.0, -10.0),   # turning west: the south-west corner comes into view
    (-1.6, -0.85, 1.00, -145.0, -12.0),  # bookshelf and plant
    (-2.6, -0.75, 1.05, -120.0, -15.0),
    (-2.7, -0.45, 1.00, -190.0, -5.0),  # west wall, picture
    (-2.7, -0.3, 1.00, -270.0, -15.0),  # dining table from the south-west
)
#: Index of the first waypoint of phase 3 (the part of the room seen only late).
LATE_PHASE_START = 12

#: Waypoints of the studio path (same columns as :data:`WAYPOINTS`; yaw is continuous, not wrapped).
STUDIO_WAYPOINTS: tuple[tuple[float, float, float, float, float], ...] = (
    # phase 1: living corner, then the long view west
    (0.9, -0.3, 1.00, 0.0, -8.0),        # sofa, coffee table and picture ~3 m ahead
    (1.8, -1.0, 1.00, 35.0, -18.0),      # rug, coffee table, sofa arm from close by
    (2.0, 0.9, 1.05, 60.0, 0.0),         # window, lamp and plant in the north-east
    (1.6, 0.3, 1.00, 180.0, 4.0),        # long view west: kitchen, bookshelf, door 5-6 m away
    # phase 2: dining table and desk from close by
    (0.2, -0.3, 1.00, 150.0, -12.0),     # dining table from the south-east
    (-1.3, -0.5, 1.00, 250.0, -20.0),    # desk, desk chair, picture above the desk
    # phase 3: the west end close for the first time, long view back east
    (-2.8, -0.2, 1.00, 200.0, -8.0),     # moving boxes, door, lamp
    (-3.4, 0.1, 1.00, 170.0, -10.0),     # bookshelf (~0.8 m)
    (-3.3, 0.5, 1.05, 100.0, -10.0),     # kitchen
    (-3.2, 0.0, 1.00, 0.0, -3.0),        # long view east: sofa and windows 6-8 m away
    (-1.5, -0.4, 1.00, 20.0, -6.0),
    (0.5, -0.6, 1.00, -20.0, -10.0),     # south wall, outlets, picture
    (1.2, 0.2, 1.00, 60.0, -5.0),
)
_Waypoints = tuple[tuple[float, float, float, float, float], ...]


@dataclass(frozen=True)
class _Path:
    """A layout's path: waypoints, first waypoints of phases 2 and 3, and the robot's speed limits
    (m/s, deg/s of yaw, deg/s of pitch)."""

    waypoints: _Waypoints
    phase2: int
    late: int
    speed: float = 0.5
    turn: float = 35.0
    pitch: float = 20.0


_PATHS: dict[str, _Path] = {
    "room": _Path(WAYPOINTS, 9, LATE_PHASE_START),
    # the studio path turns more per metre: a slower turn rate keeps the frame-to-frame rotation of an
    # 80-frame sampling (~0.48 s per frame) near 20 degrees
    "studio": _Path(STUDIO_WAYPOINTS, 4, 6, turn=28.0),
}


@dataclass(frozen=True)
class Trajectory:
    """Sampled camera path (F frames).

    Attributes:
        times: (F,) seconds since the start of the path.
        T_map_cam: (F, 4, 4) optical-frame poses in the map frame (metres).
        positions: (F, 3) optical-frame origins, metres.
        quaternions_xyzw: (F, 4) optical-frame orientations (x, y, z, w), w >= 0.
        phase: (F,) int 1, 2 or 3 (see module docstring).
    """

    times: np.ndarray
    T_map_cam: np.ndarray
    positions: np.ndarray
    quaternions_xyzw: np.ndarray
    phase: np.ndarray

    def __len__(self) -> int:
        return len(self.times)


def look_at_rotation(forward: np.ndarray, up: np.ndarray | None = None) -> np.ndarray:
    """R_map_cam (..., 3, 3) of optical frames looking along ``forward`` (..., 3), image-up towards ``up``.

    Columns: x right = forward x up, y down = forward x right, z = forward (all unit).
    """
    f = np.asarray(forward, float)
    f = f / np.linalg.norm(f, axis=-1, keepdims=True)
    u = np.broadcast_to(np.array([0.0, 0.0, 1.0]) if up is None else np.asarray(up, float), f.shape)
    x = np.cross(f, u)
    x /= np.linalg.norm(x, axis=-1, keepdims=True)
    y = np.cross(f, x)
    return np.stack([x, y, f], axis=-1)


def _path(layout: str) -> _Path:
    if layout not in _PATHS:
        raise ValueError(f"unknown scene layout {layout!r}; expected one of {', '.join(_PATHS)}")
    return _PATHS[layout]


def late_phase_start(layout: str = "room") -> int:
    """Index of the first phase-3 waypoint of a layout's path (:data:`LATE_PHASE_START` for the room)."""
    return _path(layout).late


def waypoint_spline(seed: int = 0, layout: str = "room") -> tuple[PchipInterpolator, np.ndarray]:
    """The path through :data:`WAYPOINTS` (or :data:`STUDIO_WAYPOINTS`) as a function of time: (spline t [s] ->
    (x, y, height, yaw, pitch) [m, deg], waypoint times [s]).

    ``seed`` perturbs the waypoints slightly (+-4 cm, +-2 deg); seed 0 is the shipped demo. Translation, turning
    and pitching take time (room: 0.5 m/s, 35 deg/s, 20 deg/s; studio: 0.5 m/s, 28 deg/s, 20 deg/s), whichever
    is longest, at least 1 s per waypoint.
    """
    path = _path(layout)
    wp = np.array(path.waypoints, dtype=np.float64)
    if seed:
        rng = np.random.default_rng(seed)
        wp[:, :2] += rng.uniform(-0.04, 0.04, (len(wp), 2))
        wp[:, 3:] += rng.uniform(-2.0, 2.0, (len(wp), 2))
    d_xy = np.linalg.norm(np.diff(wp[:, :2], axis=0), axis=1)
    d_yaw = np.abs(np.diff(wp[:, 3]))
    d_pitch = np.abs(np.diff(wp[:, 4]))
    dt = np.maximum.reduce([d_xy / path.speed, d_yaw / path.turn, d_pitch / path.pitch, np.full_like(d_xy, 1.0)])
    t_wp = np.concatenate([[0.0], np.cumsum(dt)])
    return PchipInterpolator(t_wp, wp, axis=0), t_wp  # C1, no overshoot between waypoints


def robot_trajectory(num_frames: int, seed: int = 0, sway: bool = True, layout: str = "room") -> Trajectory:
    """Sample the demo path at ``num_frames`` instants equally spaced in time.

    Args:
        num_frames: F >= 2.
        seed: perturbs the waypoints slightly (+-4 cm, +-2 deg); seed 0 is the shipped demo.
        sway: add the small periodic camera sway of a driving robot (+-1 cm height, +-1 deg roll).
        layout: "room" (the shipped demo's path) or "studio" (:data:`STUDIO_WAYPOINTS`).
    Returns:
        :class:`Trajectory`; the total duration is fixed by the robot speeds (room ~49 s, studio ~38 s), so F
        sets the frame rate.
    """
    if num_frames < 2:
        raise ValueError(f"num_frames must be >= 2, got {num_frames}")
    path = _path(layout)
    spline, t_wp = waypoint_spline(seed, layout)
    times = np.linspace(0.0, t_wp[-1], num_frames)
    s = spline(times)
    x, y, z, yaw, pitch = (s[:, i] for i in range(5))
    roll = np.zeros_like(x)
    if sway:
        z = z + 0.01 * np.sin(2 * math.pi * times / 1.7)
        roll = np.radians(1.0) * np.sin(2 * math.pi * times / 2.3 + 0.5)
    yaw_r, pitch_r = np.radians(yaw), np.radians(pitch)
    forward = np.stack([np.cos(pitch_r) * np.cos(yaw_r), np.cos(pitch_r) * np.sin(yaw_r), np.sin(pitch_r)], 1)
    R = look_at_rotation(forward)
    # roll about the optical axis
    c, sn = np.cos(roll), np.sin(roll)
    Rz = np.zeros((num_frames, 3, 3))
    Rz[:, 0, 0], Rz[:, 0, 1], Rz[:, 1, 0], Rz[:, 1, 1], Rz[:, 2, 2] = c, -sn, sn, c, 1.0
    R = R @ Rz
    T = np.tile(np.eye(4), (num_frames, 1, 1))
    T[:, :3, :3] = R
    T[:, :3, 3] = np.stack([x, y, z], 1)
    from ..engine.camera import matrix_to_quaternion_xyzw

    phase = np.where(times < t_wp[path.phase2], 1, np.where(times < t_wp[path.late], 2, 3))
    return Trajectory(times=times, T_map_cam=T, positions=T[:, :3, 3].copy(),
                      quaternions_xyzw=matrix_to_quaternion_xyzw(R), phase=phase.astype(np.int64))
