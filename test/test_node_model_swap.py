"""Live splat swap over real DDS: css_node moves its map to a newer PLY dropped into model_watch_dir."""
from __future__ import annotations

import os
import sys
import time
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


def _swap_node(tmp_path: Path, watch: Path, template: str, domain: int, log: str, **extra) -> "rh.NodeProcess":
    model_path = tmp_path / "wall.ply"
    params = dict(model_path=str(model_path), class_file="", num_classes=rh.NUM_CLASSES, prior=PRIOR,
                  checkpoint_path=template, resume=True, checkpoint_period=0.0, log_period=0.5, warmup=False,
                  model_watch_dir=str(watch), model_watch_period=0.3)
    params.update(extra)
    return rh.NodeProcess(params, domain, tmp_path / log)


def _send_frames(client, stamps_s) -> None:
    for s in stamps_s:
        assert client.send_frame_until_processed(s * 10**9) is not None


def test_restart_after_a_swap_resumes_the_newest_map(tmp_path):
    """Map, swap, map more, stop, restart with the same parameters: the node starts on the newer splat of
    model_watch_dir and its checkpoint (every frame kept), not on model_path's older checkpoint (which it would
    then swap again, overwriting the newer map)."""
    domain = rh.next_domain_id()
    old = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    watch = tmp_path / "watch"
    watch.mkdir()
    template = str(tmp_path / "maps" / "{fingerprint}.npz")
    node = _swap_node(tmp_path, watch, template, domain, "node1.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0)
        _send_frames(client, range(1, 4))
        assert client.call(client.save_client).success
        new = retrained_variant(old, seed=3, jitter=0.005)
        new.to_ply(watch / "retrained.ply")
        new = GaussianModel.from_ply(watch / "retrained.ply")
        assert node.wait_log("model swapped to", 30.0), node.log()
        _send_frames(client, range(10, 15))
        assert client.call(client.save_client).success
        new_ckpt = Path(checkpoint_file(template, new.fingerprint))
        before = SemanticMap.load(new_ckpt, new)
        assert before.frames_observed == 8
    finally:
        client.close()
        assert node.stop() == 0, node.log()
    node = _swap_node(tmp_path, watch, template, domain, "node2.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0)
        assert node.wait_log(f"resumed from {new_ckpt} (8 frames observed)", 10.0), node.log()
        time.sleep(2.0)                        # several scans of model_watch_dir: nothing to swap
        assert "model swapped to" not in node.log(), node.log()
        assert client.call(client.save_client).success
        after = SemanticMap.load(new_ckpt, new)
        assert after.frames_observed == before.frames_observed
        np.testing.assert_array_equal(after.concentrations, before.concentrations)
        _send_frames(client, [20])                 # mapping goes on on the newer splat
        assert client.call(client.save_client).success
        assert SemanticMap.load(new_ckpt, new).frames_observed == 9
        assert SemanticMap.load(Path(checkpoint_file(template, old.fingerprint)), old).frames_observed == 3
    finally:
        client.close()
        node.stop()


def test_newest_watched_model_picks_the_newest_splat_with_its_checkpoint(tmp_path):
    """A -> B swapped (B's checkpoint written), then C dropped while the node was down: start on B (C is swapped
    to by the running node); with one fixed checkpoint file the file's recorded fingerprint decides."""
    from css_ros.ros.params import NodeParams
    from css_ros.ros.startup import newest_watched_model

    a_path = rh.write_wall_model(tmp_path / "wall.ply")
    a = GaussianModel.from_ply(a_path)
    watch = tmp_path / "watch"
    watch.mkdir()
    b, c = retrained_variant(a, seed=1, jitter=0.005), retrained_variant(a, seed=2, jitter=0.005)
    for name, m, t in (("b.ply", b, 10), ("c.ply", c, 20)):
        m.to_ply(watch / name)
        os.utime(watch / name, ns=(a_path.stat().st_mtime_ns + t * 10**9,) * 2)
    logs: list[str] = []
    template = str(tmp_path / "maps" / "{fingerprint}.npz")
    p = NodeParams(model_path=str(a_path), model_watch_dir=str(watch), checkpoint_path=template)
    assert newest_watched_model(p, a_path, logs.append, logs.append) is None     # no checkpoint of B or C
    SemanticMap(a, 4).save(checkpoint_file(template, a.fingerprint))
    assert newest_watched_model(p, a_path, logs.append, logs.append) is None
    SemanticMap(b, 4).save(checkpoint_file(template, b.fingerprint))
    path, model = newest_watched_model(p, a_path, logs.append, logs.append)
    assert path == watch / "b.ply" and model.fingerprint == b.fingerprint
    assert newest_watched_model(NodeParams(model_path=str(a_path), model_watch_dir=str(watch),
                                           checkpoint_path=template, resume=False), a_path, print, print) is None
    fixed = tmp_path / "fixed.npz"          # one file for every model: its recorded fingerprint decides
    p = NodeParams(model_path=str(a_path), model_watch_dir=str(watch), checkpoint_path=str(fixed))
    SemanticMap(a, 4).save(fixed)
    assert newest_watched_model(p, a_path, logs.append, logs.append) is None
    SemanticMap(c, 4).save(fixed)
    assert newest_watched_model(p, a_path, logs.append, logs.append)[0] == watch / "c.ply"
    (watch / "d.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 5\n")   # newest, broken
    os.utime(watch / "d.ply", ns=(a_path.stat().st_mtime_ns + 30 * 10**9,) * 2)
    assert newest_watched_model(p, a_path, logs.append, logs.append)[0] == watch / "c.ply"
    assert any("d.ply unreadable at start" in line for line in logs)


def test_view_stream_follows_a_swap(tmp_path):
    """After a swap ~/view/info names the new model, ~/view/model carries it (a late joiner gets only its
    chunks) and ~/view/semantics goes on, indexed on the new splat, matching the map."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_msgs.msg import String

    from css_ros.engine.field3d import gaussian_semantics
    from css_ros.io.clouds import unpack_cloud
    from css_ros.io.view_stream import parse_info

    domain = rh.next_domain_id()
    old = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    watch = tmp_path / "watch"
    watch.mkdir()
    template = str(tmp_path / "maps" / "{fingerprint}.npz")
    node = _swap_node(tmp_path, watch, template, domain, "node.log", resume=False, view_period=0.2)
    client = rh.RosClient(domain)
    latched = QoSProfile(depth=100, reliability=ReliabilityPolicy.RELIABLE,
                         durability=DurabilityPolicy.TRANSIENT_LOCAL)
    got: dict[str, list] = {"info": [], "model": [], "semantics": [], "info_late": [], "model_late": []}

    def record(kind):
        def cb(msg):
            with client.lock:
                got[kind].append(msg)
        return cb

    def listen(tag: str) -> None:
        client.node.create_subscription(String, "/css_node/view/info", record("info" + tag), latched)
        client.node.create_subscription(PointCloud2, "/css_node/view/model", record("model" + tag), latched)

    def infos(tag: str = "") -> list[dict]:
        with client.lock:
            return [parse_info(m.data) for m in got["info" + tag]]

    def sems() -> list:
        with client.lock:
            return list(got["semantics"])

    listen("")
    client.node.create_subscription(PointCloud2, "/css_node/view/semantics", record("semantics"),
                                    QoSProfile(depth=1000, reliability=ReliabilityPolicy.RELIABLE))
    try:
        assert client.wait_connected(60.0)
        assert client.wait_until(lambda: infos() and infos()[-1]["fingerprint"] == old.fingerprint, 20.0)
        _send_frames(client, range(1, 4))
        assert client.wait_until(lambda: len(sems()) >= 1, 10.0), "no semantics before the swap"
        retrained_variant(old, seed=3, jitter=0.005).to_ply(watch / "retrained.ply")
        new = GaussianModel.from_ply(watch / "retrained.ply")
        assert new.num_gaussians > old.num_gaussians
        assert node.wait_log("model swapped to", 30.0), node.log()
        assert client.wait_until(lambda: infos()[-1]["fingerprint"] == new.fingerprint, 10.0), \
            f"~/view/info still names {infos()[-1]['fingerprint'][:12]}"
        assert infos()[-1]["num_gaussians"] == new.num_gaussians

        def new_model_rows():
            with client.lock:
                msgs = list(got["model"])
            rows = [unpack_cloud(m) for m in msgs if m.width]
            return [r for r in rows if len(r) == new.num_gaussians]
        assert client.wait_until(new_model_rows, 10.0), "~/view/model did not carry the new splat"
        rows = new_model_rows()[-1]
        np.testing.assert_allclose(np.stack([rows["x"], rows["y"], rows["z"]], 1), new.means, atol=1e-6)
        with client.lock:
            n_before = len(got["semantics"])
        for s in range(10, 16):                               # one frame per ~2 view periods (0.2 s)
            _send_frames(client, [s])
            time.sleep(0.4)
        assert client.wait_until(lambda: len(sems()) >= n_before + 3, 10.0), \
            f"{len(sems()) - n_before} ~/view/semantics messages after the swap while 6 frames were mapped"
        # the viewer's state, rebuilt from the messages since the swap, is the node's map on the new splat: the
        # first message of the new stream resends every Gaussian (indices beyond the old splat's included)
        first = next(i for i, m in enumerate(sems()) if int(unpack_cloud(m)["index"].max()) >= old.num_gaussians)
        assert len(unpack_cloud(sems()[first])) == new.num_gaussians
        assert max(int(unpack_cloud(m)["index"].max()) for m in sems()[first:]) < new.num_gaussians
        new_ckpt = Path(checkpoint_file(template, new.fingerprint))

        def viewer_matches_map() -> bool:
            assert client.call(client.save_client).success
            ref = gaussian_semantics(SemanticMap.load(new_ckpt, new).concentrations, PRIOR, 0.5, 255)
            label = np.full(new.num_gaussians, -1)
            evidence = np.full(new.num_gaussians, np.nan)
            for m in sems()[first:]:
                r = unpack_cloud(m)
                label[r["index"]], evidence[r["index"]] = r["label"], r["evidence"]
            lab_ref = np.where(ref.observed, ref.label, 255)
            # evidence is resent when it leaves its bin of 1/8 of a doubling (log2(1 + S_n - C alpha_0))
            octaves = np.abs(np.log2(1 + evidence) - np.log2(1 + np.maximum(ref.evidence, 0)))
            return bool(np.array_equal(label, lab_ref) and np.all(octaves <= 1 / 8 + 1e-4))
        assert client.wait_until(viewer_matches_map, 10.0, 0.5)
        listen("_late")                                       # a viewer that joins now gets the new model only
        assert client.wait_until(lambda: infos("_late"), 10.0)
        time.sleep(1.0)
        assert [i["fingerprint"] for i in infos("_late")] == [new.fingerprint]
        with client.lock:
            late = [unpack_cloud(m) for m in got["model_late"]]
        assert sum(len(r) for r in late) == new.num_gaussians
    finally:
        client.close()
        node.stop()


def test_unrelated_splat_is_refused_and_a_poor_one_warned(tmp_path):
    """The same wall moved 1 km keeps no evidence: refused with a warning naming the ratio, the map and its
    frame count stay on the old splat. A splat that lost part of the scene (ratio between model_swap_min_ratio
    and model_swap_warn_ratio) is swapped to with a warning; frames_observed is kept."""
    from css_ros.engine.transfer import transfer_concentrations

    domain = rh.next_domain_id()
    old = GaussianModel.from_ply(rh.write_wall_model(tmp_path / "wall.ply"))
    watch = tmp_path / "watch"
    watch.mkdir()
    template = str(tmp_path / "maps" / "{fingerprint}.npz")
    node = _swap_node(tmp_path, watch, template, domain, "node.log", resume=False)
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0)
        _send_frames(client, range(1, 4))
        far = GaussianModel(old.means + np.float32([1000.0, 0.0, 0.0]), old.sh, old.opacity_logits,
                            old.log_scales, old.rotations)
        far.to_ply(watch / "far.ply")
        assert node.wait_log("model swap REFUSED", 30.0), node.log()
        line = next(x for x in node.log().splitlines() if "model swap REFUSED" in x)
        assert "evidence ratio 0.0000" in line and "3 frames" in line and "WARN" in line, line
        assert not Path(checkpoint_file(template, far.fingerprint)).exists()
        assert client.wait_diag("model_swaps_refused", 1) == 1
        _send_frames(client, [5])                          # mapping goes on, on the old splat
        assert client.call(client.save_client).success
        kept = SemanticMap.load(checkpoint_file(template, old.fingerprint), old)
        assert kept.frames_observed == 4
        time.sleep(1.0)                                    # a refused file is not tried again
        assert node.log().count("model swap REFUSED") == 1

        cropped = old.select(old.means[:, 0] < 1.0)        # a quarter of the wall gone
        ratio = transfer_concentrations(old, kept.concentrations, PRIOR, cropped)[1].ratio
        assert 0.7 <= ratio < 0.95, ratio                  # between the default thresholds
        cropped.to_ply(watch / "cropped.ply")
        assert node.wait_log("LOW evidence ratio", 30.0), node.log()
        line = next(x for x in node.log().splitlines() if "LOW evidence ratio" in x)
        assert f"evidence ratio {ratio:.4f}" in line and "WARN" in line, line
        ckpt = Path(checkpoint_file(template, cropped.fingerprint))
        assert client.wait_until(ckpt.is_file, 10.0)
        moved = SemanticMap.load(ckpt, cropped)
        assert moved.frames_observed == 4
        np.testing.assert_allclose((moved.concentrations - PRIOR).sum(), ratio * (kept.concentrations - PRIOR).sum(),
                                   rtol=1e-9)
        assert node.proc.poll() is None
    finally:
        client.close()
        node.stop()
