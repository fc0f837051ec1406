"""css_node's 3D map over real DDS: ~/semantic_cloud (late subscriber), point_queries, ~/load_map."""
from __future__ import annotations

import time

import numpy as np
import pytest

rclpy = pytest.importorskip("rclpy")

import ros_helpers as rh  # noqa: E402
from css_ros.engine.gaussians import GaussianModel  # noqa: E402
from css_ros.io.clouds import pack_cloud, unpack_cloud, unpack_rgb  # noqa: E402

pytestmark = pytest.mark.slow

C = rh.NUM_CLASSES
CLOUD_FIELDS = ("x", "y", "z", "rgb", "label", "expectation", "variance", "evidence")


def _observed_reference(npz, min_evidence=0.5, prior=1e-3):
    """Independent SPEC §9 per-Gaussian semantics from a saved checkpoint (numpy)."""
    a = np.load(npz, allow_pickle=False)["concentrations"]
    S = a.sum(axis=1)
    observed = S - a.shape[1] * prior >= min_evidence
    label = np.argmax(a, axis=1)
    E = a[np.arange(len(a)), label] / S
    return observed, label, E, E * (1 - E) / (1 + S)


def _cloud_msg(header_stamp_ns, xyz):
    from sensor_msgs.msg import PointCloud2, PointField

    from css_ros.ros.conversions import header_msg

    f = pack_cloud({"x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32),
                    "z": xyz[:, 2].astype(np.float32)})
    msg = PointCloud2(header=header_msg(header_stamp_ns, "map"), height=1, width=f["width"],
                      fields=[PointField(name=n, offset=o, datatype=d, count=c) for n, o, d, c in f["fields"]],
                      is_bigendian=False, point_step=f["point_step"], row_step=f["row_step"], is_dense=True)
    msg.data = f["data"].tobytes()
    return msg


def _write_corrupt_compressed_map(path, model) -> None:
    """A valid map of ``model`` written with np.savez_compressed, then the first byte of the
    concentrations' deflate stream set to 0x07 (an invalid block type)."""
    import zipfile

    from css_ros.engine.semantic_map import SemanticMap

    smap = SemanticMap(model, C)
    smap.concentrations[:] = np.random.default_rng(0).uniform(1, 2, smap.concentrations.shape)
    smap.save(path)
    with np.load(path, allow_pickle=False) as data:
        members = {k: data[k] for k in data.files}
    with open(path, "wb") as fh:
        np.savez_compressed(fh, **members)
    raw = bytearray(path.read_bytes())
    with zipfile.ZipFile(path) as zf:
        info = zf.getinfo("concentrations.npy")
    o = info.header_offset
    raw[o + 30 + int.from_bytes(raw[o + 26:o + 28], "little") + int.from_bytes(raw[o + 28:o + 30], "little")] = 7
    path.write_bytes(bytes(raw))


def test_semantic_cloud_point_queries_and_load_map(tmp_path):
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import PointCloud2
    from std_srvs.srv import Trigger

    domain = rh.next_domain_id()
    model_path = rh.write_wall_model(tmp_path / "wall.ply")
    model = GaussianModel.from_ply(model_path)
    npz = tmp_path / "map.npz"
    node = rh.NodeProcess(dict(model_path=str(model_path), class_file="", num_classes=C, log_period=0.3,
                               checkpoint_path=str(npz), checkpoint_period=0.0, cloud_period=0.3,
                               max_query_points=5), domain, tmp_path / "node.log")
    client = rh.RosClient(domain)
    try:
        assert client.wait_connected(60.0), node.log()
        time.sleep(0.5)
        for i in range(3):
            assert client.send_frame_until_processed((i + 1) * 10**9, output="view_uncertainty"), node.log()[-3000:]
        saved = client.call(client.save_client)
        assert saved.success, saved.message
        observed, label, E, V = _observed_reference(npz)
        assert 50 < observed.sum() < model.num_gaussians  # the wall's centre seen, its rim not

        # A subscriber that joins now still gets the last cloud (transient local); the cloud of the final map
        # goes out within a cloud_period of the last frame (later on a loaded host: wait for it, bounded).
        clouds = []
        qos = QoSProfile(depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL)
        client.node.create_subscription(PointCloud2, "/css_node/semantic_cloud", clouds.append, qos)
        assert client.wait_until(lambda: clouds and clouds[-1].width == observed.sum(), 30.0), (
            [c.width for c in clouds], int(observed.sum()), node.log()[-3000:])
        cloud = clouds[-1]
        assert cloud.header.frame_id == "map"
        assert tuple(f.name for f in cloud.fields) == CLOUD_FIELDS
        pts = unpack_cloud(cloud)
        assert len(pts) == observed.sum()
        means = np.asarray(model.means)[observed]
        np.testing.assert_allclose(np.stack([pts["x"], pts["y"], pts["z"]], 1), means, atol=1e-6)
        np.testing.assert_array_equal(pts["label"], label[observed])
        np.testing.assert_allclose(pts["expectation"], E[observed], rtol=1e-5)
        np.testing.assert_allclose(pts["variance"], V[observed], rtol=1e-4, atol=1e-12)
        from css_ros.engine.classes import ClassSet

        np.testing.assert_array_equal(unpack_rgb(pts["rgb"]), ClassSet.default(C).palette[label[observed]])

        # Point queries: request order, header echoed, per-class fields; far and NaN points unknown.
        answers = []
        client.node.create_subscription(PointCloud2, "/css_node/point_query_results", answers.append, 10)
        pub = client.node.create_publisher(PointCloud2, "point_queries", 10)
        assert client.wait_until(lambda: pub.get_subscription_count() > 0, 20.0)
        assert client.wait_outputs_heard(("point_query_results",)), node.log()[-3000:]
        first = int(np.flatnonzero(observed)[0])
        xyz = np.array([model.means[first], [100.0, 100.0, 100.0], [np.nan, 0.0, 0.0]])
        pub.publish(_cloud_msg(77, xyz))
        assert client.wait_until(lambda: answers, 20.0), node.log()[-3000:]
        ans = answers[-1]
        assert ans.header.stamp.nanosec == 77 and ans.header.frame_id == "map"
        names = [f.name for f in ans.fields]
        assert names == ["x", "y", "z", "label", "expectation", "variance"] + [f"class_{c}" for c in range(C)]
        q = unpack_cloud(ans)
        assert q["label"].tolist()[1:] == [255, 255]
        assert q["label"][0] == label[first]
        np.testing.assert_allclose([q[f"class_{c}"][1] for c in range(C)], 1.0 / C, rtol=1e-6)
        # A NaN point gets exactly the far point's answer (one rule for points that cannot be located).
        assert [q[f"class_{c}"][2] for c in range(C)] == [q[f"class_{c}"][1] for c in range(C)]
        assert q["variance"][2] == q["variance"][1]
        # Too many points (from the header): an empty answer at once, counted.
        answers.clear()
        pub.publish(_cloud_msg(78, np.zeros((6, 3))))
        assert client.wait_until(lambda: answers, 20.0)
        assert answers[-1].width == 0 and answers[-1].header.stamp.nanosec == 78 and len(answers[-1].data) == 0
        assert client.wait_diag("requests_nan[too many points]", 1) == 1

        # load_map: reset, then load the checkpoint back; the next cloud shows the loaded map again. The list is
        # cleared before the reset: the loaded map's cloud may go out before the load's answer arrives, and after
        # the reset only the reset's (empty) cloud or the loaded one can come.
        clouds.clear()
        assert client.call(client.reset_client).success
        load = client.node.create_client(Trigger, "/css_node/load_map")
        res = client.call(load)
        assert res.success and res.message.startswith(f"loaded {npz}"), res.message
        assert client.wait_until(lambda: clouds and clouds[-1].width == observed.sum(), 20.0), (
            [c.width for c in clouds], int(observed.sum()))
        npz.write_bytes(b"not a map")
        res = client.call(load)
        assert not res.success and "checkpoint refused, map unchanged" in res.message
        # A corrupt compressed checkpoint (invalid deflate block): refused by name, the node keeps answering.
        _write_corrupt_compressed_map(npz, model)
        res = client.call(load)
        assert not res.success and f"checkpoint refused, map unchanged: cannot read map file {npz}" in res.message
        assert client.call(client.save_client).success and node.proc.poll() is None
    finally:
        client.close()
        assert node.stop() == 0
