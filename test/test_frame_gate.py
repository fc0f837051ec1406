"""The shared frame gate (css_ros/io/frame_gate.py) with robot-like inputs, against closed forms.

Robot timing (odometry at its own rate between the camera stamps, a late segmentation, jitter), pose message
types with camera extrinsics, the splat in its own frame (splat_to_map), several cameras, a segmentation at its
own resolution, and bad pose streams. No DDS here: the node-level checks are in test_node_robot.py.
"""
from __future__ import annotations

import math
from types import SimpleNamespace as NS

import numpy as np
import pytest

from css_ros.engine.camera import Camera, matrix_to_quaternion_xyzw, quaternion_xyzw_to_matrix
from css_ros.engine.gaussians import GaussianModel
from css_ros.engine.semantic_map import SemanticMap
from css_ros.engine.similarity import Similarity
from css_ros.io.frame_gate import FrameGate, GateConfig, intrinsics_for
from css_ros.io.frames import Intrinsics
from css_ros.io.messages import array_to_image_fields, ns_to_sec_nanosec
from css_ros.io.pose_history import PosePolicy

W, H = 32, 24
K = np.array([[30.0, 0.0, (W - 1) / 2], [0.0, 30.0, (H - 1) / 2], [0.0, 0.0, 1.0]])
T0 = 1_000 * 10**9
#: optical frame of a camera looking forward from a REP-103 base (x fwd, y left, z up), 20 cm ahead, 50 cm up
EXTRINSICS = [0.2, 0.0, 0.5, -0.5, 0.5, -0.5, 0.5]


def header(stamp_ns: int, frame_id: str = "map") -> NS:
    sec, nanosec = ns_to_sec_nanosec(stamp_ns)
    return NS(stamp=NS(sec=sec, nanosec=nanosec), frame_id=frame_id)


def pose_obj(p: np.ndarray, q: np.ndarray) -> NS:
    return NS(position=NS(x=p[0], y=p[1], z=p[2]), orientation=NS(x=q[0], y=q[1], z=q[2], w=q[3]))


def pose_message(kind: str, stamp_ns: int, p: np.ndarray, q: np.ndarray) -> NS:
    """Duck-typed PoseStamped / PoseWithCovarianceStamped / Odometry."""
    if kind == "pose_stamped":
        return NS(header=header(stamp_ns), pose=pose_obj(p, q))
    inner = NS(pose=pose_obj(p, q), covariance=[0.0] * 36)
    if kind == "odometry":
        return NS(header=header(stamp_ns, "odom"), child_frame_id="base_link", pose=inner, twist=None)
    return NS(header=header(stamp_ns), pose=inner)


def image(stamp_ns: int, array: np.ndarray, encoding: str) -> NS:
    f = array_to_image_fields(array, encoding)
    f["data"] = f["data"].tobytes()
    return NS(header=header(stamp_ns, "cam"), **f)


def camera_info(w: int = W, h: int = H) -> NS:
    return NS(header=header(0, "cam"), width=w, height=h, k=list(K.ravel()))


def base_truth(t: float) -> tuple[np.ndarray, np.ndarray]:
    """The base's pose at t [s]: 1 m/s along a straight line, yawing at 45 deg/s (exact under interpolation)."""
    yaw = math.radians(45.0) * t
    return np.array([1.0 * t, 0.3 - 0.2 * t, 0.0]), np.array([0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)])


class Recorder:
    def __init__(self) -> None:
        self.warnings: dict[str, int] = {}
        self.counts: dict[str, int] = {}

    def warn(self, topic: str, reason: str, detail: str = "", dropped: bool = True) -> None:
        key = f"{topic}: {reason}"
        self.warnings[key] = self.warnings.get(key, 0) + 1

    def count(self, key: str, n: int = 1) -> None:
        self.counts[key] = self.counts.get(key, 0) + n


def gate_for(rec: Recorder, **kw) -> FrameGate:
    cfg = GateConfig(**kw)
    return FrameGate(cfg, rec.warn, rec.count, lambda cam: False)


def robot_stream(n_frames: int = 40, pose_rate: float = 200.0, seg_latency: float = 0.3, fps: float = 5.0,
                 jitter: float = 0.01, pose_kind: str = "pose_stamped", seed: int = 0) -> tuple[list, list]:
    """(arrival time [s], kind, message) sorted by arrival, and the frame stamps.

    Poses at ``pose_rate`` sampled between the camera stamps (offset half a period), each arriving 1-3 ms after
    its stamp; camera_info at the camera stamp; the segmentation ``seg_latency`` s (+ up to ``jitter``) late.
    """
    rng = np.random.default_rng(seed)
    events = []
    duration = n_frames / fps + seg_latency + 1.0
    for k in range(int(duration * pose_rate)):
        t = 0.5 / pose_rate + k / pose_rate
        p, q = base_truth(t)
        events.append((t + rng.uniform(0.001, 0.003), "pose", pose_message(pose_kind, T0 + int(round(t * 1e9)), p, q)))
    stamps = []
    for i in range(n_frames):
        t = 0.1 + i / fps
        s = T0 + int(round(t * 1e9))
        stamps.append(s)
        events.append((t, "camera_info", camera_info()))
        events.append((t + seg_latency + rng.uniform(0, jitter), "segmentation",
                       image(s, np.full((H, W), 1, np.uint8), "mono8")))
    events.sort(key=lambda e: e[0])
    return events, stamps


def feed(gate: FrameGate, events: list, cam: int = 0) -> list:
    frames = []
    for t, kind, msg in events:
        frames += gate.poll(t)
        if kind == "pose":
            frames += gate.on_pose(msg, t)
        elif kind == "camera_info":
            gate.on_camera_info(cam, msg)
        elif kind == "segmentation":
            frames += gate.on_segmentation(cam, msg, t)
    return frames + gate.flush()


def optical_truth(stamp_ns: int, extrinsics: list[float] | None) -> tuple[np.ndarray, np.ndarray]:
    p, q = base_truth((stamp_ns - T0) * 1e-9)
    if extrinsics is None:
        return p, q
    T = np.eye(4)
    T[:3, :3] = quaternion_xyzw_to_matrix(q)
    T[:3, 3] = p
    E = Similarity.rigid_from_params(extrinsics).matrix()
    M = T @ E
    return M[:3, 3], matrix_to_quaternion_xyzw(M[:3, :3])


def angle_deg(q0: np.ndarray, q1: np.ndarray) -> float:
    if float(np.dot(q0, q1)) < 0:
        q1 = -q1
    return math.degrees(4.0 * math.atan2(np.linalg.norm(q0 - q1), np.linalg.norm(q0 + q1)))


# ------------------------------------------------------------------ robot timing with default parameters
@pytest.mark.parametrize("pose_rate, latency", [(200.0, 0.3), (30.0, 0.3), (100.0, 0.05), (200.0, 1.2)])
def test_robot_stream_with_defaults_maps_every_frame_with_the_interpolated_pose(pose_rate, latency):
    rec = Recorder()
    gate = gate_for(rec)
    events, stamps = robot_stream(pose_rate=pose_rate, seg_latency=latency)
    frames = feed(gate, events)
    assert [f.stamp_ns for f in frames] == stamps, rec.warnings
    for f in frames:
        p, q = optical_truth(f.stamp_ns, None)
        assert np.linalg.norm(f.position_map - p) < 1e-3 and angle_deg(f.quat_map, q) < 0.01
        assert f.pose_how == "interpolated"
        # No splat_to_map: the engine's camera is the map pose itself.
        np.testing.assert_allclose(f.camera.position, f.position_map, atol=1e-12)


@pytest.mark.parametrize("pose_kind", ["odometry", "pose_with_covariance"])
def test_pose_types_and_extrinsics_give_the_optical_frame_of_the_camera(pose_kind):
    rec = Recorder()
    gate = gate_for(rec, pose_type=pose_kind, extrinsics=(Similarity.rigid_from_params(EXTRINSICS),))
    events, stamps = robot_stream(n_frames=10, pose_kind=pose_kind)
    frames = feed(gate, events)
    assert len(frames) == 10, rec.warnings
    for f in frames:
        p, q = optical_truth(f.stamp_ns, EXTRINSICS)
        assert np.linalg.norm(f.position_map - p) < 1e-3 and angle_deg(f.quat_map, q) < 0.01
        # the optical axis (z) of a forward camera is the base's heading
        yaw = math.radians(45.0) * (f.stamp_ns - T0) * 1e-9
        np.testing.assert_allclose(quaternion_xyzw_to_matrix(f.quat_map)[:, 2], [math.cos(yaw), math.sin(yaw), 0],
                                   atol=1e-6)


def test_frame_waits_pose_wait_then_extrapolates_or_drops():
    rec = Recorder()
    gate = gate_for(rec, pose_policy=PosePolicy(wait=0.5, max_extrapolation=0.02))
    gate.on_camera_info(0, camera_info())
    p, q = base_truth(0.0)
    gate.on_pose(pose_message("pose_stamped", T0 - 10_000_000, p, q), 0.0)
    gate.on_pose(pose_message("pose_stamped", T0, p, q), 0.0)
    assert gate.on_segmentation(0, image(T0 + 10_000_000, np.ones((H, W), np.uint8), "mono8"), 0.0) == []
    assert gate.poll(0.49) == []                       # still waiting for a later pose
    (f,) = gate.poll(0.5)                              # 10 ms past the newest pose: extrapolated
    assert f.pose_how == "extrapolated"
    assert gate.on_segmentation(0, image(T0 + 100_000_000, np.ones((H, W), np.uint8), "mono8"), 1.0) == []
    assert gate.poll(1.6) == [] and rec.warnings["segmentation: pose too old to extrapolate"] == 1


# ------------------------------------------------------------------ the splat in its own frame
def _scene(seed: int = 0, n: int = 300) -> GaussianModel:
    rng = np.random.default_rng(seed)
    means = np.c_[rng.uniform(-1.5, 1.5, n), rng.uniform(-1.0, 1.0, n), rng.uniform(2.5, 3.5, n)]
    q = rng.normal(size=(n, 4))
    return GaussianModel.from_activated(means, rng.uniform(0.05, 0.2, (n, 3)), q / np.linalg.norm(q, axis=1)[:, None],
                                        rng.uniform(0.3, 0.95, n), rng.uniform(0, 1, (n, 3)))


def test_splat_in_its_own_scaled_rotated_frame_renders_as_the_map_splat():
    """The splat moved into a scaled, rotated frame plus splat_to_map gives the renders of the original."""
    map_model = _scene()
    q = np.array([0.2, -0.5, 0.3, 0.8])
    to_map = Similarity.from_params([0.37, 1.0, -2.0, 0.5, *(q / np.linalg.norm(q))])
    splat_model = to_map.inverse().transform_model(map_model)
    rec = Recorder()
    gate = gate_for(rec, splat_to_map=to_map)
    gate.on_camera_info(0, camera_info())
    C = 3
    ref = SemanticMap(map_model, num_classes=C)
    moved = SemanticMap(splat_model, num_classes=C)
    rng = np.random.default_rng(1)
    for i in range(4):
        p = np.array([0.2 * i - 0.3, 0.1 * i, 0.0])
        q = np.array([0.05 * i, -0.03 * i, 0.0, 1.0])
        q /= np.linalg.norm(q)
        s = T0 + i * 100_000_000
        gate.on_pose(pose_message("pose_stamped", s, p, q), 0.0)
        labels = rng.integers(0, C, (H, W)).astype(np.uint8)
        (f,) = gate.on_segmentation(0, image(s, labels, "mono8"), 0.0)
        cam_map = Camera.from_pose(K, W, H, p, q)
        v_ref = ref.observe(cam_map, labels.astype(np.int32))
        v_moved = moved.observe(f.camera, f.labels)
        np.testing.assert_allclose(f.position_map, p, atol=1e-12)
        for a, b in ((v_ref.expectation, v_moved.expectation), (v_ref.variance, v_moved.variance)):
            np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-7)
        np.testing.assert_allclose([v_moved.u_var, v_moved.u_exp], [v_ref.u_var, v_ref.u_exp], rtol=1e-4)
    np.testing.assert_allclose(moved.concentrations, ref.concentrations, rtol=1e-5, atol=1e-9)  # float32 means
    # Requests in the map frame land where they should in the splat frame.
    pts = rng.normal(size=(5, 3))
    np.testing.assert_allclose(to_map.apply(gate.map_points_to_splat(pts)), pts, atol=1e-12)


# ------------------------------------------------------------------ several cameras
def test_two_cameras_share_the_pose_stream_with_their_own_extrinsics_and_intrinsics():
    left = [0.0, 0.1, 0.5, *matrix_to_quaternion_xyzw(
        quaternion_xyzw_to_matrix([0, 0, math.sin(math.pi / 4), math.cos(math.pi / 4)])
        @ quaternion_xyzw_to_matrix([-0.5, 0.5, -0.5, 0.5]))]
    rec = Recorder()
    gate = gate_for(rec, cameras=("front", "left"),
                    extrinsics=(Similarity.rigid_from_params(EXTRINSICS), Similarity.rigid_from_params(left)))
    assert gate.topic(1, "segmentation") == "left/segmentation" and gate.topic(1, "pose") == "pose"
    gate.on_camera_info(0, camera_info())
    gate.on_camera_info(1, camera_info(W // 2, H // 2))
    events, stamps = robot_stream(n_frames=6)
    out = []
    for t, kind, msg in events:
        if kind == "pose":
            out += gate.on_pose(msg, t)
        elif kind == "segmentation":
            out += gate.on_segmentation(0, msg, t)
            s = msg.header.stamp.sec * 10**9 + msg.header.stamp.nanosec
            out += gate.on_segmentation(1, image(s, np.ones((H // 2, W // 2), np.uint8), "mono8"), t)
    out += gate.flush()
    assert sorted((f.camera_index, f.stamp_ns) for f in out) == sorted(
        [(0, s) for s in stamps] + [(1, s) for s in stamps])
    for f in out:
        ext = EXTRINSICS if f.camera_index == 0 else left
        p, q = optical_truth(f.stamp_ns, ext)
        assert np.linalg.norm(f.position_map - p) < 1e-3 and angle_deg(f.quat_map, q) < 0.01
        assert (f.camera.width, f.camera.height) == ((W, H) if f.camera_index == 0 else (W // 2, H // 2))
    assert rec.counts["camera[left].frames"] == 6 and rec.counts["camera[front].frames"] == 6


def test_a_camera_without_camera_info_does_not_stop_the_other():
    rec = Recorder()
    gate = gate_for(rec, cameras=("front", "back"), extrinsics=(None, None))
    gate.on_camera_info(0, camera_info())
    events, stamps = robot_stream(n_frames=5)
    out = []
    for t, kind, msg in events:
        if kind == "pose":
            out += gate.on_pose(msg, t)
        elif kind == "segmentation":
            out += gate.on_segmentation(0, msg, t) + gate.on_segmentation(1, msg, t)
    out += gate.flush()
    assert [f.stamp_ns for f in out if f.camera_index == 0] == stamps
    assert not [f for f in out if f.camera_index == 1]
    assert rec.warnings["back/segmentation: no camera_info received yet"] == 5


# ------------------------------------------------------------------ segmentation at its own resolution
@pytest.mark.parametrize("factor", [2, 4])
def test_segmentation_at_a_fraction_of_the_camera_resolution(factor):
    info = Intrinsics(K.copy(), W, H)
    intr = intrinsics_for((H // factor, W // factor), info)
    full = Camera(K=K, width=W, height=H, T_map_cam=np.eye(4))
    low = Camera(K=intr.K, width=intr.width, height=intr.height, T_map_cam=np.eye(4))
    pts = np.random.default_rng(2).uniform([-1, -1, 2], [1, 1, 4], (50, 3))
    uv_full, _ = full.project(pts)
    uv_low, _ = low.project(pts)
    # the same ray hits the same place of the image: pixel centres at integers on both grids
    np.testing.assert_allclose(uv_low, (uv_full + 0.5) / factor - 0.5, atol=1e-9)
    # against a render at full resolution: the low-resolution labels are the full ones at the same places
    model = _scene(3, 600)
    smap = SemanticMap(model, num_classes=3)
    cam = Camera.from_pose(K, W, H, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0])
    labels = (np.arange(W)[None, :] * 3 // W).repeat(H, 0).astype(np.int32)
    smap.update(cam, labels)
    lab_full = smap.render(cam).labels
    lab_low = smap.render(Camera.from_pose(intr.K, intr.width, intr.height, [0.0, 0.0, 0.0],
                                           [0.0, 0.0, 0.0, 1.0])).labels
    y = np.clip(((np.arange(H // factor) + 0.5) * factor).astype(int), 0, H - 1)
    x = np.clip(((np.arange(W // factor) + 0.5) * factor).astype(int), 0, W - 1)
    agree = np.mean(lab_low == lab_full[y[:, None], x[None, :]])
    assert agree >= 0.9, agree


def test_segmentation_of_another_aspect_ratio_refused():
    rec = Recorder()
    gate = gate_for(rec)
    gate.on_camera_info(0, camera_info())
    gate.on_pose(pose_message("pose_stamped", T0, *base_truth(0.0)), 0.0)
    assert gate.on_segmentation(0, image(T0, np.ones((H // 2, W), np.uint8), "mono8"), 0.0) == []
    assert rec.warnings["segmentation: size mismatch with camera_info"] == 1


# ------------------------------------------------------------------ bad pose streams
def test_bad_pose_samples_are_counted_and_the_frames_still_map():
    rec = Recorder()
    gate = gate_for(rec)
    gate.on_camera_info(0, camera_info())
    t = 0.0
    good = [T0 + k * 10_000_000 for k in range(30)]
    for k, s in enumerate(good):
        p, q = base_truth((s - T0) * 1e-9)
        gate.on_pose(pose_message("pose_stamped", s, p, q), t)
        if k % 5 == 0:
            gate.on_pose(pose_message("pose_stamped", s, p, q), t)                       # repeated stamp
            gate.on_pose(pose_message("pose_stamped", s + 1, [np.nan, 0, 0], q), t)      # NaN
            gate.on_pose(pose_message("pose_stamped", s + 2, p, 3 * q), t)               # non-unit quaternion
        if k % 7 == 3:
            gate.on_pose(pose_message("pose_stamped", s - 5_000_000, *base_truth((s - T0) * 1e-9 - 0.005)), t)
    frames = gate.on_segmentation(0, image(good[15] + 3_000_000, np.ones((H, W), np.uint8), "mono8"), t)
    assert len(frames) == 1
    p, q = optical_truth(frames[0].stamp_ns, None)
    assert np.linalg.norm(frames[0].position_map - p) < 1e-3
    assert rec.warnings["pose: repeated stamp"] == 6
    assert rec.warnings["pose: invalid pose"] == 12
    assert rec.warnings["pose: stamp out of order"] >= 4


def test_pose_gap_is_not_interpolated_across():
    rec = Recorder()
    gate = gate_for(rec)
    gate.on_camera_info(0, camera_info())
    gate.on_pose(pose_message("pose_stamped", T0, *base_truth(0.0)), 0.0)
    gate.on_pose(pose_message("pose_stamped", T0 + 3 * 10**9, *base_truth(3.0)), 0.0)   # relocalised 3 s later
    assert gate.on_segmentation(0, image(T0 + 10**9, np.ones((H, W), np.uint8), "mono8"), 0.0) == []
    assert rec.warnings["segmentation: pose gap"] == 1


def test_a_1khz_pose_stream_keeps_memory_bounded():
    rec = Recorder()
    gate = gate_for(rec)
    q = np.array([0.0, 0.0, 0.0, 1.0])
    for k in range(60_000):   # 60 s at 1 kHz
        gate.on_pose(pose_message("pose_stamped", T0 + k * 1_000_000, np.array([k * 1e-3, 0.0, 0.0]), q), k * 1e-3)
    h = gate.histories[0]
    assert len(h) <= 10_000 * 1.2 + 1 and h.newest_ns - h.oldest_ns <= 12 * 10**9
    assert rec.counts["pose_samples"] == 60_000 and not rec.warnings


def test_unknown_pose_type_refused():
    with pytest.raises(ValueError, match="pose_type"):
        gate_for(Recorder(), pose_type="tf")


def test_pose_per_camera_keeps_one_history_per_camera():
    rec = Recorder()
    gate = gate_for(rec, cameras=("a", "b"), extrinsics=(None, None), pose_per_camera=True)
    assert gate.topic(0, "pose") == "a/pose" and gate.topic(1, "pose") == "b/pose"
    for c in (0, 1):
        gate.on_camera_info(c, camera_info())
    shift = np.array([0.0, 5.0, 0.0])
    for k in range(3):
        p, q = base_truth(0.1 * k)
        gate.on_pose(pose_message("pose_stamped", T0 + k * 100_000_000, p, q), 0.0, cam=0)
        gate.on_pose(pose_message("pose_stamped", T0 + k * 100_000_000, p + shift, q), 0.0, cam=1)
    s = T0 + 150_000_000
    (fa,) = gate.on_segmentation(0, image(s, np.ones((H, W), np.uint8), "mono8"), 0.0)
    (fb,) = gate.on_segmentation(1, image(s, np.ones((H, W), np.uint8), "mono8"), 0.0)
    np.testing.assert_allclose(fb.position_map - fa.position_map, shift, atol=1e-12)


def test_candidate_poses_take_camera_0_extrinsics_and_go_into_the_splat_frame():
    to_map = Similarity.from_params([2.0, 1.0, 2.0, 3.0, 0.0, 0.0, math.sin(0.4), math.cos(0.4)])
    ext = Similarity.rigid_from_params(EXTRINSICS)
    gate = gate_for(Recorder(), extrinsics=(ext,), splat_to_map=to_map)
    rng = np.random.default_rng(5)
    pos = rng.normal(size=(4, 3))
    quats = rng.normal(size=(4, 4))
    quats /= np.linalg.norm(quats, axis=1, keepdims=True)
    quats[2] = np.nan                                   # an invalid candidate stays invalid
    p_s, q_s = gate.map_poses_to_splat(pos, quats)
    for i in (0, 1, 3):
        p_opt, q_opt = ext.compose_pose(pos[i], quats[i])   # the camera of a robot standing at the candidate
        back_p, back_q = to_map.apply_pose(p_s[i], q_s[i])
        np.testing.assert_allclose(back_p, p_opt, atol=1e-12)
        assert angle_deg(back_q, q_opt) < 1e-9
    assert np.all(np.isnan(q_s[2]))


# ------------------------------------------------------------------ frames whose pose is not the interpolation
def test_a_frame_whose_bracketing_pose_sample_never_arrived_is_flagged():
    """A 200 Hz stream numbered 1, 2, ... (publication sequence numbers) with samples lost before the gate: a frame
    whose two published samples around its stamp both arrived gets pose_flags 0 and their interpolation; one whose
    published neighbour was lost is interpolated across the gap, counted, warned and flagged
    (POSE_SAMPLES_MISSING), exactly the frames an independent pass over the published stream predicts."""
    from css_ros.io.frame_gate import POSE_EXTRAPOLATED, POSE_SAMPLES_MISSING

    rec = Recorder()
    gate = gate_for(rec)
    events, stamps = robot_stream(n_frames=30, seed=3)
    rng = np.random.default_rng(4)
    published = [(e[2].header.stamp.sec * 10**9 + e[2].header.stamp.nanosec) for e in events if e[1] == "pose"]
    lost = set(rng.choice(len(published), 120, replace=False).tolist())
    fed, k = [], 0
    for t, kind, msg in events:
        if kind == "pose":
            if k not in lost:
                fed.append((t, kind, msg, k + 1))
            k += 1
        else:
            fed.append((t, kind, msg, None))
    frames = []
    for t, kind, msg, seq in fed:
        frames += gate.poll(t)
        if kind == "pose":
            frames += gate.on_pose(msg, t, 0, seq)
        elif kind == "camera_info":
            gate.on_camera_info(0, msg)
        else:
            frames += gate.on_segmentation(0, msg, t)
    frames += gate.flush()
    assert [f.stamp_ns for f in frames] == stamps, rec.warnings
    expect = {}
    for s in stamps:
        i = int(np.searchsorted(published, s))          # published[i - 1] < s < published[i]
        expect[s] = POSE_SAMPLES_MISSING if (i - 1 in lost or i in lost) else 0
    assert 0 < sum(1 for v in expect.values() if v) < len(stamps)
    assert {f.stamp_ns: f.pose_flags for f in frames} == expect
    assert rec.counts["frames_pose_samples_missing"] == rec.warnings["segmentation: pose samples missing"] == \
        sum(1 for v in expect.values() if v)
    for f in frames:
        if not f.pose_flags:                            # the interpolation of the published neighbours
            i = int(np.searchsorted(published, f.stamp_ns))
            (p0, _), (p1, _) = [base_truth((published[j] - T0) * 1e-9) for j in (i - 1, i)]
            u = (f.stamp_ns - published[i - 1]) / (published[i] - published[i - 1])
            np.testing.assert_allclose(f.position_map, p0 + u * (p1 - p0), rtol=0, atol=1e-12)
    assert POSE_EXTRAPOLATED not in {f.pose_flags for f in frames}


def test_an_extrapolated_frame_is_counted_warned_and_flagged():
    from css_ros.io.frame_gate import POSE_EXTRAPOLATED

    rec = Recorder()
    gate = gate_for(rec, pose_policy=PosePolicy(wait=0.5, max_extrapolation=0.02))
    gate.on_camera_info(0, camera_info())
    for k, dt in enumerate((-10_000_000, 0)):
        gate.on_pose(pose_message("pose_stamped", T0 + dt, *base_truth(dt * 1e-9)), 0.0, 0, k + 1)
    gate.on_segmentation(0, image(T0 + 10_000_000, np.ones((H, W), np.uint8), "mono8"), 0.0)
    (f,) = gate.poll(0.5)
    assert f.pose_how == "extrapolated" and f.pose_flags == POSE_EXTRAPOLATED
    assert rec.counts["frames_pose_extrapolated"] == rec.warnings["segmentation: pose extrapolated"] == 1
    assert "frames_pose_samples_missing" not in rec.counts
