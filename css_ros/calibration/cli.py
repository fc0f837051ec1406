"""``css_calibrate``: learn the segmenter's sensor model (and the calibrated confidence map) from labelled bags.

Writes ``--out`` (YAML, read by css_node's ``sensor_model`` parameter and css_replay's ``--sensor-model``) and,
beside it, ``<stem>_reliability_by_depth.png``, ``<stem>_confusion.png`` and ``<stem>_reliability.png``. Every
file is written atomically, the YAML last: a failed run leaves no partial file.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from ..console import run_console
from ..engine.classes import ClassSet
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import SemanticMap
from ..engine.sensor_model import SensorModel, uniform_edges
from ..errors import ConfigError, CssError
from ..evaluation import cli as replay_cli
from ..evaluation.calibration_metrics import ReliabilityBins
from ..evaluation.config import ReplayConfig
from ..evaluation.source import FrameSource
from .learn import (DEFAULT_VOTES, VOTE_KINDS, DEFAULT_BIN_WIDTH, DEFAULT_HELDOUT_EVERY, DEFAULT_MAX_DEPTH, DEFAULT_PSEUDO_COUNT,
                    DEFAULT_WEIGHT_FLOOR, MIN_LABELLED_PIXELS, ConfidenceSamples, LabelDepthCounts, fit_confidence,
                    extrapolated_bins, fit_sensor_model, fused_frames, is_heldout, label_reliability, label_samples,
                    right_rates)

PROG = "css_calibrate"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog=PROG,
        description="Learn how reliable the segmentation is per class and depth from labelled bags (the bags carry "
                    "/segmentation_gt; css_import --gt makes such bags from image folders), and calibrate the map's "
                    "confidence. Each bag's model.ply and classes.yaml are found as css_replay finds them.",
        epilog="Example: css_calibrate bags/calib_range/bag --out sensor_model.yaml; then css_replay BAG "
               "--sensor-model sensor_model.yaml, or css_node with sensor_model:=sensor_model.yaml")
    p.add_argument("bags", nargs="+", type=Path, metavar="BAG", help="labelled bag directories")
    p.add_argument("--out", type=Path, required=True, metavar="YAML", help="sensor model file to write")
    p.add_argument("--model", type=Path, default=None, metavar="PLY",
                   help="splat model (only with one bag; default: <bag parent>/model.ply)")
    p.add_argument("--classes", default=None, metavar="YAML",
                   help="class file (default: <bag parent>/classes.yaml; every bag must have the same classes)")
    p.add_argument("--bin-width", type=float, default=DEFAULT_BIN_WIDTH, metavar="M",
                   help=f"depth-bin width in metres (default {DEFAULT_BIN_WIDTH:g})")
    p.add_argument("--max-depth", type=float, default=DEFAULT_MAX_DEPTH, metavar="M",
                   help=f"last bin edge in metres; deeper pixels fall in the last bin (default {DEFAULT_MAX_DEPTH:g})")
    p.add_argument("--votes", choices=VOTE_KINDS, default=DEFAULT_VOTES,
                   help="how a vote is spread over the classes: symmetric (default: p on the label, the rest evenly "
                        "on the others), onehot (the label only) or confusion (the rows p(true class | label, depth))")
    p.add_argument("--per-class", action="store_true",
                   help="weights per label and depth (default: per depth, the same for every label)")
    p.add_argument("--pseudo-count", type=float, default=DEFAULT_PSEUDO_COUNT, metavar="N",
                   help="smoothing of sparse (label, depth) bins toward their neighbours and the class rate, in "
                        f"pixels (default {DEFAULT_PSEUDO_COUNT:g})")
    p.add_argument("--weight-floor", type=float, default=DEFAULT_WEIGHT_FLOOR, metavar="W",
                   help=f"vote weight of labels no better than chance (default {DEFAULT_WEIGHT_FLOOR:g})")
    p.add_argument("--heldout-every", type=int, default=DEFAULT_HELDOUT_EVERY, metavar="K",
                   help=f"hold out every K-th frame of each bag for the before/after calibration (default "
                        f"{DEFAULT_HELDOUT_EVERY}; 0 = none)")
    p.add_argument("--no-confidence", action="store_true",
                   help="skip the second pass that fits the calibrated confidence map (~/confidence)")
    p.add_argument("--gt-topic", default=None, metavar="TOPIC", help="ground-truth topic (default /segmentation_gt)")
    p.add_argument("--segmentation-topic", default=None, metavar="TOPIC",
                   help="segmentation topic (default /segmentation)")
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
    cfg = replay_cli.resolve_paths(replay_cli.build_parser().parse_args(argv))
    if cfg.classes is None:
        raise ConfigError(f"{bag}: no class file (pass --classes)")
    return cfg


def check_options(args: argparse.Namespace) -> None:
    if args.model is not None and len(args.bags) > 1:
        raise ConfigError("--model applies to one bag; with several, each bag's parent holds its model.ply")
    if not (args.bin_width > 0 and args.max_depth > args.bin_width):
        raise ConfigError("--bin-width must be > 0 and --max-depth larger than it")
    if not 0 <= args.weight_floor <= 1:
        raise ConfigError("--weight-floor must be in [0, 1]")
    if not args.pseudo_count >= 0:
        raise ConfigError("--pseudo-count must be >= 0")
    if args.heldout_every < 0 or args.heldout_every == 1:
        raise ConfigError("--heldout-every must be 0 (none) or >= 2")
    if args.out.suffix.lower() not in (".yaml", ".yml"):
        raise ConfigError(f"--out {args.out}: expected a .yaml file")


def _frames(cfg: ReplayConfig, what: str, quiet: bool) -> Any:
    source = FrameSource(cfg)
    source.check()
    if not source.present.get("gt"):
        raise CssError(f"{cfg.bag} has no ground-truth topic {cfg.topics['gt'] or '(none)'}: css_calibrate needs "
                       "labelled frames")
    return tqdm(source.frames(), total=source.anchor_count, desc=f"{what} {cfg.bag.parent.name or cfg.bag.name}",
                unit="frame", disable=quiet, file=sys.stderr, dynamic_ncols=True)


def collect(configs: list[ReplayConfig], edges: np.ndarray, num_classes: int, heldout_every: int,
            quiet: bool) -> LabelDepthCounts:
    """Pass 1: (label, depth bin, ground truth) counts of every labelled frame of every bag."""
    counts = LabelDepthCounts(num_classes, edges)
    for cfg in configs:
        model = GaussianModel.from_ply(cfg.model)
        smap = SemanticMap(model, num_classes, ignore_label=cfg.ignore_label, depth_scale=float(cfg.splat_to_map[0]))
        for frame in _frames(cfg, "statistics", quiet):
            if frame.gt is None:
                continue
            depth = smap.render(frame.camera, outputs=("depth",)).depth
            assert depth is not None  # the numba backend always renders depth
            counts.add(frame.labels, frame.gt, depth, is_heldout(frame.index, heldout_every))
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
    counts = collect(configs, edges, classes.num_classes, args.heldout_every, args.quiet)
    fit_pixels = int(counts.fit.sum())
    if fit_pixels < MIN_LABELLED_PIXELS:
        raise CssError(f"too few labelled pixels to calibrate: {fit_pixels} with a ground truth and a rendered depth "
                       f"in {counts.frames_fit} fitting frames (need {MIN_LABELLED_PIXELS})")
    sensor = fit_sensor_model(counts, classes.names, votes=args.votes, per_class=args.per_class,
                              pseudo_count=args.pseudo_count, weight_floor=args.weight_floor)
    conf, ok = label_samples(counts.heldout if counts.frames_heldout else counts.fit,
                             right_rates(counts.fit, args.pseudo_count))
    labels_report = label_reliability(conf, ok)
    info: dict[str, Any] = {
        "bags": [str(c.bag) for c in configs], "frames_fit": counts.frames_fit,
        "frames_heldout": counts.frames_heldout, "heldout_every": args.heldout_every, "pixels_fit": fit_pixels,
        "pixels_heldout": int(counts.heldout.sum()), "pixels_without_depth": counts.no_depth,
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
          f"{counts.no_depth} labelled pixels had no rendered depth")
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
    """The figures (each atomic), then the YAML (atomic, last); returns the figures written."""
    from .plots import (confusion_bands_figure, reliability_by_depth_figure, reliability_panels_figure,
                        save_figure)

    out.parent.mkdir(parents=True, exist_ok=True)
    paths = figure_paths(out)
    total = counts.fit + counts.heldout
    save_figure(reliability_by_depth_figure(sensor, counts.fit, classes), paths["reliability_by_depth"])
    save_figure(confusion_bands_figure(total, sensor.depth_edges, classes), paths["confusion"])
    written = [paths["reliability_by_depth"], paths["confusion"]]
    if panels:
        save_figure(reliability_panels_figure(panels), paths["reliability"])
        written.append(paths["reliability"])
    sensor.save(out)
    return written


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point: 0 written, 1 refused (one line), 2 usage error."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:
        return int(exc.code or 0)
    return run_console(PROG, lambda: calibrate(args))


if __name__ == "__main__":
    sys.exit(main())
