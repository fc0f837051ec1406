"""Messages lost before the node, from publication sequence numbers (css_ros/io/sequence.py)."""
from __future__ import annotations

import numpy as np

from css_ros.io.sequence import SequenceWatch, publication_seq


def test_publication_seq_only_identifies_a_sample_of_one_publisher():
    info = {"publication_sequence_number": 17, "source_timestamp": 1}
    assert publication_seq(info, 1) == 17
    assert publication_seq(info, 0) is None and publication_seq(info, 2) is None   # unknown writers
    assert publication_seq({"publication_sequence_number": None}, 1) is None
    assert publication_seq({"publication_sequence_number": 0}, 1) is None
    assert publication_seq(None, 1) is None


def test_the_watch_counts_exactly_the_numbers_skipped():
    """A stream 1..500 of one writer with a random subset dropped: the watch counts the dropped ones after the first
    received (the ones before it cannot be known), per sample and in all; a restart of the writer (numbers from 1
    again) or an unknown number starts over without counting."""
    rng = np.random.default_rng(0)
    kept = sorted(set(range(1, 501)) - set(rng.choice(np.arange(1, 501), 120, replace=False).tolist()))
    watch = SequenceWatch()
    missing = [watch.see(s) for s in kept]
    assert missing[0] == 0
    assert missing[1:] == [b - a - 1 for a, b in zip(kept, kept[1:])]
    assert watch.lost == kept[-1] - kept[0] + 1 - len(kept)
    lost = watch.lost
    assert [watch.see(s) for s in (1, 2, 5)] == [0, 0, 2]          # the writer restarted
    assert [watch.see(s) for s in (None, 9, 10)] == [0, 0, 0]      # unknown, then a new start
    assert watch.lost == lost + 2


def test_cloud_head_reads_a_serialized_cloud_without_deserializing_it():
    """cloud_head gives the header and size rclpy's own serialization wrote, for frame ids of every length modulo 4
    (the alignment after the string), and refuses what is not CDR or is cut short."""
    import pytest

    pytest.importorskip("rclpy")
    from rclpy.serialization import serialize_message
    from sensor_msgs.msg import PointCloud2

    from css_ros.errors import InputError
    from css_ros.io.point_queries import cloud_head
    from css_ros.ros.conversions import header_msg

    for frame_id in ("", "m", "ma", "map", "mapx", "robot_1/map"):
        msg = PointCloud2(header=header_msg(1_700_000_000_123_456_789, frame_id), height=3, width=4_000_000_000)
        head = cloud_head(serialize_message(msg))
        assert (head.sec, head.nanosec, head.frame_id) == (1_700_000_000, 123_456_789, frame_id)
        assert (head.height, head.width, head.points) == (3, 4_000_000_000, 12_000_000_000)
    raw = serialize_message(PointCloud2(header=header_msg(5, "map"), height=1, width=2))
    for bad in (b"", b"\x01\x01\x00\x00", raw[:14], b"\x00\x01" + b"\xff" * 30):
        with pytest.raises(InputError):
            cloud_head(bad)
