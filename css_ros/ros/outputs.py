"""css_node's publishers: per-frame images and view point, candidate scores (SPEC §8)."""
from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Callable

import numpy as np
from rclpy.duration import Duration
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from sensor_msgs.msg import Image, PointCloud2

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ..engine.classes import ClassSet
from ..engine.similarity import Similarity
from ..io.clouds import pack_cloud
from ..io.outputs import TOPIC_IMAGES, frame_output_images
from ..io.point_queries import answer_columns
from ..io.semantic_cloud import semantic_cloud_columns
from ..io.topics import FRAME_OUTPUTS, OUTPUT_TOPICS, POINTCLOUD2_TYPE
from . import conversions as rc
from .params import NodeParams
from .work import FrameJob, PointQueryJob

#: ~/semantic_cloud: reliable, transient local (a viewer that joins later gets the last map), keep the last one.
CLOUD_QOS = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.RELIABLE,
                       durability=DurabilityPolicy.TRANSIENT_LOCAL)


#: Outputs that answer requests (one message per request) -> the prefix of their counters (``<prefix>_served``,
#: ``<prefix>_unanswered[<reason>]``; ``requests_*`` are the candidate requests').
ANSWER_OUTPUTS = {"candidate_scores": "requests", "point_query_results": "point_queries"}
#: Seconds an answer made while no subscriber of its topic is matched waits for one (a client's reader that the
#: node's writer has not matched yet, on a loaded host): published as soon as one matches, else counted
#: unanswered. At most request_queue_size answers and ANSWER_HOLD_BYTES of them per topic wait (the oldest gives
#: way, counted likewise).
ANSWER_HOLD_S = 10.0
ANSWER_HOLD_BYTES = 64 * 2**20
NO_SUBSCRIBER = "no subscriber matched within 10 s"   # (or held beyond the bounds above)
PUBLISH_FAILED = "publish failed"


class OutputPublisher:
    """Creates the enabled ``~/<output>`` publishers and publishes the worker's results.

    Every per-frame output carries the frame's input stamp; images the input frame_id, the view point the
    map frame. Camera i's frame outputs are ``~/<ns_i>/<name>`` (the un-namespaced camera keeps ``~/<name>``).
    ``~/candidate_scores`` and ``~/point_query_results`` are always published (they answer requests);
    ``~/semantic_cloud`` unless ``cloud_period`` is 0. Everything 3D is in the map frame (``splat_to_map``).
    ``~/confidence`` exists only when ``confidence_available`` (the sensor model holds a calibrated confidence
    map, so every rendered view carries a confidence image) and ``publish_confidence`` is set; ``~/surprise``
    only with ``output_scale`` 1 (the full-resolution update makes it) and ``publish_surprise``.
    """

    def __init__(self, node: Node, params: NodeParams, classes: ClassSet, depth: int = 10,
                 confidence_available: bool = False, on_matched: Callable[[], None] | None = None,
                 count: Callable[..., None] = lambda key, n=1: None,
                 warn: Callable[..., None] = lambda *a, **k: None) -> None:
        """``on_matched``: called (on the node's executor) whenever a subscriber matches or leaves an output;
        ``count(key, n)``: the node's counters (answers served / unanswered); ``warn``: its rate-limited warnings."""

        def matched(_status: Any) -> None:
            self.release_answers()
            if on_matched is not None:
                on_matched()
        events = PublisherEventCallbacks(matched=matched)
        self.count, self.warn = count, warn
        self._held: dict[str, deque[tuple[float, Any]]] = {name: deque() for name in ANSWER_OUTPUTS}
        self._held_bytes: dict[str, int] = dict.fromkeys(ANSWER_OUTPUTS, 0)
        self._held_lock = threading.Lock()
        self.p = params
        self.classes = classes
        self.clock = node.get_clock()
        self.splat_to_map = Similarity.from_params(params.splat_to_map)
        self.pubs: dict[str, Any] = {}
        #: per camera: output name -> publisher (the per-frame outputs)
        self.camera_pubs: list[dict[str, Any]] = []
        for name, msgtype in OUTPUT_TOPICS.items():
            if name in FRAME_OUTPUTS:
                continue
            if name == "semantic_cloud" and params.cloud_period <= 0:
                continue
            qos = CLOUD_QOS if name == "semantic_cloud" else \
                params.request_queue_size if name in ANSWER_OUTPUTS else depth  # bursts of answers
            self.pubs[name] = node.create_publisher(PointCloud2, f"~/{name}", qos, event_callbacks=events)
        node.create_timer(1.0, self.release_answers)   # answers held longer than ANSWER_HOLD_S are given up
        for ns in params.cameras:
            ns = ns.strip("/")
            pubs = {}
            for name in FRAME_OUTPUTS:
                if not getattr(params, f"publish_{name}") or (name == "confidence" and not confidence_available) \
                        or (name == "surprise" and params.output_scale != 1.0):
                    continue
                typ = PointCloud2 if OUTPUT_TOPICS[name] == POINTCLOUD2_TYPE else Image
                pubs[name] = node.create_publisher(typ, f"~/{ns}/{name}" if ns else f"~/{name}", depth,
                                                   event_callbacks=events)
            self.camera_pubs.append(pubs)
        #: publish the frame images as serialised bytes (one copy of the pixels) when the rmw reads them alike
        self.serialised_images = rc.serialised_images_supported()
        classes.colorize(np.zeros((1, 1), np.int32))   # compile (or load) the colour map's kernel before frame 1

    def subscriber_counts(self) -> dict[str, int]:
        """Subscribers matched by each output publisher now (name relative to the node, e.g. ``semantic`` or
        ``cam1/semantic``): a frame's outputs reach only these (late subscribers get nothing of earlier frames)."""
        out = {name: pub.get_subscription_count() for name, pub in self.pubs.items()}
        for ns, pubs in zip(self.p.cameras, self.camera_pubs):
            ns = ns.strip("/")
            out.update({f"{ns}/{n}" if ns else n: pub.get_subscription_count() for n, pub in pubs.items()})
        return out

    def topic_names(self) -> list[str]:
        """Relative names (``~/...``) of every publisher, for the start-up log."""
        names = [f"~/{n}" for n in self.pubs]
        for ns, pubs in zip(self.p.cameras, self.camera_pubs):
            ns = ns.strip("/")
            names += [f"~/{ns}/{n}" if ns else f"~/{n}" for n in pubs]
        return names

    def frame_outputs(self, camera_index: int) -> frozenset[str]:
        """The images camera ``camera_index``'s next frame must render (SemanticMap.observe's ``outputs``): those
        of its enabled image topics that have a subscriber now. A topic without one would deliver to no one, so
        its images are neither made final nor copied from the GPU."""
        names: set[str] = set()
        for name, pub in self.camera_pubs[camera_index].items():
            if name in TOPIC_IMAGES and pub.get_subscription_count() > 0:
                names.update(TOPIC_IMAGES[name])
        return frozenset(names)

    def publish_frame(self, job: FrameJob, view: Any) -> None:
        frame = job.frame
        pubs = self.camera_pubs[frame.camera_index]
        header = rc.header_msg(frame.stamp_ns, frame.frame_id)
        wanted = [n for n in ("semantic", "semantic_color", "expectation", "variance", "rendered_image",
                              "confidence", "surprise") if n in pubs]
        if "surprise" in wanted and pubs["surprise"].get_subscription_count() == 0:
            wanted.remove("surprise")   # made for the diagnostics' mean every frame: sent only to a subscriber
        if wanted:
            images = frame_output_images(view, self.classes, self.p.ignore_label, wanted)
            for name in wanted:
                if name not in images:  # confidence: only views of a map with a calibrated confidence map
                    continue
                array, encoding = images[name]
                if self.serialised_images:
                    pubs[name].publish(rc.image_bytes(array, encoding, frame.stamp_ns, frame.frame_id))
                else:
                    pubs[name].publish(rc.image_msg(array, encoding, header))
        if "view_uncertainty" in pubs:
            cloud = rc.view_points_msg(rc.header_msg(frame.stamp_ns, self.p.map_frame), frame.position_map[None],
                                       frame.quat_map[None], np.array([view.u_var]), np.array([view.u_exp]),
                                       pose_flags=np.array([frame.pose_flags]))
            pubs["view_uncertainty"].publish(cloud)

    def publish_scores(self, header: Any, positions: np.ndarray, quats: np.ndarray, u_var: np.ndarray,
                       u_exp: np.ndarray, info_gain: np.ndarray) -> None:
        """One point per candidate in request order (fields x y z qx qy qz qw u_var u_exp info_gain,
        css_ros.io.clouds.CANDIDATE_FIELDS); the header echoes the request header."""
        self.answer("candidate_scores",
                    rc.view_points_msg(rc.copy_header(header), positions, quats, u_var, u_exp, info_gain))

    def publish_points(self, job: PointQueryJob) -> None:
        """Answer a point query: one point per query point in request order, the request header echoed."""
        cols = answer_columns(job.xyz, job.labels, job.expectation, job.variance, self.classes.names)
        self.answer("point_query_results", rc.cloud_msg(rc.copy_header(job.header), pack_cloud(cols)))

    # ------------------------------------------------------------------ answers
    def answer(self, name: str, msg: Any) -> None:
        """Publish the answer ``msg`` on ``~/<name>`` (counted ``<prefix>_served``), or, while no subscriber of it
        is matched, hold it up to ANSWER_HOLD_S for one (any thread: the worker, the executors)."""
        with self._held_lock:
            held = self._held[name]
            if held or self.pubs[name].get_subscription_count() == 0:
                held.append((time.monotonic(), msg))
                self._held_bytes[name] += len(msg.data)
                self.count(f"answers_held[{name}]")
                while len(held) > 1 and (len(held) > self.p.request_queue_size or
                                         self._held_bytes[name] > ANSWER_HOLD_BYTES):
                    self._give_up(name)
            else:
                self._publish(name, msg)
        if held:
            self.release_answers()

    def release_answers(self) -> None:
        """Publish the held answers of every topic that has a subscriber now; give up those held too long."""
        now = time.monotonic()
        with self._held_lock:
            for name, held in self._held.items():
                if held and self.pubs[name].get_subscription_count() > 0:
                    while held:
                        msg = held.popleft()[1]
                        self._held_bytes[name] -= len(msg.data)
                        self._publish(name, msg)
                while held and now - held[0][0] > ANSWER_HOLD_S:
                    self._give_up(name)

    def held_answers(self) -> int:
        """Answers waiting for a subscriber now (all answer topics)."""
        with self._held_lock:
            return sum(len(h) for h in self._held.values())

    def _give_up(self, name: str) -> None:
        """Drop the oldest held answer of ``name`` (under the lock), counted unanswered."""
        msg = self._held[name].popleft()[1]
        self._held_bytes[name] -= len(msg.data)
        self._unanswered(name, NO_SUBSCRIBER)

    def _publish(self, name: str, msg: Any) -> None:
        try:
            self.pubs[name].publish(msg)
        except Exception as exc:  # noqa: BLE001 - whatever the middleware raises: counted, the caller goes on
            self._unanswered(name, PUBLISH_FAILED, f"{type(exc).__name__}: {exc}")
            return
        self.count(f"{ANSWER_OUTPUTS[name]}_served")

    def _unanswered(self, name: str, reason: str, detail: str = "") -> None:
        self.count(f"{ANSWER_OUTPUTS[name]}_unanswered[{reason}]")
        self.warn(name, reason, detail or "answer not delivered")

    def publish_cloud(self, smap: Any, min_evidence: float) -> int:
        """Publish ``~/semantic_cloud`` (map frame, stamped now) from the map; returns its number of points."""
        sem = smap.gaussian_semantics(min_evidence)
        means = smap.model.means if self.splat_to_map.is_identity else self.splat_to_map.apply(smap.model.means)
        cols = semantic_cloud_columns(means, sem.label, sem.expectation, sem.variance, sem.evidence,
                                      sem.observed, self.classes.palette, self.p.cloud_voxel_size,
                                      self.p.cloud_max_points)
        header = rc.header_msg(self.clock.now().nanoseconds, self.p.map_frame)
        self.pubs["semantic_cloud"].publish(rc.cloud_msg(header, pack_cloud(cols)))
        return len(cols["x"])

    def flush(self, timeout_s: float = 1.0) -> bool:
        """Wait up to ``timeout_s`` [s] until reliable subscribers acknowledged every candidate answer."""
        try:
            return bool(self.pubs["candidate_scores"].wait_for_all_acked(Duration(nanoseconds=int(timeout_s * 1e9))))
        except Exception:  # noqa: BLE001 - best effort at shutdown (middleware without the feature)
            return False
