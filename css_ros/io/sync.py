"""Stamp-based frame synchroniser shared by css_node and css_replay (message_filters is not needed)."""
from __future__ import annotations

from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any, Iterable


@dataclass
class SyncedFrame:
    """One synchronised frame: ``items[kind]`` is the payload pushed for that kind.

    ``stamp_ns`` is the anchor message's stamp (integer nanoseconds); every output of the frame
    carries it.
    """

    stamp_ns: int
    items: dict[str, Any] = field(default_factory=dict)


class FrameSynchronizer:
    """Approximate-time synchroniser keyed on an anchor stream.

    A frame is emitted as soon as, for the oldest pending anchor message (the segmentation by
    default), every other kind has a pending message whose stamp lies within ``slop_ns`` of it (the
    closest one is taken). Messages of each kind are assumed to arrive in stamp order per kind; a
    message older than the last emitted frame is dropped as ``stale_<kind>``. An anchor that can no
    longer be matched (another kind has already moved past ``anchor + slop`` without a match) is
    dropped as ``unmatched``. Each kind keeps at most ``queue_size`` pending messages (oldest
    dropped, counted as ``overflow_<kind>``), so memory is bounded whatever arrives.

    Args:
        kinds: the kinds a frame needs (the anchor included), e.g. ("segmentation", "pose").
        slop_ns: maximum stamp difference to the anchor [ns].
        anchor: the kind whose stamp defines the frame.
        queue_size: pending messages kept per kind.
    """

    def __init__(self, kinds: Iterable[str], slop_ns: int, anchor: str = "segmentation",
                 queue_size: int = 30) -> None:
        self.kinds = tuple(dict.fromkeys(kinds))
        if anchor not in self.kinds:
            raise ValueError(f"anchor '{anchor}' must be one of the kinds {self.kinds}")
        if slop_ns < 0 or queue_size < 1:
            raise ValueError("slop_ns must be >= 0 and queue_size >= 1")
        self.anchor = anchor
        self.slop_ns = int(slop_ns)
        self.queue_size = int(queue_size)
        self._queues: dict[str, deque[tuple[int, Any]]] = {k: deque() for k in self.kinds}
        self._last_emitted_ns: int | None = None
        self.counts: Counter[str] = Counter()

    def pending(self) -> dict[str, int]:
        """Number of pending messages per kind."""
        return {k: len(q) for k, q in self._queues.items()}

    def push(self, kind: str, stamp_ns: int, payload: Any) -> list[SyncedFrame]:
        """Add one message; return the frames it completes (oldest first, usually zero or one)."""
        if kind not in self._queues:
            raise KeyError(f"unknown kind '{kind}' (expected one of {self.kinds})")
        stamp_ns = int(stamp_ns)
        if self._last_emitted_ns is not None and stamp_ns <= self._last_emitted_ns - self.slop_ns:
            self.counts[f"stale_{kind}"] += 1
            return []
        queue = self._queues[kind]
        if queue and stamp_ns < queue[-1][0]:
            # Out of order within one stream: keep the queue sorted.
            self.counts[f"reordered_{kind}"] += 1
            items = sorted([*queue, (stamp_ns, payload)], key=lambda e: e[0])
            queue.clear()
            queue.extend(items)
        else:
            queue.append((stamp_ns, payload))
        if len(queue) > self.queue_size:
            queue.popleft()
            self.counts[f"overflow_{kind}"] += 1
        return self._match()

    def _match(self) -> list[SyncedFrame]:
        frames: list[SyncedFrame] = []
        anchors = self._queues[self.anchor]
        while anchors:
            t_anchor, anchor_payload = anchors[0]
            picked: dict[str, tuple[int, Any]] = {}
            hopeless = False
            for kind in self.kinds:
                if kind == self.anchor:
                    continue
                best = None
                for stamp, payload in self._queues[kind]:
                    d = abs(stamp - t_anchor)
                    if d <= self.slop_ns and (best is None or d < abs(best[0] - t_anchor)):
                        best = (stamp, payload)
                if best is not None:
                    picked[kind] = best
                    continue
                q = self._queues[kind]
                if q and q[-1][0] > t_anchor + self.slop_ns:
                    hopeless = True
                break
            if len(picked) == len(self.kinds) - 1:
                anchors.popleft()
                frame = SyncedFrame(t_anchor, {self.anchor: anchor_payload})
                for kind, (stamp, payload) in picked.items():
                    frame.items[kind] = payload
                    q = self._queues[kind]
                    while q and q[0][0] <= stamp:
                        q.popleft()
                self._last_emitted_ns = t_anchor
                self.counts["frames"] += 1
                frames.append(frame)
            elif hopeless:
                anchors.popleft()
                self.counts["unmatched"] += 1
            else:
                break
        return frames
