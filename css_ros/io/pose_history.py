"""Poses by time: a bounded, time-ordered pose history interpolated at a frame's stamp (css_node and css_replay).

A robot publishes its pose (odometry, localisation) at its own rate; a segmentation arrives late and is stamped
with its image's time. A frame takes its pose **interpolated at the segmentation stamp** between the two
bracketing samples (linear position, slerp orientation). The rules (docs/reliability.md, "Poses by time"):

- a sample stamped exactly at the frame is used as is (bags whose poses share the frames' stamps give exactly
  the recorded poses);
- no sample after the stamp yet: the caller waits (``LookupStatus.WAIT``) up to ``pose_wait`` s; after that the
  newest pose is extrapolated at constant velocity when the stamp is at most ``max_pose_extrapolation`` s past
  it, otherwise the frame is refused;
- two bracketing samples more than ``max_pose_gap`` s apart (a relocalisation jump, a dropped stream) are not
  interpolated across: refused;
- a stamp older than the history (``pose_buffer`` s, or the first pose) by more than ``max_pose_extrapolation``
  is refused.

Samples: a repeated stamp is dropped; an out-of-order one is inserted in order (reported); one older than the
buffer is dropped, except that :data:`HISTORY_RESET_COUNT` such samples in a row are taken as a clock reset
(bag restarted) and start a new history. The history holds at most ``max_samples`` samples (oldest dropped), so
a 1 kHz stream keeps memory bounded. A sample may carry its sequence number in the publisher's stream
(:mod:`css_ros.io.sequence`): a lookup then says how many samples are missing between the two it used
(``PoseLookup.missing``), so a frame whose pose is not the interpolation of the samples around its stamp is known.
"""
from __future__ import annotations

import bisect
import math
from dataclasses import dataclass
from enum import Enum

import numpy as np

#: Defaults (seconds); one definition, used by the node's parameter table and css_replay's options.
DEFAULT_POSE_BUFFER_S = 10.0
DEFAULT_POSE_WAIT_S = 0.5
DEFAULT_MAX_POSE_EXTRAPOLATION_S = 0.02
DEFAULT_MAX_POSE_GAP_S = 1.0
#: Samples kept at most (10 s of a 2 kHz stream).
DEFAULT_MAX_POSE_SAMPLES = 20000
#: Consecutive samples older than the buffer after which the history restarts (clock reset).
HISTORY_RESET_COUNT = 5


class LookupStatus(Enum):
    OK = "ok"
    WAIT = "wait"
    REFUSED = "refused"


@dataclass(frozen=True)
class PoseLookup:
    """The pose at a stamp: ``position`` (3,) [m] and ``quat`` (4,) xyzw unit, or why not.

    ``reason`` is a short stable drop reason (counter key) when refused; ``detail`` says more.
    ``how`` is "exact", "interpolated" or "extrapolated" for an OK lookup. ``missing``: samples of the stream that
    are missing between the two samples the pose was interpolated (or extrapolated) from, as their sequence numbers
    tell (0: consecutive, or no numbers known).
    """

    status: LookupStatus
    position: np.ndarray | None = None
    quat: np.ndarray | None = None
    reason: str = ""
    detail: str = ""
    how: str = ""
    missing: int = 0


@dataclass(frozen=True)
class PosePolicy:
    """How poses are looked up by time; every duration in seconds."""

    buffer: float = DEFAULT_POSE_BUFFER_S
    wait: float = DEFAULT_POSE_WAIT_S
    max_extrapolation: float = DEFAULT_MAX_POSE_EXTRAPOLATION_S
    max_gap: float = DEFAULT_MAX_POSE_GAP_S
    max_samples: int = DEFAULT_MAX_POSE_SAMPLES

    def __post_init__(self) -> None:
        for name in ("buffer", "wait", "max_extrapolation", "max_gap"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"pose policy {name} must be a finite number >= 0 s, got {v!r}")
        if self.buffer <= 0 or self.max_gap <= 0:
            raise ValueError("pose_buffer and max_pose_gap must be > 0 s")
        if int(self.max_samples) < 2:
            raise ValueError("max_samples must be >= 2")


def slerp_xyzw(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """Spherical linear interpolation of unit quaternions (x, y, z, w) at u in [0, 1] (shortest arc)."""
    q0 = np.asarray(q0, dtype=np.float64)
    q1 = np.asarray(q1, dtype=np.float64)
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    if d > 1.0 - 1e-12:  # equal to ~1e-6 rad: normalised lerp avoids 0/0 and is exact to ~1e-18 rad here
        q = q0 + u * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = math.acos(min(1.0, d))
    s = math.sin(theta)
    q = (math.sin((1.0 - u) * theta) / s) * q0 + (math.sin(u * theta) / s) * q1
    return q / np.linalg.norm(q)


class PoseHistory:
    """Time-ordered pose samples of one stream, looked up by time (see the module docstring).

    Stamps are integer nanoseconds; positions (3,) [m]; quaternions (4,) xyzw, already validated and normalised
    (:func:`css_ros.io.frames.decode_pose`).
    """

    def __init__(self, policy: PosePolicy | None = None) -> None:
        self.policy = policy or PosePolicy()
        self._buffer_ns = int(round(self.policy.buffer * 1e9))
        self._gap_ns = int(round(self.policy.max_gap * 1e9))
        self._extrap_ns = int(round(self.policy.max_extrapolation * 1e9))
        self._times: list[int] = []
        self._poses: list[tuple[np.ndarray, np.ndarray]] = []
        self._seqs: list[int | None] = []
        self._restart: list[tuple[int, np.ndarray, np.ndarray, int | None]] = []
        #: samples dropped for being too old and the stamp before which the history was trimmed
        self.trimmed_before_ns: int | None = None

    def __len__(self) -> int:
        return len(self._times)

    @property
    def newest_ns(self) -> int | None:
        return self._times[-1] if self._times else None

    @property
    def oldest_ns(self) -> int | None:
        return self._times[0] if self._times else None

    def clear(self) -> None:
        self._times.clear()
        self._poses.clear()
        self._seqs.clear()
        self._restart.clear()
        self.trimmed_before_ns = None

    # ------------------------------------------------------------------ samples
    def add(self, stamp_ns: int, position: np.ndarray, quat: np.ndarray, seq: int | None = None) -> str | None:
        """Add one sample (``seq``: its sequence number in the publisher's stream, or None). Returns None when
        appended in order, else a short reason:

        ``"out of order"`` (inserted in order, kept), ``"repeated stamp"`` (dropped),
        ``"older than pose_buffer"`` (dropped), ``"clock reset"`` (the history restarted with this stamp).
        """
        t = int(stamp_ns)
        pose = (np.asarray(position, dtype=np.float64), np.asarray(quat, dtype=np.float64))
        times = self._times
        if not times or t > times[-1]:
            self._restart.clear()
            times.append(t)
            self._poses.append(pose)
            self._seqs.append(seq)
            self._trim()
            return None
        if t < times[-1] - self._buffer_ns:
            self._restart.append((t, *pose, seq))
            if len(self._restart) < HISTORY_RESET_COUNT:
                return "older than pose_buffer"
            restart = sorted(self._restart, key=lambda e: e[0])
            self.clear()
            for ts, p, q, n in restart:
                if not self._times or ts > self._times[-1]:
                    self._times.append(ts)
                    self._poses.append((p, q))
                    self._seqs.append(n)
            return "clock reset"
        i = bisect.bisect_left(times, t)
        if i < len(times) and times[i] == t:
            return "repeated stamp"
        self._restart.clear()
        times.insert(i, t)
        self._poses.insert(i, pose)
        self._seqs.insert(i, seq)
        self._trim()
        return "out of order"

    def _trim(self) -> None:
        times = self._times
        cut = bisect.bisect_left(times, times[-1] - self._buffer_ns)
        over = len(times) - int(self.policy.max_samples)
        cut = max(cut, over)
        # Trim in batches (a 1 kHz stream would otherwise shift the lists on every sample).
        if cut > 0 and (over > 0 or cut >= 64 or cut >= len(times) // 8):
            self.trimmed_before_ns = times[cut]
            del times[:cut]
            del self._poses[:cut]
            del self._seqs[:cut]

    # ------------------------------------------------------------------ lookups
    def lookup(self, stamp_ns: int, waited: bool) -> PoseLookup:
        """The pose at ``stamp_ns``; ``waited``: the frame has waited ``pose_wait`` already (no more waiting)."""
        t = int(stamp_ns)
        times = self._times
        if not times:
            if waited:
                return PoseLookup(LookupStatus.REFUSED, reason="no pose received",
                                  detail=f"no pose within pose_wait={self.policy.wait:g} s")
            return PoseLookup(LookupStatus.WAIT)
        newest = times[-1]
        if t > newest:
            if not waited:
                return PoseLookup(LookupStatus.WAIT)
            if t - newest > self._extrap_ns:
                return PoseLookup(LookupStatus.REFUSED, reason="pose too old to extrapolate",
                                  detail=f"newest pose {(t - newest) * 1e-9:.3f} s before the frame after waiting "
                                         f"pose_wait={self.policy.wait:g} s (max_pose_extrapolation="
                                         f"{self.policy.max_extrapolation:g} s)")
            return self._extrapolate(len(times) - 1, len(times) - 2, t)
        if t < newest - self._buffer_ns:
            return PoseLookup(LookupStatus.REFUSED, reason="frame older than pose_buffer",
                              detail=f"frame {(newest - t) * 1e-9:.3f} s older than the newest pose "
                                     f"(pose_buffer={self.policy.buffer:g} s)")
        i = bisect.bisect_left(times, t)
        if times[i] == t:
            p, q = self._poses[i]
            return PoseLookup(LookupStatus.OK, p.copy(), q.copy(), how="exact")
        if i == 0:
            if times[0] - t > self._extrap_ns:
                older = " (older poses were trimmed)" if self.trimmed_before_ns is not None else ""
                return PoseLookup(LookupStatus.REFUSED, reason="no pose before the frame",
                                  detail=f"oldest pose {(times[0] - t) * 1e-9:.3f} s after the frame{older}")
            return self._extrapolate(0, 1, t)
        t0, t1 = times[i - 1], times[i]
        if t1 - t0 > self._gap_ns:
            return PoseLookup(LookupStatus.REFUSED, reason="pose gap",
                              detail=f"bracketing poses {(t1 - t0) * 1e-9:.3f} s apart > max_pose_gap="
                                     f"{self.policy.max_gap:g} s: not interpolated across")
        u = (t - t0) / (t1 - t0)
        (p0, q0), (p1, q1) = self._poses[i - 1], self._poses[i]
        return PoseLookup(LookupStatus.OK, p0 + u * (p1 - p0), slerp_xyzw(q0, q1, u), how="interpolated",
                          missing=self._missing(i - 1, i))

    def _missing(self, i: int, j: int) -> int:
        """Samples of the stream missing between samples i and j (|i - j| = 1) by their sequence numbers (0 when a
        number is unknown; a pair whose numbers are not increasing with time counts as one missing)."""
        a, b = self._seqs[min(i, j)], self._seqs[max(i, j)]
        if a is None or b is None:
            return 0
        return b - a - 1 if b > a else 1

    def _extrapolate(self, i: int, j: int, t: int) -> PoseLookup:
        """Constant-velocity extrapolation from sample i using the segment (j, i); a hold without a usable j."""
        p_i, q_i = self._poses[i]
        times = self._times
        if 0 <= j < len(times) and 0 < abs(times[i] - times[j]) <= self._gap_ns:
            p_j, q_j = self._poses[j]
            u = (t - times[j]) / (times[i] - times[j])  # > 1 past the newest, < 0 before the oldest
            pos = p_j + u * (p_i - p_j)
            quat = _extrapolate_rotation(q_j, q_i, u)
            return PoseLookup(LookupStatus.OK, pos, quat, how="extrapolated", missing=self._missing(i, j))
        return PoseLookup(LookupStatus.OK, p_i.copy(), q_i.copy(), how="extrapolated")


def _extrapolate_rotation(q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
    """q0 advanced by u times the rotation from q0 to q1 (u outside [0, 1] extrapolates)."""
    d = float(np.dot(q0, q1))
    if d < 0.0:
        q1, d = -q1, -d
    theta = math.acos(min(1.0, d))
    if theta < 1e-9:
        return q1.copy()
    s = math.sin(theta)
    q = (math.sin((1.0 - u) * theta) / s) * q0 + (math.sin(u * theta) / s) * q1
    return q / np.linalg.norm(q)
