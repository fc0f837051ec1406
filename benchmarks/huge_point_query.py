"""One oversized point query while frames stream: css_node's memory, lost frames and the answer.

Starts css_node (the test wall model, 4 anonymous classes, no checkpoint) on ``--domain-id``, streams
frames at 5 Hz for ``--seconds`` s and, one second in, publishes one PointCloud2 of ``--points`` points
(x y z float32) on ``point_queries``. Prints the node's RSS before, the maximum sampled every 50 ms while
the request is handled, and at the end; the answer's width, size and latency; frames sent / processed.

    python benchmarks/huge_point_query.py --points 10000000 --domain-id 92
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path[:0] = [str(REPO), str(REPO / "test")]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=10_000_000, help="points in the request (default 1e7)")
    ap.add_argument("--seconds", type=float, default=12.0, help="frame streaming time [s] (default 12)")
    ap.add_argument("--domain-id", type=int, default=92, help="ROS_DOMAIN_ID (default 92)")
    args = ap.parse_args(argv)

    import ros_helpers as rh
    from sensor_msgs.msg import PointCloud2, PointField

    from css_ros.ros.conversions import header_msg

    tmp = Path(tempfile.mkdtemp(prefix="css_huge_query_"))
    model = rh.write_wall_model(tmp / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, log_period=1.0,
                               checkpoint_path=""), args.domain_id, tmp / "node.log")
    client = rh.RosClient(args.domain_id)
    try:
        assert client.wait_connected(60.0), node.log()
        answers: list = []
        t_answer: list[float] = []

        def on_answer(msg) -> None:
            t_answer.append(time.monotonic())
            answers.append(msg)

        client.node.create_subscription(PointCloud2, "/css_node/point_query_results", on_answer, 10)
        pub = client.node.create_publisher(PointCloud2, "point_queries", 10)
        assert client.wait_until(lambda: pub.get_subscription_count() > 0, 20.0)
        msg = PointCloud2(header=header_msg(1, "map"), height=1, width=args.points, is_bigendian=False,
                          point_step=12, row_step=12 * args.points, is_dense=True,
                          fields=[PointField(name=n, offset=4 * i, datatype=7, count=1) for i, n in enumerate("xyz")])
        msg.data = np.zeros(3 * args.points, np.float32).tobytes()
        rss0 = node.rss_mb()
        peak = [rss0]
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                peak.append(node.rss_mb())
                time.sleep(0.05)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        sent, t0, t_query = 0, time.monotonic(), None
        while time.monotonic() - t0 < args.seconds:
            sent += 1
            client.send_frame(sent * 10**8)
            if t_query is None and time.monotonic() - t0 >= 1.0:
                t_query = time.monotonic()
                pub.publish(msg)
            time.sleep(0.2)
        time.sleep(2.0)
        stop.set()
        sampler.join()
        processed = len({m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
                         for m in client.messages("view_uncertainty")})
        print(f"request: {args.points} points ({12 * args.points / 2**20:.0f} MiB of data)")
        if answers:
            a = answers[0]
            print(f"answer: width {a.width}, {len(a.data)} data bytes, {1e3 * (t_answer[0] - t_query):.0f} ms after "
                  "publishing")
        else:
            print("answer: none")
        print(f"node RSS [MiB]: before {rss0:.0f}, max while handled {max(peak):.0f}, end {node.rss_mb():.0f}")
        print(f"frames sent {sent}, processed {processed}")
    finally:
        client.close()
        node.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
