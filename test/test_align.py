"""css_align and the up direction: a known similarity recovered from noisy matched poses with outliers, the
refusals, a real INRIA cameras.json against robot poses given as a CSV or as a bag's Odometry with extrinsics."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from css_ros.demo.robot_demo import write_odometry
from css_ros.engine.camera import matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from css_ros.engine.similarity import Similarity
from css_ros.importers.align import AlignError, camera_up, fit_splat_to_map, up_alignment
from css_ros.importers.align_cli import main
from css_ros.importers.inria import load_inria
from css_ros.io.bag import BagWriter
from css_ros.io.params_file import read_params_file

REAL = Path("/work/shared/data/real-cameras/train")
TRUTH = Similarity.from_params([3.7, 12.0, -4.0, 1.5, *(np.array([0.3, -0.2, 0.6, 0.7]) / np.linalg.norm([0.3, -0.2, 0.6, 0.7]))])


def random_rotations(n: int, rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=(n, 4))
    return quaternion_xyzw_to_matrix(q / np.linalg.norm(q, axis=1, keepdims=True))


def angle_deg(R1: np.ndarray, R2: np.ndarray) -> float:
    return math.degrees(math.acos(np.clip((np.trace(R1.T @ R2) - 1) / 2, -1, 1)))


def test_known_similarity_recovered_from_noisy_poses_with_outliers() -> None:
    rng = np.random.default_rng(0)
    n = 60
    src = rng.uniform(-2, 2, (n, 3))
    R_src = random_rotations(n, rng)
    dst = TRUTH.apply(src) + rng.normal(0, 0.01, (n, 3))           # 1 cm noise on the robot side
    R_dst = TRUTH.R[None] @ R_src
    bad = rng.choice(n, 8, replace=False)
    dst[bad] += rng.uniform(-3, 3, (8, 3))                         # 8 wrong matches
    fit = fit_splat_to_map(src, dst, R_src, R_dst)
    sim = fit.similarity
    assert abs(sim.scale / TRUTH.scale - 1) < 0.01
    assert angle_deg(sim.R, TRUTH.R) < 0.5
    assert np.linalg.norm(sim.t - TRUTH.t) < 0.05
    assert not fit.inliers[bad].any() and fit.num_inliers >= n - 8 - 2
    assert fit.rms_m < 0.03 and fit.rot_median_deg < 0.5


def test_refusals_name_the_problem() -> None:
    rng = np.random.default_rng(1)
    with pytest.raises(AlignError, match="at least 3"):
        fit_splat_to_map(rng.normal(size=(2, 3)), rng.normal(size=(2, 3)))
    line = np.outer(np.linspace(0, 1, 10), [1.0, 2.0, 0.5])
    with pytest.raises(AlignError, match="one line"):
        fit_splat_to_map(line, TRUTH.apply(line))
    with pytest.raises(AlignError, match="residual"):
        fit_splat_to_map(rng.normal(size=(20, 3)), rng.normal(size=(20, 3)) * 5)
    src = rng.normal(size=(10, 3))
    R_src = random_rotations(10, rng)
    with pytest.raises(AlignError, match="rotation residual"):   # positions agree, orientations do not
        fit_splat_to_map(src, TRUTH.apply(src), R_src, random_rotations(10, rng))


def test_up_direction_from_the_cameras() -> None:
    rng = np.random.default_rng(2)
    # cameras of a y-down trainer frame: upright cameras (image y along the frame's +y) with random yaw
    R = []
    for yaw in rng.uniform(0, 2 * math.pi, 20):
        c, s = math.cos(yaw), math.sin(yaw)
        R.append(np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]))   # optical y = frame +y (down)
    R = np.array(R)
    np.testing.assert_allclose(camera_up(R), [0, -1, 0], atol=1e-12)
    sim = up_alignment(R)
    np.testing.assert_allclose(sim.R @ [0, -1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(up_alignment(R, "-y").R, sim.R, atol=1e-12)
    assert up_alignment(R, "none").is_identity
    with pytest.raises(AlignError, match="up-axis"):
        camera_up(random_rotations(50, rng))


@pytest.mark.skipif(not REAL.is_dir(), reason="real INRIA cameras not available")
def test_real_trainer_frame_is_made_z_up() -> None:
    """The real INRIA cameras (a hand-held capture): after up_alignment their mean up is +z and they look roughly
    level (the mean |elevation| of their viewing directions is small), as people hold cameras."""
    R = np.array([v.T_map_cam[:3, :3] for v in load_inria(REAL / "cameras.json")])
    sim = up_alignment(R)
    R_map = sim.R[None] @ R
    np.testing.assert_allclose(camera_up(R_map), [0, 0, 1], atol=1e-9)
    elevation = np.degrees(np.arcsin(np.abs(R_map[:, 2, 2])))
    assert np.mean(elevation) < 30.0, np.mean(elevation)


def _robot_side(views, rng, noise: float = 0.005):
    """The robot's optical poses of the trainer's images (TRUTH applied, noise added)."""
    out = []
    for v in views:
        p = TRUTH.apply(v.position) + rng.normal(0, noise, 3)
        q = matrix_to_quaternion_xyzw(TRUTH.R @ v.T_map_cam[:3, :3])
        out.append((v.stem, p, q))
    return out


@pytest.mark.skipif(not REAL.is_dir(), reason="real INRIA cameras not available")
def test_css_align_on_real_cameras_with_a_csv(tmp_path: Path, capsys) -> None:
    views = load_inria(REAL / "cameras.json")
    rng = np.random.default_rng(3)
    rows = _robot_side(views[::5], rng)
    csv = tmp_path / "robot.csv"
    lines = ["name,x,y,z,qx,qy,qz,qw"] + [f"{n}.jpg," + ",".join(f"{x:.9f}" for x in [*p, *q]) for n, p, q in rows]
    lines[3] = lines[3].split(",")[0] + ",99,99,99,0,0,0,1"   # one wrong pose
    csv.write_text("\n".join(lines) + "\n")
    out = tmp_path / "css_node.yaml"
    assert main([str(REAL / "cameras.json"), "--poses-csv", str(csv), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "inliers" in printed and "outliers:" in printed
    sim = Similarity.from_params(read_params_file(out)["splat_to_map"])
    assert abs(sim.scale / TRUTH.scale - 1) < 0.005 and angle_deg(sim.R, TRUTH.R) < 0.2
    assert np.linalg.norm(sim.t - TRUTH.t) < 0.05
    # too few matches: a one-line error, exit 1
    csv.write_text("\n".join(lines[:3]) + "\n")
    assert main([str(REAL / "cameras.json"), "--poses-csv", str(csv), "--out", str(out)]) == 1
    assert capsys.readouterr().err.startswith("css_align: error: only 2 matched camera(s)")


@pytest.mark.skipif(not REAL.is_dir(), reason="real INRIA cameras not available")
def test_css_align_from_a_bag_of_odometry_with_extrinsics(tmp_path: Path) -> None:
    """Odometry of base_link at 100 Hz; the images' stamps fall between samples; the camera sits on the base."""
    views = load_inria(REAL / "cameras.json")[:40]
    rng = np.random.default_rng(4)
    ext = Similarity.rigid_from_params([0.2, 0.0, 1.0, -0.5, 0.5, -0.5, 0.5])
    E_inv = ext.inverse()
    t0 = 1_700_000_000 * 10**9
    keys = []
    for i, (name, p, q) in enumerate(_robot_side(views, rng, noise=0.0)):
        base_p, base_q = E_inv.compose_pose(p, q)   # T_map_base = T_map_optical . T_optical_base
        keys.append((t0 + i * 10**9, base_p, base_q, name))
    from css_ros.io.pose_history import slerp_xyzw

    with BagWriter(tmp_path / "bag") as w:
        for (ta, pa, qa, _), (tb, pb, qb, _) in zip(keys, keys[1:] + [keys[-1]]):
            for k in range(100 if tb > ta else 1):   # 100 Hz along the straight segment to the next key
                u = k / 100
                write_odometry(w, "/odom", ta + k * 10**7, ta + k * 10**7, pa + u * (pb - pa), slerp_xyzw(qa, qb, u))
    stamps = tmp_path / "stamps.csv"
    stamps.write_text("".join(f"{name}.jpg,{(t + 3_000_000) * 1e-9 if i % 2 else t + 3_000_000}\n"
                              for i, (t, _, _, name) in enumerate(keys[:-1])))   # seconds and nanoseconds
    out = tmp_path / "a.yaml"
    assert main([str(REAL / "cameras.json"), "--bag", str(tmp_path / "bag"), "--stamps-csv", str(stamps),
                 "--pose-topic", "/odom", "--camera-extrinsics", *map(str, [0.2, 0.0, 1.0, -0.5, 0.5, -0.5, 0.5]),
                 "--out", str(out)]) == 0
    sim = Similarity.from_params(read_params_file(out)["splat_to_map"])
    assert abs(sim.scale / TRUTH.scale - 1) < 0.01 and angle_deg(sim.R, TRUTH.R) < 0.5


def test_css_align_refuses_duplicated_names_bad_bounds_huge_and_binary_files(tmp_path: Path, capsys) -> None:
    """Every image given twice (the second copy 5 m off), non-finite residual bounds, 1e308 coordinates and a binary
    file each get a one-line error naming the problem (exit 1), and nothing is written."""
    views = load_inria(REAL / "cameras.json")
    rows = _robot_side(views[::5], np.random.default_rng(3))
    good = [f"{n}.jpg," + ",".join(f"{x:.9f}" for x in [*p, *q]) for n, p, q in rows]
    twice = [f"{n}.jpg," + ",".join(f"{x:.9f}" for x in [p[0] + 5.0, p[1], p[2], *q]) for n, p, q in rows]
    csv = tmp_path / "robot.csv"
    out = tmp_path / "out.yaml"
    cams = str(REAL / "cameras.json")

    def refused(argv: list[str], message: str) -> None:
        assert main([cams, "--poses-csv", str(csv), "--out", str(out), *argv]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not out.exists()

    csv.write_text("\n".join(["name,x,y,z,qx,qy,qz,qw", *good, *twice]) + "\n")
    refused([], "already on line")
    csv.write_text("\n".join(["name,x,y,z,qx,qy,qz,qw", *good]) + "\n")
    refused(["--max-residual", "nan"], "--max-residual must be a finite number > 0")
    refused(["--max-rotation-residual", "inf"], "--max-rotation-residual must be a finite number > 0")
    huge = good[:]
    huge[2] = huge[2].split(",")[0] + ",1e308,0,0,0,0,0,1"
    csv.write_text("\n".join(["name,x,y,z,qx,qy,qz,qw", *huge]) + "\n")
    refused([], "not finite or beyond")
    csv.write_bytes(bytes(range(256)) * 8)
    refused([], "is not a text CSV file")
