"""css_nbv_client --once without a pose: exit 1 with a warning that says which topic it waited on and what to start."""
from __future__ import annotations

import subprocess
import sys

import ros_helpers as rh


def test_once_without_a_pose_names_the_topic_and_what_to_start():
    env = rh.node_env(rh.next_domain_id())
    proc = subprocess.run([sys.executable, "-m", "css_ros.clients.nbv_client", "--once", "--timeout", "1",
                           "--ros-args", "-r", "pose:=/robot/camera_pose"],
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    warn = [line for line in proc.stderr.splitlines() if "no pose received" in line]
    assert len(warn) == 1, proc.stderr
    line = warn[0]
    assert "within 1 s on /robot/camera_pose (geometry_msgs/msg/PoseStamped)" in line
    assert "css_demo" in line and "-r pose:=" in line and "--pose-type" in line
