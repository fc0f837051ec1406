"""css_node: the rclpy node that maps segmentations onto a splat model and scores candidate views (SPEC §7-8).

The node only wires the parts together: parameters (params.py), input gate (gate.py), work queue
(work.py), worker and checkpoints (worker.py), publishers (outputs.py), diagnostics (diagnostics.py).
"""
from __future__ import annotations

from dataclasses import fields
from types import SimpleNamespace
from typing import Any

import numpy as np

from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.event_handler import PublisherEventCallbacks
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
from rclpy.serialization import deserialize_message
from builtin_interfaces.msg import Time
from std_msgs.msg import Header
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from diagnostic_msgs.msg import DiagnosticArray

from ..engine.similarity import Similarity
from ..errors import ConfigError, InputError, MapError
from ..io.point_queries import CloudHead, cloud_head
from ..io.topics import INPUT_TOPICS, NODE_NAME, TF_STATIC_TOPIC, TF_TOPIC
from .diagnostics import Stats, StatusReporter
from .evidence import EvidenceLink
from .model_swap import ModelWatcher
from .gate import InputGate, NanAnswer
from .intake import Intake
from .outputs import OutputPublisher
from .params import NodeParams, check_params, coerce
from .startup import describe_changing_world, describe_sensor_model, load_engine, warm_up
from .transport import open_inputs_node
from .work import WarnLimiter, WorkQueue
from .worker import MapWorker
from .view_publisher import ViewPublisher

#: Depth of the save_map / reset_map service queues: bursts up to this many calls are all answered.
SERVICE_QUEUE_DEPTH = 64
#: Seconds the worker gets to finish its current frame / slice at shutdown before the final checkpoint.
WORKER_STOP_TIMEOUT_S = 10.0
#: pose_type -> rclpy message class.
POSE_MESSAGES = {"pose_stamped": PoseStamped, "pose_with_covariance": PoseWithCovarianceStamped,
                 "odometry": Odometry}
#: Depth of the /tf_static subscriptions (tf2_ros's listener QoS).
TF_QOS_DEPTH = 100
#: Depth of the pose and /tf subscriptions [messages]: 10 s of a 200 Hz odometry stream. With a depth of queue_size
#: (30: 0.15 s at 200 Hz) a busy executor let the queue overwrite the samples around a frame's stamp.
POSE_QUEUE_DEPTH = 2000
#: Period [s] of the timer that releases frames whose wait for a pose has ended (at most pose_wait / 4).
POSE_POLL_PERIOD_S = 0.05


def tf_message_class() -> Any:
    """tf2_msgs/msg/TFMessage (ConfigError saying how to get it when tf2_msgs is not importable)."""
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError as exc:
        raise ConfigError(f"pose_source tf needs the tf2_msgs messages ({exc}): source a ROS install that has them, "
                          "or build them into this environment with msg_packages/build_tf2_msgs.py (README, "
                          "command 1)") from None
    return TFMessage


def declare_params(node: Node) -> NodeParams:
    """Declare every NodeParams field as a read-only ROS parameter (dynamic typing) and return the values.

    ``-p prior:=1`` (an integer for a float parameter) works; a wrong type is a ConfigError naming the
    parameter; parameters given but not declared are returned by :func:`undeclared_params`.
    """
    defaults = NodeParams()
    values: dict[str, Any] = {}
    for f in fields(NodeParams):
        default = getattr(defaults, f.name)
        desc = ParameterDescriptor(description=f.metadata["description"]
                                   + (f" [{f.metadata['unit']}]" if f.metadata["unit"] else ""),
                                   read_only=True, dynamic_typing=True)
        values[f.name] = coerce(f.name, node.declare_parameter(f.name, default, desc).value, default,
                                f.metadata["items"])
    p = NodeParams(**values)
    check_params(p)
    return p


def _header(head: CloudHead) -> Header:
    """The std_msgs/Header a serialized cloud declares."""
    return Header(stamp=Time(sec=head.sec, nanosec=head.nanosec), frame_id=head.frame_id)


def undeclared_params(node: Node) -> list[str]:
    """Names given to this node (-p, params file) that it does not know (typos such as num_clases)."""
    overrides = getattr(node, "_parameter_overrides", {}) or {}
    return sorted(n for n in overrides if not node.has_parameter(n))


class CssNode(Node):
    """Continuous Semantic Splatting mapping node (see the module docstring and SPEC §7-8)."""

    def __init__(self, inputs_transport: str | None = None, **kwargs: Any) -> None:
        """``inputs_transport``: FASTDDS_BUILTIN_TRANSPORTS of a separate inputs participant (see
        :mod:`css_ros.ros.transport`; the caller spins ``self.inputs`` in its context); None: the inputs are
        subscribed on this node."""
        super().__init__(NODE_NAME, **kwargs)
        log = self.get_logger()
        self.p = p = declare_params(self)
        for name in undeclared_params(self):
            log.warning(f"unknown parameter '{name}' ignored (see css_node --help for the parameters)")
        # pose_source tf without tf2_msgs: a start-up error before the model is loaded
        self._tf_message = tf_message_class() if p.pose_source == "tf" else None
        self.warn = WarnLimiter(log.warning, p.warn_period)
        self.stats = Stats()

        engine = load_engine(p, log.info, log.warning)
        self.smap, self.classes, self.model_path = engine.smap, engine.classes, engine.model_path
        self.checkpoint_path = engine.checkpoint_path
        self.resume_status = engine.resume_status
        if p.warmup:
            warm_up(self.smap, p, log.info)  # CssError: fatal (cannot start)

        self.queue = WorkQueue(p.max_pending_frames)
        sensor_model = self.smap.sensor_model
        self.outputs = OutputPublisher(self, p, self.classes, confidence_available=sensor_model is not None
                                       and sensor_model.confidence is not None, on_matched=self._endpoint_matched,
                                       count=self.stats.count, warn=self.warn)
        self.worker = MapWorker(self.smap, p, self.queue, self.outputs, self.warn, self.stats,
                                self.checkpoint_path, log.info, log.error)
        self.evidence = EvidenceLink(self, p, self.worker, self.warn, self.stats.count)
        self.model_watcher = ModelWatcher(self, p, self.warn, self.stats.count, log.info, log.warning)
        if p.view_period > 0:  # css_view --live
            self.worker.view_stream = ViewPublisher(self, self.smap, self.classes, p.view_period,
                                                    p.view_max_changes, p.min_evidence,
                                                    Similarity.from_params(p.splat_to_map))
        self.gate = InputGate(p, self.warn, self.stats.count, lambda: self.get_clock().now().nanoseconds,
                              self._confidence_published, log.warning, depth_published=self._depth_published)
        frames = self.gate.frames
        self._confidence_topics = [self.resolve_topic_name(frames.topic(i, "confidence"))
                                   for i in range(len(p.cameras))]
        self._depth_topics = [self.resolve_topic_name(frames.topic(i, "depth")) if p.depth_topic else ""
                              for i in range(len(p.cameras))]

        if p.input_qos == "reliable":
            qos_in = QoSProfile(depth=p.queue_size, reliability=ReliabilityPolicy.RELIABLE,
                                history=HistoryPolicy.KEEP_LAST)
        else:
            qos_in = QoSProfile(depth=p.queue_size, reliability=qos_profile_sensor_data.reliability,
                                durability=qos_profile_sensor_data.durability, history=HistoryPolicy.KEEP_LAST)
        # Deep enough for a burst of request_queue_size requests: none is lost before its callback runs.
        qos_req = QoSProfile(depth=p.request_queue_size, reliability=ReliabilityPolicy.RELIABLE,
                             history=HistoryPolicy.KEEP_LAST)
        qos_pose = QoSProfile(depth=max(p.queue_size, POSE_QUEUE_DEPTH), reliability=qos_in.reliability,
                              durability=qos_in.durability, history=HistoryPolicy.KEEP_LAST)
        # Every call of the gate's frame path comes from the inputs node's executor (one thread): the gate keeps no
        # lock. Requests come on this node's own executor: the gate reads only its configuration and the latest
        # camera_info for them, and a huge request no longer holds up (or floods the sockets of) the camera streams.
        self.inputs: Node = self
        self.inputs_context: Any = None
        if inputs_transport is not None:
            self.inputs, self.inputs_context = open_inputs_node(NODE_NAME, self.get_namespace(), inputs_transport)
        # the inputs' readers matching a publisher publish the diagnostics too (``publishers[<topic>]``), on this
        # node's executor: the inputs node's executor is another thread
        self._matched_guard = self.create_guard_condition(self._endpoint_matched)
        self.intake = Intake(self.inputs, self.stats.count, self.warn, on_matched=self._inputs_matched)
        self.request_intake = Intake(self, self.stats.count, self.warn)

        def sub(msg_type: Any, topic: str, handler: Any, qos: QoSProfile, drained: bool = False) -> None:
            """Subscribe the inputs node to ``topic`` as this node resolves it (namespace, remappings);
            ``handler(msg, seq)``; messages lost before the node count as ``<topic>_lost`` (topic as given, without
            a leading /)."""
            self.intake.subscribe(msg_type, self.resolve_topic_name(topic), handler, qos, topic.lstrip("/"), drained)

        # camera_info first: when several messages are ready the executor takes them in this order.
        t = INPUT_TOPICS
        pose_msg = POSE_MESSAGES[p.pose_type]
        for i in range(len(p.cameras)):
            sub(CameraInfo, frames.topic(i, "camera_info"),
                lambda m, _s, i=i: self.gate.on_camera_info(m, i), qos_in)
        if p.pose_source == "tf":
            self._subscribe_tf(sub)
        else:
            for i in range(len(p.cameras) if p.pose_per_camera else 1):
                sub(pose_msg, frames.topic(i, "pose"),
                    lambda m, seq, i=i: self._put_frames(self.gate.on_pose(m, i, seq)), qos_pose, drained=True)
        for i in range(len(p.cameras)):
            sub(Image, frames.topic(i, "image"),
                lambda m, _s, i=i: self._put_frames(self.gate.on_image(m, i)), qos_in)
            sub(Image, frames.topic(i, "confidence"),
                lambda m, _s, i=i: self._put_frames(self.gate.on_confidence(m, i)), qos_in)
            if p.depth_topic:
                sub(Image, frames.topic(i, "depth"), lambda m, _s, i=i: self._put_frames(self.gate.on_depth(m, i)),
                    qos_in)
            sub(Image, frames.topic(i, "segmentation"),
                lambda m, _s, i=i: self._put_frames(self.gate.on_segmentation(m, i)), qos_in)
        self.inputs.create_timer(min(POSE_POLL_PERIOD_S, max(p.pose_wait / 4, 0.005)), self._poll_frames)
        self.request_intake.subscribe(PoseArray, self.resolve_topic_name(t["candidates"]),
                                      lambda m, _s: self._on_candidates(m), qos_req, "candidates")
        self.request_intake.subscribe(PointCloud2, self.resolve_topic_name(t["point_queries"]),
                                      lambda m, _s: self._on_point_query_raw(m), qos_req, "point_queries", raw=True)

        qos_srv = QoSProfile(depth=SERVICE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE)
        self.create_service(Trigger, "~/save_map", self._on_save_map, qos_profile=qos_srv)
        self.create_service(Trigger, "~/reset_map", self._on_reset_map, qos_profile=qos_srv)
        self.create_service(Trigger, "~/load_map", self._on_load_map, qos_profile=qos_srv)
        diag_pub = self.create_publisher(DiagnosticArray, "/diagnostics", 10, event_callbacks=PublisherEventCallbacks(
            matched=lambda _status: self._endpoint_matched())) if p.publish_diagnostics else None
        self.reporter = StatusReporter(self.stats, self.warn, self.queue.sizes,
                                       lambda: (*self.worker.last_u, self.worker.last_psnr), log.info, diag_pub,
                                       self.get_fully_qualified_name(), str(self.model_path),
                                       lambda: self.get_clock().now().to_msg(), self._diagnostics_info)
        if p.log_period > 0:
            self.create_timer(p.log_period, self.reporter.report)
        self.worker.start()
        self._log_start()

    # ------------------------------------------------------------------ wiring
    def _subscribe_tf(self, sub: Any) -> None:
        """/tf (reliable, depth POSE_QUEUE_DEPTH, drained) and /tf_static with tf2_ros's listener QoS (reliable,
        depth 100, transient-local, so the static transforms published before the node started arrive too, and once
        more volatile)."""
        tf_message = self._tf_message
        qos_tf = QoSProfile(depth=POSE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                            history=HistoryPolicy.KEEP_LAST)
        qos_static = QoSProfile(depth=TF_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                                durability=DurabilityPolicy.TRANSIENT_LOCAL, history=HistoryPolicy.KEEP_LAST)
        sub(tf_message, TF_TOPIC, lambda m, _s: self._put_frames(self.gate.on_tf(m)), qos_tf, drained=True)

        def on_static(m: Any, _seq: Any) -> None:
            self._put_frames(self.gate.on_tf(m, static=True))
        sub(tf_message, TF_STATIC_TOPIC, on_static, qos_static)
        # A transient-local subscription does not match a volatile publisher (a /tf_static publisher that is not
        # tf2_ros's): a volatile one does; a static transform received twice is simply set twice.
        sub(tf_message, TF_STATIC_TOPIC, on_static,
            QoSProfile(depth=TF_QOS_DEPTH, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST))

    def _endpoint_matched(self) -> None:
        """A subscriber matched (or left) an output or /diagnostics, or a publisher an input: publish the diagnostics
        now, so that a client can tell from ``subscribers[<output>]`` that this node's outputs reach it, and from
        ``publishers[<input topic>]`` that its inputs reach the node, before it sends a frame."""
        reporter = getattr(self, "reporter", None)
        if reporter is not None:
            reporter.publish()

    def _inputs_matched(self) -> None:
        """A publisher matched (or left) an input, on the inputs node's thread: the diagnostics are published by this
        node's executor (:meth:`_endpoint_matched`)."""
        try:
            self._matched_guard.trigger()
        except Exception:  # noqa: BLE001 - the node is being destroyed: nothing left to report
            pass

    def _diagnostics_info(self) -> dict[str, str]:
        """Diagnostics entries beyond the counters: the update in use, ``subscribers[<output>]``,
        ``publishers[<input topic>]`` (resolved name) and the last fused frame's ``last_pixels_transient``,
        ``last_pixels_occluded`` and ``last_surprise_mean``."""
        counts = {f"subscribers[{name}]": str(n) for name, n in self.outputs.subscriber_counts().items()}
        counts.update({f"publishers[{topic}]": str(n) for topic, n in self.intake.publisher_counts().items()})
        last = self.worker.last_frame
        frame = {"last_pixels_transient": str(last.transient), "last_pixels_occluded": str(last.occluded),
                 "last_surprise_mean": f"{last.surprise_mean:.6g}"}
        return {**self._sensor_info(), **counts, **frame, "answers_waiting": str(self.outputs.held_answers())}

    def _sensor_info(self) -> dict[str, str]:
        """Diagnostics entries naming the update in use."""
        text = describe_sensor_model(self.smap.sensor_model)
        return {"sensor_model": text.removeprefix("sensor model: ").removeprefix("sensor model "),
                "sensor_model_fingerprint": self.smap.sensor_fingerprint}

    def _confidence_published(self, cam: int) -> bool:
        return self.count_publishers(self._confidence_topics[cam]) > 0

    def _depth_published(self, cam: int) -> bool:
        return self.count_publishers(self._depth_topics[cam]) > 0

    def _put_frames(self, jobs: list[Any]) -> None:
        """Frames released by the gate go to the worker's queue (newest wins: a dropped one is counted and said)."""
        for job in jobs:
            dropped = self.queue.put_frame(job)
            if dropped is not None:
                self.stats.count("frames_dropped_busy")
                ns = self.p.cameras[job.camera_index].strip("/") or "/"
                self.stats.count(f"camera[{ns}].frames_dropped_busy")
                self.warn("worker", "busy", f"mapping slower than the input: oldest pending frame of camera {ns} "
                                            f"(stamp {dropped.stamp_ns * 1e-9:.9f} s) dropped (newest frames win)")

    def _poll_frames(self) -> None:
        """Timer: take the poses waiting in their queues, then release the frames whose wait ended."""
        self.intake.drain()
        self._put_frames(self.gate.poll())

    def _on_candidates(self, msg: Any) -> None:
        job = self.gate.on_candidates(msg)
        if isinstance(job, NanAnswer):
            self.stats.count(f"requests_nan[{job.reason}]")
            nan = np.full(len(job.positions), np.nan)
            self.outputs.publish_scores(job.header, job.positions, job.quats, nan, nan, nan)
            return
        dropped = self.queue.put_request(job)
        if dropped is not None:
            self.stats.count("requests_dropped_busy")
            self.warn("candidates", "request queue full", "oldest pending request answered with NaN scores")
            self.worker.finish_request(dropped, "request queue full")

    def _on_point_query_raw(self, raw: bytes) -> None:
        """A serialized point query. One declaring more than max_query_points is answered from its header alone:
        its data never becomes a Python object (deserializing 10^7 points held the interpreter for seconds, and
        the camera streams with it). Others are deserialized and go through the gate."""
        try:
            head: CloudHead | None = cloud_head(raw)
        except InputError:
            head = None
        if head is not None and head.points > self.p.max_query_points:
            self._on_point_query(SimpleNamespace(header=_header(head), width=head.width, height=head.height,
                                                 point_step=0))
            return
        try:
            msg = deserialize_message(raw, PointCloud2)
        except Exception:  # noqa: BLE001 - whatever the type support raises for malformed CDR
            if head is None:   # no request id to answer with
                self.stats.count("point_queries_received")
                self.stats.count("point_queries_unanswered[unreadable message]")
                self.warn("point_queries", "unreadable message", "not a PointCloud2: no answer (no header)")
                return
            msg = SimpleNamespace(header=_header(head), width=0, height=0, point_step=0, fields=[], data=b"")
        self._on_point_query(msg)

    def _on_point_query(self, msg: Any) -> None:
        job = self.gate.on_point_query(msg, self.smap.num_classes)
        if job.done:  # empty, unreadable or too large: answered at once
            if job.status is not None:
                self.stats.count(f"requests_nan[{job.status}]")
            self.outputs.publish_points(job)
            return
        dropped = self.queue.put_request(job)
        if dropped is not None:
            self.stats.count("requests_dropped_busy")
            self.warn("point_queries", "request queue full", "oldest pending request answered as unknown / NaN")
            self.worker.finish_request(dropped, "request queue full")

    def status(self) -> dict[str, Any]:
        """Counters and rates (also published as diagnostics)."""
        return self.reporter.status()

    def _on_save_map(self, request: Any, response: Any) -> Any:
        path = self.checkpoint_path
        if path is None:
            response.success, response.message = False, "checkpoint_path is empty: saving is disabled"
            return response
        try:
            dt = self.worker.save(path)
            response.success = True
            fused = self.smap.fused_sensor_model
            response.message = (f"saved {self.smap.model.num_gaussians}x{self.smap.num_classes} concentrations "
                                f"to {path} in {dt:.2f} s"
                                + (f" (fused with sensor model {fused[:12]})" if fused else ""))
        except (MapError, OSError) as exc:
            response.success, response.message = False, f"saving {path} failed: {exc}"
            self.get_logger().error(response.message)
        return response

    def _on_load_map(self, request: Any, response: Any) -> Any:
        """Replace the map by the checkpoint at checkpoint_path (fingerprint, size and value checks of resume)."""
        path = self.checkpoint_path
        if path is None:
            response.success, response.message = False, "checkpoint_path is empty: loading is disabled"
        elif not path.is_file():
            response.success, response.message = False, f"no checkpoint at {path}"
        else:
            try:
                response.success, response.message = True, self.worker.load_map(path)   # evidence re-synced in it
                self.stats.count("maps_loaded")
                self.get_logger().info(response.message)
            except MapError as exc:
                response.success, response.message = False, f"checkpoint refused, map unchanged: {exc}"
                self.get_logger().warning(response.message)
        return response

    def _on_reset_map(self, request: Any, response: Any) -> Any:
        self.worker.reset_map()   # the evidence exchange re-syncs under the same lock (worker.on_map_replaced)
        self.stats.count("resets")
        response.success = True
        response.message = f"all {self.smap.model.num_gaussians} Gaussians reset to the prior"
        self.get_logger().info(response.message)
        return response

    def _log_start(self) -> None:
        p, m = self.p, self.smap.model
        names = ", ".join(f"{i}:{n}" for i, n in enumerate(self.classes.names))
        frames = self.gate.frames
        if p.pose_source == "tf":
            in_names = [TF_TOPIC, TF_STATIC_TOPIC]
        else:
            in_names = [frames.topic(0, "pose")] if not p.pose_per_camera else []
        for i in range(len(p.cameras)):
            in_names += [frames.topic(i, k) for k in ("camera_info", "image", "segmentation", "confidence")]
            in_names += [frames.topic(i, "depth")] if p.depth_topic else []
            in_names += [frames.topic(i, "pose")] if p.pose_per_camera and p.pose_source == "topic" else []
        in_names += [INPUT_TOPICS["candidates"], INPUT_TOPICS["point_queries"]]
        ins = ", ".join(self.resolve_topic_name(t) for t in in_names)
        outs = ", ".join(self.resolve_topic_name(t) for t in self.outputs.topic_names())
        log = self.get_logger()
        log.info(f"model {self.model_path}: {m.num_gaussians} Gaussians, SH degree {m.sh_degree}, fingerprint "
                 f"{m.fingerprint[:12]}; {self.smap.num_classes} classes [{names}]; backend {p.backend}; "
                 f"{describe_sensor_model(self.smap.sensor_model)}; {self.resume_status}")
        sm = self.smap.sensor_model
        if sm is not None and p.publish_confidence and sm.confidence is None:
            log.info("~/confidence is not published: the sensor model holds no calibrated confidence map")
        log.info(describe_changing_world(self.smap, self.classes.names, p))
        if sm is not None and self.evidence.enabled:
            log.warning("evidence exchange with a sensor model: every node of the exchange must use the same "
                        "sensor model (evidence packets do not carry its fingerprint)")
        source = (f"poses from TF: {p.map_frame} <- each segmentation's frame_id (tf_buffer_s {p.tf_buffer_s:g} s)"
                  if p.pose_source == "tf" else f"pose_type {p.pose_type}, poses")
        log.info(f"inputs ({p.input_qos} QoS; candidates reliable; TF reliable): {ins}; {source} "
                 f"interpolated at the segmentation stamp (pose_buffer {p.pose_buffer:g} s, pose_wait "
                 f"{p.pose_wait:g} s); {len(p.cameras)} camera(s)"
                 + ("" if not p.camera_extrinsics else " with extrinsics")
                 + ("" if Similarity.from_params(p.splat_to_map).is_identity else
                    f"; splat_to_map scale {p.splat_to_map[0]:g}"))
        log.info(f"outputs: {outs}; services: {self.resolve_topic_name('~/save_map')}, "
                 f"{self.resolve_topic_name('~/reset_map')}, {self.resolve_topic_name('~/load_map')}; checkpoint "
                 + (f"{self.checkpoint_path} every {p.checkpoint_period:g} s" if self.checkpoint_path else "disabled")
                 + f"; sync slop {p.sync_slop * 1e3:g} ms")

    def close_inputs(self) -> None:
        """Destroy the inputs node and shut its context down (after its executor stopped; nothing when the
        inputs are subscribed on this node)."""
        if self.inputs is self:
            return
        import rclpy

        self.inputs.destroy_node()
        rclpy.try_shutdown(context=self.inputs_context)
        self.inputs = self

    def shutdown(self) -> bool:
        """Stop the worker (it finishes at most one frame or candidate slice) and write a final checkpoint.

        Returns False when the worker did not stop within WORKER_STOP_TIMEOUT_S (no checkpoint is then
        written, since the map may be mid-update).
        """
        stopped = self.worker.stop(WORKER_STOP_TIMEOUT_S)
        if not stopped:
            self.get_logger().error("worker did not stop in time: no final checkpoint")
            return False
        self.outputs.flush(1.0)  # answers published while stopping reach their clients
        waiting = self.gate.frames.waiting()   # the inputs thread has stopped: nothing adds to it now
        if waiting:   # every frame not answered is counted and said
            self.stats.count("frames_dropped_stopping", waiting)
            self.warn("segmentation", "node stopping", f"{waiting} frame(s) still waiting for a pose or confidence "
                                                       "not processed")
        self.worker.save_checkpoint("shutdown")
        return True
