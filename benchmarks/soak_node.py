"""Soak test of css_node: N minutes of realistic mixed traffic over real DDS, then SIGTERM (issue 11).

Starts ``python -m css_ros.node`` as a subprocess (own checkpoint in a temporary directory, checkpoint
every few seconds, log to a file) and drives it from one rclpy executor thread with:

- good frames at ~5 Hz: the demo bag's camera_info, pose, segmentation and confidence replayed in a
  loop with fresh stamps (one stamp per frame);
- bad frames at ~1 Hz, kinds drawn at random: wrong encoding, truncated data, size mismatch, NaN pose,
  non-unit quaternion, stale stamp, NaN confidence, zero-K camera_info, huge camera_info, fx = 1e300;
- candidate requests at ~1 Hz (16 poses) and a big one (256 poses) every 20 s;
- point queries at ~1 Hz (1000 points near the model's Gaussians);
- save_map every 30 s, load_map every 60 s, reset_map once in the middle.

Records frames sent / processed (~/view_uncertainty) / dropped per reason (/diagnostics counters),
request latency percentiles (candidates and point queries separately, unanswered requests counted),
the node's RSS every 10 s, exit code and time to exit after SIGTERM, and checks the final checkpoint
loads onto the model. Prints a summary table and writes a JSON summary (``--out``).

    python benchmarks/soak_node.py --minutes 10 --domain-id 91 --out /tmp/soak.json
"""
from __future__ import annotations

import argparse
import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

BAD_KINDS = ("wrong encoding", "truncated data", "size mismatch", "NaN pose", "non-unit quaternion",
             "stale stamp", "NaN confidence", "zero-K camera_info", "huge camera_info", "fx=1e300")
GOOD_HZ, BAD_HZ, CAND_HZ, QUERY_HZ = 5.0, 1.0, 1.0, 1.0
BIG_CAND_PERIOD, SAVE_PERIOD, LOAD_PERIOD, RSS_PERIOD = 20.0, 30.0, 60.0, 10.0
SMALL_CAND, BIG_CAND, QUERY_POINTS = 16, 256, 1000


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--minutes", type=float, default=10.0, help="duration of the traffic (default 10)")
    ap.add_argument("--domain-id", type=int, default=91, help="ROS_DOMAIN_ID of node and driver (default 91)")
    ap.add_argument("--out", type=Path, default=None, help="write the JSON summary here")
    ap.add_argument("--model", type=Path, default=REPO / "bags/demo/model.ply", help="3DGS PLY (default: demo)")
    ap.add_argument("--class-file", type=Path, default=REPO / "bags/demo/classes.yaml",
                    help="class YAML (default: demo classes)")
    ap.add_argument("--bag", type=Path, default=REPO / "bags/demo/bag",
                    help="bag whose camera_info/pose/segmentation/confidence are replayed (default: demo bag)")
    ap.add_argument("--checkpoint-period", type=float, default=5.0, help="node checkpoint_period [s] (default 5)")
    ap.add_argument("--input-qos", choices=("reliable", "sensor_data"), default="reliable",
                    help="node input QoS (default reliable: every frame sent is accounted for)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--keep", action="store_true", help="keep the temporary directory (log, checkpoint)")
    return ap.parse_args(argv)


# ----------------------------------------------------------------------------- helpers
def percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p90": None, "p99": None, "max": None}
    a = np.asarray(values)
    return {"p50": float(np.percentile(a, 50)), "p90": float(np.percentile(a, 90)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def rss_mb(pid: int) -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    except OSError:
        return None
    return None


def load_frames(bag: Path) -> list[dict[str, Any]]:
    """The bag's frames as rclpy messages, grouped by stamp: camera_info, pose, segmentation, confidence."""
    from css_ros.io.bag import InputBag
    from css_ros.io.messages import stamp_to_ns
    from css_ros.ros.conversions import to_rclpy

    kinds = {"/camera_info": "camera_info", "/pose": "pose", "/segmentation": "segmentation",
             "/segmentation_confidence": "confidence"}
    by_stamp: dict[int, dict[str, Any]] = {}
    with InputBag(bag) as b:
        for m in b.messages(list(kinds)):
            by_stamp.setdefault(stamp_to_ns(m.msg.header.stamp), {})[kinds[m.topic]] = to_rclpy(m.msg, None)
    frames = [by_stamp[s] for s in sorted(by_stamp) if len(by_stamp[s]) == len(kinds)]
    if not frames:
        raise SystemExit(f"no complete frames in {bag}")
    return frames


class Driver:
    """rclpy client on its own context: publishers, recorders and service clients; one executor thread."""

    def __init__(self, domain_id: int) -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseArray, PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image, PointCloud2
        from std_srvs.srv import Trigger

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(f"css_soak_driver_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        qos = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        n = self.node
        self.pub = {"camera_info": n.create_publisher(CameraInfo, "camera_info", qos),
                    "pose": n.create_publisher(PoseStamped, "pose", qos),
                    "segmentation": n.create_publisher(Image, "segmentation", qos),
                    "confidence": n.create_publisher(Image, "segmentation_confidence", qos),
                    "candidates": n.create_publisher(PoseArray, "candidates", 10),
                    "point_queries": n.create_publisher(PointCloud2, "point_queries", 10)}
        qos_out = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE)
        # stamp_ns -> receive time (monotonic) and, for answers, the NaN fraction
        self.views: dict[int, float] = {}
        self.cand_answers: dict[int, tuple[float, int, int]] = {}
        self.query_answers: dict[int, tuple[float, int, int]] = {}
        self.diag: dict[str, str] = {}
        self.diag_count = 0
        n.create_subscription(PointCloud2, "/css_node/view_uncertainty", self._on_view, qos_out)
        n.create_subscription(PointCloud2, "/css_node/candidate_scores", self._on_cand, qos_out)
        n.create_subscription(PointCloud2, "/css_node/point_query_results", self._on_query, qos_out)
        n.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos_out)
        self.srv = {name: n.create_client(Trigger, f"/css_node/{name}") for name in ("save_map", "load_map",
                                                                                      "reset_map")}
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - context shut down
            pass

    @staticmethod
    def _stamp(msg: Any) -> int:
        return int(msg.header.stamp.sec) * 10**9 + int(msg.header.stamp.nanosec)

    def _on_view(self, msg: Any) -> None:
        with self.lock:
            self.views.setdefault(self._stamp(msg), time.monotonic())

    def _on_cand(self, msg: Any) -> None:
        from css_ros.io.messages import unpack_view_points

        pts = unpack_view_points(msg)
        with self.lock:
            self.cand_answers.setdefault(self._stamp(msg), (time.monotonic(), len(pts),
                                                            int(np.count_nonzero(np.isnan(pts["u_var"])))))

    def _on_query(self, msg: Any) -> None:
        from css_ros.io.clouds import unpack_cloud

        try:
            pts = unpack_cloud(msg, ("expectation",))
            n, nan = len(pts), int(np.count_nonzero(~np.isfinite(pts["expectation"])))
        except Exception:  # noqa: BLE001 - an unreadable answer counts as all-unknown
            n, nan = int(msg.width) * int(msg.height), -1
        with self.lock:
            self.query_answers.setdefault(self._stamp(msg), (time.monotonic(), n, nan))

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name.startswith("css_node"):
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}
                    self.diag_count += 1

    def connected(self) -> bool:
        from css_ros.ros.conversions import header_msg  # noqa: F401 - import early (not on the hot path)

        subs = all(p.get_subscription_count() > 0 for p in self.pub.values())
        return subs and self.node.count_publishers("/css_node/view_uncertainty") > 0 and \
            all(c.service_is_ready() for c in self.srv.values())

    def call_async(self, name: str) -> Any:
        from std_srvs.srv import Trigger

        return self.srv[name].call_async(Trigger.Request())

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(5.0)


# ----------------------------------------------------------------------------- traffic
class Traffic:
    """Builds and publishes good frames, bad frames and requests."""

    def __init__(self, drv: Driver, frames: list[dict[str, Any]], means: np.ndarray, rng: random.Random) -> None:
        self.drv, self.frames, self.means, self.rng = drv, frames, means, rng
        self.np_rng = np.random.default_rng(rng.randrange(2**32))
        self.i = 0
        self.last_stamp = 0
        self.good_sent: dict[int, float] = {}
        self.bad_sent: dict[str, int] = {k: 0 for k in BAD_KINDS}
        self.bad_stamps: dict[int, str] = {}
        self.last_good = 0
        self.cand_sent: dict[int, tuple[float, int]] = {}
        self.query_sent: dict[int, float] = {}
        self.poses = np.array([[f["pose"].pose.position.x, f["pose"].pose.position.y, f["pose"].pose.position.z,
                                f["pose"].pose.orientation.x, f["pose"].pose.orientation.y,
                                f["pose"].pose.orientation.z, f["pose"].pose.orientation.w] for f in frames])

    def stamp(self) -> int:
        """A fresh stamp (wall clock, what the node's clock runs on), strictly increasing."""
        s = max(time.time_ns(), self.last_stamp + 1_000_000)
        self.last_stamp = s
        return s

    @staticmethod
    def _restamp(msg: Any, stamp_ns: int) -> Any:
        msg.header.stamp.sec, msg.header.stamp.nanosec = stamp_ns // 10**9, stamp_ns % 10**9
        return msg

    def _publish_frame(self, f: dict[str, Any], stamp_ns: int) -> None:
        for kind in ("camera_info", "pose", "confidence", "segmentation"):
            if kind in f:
                self.drv.pub[kind].publish(self._restamp(f[kind], stamp_ns))

    def next_frame(self) -> dict[str, Any]:
        f = self.frames[self.i % len(self.frames)]
        self.i += 1
        return f

    def good(self) -> None:
        s = self.stamp()
        self._publish_frame(self.next_frame(), s)
        self.good_sent[s] = time.monotonic()
        self.last_good = s

    def bad(self) -> str:
        from geometry_msgs.msg import PoseStamped
        from sensor_msgs.msg import CameraInfo, Image

        kind = self.rng.choice(BAD_KINDS)
        self.bad_sent[kind] += 1
        base = self.frames[self.rng.randrange(len(self.frames))]
        f = dict(base)

        def copy_image(msg: Image) -> Image:
            out = Image(header=msg.header, height=msg.height, width=msg.width, encoding=msg.encoding,
                        is_bigendian=msg.is_bigendian, step=msg.step)
            out.data = bytes(msg.data)
            return out

        def copy_info(msg: CameraInfo) -> CameraInfo:
            return CameraInfo(header=msg.header, width=msg.width, height=msg.height,
                              distortion_model=msg.distortion_model, d=list(msg.d), k=list(msg.k), r=list(msg.r),
                              p=list(msg.p))

        def copy_pose(msg: PoseStamped) -> PoseStamped:
            out = PoseStamped(header=msg.header)
            p, q = msg.pose.position, msg.pose.orientation
            out.pose.position.x, out.pose.position.y, out.pose.position.z = p.x, p.y, p.z
            out.pose.orientation.x, out.pose.orientation.y = q.x, q.y
            out.pose.orientation.z, out.pose.orientation.w = q.z, q.w
            return out

        # Half-way between two good frames: further from them than sync_slop (50 ms), so a bad frame's
        # parts never pair with a good frame's.
        s = max(self.last_good + 100_000_000, self.last_stamp + 1_000_000)
        self.last_stamp = s
        self.bad_stamps[s] = kind
        if kind == "wrong encoding":
            f["segmentation"] = seg = copy_image(base["segmentation"])
            seg.encoding = "yuv422_bogus"
        elif kind == "truncated data":
            f["segmentation"] = seg = copy_image(base["segmentation"])
            seg.data = bytes(base["segmentation"].data)[: len(seg.data) // 2]
        elif kind == "size mismatch":
            from css_ros.ros.conversions import header_msg, image_msg
            from css_ros.io.messages import image_to_array

            labels = image_to_array(base["segmentation"])
            conf = image_to_array(base["confidence"])
            f["segmentation"] = image_msg(np.ascontiguousarray(labels[::2, ::2]), "mono8", header_msg(s, "camera"))
            f["confidence"] = image_msg(np.ascontiguousarray(conf[::2, ::2]), "32FC1", header_msg(s, "camera"))
        elif kind == "NaN pose":
            f["pose"] = pose = copy_pose(base["pose"])
            pose.pose.position.x = float("nan")
        elif kind == "non-unit quaternion":
            f["pose"] = pose = copy_pose(base["pose"])
            q = pose.pose.orientation
            q.x, q.y, q.z, q.w = 2 * q.x, 2 * q.y, 2 * q.z, 2 * q.w
        elif kind == "stale stamp":
            s = self.last_stamp - 30 * 10**9  # out of order (one at a time: never 5 in a row)
        elif kind == "NaN confidence":
            from css_ros.ros.conversions import header_msg, image_msg
            from css_ros.io.messages import image_to_array

            conf = image_to_array(base["confidence"]).copy()
            conf[: conf.shape[0] // 4] = np.nan
            f["confidence"] = image_msg(conf.astype(np.float32), "32FC1", header_msg(s, "camera"))
        else:  # camera_info kinds: only the bad camera_info (the previous valid one stays in use)
            info = copy_info(base["camera_info"])
            if kind == "zero-K camera_info":
                info.k = [0.0] * 9
            elif kind == "huge camera_info":
                info.width, info.height = 100_000, 100_000
            else:  # fx=1e300
                k = list(info.k)
                k[0] = 1e300
                info.k = k
            self.drv.pub["camera_info"].publish(self._restamp(info, s))
            return kind
        self._publish_frame(f, s)
        return kind

    def candidates(self, m: int) -> None:
        from css_ros.ros.conversions import header_msg, pose_array_msg

        idx = self.np_rng.integers(0, len(self.poses), m)
        pos = self.poses[idx, :3] + self.np_rng.normal(0, 0.2, (m, 3))
        quats = self.poses[idx, 3:]
        s = self.stamp()
        msg = pose_array_msg(pos, quats, header_msg(s, "map"))
        self.cand_sent[s] = (time.monotonic(), m)
        self.drv.pub["candidates"].publish(msg)

    def point_query(self) -> None:
        from css_ros.io.clouds import pack_cloud
        from css_ros.ros.conversions import cloud_msg, header_msg

        idx = self.np_rng.integers(0, len(self.means), QUERY_POINTS)
        xyz = (self.means[idx] + self.np_rng.normal(0, 0.02, (QUERY_POINTS, 3))).astype(np.float32)
        s = self.stamp()
        msg = cloud_msg(header_msg(s, "map"), pack_cloud({"x": xyz[:, 0], "y": xyz[:, 1], "z": xyz[:, 2]}))
        self.query_sent[s] = time.monotonic()
        self.drv.pub["point_queries"].publish(msg)


# ----------------------------------------------------------------------------- main
def node_env(domain_id: int) -> dict[str, str]:
    env = dict(os.environ)
    env["ROS_DOMAIN_ID"] = str(domain_id)
    env["PYTHONPATH"] = os.pathsep.join([str(REPO), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    env.setdefault("RMW_IMPLEMENTATION", "rmw_fastrtps_cpp")
    env["PYTHONUNBUFFERED"] = "1"
    env["RCUTILS_COLORIZED_OUTPUT"] = "0"
    return env


def latency_summary(sent: dict[int, Any], answers: dict[int, tuple[float, int, int]]) -> dict[str, Any]:
    lat, nan_rows, rows, partial = [], 0, 0, 0
    for s, v in sent.items():
        t0 = v[0] if isinstance(v, tuple) else v
        if s in answers:
            t, n, nan = answers[s]
            lat.append((t - t0) * 1e3)
            rows += n
            nan_rows += max(nan, 0)
            partial += nan != 0
    return {"sent": len(sent), "answered": len(lat), "unanswered": len(sent) - len(lat),
            "answers_with_nan_rows": partial, "nan_rows": nan_rows, "rows": rows,
            "latency_ms": percentiles(lat)}


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    os.environ["ROS_DOMAIN_ID"] = str(args.domain_id)
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap

    rng = random.Random(args.seed)
    tmp = Path(tempfile.mkdtemp(prefix="css_soak_"))
    ckpt, log_path = tmp / "map.npz", tmp / "css_node.log"
    print(f"soak: {args.minutes:g} min, domain {args.domain_id}, model {args.model}, work dir {tmp}", flush=True)
    model = GaussianModel.from_ply(args.model)
    frames = load_frames(args.bag)
    print(f"soak: {len(frames)} bag frames, {model.num_gaussians} Gaussians", flush=True)

    params = {"model_path": str(args.model), "class_file": str(args.class_file), "checkpoint_path": str(ckpt),
              "checkpoint_period": args.checkpoint_period, "resume": False, "log_period": 2.0,
              "input_qos": args.input_qos}
    cmd = [sys.executable, "-m", "css_ros.node", "--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={str(v).lower() if isinstance(v, bool) else v}"]
    log = open(log_path, "ab")
    t_start = time.monotonic()
    proc = subprocess.Popen(cmd, env=node_env(args.domain_id), stdout=log, stderr=subprocess.STDOUT, cwd=str(tmp))
    drv = Driver(args.domain_id)
    summary: dict[str, Any] = {"minutes": args.minutes, "domain_id": args.domain_id, "model": str(args.model),
                               "machine": {"cpus": os.cpu_count()}, "problems": []}
    problems: list[str] = summary["problems"]
    rss: list[tuple[float, float]] = []
    services: dict[str, list[dict[str, Any]]] = {"save_map": [], "load_map": [], "reset_map": []}
    pending_srv: list[tuple[str, float, Any]] = []
    try:
        end = time.monotonic() + 120
        while not drv.connected():
            if proc.poll() is not None or time.monotonic() > end:
                raise SystemExit(f"node did not come up (rc {proc.poll()}); log:\n{log_path.read_text()[-3000:]}")
            time.sleep(0.1)
        time.sleep(1.0)
        startup_s = time.monotonic() - t_start
        print(f"soak: node up after {startup_s:.1f} s (pid {proc.pid}); traffic for {args.minutes:g} min",
              flush=True)
        tr = Traffic(drv, frames, model.means, rng)
        duration = args.minutes * 60.0
        t0 = time.monotonic()
        nxt = {"good": t0, "bad": t0 + 0.5 + 0.1, "cand": t0 + 0.3, "big": t0 + BIG_CAND_PERIOD, "query": t0 + 0.7,
               "save": t0 + SAVE_PERIOD, "load": t0 + LOAD_PERIOD + 5.0, "reset": t0 + duration / 2,
               "rss": t0, "print": t0 + 60.0}
        reset_done = False
        while True:
            now = time.monotonic()
            el = now - t0
            if el >= duration:
                break
            if proc.poll() is not None:
                problems.append(f"node exited during the soak with code {proc.returncode} at {el:.0f} s")
                break
            if now >= nxt["good"]:
                tr.good()
                nxt["good"] += 1.0 / GOOD_HZ
            if now >= nxt["bad"]:
                tr.bad()
                # next one 0.5-1.5 s later, snapped half-way between two good frames
                t = nxt["bad"] + rng.uniform(0.5, 1.5) / BAD_HZ - t0
                nxt["bad"] = t0 + 0.1 + round((t - 0.1) * GOOD_HZ) / GOOD_HZ
            if now >= nxt["cand"]:
                tr.candidates(SMALL_CAND)
                nxt["cand"] += 1.0 / CAND_HZ
            if now >= nxt["big"]:
                tr.candidates(BIG_CAND)
                nxt["big"] += BIG_CAND_PERIOD
            if now >= nxt["query"]:
                tr.point_query()
                nxt["query"] += 1.0 / QUERY_HZ
            for name, key, period in (("save_map", "save", SAVE_PERIOD), ("load_map", "load", LOAD_PERIOD)):
                if now >= nxt[key]:
                    pending_srv.append((name, now, drv.call_async(name)))
                    nxt[key] += period
            if not reset_done and now >= nxt["reset"]:
                pending_srv.append(("reset_map", now, drv.call_async("reset_map")))
                reset_done = True
            for item in list(pending_srv):
                name, ts, fut = item
                if fut.done():
                    res = fut.result()
                    services[name].append({"t_s": round(ts - t0, 1), "latency_ms": (time.monotonic() - ts) * 1e3,
                                           "success": bool(res.success), "message": res.message})
                    pending_srv.remove(item)
            if now >= nxt["rss"]:
                r = rss_mb(proc.pid)
                if r is not None:
                    rss.append((el, r))
                nxt["rss"] += RSS_PERIOD
            if now >= nxt["print"]:
                with drv.lock:
                    nv, nc, nq = len(drv.views), len(drv.cand_answers), len(drv.query_answers)
                print(f"soak: {el / 60:4.1f} min: sent {len(tr.good_sent)} good, processed {nv}, candidate "
                      f"answers {nc}/{len(tr.cand_sent)}, query answers {nq}/{len(tr.query_sent)}, "
                      f"RSS {rss[-1][1] if rss else float('nan'):.0f} MiB", flush=True)
                nxt["print"] += 60.0
            time.sleep(0.005)
        # Drain: no more traffic; wait for the answers still in flight (up to 30 s).
        drain_end = time.monotonic() + 30.0

        def outstanding() -> int:
            with drv.lock:
                return (sum(s not in drv.cand_answers for s in tr.cand_sent)
                        + sum(s not in drv.query_answers for s in tr.query_sent))
        while (outstanding() or pending_srv) and time.monotonic() < drain_end and proc.poll() is None:
            for item in list(pending_srv):
                name, ts, fut = item
                if fut.done():
                    res = fut.result()
                    services[name].append({"t_s": round(ts - t0, 1), "latency_ms": (time.monotonic() - ts) * 1e3,
                                           "success": bool(res.success), "message": res.message})
                    pending_srv.remove(item)
            time.sleep(0.05)
        for name, ts, _ in pending_srv:
            services[name].append({"t_s": round(ts - t0, 1), "latency_ms": None, "success": False,
                                   "message": "no answer"})
            problems.append(f"{name} called at {ts - t0:.0f} s never answered")
        time.sleep(2.5)  # one more diagnostics message (log_period 2 s)
        with drv.lock:
            diag_final = dict(drv.diag)
        # SIGTERM
        exit_code, exit_s = None, None
        if proc.poll() is None:
            ts = time.monotonic()
            proc.send_signal(signal.SIGTERM)
            try:
                exit_code = proc.wait(30.0)
                exit_s = time.monotonic() - ts
            except subprocess.TimeoutExpired:
                problems.append("node did not exit within 30 s of SIGTERM (killed)")
                proc.kill()
                proc.wait(10)
        else:
            exit_code = proc.returncode
        time.sleep(1.0)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
        log.close()
        with drv.lock:
            views, cand_ans, query_ans = dict(drv.views), dict(drv.cand_answers), dict(drv.query_answers)
        drv.close()

    # -------------------------------------------------------------- final checkpoint
    ckpt_info: dict[str, Any] = {"path": str(ckpt), "exists": ckpt.is_file()}
    try:
        smap = SemanticMap.load(ckpt, model)
        ckpt_info.update(valid=True, frames_observed=int(smap.frames_observed), bytes=ckpt.stat().st_size)
        if smap.frames_observed <= 0:
            problems.append("final checkpoint has frames_observed == 0")
    except Exception as exc:  # noqa: BLE001 - report any failure
        ckpt_info.update(valid=False, error=f"{type(exc).__name__}: {exc}")
        problems.append(f"final checkpoint invalid: {exc}")
    node_log = log_path.read_text(errors="replace")
    ckpt_info["shutdown_checkpoint_logged"] = "checkpoint (shutdown) written" in node_log
    if exit_code != 0:
        problems.append(f"exit code {exit_code} after SIGTERM")
    tracebacks = node_log.count("Traceback")
    if tracebacks:
        problems.append(f"{tracebacks} Python traceback(s) in the node log")

    # -------------------------------------------------------------- figures
    processed = sum(s in views for s in tr.good_sent)
    bad_processed: dict[str, int] = {}
    for s, kind in tr.bad_stamps.items():
        if s in views:
            bad_processed[kind] = bad_processed.get(kind, 0) + 1
    diag_num = {}
    for k, v in diag_final.items():
        try:
            diag_num[k] = float(v)
        except ValueError:
            diag_num[k] = v
    drops = {k: v for k, v in diag_num.items() if (k.startswith(("warn[", "dropped[", "requests_nan["))
             or k in ("frames_dropped_busy", "requests_dropped_busy", "clock_resets", "worker_errors",
                      "confidence_pixels_non_finite", "checkpoint_failures"))}
    cand = latency_summary(tr.cand_sent, cand_ans)
    cand_small = latency_summary({s: v for s, v in tr.cand_sent.items() if v[1] == SMALL_CAND}, cand_ans)
    cand_big = latency_summary({s: v for s, v in tr.cand_sent.items() if v[1] == BIG_CAND}, cand_ans)
    query = latency_summary(tr.query_sent, query_ans)
    for name, q in (("candidate", cand), ("point query", query)):
        if q["unanswered"]:
            problems.append(f"{q['unanswered']} of {q['sent']} {name} requests unanswered")
    rss_vals = [r for _, r in rss]
    first = [r for t, r in rss if t < 60.0]
    last = [r for t, r in rss if t >= rss[-1][0] - 60.0] if rss else []
    rss_info = {"samples": [[round(t, 1), round(r, 1)] for t, r in rss],
                "min_mb": min(rss_vals) if rss_vals else None, "max_mb": max(rss_vals) if rss_vals else None,
                "first_minute_mean_mb": float(np.mean(first)) if first else None,
                "last_minute_mean_mb": float(np.mean(last)) if last else None}
    if first and last:
        rss_info["growth_mb"] = rss_info["last_minute_mean_mb"] - rss_info["first_minute_mean_mb"]
    summary.update({
        "startup_s": startup_s,
        "frames": {"good_sent": len(tr.good_sent), "processed": processed,
                   "processed_total_view_uncertainty": len(views), "bad_sent": tr.bad_sent,
                   "bad_sent_total": sum(tr.bad_sent.values()),
                   "bad_processed": bad_processed},
        "drops": drops, "candidates": cand, "candidates_16": cand_small, "candidates_256": cand_big,
        "point_queries": query, "services": services, "rss": rss_info,
        "shutdown": {"exit_code": exit_code, "exit_s": exit_s}, "checkpoint": ckpt_info,
        "diagnostics_final": diag_final, "node_log": str(log_path),
    })

    def fmt(v: Any) -> str:
        return "-" if v is None else f"{v:.0f}" if isinstance(v, float) else str(v)

    lines = ["", "=" * 78, f"css_node soak test: {args.minutes:g} min, node pid {proc.pid}", "=" * 78,
             f"start-up (launch -> connected)          {startup_s:.1f} s",
             f"good frames sent / processed            {len(tr.good_sent)} / {processed} "
             f"({100.0 * processed / max(1, len(tr.good_sent)):.1f} %)",
             f"frames_dropped_busy                     {fmt(diag_num.get('frames_dropped_busy', 0.0))}",
             f"bad frames sent                         {sum(tr.bad_sent.values())}: "
             + ", ".join(f"{k} {v}" for k, v in tr.bad_sent.items()),
             f"bad frames processed (kept)             {sum(bad_processed.values())}: "
             + (", ".join(f"{k} {v}" for k, v in bad_processed.items()) or "none"),
             "drop / refusal counters (/diagnostics):"]
    for k, v in sorted(drops.items()):
        lines.append(f"  {k:<60s} {fmt(v)}")
    lines.append("requests                 sent  answered  unanswered  with NaN rows  p50 / p90 / p99 / max [ms]")
    for name, q in (("candidates (all)", cand), ("  16 poses", cand_small), ("  256 poses", cand_big),
                    ("point queries (1000)", query)):
        lat = q["latency_ms"]
        lines.append(f"  {name:<22s} {q['sent']:5d} {q['answered']:9d} {q['unanswered']:11d} "
                     f"{q['answers_with_nan_rows']:14d}  {fmt(lat['p50'])} / {fmt(lat['p90'])} / "
                     f"{fmt(lat['p99'])} / {fmt(lat['max'])}")
    for name, calls in services.items():
        ok = sum(c["success"] for c in calls)
        lat = [c["latency_ms"] for c in calls if c["latency_ms"] is not None]
        lines.append(f"service {name:<10s} calls {len(calls):3d}, success {ok:3d}, "
                     f"max latency {fmt(max(lat) if lat else None)} ms"
                     + (f"  (failures: {sorted({c['message'][:60] for c in calls if not c['success']})})"
                        if ok < len(calls) else ""))
    lines += [f"node RSS [MiB]                          min {fmt(rss_info['min_mb'])}, max {fmt(rss_info['max_mb'])}, "
              f"first-minute mean {fmt(rss_info['first_minute_mean_mb'])}, last-minute mean "
              f"{fmt(rss_info['last_minute_mean_mb'])}, growth {rss_info.get('growth_mb', float('nan')):+.1f}",
              f"SIGTERM: exit code {exit_code}, exit after {fmt(None if exit_s is None else round(exit_s, 2))} s"
              if exit_s is None else f"SIGTERM: exit code {exit_code}, exit after {exit_s:.2f} s",
              f"final checkpoint: valid {ckpt_info.get('valid')}, frames_observed "
              f"{ckpt_info.get('frames_observed')}, shutdown checkpoint written "
              f"{ckpt_info['shutdown_checkpoint_logged']}",
              "problems: " + ("none" if not problems else "; ".join(problems)), "=" * 78]
    print("\n".join(lines), flush=True)
    summary["table"] = lines
    if args.out:
        args.out.write_text(json.dumps(summary, indent=2, default=str))
        print(f"JSON summary: {args.out}")
    if not args.keep and not problems:
        import shutil
        shutil.rmtree(tmp, ignore_errors=True)
    else:
        print(f"work dir kept: {tmp}")
    return 1 if problems else 0


if __name__ == "__main__":
    sys.exit(main())
