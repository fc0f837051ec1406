"""A TF buffer without rclpy: ``/tf`` and ``/tf_static`` in, poses of frames by name at a stamp out.

The transform tree of a robot (REP 105: ``map -> odom -> base_link -> camera_link -> camera_optical_frame``) is
kept as one edge per child frame: the child's pose in its parent, either **static** (``/tf_static``: valid at
every time) or **dynamic** (``/tf``: a :class:`~css_ros.io.pose_history.PoseHistory` of samples). A lookup
``target <- source`` at a stamp walks both frames up to their common ancestor and composes the edges, each one
taken at the stamp with the pose history's rules (exact sample, linear position + slerp between the bracketing
samples, the wait, extrapolation and gap limits; docs/reliability.md "Poses by time"), so a chain through any
number of frames is resolved as tf2 resolves it, and a camera pose from TF is held to the same bounds as one from
a pose topic.

Every edge keeps at most ``tf_buffer_s`` seconds before its newest sample (``PosePolicy.buffer``). A lookup that
cannot be answered says why, with a short stable reason (the counter key) and a detail:

- ``tf unknown frame``: no transform names the frame (after waiting ``pose_wait``);
- ``tf no path``: both frames are known but in two trees that no transform joins (after waiting);
- ``tf extrapolation into the future``: an edge's newest sample is older than the stamp by more than
  ``max_pose_extrapolation`` after waiting;
- ``tf extrapolation into the past``: the stamp is older than an edge's history (``tf_buffer_s`` or its first
  sample) by more than ``max_pose_extrapolation``;
- ``tf gap``: an edge's bracketing samples are more than ``max_pose_gap`` apart.

Frame names are compared without a leading ``/`` (ROS 1 style names are accepted).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..engine.camera import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from .frames import FrameRejected, decode_pose
from .messages import stamp_to_ns
from .pose_history import LookupStatus, PoseHistory, PoseLookup, PosePolicy

#: Default of ``tf_buffer_s`` [s]: how much history every dynamic edge keeps (tf2's default cache time).
DEFAULT_TF_BUFFER_S = 10.0
#: Frames the tree holds at most (a stream naming ever new frames cannot grow it without bound).
MAX_TF_FRAMES = 10_000

#: Pose-history refusal reason -> TF drop reason.
_REASONS = {
    "pose too old to extrapolate": "tf extrapolation into the future",
    "no pose before the frame": "tf extrapolation into the past",
    "frame older than pose_buffer": "tf extrapolation into the past",
    "pose gap": "tf gap",
}
#: How an OK lookup was found, least to most approximate (a chain is as approximate as its worst edge).
_HOW_RANK = {"exact": 0, "interpolated": 1, "extrapolated": 2}


def normalise_frame(name: str) -> str:
    """A frame id as compared here: surrounding blanks and a leading ``/`` removed."""
    return str(name).strip().lstrip("/")


@dataclass(frozen=True)
class TfSample:
    """One transform: the pose of ``child`` in ``parent`` at ``stamp_ns`` [ns] (``translation`` (3,) [m],
    ``quat`` (4,) xyzw unit), i.e. T_parent_child."""

    parent: str
    child: str
    stamp_ns: int
    translation: np.ndarray
    quat: np.ndarray


class _PoseView:
    """Adapter: a geometry_msgs/Transform seen as the ``msg.pose`` that :func:`decode_pose` validates."""

    __slots__ = ("pose",)

    def __init__(self, transform: Any) -> None:
        self.pose = _Pose(transform.translation, transform.rotation)


@dataclass
class _Pose:
    position: Any
    orientation: Any


def decode_tf_message(msg: Any) -> tuple[list[TfSample], list[tuple[str, str]]]:
    """A tf2_msgs/TFMessage -> its valid transforms and ``(reason, detail)`` of each one dropped.

    A transform is dropped when unreadable, when its translation or rotation is invalid (the pose checks of
    :func:`~css_ros.io.frames.decode_pose`: finite, bounded, unit quaternion within tolerance), when a frame id is
    empty, or when it names one frame as its own parent.
    """
    samples: list[TfSample] = []
    problems: list[tuple[str, str]] = []
    try:
        transforms = list(msg.transforms)
    except (AttributeError, TypeError) as exc:
        return [], [("invalid tf message", f"no transforms: {exc}")]
    for t in transforms:
        try:
            parent = normalise_frame(t.header.frame_id)
            child = normalise_frame(t.child_frame_id)
            stamp = stamp_to_ns(t.header.stamp)
            translation, quat = decode_pose(_PoseView(t.transform))
        except FrameRejected as exc:
            problems.append(("invalid transform", f"{exc}"))
            continue
        except (AttributeError, TypeError, ValueError) as exc:
            problems.append(("invalid transform", f"cannot read a geometry_msgs/TransformStamped: {exc}"))
            continue
        if not parent or not child:
            problems.append(("invalid transform", f"empty frame id (parent '{parent}', child '{child}')"))
        elif parent == child:
            problems.append(("invalid transform", f"frame '{child}' given as its own parent"))
        else:
            samples.append(TfSample(parent, child, stamp, translation, quat))
    return samples, problems


class _Edge:
    """The pose of one child frame in its parent: static, or a history of samples."""

    __slots__ = ("parent", "static", "history")

    def __init__(self, parent: str, static: tuple[np.ndarray, np.ndarray] | None,
                 history: PoseHistory | None) -> None:
        self.parent = parent
        self.static = static
        self.history = history

    def lookup(self, stamp_ns: int, waited: bool) -> PoseLookup:
        if self.static is not None:
            return PoseLookup(LookupStatus.OK, self.static[0].copy(), self.static[1].copy(), how="exact")
        assert self.history is not None
        return self.history.lookup(stamp_ns, waited)


def compose(a: tuple[np.ndarray, np.ndarray], b: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """T_a @ T_b of two poses given as (translation (3,) [m], quaternion (4,) xyzw)."""
    Ra = quaternion_xyzw_to_matrix(a[1])
    Rb = quaternion_xyzw_to_matrix(b[1])
    return a[0] + Ra @ b[0], matrix_to_quaternion_xyzw(Ra @ Rb)


def invert(a: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """T_a^-1 of a pose (translation (3,) [m], quaternion (4,) xyzw)."""
    R = quaternion_xyzw_to_matrix(a[1])
    return -(R.T @ a[0]), matrix_to_quaternion_xyzw(R.T)


class TfBuffer:
    """The transform tree of ``/tf`` and ``/tf_static``, looked up by frame names at a stamp.

    Args:
        policy: the time rules of every dynamic edge (``buffer`` = ``tf_buffer_s``; ``wait``,
            ``max_extrapolation``, ``max_gap`` as for pose topics).
    """

    def __init__(self, policy: PosePolicy | None = None) -> None:
        self.policy = policy or PosePolicy(buffer=DEFAULT_TF_BUFFER_S)
        self._edges: dict[str, _Edge] = {}
        self._parents_seen: set[str] = set()

    def __len__(self) -> int:
        """Number of edges (child frames)."""
        return len(self._edges)

    def frames(self) -> set[str]:
        """Every frame named by a transform (as child or as parent)."""
        return set(self._edges) | self._parents_seen

    def clear(self) -> None:
        self._edges.clear()
        self._parents_seen.clear()

    # ------------------------------------------------------------------ samples
    def add(self, sample: TfSample, static: bool) -> str | None:
        """Add one transform (from ``/tf_static`` when ``static``). Returns None, or a short reason:

        ``"parent changed"`` (the child had another parent: its history restarts with this sample),
        ``"too many frames"`` (dropped: the tree holds :data:`MAX_TF_FRAMES`), or the pose history's reason
        (``"out of order"`` kept, ``"repeated stamp"`` / ``"older than pose_buffer"`` dropped, ``"clock reset"``).
        A static transform replaces the child's edge (the latest one wins, as in tf2).
        """
        child, parent = sample.child, sample.parent
        edge = self._edges.get(child)
        if edge is None and len(self._edges) >= MAX_TF_FRAMES:
            return "too many frames"
        problem = None
        if edge is not None and edge.parent != parent:
            problem = "parent changed"
            edge = None
        self._parents_seen.add(parent)
        if static:
            self._edges[child] = _Edge(parent, (sample.translation, sample.quat), None)
            return problem
        if edge is None or edge.history is None:
            edge = _Edge(parent, None, PoseHistory(self.policy))
            self._edges[child] = edge
        assert edge.history is not None
        added = edge.history.add(sample.stamp_ns, sample.translation, sample.quat)
        return problem or added

    def add_message(self, msg: Any, static: bool) -> list[tuple[str, str, bool]]:
        """Add every transform of a TFMessage; returns ``(reason, detail, dropped)`` of each problem."""
        samples, problems = decode_tf_message(msg)
        out = [(r, f"{d}; dropped", True) for r, d in problems]
        for s in samples:
            problem = self.add(s, static)
            if problem is None:
                continue
            edge = f"{s.parent} -> {s.child}"
            if problem == "out of order":
                out.append(("tf stamp out of order", f"{edge}: inserted in time order", False))
            elif problem == "parent changed":
                out.append(("tf parent changed", f"{edge}: the frame had another parent; its history restarts",
                            False))
            elif problem == "clock reset":
                out.append(("tf clock reset", f"{edge}: stamps jumped back several times: new history", False))
            else:
                out.append((f"tf {problem}", f"{edge}: dropped", True))
        return out

    # ------------------------------------------------------------------ lookups
    def _path_up(self, frame: str) -> list[str]:
        """``frame`` and its ancestors up to its root (a cycle ends the walk where it closes)."""
        path = [frame]
        seen = {frame}
        while True:
            edge = self._edges.get(path[-1])
            if edge is None or edge.parent in seen:
                return path
            path.append(edge.parent)
            seen.add(edge.parent)

    def lookup(self, target: str, source: str, stamp_ns: int, waited: bool) -> PoseLookup:
        """The pose of frame ``source`` in frame ``target`` (T_target_source) at ``stamp_ns`` [ns].

        ``waited``: the caller has waited ``pose_wait`` already; before that a lookup that later samples could
        answer returns ``LookupStatus.WAIT``. Refusals carry the reasons of the module docstring.
        """
        target, source = normalise_frame(target), normalise_frame(source)
        if target == source:
            return PoseLookup(LookupStatus.OK, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), how="exact")
        known = self.frames()
        missing = [f for f in (target, source) if f not in known]
        if missing:
            if not waited:
                return PoseLookup(LookupStatus.WAIT)
            names = ", ".join(sorted(known)[:20]) or "none"
            return PoseLookup(LookupStatus.REFUSED, reason="tf unknown frame",
                              detail=f"no transform names frame '{missing[0]}' after waiting pose_wait="
                                     f"{self.policy.wait:g} s (known frames: {names})")
        up_src, up_tgt = self._path_up(source), self._path_up(target)
        common = next((f for f in up_src if f in set(up_tgt)), None)
        if common is None:
            if not waited:
                return PoseLookup(LookupStatus.WAIT)
            return PoseLookup(LookupStatus.REFUSED, reason="tf no path",
                              detail=f"'{source}' (root '{up_src[-1]}') and '{target}' (root '{up_tgt[-1]}') are "
                                     "not connected by any transform")
        chain = [(f, False) for f in up_src[:up_src.index(common)]] + \
                [(f, True) for f in up_tgt[:up_tgt.index(common)]]
        looks = []
        for frame, _ in chain:
            edge = self._edges[frame]
            look = edge.lookup(stamp_ns, waited)
            if look.status is LookupStatus.REFUSED:
                reason = _REASONS.get(look.reason, f"tf {look.reason}")
                detail = re.sub(r"\bpose(s?)\b", r"transform\1", look.detail.replace("pose_buffer=", "tf_buffer_s="))
                return PoseLookup(LookupStatus.REFUSED, reason=reason,
                                  detail=f"{edge.parent} -> {frame}: {detail}")
            looks.append(look)
        if any(look.status is LookupStatus.WAIT for look in looks):
            return PoseLookup(LookupStatus.WAIT)
        t_common_source = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
        t_common_target = (np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]))
        how = "exact"
        for (frame, on_target), look in zip(chain, looks):
            assert look.position is not None and look.quat is not None
            if _HOW_RANK[look.how] > _HOW_RANK[how]:
                how = look.how
            if on_target:
                t_common_target = compose((look.position, look.quat), t_common_target)
            else:
                t_common_source = compose((look.position, look.quat), t_common_source)
        p, q = compose(invert(t_common_target), t_common_source)
        return PoseLookup(LookupStatus.OK, p, q, how=how, missing=sum(look.missing for look in looks))
