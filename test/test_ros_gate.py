"""css_node's input gate without rclpy: stamps, clock reset, sizes, camera_info, sync, candidate requests."""
from __future__ import annotations

import warnings
from types import SimpleNamespace as NS

import numpy as np
import pytest

from css_ros.io.frames import DEFAULT_MAX_IMAGE_PIXELS
from css_ros.io.messages import array_to_image_fields, ns_to_sec_nanosec
from css_ros.ros.gate import STAMP_RESET_COUNT, InputGate, NanAnswer
from css_ros.ros.params import NodeParams
from css_ros.ros.work import CandidateJob, FrameJob, WarnLimiter

W, H = 8, 6
K = [20.0, 0, 3.5, 0, 20.0, 2.5, 0, 0, 1]
S = 1_000_000_000


def header(stamp_ns: int, frame_id: str = "cam") -> NS:
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return NS(stamp=NS(sec=sec, nanosec=nanosec), frame_id=frame_id)


def image(stamp_ns: int, array: np.ndarray, encoding: str) -> NS:
    f = array_to_image_fields(array, encoding)
    f["data"] = f["data"].tobytes()
    return NS(header=header(stamp_ns), **f)


def labels(stamp_ns: int, w: int = W, h: int = H) -> NS:
    return image(stamp_ns, np.ones((h, w), np.uint8), "mono8")


def pose(stamp_ns: int, position=(0.0, 0.0, 0.0), quat=(0.0, 0.0, 0.0, 1.0), frame_id: str = "map") -> NS:
    return NS(header=header(stamp_ns, frame_id), pose=NS(position=NS(x=position[0], y=position[1], z=position[2]),
                                                         orientation=NS(x=quat[0], y=quat[1], z=quat[2], w=quat[3])))


def camera_info(w: int = W, h: int = H, k=K) -> NS:
    return NS(header=header(0), width=w, height=h, k=list(k))


class Harness:
    def __init__(self, now_ns: int = 0, confidence: bool = False, **params) -> None:
        self.lines: list[str] = []
        self.logged: list[str] = []
        self.counts: dict[str, int] = {}
        self.warn = WarnLimiter(self.lines.append, params.get("warn_period", 0.0))
        self.now = now_ns
        self.confidence = confidence
        self.mono = 0.0   # the clock frames wait on [s]
        self.gate = InputGate(NodeParams(**params), self.warn, self.count, lambda: self.now, lambda: self.confidence,
                              self.logged.append, lambda: self.mono)

    def count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n

    def warned(self, key: str) -> int:
        return self.warn.snapshot()[0].get(key, 0)

    def frame(self, stamp: int, **kw) -> list[FrameJob]:
        return self.gate.on_pose(pose(stamp)) + self.gate.on_segmentation(labels(stamp, **kw))


def test_frame_needs_camera_info_then_completes_with_its_intrinsics():
    h = Harness()
    assert h.frame(S) == [] and h.warned("segmentation: no camera_info received yet") == 0   # waits for it
    h.mono = NodeParams().pose_wait
    assert h.gate.poll() == [] and h.warned("segmentation: no camera_info received yet") == 1   # none came: dropped
    assert h.gate.on_camera_info(camera_info())
    (job,) = h.frame(2 * S)
    f = job.frame
    assert job.stamp_ns == 2 * S and f.labels.shape == (H, W) and f.camera.K[0, 0] == 20.0
    assert f.confidence is None and h.counts["frames_synchronised"] == 1


def test_a_first_segmentation_before_its_camera_info_waits_for_it():
    """DDS orders no two topics: a driver's first camera_info may reach the node after the segmentation it was
    published with. That frame once was dropped at once ("no camera_info received yet"); it now waits up to
    pose_wait, like a frame waiting for its pose, and is mapped with the camera_info that came."""
    h = Harness()
    assert h.frame(S) == []
    h.mono = 0.4 * NodeParams().pose_wait
    assert h.gate.on_camera_info(camera_info())
    (job,) = h.gate.poll()   # the node's pose-wait timer releases it
    assert job.stamp_ns == S and job.frame.camera.K[0, 0] == 20.0
    assert h.warned("segmentation: no camera_info received yet") == 0


def test_frame_waits_for_the_pose_after_its_stamp_then_interpolates():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    h.gate.on_pose(pose(S - 40_000_000, (0.0, 0.0, 0.0)))
    assert h.gate.on_segmentation(labels(S)) == []         # no pose after S yet: waits
    (job,) = h.gate.on_pose(pose(S + 60_000_000, (1.0, 0.0, 0.0)))
    assert job.stamp_ns == S and job.frame.pose_how == "interpolated"
    np.testing.assert_allclose(job.frame.position_map, [0.4, 0.0, 0.0], atol=1e-12)   # 40 of 100 ms


def test_stamp_out_of_order_dropped_then_clock_reset_after_count():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    assert len(h.frame(100 * S)) == 1
    old = [S + k * S // 10 for k in range(STAMP_RESET_COUNT)]
    out = [h.frame(s) for s in old]
    assert all(o == [] for o in out[:-1])
    assert h.warned("segmentation: stamp out of order") == STAMP_RESET_COUNT - 1
    assert [j.stamp_ns for j in out[-1]] == [old[-1]]   # the reset frame itself is accepted
    assert h.counts["clock_resets"] == 1 and any("assuming the clock was reset" in m for m in h.logged)
    assert len(h.frame(old[-1] + S)) == 1               # and the new time line continues


def test_an_in_order_frame_ends_a_run_of_stale_ones():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    h.frame(100 * S)
    for k in range(STAMP_RESET_COUNT - 1):
        h.frame(S + k)
    assert len(h.frame(101 * S)) == 1
    assert h.frame(2 * S) == [] and "counts" and not h.logged   # the run starts again from 1


def test_stamp_in_the_future_dropped():
    h = Harness(now_ns=1000 * S)
    h.gate.on_camera_info(camera_info())
    assert h.frame(1000 * S + 11 * S) == []
    assert h.warned("segmentation: stamp in the future") == 1 and h.warned("pose: stamp in the future") == 1
    assert len(h.frame(1000 * S + 9 * S)) == 1


def test_size_mismatch_with_camera_info_dropped():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    h.gate.on_pose(pose(S))
    assert h.gate.on_segmentation(labels(S, w=W // 2)) == []
    assert h.warned("segmentation: size mismatch with camera_info") == 1
    assert "segmentation 4x6 is not camera_info 8x6 scaled by one factor" in h.lines[-1]


def test_size_checked_against_camera_info_of_frame_time_when_info_came_late():
    h = Harness()
    h.gate.on_pose(pose(S))
    h.gate.on_segmentation(labels(S, w=W // 2))  # no camera_info yet: size unknown, the frame waits for it
    h.gate.on_camera_info(camera_info())
    h.gate.on_pose(pose(2 * S))
    assert h.gate.on_segmentation(labels(2 * S, w=W // 2)) == []
    # both frames are checked against the camera_info that came: the waiting one too
    assert h.warned("segmentation: size mismatch with camera_info") == 2


def test_invalid_camera_info_refused_previous_kept():
    h = Harness()
    assert h.gate.on_camera_info(camera_info())
    assert not h.gate.on_camera_info(camera_info(k=[0.0] * 9))
    assert h.warned("camera_info: invalid camera_info") == 1 and "keeping the previous one" in h.lines[-1]
    assert h.gate.camera_info.width == W and len(h.frame(S)) == 1


def test_huge_camera_info_refused_and_warnings_rate_limited():
    h = Harness(warn_period=60.0)
    h.gate.on_camera_info(camera_info())
    for _ in range(10):
        assert not h.gate.on_camera_info(camera_info(100_000, 100_000))
    assert h.warned("camera_info: image too large") == 10
    assert len([line for line in h.lines if "image too large" in line]) == 1
    assert f"max_image_pixels {DEFAULT_MAX_IMAGE_PIXELS}" in h.lines[-1]
    assert h.gate.camera_info.width == W


def test_max_image_pixels_parameter_bounds_camera_info():
    h = Harness(max_image_pixels=W * H - 1)
    assert not h.gate.on_camera_info(camera_info())
    assert h.warned("camera_info: image too large") == 1


@pytest.mark.parametrize("k, position", [([1e300, 0, 3.5, 0, 1e300, 2.5, 0, 0, 1], (0, 0, 0)),
                                         (K, (1e300, 0, 0)), (K, (0, 1e7, 0))])
def test_extreme_finite_values_refused_without_runtime_warnings(k, position):
    h = Harness()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ok = h.gate.on_camera_info(camera_info(k=k))
        jobs = h.gate.on_pose(pose(S, position)) + h.gate.on_segmentation(labels(S)) if ok else []
    assert jobs == []
    if not ok:
        assert h.warned("camera_info: invalid camera_info") == 1
    else:
        assert h.warned("pose: invalid pose") == 1 and "beyond" in h.lines[-1]


def test_confidence_non_finite_pixels_count_as_zero_and_frame_kept():
    h = Harness(confidence=True)
    h.gate.on_camera_info(camera_info())
    conf = np.full((H, W), 0.5, np.float32)
    conf[0, :3] = [np.nan, np.inf, -np.inf]
    h.gate.on_confidence(image(S, conf, "32FC1"))
    (job,) = h.frame(S)
    conf = job.frame.confidence
    assert conf[0, :3].tolist() == [0.0, 0.0, 0.0] and conf[1, 1] == 0.5
    assert h.counts["confidence_pixels_non_finite"] == 3
    assert h.warned("segmentation_confidence: non-finite confidence values") == 1


def test_frame_waits_for_confidence_while_it_is_published():
    h = Harness(confidence=True)
    h.gate.on_camera_info(camera_info())
    assert h.frame(S) == []
    (job,) = h.gate.on_confidence(image(S, np.ones((H, W), np.float32), "32FC1"))
    assert job.frame.confidence is not None


def test_segmentation_before_the_first_pose_dropped_with_reason():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    h.gate.on_segmentation(labels(S))
    h.gate.on_pose(pose(S + S // 2))
    assert h.warned("segmentation: no pose before the frame") == 1


def _pose_array(n: int, stamp: int = 7, position=(0.0, 0.0, 0.0)) -> NS:
    return NS(header=header(stamp, "map"), poses=[pose(0, position).pose for _ in range(n)])


def test_candidates_without_camera_info_answered_nan():
    h = Harness()
    ans = h.gate.on_candidates(_pose_array(3))
    assert isinstance(ans, NanAnswer) and ans.reason == "no camera_info received yet"
    assert ans.positions.shape == (3, 3) and ans.header.stamp.nanosec == 7


def test_too_many_candidates_answered_nan():
    h = Harness(max_candidates=4)
    h.gate.on_camera_info(camera_info())
    ans = h.gate.on_candidates(_pose_array(5))
    assert isinstance(ans, NanAnswer) and ans.reason == "too many candidates" and len(ans.positions) == 5
    assert h.warned("candidates: too many candidates") == 1
    assert isinstance(h.gate.on_candidates(_pose_array(4)), CandidateJob)


def test_candidate_with_extreme_position_scored_nan():
    h = Harness()
    h.gate.on_camera_info(camera_info())
    job = h.gate.on_candidates(NS(header=header(1, "map"), poses=[pose(0).pose, pose(0, (1e300, 0, 0)).pose]))
    assert isinstance(job, CandidateJob)
    assert np.all(np.isfinite(job.quats_splat[0])) and np.all(np.isnan(job.quats_splat[1]))
    assert h.warned("candidates: invalid candidate poses") == 1


def test_oversized_point_query_is_refused_from_its_header_without_touching_the_data():
    class Untouchable:
        def __getattr__(self, name):
            raise AssertionError("the request's data was read")

        def __len__(self):
            raise AssertionError("the request's data was read")

        def __buffer__(self, flags):
            raise AssertionError("the request's data was read")

    h = Harness(max_query_points=1000)
    fields = [NS(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")]
    msg = NS(header=header(5), width=10**7, height=1, point_step=12, row_step=12 * 10**7, fields=fields,
             is_bigendian=False, data=Untouchable(), is_dense=True)
    job = h.gate.on_point_query(msg, 4)
    assert job.done and job.status == "too many points" and job.xyz.shape == (0, 3)
    assert job.expectation.shape == (0, 4) and job.header is msg.header
    assert h.warned("point_queries: too many points") == 1 and h.counts["point_queries_received"] == 1
    # 1000 x 1 declared is within the bound: evaluated (here: truncated data, answered empty as unreadable).
    msg.width, msg.data = 1000, b""
    job = h.gate.on_point_query(msg, 4)
    assert job.status is None and h.warned("point_queries: unreadable point query") == 1
