"""benchmarks/bench_node.py in its engine-stub mode, tiny: a real css_node over real DDS, every frame answered, and
the stage timings it reports nest as the node's calls do; and the engine stub's views have the promised form."""
from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ros_helpers as rh

pytest.importorskip("rclpy")

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "bench_node.py"
FRAMES = 8
PER_FRAME_OUTPUTS = ["semantic", "semantic_color", "expectation", "variance", "rendered_image", "surprise",
                     "view_uncertainty"]


@pytest.fixture(scope="module")
def result(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench_node") / "result.json"
    domain = rh.next_domain_id()
    cmd = [sys.executable, str(SCRIPT), "--engine-stub", "--gaussians", "1500", "--width", "64", "--height", "48",
           "--classes", "4", "--frames", str(FRAMES), "--warmup", "2", "--poses", "4", "--domain-id",
           str(domain), "--start-timeout", str(rh.NODE_START_S), "--drain-timeout", "20",
           "--json", str(out)]
    proc = subprocess.run(cmd, cwd=ROOT, env=rh.node_env(domain), capture_output=True, text=True,
                          timeout=rh.NODE_START_S + 120)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return json.loads(out.read_text()), proc.stdout


def test_every_frame_sent_comes_back_on_every_output(result):
    r, _ = result
    assert r["engine_stub"] and r["backend"] == "numba"
    assert r["outputs"] == PER_FRAME_OUTPUTS
    assert r["frames_sent"] == FRAMES and r["frames_received"] == FRAMES
    assert r["node_exit_code"] == 0


def test_latencies_and_rate_are_finite_and_ordered(result):
    r, _ = result
    lat = r["latency_ms"]
    assert 0.0 < r["first_output_latency_ms"]["p50"] <= lat["p50"]
    assert 0.0 < lat["p50"] <= lat["p90"] <= lat["p99"] <= lat["max"] < 60_000.0
    assert math.isfinite(r["frames_per_s"]) and r["frames_per_s"] > 0.0


def test_stage_times_nest_like_the_node_calls(result):
    r, text = result
    st = r["stages_ms"]
    assert st["frames"] == FRAMES   # the node timed every frame the player counted
    mean = {k: v["mean"] for k, v in st.items() if k != "frames"}
    assert mean["own"] > 0.0 and mean["decode"] > 0.0 and mean["take"] > 0.0 and mean["publish"] > 0.0
    assert mean["observe"] >= 0.0
    # per frame: decode inside the callbacks, observe and the outputs inside the worker's frame, the outputs' parts
    # inside the outputs; the node's own work is the inputs plus the worker's frame without the observe
    assert mean["callback"] >= mean["decode"]
    assert mean["worker_other"] >= 0.0
    parts = mean["images"] + mean["image_msgs"] + mean["view_msg"] + mean["publish"]
    assert mean["publish_frame"] >= parts
    assert mean["own"] == pytest.approx(mean["take"] + mean["callback"] + mean["worker"] - mean["observe"])
    assert f"frames sent / received (all 7 per-frame outputs): {FRAMES} / {FRAMES}" in text


def test_engine_stub_returns_the_requested_images_in_final_form():
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from node_harness import STUB_U_EXP, STUB_U_VAR, stub_observe

    from css_ros.engine.camera import Camera
    from css_ros.engine.gaussians import GaussianModel
    from css_ros.engine.semantic_map import SemanticMap

    rng = np.random.default_rng(0)
    model = GaussianModel.from_activated(rng.normal(size=(30, 3)) + [0, 0, 4], np.full((30, 3), 0.1),
                                         np.tile([1.0, 0, 0, 0], (30, 1)), np.full(30, 0.9), rng.random((30, 3)))
    smap = SemanticMap(model, 4)
    cam = Camera.look_at([0, 0, 0], [0, 0, 1], rh.K, rh.WIDTH, rh.HEIGHT, up=(0, -1, 0))
    labels = rng.integers(0, 4, (rh.HEIGHT, rh.WIDTH)).astype(np.uint8)
    labels[:5] = smap.ignore_label
    view = stub_observe(smap, cam, labels, outputs=("labels", "rgb", "variance"))
    assert view.labels.dtype == np.int32 and np.array_equal(view.labels, labels)
    assert view.rgb.shape == (rh.HEIGHT, rh.WIDTH, 3) and view.rgb.dtype == np.uint8
    assert view.variance.shape == (rh.HEIGHT, rh.WIDTH) and view.variance.dtype == np.float32
    assert view.expectation is None and view.confidence is None and view.depth is None
    assert (view.u_var, view.u_exp) == (STUB_U_VAR, STUB_U_EXP)
    assert smap.last_update.used == labels.size - 5 * rh.WIDTH and smap.last_update.ignored == 5 * rh.WIDTH
    assert smap.frames_observed == 1
