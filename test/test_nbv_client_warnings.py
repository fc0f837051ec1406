"""css_nbv_client's per-request warnings are rate-limited: with --period 0.05 and no pose publisher it used to log
one ~300-character warning per request (20 a second); now the first at once, then at most one per reason every
WARN_PERIOD_S seconds, counting the ones it suppressed."""
from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

pytest.importorskip("rclpy")
import ros_helpers as rh  # noqa: E402
from css_ros.clients.nbv_client import WARN_PERIOD_S  # noqa: E402


def test_no_pose_warning_is_logged_once_per_period_not_per_request():
    script = Path(sys.executable).with_name("css_nbv_client")
    cmd = [str(script)] if script.exists() else [sys.executable, "-m", "css_ros.clients.nbv_client"]
    proc = subprocess.Popen([*cmd, "--period", "0.05"], env=rh.node_env(rh.next_domain_id()),
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    lines: list[str] = []
    first = threading.Event()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.append(line)
            if "no pose received" in line:
                first.set()
    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        assert first.wait(120), "".join(lines)
        time.sleep(3.0)   # about 60 more requests without a pose, well within WARN_PERIOD_S
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        reader.join(5)
    assert WARN_PERIOD_S >= 5.0
    warned = [line for line in lines if "no pose received" in line]
    assert len(warned) == 1, "".join(lines)
    assert "[pose] no pose received yet on /pose" in warned[0] and warned[0].rstrip().endswith("total 1"), warned
