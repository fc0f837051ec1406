"""css_demo: play a demo bag into a running css_node over DDS and print per-frame uncertainty as results arrive."""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from ..errors import CssError
from ..io.paths import resolve_data_path
from ..io.topics import BAG_TOPICS, INPUT_TOPICS, REQUIRED_BAG_KINDS
from ..io.messages import image_to_array, ns_to_sec_nanosec, stamp_to_ns, unpack_view_points

DEFAULT_BAG = "bags/demo/bag"
#: Bag topics played into the node, in the order a frame's messages are published (segmentation last:
#: it completes the frame); the GT labels stay in the player to score the node's answers.
PLAYED_TOPICS = tuple(BAG_TOPICS[k] for k in ("camera_info", "pose", "image", "confidence", "segmentation"))
GT_TOPIC = BAG_TOPICS["gt"]
#: Node outputs written as PNG files by ``--save-frames``.
SAVED_OUTPUTS = ("semantic_color", "rendered_image")


@dataclass
class FrameRecord:
    """One played frame: its index, the stamp it was published with, when, and what came back."""

    index: int
    stamp_ns: int
    sent: float
    gt: np.ndarray | None = None
    u_var: float = float("nan")
    u_exp: float = float("nan")
    latency_ms: float = float("nan")
    accuracy: float = float("nan")
    done: bool = False


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_demo",
        description="Play a bag (default: the shipped demo) into a running css_node over DDS at a chosen rate "
                    "and print each frame's U_var / U_exp (and label accuracy against /segmentation_gt when "
                    "the bag has it) as the node answers. With --start-node it starts css_node itself on the "
                    "demo model, so one command shows the live demo.")
    p.add_argument("bag", nargs="?", default=DEFAULT_BAG, help=f"rosbag2 directory (default {DEFAULT_BAG})")
    p.add_argument("--rate", type=float, default=1.0,
                   help="playback speed factor (1 = real time; 0 = as fast as possible: a node that is still "
                        "busy with a frame then drops the older waiting frames, newest wins)")
    p.add_argument("--node", default="/css_node", help="css_node's name with namespace (default /css_node)")
    p.add_argument("--prefix", default="", help="namespace prepended to the played topics (default none)")
    p.add_argument("--keep-stamps", action="store_true",
                   help="publish the bag's header stamps (default: restamp to now, so replays stay in order "
                        "for a node that already saw this bag)")
    p.add_argument("--loops", type=int, default=1, help="play the bag this many times (default 1)")
    p.add_argument("--max-frames", type=int, default=0, help="stop after this many frames (0: all)")
    p.add_argument("--wait", type=float, default=30.0,
                   help="seconds to wait for css_node to subscribe, and for the last results (default 30)")
    p.add_argument("--start-node", action="store_true",
                   help="start css_node (python -m css_ros.node) with the model next to the bag")
    p.add_argument("--model", default=None, help="model for --start-node (default: BAG/../model.ply)")
    p.add_argument("--classes", default=None, help="class file for --start-node (default: BAG/../classes.yaml)")
    p.add_argument("--num-classes", type=int, default=None, metavar="N",
                   help="--start-node on a bag without a class file: N anonymous classes")
    p.add_argument("--node-param", action="append", default=[], metavar="NAME:=VALUE",
                   help="extra css_node parameter for --start-node (repeatable)")
    p.add_argument("--save", action="store_true",
                   help="call ~/save_map at the end (with --start-node the map goes to --map)")
    p.add_argument("--map", default="css_demo_map.npz", metavar="NPZ",
                   help="checkpoint file of the node started by --start-node --save (default css_demo_map.npz)")
    p.add_argument("--save-frames", default=None, metavar="DIR",
                   help="write the node's answers as PNG files into DIR (frame_NNNN_semantic_color.png, "
                        "frame_NNNN_rendered_image.png): a way to see the live outputs without RViz")
    p.add_argument("--quiet", action="store_true", help="print only the summary")
    return p




#: Seconds css_demo waits for css_node's diagnostics (which say its outputs reach the player) once the node has
#: subscribed to every played topic; a node without diagnostics is trusted after that.
DIAGNOSTICS_GRACE_S = 15.0
#: Longest wait for the answers after the last frame was played [s] (while the node shows progress).
WAIT_RESULTS_MAX_S = 300.0


def start_node(args: argparse.Namespace, bag: Path) -> subprocess.Popen:
    """Start css_node as a child process (same Python, same ROS_DOMAIN_ID) on the model next to the bag.

    Raises:
        CssError: no model, or no class file and no ``--num-classes``.
    """
    model = Path(args.model) if args.model else bag.parent / "model.ply"
    classes = Path(args.classes) if args.classes else bag.parent / "classes.yaml"
    if not model.is_file():
        raise CssError(f"--start-node: model not found: {model} (pass --model)")
    if not classes.is_file() and args.num_classes is None:
        raise CssError(f"--start-node: class file not found: {classes} (pass --classes FILE or --num-classes N)")
    node_name = args.node.rstrip("/").split("/")[-1]
    ns = "/".join(args.node.rstrip("/").split("/")[:-1]) or "/"
    checkpoint = str(Path(args.map).resolve()) if args.save else "''"
    cmd = [sys.executable, "-m", "css_ros.node", "--ros-args", "-r", f"__node:={node_name}", "-r", f"__ns:={ns}",
           "-p", f"model_path:={model.resolve()}", "-p", f"checkpoint_path:={checkpoint}", "-p", "resume:=false"]
    if classes.is_file():
        cmd += ["-p", f"class_file:={classes.resolve()}"]
    else:
        cmd += ["-p", "class_file:=''", "-p", f"num_classes:={args.num_classes}"]
    if args.prefix:
        for topic in (INPUT_TOPICS[k] for k in ("image", "segmentation", "confidence", "camera_info", "pose")):
            cmd += ["-r", f"{topic}:={args.prefix.rstrip('/')}/{topic}"]
    for item in args.node_param:
        cmd += ["-p", item]
    print(f"css_demo: starting css_node: {' '.join(cmd)}", flush=True)
    return subprocess.Popen(cmd, env=dict(os.environ))


class DemoPlayer:
    """Publishes bag messages with rclpy and collects css_node's per-frame results."""

    def __init__(self, args: argparse.Namespace) -> None:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from diagnostic_msgs.msg import DiagnosticArray
        from rclpy.qos import QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image, PointCloud2
        from std_srvs.srv import Trigger

        self.args = args
        self.node = rclpy.create_node("css_demo")
        self.log = self.node.get_logger()
        self.qos = QoSProfile(depth=20, reliability=ReliabilityPolicy.RELIABLE)
        self.pubs: dict[str, Any] = {}
        self.frames: dict[int, FrameRecord] = {}
        self.lock = threading.Lock()
        node = args.node.rstrip("/")
        # semantic first: when both are ready the executor handles it first, so the accuracy is known
        # when the uncertainty line is printed.
        self.outputs = {name: self.node.create_subscription(typ, f"{node}/{name}", cb, 100) for name, typ, cb in (
            ("semantic", Image, self._on_semantic), ("view_uncertainty", PointCloud2, self._on_uncertainty))}
        self.node_diagnostics: dict[str, str] | None = None   # the node's latest diagnostics entries
        self.node.create_subscription(DiagnosticArray, "/diagnostics", self._on_diagnostics, 10)
        if args.save_frames:
            self.frames_dir = Path(args.save_frames)
            self.frames_dir.mkdir(parents=True, exist_ok=True)
            for name in SAVED_OUTPUTS:
                self.node.create_subscription(Image, f"{node}/{name}",
                                              lambda msg, name=name: self._on_image_output(name, msg), 100)
        self.save_client = self.node.create_client(Trigger, f"{node}/save_map")
        self.executor = SingleThreadedExecutor()
        self.executor.add_node(self.node)
        self._stop = threading.Event()
        self._spin = threading.Thread(target=self._spin_loop, daemon=True)
        self._spin.start()

    def _spin_loop(self) -> None:
        try:
            while not self._stop.is_set() and self.executor.context.ok():
                self.executor.spin_once(timeout_sec=0.05)
        except Exception:  # noqa: BLE001 - context shut down while spinning
            pass

    def publisher(self, topic: str, msg: Any) -> Any:
        if topic not in self.pubs:
            self.pubs[topic] = self.node.create_publisher(type(msg), self.args.prefix.rstrip("/") + topic, self.qos)
        return self.pubs[topic]

    def _on_diagnostics(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == f"{self.args.node.rstrip('/')}: semantic map":
                with self.lock:
                    self.node_diagnostics = {kv.key: kv.value for kv in st.values}

    def outputs_reach_us(self) -> bool | None:
        """True when css_node's outputs reach this player: our readers matched its writers, and its diagnostics
        (published whenever a subscriber of an output matches) count at least the subscribers we know of; None while
        the node has published no diagnostics (publish_diagnostics off, or not heard yet)."""
        if not all(sub.get_publisher_count() > 0 for sub in self.outputs.values()):
            return False
        with self.lock:
            diag = self.node_diagnostics
        if diag is None:
            return None
        return all(int(diag.get(f"subscribers[{name}]", 0)) >= self.node.count_subscribers(sub.topic_name)
                   for name, sub in self.outputs.items())

    # ---------------------------------------------------------------- results
    def _on_uncertainty(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            rec = self.frames.get(stamp)
            if rec is None or rec.done:
                return
            pt = unpack_view_points(msg)
            if len(pt) == 0:
                return
            rec.u_var, rec.u_exp = float(pt["u_var"][0]), float(pt["u_exp"][0])
            rec.latency_ms = (time.monotonic() - rec.sent) * 1e3
            rec.done = True
        if not self.args.quiet:
            acc = f"  acc {rec.accuracy * 100:5.1f} %" if np.isfinite(rec.accuracy) else ""
            print(f"frame {rec.index:4d}  stamp {stamp * 1e-9:.3f}  U_var {rec.u_var:.4e}  U_exp {rec.u_exp:.4f}"
                  f"{acc}  latency {rec.latency_ms:6.0f} ms", flush=True)

    def _on_image_output(self, name: str, msg: Any) -> None:
        """--save-frames: write one of the node's rgb8 answers as DIR/frame_NNNN_<name>.png."""
        from matplotlib.image import imsave

        with self.lock:
            rec = self.frames.get(stamp_to_ns(msg.header.stamp))
        if rec is None:
            return
        try:
            imsave(self.frames_dir / f"frame_{rec.index:04d}_{name}.png", image_to_array(msg, allowed=("rgb8",)))
        except CssError:
            return

    def _on_semantic(self, msg: Any) -> None:
        stamp = stamp_to_ns(msg.header.stamp)
        with self.lock:
            rec = self.frames.get(stamp)
            gt = rec.gt if rec is not None else None
        if gt is None:
            return
        try:
            labels = image_to_array(msg)
        except CssError:
            return
        if labels.shape != gt.shape:
            return
        valid = gt != 255
        if valid.any():
            rec.accuracy = float(np.mean(labels[valid] == gt[valid]))

    # ---------------------------------------------------------------- playing
    def create_publishers(self, bag_path: Path) -> None:
        """One publisher per played topic of the bag, created before playing so discovery completes first."""
        from ..io.bag import InputBag
        from ..ros.conversions import rclpy_class

        with InputBag(bag_path) as bag:
            topics = bag.topics()
        missing = [BAG_TOPICS[k] for k in REQUIRED_BAG_KINDS if BAG_TOPICS[k] not in topics]
        if missing:
            raise CssError(f"bag {bag_path} lacks {', '.join(missing)} (has {', '.join(sorted(topics))})")
        for topic in PLAYED_TOPICS:
            if topic in topics:
                self.publisher(topic, rclpy_class(topics[topic][0])())

    def unsubscribed_topics(self) -> list[str]:
        """Played topics that nobody subscribes to (full names, with --prefix)."""
        return [pub.topic_name for pub in self.pubs.values() if pub.get_subscription_count() == 0]

    def inputs_reach_node(self) -> bool | None:
        """True when css_node's readers have matched our writers of every played topic (its diagnostics
        ``publishers[<topic>]``; discovery ends at each side on its own, and a sensor-data reader drops what a writer
        it has not matched yet sends, so the first frame would be lost); None while no diagnostics were heard."""
        with self.lock:
            diag = self.node_diagnostics
        if diag is None:
            return None
        return all(int(diag.get(f"publishers[{pub.topic_name}]", 0)) > 0 for pub in self.pubs.values())

    def wait_for_node(self, timeout: float) -> bool:
        """Wait until css_node subscribes to every played topic, matched at both ends (our writers matched its readers,
        and its readers ours: :meth:`inputs_reach_node`), and its outputs reach us (see :meth:`outputs_reach_us`; an
        answer published before its writer matched our reader would be lost). A node that publishes no diagnostics
        within DIAGNOSTICS_GRACE_S of the inputs matching is trusted after that wait."""
        end = time.monotonic() + timeout
        inputs_at = None
        while time.monotonic() < end:
            if self.pubs and all(pub.get_subscription_count() > 0 for pub in self.pubs.values()):
                inputs_at = inputs_at or time.monotonic()
                reach = self.outputs_reach_us()
                if reach:
                    reach = self.inputs_reach_node()
                if reach or (reach is None and time.monotonic() - inputs_at > DIAGNOSTICS_GRACE_S):
                    return True
            time.sleep(0.1)
        return False

    def play(self, bag_path: Path) -> int:
        from ..io.bag import InputBag
        from ..ros.conversions import to_rclpy

        args = self.args
        played = 0
        with InputBag(bag_path) as bag:
            topics = bag.topics()
            present = [t for t in PLAYED_TOPICS if t in topics]
            wanted = present + ([GT_TOPIC] if GT_TOPIC in topics else [])
            for loop in range(max(1, args.loops)):
                t_wall0 = time.monotonic()
                t_bag0: int | None = None
                restamp: dict[int, int] = {}
                last_new = 0
                pending_gt: dict[int, np.ndarray] = {}
                for item in bag.messages(wanted):
                    if t_bag0 is None:
                        t_bag0 = item.log_time_ns
                    if args.rate > 0:
                        delay = (item.log_time_ns - t_bag0) * 1e-9 / args.rate - (time.monotonic() - t_wall0)
                        if delay > 0:
                            time.sleep(delay)
                    msg = item.msg
                    orig = stamp_to_ns(msg.header.stamp)
                    if args.keep_stamps:
                        stamp = orig
                    else:  # the wall-clock time at which the first message with this bag stamp goes out
                        stamp = restamp.setdefault(orig, max(time.time_ns(), last_new + 1))
                        last_new = stamp
                    if item.topic == GT_TOPIC:
                        try:
                            gt = image_to_array(msg)
                        except CssError:
                            continue
                        with self.lock:
                            if stamp in self.frames:
                                self.frames[stamp].gt = gt
                            else:
                                pending_gt[stamp] = gt
                        continue
                    out = to_rclpy(msg)
                    out.header.stamp.sec, out.header.stamp.nanosec = ns_to_sec_nanosec(stamp)
                    if item.topic == BAG_TOPICS["segmentation"]:
                        with self.lock:
                            self.frames[stamp] = FrameRecord(played, stamp, time.monotonic(),
                                                             gt=pending_gt.pop(stamp, None))
                        played += 1
                    self.publisher(item.topic, out).publish(out)
                    if args.max_frames and played >= args.max_frames:
                        break
                if args.max_frames and played >= args.max_frames:
                    break
        return played

    def wait_results(self, timeout: float) -> None:
        """Wait until the last frame's result arrives, or ``timeout`` s pass without a new result while the node's
        diagnostics show no progress either (frames processed, frames pending: a first frame that compiles the
        kernels on a loaded host takes longer than ``timeout``); at most WAIT_RESULTS_MAX_S in all."""
        start = time.monotonic()
        last_progress: tuple[Any, ...] = ()
        last_change = start
        while time.monotonic() - last_change < timeout and time.monotonic() - start < WAIT_RESULTS_MAX_S:
            with self.lock:
                done = sum(r.done for r in self.frames.values())
                last = max(self.frames.values(), key=lambda r: r.index, default=None)
                diag = self.node_diagnostics or {}
            if last is not None and last.done:
                return
            progress = (done, diag.get("frames_processed"), diag.get("segmentations_received"))
            if progress != last_progress or diag.get("pending_frames", "0") not in ("0", "0.0"):
                last_progress, last_change = progress, time.monotonic()
            time.sleep(0.1)

    def summary(self, elapsed: float) -> str:
        with self.lock:
            recs = sorted(self.frames.values(), key=lambda r: r.index)
        done = [r for r in recs if r.done]
        if not done:
            return f"css_demo: played {len(recs)} frames in {elapsed:.1f} s; no result from css_node"
        acc = [r.accuracy for r in done if np.isfinite(r.accuracy)]
        last_done = done[-1].index
        skipped = sum(1 for r in recs if not r.done and r.index < last_done)
        late = sum(1 for r in recs if not r.done and r.index > last_done)
        unanswered = []
        if skipped:
            unanswered.append(f"{skipped} skipped by the node (busy with an earlier frame, or refused: see its "
                              "log and /diagnostics)")
        if late:
            unanswered.append(f"{late} at the end without an answer before the wait ran out")
        text = (f"css_demo: played {len(recs)} frames in {elapsed:.1f} s; css_node answered {len(done)}"
                + (f" ({'; '.join(unanswered)})" if unanswered else "") + "; "
                f"U_var {done[0].u_var:.4e} -> {done[-1].u_var:.4e}, "
                f"U_exp {done[0].u_exp:.4f} -> {done[-1].u_exp:.4f}; median latency "
                f"{np.median([r.latency_ms for r in done]):.0f} ms")
        if acc:
            text += f"; label accuracy vs ground truth {acc[0] * 100:.1f} % -> {acc[-1] * 100:.1f} %"
        return text

    def save(self) -> str:
        from std_srvs.srv import Trigger

        if not self.save_client.wait_for_service(timeout_sec=5.0):
            return "save_map service not available"
        future = self.save_client.call_async(Trigger.Request())
        end = time.monotonic() + 60.0
        while not future.done() and time.monotonic() < end:
            time.sleep(0.05)
        res = future.result() if future.done() else None
        return res.message if res is not None else "save_map timed out"

    def close(self) -> None:
        """Stop the spin thread before tearing down (a thread left inside rcl aborts the interpreter at exit)."""
        self._stop.set()
        self._spin.join(timeout=5.0)
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``css_demo``."""
    import rclpy

    raw = list(sys.argv[1:] if argv is None else argv)
    # Everything from --ros-args on goes to rclpy (not rclpy's remove_ros_args: it would also eat the
    # NAME:=VALUE of --node-param as an old-style remap rule).
    cut = raw.index("--ros-args") if "--ros-args" in raw else len(raw)
    args = build_parser().parse_args(raw[:cut])
    ros_args = raw[cut:]
    bag = resolve_data_path(args.bag)
    if not bag.exists():
        print(f"css_demo: bag not found: {bag} (generate the demo with css_make_demo, or pass a bag)",
              file=sys.stderr)
        return 2
    child = None
    rclpy.init(args=["css_demo", *ros_args])
    player = None
    code = 0
    try:
        if args.start_node:
            child = start_node(args, bag)
        player = DemoPlayer(args)
        player.create_publishers(bag)
        print(f"css_demo: waiting for {args.node} to subscribe to {args.prefix.rstrip('/')}/segmentation ...",
              flush=True)
        if not player.wait_for_node(args.wait + (60.0 if child else 0.0)):
            if child is not None and child.poll() is not None:
                print(f"css_demo: css_node exited with code {child.returncode}", file=sys.stderr)
            else:
                lonely = ", ".join(player.unsubscribed_topics())
                print(f"css_demo: no subscriber on {lonely} within {args.wait:g} s: is css_node running (start it "
                      "with `css_node` or pass --start-node) on the same ROS_DOMAIN_ID, with matching topic "
                      "names (--prefix)?", file=sys.stderr)
            code = 1
            return code
        t0 = time.monotonic()
        print(f"css_demo: playing {bag} at rate {args.rate:g}", flush=True)
        player.play(bag)
        player.wait_results(min(args.wait, 10.0))
        print(player.summary(time.monotonic() - t0), flush=True)
        if args.save:
            print(f"css_demo: save_map: {player.save()}", flush=True)
    except CssError as exc:
        print(f"css_demo: {exc}", file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        code = 130
    except Exception as exc:  # noqa: BLE001 - rclpy's ExternalShutdownException on SIGTERM
        if type(exc).__name__ != "ExternalShutdownException":
            raise
        code = 143
    finally:
        if player is not None:
            player.close()
        rclpy.try_shutdown()
        if child is not None and child.poll() is None:
            child.send_signal(2)
            try:
                child.wait(30)
            except subprocess.TimeoutExpired:
                child.kill()
    return code


if __name__ == "__main__":
    sys.exit(main())
