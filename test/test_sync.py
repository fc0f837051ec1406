"""FrameSynchronizer: matching by stamp within the slop, drops, bounded queues."""
from __future__ import annotations

import pytest

from css_ros.io.sync import FrameSynchronizer

MS = 1_000_000


def test_exact_and_approximate_matches_any_arrival_order():
    sync = FrameSynchronizer(("segmentation", "pose", "image"), slop_ns=10 * MS)
    assert sync.push("pose", 100 * MS, "p0") == []
    assert sync.push("segmentation", 103 * MS, "s0") == []
    frames = sync.push("image", 95 * MS, "i0")
    assert len(frames) == 1
    f = frames[0]
    assert f.stamp_ns == 103 * MS  # the anchor's stamp
    assert f.items == {"segmentation": "s0", "pose": "p0", "image": "i0"}
    assert sync.pending() == {"segmentation": 0, "pose": 0, "image": 0}


def test_closest_candidate_is_taken():
    sync = FrameSynchronizer(("segmentation", "pose"), slop_ns=20 * MS)
    sync.push("pose", 90 * MS, "far")
    sync.push("pose", 99 * MS, "near")
    (f,) = sync.push("segmentation", 100 * MS, "s")
    assert f.items["pose"] == "near"


def test_unmatched_anchor_is_dropped_once_hopeless():
    sync = FrameSynchronizer(("segmentation", "pose"), slop_ns=5 * MS)
    sync.push("segmentation", 100 * MS, "s0")        # its pose never comes
    sync.push("segmentation", 200 * MS, "s1")
    frames = sync.push("pose", 200 * MS, "p1")        # pose moved past 100 + slop
    assert [f.items["segmentation"] for f in frames] == ["s1"]
    assert sync.counts["unmatched"] == 1


def test_stale_messages_are_dropped_and_counted():
    sync = FrameSynchronizer(("segmentation", "pose"), slop_ns=5 * MS)
    sync.push("pose", 100 * MS, "p")
    assert len(sync.push("segmentation", 100 * MS, "s")) == 1
    assert sync.push("segmentation", 50 * MS, "old") == []
    assert sync.counts["stale_segmentation"] == 1


def test_queues_are_bounded():
    sync = FrameSynchronizer(("segmentation", "pose"), slop_ns=MS, queue_size=5)
    for i in range(100):
        sync.push("segmentation", i * 100 * MS, i)
    assert sync.pending()["segmentation"] == 5
    assert sync.counts["overflow_segmentation"] == 95


def test_stream_of_frames_in_order():
    sync = FrameSynchronizer(("segmentation", "pose", "confidence"), slop_ns=2 * MS)
    out = []
    for i in range(20):
        t = i * 100 * MS
        out += sync.push("confidence", t + MS, i)
        out += sync.push("segmentation", t, i)
        out += sync.push("pose", t - MS, i)
    assert [f.items["segmentation"] for f in out] == list(range(20))
    assert all(f.items["pose"] == f.items["segmentation"] == f.items["confidence"] for f in out)


def test_bad_configuration():
    with pytest.raises(ValueError):
        FrameSynchronizer(("pose",), slop_ns=0, anchor="segmentation")
    with pytest.raises(KeyError):
        FrameSynchronizer(("segmentation",), slop_ns=0).push("pose", 0, None)
