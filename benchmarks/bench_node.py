"""css_node end to end: a 30 Hz camera into a real node on a splat, every output subscribed, timed per stage.

    python benchmarks/bench_node.py                       # backend cuda on a CUDA GPU, else the engine stubbed
    python benchmarks/bench_node.py --backend cuda        # the node on the GPU (needs one)
    python benchmarks/bench_node.py --engine-stub         # the node's own work only, on the CPU
    python benchmarks/bench_node.py --gaussians 2000 --width 64 --height 48 --classes 4 --frames 10 --json out.json

The scene is bench_frame's "1M" scene by default (the procedural room, 1M Gaussians with SH degree 3 colour, KITTI
intrinsics at 1241x376, 19 classes), written as a PLY that css_node loads. The node runs as its own process
(``benchmarks/node_harness.py``: css_node's entry point with per-stage timers, ``--engine-stub`` replacing
``SemanticMap.observe`` by a view returned at once). This process plays the camera at ``--rate`` Hz over DDS:
per frame a camera_info, a PoseStamped (the robot path of the room; ``--poses`` poses, looped) and a mono8
segmentation with one stamp (the publish time), reliable QoS. Segmentations are ground truth rendered on the GPU
before the node starts when the backend is cuda, else blocks of 32x32 pixels of random classes (5 % unlabelled):
the stub does not look at them and the node's own work does not depend on their content.

It subscribes to every output topic of the node (``~/semantic``, ``~/semantic_color``, ``~/expectation``,
``~/variance``, ``~/rendered_image``, ``~/view_uncertainty``, ``~/candidate_scores``, ``~/semantic_cloud``,
``~/point_query_results``, and ``~/confidence`` when the node has it) as raw (serialised) messages, reading only
each header's stamp, and waits until the node's diagnostics count those subscribers before the first frame.

Prints: frames sent / completed (every per-frame output received), frames/s, end-to-end latency percentiles (input
stamp -> last output of the frame received here), the node's own time per frame (rclpy taking the input messages,
its input callbacks with the label decode, the worker's frame minus the engine's observe, of which the output
messages and their publishing) beside the observe, the node process's CPU time per frame (all threads) and the work
between frames (live-view stream, semantic cloud, status). The first ``--warmup`` frames are not counted.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import struct
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
sys.path.insert(0, str(Path(__file__).resolve().parent))

from soak_node import node_env  # noqa: E402  (the environment of a css_node process, one definition)

HARNESS = Path(__file__).resolve().parent / "node_harness.py"
#: Stages of the node's own work per frame, as the harness names them (see node_harness.py).
OWN_STAGES = ("take", "callback", "decode", "worker_other", "publish_frame", "images", "image_msgs", "view_msg",
              "publish")
#: The node's own work per frame that the GPU work item allows [ms].
OWN_TARGET_MS = 3.0
#: Side of the label blocks of the synthetic segmentations [px], and their unlabelled share.
BLOCK_PX, UNLABELLED_SHARE = 32, 0.05
IGNORE_LABEL = 255


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--backend", choices=("auto", "cuda", "numba", "torch"), default="auto",
                    help="css_node's backend (auto: cuda when a CUDA GPU is present, else numba with the engine stub)")
    stub = ap.add_mutually_exclusive_group()
    stub.add_argument("--engine-stub", dest="engine_stub", action="store_true", default=None,
                      help="replace SemanticMap.observe by a view returned at once (default without a GPU)")
    stub.add_argument("--no-engine-stub", dest="engine_stub", action="store_false",
                      help="run the real engine even without a GPU (numba: ~3 frames/s at 1M on 2 cores)")
    ap.add_argument("--gaussians", type=int, default=1_000_000, help="Gaussians of the room (default 1M)")
    ap.add_argument("--width", type=int, default=1241, help="image width [px] (default 1241, KITTI)")
    ap.add_argument("--height", type=int, default=376, help="image height [px] (default 376)")
    ap.add_argument("--classes", type=int, default=19, help="number of classes (default 19)")
    ap.add_argument("--rate", type=float, default=30.0, help="camera rate [Hz] (default 30)")
    ap.add_argument("--frames", type=int, default=300, help="timed frames (default 300: 10 s at 30 Hz)")
    ap.add_argument("--warmup", type=int, default=15, help="frames sent first and not counted (default 15)")
    ap.add_argument("--poses", type=int, default=90, help="distinct poses along the room's path, looped (default 90)")
    ap.add_argument("--labels", choices=("auto", "gt", "blocks"), default="auto",
                    help="segmentations: gt (rendered on the GPU), blocks (synthetic); auto: gt with cuda")
    ap.add_argument("--model", type=Path, default=None,
                    help="use this PLY (written by an earlier run with --keep) instead of building the room")
    ap.add_argument("--domain-id", type=int, default=int(os.environ.get("ROS_DOMAIN_ID", "102")),
                    help="ROS_DOMAIN_ID of node and player (default $ROS_DOMAIN_ID or 102)")
    ap.add_argument("--node-param", action="append", default=[], metavar="NAME:=VALUE",
                    help="extra css_node parameter (repeatable)")
    ap.add_argument("--start-timeout", type=float, default=300.0,
                    help="longest wait [s] for the node to come up and see the subscribers (default 300)")
    ap.add_argument("--drain-timeout", type=float, default=30.0,
                    help="longest wait [s] for outputs after the last frame while none arrive (default 30)")
    ap.add_argument("--json", type=Path, default=None, help="write the results here")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (PLY, node log, stage records)")
    return ap.parse_args(argv)


def cuda_available() -> bool:
    try:
        from numba import cuda
        return bool(cuda.is_available())
    except Exception:  # noqa: BLE001 - no numba-cuda, no driver: no GPU
        return False


def percentiles(values: list[float] | np.ndarray) -> dict[str, float]:
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0:
        return {k: float("nan") for k in ("mean", "p50", "p90", "p99", "max")}
    return {"mean": float(a.mean()), "p50": float(np.percentile(a, 50)), "p90": float(np.percentile(a, 90)),
            "p99": float(np.percentile(a, 99)), "max": float(a.max())}


def block_labels(height: int, width: int, classes: int, seed: int) -> np.ndarray:
    """(H, W) uint8 segmentation: BLOCK_PX-square blocks of random classes, UNLABELLED_SHARE of them IGNORE_LABEL."""
    rng = np.random.default_rng(seed)
    bh, bw = -(-height // BLOCK_PX), -(-width // BLOCK_PX)
    blocks = rng.integers(0, classes, (bh, bw)).astype(np.uint8)
    blocks[rng.random((bh, bw)) < UNLABELLED_SHARE] = IGNORE_LABEL
    return np.ascontiguousarray(np.kron(blocks, np.ones((BLOCK_PX, BLOCK_PX), np.uint8))[:height, :width])


def gt_labels(model: Any, gt: np.ndarray, cams: list, classes: int, backend: str) -> list[np.ndarray]:
    """Ground-truth segmentations at ``cams`` (the map holding each Gaussian's class), rendered with ``backend``."""
    from css_ros import SemanticMap

    smap = SemanticMap(model, classes, backend=backend)  # type: ignore[arg-type]
    conc = np.full((model.num_gaussians, classes), 1e-3)
    conc[np.arange(model.num_gaussians), gt % classes] = 1e3
    smap.concentrations = conc
    out = [np.where(v.labels < classes, v.labels, IGNORE_LABEL).astype(np.uint8)
           for v in (smap.render(c, outputs=("labels",)) for c in cams)]
    del smap
    try:
        import torch
        torch.cuda.empty_cache()
    except Exception:  # noqa: BLE001 - the GPU memory goes back when this process ends anyway
        pass
    return out


def path_cameras(cfg: dict[str, Any], count: int) -> list:
    """The cameras of bench_frame.build_scene (the room's robot path, ``count`` poses) without building the model."""
    from bench_frame import intrinsics

    from css_ros import Camera
    from css_ros.demo.trajectory import robot_trajectory

    K = intrinsics(cfg["width"], cfg["height"], cfg["kitti"])
    return [Camera(K, cfg["width"], cfg["height"], T) for T in robot_trajectory(count, seed=0).T_map_cam]


def cdr_stamp(data: bytes) -> int:
    """Header stamp [ns] of a serialised message whose first field is a std_msgs/Header (CDR, after the 4-byte
    encapsulation: int32 sec, uint32 nanosec)."""
    little = data[1] & 1
    sec, nanosec = struct.unpack_from("<iI" if little else ">iI", data, 4)
    return sec * 1_000_000_000 + nanosec


def proc_cpu_s(pid: int) -> float:
    """User + system CPU time [s] of process ``pid`` so far, all threads (/proc)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def machine() -> dict[str, Any]:
    model = "unknown"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": model, "cores": os.cpu_count(), "load_average": list(os.getloadavg())}


class Player:
    """rclpy participant of its own: the camera's publishers and raw subscribers of every node output."""

    def __init__(self, domain_id: int, node_name: str = "css_node") -> None:
        import rclpy
        from diagnostic_msgs.msg import DiagnosticArray
        from geometry_msgs.msg import PoseStamped
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import CameraInfo, Image

        from css_ros.io.topics import INPUT_TOPICS, OUTPUT_TOPICS, output_topic
        from css_ros.ros.conversions import rclpy_class

        self.context = Context()
        rclpy.init(context=self.context, domain_id=domain_id)
        self.node = rclpy.create_node(f"css_bench_player_{os.getpid()}", context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.lock = threading.Lock()
        qos = QoSProfile(depth=30, reliability=ReliabilityPolicy.RELIABLE)
        self.pub = {"camera_info": self.node.create_publisher(CameraInfo, INPUT_TOPICS["camera_info"], qos),
                    "pose": self.node.create_publisher(PoseStamped, INPUT_TOPICS["pose"], qos),
                    "segmentation": self.node.create_publisher(Image, INPUT_TOPICS["segmentation"], qos)}
        #: output name -> {stamp: time.time_ns() of receipt}
        self.received: dict[str, dict[int, int]] = {name: {} for name in OUTPUT_TOPICS}
        self.diag: dict[str, str] = {}
        qos_out = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE)
        self.subs: dict[str, Any] = {}
        for name, msgtype in OUTPUT_TOPICS.items():
            self.subs[name] = self.node.create_subscription(
                rclpy_class(msgtype), output_topic(name, node_name), self._receiver(name), qos_out, raw=True)
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, qos_out)
        self._diag_name = f"/{node_name}: semantic map"
        self._thread = threading.Thread(target=self._spin, daemon=True)
        self._thread.start()

    def _spin(self) -> None:
        try:
            while self.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - the context was shut down under us
            pass

    def _receiver(self, name: str) -> Any:
        """Callback of the raw subscription of output ``name``: its receipt time per stamp."""
        def on_output(data: bytes) -> None:
            now = time.time_ns()
            stamp = cdr_stamp(data)
            with self.lock:
                self.received[name].setdefault(stamp, now)
        return on_output

    def _on_diag(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == self._diag_name:
                with self.lock:
                    self.diag = {kv.key: kv.value for kv in st.values}

    def inputs_matched(self) -> bool:
        return all(p.get_subscription_count() > 0 for p in self.pub.values())

    def frame_outputs(self) -> list[str]:
        """The per-frame outputs the node publishes (its publishers matched ours)."""
        from css_ros.io.topics import FRAME_OUTPUTS

        return [n for n in FRAME_OUTPUTS if self.subs[n].get_publisher_count() > 0]

    def outputs_reach_us(self) -> bool:
        """Every per-frame output publisher counts our subscriber (the node's diagnostics say so)."""
        names = self.frame_outputs()
        with self.lock:
            diag = dict(self.diag)
        return bool(names) and all(int(diag.get(f"subscribers[{n}]", "0")) >= 1 for n in names)

    def close(self) -> None:
        import rclpy

        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        rclpy.try_shutdown(context=self.context)
        self._thread.join(2.0)


def frame_messages(cams: list, labels: list[np.ndarray]) -> list[tuple[Any, Any, Any]]:
    """(camera_info, pose, segmentation) messages per pose; the player only sets their stamps."""
    from css_ros.io.topics import BAG_CAMERA_FRAME, BAG_MAP_FRAME
    from css_ros.ros import conversions as rc

    out = []
    for i, cam in enumerate(cams):
        info = rc.camera_info_msg(cam.K, cam.width, cam.height, rc.header_msg(0, BAG_CAMERA_FRAME))
        pose = rc.pose_stamped_msg(cam.position, cam.quaternion_xyzw, rc.header_msg(0, BAG_MAP_FRAME))
        seg = rc.image_msg(labels[i % len(labels)], "mono8", rc.header_msg(0, BAG_CAMERA_FRAME))
        out.append((info, pose, seg))
    return out


def play(player: Player, msgs: list[tuple[Any, Any, Any]], count: int, rate: float, first: int,
         sent: dict[int, int]) -> None:
    """Publish ``count`` frames at ``rate`` Hz (poses ``first``, ``first + 1``, ... looped); stamps -> ``sent``
    (stamp [ns] -> index)."""
    from css_ros.ros.conversions import time_msg

    t0 = time.monotonic()
    for i in range(count):
        delay = t0 + i / rate - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        info, pose, seg = msgs[(first + i) % len(msgs)]
        stamp = time.time_ns()
        t = time_msg(stamp)
        info.header.stamp = pose.header.stamp = seg.header.stamp = t
        sent[stamp] = first + i
        player.pub["camera_info"].publish(info)
        player.pub["pose"].publish(pose)
        player.pub["segmentation"].publish(seg)


def wait_until(cond: Any, timeout: float, alive: Any, what: str) -> None:
    end = time.monotonic() + timeout
    while not cond():
        if not alive():
            raise SystemExit(f"bench_node: the node exited while waiting for {what}")
        if time.monotonic() > end:
            raise SystemExit(f"bench_node: timed out after {timeout:g} s waiting for {what}")
        time.sleep(0.05)


def stage_table(records: dict[int, dict[str, list[float]]], stamps: list[int]) -> dict[str, Any]:
    """Per-frame stage times [ms] of the frames ``stamps`` from the harness records (wall and thread CPU)."""
    rows: dict[str, list[float]] = {}
    for s in stamps:
        rec = records.get(s)
        if rec is None or "worker" not in rec:
            continue

        def get(stage: str, i: int, rec: dict[str, list[float]] = rec) -> float:
            if stage in ("take", "callback"):
                return sum(v[i] for k, v in rec.items() if k.startswith(stage + ":"))
            return rec.get(stage, [0.0, 0.0])[i]
        for i, suffix in ((0, ""), (1, "_cpu")):
            worker, observe, publish_frame = get("worker", i), get("observe", i), get("publish_frame", i)
            vals = {"take": get("take", i), "callback": get("callback", i), "decode": get("decode", i),
                    "worker": worker, "observe": observe, "worker_other": worker - observe - publish_frame,
                    "publish_frame": publish_frame, "images": get("images", i), "image_msgs": get("image_msgs", i),
                    "view_msg": get("view_msg", i), "publish": get("publish", i)}
            vals["own"] = vals["take"] + vals["callback"] + worker - observe
            vals["own_without_publish"] = vals["own"] - vals["publish"]
            for k, v in vals.items():
                rows.setdefault(k + suffix, []).append(v * 1e3)
    return {k: percentiles(v) for k, v in rows.items()} | {"frames": len(rows.get("own", []))}


def run(args: argparse.Namespace) -> dict[str, Any]:
    from bench_frame import SCENES, build_scene

    backend = args.backend
    if backend == "auto":
        backend = "cuda" if cuda_available() else "numba"
    stub = (backend != "cuda") if args.engine_stub is None else args.engine_stub
    label_kind = args.labels if args.labels != "auto" else ("gt" if backend == "cuda" and not stub else "blocks")
    base: dict[str, Any] = dict(SCENES["1M"])  # type: ignore[call-overload]
    cfg: dict[str, Any] = {**base, "gaussians": args.gaussians, "width": args.width, "height": args.height,
                           "classes": args.classes}
    work = Path(tempfile.mkdtemp(prefix="css_bench_node_"))
    print(f"bench_node: backend {backend}{' (engine stubbed)' if stub else ''}, {args.gaussians} Gaussians, "
          f"{args.width}x{args.height}, {args.classes} classes, {args.rate:g} Hz, {args.warmup}+{args.frames} frames, "
          f"domain {args.domain_id}, work folder {work}", flush=True)
    t0 = time.perf_counter()
    if args.model is None or label_kind == "gt":
        model, gt, cams = build_scene(cfg, max(args.poses, 2))
    else:   # the path's cameras only: the node loads the given model
        cams = path_cameras(cfg, max(args.poses, 2))
    if args.model is not None:
        ply = args.model
    else:
        ply = work / "model.ply"
        model.to_ply(ply)
    labels = (gt_labels(model, gt, cams, args.classes, backend) if label_kind == "gt" else
              [block_labels(args.height, args.width, args.classes, i) for i in range(min(len(cams), 8))])
    msgs = frame_messages(cams, labels)
    model = gt = None
    print(f"bench_node: scene ready in {time.perf_counter() - t0:.1f} s ({label_kind} labels)", flush=True)

    stats_path, log_path = work / "stages.json", work / "css_node.log"
    params = {"model_path": str(ply), "class_file": "''", "num_classes": args.classes, "checkpoint_path": "''",
              "resume": "false", "backend": backend, "warmup": "false" if stub else "true",
              "input_qos": "reliable", "ignore_label": IGNORE_LABEL}
    cmd = [sys.executable, str(HARNESS), "--stats-out", str(stats_path), *(["--engine-stub"] if stub else []),
           "--ros-args"]
    for k, v in params.items():
        cmd += ["-p", f"{k}:={v}"]
    for item in args.node_param:
        cmd += ["-p", item]
    log = open(log_path, "ab")
    proc = subprocess.Popen(cmd, env=node_env(args.domain_id), stdout=log, stderr=subprocess.STDOUT, cwd=str(work))
    player = Player(args.domain_id)
    sent: dict[int, int] = {}
    result: dict[str, Any] = {}
    try:
        alive = lambda: proc.poll() is None  # noqa: E731
        t_start = time.monotonic()
        wait_until(lambda: player.inputs_matched() and player.outputs_reach_us(), args.start_timeout, alive,
                   "the node's inputs and outputs to match")
        startup_s = time.monotonic() - t_start
        outputs = player.frame_outputs()
        print(f"bench_node: node up after {startup_s:.1f} s; per-frame outputs {', '.join(outputs)}", flush=True)

        def complete(stamps: list[int]) -> int:
            with player.lock:
                return sum(all(s in player.received[n] for n in outputs) for s in stamps)

        def drain(stamps: list[int]) -> None:
            """Wait for the outputs of ``stamps`` while they keep arriving (drain_timeout without progress)."""
            last, t_last = -1, time.monotonic()
            while alive():
                done = complete(stamps)
                if done == len(stamps):
                    return
                if done != last:
                    last, t_last = done, time.monotonic()
                elif time.monotonic() - t_last > args.drain_timeout:
                    return
                time.sleep(0.05)

        warm: dict[int, int] = {}
        play(player, msgs, args.warmup, args.rate, 0, warm)
        drain(list(warm))
        timed: dict[int, int] = {}
        cpu0, wall0 = proc_cpu_s(proc.pid), time.time_ns()
        play(player, msgs, args.frames, args.rate, args.warmup, timed)
        drain(list(timed))
        cpu1 = proc_cpu_s(proc.pid)
        sent.update(timed)
        with player.lock:
            received = {n: dict(player.received[n]) for n in player.received}
            diag = dict(player.diag)
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(60)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(10)
        log.close()
        player.close()
    if not stats_path.is_file():
        raise SystemExit(f"bench_node: the node wrote no stage records; log:\n{log_path.read_text()[-3000:]}")
    stats = json.loads(stats_path.read_text())
    records = {int(k): v for k, v in stats["frames"].items()}
    stamps = sorted(sent)
    done = [s for s in stamps if all(s in received[n] for n in outputs)]
    last_out = {s: max(received[n][s] for n in outputs) for s in done}
    latency = [(last_out[s] - s) / 1e6 for s in done]
    first_out = [(min(received[n][s] for n in outputs) - s) / 1e6 for s in done]
    span = (max(last_out.values()) - min(last_out.values())) / 1e9 if len(done) > 1 else float("nan")
    periodic = {k: {"calls": len(v), "wall_ms": percentiles([x[0] * 1e3 for x in v])}
                for k, v in stats["periodic"].items()}
    result = {
        "backend": backend, "engine_stub": stub, "labels": label_kind, "gaussians": args.gaussians,
        "width": args.width, "height": args.height, "classes": args.classes, "rate_hz": args.rate,
        "machine": machine(), "startup_s": startup_s, "outputs": outputs,
        "frames_sent": len(stamps), "frames_received": len(done),
        "frames_per_s": (len(done) - 1) / span if len(done) > 1 and span > 0 else float("nan"),
        "latency_ms": percentiles(latency), "first_output_latency_ms": percentiles(first_out),
        "stages_ms": stage_table(records, done),
        "node_process_cpu_ms_per_frame": (cpu1 - cpu0) * 1e3 / max(len(done), 1),
        "node_process_cpu_share": (cpu1 - cpu0) / max((max(last_out.values(), default=wall0) - wall0) / 1e9, 1e-9),
        "between_frames": periodic, "node_exit_code": proc.returncode,
        "frames_dropped_busy": int(diag.get("frames_dropped_busy", "0") or 0),
        "work_folder": str(work),
    }
    if not args.keep:
        import shutil
        shutil.rmtree(work, ignore_errors=True)
    return result


def report(r: dict[str, Any]) -> str:
    st = r["stages_ms"]

    def row(name: str, label: str) -> str:
        w, c = st.get(name), st.get(name + "_cpu")
        if w is None:
            return ""
        return (f"  {label:<44s} {w['mean']:7.3f} {w['p50']:7.3f} {w['p90']:7.3f} {w['p99']:7.3f}   "
                f"{c['mean']:7.3f}\n")
    lat, m = r["latency_ms"], r["machine"]
    nan = {"mean": float("nan"), "p50": float("nan"), "p90": float("nan")}
    own, own_cpu = st.get("own", nan), st.get("own_cpu", nan)
    verdict = "met" if own_cpu["mean"] <= OWN_TARGET_MS else "NOT met"
    return (
        f"\ncss_node end to end: backend {r['backend']}{' (engine stubbed)' if r['engine_stub'] else ''}, "
        f"{r['gaussians']} Gaussians, {r['width']}x{r['height']}, {r['classes']} classes, {r['rate_hz']:g} Hz input\n"
        f"machine: {m['cpu']}, {m['cores']} cores, load average {m['load_average'][0]:.2f}\n"
        f"frames sent / received (all {len(r['outputs'])} per-frame outputs): {r['frames_sent']} / "
        f"{r['frames_received']}; dropped busy {r['frames_dropped_busy']}\n"
        f"frames/s: {r['frames_per_s']:.2f}\n"
        f"latency stamp -> last output received [ms]: p50 {lat['p50']:.1f}, p90 {lat['p90']:.1f}, "
        f"p99 {lat['p99']:.1f}, max {lat['max']:.1f} (first output p50 {r['first_output_latency_ms']['p50']:.1f})\n"
        f"per frame [ms], wall time in the stage         mean     p50     p90     p99   cpu mean\n"
        + row("own", "node's own work")
        + row("take", "  rclpy take (deserialise inputs)")
        + row("callback", "  input callbacks (gate)")
        + row("decode", "    of which the label decode")
        + row("worker_other", "  worker bookkeeping")
        + row("publish_frame", "  per-frame outputs")
        + row("images", "    colour-mapped labels")
        + row("image_msgs", "    Image messages")
        + row("view_msg", "    view_uncertainty message")
        + row("publish", "    publish (serialise + DDS write)")
        + row("own_without_publish", "node's own work without the DDS publish")
        + row("observe", "engine observe" + (" (stub)" if r["engine_stub"] else ""))
        + f"node process CPU per frame, all threads: {r['node_process_cpu_ms_per_frame']:.2f} ms "
          f"({100 * r['node_process_cpu_share']:.0f} % of one core)\n"
        + "between frames [ms per call]: " + (", ".join(
            f"{k} {v['calls']}x mean {v['wall_ms']['mean']:.1f} max {v['wall_ms']['max']:.1f}"
            for k, v in r["between_frames"].items()) or "none") + "\n"
        + f"node's own work per frame: CPU mean {own_cpu['mean']:.2f} ms, p50 {own_cpu['p50']:.2f}, p90 "
          f"{own_cpu['p90']:.2f}; wall mean {own['mean']:.2f}, p50 {own['p50']:.2f}, p90 {own['p90']:.2f} "
          f"(target <= {OWN_TARGET_MS:g} ms of CPU: {verdict})\n")


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    r = run(args)
    print(report(r), flush=True)
    if args.json:
        args.json.write_text(json.dumps(r, indent=2))
        print(f"results: {args.json}")
    return 0 if r["frames_received"] == r["frames_sent"] else 1


if __name__ == "__main__":
    sys.exit(main())
