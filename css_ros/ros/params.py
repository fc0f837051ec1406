"""css_node parameters: one table (name, default, unit, description), coercion and validation.

Every default comes from the engine (:mod:`css_ros.engine.spec`) or the frame decoder
(:mod:`css_ros.io.frames`) where those define one; every time quantity is in seconds.
``config/css_node.yaml`` and ``docs/parameters.md`` are checked against this table by the tests
(``params_markdown()`` writes the latter).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Callable

from ..engine.spec import (DEFAULT_BACKGROUND, DEFAULT_IGNORE_LABEL, DEFAULT_MIN_EVIDENCE, DEFAULT_PRIOR,
                           DEFAULT_QUERY_BACKGROUND_WEIGHT, DEFAULT_UNKNOWN_THRESHOLD)
from ..engine.backends import BACKENDS
from ..engine.change_rules import (DEFAULT_DEPTH_TOLERANCE, DEFAULT_DEPTH_TOLERANCE_RELATIVE, MAX_DEPTH_TOLERANCE,
                                   MAX_DEPTH_TOLERANCE_RELATIVE, MAX_HALF_LIFE, MIN_HALF_LIFE)
from ..engine.camera import MAX_CAMERA_PIXELS
from ..engine.map_args import MAX_CONCENTRATION, MIN_CONCENTRATION
from ..engine.map_file import MAX_RECEIVED_SOURCES
from ..errors import ConfigError
from ..engine.similarity import IDENTITY_SIMILARITY, Similarity, parse_extrinsics
from ..io.evidence import DEFAULT_MAX_ROWS
from ..io.frames import DEFAULT_MAX_IMAGE_PIXELS
from ..io.pose_history import (DEFAULT_MAX_POSE_EXTRAPOLATION_S, DEFAULT_MAX_POSE_GAP_S, DEFAULT_POSE_BUFFER_S,
                               DEFAULT_POSE_WAIT_S, PosePolicy)
from ..io.tf_buffer import DEFAULT_TF_BUFFER_S
from ..io.topics import POSE_SOURCES, POSE_TYPES

DEFAULT_MODEL = "bags/demo/model.ply"
DEFAULT_CLASSES = "bags/demo/classes.yaml"
#: ``{fingerprint}`` is replaced by the first 16 hex digits of the model fingerprint: one map file per model.
DEFAULT_CHECKPOINT = "~/.ros/css_ros/maps/{fingerprint}.npz"
FINGERPRINT_DIGITS = 16


def _p(default: Any, unit: str, description: str, items: type | None = None) -> Any:
    """A table entry: the dataclass field default plus its unit and description (dataclass metadata); ``items``:
    the element type of a list parameter whose default is empty (str; otherwise numbers)."""
    meta = {"unit": unit, "description": description, "items": items}
    if isinstance(default, list):
        return field(default_factory=lambda: list(default), metadata=meta)
    return field(default=default, metadata=meta)


@dataclass
class NodeParams:
    """Parameters of css_node, in the order of config/css_node.yaml; see :func:`params_markdown`."""

    # --- scene and classes
    model_path: str = _p(DEFAULT_MODEL, "path", "3DGS PLY of the scene (map frame); relative paths are tried "
                         "against the working directory, the package share directory and the source tree")
    class_file: str = _p(DEFAULT_CLASSES, "path", "class YAML (classes: [{id, name, color}]); empty: "
                         "num_classes anonymous classes")
    num_classes: int = _p(0, "", "number of classes C (0: take it from class_file); given while class_file is "
                          "left at its default (the demo's): C anonymous classes; contradicting a class_file "
                          "that is set: start-up error")
    # --- semantic model
    prior: float = _p(DEFAULT_PRIOR, "", "initial Dirichlet concentration per class and Gaussian (alpha_0)")
    background: float = _p(DEFAULT_BACKGROUND, "", "background Dirichlet concentration per class (alpha_b)")
    ignore_label: int = _p(DEFAULT_IGNORE_LABEL, "class id", "segmentation value meaning 'no label'; also "
                           "published for unknown pixels")
    unknown_threshold: float = _p(DEFAULT_UNKNOWN_THRESHOLD, "", "background weight kappa_b above which a pixel "
                                  "is published as ignore_label (1.0: never)")
    backend: str = _p("numba", "", "rasteriser backend: numba (CPU), cuda (GPU, the cuda extra) or torch")
    sensor_model: str = _p("", "path", "sensor-model YAML of the segmenter (css_calibrate writes it): each "
                           "labelled pixel adds evidence weighted by its label and rendered depth (depth bins in "
                           "metres, splat_to_map's scale applies); must list the class file's classes; a "
                           "checkpoint fused with another sensor model is refused; empty: the paper's update")
    # --- inputs
    input_qos: str = _p("sensor_data", "", "QoS of the sensor inputs: sensor_data (best effort) or reliable")
    queue_size: int = _p(30, "messages", "subscription depth, and buffered images / confidences / frames waiting "
                         "for a pose, per input and camera")
    sync_slop: float = _p(0.05, "s", "maximum stamp difference between a segmentation and its confidence and "
                          "colour image")
    max_stamp_future: float = _p(10.0, "s", "drop inputs stamped more than this ahead of the node clock (0: off)")
    max_image_pixels: int = _p(DEFAULT_MAX_IMAGE_PIXELS, "px", "largest camera_info width x height accepted; "
                               "larger ones are refused (the previous one stays)")
    use_confidence: bool = _p(True, "", "synchronise segmentation_confidence whenever it has a publisher")
    depth_topic: str = _p("", "topic", "measured depth registered to the segmentation (sensor_msgs/Image 16UC1 in "
                          "millimetres or 32FC1 in metres along the optical axis; 0, NaN, inf: no measurement), "
                          "matched by stamp like the colour image (nearest within sync_slop); relative names are "
                          "read under each camera's namespace (<ns>/<depth_topic>); while it has a publisher a frame "
                          "waits up to pose_wait for a depth stamped at or after its own, else it is fused without "
                          "depth (counted); empty: off")
    # --- poses, cameras and frames (docs/reliability.md "Poses by time"; README "On your robot")
    pose_source: str = _p("topic", "", "where camera poses come from: topic (the pose topic, pose_type, composed "
                          "with camera_extrinsics) or tf (/tf and /tf_static: the pose of each segmentation's "
                          "header.frame_id in map_frame at its stamp, then camera_extrinsics if given; the pose topic "
                          "is not subscribed)")
    tf_buffer_s: float = _p(DEFAULT_TF_BUFFER_S, "s", "TF history kept per transform (pose_source tf); the "
                            "pose_wait, max_pose_extrapolation and max_pose_gap rules apply to every transform")
    pose_type: str = _p("pose_stamped", "", "message type on pose: pose_stamped (geometry_msgs/PoseStamped), "
                        "pose_with_covariance (geometry_msgs/PoseWithCovarianceStamped) or odometry "
                        "(nav_msgs/Odometry, its pose.pose)")
    pose_buffer: float = _p(DEFAULT_POSE_BUFFER_S, "s", "pose history kept; a frame takes its pose interpolated "
                            "at the segmentation stamp")
    pose_wait: float = _p(DEFAULT_POSE_WAIT_S, "s", "longest wait of a frame for a pose after its stamp (or for "
                          "its confidence); then it is extrapolated (max_pose_extrapolation) or dropped")
    max_pose_extrapolation: float = _p(DEFAULT_MAX_POSE_EXTRAPOLATION_S, "s", "largest extrapolation past the "
                                       "newest (or before the oldest) pose; beyond it the frame is dropped")
    max_pose_gap: float = _p(DEFAULT_MAX_POSE_GAP_S, "s", "two poses further apart than this are not "
                             "interpolated across (relocalisation jump, lost stream): the frame is dropped")
    cameras: list[str] = _p([""], "", "camera namespaces: camera i reads <ns>/image, <ns>/segmentation, "
                            "<ns>/segmentation_confidence, <ns>/camera_info and publishes under ~/<ns>/ "
                            "('' = the un-namespaced topics)")
    pose_per_camera: bool = _p(False, "", "each camera has its own <ns>/pose (default: all share pose)")
    camera_extrinsics: list[float] = _p([], "m, quaternion", "7 numbers per camera (x y z qx qy qz qw): the "
                                        "camera's optical frame in the frame the pose describes (e.g. base_link); "
                                        "empty: the pose is the optical frame's")
    splat_to_map: list[float] = _p(list(IDENTITY_SIMILARITY), "scale, m, quaternion", "8 numbers (s x y z qx qy "
                                   "qz qw): the similarity x_map = s R x_splat + t taking splat coordinates into "
                                   "the map frame (css_align estimates it)")
    map_frame: str = _p("map", "", "frame of poses, requests and 3D outputs; frame_id of ~/view_uncertainty; "
                        "with pose_source tf the target of the TF lookups")
    # --- processing and outputs
    max_pending_frames: int = _p(2, "frames", "synchronised frames waiting for the worker; the oldest is "
                                 "dropped when full (newest wins)")
    output_scale: float = _p(1.0, "", "resolution scale of the published renders, in (0, 1] (the update uses "
                             "full resolution)")
    candidate_scale: float = _p(0.25, "", "resolution scale at which candidate views are rendered, in (0, 1]")
    max_candidates: int = _p(256, "views", "largest PoseArray scored on candidates (larger: answered with NaN)")
    candidate_slice: int = _p(16, "views", "candidate views scored between two observed frames (a frame never "
                              "waits for more than one slice)")
    candidate_time_budget: float = _p(5.0, "s", "a request not finished this long after it arrived is "
                                      "answered with NaN for the views not yet scored (0: no limit)")
    publish_semantic: bool = _p(True, "", "publish ~/semantic (mono8, or mono16 when ids exceed 255)")
    publish_semantic_color: bool = _p(True, "", "publish ~/semantic_color (rgb8, class palette)")
    publish_expectation: bool = _p(True, "", "publish ~/expectation (32FC1, E of the argmax class)")
    publish_variance: bool = _p(True, "", "publish ~/variance (32FC1, Var of the argmax class)")
    publish_rendered_image: bool = _p(True, "", "publish ~/rendered_image (rgb8 splat render)")
    publish_confidence: bool = _p(True, "", "publish ~/confidence (32FC1, probability that ~/semantic is right) "
                                  "when the sensor_model holds a calibrated confidence map")
    publish_surprise: bool = _p(True, "", "publish ~/surprise (32FC1, 1 - E of each pixel's observed label under "
                                "the map before the frame; NaN where the segmentation has no label; only with "
                                "output_scale 1)")
    publish_view_uncertainty: bool = _p(True, "", "publish ~/view_uncertainty (PointCloud2, one point per "
                                        "observed frame)")
    publish_diagnostics: bool = _p(True, "", "publish counters on /diagnostics (diagnostic_msgs/DiagnosticArray)")
    # --- a changing world (docs/changing_world.md)
    transient_classes: list[str] = _p([], "class names or ids", "classes whose pixels never add evidence (people, "
                                      "animals, vehicles in motion), by name in the class setup or by id; an "
                                      "unknown name is a start-up error", items=str)
    evidence_half_life: float = _p(0.0, "observations", "a Gaussian's accumulated evidence halves over this many "
                                   "observations of it (the map follows a changing world); 0 or negative: not "
                                   "set (a fresh map does not forget, a resumed one keeps the half-life its "
                                   "checkpoint holds). A map that forgets refuses the evidence exchange "
                                   "(publish_evidence, evidence_in): its evidence is no longer additive")
    depth_tolerance: float = _p(DEFAULT_DEPTH_TOLERANCE, "m", "measured depth nearer than the map's rendered "
                                "depth by more than max(depth_tolerance, depth_tolerance_relative x depth): the "
                                "pixel is occluded (adds no evidence); Gaussians in front of the measured surface "
                                "by more than that add none either")
    depth_tolerance_relative: float = _p(DEFAULT_DEPTH_TOLERANCE_RELATIVE, "", "share of the measured depth in "
                                         "the depth tolerance (see depth_tolerance)")
    # --- the map in 3D (SPEC §9)
    cloud_period: float = _p(5.0, "s", "time between ~/semantic_cloud messages, sent only when the map changed "
                             "(transient local: late subscribers get the last one; 0: off)")
    cloud_voxel_size: float = _p(0.0, "m", "keep only the most certain observed Gaussian per voxel of this edge "
                                 "in ~/semantic_cloud (0: every observed Gaussian)")
    cloud_max_points: int = _p(500_000, "points", "largest ~/semantic_cloud; the most certain points are kept "
                               "(0: no limit)")
    min_evidence: float = _p(DEFAULT_MIN_EVIDENCE, "", "a Gaussian is observed (in ~/semantic_cloud) when its "
                             "concentrations exceed the prior by this total (S_n - C alpha_0)")
    max_query_points: int = _p(1_000_000, "points", "largest point_queries cloud evaluated (larger, from its "
                               "header: answered at once with an empty cloud)")
    point_query_slice: int = _p(65_536, "points", "query points evaluated between two observed frames")
    query_background_weight: float = _p(DEFAULT_QUERY_BACKGROUND_WEIGHT, "", "background weight w_b of the "
                                        "continuous field at a 3D point (SPEC §9)")
    request_queue_size: int = _p(256, "requests", "subscription depth of candidates and point_queries and history "
                                 "of their answer topics: a burst of up to this many requests is received and "
                                 "answered in full (beyond the 8 pending ones: at once, as busy)")
    view_period: float = _p(1.0, "s", "time between ~/view/semantics messages for css_view --live (only the "
                            "Gaussians that changed; 0: no ~/view/* topics)")
    view_max_changes: int = _p(262_144, "Gaussians", "largest ~/view/semantics message (10 bytes a Gaussian); "
                               "more changes go out in the next ones")
    # --- persistence
    checkpoint_path: str = _p(DEFAULT_CHECKPOINT, "path", "semantic map checkpoint (.npz); {fingerprint} is "
                              "replaced by 16 hex digits of the model fingerprint; empty disables saving and "
                              "resuming")
    checkpoint_period: float = _p(60.0, "s", "time between automatic checkpoints (0: only on ~/save_map and "
                                  "shutdown)")
    checkpoint_retry_max: float = _p(600.0, "s", "longest wait before retrying a failed checkpoint (the wait "
                                     "doubles from checkpoint_period, or 1 s, per failure)")
    resume: bool = _p(True, "", "load checkpoint_path at start if it matches the model")
    # --- logging
    log_period: float = _p(10.0, "s", "time between status log lines and diagnostics messages (0: never)")
    warn_period: float = _p(5.0, "s", "minimum time between two warnings of the same topic and reason")
    warmup: bool = _p(True, "", "compile the rasteriser kernels before subscribing; a failed warm-up stops the node")
    # --- evidence exchange between nodes of one splat (css_ros/io/evidence.py)
    publish_evidence: bool = _p(False, "", "publish the evidence this node fuses on ~/evidence (never what it "
                                "received)")
    evidence_in: str = _p("", "topics", "comma-separated evidence topics of other nodes to add to the map "
                          "(e.g. /robot_b/css_node/evidence; empty: none)")
    evidence_origin: str = _p("", "", "origin id of this node's evidence, <= 32 ASCII characters (empty: "
                              "host name and process id)")
    evidence_period: float = _p(0.5, "s", "time between ~/evidence delta packets (only when evidence was added)")
    evidence_snapshot_period: float = _p(5.0, "s", "time between snapshots of this node's total evidence on "
                                         "~/evidence (late joiners and receivers that missed a packet catch up)")
    evidence_max_rows: int = _p(DEFAULT_MAX_ROWS, "Gaussians", "most Gaussians per evidence packet (sent and accepted)")
    evidence_max_sources: int = _p(8, "sources", "most other nodes whose evidence is added (8 N C bytes each)")
    model_watch_dir: str = _p("", "path", "folder watched for a newer splat (*.ply): the map moves to it by "
                              "the transfer of SPEC §10 while the node runs (empty: off)")
    model_watch_period: float = _p(2.0, "s", "time between two scans of model_watch_dir (a file must be "
                                   "unchanged over two scans)")
    model_swap_min_ratio: float = _p(0.7, "", "a newer splat of model_watch_dir whose transfer keeps less than "
                                     "this share of the map's evidence is refused, with a warning (almost surely "
                                     "another scene, or a splat in another frame): the map stays on the current "
                                     "splat (0: accept any; docs/maps.md gives the measured ratios)")
    model_swap_warn_ratio: float = _p(0.95, "", "a swap that keeps less than this share of the evidence (but at "
                                      "least model_swap_min_ratio) is done with a warning naming the ratio")
    evidence_max_rate: float = _p(200.0, "packets/s", "evidence packets accepted per source and second (a "
                                  "flood beyond is refused)")
    evidence_allowed_origins: str = _p("", "", "comma-separated origin ids whose evidence is accepted (empty: any; "
                                       "DDS does not authenticate peers, docs/reliability.md)")
    evidence_max_frame_rate: float = _p(100.0, "frames/s", "most frames per second a source's evidence may claim "
                                        "(each adds at most max_image_pixels to a Gaussian and to the source's "
                                        "total); more is refused")


def param_table() -> list[tuple[str, Any, str, str]]:
    """(name, default, unit, description) of every parameter, in declaration order."""
    defaults = NodeParams()
    return [(f.name, getattr(defaults, f.name), f.metadata["unit"], f.metadata["description"])
            for f in fields(NodeParams)]


def format_default(value: Any) -> str:
    """A default as written in YAML (true/false, lists in brackets, '' for the empty string)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "[" + ", ".join(format_default(v) for v in value) + "]"
    if isinstance(value, str) and value == "":
        return "''"
    return str(value)


def params_markdown() -> str:
    """The parameter table as markdown (docs/parameters.md is this text)."""
    lines = ["# css_node parameters", "",
             "Generated from `css_ros/ros/params.py` by `css_ros.ros.params.params_markdown()`; "
             "`test/test_ros_params.py` checks that this file and `config/css_node.yaml` are up to date.",
             "All parameters are read once at start-up; every time quantity is in seconds.", "",
             "| name | default | unit | description |", "|---|---|---|---|"]
    for name, default, unit, desc in param_table():
        lines.append(f"| `{name}` | `{format_default(default)}` | {unit} | {desc.replace('|', '/')} |")
    return "\n".join(lines) + "\n"


def coerce(name: str, value: Any, default: Any, items: type | None = None) -> Any:
    """Convert a parameter value to the type of its default (int -> float allowed); ConfigError otherwise.
    ``items`` str: a list of strings, integers accepted as their decimal text (``transient_classes:=[11, 12]``)."""
    def bad() -> ConfigError:
        return ConfigError(f"parameter {name}={value!r}: expected {type(default).__name__}"
                           + (" of numbers" if isinstance(default, list) else ""))

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise bad()
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad()
        return float(value)
    if isinstance(default, int):
        if isinstance(value, bool) or not (isinstance(value, int) or (isinstance(value, float)
                                                                       and float(value).is_integer())):
            raise bad()
        return int(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise bad()
        return value
    if isinstance(default, list):
        if value is None or (isinstance(value, (list, tuple)) and len(value) == 0):
            return []  # ROS has no typed empty array: an empty list arrives as "not set"
        if isinstance(value, (str, bytes)):
            raise bad()
        try:
            values = list(value)
        except TypeError:
            raise bad() from None
        if items is str:
            if not all(isinstance(v, str) or (isinstance(v, int) and not isinstance(v, bool)) for v in values):
                raise ConfigError(f"parameter {name}={value!r}: expected a list of names or integer ids")
            return [str(v) for v in values]
        if default and all(isinstance(v, str) for v in default):
            if not all(isinstance(v, str) for v in values):
                raise bad()
            return [str(v) for v in values]
        if not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            raise bad()
        return [float(v) for v in values]
    return value


def params_from_values(values: dict[str, Any]) -> NodeParams:
    """NodeParams from raw values (missing names take their defaults), coerced and validated."""
    defaults = NodeParams()
    unknown = set(values) - {f.name for f in fields(NodeParams)}
    if unknown:
        raise ConfigError(f"unknown parameter(s): {', '.join(sorted(unknown))}")
    p = NodeParams(**{f.name: coerce(f.name, values[f.name], getattr(defaults, f.name), f.metadata["items"])
                      if f.name in values
                      else getattr(defaults, f.name) for f in fields(NodeParams)})
    check_params(p)
    return p


def check_params(p: NodeParams) -> None:
    """Raise ConfigError naming the parameter when a value is out of range."""
    def bad(name: str, why: str) -> ConfigError:
        return ConfigError(f"parameter {name}={getattr(p, name)!r}: {why}")

    if p.input_qos not in ("sensor_data", "reliable"):
        raise bad("input_qos", "expected 'sensor_data' or 'reliable'")
    if p.backend not in BACKENDS:
        raise bad("backend", f"expected one of {', '.join(BACKENDS)}")
    for name in ("prior", "background", "unknown_threshold", "output_scale", "candidate_scale",
                 "query_background_weight"):
        if not (math.isfinite(getattr(p, name)) and getattr(p, name) > 0):
            raise bad(name, "must be finite and > 0")
    for name in ("prior", "background"):
        if not MIN_CONCENTRATION <= getattr(p, name) <= MAX_CONCENTRATION:
            raise bad(name, f"must be in [{MIN_CONCENTRATION:g}, {MAX_CONCENTRATION:g}] (what a map file may hold)")
    if p.unknown_threshold > 1:
        raise bad("unknown_threshold", "must be <= 1 (a background weight; 1.0: never unknown)")
    for name in ("output_scale", "candidate_scale"):
        if getattr(p, name) > 1:
            raise bad(name, "must be <= 1 (renders never exceed the camera resolution)")
    for name in ("sync_slop", "max_stamp_future", "checkpoint_period", "checkpoint_retry_max", "log_period",
                 "warn_period", "candidate_time_budget", "cloud_period", "cloud_voxel_size", "min_evidence",
                 "evidence_snapshot_period", "view_period"):
        if not (math.isfinite(getattr(p, name)) and getattr(p, name) >= 0):
            raise bad(name, "must be finite and >= 0")
    for name in ("model_watch_period", "evidence_period"):
        if not (math.isfinite(getattr(p, name)) and getattr(p, name) > 0):
            raise bad(name, "must be finite and > 0")
    for name in ("queue_size", "max_pending_frames", "max_candidates", "candidate_slice", "max_image_pixels",
                 "max_query_points", "point_query_slice", "request_queue_size", "evidence_max_rows",
                 "evidence_max_sources", "view_max_changes"):
        if getattr(p, name) < 1:
            raise bad(name, "must be >= 1")
    if p.max_image_pixels > MAX_CAMERA_PIXELS:
        raise bad("max_image_pixels", f"must be <= {MAX_CAMERA_PIXELS} (8192 x 8192, the engine's largest camera)")
    if p.cloud_max_points < 0:
        raise bad("cloud_max_points", "must be >= 0")
    if p.num_classes < 0:
        raise bad("num_classes", "must be >= 0")
    if not 0 <= p.ignore_label <= 65535:
        raise bad("ignore_label", "must be in 0..65535")
    for name in ("model_swap_min_ratio", "model_swap_warn_ratio"):
        if not (math.isfinite(getattr(p, name)) and 0 <= getattr(p, name) <= 1):
            raise bad(name, "must be in [0, 1] (a share of the map's evidence)")
    if p.model_swap_warn_ratio < p.model_swap_min_ratio:
        raise bad("model_swap_warn_ratio", f"must be >= model_swap_min_ratio ({p.model_swap_min_ratio:g})")
    if p.evidence_max_sources > MAX_RECEIVED_SOURCES:
        raise bad("evidence_max_sources", f"at most {MAX_RECEIVED_SOURCES} (the received sources a map file keeps: "
                  "a checkpoint with more would not load)")
    if not (math.isfinite(p.evidence_max_rate) and p.evidence_max_rate > 0):
        raise bad("evidence_max_rate", "must be finite and > 0")
    if len(p.evidence_origin) > 32 or not p.evidence_origin.isascii():
        raise bad("evidence_origin", "at most 32 ASCII characters")
    if any(len(o.strip()) > 32 or not o.isascii() for o in p.evidence_allowed_origins.split(",")):
        raise bad("evidence_allowed_origins", "origin ids of at most 32 ASCII characters, comma-separated")
    if not (math.isfinite(p.evidence_max_frame_rate) and p.evidence_max_frame_rate > 0):
        raise bad("evidence_max_frame_rate", "must be finite and > 0")
    if p.pose_type not in POSE_TYPES:
        raise bad("pose_type", f"expected one of {', '.join(POSE_TYPES)}")
    if p.pose_source not in POSE_SOURCES:
        raise bad("pose_source", f"expected one of {', '.join(POSE_SOURCES)}")
    if not (math.isfinite(p.tf_buffer_s) and p.tf_buffer_s > 0):
        raise bad("tf_buffer_s", "must be finite and > 0")
    if p.pose_source == "tf" and p.pose_per_camera:
        raise bad("pose_per_camera", "has no meaning with pose_source tf (each camera's frame_id names its pose)")
    if p.pose_source == "tf" and not p.map_frame.strip().lstrip("/"):
        raise bad("map_frame", "must name the TF frame of the map with pose_source tf")
    for name in ("pose_buffer", "pose_wait", "max_pose_extrapolation", "max_pose_gap"):
        if not (math.isfinite(getattr(p, name)) and getattr(p, name) >= 0):
            raise bad(name, "must be finite and >= 0")
    for name in ("pose_buffer", "max_pose_gap"):
        if getattr(p, name) <= 0:
            raise bad(name, "must be > 0")
    if not p.cameras:
        raise bad("cameras", "needs at least one namespace ('' = the un-namespaced topics)")
    names = [c.strip("/") for c in p.cameras]
    if len(set(names)) != len(names):
        raise bad("cameras", "namespaces must be distinct")
    bad_ns = [c for c in names if c and not all(part.isascii() and part.replace("_", "a").isalnum()
                                                 and not part[0].isdigit() for part in c.split("/"))]
    if bad_ns:
        raise bad("cameras", f"not a valid ROS namespace: {bad_ns[0]!r}")
    parse_extrinsics(p.camera_extrinsics, len(p.cameras))   # ConfigError naming camera_extrinsics
    _check_changing_world(p, bad)
    Similarity.from_params(p.splat_to_map, "splat_to_map")  # ConfigError naming splat_to_map


def _check_changing_world(p: NodeParams, bad: Callable[[str, str], ConfigError]) -> None:
    """depth_topic, the depth tolerances, evidence_half_life (and its refusal of the evidence exchange)."""
    topic = p.depth_topic.strip()
    if topic != p.depth_topic or (topic and not all(part and part.isascii() and part.replace("_", "a").isalnum()
                                                    and not part[0].isdigit()
                                                    for part in topic.removeprefix("/").split("/"))):
        raise bad("depth_topic", "not a valid ROS topic name (empty: off)")
    if topic.startswith("/") and len(p.cameras) > 1:
        raise bad("depth_topic", f"an absolute name would be one topic for all {len(p.cameras)} cameras: give a "
                  "relative one (read as <ns>/<depth_topic> per camera)")
    for name, upper in (("depth_tolerance", MAX_DEPTH_TOLERANCE),
                        ("depth_tolerance_relative", MAX_DEPTH_TOLERANCE_RELATIVE)):
        if not (math.isfinite(getattr(p, name)) and 0 <= getattr(p, name) <= upper):
            raise bad(name, f"must be in [0, {upper:g}]")
    h = p.evidence_half_life
    if not math.isfinite(h) or (h > 0 and not MIN_HALF_LIFE <= h <= MAX_HALF_LIFE):
        raise bad("evidence_half_life", f"must be in [{MIN_HALF_LIFE:g}, {MAX_HALF_LIFE:g}] observations, or 0 "
                  "(off)")
    if h > 0 and (p.publish_evidence or p.evidence_in.strip()):
        raise bad("evidence_half_life", "with a half-life the map's evidence is no longer additive (it decays as "
                  "it is observed), so it cannot be exchanged: set evidence_half_life:=0.0, or turn the evidence "
                  "exchange off (publish_evidence:=false, evidence_in:='')")


def half_life(p: NodeParams) -> float | None:
    """The evidence half-life [observations] these parameters set (None: not set)."""
    return p.evidence_half_life if p.evidence_half_life > 0 else None


def pose_policy(p: NodeParams) -> PosePolicy:
    """The pose lookup rules of these parameters."""
    return PosePolicy(buffer=p.pose_buffer, wait=p.pose_wait, max_extrapolation=p.max_pose_extrapolation,
                      max_gap=p.max_pose_gap)


def checkpoint_file(template: str, fingerprint: str) -> str:
    """checkpoint_path with ``{fingerprint}`` replaced by the model fingerprint's first 16 hex digits."""
    return template.replace("{fingerprint}", fingerprint[:FINGERPRINT_DIGITS])
