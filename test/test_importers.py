"""css_import: pose importers against the real INRIA cameras, independent writers of each format (round trips),
label decoding, refusals, and an end-to-end import of demo frames evaluated by css_replay."""
from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image
from plyfile import PlyData

from css_ros.engine.camera import Camera, quaternion_xyzw_to_matrix
from css_ros.engine.classes import ClassSet
from css_ros.importers.cli import main
from css_ros.importers.colmap import load_colmap
from css_ros.importers.inria import load_inria
from css_ros.importers.labels import LabelDecoder, load_remap, read_confidence
from css_ros.importers.nerfstudio import load_nerfstudio
from css_ros.io.bag import InputBag
from css_ros.io.frames import decode_camera_info, decode_confidence, decode_image, decode_labels, decode_pose
from css_ros.io.topics import BAG_TOPICS

ROOT = Path(__file__).resolve().parents[1]
REAL = Path("/work/shared/data/real-cameras/train")
DEMO = ROOT / "bags" / "demo"


# ------------------------------------------------------------------------------------------ fixtures
def synthetic_cameras(n: int = 7, w: int = 64, h: int = 48) -> list[tuple[str, np.ndarray, np.ndarray]]:
    """(name, K (3, 3) in SPEC §2 pixel convention, T_map_cam (4, 4) OpenCV camera-to-world), varied poses."""
    rng = np.random.default_rng(3)
    out = []
    for i in range(n):
        q = rng.normal(size=4)
        T = np.eye(4)
        T[:3, :3] = quaternion_xyzw_to_matrix(q / np.linalg.norm(q))
        T[:3, 3] = rng.uniform(-5, 5, size=3)
        K = np.array([[50.0 + i, 0, 31.5 + 0.25 * i], [0, 52.0 + i, 23.5 - 0.5 * i], [0, 0, 1]])
        out.append((f"frame_{i:03d}.png", K, T))
    return out


def assert_views_equal(views, cams, w=64, h=48, centred=False):
    assert [v.name.split("/")[-1] for v in views] == [c[0] for c in cams]
    for v, (_, K, T) in zip(views, cams):
        np.testing.assert_allclose(v.T_map_cam, T, atol=1e-9, rtol=0)
        if centred:
            K = K.copy()
            K[0, 2], K[1, 2] = (w - 1) / 2, (h - 1) / 2
        np.testing.assert_allclose(v.K, K, atol=1e-9, rtol=0)
        assert (v.width, v.height) == (w, h)


# --------------------------------------------------------------- independent writers of each format
def write_inria(path: Path, cams, w=64, h=48) -> None:
    data = [{"id": i, "img_name": name, "width": w, "height": h, "position": T[:3, 3].tolist(),
             "rotation": T[:3, :3].tolist(), "fx": K[0, 0], "fy": K[1, 1]} for i, (name, K, T) in enumerate(cams)]
    path.write_text(json.dumps(data))


def write_nerfstudio(path: Path, cams, w=64, h=48, shared: dict | None = None) -> None:
    frames = []
    for name, K, T in cams:
        gl = T.copy()
        gl[:3, 1] *= -1  # OpenCV y down -> OpenGL y up
        gl[:3, 2] *= -1  # OpenCV z forward -> OpenGL z backward
        frames.append({"file_path": f"images/{name}", "transform_matrix": gl.tolist(),
                       "fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5})
    path.write_text(json.dumps({"w": w, "h": h, "camera_model": "OPENCV", **(shared or {}), "frames": frames}))


def _colmap_qt(T: np.ndarray) -> tuple[list[float], list[float]]:
    """World-to-camera (qvec w x y z, tvec) of a camera-to-world T, computed independently (trace method)."""
    R = T[:3, :3].T
    t = -R @ T[:3, 3]
    w = np.sqrt(max(1e-300, 1 + np.trace(R))) / 2
    if w > 0.1:
        q = [w, (R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w)]
    else:  # fall back to the largest diagonal pivot
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = np.sqrt(1 + R[i, i] - R[j, j] - R[k, k]) * 2
        v = np.zeros(3)
        v[i] = s / 4
        v[j] = (R[j, i] + R[i, j]) / s
        v[k] = (R[k, i] + R[i, k]) / s
        q = [(R[k, j] - R[j, k]) / s, *v]
    return list(map(float, q)), t.tolist()


def write_colmap_txt(folder: Path, cams, w=64, h=48) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    cl = ["# Camera list", "# CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    il = ["# Image list", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for i, (name, K, T) in enumerate(cams, 1):
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5]
        cl.append(f"{i} PINHOLE {w} {h} " + " ".join(repr(float(p)) for p in params))
        q, t = _colmap_qt(T)
        il.append(" ".join([str(i), *(repr(float(x)) for x in [*q, *t]), str(i), name]))
        il.append("" if i % 2 else "1.0 2.0 -1 3.0 4.0 7")  # empty and non-empty POINTS2D lines
    (folder / "cameras.txt").write_text("\n".join(cl) + "\n")
    (folder / "images.txt").write_text("\n".join(il) + "\n")


def write_colmap_bin(folder: Path, cams, w=64, h=48, model_id=1, extra_params=()) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    cb = struct.pack("<Q", len(cams))
    ib = struct.pack("<Q", len(cams))
    for i, (name, K, T) in enumerate(cams, 1):
        params = [K[0, 0], K[1, 1], K[0, 2] + 0.5, K[1, 2] + 0.5, *extra_params]
        cb += struct.pack("<iiQQ", i, model_id, w, h) + struct.pack(f"<{len(params)}d", *params)
        q, t = _colmap_qt(T)
        ib += struct.pack("<I4d3di", i, *q, *t, i) + name.encode() + b"\0"
        ib += struct.pack("<Q", 2) + struct.pack("<ddqddq", 1.0, 2.0, -1, 3.0, 4.0, 5)
    (folder / "cameras.bin").write_bytes(cb)
    (folder / "images.bin").write_bytes(ib)


# ------------------------------------------------------------------------------------ real cameras
def _inside_fraction(views, points: np.ndarray) -> np.ndarray:
    fr = []
    for v in views:
        cam = Camera(K=v.K, width=v.width, height=v.height, T_map_cam=v.T_map_cam)
        uv, z = cam.project(points)
        ok = (z > 0) & (uv[:, 0] >= -0.5) & (uv[:, 0] < v.width - 0.5) & (uv[:, 1] >= -0.5) & (uv[:, 1] < v.height - 0.5)
        fr.append(ok.mean())
    return np.array(fr)


@pytest.mark.skipif(not REAL.is_dir(), reason="real INRIA cameras not available")
def test_inria_real_cameras_see_the_trained_gaussians():
    views = load_inria(REAL / "cameras.json")
    assert len(views) == 301 and (views[0].width, views[0].height) == (979, 543)
    assert views[0].name == "00001.jpg"
    np.testing.assert_allclose(views[0].K[:2, 2], [489.0, 271.0])
    v = PlyData.read(str(REAL / "train-1000.ply"))["vertex"]
    pts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    inside = _inside_fraction(views, pts)
    # The trainer's convention: ~73 % of the Gaussians land in front of the camera inside the image on average.
    assert inside.mean() > 0.65
    assert np.mean(inside > 0.5) > 0.8
    # Reading `rotation` as world-to-camera (the classic mistake) loses most of them.
    wrong = [type(x)(name=x.name, K=x.K, width=x.width, height=x.height,
                     T_map_cam=np.block([[x.T_map_cam[:3, :3].T, x.T_map_cam[:3, 3:]], [np.zeros((1, 3)), 1]]))
             for x in views]
    assert _inside_fraction(wrong, pts).mean() < 0.3


# ------------------------------------------------------------------------------------- round trips
def test_inria_round_trip(tmp_path):
    cams = synthetic_cameras()
    write_inria(tmp_path / "cameras.json", cams)
    assert_views_equal(load_inria(tmp_path / "cameras.json"), cams, centred=True)


def test_nerfstudio_round_trip_per_frame_and_shared(tmp_path):
    cams = synthetic_cameras()
    write_nerfstudio(tmp_path / "transforms.json", cams)
    assert_views_equal(load_nerfstudio(tmp_path), cams)
    same = [(n, cams[0][1], T) for n, _, T in cams]
    K = cams[0][1]
    d = json.loads((tmp_path / "transforms.json").read_text())
    for f in d["frames"]:
        for k in ("fl_x", "fl_y", "cx", "cy"):
            del f[k]
    d.update({"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2] + 0.5, "cy": K[1, 2] + 0.5})
    (tmp_path / "transforms.json").write_text(json.dumps(d))
    assert_views_equal(load_nerfstudio(tmp_path / "transforms.json"), same)


@pytest.mark.parametrize("kind", ["txt", "bin"])
def test_colmap_round_trip(tmp_path, kind):
    cams = synthetic_cameras()
    (write_colmap_txt if kind == "txt" else write_colmap_bin)(tmp_path / "sparse", cams)
    assert_views_equal(load_colmap(tmp_path / "sparse"), cams)


def test_colmap_bin_declared_count_checked_against_size(tmp_path):
    cams = synthetic_cameras(2)
    write_colmap_bin(tmp_path / "s", cams)
    data = (tmp_path / "s" / "images.bin").read_bytes()
    (tmp_path / "s" / "images.bin").write_bytes(struct.pack("<Q", 10**15) + data[8:])
    with pytest.raises(Exception, match="declares 1000000000000000 images"):
        load_colmap(tmp_path / "s")
    (tmp_path / "s" / "images.bin").write_bytes(data[:-30])
    with pytest.raises(Exception, match="declares 2 2D points"):
        load_colmap(tmp_path / "s")


# --------------------------------------------------------------------------------------- refusals
def _label_dir(tmp_path: Path, cams, w=64, h=48) -> Path:
    d = tmp_path / "labels"
    d.mkdir()
    for name, _, _ in cams:
        Image.fromarray(np.zeros((h, w), np.uint8)).save(d / (Path(name).stem + ".png"))
    return d


def test_distortion_refused_unless_ignored(tmp_path, capsys):
    cams = synthetic_cameras(3)
    write_colmap_bin(tmp_path / "sparse", cams, model_id=4, extra_params=(0.1, 0.0, 0.0, 0.0))  # OPENCV
    labels = _label_dir(tmp_path, cams)
    model = DEMO / "model.ply"
    args = [str(tmp_path / "sparse"), "--model", str(model), "--labels", str(labels), "--num-classes", "3",
            "--out", str(tmp_path / "out"), "--quiet"]
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0
    assert err.startswith("css_import: error: ")
    assert "camera model OPENCV has lens distortion" in err and "--ignore-distortion" in err
    assert main(args + ["--ignore-distortion"]) == 0
    with InputBag(tmp_path / "out" / "bag") as bag:
        assert bag.topics()[BAG_TOPICS["segmentation"]][1] == 3
    # nerfstudio: a non-zero k1 is refused with the same advice
    write_nerfstudio(tmp_path / "transforms.json", cams, shared={"k1": -0.05})
    with pytest.raises(Exception, match=r"camera_model OPENCV with distortion k1=-0.05 .*--ignore-distortion"):
        load_nerfstudio(tmp_path / "transforms.json")
    assert len(load_nerfstudio(tmp_path / "transforms.json", ignore_distortion=True)) == 3
    write_nerfstudio(tmp_path / "transforms.json", cams, shared={"camera_model": "OPENCV_FISHEYE"})
    with pytest.raises(Exception, match="camera_model OPENCV_FISHEYE is not an undistorted pinhole"):
        load_nerfstudio(tmp_path / "transforms.json")


# --------------------------------------------------------------------------------------- labels
def test_colour_png_mapping_and_remap(tmp_path):
    classes = ClassSet(("a", "b", "c"), np.array([[255, 0, 0], [0, 255, 0], [0, 0, 255]], np.uint8))
    ids = np.array([[0, 1, 2], [2, 1, 0]])
    rgb = classes.palette[ids]
    Image.fromarray(rgb).save(tmp_path / "c.png")
    np.testing.assert_array_equal(LabelDecoder(palette=classes.palette).read(tmp_path / "c.png"), ids)
    rgb[0, 0] = (1, 2, 3)
    Image.fromarray(rgb).save(tmp_path / "u.png")
    with pytest.raises(Exception, match=r"1 colour\(s\) are no class colour .* \(1, 2, 3\)"):
        LabelDecoder(palette=classes.palette).read(tmp_path / "u.png")
    dec = LabelDecoder(palette=classes.palette, unknown_colors="ignore", ignore_label=255)
    got = dec.read(tmp_path / "u.png")
    assert got[0, 0] == 255 and dec.unknown_color_pixels == 1
    (tmp_path / "r.yaml").write_text("remap:\n  0: 255\n  2: 1\n")
    remap = load_remap(tmp_path / "r.yaml")
    assert remap == {0: 255, 2: 1}
    np.testing.assert_array_equal(LabelDecoder(palette=classes.palette, remap=remap).read(tmp_path / "c.png"),
                                  [[255, 1, 1], [1, 1, 255]])
    grey = np.array([[0, 7, 300]], np.uint16)
    Image.fromarray(grey).save(tmp_path / "g16.png")
    np.testing.assert_array_equal(LabelDecoder(remap={7: 1}).read(tmp_path / "g16.png"), [[0, 1, 300]])
    (tmp_path / "bad.yaml").write_text("remap:\n  a: 1\n")
    with pytest.raises(Exception, match="is not a pair of ids"):
        load_remap(tmp_path / "bad.yaml")


def test_confidence_npy_and_png(tmp_path):
    c = np.array([[0.0, 0.5], [1.0, 0.25]], np.float32)
    np.save(tmp_path / "c.npy", c)
    np.testing.assert_array_equal(read_confidence(tmp_path / "c.npy"), c)
    np.save(tmp_path / "o.npy", np.array([[1.5]], np.float32))
    with pytest.raises(Exception, match=r"must lie in \[0, 1\]"):
        read_confidence(tmp_path / "o.npy")
    np.save(tmp_path / "p.npy", np.array([{"a": 1}], dtype=object), allow_pickle=True)
    with pytest.raises(Exception, match="cannot read confidence"):
        read_confidence(tmp_path / "p.npy")
    Image.fromarray(np.array([[0, 65535]], np.uint16)).save(tmp_path / "c16.png")
    np.testing.assert_allclose(read_confidence(tmp_path / "c16.png"), [[0.0, 1.0]])


# ------------------------------------------------------------------------------------- end to end
N_E2E = 10


def _export_demo_frames(tmp_path: Path) -> Path:
    """Write the first N demo frames as a COLMAP txt model + PNG/npy folders (independent of the importer)."""
    topics = {BAG_TOPICS[k]: k for k in ("camera_info", "pose", "image", "segmentation", "confidence", "gt")}
    frames: dict[int, dict] = {}
    with InputBag(DEMO / "bag") as bag:
        for m in bag.messages(list(topics)):
            kind = topics[m.topic]
            st = m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec
            if len(frames) >= N_E2E and st not in frames:
                break
            frames.setdefault(st, {})[kind] = m.msg
    src = tmp_path / "src"
    for sub in ("images", "labels", "gt", "conf"):
        (src / sub).mkdir(parents=True)
    cams = []
    for i, (st, f) in enumerate(sorted(frames.items())[:N_E2E]):
        intr = decode_camera_info(f["camera_info"])
        pos, quat = decode_pose(f["pose"])
        T = np.eye(4)
        T[:3, :3] = quaternion_xyzw_to_matrix(quat)
        T[:3, 3] = pos
        name = f"{i:05d}.png"
        cams.append((name, intr.K, T))
        Image.fromarray(decode_image(f["image"])).save(src / "images" / name)
        Image.fromarray(decode_labels(f["segmentation"]).astype(np.uint8)).save(src / "labels" / name)
        Image.fromarray(decode_labels(f["gt"]).astype(np.uint8)).save(src / "gt" / name)
        np.save(src / "conf" / f"{i:05d}.npy", decode_confidence(f["confidence"])[0])
    w, h = intr.width, intr.height
    write_colmap_txt(src / "sparse", cams, w, h)
    return src


@pytest.mark.skipif(not (DEMO / "bag").is_dir(), reason="demo bag not available")
def test_end_to_end_import_then_replay_matches_demo(tmp_path, capsys):
    from css_ros.evaluation.cli import main as replay

    src = _export_demo_frames(tmp_path)
    out = tmp_path / "imported"
    assert main([str(src / "sparse"), "--model", str(DEMO / "model.ply"), "--classes", str(DEMO / "classes.yaml"),
                 "--labels", str(src / "labels"), "--gt", str(src / "gt"), "--confidence", str(src / "conf"),
                 "--images", str(src / "images"), "--rate", "5", "--out", str(out), "--quiet"]) == 0
    stdout = capsys.readouterr().out
    assert f"imported {N_E2E} frames of {N_E2E} cameras (mono8 labels)" in stdout
    assert (out / "model.ply").is_file() and (out / "classes.yaml").is_file()
    # the demo's frame is already z-up: the up found from the cameras is +z to within their mean pitch/roll
    from css_ros.engine.similarity import Similarity
    from css_ros.io.params_file import read_params_file

    up = Similarity.from_params(read_params_file(out / "css_node.yaml")["splat_to_map"])
    assert up.scale == 1.0 and np.degrees(np.arccos(np.clip(up.R[2, 2], -1, 1))) < 15.0
    with InputBag(out / "bag") as bag:
        topics = bag.topics()
        imported = {k: t for k, t in BAG_TOPICS.items() if k not in ("depth", "gt_changed")}  # no such inputs
        assert {t: n for t, (_, n) in topics.items()} == {t: N_E2E for t in imported.values()}
        stamps = [m.log_time_ns for m in bag.messages([BAG_TOPICS["pose"]])]
        assert np.all(np.diff(stamps) == 200_000_000)  # --rate 5 Hz
    common = ["--no-output-bag", "--quiet", "--examples", "0"]
    assert replay([str(out / "bag"), "--out", str(tmp_path / "r_imp"), *common]) == 0
    assert replay([str(DEMO / "bag"), "--max-frames", str(N_E2E), "--out", str(tmp_path / "r_demo"), *common]) == 0
    a = json.loads((tmp_path / "r_imp" / "metrics.json").read_text())
    b = json.loads((tmp_path / "r_demo" / "metrics.json").read_text())
    assert a["frames"]["processed"] == b["frames"]["processed"] == N_E2E
    for key in ("input", "css"):
        assert abs(a["segmentation"][key]["miou"] - b["segmentation"][key]["miou"]) <= 1e-6
        assert a["segmentation"][key]["num_pixels"] == b["segmentation"][key]["num_pixels"]


def test_label_size_mismatch_and_missing_gt_are_errors(tmp_path, capsys):
    cams = synthetic_cameras(2)
    write_inria(tmp_path / "cameras.json", cams)
    labels = _label_dir(tmp_path, cams, w=32, h=24)  # half size: intrinsics would not match
    args = [str(tmp_path / "cameras.json"), "--model", str(DEMO / "model.ply"), "--labels", str(labels),
            "--num-classes", "3", "--out", str(tmp_path / "out"), "--quiet"]
    assert main(args) == 1
    assert capsys.readouterr().err.strip() == (
        f"css_import: error: {labels / 'frame_000.png'}: image is 32x24 but camera frame_000.png is 64x48 "
        "(images must have the calibrated size)")
    (tmp_path / "gt").mkdir()
    assert main(args + ["--gt", str(tmp_path / "gt")]) == 1
    assert capsys.readouterr().err.strip() == (
        "css_import: error: no gt file for image frame_000.png (looked for frame_000.* in the gt folder)")
    assert main(args + ["--classes", str(DEMO / "classes.yaml")]) == 1
    assert "--num-classes 3 contradicts" in capsys.readouterr().err


def test_palette_png_index_is_the_class_id(tmp_path):
    img = Image.fromarray(np.array([[0, 1], [2, 255]], np.uint8), mode="P")
    img.putpalette([0, 0, 0, 10, 10, 10, 20, 20, 20] + [0] * (253 * 3))
    img.save(tmp_path / "p.png")
    np.testing.assert_array_equal(LabelDecoder().read(tmp_path / "p.png"), [[0, 1], [2, 255]])


@pytest.mark.skipif(not (DEMO / "bag").is_dir(), reason="demo bag not available")
def test_import_with_poses_on_tf_replays_like_the_pose_topic(tmp_path, capsys):
    """css_import --poses-on tf writes the camera poses as map -> camera_optical on /tf (no /pose); css_replay takes
    them from TF and gets the same frames, poses and metrics as from the pose-topic import."""
    from css_ros.evaluation.cli import main as replay
    from css_ros.io.topics import TF_TOPIC

    src = _export_demo_frames(tmp_path)
    common = [str(src / "sparse"), "--model", str(DEMO / "model.ply"), "--classes", str(DEMO / "classes.yaml"),
              "--labels", str(src / "labels"), "--gt", str(src / "gt"), "--rate", "5", "--quiet"]
    assert main([*common, "--out", str(tmp_path / "topic")]) == 0
    assert main([*common, "--poses-on", "tf", "--out", str(tmp_path / "tf")]) == 0
    with InputBag(tmp_path / "tf" / "bag") as bag:
        topics = bag.topics()
        assert BAG_TOPICS["pose"] not in topics and topics[TF_TOPIC][1] == N_E2E
    with InputBag(tmp_path / "topic" / "bag") as a, InputBag(tmp_path / "tf" / "bag") as b:
        poses = [m.msg.pose for m in a.messages([BAG_TOPICS["pose"]])]
        tfs = [m.msg.transforms[0] for m in b.messages([TF_TOPIC])]
        assert [t.header.frame_id for t in tfs] == ["map"] * N_E2E
        for p, t in zip(poses, tfs):
            assert (p.position.x, p.position.y, p.position.z) == (t.transform.translation.x,
                                                                  t.transform.translation.y,
                                                                  t.transform.translation.z)
            assert (p.orientation.x, p.orientation.w) == (t.transform.rotation.x, t.transform.rotation.w)
    args = ["--no-output-bag", "--quiet", "--examples", "0"]
    assert replay([str(tmp_path / "topic" / "bag"), "--out", str(tmp_path / "r_topic"), *args]) == 0
    assert replay([str(tmp_path / "tf" / "bag"), "--out", str(tmp_path / "r_tf"), *args]) == 0
    a = json.loads((tmp_path / "r_topic" / "metrics.json").read_text())
    b = json.loads((tmp_path / "r_tf" / "metrics.json").read_text())
    assert a["frames"]["processed"] == b["frames"]["processed"] == N_E2E
    for key in ("input", "css"):
        assert a["segmentation"][key]["miou"] == b["segmentation"][key]["miou"]
