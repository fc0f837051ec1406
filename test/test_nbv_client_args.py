"""css_nbv_client checks every argument when parsed: a usage error naming the option (exit 2) at once, before rclpy
starts (css_ros/clients/nbv_client.py)."""
from __future__ import annotations

import time

import pytest

pytest.importorskip("rclpy")
from css_ros.clients.nbv_client import MAX_NUM_CANDIDATES, build_parser, main  # noqa: E402


@pytest.mark.parametrize("option, value, says", [
    ("--period", "0", "outside [0.05, 3600]"),
    ("--period", "nan", "outside [0.05, 3600]"),
    ("--period", "-1", "outside [0.05, 3600]"),
    ("--timeout", "inf", "outside (0, 3600]"),
    ("--timeout", "0", "outside (0, 3600]"),
    ("--num-candidates", "0", f"outside [1, {MAX_NUM_CANDIDATES}]"),
    ("--num-candidates", "100000", f"outside [1, {MAX_NUM_CANDIDATES}]"),
    ("--num-candidates", "2.5", "'2.5' is not an integer"),
    ("--yaw-range", "nan", "outside [0, 180]"),
    ("--position-std", "-0.1", "outside [0, 100]"),
    ("--vertical-std", "inf", "outside [0, 100]"),
    ("--seed", "-1", "outside [0, "),
    ("--node", "not a node", "is not a node name"),
    ("--node", "css_node", "is not a node name"),
])
def test_bad_arguments_are_usage_errors_naming_the_option(capsys, option, value, says):
    start = time.monotonic()
    assert main([option, value, "--once"]) == 2
    assert time.monotonic() - start < 5.0
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("css_nbv_client: error: argument") and option in err[-1] and says in err[-1], err


def test_good_arguments_parse_to_their_values():
    args = build_parser().parse_args(["--period", "0.05", "--timeout", "3600", "--num-candidates", str(MAX_NUM_CANDIDATES),
                                      "--node", "/robot1/css_node", "--seed", "7", "--yaw-range", "180"])
    assert (args.period, args.timeout, args.num_candidates, args.node, args.seed, args.yaw_range) == \
        (0.05, 3600.0, MAX_NUM_CANDIDATES, "/robot1/css_node", 7, 180.0)


def test_bad_ros_arguments_are_one_line_not_a_traceback(capsys):
    assert main(["--once", "--ros-args", "-r"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("css_nbv_client: error: cannot initialise ROS"), err
