"""benchmarks/changing_world.py on tiny demos: it runs, css_replay's report gives the same figures as its table
(--check-replay), and what it reports agrees with the bag and with the rules."""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from css_ros.demo.changes import PERSON_CLASS
from css_ros.engine.classes import ClassSet
from css_ros.evaluation.config import ReplayConfig
from css_ros.evaluation.source import FrameSource

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = ROOT / "benchmarks" / "changing_world.py"


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    out = tmp_path_factory.mktemp("changing_world")
    proc = subprocess.run([sys.executable, str(SCRIPT), "--out", str(out), "--gaussians", "3000", "--frames", "16",
                           "--width", "48", "--height", "36", "--people", "3", "--quiet", "--check-replay"],
                          capture_output=True, text=True, timeout=1200, cwd=ROOT)
    return proc, out


@pytest.mark.slow
def test_runs_and_css_replay_agrees(bench):
    proc, out = bench
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "css_replay cross-check (depth+transient+half-life 5): the same figures" in proc.stdout
    text = (out / "results.md").read_text()
    assert text.strip() in proc.stdout and "| variant | person share of the map |" in text
    res = json.loads((out / "results.json").read_text())
    assert list(res["results"]) == ["paper", "depth", "transient", "depth+transient", "half-life 5",
                                    "depth+transient+half-life 5", "depth+transient+half-life 10",
                                    "depth+transient+half-life 20", "person-free paper", "person-free depth"]
    assert len(res["targets"]) == 8 and all(t["met"] in (True, False, None) for t in res["targets"])


@pytest.mark.slow
def test_figures_agree_with_the_bag_and_the_rules(bench):
    _, out = bench
    res = json.loads((out / "results.json").read_text())["results"]
    bag = out / "people"
    classes = ClassSet.from_yaml(bag / "classes.yaml")
    cfg = ReplayConfig(bag=bag / "bag", model=bag / "model.ply", classes=bag / "classes.yaml", out=out / "x",
                       num_classes=classes.num_classes, quiet=True, output_bag=False)
    source = FrameSource(cfg)
    source.check()
    person = classes.names.index(PERSON_CLASS)
    labelled = sum(int(np.count_nonzero(f.labels == person)) for f in source.frames())
    assert labelled > 0
    # a transient class holds back every pixel labelled with it; depth alone holds back only what is in front
    for name in ("transient", "depth+transient", "depth+transient+half-life 5"):
        assert res[name]["transient_pixels"] == labelled and res[name]["person_share"] == 0.0, name
    assert 0 < res["depth"]["occluded_pixels"] <= labelled and res["depth"]["transient_pixels"] == 0
    assert res["depth"]["person_share"] == 0.0                 # no Gaussian ever got a person vote
    assert res["paper"]["transient_pixels"] == res["paper"]["occluded_pixels"] == 0
    assert res["person-free depth"]["occluded_pixels"] == 0      # the room's own depth is never in front of it
    assert res["paper"]["others_kept"] is None and res["half-life 5"]["others_kept_reference"] == "paper"
    assert res["depth+transient+half-life 10"]["others_kept_reference"] == "depth+transient"
    assert 0.0 < res["half-life 5"]["others_kept"] <= 1.0
