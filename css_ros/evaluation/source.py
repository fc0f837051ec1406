"""Frames from a bag: read every message in log-time order and turn them into frames with the node's gate
(:class:`~css_ros.io.frame_gate.FrameGate`: the same decoders, stamp matching, pose interpolation, extrinsics and
splat_to_map as css_node). Time for the gate's waits is the bag's log time, so a replay is deterministic."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from ..engine.camera import Camera
from ..engine.similarity import Similarity, parse_extrinsics
from ..errors import BagError, InputError
from ..io.bag import InputBag
from ..io.frame_gate import FrameGate, GateConfig, GateFrame
from ..io.frames import FrameRejected, Intrinsics, decode_camera_info, resample_to
from ..io.pose_history import PosePolicy
from ..io.topics import (INPUT_TYPES, POSE_TYPES, REQUIRED_BAG_KINDS, TF_STATIC_TOPIC, TF_TOPIC, TF_TYPE,
                         camera_bag_topics)
from .metrics import LabelRangeCounter

if TYPE_CHECKING:
    from .config import ReplayConfig


@dataclass
class Frame:
    """One synchronised, decoded frame.

    Attributes:
        index: 0-based index among the usable frames of the bag (all cameras, in emission order).
        stamp_ns: segmentation header stamp [ns]; every output of the frame carries it.
        camera: intrinsics (at the segmentation's resolution) and the optical pose in the splat frame.
        labels: (H, W) int32 input segmentation (class ids, ignore_label = no label).
        confidence: (H, W) float32 in [0, 1] or None.
        gt: (H, W) int32 ground-truth labels at the segmentation's resolution, or None.
        rgb: (H, W, 3) uint8 camera image at the segmentation's resolution, or None.
        camera_frame: frame_id of the segmentation header (optical frame).
        map_frame: the map frame (frame_id of the pose stream's poses).
        camera_index: which camera (index into the configured namespaces).
        position_map, quat_map: the optical frame's pose in the map frame [m], xyzw.
        depth: (H, W) float32 measured depth [m] along the optical axis at the segmentation's resolution (nearest
            neighbour), NaN = no measurement; None without a depth topic.
        gt_changed: (H, W) int32 class at the end of the bag of the pixels whose class changes during it
            (ignore_label elsewhere), at the segmentation's resolution, or None.
    """

    index: int
    stamp_ns: int
    camera: Camera
    labels: np.ndarray
    confidence: np.ndarray | None
    gt: np.ndarray | None
    rgb: np.ndarray | None
    camera_frame: str
    map_frame: str
    camera_index: int = 0
    position_map: np.ndarray | None = None
    quat_map: np.ndarray | None = None
    depth: np.ndarray | None = None
    gt_changed: np.ndarray | None = None


#: Optional label images matched to each segmentation by stamp and brought to its resolution (nearest neighbour);
#: the depth goes through the gate's own depth path (FrameGate.on_depth: waits, pairing and resizing as css_node's).
EXTRA_KINDS = ("gt", "gt_changed")


def replay_gate_config(cfg: ReplayConfig, pose_type: str, extra_kinds: tuple[str, ...],
                       wait_for: tuple[str, ...], pose_source: str = "topic", depth_topic: str = "") -> GateConfig:
    """The node's gate configuration from css_replay's options (the same names as the node parameters);
    ``pose_source``: "topic" or "tf" (the bag's, found by :meth:`FrameSource.check`); ``depth_topic``: the bag's
    depth topic ("" when it has none or it is disabled)."""
    cams = tuple(c.strip("/") for c in cfg.cameras)
    return GateConfig(cameras=cams, pose_type=pose_type, pose_per_camera=cfg.pose_per_camera,
                      extrinsics=tuple(parse_extrinsics(cfg.camera_extrinsics, len(cams))),
                      splat_to_map=Similarity.from_params(cfg.splat_to_map),
                      pose_policy=PosePolicy(buffer=cfg.pose_buffer, wait=cfg.pose_wait,
                                             max_extrapolation=cfg.max_pose_extrapolation, max_gap=cfg.max_pose_gap),
                      sync_slop=cfg.sync_slop, queue_size=cfg.sync_queue, map_frame=cfg.map_frame,
                      max_image_pixels=cfg.max_image_pixels, extra_label_kinds=extra_kinds, wait_for=wait_for,
                      pose_source=pose_source, tf_buffer=cfg.tf_buffer_s, depth_topic=depth_topic)


class FrameSource:
    """Reads a bag and yields its frames through the node's gate.

    camera_info is not synchronised: the latest valid one of each camera is used (frames before a camera's first
    camera_info message use its first valid one). Frames that cannot be used are skipped and counted in
    :attr:`skips` by reason.
    """

    #: CLI option of each optional topic kind (for error messages).
    TOPIC_OPTIONS = {"image": "--image-topic", "confidence": "--confidence-topic", "gt": "--gt-topic",
                     "depth": "--depth-topic", "gt_changed": "--gt-changed-topic"}

    def __init__(self, cfg: ReplayConfig) -> None:
        self.cfg = cfg
        #: Label ids >= C (not ignore_label) in the decoded segmentation / GT images (needs cfg.num_classes).
        self.label_range = LabelRangeCounter(int(cfg.num_classes or 0), cfg.ignore_label)
        self.skips: Counter[str] = Counter()
        self.sync_counts: dict[str, int] = {}
        self.undecodable: dict[str, int] = {}
        #: kind -> present for every camera (camera 0's topics for the single-camera case)
        self.present: dict[str, bool] = {}
        self.anchor_count = 0
        self.pose_type = cfg.pose_type
        #: "topic" or "tf" once the bag was opened (cfg.pose_source "auto" resolved; None before)
        self.pose_source: str | None = None
        self.camera_info_refused: Counter[str] = Counter()  # invalid camera_info messages (previous one kept)
        self.non_finite_confidence = 0  # confidence pixels that were NaN/inf and counted as 0
        self.topics = camera_bag_topics(cfg.cameras, cfg.topics, cfg.pose_per_camera)

    def check(self) -> None:
        """Open the bag once: check topics and types, find the pose type, count segmentations (raises BagError)."""
        with InputBag(self.cfg.bag) as bag:
            topics = bag.topics()
            pose_topics = {t["pose"] for t in self.topics}
            self.pose_source = self._pose_source(bag, topics, pose_topics)
            if self.pose_type == "auto":
                found = {topics[t][0] for t in pose_topics if t in topics}
                by_type = {v: k for k, v in POSE_TYPES.items()}
                known = [by_type[f] for f in found if f in by_type]
                self.pose_type = known[0] if len(known) == 1 else "pose_stamped"
            present: dict[str, bool] = {}
            for cam_topics in self.topics:
                for kind, topic in cam_topics.items():
                    if topic and kind in self.cfg.explicit_topics and kind not in REQUIRED_BAG_KINDS \
                            and topic not in topics:
                        have = ", ".join(sorted(topics)) or "none"
                        raise BagError(f"{self.TOPIC_OPTIONS.get(kind, kind)} {topic}: no such topic in bag "
                                       f"{self.cfg.bag}; topics in the bag: {have} ('' disables it)")
                    required = kind in REQUIRED_BAG_KINDS and not (kind == "pose" and self.pose_source == "tf")
                    if kind == "pose" and self.pose_source == "tf":
                        present[kind] = False
                        continue
                    msgtype = POSE_TYPES[self.pose_type] if kind == "pose" else INPUT_TYPES[kind]
                    ok = bool(topic) and bag.check_topic(topic, msgtype, required)
                    present[kind] = present.get(kind, True) and ok
            self.present = present
            self.anchor_count = sum(topics[t["segmentation"]][1] for t in self.topics)

    def _pose_source(self, bag: InputBag, topics: dict[str, tuple[str, int]], pose_topics: set[str]) -> str:
        """"topic" or "tf" for this bag (``--pose-source auto``: the pose topic if the bag has it, else TF);
        raises BagError when TF is chosen and the bag has neither /tf nor /tf_static of type TFMessage."""
        source = self.cfg.pose_source
        has_tf = [bag.check_topic(t, TF_TYPE, required=False) for t in (TF_TOPIC, TF_STATIC_TOPIC)]
        if source == "auto":
            source = "tf" if any(has_tf) and not any(t in topics for t in pose_topics) else "topic"
        if source == "tf" and not any(has_tf):
            have = ", ".join(sorted(topics)) or "none"
            raise BagError(f"bag {self.cfg.bag}: pose_source tf needs {TF_TOPIC} or {TF_STATIC_TOPIC} ({TF_TYPE}); "
                           f"topics in the bag: {have}")
        return source

    def frames(self) -> Iterator[Frame]:
        """Yield the usable frames (call :meth:`check` first)."""
        try:
            yield from self._iterate()
        finally:
            self._finish()

    def _warn(self, topic: str, reason: str, detail: str = "", dropped: bool = True) -> None:
        if dropped:
            self.skips[reason.replace(" ", "_")] += 1

    def _count(self, key: str, n: int = 1) -> None:
        if key == "confidence_pixels_non_finite":
            self.non_finite_confidence += n

    def _iterate(self) -> Iterator[Frame]:
        cfg = self.cfg
        if self.pose_source is None:  # a second pass that copied check()'s results without calling it
            with InputBag(cfg.bag) as bag:
                self.pose_source = self._pose_source(bag, bag.topics(), {t["pose"] for t in self.topics})
        extra = tuple(k for k in EXTRA_KINDS if self.present.get(k))
        wait_for = tuple(k for k in ("image", *EXTRA_KINDS) if self.present.get(k))
        depth_topic = cfg.topics.get("depth", "") if self.present.get("depth") else ""
        self.gate = gate = FrameGate(replay_gate_config(cfg, self.pose_type, extra, wait_for, self.pose_source,
                                                        depth_topic),
                                     self._warn, self._count, lambda cam: bool(self.present.get("confidence")),
                                     depth_expected=lambda cam: bool(self.present.get("depth")))
        routes: dict[str, list[tuple[int, str]]] = {}
        for cam, cam_topics in enumerate(self.topics):
            for kind, topic in cam_topics.items():
                if topic and (self.present.get(kind) or kind in REQUIRED_BAG_KINDS):
                    if kind == "pose" and (self.pose_source == "tf" or (not cfg.pose_per_camera and cam > 0)):
                        continue
                    routes.setdefault(topic, []).append((cam, kind))
        if self.pose_source == "tf":
            routes[TF_TOPIC] = [(0, "tf")]
        index = 0
        with InputBag(cfg.bag) as bag:
            self.undecodable = bag.undecodable  # shared dict, filled while reading
            for cam, cam_topics in enumerate(self.topics):
                first = bag.messages([cam_topics["camera_info"]])
                intrinsics = None
                for m in first:  # frames before the first camera_info use the first valid one
                    intrinsics = self._camera_info(m.msg, count=False)
                    if intrinsics is not None:
                        break
                first.close()
                if intrinsics is None:
                    raise BagError(f"bag {cfg.bag}: no valid message on {cam_topics['camera_info']}")
                gate.set_camera_info(cam, intrinsics)
            if self.pose_source == "tf":  # static transforms hold at every time: all of the bag's first
                for m in bag.messages([TF_STATIC_TOPIC]):
                    gate.on_tf(m.msg, m.log_time_ns * 1e-9, static=True)
            for m in bag.messages(list(routes)):
                now = m.log_time_ns * 1e-9
                out: list[GateFrame] = []
                for cam, kind in routes[m.topic]:
                    if kind == "tf":  # a TFMessage has no header of its own
                        out += gate.on_tf(m.msg, now)
                        continue
                    try:
                        m.msg.header.stamp.sec  # noqa: B018 - a header is needed by every kind
                    except AttributeError:
                        self.skips[f"bad_header_{kind}"] += 1
                        continue
                    if kind == "camera_info":
                        intr = self._camera_info(m.msg, count=True)
                        if intr is not None:
                            gate.set_camera_info(cam, intr)
                    elif kind == "pose":
                        out += gate.on_pose(m.msg, now, cam)
                    elif kind == "segmentation":
                        out += gate.on_segmentation(cam, m.msg, now)
                    elif kind == "confidence":
                        out += gate.on_confidence(cam, m.msg, now)
                    elif kind == "image":
                        out += gate.on_image(cam, m.msg, now)
                    elif kind == "depth":
                        out += gate.on_depth(cam, m.msg, now)
                    elif kind in EXTRA_KINDS:
                        out += gate.on_extra(cam, kind, m.msg, now, m.topic)
                out += gate.poll(now)
                for gf in out:
                    frame = self._frame(index, gf)
                    if frame is not None:
                        index += 1
                        yield frame
            for gf in gate.flush():
                frame = self._frame(index, gf)
                if frame is not None:
                    index += 1
                    yield frame

    def _camera_info(self, msg: Any, count: bool) -> Intrinsics | None:
        """The decoded camera_info, or None (counted under ``camera_info_refused``) when invalid."""
        try:
            return decode_camera_info(msg, self.cfg.max_image_pixels)
        except FrameRejected as exc:
            if count:
                self.camera_info_refused[exc.reason] += 1
            return None

    def _finish(self) -> None:
        """Turn the gate's diagnostics into counts (how each pose was found; undecodable messages)."""
        gate = getattr(self, "gate", None)
        if gate is not None:
            self.sync_counts = {f"pose_{k}": v for k, v in gate.frames_by_how.items()}
        for topic, n in self.undecodable.items():
            self.skips[f"undecodable_{topic}"] += n

    def _frame(self, index: int, gf: GateFrame) -> Frame | None:
        """A gate frame as css_replay's Frame (GT and colour image brought to the segmentation's resolution, label
        images by nearest neighbour; the gate already did so for the depth)."""
        shape = gf.labels.shape
        extras: dict[str, np.ndarray | None] = {k: gf.extras.get(k) for k in EXTRA_KINDS}
        rgb = gf.image
        try:
            for kind, image in extras.items():
                if image is not None and image.shape != shape:
                    if not _same_aspect(image.shape, shape):
                        raise FrameRejected("size mismatch with camera_info", kind)
                    extras[kind] = resample_to(image, shape, labels=True)
            if rgb is not None and rgb.shape[:2] != shape:
                if not _same_aspect(rgb.shape[:2], shape):
                    raise FrameRejected("size mismatch with camera_info", "image")
                rgb = resample_to(rgb, shape)
        except FrameRejected as exc:
            self.skips[exc.reason.replace(" ", "_")] += 1
            return None
        gt = extras["gt"]
        if self.label_range.num_classes:
            self.label_range.update("segmentation", gf.labels)
            if gt is not None:
                self.label_range.update("gt", gt)
        return Frame(index=index, stamp_ns=gf.stamp_ns, camera=gf.camera, labels=gf.labels,
                     confidence=gf.confidence, gt=gt, rgb=rgb, camera_frame=gf.frame_id, map_frame=gf.map_frame,
                     camera_index=gf.camera_index, position_map=gf.position_map, quat_map=gf.quat_map,
                     depth=gf.depth, gt_changed=extras["gt_changed"])


def _same_aspect(a: tuple[int, ...], b: tuple[int, ...]) -> bool:
    """True when (H, W) sizes ``a`` and ``b`` differ by one factor (within a pixel of rounding)."""
    f = b[1] / a[1]
    return abs(a[0] * f - b[0]) <= 1.0


def check_label_range(counter: LabelRangeCounter, max_share: float, allow: bool) -> str | None:
    """The stderr warning about out-of-range label ids (None when there are none).

    Raises:
        InputError: the share of out-of-range pixels of a kind exceeds ``max_share`` and not ``allow``.
    """
    parts = []
    worst = 0.0
    for kind, rec in counter.summary().items():
        if rec["pixels"]:
            ids = ", ".join(rec["ids"])
            parts.append(f"{kind}: {rec['pixels']} px ({100 * rec['share']:.2f} % of labelled pixels; ids {ids})")
            worst = max(worst, rec["share"])
    if not parts:
        return None
    text = (f"label ids >= {counter.num_classes} (not a class; ignore_label {counter.ignore_label} excluded) in "
            + "; ".join(parts))
    if worst > max_share and not allow:
        raise InputError(f"{text}: more than {100 * max_share:g} % of the labelled pixels, so the class file "
                         "does not fit this bag (GT pixels would be dropped from the metrics); fix --classes / "
                         "--num-classes or --ignore-label, or pass --allow-out-of-range")
    return f"css_replay: warning: {text}; GT pixels with such ids are excluded from the metrics, input pixels " \
           "count as wrong"
