"""css_replay's configuration: one record of every option, defaults from the engine's SPEC constants."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from ..engine.change_rules import DEFAULT_DEPTH_TOLERANCE, DEFAULT_DEPTH_TOLERANCE_RELATIVE
from ..engine.similarity import IDENTITY_SIMILARITY
from ..engine.spec import DEFAULT_BACKGROUND, DEFAULT_IGNORE_LABEL, DEFAULT_PRIOR
from ..io.frames import DEFAULT_MAX_IMAGE_PIXELS
from ..io.pose_history import (DEFAULT_MAX_POSE_EXTRAPOLATION_S, DEFAULT_MAX_POSE_GAP_S, DEFAULT_POSE_BUFFER_S,
                               DEFAULT_POSE_WAIT_S)
from ..io.tf_buffer import DEFAULT_TF_BUFFER_S
from ..io.topics import BAG_TOPICS, NODE_NAME

#: Default sync tolerance [s] between a segmentation and its pose/image/GT (the node's ``sync_slop``).
DEFAULT_SYNC_SLOP_S = 0.05
#: Default pending messages kept per topic while synchronising (the node's ``queue_size``).
DEFAULT_SYNC_QUEUE = 100
#: Largest share of labelled pixels (input or GT, ignore_label excluded) that may hold ids >= C before
#: css_replay fails (unless ``--allow-out-of-range``): such pixels are excluded from the GT metrics and
#: count as wrong input predictions, so a larger share means a class file that does not fit the bag.
OUT_OF_RANGE_MAX_SHARE = 0.01
#: Fields of :class:`ReplayConfig` that are run facts, not options (left out of ``to_json``).
_NOT_OPTIONS = ("explicit_topics", "warmup_s")


@dataclass
class ReplayConfig:
    """Everything css_replay needs; the defaults are the CLI defaults (paths resolved in :func:`resolve_paths`)."""

    bag: Path
    model: Path
    classes: Path | None
    out: Path
    num_classes: int | None = None
    topics: dict[str, str] = field(default_factory=lambda: dict(BAG_TOPICS))
    train_frames: int | None = None
    max_frames: int | None = None
    prior: float = DEFAULT_PRIOR
    background: float = DEFAULT_BACKGROUND
    unknown_threshold: float | None = None  # None = engine default
    ignore_label: int = DEFAULT_IGNORE_LABEL
    backend: str = "numba"
    #: sensor-model YAML (css_calibrate) for the update and ~/confidence; None: the paper's update
    sensor_model: Path | None = None
    #: with a sensor model, also fuse a second map with the paper's update for the report's comparison
    paper_baseline: bool = True
    # --- a changing world (engine/change_rules.py; the bag's depth topic is topics["depth"])
    #: class ids whose pixels add no evidence (people, ...): --transient-classes, resolved through the class names
    transient_classes: list[int] = field(default_factory=list)
    #: evidence half-life in observations (None: the paper's update, evidence adds up forever)
    evidence_half_life: float | None = None
    depth_tolerance: float = DEFAULT_DEPTH_TOLERANCE  # m
    depth_tolerance_relative: float = DEFAULT_DEPTH_TOLERANCE_RELATIVE  # fraction of the measured depth
    output_bag: bool = True
    quiet: bool = False
    sync_slop: float = DEFAULT_SYNC_SLOP_S  # s
    sync_queue: int = DEFAULT_SYNC_QUEUE
    namespace: str = "/" + NODE_NAME
    max_pixels: int = 4_000_000
    seed: int = 0
    examples: int = 4
    max_image_pixels: int = DEFAULT_MAX_IMAGE_PIXELS
    allow_out_of_range: bool = False
    # --- poses, cameras and frames: the node's parameters of the same names (README "On your robot")
    pose_type: str = "auto"  # auto: from the bag's pose topic type
    #: "topic", "tf" (the TF lookup map_frame <- segmentation frame_id from /tf and /tf_static), or "auto": the
    #: pose topic when the bag has it, else TF when the bag has /tf or /tf_static
    pose_source: str = "auto"
    tf_buffer_s: float = DEFAULT_TF_BUFFER_S  # s
    pose_buffer: float = DEFAULT_POSE_BUFFER_S  # s
    pose_wait: float = DEFAULT_POSE_WAIT_S  # s (bag log time)
    max_pose_extrapolation: float = DEFAULT_MAX_POSE_EXTRAPOLATION_S  # s
    max_pose_gap: float = DEFAULT_MAX_POSE_GAP_S  # s
    cameras: list[str] = field(default_factory=lambda: [""])
    pose_per_camera: bool = False
    camera_extrinsics: list[float] = field(default_factory=list)
    splat_to_map: list[float] = field(default_factory=lambda: list(IDENTITY_SIMILARITY))
    map_frame: str = "map"
    #: the css_node parameter file the options above came from (None: none)
    params_file: Path | None = None
    #: Kinds whose topic the user named explicitly: a missing one is an error, not "disabled".
    explicit_topics: frozenset[str] = frozenset()
    #: Seconds spent compiling / warming up the kernels before the timed run (set by the CLI; None = none).
    warmup_s: float | None = None

    def to_json(self) -> dict[str, Any]:
        d = {k: v for k, v in asdict(self).items() if k not in _NOT_OPTIONS}
        for k, v in d.items():
            if isinstance(v, Path):
                d[k] = str(v)
        return d
