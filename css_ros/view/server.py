"""The page: a viser server drawing the semantic splat with its modes, filters, legend, colour bar,
trajectory and click queries. One :class:`MapView` per ``css_view`` process; every browser tab shares it."""
from __future__ import annotations

import html
import socket
import threading
import time
from typing import Callable

import numpy as np

from ..errors import CssError
from .coloring import MODE_LABELS, MODES, ColorBar, mode_colors, visible_mask
from .data import ViewData
from .frame_images import FRAME_IMAGE_LABELS, FRAME_IMAGES, SURPRISE_BAR, surprise_rgb
from .opening import OpeningView, axis_label, opening_view

SPLAT_NAME = "/map"
DEFAULT_VAR_THRESHOLD = 0.05   # uncertain-only slider start (Var of the argmax class; the maximum is 0.25)
PICK_SIGMAS = 2.0              # a click hits a Gaussian whose centre is within this many std. devs of the ray
PICK_MIN_OPACITY = 0.1
FRUSTUM_SCALE = 0.15           # largest drawn size of a fused frame's frustum [m]; smaller where frames crowd
FRUSTUM_LINE_PX = 2.0          # frustum line width [screen px] (world-width lines fill the view near a frame)


def check_port_free(host: str, port: int) -> None:
    """Raise :class:`CssError` when ``host:port`` cannot be bound (in use, not allowed, or not a port number)."""
    if not 0 <= port <= 65535:
        raise CssError(f"--port {port} is not a TCP port (0..65535; 0 = any free port)")
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            s.bind((host if host not in ("", "0.0.0.0") else "0.0.0.0", port))
        except OSError as exc:
            raise CssError(f"cannot serve on {host}:{port}: {exc.strerror or exc} (is another css_view running? "
                           "pick another --port)") from None


def pick_gaussian(data: ViewData, keep: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> int | None:
    """Displayed-row index of the first Gaussian the ray ``origin + t·direction`` (t > 0, map frame) hits:
    centre within PICK_SIGMAS of its largest standard deviation from the ray and opacity >= PICK_MIN_OPACITY;
    the nearest along the ray wins. None when the ray hits nothing."""
    d = np.asarray(direction, np.float64)
    d = d / max(np.linalg.norm(d), 1e-12)
    rel = data.centers.astype(np.float64) - np.asarray(origin, np.float64)
    t = rel @ d
    perp = np.linalg.norm(rel - t[:, None] * d, axis=1)
    sigma = np.sqrt(np.maximum(np.linalg.eigvalsh(data.covariances.astype(np.float64))[:, -1], 1e-12))
    hit = keep & (t > 0) & (perp <= PICK_SIGMAS * sigma) & (data.opacity >= PICK_MIN_OPACITY)
    if not np.any(hit):
        return None
    rows = np.flatnonzero(hit)
    return int(rows[np.argmin(t[rows])])


def colorbar_html(bar: ColorBar, grey: str = "unobserved", element_id: str = "css-colorbar") -> str:
    """A horizontal CSS gradient with the two ends of the scale and its label; ``grey``: what grey means."""
    stops = ", ".join(f"rgb{c}" for c in bar.stops())
    fmt = (lambda v: f"{v:.2e}") if bar.log else (lambda v: f"{v:.3g}")
    scale = "log scale" if bar.log else "linear"
    return (f'<div id="{element_id}" data-vmin="{bar.vmin:.6g}" data-vmax="{bar.vmax:.6g}">'
            f'<div style="height:14px;background:linear-gradient(to right, {stops});border:1px solid #888"></div>'
            f'<div style="display:flex;justify-content:space-between;font-size:11px">'
            f'<span class="vmin">{fmt(bar.vmin)}</span><span>{scale}</span><span class="vmax">{fmt(bar.vmax)}</span>'
            f'</div><div style="font-size:11px">{html.escape(bar.label)}; grey = {html.escape(grey)}</div></div>')


def frustum_scale(positions: np.ndarray) -> float:
    """Frustum size [m] for camera centres (F, 3) [m]: FRUSTUM_SCALE, or half the median step between consecutive
    frames when they are closer (so that a dense trajectory does not become a fence)."""
    if len(positions) < 2:
        return FRUSTUM_SCALE
    step = float(np.median(np.linalg.norm(np.diff(positions, axis=0), axis=1)))
    return float(np.clip(0.5 * step, 0.03, FRUSTUM_SCALE))


def legend_html(names, palette) -> str:
    """Colour swatches of the classes (the toggles below carry the same names)."""
    items = "".join(
        f'<span style="display:inline-block;margin:1px 6px 1px 0;font-size:11px">'
        f'<span style="display:inline-block;width:10px;height:10px;margin-right:3px;border:1px solid #666;'
        f'background:rgb({int(c[0])},{int(c[1])},{int(c[2])})"></span>{html.escape(n)}</span>'
        for n, c in zip(names, palette))
    return f'<div id="css-legend">{items}</div>'


class MapView:
    """Serve ``data`` on ``host:port``.

    Args:
        data: what to draw.
        query: optional SPEC §9 point query, (M, 3) map-frame points -> (labels (M,), E (M, C), Var (M, C)).
        title: shown on the page.
        up: (3,) up axis of the map frame (``--up``); None: estimated (:mod:`css_ros.view.opening`).
        frame_images: add the "Frame image" control (live pages: a frame image of the node, such as its surprise,
            shown beside the splat; :meth:`show_frame_image` hands them over).
    """

    def __init__(self, data: ViewData, host: str = "127.0.0.1", port: int = 8080,
                 query: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]] | None = None,
                 title: str = "css_ros map", up: np.ndarray | None = None, frame_images: bool = False) -> None:
        import viser

        check_port_free(host, port)
        self.data = data
        self.opening: OpeningView = opening_view(data, up)
        self._heights = data.centers.astype(np.float64) @ self.opening.up   # (M,) [m] along the up axis
        # the default cut on the slider's 5 cm grid (so the slider echoes the same value back)
        self.cut = (float(np.floor(self.opening.cut * 20.0) / 20.0) if self.opening.cut is not None
                    else self.cut_max())
        self.query = query
        self.lock = threading.RLock()
        self.mode = "semantic"
        self.hidden: set[int] = set()
        self.observed_only = False
        self.uncertain_only = False
        self.var_threshold = DEFAULT_VAR_THRESHOLD
        self.redraws = 0
        self.frame_choice = "none"     # the frame image shown (FRAME_IMAGES)
        self.frame_draws = 0           # frame images sent to the page (the caption ends with this number)
        self._frames: dict[str, tuple[np.ndarray, str]] = {}   # kind -> (latest image, caption)
        self.status_note = ""          # extra status text (live mode: node state, age of the last update)
        self.keep = np.zeros(0, dtype=bool)
        self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.server.gui.configure_theme(control_width="medium", show_logo=False, show_share_button=False,
                                        dark_mode=False)
        self.server.gui.main_panel.dock_right()
        # the port the server really took (--port 0 asks the system for a free one)
        self.url = f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.server.get_port()}"
        self._build_gui(title)
        if frame_images:
            self._build_frame_gui()
        self._draw_trajectory()
        self.frame_camera()
        self.redraw()

    def frame_camera(self) -> None:
        """Open inside the map, on its observed surfaces (:func:`css_ros.view.opening.opening_view`): at a fused
        frame or the in-room viewpoint that shows the most classes, with the map's up axis up."""
        o = self.opening
        self.server.scene.set_up_direction(tuple(float(v) for v in o.up))
        cam = self.server.initial_camera
        cam.up = tuple(float(v) for v in o.up)
        cam.fov = o.fov_y
        cam.look_at = tuple(float(v) for v in o.look_at)
        cam.position = tuple(float(v) for v in o.position)

    def heights(self) -> np.ndarray:
        """(M,) heights [m] of the displayed Gaussians' centres along the up axis (their centres never move)."""
        return self._heights

    def cut_max(self) -> float:
        """The slider's top [m]: a cut height that keeps every Gaussian."""
        return float(np.ceil(max(self.opening.top, self.opening.high) * 20.0 + 1.0) / 20.0)

    def set_cut(self, height: float) -> None:
        """Draw only the Gaussians whose centre lies at or below ``height`` [m along the up axis] and redraw."""
        with self.lock:
            self.cut = float(height)
            if abs(self.cut_slider.value - self.cut) > 1e-9:
                self.cut_slider.value = self.cut
        self.redraw()

    # ------------------------------------------------------------------ GUI
    def _build_gui(self, title: str) -> None:
        gui = self.server.gui
        gui.add_markdown(f"**{html.escape(title)}**")
        self.status = gui.add_markdown("loading…")
        self.mode_dd = gui.add_dropdown("Colour", options=[MODE_LABELS[m] for m in MODES],
                                        initial_value=MODE_LABELS[self.mode])
        self.observed_cb = gui.add_checkbox("Observed only", initial_value=False)
        self.uncertain_cb = gui.add_checkbox("Uncertain only", initial_value=False)
        self.threshold = gui.add_slider("Var threshold", min=0.0, max=0.25, step=0.005,
                                        initial_value=DEFAULT_VAR_THRESHOLD)
        self.colorbar = gui.add_html("")
        o = self.opening
        lo = float(np.floor(o.low * 20.0) / 20.0)
        self.cut_slider = gui.add_slider(f"Cut above (m, {axis_label(o.up)} up)", min=lo, max=self.cut_max(),
                                         step=0.05, initial_value=self.cut,
                                         hint="hide Gaussians above this height (ceilings); the top keeps all; "
                                         f"up axis from {o.up_source}")
        self.cut_slider.on_update(lambda ev: self.set_cut(ev.target.value) if abs(ev.target.value - self.cut) > 1e-9
                                  else None)
        folder = gui.add_folder("Classes")
        self.class_cbs = []
        with folder:
            gui.add_html(legend_html(self.data.classes.names, self.data.classes.palette))
            counts = np.bincount(self.data.semantics.label[self.data.semantics.observed],
                                 minlength=self.data.classes.num_classes)
            for c, name in enumerate(self.data.classes.names):
                r, g, b = (int(v) for v in self.data.classes.palette[c])
                cb = gui.add_checkbox(f"{name} ({counts[c]})", initial_value=True,
                                      hint=f"class {c}, colour rgb({r},{g},{b})")
                self.class_cbs.append(cb)
                cb.on_update(lambda ev, c=c: self._toggle_class(c, ev.target.value))
        self.query_md = gui.add_markdown("Click the splat to query the map there (SPEC §9).")
        self.mode_dd.on_update(lambda ev: self.set_mode(MODES[[MODE_LABELS[m] for m in MODES].index(ev.target.value)]))
        self.observed_cb.on_update(lambda ev: self._set_filter(observed_only=ev.target.value))
        self.uncertain_cb.on_update(lambda ev: self._set_filter(uncertain_only=ev.target.value))
        self.threshold.on_update(lambda ev: self._set_filter(var_threshold=ev.target.value))
        self.server.scene.on_click()(self._on_click)

    def _build_frame_gui(self) -> None:
        gui = self.server.gui
        with gui.add_folder("Frame image"):
            self.frame_dd = gui.add_dropdown("Show", options=[FRAME_IMAGE_LABELS[k] for k in FRAME_IMAGES],
                                             initial_value=FRAME_IMAGE_LABELS[self.frame_choice],
                                             hint="an image of the node's last fused frame")
            self.frame_img = gui.add_image(np.zeros((1, 1, 3), np.uint8), format="png", visible=False)
            self.frame_bar = gui.add_html("")
            self.frame_md = gui.add_markdown("")
        labels = [FRAME_IMAGE_LABELS[k] for k in FRAME_IMAGES]
        self.frame_dd.on_update(lambda ev: self.set_frame_image(FRAME_IMAGES[labels.index(ev.target.value)]))

    def set_frame_image(self, kind: str) -> None:
        """Choose the frame image shown (one of :data:`~css_ros.view.frame_images.FRAME_IMAGES`; "none": none)."""
        if kind not in FRAME_IMAGES:
            raise ValueError(f"unknown frame image {kind!r} (one of {', '.join(FRAME_IMAGES)})")
        with self.lock:
            if kind == self.frame_choice:
                return   # no change (the dropdown echoing a programmatic change)
            self.frame_choice = kind
            if self.frame_dd.value != FRAME_IMAGE_LABELS[kind]:
                self.frame_dd.value = FRAME_IMAGE_LABELS[kind]
        self._draw_frame_image()

    def show_frame_image(self, kind: str, image: np.ndarray, caption: str) -> None:
        """The latest ``kind`` image ((H, W) float32 surprise) with its caption (markdown); drawn when chosen."""
        with self.lock:
            self._frames[kind] = (image, caption)
            chosen = kind == self.frame_choice
        if chosen:
            self._draw_frame_image()

    def frame_image(self, kind: str) -> np.ndarray | None:
        """The latest ``kind`` image handed over (None: none yet)."""
        with self.lock:
            latest = self._frames.get(kind)
        return None if latest is None else latest[0]

    def _draw_frame_image(self) -> None:
        with self.lock:
            kind = self.frame_choice
            latest = self._frames.get(kind)
            if kind == "none" or latest is None:
                self.frame_img.visible = False
                self.frame_bar.content = ""
                self.frame_md.content = "" if kind == "none" else f"waiting for the node's {kind} image…"
                return
            image, caption = latest
            self.frame_img.image = surprise_rgb(image)
            self.frame_img.visible = True
            self.frame_bar.content = colorbar_html(SURPRISE_BAR, "no label", "css-frame-colorbar")
            self.frame_draws += 1
            self.frame_md.content = f"{caption} · frame {self.frame_draws}"

    def _toggle_class(self, c: int, visible: bool) -> None:
        with self.lock:
            if (c not in self.hidden) == visible:
                return  # no change (the checkbox echoing a programmatic change)
            (self.hidden.discard if visible else self.hidden.add)(c)
        self.redraw()

    def _set_filter(self, **kw) -> None:
        with self.lock:
            for k, v in kw.items():
                setattr(self, k, v)
        self.redraw()

    def set_mode(self, mode: str) -> None:
        """Switch the colour mode (one of :data:`MODES`) and redraw."""
        if mode not in MODES:
            raise ValueError(f"unknown mode {mode!r}")
        with self.lock:
            self.mode = mode
            if self.mode_dd.value != MODE_LABELS[mode]:
                self.mode_dd.value = MODE_LABELS[mode]
        self.redraw()

    def set_class_visible(self, c: int, visible: bool) -> None:
        """Show or hide class ``c`` (as its legend checkbox does)."""
        self.class_cbs[c].value = visible
        self._toggle_class(c, visible)

    # ------------------------------------------------------------------ drawing
    def redraw(self) -> None:
        """Send the displayed Gaussians in the current mode and filters to every browser."""
        with self.lock:
            d = self.data
            rgb, bar = mode_colors(d, self.mode)
            keep = visible_mask(d, self.hidden, self.observed_only, self.uncertain_only, self.var_threshold)
            if self.cut < self.cut_max():
                keep &= self.heights() <= self.cut
            self.keep = keep
            self.colorbar.content = colorbar_html(bar) if bar is not None else ""
            if np.any(keep):
                self.server.scene.add_gaussian_splats(SPLAT_NAME, centers=d.centers[keep],
                                                      covariances=d.covariances[keep], rgbs=rgb[keep],
                                                      opacities=d.opacity[keep, None])
            else:
                self.server.scene.remove_by_name(SPLAT_NAME)
            self.redraws += 1
            self.show_status()

    def show_status(self) -> None:
        """Refresh the status line (Gaussians shown, mode, redraw count, live state)."""
        with self.lock:
            self.status.content = (f"showing {int(self.keep.sum()):,} of {self.data.num_gaussians:,} Gaussians · "
                                   f"{MODE_LABELS[self.mode]} · "
                                   + (f"cut above {self.cut:.2f} m · " if self.cut < self.cut_max() else "")
                                   + f"update {self.redraws} · "
                                   f"{time.strftime('%H:%M:%S')}" + (f"\n\n{self.status_note}" if self.status_note
                                                                     else ""))

    def _draw_trajectory(self) -> None:
        traj = self.data.trajectory
        if not traj:
            return
        import matplotlib
        from ..engine.camera import matrix_to_quaternion_xyzw

        u = np.array([t[3] for t in traj], dtype=np.float64)
        ok = np.isfinite(u) & (u > 0)
        lo, hi = (np.log(u[ok].min()), np.log(u[ok].max())) if ok.any() else (0.0, 1.0)
        cm = matplotlib.colormaps["magma"]
        scale = frustum_scale(np.array([t[0][:3, 3] for t in traj], np.float64))
        for i, (T, fov_y, aspect, uv) in enumerate(traj):
            x, y, z, w = matrix_to_quaternion_xyzw(T[:3, :3])
            if ok[i]:
                color = tuple(int(255 * v) for v in cm((np.log(uv) - lo) / max(hi - lo, 1e-12))[:3])
            else:
                color = (128, 128, 128)
            self.server.scene.add_camera_frustum(f"/trajectory/frame_{i:05d}", fov=float(fov_y),
                                                 aspect=float(aspect), scale=scale, color=color,
                                                 thickness=FRUSTUM_LINE_PX, thickness_units="screen",
                                                 wxyz=(w, x, y, z), position=tuple(T[:3, 3]))

    # ------------------------------------------------------------------ clicks
    def _on_click(self, event) -> None:
        if event.ray_origin is None or event.ray_direction is None:
            return
        with self.lock:
            row = pick_gaussian(self.data, self.keep, np.array(event.ray_origin), np.array(event.ray_direction))
        if row is None:
            self.query_md.content = "The click hit no Gaussian."
            return
        self.show_query(self.data.centers[row].astype(np.float64))

    def show_query(self, point: np.ndarray) -> str:
        """Query the map at ``point`` (map frame, m) and show the answer; returns the markdown shown."""
        p = np.asarray(point, np.float64).reshape(1, 3)
        self.server.scene.add_icosphere("/query_point", radius=0.03, color=(255, 0, 255), position=tuple(p[0]))
        if self.query is None:
            text = f"point ({p[0, 0]:.2f}, {p[0, 1]:.2f}, {p[0, 2]:.2f}) m: no map query available"
        else:
            labels, e, v = self.query(p)
            names = self.data.classes.names
            lab = int(labels[0])
            head = names[lab] if 0 <= lab < len(names) else "unknown (mostly empty space)"
            order = np.argsort(-e[0])[:5]
            rows = "\n".join(f"| {html.escape(names[c])} | {e[0, c]:.3f} | {v[0, c]:.2e} |" for c in order)
            text = (f"**Query** at ({p[0, 0]:.2f}, {p[0, 1]:.2f}, {p[0, 2]:.2f}) m: **{html.escape(head)}**\n\n"
                    f"| class | E | Var |\n|---|---|---|\n{rows}")
        self.query_md.content = text
        return text

    def stop(self) -> None:
        """Stop serving."""
        self.server.stop()
