"""css_node says and counts every frame it does not answer when it stops (css_ros/ros/node.py shutdown)."""
from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402

pytestmark = pytest.mark.slow


def test_a_frame_still_waiting_for_its_pose_at_stop_is_said(tmp_path):
    """A segmentation arrives, its pose never does (pose_wait 60 s keeps it waiting); the node is stopped: it exits 0
    and its log names the one frame it did not process."""
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, warmup=False,
                               checkpoint_path="", pose_wait=60.0, log_period=0.5), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        for _ in range(15):   # best-effort inputs: sent again until received (a copy is refused as out of order)
            client.send_camera_info(10**9)
            client.send_image("segmentation", 10**9, rh.wall_labels(), "mono8")
            if client.wait_diag("segmentations_received", 1, 2.0) >= 1:
                break
        assert client.wait_diag("segmentations_received", 1, 1.0) >= 1, node.log()
        client.close()
        assert node.stop() == 0, node.log()[-3000:]
        log = node.log()
        assert "1 frame(s) still waiting for a pose or confidence not processed" in log, log[-3000:]
        assert "frames processed 0" in log or "no frame yet" in log
    finally:
        client.close()
        node.stop()
