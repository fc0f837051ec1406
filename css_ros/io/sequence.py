"""Samples lost before the node: gaps in a topic's publication sequence numbers (ROS-free).

DDS numbers every sample a writer publishes (1, 2, ...); rclpy hands that number to a subscription callback that
takes a ``MessageInfo`` (``publication_sequence_number``). While a topic has exactly one publisher, a number more
than one past the previous one means samples of it never reached the callback: lost in transport (best effort),
or overwritten in the subscription's queue (KEEP_LAST) before the executor took them. With several publishers the
numbers of their writers interleave and nothing can be said (rclpy does not say which writer sent a sample), so the
caller passes None and the watch starts over.
"""
from __future__ import annotations

from typing import Any, Mapping


def publication_seq(info: Mapping[str, Any] | None, publishers: int) -> int | None:
    """The sample's publication sequence number from an rclpy MessageInfo, when it identifies the sample in one
    publisher's stream (``publishers`` = 1); else None."""
    if publishers != 1 or not info:
        return None
    seq = info.get("publication_sequence_number")
    return int(seq) if isinstance(seq, int) and seq > 0 else None


class SequenceWatch:
    """The samples missing before each one of a stream of publication sequence numbers.

    :meth:`see` returns how many numbers were skipped since the previous sample (0 in step). None (unknown: several
    publishers, no number) or a number not above the previous one (a publisher restarted, or another one took over)
    starts over without counting anything.
    """

    def __init__(self) -> None:
        self.last: int | None = None
        #: samples missing in all
        self.lost = 0

    def see(self, seq: int | None) -> int:
        last, self.last = self.last, seq
        if seq is None or last is None or seq <= last:
            return 0
        missing = seq - last - 1
        self.lost += missing
        return missing
