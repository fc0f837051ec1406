"""css_node's worker thread: engine calls (update, render, score) and the checkpoint policy.

Guarantees (docs/reliability.md):

- Each frame is applied under the map lock in one piece, so a checkpoint always holds a state after a
  whole number of frames.
- The stop flag is checked between frames and between candidate slices: on SIGTERM the worker stops
  after at most one frame or one slice of ``candidate_slice`` views.
- A candidate request is scored ``candidate_slice`` views at a time with observed frames interleaved
  (a frame never waits for more than one slice); views not scored within ``candidate_time_budget`` s of
  the request's arrival, or when the node stops, are answered NaN. Every request gets one answer.
- A failing checkpoint is retried after an exponentially growing delay (capped at
  ``checkpoint_retry_max`` s); failures are counted and warned about at the warning rate limit.
"""
from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Protocol

import numpy as np

from ..engine.camera import Camera
from ..engine.final_form import DEFAULT_OUTPUTS
from ..engine.semantic_map import SemanticMap
from ..errors import CameraError, MapError
from ..engine.photometric import psnr
from ..io.frames import resample_to
from .params import NodeParams, half_life
from .work import CandidateJob, FrameJob, PointQueryJob, RequestJob, WarnLimiter, WorkQueue


class OutputSink(Protocol):
    """Where the worker sends its results (css_ros.ros.outputs.OutputPublisher)."""

    def publish_frame(self, job: FrameJob, view: Any) -> None: ...

    def publish_scores(self, header: Any, positions: np.ndarray, quats: np.ndarray, u_var: np.ndarray,
                       u_exp: np.ndarray, info_gain: np.ndarray) -> None: ...

    def publish_points(self, job: PointQueryJob) -> None: ...

    def publish_cloud(self, smap: Any, min_evidence: float) -> int: ...

    # optional: ``frame_outputs(camera_index) -> frozenset[str]``, the images a frame of that camera must render
    # (OutputPublisher: those of subscribed topics); a sink without it gets every image


@dataclass(frozen=True)
class LastFrame:
    """What the last fused frame's update found (diagnostics ``last_*``): pixels that added no evidence because
    their class is transient or their measured depth was nearer than the map (occluded), and the mean surprise
    over its labelled pixels (NaN: no surprise image, or no labelled pixel)."""

    transient: int = 0
    occluded: int = 0
    surprise_mean: float = math.nan


def mean_surprise(surprise: np.ndarray | None) -> float:
    """Mean of a surprise image over its labelled pixels (the finite ones); NaN when there is none."""
    if surprise is None:
        return math.nan
    finite = np.isfinite(surprise)
    n = int(np.count_nonzero(finite))
    return float(np.sum(surprise, where=finite, dtype=np.float64) / n) if n else math.nan


def check_half_life_of(loaded: SemanticMap, running: SemanticMap, path: Path, exchange: bool) -> None:
    """Refuse (MapError) a map file for ``~/load_map`` whose evidence half-life is not the running map's (its
    concentrations replace the running map's, whose rules stay), or that forgets while the node exchanges evidence."""
    h, mine = loaded.evidence_half_life, running.evidence_half_life
    if h is not None and exchange:
        raise MapError(f"map file {path} has an evidence half-life ({h:g} observations): its evidence is not "
                       "additive, and this node exchanges evidence")
    if h != mine:
        def name(v: float | None) -> str:
            return "none" if v is None else f"{v:g} observations"
        raise MapError(f"map file {path} has the evidence half-life {name(h)}, this node's map {name(mine)}: restart "
                       "the node on it (it resumes with the file's half-life unless evidence_half_life is set)")


class CheckpointPolicy:
    """When to write the next automatic checkpoint.

    ``period`` [s] between checkpoints while the map changes (0: never automatically); after a failure
    the next attempt waits ``max(period, 1 s) * 2**(failures - 1)``, capped at ``retry_max`` [s].
    """

    def __init__(self, period: float, retry_max: float, now: float) -> None:
        self.period = period
        self.retry_max = retry_max
        self.dirty = 0                # map changes since the last successful save
        self.failures = 0             # consecutive failed saves
        self.total_failures = 0
        self.next_due = now + period

    def changed(self, n: int = 1) -> None:
        self.dirty += n

    def due(self, now: float) -> bool:
        """An automatic checkpoint is due now."""
        return self.period > 0 and self.dirty > 0 and now >= self.next_due

    def retry_delay(self) -> float:
        """Wait [s] after the current run of failures."""
        if self.failures == 0:
            return self.period
        return min(self.retry_max, max(self.period, 1.0) * 2.0 ** (self.failures - 1))

    def saved(self, now: float, dirty_at_save: int) -> None:
        self.dirty = max(0, self.dirty - dirty_at_save)
        self.failures = 0
        self.next_due = now + self.period

    def failed(self, now: float) -> float:
        """Record a failure; returns the delay [s] until the next automatic attempt."""
        self.failures += 1
        self.total_failures += 1
        delay = self.retry_delay()
        self.next_due = now + delay
        return delay


class MapWorker:
    """Owns the semantic map; runs frames and candidate slices from a WorkQueue on its own thread."""

    def __init__(self, smap: Any, params: NodeParams, queue: WorkQueue, sink: OutputSink, warn: WarnLimiter,
                 stats: Any, checkpoint_path: Path | None, log_info: Callable[[str], None],
                 log_error: Callable[[str], None]) -> None:
        self.smap = smap
        self.p = params
        self.C = smap.num_classes
        self.queue = queue
        self.sink = sink
        self.warn = warn
        self.stats = stats
        self.checkpoint_path = checkpoint_path
        self.log_info = log_info
        self.log_error = log_error
        self.map_lock = threading.Lock()
        self.save_lock = threading.Lock()
        self.policy = CheckpointPolicy(params.checkpoint_period, params.checkpoint_retry_max, time.monotonic())
        self.stop_flag = threading.Event()
        self._thread: threading.Thread | None = None
        self.last_u = (float("nan"), float("nan"))
        self.last_psnr = float("nan")
        self.last_frame = LastFrame()
        self.map_version = 0            # +1 per map change (frame, reset, load): the cloud is sent on change
        self._cloud_version = -1        # map_version of the last ~/semantic_cloud (-1: none yet)
        self._cloud_next = 0.0          # time.monotonic() before which no cloud is sent
        self.view_stream: Any = None    # ros.view_publisher.ViewPublisher for css_view --live, or None
        #: called under the map lock after a reset or a load (the evidence exchange re-syncs in the same step)
        self.on_map_replaced: Callable[[], None] | None = None

    # ------------------------------------------------------------------ thread
    def start(self) -> None:
        self._thread = threading.Thread(target=self.run, name="css_worker", daemon=True)
        self._thread.start()

    def stop(self, timeout: float = 10.0) -> bool:
        """Set the stop flag, wake the worker and wait for it; True when it has stopped."""
        self.stop_flag.set()
        self.queue.close()
        if self._thread is not None:
            self._thread.join(timeout)
            return not self._thread.is_alive()
        return True

    def run(self) -> None:
        while not self.stop_flag.is_set():
            job = self.queue.get(timeout=0.2)
            if self.stop_flag.is_set():
                if isinstance(job, (CandidateJob, PointQueryJob)):
                    self.finish_request(job, "node stopping")
                elif isinstance(job, FrameJob):
                    self.queue.put_frame(job)   # counted with the other unprocessed frames below
                break
            self.run_job(job)
            now = time.monotonic()
            if self.policy.due(now):
                self.save_checkpoint("periodic")
            if self.cloud_due(now):
                self.publish_cloud(now)
            if self.view_stream is not None:
                self.view_stream.tick(now, self.map_version, self.map_lock)
        for job in self.queue.drain_requests():
            self.finish_request(job, "node stopping")
        unprocessed = self.queue.drain_frames()
        if unprocessed:   # every frame not answered is counted and said
            self.stats.count("frames_dropped_stopping", len(unprocessed))
            self.warn("worker", "node stopping", f"{len(unprocessed)} pending frame(s) not processed (stamps "
                                                 f"{', '.join(str(j.stamp_ns) for j in unprocessed[:5])}"
                                                 f"{', ...' if len(unprocessed) > 5 else ''})")

    def run_job(self, job: FrameJob | RequestJob | None) -> None:
        """One frame, or one slice of a request (the rest goes back to the queue)."""
        try:
            if isinstance(job, FrameJob):
                self.process_frame(job)
            elif isinstance(job, (CandidateJob, PointQueryJob)):
                if isinstance(job, CandidateJob):
                    self.process_slice(job)
                else:
                    self.process_points(job)
                if not job.done:
                    self.queue.resume_request(job)
        except Exception as exc:  # noqa: BLE001 - the worker must survive anything one frame does
            self.stats.count("worker_errors")
            self.warn("worker", "processing failed", f"{type(exc).__name__}: {exc}")
            if isinstance(job, (CandidateJob, PointQueryJob)):
                self.finish_request(job, "processing failed")

    # ------------------------------------------------------------------ frames
    def process_frame(self, job: FrameJob) -> None:
        p = self.p
        frame = job.frame
        cam = frame.camera
        labels = frame.labels
        valid = labels != p.ignore_label
        out_of_range = int(np.count_nonzero(valid & (labels >= self.C)))
        if out_of_range:
            self.stats.count("label_pixels_out_of_range", out_of_range)
            self.warn("segmentation", "class ids >= num_classes",
                      f"{out_of_range} pixels with ids >= {self.C} (max {int(labels.max())}) treated as no label",
                      dropped=False)
        needed = getattr(self.sink, "frame_outputs", None)
        outputs = set(DEFAULT_OUTPUTS) if needed is None else set(needed(frame.camera_index))
        if frame.image is not None:
            outputs.add("rgb")  # the rendered colour's PSNR against the input image (diagnostics)
        if p.output_scale == 1.0:
            outputs.add("surprise")  # its mean is in the diagnostics (the update makes it: no render)
        with self.map_lock:
            smap = self.smap
            if p.output_scale == 1.0:
                view = smap.observe(cam, labels, confidence=frame.confidence, outputs=outputs, depth=frame.depth)
                stats = smap.last_update   # observe returns the view; the update's pixel counts stay here
            else:   # the update at full resolution makes no surprise image (update() returns none)
                stats = smap.update(cam, labels, confidence=frame.confidence, depth=frame.depth)
                view = smap.render(cam.scaled(p.output_scale), outputs=outputs)
            self.policy.changed()
            self.map_version += 1
        self._count_update(stats, frame.depth is not None, view)
        self.sink.publish_frame(job, view)
        image = frame.image
        if image is not None and view.rgb is not None and image.shape[:2] != view.rgb.shape[:2]:
            image = resample_to(image, view.rgb.shape[:2])
        if image is not None and view.rgb is not None and view.rgb.shape == image.shape:
            self.last_psnr = psnr(view.rgb, image)
        self.last_u = (float(view.u_var), float(view.u_exp))
        self.stats.count("frames_processed")
        self.stats.count(f"camera[{p.cameras[frame.camera_index].strip('/') or '/'}].frames_processed")
        self.stats.frame_latency((time.monotonic() - frame.t_arrival) * 1e3)

    def _count_update(self, stats: Any, with_depth: bool, view: Any) -> None:
        """The update's pixel counts into the counters and :attr:`last_frame`."""
        self.stats.count("label_pixels_used", stats.used)
        self.stats.count("label_pixels_ignored", stats.ignored)
        if self.smap.sensor_model is not None:  # measured only with a sensor model (the paper's update needs no depth)
            self.stats.count("label_pixels_no_depth", stats.no_depth)
        self.stats.count("label_pixels_transient", stats.transient)
        self.stats.count("label_pixels_occluded", stats.occluded)
        if self.p.depth_topic:
            self.stats.count("frames_with_depth" if with_depth else "frames_without_depth")
        self.last_frame = LastFrame(stats.transient, stats.occluded, mean_surprise(view.surprise))

    # ------------------------------------------------------------------ candidate requests
    def process_slice(self, job: CandidateJob) -> None:
        """Score the next ``candidate_slice`` views of ``job``; answer it when done or over its time budget."""
        budget = self.p.candidate_time_budget
        if budget > 0 and time.monotonic() - job.t_received > budget:
            self.finish_request(job, "time budget exceeded")
            return
        m = len(job.positions)
        start, stop = job.next_index, min(m, job.next_index + self.p.candidate_slice)
        cams, scored = [], []
        for i in range(start, stop):
            if not np.all(np.isfinite(job.quats_splat[i])):
                continue
            try:
                cam = Camera.from_pose(job.K, job.width, job.height, job.positions_splat[i], job.quats_splat[i])
                cams.append(cam.scaled(self.p.candidate_scale))
                scored.append(i)
            except CameraError as exc:
                self.warn("candidates", "invalid candidate pose", f"{exc}; scored NaN", dropped=False)
        if cams:
            with self.map_lock:
                # candidates are rendered at candidate_scale: their evidence counts as a full-size frame would add it
                scores = self.smap.score_views(cams, pixel_scale=1.0 / self.p.candidate_scale ** 2)
            job.u_var[scored], job.u_exp[scored] = scores[:, 0], scores[:, 1]
            if scores.shape[1] > 2:  # (U_var, U_exp, info_gain); an engine without the column leaves NaN
                job.info_gain[scored] = scores[:, 2]
        job.next_index = stop
        self.stats.count("candidate_views_scored", len(cams))
        if job.done:
            self.finish_request(job, None)

    def process_points(self, job: PointQueryJob) -> None:
        """Evaluate the next ``point_query_slice`` points of ``job`` (SPEC §9); answer when done or over budget."""
        budget = self.p.candidate_time_budget
        if budget > 0 and time.monotonic() - job.t_received > budget:
            self.finish_request(job, "time budget exceeded")
            return
        start, stop = job.next_index, min(len(job.xyz), job.next_index + self.p.point_query_slice)
        rows = np.arange(start, stop)  # non-finite points get the far-point answer (field3d.query_field)
        if len(rows):
            with self.map_lock:
                q = self.smap.query_points(job.xyz_splat[rows], self.p.query_background_weight)
            job.labels[rows], job.expectation[rows], job.variance[rows] = q.labels, q.expectation, q.variance
        job.next_index = stop
        self.stats.count("query_points_evaluated", len(rows))
        if job.done:
            self.finish_request(job, None)

    def finish_request(self, job: RequestJob, reason: str | None) -> None:
        """Publish the answer of ``job``; ``reason``: why rows from next_index on are NaN (None: complete)."""
        points = isinstance(job, PointQueryJob)
        if reason is not None:
            left = len(job.positions) - job.next_index
            job.next_index = len(job.positions)
            self.stats.count(f"requests_nan[{reason}]")
            self.warn("point_queries" if points else "candidates", reason,
                      f"{left} {'points answered as unknown' if points else 'views answered with NaN scores'}",
                      dropped=False)
        if points:   # the sink counts <kind>_served when it publishes the answer
            self.sink.publish_points(job)
            self.stats.count("query_points", len(job.xyz))
        else:
            self.sink.publish_scores(job.header, job.positions, job.quats_in, job.u_var, job.u_exp, job.info_gain)
            self.stats.count("candidate_views", len(job.positions))
        self.stats.request_latency((time.monotonic() - job.t_received) * 1e3)

    # ------------------------------------------------------------------ the map in 3D
    def cloud_due(self, now: float) -> bool:
        """``~/semantic_cloud`` is due: enabled, the map changed since the last one, cloud_period elapsed."""
        return self.p.cloud_period > 0 and self.map_version != self._cloud_version and now >= self._cloud_next

    def publish_cloud(self, now: float) -> None:
        """Publish the observed Gaussians (the sink reads the map under the map lock)."""
        version = self.map_version
        with self.map_lock:
            n = self.sink.publish_cloud(self.smap, self.p.min_evidence)
        self._cloud_version = version
        self._cloud_next = now + self.p.cloud_period
        self.stats.count("clouds_published")
        self.stats.count("cloud_points", n)

    def load_map(self, path: Path) -> str:
        """Replace the map's state by the checkpoint at ``path`` (same checks as resume at start).

        Returns a status line; raises MapError (the current map is then kept unchanged).
        """
        # sensor_model passed (None included): a checkpoint fused with another sensor model is refused
        # the node's evidence_half_life when set, else the file's (as at start)
        given = {"evidence_half_life": half_life(self.p)} if half_life(self.p) is not None else {}
        loaded = SemanticMap.load(path, self.smap.model, expected_classes=self.C, sensor_model=self.smap.sensor_model,
                                  **given)
        check_half_life_of(loaded, self.smap, path, self.p.publish_evidence or bool(self.p.evidence_in.strip()))
        with self.map_lock:
            self.smap.concentrations[...] = loaded.concentrations
            self.smap.frames_observed = loaded.frames_observed
            self.smap.evidence_origin, self.smap.received = loaded.evidence_origin, loaded.received
            # load refused other updates' evidence: what it accepted is this map's own (or the prior only)
            self.smap.fused_sensor_model = loaded.fused_sensor_model
            self.map_version += 1
            self.policy.saved(time.monotonic(), self.policy.dirty)  # the map now equals the file
            if self.on_map_replaced is not None:
                self.on_map_replaced()
        note = ""
        if (loaded.prior, loaded.background) != (self.smap.prior, self.smap.background):
            note = (f"; its prior/background ({loaded.prior:g}, {loaded.background:g}) differ from the node's "
                    f"({self.smap.prior:g}, {self.smap.background:g}): concentrations taken as they are")
        return f"loaded {path} ({loaded.frames_observed} frames observed){note}"

    # ------------------------------------------------------------------ checkpoints
    def save(self, path: Path) -> float:
        """Write the map to ``path`` now (atomic); returns the time taken [s]. MapError/OSError on failure."""
        t0 = time.perf_counter()
        with self.save_lock, self.map_lock:
            dirty = self.policy.dirty
            self.smap.save(path)
            self.policy.saved(time.monotonic(), dirty)
        self.stats.count("checkpoints")
        return time.perf_counter() - t0

    def save_checkpoint(self, reason: str, force: bool = False) -> bool:
        """Save to checkpoint_path if set and changed (or ``force``); failures back off and are warned."""
        path = self.checkpoint_path
        if path is None or (not force and not self.policy.dirty):
            return False
        try:
            dt = self.save(path)
        except (MapError, OSError) as exc:
            delay = self.policy.failed(time.monotonic())
            self.stats.count("checkpoint_failures")
            self.warn("checkpoint", "checkpoint failed",
                      f"({reason}) to {path}: {exc}; failure {self.policy.failures} in a row, next attempt in "
                      f"{delay:g} s", dropped=False)
            return False
        self.log_info(f"checkpoint ({reason}) written to {path} in {dt:.2f} s")
        return True

    def reset_map(self) -> None:
        with self.map_lock:
            self.smap.reset()
            self.policy.changed()
            self.map_version += 1
            if self.on_map_replaced is not None:
                self.on_map_replaced()
