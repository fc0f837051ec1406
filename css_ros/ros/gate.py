"""The input gate of css_node: messages -> FrameJobs (through the shared :class:`~css_ros.io.frame_gate.FrameGate`)
and requests -> CandidateJobs / PointQueryJobs.

No rclpy here: messages are duck-typed, so the gate is unit-tested with simple objects. Frames go through
:mod:`css_ros.io.frame_gate` (which css_replay uses too), so node and replay keep the same frames with the same
interpolated poses and drop the others for the same reasons (the keys of the warnings and of
``warn[topic: reason]`` in diagnostics).

Policies (docs/reliability.md): camera_info latest valid one per camera; poses interpolated at the segmentation
stamp (pose_buffer, pose_wait, max_pose_extrapolation, max_pose_gap), from the pose topic or, with pose_source tf,
from the TF tree (tf_buffer_s); inputs stamped more than
``max_stamp_future`` s ahead of the node clock are dropped; a segmentation not newer than its camera's last frame
is dropped as out of order, except that :data:`STAMP_RESET_COUNT` consecutive ones are taken as a clock reset.
Candidate poses and query points arrive in the map frame and are taken into the splat frame here.
"""
from __future__ import annotations

import inspect
import time
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import numpy as np

from ..engine.similarity import Similarity, parse_extrinsics
from ..errors import InputError
from ..io.frame_gate import STAMP_RESET_COUNT, FrameGate, GateConfig, GateFrame
from ..io.frames import FrameRejected, decode_pose
from ..io.point_queries import declared_points, request_points
from ..io.topics import INPUT_TOPICS
from .params import NodeParams, pose_policy
from .work import CandidateJob, FrameJob, PointQueryJob, WarnLimiter

__all__ = ["STAMP_RESET_COUNT", "InputGate", "NanAnswer", "gate_config"]


def gate_config(p: NodeParams) -> GateConfig:
    """The shared gate's configuration from the node parameters (validated by check_params)."""
    cams = tuple(c.strip("/") for c in p.cameras)
    return GateConfig(cameras=cams, pose_type=p.pose_type, pose_per_camera=p.pose_per_camera,
                      extrinsics=tuple(parse_extrinsics(p.camera_extrinsics, len(cams))),
                      splat_to_map=Similarity.from_params(p.splat_to_map), pose_policy=pose_policy(p),
                      sync_slop=p.sync_slop, queue_size=p.queue_size, map_frame=p.map_frame,
                      max_image_pixels=p.max_image_pixels, max_stamp_future=p.max_stamp_future,
                      pose_source=p.pose_source, tf_buffer=p.tf_buffer_s, depth_topic=p.depth_topic)


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
        confidence_published: ``confidence_published(camera_index)``: True while that camera's
            segmentation_confidence has a publisher (a bare callable without argument is accepted for one camera).
        log_warning: unconditional warnings (clock reset).
        monotonic: the clock [s] on which frames wait for their pose (time.monotonic; tests pass their own).
        depth_published: ``depth_published(camera_index)``: True while that camera's depth topic has a publisher
            (frames then wait for their depth up to pose_wait); None: never waited for.
    """

    def __init__(self, params: NodeParams, warn: WarnLimiter, count: Callable[..., None],
                 now_ns: Callable[[], int], confidence_published: Callable[..., bool],
                 log_warning: Callable[[str], None], monotonic: Callable[[], float] = time.monotonic,
                 depth_published: Callable[[int], bool] | None = None) -> None:
        self.p = params
        self.warn = warn
        self.count = count
        self.monotonic = monotonic
        if len(inspect.signature(confidence_published).parameters) == 0:
            published = lambda cam: confidence_published()  # noqa: E731 - one-camera form
        else:
            published = confidence_published
        self.frames = FrameGate(gate_config(params), warn, count,
                                lambda cam: params.use_confidence and bool(published(cam)), now_ns, log_warning,
                                depth_published)

    @property
    def camera_info(self) -> Any:
        """The first camera's latest valid intrinsics (None before the first camera_info)."""
        return self.frames.cams[0].info

    def _jobs(self, frames: list[GateFrame]) -> list[FrameJob]:
        return [FrameJob(f, time.monotonic()) for f in frames]

    # ------------------------------------------------------------------ inputs (camera index first)
    def on_camera_info(self, msg: Any, cam: int = 0) -> bool:
        return self.frames.on_camera_info(cam, msg)

    def on_image(self, msg: Any, cam: int = 0) -> list[FrameJob]:
        return self._jobs(self.frames.on_image(cam, msg, self.monotonic()))

    def on_confidence(self, msg: Any, cam: int = 0) -> list[FrameJob]:
        return self._jobs(self.frames.on_confidence(cam, msg, self.monotonic()))

    def on_depth(self, msg: Any, cam: int = 0) -> list[FrameJob]:
        return self._jobs(self.frames.on_depth(cam, msg, self.monotonic()))

    def on_segmentation(self, msg: Any, cam: int = 0) -> list[FrameJob]:
        return self._jobs(self.frames.on_segmentation(cam, msg, self.monotonic()))

    def on_pose(self, msg: Any, cam: int = 0, seq: int | None = None) -> list[FrameJob]:
        """``seq``: the message's publication sequence number in its one publisher's stream (None: unknown)."""
        return self._jobs(self.frames.on_pose(msg, self.monotonic(), cam, seq))

    def on_tf(self, msg: Any, static: bool = False) -> list[FrameJob]:
        """A tf2_msgs/TFMessage of /tf (or /tf_static): frames waiting for their transforms are released."""
        return self._jobs(self.frames.on_tf(msg, self.monotonic(), static))

    def poll(self) -> list[FrameJob]:
        """Frames whose wait for a pose or confidence ended (called on a timer)."""
        return self._jobs(self.frames.poll(self.monotonic()))

    def frame_id_check(self, topic: str, frame_id: str) -> None:
        self.frames.frame_id_check(topic, frame_id)

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
        valid_q = np.full((m, 4), np.nan)
        bad = 0
        for i, pose in enumerate(msg.poses):
            try:
                _, valid_q[i] = decode_pose(_Stamped(pose))
            except FrameRejected:
                bad += 1
        if bad:
            self.warn(topic, "invalid candidate poses", f"{bad} of {m} non-finite, out of bounds or non-unit: "
                      "scored NaN", dropped=False)
        pos_splat, q_splat = self.frames.map_poses_to_splat(positions, valid_q)
        return CandidateJob(msg.header, info.K, info.width, info.height, positions, quats, pos_splat, q_splat,
                            time.monotonic())


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
        job = PointQueryJob(msg.header, xyz, num_classes, self.p.ignore_label, time.monotonic(),
                            xyz_splat=self.frames.map_points_to_splat(xyz))
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
