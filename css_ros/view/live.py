"""``css_view --live``: follow a running css_node over DDS (its ``~/view/*`` topics; no shared files).

The model arrives once (transient local), then only the Gaussians whose semantics changed; the page is
redrawn at most every REDRAW_PERIOD_S while updates come in. Observed frames (``~/view_uncertainty``) are drawn
as frustums coloured by U_var. Of the last answered candidate request (``~/candidate_scores``, whoever sent it:
css_nbv_client, css_ctl, a planner) the chosen view, the candidate with the largest expected information gain,
is drawn as a large highlighted frustum (``/candidates/best``) and the others as small faint ones; from a node
that publishes no info gain the most uncertain candidate (largest U_var) is chosen instead. The answer echoes
the request's poses in request order, so the request (``candidates``) itself need not be followed. A click
queries the node (``point_queries``). The page's "Frame image" control shows the node's ``~/surprise`` of its last
fused frame (of camera ``--camera``); the viewer subscribes to it only while it is chosen (an image a frame is much
more than the semantics stream), best effort and one deep (only the newest matters).
"""
from __future__ import annotations

import argparse
import threading
import time
from typing import Any

import numpy as np

from ..clients.node_link import NodeLink
from ..engine.classes import ClassSet
from ..engine.field3d import GaussianSemantics
from ..errors import CssError
from ..io.clouds import unpack_cloud, unpack_rgb, unpack_scored_views
from ..io.messages import image_to_array, stamp_to_ns
from ..io.view_stream import parse_info
from .data import ViewData
from .frame_images import surprise_caption

REDRAW_PERIOD_S = 0.5      # at most two redraws a second while updates arrive
NODE_GONE_S = 3.0          # no publisher of ~/view/semantics for this long: the page says the node is gone
FRUSTUM_FOV_Y = 0.8        # rad; drawn frustums (the stream carries poses, not intrinsics)
MAX_FRUSTUMS = 300         # observed frames drawn (the latest)
BEST_VIEW_COLOR = (20, 220, 90)     # the chosen candidate (largest info gain)
BEST_VIEW_SCALE = 0.35
FAINT_VIEW_COLOR = (185, 185, 185)  # the other candidates
FAINT_VIEW_SCALE = 0.1


def semantics_from(label: np.ndarray, e_q: np.ndarray, evidence: np.ndarray, num_classes: int, prior: float,
                   min_evidence: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(label int32, E float32, Var float32, S float64, observed bool) from the stream's quantised columns;
    Var = E (1 − E) / (1 + S) with S = evidence + C α₀ (SPEC §4)."""
    e = e_q.astype(np.float32) / 255.0
    total = evidence.astype(np.float64) + num_classes * prior
    var = (e * (1.0 - e) / (1.0 + total)).astype(np.float32)
    return label.astype(np.int32), e, var, total, evidence >= min_evidence


class LiveFollower:
    """Subscribes to a node's view stream and keeps the page up to date."""

    def __init__(self, node_name: str, on_status, camera: str = "") -> None:
        """``camera``: the namespace of the node's camera whose frame images are shown ("" = the default camera)."""
        from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import PointCloud2
        from std_msgs.msg import String

        self.node_name = "/" + node_name.strip("/")
        self.on_status = on_status
        self.link = NodeLink("css_view", start=False)
        self.node, self.context = self.link.node, self.link.context
        self.lock = threading.Lock()
        self.info: dict[str, Any] | None = None
        self.model_changed = False     # the node swapped its splat (model_watch_dir) after we started
        self.chunks: dict[int, Any] = {}
        self.pending: list[Any] = []
        self.frames: list[np.ndarray] = []
        self.candidates: Any = None    # (request stamp [ns], SCORED_VIEW_DTYPE rows) of the last answer
        self.last_update = 0.0
        self.updates = 0
        cam = camera.strip("/")
        self.surprise_topic = f"{self.node_name}/{cam}/surprise" if cam else f"{self.node_name}/surprise"
        self._surprise_sub: Any = None
        self._surprise: tuple[int, np.ndarray] | None = None   # (stamp [ns], (H, W) float32) not yet shown
        latched = QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE,
                             durability=DurabilityPolicy.TRANSIENT_LOCAL)
        reliable = QoSProfile(depth=50, reliability=ReliabilityPolicy.RELIABLE)
        n = self.node_name
        self.node.create_subscription(String, f"{n}/view/info", self._on_info, latched)
        self.node.create_subscription(PointCloud2, f"{n}/view/model", self._on_model, latched)
        self.node.create_subscription(PointCloud2, f"{n}/view/semantics", self._on_semantics, reliable)
        self.node.create_subscription(PointCloud2, f"{n}/view_uncertainty", self._on_frame, reliable)
        self.node.create_subscription(PointCloud2, f"{n}/candidate_scores", self._on_candidates, reliable)
        self.link.start()

    def _on_info(self, msg: Any) -> None:
        try:
            info = parse_info(msg.data)
        except ValueError as exc:
            self.on_status(f"unreadable {self.node_name}/view/info: {exc}")
            return
        with self.lock:
            if self.info is not None and info["fingerprint"] != self.info["fingerprint"]:
                self.on_status("the node now runs another model: restart css_view --live")
                self.model_changed = True   # its semantics index the new splat: no longer applied to this page
                return
            self.info = info

    def _on_model(self, msg: Any) -> None:
        with self.lock:
            self.chunks[int(unpack_cloud(msg, ("index",))["index"][0]) if msg.width else -1] = msg

    def _on_semantics(self, msg: Any) -> None:
        with self.lock:
            if self.model_changed:
                return
            self.pending.append(msg)
            self.last_update = time.monotonic()

    def _on_frame(self, msg: Any) -> None:
        with self.lock:
            self.frames.append(unpack_scored_views(msg))
            del self.frames[:-MAX_FRUSTUMS]

    def _on_candidates(self, msg: Any) -> None:
        try:
            rows = unpack_scored_views(msg)
        except CssError as exc:
            self.on_status(f"unreadable {self.node_name}/candidate_scores: {exc}")
            return
        with self.lock:
            self.candidates = (stamp_to_ns(msg.header.stamp), rows)

    def follow_surprise(self, on: bool) -> None:
        """Subscribe to the node's ``~/surprise`` (``on``) or leave it (the node then stops sending it)."""
        from rclpy.qos import HistoryPolicy, QoSProfile, ReliabilityPolicy
        from sensor_msgs.msg import Image

        if on and self._surprise_sub is None:
            qos = QoSProfile(depth=1, history=HistoryPolicy.KEEP_LAST, reliability=ReliabilityPolicy.BEST_EFFORT)
            self._surprise_sub = self.node.create_subscription(Image, self.surprise_topic, self._on_surprise, qos)
        elif not on and self._surprise_sub is not None:
            self.node.destroy_subscription(self._surprise_sub)
            self._surprise_sub = None

    def _on_surprise(self, msg: Any) -> None:
        try:
            image = image_to_array(msg, allowed=("32FC1",))
        except CssError as exc:
            self.on_status(f"unreadable {self.surprise_topic}: {exc}")
            return
        with self.lock:
            self._surprise = (stamp_to_ns(msg.header.stamp), image)

    def take_surprise(self) -> tuple[int, np.ndarray] | None:
        """The newest surprise image received since the last call (stamp [ns], (H, W) float32), or None."""
        with self.lock:
            latest, self._surprise = self._surprise, None
        return latest

    def model_complete(self) -> bool:
        with self.lock:
            if self.info is None:
                return False
            n, chunk = self.info["num_gaussians"], self.info["chunk"]
            return len([k for k in self.chunks if k >= 0]) >= -(-n // chunk)

    def resync(self, timeout: float) -> None:
        """Ask the node to resend every Gaussian's semantics (we joined late)."""
        from std_srvs.srv import Trigger

        client = self.node.create_client(Trigger, f"{self.node_name}/view/resync")
        if client.wait_for_service(timeout_sec=timeout):
            client.call_async(Trigger.Request())

    def node_alive(self) -> bool:
        return self.node.count_publishers(f"{self.node_name}/view/semantics") > 0

    def build_data(self) -> ViewData:
        """ViewData of the received model, every Gaussian unobserved until its semantics arrive."""
        info = self.info
        with self.lock:
            chunks = [self.chunks[k] for k in sorted(k for k in self.chunks if k >= 0)]
        cols = [unpack_cloud(m) for m in chunks]
        pts = np.concatenate(cols)
        n = int(info["num_gaussians"])
        if len(pts) != n or not np.array_equal(pts["index"], np.arange(n)):
            raise CssError(f"incomplete model stream from {self.node_name} ({len(pts)} of {n} Gaussians)")
        cov = np.empty((n, 3, 3), np.float32)
        for (i, j), name in zip(((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2)),
                                ("c00", "c01", "c02", "c11", "c12", "c22")):
            cov[:, i, j] = cov[:, j, i] = pts[name]
        classes = ClassSet(tuple(info["classes"]), np.asarray(info["palette"], np.uint8).reshape(-1, 3))
        c = classes.num_classes
        sem = GaussianSemantics(np.full(n, 255, np.int32), np.full(n, 1.0 / c, np.float32),
                                np.zeros(n, np.float32), np.full(n, c * info["prior"]), np.zeros(n),
                                np.zeros(n, bool))
        return ViewData(index=np.arange(n), centers=np.stack([pts["x"], pts["y"], pts["z"]], 1).astype(np.float32),
                        covariances=cov, rgb=unpack_rgb(pts["rgb"]).astype(np.float32) / 255.0,
                        opacity=pts["opacity"].astype(np.float32), classes=classes, semantics=sem, num_gaussians=n)

    def apply_updates(self, data: ViewData) -> int:
        """Apply the semantics messages received since the last call to ``data``; returns Gaussians changed."""
        with self.lock:
            msgs, self.pending = self.pending, []
        info, changed = self.info, 0
        sem = data.semantics
        for msg in msgs:
            rows = unpack_cloud(msg)
            idx = rows["index"].astype(np.int64)
            ok = idx < data.num_gaussians
            idx, rows = idx[ok], rows[ok]
            lab, e, var, total, obs = semantics_from(rows["label"], rows["expectation"], rows["evidence"],
                                                     data.classes.num_classes, info["prior"], info["min_evidence"])
            sem.label[idx], sem.expectation[idx], sem.variance[idx] = lab, e, var
            sem.total[idx], sem.evidence[idx], sem.observed[idx] = total, rows["evidence"], obs
            changed += len(idx)
        self.updates += len(msgs)
        return changed

    def close(self) -> None:
        self.link.close()


def serve_live(args: argparse.Namespace, ready: threading.Event | None = None,
               stop: threading.Event | None = None) -> int:
    """Follow ``args.node`` and serve the page until interrupted (or ``--exit-after`` seconds, or ``stop``)."""
    from .opening import up_vector
    from .server import MapView, check_port_free

    check_port_free(args.host, args.port)
    notes: list[str] = []
    follower = LiveFollower(args.node, notes.append, getattr(args, "camera", ""))
    deadline = None if args.exit_after is None else time.monotonic() + args.exit_after
    view = None
    try:
        print(f"css_view: waiting for {follower.node_name}/view/model (is css_node running with view_period > 0, "
              "same ROS_DOMAIN_ID?)", flush=True)
        while not follower.model_complete():
            if stop is not None and stop.is_set():
                return 0
            if deadline is not None and time.monotonic() > deadline:
                raise CssError(f"no model from {follower.node_name} within --exit-after")
            time.sleep(0.1)
        data = follower.build_data()
        follower.resync(10.0)
        view = MapView(data, args.host, args.port, query=None, title=f"live: {follower.node_name}",
                       up=up_vector(getattr(args, "up", None)), frame_images=True)
        view.query = _node_query(follower)
        print(f"css_view: following {follower.node_name} ({data.num_gaussians:,} Gaussians)", flush=True)
        print(f"css_view: open {view.url}  (Ctrl+C to stop)", flush=True)
        if ready is not None:
            ready.set()
        drawn_frames = drawn_candidates = None
        chosen_note = ""
        while (deadline is None or time.monotonic() < deadline) and not (stop is not None and stop.is_set()):
            time.sleep(REDRAW_PERIOD_S)
            with view.lock:
                changed = follower.apply_updates(view.data)
            if changed:
                view.redraw()
            age = time.monotonic() - follower.last_update if follower.last_update else None
            alive = follower.node_alive()
            state = ("**node gone**: no publisher of view/semantics; waiting for it to come back" if not alive
                     else f"live: {follower.updates} updates" + (f", last {age:.1f} s ago" if age is not None else ""))
            with follower.lock:
                frames = list(follower.frames)
                cands = follower.candidates
            if frames and (drawn_frames is None or len(frames) != drawn_frames):
                _draw_views(view, "/trajectory", np.concatenate(frames), "magma")
                drawn_frames = len(frames)
            if cands is not None and cands is not drawn_candidates:
                chosen_note = _draw_candidates(view, cands[1])
                drawn_candidates = cands
            _follow_frame_image(view, follower)
            view.status_note = state + ("; " + notes[-1] if notes else "") + (f"\n\n{chosen_note}" if chosen_note else "")
            view.show_status()
    except KeyboardInterrupt:
        pass
    finally:
        if view is not None:
            view.stop()
        follower.close()
    return 0


def _follow_frame_image(view, follower: LiveFollower) -> None:
    """Subscribe to the node's surprise while the page shows it, and hand the newest one to the page."""
    follower.follow_surprise(view.frame_choice == "surprise")
    latest = follower.take_surprise()
    if latest is not None:
        stamp, image = latest
        view.show_frame_image("surprise", image, surprise_caption(image, stamp, follower.surprise_topic))


def _draw_views(view, prefix: str, rows: np.ndarray, cmap: str) -> None:
    """Frustums of scored views (SCORED_VIEW_DTYPE rows) coloured by U_var on a log scale."""
    import matplotlib

    u = rows["u_var"].astype(np.float64)
    ok = np.isfinite(u) & (u > 0)
    lo, hi = (np.log(u[ok].min()), np.log(u[ok].max())) if ok.any() else (0.0, 1.0)
    cm = matplotlib.colormaps[cmap]
    view.server.scene.remove_by_name(prefix)
    for i, r in enumerate(rows):
        t = (np.log(u[i]) - lo) / max(hi - lo, 1e-12) if ok[i] else 0.0
        color = tuple(int(255 * v) for v in cm(t)[:3]) if ok[i] else (128, 128, 128)
        _frustum(view, f"{prefix}/v{i:04d}", r, 0.15, color)


def _frustum(view, name: str, r: Any, scale: float, color: tuple[int, ...]) -> None:
    """A camera frustum at the pose of the scored-view row ``r`` (optical frame in the map)."""
    view.server.scene.add_camera_frustum(name, fov=FRUSTUM_FOV_Y, aspect=4 / 3, scale=scale, color=color,
                                         wxyz=(float(r["qw"]), float(r["qx"]), float(r["qy"]), float(r["qz"])),
                                         position=(float(r["x"]), float(r["y"]), float(r["z"])))


def chosen_candidate(rows: np.ndarray) -> tuple[int, str]:
    """(index, metric) of the view to take next among answered candidates: the largest finite ``info_gain``, or,
    when no row has one (a node that does not publish it), the largest finite ``u_var``; (-1, "") if none."""
    for metric in ("info_gain", "u_var"):
        v = rows[metric].astype(np.float64)
        ok = np.isfinite(v)
        if ok.any():
            return int(np.argmax(np.where(ok, v, -np.inf))), metric
    return -1, ""


def _draw_candidates(view, rows: np.ndarray) -> str:
    """Redraw ``/candidates``: the chosen view (:func:`chosen_candidate`) as ``/candidates/best``, large and
    highlighted, the others as faint ``/candidates/vNNNN``. Returns a status line naming the chosen view."""
    view.server.scene.remove_by_name("/candidates")
    best, metric = chosen_candidate(rows)
    for i, r in enumerate(rows):
        if i != best:
            _frustum(view, f"/candidates/v{i:04d}", r, FAINT_VIEW_SCALE, FAINT_VIEW_COLOR)
    if best < 0:
        return f"candidates: none of {len(rows)} could be scored"
    _frustum(view, "/candidates/best", rows[best], BEST_VIEW_SCALE, BEST_VIEW_COLOR)
    what = (f"info gain {rows['info_gain'][best]:.4g}" if metric == "info_gain"
            else f"U_var {rows['u_var'][best]:.3e} (the node publishes no info gain)")
    return f"next best view (green): candidate {best} of {len(rows)}, {what}"


def _node_query(follower: LiveFollower):
    """SPEC §9 point query answered by the node (its ``point_queries`` topic)."""
    from ..clients.ctl import query
    from ..io.point_queries import ANSWER_FIELDS

    def ask(xyz: np.ndarray):
        rows = query(follower.link, follower.node_name, np.asarray(xyz, np.float64).reshape(-1, 3), 5.0)
        names = [n for n in rows.dtype.names if n not in ANSWER_FIELDS]
        e = np.stack([rows[n] for n in names], axis=1).astype(np.float64)
        v = np.full_like(e, np.nan)
        top = np.argmax(np.nan_to_num(e, nan=-1.0), axis=1)
        v[np.arange(len(rows)), top] = rows["variance"]
        return rows["label"].astype(np.int64), e, v
    return ask
