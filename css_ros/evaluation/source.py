"""Frames from a bag: read, synchronise (the node's :class:`~css_ros.io.sync.FrameSynchronizer`) and
decode (the node's :mod:`css_ros.io.frames` decoder) every usable frame of a rosbag2 bag."""
from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterator

import numpy as np

from ..engine.camera import Camera
from ..errors import BagError, CameraError, InputError
from ..io.bag import InputBag
from ..io.frames import (FrameRejected, Intrinsics, check_size, decode_camera_info, decode_confidence, decode_image,
                         decode_labels, decode_pose)
from ..io.messages import stamp_to_ns
from ..io.sync import FrameSynchronizer
from ..io.topics import INPUT_TYPES, REQUIRED_BAG_KINDS
from .metrics import LabelRangeCounter

if TYPE_CHECKING:
    from .config import ReplayConfig


@dataclass
class Frame:
    """One synchronised, decoded frame.

    Attributes:
        index: 0-based index among the usable frames of the bag.
        stamp_ns: segmentation header stamp [ns]; every output of the frame carries it.
        camera: intrinsics of the latest camera_info and T_map_cam from the pose.
        labels: (H, W) int32 input segmentation (class ids, ignore_label = no label).
        confidence: (H, W) float32 in [0, 1] or None.
        gt: (H, W) int32 ground-truth labels or None.
        rgb: (H, W, 3) uint8 camera image or None.
        camera_frame: frame_id of the segmentation header (optical frame).
        map_frame: frame_id of the pose header.
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


class FrameSource:
    """Reads, synchronises (shared :class:`~css_ros.sync.FrameSynchronizer`) and decodes the frames of a bag.

    camera_info is not synchronised: the latest received one is used (frames before the first
    camera_info message use the first one). Frames that cannot be used are skipped and counted in
    :attr:`skips` by reason.
    """

    SYNC_KINDS = ("segmentation", "pose", "image", "confidence", "gt")
    #: CLI option of each optional topic kind (for error messages).
    TOPIC_OPTIONS = {"image": "--image-topic", "confidence": "--confidence-topic", "gt": "--gt-topic"}

    def __init__(self, cfg: ReplayConfig) -> None:
        self.cfg = cfg
        #: Label ids >= C (not ignore_label) in the decoded segmentation / GT images (needs cfg.num_classes).
        self.label_range = LabelRangeCounter(int(cfg.num_classes or 0), cfg.ignore_label)
        self.skips: Counter[str] = Counter()
        self.sync_counts: dict[str, int] = {}
        self.undecodable: dict[str, int] = {}
        self.present: dict[str, bool] = {}
        self.anchor_count = 0
        self.camera_info_refused: Counter[str] = Counter()  # invalid camera_info messages (previous one kept)
        self.non_finite_confidence = 0  # confidence pixels that were NaN/inf and counted as 0

    def check(self) -> None:
        """Open the bag once: check topics and types, count segmentation messages (raises BagError)."""
        with InputBag(self.cfg.bag) as bag:
            topics = bag.topics()
            for kind, topic in self.cfg.topics.items():
                if topic and kind in self.cfg.explicit_topics and kind not in REQUIRED_BAG_KINDS \
                        and topic not in topics:
                    have = ", ".join(sorted(topics)) or "none"
                    raise BagError(f"{self.TOPIC_OPTIONS.get(kind, kind)} {topic}: no such topic in bag "
                                   f"{self.cfg.bag}; topics in the bag: {have} ('' disables it)")
                required = kind in REQUIRED_BAG_KINDS
                self.present[kind] = bool(topic) and bag.check_topic(topic, INPUT_TYPES[kind], required)
            self.anchor_count = bag.topics()[self.cfg.topics["segmentation"]][1]

    def frames(self) -> Iterator[Frame]:
        """Yield the usable frames in stamp order (call :meth:`check` first)."""
        cfg = self.cfg
        kinds = [k for k in self.SYNC_KINDS if self.present.get(k)]
        sync = FrameSynchronizer(kinds, slop_ns=int(round(cfg.sync_slop * 1e9)), anchor="segmentation",
                                 queue_size=cfg.sync_queue)
        topic_kind = {cfg.topics[k]: k for k in kinds}
        cam_topic = cfg.topics["camera_info"]
        exhausted = False
        try:
            yield from self._iterate(bag_path=cfg.bag, sync=sync, topic_kind=topic_kind, cam_topic=cam_topic)
            exhausted = True
        finally:
            self._finish(sync, exhausted)

    def _iterate(self, bag_path: Path, sync: FrameSynchronizer, topic_kind: dict[str, str], cam_topic: str) -> Iterator[Frame]:
        index = 0
        with InputBag(bag_path) as bag:
            self.undecodable = bag.undecodable  # shared dict, filled while reading
            first = bag.messages([cam_topic])
            intrinsics = None
            for m in first:  # frames before the first camera_info use the first valid one
                intrinsics = self._camera_info(m.msg, count=False) or intrinsics
                if intrinsics is not None:
                    break
            first.close()
            if intrinsics is None:
                raise BagError(f"bag {bag_path}: no valid message on {cam_topic}")
            for m in bag.messages([*topic_kind, cam_topic]):
                if m.topic == cam_topic:
                    intrinsics = self._camera_info(m.msg, count=True) or intrinsics  # keep the last valid one
                    continue
                kind = topic_kind[m.topic]
                try:
                    stamp = stamp_to_ns(m.msg.header.stamp)
                except (AttributeError, TypeError, ValueError):
                    self.skips[f"bad_header_{kind}"] += 1
                    continue
                for synced in sync.push(kind, stamp, m.msg):
                    frame = self._decode(index, synced.stamp_ns, synced.items, intrinsics)
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

    def _finish(self, sync: FrameSynchronizer, exhausted: bool) -> None:
        """Turn the synchroniser's diagnostics into skip counts (pending anchors only at the end of the bag)."""
        self.sync_counts = dict(sync.counts)
        if sync.counts.get("unmatched"):
            self.skips["unmatched_missing_pose_or_other_topic"] += sync.counts["unmatched"]
        pending = sync.pending().get("segmentation", 0)
        if exhausted and pending:
            self.skips["unmatched_at_end_of_bag"] += pending
        for k, v in sync.counts.items():
            if k.startswith(("stale_segmentation", "overflow_segmentation")):
                self.skips[k] += v
        for topic, n in self.undecodable.items():
            self.skips[f"undecodable_{topic}"] += n

    def _decode(self, index: int, stamp_ns: int, items: dict[str, Any], intrinsics: Intrinsics) -> Frame | None:
        """Decode one synchronised frame with the shared decoder (:mod:`css_ros.io.frames`); None = skipped."""
        seg_msg, pose_msg = items["segmentation"], items["pose"]
        try:
            labels = decode_labels(seg_msg)
            check_size(labels, intrinsics, "segmentation")
            gt = confidence = rgb = None
            if "gt" in items:
                gt = decode_labels(items["gt"], "gt")
                check_size(gt, intrinsics, "gt")
            if "confidence" in items:
                confidence, non_finite = decode_confidence(items["confidence"])
                check_size(confidence, intrinsics, "confidence")
                self.non_finite_confidence += non_finite
            if "image" in items:
                rgb = decode_image(items["image"])
                check_size(rgb, intrinsics, "image")
            position, quat = decode_pose(pose_msg)
            camera = Camera.from_pose(intrinsics.K, intrinsics.width, intrinsics.height, position, quat)
        except FrameRejected as exc:
            self.skips[exc.reason.replace(" ", "_")] += 1
            return None
        except CameraError:
            self.skips["invalid_pose"] += 1
            return None
        if self.label_range.num_classes:
            self.label_range.update("segmentation", labels)
            if gt is not None:
                self.label_range.update("gt", gt)
        return Frame(
            index=index, stamp_ns=int(stamp_ns), camera=camera, labels=labels, confidence=confidence,
            gt=gt, rgb=rgb, camera_frame=str(seg_msg.header.frame_id), map_frame=str(pose_msg.header.frame_id),
        )


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
