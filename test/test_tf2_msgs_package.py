"""The tf2_msgs message package of msg_packages/: its definition is the robot's type on the wire (RIHS01 hash from
rosbags' own Jazzy store), the build script never shadows a system tf2_msgs, and (where it was built) the importable
tf2_msgs is that type."""
from __future__ import annotations

import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from rosbags.typesys import Stores, get_types_from_msg, get_typestore

REPO = Path(__file__).resolve().parents[1]
PKG = REPO / "msg_packages" / "tf2_msgs"
SCRIPT = REPO / "msg_packages" / "build_tf2_msgs.py"


def test_the_definition_hashes_to_the_jazzy_type():
    jazzy = get_typestore(Stores.ROS2_JAZZY)
    own = get_typestore(Stores.EMPTY)
    own.register({k: v for k, v in jazzy.fielddefs.items() if k.startswith(("std_msgs/", "builtin_interfaces/",
                                                                             "geometry_msgs/"))})
    own.register(get_types_from_msg((PKG / "msg" / "TFMessage.msg").read_text(), "tf2_msgs/msg/TFMessage"))
    assert own.hash_rihs01("tf2_msgs/msg/TFMessage") == jazzy.hash_rihs01("tf2_msgs/msg/TFMessage") == \
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_colcon_in_the_repository_root_never_builds_it():
    assert (REPO / "msg_packages" / "COLCON_IGNORE").is_file()


def test_a_system_tf2_msgs_is_never_shadowed(tmp_path):
    """A tf2_msgs importable from elsewhere (as /opt/ros/jazzy's is) makes the script build nothing."""
    fake = tmp_path / "ros" / "tf2_msgs"
    (fake / "msg").mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    env = dict(os.environ, PYTHONPATH=str(tmp_path / "ros"))
    res = subprocess.run([sys.executable, str(SCRIPT)], env=env, capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    assert "provided by this ROS install" in res.stdout and str(fake) in res.stdout


@pytest.mark.skipif(importlib.util.find_spec("tf2_msgs") is None,
                    reason="tf2_msgs not built here (run msg_packages/build_tf2_msgs.py, as README command 1 does)")
def test_the_importable_tf2_msgs_is_the_robots_type():
    import tf2_msgs

    share = Path(sys.prefix) / "share" / "tf2_msgs" / "msg" / "TFMessage.json"
    if not share.is_file():
        pytest.skip(f"tf2_msgs from {tf2_msgs.__path__}: not the copy built into this environment")
    desc = json.loads(share.read_text())
    hashes = {t["type_name"]: t["hash_string"] for t in desc["type_hashes"]}
    assert hashes["tf2_msgs/msg/TFMessage"] == get_typestore(Stores.ROS2_JAZZY).hash_rihs01("tf2_msgs/msg/TFMessage")
    res = subprocess.run([sys.executable, str(SCRIPT)], capture_output=True, text=True, timeout=300)
    assert res.returncode == 0 and "up to date" in res.stdout, res.stdout + res.stderr
