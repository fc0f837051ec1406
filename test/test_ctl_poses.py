"""css_ctl's candidate poses as the README and ``--help`` show them: the examples look ahead (optical axis level in
the map, image upright), and ``--yaw`` builds the same optical-frame quaternions from x y z yaw."""
from __future__ import annotations

import re
import shlex
from pathlib import Path

import numpy as np
import pytest

from css_ros.clients.ctl import EXAMPLES, level_poses, main
from css_ros.engine.camera import quaternion_xyzw_to_matrix

README = Path(__file__).resolve().parents[1] / "README.md"


def candidate_examples(text: str) -> list[list[str]]:
    """The argument lists of every ``css_ctl candidates`` example line in ``text`` (comments cut off)."""
    out = []
    for line in text.splitlines():
        m = re.match(r"\s*css_ctl candidates (.*)", line)
        if m:
            out.append(shlex.split(m.group(1).split("#")[0]))
    return out


def example_poses(args: list[str]) -> np.ndarray:
    """(M, 7) poses of one example's numbers (x y z yaw turned into quaternions when it says --yaw)."""
    numbers = np.array([float(a) for a in args if a != "--yaw"])
    if "--yaw" in args:
        return level_poses(numbers.reshape(-1, 4))
    return numbers.reshape(-1, 7)


@pytest.mark.parametrize("where", ["README", "--help"])
def test_every_candidates_example_looks_ahead(where):
    text = README.read_text() if where == "README" else EXAMPLES
    examples = [a for a in candidate_examples(text) if "--file" not in a]
    assert len(examples) >= 2 and any("--yaw" in a for a in examples) and any("--yaw" not in a for a in examples)
    for args in examples:
        for pose in example_poses(args):
            R = quaternion_xyzw_to_matrix(pose[3:])
            forward, down = R[:, 2], R[:, 1]
            assert abs(forward[2]) < 1e-9, f"{where} {args}: the optical axis {forward} is not level"
            np.testing.assert_allclose(down, [0.0, 0.0, -1.0], atol=1e-9, err_msg=f"{where} {args}: image not upright")


def test_the_quaternion_and_yaw_examples_are_the_same_view():
    examples = candidate_examples(README.read_text())
    quat = next(example_poses(a) for a in examples if "--yaw" not in a and "--file" not in a)
    yaw = next(example_poses(a) for a in examples if "--yaw" in a)
    np.testing.assert_allclose(yaw[0], quat[0], atol=1e-12)


@pytest.mark.parametrize("yaw", [0.0, 30.0, 90.0, 180.0, -135.0])
def test_yaw_turns_a_level_camera_about_the_map_z(yaw):
    t = np.radians(yaw)
    pose = level_poses(np.array([[1.0, -2.0, 1.5, yaw]]))[0]
    np.testing.assert_array_equal(pose[:3], [1.0, -2.0, 1.5])
    R = quaternion_xyzw_to_matrix(pose[3:])
    # optical frame: z forward, x right, y down; a level camera looking at yaw from +x towards +y
    np.testing.assert_allclose(R[:, 2], [np.cos(t), np.sin(t), 0.0], atol=1e-12)
    np.testing.assert_allclose(R[:, 0], [np.sin(t), -np.cos(t), 0.0], atol=1e-12)
    np.testing.assert_allclose(R[:, 1], [0.0, 0.0, -1.0], atol=1e-12)


def test_yaw_poses_come_in_fours(capsys):
    assert main(["candidates", "--yaw", "0", "0", "1.5"]) == 2   # a usage error, before ROS starts
    assert "give x y z yaw poses as groups of 4 numbers (got 3)" in capsys.readouterr().err
