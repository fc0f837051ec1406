"""css_node's live-viewer stream (``~/view/*``, layouts in :mod:`css_ros.io.view_stream`): the model once,
then only the Gaussians whose semantics changed visibly, bounded per message, from the worker thread."""
from __future__ import annotations

import threading
import time
from typing import Any

import numpy as np
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import PointCloud2
from std_msgs.msg import String
from std_srvs.srv import Trigger

from ..engine.field3d import gaussian_semantics
from ..engine.similarity import Similarity
from ..io.view_stream import MODEL_CHUNK, changed_gaussians, info_json, model_chunks, semantics_columns
from . import conversions as rc

UNSENT = np.int64(-1)
#: largest share of the worker's time the stream may take: the period stretches to cost / MAX_WORKER_SHARE
#: on very large maps (a full scan reads all N·C concentrations: ~60 ms at 1M × 16 on 2 cores)
MAX_WORKER_SHARE = 0.1


class ViewPublisher:
    """Publishes ``~/view/info``, ``~/view/model`` and ``~/view/semantics``; ``~/view/resync`` (Trigger) makes
    the next messages resend every Gaussian (a viewer that joins late calls it)."""

    def __init__(self, node: Node, smap: Any, classes: Any, period: float, max_changes: int,
                 min_evidence: float, splat_to_map: Similarity | None = None) -> None:
        self.period, self.max_changes, self.min_evidence = period, max_changes, min_evidence
        self.node, self.classes, self.splat_to_map = node, classes, splat_to_map
        self.clock = node.get_clock()
        info_qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE,
                              durability=DurabilityPolicy.TRANSIENT_LOCAL)
        self.pub_info = node.create_publisher(String, "~/view/info", info_qos)
        self.pub_model: Any = None
        self.pub_sem = node.create_publisher(PointCloud2, "~/view/semantics", 10)
        node.create_service(Trigger, "~/view/resync", self._on_resync)
        # compile (or load) now, for the kind of array the map hands out to readers (a device backend: read-only)
        sample = np.ones((1, 1))
        sample.flags.writeable = smap.concentrations_readonly.flags.writeable
        changed_gaussians(sample, 1e-3, 0.5, 255, np.zeros(1, np.int64))
        self._resync = threading.Event()
        self._rebind_lock = threading.Lock()
        self._rebind: Any = None   # a map on another splat (model swap), taken over by the worker's next tick
        self._version = -1
        self._next = 0.0
        self.last_cost_s = 0.0
        self.last_sent = 0
        self._start_stream(smap)

    def _start_stream(self, smap: Any) -> None:
        """(Re)start the stream on ``smap``: ``~/view/info``, then ``~/view/model`` from a new transient-local
        publisher whose history holds exactly this model's chunks (a late joiner never gets another model's),
        and every Gaussian counted unsent (the next ``~/view/semantics`` send them all)."""
        n = smap.model.num_gaussians
        latched = QoSProfile(depth=max(1, -(-n // MODEL_CHUNK)), history=HistoryPolicy.KEEP_LAST,
                             reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        if self.pub_model is not None:
            self.node.destroy_publisher(self.pub_model)
        self.pub_model = self.node.create_publisher(PointCloud2, "~/view/model", latched)
        self.smap = smap
        self.sent = np.full(n, UNSENT, dtype=np.int64)   # key last sent per Gaussian
        self.pending = 0
        model, classes = smap.model, self.classes
        header = rc.header_msg(self.clock.now().nanoseconds, "map")
        self.pub_info.publish(String(data=info_json(n, model.fingerprint, classes.names, classes.palette,
                                                    self.min_evidence, smap.prior)))
        if self.splat_to_map is not None and not self.splat_to_map.is_identity:
            model = self.splat_to_map.transform_model(model)   # the map frame, as every other 3D output
        for cols in model_chunks(model.means, model.covariances(), model.base_colors, model.opacities):
            self.pub_model.publish(rc.cloud_msg(header, cols))

    def rebind(self, smap: Any) -> None:
        """The node's map moved to another splat (model swap): the worker's next :meth:`tick` restarts the
        stream on ``smap`` (new info and model, then every Gaussian's semantics)."""
        with self._rebind_lock:
            self._rebind = smap

    def _on_resync(self, request: Any, response: Any) -> Any:
        self._resync.set()
        response.success, response.message = True, "the next ~/view/semantics messages resend every Gaussian"
        return response

    def tick(self, now: float, map_version: int, map_lock: threading.Lock) -> None:
        """Called by the worker between jobs: publish the changed Gaussians when due."""
        with self._rebind_lock:
            rebind, self._rebind = self._rebind, None
        if rebind is not None:
            self._start_stream(rebind)
            self._version, self._next = -1, 0.0   # the new map's semantics go out now
        resync = self._resync.is_set()
        if now < self._next or (map_version == self._version and not resync and self.pending == 0):
            return
        t0 = time.perf_counter()
        if resync:
            self._resync.clear()
            self.sent[:] = UNSENT
        with map_lock:
            # keys are updated for every changed Gaussian; those beyond max_changes are marked unsent again
            alpha = self.smap.concentrations_readonly   # read only: a device backend neither re-uploads it
            changed = changed_gaussians(alpha, self.smap.prior, self.min_evidence,
                                        self.smap.ignore_label, self.sent)
            later = changed[self.max_changes:]
            changed = changed[: self.max_changes]
            sem = gaussian_semantics(alpha[changed], self.smap.prior, self.min_evidence,
                                     self.smap.ignore_label)
        self.sent[later] = UNSENT
        self.pending = len(later)
        if len(changed):
            cols = semantics_columns(changed, sem.label, sem.expectation, sem.evidence)
            self.pub_sem.publish(rc.cloud_msg(rc.header_msg(self.clock.now().nanoseconds, "map"), cols))
        self._version = map_version
        self.last_sent = len(changed)
        self.last_cost_s = time.perf_counter() - t0
        self._next = now + max(self.period, self.last_cost_s / MAX_WORKER_SHARE)

    pending = 0
