"""css_node's changing-world parameters and worker without rclpy: transient_classes by name, evidence_half_life
against the evidence exchange, depth_topic names, and what the worker counts and fuses with a measured depth.
test_node_depth.py runs the same over DDS."""
from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np
import pytest

import ros_helpers as rh
from css_ros.engine.camera import Camera
from css_ros.engine.classes import ClassSet
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.errors import ConfigError, MapError
from css_ros.io.frame_gate import GateFrame
from css_ros.ros.diagnostics import Stats
from css_ros.ros.params import NodeParams, half_life, params_from_values
from css_ros.ros.startup import change_kwargs, check_exchange, load_engine, transient_class_ids
from css_ros.ros.work import FrameJob, WarnLimiter, WorkQueue
from css_ros.ros.worker import MapWorker, mean_surprise

CLASSES = ClassSet(("wall", "floor", "person", "dog"), np.zeros((4, 3), np.uint8))


# ------------------------------------------------------------------ parameters
def test_transient_classes_are_names_or_ids_of_the_class_setup():
    assert transient_class_ids(["person", "3", " dog "], CLASSES) == [2, 3]
    assert transient_class_ids([], CLASSES) == []
    for bad in ("persn", "4", "-1", "2.0", ""):
        with pytest.raises(ConfigError, match=r"transient_classes: .* is no class name nor id .*2 person"):
            transient_class_ids([bad], CLASSES)


def test_transient_classes_parameter_takes_names_and_integer_ids():
    assert params_from_values({"transient_classes": ["person", 3]}).transient_classes == ["person", "3"]
    for bad in ([1.5], [True], "person"):
        with pytest.raises(ConfigError, match="transient_classes"):
            params_from_values({"transient_classes": bad})


def test_half_life_zero_or_negative_is_off_and_refuses_the_evidence_exchange():
    assert half_life(params_from_values({"evidence_half_life": 0.0})) is None
    assert half_life(params_from_values({"evidence_half_life": -3})) is None
    assert half_life(params_from_values({"evidence_half_life": 20})) == 20.0
    for exchange in ({"publish_evidence": True}, {"evidence_in": "/robot_b/css_node/evidence"}):
        with pytest.raises(ConfigError, match="evidence_half_life=20.0: .*no longer additive.*publish_evidence"):
            params_from_values({"evidence_half_life": 20.0, **exchange})
        params_from_values({"evidence_half_life": 0.0, **exchange})   # off: exchanged as before
    for bad in (1e-3, math.inf, math.nan, 2e9):
        with pytest.raises(ConfigError, match="evidence_half_life"):
            params_from_values({"evidence_half_life": bad})


@pytest.mark.parametrize("values, match", [
    ({"depth_tolerance": -0.01}, "depth_tolerance"), ({"depth_tolerance": 101.0}, "depth_tolerance"),
    ({"depth_tolerance_relative": math.nan}, "depth_tolerance_relative"),
    ({"depth_topic": "depth image"}, "depth_topic"), ({"depth_topic": "1depth"}, "depth_topic"),
    ({"depth_topic": "/cam/depth", "cameras": ["a", "b"]}, "absolute name")])
def test_bad_depth_parameters_are_refused_by_name(values, match):
    with pytest.raises(ConfigError, match=match):
        params_from_values(values)


def test_a_map_with_a_half_life_is_refused_when_the_node_exchanges_evidence(model):
    p = params_from_values({"publish_evidence": True})
    check_exchange(p, SemanticMap(model, 4))
    with pytest.raises(ConfigError, match=r"half-life \(7 observations\).*publish_evidence:=false"):
        check_exchange(p, SemanticMap(model, 4, evidence_half_life=7.0))


def test_the_engine_gets_the_parameters(tmp_path, model_path):
    p = params_from_values(dict(model_path=str(model_path), class_file="", num_classes=4, checkpoint_path="",
                                transient_classes=["class_2"], evidence_half_life=12.5, depth_tolerance=0.2,
                                depth_tolerance_relative=0.01))
    smap = load_engine(p, lambda s: None, lambda s: None).smap
    assert smap.transient_classes == [2] and smap.evidence_half_life == 12.5
    assert (smap.change_rules.tol_abs, smap.change_rules.tol_rel) == (0.2, 0.01)
    assert "evidence_half_life" not in change_kwargs(NodeParams(), ClassSet.default(4))   # a file's may apply


def test_a_resumed_map_keeps_its_files_half_life_unless_the_parameter_is_set(tmp_path, model, model_path):
    ckpt = tmp_path / "map.npz"
    SemanticMap(model, 4, evidence_half_life=6.0).save(ckpt)
    base = dict(model_path=str(model_path), class_file="", num_classes=4, checkpoint_path=str(ckpt))
    assert load_engine(params_from_values(base), print, print).smap.evidence_half_life == 6.0
    assert load_engine(params_from_values({**base, "evidence_half_life": 2.0}), print, print).smap.evidence_half_life \
        == 2.0
    with pytest.raises(ConfigError, match=r"evidence half-life \(6 observations\).*cannot be exchanged"):
        load_engine(params_from_values({**base, "publish_evidence": True}), print, print)
    assert ckpt.is_file()   # refused at start, not renamed aside


# ------------------------------------------------------------------ worker
class Sink:
    def __init__(self) -> None:
        self.views: list = []

    def publish_frame(self, job, view) -> None:
        self.views.append(view)

    def frame_outputs(self, camera_index: int) -> frozenset[str]:
        return frozenset({"labels"})   # what subscribers ask for; the worker adds surprise for its mean


@pytest.fixture(scope="module")
def model_path(tmp_path_factory) -> Path:
    return rh.write_wall_model(tmp_path_factory.mktemp("w") / "wall.ply")


@pytest.fixture(scope="module")
def model(model_path) -> GaussianModel:
    return GaussianModel.from_ply(model_path)


def make_worker(model, smap: SemanticMap | None = None, **params) -> tuple[MapWorker, Sink, Stats]:
    p = NodeParams(**params)
    sink, stats = Sink(), Stats()
    w = MapWorker(smap or SemanticMap(model, rh.NUM_CLASSES), p, WorkQueue(p.max_pending_frames), sink,
                  WarnLimiter(lambda s: None, p.warn_period), stats, None, lambda s: None, lambda s: None)
    return w, sink, stats


def frame(labels: np.ndarray, depth: np.ndarray | None) -> FrameJob:
    cam = Camera.from_pose(rh.K, labels.shape[1], labels.shape[0], np.zeros(3), rh.IDENTITY)
    return FrameJob(GateFrame(0, 1, "cam", "map", labels.astype(np.int32), None, None, cam, np.zeros(3),
                              rh.IDENTITY.copy(), "exact", time.monotonic(), depth=depth), time.monotonic())


def test_a_depth_nearer_than_the_wall_blocks_its_region_as_if_unlabelled(model):
    """A person 1 m away in front of the wall (3 m) over a block of the image, no measurement elsewhere: the
    block's pixels are occluded and the map is the one of the same frame with that block unlabelled."""
    labels = rh.wall_labels()
    depth = np.full(labels.shape, np.nan, np.float32)
    depth[10:26, 8:30] = 1.0
    w, sink, stats = make_worker(model, depth_topic="depth")
    w.process_frame(frame(labels, depth))
    w.process_frame(frame(labels, None))
    counts = stats.snapshot()[0]
    assert counts["label_pixels_occluded"] == 16 * 22 and w.last_frame.occluded == 0
    assert (counts["frames_with_depth"], counts["frames_without_depth"]) == (1, 1)
    ref = SemanticMap(model, rh.NUM_CLASSES)
    hidden = labels.copy()
    hidden[10:26, 8:30] = ref.ignore_label
    cam = Camera.from_pose(rh.K, labels.shape[1], labels.shape[0], np.zeros(3), rh.IDENTITY)
    ref.update(cam, hidden)
    ref.update(cam, labels)
    np.testing.assert_allclose(w.smap.concentrations, ref.concentrations, rtol=1e-12, atol=0)


def test_transient_pixels_are_counted_per_frame_and_add_nothing(model):
    labels = rh.wall_labels()
    labels[:, :6] = 2                                     # a person at the left edge: class 2 is transient
    smap = SemanticMap(model, rh.NUM_CLASSES, transient_classes=[2])
    w, _, stats = make_worker(model, smap)
    w.process_frame(frame(labels, None))
    n = int(np.count_nonzero(labels == 2))
    assert w.last_frame.transient == n and stats.snapshot()[0]["label_pixels_transient"] == n
    assert "frames_with_depth" not in stats.snapshot()[0]       # no depth_topic: not counted
    assert np.all(w.smap.concentrations[:, 2] == w.smap.prior)   # class 2 never gained evidence


def test_surprise_mean_of_the_first_frame_is_one_minus_one_over_c(model):
    """On a fresh map every class has E = 1/C everywhere (prior and background alike): surprise 1 - 1/C on every
    labelled pixel, NaN on the unlabelled ones, whose mean ignores them."""
    labels = rh.wall_labels()
    labels[:5] = 255
    w, sink, _ = make_worker(model)
    w.process_frame(frame(labels, None))
    s = sink.views[0].surprise
    assert s is not None and s.dtype == np.float32 and sink.views[0].expectation is None
    np.testing.assert_array_equal(np.isnan(s), labels == 255)
    np.testing.assert_allclose(s[labels != 255], 1 - 1 / rh.NUM_CLASSES, rtol=1e-6)
    assert w.last_frame.surprise_mean == pytest.approx(1 - 1 / rh.NUM_CLASSES, rel=1e-6)
    w.process_frame(frame(labels, None))
    assert w.last_frame.surprise_mean < 0.5                       # the map now expects these labels


def test_mean_surprise_ignores_unlabelled_pixels_and_is_nan_without_any():
    assert mean_surprise(np.array([[0.25, np.nan], [0.75, np.nan]], np.float32)) == 0.5
    assert math.isnan(mean_surprise(np.full((2, 2), np.nan, np.float32)))
    assert math.isnan(mean_surprise(None))


def test_without_full_resolution_outputs_there_is_no_surprise(model):
    w, sink, _ = make_worker(model, output_scale=0.5)
    w.process_frame(frame(rh.wall_labels(), None))
    assert sink.views[0].surprise is None and math.isnan(w.last_frame.surprise_mean)


def test_a_model_swap_keeps_the_rules_for_a_changing_world(model):
    from css_ros.engine.transfer import transfer_map
    from css_ros.ros.model_swap import keep_sensor_model

    old = SemanticMap(model, 4, transient_classes=[1, 3], evidence_half_life=9.0, depth_tolerance=0.2,
                      depth_scale=2.0)
    moved, _ = transfer_map(old, model)
    keep_sensor_model(old, moved)
    assert moved.transient_classes == [1, 3] and moved.evidence_half_life == 9.0
    assert moved.change_rules == old.change_rules and moved.change_rules.depth_scale == 2.0


def test_load_map_takes_a_file_only_with_the_running_maps_half_life(model, tmp_path):
    path = tmp_path / "m.npz"
    SemanticMap(model, rh.NUM_CLASSES, evidence_half_life=3.0).save(path)
    w, _, _ = make_worker(model, publish_evidence=True)
    with pytest.raises(MapError, match="half-life .*not additive, and this node exchanges evidence"):
        w.load_map(path)
    w, _, _ = make_worker(model)
    with pytest.raises(MapError, match="half-life 3 observations, this node's map none: restart"):
        w.load_map(path)
    w, _, _ = make_worker(model, SemanticMap(model, rh.NUM_CLASSES, evidence_half_life=3.0))
    assert "loaded" in w.load_map(path)                           # the file's rate is the running map's
    w, _, _ = make_worker(model, SemanticMap(model, rh.NUM_CLASSES, evidence_half_life=8.0), evidence_half_life=8.0)
    assert "loaded" in w.load_map(path)                           # the node's parameter applies to the file
