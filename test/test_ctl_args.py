"""css_ctl refuses, before ROS starts, what it cannot send: bad --timeout / --node (argparse, exit 2), points and poses
the node could not use (exit 2, naming the point or pose and why), and a --file that is not a regular file (exit 1).
No css_node is needed: each refusal comes before any DDS participant."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
import ros_helpers as rh  # noqa: E402


def css_ctl(*args: str) -> subprocess.CompletedProcess:
    """The installed console script (``python -m`` where the venv has none), on a domain of its own."""
    script = Path(sys.executable).with_name("css_ctl")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "css_ros.clients.ctl"]
    return subprocess.run([*cmd, *args], capture_output=True, text=True, env=rh.node_env(rh.next_domain_id()),
                          timeout=120)


def refused(r: subprocess.CompletedProcess, code: int, *says: str) -> None:
    """One ``css_ctl: error:`` line (after argparse's usage) saying each of ``says``; no warning, no traceback."""
    err = r.stderr.strip().splitlines()
    assert r.returncode == code, r.stderr
    assert err and err[-1].startswith("css_ctl: error: ") and all(s in err[-1] for s in says), r.stderr
    assert "Warning" not in r.stderr and "Traceback" not in r.stderr and "unexpected" not in r.stderr, r.stderr
    assert r.stdout == "", r.stdout


@pytest.mark.parametrize("value", ["nan", "inf", "-1", "0", "86401", "1e-320", "0.001"])
def test_timeout_is_checked_when_parsed(value):
    # used to be exit 1 from the run ("--timeout must be ..."); 1e-320 was accepted
    refused(css_ctl("--timeout", value, "save"), 2, "argument --timeout:", f"{value} is outside [0.01, 86400]")


@pytest.mark.parametrize("value, says", [
    ("bad name!", "is relative (no leading '/')"),
    ("/css-node", "'css-node' is not a ROS name"),
    ("/1x", "'1x' is not a ROS name"),
    ("/" + "a" * 300, "which ROS refuses: longer than the 247 characters ROS allows"),
    ("", "an empty name"),
    ("relative", "'relative' is relative (no leading '/')"),
    ("~", "starts with '~', which names this tool's own private namespace, not css_node's"),
])
def test_node_is_checked_when_parsed(value, says):
    # used to start DDS and die on an rclpy InvalidServiceNameException (exit 1), or call ~/save_map silently
    refused(css_ctl("--timeout", "0.5", "--node", value, "save"), 2, "argument --node:", says)


@pytest.mark.parametrize("pose, says", [
    ("0 0 1.5 0 0 0 0", "pose 0: quaternion [0.0, 0.0, 0.0, 0.0] has norm 0 outside [0.9, 1.1]"),
    ("0 0 1.5 0 0 0 5", "pose 0: quaternion [0.0, 0.0, 0.0, 5.0] has norm 5 outside [0.9, 1.1]"),
    ("nan 0 0 0 0 0 1", "pose 0: non-finite position [nan, 0.0, 0.0]"),
    ("0 0 1.5 -0.5 0.5 -0.5 0.5  1e300 0 1.5 -0.5 0.5 -0.5 0.5", "pose 1: position [1e+300, 0.0, 1.5] beyond 1e+06 m"),
    ("0 0 1.5 -0.5 0.5 nan 0.5", "pose 0: non-finite quaternion"),
])
def test_candidates_refuses_poses_the_node_would_score_nan(pose, says):
    # used to be sent: a NaN row misdiagnosed as "more than its max_candidates, or no camera_info yet" (exit 1), or,
    # beside a good pose, a silent NaN row (exit 0)
    refused(css_ctl("--timeout", "0.5", "candidates", *pose.split()), 2, says, "css_node would score it NaN")


def test_candidates_refuses_invalid_poses_from_a_file(tmp_path):
    poses = tmp_path / "poses.txt"
    poses.write_text("# x y z qx qy qz qw\n0 0 1.5 -0.5 0.5 -0.5 0.5\n0 0 1.5 0 0 0 2\n")
    refused(css_ctl("--timeout", "0.5", "candidates", "--file", str(poses)), 2,
            "pose 1: quaternion [0.0, 0.0, 0.0, 2.0] has norm 2 outside [0.9, 1.1]")


@pytest.mark.parametrize("yaw", ["inf", "nan", "-inf"])
def test_yaw_must_be_finite(yaw):
    # used to print two RuntimeWarnings (cos, sin), then "rotation matrix holds non-finite values"
    refused(css_ctl("--timeout", "0.5", "candidates", "--yaw", "0", "0", "1.5", "0", "0", "0", "1", yaw),
            2, f"pose 1: yaw must be finite, got {yaw}")


@pytest.mark.parametrize("point, says", [
    ("1e300 0 0", "point 0 (1e+300 0 0)"),
    ("0 0 0  1e39 0 0", "point 1 (1e+39 0 0)"),
    ("0 nan 0", "point 0 (0 nan 0)"),
])
def test_query_refuses_points_that_are_not_finite_float32(point, says):
    # 1e300 / 1e39 used to be cast to inf with "RuntimeWarning: overflow encountered in cast"; NaN was sent as is
    refused(css_ctl("--timeout", "0.5", "query", *point.split()), 2, says,
            "coordinates must be finite and within +-3.40282e+38 m (sent as float32)")


def test_file_that_is_not_a_regular_file_is_not_called_missing(tmp_path):
    refused(css_ctl("--timeout", "0.5", "query", "--file", "/dev/null"), 1,
            "points file is not a regular file: /dev/null")
    refused(css_ctl("--timeout", "0.5", "candidates", "--file", str(tmp_path)), 1,
            f"poses file is not a regular file: {tmp_path}")
    refused(css_ctl("--timeout", "0.5", "query", "--file", str(tmp_path / "none.txt")), 1,
            f"points file not found: {tmp_path / 'none.txt'}")


def test_empty_file_is_one_line_without_a_numpy_warning(tmp_path):
    empty = tmp_path / "points.txt"
    empty.write_text("# nothing\n")
    refused(css_ctl("--timeout", "0.5", "query", "--file", str(empty)), 2, f"{empty}: expected 3 numbers per line")


def test_points_on_the_command_line_and_in_a_file_are_refused_not_one_ignored(tmp_path):
    points = tmp_path / "points.txt"
    points.write_text("0 0 1\n")
    refused(css_ctl("--timeout", "0.5", "query", "1", "2", "3", "--file", str(points)), 2,
            "on the command line or with --file, not both")


def test_a_points_file_larger_than_the_bound_is_refused_before_it_is_read(tmp_path):
    from css_ros.clients.ctl import MAX_ROWS_FILE_BYTES

    big = tmp_path / "points.txt"
    with open(big, "wb") as fh:        # sparse: the declared size, no data written
        fh.truncate(MAX_ROWS_FILE_BYTES + 1)
    refused(css_ctl("--timeout", "0.5", "query", "--file", str(big)), 1, "more than 64 MiB")
