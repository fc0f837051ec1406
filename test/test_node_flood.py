"""css_node under a flood of frames: bounded memory, counted drops, candidate queries still answered."""
from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.io.messages import unpack_view_points  # noqa: E402

pytestmark = pytest.mark.slow

FLOOD_W, FLOOD_H = 320, 240
N_FLOOD = 300


def test_flood_bounded_memory_counted_drops_responsive(tmp_path):
    domain = rh.next_domain_id()
    model = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES,
                               checkpoint_path="", resume=False, log_period=0.3, output_scale=0.5,
                               max_pending_frames=2, candidate_scale=0.1),
                          domain, tmp_path / "node.log",
                          # Namespaced node with one input remapped: outputs follow the node's namespace.
                          remaps={"__ns": "/robot1", "segmentation": "/camera/labels"})
    client = rh.RosClient(domain, node_ns="/robot1/css_node", input_reliable=False,
                          topics={"segmentation": "/camera/labels", "image": "/robot1/image",
                                  "camera_info": "/robot1/camera_info", "pose": "/robot1/pose",
                                  "candidates": "/robot1/candidates"})
    try:
        assert client.wait_connected(60.0), node.log()
        time.sleep(0.5)
        labels = rh.wall_labels(FLOOD_W, FLOOD_H)
        K = rh.scaled_K((FLOOD_H, FLOOD_W))
        stamp = 10**9
        client.send_frame(stamp, labels)
        assert client.wait_stamp("view_uncertainty", stamp, 30.0), node.log()[-3000:]
        # output_scale = 0.5: renders are published at half resolution.
        sem = client.wait_stamp("semantic", stamp)
        assert (sem.width, sem.height) == (FLOOD_W // 2, FLOOD_H // 2)
        rss_before = node.rss_mb()

        from css_ros.ros.conversions import camera_info_msg, header_msg, image_msg, pose_stamped_msg

        t0 = time.monotonic()
        request_stamp = None
        request_sent = None
        for i in range(1, N_FLOOD + 1):
            s = stamp + i * 10_000_000  # 100 Hz stamps, sent as fast as possible
            h = header_msg(s, "camera")
            client.pub["camera_info"].publish(camera_info_msg(K, FLOOD_W, FLOOD_H, h))
            client.pub["pose"].publish(pose_stamped_msg((0, 0, 0), rh.IDENTITY, header_msg(s, "map")))
            client.pub["segmentation"].publish(image_msg(labels, "mono8", h))
            if i == N_FLOOD // 2:
                request_stamp = 7
                request_sent = time.monotonic()
                client.send_candidates(request_stamp, np.zeros((3, 3)), np.tile(rh.IDENTITY, (3, 1)))
        send_s = time.monotonic() - t0
        reply = client.wait_stamp("candidate_scores", request_stamp, timeout=20.0)
        assert reply is not None, node.log()[-3000:]
        reply_latency = time.monotonic() - request_sent
        assert len(unpack_view_points(reply)) == 3
        # The node settles: counters stop moving once the queues are drained.
        def settled() -> bool:
            a = client.diagnostics()
            time.sleep(0.7)
            b = client.diagnostics()
            return bool(a) and a.get("frames_processed") == b.get("frames_processed") \
                and b.get("pending_frames") == "0"
        assert rh.RosClient.wait_until(settled, 30.0), node.log()[-3000:]
        rss_after = node.rss_mb()
        diag = client.diagnostics()
        processed = int(diag["frames_processed"])
        busy = int(diag.get("frames_dropped_busy", 0))
        received = int(diag["segmentations_received"])
        print(f"\nflood: sent {N_FLOOD} frames of {FLOOD_W}x{FLOOD_H} in {send_s:.2f} s; node received {received}, "
              f"processed {processed}, dropped busy {busy}, dropped per topic "
              f"{ {k: v for k, v in diag.items() if k.startswith('dropped[')} }; candidate reply after "
              f"{reply_latency * 1e3:.0f} ms; RSS {rss_before:.0f} -> {rss_after:.0f} MB; "
              f"median frame latency {diag.get('frame_latency_ms_median')} ms, request latency in node "
              f"{diag.get('request_latency_ms_median')} ms")
        # Slower than the input: frames were dropped and counted, not queued without bound.
        assert processed < received <= N_FLOOD + 1
        assert busy > 0
        # Inside the node a request waits for at most about one frame (the worker alternates).
        assert float(diag["request_latency_ms_median"]) < 2000.0
        assert rss_after - rss_before < 150.0
        # Still alive and mapping afterwards.
        final = stamp + (N_FLOOD + 100) * 10_000_000
        client.send_frame(final, labels)
        assert client.wait_stamp("view_uncertainty", final, timeout=20.0), node.log()[-3000:]
    finally:
        client.close()
        assert node.stop() == 0
