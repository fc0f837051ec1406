"""PoseHistory: interpolation by time against closed forms, and the wait / extrapolation / gap / buffer rules."""
from __future__ import annotations

import math

import numpy as np
import pytest

from css_ros.io.pose_history import (HISTORY_RESET_COUNT, LookupStatus, PoseHistory, PosePolicy, slerp_xyzw)

NS = 1_000_000_000


def yaw_quat(angle: float) -> np.ndarray:
    return np.array([0.0, 0.0, math.sin(angle / 2), math.cos(angle / 2)])


def trajectory(t: float) -> tuple[np.ndarray, np.ndarray]:
    """1 m/s along x, 45 deg/s about z: the robot of the closed-form checks."""
    return np.array([t, 0.5, 0.2]), yaw_quat(math.radians(45.0) * t)


def filled(rate_hz: float, t0: float, t1: float, policy: PosePolicy | None = None) -> PoseHistory:
    h = PoseHistory(policy)
    for t in np.arange(t0, t1, 1.0 / rate_hz):
        p, q = trajectory(float(t))
        assert h.add(int(round(t * NS)), p, q) is None
    return h


def angle_between(q0: np.ndarray, q1: np.ndarray) -> float:
    """Angle [deg] of the rotation between two unit quaternions (atan2 form: accurate near 0)."""
    if float(np.dot(q0, q1)) < 0:
        q1 = -q1
    return math.degrees(4.0 * math.atan2(np.linalg.norm(q0 - q1), np.linalg.norm(q0 + q1)))


def test_interpolation_between_stamps_is_exact_for_constant_velocity() -> None:
    h = filled(30.0, 0.0, 2.0)
    rng = np.random.default_rng(0)
    for t in rng.uniform(0.1, 1.9, 50):
        look = h.lookup(int(round(t * NS)), waited=False)
        assert look.status is LookupStatus.OK and look.how == "interpolated"
        p, q = trajectory(float(t))
        assert np.linalg.norm(look.position - p) < 1e-9
        assert angle_between(look.quat, q) < 1e-6


def test_exact_stamp_returns_the_sample_itself() -> None:
    h = PoseHistory()
    p, q = np.array([1.0, 2.0, 3.0]), np.array([0.1, 0.2, 0.3, 0.9]) / np.linalg.norm([0.1, 0.2, 0.3, 0.9])
    h.add(5 * NS, p, q)
    look = h.lookup(5 * NS, waited=False)
    assert look.how == "exact" and np.array_equal(look.position, p) and np.array_equal(look.quat, q)


def test_waits_for_a_later_sample_then_extrapolates_or_refuses() -> None:
    h = filled(100.0, 0.0, 1.0)   # newest sample at 0.99 s
    newest = h.newest_ns
    assert h.lookup(newest + NS // 200, waited=False).status is LookupStatus.WAIT
    look = h.lookup(newest + NS // 200, waited=True)    # 5 ms past: within the 20 ms default
    assert look.status is LookupStatus.OK and look.how == "extrapolated"
    p, q = trajectory(newest / NS + 0.005)
    assert np.linalg.norm(look.position - p) < 1e-9 and angle_between(look.quat, q) < 1e-6
    far = h.lookup(newest + NS // 10, waited=True)
    assert far.status is LookupStatus.REFUSED and far.reason == "pose too old to extrapolate"


def test_gap_is_not_interpolated_across() -> None:
    h = PoseHistory(PosePolicy(max_gap=0.5))
    h.add(0, *trajectory(0.0))
    h.add(2 * NS, *trajectory(2.0))
    look = h.lookup(NS, waited=True)
    assert look.status is LookupStatus.REFUSED and look.reason == "pose gap"


def test_buffer_bounds_time_and_memory_at_1khz() -> None:
    h = filled(1000.0, 0.0, 30.0, PosePolicy(buffer=2.0, max_samples=100000))
    assert len(h) <= int(2.0 * 1000 * 1.2) + 1
    assert h.oldest_ns >= h.newest_ns - int(2.4 * NS)
    old = h.lookup(int(10 * NS), waited=True)
    assert old.status is LookupStatus.REFUSED and old.reason == "frame older than pose_buffer"
    capped = filled(1000.0, 0.0, 5.0, PosePolicy(buffer=10.0, max_samples=500))
    assert len(capped) <= 500


def test_bad_sample_order() -> None:
    h = PoseHistory()
    h.add(1 * NS, *trajectory(1.0))
    h.add(3 * NS, *trajectory(3.0))
    assert h.add(2 * NS, *trajectory(2.0)) == "out of order"
    assert h.add(2 * NS, *trajectory(2.5)) == "repeated stamp"
    look = h.lookup(int(1.5 * NS), waited=False)
    assert np.allclose(look.position, trajectory(1.5)[0])   # the inserted sample brackets it
    assert h.add(-20 * NS, *trajectory(0.0)) == "older than pose_buffer"


def test_clock_reset_restarts_the_history() -> None:
    h = filled(10.0, 100.0, 101.0)
    reasons = [h.add(int(t * NS), *trajectory(t)) for t in (0.0, 0.1, 0.2, 0.3, 0.4)]
    assert reasons[:HISTORY_RESET_COUNT - 1] == ["older than pose_buffer"] * (HISTORY_RESET_COUNT - 1)
    assert reasons[HISTORY_RESET_COUNT - 1] == "clock reset"
    assert h.oldest_ns == 0 and h.newest_ns == int(0.4 * NS)
    assert np.allclose(h.lookup(int(0.25 * NS), waited=False).position, trajectory(0.25)[0])


def test_slerp_halfway_and_shortest_arc() -> None:
    q = slerp_xyzw(yaw_quat(0.0), -yaw_quat(math.radians(90)), 0.5)   # -q is the same rotation
    assert angle_between(q, yaw_quat(math.radians(45))) < 1e-9


def test_policy_rejects_bad_values() -> None:
    with pytest.raises(ValueError):
        PosePolicy(buffer=0.0)
    with pytest.raises(ValueError):
        PosePolicy(wait=float("nan"))
