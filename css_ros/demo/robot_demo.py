"""``css_make_demo --robot``: the demo room as a robot stack publishes it.

What differs from the plain demo (and what css_node's pose, camera and frame parameters are for):

- the pose is ``nav_msgs/Odometry`` of ``base_link`` (frame ``odom``) at :data:`ODOM_RATE_HZ`, sampled on its own
  clock, not at the camera stamps;
- two cameras, ``front`` and ``left`` (topics ``/<ns>/image``, ``/<ns>/segmentation``, ...), each with its own
  extrinsics (lever arm and rotation of its optical frame in ``base_link``) and its own stamps (the left camera is
  offset by half a frame period);
- the segmentation (and its confidence) arrive :data:`SEGMENTATION_LATENCY_S` after their image (bag log time),
  stamped with the image's time, as a network's output does;
- the splat is written in its own frame: scaled by 1/:data:`SPLAT_SCALE`, rotated and shifted like a trainer's
  (COLMAP-like: y down), so only ``splat_to_map`` puts it back into the z-up map.

``OUT/css_node.yaml`` holds the matching node parameters (pose_type, cameras, camera_extrinsics, splat_to_map);
``css_replay OUT/bag`` picks it up, ``css_node --ros-args --params-file OUT/css_node.yaml`` takes it.

``--tf``: the same robot on TF instead of a pose topic, as REP 105 stacks publish it: ``/tf`` carries
``odom -> base_link`` (the odometry samples, same stamps) and ``map -> odom`` (identity, :data:`MAP_ODOM_RATE_HZ`),
``/tf_static`` the chain ``base_link -> <ns>_link -> <ns>_optical`` of each camera (lever arm and yaw/pitch, then
the body-to-optical rotation; composed they are the extrinsics); css_node.yaml says ``pose_source: tf``. Every other
message is the same, so its replay gives the poses and maps of the pose-topic bag.
"""
from __future__ import annotations

import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..engine.camera import Camera, matrix_to_quaternion_xyzw
from ..engine.similarity import Similarity
from ..errors import CssError
from ..io.bag import BagWriter
from ..io.params_file import PARAMS_FILE_NAME, write_params_file
from ..io.topics import BAG_START_NS, BAG_TOPICS, POSE_TYPES, TF_STATIC_TOPIC, TF_TOPIC
from .renderer import DemoRenderer, bag_in_place, camera_k, systematic_rule_masks

#: Odometry rate [Hz] and the delay [s] between an odometry sample's stamp and its log time.
ODOM_RATE_HZ = 100.0
ODOM_DELAY_S = 0.002
#: Delay [s] between an image and its segmentation (log time; both carry the image's stamp).
SEGMENTATION_LATENCY_S = 0.25
#: The splat's frame: x_map = SPLAT_SCALE * R x_splat + t (R: -90 deg about x then 30 deg about the new z, so the
#: splat's y axis points down, as COLMAP's often does).
SPLAT_SCALE = 2.5
SPLAT_TRANSLATION = (1.5, -0.8, 0.3)
#: Camera namespaces and their optical frames in base_link: (x, y, z [m], yaw, pitch [deg]).
CAMERAS: dict[str, tuple[float, float, float, float, float]] = {
    "front": (0.20, 0.00, 1.00, 0.0, -12.0),
    "left": (0.05, 0.12, 0.95, 70.0, -8.0),
}
ODOM_FRAME = "odom"
BASE_FRAME = "base_link"
MAP_FRAME = "map"
#: Rate [Hz] of map -> odom on /tf in the --tf variant (a localiser's rate; every 5th odometry stamp).
MAP_ODOM_RATE_HZ = 20.0
#: Defaults of ``css_make_demo --robot`` (per camera frames over the ~80 s path).
ROBOT_DEFAULTS = {"num_gaussians": 50_000, "frames": 60, "width": 160, "height": 120}


def _rot_z(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_y(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def _rot_x(deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])


#: REP-103 body (x fwd, y left, z up) -> optical (z fwd, x right, y down).
_BODY_TO_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def camera_extrinsics(ns: str) -> list[float]:
    """[x, y, z, qx, qy, qz, qw] of camera ``ns``'s optical frame in base_link."""
    x, y, z, yaw, pitch = CAMERAS[ns]
    # yaw about base z, then pitch about the camera body's y (negative pitch = looking down)
    R = _rot_z(yaw) @ _rot_y(-pitch) @ _BODY_TO_OPTICAL
    return [x, y, z, *(float(v) for v in matrix_to_quaternion_xyzw(R))]


def camera_static_transforms(ns: str) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """The /tf_static chain of camera ``ns`` (--tf): (parent, child, translation (3,) [m], quaternion xyzw) of
    ``<ns>_link`` in base_link (lever arm, yaw then pitch; body axes) and ``<ns>_optical`` in ``<ns>_link``."""
    x, y, z, yaw, pitch = CAMERAS[ns]
    link = (BASE_FRAME, f"{ns}_link", np.array([x, y, z]), matrix_to_quaternion_xyzw(_rot_z(yaw) @ _rot_y(-pitch)))
    optical = (f"{ns}_link", f"{ns}_optical", np.zeros(3), matrix_to_quaternion_xyzw(_BODY_TO_OPTICAL))
    return [link, optical]


def splat_to_map() -> Similarity:
    """The similarity that takes the written splat back into the demo's z-up map frame."""
    R = _rot_x(-90.0) @ _rot_z(30.0)
    return Similarity(SPLAT_SCALE, R, np.array(SPLAT_TRANSLATION))


@dataclass(frozen=True)
class BasePath:
    """The base's path: t [s] -> (position (3,) [m], quaternion (4,) xyzw) of base_link in odom (= map)."""

    spline: Any
    duration: float

    def pose(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        x, y, _, yaw, _ = self.spline(np.clip(t, 0.0, self.duration))
        return np.array([x, y, 0.0]), matrix_to_quaternion_xyzw(_rot_z(float(yaw)))

    def camera_pose(self, t: float, ns: str) -> tuple[np.ndarray, np.ndarray]:
        """Exact optical pose of camera ``ns`` at t (closed form: base pose composed with the extrinsics)."""
        p, q = self.pose(t)
        return Similarity.rigid_from_params(camera_extrinsics(ns)).compose_pose(p, q)


def base_path(seed: int = 0) -> BasePath:
    from .trajectory import waypoint_spline

    spline, t_wp = waypoint_spline(seed)
    return BasePath(spline, float(t_wp[-1]))


def robot_params(tf: bool = False) -> dict[str, Any]:
    """The css_node parameters of the robot demo (``tf``: of its TF variant)."""
    if tf:
        return {"pose_source": "tf", "map_frame": MAP_FRAME, "cameras": list(CAMERAS),
                "splat_to_map": splat_to_map().to_params()}
    return {"pose_type": "odometry", "cameras": list(CAMERAS),
            "camera_extrinsics": [v for ns in CAMERAS for v in camera_extrinsics(ns)],
            "splat_to_map": splat_to_map().to_params()}


def write_odometry(writer: BagWriter, topic: str, stamp_ns: int, log_ns: int, position: np.ndarray,
                   quat: np.ndarray) -> None:
    """A nav_msgs/Odometry of base_link in odom (zero twist, zero covariance)."""
    T = writer.store.types
    pose = T["geometry_msgs/msg/Pose"](
        position=T["geometry_msgs/msg/Point"](x=float(position[0]), y=float(position[1]), z=float(position[2])),
        orientation=T["geometry_msgs/msg/Quaternion"](x=float(quat[0]), y=float(quat[1]), z=float(quat[2]),
                                                      w=float(quat[3])))
    zero = T["geometry_msgs/msg/Vector3"](x=0.0, y=0.0, z=0.0)
    msg = T[POSE_TYPES["odometry"]](
        header=writer.header(stamp_ns, ODOM_FRAME), child_frame_id=BASE_FRAME,
        pose=T["geometry_msgs/msg/PoseWithCovariance"](pose=pose, covariance=np.zeros(36)),
        twist=T["geometry_msgs/msg/TwistWithCovariance"](twist=T["geometry_msgs/msg/Twist"](linear=zero, angular=zero),
                                                         covariance=np.zeros(36)))
    writer.write(topic, POSE_TYPES["odometry"], msg, log_ns)


def make_robot_demo(out: str | Path, num_gaussians: int = ROBOT_DEFAULTS["num_gaussians"],
                    frames: int = ROBOT_DEFAULTS["frames"], width: int = ROBOT_DEFAULTS["width"],
                    height: int = ROBOT_DEFAULTS["height"], seed: int = 0, overwrite: bool = False,
                    progress: bool = True, tf: bool = False) -> dict[str, Any]:
    """Write the robot demo into ``out`` (bag/, model.ply, classes.yaml, css_node.yaml); returns a summary.

    ``frames`` per camera, equally spaced over the path; the left camera's stamps are offset by half a period.
    ``tf``: poses on /tf and /tf_static instead of /pose (see the module docstring).
    """
    from .scene import CLASS_NAMES, build_scene_arrays, demo_class_set
    from .segmentation_noise import DEFAULT_SYSTEMATIC, SegmentationNoise
    from ..engine.gaussians import GaussianModel

    if frames < 2 or width < 16 or height < 16:
        raise CssError("--frames must be >= 2 and the image at least 16x16")
    out = Path(out)
    bag_dir = out / "bag"
    if bag_dir.exists() and not overwrite:
        raise CssError(f"{bag_dir} exists; pass --overwrite to regenerate it")
    out.mkdir(parents=True, exist_ok=True)
    scene = build_scene_arrays(num_gaussians, seed)
    model = GaussianModel.from_activated(scene.means, scene.scales, scene.quats_wxyz, scene.opacities, scene.colors)
    classes = demo_class_set()
    path = base_path(seed)
    noise = SegmentationNoise(CLASS_NAMES, seed=seed)
    masks, targets = systematic_rule_masks(scene, CLASS_NAMES, DEFAULT_SYSTEMATIC)
    renderer = DemoRenderer(model, scene.class_ids, classes.num_classes, masks, targets)
    K = camera_k(width, height)
    period = path.duration / frames
    events: list[tuple[int, int, Any]] = []   # (log time, order, write function)
    n_odom = int(path.duration * ODOM_RATE_HZ) + 1
    for k in range(n_odom):
        t = k / ODOM_RATE_HZ
        stamp = BAG_START_NS + int(round(t * 1e9))
        events.append((stamp + int(ODOM_DELAY_S * 1e9), 0, ("odom", stamp, *path.pose(t))))
    for c, ns in enumerate(CAMERAS):
        for i in range(frames):
            t = (i + 0.5 * c) * period
            stamp = BAG_START_NS + int(round(t * 1e9))
            events.append((stamp, 1, ("camera", stamp, ns, c, i, t)))
            events.append((stamp + int(SEGMENTATION_LATENCY_S * 1e9), 2, ("seg", stamp, ns)))
    events.sort(key=lambda e: (e[0], e[1]))
    pending: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}
    iterator: Any = events
    if progress:
        from tqdm import tqdm

        iterator = tqdm(events, desc="css_make_demo --robot", unit="msg", file=sys.stderr, mininterval=0.5)
    with bag_in_place(out) as writer:
        writer.set_custom_data("css_ros.demo", json.dumps({"generator": "css_make_demo --robot", "frames": frames,
                                                           "width": width, "height": height, "seed": seed,
                                                           "num_gaussians": num_gaussians}, sort_keys=True))
        with writer:
            if tf:
                writer.write_tf(TF_STATIC_TOPIC, BAG_START_NS,
                         [(a, b, BAG_START_NS, p, q) for ns in CAMERAS for a, b, p, q in camera_static_transforms(ns)])
            every = int(round(ODOM_RATE_HZ / MAP_ODOM_RATE_HZ))
            for log_ns, _, ev in iterator:
                if ev[0] == "odom" and tf:
                    _, stamp, p, q = ev
                    entries = [(ODOM_FRAME, BASE_FRAME, stamp, p, q)]
                    if round((stamp - BAG_START_NS) * 1e-9 * ODOM_RATE_HZ) % every == 0:
                        entries.insert(0, (MAP_FRAME, ODOM_FRAME, stamp, np.zeros(3), np.array([0.0, 0, 0, 1])))
                    writer.write_tf(TF_TOPIC, log_ns, entries)
                elif ev[0] == "odom":
                    _, stamp, p, q = ev
                    write_odometry(writer, BAG_TOPICS["pose"], stamp, log_ns, p, q)
                elif ev[0] == "camera":
                    _, stamp, ns, c, i, t = ev
                    p, q = path.camera_pose(t, ns)
                    cam = Camera.from_pose(K, width, height, p, q)
                    frame_no = c * 100_000 + i
                    active = [noise.systematic_active(frame_no, r, rule.probability)
                              for r, rule in enumerate(DEFAULT_SYSTEMATIC)]
                    rgb, gt, biased = renderer.render(cam, active)
                    seg, conf = noise.apply(biased, frame_no)
                    opt = f"{ns}_optical"
                    writer.write_camera_info(f"/{ns}{BAG_TOPICS['camera_info']}", K, width, height, stamp, opt)
                    writer.write_image(f"/{ns}{BAG_TOPICS['image']}", rgb, "rgb8", stamp, opt)
                    writer.write_image(f"/{ns}{BAG_TOPICS['gt']}", gt, "mono8", stamp, opt)
                    pending[(ns, stamp)] = (seg, conf)
                else:
                    _, stamp, ns = ev
                    seg, conf = pending.pop((ns, stamp))
                    # written at their arrival (log) time, stamped with the image's time
                    _write_late_image(writer, f"/{ns}{BAG_TOPICS['confidence']}", conf, "32FC1", stamp, log_ns, ns)
                    _write_late_image(writer, f"/{ns}{BAG_TOPICS['segmentation']}", seg, "mono8", stamp, log_ns, ns)
    to_map = splat_to_map()
    to_map.inverse().transform_model(model).to_ply(out / "model.ply",
                                                    extra_fields={"class_id": scene.class_ids.astype(np.uint8)})
    classes.to_yaml(out / "classes.yaml")
    if tf:
        write_params_file(out / PARAMS_FILE_NAME, robot_params(tf=True),
                          comment="css_node parameters of the robot demo on TF (css_make_demo --robot --tf): camera\n"
                                  "poses from /tf and /tf_static, two cameras, the splat in its own frame.")
    else:
        write_params_file(out / PARAMS_FILE_NAME, robot_params(),
                          comment="css_node parameters of the robot demo (css_make_demo --robot): Odometry of "
                                  "base_link,\ntwo cameras with their extrinsics, the splat in its own frame "
                                  "(splat_to_map).")
    return {"frames_per_camera": frames, "cameras": list(CAMERAS), "odometry_messages": n_odom,
            "duration_s": path.duration}


def _write_late_image(writer: BagWriter, topic: str, array: np.ndarray, encoding: str, stamp_ns: int, log_ns: int,
                      ns: str) -> None:
    from ..io.messages import array_to_image_fields

    f = array_to_image_fields(array, encoding)
    msg = writer.store.types["sensor_msgs/msg/Image"](
        header=writer.header(stamp_ns, f"{ns}_optical"), height=f["height"], width=f["width"],
        encoding=f["encoding"], is_bigendian=int(f["is_bigendian"]), step=f["step"], data=f["data"])
    writer.write(topic, "sensor_msgs/msg/Image", msg, log_ns)
