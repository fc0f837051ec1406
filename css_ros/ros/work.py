"""Jobs and the bounded queue between css_node's executor (producers) and its worker thread; WarnLimiter."""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

from ..io.frame_gate import GateFrame


class WarnLimiter:
    """Counts bad inputs per (topic, reason) and logs at most one warning per key and ``period`` seconds."""

    def __init__(self, log: Callable[[str], None], period: float) -> None:
        self._log = log
        self.period = period
        self.counts: Counter[str] = Counter()
        self.dropped: Counter[str] = Counter()
        self._last: dict[str, float] = {}
        self._suppressed: Counter[str] = Counter()
        self._lock = threading.Lock()

    def __call__(self, topic: str, reason: str, detail: str = "", dropped: bool = True) -> None:
        """Count and (rate-limited) log a problem with ``topic``; ``dropped``: the message was discarded."""
        key = f"{topic}: {reason}"
        now = time.monotonic()
        with self._lock:
            self.counts[key] += 1
            if dropped:
                self.dropped[topic] += 1
            last = self._last.get(key)
            if last is not None and now - last < self.period:
                self._suppressed[key] += 1
                return
            self._last[key] = now
            extra = f" (+{self._suppressed.pop(key)} similar since last warning)" if self._suppressed.get(key) else ""
        self._log(f"[{topic}] {reason}{': ' + detail if detail else ''}; total {self.counts[key]}{extra}")

    def snapshot(self) -> tuple[dict[str, int], dict[str, int]]:
        """(counts per 'topic: reason', dropped messages per topic)."""
        with self._lock:
            return dict(self.counts), dict(self.dropped)


@dataclass
class FrameJob:
    """A frame from the gate (:class:`~css_ros.io.frame_gate.GateFrame`) waiting for the worker.

    ``t_received``: time.monotonic() [s] at which it left the gate (frame latency is measured from the
    segmentation's arrival, ``frame.t_arrival``).
    """

    frame: GateFrame
    t_received: float

    @property
    def stamp_ns(self) -> int:
        return self.frame.stamp_ns

    @property
    def camera_index(self) -> int:
        return self.frame.camera_index


@dataclass
class CandidateJob:
    """A PoseArray of candidate views waiting for (or being scored by) the worker.

    The worker scores ``next_index`` onwards, one slice at a time; ``u_var`` / ``u_exp`` / ``info_gain``
    (the columns of ``SemanticMap.score_views``) start as NaN and rows that cannot be scored stay NaN.
    """

    header: Any
    K: np.ndarray
    width: int
    height: int
    positions: np.ndarray         # (M, 3) m, map frame, as received
    quats_in: np.ndarray          # (M, 4) xyzw, as received
    positions_splat: np.ndarray   # (M, 3) optical frame origin in the splat frame
    quats_splat: np.ndarray       # (M, 4) optical frame in the splat frame; rows of invalid poses are NaN
    t_received: float             # time.monotonic() [s]
    next_index: int = 0
    u_var: np.ndarray = field(default=None)  # type: ignore[assignment]
    u_exp: np.ndarray = field(default=None)  # type: ignore[assignment]
    info_gain: np.ndarray = field(default=None)  # type: ignore[assignment]

    def __post_init__(self) -> None:
        m = len(self.positions)
        if self.u_var is None:
            self.u_var = np.full(m, np.nan)
        if self.u_exp is None:
            self.u_exp = np.full(m, np.nan)
        if self.info_gain is None:
            self.info_gain = np.full(m, np.nan)

    @property
    def done(self) -> bool:
        return self.next_index >= len(self.positions)


@dataclass
class PointQueryJob:
    """A cloud of 3D query points waiting for (or being evaluated by) the worker (SPEC §9).

    The worker evaluates ``next_index`` onwards, one slice at a time. Rows start unknown (``ignore_label``,
    E and Var NaN); rows that cannot be evaluated (non-finite points, budget exceeded) stay so.
    """

    header: Any
    xyz: np.ndarray               # (M, 3) m, map frame (echoed in the answer)
    num_classes: int
    ignore_label: int
    t_received: float             # time.monotonic() [s]
    xyz_splat: np.ndarray | None = None  # (M, 3) the same points in the splat frame (None: the same as xyz)
    next_index: int = 0
    labels: np.ndarray = field(default=None)       # type: ignore[assignment]  (M,) int32
    expectation: np.ndarray = field(default=None)  # type: ignore[assignment]  (M, C) float32
    variance: np.ndarray = field(default=None)     # type: ignore[assignment]  (M, C) float32
    status: str | None = None     # why the request was answered at once (e.g. "too many points"), else None

    def __post_init__(self) -> None:
        m = len(self.xyz)
        if self.xyz_splat is None:
            self.xyz_splat = self.xyz
        self.labels = np.full(m, self.ignore_label, np.int32)
        self.expectation = np.full((m, self.num_classes), np.nan, np.float32)
        self.variance = np.full((m, self.num_classes), np.nan, np.float32)

    @property
    def done(self) -> bool:
        return self.next_index >= len(self.xyz)

    @property
    def positions(self) -> np.ndarray:
        """The query points (requests of both kinds expose their rows as ``positions``)."""
        return self.xyz


#: A request served between frames, slice by slice: candidate views or 3D query points.
RequestJob = CandidateJob | PointQueryJob


class WorkQueue:
    """Bounded queues between the executor (producers) and the worker thread (consumer).

    Frames: one queue per camera, newest wins (a camera's oldest pending frame is dropped when it holds
    ``max_frames``); cameras are served round-robin, so a 30 Hz camera cannot starve a 5 Hz one. Requests
    (candidate views and point queries) have their own queue and are served between frames, one slice per turn:
    when both are waiting the worker alternates, so neither stream starves the other. A request partly scored
    goes back to the head of its queue (:meth:`resume_request`).
    """

    def __init__(self, max_frames: int, max_requests: int = 8) -> None:
        self.camera_frames: dict[int, deque[FrameJob]] = {}
        self.requests: deque[RequestJob] = deque()
        self.max_frames = max_frames
        self.max_requests = max_requests
        self._cond = threading.Condition()
        self._last_was_frame = False
        self._next_camera = 0
        self.closed = False

    @property
    def frames(self) -> list[FrameJob]:
        """Every pending frame (all cameras)."""
        with self._cond:
            return [j for q in self.camera_frames.values() for j in q]

    def put_frame(self, job: FrameJob) -> FrameJob | None:
        """Queue a frame; returns the frame of the same camera dropped to make room, if any."""
        with self._cond:
            q = self.camera_frames.setdefault(job.camera_index, deque())
            dropped = q.popleft() if len(q) >= self.max_frames else None
            q.append(job)
            self._cond.notify()
        return dropped

    def _pop_frame(self) -> FrameJob | None:
        cams = sorted(c for c, q in self.camera_frames.items() if q)
        if not cams:
            return None
        cam = next((c for c in cams if c >= self._next_camera), cams[0])
        self._next_camera = cam + 1
        return self.camera_frames[cam].popleft()

    def _has_frames(self) -> bool:
        return any(self.camera_frames.values())

    def put_request(self, job: RequestJob) -> RequestJob | None:
        """Queue a request; returns the (oldest) request dropped to make room, if any."""
        with self._cond:
            dropped = self.requests.popleft() if len(self.requests) >= self.max_requests else None
            self.requests.append(job)
            self._cond.notify()
        return dropped

    def resume_request(self, job: RequestJob) -> None:
        """Put a partly scored request back at the head of the request queue (never dropped)."""
        with self._cond:
            self.requests.appendleft(job)
            self._cond.notify()

    def get(self, timeout: float) -> FrameJob | RequestJob | None:
        """Next job (None after ``timeout`` s or when closed)."""
        with self._cond:
            if not self._has_frames() and not self.requests and not self.closed:
                self._cond.wait(timeout)
            if self.closed:
                return None
            if self.requests and (not self._has_frames() or self._last_was_frame):
                self._last_was_frame = False
                return self.requests.popleft()
            if self._has_frames():
                self._last_was_frame = True
                return self._pop_frame()
            return None

    def drain_requests(self) -> list[RequestJob]:
        """Remove and return every pending request (answered with NaN at shutdown)."""
        with self._cond:
            out = list(self.requests)
            self.requests.clear()
            return out

    def drain_frames(self) -> list[FrameJob]:
        """Remove and return every pending frame (not processed: the node is stopping)."""
        with self._cond:
            out = [j for q in self.camera_frames.values() for j in q]
            for q in self.camera_frames.values():
                q.clear()
            return out

    def close(self) -> None:
        with self._cond:
            self.closed = True
            self._cond.notify_all()

    def sizes(self) -> tuple[int, int]:
        with self._cond:
            return sum(len(q) for q in self.camera_frames.values()), len(self.requests)
