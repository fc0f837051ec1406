"""css_node under hostile input over real DDS: huge camera_info, oversize requests, SIGTERM while busy."""
from __future__ import annotations

import signal
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.io.messages import unpack_view_points  # noqa: E402

pytestmark = pytest.mark.slow


def _start(tmp, name: str, **params) -> tuple[rh.NodeProcess, rh.RosClient]:
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp / "wall.ply")
    base = dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, log_period=0.3, warn_period=60.0,
                checkpoint_path=str(tmp / "map.npz"), checkpoint_period=0.0)
    base.update(params)
    node = rh.NodeProcess(base, domain, tmp / f"{name}.log")
    client = rh.RosClient(domain)
    assert client.wait_connected(60.0), node.log()
    time.sleep(0.5)
    return node, client


def test_huge_camera_info_and_oversize_requests_answered(tmp_path):
    node, client = _start(tmp_path, "hostile", max_candidates=8)
    try:
        # A request before any camera_info: answered at once, every score NaN.
        client.send_candidates(11, np.zeros((3, 3)), np.tile(rh.IDENTITY, (3, 1)))
        msg = client.wait_stamp("candidate_scores", 11)
        assert msg is not None and np.all(np.isnan(unpack_view_points(msg)["u_var"]))
        assert client.wait_diag("requests_nan[no camera_info received yet]", 1) == 1
        assert client.send_frame_until_processed(10**9, output="view_uncertainty"), node.log()[-3000:]
        # 100000 x 100000 camera_info: refused (warned once, counted each time), the previous one stays.
        for _ in range(5):
            client.send_camera_info(2 * 10**9, width=100_000, height=100_000)
        assert client.wait_diag("warn[camera_info: image too large]", 5) == 5, node.log()[-3000:]
        assert node.log().count("[camera_info] image too large") == 1
        client.send_pose(3 * 10**9)
        client.send_image("segmentation", 3 * 10**9, rh.wall_labels(), "mono8")
        assert client.wait_stamp("view_uncertainty", 3 * 10**9), node.log()[-3000:]
        # Too many poses: answered with one NaN row per pose, in request order.
        positions = np.arange(27, dtype=float).reshape(9, 3) * 0.01
        client.send_candidates(12, positions, np.tile(rh.IDENTITY, (9, 1)))
        pts = unpack_view_points(client.wait_stamp("candidate_scores", 12))
        assert len(pts) == 9 and np.all(np.isnan(pts["u_exp"]))
        np.testing.assert_allclose(pts["x"], positions[:, 0], atol=1e-6)
        assert client.wait_diag("requests_nan[too many candidates]", 1) == 1
    finally:
        client.close()
        assert node.stop() == 0


def test_sigterm_while_scoring_exits_fast_with_checkpoint(tmp_path):
    node, client = _start(tmp_path, "sigterm", max_candidates=100_000, candidate_slice=8, candidate_scale=1.0,
                          candidate_time_budget=0.0)
    try:
        stamps = [k * 10**9 for k in range(1, 4)]
        for s in stamps:
            client.send_frame(s)
            assert client.wait_stamp("view_uncertainty", s), node.log()[-3000:]
        m = 20_000  # minutes of scoring on this machine
        client.send_candidates(99, np.zeros((m, 3)), np.tile(rh.IDENTITY, (m, 1)))
        assert client.wait_diag("candidate_views_scored", 16, timeout=30.0) >= 16, node.log()[-3000:]
        t0 = time.monotonic()
        node.proc.send_signal(signal.SIGTERM)
        code = node.proc.wait(20.0)
        elapsed = time.monotonic() - t0
        assert code == 0 and elapsed < 5.0, (elapsed, node.log()[-3000:])
        assert "checkpoint (shutdown) written" in node.log()
        smap = SemanticMap.load(tmp_path / "map.npz", GaussianModel.from_ply(tmp_path / "wall.ply"))
        assert smap.frames_observed == len(stamps)
        answer = client.wait_stamp("candidate_scores", 99, timeout=5.0)
        assert answer is not None and len(unpack_view_points(answer)) == m
        assert np.isnan(unpack_view_points(answer)["u_var"][-1])
    finally:
        client.close()
        node.stop()
