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
from pathlib import Path
from typing import Any

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


def default_out_dir(bag: Path) -> Path:
    """``out/replay_<bagname>``; a bag directory named ``bag`` is named after its parent (``out/replay_demo``)."""
    bag = bag.resolve()
    name = bag.parent.name if bag.name == "bag" and bag.parent.name else bag.name
    return Path("out") / f"replay_{name}"


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


def run(cfg: ReplayConfig) -> dict[str, Any]:
    """Replay ``cfg.bag``; write outputs into ``cfg.out``; return the metrics dict (also in metrics.json)."""
    from .report import make_plots, write_markdown  # matplotlib: imported only when a report is made

    t0 = time.perf_counter()
    model = GaussianModel.from_ply(cfg.model)
    classes = ClassSet.from_yaml(cfg.classes) if cfg.classes else ClassSet.default(int(cfg.num_classes or 0))
    C = classes.num_classes
    extra: dict[str, Any] = {} if cfg.unknown_threshold is None else {"unknown_threshold": cfg.unknown_threshold}
    sensor = None if cfg.sensor_model is None else SensorModel.load(cfg.sensor_model, classes.names)
    depth_scale = float(cfg.splat_to_map[0])

    def new_map(sensor_model: SensorModel | None) -> SemanticMap:
        return SemanticMap(model, num_classes=C, prior=cfg.prior, background=cfg.background,
                           ignore_label=cfg.ignore_label, backend=cfg.backend, sensor_model=sensor_model,
                           depth_scale=depth_scale, **extra)

    smap = new_map(sensor)
    cfg.unknown_threshold = smap.unknown_threshold
    # the paper's update on the same frames, for the report's comparison (only with a sensor model)
    paper = new_map(None) if sensor is not None and cfg.paper_baseline else None
    paper_online_cm = ConfusionMatrix(C, cfg.ignore_label)
    paper_fused_cm = ConfusionMatrix(C, cfg.ignore_label)
    online_pixels = PixelSampler(max_samples=cfg.max_pixels, seed=cfg.seed + 1)
    no_depth = 0
    source = FrameSource(cfg)
    source.check()
    if not source.present.get("gt") and not cfg.quiet:
        print(f"css_replay: note: no ground-truth topic {cfg.topics['gt'] or '(disabled)'}; "
              "segmentation metrics are skipped", file=sys.stderr)
    expected = source.anchor_count if cfg.max_frames is None else min(source.anchor_count, cfg.max_frames)
    K = expected if cfg.train_frames is None else min(cfg.train_frames, expected)
    n_ex = min(cfg.examples, expected)
    example_indices = sorted({int(round(i)) for i in np.linspace(0, max(expected - 1, 0), n_ex)}) if n_ex else []
    evaluator = Evaluator(cfg, classes, example_indices)
    input_cm = ConfusionMatrix(C, cfg.ignore_label)
    online_cm = ConfusionMatrix(C, cfg.ignore_label)  # the online renders written to the output bag
    cfg.out.mkdir(parents=True, exist_ok=True)
    t_load = time.perf_counter() - t0

    # Pass 1: fuse the first K frames (observe), render the rest; write the online outputs.
    t1 = time.perf_counter()
    processed = trained = 0
    trajectory: list = []  # (camera, U_var or None) of the fused frames, for css_view
    bag_ctx = BagWriter(cfg.out / "bag") if cfg.output_bag else nullcontext()
    with bag_ctx as obag, _progress(expected, "fuse", cfg.quiet) as bar:
        for frame in source.frames() if expected > 0 else ():
            online = obag is not None or frame.gt is not None
            if frame.index < K:
                trajectory.append((frame.camera, None))
                if online:
                    view = smap.observe(frame.camera, frame.labels, frame.confidence)
                else:  # no online outputs wanted: skip the render (the evaluation renders in pass 2)
                    smap.update(frame.camera, frame.labels, frame.confidence)
                    view = None
                no_depth += smap.last_update.no_depth if smap.last_update is not None else 0
                trained += 1
                if paper is not None:
                    pview = paper.observe(frame.camera, frame.labels, frame.confidence) if frame.gt is not None \
                        else paper.update(frame.camera, frame.labels, frame.confidence)
                    if frame.gt is not None:
                        paper_online_cm.update(frame.gt, pview.labels)
            else:
                view = smap.render(frame.camera)
                evaluator.add(frame, view, trained=False)  # map is final: evaluate now
                if paper is not None and frame.gt is not None:
                    pview = paper.render(frame.camera)
                    paper_online_cm.update(frame.gt, pview.labels)
                    paper_fused_cm.update(frame.gt, pview.labels)
            if frame.gt is not None:
                input_cm.update(frame.gt, frame.labels)
                if view is not None:
                    online_cm.update(frame.gt, view.labels)
                    push_calibration(online_pixels, frame.gt, view, C, cfg.ignore_label)
            if obag is not None and view is not None:
                _write_outputs(obag, frame, view, classes, cfg)
            if view is not None and frame.index < K:
                trajectory[-1] = (frame.camera, view.u_var)
            processed += 1
            bar.update(1)
            if cfg.max_frames is not None and processed >= cfg.max_frames:
                break
    t_fuse = time.perf_counter() - t1
    if processed == 0:
        reasons = ", ".join(f"{k}={v}" for k, v in sorted(source.skips.items())) or "no synchronised frames"
        raise CssError(f"no usable frames in {cfg.bag} ({reasons})")
    range_warning = check_label_range(source.label_range, OUT_OF_RANGE_MAX_SHARE, cfg.allow_out_of_range)
    if range_warning:
        print(range_warning, file=sys.stderr)

    # Pass 2: render every trained frame's pose with the final map (paper protocol).
    t2 = time.perf_counter()
    skips_pass1 = Counter(source.skips)
    evaluated_train = 0
    if trained:
        source2 = FrameSource(cfg)
        source2.present, source2.anchor_count = source.present, source.anchor_count
        source2.pose_type = source.pose_type
        with _progress(trained, "evaluate", cfg.quiet) as bar:
            for frame in source2.frames():
                evaluator.add(frame, smap.render(frame.camera), trained=True)
                if paper is not None and frame.gt is not None:
                    paper_fused_cm.update(frame.gt, paper.render(frame.camera).labels)
                evaluated_train += 1
                bar.update(1)
                if evaluated_train >= trained:
                    break
    t_eval = time.perf_counter() - t2
    evaluator.images.sort(key=lambda r: r["index"])
    evaluator.examples.sort(key=lambda r: r["index"])

    # Map, viewer files (semantic and uncertainty splats) and the bird's-eye picture.
    t3 = time.perf_counter()
    smap.save(cfg.out / "map.npz")
    splat_to_map = Similarity.from_params(cfg.splat_to_map)
    write_replay_trajectory(cfg.out / "trajectory.npz", trajectory, splat_to_map)
    export_map(smap, classes, cfg.out, "map", formats=("semantic", "uncertainty"), splat_to_map=splat_to_map)
    birdseye = _birdseye(smap, classes, cfg.out / "birdseye.png", splat_to_map)

    has_gt = input_cm.num_pixels > 0
    metrics: dict[str, Any] = {
        "bag": str(cfg.bag), "model": str(cfg.model), "num_gaussians": int(model.num_gaussians),
        "classes": list(classes.names),
        "config": cfg.to_json(),
        "frames": {
            "segmentation_messages": source.anchor_count, "processed": processed, "trained": trained,
            "evaluated": len(evaluator.images), "heldout": processed - trained,
            "skipped": dict(sorted(skips_pass1.items())), "sync_counts": source.sync_counts,
            "topics_used": {k: (cfg.topics[k] if v else None) for k, v in source.present.items()},
            "out_of_range_labels": {"kinds": source.label_range.summary(), "max_share": OUT_OF_RANGE_MAX_SHARE,
                                    "allowed": cfg.allow_out_of_range},
        },
        "segmentation": {
            "miou_definition": "mean IoU over classes present in the GT or the prediction; pixels with GT = "
                               "ignore_label (or >= C) are excluded; predicted 'no label' counts as wrong",
            "input": input_cm.summary(classes.names) if has_gt else None,
            "css": evaluator.css.summary(classes.names) if has_gt else None,
            "css_online": online_cm.summary(classes.names) if has_gt and online_cm.num_pixels else None,
            "css_definition": "css: every frame rendered with the FINAL map (after all training frames, the "
                              "paper's protocol); css_online: the renders published per frame (output bag), "
                              "made right after that frame's update",
        },
        "pixel_sparsification": evaluator.pixel_report(),
        "image_level": evaluator.image_report(),
    }
    metrics["sensor_model"] = None if sensor is None else {
        "file": str(cfg.sensor_model), "fingerprint": sensor.fingerprint, "description": sensor.describe(),
        "labelled_pixels_without_depth": no_depth,
        "without_depth_rule": "a labelled pixel that no Gaussian covers has no rendered depth and adds nothing"}
    if paper is not None and has_gt:
        metrics["segmentation"]["paper_online"] = paper_online_cm.summary(classes.names)
        metrics["segmentation"]["paper_fused"] = paper_fused_cm.summary(classes.names)
    if has_gt:
        metrics["calibration"] = {"online": calibration_report(online_pixels),
                                  "fused": calibration_report(evaluator.calibration_pixels),
                                  "definition": "probability that the rendered label is right: E of the argmax "
                                                "class, and the calibrated ~/confidence of the sensor model"}
    if has_gt and 0 < trained < processed:
        metrics["segmentation"]["css_trained_frames"] = evaluator.css_train.summary(classes.names)
        metrics["segmentation"]["css_heldout_frames"] = evaluator.css_heldout.summary(classes.names)
    metrics["timing"] = {
        "warmup_s": cfg.warmup_s, "compilation_excluded": cfg.warmup_s is not None,
        "load_s": t_load, "fuse_s": t_fuse, "fuse_fps": processed / t_fuse if t_fuse > 0 else None,
        "evaluate_s": t_eval, "evaluate_fps": evaluated_train / t_eval if t_eval > 0 else None,
    }
    plots = make_plots(cfg.out, metrics, evaluator.examples, classes, cfg.ignore_label)
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
        lines.append("ECE of the online renders: E " + f"{cal['expectation']['ece']:.3f}"
                     + (f", calibrated confidence {cal['confidence']['ece']:.3f}" if cal.get("confidence") else ""))
    im = metrics["image_level"].get("spearman")
    if im:
        lines.append("image-level Spearman rho vs error: " + "  ".join(
            f"{k} {v:+.3f}" for k, v in im.items() if v is not None))
    f = metrics["frames"]
    skipped = sum(f["skipped"].values())
    lines.append(f"frames: {f['processed']} processed ({f['trained']} fused), {skipped} skipped; "
                 f"total {metrics['timing']['total_s']:.1f} s")
    return "\n".join(lines)
