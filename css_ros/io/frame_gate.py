"""The frame gate shared by css_node and css_replay: messages of one or more cameras + a pose stream -> frames.

No rclpy here: messages are duck-typed (``header.stamp``, ``header.frame_id`` and the fields
:mod:`css_ros.io.frames` reads), and time is passed in by the caller (the node's monotonic clock, or a bag's log
time in css_replay), so node and replay keep the same frames with the same poses.

A frame of camera i is its segmentation, matched by stamp (nearest within ``sync_slop``) with that camera's
confidence (required while it is published), colour image and extra images (optional: GT in css_replay), and
the latest valid camera_info. Its pose comes from the pose history **interpolated at the segmentation stamp**
(:mod:`css_ros.io.pose_history`), composed with the camera's extrinsics (pose of the optical frame in the frame
the pose describes) and taken from the map into the splat frame by ``splat_to_map``'s inverse. A frame whose
pose is not yet bracketed (or whose confidence, or its camera's first camera_info, has not arrived) waits up to
``pose_wait`` s; frames of a camera are emitted in stamp order.

With ``depth_topic`` set, a frame also takes the depth image of its camera nearest its stamp (within
``sync_slop``). While ``depth_expected(camera)`` (the node: the depth topic has a publisher) it first waits, up to
``pose_wait`` s like for its confidence, until a depth stamped at or after its own has arrived (a depth camera faster
than the segmentation has one 33 ms before and one at the stamp: the one at the stamp must win even when it comes
after the segmentation); then it takes the nearest, or goes on **without** depth (counted and warned, never dropped:
the depth only refines the update). A depth message that cannot be used (bad encoding, truncated) is warned and
dropped, and the frame with its stamp goes on without depth at once (it does not wait for another). The depth is
brought to the segmentation's resolution by the nearest pixel (:func:`~css_ros.io.frames.depth_for`).

With ``pose_source`` "tf" the pose stream is not used: the pose is the TF lookup ``map_frame <- frame_id`` of the
segmentation's header at its stamp (:mod:`css_ros.io.tf_buffer`, fed by :meth:`FrameGate.on_tf`), with the same
interpolation, wait and extrapolation rules; extrinsics, when given, then compose onto that frame's pose.

Every refusal goes through ``warn(topic, reason, detail, dropped)`` with a short stable reason; the node logs
and counts them (rate-limited), css_replay counts them as skipped frames.
"""
from __future__ import annotations

import math
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from ..engine.camera import Camera
from ..engine.similarity import Similarity
from ..errors import CameraError
from .frames import (DEFAULT_MAX_IMAGE_PIXELS, FrameRejected, Intrinsics, RawDepth, decode_camera_info,
                     decode_confidence, decode_depth, decode_image, decode_labels, decode_pose, depth_for)
from .messages import stamp_to_ns
from .pose_history import LookupStatus, PoseHistory, PoseLookup, PosePolicy
from .tf_buffer import DEFAULT_TF_BUFFER_S, TfBuffer
from .topics import INPUT_TOPICS, POSE_SOURCES, POSE_TYPES, TF_STATIC_TOPIC, TF_TOPIC

#: Consecutive segmentations older than the camera's last frame after which the clock is taken as reset.
STAMP_RESET_COUNT = 5
#: Pose samples remembered in arrival order (to rebuild the history of a new time line after a clock reset).
RECENT_POSES = 2000
#: Largest accepted mismatch [px] between a segmentation's size and camera_info scaled by one common factor.
RESOLUTION_TOLERANCE_PX = 1.0
#: ``GateFrame.pose_flags`` bits (``pose_flags`` of ``~/view_uncertainty``): 0 = the pose is the sample at the stamp
#: or the interpolation of the two consecutive samples around it.
POSE_EXTRAPOLATED = 1        # no sample after (or before) the stamp within pose_wait: extrapolated
POSE_SAMPLES_MISSING = 2     # samples of the stream missing between the two the pose was computed from

Warn = Callable[..., None]


def camera_topic(namespace: str, kind: str) -> str:
    """Relative input topic of ``kind`` for the camera in ``namespace`` ("" = today's names: ``segmentation``)."""
    ns = namespace.strip("/")
    return f"{ns}/{INPUT_TOPICS[kind]}" if ns else INPUT_TOPICS[kind]


def pose_message_pose(msg: Any, pose_type: str) -> Any:
    """The object holding ``.pose`` (a geometry_msgs/Pose) in a pose message of ``pose_type``.

    PoseStamped: the message; PoseWithCovarianceStamped and Odometry: ``msg.pose`` (whose ``.pose`` is the Pose).
    """
    if pose_type == "pose_stamped":
        return msg
    if pose_type in POSE_TYPES:
        return msg.pose
    raise ValueError(f"unknown pose_type '{pose_type}' (expected one of {', '.join(POSE_TYPES)})")


def intrinsics_for(labels_shape: tuple[int, int], info: Intrinsics) -> Intrinsics:
    """Intrinsics for a segmentation of ``labels_shape`` (H, W): camera_info's, or scaled to that resolution.

    A segmentation smaller or larger than camera_info by one factor in x and y (within
    :data:`RESOLUTION_TOLERANCE_PX` of rounding) is used at its own resolution with K scaled (pixel centres at
    integers: fx' = fx s_x, cx' = (cx + 0.5) s_x - 0.5). Other sizes raise FrameRejected.
    """
    h, w = labels_shape
    if (h, w) == info.shape:
        return info
    f = w / info.width
    if h <= 0 or w <= 0 or abs(info.height * f - h) > RESOLUTION_TOLERANCE_PX or \
            abs(info.width * (h / info.height) - w) > RESOLUTION_TOLERANCE_PX:
        raise FrameRejected("size mismatch with camera_info",
                            f"segmentation {w}x{h} is not camera_info {info.width}x{info.height} scaled by one "
                            "factor in x and y (different aspect ratio)")
    K = Camera(K=info.K, width=info.width, height=info.height, T_map_cam=np.eye(4)).resized(w, h).K
    return Intrinsics(np.array(K), w, h)


@dataclass(frozen=True)
class GateConfig:
    """What the gate needs to know; node parameters and css_replay options map onto it one to one.

    ``cameras``: namespaces ("" = the un-namespaced topics); ``extrinsics``: one rigid T_body_optical per camera
    or None (the pose is the optical frame's); ``splat_to_map``: map <- splat similarity; times in seconds.
    """

    cameras: tuple[str, ...] = ("",)
    pose_type: str = "pose_stamped"
    pose_per_camera: bool = False
    extrinsics: tuple[Similarity | None, ...] = (None,)
    splat_to_map: Similarity = field(default_factory=Similarity.identity)
    pose_policy: PosePolicy = field(default_factory=PosePolicy)
    sync_slop: float = 0.05
    queue_size: int = 30
    map_frame: str = "map"
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    max_stamp_future: float = 0.0
    #: extra image kinds matched to frames and decoded as labels (css_replay: "gt")
    extra_label_kinds: tuple[str, ...] = ()
    #: optional kinds ("image", extra kinds) a frame waits for (up to pose_wait) before it is emitted without
    #: them (css_replay: those its bag has, so that log-time order does not decide what a frame gets)
    wait_for: tuple[str, ...] = ()
    #: "topic": poses from the pose stream(s); "tf": the TF lookup map_frame <- segmentation frame_id
    pose_source: str = "topic"
    #: history [s] every dynamic TF edge keeps (pose_source "tf")
    tf_buffer: float = DEFAULT_TF_BUFFER_S
    #: the depth image topic of each camera, relative to its namespace (absolute: as it is); "": no depth
    depth_topic: str = ""


@dataclass
class GateFrame:
    """One frame ready for the engine.

    ``camera``: intrinsics at the segmentation's resolution and the optical pose in the **splat** frame (what the
    engine renders); ``position_map`` (3,) [m] and ``quat_map`` (4,) xyzw: the optical frame in the **map** frame
    (what is published); ``pose_how``: "exact", "interpolated" or "extrapolated"; ``t_arrival``: the gate time
    [s] at which the segmentation arrived; ``extras[kind]``: matched extra label images (or absent);
    ``pose_missing``: samples of the pose stream missing between the two the pose was computed from (their
    publication sequence numbers tell; 0 when consecutive or unknown); ``depth``: (H, W) float32 measured depth [m]
    at the segmentation's resolution (NaN: no measurement), None without one.
    """

    camera_index: int
    stamp_ns: int
    frame_id: str
    map_frame: str
    labels: np.ndarray
    confidence: np.ndarray | None
    image: np.ndarray | None
    camera: Camera
    position_map: np.ndarray
    quat_map: np.ndarray
    pose_how: str
    t_arrival: float
    extras: dict[str, np.ndarray] = field(default_factory=dict)
    pose_missing: int = 0
    depth: np.ndarray | None = None

    @property
    def pose_flags(self) -> int:
        """POSE_EXTRAPOLATED | POSE_SAMPLES_MISSING as they apply; 0: the interpolation of the samples around the
        stamp (or the sample at it)."""
        return (POSE_EXTRAPOLATED if self.pose_how == "extrapolated" else 0) | \
            (POSE_SAMPLES_MISSING if self.pose_missing else 0)


@dataclass
class _Pending:
    stamp_ns: int
    labels: np.ndarray
    frame_id: str
    t_arrival: float


class _CameraState:
    """Buffers of one camera (all bounded by ``queue_size`` entries)."""

    def __init__(self, index: int, namespace: str, queue_size: int, extra_kinds: Sequence[str]) -> None:
        self.index = index
        self.namespace = namespace
        self.info: Intrinsics | None = None
        self.pending: deque[_Pending] = deque()
        self.buffers: dict[str, deque[tuple[int, Any]]] = {
            k: deque(maxlen=queue_size) for k in ("confidence", "image", "depth", *extra_kinds)}
        self.last_frame_ns: int | None = None
        self.stale_run = 0


class FrameGate:
    """Turns the input messages of every camera and the pose stream(s) into :class:`GateFrame` s.

    Args:
        config: see :class:`GateConfig`.
        warn: ``warn(topic, reason, detail="", dropped=True)``: every refusal (the node's WarnLimiter).
        count: ``count(key, n=1)``: counters (frames per camera, pose samples, ...).
        confidence_expected: ``confidence_expected(camera_index) -> bool``: frames of that camera wait for a
            confidence image (node: it has a publisher; replay: the bag has the topic).
        now_ns: the clock against which ``max_stamp_future`` is checked (0 or less: unknown, check skipped).
        log_warning: unconditional warnings (clock reset).
        depth_expected: ``depth_expected(camera_index) -> bool``: with ``depth_topic``, frames of that camera wait
            (up to pose_wait) for a depth image (node: it has a publisher); None: they never wait for one.
    """

    def __init__(self, config: GateConfig, warn: Warn, count: Callable[..., None],
                 confidence_expected: Callable[[int], bool], now_ns: Callable[[], int] = lambda: 0,
                 log_warning: Callable[[str], None] = lambda s: None,
                 depth_expected: Callable[[int], bool] | None = None) -> None:
        if config.pose_type not in POSE_TYPES:
            raise ValueError(f"unknown pose_type '{config.pose_type}' (expected one of {', '.join(POSE_TYPES)})")
        if len(config.extrinsics) != len(config.cameras):
            raise ValueError("one extrinsics entry (or None) per camera")
        if config.pose_source not in POSE_SOURCES:
            raise ValueError(f"unknown pose_source '{config.pose_source}' (expected one of {', '.join(POSE_SOURCES)})")
        self.cfg = config
        self.warn = warn
        self.count = count
        self.confidence_expected = confidence_expected
        self.depth_expected = depth_expected if config.depth_topic else None
        self.now_ns = now_ns
        self.log_warning = log_warning
        self.cams = [_CameraState(i, ns, config.queue_size, config.extra_label_kinds)
                     for i, ns in enumerate(config.cameras)]
        n_hist = len(config.cameras) if config.pose_per_camera else 1
        self.histories = [PoseHistory(config.pose_policy) for _ in range(n_hist)]
        self._recent: list[deque[tuple[int, np.ndarray, np.ndarray, int | None]]] = [
            deque(maxlen=RECENT_POSES) for _ in range(n_hist)]
        self._map_to_splat = config.splat_to_map.inverse()
        self._slop_ns = int(round(config.sync_slop * 1e9))
        self._wait_ns = int(round(config.pose_policy.wait * 1e9))
        self.frames_by_how: Counter[str] = Counter()
        #: the TF tree (pose_source "tf"; its edges follow the pose policy with buffer = tf_buffer)
        self.tf: TfBuffer | None = None
        if config.pose_source == "tf":
            self.tf = TfBuffer(PosePolicy(buffer=config.tf_buffer, wait=config.pose_policy.wait,
                                          max_extrapolation=config.pose_policy.max_extrapolation,
                                          max_gap=config.pose_policy.max_gap,
                                          max_samples=config.pose_policy.max_samples))

    # ------------------------------------------------------------------ naming
    def topic(self, cam: int, kind: str) -> str:
        """Relative topic name of camera ``cam``'s input ``kind`` (pose: per camera only with pose_per_camera)."""
        if kind == "pose" and not self.cfg.pose_per_camera:
            return INPUT_TOPICS["pose"]
        if kind == "depth":
            name, ns = self.cfg.depth_topic, self.cfg.cameras[cam].strip("/")
            return name if name.startswith("/") or not ns else f"{ns}/{name}"
        return camera_topic(self.cfg.cameras[cam], kind)

    def _history_index(self, cam: int) -> int:
        return cam if self.cfg.pose_per_camera else 0

    def _cams_of_history(self, h: int) -> list[int]:
        return [h] if self.cfg.pose_per_camera else list(range(len(self.cams)))

    # ------------------------------------------------------------------ checks
    def stamp_ok(self, topic: str, stamp_ns: int) -> bool:
        """False (warned) when ``stamp_ns`` is more than max_stamp_future s ahead of the clock."""
        if self.cfg.max_stamp_future > 0:
            now = self.now_ns()
            if now > 0 and stamp_ns > now + self.cfg.max_stamp_future * 1e9:
                self.warn(topic, "stamp in the future",
                          f"{(stamp_ns - now) * 1e-9:.3f} s ahead of the node clock (max_stamp_future)")
                return False
        return True

    def frame_id_check(self, topic: str, frame_id: str) -> None:
        """Warn (not dropped) when a pose's frame_id is not map_frame: there is no tf here."""
        if frame_id and frame_id.lstrip("/") != self.cfg.map_frame:
            self.warn(topic, "frame_id differs from map_frame",
                      f"'{frame_id}' != '{self.cfg.map_frame}' (no tf here): used as map frame", dropped=False)

    # ------------------------------------------------------------------ inputs
    def set_camera_info(self, cam: int, intrinsics: Intrinsics) -> None:
        """Use ``intrinsics`` for camera ``cam`` (css_replay: the first valid camera_info of the bag)."""
        self.cams[cam].info = intrinsics

    def on_camera_info(self, cam: int, msg: Any) -> bool:
        """Keep a valid camera_info; refuse (warned, previous one kept) an invalid one."""
        try:
            self.cams[cam].info = decode_camera_info(msg, self.cfg.max_image_pixels)
        except FrameRejected as exc:
            self.warn(self.topic(cam, "camera_info"), exc.reason, f"{exc}; keeping the previous one")
            return False
        return True

    def on_pose(self, msg: Any, now: float, cam: int = 0, seq: int | None = None) -> list[GateFrame]:
        """A pose message (of ``pose_type``); ``cam`` only matters with pose_per_camera; ``seq``: its publication
        sequence number when it identifies it in one publisher's stream (:mod:`css_ros.io.sequence`), else None."""
        h = self._history_index(cam)
        topic = self.topic(cam, "pose")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            position, quat = decode_pose(pose_message_pose(msg, self.cfg.pose_type))
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; dropped")
            return []
        except (AttributeError, TypeError, ValueError) as exc:
            self.warn(topic, "invalid pose", f"cannot read a {self.cfg.pose_type} message: {exc}; dropped")
            return []
        self.frame_id_check(topic, str(msg.header.frame_id))
        if not self.stamp_ok(topic, stamp):
            return []
        self._recent[h].append((stamp, position, quat, seq))
        problem = self.histories[h].add(stamp, position, quat, seq)
        self.count("pose_samples")
        if problem == "out of order":
            self.warn(topic, "stamp out of order", "older than the newest pose: inserted in time order",
                      dropped=False)
        elif problem == "clock reset":
            self.log_warning(f"[{topic}] pose stamps jumped back by more than pose_buffer="
                             f"{self.cfg.pose_policy.buffer:g} s several times in a row: new pose history "
                             "(clock reset?)")
            self.count("pose_history_resets")
        elif problem is not None:
            self.warn(topic, problem, "dropped")
        out: list[GateFrame] = []
        for c in self._cams_of_history(h):
            out += self._poll(c, now)
        return out

    def on_tf(self, msg: Any, now: float, static: bool = False) -> list[GateFrame]:
        """A tf2_msgs/TFMessage of ``/tf`` (or ``/tf_static`` when ``static``) into the TF tree (pose_source tf;
        ignored otherwise); frames that waited for it are released."""
        if self.tf is None:
            return []
        topic = TF_STATIC_TOPIC if static else TF_TOPIC
        for reason, detail, dropped in self.tf.add_message(msg, static):
            self.warn(topic, reason, detail, dropped=dropped)
        self.count("tf_static_messages" if static else "tf_messages")
        return self.poll(now)

    def on_image(self, cam: int, msg: Any, now: float) -> list[GateFrame]:
        """Colour image (colour render / PSNR only): kept for the frame with the nearest stamp."""
        topic = self.topic(cam, "image")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            rgb = decode_image(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; ignored")
            return []
        if self.stamp_ok(topic, stamp):
            self.cams[cam].buffers["image"].append((stamp, rgb))
        return self._poll(cam, now)

    def on_depth(self, cam: int, msg: Any, now: float) -> list[GateFrame]:
        """A depth image (``depth_topic``): kept for the frame with the nearest stamp. One that cannot be used is
        warned and dropped, and stands for "no depth at this stamp": that frame goes on without depth at once."""
        topic = self.topic(cam, "depth")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
        except (AttributeError, TypeError, ValueError) as exc:
            self.warn(topic, "bad depth", f"no readable stamp ({exc}); dropped")
            return []
        depth: RawDepth | str
        try:
            depth = decode_depth(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; dropped (the frame of its stamp is fused without depth)")
            depth = exc.reason
        if self.stamp_ok(topic, stamp):
            self.cams[cam].buffers["depth"].append((stamp, depth))
        return self._poll(cam, now)

    def on_extra(self, cam: int, kind: str, msg: Any, now: float, topic: str) -> list[GateFrame]:
        """An extra label image (css_replay's GT), matched to frames like the colour image."""
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            labels = decode_labels(msg, kind)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; ignored")
            return []
        self.cams[cam].buffers[kind].append((stamp, labels))
        return self._poll(cam, now)

    def on_confidence(self, cam: int, msg: Any, now: float) -> list[GateFrame]:
        """Confidence image: non-finite pixels count as 0 (counted), values clipped to [0, 1]."""
        topic = self.topic(cam, "confidence")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            conf, non_finite = decode_confidence(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; dropped")
            return []
        if non_finite:
            self.count("confidence_pixels_non_finite", non_finite)
            self.warn(topic, "non-finite confidence values", f"{non_finite} pixels counted as 0; frame kept",
                      dropped=False)
        if self.stamp_ok(topic, stamp):
            self.cams[cam].buffers["confidence"].append((stamp, conf))
        return self._poll(cam, now)

    def on_segmentation(self, cam: int, msg: Any, now: float) -> list[GateFrame]:
        """A segmentation: a new frame of camera ``cam`` (waits for its pose / confidence, see the module doc)."""
        st = self.cams[cam]
        topic = self.topic(cam, "segmentation")
        self.count("segmentations_received")
        self.count(f"camera[{st.namespace or '/'}].segmentations_received")
        try:
            stamp = stamp_to_ns(msg.header.stamp)
            labels = decode_labels(msg)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; frame dropped")
            return []
        if not self.stamp_ok(topic, stamp):
            return []
        newest = max([p.stamp_ns for p in st.pending] + [st.last_frame_ns or -1])
        if newest >= 0 and stamp <= newest:
            st.stale_run += 1
            if st.stale_run < STAMP_RESET_COUNT:
                self.warn(topic, "stamp out of order",
                          f"{(newest - stamp) * 1e-9:.3f} s older than the last frame; dropped")
                return []
            self._clock_reset(cam, stamp)
        else:
            st.stale_run = 0
        st.pending.append(_Pending(stamp, labels, str(msg.header.frame_id), now))
        if len(st.pending) > self.cfg.queue_size:
            old = st.pending.popleft()
            self.warn(topic, "too many frames waiting for a pose",
                      f"{len(st.pending)} frames waiting (queue_size); the oldest ({old.stamp_ns * 1e-9:.3f} s) "
                      "dropped")
        return self._poll(cam, now)

    def poll(self, now: float) -> list[GateFrame]:
        """Resolve waiting frames whose wait has expired (the node calls it on a timer; replay per message)."""
        out: list[GateFrame] = []
        for c in range(len(self.cams)):
            out += self._poll(c, now)
        return out

    def flush(self) -> list[GateFrame]:
        """End of input (end of a bag): every waiting frame is resolved as if its wait had expired."""
        return self.poll(math.inf)

    def waiting(self) -> int:
        """Frames waiting for a pose or confidence, all cameras."""
        return sum(len(c.pending) for c in self.cams)

    # ------------------------------------------------------------------ matching
    def _clock_reset(self, cam: int, stamp: int) -> None:
        st = self.cams[cam]
        self.log_warning(
            f"[{self.topic(cam, 'segmentation')}] {st.stale_run} consecutive stamps older than the last frame: "
            "assuming the clock was reset (bag restarted?), accepting the new stamps")
        self.count("clock_resets")
        st.last_frame_ns = None
        st.stale_run = 0
        st.pending.clear()
        for buf in st.buffers.values():
            buf.clear()
        # Rebuild the pose history from the poses received since the stamps last jumped back.
        h = self._history_index(cam)
        recent = list(self._recent[h])
        start = 0
        gap = int(self.cfg.pose_policy.max_gap * 1e9)
        for i in range(1, len(recent)):
            if recent[i][0] < recent[i - 1][0] - gap:
                start = i
        if start > 0 or (recent and recent[0][0] > stamp + gap):
            history = self.histories[h]
            history.clear()
            for t, p, q, n in recent[start:]:
                history.add(t, p, q, n)

    def _nearest(self, buf: deque[tuple[int, Any]], stamp: int) -> Any | None:
        best = None
        for t, payload in buf:
            d = abs(t - stamp)
            if d <= self._slop_ns and (best is None or d < best[0]):
                best = (d, payload)
        return None if best is None else best[1]

    def _poll(self, cam: int, now: float) -> list[GateFrame]:
        st = self.cams[cam]
        out: list[GateFrame] = []
        history = self.histories[self._history_index(cam)]
        while st.pending:
            fr = st.pending[0]
            waited = (now - fr.t_arrival) * 1e9 >= self._wait_ns
            confidence = self._nearest(st.buffers["confidence"], fr.stamp_ns)
            if confidence is None and self.confidence_expected(cam):
                if not waited:
                    break
                st.pending.popleft()
                self.warn(self.topic(cam, "segmentation"), "no matching confidence",
                          f"no {self.topic(cam, 'confidence')} within sync_slop={self.cfg.sync_slop:g} s after "
                          f"waiting pose_wait={self.cfg.pose_policy.wait:g} s; frame dropped")
                continue
            if not waited and any(self._nearest(st.buffers[k], fr.stamp_ns) is None for k in self.cfg.wait_for):
                break
            if not waited and self.depth_expected is not None and self.depth_expected(cam) and \
                    not any(t >= fr.stamp_ns for t, _ in st.buffers["depth"]):
                break   # a depth at or after the stamp may still come: nearer than one before it
            if st.info is None and not waited:
                # the camera's first camera_info may arrive after its first segmentation: DDS orders no two topics
                break
            look = self._lookup(history, fr, waited)
            if look.status is LookupStatus.WAIT:
                break
            st.pending.popleft()
            if look.status is LookupStatus.REFUSED:
                self.warn(self.topic(cam, "segmentation"), look.reason, f"{look.detail}; frame dropped")
                continue
            assert look.position is not None and look.quat is not None  # OK lookups carry a pose
            frame = self._build(st, fr, confidence, look.position, look.quat, look.how, look.missing)
            if frame is not None:
                out.append(frame)
        return out

    def _lookup(self, history: PoseHistory, fr: _Pending, waited: bool) -> PoseLookup:
        """The pose of the frame's camera in the map at its stamp: from the pose history, or from TF (the pose of
        the segmentation's frame_id in map_frame)."""
        if self.tf is None:
            return history.lookup(fr.stamp_ns, waited)
        if not fr.frame_id.strip().lstrip("/"):
            return PoseLookup(LookupStatus.REFUSED, reason="no frame_id",
                              detail="the segmentation's header.frame_id is empty: nothing to look up in TF")
        return self.tf.lookup(self.cfg.map_frame, fr.frame_id, fr.stamp_ns, waited)

    def _build(self, st: _CameraState, fr: _Pending, confidence: np.ndarray | None, position: np.ndarray,
               quat: np.ndarray, how: str, missing: int = 0) -> GateFrame | None:
        topic = self.topic(st.index, "segmentation")
        info = st.info
        if info is None:
            self.warn(topic, "no camera_info received yet",
                      f"none within pose_wait={self.cfg.pose_policy.wait:g} s of the frame; frame dropped")
            return None
        try:
            intr = intrinsics_for(fr.labels.shape, info)
            if confidence is not None and confidence.shape != fr.labels.shape:
                raise FrameRejected("size mismatch with camera_info",
                                    f"segmentation_confidence {confidence.shape[1]}x{confidence.shape[0]} != "
                                    f"segmentation {fr.labels.shape[1]}x{fr.labels.shape[0]}")
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; frame dropped")
            return None
        ext = self.cfg.extrinsics[st.index]
        if ext is not None:
            position, quat = ext.compose_pose(position, quat)
        pos_s, quat_s = self._map_to_splat.apply_pose(position, quat)
        try:
            camera = Camera.from_pose(intr.K, intr.width, intr.height, pos_s, quat_s)
        except CameraError as exc:
            self.warn(topic, "invalid camera", f"{exc}; frame dropped")
            return None
        image = self._nearest(st.buffers["image"], fr.stamp_ns)
        depth = self._depth(st, fr) if self.cfg.depth_topic else None
        extras = {}
        for kind in self.cfg.extra_label_kinds:
            found = self._nearest(st.buffers[kind], fr.stamp_ns)
            if found is not None:
                extras[kind] = found
        st.last_frame_ns = fr.stamp_ns
        # Older buffered inputs can no longer match a later frame of this camera.
        limit = fr.stamp_ns - self._slop_ns
        for buf in st.buffers.values():
            while buf and buf[0][0] < limit:
                buf.popleft()
        self.frames_by_how[how] += 1
        self.count("frames_synchronised")
        self.count(f"camera[{st.namespace or '/'}].frames")
        self._flag_pose(topic, fr.stamp_ns, how, missing)
        return GateFrame(st.index, fr.stamp_ns, fr.frame_id, self.cfg.map_frame, fr.labels, confidence, image,
                         camera, np.asarray(position, dtype=np.float64), np.asarray(quat, dtype=np.float64), how,
                         fr.t_arrival, extras, missing, depth)

    def _depth(self, st: _CameraState, fr: _Pending) -> np.ndarray | None:
        """The frame's depth [m] at its resolution, or None (warned when none came; a bad one was at arrival)."""
        topic = self.topic(st.index, "depth")
        found = self._nearest(st.buffers["depth"], fr.stamp_ns)
        if found is None:
            self.warn(topic, "no matching depth", f"none within sync_slop={self.cfg.sync_slop:g} s of frame "
                      f"{fr.stamp_ns * 1e-9:.9f} s (waited up to pose_wait={self.cfg.pose_policy.wait:g} s while "
                      "the topic had a publisher): fused without depth", dropped=False)
            return None
        if isinstance(found, str):   # a bad depth message at this stamp, warned and counted at arrival
            return None
        try:
            return depth_for(found, fr.labels.shape, RESOLUTION_TOLERANCE_PX)
        except FrameRejected as exc:
            self.warn(topic, exc.reason, f"{exc}; the frame is fused without depth", dropped=False)
            return None

    def _flag_pose(self, topic: str, stamp_ns: int, how: str, missing: int) -> None:
        """Count and warn (frame kept) when a frame's pose is not the interpolation of the samples around its stamp."""
        if how == "extrapolated":
            self.count("frames_pose_extrapolated")
            self.warn(topic, "pose extrapolated",
                      f"frame {stamp_ns * 1e-9:.9f} s: no pose on the other side of its stamp within pose_wait="
                      f"{self.cfg.pose_policy.wait:g} s; the nearest pose extrapolated (max_pose_extrapolation="
                      f"{self.cfg.pose_policy.max_extrapolation:g} s); pose_flags {POSE_EXTRAPOLATED}", dropped=False)
        if missing:
            self.count("frames_pose_samples_missing")
            self.warn(topic, "pose samples missing",
                      f"frame {stamp_ns * 1e-9:.9f} s: {missing} sample(s) of the pose stream missing between the "
                      "two its pose was computed from (lost before the node, or dropped as bad); pose_flags "
                      f"{POSE_SAMPLES_MISSING}", dropped=False)

    # ------------------------------------------------------------------ map <-> splat for requests
    def map_poses_to_splat(self, positions: np.ndarray, quats: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidate poses (M, 3), (M, 4) of the pose frame in the map -> optical poses in the splat frame.

        Camera 0's extrinsics apply (a candidate is "the robot here"); NaN rows stay NaN.
        """
        positions = np.asarray(positions, dtype=np.float64).reshape(-1, 3)
        quats = np.asarray(quats, dtype=np.float64).reshape(-1, 4)
        ext = self.cfg.extrinsics[0]
        if ext is not None:
            pos_o = np.full_like(positions, np.nan)
            q_o = np.full_like(quats, np.nan)
            for i in range(len(positions)):
                if np.all(np.isfinite(quats[i])) and np.all(np.isfinite(positions[i])):
                    pos_o[i], q_o[i] = ext.compose_pose(positions[i], quats[i])
            positions, quats = pos_o, q_o
        return self._map_to_splat.apply_poses(positions, quats)

    def map_points_to_splat(self, xyz: np.ndarray) -> np.ndarray:
        """Query points (M, 3) in the map -> splat frame."""
        return self._map_to_splat.apply(xyz)
