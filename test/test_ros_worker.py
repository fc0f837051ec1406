"""css_node's worker without rclpy: checkpoint policy and back-off, candidate slicing, budgets, stop flag."""
from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from css_ros.engine.camera import Camera
from css_ros.io.frame_gate import GateFrame
import pytest

import ros_helpers as rh
from css_ros.engine.gaussians import GaussianModel
from css_ros.errors import MapError
from css_ros.engine.semantic_map import SemanticMap
from css_ros.ros.diagnostics import Stats
from css_ros.ros.params import NodeParams
from css_ros.ros.work import CandidateJob, FrameJob, PointQueryJob, WarnLimiter, WorkQueue
from css_ros.ros.worker import CheckpointPolicy, MapWorker


class Sink:
    def __init__(self) -> None:
        self.frames: list[int] = []
        self.scores: list[tuple] = []
        self.gains: list[np.ndarray] = []   # info_gain of each answer (same order as scores)
        self.order: list[str] = []
        self.points: list = []
        self.clouds: list[int] = []

    def publish_frame(self, job, view) -> None:
        self.frames.append(job.stamp_ns)
        self.order.append("f")

    def publish_scores(self, header, positions, quats, u_var, u_exp, info_gain) -> None:
        self.scores.append((header, u_var.copy(), u_exp.copy()))
        self.gains.append(info_gain.copy())
        self.order.append("r")

    def publish_points(self, job) -> None:
        self.points.append(job)
        self.order.append("q")

    def publish_cloud(self, smap, min_evidence) -> int:
        self.clouds.append(smap.gaussian_semantics(min_evidence).observed.sum())
        return int(self.clouds[-1])


@pytest.fixture(scope="module")
def model(tmp_path_factory) -> GaussianModel:
    return GaussianModel.from_ply(rh.write_wall_model(tmp_path_factory.mktemp("w") / "wall.ply"))


def make_worker(model, ckpt: Path | None = None, **params) -> tuple[MapWorker, Sink, list[str], Stats]:
    p = NodeParams(**params)
    lines: list[str] = []
    sink, stats = Sink(), Stats()
    w = MapWorker(SemanticMap(model, rh.NUM_CLASSES), p, WorkQueue(p.max_pending_frames), sink,
                  WarnLimiter(lines.append, p.warn_period), stats, ckpt, lines.append, lines.append)
    return w, sink, lines, stats


def frame(stamp: int) -> FrameJob:
    q = rh.IDENTITY.copy()
    labels = rh.wall_labels().astype(np.int32)
    cam = Camera.from_pose(rh.K, labels.shape[1], labels.shape[0], np.zeros(3), q)
    return FrameJob(GateFrame(0, stamp, "cam", "map", labels, None, None, cam, np.zeros(3), q, "exact",
                              time.monotonic()), time.monotonic())


def request(m: int, t_received: float | None = None) -> CandidateJob:
    positions = np.zeros((m, 3))
    quats = np.tile(rh.IDENTITY, (m, 1))
    return CandidateJob("hdr", rh.K, rh.WIDTH, rh.HEIGHT, positions, quats, positions.copy(), quats.copy(),
                        time.monotonic() if t_received is None else t_received)


# ------------------------------------------------------------------ checkpoint policy
def test_policy_due_only_when_dirty_and_period_elapsed():
    pol = CheckpointPolicy(period=10.0, retry_max=100.0, now=0.0)
    assert not pol.due(20.0)                   # nothing changed
    pol.changed()
    assert not pol.due(5.0) and pol.due(10.0)
    pol.saved(10.0, dirty_at_save=1)
    assert pol.dirty == 0 and not pol.due(30.0)


def test_policy_changes_during_a_save_stay_dirty():
    pol = CheckpointPolicy(period=1.0, retry_max=10.0, now=0.0)
    pol.changed(3)
    pol.saved(1.0, dirty_at_save=2)
    assert pol.dirty == 1


def test_policy_period_zero_never_automatic():
    pol = CheckpointPolicy(period=0.0, retry_max=10.0, now=0.0)
    pol.changed()
    assert not pol.due(1e9)


def test_policy_failures_back_off_exponentially_capped_and_reset_on_success():
    pol = CheckpointPolicy(period=5.0, retry_max=60.0, now=0.0)
    pol.changed()
    delays = [pol.failed(0.0) for _ in range(6)]
    assert delays == [5.0, 10.0, 20.0, 40.0, 60.0, 60.0]
    assert pol.total_failures == 6 and pol.next_due == 60.0
    pol.saved(100.0, 1)
    assert pol.failures == 0 and pol.retry_delay() == 5.0 and pol.total_failures == 6


def test_failing_checkpoint_counted_warned_rate_limited_and_backs_off(model, tmp_path):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    w, _, lines, stats = make_worker(model, blocker / "map.npz", checkpoint_period=0.01, warn_period=60.0)
    w.policy.changed()
    for _ in range(3):
        assert not w.save_checkpoint("periodic", force=True)
    assert stats.snapshot()[0]["checkpoint_failures"] == 3 and w.policy.failures == 3
    warned = [line for line in lines if "checkpoint failed" in line]
    assert len(warned) == 1 and "next attempt in 1 s" in warned[0]
    assert w.warn.snapshot()[0]["checkpoint: checkpoint failed"] == 3
    assert not w.policy.due(time.monotonic() + 3.0) and w.policy.due(time.monotonic() + 4.1)


def test_checkpoint_written_after_frames_and_not_when_clean(model, tmp_path):
    ckpt = tmp_path / "map.npz"
    w, sink, _, stats = make_worker(model, ckpt)
    assert not w.save_checkpoint("shutdown") and not ckpt.exists()
    w.run_job(frame(1))
    assert sink.frames == [1] and w.policy.dirty == 1
    assert w.save_checkpoint("shutdown") and w.policy.dirty == 0
    assert SemanticMap.load(ckpt, model).frames_observed == 1


# ------------------------------------------------------------------ candidate requests
def test_big_request_split_into_slices_interleaved_with_frames(model):
    w, sink, _, stats = make_worker(model, candidate_slice=4, max_pending_frames=10)
    w.queue.put_request(request(10))
    for s in range(1, 4):
        w.queue.put_frame(frame(s))
    for _ in range(6):
        w.run_job(w.queue.get(0))
    # slice 1 of the request, frame, slice 2, frame, slice 3 (answers), frame
    assert sink.order == ["f", "f", "f", "r"]  # f, slice, f, slice, f, last slice -> answer
    assert sink.frames == [1, 2, 3] and len(sink.scores) == 1
    _, u_var, u_exp = sink.scores[0]
    assert np.all(np.isfinite(u_var)) and np.all(np.isfinite(u_exp))
    assert stats.snapshot()[0]["candidate_views_scored"] == 10


def test_info_gain_stored_per_view_in_request_order_across_slices(model):
    """The third column of score_views reaches the answer row by row; slicing does not change it."""
    w, sink, _, _ = make_worker(model, candidate_slice=3, max_pending_frames=10)
    w.process_frame(frame(1))
    job = request(7)
    job.positions_splat[:, 0] = np.linspace(-1.5, 1.5, 7)        # seven views along the wall
    job.quats_splat[5] = np.nan                                   # an invalid pose: NaN in every column
    while not job.done:
        w.process_slice(job)
    (_, u_var, u_exp), = sink.scores
    gain, = sink.gains
    ok = np.arange(7) != 5
    cams = [Camera.from_pose(rh.K, rh.WIDTH, rh.HEIGHT, job.positions_splat[i], job.quats_splat[i])
            .scaled(w.p.candidate_scale) for i in np.flatnonzero(ok)]
    ref = w.smap.score_views(cams, pixel_scale=1.0 / w.p.candidate_scale ** 2)   # as the worker counts them
    assert ref.shape == (6, 3), "SemanticMap.score_views returns no info_gain column"
    np.testing.assert_allclose(np.c_[u_var, u_exp, gain][ok], ref, rtol=1e-12)
    assert np.all(np.isnan([u_var[5], u_exp[5], gain[5]])) and np.all(gain[ok] >= 0)


def test_engine_without_info_gain_column_answers_nan_gains(model):
    w, sink, _, _ = make_worker(model)
    w.smap.score_views = lambda cams, **kw: np.full((len(cams), 2), 0.25)   # type: ignore[method-assign]
    w.process_slice(request(3))
    (_, u_var, _), = sink.scores
    assert np.all(u_var == 0.25) and np.all(np.isnan(sink.gains[0]))
    w.smap.score_views = lambda cams, **kw: np.tile([0.25, 0.5, 3.0], (len(cams), 1))  # type: ignore[method-assign]
    w.process_slice(request(2))
    np.testing.assert_array_equal(sink.gains[1], [3.0, 3.0])


def test_frames_never_wait_for_more_than_one_slice(model):
    w, sink, _, _ = make_worker(model, candidate_slice=2, max_pending_frames=10)
    w.queue.put_request(request(8))
    for s in range(1, 4):
        w.queue.put_frame(frame(s))
    kinds = []
    while True:
        job = w.queue.get(0)
        if job is None:
            break
        kinds.append("f" if isinstance(job, FrameJob) else "s")
        w.run_job(job)
    assert kinds == ["f", "s", "f", "s", "f", "s", "s"]


def test_request_over_time_budget_answered_nan_with_status(model):
    w, sink, lines, stats = make_worker(model, candidate_slice=2, candidate_time_budget=1.0)
    job = request(6, t_received=time.monotonic() - 2.0)
    w.run_job(job)
    (_, u_var, _), = sink.scores
    assert np.all(np.isnan(u_var))
    assert stats.snapshot()[0]["requests_nan[time budget exceeded]"] == 1
    assert "[candidates] time budget exceeded: 6 views answered with NaN scores" in lines[-1]


def test_stop_flag_answers_pending_requests_and_exits_fast(model):
    w, sink, _, stats = make_worker(model, candidate_slice=1)
    w.queue.put_request(request(20000))
    w.start()
    time.sleep(0.05)
    t0 = time.monotonic()
    assert w.stop(5.0)
    assert time.monotonic() - t0 < 2.0
    (_, u_var, _), = sink.scores                      # answered exactly once
    assert np.isnan(u_var[-1])
    assert stats.snapshot()[0]["requests_nan[node stopping]"] == 1


def test_point_query_slices_interleave_with_frames(model):
    # no time budget: on a loaded machine the first frames' kernel compiles could otherwise use it up
    w, sink, _, _ = make_worker(model, point_query_slice=2, cloud_period=0.0, candidate_time_budget=0.0)
    w.process_frame(frame(1))
    xyz = np.array(model.means[:5], dtype=np.float64)
    xyz[3] = np.nan  # a non-finite row is unknown
    w.queue.put_request(PointQueryJob("hdr", xyz, rh.NUM_CLASSES, 255, time.monotonic()))
    w.queue.put_frame(frame(2))
    w.queue.put_frame(frame(3))
    while any(w.queue.sizes()):
        w.run_job(w.queue.get(0.0))
    # frame 2, slice [0, 2), frame 3, slice [2, 4), slice [4, 5) -> answer: the frames never waited
    assert sink.order == ["f", "f", "f", "q"] and sink.frames == [1, 2, 3]
    job = sink.points[0]
    far = w.smap.query_points(np.array([[1e9, 1e9, 1e9]]))  # a non-finite point is answered as a far one
    assert job.labels[3] == 255 and np.all(job.expectation[3] == far.expectation[0])
    assert np.all(job.variance[3] == far.variance[0])
    final = w.smap.query_points(xyz[[2, 4]])  # rows 2 and 4 were evaluated on the final map
    np.testing.assert_allclose(job.expectation[[2, 4]], final.expectation, rtol=1e-6)
    np.testing.assert_allclose(job.variance[[2, 4]], final.variance, rtol=1e-6)
    np.testing.assert_array_equal(job.labels[[2, 4]], final.labels)


def test_cloud_is_sent_when_the_map_changed_and_the_period_elapsed(model):
    w, sink, _, stats = make_worker(model, cloud_period=10.0)
    assert w.cloud_due(0.0)              # the first cloud goes out at once (even of an empty map)
    w.publish_cloud(0.0)
    assert sink.clouds == [0] and not w.cloud_due(100.0)  # unchanged map: nothing new to send
    w.process_frame(frame(1))
    assert not w.cloud_due(5.0) and w.cloud_due(10.0)     # changed, but not before cloud_period
    w.publish_cloud(10.0)
    assert sink.clouds[-1] > 50 and stats.snapshot()[0]["clouds_published"] == 2


def test_load_map_replaces_the_state_and_refuses_another_model(model, tmp_path):
    w, _, _, _ = make_worker(model, cloud_period=0.0)
    w.process_frame(frame(1))
    saved = w.smap.concentrations.copy()
    w.save(tmp_path / "m.npz")
    w.reset_map()
    version = w.map_version
    assert "loaded" in w.load_map(tmp_path / "m.npz")
    np.testing.assert_array_equal(w.smap.concentrations, saved)
    assert w.map_version == version + 1 and w.policy.dirty == 0
    other = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "other.ply", seed=1, depth=4.0))
    SemanticMap(other, rh.NUM_CLASSES).save(tmp_path / "other.npz")
    with pytest.raises(MapError, match="this map belongs to model [0-9a-f]{16}, not "):
        w.load_map(tmp_path / "other.npz")
    np.testing.assert_array_equal(w.smap.concentrations, saved)


def test_frames_pending_at_stop_are_counted_and_said(model):
    """Frames still queued when the node stops are not processed: each is counted (frames_dropped_stopping) and one
    warning names them; none is published half-done and none vanishes unsaid."""
    w, sink, lines, stats = make_worker(model, max_pending_frames=8)
    for k in range(3):
        assert w.queue.put_frame(frame(10**9 * (k + 1))) is None
    w.stop_flag.set()   # stopped before the worker thread took any frame
    w.run()
    assert sink.frames == []
    counts, _, _ = stats.snapshot()
    assert counts["frames_dropped_stopping"] == 3
    said = [ln for ln in lines if "node stopping" in ln]
    assert len(said) == 1 and "3 pending frame(s) not processed" in said[0] and "1000000000" in said[0], lines
    assert w.queue.frames == []
