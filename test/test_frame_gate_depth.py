"""Measured depth in the shared frame gate (css_ros/io/frame_gate.py) and its decoder (css_ros/io/frames.py): units
of 16UC1 and 32FC1, "no measurement" values, nearest-pixel resizing, and when a frame waits for its depth. No DDS
here: test_node_depth.py runs the node."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.io.frame_gate import FrameGate, GateConfig
from css_ros.io.frames import FrameRejected, RawDepth, decode_depth, depth_for
from css_ros.io.pose_history import PosePolicy
from test_frame_gate import H, T0, W, Recorder, camera_info, image, pose_message

WAIT = 0.5   # pose_wait [s]


def test_16uc1_is_millimetres_and_0_is_no_measurement():
    mm = np.array([[0, 1, 1500], [65535, 250, 0]], np.uint16)
    d = decode_depth(image(T0, mm, "16UC1")).metres()
    assert d.dtype == np.float32
    np.testing.assert_array_equal(np.isnan(d), mm == 0)
    np.testing.assert_allclose(d[mm > 0], mm[mm > 0].astype(np.float64) / 1000.0, rtol=1e-7)


def test_32fc1_is_metres_and_nan_inf_zero_negative_are_no_measurement():
    m = np.array([[np.nan, np.inf, -np.inf], [0.0, -1.5, 2.25]], np.float32)
    d = decode_depth(image(T0, m, "32FC1")).metres()
    np.testing.assert_array_equal(np.isnan(d), [[True, True, True], [True, True, False]])
    assert d[1, 2] == np.float32(2.25)


@pytest.mark.parametrize("encoding", ["mono8", "rgb8", "mono16"])
def test_other_encodings_are_refused_as_bad_depth(encoding):
    arr = np.zeros((2, 3, 3) if encoding == "rgb8" else (2, 3), np.uint16 if encoding == "mono16" else np.uint8)
    with pytest.raises(FrameRejected) as err:
        decode_depth(image(T0, arr, encoding))
    assert err.value.reason == "bad depth" and encoding in str(err.value)


def test_resizing_takes_the_nearest_pixel_and_never_mixes_two_surfaces():
    """A person 1.2 m away in front of a wall 3.4 m away, with holes; depth at twice the segmentation's resolution,
    at half of it and at 3/4 of it: every resized pixel holds the depth of a source pixel whose centre is nearest its
    centre (brute force; at an exact factor two source centres tie)."""
    rng = np.random.default_rng(0)
    src = np.full((36, 48), 3400, np.uint16)
    src[8:30, 13:27] = 1200
    src[rng.random(src.shape) < 0.05] = 0                      # holes
    metres = np.where(src > 0, src / 1000.0, np.nan)

    def nearest(n_src: int, n_out: int, i: int) -> np.ndarray:
        dist = np.abs((np.arange(n_src) + 0.5) / n_src - (i + 0.5) / n_out)
        return np.flatnonzero(dist <= dist.min() + 1e-12)

    for h, w in ((18, 24), (72, 96), (27, 36)):
        out = depth_for(RawDepth(src, 1000.0), (h, w), 1.0)
        assert out.shape == (h, w) and out.dtype == np.float32
        for y in range(h):
            for x in range(w):
                cands = metres[np.ix_(nearest(36, h, y), nearest(48, w, x))].ravel()
                assert np.any(np.isclose(cands, out[y, x], rtol=1e-6) | (np.isnan(cands) & np.isnan(out[y, x]))), \
                    (h, w, y, x, out[y, x], cands)
        np.testing.assert_allclose(np.unique(out[np.isfinite(out)]), [1.2, 3.4], rtol=1e-6)


def test_another_aspect_ratio_is_refused():
    with pytest.raises(FrameRejected) as err:
        depth_for(RawDepth(np.ones((36, 48), np.uint16), 1000.0), (36, 36), 1.0)
    assert err.value.reason == "depth size mismatch"


class DepthGate:
    """A one-camera gate with ``depth_topic`` and a switch for whether the depth topic has a publisher."""

    def __init__(self, cameras: tuple[str, ...] = ("",), depth_topic: str = "depth") -> None:
        self.rec = Recorder()
        self.published = True
        self.gate = FrameGate(GateConfig(cameras=cameras, extrinsics=(None,) * len(cameras), depth_topic=depth_topic,
                                         pose_policy=PosePolicy(wait=WAIT)),
                              self.rec.warn, self.rec.count, lambda cam: False, depth_expected=lambda cam: self.published)
        for c in range(len(cameras)):
            self.gate.on_camera_info(c, camera_info())

    def posed(self, stamp: int, t: float) -> list:
        """Poses 10 ms either side of ``stamp``: its pose is the interpolation, at once."""
        out = []
        for s in (stamp - 10**7, stamp + 10**7):
            out += self.gate.on_pose(pose_message("pose_stamped", s, np.zeros(3), np.array([0, 0, 0, 1.0])), t)
        return out

    def seg(self, stamp: int, t: float) -> list:
        return self.gate.on_segmentation(0, image(stamp, np.ones((H, W), np.uint8), "mono8"), t)

    def depth(self, stamp: int, t: float, array: np.ndarray, encoding: str = "16UC1") -> list:
        return self.gate.on_depth(0, image(stamp, array, encoding), t)


def mm(value: int, shape: tuple[int, int] = (H, W)) -> np.ndarray:
    return np.full(shape, value, np.uint16)


def test_depth_before_the_segmentation_is_taken_at_once():
    g = DepthGate()
    g.posed(T0, 0.0)
    assert g.depth(T0 + 3 * 10**6, 0.01, mm(2000)) == []        # 3 ms off the stamp: within sync_slop
    frames = g.seg(T0, 0.02)
    assert len(frames) == 1 and np.all(frames[0].depth == np.float32(2.0))


def test_a_frame_waits_for_its_depth_while_the_topic_has_a_publisher():
    g = DepthGate()
    g.posed(T0, 0.0)
    assert g.seg(T0, 0.01) == []                                  # the depth is late: the frame waits
    assert g.gate.poll(0.01 + WAIT * 0.9) == []
    frames = g.depth(T0, 0.01 + WAIT * 0.95, mm(1500, (2 * H, 2 * W)))   # at twice the resolution
    assert len(frames) == 1 and frames[0].depth.shape == (H, W) and np.all(frames[0].depth == np.float32(1.5))
    assert not g.rec.warnings


def test_a_depth_at_the_stamp_wins_over_an_earlier_one_that_came_first():
    """A 30 Hz depth camera: the depth 33 ms before the frame has arrived, the one at its stamp comes after the
    segmentation: the frame waits for it and takes it; a depth after the stamp ends the wait too."""
    g = DepthGate()
    g.posed(T0, 0.0)
    g.depth(T0 - 33 * 10**6, 0.0, mm(3000))
    assert g.seg(T0, 0.01) == []
    frames = g.depth(T0, 0.05, mm(1000))
    assert len(frames) == 1 and np.all(frames[0].depth == np.float32(1.0))
    g.posed(T0 + 10**8, 0.1)
    g.depth(T0 + 10**8 - 20 * 10**6, 0.1, mm(2000))               # 20 ms before: within sync_slop
    assert g.seg(T0 + 10**8, 0.11) == []
    frames = g.depth(T0 + 10**8 + 40 * 10**6, 0.15, mm(4000))     # 40 ms after: ends the wait, the earlier is nearer
    assert len(frames) == 1 and np.all(frames[0].depth == np.float32(2.0))
    assert not g.rec.warnings


def test_without_its_depth_by_pose_wait_a_frame_is_fused_without_depth_and_warned():
    g = DepthGate()
    g.posed(T0, 0.0)
    g.depth(T0 - 2 * 10**8, 0.0, mm(1000))                        # 200 ms before: another frame's depth
    assert g.seg(T0, 0.01) == [] and g.gate.poll(0.01 + WAIT * 0.99) == []
    frames = g.gate.poll(0.01 + WAIT)
    assert len(frames) == 1 and frames[0].depth is None
    assert g.rec.warnings == {"depth: no matching depth": 1}


def test_without_a_depth_publisher_a_frame_does_not_wait():
    g = DepthGate()
    g.published = False
    g.posed(T0, 0.0)
    frames = g.seg(T0, 0.01)
    assert len(frames) == 1 and frames[0].depth is None
    assert g.rec.warnings == {"depth: no matching depth": 1}


def test_a_bad_depth_is_warned_and_its_frame_goes_on_without_depth_at_once():
    g = DepthGate()
    g.posed(T0, 0.0)
    assert g.depth(T0, 0.0, np.zeros((H, W), np.uint8), "mono8") == []
    frames = g.seg(T0, 0.01)                                       # no wait for another depth
    assert len(frames) == 1 and frames[0].depth is None
    assert g.rec.warnings == {"depth: bad depth": 1}
    g.posed(T0 + 10**8, 0.1)
    g.depth(T0 + 10**8, 0.1, mm(0))                                # all holes: a depth without any measurement
    frames = g.seg(T0 + 10**8, 0.11)
    assert len(frames) == 1 and np.all(np.isnan(frames[0].depth))


def test_depth_of_another_aspect_ratio_is_warned_and_the_frame_fused_without():
    g = DepthGate()
    g.posed(T0, 0.0)
    g.depth(T0, 0.0, mm(1000, (H, H)))
    frames = g.seg(T0, 0.01)
    assert len(frames) == 1 and frames[0].depth is None
    assert g.rec.warnings == {"depth: depth size mismatch": 1}


def test_each_camera_reads_the_depth_topic_under_its_namespace():
    g = DepthGate(cameras=("front", "left"), depth_topic="aligned_depth_to_color/image_raw")
    assert [g.gate.topic(i, "depth") for i in range(2)] == ["front/aligned_depth_to_color/image_raw",
                                                            "left/aligned_depth_to_color/image_raw"]
    assert DepthGate(depth_topic="/camera/depth").gate.topic(0, "depth") == "/camera/depth"
    assert DepthGate(cameras=("front",), depth_topic="depth").gate.topic(0, "depth") == "front/depth"
