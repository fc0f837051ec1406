"""css_node's counters, status log line and /diagnostics message."""
from __future__ import annotations

import threading
import time
from collections import Counter, deque
from typing import Any, Callable

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue

from ..engine.photometric import format_psnr
from .work import WarnLimiter


class Stats:
    """Thread-safe counters and the last 200 frame / request latencies [ms]."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counts: Counter[str] = Counter()
        self._frame_ms: deque[float] = deque(maxlen=200)
        self._request_ms: deque[float] = deque(maxlen=200)

    def count(self, key: str, n: int = 1) -> None:
        """Add ``n`` to counter ``key``; a counter taken back to 0 by a negative ``n`` is dropped (the per-source
        keys of evidence sources that gave up their slot: the key set stays bounded)."""
        with self._lock:
            self.counts[key] += n
            if n < 0 and self.counts[key] <= 0:
                del self.counts[key]

    def frame_latency(self, ms: float) -> None:
        with self._lock:
            self._frame_ms.append(ms)

    def request_latency(self, ms: float) -> None:
        with self._lock:
            self._request_ms.append(ms)

    def snapshot(self) -> tuple[dict[str, int], list[float], list[float]]:
        with self._lock:
            return dict(self.counts), list(self._frame_ms), list(self._request_ms)


class StatusReporter:
    """Builds the status dict, logs it every log_period and publishes it on /diagnostics.

    Keys: the counters of :class:`Stats` (among them ``label_pixels_used``, ``label_pixels_ignored``,
    ``label_pixels_out_of_range`` and, with a sensor model, ``label_pixels_no_depth``: labelled pixels without
    rendered depth, which add nothing), ``dropped[<topic>]`` and ``warn[<topic>: <reason>]`` of the
    WarnLimiter, rates, latencies, the last view's uncertainty / PSNR (docs/reliability.md) and the constant
    entries of ``info`` (``sensor_model``: the update in use, ``sensor_model_fingerprint``).
    """

    def __init__(self, stats: Stats, warn: WarnLimiter, pending: Callable[[], tuple[int, int]],
                 last_view: Callable[[], tuple[float, float, float]], log: Callable[[str], None],
                 diag_pub: Any | None, name: str, hardware_id: str, now_msg: Callable[[], Any],
                 info: Callable[[], dict[str, str]] | None = None) -> None:
        self.stats = stats
        self.warn = warn
        self.pending = pending
        self.last_view = last_view
        self.log = log
        self.diag_pub = diag_pub
        self.name = name
        self.hardware_id = hardware_id
        self.now_msg = now_msg
        self.info = info
        self._last = (time.monotonic(), 0)
        self._last_problems: dict[str, int] = {}

    def status(self) -> dict[str, Any]:
        counts, frame_ms, req_ms = self.stats.snapshot()
        problems, dropped = self.warn.snapshot()
        now = time.monotonic()
        t_last, n_last = self._last
        processed = counts.get("frames_processed", 0)
        pending = self.pending()
        u_var, u_exp, last_psnr = self.last_view()
        out: dict[str, Any] = {
            **counts,
            "frames_processed": processed,
            "rate_hz": (processed - n_last) / max(now - t_last, 1e-9),
            "pending_frames": pending[0],
            "pending_requests": pending[1],
            "frame_latency_ms_median": float(np.median(frame_ms)) if frame_ms else float("nan"),
            "request_latency_ms_median": float(np.median(req_ms)) if req_ms else float("nan"),
            "last_u_var": u_var,
            "last_u_exp": u_exp,
            "last_psnr_db": last_psnr,
        }
        out.update({f"dropped[{k}]": v for k, v in dropped.items()})
        out.update({f"warn[{k}]": v for k, v in problems.items()})
        if self.info is not None:
            out.update(self.info())
        return out

    def report(self) -> None:
        """Log one status line and publish diagnostics (WARN level when new problems appeared)."""
        s = self.status()
        self._last = (time.monotonic(), s["frames_processed"])
        dropped = {k[8:-1]: v for k, v in s.items() if k.startswith("dropped[")}
        problems = {k[5:-1]: v for k, v in s.items() if k.startswith("warn[")}
        new = {k: v - self._last_problems.get(k, 0) for k, v in problems.items()
               if v != self._last_problems.get(k, 0)}
        self._last_problems = problems
        if s["frames_processed"] == 0 and not s.get("requests_served") and not new:
            self.log("waiting for input: no frame yet (needs segmentation and pose with matching stamps, "
                     "segmentation_confidence too while it has a publisher, and camera_info); segmentations "
                     f"received {s.get('segmentations_received', 0)}")
        else:
            self.log(f"frames processed {s['frames_processed']} ({s['rate_hz']:.2f} Hz, median latency "
                     f"{s['frame_latency_ms_median']:.0f} ms), pending {s['pending_frames']}, dropped "
                     f"{dropped or 0}; candidate requests served {s.get('requests_served', 0)} (median "
                     f"{s['request_latency_ms_median']:.0f} ms); last U_var {s['last_u_var']:.4g} "
                     f"U_exp {s['last_u_exp']:.4g}; PSNR {format_psnr(s['last_psnr_db'])}"
                     + (f"; labelled pixels without rendered depth {s['label_pixels_no_depth']}"
                        if s.get("label_pixels_no_depth") else "")
                     + (f"; new input problems: {new}" if new else ""))
        self.publish(s, new)

    def publish(self, s: dict[str, Any] | None = None, new: dict[str, int] | None = None) -> None:
        """Publish the diagnostics (``s``: :meth:`status`, taken now when None; WARN level when ``new`` problems
        appeared) without a log line: the periodic report, and at once whenever a subscriber matches an output."""
        if self.diag_pub is None:
            return
        s = self.status() if s is None else s
        level = DiagnosticStatus.WARN if new else DiagnosticStatus.OK
        st = DiagnosticStatus(level=level, name=f"{self.name}: semantic map",
                              message="; ".join(new) if new else "ok", hardware_id=self.hardware_id)
        st.values = [KeyValue(key=str(k), value=f"{v:.6g}" if isinstance(v, float) else str(v))
                     for k, v in s.items()]
        arr = DiagnosticArray(status=[st])
        arr.header.stamp = self.now_msg()
        self.diag_pub.publish(arr)
