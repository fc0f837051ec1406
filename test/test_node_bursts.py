"""Bursts of requests over real DDS: 200 point queries and 200 candidate requests published back to back
are every one answered exactly once (request_queue_size; docs/reliability.md)."""
from __future__ import annotations

import threading
import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from test_node_map3d import _cloud_msg  # noqa: E402

pytestmark = pytest.mark.slow

BURST = 200


def test_bursts_of_200_point_queries_and_candidates_are_all_answered(tmp_path):
    from geometry_msgs.msg import PoseArray
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from css_ros.ros.conversions import header_msg, pose_array_msg

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES,
                               log_period=0.3, checkpoint_path="", warmup=False), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        # camera_info + one frame: candidates can be scored
        assert client.send_frame_until_processed(10**9, output="view_uncertainty"), node.log()[-3000:]
        deep = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE, history=HistoryPolicy.KEEP_LAST)
        points: list = []
        lock = threading.Lock()

        def on_points(msg) -> None:
            with lock:
                points.append(msg)

        sub_points = client.node.create_subscription(PointCloud2, "/css_node/point_query_results", on_points, deep)
        pub_q = client.node.create_publisher(PointCloud2, "point_queries", deep)
        pub_c = client.node.create_publisher(PoseArray, "candidates", deep)
        assert client.wait_until(lambda: pub_q.get_subscription_count() > 0 and pub_c.get_subscription_count() > 0
                                 and sub_points.get_publisher_count() > 0, 20.0)   # matched, both participants
        assert client.wait_outputs_heard(("point_query_results", "candidate_scores"))   # its writers matched ours too
        xyz = np.array([[0.0, 0.0, 3.0], [100.0, 0.0, 0.0]])
        pose = (np.zeros((1, 3)), np.array([[0.0, 0.0, 0.0, 1.0]]))
        for i in range(1, BURST + 1):  # back to back, no pause
            pub_q.publish(_cloud_msg(i, xyz))
            pub_c.publish(pose_array_msg(*pose, header_msg(i, "map")))
        ok = client.wait_until(lambda: len(points) >= BURST and len(client.messages("candidate_scores")) >= BURST,
                               120.0)
        time.sleep(0.5)  # nothing more may come
        q_ids = sorted(m.header.stamp.nanosec for m in points)
        c_ids = sorted(m.header.stamp.nanosec for m in client.messages("candidate_scores"))
        assert ok, (len(q_ids), len(c_ids), node.log()[-3000:])
        assert q_ids == c_ids == list(range(1, BURST + 1))  # every request answered exactly once
        assert all(m.width == 2 for m in points)
        # Counted as received and served (some as busy: request queue full, answered at once).
        assert client.wait_diag("point_queries_received", BURST) == BURST
        assert client.wait_diag("point_queries_served", BURST) == BURST
        assert client.wait_diag("requests_received", BURST) == BURST
        assert client.wait_diag("requests_served", BURST) == BURST
    finally:
        client.close()
        assert node.stop() == 0
