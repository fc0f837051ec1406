"""css_replay's run: replay a bag through CSS exactly as css_node would, evaluate, write the outputs.

Pass 1 fuses the first K frames (observe) and renders the rest, writing the node's output topics;
pass 2 renders every trained frame's pose with the final map (the paper's protocol).
"""
from __future__ import annotations

import json
import sys
import time
from collections import Counter
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np
from tqdm import tqdm

from ..engine.classes import ClassSet
from ..engine.gaussians import GaussianModel
from ..engine.semantic_map import RenderedView, SemanticMap
from ..engine.sensor_model import SensorModel
from ..engine.similarity import Similarity
from ..errors import CssError, MapError
from ..export.birdseye import render_birdseye
from ..export.bundle import export_map
from ..io.bag import BagWriter
from ..io.outputs import frame_output_images
from ..io.topics import output_topic
from ..io.trajectory import write_replay_trajectory
from .config import OUT_OF_RANGE_MAX_SHARE, ReplayConfig
from .evaluator import Evaluator, calibration_report, push_calibration
from .metrics import ConfusionMatrix, PixelSampler
from .source import Frame, FrameSource, check_label_range


def default_out_dir(bag: Path, sensor_model: Path | None = None) -> Path:
    """``out/replay_<bagname>`` for the paper's update, ``out/replay_<bagname>_<sensor-model stem>`` with a sensor
    model (runs of the two updates never overwrite each other); a bag directory named ``bag`` is named after its
    parent (``bags/demo/bag`` -> ``out/replay_demo``)."""
    bag = bag.resolve()
    name = bag.parent.name if bag.name == "bag" and bag.parent.name else bag.name
    suffix = "" if sensor_model is None else f"_{Path(sensor_model).stem}"
    return Path("out") / f"replay_{name}{suffix}"


def _progress(total: int | None, desc: str, quiet: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="frame", disable=quiet, dynamic_ncols=True, leave=True,
                file=sys.stderr)


def _write_outputs(obag: BagWriter, frame: Frame, view: RenderedView, classes: ClassSet, cfg: ReplayConfig) -> None:
    """The node's per-frame outputs, stamped with the segmentation stamp, under ``cfg.namespace``."""
    node = cfg.namespace.strip("/")
    ns = cfg.cameras[frame.camera_index].strip("/") if frame.camera_index < len(cfg.cameras) else ""
    prefix = f"{node}/{ns}" if ns else node
    s, f = frame.stamp_ns, frame.camera_frame
    for name, (array, encoding) in frame_output_images(view, classes, cfg.ignore_label).items():
        obag.write_image(output_topic(name, prefix), array, encoding, s, f)
    obag.write_view_points(output_topic("view_uncertainty", prefix), frame.position_map[None, :],
                           frame.quat_map[None, :], np.array([view.u_var]), np.array([view.u_exp]), s,
                           frame.map_frame)


#: the images css_replay evaluates and writes (the report's metrics and plots, the output bag's topics); the
#: engine does not make or copy the others (kappa_b, depth)
EVALUATED_IMAGES = ("labels", "expectation", "variance", "evidence", "rgb", "confidence")


class PaperBaseline:
    """The paper's update (no sensor model) fused on the same frames as the main map and evaluated the same way:
    online and fused accuracy / mIoU, pixel sparsification (AUSE) and calibration (ECE) of its E."""

    def __init__(self, smap: SemanticMap, cfg: ReplayConfig, classes: ClassSet) -> None:
        self.smap = smap
        self.cfg = cfg
        self.num_classes = classes.num_classes
        self.online_cm = ConfusionMatrix(classes.num_classes, cfg.ignore_label)
        #: the online renders' (right, E) samples; the same seed as the main map's, so the same pixels
        self.online_pixels = PixelSampler(max_samples=cfg.max_pixels, seed=cfg.seed + 1)
        self.evaluator = Evaluator(cfg, classes, [])  # the fused renders (every frame with the final map)

    def _online(self, frame: Frame, view: RenderedView) -> None:
        assert frame.gt is not None
        self.online_cm.update(frame.gt, view.labels)
        push_calibration(self.online_pixels, frame.gt, view, self.num_classes, self.cfg.ignore_label)

    def fuse(self, frame: Frame) -> None:
        """A training frame: update (and, with ground truth, render online at the same pose)."""
        if frame.gt is None:
            self.smap.update(frame.camera, frame.labels, frame.confidence, depth=frame.depth)
        else:
            self._online(frame, self.smap.observe(frame.camera, frame.labels, frame.confidence,
                                                  outputs=EVALUATED_IMAGES, depth=frame.depth))

    def heldout(self, frame: Frame) -> None:
        """A held-out frame (the map is final): its render is both online and fused."""
        if frame.gt is not None:
            view = self.smap.render(frame.camera, outputs=EVALUATED_IMAGES)
            self._online(frame, view)
            self.evaluator.add(frame, view, trained=False)

    def evaluate(self, frame: Frame) -> None:
        """Pass 2: a training frame's pose rendered with the final map."""
        if frame.gt is not None:
            self.evaluator.add(frame, self.smap.render(frame.camera, outputs=EVALUATED_IMAGES), trained=True)

    def report(self, class_names: Sequence[str]) -> dict[str, Any]:
        """metrics.json's ``paper_update``: the same sections as the main map's, for the paper's update."""
        return {
            "segmentation": {"online": self.online_cm.summary(class_names),
                             "fused": self.evaluator.css.summary(class_names)},
            "pixel_sparsification": self.evaluator.pixel_report(),
            "calibration": {"online": calibration_report(self.online_pixels),
                            "fused": calibration_report(self.evaluator.calibration_pixels)},
        }


@dataclass
class _Setup:
    """What a run needs before its first frame: the model, classes, maps, frame source and accumulators."""

    model: GaussianModel
    classes: ClassSet
    sensor: SensorModel | None
    smap: SemanticMap
    paper: PaperBaseline | None
    source: FrameSource
    expected: int  # frames the run will process
    train: int  # K: frames fused into the map
    evaluator: Evaluator
    input_cm: ConfusionMatrix
    online_cm: ConfusionMatrix  # the online renders written to the output bag
    online_pixels: PixelSampler


@dataclass
class _FusePass:
    """What pass 1 counted."""

    processed: int = 0
    trained: int = 0
    no_depth: int = 0  # labelled pixels without a rendered depth (sensor model only)
    transient: int = 0  # labelled pixels of a transient class (no evidence)
    occluded: int = 0  # labelled pixels whose measured depth is nearer than the map's (no evidence)
    #: (camera, U_var or None) of the fused frames, for css_view
    trajectory: list = field(default_factory=list)


def _setup(cfg: ReplayConfig) -> _Setup:
    """Load model, classes and sensor model; build the map (and the paper's baseline); open the frame source."""
    model = GaussianModel.from_ply(cfg.model)
    classes = ClassSet.from_yaml(cfg.classes) if cfg.classes else ClassSet.default(int(cfg.num_classes or 0))
    C = classes.num_classes
    extra: dict[str, Any] = {} if cfg.unknown_threshold is None else {"unknown_threshold": cfg.unknown_threshold}
    sensor = None if cfg.sensor_model is None else SensorModel.load(cfg.sensor_model, classes.names)
    depth_scale = float(cfg.splat_to_map[0])

    def new_map(sensor_model: SensorModel | None) -> SemanticMap:
        return SemanticMap(model, num_classes=C, prior=cfg.prior, background=cfg.background,
                           ignore_label=cfg.ignore_label, backend=cfg.backend, sensor_model=sensor_model,
                           depth_scale=depth_scale, transient_classes=cfg.transient_classes,
                           evidence_half_life=cfg.evidence_half_life, depth_tolerance=cfg.depth_tolerance,
                           depth_tolerance_relative=cfg.depth_tolerance_relative, **extra)

    smap = new_map(sensor)
    cfg.unknown_threshold = smap.unknown_threshold
    # the paper's update on the same frames, for the report's comparison (only with a sensor model)
    paper = PaperBaseline(new_map(None), cfg, classes) if sensor is not None and cfg.paper_baseline else None
    source = FrameSource(cfg)
    source.check()
    if not source.present.get("gt") and not cfg.quiet:
        print(f"css_replay: note: no ground-truth topic {cfg.topics['gt'] or '(disabled)'}; "
              "segmentation metrics are skipped", file=sys.stderr)
    expected = source.anchor_count if cfg.max_frames is None else min(source.anchor_count, cfg.max_frames)
    K = expected if cfg.train_frames is None else min(cfg.train_frames, expected)
    n_ex = min(cfg.examples, expected)
    example_indices = sorted({int(round(i)) for i in np.linspace(0, max(expected - 1, 0), n_ex)}) if n_ex else []
    return _Setup(model, classes, sensor, smap, paper, source, expected, K, Evaluator(cfg, classes, example_indices),
                  ConfusionMatrix(C, cfg.ignore_label), ConfusionMatrix(C, cfg.ignore_label),
                  PixelSampler(max_samples=cfg.max_pixels, seed=cfg.seed + 1))


def _fuse_pass(cfg: ReplayConfig, st: _Setup) -> _FusePass:
    """Pass 1: fuse the first K frames (observe), render the rest (the map is final for them: evaluated now);
    write the online outputs. Raises CssError when no frame was usable."""
    res = _FusePass()
    smap, C = st.smap, st.classes.num_classes
    # the surprise image is made only where the report measures it (a bag with the changed-class ground truth)
    outputs = EVALUATED_IMAGES + (("surprise",) if st.source.present.get("gt_changed") else ())
    bag_ctx = BagWriter(cfg.out / "bag") if cfg.output_bag else nullcontext()
    with bag_ctx as obag, _progress(st.expected, "fuse", cfg.quiet) as bar:
        for frame in st.source.frames() if st.expected > 0 else ():
            st.evaluator.change.add_input(frame.labels)
            online = obag is not None or frame.gt is not None or frame.gt_changed is not None
            view: RenderedView | None
            if frame.index < st.train:
                res.trajectory.append((frame.camera, None))
                if online:
                    view = smap.observe(frame.camera, frame.labels, frame.confidence, outputs=outputs,
                                        depth=frame.depth)
                    st.evaluator.change.add_observation(frame.index, frame.gt, frame.gt_changed, view.surprise)
                else:  # no online outputs wanted: skip the render (the evaluation renders in pass 2)
                    smap.update(frame.camera, frame.labels, frame.confidence, depth=frame.depth)
                    view = None
                last = smap.last_update
                if last is not None:
                    res.no_depth, res.transient, res.occluded = (res.no_depth + last.no_depth,
                                                                 res.transient + last.transient,
                                                                 res.occluded + last.occluded)
                res.trained += 1
                if st.paper is not None:
                    st.paper.fuse(frame)
            else:
                view = smap.render(frame.camera, outputs=EVALUATED_IMAGES)
                st.evaluator.add(frame, view, trained=False)  # map is final: evaluate now
                if st.paper is not None:
                    st.paper.heldout(frame)
            if frame.gt is not None:
                st.input_cm.update(frame.gt, frame.labels)
                if view is not None:
                    st.online_cm.update(frame.gt, view.labels)
                    push_calibration(st.online_pixels, frame.gt, view, C, cfg.ignore_label)
            if obag is not None and view is not None:
                _write_outputs(obag, frame, view, st.classes, cfg)
            if view is not None and frame.index < st.train:
                res.trajectory[-1] = (frame.camera, view.u_var)
            res.processed += 1
            bar.update(1)
            if cfg.max_frames is not None and res.processed >= cfg.max_frames:
                break
    if res.processed == 0:
        reasons = ", ".join(f"{k}={v}" for k, v in sorted(st.source.skips.items())) or "no synchronised frames"
        raise CssError(f"no usable frames in {cfg.bag} ({reasons})")
    return res


def _evaluate_pass(cfg: ReplayConfig, st: _Setup, trained: int) -> int:
    """Pass 2: render every trained frame's pose with the final map (the paper's protocol); returns the count."""
    evaluated = 0
    if trained:
        source2 = FrameSource(cfg)
        source2.present, source2.anchor_count = st.source.present, st.source.anchor_count
        source2.pose_type = st.source.pose_type
        with _progress(trained, "evaluate", cfg.quiet) as bar:
            for frame in source2.frames():
                st.evaluator.add(frame, st.smap.render(frame.camera, outputs=EVALUATED_IMAGES), trained=True)
                if st.paper is not None:
                    st.paper.evaluate(frame)
                evaluated += 1
                bar.update(1)
                if evaluated >= trained:
                    break
    st.evaluator.images.sort(key=lambda r: r["index"])
    st.evaluator.examples.sort(key=lambda r: r["index"])
    return evaluated


def _write_map_files(cfg: ReplayConfig, st: _Setup, trajectory: list) -> str | None:
    """Map, viewer files (semantic and uncertainty splats), trajectory and the bird's-eye picture (its file name,
    None when nothing was observed)."""
    st.smap.save(cfg.out / "map.npz")
    splat_to_map = Similarity.from_params(cfg.splat_to_map)
    write_replay_trajectory(cfg.out / "trajectory.npz", trajectory, splat_to_map)
    export_map(st.smap, st.classes, cfg.out, "map", formats=("semantic", "uncertainty"), splat_to_map=splat_to_map)
    return _birdseye(st.smap, st.classes, cfg.out / "birdseye.png", splat_to_map)


def _metrics(cfg: ReplayConfig, st: _Setup, fused: _FusePass, skips_pass1: Counter) -> dict[str, Any]:
    """metrics.json (all but the timings) from what the two passes accumulated."""
    names = st.classes.names
    source, evaluator = st.source, st.evaluator
    has_gt = st.input_cm.num_pixels > 0
    metrics: dict[str, Any] = {
        "bag": str(cfg.bag), "model": str(cfg.model), "num_gaussians": int(st.model.num_gaussians),
        "classes": list(names),
        "config": cfg.to_json(),
        "frames": {
            "segmentation_messages": source.anchor_count, "processed": fused.processed, "trained": fused.trained,
            "evaluated": len(evaluator.images), "heldout": fused.processed - fused.trained,
            "skipped": dict(sorted(skips_pass1.items())), "sync_counts": source.sync_counts,
            "topics_used": {k: (cfg.topics[k] if v else None) for k, v in source.present.items()},
            "out_of_range_labels": {"kinds": source.label_range.summary(), "max_share": OUT_OF_RANGE_MAX_SHARE,
                                    "allowed": cfg.allow_out_of_range},
        },
        "segmentation": {
            "miou_definition": "mean IoU over classes present in the GT or the prediction; pixels with GT = "
                               "ignore_label (or >= C) are excluded; predicted 'no label' counts as wrong",
            "input": st.input_cm.summary(names) if has_gt else None,
            "css": evaluator.css.summary(names) if has_gt else None,
            "css_online": st.online_cm.summary(names) if has_gt and st.online_cm.num_pixels else None,
            "css_definition": "css: every frame rendered with the FINAL map (after all training frames, the "
                              "paper's protocol); css_online: the renders published per frame (output bag), "
                              "made right after that frame's update",
        },
        "pixel_sparsification": evaluator.pixel_report(),
        "image_level": evaluator.image_report(),
    }
    metrics["sensor_model"] = None if st.sensor is None else {
        "file": str(cfg.sensor_model), "fingerprint": st.sensor.fingerprint, "description": st.sensor.describe(),
        "labelled_pixels_without_depth": fused.no_depth,
        "without_depth_rule": "a labelled pixel that no Gaussian covers has no rendered depth and adds nothing"}
    if st.paper is not None and has_gt:
        paper = st.paper.report(names)
        metrics["paper_update"] = paper
        metrics["segmentation"]["paper_online"] = paper["segmentation"]["online"]
        metrics["segmentation"]["paper_fused"] = paper["segmentation"]["fused"]
    if has_gt:
        metrics["calibration"] = {"online": calibration_report(st.online_pixels),
                                  "fused": calibration_report(evaluator.calibration_pixels),
                                  "definition": "probability that the rendered label is right: E of the argmax "
                                                "class, and the calibrated ~/confidence of the sensor model"}
    if has_gt and 0 < fused.trained < fused.processed:
        metrics["segmentation"]["css_trained_frames"] = evaluator.css_train.summary(names)
        metrics["segmentation"]["css_heldout_frames"] = evaluator.css_heldout.summary(names)
    metrics["changing_world"] = _changing_world(cfg, st, fused)
    return metrics


def _changing_world(cfg: ReplayConfig, st: _Setup, fused: _FusePass) -> dict[str, Any]:
    """metrics.json's ``changing_world``: the map's rules, what they held back, and the figures of
    :class:`~css_ros.evaluation.change_metrics.ChangeTally`."""
    depth_topic = cfg.topics.get("depth") if st.source.present.get("depth") else None
    return {
        "rules": {"transient_classes": [st.classes.names[c] for c in cfg.transient_classes],
                  "evidence_half_life": cfg.evidence_half_life, "depth_topic": depth_topic,
                  "depth_tolerance": cfg.depth_tolerance, "depth_tolerance_relative": cfg.depth_tolerance_relative},
        "fused_pixels_without_evidence": {"transient": fused.transient, "occluded": fused.occluded},
        **st.evaluator.change.summary(),
    }


def run(cfg: ReplayConfig) -> dict[str, Any]:
    """Replay ``cfg.bag``; write outputs into ``cfg.out``; return the metrics dict (also in metrics.json)."""
    from .report import make_plots, write_markdown  # matplotlib: imported only when a report is made

    t0 = time.perf_counter()
    st = _setup(cfg)
    cfg.out.mkdir(parents=True, exist_ok=True)
    t_load = time.perf_counter() - t0

    t1 = time.perf_counter()
    fused = _fuse_pass(cfg, st)
    t_fuse = time.perf_counter() - t1
    range_warning = check_label_range(st.source.label_range, OUT_OF_RANGE_MAX_SHARE, cfg.allow_out_of_range)
    if range_warning:
        print(range_warning, file=sys.stderr)

    t2 = time.perf_counter()
    skips_pass1 = Counter(st.source.skips)
    evaluated_train = _evaluate_pass(cfg, st, fused.trained)
    t_eval = time.perf_counter() - t2

    t3 = time.perf_counter()
    birdseye = _write_map_files(cfg, st, fused.trajectory)
    metrics = _metrics(cfg, st, fused, skips_pass1)
    metrics["timing"] = {
        "warmup_s": cfg.warmup_s, "compilation_excluded": cfg.warmup_s is not None,
        "load_s": t_load, "fuse_s": t_fuse, "fuse_fps": fused.processed / t_fuse if t_fuse > 0 else None,
        "evaluate_s": t_eval, "evaluate_fps": evaluated_train / t_eval if t_eval > 0 else None,
    }
    plots = make_plots(cfg.out, metrics, st.evaluator.examples, st.classes, cfg.ignore_label)
    if birdseye:
        plots.insert(0, ("The semantic map from above (observed Gaussians, rendered with the engine)", birdseye))
    metrics["timing"]["save_report_s"] = time.perf_counter() - t3
    metrics["timing"]["total_s"] = time.perf_counter() - t0
    write_markdown(cfg.out, metrics, plots)
    (cfg.out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=2))
    return metrics


def _birdseye(smap: SemanticMap, classes: ClassSet, path: Path, splat_to_map: Similarity) -> str | None:
    """Render the bird's-eye picture of the map; None (and a note on stderr) when nothing was observed."""
    try:
        render_birdseye(smap, classes, path, title="Semantic map, view from above", splat_to_map=splat_to_map)
    except MapError as exc:
        print(f"css_replay: note: no bird's-eye picture: {exc}", file=sys.stderr)
        return None
    return path.name


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (float, np.floating)):
        return float(x) if np.isfinite(x) else None
    if isinstance(x, Path):
        return str(x)
    return x


def _ece_text(summary: dict[str, Any]) -> str:
    """An ECE for the summary, saying how many pixels were left out for a NaN / inf value (never silently)."""
    ece = summary.get("ece")
    text = "n/a" if ece is None else f"{ece:.3f}"
    dropped = int(summary.get("dropped") or 0)
    return text + (f" ({dropped} pixels with a NaN / inf value left out)" if dropped else "")


def change_headline(cw: dict[str, Any]) -> str:
    """The headline's line on a changing world (report.md's section has the definitions and the reasons)."""
    def pct(rec: dict[str, Any]) -> str:
        return "n/a" if rec["value"] is None else f"{100 * rec['value']:.2f}%"

    sa = cw["surprise_auroc"]["value"]
    return (f"changing world: transient share {pct(cw['transient_share'])}, static accuracy "
            f"{pct(cw['static_accuracy'])}, changed objects in their new class {pct(cw['changed_accuracy'])}, "
            f"surprise AUROC {'n/a' if sa is None else f'{sa:.3f}'}")


def headline(metrics: dict[str, Any]) -> str:
    """One-paragraph summary printed at the end of a run."""
    lines = []
    seg = metrics["segmentation"]
    if seg.get("input") and seg.get("css"):
        i, c = seg["input"], seg["css"]
        lines.append(f"input segmentation: mIoU {100 * i['miou']:.1f}%  accuracy {100 * i['pixel_accuracy']:.1f}%")
        lines.append(f"CSS rendering:      mIoU {100 * c['miou']:.1f}%  accuracy {100 * c['pixel_accuracy']:.1f}%")
    if seg.get("css_online"):
        o = seg["css_online"]
        lines.append(f"CSS online:         mIoU {100 * o['miou']:.1f}%  accuracy {100 * o['pixel_accuracy']:.1f}%")
    if seg.get("paper_online") and seg.get("paper_fused"):
        po, pf = seg["paper_online"], seg["paper_fused"]
        lines.append(f"paper update:       online accuracy {100 * po['pixel_accuracy']:.1f}%, fused accuracy "
                     f"{100 * pf['pixel_accuracy']:.1f}% (the same frames without the sensor model)")
    px = metrics.get("pixel_sparsification")
    if px:
        a = px["ause"]
        lines.append("pixel AUSE (lower is better): " + "  ".join(
            f"{k} {a[k]:.4f}" for k in ("expectation", "variance", "evidence", "confidence", "random")
            if a.get(k) is not None))
    cal = (metrics.get("calibration") or {}).get("online")
    if cal:
        lines.append("ECE of the online renders: E " + _ece_text(cal["expectation"])
                     + (f", calibrated confidence {_ece_text(cal['confidence'])}" if cal.get("confidence") else ""))
    im = metrics["image_level"].get("spearman")
    if im:
        lines.append("image-level Spearman rho vs error: " + "  ".join(
            f"{k} {v:+.3f}" for k, v in im.items() if v is not None))
    cw = metrics.get("changing_world")
    if cw and (cw["rules"]["transient_classes"] or cw["rules"]["depth_topic"] or cw["rules"]["evidence_half_life"]
               or cw["changed_accuracy"]["value"] is not None):
        lines.append(change_headline(cw))
    f = metrics["frames"]
    skipped = sum(f["skipped"].values())
    lines.append(f"frames: {f['processed']} processed ({f['trained']} fused), {skipped} skipped; "
                 f"total {metrics['timing']['total_s']:.1f} s")
    return "\n".join(lines)
