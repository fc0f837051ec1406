"""css_node's input subscriptions that know what never reached them, and that drain their queue.

Every message is handed on with its publication sequence number (when its topic has exactly one matched publisher,
:mod:`css_ros.io.sequence`), so samples lost before the node (in transport, or overwritten in the subscription's
KEEP_LAST queue before the executor took them) are counted and warned per topic. A *drained* subscription (poses,
TF) takes, after each message, every message already waiting in its queue: rclpy's executor takes one message per
subscription and wait, so on a busy host a 200 Hz pose stream fell behind the segmentations and its samples were
overwritten in the queue before a frame's bracketing pose was read. :meth:`Intake.drain` does the same before the
gate decides that a frame waited long enough for its pose.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.qos import QoSProfile

from ..io.sequence import SequenceWatch, publication_seq
from .work import WarnLimiter

#: What a handler gets: the message and its publication sequence number (None: unknown).
Handler = Callable[[Any, "int | None"], None]
#: Most messages one drain takes from one subscription (its depth bounds it too): a stream faster than the node
#: cannot keep the executor in one callback.
DRAIN_LIMIT = 10_000


@dataclass
class _Stream:
    topic: str
    label: str                  # counter and warning topic (e.g. "pose", "segmentation")
    handler: Handler
    depth: int
    drained: bool
    sub: Any = None
    publishers: int = 0         # matched publishers (the matched event's current count)
    watch: SequenceWatch = field(default_factory=SequenceWatch)


class Intake:
    """Subscriptions of one node (the inputs node) with lost-message counting and optional draining.

    Args:
        node: the rclpy node the subscriptions belong to (its executor runs every callback: no lock here).
        count: ``count(key, n)`` adds to a node counter (``<label>_lost``: messages lost before the node).
        warn: the node's rate-limited warnings (``<label>: lost before the node``, message kept count).
    """

    def __init__(self, node: Any, count: Callable[..., None], warn: WarnLimiter,
                 on_matched: Callable[[], None] | None = None) -> None:
        self.node, self.count, self.warn = node, count, warn
        self.on_matched = on_matched
        self._streams: list[_Stream] = []

    def subscribe(self, msg_type: Any, topic: str, handler: Handler, qos: QoSProfile, label: str,
                  drained: bool = False, raw: bool = False) -> None:
        """Subscribe ``node`` to the resolved ``topic``; ``handler(msg, seq)`` runs for every message (``raw``: the
        serialized bytes, not deserialized)."""
        s = _Stream(topic, label, handler, int(qos.depth), drained)

        def matched(info: Any) -> None:
            s.publishers = int(info.current_count)
            if self.on_matched is not None:
                self.on_matched()

        s.sub = self.node.create_subscription(msg_type, topic, lambda msg, info: self._on_message(s, msg, info),
                                              qos, event_callbacks=SubscriptionEventCallbacks(matched=matched),
                                              raw=raw)
        self._streams.append(s)

    def _on_message(self, s: _Stream, msg: Any, info: Any) -> None:
        self._take(s, msg, info)
        if s.drained:
            self._drain(s)

    def _take(self, s: _Stream, msg: Any, info: Any) -> None:
        seq = publication_seq(info, s.publishers)
        missing = s.watch.see(seq)
        if missing:
            self.count(f"{s.label}_lost", missing)
            self.warn(s.label, "lost before the node", f"{missing} message(s) of {s.topic} never reached the node "
                      "(publication sequence gap: lost in transport, or overwritten in the subscription queue)",
                      dropped=False)
        s.handler(msg, seq)

    def _drain(self, s: _Stream) -> None:
        sub = s.sub
        for _ in range(min(DRAIN_LIMIT, max(1, s.depth))):
            with sub.handle:
                taken = sub.handle.take_message(sub.msg_type, sub.raw)
            if taken is None:
                return
            self._take(s, *taken)

    def publisher_counts(self) -> dict[str, int]:
        """Publishers this node's readers have matched, per subscribed topic (the resolved name, e.g.
        ``/robot/segmentation``; a topic subscribed twice, as /tf_static is, keeps its largest count)."""
        out: dict[str, int] = {}
        for s in self._streams:
            out[s.topic] = max(out.get(s.topic, 0), s.publishers)
        return out

    def drain(self) -> None:
        """Take every message waiting in the drained subscriptions now (before frames are released as waited)."""
        for s in self._streams:
            if s.drained:
                self._drain(s)
