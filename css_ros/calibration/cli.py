"""``css_calibrate``: learn the segmenter's sensor model (and the calibrated confidence map) from labelled bags.

Writes ``--out`` (YAML, read by css_node's ``sensor_model`` parameter and css_replay's ``--sensor-model``) and,
beside it, ``<stem>_reliability_by_depth.png``, ``<stem>_confusion.png`` and ``<stem>_reliability.png``. Every
file is written atomically, the YAML last: a failed run leaves no partial file.
"""
from __future__ import annotations

import argparse
import os
import sys
import tempfile
from collections import Counter
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from ..console import bounded_number, run_console
from ..engine.classes import ClassSet
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import SemanticMap
from ..engine.sensor_model import (MAX_DEPTH_BINS, SensorModel, shorten, uniform_bin_count, uniform_edges,
                                   vote_table_error)
from ..errors import ConfigError, CssError
from ..evaluation import cli as replay_cli
from ..evaluation.calibration_metrics import ReliabilityBins
from ..evaluation.config import ReplayConfig
from ..evaluation.source import FrameSource
from ..io.params_file import PARAMS_FILE_NAME
from .learn import (DEFAULT_VOTES, VOTE_KINDS, DEFAULT_BIN_WIDTH, DEFAULT_HELDOUT_EVERY, DEFAULT_MAX_DEPTH, DEFAULT_PSEUDO_COUNT,
                    DEFAULT_WEIGHT_FLOOR, MIN_LABELLED_PIXELS, ConfidenceSamples, LabelDepthCounts, fit_confidence,
                    extrapolated_bins, fit_sensor_model, fused_frames, in_front_of_map, is_heldout, label_reliability,
                    label_samples, right_rates)

PROG = "css_calibrate"
#: Largest --max-depth and --bin-width [m] (a segmenter's labels are not judged beyond a kilometre).
MAX_DEPTH_M = 1000.0
#: Largest --pseudo-count [pixels] (a smoothing weight of a billion pixels outweighs any bag).
MAX_PSEUDO_COUNT = 1e9
#: Largest --heldout-every [frames].
MAX_HELDOUT_EVERY = 1_000_000
#: --out when none is given, relative to the working folder (beside css_replay's out/replay_<bag>): the only folder
#: css_calibrate makes when it is missing.
DEFAULT_OUT = Path("out") / "calibration" / "sensor_model.yaml"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Learn how reliable the segmentation is per class and depth from labelled bags (the bags carry "
                    "/segmentation_gt; css_import --gt makes such bags from image folders), and calibrate the map's "
                    "confidence. Each bag's model.ply and classes.yaml are found as css_replay finds them.",
        epilog=f"Example: css_calibrate bags/calib_range/bag (writes {DEFAULT_OUT} and its three figures); then "
               f"css_replay BAG --sensor-model {DEFAULT_OUT}, or css_node with sensor_model:={DEFAULT_OUT}")
    p.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="labelled bag directories")
    p.add_argument("--out", type=Path, default=DEFAULT_OUT, metavar="YAML",
                   help=f"sensor model file to write (.yaml; its figures go beside it; default {DEFAULT_OUT}, whose "
                        "folder is made when missing). The folder of any other --out must exist and be writable: "
                        "css_calibrate creates no other folder (a typo would create directories anywhere). It "
                        "must not be inside an input bag nor be an input of the run (a bag's model, class or "
                        "parameter file). Checked before any work (exit 2)")
    p.add_argument("--model", type=Path, default=None, metavar="PLY",
                   help="splat model (only with one bag; default: <bag parent>/model.ply)")
    p.add_argument("--classes", default=None, metavar="YAML",
                   help="class file (default: <bag parent>/classes.yaml; every bag must have the same classes)")
    p.add_argument("--bin-width", type=bounded_number(0.0, MAX_DEPTH_M, lo_open=True), default=DEFAULT_BIN_WIDTH,
                   metavar="M", help=f"depth-bin width in metres, in (0, {MAX_DEPTH_M:g}] (default "
                                     f"{DEFAULT_BIN_WIDTH:g}); at most {MAX_DEPTH_BINS} bins up to --max-depth")
    p.add_argument("--max-depth", type=bounded_number(0.0, MAX_DEPTH_M, lo_open=True), default=DEFAULT_MAX_DEPTH,
                   metavar="M", help=f"last bin edge in metres, in (0, {MAX_DEPTH_M:g}]; deeper pixels fall in the "
                                     f"last bin (default {DEFAULT_MAX_DEPTH:g})")
    p.add_argument("--votes", choices=VOTE_KINDS, default=DEFAULT_VOTES,
                   help="how a vote is spread over the classes: symmetric (default: p on the label, the rest evenly "
                        "on the others), onehot (the label only) or confusion (the rows p(true class | label, depth))")
    p.add_argument("--per-class", action="store_true",
                   help="weights per label and depth (default: per depth, the same for every label)")
    p.add_argument("--pseudo-count", type=bounded_number(0.0, MAX_PSEUDO_COUNT), default=DEFAULT_PSEUDO_COUNT, metavar="N",
                   help="smoothing of sparse (label, depth) bins toward their neighbours and the class rate, in "
                        f"pixels, in [0, {MAX_PSEUDO_COUNT:g}] (default {DEFAULT_PSEUDO_COUNT:g})")
    p.add_argument("--weight-floor", type=bounded_number(0.0, 1.0), default=DEFAULT_WEIGHT_FLOOR, metavar="W",
                   help=f"vote weight of labels no better than chance, in [0, 1] (default {DEFAULT_WEIGHT_FLOOR:g})")
    p.add_argument("--heldout-every", type=bounded_number(0, MAX_HELDOUT_EVERY, integer=True), default=DEFAULT_HELDOUT_EVERY,
                   metavar="K", help=f"hold out every K-th frame of each bag for the before/after calibration, 0 "
                                     f"(none) or 2..{MAX_HELDOUT_EVERY} (default {DEFAULT_HELDOUT_EVERY})")
    p.add_argument("--no-confidence", action="store_true",
                   help="skip the second pass that fits the calibrated confidence map (~/confidence)")
    p.add_argument("--gt-topic", default=None, metavar="TOPIC", help="ground-truth topic (default /segmentation_gt)")
    p.add_argument("--segmentation-topic", default=None, metavar="TOPIC",
                   help="segmentation topic (default /segmentation)")
    p.add_argument("--depth-topic", default=None, metavar="TOPIC",
                   help="measured depth (sensor_msgs/Image 16UC1 millimetres or 32FC1 metres, registered to the "
                        "segmentation, paired with it by stamp, resampled by nearest neighbour; default /depth when "
                        "the bag has it, '' = do not use): labelled pixels nearer than the splat's surface (a "
                        "passer-by the ground truth does not show) are left out of the statistics, and the "
                        "confidence pass fuses with it as css_replay does")
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    return p


def bag_config(args: argparse.Namespace, bag: Path) -> ReplayConfig:
    """css_replay's configuration of one bag (model, classes, topics and frame options found the same way)."""
    argv = [str(bag), "--quiet", "--no-output-bag"]
    if args.model is not None:
        argv += ["--model", str(args.model)]
    if args.classes is not None:
        argv += ["--classes", str(args.classes)]
    if args.gt_topic is not None:
        argv += ["--gt-topic", args.gt_topic]
    if args.segmentation_topic is not None:
        argv += ["--segmentation-topic", args.segmentation_topic]
    if args.depth_topic is not None:
        argv += ["--depth-topic", args.depth_topic]
    cfg = replay_cli.resolve_paths(replay_cli.build_parser().parse_args(argv))
    if cfg.classes is None:
        raise ConfigError(f"{bag}: no class file (pass --classes)")
    return cfg


def option_error(args: argparse.Namespace) -> str | None:
    """What is wrong with the options together (each alone was checked by its ``type``), or None. Checked right
    after parsing, before any file is read: a usage error (exit 2)."""
    if args.model is not None and len(args.bags) > 1:
        return "--model applies to one bag; with several, each bag's parent holds its model.ply"
    if not args.max_depth > args.bin_width:
        return f"--max-depth {args.max_depth:g} must be larger than --bin-width {args.bin_width:g}"
    bins = uniform_bin_count(args.max_depth, args.bin_width)     # inf when the quotient overflows: never raises
    if not bins <= MAX_DEPTH_BINS:
        count = f"{bins:.0f} depth bins, more than {MAX_DEPTH_BINS}" if bins < 1e15 else \
            f"far more than {MAX_DEPTH_BINS} depth bins (the quotient overflows)"
        return f"--max-depth {args.max_depth:g} / --bin-width {args.bin_width:g} gives {count}: widen the bins"
    if args.heldout_every == 1:
        return "--heldout-every must be 0 (none) or >= 2 (1 would hold out every frame)"
    if args.out.suffix.lower() not in (".yaml", ".yml"):
        return f"--out {shorten(str(args.out), 200)}: expected a .yaml file"
    return out_error(args)


def _resolved(path: Path) -> Path:
    """``path`` made absolute with its symlinks resolved as far as they exist (a loop: made absolute only)."""
    try:
        return path.resolve()
    except (OSError, RuntimeError):
        return Path(os.path.abspath(path))


def run_inputs(args: argparse.Namespace) -> tuple[list[Path], list[tuple[str, Path]]]:
    """(bag folders, [(what, file)]) this run reads, found as :func:`bag_config` finds them (a bag that cannot be
    found is refused later, when it is read): --model, --classes, and each bag's default model.ply, classes.yaml and
    css_node.yaml beside it."""
    folders: list[Path] = []
    files: list[tuple[str, Path]] = []
    if args.model is not None:
        files.append(("--model", Path(args.model)))
    if args.classes:
        files.append(("--classes", Path(args.classes)))
    for given in args.bags:
        try:
            bag = replay_cli.find_bag(Path(given))
        except (CssError, OSError):
            bag = Path(given)
        try:
            is_dir = bag.is_dir()
        except OSError:
            is_dir = False
        if is_dir:
            folders.append(bag)
        else:
            files.append(("the bag", bag))
        base = _resolved(bag).parent
        files += [("the model", base / "model.ply"), ("the class file", base / "classes.yaml"),
                  ("the parameter file", base / PARAMS_FILE_NAME)]
    return folders, files


def _same_file(a: Path, b: Path) -> bool:
    """Both name one file: the same resolved path, or (both existing) the same inode (a hard link)."""
    if _resolved(a) == _resolved(b):
        return True
    try:
        return os.path.samefile(a, b)
    except (OSError, ValueError):
        return False


def out_error(args: argparse.Namespace) -> str | None:
    """What is wrong with --out as a destination, or None; checked when parsed, before any work (a usage error).

    Refused: --out (or one of its figures) an existing directory; its folder missing (css_calibrate creates no
    folder but the default's, :data:`DEFAULT_OUT`, once the other checks passed) or not a directory; --out or a figure
    inside an input bag folder or equal to an input file (it would overwrite the bag's metadata or the class file the
    run reads); a folder where no file can be created (a temporary file is made and removed there to know)."""
    out = Path(args.out)
    name = shorten(str(out), 200)
    outputs = [out, *figure_paths(out).values()]
    parent = out.parent
    try:
        for path in outputs:
            if path.is_dir():
                return (f"--out {name} is a directory: name the .yaml file to write" if path == out else
                        f"--out {name}: its figure {path} would replace a directory")
        make_default = out == DEFAULT_OUT and not parent.exists()
        if not parent.exists() and not make_default:
            return (f"--out {name}: its folder {shorten(str(parent), 200)} does not exist (css_calibrate creates no "
                    "folder: make it first)")
        if parent.exists() and not parent.is_dir():
            return f"--out {name}: {shorten(str(parent), 200)} is not a directory"
    except OSError as exc:
        return f"--out {name}: {exc.strerror or exc}"
    folders, files = run_inputs(args)
    for path in outputs:
        target = _resolved(path)
        what = f"--out {name}" if path == out else f"--out {name}: its figure {path.name}"
        for folder in folders:
            if _resolved(folder) in target.parents:
                return f"{what} would be written inside the input bag {folder}; write it outside the bag"
        for kind, file in files:
            if _same_file(path, file):
                return f"{what} is an input of this run ({kind} {file}): it would be overwritten"
    try:
        if make_default:
            parent.mkdir(parents=True, exist_ok=True)
        fd, probe = tempfile.mkstemp(dir=parent, prefix=f".{out.stem}.", suffix=".probe")
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        return f"--out {name}: cannot write in {shorten(str(parent), 200)} ({exc.strerror or exc})"
    return None


def check_options(args: argparse.Namespace) -> None:
    """:func:`option_error` as a ConfigError (for callers that build the namespace themselves)."""
    error = option_error(args)
    if error is not None:
        raise ConfigError(error)


#: How the skip reasons of the frame reader that name no image read in css_calibrate's report.
_READER_REASONS = {"size_mismatch_with_camera_info": "a ground truth or colour image of another aspect ratio than "
                                                     "the segmentation"}


class _Source(FrameSource):
    """The frame reader, keeping the first detail of each reason it drops a message for (the skip report)."""

    def __init__(self, cfg: ReplayConfig) -> None:
        super().__init__(cfg)
        self.first_detail: dict[str, str] = {}

    def _warn(self, topic: str, reason: str, detail: str = "", dropped: bool = True) -> None:
        super()._warn(topic, reason, detail, dropped)
        if dropped and detail:
            self.first_detail.setdefault(reason.replace(" ", "_"), f"{topic}: {detail}"[:200])


def _frames(cfg: ReplayConfig, what: str, quiet: bool, skipped: Counter[str] | None = None) -> Any:
    """The bag's frames (a progress bar); after the last one, what the reader dropped is added to ``skipped``
    (reason -> count)."""
    source = _Source(cfg)
    source.check()
    if not source.present.get("gt"):
        raise CssError(f"{cfg.bag} has no ground-truth topic {cfg.topics['gt'] or '(none)'}: css_calibrate needs "
                       "labelled frames")

    def frames() -> Any:
        yield from source.frames()
        if skipped is not None:
            for key, n in source.skips.items():
                detail = source.first_detail.get(key)
                text = _READER_REASONS.get(key, key.replace("_", " ")) + (f", e.g. {detail}" if detail else "")
                skipped[f"messages dropped while reading ({text})"] += n

    return tqdm(frames(), total=source.anchor_count, desc=f"{what} {cfg.bag.parent.name or cfg.bag.name}",
                unit="frame", disable=quiet, file=sys.stderr, dynamic_ncols=True)


def unusable(labels: np.ndarray, gt: np.ndarray, depth: np.ndarray, num_classes: int) -> str | None:
    """Why a frame adds no labelled pixel to the counts (None when it adds some): labels, gt (H, W) ids, depth (H, W)
    metres (NaN: none). The rule of :meth:`LabelDepthCounts.add`: ids in [0, C) in both, a finite depth."""
    if gt.shape != labels.shape:
        return "ground truth of another size than the segmentation"
    tru = (gt >= 0) & (gt < num_classes)
    lab = (labels >= 0) & (labels < num_classes)
    if not tru.any():
        return f"ground truth holds no class id below {num_classes} (ids {_ids(gt)})"
    if not lab.any():
        return f"segmentation holds no class id below {num_classes} (ids {_ids(labels)})"
    if not (tru & lab).any():
        return "no pixel labelled in both the segmentation and the ground truth"
    if not np.isfinite(depth[tru & lab]).any():
        return "no rendered depth on the labelled pixels (the splat does not cover them)"
    return None


def _ids(a: np.ndarray) -> str:
    values = np.unique(a)
    return ", ".join(str(int(v)) for v in values[:5]) + (", ..." if values.size > 5 else "")


def skip_summary(skipped: Counter[str]) -> str:
    """``n reason; n reason`` (most first) of the frames that added nothing, '' when none."""
    return "; ".join(f"{n} {reason}" for reason, n in skipped.most_common())


def collect(configs: list[ReplayConfig], edges: np.ndarray, num_classes: int, heldout_every: int,
            quiet: bool, skipped: Counter[str] | None = None) -> LabelDepthCounts:
    """Pass 1: (label, depth bin, ground truth) counts of every labelled frame of every bag. ``skipped`` gets, per
    reason, the frames that added no labelled pixel and the messages the reader dropped."""
    counts = LabelDepthCounts(num_classes, edges)
    skipped = Counter() if skipped is None else skipped
    for cfg in configs:
        model = GaussianModel.from_ply(cfg.model)
        smap = SemanticMap(model, num_classes, ignore_label=cfg.ignore_label, depth_scale=float(cfg.splat_to_map[0]))
        for frame in _frames(cfg, "statistics", quiet, skipped):
            if frame.gt is None:
                skipped["frames without a ground-truth image (none matched, or it was dropped)"] += 1
                continue
            depth = smap.render(frame.camera, outputs=("depth",)).depth
            assert depth is not None  # the numba backend always renders depth
            why = unusable(frame.labels, frame.gt, depth, num_classes)
            if why is not None:
                skipped[f"frames: {why}"] += 1
            front = None if frame.depth is None else in_front_of_map(frame.depth, depth)
            counts.add(frame.labels, frame.gt, depth, is_heldout(frame.index, heldout_every), front)
    return counts


def confidence_pass(configs: list[ReplayConfig], sensor: SensorModel, heldout_every: int,
                    quiet: bool) -> ConfidenceSamples:
    """Pass 2: fuse every bag with ``sensor`` (a fresh map per bag) and sample its online renders."""
    samples = ConfidenceSamples()
    for cfg in configs:
        model = GaussianModel.from_ply(cfg.model)
        smap = SemanticMap(model, sensor.num_classes, prior=cfg.prior, background=cfg.background,
                           ignore_label=cfg.ignore_label, sensor_model=sensor,
                           depth_scale=float(cfg.splat_to_map[0]))
        fused_frames(smap, _frames(cfg, "confidence", quiet), samples, heldout_every)
    return samples


def _fmt(summary: dict[str, Any] | None) -> str:
    if not summary or summary.get("ece") is None:
        return "n/a"
    return f"ECE {summary['ece']:.3f}, Brier {summary['brier']:.3f} (accuracy {summary['accuracy']:.3f})"


def calibrate(args: argparse.Namespace) -> int:
    check_options(args)
    configs = [bag_config(args, Path(b)) for b in args.bags]
    classes = ClassSet.from_yaml(configs[0].classes)  # type: ignore[arg-type]
    for cfg in configs[1:]:
        other = ClassSet.from_yaml(cfg.classes)  # type: ignore[arg-type]
        if other.names != classes.names:
            raise ConfigError(f"{cfg.bag} uses the classes of {cfg.classes}, which differ from {configs[0].classes}")
    edges = uniform_edges(args.max_depth, args.bin_width)
    table_error = vote_table_error(classes.num_classes, edges.size - 1)
    if table_error is not None:
        raise ConfigError(f"{configs[0].classes}: {table_error}")
    skipped: Counter[str] = Counter()
    counts = collect(configs, edges, classes.num_classes, args.heldout_every, args.quiet, skipped)
    fit_pixels = int(counts.fit.sum())
    if fit_pixels < MIN_LABELLED_PIXELS:
        why = f"; skipped: {skip_summary(skipped)}" if skipped else ""
        raise CssError(f"too few labelled pixels to calibrate: {fit_pixels} with a ground truth and a rendered depth "
                       f"in {counts.frames_fit} fitting frames (need {MIN_LABELLED_PIXELS}){why}")
    if skipped:
        print(f"{PROG}: skipped: {skip_summary(skipped)}")
    sensor = fit_sensor_model(counts, classes.names, votes=args.votes, per_class=args.per_class,
                              pseudo_count=args.pseudo_count, weight_floor=args.weight_floor)
    conf, ok = label_samples(counts.heldout if counts.frames_heldout else counts.fit,
                             right_rates(counts.fit, args.pseudo_count))
    labels_report = label_reliability(conf, ok)
    info: dict[str, Any] = {
        "bags": [str(c.bag) for c in configs], "frames_fit": counts.frames_fit,
        "frames_heldout": counts.frames_heldout, "heldout_every": args.heldout_every, "pixels_fit": fit_pixels,
        "pixels_heldout": int(counts.heldout.sum()), "pixels_without_depth": counts.no_depth,
        "pixels_in_front_of_the_map": counts.in_front,
        "pseudo_count": args.pseudo_count, "weight_floor": args.weight_floor,
        "weight_rule": "w = max(weight_floor, 2 p - 1), p = fraction of right labels "
                       + ("per label and depth bin" if args.per_class else "per depth bin (all labels)"),
        "votes": args.votes,
        "extrapolated": extrapolated_bins(counts.fit, edges, classes.names, args.per_class),
        "input_label_calibration": {"before": labels_report["before"], "after": labels_report["after"]},
    }
    panels = []  # the reliability diagrams, from the bins the reports already hold
    if labels_report["after"] is not None:
        panels.append(("input labels, held-out frames", {
            "paper: every label right (p = 1)": ReliabilityBins.from_json(labels_report["before"]["bins"]),
            "fitted p(label right | label, depth)": ReliabilityBins.from_json(labels_report["after"]["bins"])}))
    if not args.no_confidence:
        samples = confidence_pass(configs, sensor, args.heldout_every, args.quiet)
        cmap, conf_report = fit_confidence(samples)
        sensor = SensorModel(sensor.class_names, sensor.depth_edges, sensor.weight, sensor.confusion, cmap)
        info["confidence_calibration"] = conf_report
        panels.append(("map labels (online renders), " + conf_report["judged_on"], {
            "expectation E of the label": ReliabilityBins.from_json(conf_report["before"]["bins"]),
            "calibrated confidence": ReliabilityBins.from_json(conf_report["after"]["bins"])}))
    sensor = SensorModel(sensor.class_names, sensor.depth_edges, sensor.weight, sensor.confusion, sensor.confidence,
                         info)
    figures = write_outputs(args.out, sensor, counts, classes, panels)
    print(f"{PROG}: {fit_pixels} labelled pixels in {counts.frames_fit} frames ({counts.frames_heldout} held out); "
          f"{counts.no_depth} labelled pixels had no rendered depth"
          + (f", {counts.in_front} were in front of the map's surface (measured depth)" if counts.in_front else ""))
    print(f"input labels, held out: paper (p = 1): {_fmt(labels_report['before'])}; fitted p(right | label, depth): "
          f"{_fmt(labels_report['after'])}")
    if "confidence_calibration" in info:
        cr = info["confidence_calibration"]
        print(f"map confidence, {cr['judged_on']}: E: {_fmt(cr['before'])}; calibrated: {_fmt(cr['after'])}")
    print(f"wrote {args.out} ({sensor.describe()}) and its figures {', '.join(str(p) for p in figures)}")
    return 0


def figure_paths(out: Path) -> dict[str, Path]:
    """The PNGs written beside the sensor-model file."""
    stem = out.with_suffix("")
    return {name: stem.parent / f"{stem.name}_{name}.png" for name in ("reliability_by_depth", "confusion",
                                                                      "reliability")}


def write_outputs(out: Path, sensor: SensorModel, counts: LabelDepthCounts, classes: ClassSet,
                  panels: list) -> list[Path]:
    """The figures (each atomic), then the YAML (atomic, last); returns the figures written. The folder of ``out``
    must exist (no folder is created). A failure (OSError) removes the figures this call wrote and is a CssError
    naming ``out``: no partial set of files is left."""
    from .plots import (confusion_bands_figure, reliability_by_depth_figure, reliability_panels_figure,
                        save_figure)

    paths = figure_paths(out)
    total = counts.fit + counts.heldout
    written: list[Path] = []
    try:
        save_figure(reliability_by_depth_figure(sensor, counts.fit, classes), paths["reliability_by_depth"])
        written.append(paths["reliability_by_depth"])
        save_figure(confusion_bands_figure(total, sensor.depth_edges, classes), paths["confusion"])
        written.append(paths["confusion"])
        if panels:
            save_figure(reliability_panels_figure(panels), paths["reliability"])
            written.append(paths["reliability"])
        sensor.save(out)
    except OSError as exc:
        for path in written:
            try:
                path.unlink()
            except OSError:
                pass
        raise CssError(f"cannot write --out {out} ({exc.strerror or exc}); nothing was written") from None
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point: 0 written, 1 refused (one line), 2 usage error."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
        try:
            error = option_error(args)
        except (ArithmeticError, ValueError) as exc:    # a combination no check foresaw: still a usage error
            error = f"bad options: {exc}"
        if error is not None:
            parser.error(error)
    except SystemExit as exc:
        return int(exc.code or 0)
    return run_console(PROG, lambda: calibrate(args))


if __name__ == "__main__":
    sys.exit(main())
