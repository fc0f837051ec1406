"""css_ctl against a real css_node over DDS: services and requests answered as tables."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402

pytestmark = pytest.mark.slow


def css_ctl(domain: int, *args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "css_ros.clients.ctl", "--timeout", "15", *args],
                          capture_output=True, text=True, env=rh.node_env(domain), timeout=timeout)


def test_ctl_save_query_candidates_reset(tmp_path):
    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    npz = tmp_path / "map.npz"
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES,
                               checkpoint_path=str(npz), checkpoint_period=0.0), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        # before any frame (no camera_info): every row NaN; css_ctl prints no NaN table, but why, from the node's own
        # counters (it used to guess "more than its max_candidates, or no camera_info yet"), and what to do
        r = css_ctl(domain, "candidates", "0", "0", "1.5", "-0.5", "0.5", "-0.5", "0.5")
        assert r.returncode == 1 and r.stdout == "", r.stdout + r.stderr
        assert r.stderr.startswith("css_ctl: error: the node scored none of the 1 views: the node has seen no frame "
                                   "yet") and "play data into it first" in r.stderr, r.stderr
        assert r.stderr.rstrip().endswith("(css_node's status: no camera_info received yet)"), r.stderr
        assert client.send_frame_until_processed(10**9, output="view_uncertainty"), node.log()[-3000:]

        r = css_ctl(domain, "save")
        assert r.returncode == 0, r.stderr
        lines = r.stdout.strip().splitlines()
        assert lines[0].split() == ["service", "success", "message"] and "/css_node/save_map" in lines[2]
        assert "True" in lines[2] and npz.is_file()
        a = np.load(npz, allow_pickle=False)["concentrations"]
        seen = int(np.argmax(a.sum(axis=1)))   # the most observed Gaussian
        label = int(np.argmax(a[seen]))

        x, y, z = (f"{v:.6f}" for v in model.means[seen])
        r = css_ctl(domain, "query", x, y, z, "100", "100", "100")
        assert r.returncode == 0, r.stderr
        rows = r.stdout.strip().splitlines()
        assert rows[0].split()[:6] == ["x", "y", "z", "class", "E", "Var"] and len(rows) == 4
        assert rows[2].split()[3] == f"class_{label}" and rows[3].split()[3] == "unknown"

        r = css_ctl(domain, "candidates", "0", "0", "0", "0", "0", "0", "1", "0", "0", "-50", "0", "0", "0", "1")
        assert r.returncode == 0, r.stderr
        rows = r.stdout.strip().splitlines()
        assert rows[0].split() == ["view", "x", "y", "z", "U_var", "U_exp", "info_gain"] and len(rows) == 4
        u_facing, u_away = float(rows[2].split()[4]), float(rows[3].split()[4])
        assert u_facing < u_away   # the view of the observed wall is the less uncertain one
        gains = [float(row.split()[6]) for row in rows[2:]]
        assert all(np.isfinite(g) and g >= 0 for g in gains)
        best = 2 + int(np.argmax(gains))
        assert rows[best].endswith("<- best next view (info gain)")
        assert "<- most uncertain" in rows[3] and sum("<- best next view" in row for row in rows) == 1

        # --yaw 0 builds the README's level view along +x: the node scores the same pose, to the digit
        level = css_ctl(domain, "candidates", "0.1", "0.2", "0.5", "-0.5", "0.5", "-0.5", "0.5")
        by_yaw = css_ctl(domain, "candidates", "--yaw", "0.1", "0.2", "0.5", "0")
        assert level.returncode == 0 and by_yaw.returncode == 0, level.stderr + by_yaw.stderr
        assert by_yaw.stdout == level.stdout and np.isfinite(float(level.stdout.splitlines()[2].split()[4]))

        many = tmp_path / "poses.txt"   # one more than the node's max_candidates (256): every row NaN
        many.write_text("\n".join("0 0 0 0 0 0 1" for _ in range(257)) + "\n")
        r = css_ctl(domain, "candidates", "--file", str(many))
        assert r.returncode == 1 and r.stdout == "" and "scored none of the 257 views: more views than the node's " \
            "max_candidates parameter: send fewer per request (css_node's status: too many candidates)" in r.stderr, \
            r.stderr

        r = css_ctl(domain, "reset")
        assert r.returncode == 0 and "True" in r.stdout
        r = css_ctl(domain, "--node", "/nobody", "save", timeout=60)
        assert r.returncode == 1 and "no /nobody/save_map service" in r.stderr
    finally:
        client.close()
        assert node.stop() == 0


def test_candidates_table_marks_finite_maxima_only():
    from css_ros.clients.ctl import candidates_table
    from css_ros.io.clouds import SCORED_VIEW_DTYPE

    rows = np.zeros(4, SCORED_VIEW_DTYPE)
    rows["u_var"] = [np.nan, 0.2, 0.1, 0.05]
    rows["info_gain"] = [np.nan, 1.0, 3.0, np.nan]
    lines = candidates_table(rows).splitlines()
    assert lines[0].split()[-1] == "info_gain" and lines[2].split()[-1] == "nan"
    assert lines[3].endswith("<- most uncertain") and lines[4].endswith("<- best next view (info gain)")
    rows["info_gain"] = np.nan   # a node without the field: no best view by info gain
    lines = candidates_table(rows).splitlines()
    assert lines[3].endswith("<- most uncertain") and not any("info gain)" in ln for ln in lines)
    rows["info_gain"][1] = 2.0
    assert candidates_table(rows).splitlines()[3].endswith("<- most uncertain  <- best next view (info gain)")


def test_nan_rows_are_explained_by_the_nodes_statuses():
    from css_ros.clients.ctl import NAN_CAUSES, NAN_HINTS, explain_nan

    assert explain_nan(["no camera_info received yet"]) == (
        "the node has seen no frame yet, so it has no camera to render candidates with: play data into it first "
        "(css_demo plays the demo bag; a robot or a bag publishes camera_info, pose and segmentation), then ask "
        "again (css_node's status: no camera_info received yet)")
    two = explain_nan(["request queue full", "time budget exceeded"]).split("; ")
    assert two == [f"{NAN_HINTS[s]} (css_node's status: {s})" for s in ("request queue full", "time budget exceeded")]
    assert explain_nan(["a status of a newer node"]) == "css_node's status: a status of a newer node"
    assert explain_nan([]) == NAN_CAUSES and "seen no frame yet" in NAN_CAUSES
    # every status css_node answers NaN rows with (ros/gate.py, ros/worker.py, ros/node.py) has a hint
    import re
    from pathlib import Path
    ros = Path(__file__).resolve().parents[1] / "css_ros" / "ros"
    said = set()
    for f in ("gate.py", "worker.py", "node.py"):
        text = (ros / f).read_text()
        said |= set(re.findall(r'NanAnswer\([^)]*"([^"]+)"\)', text)) | set(re.findall(r'finish_request\([^)]*"([^"]+)"\)', text))
    assert said and said <= set(NAN_HINTS), said - set(NAN_HINTS)


def test_timeout_must_be_a_finite_number_of_seconds():
    for bad in ("nan", "inf", "1e308", "0", "-1", "1e-320"):
        r = css_ctl(0, "--timeout", bad, "save", timeout=30)
        assert r.returncode == 2 and f"argument --timeout: {bad} is outside [0.01, 86400]" in r.stderr, (bad, r.stderr)
