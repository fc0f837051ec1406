"""End-to-end tests of css_replay on tiny bags written here with rosbags (clean and deliberately broken)."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from rosbags.highlevel import AnyReader
from rosbags.rosbag2 import StoragePlugin, Writer
from rosbags.typesys import Stores, get_typestore

from css_ros.engine.camera import Camera
from css_ros.engine.classes import ClassSet
from css_ros.engine.gaussians import GaussianModel
from css_ros.io.messages import unpack_view_points
from css_ros.evaluation.cli import main

W, H = 64, 48
FX = 50.0
WALL_X = 3.0  # the scene is a wall of Gaussians on the plane x = 3 m, facing the camera
C = 3
STORE = get_typestore(Stores.ROS2_JAZZY)
T = STORE.types


def wall_class(y: np.ndarray) -> np.ndarray:
    """Ground-truth class of a wall point from its y coordinate: three vertical bands."""
    return np.where(y < -0.6, 0, np.where(y < 0.6, 1, 2))


def make_model() -> GaussianModel:
    ys, zs = np.meshgrid(np.arange(-2.5, 2.51, 0.08), np.arange(-2.0, 2.01, 0.08))
    n = ys.size
    means = np.stack([np.full(n, WALL_X), ys.ravel(), zs.ravel()], axis=1)
    scales = np.tile([0.004, 0.05, 0.05], (n, 1))
    quats = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    palette = np.array([[0.8, 0.2, 0.2], [0.2, 0.8, 0.2], [0.2, 0.2, 0.8]])
    colors = palette[wall_class(means[:, 1])]
    return GaussianModel.from_activated(means, scales, quats, np.full(n, 0.95), colors)


def cameras(n: int) -> list[Camera]:
    K = np.array([[FX, 0, (W - 1) / 2], [0, FX, (H - 1) / 2], [0, 0, 1]])
    out = []
    for i in range(n):
        pos = np.array([0.0, 0.3 * np.sin(i), 0.1 * np.cos(i)])
        target = np.array([WALL_X, 0.2 * np.sin(0.7 * i), 0.0])
        out.append(Camera.look_at(pos, target, K, W, H))
    return out


def gt_labels(cam: Camera) -> np.ndarray:
    """Independent ground truth: intersect each pixel ray with the wall plane and classify the hit point."""
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    d_cam = np.stack([(u - cam.cx) / cam.fx, (v - cam.cy) / cam.fy, np.ones_like(u, dtype=float)], axis=-1)
    d_map = d_cam @ cam.R_map_cam.T
    t = (WALL_X - cam.position[0]) / d_map[..., 0]
    y = cam.position[1] + t * d_map[..., 1]
    return wall_class(y).astype(np.uint8)


def image_msg(array: np.ndarray, encoding: str, stamp_ns: int, frame_id: str = "camera_optical"):
    channels = 1 if array.ndim == 2 else array.shape[2]
    return T["sensor_msgs/msg/Image"](
        header=header(stamp_ns, frame_id), height=array.shape[0], width=array.shape[1], encoding=encoding,
        is_bigendian=0, step=array.shape[1] * channels * array.dtype.itemsize,
        data=np.ascontiguousarray(array).view(np.uint8).reshape(-1))


def header(stamp_ns: int, frame_id: str):
    return T["std_msgs/msg/Header"](stamp=T["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9,
                                                                          nanosec=stamp_ns % 10**9),
                                    frame_id=frame_id)


def camera_info_msg(stamp_ns: int, width: int = W, height: int = H):
    K = [FX, 0.0, (width - 1) / 2, 0.0, FX, (height - 1) / 2, 0.0, 0.0, 1.0]
    return T["sensor_msgs/msg/CameraInfo"](
        header=header(stamp_ns, "camera_optical"), height=height, width=width, distortion_model="plumb_bob",
        d=np.zeros(5), k=np.array(K), r=np.eye(3).ravel(), p=np.array(K[:3] + [0.0] + K[3:6] + [0.0] + K[6:] + [0.0]),
        binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def pose_msg(cam: Camera, stamp_ns: int):
    p, q = cam.position, cam.quaternion_xyzw
    return T["geometry_msgs/msg/PoseStamped"](
        header=header(stamp_ns, "map"),
        pose=T["geometry_msgs/msg/Pose"](position=T["geometry_msgs/msg/Point"](x=p[0], y=p[1], z=p[2]),
                                         orientation=T["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2],
                                                                                       w=q[3])))


def stamp_of(i: int) -> int:
    return 1_700_000_000 * 10**9 + i * 100_000_000 + 12345


def write_scene(root: Path, n_frames: int = 6, noise: float = 0.25, storage: str = "sqlite3",
                drop_topics: tuple[str, ...] = (), no_pose_frames: tuple[int, ...] = (),
                bad_encoding_frames: tuple[int, ...] = (), small_seg_frames: tuple[int, ...] = ()) -> Path:
    """Write model.ply, classes.yaml and bag/ under ``root``; return the bag path."""
    root.mkdir(parents=True, exist_ok=True)
    make_model().to_ply(root / "model.ply")
    ClassSet(("left", "middle", "right"), np.array([[200, 50, 50], [50, 200, 50], [50, 50, 200]],
                                                   np.uint8)).to_yaml(root / "classes.yaml")
    rng = np.random.default_rng(7)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    bag = root / "bag"
    palette = np.array([[200, 50, 50], [50, 200, 50], [50, 50, 200]], np.uint8)
    with Writer(bag, version=9, storage_plugin=plugin) as w:
        conns = {}
        for topic, typ in (("/camera_info", "sensor_msgs/msg/CameraInfo"), ("/image", "sensor_msgs/msg/Image"),
                           ("/segmentation", "sensor_msgs/msg/Image"), ("/segmentation_gt", "sensor_msgs/msg/Image"),
                           ("/segmentation_confidence", "sensor_msgs/msg/Image"),
                           ("/pose", "geometry_msgs/msg/PoseStamped")):
            if topic not in drop_topics:
                conns[topic] = w.add_connection(topic, typ, typestore=STORE)

        def put(topic, msg, typ, t):
            if topic in conns:
                w.write(conns[topic], t, STORE.serialize_cdr(msg, typ))

        for i, cam in enumerate(cameras(n_frames)):
            s = stamp_of(i)
            gt = gt_labels(cam)
            seg = gt.copy()
            flip = rng.random(gt.shape) < noise
            seg[flip] = rng.integers(0, C, int(flip.sum()))
            conf = np.where(flip, 0.5, 0.9).astype(np.float32)
            if i in small_seg_frames:
                seg = seg[: H // 2, : W // 2].copy()
            put("/camera_info", camera_info_msg(s), "sensor_msgs/msg/CameraInfo", s)
            put("/image", image_msg(palette[gt], "rgb8", s), "sensor_msgs/msg/Image", s + 1)
            put("/segmentation", image_msg(seg, "weird8" if i in bad_encoding_frames else "mono8", s),
                "sensor_msgs/msg/Image", s + 2)
            put("/segmentation_gt", image_msg(gt, "mono8", s), "sensor_msgs/msg/Image", s + 3)
            put("/segmentation_confidence", image_msg(conf, "32FC1", s), "sensor_msgs/msg/Image", s + 4)
            if i not in no_pose_frames:
                # pose stamp 1 ms off: inside the default 50 ms slop
                put("/pose", pose_msg(cam, s + 1_000_000), "geometry_msgs/msg/PoseStamped", s + 5)
    return bag


def run_replay(bag: Path, out: Path, *extra: str) -> int:
    return main([str(bag), "--out", str(out), "--quiet", *extra])


OUTPUT_TOPICS = {
    "/css_node/semantic": ("sensor_msgs/msg/Image", "mono8"),
    "/css_node/semantic_color": ("sensor_msgs/msg/Image", "rgb8"),
    "/css_node/expectation": ("sensor_msgs/msg/Image", "32FC1"),
    "/css_node/variance": ("sensor_msgs/msg/Image", "32FC1"),
    "/css_node/rendered_image": ("sensor_msgs/msg/Image", "rgb8"),
    "/css_node/view_uncertainty": ("sensor_msgs/msg/PointCloud2", None),
}


@pytest.fixture(scope="module")
def clean_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("clean")
    bag = write_scene(root, n_frames=6)
    out = root / "out"
    rc = run_replay(bag, out)
    return rc, out, bag


def test_replay_clean_outputs_bag(clean_run):
    rc, out, _ = clean_run
    assert rc == 0
    stamps = [stamp_of(i) for i in range(6)]
    seen: dict[str, list[int]] = {t: [] for t in OUTPUT_TOPICS}
    with AnyReader([out / "bag"], default_typestore=STORE) as reader:
        assert {c.topic: c.msgtype for c in reader.connections} == {t: v[0] for t, v in OUTPUT_TOPICS.items()}
        for conn, t, raw in reader.messages():
            msg = reader.deserialize(raw, conn.msgtype)
            stamp = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            assert t == stamp
            seen[conn.topic].append(stamp)
            enc = OUTPUT_TOPICS[conn.topic][1]
            if enc is not None:
                assert msg.encoding == enc and (msg.width, msg.height) == (W, H)
                assert msg.header.frame_id == "camera_optical"
            else:
                pts = unpack_view_points(msg)
                assert pts.shape == (1,) and msg.header.frame_id == "map"
                assert 0.0 <= pts["u_exp"][0] <= 1.0 and pts["u_var"][0] > 0
    for topic, got in seen.items():
        assert sorted(got) == stamps, topic


def test_replay_clean_metrics(clean_run):
    rc, out, _ = clean_run
    m = json.loads((out / "metrics.json").read_text())
    for key in ("config", "frames", "segmentation", "pixel_sparsification", "image_level", "timing", "classes"):
        assert key in m
    assert m["frames"]["processed"] == 6 and m["frames"]["trained"] == 6 and m["frames"]["evaluated"] == 6
    assert sum(m["frames"]["skipped"].values()) == 0
    inp, css = m["segmentation"]["input"], m["segmentation"]["css"]
    assert set(inp["per_class_iou"]) == {"left", "middle", "right"}
    # input noise: 25% of pixels replaced by a uniform class -> accuracy ~ 1 - 0.25 * 2/3
    assert inp["pixel_accuracy"] == pytest.approx(1 - 0.25 * 2 / 3, abs=0.03)
    assert css["pixel_accuracy"] > 0.93 and css["pixel_accuracy"] > inp["pixel_accuracy"]
    assert css["miou"] > inp["miou"]
    assert m["segmentation"]["css_online"]["num_pixels"] == css["num_pixels"] == inp["num_pixels"]
    px = m["pixel_sparsification"]
    assert set(px["curves"]) == {"expectation", "variance", "evidence", "random", "oracle"}
    assert px["num_samples"] == 6 * W * H
    assert px["ause"]["oracle"] == 0.0 and all(v >= -1e-9 for v in px["ause"].values())
    assert len(px["fractions"]) == len(px["curves"]["expectation"]) == 100
    il = m["image_level"]
    assert len(il["frames"]) == 6 and set(il["spearman"]) == {"u_var", "u_exp"}
    for f in il["frames"]:
        assert 0 <= f["error"] <= 1 and f["trained"]
    for name in ("report.md", "map.npz", "map_semantic.ply", "map_uncertainty_variance.ply",
                 "map_uncertainty_variance_colorbar.png", "birdseye.png", "sparsification.png",
                 "image_uncertainty.png", "per_class_iou.png", "examples.png"):
        assert (out / name).is_file(), name
    report = (out / "report.md").read_text()
    assert "sparsification.png" in report and "examples.png" in report


def test_semantic_ply_has_class_fields(clean_run):
    from plyfile import PlyData

    _, out, _ = clean_run
    v = PlyData.read(str(out / "map_semantic.ply"))["vertex"]
    names = v.data.dtype.names
    assert {"class_id", "expectation", "variance", "x", "opacity"} <= set(names)
    alpha = np.load(out / "map.npz")
    key = next(k for k in alpha.files if alpha[k].ndim == 2)
    a = alpha[key]
    S = a.sum(axis=1)
    seen = S - a.shape[1] * 1e-3 >= 0.5  # SPEC §9 observed flag (prior 1e-3, min_evidence 0.5)
    np.testing.assert_array_equal(v["class_id"], np.where(seen, np.argmax(a, axis=1), 255))
    E = a.max(axis=1) / S
    np.testing.assert_allclose(v["expectation"], E, rtol=1e-5)
    np.testing.assert_allclose(v["variance"], E * (1 - E) / (1 + S), rtol=1e-4, atol=1e-9)
    # Gaussians on the wall carry the class of their band where observed with many counts
    x = np.stack([v["x"], v["y"], v["z"]], axis=1)
    observed = S > 5
    assert observed.sum() > 50
    assert np.mean(v["class_id"][observed] == wall_class(x[observed, 1])) > 0.95


def test_train_frames_heldout_mcap(tmp_path):
    bag = write_scene(tmp_path, n_frames=5, storage="mcap")
    rc = run_replay(bag, tmp_path / "out", "--train-frames", "3", "--no-output-bag")
    assert rc == 0
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["frames"]["trained"] == 3 and m["frames"]["heldout"] == 2
    assert [f["trained"] for f in m["image_level"]["frames"]] == [True, True, True, False, False]
    assert "css_heldout_frames" in m["segmentation"]
    assert not (tmp_path / "out" / "bag").exists()
    # css_view's trajectory: the fused frames only; the bag has ground truth, so the online renders are made (for
    # the online metrics) even without an output bag, and their U_var is kept
    from css_ros.io.trajectory import load_trajectory

    traj = load_trajectory(tmp_path / "out" / "trajectory.npz")
    assert len(traj) == 3 and all(np.isfinite(u) and u > 0 for *_, u in traj)
    assert "css_online" in m["segmentation"]


def test_replay_prints_the_css_view_command_and_writes_the_trajectory(clean_run, capsys, tmp_path):
    from css_ros.io.trajectory import load_trajectory

    rc, out, bag = clean_run
    assert run_replay(bag, tmp_path / "again", "--no-output-bag", "--max-frames", "2") == 0
    assert f"view the map in a browser: css_view {tmp_path / 'again'}" in capsys.readouterr().out
    m = json.loads((out / "metrics.json").read_text())
    traj = load_trajectory(out / "trajectory.npz")
    assert len(traj) == m["frames"]["trained"]
    u = [f["u_var"] for f in m["image_level"]["frames"] if f["trained"]]
    assert all(np.isfinite(t[3]) and t[3] > 0 for t in traj) and len(u) == len(traj)


@pytest.mark.parametrize("case", ["no_pose", "bad_encoding", "size_mismatch"])
def test_bad_frames_are_skipped_and_counted(tmp_path, capsys, case):
    # The last frame has no pose of its own and none after it: too far past the newest pose to extrapolate.
    # (A frame between two poses takes the interpolated pose: tested in test_node_replay_agree.py.)
    kw = {"no_pose": dict(no_pose_frames=(4,)), "bad_encoding": dict(bad_encoding_frames=(1,)),
          "size_mismatch": dict(small_seg_frames=(3,))}[case]
    bag = write_scene(tmp_path, n_frames=5, **kw)
    rc = run_replay(bag, tmp_path / "out")
    err = capsys.readouterr().err
    assert rc == 0 and "Traceback" not in err
    m = json.loads((tmp_path / "out" / "metrics.json").read_text())
    assert m["frames"]["processed"] == 4
    skipped = m["frames"]["skipped"]
    assert sum(skipped.values()) == 1
    expected_key = {"no_pose": "pose_too_old_to_extrapolate", "bad_encoding": "bad_segmentation",
                    "size_mismatch": "size_mismatch"}[case]
    assert any(k.startswith(expected_key) for k in skipped), skipped


def _expect_clean_failure(capsys, rc: int, *words: str) -> None:
    captured = capsys.readouterr()
    assert rc != 0
    assert "Traceback" not in captured.err and "Traceback" not in captured.out
    line = captured.err.strip().splitlines()[-1]
    assert line.startswith("css_replay: error:")
    for w in words:
        assert w in line


def test_missing_topic_fails_cleanly(tmp_path, capsys):
    bag = write_scene(tmp_path, n_frames=2, drop_topics=("/pose",))
    _expect_clean_failure(capsys, run_replay(bag, tmp_path / "out"), "/pose")


def test_all_frames_unusable_fails_cleanly(tmp_path, capsys):
    bag = write_scene(tmp_path, n_frames=3, bad_encoding_frames=(0, 1, 2))
    _expect_clean_failure(capsys, run_replay(bag, tmp_path / "out"), "no usable frames")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_truncated_bag_fails_cleanly(tmp_path, capsys, storage):
    bag = write_scene(tmp_path, n_frames=3, storage=storage)
    data_file = next(p for p in bag.iterdir() if p.suffix in (".db3", ".mcap"))
    size = data_file.stat().st_size
    with open(data_file, "r+b") as f:
        f.truncate(size // 2)
    _expect_clean_failure(capsys, run_replay(bag, tmp_path / "out"))


def test_nonexistent_paths_fail_cleanly(tmp_path, capsys):
    _expect_clean_failure(capsys, run_replay(tmp_path / "nope", tmp_path / "out"), "not found")
    bag = write_scene(tmp_path, n_frames=2)
    rc = main([str(bag), "--model", str(tmp_path / "missing.ply"), "--quiet"])
    _expect_clean_failure(capsys, rc, "missing.ply")


def test_usage_error_returns_2(capsys):
    assert main(["--train-frames", "abc"]) == 2
    assert "Traceback" not in capsys.readouterr().err


def test_help_shows_example_command_lines_that_parse():
    """css_replay --help ends with example command lines like the other tools; each one is a command line the parser
    takes (its options exist and their values have the right types), and the console script prints them."""
    import shlex
    import subprocess
    import sys

    from css_ros.evaluation.cli import EXAMPLES, build_parser

    commands = [shlex.split(line.split("#")[0]) for line in EXAMPLES.splitlines() if line.startswith("  css_replay")]
    assert len(commands) >= 5 and any("--sensor-model" in c for c in commands)
    for argv in commands:
        args = build_parser().parse_args(argv[1:])
        assert argv[1:2] == [] or str(args.bag) == argv[1]
    r = subprocess.run([sys.executable, "-m", "css_ros.evaluation.cli", "--help"], capture_output=True, text=True,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.rstrip().endswith(EXAMPLES.rstrip()), r.stdout[-2000:]


def test_online_metrics_match_output_bag(clean_run):
    """css_online accuracy recomputed independently from /css_node/semantic and the input bag's GT."""
    _, out, bag = clean_run
    m = json.loads((out / "metrics.json").read_text())

    def images(path, topic):
        res = {}
        with AnyReader([path], default_typestore=STORE) as reader:
            conns = [c for c in reader.connections if c.topic == topic]
            for conn, _, raw in reader.messages(connections=conns):
                msg = reader.deserialize(raw, conn.msgtype)
                res[msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec] = msg.data.reshape(msg.height, msg.width)
        return res

    sem = images(out / "bag", "/css_node/semantic")
    gt = images(bag, "/segmentation_gt")
    assert sem.keys() == gt.keys()
    correct = sum(int(np.sum(sem[k] == gt[k])) for k in gt)
    total = sum(gt[k].size for k in gt)
    assert m["segmentation"]["css_online"]["pixel_accuracy"] == pytest.approx(correct / total)
