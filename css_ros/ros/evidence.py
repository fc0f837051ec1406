"""css_node's evidence exchange with other nodes of the same splat (several robots, one map).

Publishes this node's own evidence on ``~/evidence`` and adds the evidence of the nodes named in the
``evidence_in`` parameter; the packet format and the exactly-once rules are in :mod:`css_ros.io.evidence`.
Messages are ``std_msgs/UInt8MultiArray`` (data = one packet), reliable QoS, bounded depth. Every map change
happens under the worker's map lock, so frames, checkpoints and received evidence never interleave.
"""
from __future__ import annotations

import os
import socket
import time
from typing import Any, Callable

import numpy as np
from rclpy.node import Node
from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.serialization import deserialize_message
from std_msgs.msg import UInt8MultiArray

from ..engine.map_file import MAX_SOURCES
from ..errors import InputError
from ..io.evidence import (FLAG_RESUMED, FLOOD_REASON, HEADER_SIZE, NOT_NEEDED_REASON, ORIGIN_BYTES, RETURN,
                           RETURN_WINDOW_S, EvidenceLedger, EvidenceOutbox, EvidenceRecovery, OriginBuckets,
                           decode_packet, own_evidence, received_sources)
from .params import NodeParams
from .work import WarnLimiter

#: Depth of the evidence publisher and subscriptions (messages; each at most evidence_max_rows rows when valid:
#: DDS itself delivers messages of any size, see docs/maps.md "Bad input").
EVIDENCE_QUEUE_DEPTH = 100
TOPIC = "evidence_in"
#: Bytes a serialized UInt8MultiArray adds to its packet (CDR header, layout, lengths), with room for a layout that
#: names a few dimensions; a larger message is refused before it is deserialized.
CDR_SLACK = 4096
OVERSIZE_REASON = "message larger than any valid packet"


def default_origin() -> str:
    """Host name and process id, cut to the 32 ASCII characters an origin id may have."""
    host = socket.gethostname().encode("ascii", "replace").decode("ascii")
    tail = f"-{os.getpid()}"
    return host[: ORIGIN_BYTES - len(tail)] + tail


class EvidenceLink:
    """Publisher, subscriptions and bookkeeping of the evidence exchange of one node.

    Args:
        node: the css_node.
        p: its parameters.
        worker: the MapWorker (its ``smap``, ``map_lock``, ``policy`` and ``map_version``).
        warn: rate-limited warnings, counted per (topic, reason) in diagnostics.
        count: the node's counter function.
    """

    def __init__(self, node: Node, p: NodeParams, worker: Any, warn: WarnLimiter,
                 count: Callable[..., None]) -> None:
        self.p, self.worker, self.warn, self.count = p, worker, warn, count
        self.logger = node.get_logger()
        # a resumed node keeps the origin of its checkpoint (also the default one): its peers know it by that id
        self.origin = p.evidence_origin or worker.smap.evidence_origin or default_origin()
        self.allowed = {o.strip() for o in p.evidence_allowed_origins.split(",") if o.strip()}
        checkpoint_epoch = int(worker.smap.evidence_epoch)   # the epoch the checkpoint's own evidence was of
        self.rebind()
        if p.resume and self.outbox is not None:
            self._start_recovery(checkpoint_epoch)
        worker.on_map_replaced = self._map_replaced_locked
        # token buckets per origin; those of origins holding a ledger slot or allowed by name are never evicted
        self._buckets = OriginBuckets(p.evidence_max_rate, 4 * p.evidence_max_sources,
                                      lambda o: o in self.ledger.sources or o in self.allowed)
        self._counted: dict[str, int] = {}   # origin -> evidence_packets_from[origin] as counted in diagnostics
        self.topics = [t.strip() for t in p.evidence_in.split(",") if t.strip()]
        qos = QoSProfile(depth=EVIDENCE_QUEUE_DEPTH, reliability=ReliabilityPolicy.RELIABLE,
                         history=HistoryPolicy.KEEP_LAST)
        self.pub = node.create_publisher(UInt8MultiArray, "~/evidence", qos) if p.publish_evidence else None
        for topic in self.topics:   # raw: the size is checked before a message is deserialized
            node.create_subscription(UInt8MultiArray, topic, self._on_raw, qos, raw=True)
        if self.pub is not None:
            node.create_timer(p.evidence_period, self.publish)
        with worker.map_lock:
            self._update_sources()

    def rebind(self) -> None:
        """(Re)start the bookkeeping for the worker's current map (at start)."""
        with self.worker.map_lock:
            self.rebind_locked()

    def rebind_locked(self) -> None:
        """Under the map lock, in the same critical section that replaced the worker's map (a model swap): the
        ledger and outbox are sized for the new splat before any timer can see the new map with the old ones."""
        smap = self.worker.smap
        fp, n, c = smap.model.fingerprint, smap.model.num_gaussians, smap.num_classes
        self._adopt_locked()
        self.outbox = EvidenceOutbox(self.origin, fp, n, c, smap.prior, self.p.evidence_max_rows) \
            if self.p.publish_evidence else None   # 8 N C bytes: only when publishing
        self._next_snapshot = 0.0
        self.recovery: EvidenceRecovery | None = None
        self._own_base: np.ndarray | None = None
        self._frames_base, self._adopted = 0, False
        if self.outbox is not None:
            smap.evidence_epoch = self.outbox.epoch

    def _start_recovery(self, checkpoint_epoch: int) -> None:
        """A resumed start: until the return window (from the first peer packet applied) ends, flag the snapshots
        "resumed" and take back from a peer's return the own evidence of the previous epoch that the checkpoint
        lacks (see :class:`~css_ros.io.evidence.EvidenceRecovery`).
        ``_own_base`` / ``_frames_base``: the own evidence and frames the map holds of before this start."""
        assert self.outbox is not None
        with self.worker.map_lock:
            smap = self.worker.smap
            self._own_base = self.outbox.own(smap.concentrations, self.ledger.received_total()).copy()
            self._frames_base = int(smap.frames_observed)
            self.recovery = EvidenceRecovery(
                self.origin, smap.model.fingerprint, smap.model.num_gaussians, smap.num_classes, smap.prior,
                checkpoint_epoch, self._frames_base, self.outbox.epoch, float(self.p.max_image_pixels),
                self.p.evidence_max_sources, time.monotonic(),
                window=max(RETURN_WINDOW_S, 3.0 * self.p.evidence_snapshot_period),
                max_frame_rate=self.p.evidence_max_frame_rate)
        self.logger.info(f"resumed: asking peers for own evidence after epoch {checkpoint_epoch} "
                         f"({self._frames_base} frames held)")

    def _adopt_return_locked(self, epoch: int, frames: int, evidence: np.ndarray) -> None:
        """Under the map lock: the returned evidence of the previous epoch replaces the own part this start began
        with (own evidence fused since the start is kept); the next publish re-states it by a snapshot."""
        smap = self.worker.smap
        alpha = smap.concentrations
        assert self._own_base is not None
        # α = α_0 + own + received, recomputed (α - old + new would lose small received evidence to the rounding
        # of large own evidence, and the checkpoint would not load)
        received = self.ledger.received_total()
        own = np.maximum(own_evidence(alpha, smap.prior, received) - self._own_base, 0.0) + evidence
        alpha[...] = smap.prior + own + received
        smap.frames_observed += frames - self._frames_base
        self._own_base, self._frames_base = evidence, frames
        self._next_snapshot = 0.0
        self._adopted = True

    def _adopt_locked(self) -> None:
        """A ledger for the map's received sources (a resumed or loaded map brings them, see
        :func:`~css_ros.io.evidence.received_sources`: the rest of its evidence is this node's own)."""
        smap = self.worker.smap
        self.ledger = EvidenceLedger(self.origin, smap.model.fingerprint, smap.model.num_gaussians, smap.num_classes,
                                     smap.prior, self.p.evidence_max_sources,
                                     max_frame_evidence=float(self.p.max_image_pixels),
                                     max_frame_rate=self.p.evidence_max_frame_rate,
                                     received=received_sources(smap, self.origin), max_rows=self.p.evidence_max_rows)
        smap.evidence_origin, smap.received = self.origin, self.ledger.sources
        # the map's sources that no received source stands for: evidence it holds as its own (e.g. a merged map's)
        self._base_sources = set(smap.sources) - set(self.ledger.sources)
        self._listed: tuple[bool, frozenset[str]] | None = None

    @property
    def enabled(self) -> bool:
        return self.pub is not None or bool(self.topics)

    # ------------------------------------------------------------------ sources
    def _update_sources(self) -> None:
        """Under the map lock. The map's ``sources``: this node's origin (when it publishes), the received sources
        whose evidence the map holds now, and the sources the map held as its own when it was loaded or resumed; at
        most MAX_SOURCES (the file bound; the last kind is cut first). A source whose evidence went to 0 (a peer's
        reset, a junk origin's empty snapshot) is not listed. Its diagnostics key goes with its ledger slot."""
        holders = frozenset(self.ledger.holders())
        key = (self.pub is not None, holders)
        if key != self._listed:
            self._listed = key
            listed = ({self.origin} if self.pub is not None else set()) | holders
            rest = sorted(self._base_sources - listed)
            self.worker.smap.sources = sorted(listed | set(rest[:max(0, MAX_SOURCES - len(listed))]))
        for origin in [o for o in self._counted if o not in self.ledger.sources]:
            self.count(f"evidence_packets_from[{origin}]", -self._counted.pop(origin))   # a counter at 0 is dropped
            self.count("evidence_sources_released")

    def _map_replaced_locked(self) -> None:
        """Under the map lock, right after a reset or a load (MapWorker.on_map_replaced). Reset: the received
        evidence is gone, every source re-syncs by its next snapshot. Load: the file's received sources are adopted
        (the rest of its evidence is own). Either way the own evidence is re-stated at once by a snapshot of a new
        epoch, which replaces what the peers held of this node."""
        smap = self.worker.smap
        if smap.received is self.ledger.sources:      # a reset (a load brings the file's sources)
            self.ledger.forget()
            self._base_sources, self._listed = set(), None   # the map holds no evidence of any source now
        else:
            self._adopt_locked()
        if self.outbox is not None:
            self.outbox.reset()
            smap.evidence_epoch = self.outbox.epoch
        self._next_snapshot = 0.0
        self.recovery = None   # a reset / load is meant: no returned evidence comes back over it
        self._update_sources()

    # ------------------------------------------------------------------ out
    def publish(self) -> None:
        """Timer: deltas of the own evidence since the last call, or a snapshot when one is due."""
        now = time.monotonic()
        if self.outbox is None:
            return
        with self.worker.map_lock:
            alpha = self.worker.smap.concentrations
            frames = self.worker.smap.frames_observed
            received = self.ledger.received_total()
            rec = self.recovery
            if rec is not None and not rec.open(now):
                self.recovery = rec = None
                self._own_base = None
            flags = FLAG_RESUMED if rec is not None and not self._adopted else 0
            if now >= self._next_snapshot:
                packets = self.outbox.snapshot(self.outbox.own(alpha, received), frames, flags)
                self._next_snapshot = now + self.p.evidence_snapshot_period
                self.count("evidence_snapshots_sent")
            else:
                packets = self.outbox.deltas(alpha, received, frames)
        for data in packets:
            msg = UInt8MultiArray()
            msg.data = data
            self.pub.publish(msg)
        self.count("evidence_packets_sent", len(packets))

    # ------------------------------------------------------------------ in
    def max_message_bytes(self) -> int:
        """The largest serialized message a valid packet makes (evidence_max_rows rows of the map's classes)."""
        c = self.worker.smap.num_classes
        return HEADER_SIZE + self.p.evidence_max_rows * (4 + 8 * c) + ORIGIN_BYTES + CDR_SLACK

    def _on_raw(self, raw: bytes) -> None:
        """A serialized message: refused unread when larger than any valid packet, else decoded."""
        if len(raw) > self.max_message_bytes():
            self._refuse(OVERSIZE_REASON)
            return
        try:
            msg = deserialize_message(raw, UInt8MultiArray)
        except Exception:   # noqa: BLE001 - whatever the type support raises for malformed CDR
            self._refuse("not a UInt8MultiArray message")
            return
        del raw
        self._on_packet(msg)

    def _on_packet(self, msg: Any) -> None:
        try:
            pkt = decode_packet(bytes(msg.data), self.p.evidence_max_rows)
        except InputError as exc:
            self._refuse(str(exc))
            return
        if self.allowed and pkt.origin not in self.allowed:
            self._refuse("origin not in evidence_allowed_origins")
            return
        if not self._buckets.allow(pkt.origin, time.monotonic()):
            self._refuse(FLOOD_REASON, pkt.origin)
            return
        if pkt.kind == RETURN:
            self._on_return(pkt)
            return
        returns: list[bytes] = []
        with self.worker.map_lock:
            reason = self.ledger.apply(pkt, self.worker.smap.concentrations)
            if reason is None:
                self.worker.policy.changed()
                self.worker.map_version += 1
                rec = self.recovery
                if rec is not None:
                    rec.heard(time.monotonic())   # the return window runs from the first peer packet applied
                self.count(f"evidence_packets_from[{pkt.origin}]")   # diagnostics name the ledger's sources
                self._counted[pkt.origin] = self._counted.get(pkt.origin, 0) + 1
            self._update_sources()
            for subject in self.ledger.returns_due:
                if self.pub is not None:
                    returns += self.ledger.return_packets(subject)
            self.ledger.returns_due.clear()
            withheld = list(self.ledger.returns_withheld)
            self.ledger.returns_withheld.clear()
        if returns and self.pub is not None:
            for data in returns:
                msg = UInt8MultiArray()
                msg.data = data
                self.pub.publish(msg)
            self.count("evidence_returns_sent")
            self.count("evidence_return_bytes_sent", sum(len(d) for d in returns))
            self.logger.info(f"sent {len(returns)} return packet(s) of a restarted peer's previous evidence")
        for origin, why, size in withheld:   # the sender is named in the (rate-limited) warning
            self.count(f"evidence_returns_withheld[{why}]")
            self.count("evidence_return_bytes_withheld", size)
            self.warn(TOPIC, f"return withheld: {why}", f"a return of {size} bytes to {origin!r} not sent",
                      dropped=False)
        if reason is not None:
            self._refuse(reason, pkt.origin)
            return
        self.count("evidence_packets_applied")

    def _on_return(self, pkt: Any) -> None:
        """A peer gives a restarted node back its evidence of the previous epoch (others' returns are ignored)."""
        if pkt.subject != self.origin:
            return
        if self.recovery is None:
            self._refuse("return while not recovering from a restart", pkt.origin)
            return
        with self.worker.map_lock:
            reason, got = self.recovery.offer(pkt, time.monotonic())
            if got is not None:
                self._adopt_return_locked(*got)
                self.worker.policy.changed()
                self.worker.map_version += 1
        if reason == NOT_NEEDED_REASON:   # a peer answered: the checkpoint holds as much (stop asking)
            self._adopted = True
            self.count("evidence_returns_not_needed")
        elif reason is not None:
            self._refuse(reason, pkt.origin)
        elif got is not None:
            self.count("evidence_returns_adopted")   # the sender is logged (no diagnostics key per origin)
            self.logger.info(f"took back the own evidence of epoch {got[0]} ({got[1]} frames) from {pkt.origin!r}")

    def _refuse(self, reason: str, origin: str = "") -> None:
        self.count(f"evidence_refused[{reason}]")
        self.warn(TOPIC, reason, f"packet from {origin!r} refused, map unchanged" if origin else "packet refused")
