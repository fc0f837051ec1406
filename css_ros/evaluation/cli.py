"""``css_replay`` command line: arguments, path defaults, validation and the exit codes."""
from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path
from typing import Sequence

from ..engine.spec import DEFAULT_BACKGROUND, DEFAULT_IGNORE_LABEL, DEFAULT_PRIOR, DEFAULT_UNKNOWN_THRESHOLD
from ..engine.backends import BACKENDS
from ..engine.change_rules import (DEFAULT_DEPTH_TOLERANCE, DEFAULT_DEPTH_TOLERANCE_RELATIVE, MAX_DEPTH_TOLERANCE,
                                   MAX_DEPTH_TOLERANCE_RELATIVE, MAX_HALF_LIFE, MIN_HALF_LIFE, check_half_life,
                                   check_tolerance)
from ..engine.map_args import MAX_CONCENTRATION, MIN_CONCENTRATION
from ..engine.warmup import warm_up_kernels
from ..console import run_console
from ..errors import ConfigError, MapError
from ..io.paths import find_demo_bag
from ..engine.similarity import Similarity, parse_extrinsics
from ..io.params_file import PARAMS_FILE_NAME, read_params_file
from ..io.pose_history import (DEFAULT_MAX_POSE_EXTRAPOLATION_S, DEFAULT_MAX_POSE_GAP_S, DEFAULT_POSE_BUFFER_S,
                               DEFAULT_POSE_WAIT_S, PosePolicy)
from ..io.tf_buffer import DEFAULT_TF_BUFFER_S
from ..io.topics import BAG_TOPICS, POSE_SOURCES, POSE_TYPES, REQUIRED_BAG_KINDS
from ..engine.classes import ClassSet, class_ids
from .config import DEFAULT_SYNC_QUEUE, DEFAULT_SYNC_SLOP_S, OUT_OF_RANGE_MAX_SHARE, ReplayConfig
from .replay import default_out_dir, headline, run

#: Printed on stderr before the kernels are compiled (numba's on-disk cache is cold).
COMPILE_NOTICE = "css_replay: compiling kernels (first run, ~1 min)"

EXAMPLES = """\
examples:
  css_replay                                  # the shipped demo bags/demo/bag -> out/replay_demo/report.md
  css_replay data/train --out out/train       # your bag (data/train/bag; model.ply and classes.yaml beside it)
  css_replay bags/demo --max-frames 10 --no-output-bag
                                              # a quick look: the first 10 frames, no output bag
  css_replay bags/demo_range/bag --sensor-model out/calibration/sensor_model.yaml
                                              # css_calibrate's sensor model beside the paper's update (same frames)
  css_replay bags/demo --train-frames 60      # fuse the first 60 frames only, evaluate all 120
  css_replay out/people --transient-classes person --evidence-half-life 10
                                              # a changing world (css_make_demo --out out/people --people 2
                                              # --change-class --depth): people add no evidence, old evidence
                                              # fades, the bag's /depth holds back what stands in front
  css_replay BAG --model splat.ply --classes classes.yaml --pose-source tf --map-frame odom
                                              # another model and class file, camera poses from /tf
A css_node parameter file (css_node.yaml) beside the bag folder gives poses, cameras and frames (or --params FILE).
Exit codes: 0 done; 1 refused in one line (a bag, model, class file or option value that cannot be used);
2 a malformed command line.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_replay",
        description="Replay a rosbag2 bag (sqlite3 or MCAP) through Continuous Semantic Splatting: fuse the "
                    "segmentation into the splat model, write the node's output topics to a bag and evaluate "
                    "against the ground-truth segmentation (metrics.json, plots, report.md).",
        epilog=EXAMPLES, formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("bag", nargs="?", type=Path, default=None,
                   help="bag directory (default: the shipped demo bags/demo/bag)")
    p.add_argument("--model", type=Path, default=None, metavar="PLY",
                   help="INRIA 3DGS PLY model (default: <bag parent>/model.ply)")
    p.add_argument("--classes", default=None, metavar="YAML",
                   help="class file YAML (default: <bag parent>/classes.yaml; '' = anonymous classes, "
                        "needs --num-classes)")
    p.add_argument("--num-classes", type=int, default=None, metavar="N",
                   help="number of classes when no class file exists (anonymous names, generated palette)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output directory (default: out/replay_<bagname>, with --sensor-model "
                        "out/replay_<bagname>_<sensor-model file stem>)")
    for kind, topic in BAG_TOPICS.items():
        opt = "--confidence-topic" if kind == "confidence" else f"--{kind.replace('_', '-')}-topic"
        p.add_argument(opt, dest=f"topic_{kind}", default=None, metavar="TOPIC",
                       help=TOPIC_HELP.get(kind, f"{kind} topic") + f" (default {topic})"
                       + ("" if kind in REQUIRED_BAG_KINDS else "; '' = do not use"))
    p.add_argument("--train-frames", type=int, default=None, metavar="K",
                   help="update the map with the first K frames only; all frames are evaluated (default: all)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after this many usable frames")
    p.add_argument("--prior", type=float, default=DEFAULT_PRIOR,
                   help=f"Dirichlet prior alpha_0 per class (default {DEFAULT_PRIOR:g})")
    p.add_argument("--background", type=float, default=DEFAULT_BACKGROUND,
                   help=f"background concentration alpha_b (default {DEFAULT_BACKGROUND:g})")
    p.add_argument("--unknown-threshold", type=float, default=None,
                   help="label a rendered pixel 'no label' when its background weight kappa_b exceeds this "
                        f"(default {DEFAULT_UNKNOWN_THRESHOLD:g}; 1.0 = never)")
    p.add_argument("--ignore-label", type=int, default=DEFAULT_IGNORE_LABEL,
                   help=f"'no label' value of label images (default {DEFAULT_IGNORE_LABEL})")
    p.add_argument("--backend", choices=tuple(BACKENDS), default="numba",
                   help="rasteriser backend: numba (CPU), cuda (GPU, needs the cuda extra) or torch")
    p.add_argument("--sync-slop", type=float, default=None, metavar="S",
                   help="max stamp difference [s] between a segmentation and its confidence/image/GT "
                        f"(default {DEFAULT_SYNC_SLOP_S:g}, as css_node's sync_slop)")
    p.add_argument("--sync-queue", type=int, default=DEFAULT_SYNC_QUEUE, help="pending messages kept per topic while syncing")
    p.add_argument("--namespace", default=ReplayConfig.namespace,
                   help=f"namespace of the output topics (default {ReplayConfig.namespace})")
    p.add_argument("--max-pixels", type=int, default=4_000_000,
                   help="pixels kept (uniform random subsample, fixed seed) for pixel sparsification")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel subsample and the random baseline")
    p.add_argument("--examples", type=int, default=4, help="example frames in the report strip")
    p.add_argument("--allow-out-of-range", action="store_true",
                   help=f"do not fail when more than {100 * OUT_OF_RANGE_MAX_SHARE:g} %% of the labelled pixels hold "
                        "ids >= the number of classes (they are always counted and reported)")
    g = p.add_argument_group("poses, cameras and frames (the css_node parameters of the same names; README "
                             "'On your robot')")
    g.add_argument("--params", type=Path, default=None, metavar="YAML",
                   help=f"css_node parameter file to take these from (default: {PARAMS_FILE_NAME} next to the bag "
                        "directory when present); options given here win")
    g.add_argument("--pose-type", choices=("auto", *POSE_TYPES), default=None,
                   help="pose message type (default auto: from the bag's pose topic)")
    g.add_argument("--pose-source", choices=("auto", *POSE_SOURCES), default=None,
                   help="camera poses from the pose topic or from /tf and /tf_static (the lookup map_frame <- the "
                        "segmentation's frame_id); default auto: the pose topic when the bag has it, else TF")
    g.add_argument("--map-frame", default=None, metavar="FRAME",
                   help="the map frame: frame of the published poses and target of the TF lookups (default map)")
    g.add_argument("--tf-buffer-s", type=float, default=None, metavar="S",
                   help=f"TF history kept per transform [s] (default {DEFAULT_TF_BUFFER_S:g})")
    g.add_argument("--pose-buffer", type=float, default=None, metavar="S",
                   help=f"pose history [s] (default {DEFAULT_POSE_BUFFER_S:g})")
    g.add_argument("--pose-wait", type=float, default=None, metavar="S",
                   help=f"longest wait of a frame for its pose [s of bag log time] (default {DEFAULT_POSE_WAIT_S:g})")
    g.add_argument("--max-pose-extrapolation", type=float, default=None, metavar="S",
                   help=f"largest pose extrapolation [s] (default {DEFAULT_MAX_POSE_EXTRAPOLATION_S:g})")
    g.add_argument("--max-pose-gap", type=float, default=None, metavar="S",
                   help=f"no interpolation across poses further apart [s] (default {DEFAULT_MAX_POSE_GAP_S:g})")
    g.add_argument("--cameras", nargs="+", default=None, metavar="NS",
                   help="camera namespaces: camera NS reads /NS/segmentation, /NS/camera_info, ... ('' = the "
                        "un-namespaced topics, the default)")
    g.add_argument("--pose-per-camera", action="store_true", default=None,
                   help="each camera has its own /NS/pose")
    g.add_argument("--camera-extrinsics", nargs="+", type=float, default=None, metavar="V",
                   help="7 numbers per camera (x y z qx qy qz qw): the optical frame in the frame the pose describes")
    g.add_argument("--splat-to-map", nargs=8, type=float, default=None, metavar="V",
                   help="s x y z qx qy qz qw: the similarity taking splat coordinates into the map frame")
    p.add_argument("--sensor-model", type=Path, default=None, metavar="YAML",
                   help="sensor model from css_calibrate: weights each pixel's vote by its label and depth and "
                        "publishes the calibrated ~/confidence (default: none, the paper's update). The same run "
                        "also fuses the paper's update on the same frames and reports both side by side (accuracy, "
                        "mIoU, AUSE, ECE, calibrated confidence)")
    p.add_argument("--no-paper-baseline", action="store_true",
                   help="with --sensor-model, do not also fuse a map with the paper's update for comparison "
                        "(saves its time)")
    _change_options(p)
    p.add_argument("--no-output-bag", action="store_true", help="do not write the output bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar, only errors and the final line")
    return p


#: help of the topic options whose kind name alone does not say enough
TOPIC_HELP = {
    "gt": "static ground-truth labels (what the map should show: no passers-by)",
    "depth": "measured depth (sensor_msgs/Image 16UC1 millimetres or 32FC1 metres along the optical axis, registered "
             "to the segmentation and paired with it by stamp; another resolution is resampled by nearest "
             "neighbour; 0 / NaN / inf = no measurement): a labelled pixel nearer than the map's surface adds no "
             "evidence, Gaussians in front of the measured surface get none from it",
    "gt_changed": "evaluation only: for the pixels of objects whose class changes during the bag, their class at "
                  "the end (ignore label elsewhere); the report measures how much of them the final map shows in "
                  "that class and the surprise when the change is first seen",
}


def _change_options(p: argparse.ArgumentParser) -> None:
    """The options of a changing world (README "A changing world"; css_ros/engine/change_rules.py)."""
    g = p.add_argument_group("a changing world (README 'A changing world'; the measured depth: --depth-topic)")
    g.add_argument("--transient-classes", nargs="+", default=None, metavar="CLASS",
                   help="classes whose pixels never add evidence (people, animals, vehicles): names of the class file "
                        "or ids; the report gives the share of the final map's pixels in these classes")
    g.add_argument("--evidence-half-life", type=float, default=None, metavar="H",
                   help="forget old evidence: a Gaussian's accumulated evidence halves every H observations of it "
                        f"(in [{MIN_HALF_LIFE:g}, {MAX_HALF_LIFE:g}]; default: never, the paper's update)")
    g.add_argument("--depth-tolerance", type=float, default=DEFAULT_DEPTH_TOLERANCE, metavar="M",
                   help="measured-depth tolerance in metres: a pixel counts as in front of the map's surface when "
                        "nearer by more than max(M, R x depth) (default "
                        f"{DEFAULT_DEPTH_TOLERANCE:g}, in [0, {MAX_DEPTH_TOLERANCE:g}])")
    g.add_argument("--depth-tolerance-relative", type=float, default=DEFAULT_DEPTH_TOLERANCE_RELATIVE, metavar="R",
                   help="the tolerance's share of the measured depth (default "
                        f"{DEFAULT_DEPTH_TOLERANCE_RELATIVE:g}, in [0, {MAX_DEPTH_TOLERANCE_RELATIVE:g}])")


def resolve_change_options(args: argparse.Namespace, classes: Path | None, num_classes: int) -> dict:
    """ReplayConfig's changing-world fields from the options, checked with the engine's rules (ConfigError naming
    the option)."""
    names = ClassSet.from_yaml(classes).names if classes is not None else ClassSet.default(num_classes).names
    out: dict = {"transient_classes": class_ids(args.transient_classes or [], names, "--transient-classes")}
    try:
        out["evidence_half_life"] = check_half_life(args.evidence_half_life)
    except MapError as exc:
        raise ConfigError(f"--evidence-half-life: {exc}") from None
    for name, upper in (("depth_tolerance", MAX_DEPTH_TOLERANCE),
                        ("depth_tolerance_relative", MAX_DEPTH_TOLERANCE_RELATIVE)):
        try:
            out[name] = check_tolerance(getattr(args, name), f"--{name.replace('_', '-')}", upper)
        except MapError as exc:
            raise ConfigError(str(exc)) from None
    return out


def is_bag_dir(path: Path) -> bool:
    """True if ``path`` is a rosbag2 directory (metadata.yaml, or MCAP / sqlite3 storage files)."""
    return path.is_dir() and ((path / "metadata.yaml").is_file() or any(path.glob("*.mcap"))
                              or any(path.glob("*.db3")))


def find_bag(path: Path) -> Path:
    """``path`` itself if it is a bag (or a bag file), else the single bag directly inside it.

    Raises:
        ConfigError: missing path, or a folder that holds no bag or several (the message names them).
    """
    if not path.exists():
        raise ConfigError(f"bag not found: {path}")
    if not path.is_dir() or is_bag_dir(path):
        return path
    inside = sorted(p for p in path.iterdir() if is_bag_dir(p))
    if len(inside) == 1:
        return inside[0]
    if inside:
        raise ConfigError(f"{path} is not a bag but holds several: did you mean "
                          + " or ".join(str(p) for p in inside) + "?")
    raise ConfigError(f"{path} is not a rosbag2 bag (no metadata.yaml, .mcap or .db3 file) and holds none")


def resolve_classes(args: argparse.Namespace, base: Path) -> tuple[Path | None, int]:
    """(class file or None for anonymous classes, number of classes C) from --classes / --num-classes."""
    if args.num_classes is not None and args.num_classes < 1:
        raise ConfigError("--num-classes must be >= 1")
    if args.classes == "":
        if args.num_classes is None:
            raise ConfigError("--classes '' (anonymous classes) needs --num-classes N")
        return None, args.num_classes
    classes = Path(args.classes) if args.classes is not None else base / "classes.yaml"
    if not classes.is_file():
        if args.classes is not None:
            raise ConfigError(f"class file not found: {classes}")
        if args.num_classes is None:
            raise ConfigError(f"class file not found: {classes} (pass --classes FILE or --num-classes N)")
        return None, args.num_classes
    n = ClassSet.from_yaml(classes).num_classes
    if args.num_classes is not None and args.num_classes != n:
        raise ConfigError(f"--num-classes {args.num_classes} contradicts the class file {classes} ({n} classes); "
                          "drop --num-classes or pass --classes ''")
    return classes, n


def resolve_paths(args: argparse.Namespace) -> ReplayConfig:
    """Turn parsed CLI arguments into a :class:`ReplayConfig` (default paths resolved, values validated)."""
    bag = args.bag
    if bag is None:
        bag = find_demo_bag()
        if bag is None:
            raise ConfigError("no bag given and the demo bag bags/demo/bag was not found; "
                           "pass a bag directory (or generate the demo with css_make_demo)")
    bag = find_bag(Path(bag))
    base = bag.resolve().parent
    model = args.model if args.model is not None else base / "model.ply"
    if not Path(model).is_file():
        raise ConfigError(f"model not found: {model}" + ("" if args.model else " (pass --model)"))
    classes, num_classes = resolve_classes(args, base)
    for name in ("train_frames", "max_frames"):
        v = getattr(args, name)
        if v is not None and v < 0:
            raise ConfigError(f"--{name.replace('_', '-')} must be >= 0")
    for name in ("prior", "background"):
        if not (math.isfinite(getattr(args, name)) and MIN_CONCENTRATION <= getattr(args, name) <= MAX_CONCENTRATION):
            raise ConfigError(f"--{name} must be in [{MIN_CONCENTRATION:g}, {MAX_CONCENTRATION:g}]")
    given = {kind: getattr(args, f"topic_{kind}") for kind in BAG_TOPICS}
    topics = {kind: BAG_TOPICS[kind] if v is None else v for kind, v in given.items()}
    for kind in REQUIRED_BAG_KINDS:
        if not topics[kind]:
            raise ConfigError(f"the {kind} topic is required")
    frames = resolve_frame_options(args, base)
    params_sensor = frames.pop("sensor_model", None)
    sensor_model = args.sensor_model if args.sensor_model is not None else params_sensor
    return ReplayConfig(
        **frames,
        bag=bag, model=Path(model), classes=classes,
        out=args.out if args.out is not None else default_out_dir(bag, sensor_model), num_classes=num_classes,
        topics=topics, train_frames=args.train_frames, max_frames=args.max_frames, prior=args.prior,
        background=args.background, unknown_threshold=args.unknown_threshold, ignore_label=args.ignore_label,
        backend=args.backend, output_bag=not args.no_output_bag, quiet=args.quiet,
        sensor_model=sensor_model,
        paper_baseline=not args.no_paper_baseline,
        sync_queue=max(1, args.sync_queue), namespace=args.namespace, max_pixels=max(1000, args.max_pixels),
        seed=args.seed, examples=max(0, args.examples), allow_out_of_range=args.allow_out_of_range,
        explicit_topics=frozenset(k for k, v in given.items() if v is not None),
        **resolve_change_options(args, classes, num_classes),
    )


#: css_node parameters css_replay takes from a parameter file (the node's names) -> ReplayConfig field.
FRAME_PARAMS = ("pose_source", "tf_buffer_s",
                "pose_type", "pose_buffer", "pose_wait", "max_pose_extrapolation", "max_pose_gap", "cameras",
                "pose_per_camera", "camera_extrinsics", "splat_to_map", "map_frame", "sync_slop")


def resolve_frame_options(args: argparse.Namespace, base: Path) -> dict:
    """The pose / camera / frame options: the parameter file's values, overridden by the command line.

    ``--params FILE``, else ``<bag parent>/css_node.yaml`` when it exists (a note on stderr says so). Values are
    validated with the node's rules (ConfigError naming the option).
    """
    values: dict = {}
    params_path = args.params
    if params_path is None and (base / PARAMS_FILE_NAME).is_file():
        params_path = base / PARAMS_FILE_NAME
        if not args.quiet:
            print(f"css_replay: using the parameters in {params_path} (--params to choose another file)",
                  file=sys.stderr)
    if params_path is not None:
        given = read_params_file(params_path)
        values.update({k: v for k, v in given.items() if k in FRAME_PARAMS})
        sensor = given.get("sensor_model")
        if isinstance(sensor, str) and sensor:  # the node's sensor model, unless --sensor-model names another
            path = Path(sensor)
            try:
                here = path.is_absolute() or path.exists()
            except OSError:  # a name too long, a folder it cannot search: SensorModel.load names the fault
                here = True
            values["sensor_model"] = path if here else Path(params_path).parent / path
    for name in FRAME_PARAMS:
        v = getattr(args, name, None)
        if v is not None:
            values[name] = v
    if "cameras" in values:
        values["cameras"] = [str(c) for c in values["cameras"]] or [""]
    for name in ("camera_extrinsics", "splat_to_map"):
        if name in values:
            try:
                values[name] = [float(v) for v in values[name]]
            except (TypeError, ValueError):
                raise ConfigError(f"{name}: expected a list of numbers, got {values[name]!r}") from None
    pose_type = values.get("pose_type", "auto")
    if pose_type not in ("auto", *POSE_TYPES):
        raise ConfigError(f"pose_type {pose_type!r}: expected auto or one of {', '.join(POSE_TYPES)}")
    if values.get("pose_source", "auto") not in ("auto", *POSE_SOURCES):
        raise ConfigError(f"pose_source {values['pose_source']!r}: expected auto or one of {', '.join(POSE_SOURCES)}")
    if "tf_buffer_s" in values:
        try:
            values["tf_buffer_s"] = float(values["tf_buffer_s"])
        except (TypeError, ValueError):
            raise ConfigError(f"tf_buffer_s: expected a number, got {values['tf_buffer_s']!r}") from None
        if not (math.isfinite(values["tf_buffer_s"]) and values["tf_buffer_s"] > 0):
            raise ConfigError(f"tf_buffer_s must be a finite number > 0 s, got {values['tf_buffer_s']!r}")
    try:
        PosePolicy(**{k: float(values[n]) for k, n in (("buffer", "pose_buffer"), ("wait", "pose_wait"),
                                                       ("max_extrapolation", "max_pose_extrapolation"),
                                                       ("max_gap", "max_pose_gap")) if n in values})
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"pose options: {exc}") from None
    parse_extrinsics(values.get("camera_extrinsics", []), len(values.get("cameras", [""])))
    if "splat_to_map" in values:
        Similarity.from_params(values["splat_to_map"])
    values["params_file"] = params_path
    return values


def numba_cache_is_cold() -> bool:
    """Best effort: True when no numba cache index of the rasteriser exists (beside the module, in
    ``NUMBA_CACHE_DIR`` or in the user-wide cache), i.e. the next run compiles the kernels."""
    from ..engine.cpu import raster

    src = Path(raster.__file__)
    places = [src.parent / "__pycache__"]
    if os.environ.get("NUMBA_CACHE_DIR"):
        places.append(Path(os.environ["NUMBA_CACHE_DIR"]))
    places.append(Path.home() / ".cache" / "numba")
    for place in places:
        if place.is_dir() and next(place.rglob(f"{src.stem}.*.nbi"), None) is not None:
            return False
    return True


def warm_up(cfg: ReplayConfig) -> float:
    """Compile the kernels on a tiny throwaway map (:func:`css_ros.engine.warmup.warm_up_kernels`) so that the
    report's timings exclude compilation; returns the seconds it took. Prints :data:`COMPILE_NOTICE` first
    when the numba cache is cold (unless ``cfg.quiet``)."""
    if cfg.backend == "numba" and not cfg.quiet and numba_cache_is_cold():
        print(COMPILE_NOTICE, file=sys.stderr, flush=True)
    return warm_up_kernels(cfg.backend, int(cfg.num_classes or 1))


def view_command(cfg: ReplayConfig) -> str:
    """The ``css_view`` command line that shows this replay's map (its output folder holds the rest)."""
    import shlex

    return f"css_view {shlex.quote(str(cfg.out))}"


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the process exit code (0 ok, 1 runtime error, 2 usage error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the usage message
        return int(exc.code or 0)

    def work() -> int:
        cfg = resolve_paths(args)
        cfg.warmup_s = warm_up(cfg)
        metrics = run(cfg)
        print(headline(metrics))
        print(f"report: {(cfg.out / 'report.md').resolve()}")
        print(f"view the map in a browser: {view_command(cfg)}")
        return 0

    return run_console("css_replay", work)


if __name__ == "__main__":
    sys.exit(main())
