"""benchmarks/active_mapping.py --quick: it runs, writes results.json / results.md / the plots, and what it writes
has the promised structure and simple properties (values are fractions, the mean lies between min and max, every
strategy starts from the same map, the random strategy draws the same candidates for every error kind)."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "active_mapping.py"
STRATEGIES = ["random", "u_var", "u_exp", "coverage", "info_gain", "info_gain_task"]
SETTINGS = ["frame", "range", "range_sensor"]
METRICS = ["miou", "accuracy", "task_miou", "task_accuracy"]


def _sensor_model(path: Path) -> Path:
    """A small sensor model of the demo classes (votes worth less with depth), written without calibrating."""
    from css_ros.demo.scene import CLASS_NAMES
    from css_ros.engine.sensor_model import SensorModel

    edges = np.arange(0.0, 8.01, 1.0)
    w = np.clip(1.2 - 0.3 * (edges[:-1] + 0.5), 0.02, 1.0)
    SensorModel(CLASS_NAMES, edges, np.tile(w, (len(CLASS_NAMES), 1))).save(path)
    return path


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("active_mapping")
    out = tmp / "out"
    sm = _sensor_model(tmp / "sensor_model.yaml")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--quick", "--out", str(out), "--sensor-model", str(sm)],
                          cwd=ROOT, capture_output=True, text=True, timeout=900)  # ~2 min idle; a busy machine takes longer
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out, proc.stdout, json.loads((out / "results.json").read_text())


def test_help():
    proc = subprocess.run([sys.executable, str(SCRIPT), "--help"], cwd=ROOT, capture_output=True, text=True,
                          timeout=60)
    assert proc.returncode == 0
    for opt in ("--quick", "--seeds", "--steps", "--candidates", "--sensor-model", "--out"):
        assert opt in proc.stdout


def test_outputs_written(quick_run):
    out, stdout, res = quick_run
    for name in ("results.json", "results.md", "miou_frame.png", "miou_range.png"):
        assert (out / name).is_file() and (out / name).stat().st_size > 0, name
    assert "wall time" in stdout
    # the printed table: one row per strategy, both error kinds and the sensor-model runs as columns
    for st in STRATEGIES:
        assert f"| {st} |" in stdout
    header = next(line for line in stdout.splitlines() if line.startswith("| strategy | frame"))
    assert "range 6" in header and "range+SM 6" in header


def test_structure(quick_run):
    _, _, res = quick_run
    cfg = res["config"]
    seeds = cfg["seeds"]
    assert len(seeds) == 2 and cfg["views"] == [4, 6] and cfg["checkpoints"] == [2, 4, 6]
    assert cfg["candidates"] == 8 and cfg["task_poses"] == 10 and cfg["eval_poses"] == 8
    assert cfg["settings"] == SETTINGS and cfg["strategies"] == STRATEGIES
    assert res["wall_time_s"] > 0
    assert len(res["eval_poses"]) == cfg["eval_poses"] and len(res["task_poses"]) == 10
    assert set(res["results"]) == set(SETTINGS)
    for setting in SETTINGS:
        assert set(res["results"][setting]) == set(STRATEGIES)
        for st in STRATEGIES:
            r = res["results"][setting][st]
            assert set(r) == set(METRICS)
            for metric in METRICS:
                assert set(r[metric]) == {"2", "4", "6"}
                for s in r[metric].values():
                    assert set(s) == {"mean", "std", "min", "max", "per_seed"}
                    v = np.array(s["per_seed"])
                    assert v.shape == (len(seeds),)
                    assert np.all((v >= 0) & (v <= 1)), (setting, st, metric, v)
                    assert s["min"] <= s["mean"] <= s["max"]
                    assert math.isclose(s["mean"], float(v.mean()), rel_tol=1e-9, abs_tol=1e-12)
                    assert math.isclose(s["std"], float(v.std()), rel_tol=1e-9, abs_tol=1e-12)
            for fact in ("input_accuracy", "median_depth_m"):
                v = np.array(res["chosen_views"][setting][st][fact]["per_seed"])
                assert v.shape == (len(seeds),) and np.all(np.isfinite(v)) and np.all(v >= 0)
            assert np.all(np.array(res["chosen_views"][setting][st]["input_accuracy"]["per_seed"]) <= 1)
            chosen = res["choices"][setting][st]
            assert set(chosen) == {str(s) for s in seeds}
            for idx in chosen.values():
                assert len(idx) == 4 and all(0 <= i < cfg["candidates"] for i in idx)


def test_same_start_for_every_strategy(quick_run):
    """Before any choice every strategy has fused the same 2 start views with the same noise: identical scores."""
    _, _, res = quick_run
    for setting in SETTINGS:
        first = res["results"][setting]["random"]
        for st in STRATEGIES[1:]:
            for metric in METRICS:
                assert res["results"][setting][st][metric]["2"]["per_seed"] == first[metric]["2"]["per_seed"]


def test_random_draws_shared_and_maps_learn(quick_run):
    _, _, res = quick_run
    ch = res["choices"]
    assert ch["frame"]["random"] == ch["range"]["random"] == ch["range_sensor"]["random"]
    # the same candidates, hence the same views, for the random strategy: same depths under both error kinds
    depth = res["chosen_views"]
    assert depth["frame"]["random"]["median_depth_m"]["per_seed"] == pytest.approx(
        depth["range"]["random"]["median_depth_m"]["per_seed"], rel=1e-3)
    for setting in SETTINGS:
        for st in STRATEGIES:
            r = res["results"][setting][st]["miou"]
            # four more views than the start: the mean map is better on the held-out poses
            assert r["6"]["mean"] > r["2"]["mean"], (setting, st)
