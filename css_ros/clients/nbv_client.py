"""css_nbv_client: example next-best-view loop over css_node's candidate-scoring topics."""
from __future__ import annotations

import argparse
import json
import math
import sys
import threading
import time
from typing import Any, Sequence

import numpy as np

from ..console import bounded_number
from ..engine.camera import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from ..io.clouds import has_field, unpack_scored_views
from ..io.messages import pose_to_arrays, stamp_to_ns
from ..io.frame_gate import pose_message_pose
from ..io.topics import POSE_TYPES
from ..ros.work import WarnLimiter
from .node_link import MIN_TIMEOUT_S, node_name_arg

#: --metric choices: the candidate with the largest value is the next best view.
METRICS = ("info_gain", "u_var", "u_exp")
#: Most candidates per request (css_node answers larger requests than its max_candidates, default 256, with NaN).
MAX_NUM_CANDIDATES = 4096
#: Largest --period / --timeout [s]; the smallest --period [s] (the loop spins at 20 Hz).
MAX_SECONDS = 3600.0
MIN_PERIOD_S = 0.05
#: Largest --position-std / --vertical-std [m].
MAX_STD_M = 100.0
#: Per-request warnings (no pose, nobody subscribes, no answer, ...): the first at once, then at most one per
#: reason every WARN_PERIOD_S seconds, saying how many were suppressed (a 0.05 s --period would log 20 a second).
WARN_PERIOD_S = 10.0
#: The topics css_nbv_client uses under --node (checked as full ROS names when --node is parsed).
NODE_TOPICS = ("candidate_scores",)


def yaw_about_map_z(angle: float) -> np.ndarray:
    """(3, 3) rotation by ``angle`` [rad] about the map's vertical (z) axis."""
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def sample_candidates(position: np.ndarray, quat_xyzw: np.ndarray, num: int, yaw_range: float,
                      position_std: float, vertical_std: float, rng: np.random.Generator
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Candidate poses around a camera pose (same convention as the input pose: optical or body frame).

    Candidate 0 is the current pose itself (the reference). The others turn the camera about the map's
    vertical axis by evenly spread yaw offsets in [-yaw_range, yaw_range] [rad] and shift it by Gaussian noise
    (``position_std`` horizontally, ``vertical_std`` vertically, metres).

    Returns:
        positions (num, 3) [m], quaternions (num, 4) xyzw, yaw offsets (num,) [rad].
    """
    R = quaternion_xyzw_to_matrix(quat_xyzw)
    yaws = np.zeros(num)
    if num > 1:
        yaws[1:] = np.linspace(-yaw_range, yaw_range, num - 1)
    positions = np.repeat(np.asarray(position, dtype=np.float64)[None], num, axis=0)
    quats = np.zeros((num, 4))
    for i, yaw in enumerate(yaws):
        if i > 0:
            positions[i, :2] += rng.normal(0.0, position_std, 2)
            positions[i, 2] += rng.normal(0.0, vertical_std)
        quats[i] = matrix_to_quaternion_xyzw(yaw_about_map_z(yaw) @ R)
    return positions, quats, yaws


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_nbv_client",
        description="Next-best-view loop over css_node's topics: take the latest pose (topic 'pose'), sample "
                    "candidate views around it, publish them as a PoseArray on 'candidates', receive "
                    "NODE/candidate_scores (matched by the request stamp) and publish the candidate with the "
                    "largest --metric (default: expected information gain) as a PoseStamped on "
                    "'next_best_view'. Topic names are relative (remappable with --ros-args -r).")
    p.add_argument("--node", type=node_name_arg(NODE_TOPICS), default="/css_node",
                   help="css_node's name with namespace (default /css_node)")
    p.add_argument("--num-candidates", type=bounded_number(1, MAX_NUM_CANDIDATES, integer=True), default=16,
                   help=f"candidates per request, incl. the current pose, 1..{MAX_NUM_CANDIDATES} (default 16; "
                        "css_node scores at most its max_candidates, default 256)")
    p.add_argument("--yaw-range", type=bounded_number(0.0, 180.0), default=90.0,
                   help="max yaw offset [deg], in [0, 180] (default 90)")
    p.add_argument("--position-std", type=bounded_number(0.0, MAX_STD_M), default=0.3,
                   help=f"horizontal position noise [m], in [0, {MAX_STD_M:g}] (default 0.3)")
    p.add_argument("--vertical-std", type=bounded_number(0.0, MAX_STD_M), default=0.0,
                   help=f"vertical position noise [m], in [0, {MAX_STD_M:g}] (default 0)")
    p.add_argument("--metric", choices=METRICS, default="info_gain",
                   help="score to maximise: info_gain (expected reduction of the map's uncertainty if the view "
                        "were observed), u_var or u_exp (the most uncertain view); NaN rows are never chosen "
                        "(default info_gain)")
    p.add_argument("--period", type=bounded_number(MIN_PERIOD_S, MAX_SECONDS), default=2.0,
                   help=f"seconds between requests, in [{MIN_PERIOD_S:g}, {MAX_SECONDS:g}] (default 2)")
    p.add_argument("--timeout", type=bounded_number(MIN_TIMEOUT_S, MAX_SECONDS), default=10.0,
                   help=f"seconds to wait for an answer (and, with --once, for a pose), in [{MIN_TIMEOUT_S:g}, "
                        f"{MAX_SECONDS:g}] "
                        "(default 10)")
    p.add_argument("--once", action="store_true", help="one request, print the result, exit (0 on success)")
    p.add_argument("--json", action="store_true", help="also print each chosen view as one JSON line on stdout "
                   "(index, yaw_deg, position, quat_xyzw, metric, u_var, u_exp, info_gain, current_*, stamp_ns, "
                   "latency_ms; NaN as null)")
    p.add_argument("--seed", type=bounded_number(0, 2**63 - 1, integer=True), default=0,
                   help="random seed of the position noise, >= 0 (default 0)")
    p.add_argument("--pose-type", choices=tuple(POSE_TYPES), default="pose_stamped",
                   help="message type on 'pose', as css_node's pose_type (default pose_stamped); candidates are "
                        "poses of the same frame (css_node applies its camera 0 extrinsics)")
    return p


class NbvClient:
    """rclpy node ``css_nbv_client`` doing the request / answer / publish loop."""

    def __init__(self, args: argparse.Namespace) -> None:
        import rclpy
        from geometry_msgs.msg import PoseArray, PoseStamped, PoseWithCovarianceStamped
        from nav_msgs.msg import Odometry
        from rclpy.qos import QoSProfile, ReliabilityPolicy, qos_profile_sensor_data
        from sensor_msgs.msg import PointCloud2

        self.args = args
        self.node = rclpy.create_node("css_nbv_client", cli_args=None)
        self.log = self.node.get_logger()
        self.warn = WarnLimiter(self.log.warning, WARN_PERIOD_S)
        self.rng = np.random.default_rng(args.seed)
        self.lock = threading.Lock()
        self.pose: Any = None
        self.replies: dict[int, Any] = {}
        # sensor-data QoS matches both best-effort and reliable pose publishers.
        pose_msg = {"pose_stamped": PoseStamped, "pose_with_covariance": PoseWithCovarianceStamped,
                    "odometry": Odometry}[args.pose_type]
        self.node.create_subscription(pose_msg, "pose", self._on_pose, qos_profile_sensor_data)
        self.sub_scores = self.node.create_subscription(PointCloud2, f"{args.node}/candidate_scores",
                                                        self._on_scores,
                                                        QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE))
        self.pub_candidates = self.node.create_publisher(PoseArray, "candidates", 10)
        self.pub_nbv = self.node.create_publisher(PoseStamped, "next_best_view", 10)
        self._stamp_last = 0

    def _on_pose(self, msg: Any) -> None:
        with self.lock:
            self.pose = msg

    def _on_scores(self, msg: Any) -> None:
        with self.lock:
            self.replies[stamp_to_ns(msg.header.stamp)] = msg

    def request(self) -> dict[str, Any] | None:
        """One request around the latest pose; returns the chosen candidate (or None)."""
        import rclpy
        from geometry_msgs.msg import PoseStamped

        from ..ros.conversions import header_msg, pose_array_msg, pose_msg

        with self.lock:
            pose = self.pose
        if pose is None:
            within = f" within {self.args.timeout:g} s" if self.args.once else " yet"
            self.warn("pose", f"no pose received{within} on {self.node.resolve_topic_name('pose')} "
                      f"({POSE_TYPES[self.args.pose_type]})", "start what publishes the camera pose (the robot's "
                      "localisation, or the demo player in another shell: css_demo --loops 10), remap the topic "
                      "with --ros-args -r pose:=/your/pose, or match its type with --pose-type", dropped=False)
            return None
        if self.pub_candidates.get_subscription_count() == 0:
            self.warn("candidates", f"nobody subscribes to {self.pub_candidates.topic_name}", "is css_node running?",
                      dropped=False)
            return None
        position, quat = pose_to_arrays(pose_message_pose(pose, self.args.pose_type).pose)
        positions, quats, yaws = sample_candidates(position, quat, self.args.num_candidates,
                                                   math.radians(self.args.yaw_range), self.args.position_std,
                                                   self.args.vertical_std, self.rng)
        # The request id is the header stamp: strictly increasing wall-clock time.
        stamp = max(self.node.get_clock().now().nanoseconds, self._stamp_last + 1)
        self._stamp_last = stamp
        frame = pose.header.frame_id or "map"
        self.pub_candidates.publish(pose_array_msg(positions, quats, header_msg(stamp, frame)))
        end = time.monotonic() + self.args.timeout
        reply = None
        while time.monotonic() < end and rclpy.ok():
            rclpy.spin_once(self.node, timeout_sec=0.05)
            with self.lock:
                reply = self.replies.pop(stamp, None)
            if reply is not None:
                break
        if reply is None:
            self.warn("candidate_scores", f"no answer on {self.args.node}/candidate_scores within "
                      f"{self.args.timeout:g} s", dropped=False)
            return None
        pts = unpack_scored_views(reply)
        if len(pts) != len(positions):
            self.warn("candidate_scores", "answer of another size than the request",
                      f"{len(pts)} points for {len(positions)} candidates", dropped=False)
            return None
        metric = self.args.metric
        if not has_field(reply, metric):
            self.warn("candidate_scores", f"{self.args.node}/candidate_scores has no field {metric}",
                      "a css_node older than it? use --metric u_var", dropped=False)
            return None
        best = best_candidate(pts[metric])
        if best is None:
            self.warn("candidate_scores", f"every candidate scored NaN on {metric}",
                      f"css_node answers NaN before its first camera_info, for requests above its max_candidates "
                      f"(this one: {len(positions)}), past its candidate_time_budget or with its request queue full; "
                      "its log and /diagnostics (requests_nan[<status>]) say which", dropped=False)
            return None
        out = PoseStamped(header=header_msg(stamp, frame), pose=pose_msg(positions[best], quats[best]))
        self.pub_nbv.publish(out)
        result: dict[str, Any] = {
            "index": best, "yaw_deg": math.degrees(yaws[best]), "position": positions[best].tolist(),
            "quat_xyzw": quats[best].tolist(), "metric": metric}
        for name in ("u_var", "u_exp", "info_gain"):
            result[name] = float(pts[name][best])
            result[f"current_{name}"] = float(pts[name][0])
        result.update(stamp_ns=stamp, latency_ms=(time.monotonic() - (end - self.args.timeout)) * 1e3)
        self.log.info(
            f"next best view (largest {metric}): candidate {best}/{len(positions)} yaw {result['yaw_deg']:+.0f} deg "
            f"at ({positions[best][0]:.2f}, {positions[best][1]:.2f}, {positions[best][2]:.2f}) m: "
            f"info gain {result['info_gain']:.4g} U_var {result['u_var']:.3e} U_exp {result['u_exp']:.3f} "
            f"(current view info gain {result['current_info_gain']:.4g} U_var {result['current_u_var']:.3e} "
            f"U_exp {result['current_u_exp']:.3f}); answer after {result['latency_ms']:.0f} ms")
        if self.args.json:
            print(json.dumps({k: _json_value(v) for k, v in result.items()}), flush=True)
        return result


def best_candidate(score: np.ndarray) -> int | None:
    """Index of the largest finite ``score`` (first of ties); None when no row is finite (NaN is never chosen)."""
    s = np.asarray(score, dtype=np.float64)
    ok = np.isfinite(s)
    return int(np.argmax(np.where(ok, s, -np.inf))) if ok.any() else None


def _json_value(v: Any) -> Any:
    """NaN / inf -> None (JSON has no NaN); lists element-wise."""
    if isinstance(v, list):
        return [_json_value(x) for x in v]
    if isinstance(v, float) and not math.isfinite(v):
        return None
    return v


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``css_nbv_client`` (ROS arguments after --ros-args are passed to rclpy)."""
    import rclpy
    from rclpy.executors import ExternalShutdownException
    from rclpy.utilities import remove_ros_args

    argv = list(sys.argv if argv is None else ["css_nbv_client", *argv])
    try:
        args = build_parser().parse_args(remove_ros_args(argv)[1:])
    except SystemExit as exc:   # argparse printed the usage and the option at fault
        return int(exc.code or 0)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as a generic RCLError
        print(f"css_nbv_client: error: cannot initialise ROS (check the --ros-args): {exc}", file=sys.stderr)
        return 2
    try:
        rclpy.init(args=argv)
    except Exception as exc:  # noqa: BLE001 - rcl reports bad --ros-args as a generic RCLError
        print(f"css_nbv_client: error: cannot initialise ROS (check the --ros-args): {exc}", file=sys.stderr)
        return 2
    client = NbvClient(args)
    code = 0
    try:
        if args.once:
            end = time.monotonic() + args.timeout
            # css_node answers from another DDS participant than the one its requests arrive on: both must have
            # matched this client before the one request goes out
            while (client.pose is None or client.pub_candidates.get_subscription_count() == 0
                   or client.sub_scores.get_publisher_count() == 0) and time.monotonic() < end:
                rclpy.spin_once(client.node, timeout_sec=0.1)
            time.sleep(0.3)  # let both ends of the candidates / scores pairs finish matching
            code = 0 if client.request() is not None else 1
        else:
            while rclpy.ok():
                t0 = time.monotonic()
                client.request()
                while rclpy.ok() and time.monotonic() - t0 < args.period:
                    rclpy.spin_once(client.node, timeout_sec=0.05)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    finally:
        client.node.destroy_node()
        rclpy.try_shutdown()
    return code


if __name__ == "__main__":
    sys.exit(main())
