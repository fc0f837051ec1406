"""css_node command line: --help prints the parameter table without starting ROS; unknown parameters are warned."""
from __future__ import annotations

import subprocess
import sys

import pytest

import ros_helpers as rh
from css_ros.ros.main import help_text, wants_help
from css_ros.ros.params import param_table


def test_help_text_lists_every_parameter_with_default():
    text = help_text()
    assert text.startswith("usage: css_node")
    for name, _, _, _ in param_table():
        assert f"  {name} = " in text


@pytest.mark.parametrize("argv, expected", [(["-h"], True), (["--help"], True), ([], False),
                                            (["--ros-args", "-p", "x:=1"], False),
                                            (["--ros-args", "-r", "-h:=x"], False)])
def test_wants_help(argv, expected):
    assert wants_help(argv) == expected


@pytest.mark.parametrize("flag", ["--help", "-h"])
def test_help_exits_0_without_starting_the_node(flag):
    res = subprocess.run([sys.executable, "-m", "css_ros.node", flag], env=rh.node_env(rh.next_domain_id()),
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "usage: css_node" in res.stdout and "  max_image_pixels = 16777216 [px]" in res.stdout
    assert "rasteriser warm-up" not in res.stdout + res.stderr  # the node never started


def test_undeclared_parameter_is_warned_by_name(tmp_path):
    model = rh.write_wall_model(tmp_path / "wall.ply")
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=3, num_clases=4, warmup=False,
                               checkpoint_path=""), rh.next_domain_id(), tmp_path / "node.log")
    try:
        assert node.wait_log("checkpoint disabled", 60.0), node.log()
        assert "unknown parameter 'num_clases' ignored" in node.log()
        assert "unknown parameter 'num_classes'" not in node.log()
    finally:
        assert node.stop() == 0
