"""A peer on the same ROS domain sends a live css_node forged evidence packets over real DDS (css_ros/ros/evidence.py).

Forged returns with huge frame claims to a node restarted with resume (it keeps running, its map and checkpoint
unchanged), and a flood of "resumed" snapshots of new epochs (the returns it answers with are counted and bounded).
"""
from __future__ import annotations

import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402

from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.io import evidence as ev  # noqa: E402

pytestmark = pytest.mark.slow
PRIOR = 1e-3


def _params(model: Path, ckpt: Path, **kw) -> dict:
    return {**dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, prior=PRIOR,
                   checkpoint_path=str(ckpt), resume=False, checkpoint_period=0.0, log_period=0.5, warmup=False,
                   evidence_period=0.2, evidence_snapshot_period=1.0, publish_evidence=True,
                   evidence_in="/crafted/evidence", evidence_origin="robot_b"), **kw}


def _publisher(client: rh.RosClient):
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import UInt8MultiArray

    pub = client.node.create_publisher(UInt8MultiArray, "/crafted/evidence",
                                       QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    assert client.wait_until(lambda: pub.get_subscription_count() > 0, 30.0)

    def send(data: bytes) -> None:
        msg = UInt8MultiArray()
        msg.data = data
        pub.publish(msg)
    return send


def _map_file(path: Path) -> tuple[np.ndarray, int]:
    with np.load(path, allow_pickle=False) as data:
        return np.array(data["concentrations"]), int(data["frames_observed"])


def test_forged_returns_with_huge_frame_claims_leave_a_resumed_node_and_its_map_intact(tmp_path):
    """B saves a checkpoint of 2 frames and is killed; restarted with resume it accepts returns of its previous
    epoch. A peer forges returns for it claiming 2^64 - 1, 2^63 + 5 and 10^6 frames (evidence within what such
    claims allow). Each is refused by name; B keeps publishing (the timer that crashed on 2^64 - 1), its saved map
    and frames_observed equal the checkpoint's, and its shutdown checkpoint is written (exit code 0)."""
    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    n, fp = model.num_gaussians, model.fingerprint
    ckpt = tmp_path / "b.npz"
    node = rh.NodeProcess(_params(model_path, ckpt), domain, tmp_path / "b.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        for i in range(2):
            assert client.send_frame_until_processed((i + 1) * 10**9) is not None, node.log()
        assert client.call(client.save_client).success
        client.close()
        node.kill9()
        want, frames = _map_file(ckpt)
        with np.load(ckpt, allow_pickle=False) as data:
            epoch = int(data["evidence_epoch"])
        assert frames == 2 and epoch > 0

        node = rh.NodeProcess(_params(model_path, ckpt, resume=True), domain, tmp_path / "b_resumed.log")
        client = rh.RosClient(domain)
        assert client.wait_connected(60.0), node.log()
        assert node.wait_log("resumed: asking peers", 30.0), node.log()
        send = _publisher(client)
        evidence = np.zeros((n, rh.NUM_CLASSES))
        evidence[:, 1] = 50.0                               # 50 per Gaussian: within P · F for any F >= 1
        for claim in (2**64 - 1, 2**63 + 5, 10**6):
            for data in ev.encode_return("crafted", "robot_b", fp, epoch, claim, evidence, PRIOR, 1000):
                send(data)
        refused = {"evidence_refused[frame count above what any map holds]": 2,
                   "evidence_refused[return claims more frames than this node could have fused since its checkpoint]": 1}
        assert client.wait_until(lambda: all(int(client.diagnostics().get(k, 0)) >= v for k, v in refused.items()),
                                 30.0, 0.2), (client.diagnostics(), node.log()[-3000:])
        sent = client.wait_diag("evidence_packets_sent", 1)
        assert client.wait_diag("evidence_packets_sent", sent + 5, 20.0) >= sent + 5   # the publish timer runs on
        assert client.call(client.save_client).success
        got, got_frames = _map_file(ckpt)
        assert got_frames == 2
        np.testing.assert_array_equal(got, want)
        assert "took back" not in node.log()
        client.close()
        assert node.stop() == 0, node.log()[-3000:]
        got, got_frames = _map_file(ckpt)                   # the shutdown checkpoint
        assert got_frames == 2 and "Traceback" not in node.log(), node.log()[-3000:]
        np.testing.assert_array_equal(got, want)
    finally:
        client.close()
        node.stop()


def test_a_flood_of_resumed_snapshots_gets_a_bounded_number_of_returns(tmp_path):
    """Source 'crafted' states evidence on every Gaussian, then sends 100 tiny snapshots flagged "resumed", each of
    a new epoch, at 40 packets/s. The node answers with at most RETURN_BURST + (seconds of the flood) /
    RETURN_INTERVAL_S + 1 returns (it answered every one before: 100 returns of the whole evidence), of at most 10
    times the bytes of the flood in all; every other one is counted as withheld. The bytes of returns received on
    ~/evidence are measured and printed."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from std_msgs.msg import UInt8MultiArray

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    n, fp = model.num_gaussians, model.fingerprint
    node = rh.NodeProcess(_params(model_path, tmp_path / "n.npz", evidence_origin="robot_n"), domain,
                          tmp_path / "n.log")
    client = rh.RosClient(domain)
    returns: list[int] = []
    lock = threading.Lock()

    def on_packet(msg) -> None:
        data = bytes(msg.data)
        if data[6] == ev.RETURN:
            with lock:
                returns.append(len(data))
    try:
        client.node.create_subscription(UInt8MultiArray, "/css_node/evidence", on_packet,
                                        QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
        assert client.wait_connected(60.0), node.log()
        send = _publisher(client)
        rows = np.arange(n)
        held = np.random.default_rng(0).uniform(0, 5, (n, rh.NUM_CLASSES))
        send(ev.encode_packet(ev.SNAPSHOT, "crafted", fp, 1, rows, held, PRIOR, n, snapshot_id=1, epoch=1, frames=1))
        assert client.wait_diag("evidence_packets_applied", 1, 30.0) >= 1, node.log()
        count, start, flood_bytes = 100, time.monotonic(), 0
        for k in range(count):
            data = ev.encode_packet(ev.SNAPSHOT, "crafted", fp, 2 + k, rows[:0], held[:0], PRIOR, n, snapshot_id=2 + k,
                                    epoch=2 + k, frames=1, flags=ev.FLAG_RESUMED)
            send(data)
            flood_bytes += len(data)
            time.sleep(0.025)
        seconds = time.monotonic() - start
        assert client.wait_diag("evidence_packets_applied", 1 + count, 30.0) >= 1 + count, client.diagnostics()
        sent = client.wait_until(lambda: int(client.diagnostics().get("evidence_returns_sent", 0)), 10.0, 0.2)
        assert client.wait_until(lambda: len(returns) >= sent, 20.0, 0.1), (len(returns), sent)
        full = len(ev.encode_return("robot_n", "crafted", fp, 1, 1, held, PRIOR, 10**6)[0])
        print(f"\n{count} hostile packets ({count * (ev.HEADER_SIZE)} B) in {seconds:.1f} s: {len(returns)} returns, "
              f"{sum(returns)} B published (one return {full} B)")
        bound = ev.RETURN_BURST + int(seconds / ev.RETURN_INTERVAL_S) + 1
        assert 1 <= len(returns) <= bound, (len(returns), bound)
        assert sum(returns) <= bound * full
        assert sum(returns) <= 10 * flood_bytes          # at most 10 bytes out per byte of the "resumed" run
        diag = client.diagnostics()                      # the rest is withheld and counted
        assert int(diag[f"evidence_returns_withheld[{ev.WITHHELD_BUDGET}]"]) + \
            int(diag.get(f"evidence_returns_withheld[{ev.WITHHELD_RATE}]", 0)) + len(returns) == count
        assert node.proc.poll() is None
    finally:
        client.close()
        node.stop()
