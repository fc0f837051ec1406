"""``css_ctl``: talk to a running css_node from a terminal (no ros2 CLI needed): save / load / reset the map,
query points (SPEC §9) and score candidate views, printing the answers as tables."""
from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path
from types import SimpleNamespace
from typing import Any, Callable, Sequence

import numpy as np

from ..console import bounded_number, run_console
from ..engine.camera import body_to_optical_rotation, matrix_to_quaternion_xyzw
from ..errors import CssError
from ..io.clouds import pack_cloud, unpack_cloud, unpack_scored_views
from ..io.frames import FrameRejected, decode_pose
from ..io.point_queries import ANSWER_FIELDS
from ..io.topics import INPUT_TOPICS
from .node_link import MIN_TIMEOUT_S, NodeLink, node_name_arg

SERVICES = {"save": "save_map", "load": "load_map", "reset": "reset_map"}
#: What css_ctl calls under --node (checked as full ROS names when --node is parsed).
NODE_TOPICS = (*SERVICES.values(), "candidate_scores", "point_query_results")
DEFAULT_TIMEOUT_S = 10.0
#: Largest --timeout [s]: beyond one day a typo would hang the terminal (the smallest: node_link.MIN_TIMEOUT_S).
MAX_TIMEOUT_S = 86400.0
#: Largest --file of points or poses [bytes]: 64 MiB of text holds more rows than css_node takes in one request
#: (max_query_points 10^6 points are ~40 MB); the size is checked before the file is read.
MAX_ROWS_FILE_BYTES = 64 << 20
#: Largest |coordinate| of a query point: points are sent as float32 (beyond, they would arrive as inf).
MAX_POINT_COORD = float(np.finfo(np.float32).max)
#: css_node's status counters (/diagnostics) that say why candidate rows are NaN (docs/reliability.md).
_NAN_STATUS_KEYS = ("requests_nan[", "warn[candidates: invalid candidate poses]")

EXAMPLES = """\
examples:
  css_ctl save                                # write the checkpoint now
  css_ctl reset                               # all concentrations back to the prior
  css_ctl load                                # replace the map by the checkpoint at checkpoint_path
  css_ctl query -1.4 0.3 0.75  0 1.5 0  -1 3 1.5
                                              # SPEC §9 point queries (x y z triples, map frame, metres): on the
                                              # demo room's table, floor and north wall; "unknown" = free space
  css_ctl query --file points.txt             # one "x y z" per line
  css_ctl candidates 0 0 1.5 -0.5 0.5 -0.5 0.5
                                              # score views (x y z qx qy qz qw of the optical frame, map frame:
                                              # z forward, x right, y down): here 1.5 m up, looking level along +x;
                                              # prints U_var, U_exp, info_gain, marks the most uncertain view and
                                              # the best next view (largest expected information gain)
  css_ctl candidates --yaw 0 0 1.5 0  0 0 1.5 90
                                              # the same as x y z yaw: a level camera turned yaw degrees from +x
                                              # towards +y about the map's z (up): along +x, then along +y
  css_ctl candidates --file poses.txt         # one "x y z qx qy qz qw" per line (with --yaw: "x y z yaw")
Use ROS_DOMAIN_ID as for the node; --node for another node name.
Exit codes: 0 done; 1 the node did not answer or refused, or a --file cannot be read; 2 usage: a bad option, or
numbers that cannot be sent (checked before ROS starts: groups of 3 / 7 / 4, finite; query points within float32;
poses as css_node checks them: |position| <= 1e6 m, quaternion norm in [0.9, 1.1]).
"""


class InputRefused(CssError):
    """Points or poses css_ctl will not send (a usage error, exit 2): the node could not use them."""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="css_ctl", description="Control and query a running css_node over DDS.",
                                epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--node", type=node_name_arg(NODE_TOPICS), default="/css_node",
                   help="css_node's full name with namespace (default /css_node)")
    p.add_argument("--timeout", type=bounded_number(MIN_TIMEOUT_S, MAX_TIMEOUT_S), default=DEFAULT_TIMEOUT_S,
                   help=f"seconds to wait for the node, in [{MIN_TIMEOUT_S:g}, {MAX_TIMEOUT_S:g}] "
                        f"(default {DEFAULT_TIMEOUT_S:g})")
    sub = p.add_subparsers(dest="command", required=True)
    for name, srv in SERVICES.items():
        sub.add_parser(name, help=f"call {srv} (std_srvs/Trigger)")
    q = sub.add_parser("query", help="SPEC §9 point queries")
    q.add_argument("xyz", type=float, nargs="*", help="x y z triples [m, map frame]")
    q.add_argument("--file", type=Path, help="text file, one 'x y z' per line")
    c = sub.add_parser("candidates", help="score candidate views (U_var, U_exp, info_gain)")
    c.add_argument("pose", type=float, nargs="*", help="x y z qx qy qz qw per view (optical frame in the map: z "
                   "forward, x right, y down; the identity looks along the map's +z), or x y z yaw with --yaw")
    c.add_argument("--yaw", action="store_true", help="give each view as x y z yaw: a level camera (REP-103 body "
                   "frame: x forward, z up) turned yaw degrees about the map's +z from +x towards +y")
    c.add_argument("--file", type=Path, help="text file, one 'x y z qx qy qz qw' per line ('x y z yaw' with --yaw)")
    return p


def read_rows(values: Sequence[float], file: Path | None, width: int, what: str) -> np.ndarray:
    """(M, width) float64 rows from the command line or a text file.

    CssError (exit 1) when the file is missing, not a regular file (a folder, /dev/null) or larger than
    MAX_ROWS_FILE_BYTES; InputRefused (exit 2) when the numbers do not come in groups of ``width``, or come both from
    the command line and a file."""
    if file is not None:
        if values:
            raise InputRefused(f"give {what} on the command line or with --file, not both ({len(values)} numbers and "
                               f"{file})")
        if not file.is_file():
            raise CssError(f"{what} file is not a regular file: {file}" if file.exists()
                           else f"{what} file not found: {file}")
        if file.stat().st_size > MAX_ROWS_FILE_BYTES:
            raise CssError(f"{what} file {file} has {file.stat().st_size} bytes, more than {MAX_ROWS_FILE_BYTES >> 20} "
                           "MiB (css_node takes at most max_query_points / max_candidates per request): split it")
        try:
            with warnings.catch_warnings():   # an empty file: "input contained no data", said below in one line
                warnings.simplefilter("ignore")
                rows = np.loadtxt(file, dtype=np.float64, ndmin=2, comments="#")
        except ValueError as exc:
            raise InputRefused(f"{file}: {exc}") from None
        if rows.size == 0 or rows.shape[1] != width:
            raise InputRefused(f"{file}: expected {width} numbers per line")
        return rows
    if not values or len(values) % width:
        raise InputRefused(f"give {what} as groups of {width} numbers (got {len(values)})")
    return np.asarray(values, np.float64).reshape(-1, width)


def check_points(xyz: np.ndarray) -> np.ndarray:
    """``xyz`` (M, 3) unchanged; InputRefused naming the first point with a non-finite coordinate or one beyond
    float32 (the request carries float32: it would arrive as inf)."""
    bad = ~np.all(np.isfinite(xyz) & (np.abs(np.nan_to_num(xyz)) <= MAX_POINT_COORD), axis=1)
    if bad.any():
        i = int(np.argmax(bad))
        raise InputRefused(f"point {i} ({' '.join(f'{v:g}' for v in xyz[i])}): coordinates must be finite and "
                           f"within +-{MAX_POINT_COORD:.6g} m (sent as float32)")
    return xyz


def check_poses(poses: np.ndarray) -> np.ndarray:
    """``poses`` (M, 7) x y z qx qy qz qw unchanged; InputRefused naming the first pose css_node would score NaN
    and why (its own check, :func:`css_ros.io.frames.decode_pose`: finite, |position| within POSITION_BOUND_M,
    quaternion norm within QUATERNION_NORM_TOLERANCE)."""
    for i, row in enumerate(poses):
        x, y, z, qx, qy, qz, qw = (float(v) for v in row)
        pose = SimpleNamespace(position=SimpleNamespace(x=x, y=y, z=z),
                               orientation=SimpleNamespace(x=qx, y=qy, z=qz, w=qw))
        try:
            decode_pose(SimpleNamespace(pose=pose))
        except FrameRejected as exc:
            raise InputRefused(f"pose {i}: {exc} (css_node would score it NaN)") from None
    return poses


def check_yaws(rows: np.ndarray) -> np.ndarray:
    """``rows`` (M, 4) x y z yaw unchanged; InputRefused naming the first pose whose yaw is not finite."""
    bad = ~np.isfinite(rows[:, 3])
    if bad.any():
        i = int(np.argmax(bad))
        raise InputRefused(f"pose {i}: yaw must be finite, got {rows[i, 3]:g}")
    return rows


def level_poses(rows: np.ndarray) -> np.ndarray:
    """(M, 7) x y z qx qy qz qw of the optical frame in the map for (M, 4) rows x y z yaw [m, degrees]: the REP-103
    body frame (x forward, y left, z up) turned by yaw about the map's +z, then to the optical frame with
    :func:`~css_ros.engine.camera.body_to_optical_rotation` (yaw 0 looks along +x: quaternion -0.5 0.5 -0.5 0.5)."""
    yaw = np.radians(rows[:, 3])
    c, s = np.cos(yaw), np.sin(yaw)
    r_map_body = np.zeros((len(rows), 3, 3))
    r_map_body[:, 0, 0], r_map_body[:, 0, 1], r_map_body[:, 1, 0], r_map_body[:, 1, 1] = c, -s, s, c
    r_map_body[:, 2, 2] = 1.0
    quats = [matrix_to_quaternion_xyzw(r @ body_to_optical_rotation()) for r in r_map_body]
    return np.hstack([rows[:, :3], np.reshape(quats, (-1, 4))])


def format_table(header: Sequence[str], rows: Sequence[Sequence[Any]]) -> str:
    """A plain text table with right-aligned columns."""
    cells = [[str(h) for h in header]] + [[str(c) for c in r] for r in rows]
    widths = [max(len(r[i]) for r in cells) for i in range(len(header))]
    lines = ["  ".join(c.rjust(w) for c, w in zip(r, widths)) for r in cells]
    lines.insert(1, "  ".join("-" * w for w in widths))
    return "\n".join(lines)


def call_service(link: NodeLink, node: str, name: str, timeout: float) -> tuple[bool, str]:
    from std_srvs.srv import Trigger

    client = link.node.create_client(Trigger, f"{node.rstrip('/')}/{name}")
    if not client.wait_for_service(timeout_sec=timeout):
        raise CssError(f"no {node}/{name} service within {timeout:g} s (is css_node running, same ROS_DOMAIN_ID?)")
    future = client.call_async(Trigger.Request())
    if not link.wait(future.done, timeout):
        raise CssError(f"{node}/{name} did not answer within {timeout:g} s")
    res = future.result()
    return bool(res.success), str(res.message)


def _request(link: NodeLink, node: str, topic: str, msg_type: type, answer_topic: str, msg: Any,
             timeout: float, before_send: Callable[[], None] | None = None) -> Any:
    """Publish ``msg`` (its header stamp is the request id) and return the answer echoing that stamp;
    ``before_send`` runs once both ends are matched, just before the request goes out."""
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2

    answers: dict[tuple[int, int], Any] = {}
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    sub = link.node.create_subscription(PointCloud2, f"{node.rstrip('/')}/{answer_topic}",
                                        lambda m: answers.__setitem__((m.header.stamp.sec, m.header.stamp.nanosec), m),
                                        qos)
    pub = link.node.create_publisher(msg_type, topic, qos)
    if not link.wait(lambda: pub.get_subscription_count() > 0, timeout):
        raise CssError(f"nobody subscribes to {pub.topic_name} within {timeout:g} s (is css_node running?)")
    key = (msg.header.stamp.sec, msg.header.stamp.nanosec)
    # the answer subscription must be matched too before the request goes out (css_node answers from another DDS
    # participant than the one its requests arrive on: the two discover this client independently)
    link.wait(lambda: sub.get_publisher_count() > 0, timeout)
    if before_send is not None:
        before_send()
    pub.publish(msg)
    if not link.wait(lambda: key in answers, timeout):
        raise CssError(f"no answer on {node}/{answer_topic} within {timeout:g} s")
    return answers[key]


def query(link: NodeLink, node: str, xyz: np.ndarray, timeout: float) -> np.ndarray:
    """Structured answer rows (x y z label expectation variance <class columns>) for points ``xyz`` (M, 3)."""
    from sensor_msgs.msg import PointCloud2, PointField

    from ..ros.conversions import header_msg

    f = pack_cloud({"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                    "z": xyz[:, 2].astype(np.float32)})
    msg = PointCloud2(header=header_msg(time.time_ns(), "map"), height=1, width=f["width"],
                      fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in f["fields"]],
                      is_bigendian=False, point_step=f["point_step"], row_step=f["row_step"], is_dense=True)
    msg.data = f["data"].tobytes()
    ans = _request(link, node, INPUT_TOPICS["point_queries"], PointCloud2, "point_query_results", msg, timeout)
    return unpack_cloud(ans)


def candidates(link: NodeLink, node: str, poses: np.ndarray, timeout: float,
               before_send: Callable[[], None] | None = None) -> np.ndarray:
    """Scored views (css_ros.io.clouds.SCORED_VIEW_DTYPE rows: x y z qx qy qz qw u_var u_exp info_gain; info_gain
    NaN from a node that does not publish it) for poses (M, 7) x y z qx qy qz qw, in request order."""
    from geometry_msgs.msg import PoseArray

    from ..ros.conversions import header_msg, pose_array_msg

    msg = pose_array_msg(poses[:, :3], poses[:, 3:], header_msg(time.time_ns(), "map"))
    return unpack_scored_views(_request(link, node, INPUT_TOPICS["candidates"], PoseArray, "candidate_scores",
                                        msg, timeout, before_send))


class NanStatusWatch:
    """Why css_node answered NaN rows: its ``requests_nan[<status>]`` counters on /diagnostics before and after one
    request (docs/reliability.md). css_node publishes its diagnostics at once whenever a subscriber matches them,
    so each new subscription asks for the current counters."""

    def __init__(self, link: NodeLink, node: str) -> None:
        from diagnostic_msgs.msg import DiagnosticArray

        self._link, self._type, self._name = link, DiagnosticArray, f"{node}: semantic map"
        self._latest: dict[str, int] | None = None
        self._subs = [self._subscribe()]
        self.before: dict[str, int] | None = None

    def _subscribe(self) -> Any:
        return self._link.node.create_subscription(self._type, "/diagnostics", self._on_diagnostics, 10)

    def _on_diagnostics(self, msg: Any) -> None:
        for st in msg.status:
            if st.name == self._name:
                counts = {}
                for kv in st.values:
                    if kv.key.startswith(_NAN_STATUS_KEYS):
                        try:
                            counts[kv.key] = int(float(kv.value))
                        except ValueError:
                            pass
                self._latest = counts

    def take_before(self, timeout: float) -> None:
        """The counters before the request (up to ``timeout`` s; none from a node without diagnostics)."""
        self._link.wait(lambda: self._latest is not None, timeout)
        self.before = self._latest

    def statuses(self, timeout: float) -> list[str]:
        """The statuses whose counters grew since :meth:`take_before` (e.g. ``no camera_info received yet``), sorted;
        empty when they cannot be known."""
        before = self.before
        if before is None:
            return []
        self._subs.append(self._subscribe())   # matching again: the node publishes its counters now
        if not self._link.wait(lambda: self._latest is not None and self._latest != before, timeout):
            return []
        after = self._latest or {}
        return [k[k.index("[") + 1:-1].removeprefix("candidates: ") for k, v in sorted(after.items())
                if v > before.get(k, 0)]


#: What to do about each status css_node gives NaN rows for (docs/reliability.md, "Every candidate request").
NAN_HINTS = {
    "no camera_info received yet": "the node has seen no frame yet, so it has no camera to render candidates with: "
                                   "play data into it first (css_demo plays the demo bag; a robot or a bag publishes "
                                   "camera_info, pose and segmentation), then ask again",
    "too many candidates": "more views than the node's max_candidates parameter: send fewer per request",
    "time budget exceeded": "scoring took longer than the node's candidate_time_budget: send fewer views or raise it",
    "request queue full": "more requests were pending at the node than it queues: ask again",
    "invalid candidate poses": "the node refused some poses (its log names them)",
    "node stopping": "the node is shutting down",
    "processing failed": "the node failed while scoring (its log says why)",
}
#: Why css_node answers NaN rows when its diagnostics cannot say (docs/reliability.md, "Every candidate request").
NAN_CAUSES = ("possible causes: the node has seen no frame yet (no camera_info: play data into it first), more views "
              "than its max_candidates, invalid poses, its candidate_time_budget exceeded or its request queue full; "
              "its log and /diagnostics (requests_nan[<status>]) say which")


def explain_nan(statuses: Sequence[str]) -> str:
    """Why css_node answered NaN rows, from the statuses it counted for the request (:meth:`NanStatusWatch.statuses`):
    each status and what to do about it; :data:`NAN_CAUSES` when there are none."""
    if not statuses:
        return NAN_CAUSES
    return "; ".join(f"{NAN_HINTS[s]} (css_node's status: {s})" if s in NAN_HINTS else f"css_node's status: {s}"
                     for s in statuses)


def _argmax_finite(values: np.ndarray) -> int:
    """Index of the largest finite value (first of ties), -1 when none is finite."""
    v = np.asarray(values, np.float64)
    ok = np.isfinite(v)
    return int(np.argmax(np.where(ok, v, -np.inf))) if ok.any() else -1


def candidates_table(rows: np.ndarray) -> str:
    """One line per view: position, U_var, U_exp, info_gain, and marks on the most uncertain view (largest
    U_var) and on the best next view (largest info_gain); NaN rows are never marked."""
    uncertain, best = _argmax_finite(rows["u_var"]), _argmax_finite(rows["info_gain"])
    out = []
    for i, r in enumerate(rows):
        marks = (["<- most uncertain"] if i == uncertain else []) + \
            (["<- best next view (info gain)"] if i == best else [])
        out.append([i, f"{r['x']:.3f}", f"{r['y']:.3f}", f"{r['z']:.3f}", f"{r['u_var']:.3e}", f"{r['u_exp']:.3f}",
                    f"{r['info_gain']:.4g}", "  ".join(marks)])
    return format_table(["view", "x", "y", "z", "U_var", "U_exp", "info_gain", ""], out)


def query_table(rows: np.ndarray, ignore_label: int = 255) -> str:
    names = [n for n in rows.dtype.names if n not in ANSWER_FIELDS]
    out = []
    for r in rows:
        lab = int(r["label"])
        cls = names[lab] if 0 <= lab < len(names) else "unknown"
        probs = sorted(((float(r[n]), n) for n in names if np.isfinite(r[n])), reverse=True)[:3]
        out.append([f"{r['x']:.3f}", f"{r['y']:.3f}", f"{r['z']:.3f}", cls, f"{r['expectation']:.3f}",
                    f"{r['variance']:.2e}", ", ".join(f"{n} {p:.2f}" for p, n in probs)])
    return format_table(["x", "y", "z", "class", "E", "Var", "top classes (E)"], out)


def read_request(args: argparse.Namespace) -> np.ndarray | None:
    """The points (M, 3) of ``query`` or poses (M, 7) of ``candidates``, checked (InputRefused); None for a
    service."""
    if args.command == "query":
        return check_points(read_rows(args.xyz, args.file, 3, "points"))
    if args.command == "candidates":
        if args.yaw:
            return check_poses(level_poses(check_yaws(read_rows(args.pose, args.file, 4, "x y z yaw poses"))))
        return check_poses(read_rows(args.pose, args.file, 7, "poses"))
    return None


def numbers_not_options(argv: Sequence[str]) -> list[str]:
    """``argv`` with the negative numbers after ``query`` / ``candidates`` that argparse would take for unknown
    options (``-inf``, ``-1e5``) prefixed by a space: then they are positionals, and float() strips the space."""
    out: list[str] = []
    for arg in argv:
        if arg.startswith("-") and any(a in ("query", "candidates") for a in out):
            try:
                float(arg)
                arg = f" {arg}"
            except ValueError:
                pass
        out.append(arg)
    return out


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of ``css_ctl``: 0 on success, 1 with a one-line error (or a refused request), 2 usage (a bad
    option, or points / poses that cannot be sent)."""
    try:
        args = build_parser().parse_args(numbers_not_options(sys.argv[1:] if argv is None else argv))
    except SystemExit as exc:   # argparse printed the usage and the option at fault
        return int(exc.code or 0)

    def work() -> int:
        try:
            data = read_request(args)
        except InputRefused as exc:
            print(f"css_ctl: error: {exc}", file=sys.stderr)
            return 2
        link = NodeLink()
        try:
            if args.command in SERVICES:
                ok, message = call_service(link, args.node, SERVICES[args.command], args.timeout)
                print(format_table(["service", "success", "message"],
                                   [[f"{args.node.rstrip('/')}/{SERVICES[args.command]}", ok, message]]))
                return 0 if ok else 1
            assert data is not None
            if args.command == "query":
                print(query_table(query(link, args.node, data, args.timeout)))
                return 0
            watch = NanStatusWatch(link, args.node)
            scores = candidates(link, args.node, data, args.timeout,
                                before_send=lambda: watch.take_before(min(args.timeout, 1.0)))
            nan = int(np.count_nonzero(~np.isfinite(scores["u_var"])))
            why = explain_nan(watch.statuses(min(args.timeout, 2.0))) if nan else ""
            if nan == len(scores):   # a table of NaN rows says nothing: only why, and what to do
                raise CssError(f"the node scored none of the {len(scores)} views: {why}")
            print(candidates_table(scores))
            if nan:
                print(f"css_ctl: {nan} of {len(scores)} views not scored (NaN rows): {why}", file=sys.stderr)
            return 0
        finally:
            link.close()

    return run_console("css_ctl", work)


if __name__ == "__main__":
    sys.exit(main())
