"""Build css_ros with colcon (ament_python) in a temporary workspace and run the installed css_node executable."""
from __future__ import annotations

import importlib.util
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

import ros_helpers as rh

pytestmark = pytest.mark.slow

COLCON = shutil.which("colcon", path=os.pathsep.join([str(Path(sys.executable).parent), os.environ.get("PATH", "")]))
SOURCES = ("css_ros", "config", "launch", "resource", "package.xml", "setup.py", "setup.cfg")


@pytest.mark.skipif(COLCON is None or importlib.util.find_spec("colcon_ros") is None
                    or importlib.util.find_spec("ament_package") is None,
                    reason="colcon with colcon-ros and ament_package not installed "
                           "(pip install colcon-core colcon-ros colcon-python-setup-py ros-jazzy-ament-package)")
def test_colcon_build_installs_css_node(tmp_path):
    src = tmp_path / "ws" / "src" / "css_ros"
    src.mkdir(parents=True)
    for name in SOURCES:
        path = rh.REPO / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__", "*.pyc"))
        else:
            shutil.copy2(path, src / name)
    ws = tmp_path / "ws"
    t0 = time.monotonic()
    env = dict(os.environ)
    env.pop("PYTHONPATH", None)
    build = subprocess.run([COLCON, "build", "--base-paths", "src", "--build-base", "build",
                            "--install-base", "install", "--event-handlers", "console_direct-"],
                           cwd=ws, env=env, capture_output=True, text=True, timeout=300)
    assert build.returncode == 0, build.stdout[-3000:] + build.stderr[-3000:]
    print(f"\ncolcon build: {time.monotonic() - t0:.1f} s")
    prefix = ws / "install" / "css_ros"
    exe = prefix / "lib" / "css_ros" / "css_node"
    assert exe.is_file() and os.access(exe, os.X_OK)  # where `ros2 run css_ros css_node` looks
    for rel in ("lib/css_ros/css_demo", "lib/css_ros/css_nbv_client", "lib/css_ros/css_replay",
                "share/css_ros/package.xml", "share/css_ros/config/css_node.yaml",
                "share/css_ros/launch/css.launch.py", "share/ament_index/resource_index/packages/css_ros"):
        assert (prefix / rel).exists(), rel
    site = next(prefix.glob("lib/python3*/site-packages"))

    # The installed executable runs from the install space (not the source tree), like after
    # `source install/setup.bash`: a missing model is a clean fatal error with the path.
    run_env = dict(env, PYTHONPATH=str(site), AMENT_PREFIX_PATH=str(prefix), ROS_DOMAIN_ID=str(rh.next_domain_id()))
    missing = tmp_path / "no_such_model.ply"
    res = subprocess.run([str(exe), "--ros-args", "-p", f"model_path:={missing}"], env=run_env,
                         capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    assert str(missing) in res.stderr + res.stdout and "Traceback" not in res.stderr

    # With the installed parameter file it starts and stops cleanly.
    model = rh.write_wall_model(tmp_path / "wall.ply")
    log = tmp_path / "installed_node.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen([str(exe), "--ros-args", "--params-file",
                                 str(prefix / "share/css_ros/config/css_node.yaml"), "-p", f"model_path:={model}",
                                 "-p", "class_file:=''", "-p", "num_classes:=3", "-p", "checkpoint_path:=''",
                                 "-p", "warmup:=false"],
                                env=run_env, stdout=fh, stderr=subprocess.STDOUT)
        end = time.monotonic() + 120
        while time.monotonic() < end and "outputs:" not in log.read_text() and proc.poll() is None:
            time.sleep(0.2)
        text = log.read_text()
        proc.send_signal(signal.SIGINT)
        assert proc.wait(30) == 0, text
    assert "outputs:" in text
    # (In a venv that also has `pip install -e .`, setuptools' editable finder takes precedence over
    # PYTHONPATH, so the executable may import the source tree; on a ROS machine it imports the install space.)
