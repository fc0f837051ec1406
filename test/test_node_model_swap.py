"""Live splat swap over real DDS: css_node moves its map to a newer PLY dropped into model_watch_dir."""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).parent))
import ros_helpers as rh  # noqa: E402
from retrain import retrained_variant  # noqa: E402

from css_ros import GaussianModel, SemanticMap  # noqa: E402
from css_ros.ros.params import checkpoint_file  # noqa: E402

pytestmark = pytest.mark.slow
PRIOR = 1e-3


def test_node_moves_its_map_to_a_newer_splat(tmp_path):
    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    old = GaussianModel.from_ply(model_path)
    watch = tmp_path / "watch"
    watch.mkdir()
    template = str(tmp_path / "maps" / "{fingerprint}.npz")
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES, prior=PRIOR,
                               checkpoint_path=template, resume=False, checkpoint_period=0.0, log_period=0.5,
                               warmup=False, model_watch_dir=str(watch), model_watch_period=0.3),
                          domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0)
        for i in range(3):
            assert client.send_frame_until_processed((i + 1) * 10**9) is not None
        old_ckpt = Path(checkpoint_file(template, old.fingerprint))
        assert client.call(client.save_client).success
        before = SemanticMap.load(old_ckpt, old)
        (watch / "broken.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")
        assert node.wait_log("new model unreadable", 20.0), node.log()
        new = retrained_variant(old, seed=3, jitter=0.005)
        new.to_ply(watch / "retrained.ply")
        assert node.wait_log("model swapped to", 30.0), node.log()
        new_ckpt = Path(checkpoint_file(template, GaussianModel.from_ply(watch / "retrained.ply").fingerprint))
        assert client.wait_until(new_ckpt.is_file, 10.0), "no checkpoint under the new fingerprint"
        moved = SemanticMap.load(new_ckpt, GaussianModel.from_ply(watch / "retrained.ply"))
        ev_before = (before.concentrations - PRIOR).sum()
        ev_after = (moved.concentrations - PRIOR).sum()
        assert abs(ev_after / ev_before - 1) < 0.15
        sem = moved.gaussian_semantics()
        left = moved.model.means[:, 0] < -0.3
        right = moved.model.means[:, 0] > 0.3
        assert np.mean(sem.label[left & sem.observed] == 1) > 0.9   # the wall's classes moved with it
        assert np.mean(sem.label[right & sem.observed] == 2) > 0.9
        client.send_frame(10 * 10**9)                                # frames go on on the new splat
        assert client.wait_stamp("semantic", 10 * 10**9) is not None
        assert client.call(client.save_client).success
        again = SemanticMap.load(new_ckpt, moved.model)
        assert again.frames_observed == moved.frames_observed + 1
        assert node.proc.poll() is None
    finally:
        client.close()
        node.stop()
