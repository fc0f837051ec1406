"""css_calibrate and css_replay --sensor-model end to end on tiny range-error bags, and the fit's pieces."""
from __future__ import annotations

import json
import stat

import numpy as np
import pytest
import yaml
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from css_ros.calibration.cli import figure_paths, main as calibrate_main
from css_ros.calibration.learn import LabelDepthCounts, fit_sensor_model, symmetric_votes
from css_ros.demo.make_demo import make_demo
from css_ros.engine.atomic import current_umask
from css_ros.engine.sensor_model import SensorModel
from css_ros.evaluation.cli import main as replay_main


@pytest.fixture(scope="module")
def bags(tmp_path_factory):
    root = tmp_path_factory.mktemp("calib")
    make_demo(root / "studio", num_gaussians=4000, frames=24, width=64, height=48, seed=1, progress=False,
              errors="range", scene="studio")
    make_demo(root / "room", num_gaussians=4000, frames=10, width=64, height=48, seed=0, progress=False,
              errors="range", scene="room")
    make_demo(root / "short", num_gaussians=3000, frames=3, width=32, height=24, seed=2, progress=False,
              errors="range", scene="studio")
    return root


def test_label_depth_counts_match_a_loop():
    rng = np.random.default_rng(0)
    edges = np.array([0.0, 1.0, 2.5, 4.0])
    counts = LabelDepthCounts(4, edges)
    lab = rng.integers(0, 6, (9, 11))
    gt = rng.integers(0, 5, (9, 11))
    depth = rng.uniform(0, 6, (9, 11))
    depth[0, :4] = np.nan
    counts.add(lab, gt, depth, heldout=False)
    expected = np.zeros((4, 3, 4), dtype=np.int64)
    no_depth = 0
    for y, c, d in zip(lab.ravel(), gt.ravel(), depth.ravel()):
        if y >= 4 or c >= 4:
            continue
        if np.isnan(d):
            no_depth += 1
            continue
        b = min(int(np.searchsorted(edges, d, side="right")) - 1, 2)
        expected[y, b, c] += 1
    np.testing.assert_array_equal(counts.fit, expected)
    assert counts.no_depth == no_depth and counts.heldout.sum() == 0


def test_weights_and_votes_are_the_documented_closed_forms():
    c, b = 3, 2
    counts = LabelDepthCounts(c, np.array([0.0, 1.0, 2.0]))
    # 9000 right of 10000 near, 6000 of 10000 far, spread over the labels
    for y in range(c):
        counts.fit[y, 0, y] = 3000
        counts.fit[y, 0, (y + 1) % c] = 333
        counts.fit[y, 1, y] = 2000
        counts.fit[y, 1, (y + 1) % c] = 1333
    p = np.array([9000 / 9999, 6000 / 9999])
    sensor = fit_sensor_model(counts, ["a", "b", "c"], pseudo_count=0.0, weight_floor=0.02)
    np.testing.assert_allclose(sensor.weight, np.broadcast_to(2 * p - 1, (c, b)), rtol=1e-12)
    rows = symmetric_votes(np.broadcast_to(p, (c, b)))
    np.testing.assert_allclose(sensor.confusion, rows)
    np.testing.assert_allclose(rows.sum(axis=2), 1.0)
    np.testing.assert_allclose(rows[0, 1], [p[1], (1 - p[1]) / 2, (1 - p[1]) / 2])
    floor = fit_sensor_model(counts, ["a", "b", "c"], votes="onehot", pseudo_count=0.0, weight_floor=0.5)
    assert floor.confusion is None and np.all(floor.weight[:, 1] == 0.5)


def test_calibrate_writes_a_valid_model_and_figures(bags, tmp_path, capsys):
    out = tmp_path / "sm.yaml"
    assert calibrate_main([str(bags / "studio" / "bag"), "--out", str(out), "--quiet", "--bin-width", "1",
                           "--max-depth", "6"]) == 0
    printed = capsys.readouterr().out
    assert "held out" in printed
    last = printed.strip().splitlines()[-1]   # the last line names the YAML and the three figures beside it
    assert last.startswith(f"wrote {out} (sensor model")
    assert all(str(p) in last for p in figure_paths(out).values())
    names = [e["name"] for e in yaml.safe_load((bags / "studio" / "classes.yaml").read_text())["classes"]]
    sensor = SensorModel.load(out, names)
    assert sensor.num_bins == 6 and sensor.confidence is not None
    assert all(p.is_file() and p.stat().st_size > 10_000 for p in figure_paths(out).values())
    # written like every other output: 0o666 less the umask (0o644 with umask 022), not mkstemp's 0o600
    mode = 0o666 & ~current_umask()
    assert all(stat.S_IMODE(p.stat().st_mode) == mode for p in [out, *figure_paths(out).values()])
    info = sensor.info
    assert info["frames_heldout"] == 4 and info["frames_fit"] == 20   # every 5th of 24 frames held out
    labels = info["input_label_calibration"]
    # the paper's "every label is right" is off by the error rate; the fitted rates are closer
    assert labels["after"]["ece"] < labels["before"]["ece"]
    assert labels["before"]["ece"] == pytest.approx(1 - labels["before"]["accuracy"])
    # the range errors: labels near the camera are more often right than far ones
    near, far = sensor.weight[0, 0], sensor.weight[0, 3]
    assert near > far


def test_calibrate_refuses_too_few_pixels_and_writes_nothing(bags, tmp_path, capsys):
    out = tmp_path / "sm.yaml"
    assert calibrate_main([str(bags / "short" / "bag"), "--out", str(out), "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "too few labelled pixels" in err[0]
    assert list(tmp_path.iterdir()) == []
    assert calibrate_main([str(bags / "studio" / "bag"), "--out", str(out), "--quiet", "--gt-topic", "/nope"]) == 1
    assert list(tmp_path.iterdir()) == []
    assert calibrate_main([str(bags / "studio" / "bag"), "--out", str(tmp_path / "x.txt")]) == 2
    assert calibrate_main([str(bags / "studio" / "bag"), "--out", str(out), "--heldout-every", "1"]) == 2


def test_replay_with_the_sensor_model_reports_both_updates(bags, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)   # default output folders: one per update, neither overwrites the other
    assert calibrate_main([str(bags / "studio" / "bag"), "--quiet"]) == 0   # the README's command: the default --out
    sm = tmp_path / "out" / "calibration" / "sensor_model.yaml"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]   # nothing beside out/ in the working folder
    assert sorted(p.name for p in sm.parent.iterdir()) == sorted([sm.name, *(p.name for p in figure_paths(sm).values())])
    assert replay_main([str(bags / "room" / "bag"), "--quiet", "--sensor-model", str(sm)]) == 0
    assert replay_main([str(bags / "room" / "bag"), "--quiet", "--no-output-bag"]) == 0
    out, paper_out = tmp_path / "out" / "replay_room_sensor_model", tmp_path / "out" / "replay_room"
    m = json.loads((out / "metrics.json").read_text())
    alone = json.loads((paper_out / "metrics.json").read_text())
    assert alone["sensor_model"] is None and m["sensor_model"] is not None
    mode = 0o666 & ~current_umask()   # every output as a plain open() makes it (map.npz and PLYs included)
    files = [p for p in out.rglob("*") if p.is_file()]
    assert {"map.npz", "map_semantic.ply", "report.md", "reliability.png"} <= {p.name for p in files}
    assert {oct(stat.S_IMODE(p.stat().st_mode)) for p in files} == {oct(mode)}
    seg = m["segmentation"]
    for key in ("input", "css", "css_online", "paper_online", "paper_fused"):
        assert 0.0 <= seg[key]["pixel_accuracy"] <= 1.0, key
    # the paper's update fused beside the sensor model is the paper's update run alone, measure for measure
    paper = m["paper_update"]
    assert paper["segmentation"]["online"] == alone["segmentation"]["css_online"] == seg["paper_online"]
    assert paper["segmentation"]["fused"] == alone["segmentation"]["css"] == seg["paper_fused"]
    assert paper["pixel_sparsification"]["ause"] == alone["pixel_sparsification"]["ause"]
    for renders in ("online", "fused"):
        assert paper["calibration"][renders]["expectation"] == alone["calibration"][renders]["expectation"]
        assert paper["calibration"][renders]["confidence"] is None
    assert m["sensor_model"]["fingerprint"] == SensorModel.load(sm).fingerprint
    cal = m["calibration"]["online"]
    assert cal["confidence"]["ece"] is not None and cal["expectation"]["ece"] is not None
    assert "confidence" in m["pixel_sparsification"]["ause"]
    report = (out / "report.md").read_text()
    assert "Paper update vs the sensor model" in report and "reliability.png" in report
    table = report[report.index("| measure | input segmentation | paper update | sensor model |"):]
    table = table[:table.index("\n\n")].splitlines()
    rows = {r.split(" | ")[0].lstrip("| "): [c.strip(" |*") for c in r.split(" | ")[1:]] for r in table[2:]}
    ause_e = rows["pixel AUSE of E (fused renders)"]
    assert ause_e == ["—", f"{paper['pixel_sparsification']['ause']['expectation']:.4f}",
                      f"{m['pixel_sparsification']['ause']['expectation']:.4f}"]
    ece = rows["ECE of E, online renders"]
    assert ece[1:] == [f"{paper['calibration']['online']['expectation']['ece']:.4f}", f"{cal['expectation']['ece']:.4f}"]
    conf = rows["ECE of the calibrated `~/confidence`, online renders"]
    assert conf == ["—", "—", f"{cal['confidence']['ece']:.4f}"]
    acc = rows["fused pixel accuracy (every pose rendered with the final map), %"]
    assert acc == ["—", f"{100 * seg['paper_fused']['pixel_accuracy']:.1f}", f"{100 * seg['css']['pixel_accuracy']:.1f}"]
    assert (out / "reliability.png").is_file()
    with AnyReader([out / "bag"], default_typestore=get_typestore(Stores.ROS2_JAZZY)) as reader:
        conf = [c for c in reader.connections if c.topic == "/css_node/confidence"]
        assert conf and conf[0].msgcount == 10
        _, _, raw = next(reader.messages(connections=conf))
        msg = reader.deserialize(raw, conf[0].msgtype)
        values = np.frombuffer(bytes(msg.data), dtype=np.float32)
        assert msg.encoding == "32FC1" and np.all((values >= 0) & (values <= 1))
    # a sensor model for other classes is refused in one line
    bad = SensorModel.load(sm)
    SensorModel(tuple(f"x{i}" for i in range(bad.num_classes)), bad.depth_edges, bad.weight).save(tmp_path / "o.yaml")
    assert replay_main([str(bags / "room" / "bag"), "--out", str(tmp_path / "r2"), "--quiet",
                        "--sensor-model", str(tmp_path / "o.yaml")]) == 1
