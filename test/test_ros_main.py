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


def test_help_text_has_an_example_and_every_topic_in_and_out():
    from css_ros.io.topics import INPUT_TOPICS, INPUT_TYPES, OUTPUT_TOPICS

    text = help_text()
    examples = text[text.index("examples:"):text.index("topics in")]
    assert "css_node --ros-args --params-file config/css_node.yaml" in examples
    assert "-r segmentation:=" in examples  # how to point an input at the robot's topic
    topics_in = text[text.index("topics in"):text.index("topics out")]
    topics_out = text[text.index("topics out"):text.index("parameters (name")]
    for kind, name in INPUT_TOPICS.items():
        assert f"  {name} [{INPUT_TYPES[kind]}]" in topics_in, name
    for name, typ in OUTPUT_TOPICS.items():
        assert f"  ~/{name} [{typ}]" in topics_out, name
    for service in ("~/save_map", "~/reset_map", "~/load_map"):
        assert service in topics_out
    assert text.index("topics out") < text.index("parameters (name") < text.index("  model_path = ")


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


def test_failed_kernel_warm_up_stops_the_node_with_its_cause():
    """A warm-up that fails (here: backend cuda on a machine without GPU or simulator) is a one-line
    CssError naming the backend, which css_node's main turns into 'cannot start' (exit 2), instead of a
    node that would drop every frame."""
    from css_ros import SemanticMap
    from css_ros.errors import CssError
    from css_ros.ros.params import NodeParams
    from css_ros.ros.startup import warm_up
    from scenes import random_scene

    smap = SemanticMap(random_scene(0, n=10), 2)
    logged: list[str] = []
    warm_up(smap, NodeParams(backend="numba"), logged.append)
    assert len(logged) == 1 and logged[0].startswith("rasteriser warm-up (numba) took")
    try:
        warm_up(smap, NodeParams(backend="cuda"), logged.append)
    except CssError as exc:
        assert "cuda" in str(exc) and "\n" not in str(exc) and len(logged) == 1
    else:
        pytest.skip("this machine runs backend cuda (a GPU or the simulator)")
