"""css_nbv_client checks every argument when parsed: a usage error naming the option (exit 2) at once, before rclpy
starts (css_ros/clients/nbv_client.py)."""
from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
from css_ros.clients.nbv_client import MAX_NUM_CANDIDATES, build_parser, main  # noqa: E402


@pytest.mark.parametrize("option, value, says", [
    ("--period", "0", "outside [0.05, 3600]"),
    ("--period", "nan", "outside [0.05, 3600]"),
    ("--period", "-1", "outside [0.05, 3600]"),
    ("--timeout", "inf", "outside [0.01, 3600]"),
    ("--timeout", "0", "outside [0.01, 3600]"),
    ("--timeout", "5e-324", "outside [0.01, 3600]"),
    ("--num-candidates", "0", f"outside [1, {MAX_NUM_CANDIDATES}]"),
    ("--num-candidates", "100000", f"outside [1, {MAX_NUM_CANDIDATES}]"),
    ("--num-candidates", "2.5", "'2.5' is not an integer"),
    ("--yaw-range", "nan", "outside [0, 180]"),
    ("--position-std", "-0.1", "outside [0, 100]"),
    ("--vertical-std", "inf", "outside [0, 100]"),
    ("--seed", "-1", "outside [0, "),
    ("--node", "/not a node", "is not a node name"),
    ("--node", "css_node", "is relative (no leading '/')"),
    ("--node", "", "an empty name"),
    ("--node", "~", "starts with '~', which names this tool's own private namespace"),
    ("--node", "/1x", "'1x' is not a ROS name"),
    # passed the node-name pattern, then rclpy refused the 327-character topic with a traceback (exit 1)
    ("--node", "/css_node/" + "a" * 300, "/candidate_scores (327 characters), which ROS refuses: longer than the 247 "
     "characters ROS allows"),
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


def test_too_long_node_name_is_a_usage_error_of_the_console_script_not_a_traceback():
    """The installed console script: exit 2 naming --node, no rclpy traceback (it used to exit 1 with one)."""
    script = Path(sys.executable).with_name("css_nbv_client")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "css_ros.clients.nbv_client"]
    r = subprocess.run([*cmd, "--node", "/css_node/" + "a" * 300, "--once", "--timeout", "0.5"],
                       capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "Traceback" not in r.stderr and "InvalidTopicName" not in r.stderr, r.stderr
    last = r.stderr.strip().splitlines()[-1]
    assert last.startswith("css_nbv_client: error: argument --node:") and "longer than the 247 characters" in last
