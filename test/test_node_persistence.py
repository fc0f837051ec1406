"""css_node persistence over real DDS: save, kill -9, resume; corrupted or foreign checkpoints are refused."""
from __future__ import annotations

import random
import time
from pathlib import Path

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.io.messages import unpack_view_points  # noqa: E402
from css_ros.engine.semantic_map import SemanticMap  # noqa: E402

pytestmark = pytest.mark.slow
PRIOR = 1e-3


def _start(tmp: Path, model: Path, ckpt: Path, name: str, **params) -> tuple[rh.NodeProcess, rh.RosClient]:
    domain = rh.next_domain_id()
    node = rh.NodeProcess(dict(model_path=str(model), class_file="", num_classes=rh.NUM_CLASSES, prior=PRIOR,
                               checkpoint_path=str(ckpt), resume=True, log_period=0.5, **params),
                          domain, tmp / f"{name}.log")
    client = rh.RosClient(domain)
    assert client.wait_connected(60.0), node.log()
    time.sleep(0.5)
    return node, client


def _frames(client: rh.RosClient, stamps: list[int]) -> None:
    for s in stamps:
        assert client.send_frame_until_processed(s, output="view_uncertainty"), f"frame {s} not processed"


def _score(client: rh.RosClient, stamp: int) -> np.ndarray:
    client.send_candidates(stamp, np.array([[0.0, 0.0, 0.0], [0.2, 0.1, 0.3]]),
                           np.array([rh.IDENTITY, rh.yaw_quat(0.1)]))
    msg = client.wait_stamp("candidate_scores", stamp)
    assert msg is not None
    pts = unpack_view_points(msg)
    return np.stack([pts["u_var"], pts["u_exp"]])


def _saved(client: rh.RosClient, ckpt: Path, model: GaussianModel) -> np.ndarray:
    res = client.call(client.save_client)
    assert res.success, res.message
    return SemanticMap.load(ckpt, model).concentrations


def test_save_kill9_resume_restores_concentrations(tmp_path):
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    ckpt = tmp_path / "maps" / "map.npz"
    node, client = _start(tmp_path, model_path, ckpt, "first", checkpoint_period=0.0)
    try:
        _frames(client, [10**9 * k for k in range(1, 5)])
        saved = _saved(client, ckpt, model)
        assert saved.max() > 1.0  # observations fused
        scores = _score(client, 1)
        _frames(client, [10**9 * k for k in range(5, 8)])  # after the save: lost by the kill
        node.kill9()
    finally:
        client.close()
    node, client = _start(tmp_path, model_path, ckpt, "second", checkpoint_period=0.0)
    try:
        assert "resumed from" in node.log()
        # Without camera_info candidates cannot be rendered: answered in order with NaN scores.
        assert np.all(np.isnan(_score(client, 2)))
        client.send_camera_info()
        time.sleep(0.3)
        np.testing.assert_array_equal(_saved(client, ckpt, model), saved)
        np.testing.assert_allclose(_score(client, 3), scores, rtol=1e-6)
    finally:
        client.close()
        assert node.stop() == 0


@pytest.mark.parametrize("kind", ["corrupted", "foreign", "truncated"])
def test_bad_checkpoint_refused_node_starts_fresh(tmp_path, kind):
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    ckpt = tmp_path / "map.npz"
    if kind == "corrupted":
        ckpt.write_bytes(np.random.default_rng(0).bytes(5000))
    elif kind == "foreign":
        other = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "other.ply", seed=1))
        smap = SemanticMap(other, rh.NUM_CLASSES)
        smap.concentrations[:] = 5.0
        smap.save(ckpt)
    else:
        smap = SemanticMap(model, rh.NUM_CLASSES)
        smap.concentrations[:] = 5.0
        smap.save(ckpt)
        ckpt.write_bytes(ckpt.read_bytes()[:300])
    original = ckpt.read_bytes()
    node, client = _start(tmp_path, model_path, ckpt, kind, checkpoint_period=0.0)
    try:
        assert "checkpoint refused" in node.log()
        # Fresh map: every concentration is the prior, and the rejected file was kept aside, unchanged.
        conc = _saved(client, ckpt, model)
        assert np.all(conc == PRIOR)
        kept = [p for p in tmp_path.iterdir() if p.name.startswith("map.npz.rejected")]
        assert len(kept) == 1 and kept[0].read_bytes() == original
        _frames(client, [10**9])
    finally:
        client.close()
        assert node.stop() == 0


def test_kill9_during_periodic_checkpoints_never_corrupts(tmp_path):
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    ckpt = tmp_path / "map.npz"
    rng = random.Random(3)
    stamp = 10**9
    for run in range(2):
        node, client = _start(tmp_path, model_path, ckpt, f"run{run}", checkpoint_period=0.05)
        try:
            end = time.monotonic() + 1.0 + rng.random()
            while time.monotonic() < end:  # frames keep the map dirty: a checkpoint every ~50 ms
                stamp += 10**8
                client.send_frame(stamp)
                time.sleep(0.01)
            node.kill9()
        finally:
            client.close()
        smap = SemanticMap.load(ckpt, model)  # loads: never a partial file
        assert smap.concentrations.max() > 1.0
        assert not [p for p in tmp_path.iterdir() if p.name.startswith("map.npz.rejected")]
