"""css_node with a sensor model (parameter ``sensor_model``): the map it fuses over real DDS equals the engine's
with the same sensor model, ``~/confidence`` carries the calibrated confidence map, bad files stop the node at
start-up (exit 2, one line), and checkpoints of another update are refused like any other unusable checkpoint."""
from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.engine.camera import Camera  # noqa: E402
from css_ros.engine.classes import ClassSet  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402
from css_ros.engine.sensor_model import ConfidenceMap, SensorModel  # noqa: E402
from css_ros.engine.similarity import Similarity  # noqa: E402
from css_ros.ros.params import NodeParams  # noqa: E402
from css_ros.ros.startup import describe_sensor_model, load_engine  # noqa: E402

C = rh.NUM_CLASSES
NAMES = ClassSet.default(C).names          # the node's classes with class_file '' and num_classes C
#: metres per splat unit: the wall (splat z = 3) is 6 m from the map origin, 3 m from map z = 3
SPLAT_TO_MAP = [2.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]
#: map-frame positions (m) and yaws (rad) of the frames: far bin, near bin, between, turned half off the wall
POSES = [((0.0, 0.0, 0.0), 0.0), ((0.0, 0.0, 3.0), 0.0), ((0.3, 0.1, 1.5), 0.1), ((0.0, 0.0, 0.0), 0.75)]


def sensor_model(confidence: bool = True, classes: tuple[str, ...] = NAMES) -> SensorModel:
    """Two depth bins (0-4 m, 4-20 m); class 1 weighs nothing in the far bin; class 2 is confused with 3."""
    weight = np.ones((C, 2))
    weight[1, 1] = 0.0
    weight[2] = [0.7, 0.4]
    confusion = np.repeat(np.eye(C)[:, None, :], 2, axis=1)
    confusion[2, 0] = [0.0, 0.1, 0.8, 0.1]
    confusion[2, 1] = [0.0, 0.0, 0.6, 0.4]
    cmap = ConfidenceMap(np.array([1.2, 0.3, -0.2]), np.array([0.0, 0.5, 1.0]), np.array([0.05, 0.6, 0.97])) \
        if confidence else None
    return SensorModel(classes, [0.0, 4.0, 20.0], weight, confusion, cmap)


def frame_labels(k: int) -> np.ndarray:
    labels = rh.wall_labels()
    labels[: 4 + 3 * k, :] = 3          # a band of class 3, growing with k
    labels[-2:, : 5 * (k + 1)] = 255    # some pixels without a label
    return labels


def splat_camera(position: Any, yaw: float) -> Camera:
    """The camera the node builds from a pose in the map frame (splat_to_map's inverse)."""
    pos, quat = Similarity.from_params(SPLAT_TO_MAP).inverse().apply_pose(np.asarray(position, float),
                                                                           rh.yaw_quat(yaw))
    return Camera.from_pose(rh.K, rh.WIDTH, rh.HEIGHT, pos, quat)


def node_args(params: dict[str, Any]) -> list[str]:
    args = [sys.executable, "-m", "css_ros.node", "--ros-args"]
    for k, v in params.items():
        v = ("true" if v else "false") if isinstance(v, bool) else v
        args += ["-p", f"{k}:={v if v != '' else chr(39) * 2}"]
    return args


# ------------------------------------------------------------------------------------ (a), (b) over DDS
@pytest.mark.slow
def test_node_fuses_with_the_sensor_model_and_publishes_confidence(tmp_path: Path) -> None:
    from sensor_msgs.msg import Image
    from std_srvs.srv import Trigger

    from css_ros.io.messages import image_to_array, stamp_to_ns

    sm = sensor_model()
    sm_path = sm.save(tmp_path / "sensor_model.yaml")
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    ckpt = tmp_path / "map.npz"
    domain = rh.next_domain_id()
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=C, sensor_model=str(sm_path),
                               splat_to_map="[" + ", ".join(map(str, SPLAT_TO_MAP)) + "]", checkpoint_path=str(ckpt),
                               checkpoint_period=0.0, resume=False, log_period=0.3, warmup=False),
                          domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    client.received["confidence"] = []
    sub_conf = client.node.create_subscription(Image, "/css_node/confidence", client._recorder("confidence"), 100)
    try:
        assert client.wait_connected(60.0), node.log()
        assert client.wait_until(lambda: sub_conf.get_publisher_count() > 0, 20.0)
        assert client.wait_outputs_heard(("confidence",)), node.log()[-3000:]   # its writer matched ours too
        log = node.log()
        assert f"fingerprint {sm.fingerprint[:12]}" in log and "calibrated confidence" in log, log
        assert "sensor model sensor model" not in log

        ref = SemanticMap(model, C, sensor_model=sm, depth_scale=SPLAT_TO_MAP[0])
        paper = SemanticMap(model, C)
        no_depth = 0
        for k, (position, yaw) in enumerate(POSES):
            stamp = (k + 1) * 10**9
            labels = frame_labels(k)
            msg = client.send_frame_until_processed(stamp, labels, position, rh.yaw_quat(yaw), output="confidence")
            assert msg is not None, node.log()[-3000:]
            cam = splat_camera(position, yaw)
            view = ref.observe(cam, labels)
            no_depth += ref.last_update.no_depth
            paper.update(cam, labels)
            # (b) ~/confidence: 32FC1 with the frame's stamp and frame_id, = the engine's confidence image,
            # = sm.confidence(E, evidence) of the in-process render (0 where the label is ignore_label).
            assert msg.encoding == "32FC1" and stamp_to_ns(msg.header.stamp) == stamp
            assert msg.header.frame_id == "camera" and (msg.height, msg.width) == (rh.HEIGHT, rh.WIDTH)
            conf = image_to_array(msg)
            assert conf.dtype == np.float32
            np.testing.assert_allclose(conf, view.confidence, atol=1e-6)
            known = view.labels != 255
            assert known.any() and np.all(conf[~known] == 0.0)
            np.testing.assert_allclose(conf[known], sm.confidence(view.expectation, view.evidence)[known],
                                       atol=1e-5)
            semantic = client.wait_stamp("semantic", stamp)
            assert semantic is not None and np.array_equal(image_to_array(semantic), view.labels)
        assert no_depth > 0   # the turned frame sees past the wall
        assert client.wait_diag("label_pixels_no_depth", no_depth) == no_depth, node.log()[-3000:]
        diag = client.diagnostics()
        assert diag["sensor_model_fingerprint"] == sm.fingerprint and str(sm_path) in diag["sensor_model"]
        assert int(diag["label_pixels_used"]) == sum(int(np.count_nonzero(frame_labels(k) != 255))
                                                     for k in range(len(POSES)))

        # (a) the node's map = the engine's with the same sensor model (and not the paper's update).
        res = client.call(client.save_client)
        assert res.success and sm.fingerprint[:12] in res.message, res.message
        saved = SemanticMap.load(ckpt, model)
        assert saved.fused_sensor_model == sm.fingerprint and saved.frames_observed == len(POSES)
        np.testing.assert_allclose(saved.concentrations, ref.concentrations, rtol=0, atol=1e-9)
        assert np.abs(saved.concentrations - paper.concentrations).max() > 1.0

        # ~/load_map of a checkpoint fused with the paper's update: refused, map unchanged.
        paper.save(ckpt)
        load = client.node.create_client(Trigger, "/css_node/load_map")
        res = client.call(load)
        assert not res.success and "checkpoint refused, map unchanged" in res.message, res.message
        assert "the paper's update" in res.message
        assert client.call(client.save_client).success
        np.testing.assert_allclose(SemanticMap.load(ckpt, model).concentrations, ref.concentrations, atol=1e-9)
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-3000:]


# ------------------------------------------------------------------------------------ (c) bad files: exit 2
def _bad_files(tmp: Path) -> dict[str, tuple[Path, str]]:
    """case -> (file, text the FATAL line must hold)."""
    good = sensor_model().to_dict()
    out: dict[str, tuple[Path, str]] = {}
    out["missing file"] = (tmp / "nope" / "sm.yaml", "does not exist")
    other = sensor_model(classes=("floor", "wall", "chair", "table"))
    out["other classes"] = (other.save(tmp / "other.yaml"), "class 0 is 'floor', the map's class file says 'class_0'")
    fewer = SensorModel(NAMES[:3], [0.0, 4.0], np.ones((3, 1)))
    out["other class count"] = (fewer.save(tmp / "fewer.yaml"), "is for 3 classes, the map has 4")
    d = dict(good, weight=[[float("nan"), 1.0]] + good["weight"][1:])
    del d["fingerprint"]
    (tmp / "nan.yaml").write_text(yaml.safe_dump(d))
    out["NaN weight"] = (tmp / "nan.yaml", "weight entries must be finite and in [0, 1]")
    d = dict(good)
    d["confusion"] = [[[0.9 * v for v in row] for row in per_label] for per_label in good["confusion"]]
    del d["fingerprint"]
    (tmp / "unnormalised.yaml").write_text(yaml.safe_dump(d))
    out["unnormalised confusion"] = (tmp / "unnormalised.yaml", "sums to 0.9, not 1")
    d = dict(good, weight=[[0.5, 0.5]] + good["weight"][1:])   # edited, fingerprint left as it was
    (tmp / "edited.yaml").write_text(yaml.safe_dump(d))
    out["fingerprint mismatch"] = (tmp / "edited.yaml", "do not match its fingerprint")
    out["PLY"] = (rh.write_wall_model(tmp / "as_sensor_model.ply"), "is not a readable YAML file")
    # the second probe (docs/reliability.md "Sensor-model files"): every reader refusal is the same FATAL line
    out["A name too long"] = (tmp / ("a" * 300 + ".yaml"), "cannot be read: file name too long")  # was a traceback
    (tmp / "adir.yaml").mkdir()
    out["H directory"] = (tmp / "adir.yaml", "is a directory, not a regular file")
    os.mkfifo(tmp / "fifo.yaml")
    out["H FIFO"] = (tmp / "fifo.yaml", "is a FIFO (named pipe), not a regular file")
    d = dict(good, classes=["B" * 100_000] + list(NAMES[1:]))
    del d["fingerprint"]
    (tmp / "long_class.yaml").write_text(yaml.safe_dump(d))
    out["B long class name"] = (tmp / "long_class.yaml", "class 0 is '" + "B" * 60 + "'…")
    d = dict(good, confidence=dict(good["confidence"], coef=[1e308, -1e308, 0.0]))
    (tmp / "coef.yaml").write_text(yaml.safe_dump(d))
    out["D huge coef"] = (tmp / "coef.yaml", "confidence.coef must be within +-1e+06")
    d = dict(good, weight=[[0.0, 0.0] for _ in NAMES])
    del d["fingerprint"]
    (tmp / "zero.yaml").write_text(yaml.safe_dump(d))
    out["E zero weights"] = (tmp / "zero.yaml", "every weight is below 1e-06")
    (tmp / "dup.yaml").write_text(yaml.safe_dump(good) + "weight: [[1.0]]\n")
    out["G duplicate key"] = (tmp / "dup.yaml", "key 'weight' given twice")
    return out


def test_bad_sensor_model_files_are_clean_fatal_exits(tmp_path: Path) -> None:
    """Every case starts its own css_node (side by side: ~1 s each) that must exit 2 with one FATAL line
    ``cannot start: sensor model <file> ...`` naming the parameter, and leave the checkpoint alone."""
    model = rh.write_wall_model(tmp_path / "wall.ply")
    ckpt = tmp_path / "map.npz"
    m = SemanticMap(GaussianModel.from_ply(model), C)
    m.concentrations[:] = 2.0
    m.save(ckpt)
    original = ckpt.read_bytes()
    cases = _bad_files(tmp_path)
    procs = {}
    for case, (path, _) in cases.items():
        params = dict(model_path=str(model), class_file="", num_classes=C, warmup=False, sensor_model=str(path),
                      checkpoint_path=str(ckpt))
        procs[case] = subprocess.Popen(node_args(params), env=rh.node_env(rh.next_domain_id()),
                                       stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    for case, proc in procs.items():
        out, _ = proc.communicate(timeout=120)
        path, expect = cases[case]
        assert proc.returncode == 2, (case, out)
        fatal = [line for line in out.splitlines() if "cannot start:" in line]
        assert len(fatal) == 1 and "FATAL" in fatal[0] and "Traceback" not in out, (case, out)
        assert f"sensor model {path}" in fatal[0] and expect in fatal[0], (case, fatal[0][:2000])
        assert f"(parameter sensor_model='{path}')" in fatal[0], (case, fatal[0][:2000])
        assert len(fatal[0]) < 2000, (case, len(fatal[0]))       # B: no value is echoed whole
    assert ckpt.read_bytes() == original and not list(tmp_path.glob("map.npz.rejected-*"))


# ------------------------------------------------------------------------------------ (d) resume
@pytest.mark.slow
def test_resume_of_a_checkpoint_without_the_sensor_model_is_refused_and_kept_aside(tmp_path: Path) -> None:
    """The documented rule: a checkpoint fused with another update (here the paper's) is refused like any other
    unusable checkpoint: warned, renamed to <name>.rejected-<time> unchanged, and the node starts fresh."""
    sm = sensor_model(confidence=False)
    sm_path = sm.save(tmp_path / "sensor_model.yaml")
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    ckpt = tmp_path / "map.npz"
    old = SemanticMap(model, C)
    old.update(splat_camera((0, 0, 0), 0.0), rh.wall_labels())
    old.save(ckpt)
    original = ckpt.read_bytes()
    domain = rh.next_domain_id()
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=C, sensor_model=str(sm_path),
                               checkpoint_path=str(ckpt), checkpoint_period=0.0, resume=True, warmup=False),
                          domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        # the start-up summary is logged after the subscriptions exist: wait for it rather than race it
        assert node.wait_log("~/confidence is not published", 30.0), node.log()   # logged after the summary line
        log = node.log()
        assert "starting fresh: checkpoint refused" in log and "fused with the paper's update" in log, log
        assert "vote rows, no confidence map" in log
        (aside,) = tmp_path.glob("map.npz.rejected-*")
        assert aside.read_bytes() == original
        assert client.node.count_publishers("/css_node/confidence") == 0
        assert client.call(client.save_client).success
        fresh = SemanticMap.load(ckpt, model)
        assert np.all(fresh.concentrations == fresh.prior) and fresh.fused_sensor_model == sm.fingerprint
    finally:
        client.close()
        assert node.stop() == 0, node.log()[-3000:]


def _engine(tmp: Path, **params: Any) -> tuple[Any, list[str]]:
    warnings: list[str] = []
    params.setdefault("checkpoint_path", str(tmp / "map.npz"))
    p = NodeParams(model_path=str(tmp / "wall.ply"), class_file="", num_classes=C, **params)
    return load_engine(p, lambda _m: None, warnings.append), warnings


def test_resume_rules_of_load_engine(tmp_path: Path) -> None:
    """In-process (no DDS): the same checkpoint resumes with its own sensor model, is refused with another one or
    without one; a prior-only checkpoint of another update resumes and is then the sensor model's own."""
    sm = sensor_model(confidence=False)
    sm_path = sm.save(tmp_path / "sensor_model.yaml")
    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    ckpt = tmp_path / "map.npz"
    made = SemanticMap(model, C, sensor_model=sm, depth_scale=2.0)
    made.update(splat_camera((0, 0, 0), 0.0), rh.wall_labels())
    made.save(ckpt)
    engine, warnings = _engine(tmp_path, sensor_model=str(sm_path), splat_to_map=SPLAT_TO_MAP)
    assert engine.resume_status.startswith("resumed") and not warnings
    assert engine.smap.sensor_model.fingerprint == sm.fingerprint and engine.smap.depth_scale == 2.0
    np.testing.assert_array_equal(engine.smap.concentrations, made.concentrations)
    engine, warnings = _engine(tmp_path)        # no sensor model now: refused, kept aside
    assert "checkpoint refused" in engine.resume_status and f"sensor model {sm.fingerprint[:12]}" in warnings[0]
    assert not ckpt.exists() and engine.smap.sensor_model is None
    assert describe_sensor_model(engine.smap.sensor_model) == "sensor model: none (paper update)"
    SemanticMap(model, C).save(ckpt)            # the paper's update, prior only
    engine, warnings = _engine(tmp_path, sensor_model=str(sm_path))
    assert engine.resume_status.startswith("resumed") and not warnings
    assert engine.smap.fused_sensor_model == sm.fingerprint


def test_refusal_of_another_update_says_why_and_how_to_keep_both(tmp_path: Path) -> None:
    """A checkpoint fused with a sensor model, a node started without one: the warning says why (units) and how to
    keep both (a checkpoint per update, the old file renamed back); following it resumes both maps."""
    sm = sensor_model(confidence=False)
    sm_path = sm.save(tmp_path / "sensor_model.yaml")
    model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    ckpt = tmp_path / "map.npz"
    made = SemanticMap(model, C, sensor_model=sm, depth_scale=2.0)
    made.update(splat_camera((0, 0, 0), 0.0), rh.wall_labels())
    made.save(ckpt)
    engine, warnings = _engine(tmp_path)                     # the paper's update now
    (aside,) = tmp_path.glob("map.npz.rejected-*")
    (warning,) = warnings
    assert f"sensor model {sm.fingerprint[:12]}" in warning and "different units" in warning
    own = tmp_path / "map_paper.npz"
    assert f"-p checkpoint_path:={own}" in warning
    assert f"rename {aside.name} back to {ckpt.name}" in warning and "fingerprint " + sm.fingerprint[:12] in warning
    # follow the advice: this update gets its own checkpoint, the old map its name back
    engine.smap.update(splat_camera((0, 0, 3), 0.0), rh.wall_labels())
    engine.smap.save(own)
    aside.rename(ckpt)
    paper, warnings = _engine(tmp_path, checkpoint_path=str(own))
    assert paper.resume_status.startswith("resumed") and not warnings and paper.smap.sensor_model is None
    again, warnings = _engine(tmp_path, sensor_model=str(sm_path), splat_to_map=SPLAT_TO_MAP)
    assert again.resume_status.startswith("resumed") and not warnings
    np.testing.assert_array_equal(again.smap.concentrations, made.concentrations)


def test_model_swap_keeps_the_sensor_model(tmp_path: Path) -> None:
    """The transfer to a new splat (ros/model_swap.py) keeps the node's sensor model and depth scale: the moved
    map then fuses frames as a map built with them."""
    from css_ros.engine.transfer import transfer_map
    from css_ros.ros.model_swap import keep_sensor_model

    sm = sensor_model()
    old_model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "a.ply", seed=0))
    new_model = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "b.ply", seed=1))
    old = SemanticMap(old_model, C, sensor_model=sm, depth_scale=2.0)
    old.update(splat_camera((0, 0, 0), 0.0), frame_labels(0))
    moved, _ = transfer_map(old, new_model)
    keep_sensor_model(old, moved)
    assert moved.sensor_model is sm and moved.depth_scale == 2.0 and moved.fused_sensor_model == sm.fingerprint
    ref = SemanticMap(new_model, C, sensor_model=sm, depth_scale=2.0)
    ref.concentrations[...] = moved.concentrations
    cam = splat_camera((0.0, 0.0, 3.0), 0.0)
    moved.update(cam, frame_labels(1))
    ref.update(cam, frame_labels(1))
    np.testing.assert_array_equal(moved.concentrations, ref.concentrations)
    assert moved.render(cam).confidence is not None
