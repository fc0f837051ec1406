"""Files written atomically get the mode a plain open() gives (0o666 less the umask), not mkstemp's 0o600."""
from __future__ import annotations

import os
import stat
from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.atomic import atomic_file, current_umask, new_file_mode
from css_ros.export.files import atomic_binary
from css_ros.io.params_file import write_params_file


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


@pytest.fixture(params=[0o022, 0o077, 0o002])
def umask(request):
    old = os.umask(request.param)
    try:
        yield request.param
    finally:
        os.umask(old)


def test_current_umask_reads_without_changing(umask):
    assert current_umask() == umask
    assert current_umask() == umask  # unchanged by the first read
    assert new_file_mode() == 0o666 & ~umask


def test_atomic_writers_match_a_plain_open(tmp_path: Path, umask):
    plain = tmp_path / "plain.txt"
    with open(plain, "w") as fh:
        fh.write("x")
    expected = _mode(plain)
    assert expected == 0o666 & ~umask
    with atomic_file(tmp_path / "a.bin") as fh:
        fh.write(b"1")
    with atomic_binary(tmp_path / "b.bin") as fh:
        fh.write(b"2")
    write_params_file(tmp_path / "c.yaml", {"a": 1})
    for name in ("a.bin", "b.bin", "c.yaml"):
        assert _mode(tmp_path / name) == expected, name
    assert (tmp_path / "a.bin").read_bytes() == b"1"
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporary file left


def test_saved_map_and_sensor_model_are_world_readable(tmp_path: Path):
    from css_ros import GaussianModel, SemanticMap
    from css_ros.engine.sensor_model import SensorModel

    old = os.umask(0o022)
    try:
        n = 4
        m = GaussianModel(means=np.zeros((n, 3)) + [0, 0, 5], log_scales=np.full((n, 3), -2.0),
                          rotations=np.tile([1.0, 0, 0, 0], (n, 1)), opacity_logits=np.zeros(n),
                          sh=np.zeros((n, 1, 3), np.float32))
        SemanticMap(m, 3).save(tmp_path / "map.npz")
        SensorModel(("a", "b", "c"), np.array([0.0, 1.0, 2.0]), np.full((3, 2), 0.5)).save(tmp_path / "sm.yaml")
    finally:
        os.umask(old)
    assert _mode(tmp_path / "map.npz") == 0o644
    assert _mode(tmp_path / "sm.yaml") == 0o644
