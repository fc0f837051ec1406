"""Live splat swap: css_node moves its map to a newer splat dropped into a watched folder.

Every ``model_watch_period`` seconds the folder ``model_watch_dir`` is scanned for ``*.ply`` files; the newest
one, when newer than the model in use and unchanged in size and time over two scans (a trainer still writing
it is left alone), is read on a background thread. A file that cannot be read (truncated, bad fields) is
warned about once and skipped. Then, under the map lock, the map is moved to the new splat by the transfer of
SPEC §10 (:func:`css_ros.engine.transfer.transfer_map`), the checkpoint path follows the new fingerprint and a
checkpoint is written (a restart then starts on the new splat and that checkpoint:
:func:`css_ros.ros.startup.newest_watched_model`). A transfer that keeps less than ``model_swap_min_ratio`` of
the map's evidence is refused (warning; the map and model stay, the file is not retried); below
``model_swap_warn_ratio`` the swap is done with a warning. ``frames_observed`` is kept by an accepted swap. The
live view stream (``~/view/*``) is restarted on the new model. Frames that arrive meanwhile wait in the bounded
work queue; beyond ``max_pending_frames`` the oldest are dropped and counted as ``frames_dropped_busy``.
Evidence exchange is re-bound to the new model (peers still on the old one are refused as "another splat model"
until they move).
The moved map keeps the node's ``sensor_model`` (and ``splat_to_map``'s depth scale).
"""
from __future__ import annotations

import threading
import time
from pathlib import Path
from typing import Any, Callable

from ..engine.gaussians import GaussianModel
from ..engine.transfer import transfer_map
from ..errors import CssError
from .params import NodeParams
from .startup import checkpoint_path
from .work import WarnLimiter

TOPIC = "model_swap"


class ModelWatcher:
    """Scans ``p.model_watch_dir`` from a node timer and swaps the node's model when a newer PLY is complete.

    Args:
        node: the CssNode (its ``worker``, ``evidence``, ``smap``, ``model_path``, ``checkpoint_path``).
        p: the node parameters.
        warn: rate-limited warnings; count: the node's counter function; log_info, log_warning: loggers
            (every refused or low-ratio swap is a warning of its own, never rate-limited).
    """

    def __init__(self, node: Any, p: NodeParams, warn: WarnLimiter, count: Callable[..., None],
                 log_info: Callable[[str], None], log_warning: Callable[[str], None] | None = None) -> None:
        self.node, self.p, self.warn, self.count, self.log_info = node, p, warn, count, log_info
        self.log_warning = log_warning or log_info
        self.folder = Path(p.model_watch_dir).expanduser() if p.model_watch_dir else None
        self._current_mtime = _mtime(Path(node.model_path))
        self._seen: dict[Path, tuple[int, int]] = {}   # path -> (size, mtime_ns) of the previous scan
        self._skipped: set[tuple[Path, int]] = set()    # unreadable files (path, mtime_ns), not retried
        self._busy = threading.Lock()
        if self.folder is not None:
            node.create_timer(p.model_watch_period, self.scan)

    def scan(self) -> None:
        """Timer: start a swap when the newest PLY of the folder is newer than the model and complete."""
        if self._busy.locked():
            return
        try:
            files = [(f.stat().st_mtime_ns, f.stat().st_size, f) for f in self.folder.glob("*.ply") if f.is_file()]
        except OSError as exc:
            self.warn(TOPIC, "model_watch_dir unreadable", str(exc), dropped=False)
            return
        if not files:
            return
        mtime, size, path = max(files)
        previous = self._seen.get(path)
        self._seen = {path: (size, mtime)}
        if mtime <= self._current_mtime or (path, mtime) in self._skipped or previous != (size, mtime):
            return
        threading.Thread(target=self._swap, args=(path, mtime), name="css_model_swap", daemon=True).start()

    def _swap(self, path: Path, mtime: int) -> None:
        with self._busy:
            t0 = time.perf_counter()
            try:
                model = GaussianModel.from_ply(path)
            except (CssError, OSError) as exc:
                self._skipped.add((path, mtime))
                self.count("model_swaps_failed")
                self.warn(TOPIC, "new model unreadable", f"{path}: {exc}; keeping the current model")
                return
            node, worker = self.node, self.node.worker
            min_ratio, warn_ratio = self.p.model_swap_min_ratio, self.p.model_swap_warn_ratio
            with worker.map_lock:   # frames wait (bounded queue) while the map moves
                moved, report = transfer_map(worker.smap, model)
                frames = worker.smap.frames_observed
                refused = report.ratio < min_ratio
                if not refused:
                    keep_sensor_model(worker.smap, moved)
                    worker.smap = node.smap = moved
                    node.model_path = path
                    ckpt = checkpoint_path(self.p, model.fingerprint)
                    worker.checkpoint_path = node.checkpoint_path = ckpt
                    worker.map_version += 1
                    worker.policy.changed()
                    node.evidence.rebind_locked()   # in this critical section: see EvidenceLink.rebind_locked
            what = (f"{path} ({model.num_gaussians} Gaussians, fingerprint {model.fingerprint[:12]}): evidence "
                    f"ratio {report.ratio:.4f} ({report.evidence_new:.4g} of {report.evidence_old:.4g} kept), "
                    f"{report.new_at_prior} new Gaussians at the prior, {report.old_dropped} of "
                    f"{report.old_observed} observed old ones dropped")
            if refused:   # almost surely another scene or a moved splat: the map stays as it is
                self._skipped.add((path, mtime))
                self.count("model_swaps_refused")
                self.log_warning(f"model swap REFUSED, keeping {node.model_path} and its map ({frames} frames): "
                                 f"{what}; below model_swap_min_ratio {min_ratio:g} (another scene, or a splat "
                                 f"in another frame?)")
                return
            if worker.view_stream is not None:
                worker.view_stream.rebind(moved)
            self._current_mtime = mtime
            self.count("model_swaps")
            line = (f"model swapped to {what}; {frames} frames observed kept; in "
                    f"{time.perf_counter() - t0:.2f} s; checkpoint {ckpt}")
            if report.ratio < warn_ratio:
                self.count("model_swaps_low_ratio")
                self.log_warning(f"{line}; LOW evidence ratio (below model_swap_warn_ratio {warn_ratio:g}): "
                                 "is this splat of the same scene and frame?")
            else:
                self.log_info(line)
            worker.save_checkpoint("model swap", force=True)


def keep_sensor_model(old: Any, new: Any) -> None:
    """The moved map keeps the node's sensor model, depth scale and rules for a changing world (transfer_map builds
    the new map with the paper's update and default rules; the evidence it carries, and its fingerprint in map files,
    are the old map's)."""
    new.depth_scale = old.depth_scale
    new.evidence_half_life, new.change_rules = old.evidence_half_life, old.change_rules
    if old.sensor_model is not None:
        new.sensor_model = old.sensor_model
    new.fused_sensor_model = old.fused_sensor_model


def _mtime(path: Path) -> int:
    try:
        return path.stat().st_mtime_ns
    except OSError:
        return 0
