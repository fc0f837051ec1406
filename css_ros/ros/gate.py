"""The input gate of css_node: decoded, checked and synchronised inputs -> FrameJobs / CandidateJobs.

No rclpy here: messages are duck-typed (``header.stamp.sec/nanosec``, ``header.frame_id`` and the
fields :mod:`css_ros.io.frames` reads), so the gate is unit-tested with simple objects. Every decode
goes through :mod:`css_ros.io.frames`, so css_node and css_replay accept and refuse the same messages
with the same drop reasons (the keys of the warnings and of ``warn[topic: reason]`` in diagnostics).

Policies (docs/reliability.md):

- camera_info: the latest valid one is used; an invalid one (or one above ``max_image_pixels``) is
  refused and the previous one stays; frames before the first valid one are dropped.
- stamps: inputs stamped more than ``max_stamp_future`` s ahead of the node clock are dropped; a
  segmentation not newer than the last frame is dropped as out of order, except that
  :data:`STAMP_RESET_COUNT` consecutive ones are taken as a clock reset (bag restarted) and accepted.
- sizes: every image of a frame must have the camera_info's size.
"""
from __future__ import annotations

import time
from collections import Counter, deque
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..engine.camera import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from ..io.frames import (FrameRejected, Intrinsics, check_size, decode_camera_info, decode_confidence, decode_image,
                         decode_labels, decode_pose)
from ..errors import InputError
from ..io.messages import stamp_to_ns
from ..io.point_queries import declared_points, request_points
from ..io.sync import FrameSynchronizer
from ..io.topics import INPUT_TOPICS
from .params import NodeParams
from .work import CandidateJob, FrameJob, PointQueryJob, WarnLimiter

#: Consecutive segmentations older than the last frame after which the node assumes the clock was reset.
STAMP_RESET_COUNT = 5
CONFIDENCE_TOPIC = INPUT_TOPICS["confidence"]


def body_to_optical(quats_xyzw: np.ndarray, q_body_optical: np.ndarray) -> np.ndarray:
    """Orientation of the optical frame: R_map_optical = R_map_body @ R_body_optical; (M, 4) -> (M, 4) xyzw."""
    R = quaternion_xyzw_to_matrix(quats_xyzw) @ quaternion_xyzw_to_matrix(q_body_optical)
    return matrix_to_quaternion_xyzw(R)


@dataclass
class NanAnswer:
    """A candidate request answered at once with NaN scores; ``reason`` is the documented status."""

    header: Any
    positions: np.ndarray   # (M, 3)
    quats: np.ndarray       # (M, 4)
    reason: str


class _Stamped:
    """Adapter: a bare geometry_msgs/Pose as the ``msg.pose`` that decode_pose reads."""

    __slots__ = ("pose",)

    def __init__(self, pose: Any) -> None:
        self.pose = pose


def _raw_pose(pose: Any) -> tuple[list[float], list[float]]:
    p, o = pose.position, pose.orientation
    return [p.x, p.y, p.z], [o.x, o.y, o.z, o.w]


class InputGate:
    """Turns input messages into work for the worker, applying the policies of the module docstring.

    Args:
        params: node parameters.
        warn: the node's WarnLimiter (counts and rate-limits every refusal).
        count: ``count(key, n=1)`` adds to a node counter.
        now_ns: the node clock [ns] (0 or less: unknown, the future check is skipped).
        confidence_published: True while segmentation_confidence has a publisher.
        log_warning: unconditional warnings (clock reset).
    """

    def __init__(self, params: NodeParams, warn: WarnLimiter, count: Callable[..., None],
                 now_ns: Callable[[], int], confidence_published: Callable[[], bool],
                 log_warning: Callable[[str], None]) -> None:
        self.p = params
        self.warn = warn
        self.count = count
        self.now_ns = now_ns
        self.confidence_published = confidence_published
        self.log_warning = log_warning
        self.camera_info: Intrinsics | None = None
        self._q_b2o = np.asarray(params.body_to_optical_quaternion, dtype=np.float64)
        self._slop_ns = int(round(params.sync_slop * 1e9))
        self._images: deque[tuple[int, np.ndarray]] = deque(maxlen=params.queue_size)
        self.last_frame_ns: int | None = None
        self._stale_run = 0
        self.kinds: tuple[str, ...] = ("segmentation", "pose", "confidence") if params.use_confidence \
            else ("segmentation", "pose")
        self.sync = self._make_sync()
        #: last messages pushed per non-anchor kind (re-offered to the synchroniser after a clock reset)
        self._recent: dict[str, deque[tuple[int, Any]]] = {
            k: deque(maxlen=params.queue_size) for k in self.kinds if k != "segmentation"}

    # ------------------------------------------------------------------ checks
    def _make_sync(self) -> FrameSynchronizer:
        self._sync_counts: Counter[str] = Counter()
        return FrameSynchronizer(self.kinds, slop_ns=self._slop_ns, anchor="segmentation",
                                 queue_size=self.p.queue_size)

    def stamp_ok(self, topic: str, stamp_ns: int) -> bool:
        """False (warned) when ``stamp_ns`` is more than max_stamp_future s ahead of the node clock."""
        if self.p.max_stamp_future > 0:
            now = self.now_ns()
            if now > 0 and stamp_ns > now + self.p.max_stamp_future * 1e9:
                self.warn(topic, "stamp in the future",
                          f"{(stamp_ns - now) * 1e-9:.3f} s ahead of the node clock (max_stamp_future)")
                return False
        return True

    def size_ok(self, topic: str, array: np.ndarray) -> bool:
        """Image size check against the latest camera_info (deferred to the frame if none yet)."""
        if self.camera_info is None:
            return True
        try:
            check_size(array, self.camera_info, "image")
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; frame dropped")
            return False
        return True

    def frame_id_check(self, topic: str, frame_id: str) -> None:
        """Warn (not dropped) when a pose's frame_id is not map_frame: there is no tf here."""
        if frame_id and frame_id.lstrip("/") != self.p.map_frame:
            self.warn(topic, "frame_id differs from map_frame",
                      f"'{frame_id}' != '{self.p.map_frame}' (no tf here): used as map frame", dropped=False)

    def optical(self, quat: np.ndarray) -> np.ndarray:
        """The optical frame's orientation for a received (normalised) quaternion."""
        return body_to_optical(quat, self._q_b2o) if self.p.body_to_optical else quat

    # ------------------------------------------------------------------ inputs
    def on_camera_info(self, msg: Any) -> bool:
        """Keep a valid camera_info; refuse (warned, previous one kept) an invalid one."""
        try:
            self.camera_info = decode_camera_info(msg, self.p.max_image_pixels)
        except FrameRejected as exc:
            self.warn(INPUT_TOPICS["camera_info"], exc.reason, f"{exc}; keeping the previous one")
            return False
        return True

    def on_image(self, msg: Any) -> list[FrameJob]:
        """Colour image (PSNR diagnostics only): kept for the frame with the nearest stamp."""
        topic = INPUT_TOPICS["image"]
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            rgb = decode_image(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; ignored")
            return []
        if self.size_ok(topic, rgb) and self.stamp_ok(topic, stamp):
            self._images.append((stamp, rgb))
        return []

    def on_confidence(self, msg: Any) -> list[FrameJob]:
        """Confidence image: non-finite pixels count as 0 (counted), values clipped to [0, 1]."""
        topic = CONFIDENCE_TOPIC
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            conf, non_finite = decode_confidence(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; dropped")
            return []
        if non_finite:
            self.count("confidence_pixels_non_finite", non_finite)
            self.warn(topic, "non-finite confidence values", f"{non_finite} pixels counted as 0; frame kept",
                      dropped=False)
        if not self.size_ok(topic, conf) or not self.stamp_ok(topic, stamp):
            return []
        if "confidence" not in self.kinds:
            return []
        return self._push("confidence", stamp, conf)

    def on_pose(self, msg: Any) -> list[FrameJob]:
        topic = INPUT_TOPICS["pose"]
        stamp = stamp_to_ns(msg.header.stamp)
        try:
            position, quat = decode_pose(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; dropped")
            return []
        self.frame_id_check(topic, msg.header.frame_id)
        if not self.stamp_ok(topic, stamp):
            return []
        return self._push("pose", stamp, (position, quat, self.optical(quat)))

    def on_segmentation(self, msg: Any) -> list[FrameJob]:
        topic = INPUT_TOPICS["segmentation"]
        stamp = stamp_to_ns(msg.header.stamp)
        self.count("segmentations_received")
        try:
            labels = decode_labels(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; frame dropped")
            return []
        if not self.size_ok(topic, labels) or not self.stamp_ok(topic, stamp):
            return []
        if self.last_frame_ns is not None and stamp <= self.last_frame_ns:
            self._stale_run += 1
            if self._stale_run < STAMP_RESET_COUNT:
                self.warn(topic, "stamp out of order",
                          f"{(self.last_frame_ns - stamp) * 1e-9:.3f} s older than the last frame; dropped")
                return []
            self._clock_reset(stamp)
        else:
            self._stale_run = 0
        jobs: list[FrameJob] = []
        if "confidence" in self.kinds and not self.confidence_published():
            # Nobody publishes confidence: complete the frame with "no confidence" (weight 1).
            jobs += self._push("confidence", stamp, None)
        return jobs + self._push("segmentation", stamp, (labels, msg.header.frame_id, time.monotonic()))

    def _clock_reset(self, stamp: int) -> None:
        self.log_warning(
            f"[segmentation] {self._stale_run} consecutive stamps older than the last frame: assuming the "
            f"clock was reset (bag restarted?), accepting the new stamps")
        self.count("clock_resets")
        old_last = self.last_frame_ns or 0
        self.last_frame_ns = None
        self._stale_run = 0
        self._images.clear()
        self.sync = self._make_sync()
        # The poses / confidences of the new time line were refused as stale: offer them again
        # (those still stamped after the old last frame belong to the old time line).
        for kind, recent in self._recent.items():
            for t, payload in sorted(recent, key=lambda e: e[0]):
                if stamp - self._slop_ns <= t < old_last:
                    self.sync.push(kind, t, payload)
        self._sync_counts = Counter(self.sync.counts)

    def _push(self, kind: str, stamp: int, payload: Any) -> list[FrameJob]:
        if kind != "segmentation":
            self._recent[kind].append((stamp, payload))
        frames = self.sync.push(kind, stamp, payload)
        self._report_sync()
        jobs = []
        for frame in frames:
            job = self._frame_job(frame)
            if job is not None:
                jobs.append(job)
        return jobs

    def _report_sync(self) -> None:
        """Report what the synchroniser dropped (stale, unmatched, overflow) under the topic concerned."""
        counts = self.sync.counts
        for key, value in counts.items():
            n = value - self._sync_counts.get(key, 0)
            if n <= 0 or key == "frames" or key.startswith("reordered_"):
                continue
            if key == "unmatched":
                others = "pose" + (" or segmentation_confidence" if "confidence" in self.kinds
                                   and self.confidence_published() else "")
                self.warn("segmentation", "no matching stamp",
                          f"no {others} within sync_slop={self.p.sync_slop:g} s of the segmentation; frame dropped")
            elif key == "overflow_confidence" and not self.confidence_published():
                continue  # placeholders of segmentations that never matched a pose
            else:
                what, _, k = key.partition("_")
                name = INPUT_TOPICS.get(k, k)
                reason = {"stale": "stamp older than the last frame",
                          "overflow": "synchroniser buffer full"}.get(what, what)
                self.warn(name, reason, "dropped")
        self._sync_counts = Counter(counts)

    def _frame_job(self, frame: Any) -> FrameJob | None:
        info = self.camera_info
        labels, frame_id, t_recv = frame.items["segmentation"]
        position, quat_in, quat_opt = frame.items["pose"]
        if info is None:
            self.warn("segmentation", "no camera_info received yet", "frame dropped")
            return None
        confidence = frame.items.get("confidence")
        try:
            check_size(labels, info, "segmentation")
        except FrameRejected as exc:
            self.warn("segmentation", exc.reason, f"{exc}; frame dropped")
            return None
        if confidence is not None:
            try:
                check_size(confidence, info, "segmentation_confidence")
            except FrameRejected as exc:
                self.warn(CONFIDENCE_TOPIC, exc.reason, f"{exc}; frame dropped")
                return None
        self.last_frame_ns = frame.stamp_ns
        best = None
        for stamp, rgb in self._images:
            d = abs(stamp - frame.stamp_ns)
            if d <= self._slop_ns and (best is None or d < best[0]):
                best = (d, rgb)
        image = best[1] if best is not None and best[1].shape[:2] == labels.shape else None
        self.count("frames_synchronised")
        return FrameJob(frame.stamp_ns, frame_id, labels, confidence, image, info.K, position, quat_in, quat_opt,
                        t_recv)

    # ------------------------------------------------------------------ candidate requests
    def on_candidates(self, msg: Any) -> CandidateJob | NanAnswer:
        """A PoseArray -> a job for the worker, or a NaN answer (no camera_info, too many poses).

        Every request is answered: rows of poses that cannot be scored are NaN.
        """
        topic = INPUT_TOPICS["candidates"]
        m = len(msg.poses)
        self.count("requests_received")
        raw = [_raw_pose(p) for p in msg.poses]
        positions = np.array([r[0] for r in raw], dtype=np.float64).reshape(m, 3)
        quats = np.array([r[1] for r in raw], dtype=np.float64).reshape(m, 4)
        info = self.camera_info
        if info is None:
            self.warn(topic, "no camera_info received yet", "cannot render: answered with NaN scores",
                      dropped=False)
            return NanAnswer(msg.header, positions, quats, "no camera_info received yet")
        if m > self.p.max_candidates:
            self.warn(topic, "too many candidates",
                      f"{m} > max_candidates={self.p.max_candidates}: answered with NaN scores", dropped=False)
            return NanAnswer(msg.header, positions, quats, "too many candidates")
        self.frame_id_check(topic, msg.header.frame_id)
        optical = np.full((m, 4), np.nan)
        bad = 0
        for i, pose in enumerate(msg.poses):
            try:
                _, q = decode_pose(_Stamped(pose))
            except FrameRejected:
                bad += 1
                continue
            optical[i] = self.optical(q)
        if bad:
            self.warn(topic, "invalid candidate poses", f"{bad} of {m} non-finite, out of bounds or non-unit: "
                      "scored NaN", dropped=False)
        return CandidateJob(msg.header, info.K, info.width, info.height, positions, quats, optical, time.monotonic())


    def on_point_query(self, msg: Any, num_classes: int) -> PointQueryJob:
        """A PointCloud2 of query points -> a job for the worker.

        Every request is answered in request order: a cloud without readable x y z fields, or declaring
        more than ``max_query_points`` points in its header (width x height; checked before its data is
        touched), is answered at once with an empty cloud; non-finite points are answered as unknown.
        """
        topic = INPUT_TOPICS["point_queries"]
        self.count("point_queries_received")
        try:
            declared = declared_points(msg)
        except InputError:
            declared = 0  # request_points below says what is wrong
        if declared > self.p.max_query_points:
            self.warn(topic, "too many points", f"{declared} > max_query_points={self.p.max_query_points}: "
                      "answered with an empty cloud", dropped=False)
            job = PointQueryJob(msg.header, np.zeros((0, 3)), num_classes, self.p.ignore_label, time.monotonic())
            job.status = "too many points"
            return job
        try:
            xyz = request_points(msg)
        except (InputError, AttributeError, TypeError, ValueError) as exc:
            self.warn(topic, "unreadable point query", f"{exc}: answered with an empty cloud", dropped=False)
            xyz = np.zeros((0, 3))
        job = PointQueryJob(msg.header, xyz, num_classes, self.p.ignore_label, time.monotonic())
        self.frame_id_check(topic, msg.header.frame_id)
        bad = int(np.count_nonzero(~np.all(np.isfinite(xyz), axis=1)))
        if bad:
            self.warn(topic, "non-finite query points", f"{bad} of {len(xyz)}: answered as unknown (as points "
                      "far from every Gaussian)", dropped=False)
        return job


def input_topics() -> Sequence[str]:
    """The relative input topic names, in subscription order."""
    return tuple(INPUT_TOPICS[k] for k in ("camera_info", "pose", "image", "confidence", "segmentation",
                                           "candidates", "point_queries"))
