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


def test_a_burst_beside_busy_loops_is_answered_or_counted_and_the_counters_add_up(tmp_path):
    """200 candidate requests (one pose each) and 200 point queries back to back by reliable publishers (KEEP_LAST
    1000) while two busy loops share the cores. Every request reaches its client's reliable reader exactly once, or
    is counted: lost before the node (``candidates_lost``), or unanswered with a reason; and the node's counters add
    up: received + lost = sent, served + unanswered + pending = received, served = answers the client got."""
    from geometry_msgs.msg import PoseArray
    from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    from css_ros.ros.conversions import header_msg, pose_array_msg

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES,
                               log_period=0.3, checkpoint_path=""), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
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
                                 and sub_points.get_publisher_count() > 0, 20.0)
        assert client.wait_outputs_heard(("point_query_results", "candidate_scores"))
        xyz = np.array([[0.0, 0.0, 3.0], [100.0, 0.0, 0.0]])
        pose = (np.zeros((1, 3)), np.array([[0.0, 0.0, 0.0, 1.0]]))
        with rh.BusyLoops(2):
            t0 = time.monotonic()
            for i in range(1, BURST + 1):
                pub_q.publish(_cloud_msg(i, xyz))
                pub_c.publish(pose_array_msg(*pose, header_msg(i, "map")))

            def settled() -> bool:
                d = client.diagnostics()
                return all(int(d.get(f"{k}_received", 0)) + int(d.get(f"{t}_lost", 0)) >= BURST and
                           int(d.get(f"{k}_served", 0)) + _unanswered(d, k) >= int(d.get(f"{k}_received", 0))
                           for k, t in (("requests", "candidates"), ("point_queries", "point_queries"))) and \
                    d.get("pending_requests") == "0" and d.get("answers_waiting") == "0"
            assert client.wait_until(settled, 120.0, 0.2), (client.diagnostics(), node.log()[-3000:])
            seconds = time.monotonic() - t0
        d = client.diagnostics()
        for kind, topic, answers in (("requests", "candidates", lambda: client.messages("candidate_scores")),
                                     ("point_queries", "point_queries", lambda: list(points))):
            served = int(d[f"{kind}_served"])
            assert client.wait_until(lambda a=answers, n=served: len(a()) >= n, 30.0)
            time.sleep(0.3)   # nothing more may come
            ids = sorted(m.header.stamp.nanosec for m in answers())
            assert len(ids) == len(set(ids)) == served                    # each once, as counted
            assert int(d[f"{kind}_received"]) + int(d.get(f"{topic}_lost", 0)) == BURST
            assert served + _unanswered(d, kind) == int(d[f"{kind}_received"])
        print(f"\nburst beside 2 busy loops: {len(client.messages('candidate_scores'))}/{BURST} candidate and "
              f"{len(points)}/{BURST} point answers in {seconds:.1f} s; requests_dropped_busy "
              f"{d.get('requests_dropped_busy')}, lost {d.get('candidates_lost', 0)}/{d.get('point_queries_lost', 0)}")
    finally:
        client.close()
        assert node.stop() == 0


def _unanswered(diag: dict[str, str], kind: str) -> int:
    return sum(int(v) for k, v in diag.items() if k.startswith(f"{kind}_unanswered["))


def test_answers_made_before_the_clients_reader_matched_reach_it(tmp_path):
    """A client sends 20 candidate requests before it subscribes to ~/candidate_scores (or before the node's writer
    has matched its reader, as on a loaded host). The answers wait (answers_waiting, answers_held[...]) and are
    published when its reader matches: all 20 arrive, counted served once. Before, they went to no one while the
    node counted them as served."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES,
                               log_period=0.3, checkpoint_path=""), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        assert client.send_frame_until_processed(10**9, output="view_uncertainty"), node.log()[-3000:]
        client.node.destroy_subscription(client.subs.pop("candidate_scores"))
        assert client.wait_until(lambda: client.diagnostics().get("subscribers[candidate_scores]") == "0", 30.0)
        for i in range(1, 21):
            client.send_candidates(i, np.zeros((1, 3)), np.tile(rh.IDENTITY, (1, 1)))
        assert client.wait_until(lambda: client.diagnostics().get("answers_waiting") == "20", 30.0), \
            (client.diagnostics(), node.log()[-3000:])
        assert client.diagnostics().get("requests_served", "0") == "0"
        got: list = []
        client.node.create_subscription(PointCloud2, "/css_node/candidate_scores", got.append,
                                        QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE))
        assert client.wait_until(lambda: len(got) >= 20, 30.0), (len(got), client.diagnostics())
        assert sorted(m.header.stamp.nanosec for m in got) == list(range(1, 21))
        assert client.wait_diag("requests_served", 20) == 20
        assert client.diagnostics()["answers_held[candidate_scores]"] == "20"
    finally:
        client.close()
        assert node.stop() == 0


def test_frames_while_a_huge_point_query_arrives_are_mapped_or_counted(tmp_path):
    """Frames at 5 Hz while a point query of 3 x 10^6 points (34 MiB, above max_query_points) arrives: the query is
    answered at once from its serialized header (an empty cloud, its request header echoed), and every frame sent is
    mapped or counted as dropped with a reason (busy, lost before the node, or refused by the gate)."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2, PointField

    from css_ros.ros.conversions import header_msg

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES,
                               log_period=0.3, checkpoint_path=""), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    sender = rh.RosClient(domain)     # another participant: the frames' writer is not held up by the big one
    try:
        assert client.wait_connected(60.0), node.log()
        answers: list = []
        sub = client.node.create_subscription(PointCloud2, "/css_node/point_query_results", answers.append,
                                              QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        pub = sender.node.create_publisher(PointCloud2, "point_queries", 10)
        assert client.wait_until(lambda: pub.get_subscription_count() > 0 and sub.get_publisher_count() > 0, 30.0)
        assert client.wait_outputs_heard(("point_query_results",))
        n = 3_000_000
        big = PointCloud2(header=header_msg(77, "map"), height=1, width=n, point_step=12, row_step=12 * n,
                          is_dense=True, fields=[PointField(name=c, offset=4 * i, datatype=7, count=1)
                                                 for i, c in enumerate("xyz")])
        big.data = np.zeros(3 * n, np.float32).tobytes()
        query = threading.Thread(target=lambda: (time.sleep(1.0), pub.publish(big)), daemon=True)
        stamps = [10**9 * (k + 1) for k in range(30)]
        query.start()
        for s in stamps:
            client.send_frame(s)
            time.sleep(0.2)
        query.join(30.0)
        client.send_frame(10**9 * 40)     # a later frame: a gap before it is counted (segmentation_lost)
        assert client.wait_until(lambda: answers, 30.0), (client.diagnostics(), node.log()[-3000:])
        assert answers[0].width == 0 and answers[0].header.stamp.nanosec == 77

        def accounted() -> tuple[int, int, int]:
            """From the node's own counters, later frame included: (segmentations received, frames mapped or
            dropped at the node, segmentations counted as lost before it). The outputs received are only
            reported: a per-frame output is kept-last at both ends, so a loaded client may miss one."""
            d = client.diagnostics()
            settled = sum(int(d.get(k, 0)) for k in ("frames_processed", "frames_dropped_busy", "dropped[segmentation]"))
            return int(d.get("segmentations_received", 0)), settled, int(d.get("segmentation_lost", 0))

        def report() -> str:
            got = sorted(stamp_ns(m) // 10**9 for m in client.messages("view_uncertainty"))
            return f"{accounted()}; outputs received (s) {got}\n{client.diagnostics()}\n{node.log()[-6000:]}"

        sent = len(stamps) + 1
        # every segmentation received is mapped or dropped with a reason, and every one sent was received or
        # counted lost (but for the later one: a loss of the last message shows no gap)
        client.wait_until(lambda: (a := accounted())[1] == a[0] and a[0] + a[2] >= sent, 30.0)
        received, settled, lost = accounted()
        assert settled == received, report()
        assert sent - 1 <= received + lost <= sent, report()
        outputs = {stamp_ns(m) for m in client.messages("view_uncertainty")}
        assert outputs <= set(stamps) | {10**9 * 40}, report()
        assert client.diagnostics()["requests_nan[too many points]"] == "1"
        d = client.diagnostics()
        print(f"\nframes during a {12 * n >> 20} MiB query (and a later one): {received} of {sent} received, "
              f"{d.get('frames_processed')} mapped, {settled - int(d.get('frames_processed', 0))} dropped at the node, "
              f"{lost} lost before it, {len(outputs)} outputs heard")
    finally:
        sender.close()
        client.close()
        assert node.stop() == 0


def stamp_ns(msg) -> int:
    return msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
