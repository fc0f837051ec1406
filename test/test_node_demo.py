"""css_demo (bag -> DDS -> css_node) end to end on a tiny generated demo."""
from __future__ import annotations

import re
import subprocess
import sys

import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402

pytestmark = pytest.mark.slow


def test_css_demo_start_node_prints_every_frame(tmp_path):
    demo = tmp_path / "demo"
    made = subprocess.run([sys.executable, "-m", "css_ros.demo.make_demo", "--out", str(demo), "--num-gaussians", "3000",
                           "--frames", "5", "--width", "48", "--height", "36", "--quiet"],
                          env=rh.node_env(0), capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    res = subprocess.run([sys.executable, "-m", "css_ros.demo.player", str(demo / "bag"), "--start-node",
                          "--rate", "8", "--node-param", "warmup:=false"],
                         env=rh.node_env(rh.next_domain_id()), capture_output=True, text=True, timeout=300)
    out = res.stdout + res.stderr
    assert res.returncode == 0, out
    lines = [ln for ln in res.stdout.splitlines() if ln.startswith("frame ")]
    assert len(lines) == 5, out
    for ln in lines:
        m = re.search(r"U_var (\S+)\s+U_exp (\S+)\s+acc\s+(\S+) %", ln)
        assert m, ln
        u_var, u_exp, acc = (float(g) for g in m.groups())
        assert 0 < u_var <= 0.25 and 0 <= u_exp <= 1 and 0 <= acc <= 100
    assert "css_node answered 5" in res.stdout
