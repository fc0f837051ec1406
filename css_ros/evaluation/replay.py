"""css_replay: replay a rosbag2 bag through the CSS engine, write the node's outputs and an evaluation report."""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from collections import Counter
from contextlib import nullcontext
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np
from tqdm import tqdm

from ..io.paths import find_demo_bag
from ..io.bag import CAMERA_INFO_TYPE, IMAGE_TYPE, POSE_STAMPED_TYPE, BagError, InputBag, OutputBag
from ..engine.camera import Camera
from ..engine.classes import ClassSet
from ..errors import CameraError, CssError, InputError
from ..engine.gaussians import GaussianModel
from ..io.messages import (COLOR_ENCODINGS, CONFIDENCE_ENCODINGS, LABEL_ENCODINGS, camera_info_to_intrinsics,
                       image_to_array, pose_to_arrays, stamp_to_ns)
from .metrics import ConfusionMatrix, PixelSampler, psnr, sparsification_report, spearman
from ..engine.semantic_map import RenderedView, SemanticMap
from ..io.sync import FrameSynchronizer


#: kind -> default topic (SPEC §8 names, absolute).
DEFAULT_TOPICS = {
    "image": "/image",
    "segmentation": "/segmentation",
    "confidence": "/segmentation_confidence",
    "camera_info": "/camera_info",
    "pose": "/pose",
    "gt": "/segmentation_gt",
}


# ----------------------------------------------------------------------------------------------
# Configuration
# ----------------------------------------------------------------------------------------------
@dataclass
class ReplayConfig:
    """Everything css_replay needs; the defaults are the CLI defaults (paths resolved in :func:`resolve_paths`)."""

    bag: Path
    model: Path
    classes: Path | None
    out: Path
    num_classes: int | None = None
    topics: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_TOPICS))
    train_frames: int | None = None
    max_frames: int | None = None
    prior: float = 1e-3
    background: float = 1e-3
    unknown_threshold: float | None = None  # None = engine default
    ignore_label: int = 255
    backend: str = "numba"
    output_bag: bool = True
    quiet: bool = False
    slop_ms: float = 50.0
    sync_queue: int = 100
    namespace: str = "/css_node"
    max_pixels: int = 4_000_000
    seed: int = 0
    examples: int = 4

    def to_json(self) -> dict[str, Any]:
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, Path):
                d[k] = str(v)
        return d


def default_out_dir(bag: Path) -> Path:
    """``out/replay_<bagname>``; a bag directory named ``bag`` is named after its parent (``out/replay_demo``)."""
    bag = bag.resolve()
    name = bag.parent.name if bag.name == "bag" and bag.parent.name else bag.name
    return Path("out") / f"replay_{name}"


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="css_replay",
        description="Replay a rosbag2 bag (sqlite3 or MCAP) through Continuous Semantic Splatting: fuse the "
                    "segmentation into the splat model, write the node's output topics to a bag and evaluate "
                    "against the ground-truth segmentation (metrics.json, plots, report.md).",
    )
    p.add_argument("bag", nargs="?", type=Path, default=None,
                   help="bag directory (default: the shipped demo bags/demo/bag)")
    p.add_argument("--model", type=Path, default=None, metavar="PLY",
                   help="INRIA 3DGS PLY model (default: <bag parent>/model.ply)")
    p.add_argument("--classes", type=Path, default=None, metavar="YAML",
                   help="class file YAML (default: <bag parent>/classes.yaml)")
    p.add_argument("--num-classes", type=int, default=None, metavar="N",
                   help="number of classes when no class file exists (anonymous names, generated palette)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output directory (default: out/replay_<bagname>)")
    for kind, topic in DEFAULT_TOPICS.items():
        opt = "--confidence-topic" if kind == "confidence" else f"--{kind.replace('_', '-')}-topic"
        p.add_argument(opt, dest=f"topic_{kind}", default=topic, metavar="TOPIC",
                       help=f"{kind} topic (default {topic})" + ("" if kind in ("segmentation", "pose", "camera_info")
                                                              else "; '' = do not use"))
    p.add_argument("--train-frames", type=int, default=None, metavar="K",
                   help="update the map with the first K frames only; all frames are evaluated (default: all)")
    p.add_argument("--max-frames", type=int, default=None, metavar="N", help="stop after this many usable frames")
    p.add_argument("--prior", type=float, default=1e-3, help="Dirichlet prior alpha_0 per class (default 1e-3)")
    p.add_argument("--background", type=float, default=1e-3, help="background concentration alpha_b (default 1e-3)")
    p.add_argument("--unknown-threshold", type=float, default=None,
                   help="label a rendered pixel 'no label' when its background weight kappa_b exceeds this "
                        "(default: the engine's, 0.5; 1.0 = never)")
    p.add_argument("--ignore-label", type=int, default=255, help="'no label' value of label images (default 255)")
    p.add_argument("--backend", choices=("numba", "torch"), default="numba", help="rasteriser backend")
    p.add_argument("--slop-ms", type=float, default=50.0,
                   help="max stamp difference [ms] between a segmentation and its pose/image/GT "
                        "(default 50, as css_node's sync_slop)")
    p.add_argument("--sync-queue", type=int, default=100, help="pending messages kept per topic while syncing")
    p.add_argument("--namespace", default="/css_node", help="namespace of the output topics (default /css_node)")
    p.add_argument("--max-pixels", type=int, default=4_000_000,
                   help="pixels kept (uniform random subsample, fixed seed) for pixel sparsification")
    p.add_argument("--seed", type=int, default=0, help="seed of the pixel subsample and the random baseline")
    p.add_argument("--examples", type=int, default=4, help="example frames in the report strip")
    p.add_argument("--no-output-bag", action="store_true", help="do not write the output bag")
    p.add_argument("--quiet", action="store_true", help="no progress bar, only errors and the final line")
    return p


def resolve_paths(args: argparse.Namespace) -> ReplayConfig:
    """Turn parsed CLI arguments into a :class:`ReplayConfig` (default paths resolved, values validated)."""
    bag = args.bag
    if bag is None:
        bag = find_demo_bag()
        if bag is None:
            raise CssError("no bag given and the demo bag bags/demo/bag was not found; "
                           "pass a bag directory (or generate the demo with css_make_demo)")
    bag = Path(bag)
    if not bag.exists():
        raise CssError(f"bag not found: {bag}")
    base = bag.resolve().parent if bag.is_dir() else bag.resolve().parent
    model = args.model if args.model is not None else base / "model.ply"
    if not Path(model).is_file():
        raise CssError(f"model not found: {model}" + ("" if args.model else " (pass --model)"))
    classes = args.classes
    if classes is None:
        classes = base / "classes.yaml"
        if not classes.is_file():
            if args.num_classes is None:
                raise CssError(f"class file not found: {classes} (pass --classes FILE or --num-classes N)")
            classes = None
    elif not Path(classes).is_file():
        raise CssError(f"class file not found: {classes}")
    for name in ("train_frames", "max_frames"):
        v = getattr(args, name)
        if v is not None and v < 0:
            raise CssError(f"--{name.replace('_', '-')} must be >= 0")
    if args.num_classes is not None and args.num_classes < 1:
        raise CssError("--num-classes must be >= 1")
    if args.prior <= 0 or args.background <= 0:
        raise CssError("--prior and --background must be > 0")
    topics = {kind: getattr(args, f"topic_{kind}") for kind in DEFAULT_TOPICS}
    for kind in ("segmentation", "pose", "camera_info"):
        if not topics[kind]:
            raise CssError(f"the {kind} topic is required")
    return ReplayConfig(
        bag=bag, model=Path(model), classes=Path(classes) if classes else None,
        out=args.out if args.out is not None else default_out_dir(bag), num_classes=args.num_classes,
        topics=topics, train_frames=args.train_frames, max_frames=args.max_frames, prior=args.prior,
        background=args.background, unknown_threshold=args.unknown_threshold, ignore_label=args.ignore_label,
        backend=args.backend, output_bag=not args.no_output_bag, quiet=args.quiet, slop_ms=args.slop_ms,
        sync_queue=max(1, args.sync_queue), namespace=args.namespace, max_pixels=max(1000, args.max_pixels),
        seed=args.seed, examples=max(0, args.examples),
    )


# ----------------------------------------------------------------------------------------------
# Frames from the bag
# ----------------------------------------------------------------------------------------------
@dataclass
class Frame:
    """One synchronised, decoded frame.

    Attributes:
        index: 0-based index among the usable frames of the bag.
        stamp_ns: segmentation header stamp [ns]; every output of the frame carries it.
        camera: intrinsics of the latest camera_info and T_map_cam from the pose.
        labels: (H, W) int32 input segmentation (class ids, ignore_label = no label).
        confidence: (H, W) float32 in [0, 1] or None.
        gt: (H, W) int32 ground-truth labels or None.
        rgb: (H, W, 3) uint8 camera image or None.
        camera_frame: frame_id of the segmentation header (optical frame).
        map_frame: frame_id of the pose header.
    """

    index: int
    stamp_ns: int
    camera: Camera
    labels: np.ndarray
    confidence: np.ndarray | None
    gt: np.ndarray | None
    rgb: np.ndarray | None
    camera_frame: str
    map_frame: str


class FrameSource:
    """Reads, synchronises (shared :class:`~css_ros.sync.FrameSynchronizer`) and decodes the frames of a bag.

    camera_info is not synchronised: the latest received one is used (frames before the first
    camera_info message use the first one). Frames that cannot be used are skipped and counted in
    :attr:`skips` by reason.
    """

    SYNC_KINDS = ("segmentation", "pose", "image", "confidence", "gt")

    def __init__(self, cfg: ReplayConfig) -> None:
        self.cfg = cfg
        self.skips: Counter[str] = Counter()
        self.sync_counts: dict[str, int] = {}
        self.undecodable: dict[str, int] = {}
        self.present: dict[str, bool] = {}
        self.anchor_count = 0

    def check(self) -> None:
        """Open the bag once: check topics and types, count segmentation messages (raises BagError)."""
        types = {"image": IMAGE_TYPE, "segmentation": IMAGE_TYPE, "confidence": IMAGE_TYPE,
                 "camera_info": CAMERA_INFO_TYPE, "pose": POSE_STAMPED_TYPE, "gt": IMAGE_TYPE}
        with InputBag(self.cfg.bag) as bag:
            for kind, topic in self.cfg.topics.items():
                required = kind in ("segmentation", "pose", "camera_info")
                self.present[kind] = bool(topic) and bag.check_topic(topic, types[kind], required)
            self.anchor_count = bag.topics()[self.cfg.topics["segmentation"]][1]

    def frames(self) -> Iterator[Frame]:
        """Yield the usable frames in stamp order (call :meth:`check` first)."""
        cfg = self.cfg
        kinds = [k for k in self.SYNC_KINDS if self.present.get(k)]
        sync = FrameSynchronizer(kinds, slop_ns=int(round(cfg.slop_ms * 1e6)), anchor="segmentation",
                                 queue_size=cfg.sync_queue)
        topic_kind = {cfg.topics[k]: k for k in kinds}
        cam_topic = cfg.topics["camera_info"]
        exhausted = False
        try:
            yield from self._iterate(bag_path=cfg.bag, sync=sync, topic_kind=topic_kind, cam_topic=cam_topic)
            exhausted = True
        finally:
            self._finish(sync, exhausted)

    def _iterate(self, bag_path: Path, sync: FrameSynchronizer, topic_kind: dict[str, str], cam_topic: str) -> Iterator[Frame]:
        index = 0
        with InputBag(bag_path) as bag:
            self.undecodable = bag.undecodable  # shared dict, filled while reading
            first = bag.messages([cam_topic])
            camera_info = next((m.msg for m in first), None)
            first.close()
            if camera_info is None:
                raise BagError(f"bag {bag_path}: no readable message on {cam_topic}")
            for m in bag.messages([*topic_kind, cam_topic]):
                if m.topic == cam_topic:
                    camera_info = m.msg
                    continue
                kind = topic_kind[m.topic]
                try:
                    stamp = stamp_to_ns(m.msg.header.stamp)
                except (AttributeError, TypeError, ValueError):
                    self.skips[f"bad_header_{kind}"] += 1
                    continue
                for synced in sync.push(kind, stamp, m.msg):
                    frame = self._decode(index, synced.stamp_ns, synced.items, camera_info)
                    if frame is not None:
                        index += 1
                        yield frame

    def _finish(self, sync: FrameSynchronizer, exhausted: bool) -> None:
        """Turn the synchroniser's diagnostics into skip counts (pending anchors only at the end of the bag)."""
        self.sync_counts = dict(sync.counts)
        if sync.counts.get("unmatched"):
            self.skips["unmatched_missing_pose_or_other_topic"] += sync.counts["unmatched"]
        pending = sync.pending().get("segmentation", 0)
        if exhausted and pending:
            self.skips["unmatched_at_end_of_bag"] += pending
        for k, v in sync.counts.items():
            if k.startswith(("stale_segmentation", "overflow_segmentation")):
                self.skips[k] += v
        for topic, n in self.undecodable.items():
            self.skips[f"undecodable_{topic}"] += n

    def _decode(self, index: int, stamp_ns: int, items: dict[str, Any], camera_info: Any) -> Frame | None:
        try:
            K, width, height = camera_info_to_intrinsics(camera_info)
        except (InputError, AttributeError, TypeError, ValueError):
            self.skips["bad_camera_info"] += 1
            return None
        seg_msg = items["segmentation"]
        arrays: dict[str, np.ndarray | None] = {"image": None, "confidence": None, "gt": None}
        allowed = {"segmentation": LABEL_ENCODINGS, "gt": LABEL_ENCODINGS, "confidence": CONFIDENCE_ENCODINGS,
                   "image": COLOR_ENCODINGS}
        for kind in ("segmentation", "gt", "confidence", "image"):
            if kind not in items:
                continue
            try:
                arrays[kind] = image_to_array(items[kind], allowed=allowed[kind])
            except (InputError, AttributeError, TypeError, ValueError):
                self.skips[f"bad_{kind}_message"] += 1
                return None
            a = arrays[kind]
            if a.shape[:2] != (height, width):
                self.skips["size_mismatch"] += 1
                return None
        if arrays["image"] is not None and arrays["image"].ndim == 2:  # mono8 camera image
            arrays["image"] = np.repeat(arrays["image"][:, :, None], 3, axis=2)
        pose_msg = items["pose"]
        try:
            position, quat = pose_to_arrays(pose_msg.pose)
            camera = Camera.from_pose(K, width, height, position, quat)
        except CameraError:
            self.skips["bad_pose_or_camera_info"] += 1
            return None
        except (AttributeError, TypeError, ValueError):
            self.skips["bad_pose_or_camera_info"] += 1
            return None
        confidence = arrays["confidence"]
        if confidence is not None:
            confidence = np.clip(np.nan_to_num(confidence.astype(np.float32), nan=0.0), 0.0, 1.0)
        gt = arrays["gt"]
        return Frame(
            index=index, stamp_ns=int(stamp_ns), camera=camera,
            labels=arrays["segmentation"].astype(np.int32), confidence=confidence,
            gt=gt.astype(np.int32) if gt is not None else None, rgb=arrays["image"],
            camera_frame=str(seg_msg.header.frame_id), map_frame=str(pose_msg.header.frame_id),
        )


# ----------------------------------------------------------------------------------------------
# Evaluation
# ----------------------------------------------------------------------------------------------
class Evaluator:
    """Accumulates CSS-vs-GT metrics of rendered views (pixel + image level) and the report's example frames."""

    def __init__(self, cfg: ReplayConfig, classes: ClassSet, example_indices: Sequence[int]) -> None:
        C = classes.num_classes
        self.cfg = cfg
        self.classes = classes
        self.css = ConfusionMatrix(C, cfg.ignore_label)
        self.css_train = ConfusionMatrix(C, cfg.ignore_label)
        self.css_heldout = ConfusionMatrix(C, cfg.ignore_label)
        self.pixels = PixelSampler(max_samples=cfg.max_pixels, seed=cfg.seed)
        self.images: list[dict[str, Any]] = []
        self.example_indices = set(example_indices)
        self.examples: list[dict[str, Any]] = []

    def add(self, frame: Frame, view: RenderedView, trained: bool) -> None:
        rec: dict[str, Any] = {
            "index": frame.index, "stamp_ns": frame.stamp_ns, "trained": trained,
            "u_var": float(view.u_var), "u_exp": float(view.u_exp), "error": None, "psnr": None,
        }
        if frame.rgb is not None:
            p = psnr(view.rgb, frame.rgb)
            rec["psnr"] = p if np.isfinite(p) else None
        if frame.gt is not None:
            gt = frame.gt
            (self.css_train if trained else self.css_heldout).update(gt, view.labels)
            self.css.update(gt, view.labels)
            valid = (gt >= 0) & (gt < self.classes.num_classes) & (gt != self.cfg.ignore_label)
            if valid.any():
                wrong = (view.labels[valid] != gt[valid])
                rec["error"] = float(wrong.mean())
                self.pixels.push(
                    wrong=wrong.astype(np.uint8),
                    expectation=-view.expectation[valid].astype(np.float32),
                    variance=view.variance[valid].astype(np.float32),
                    evidence=-view.evidence[valid].astype(np.float32),
                )
        self.images.append(rec)
        if frame.index in self.example_indices:
            self.examples.append({
                "index": frame.index, "rgb": frame.rgb, "gt": frame.gt, "input": frame.labels,
                "css": view.labels, "expectation": view.expectation, "variance": view.variance,
            })

    def pixel_report(self) -> dict[str, Any] | None:
        cols = self.pixels.columns()
        if not cols or cols["wrong"].size == 0:
            return None
        rep = sparsification_report(
            {"expectation": cols["expectation"], "variance": cols["variance"], "evidence": cols["evidence"]},
            cols["wrong"], random_seed=self.cfg.seed,
        )
        rep["uncertainty_definition"] = {"expectation": "-E (of the argmax class)", "variance": "Var (argmax class)",
                                         "evidence": "-evidence (observation-count baseline)",
                                         "random": "uniform random ordering (seeded)",
                                         "oracle": "actual error (wrong pixels first)"}
        rep["pixels_total"] = self.pixels.total_seen
        rep["subsampled"] = self.pixels.subsampled
        rep["keep_probability"] = self.pixels.keep_probability
        return rep

    def image_report(self) -> dict[str, Any]:
        recs = [r for r in self.images if r["error"] is not None]
        out: dict[str, Any] = {"frames": self.images, "num_evaluated": len(recs)}
        if len(recs) >= 2:
            err = np.array([r["error"] for r in recs])
            uv = np.array([r["u_var"] for r in recs])
            ue = np.array([r["u_exp"] for r in recs])
            out["spearman"] = {"u_var": _num(spearman(uv, err)), "u_exp": _num(spearman(ue, err))}
            out["sparsification"] = sparsification_report({"u_var": uv, "u_exp": ue}, err, random_seed=self.cfg.seed)
            out["error_definition"] = "per-image error = 1 - pixel accuracy of the CSS labels vs GT"
        return out


def _num(x: float) -> float | None:
    return float(x) if x is not None and np.isfinite(x) else None


def gaussian_semantics(concentrations: np.ndarray) -> dict[str, np.ndarray]:
    """Per-Gaussian top class and its Dirichlet moments.

    Args:
        concentrations: (N, C) alpha.
    Returns:
        class_id (N,) uint8 (int32 if C > 256), expectation (N,) float32 = alpha_top / S,
        variance (N,) float32 = E (1 - E) / (1 + S), with S = sum_c alpha_c.
    """
    alpha = np.asarray(concentrations, dtype=np.float64)
    S = alpha.sum(axis=1)
    top = np.argmax(alpha, axis=1)
    E = alpha[np.arange(alpha.shape[0]), top] / np.where(S > 0, S, 1.0)
    var = E * (1.0 - E) / (1.0 + S)
    dtype = np.uint8 if alpha.shape[1] <= 256 else np.int32
    return {"class_id": top.astype(dtype), "expectation": E.astype(np.float32), "variance": var.astype(np.float32)}


# ----------------------------------------------------------------------------------------------
# Orchestration
# ----------------------------------------------------------------------------------------------
def _progress(total: int | None, desc: str, quiet: bool) -> tqdm:
    return tqdm(total=total, desc=desc, unit="frame", disable=quiet, dynamic_ncols=True, leave=True,
                file=sys.stderr)


def _write_outputs(obag: OutputBag, frame: Frame, view: RenderedView, classes: ClassSet, cfg: ReplayConfig) -> None:
    C = classes.num_classes
    label_enc = "mono8" if max(C - 1, cfg.ignore_label) <= 255 else "mono16"
    labels = view.labels
    s, f = frame.stamp_ns, frame.camera_frame
    obag.write_image("semantic", labels, label_enc, s, f)
    obag.write_image("semantic_color", classes.colorize(labels, cfg.ignore_label), "rgb8", s, f)
    obag.write_image("expectation", view.expectation, "32FC1", s, f)
    obag.write_image("variance", view.variance, "32FC1", s, f)
    obag.write_image("rendered_image", view.rgb, "rgb8", s, f)
    cam = frame.camera
    obag.write_view_points("view_uncertainty", cam.position[None, :], cam.quaternion_xyzw[None, :],
                           np.array([view.u_var]), np.array([view.u_exp]), s, frame.map_frame)


def run(cfg: ReplayConfig) -> dict[str, Any]:
    """Replay ``cfg.bag``; write outputs into ``cfg.out``; return the metrics dict (also in metrics.json)."""
    from .report import make_plots, write_markdown  # matplotlib: imported only when a report is made

    t0 = time.perf_counter()
    model = GaussianModel.from_ply(cfg.model)
    classes = ClassSet.from_yaml(cfg.classes) if cfg.classes else ClassSet.default(int(cfg.num_classes or 0))
    C = classes.num_classes
    extra = {} if cfg.unknown_threshold is None else {"unknown_threshold": cfg.unknown_threshold}
    smap = SemanticMap(model, num_classes=C, prior=cfg.prior, background=cfg.background,
                       ignore_label=cfg.ignore_label, backend=cfg.backend, **extra)
    cfg.unknown_threshold = smap.unknown_threshold
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
    bag_ctx = OutputBag(cfg.out / "bag", namespace=cfg.namespace) if cfg.output_bag else nullcontext()
    with bag_ctx as obag, _progress(expected, "fuse", cfg.quiet) as bar:
        for frame in source.frames() if expected > 0 else ():
            if frame.index < K:
                if obag is not None:
                    view = smap.observe(frame.camera, frame.labels, frame.confidence)
                else:  # no online outputs wanted: skip the render (the evaluation renders in pass 2)
                    smap.update(frame.camera, frame.labels, frame.confidence)
                    view = None
                trained += 1
            else:
                view = smap.render(frame.camera)
                evaluator.add(frame, view, trained=False)  # map is final: evaluate now
            if frame.gt is not None:
                input_cm.update(frame.gt, frame.labels)
                if view is not None:
                    online_cm.update(frame.gt, view.labels)
            if obag is not None and view is not None:
                _write_outputs(obag, frame, view, classes, cfg)
            processed += 1
            bar.update(1)
            if cfg.max_frames is not None and processed >= cfg.max_frames:
                break
    t_fuse = time.perf_counter() - t1
    if processed == 0:
        reasons = ", ".join(f"{k}={v}" for k, v in sorted(source.skips.items())) or "no synchronised frames"
        raise CssError(f"no usable frames in {cfg.bag} ({reasons})")

    # Pass 2: render every trained frame's pose with the final map (paper protocol).
    t2 = time.perf_counter()
    skips_pass1 = Counter(source.skips)
    evaluated_train = 0
    if trained:
        source2 = FrameSource(cfg)
        source2.present, source2.anchor_count = source.present, source.anchor_count
        with _progress(trained, "evaluate", cfg.quiet) as bar:
            for frame in source2.frames():
                evaluator.add(frame, smap.render(frame.camera), trained=True)
                evaluated_train += 1
                bar.update(1)
                if evaluated_train >= trained:
                    break
    t_eval = time.perf_counter() - t2
    evaluator.images.sort(key=lambda r: r["index"])
    evaluator.examples.sort(key=lambda r: r["index"])

    # Map + semantic PLY.
    t3 = time.perf_counter()
    smap.save(cfg.out / "map.npz")
    model.to_ply(cfg.out / "semantic_model.ply", extra_fields=gaussian_semantics(smap.concentrations))

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
    if has_gt and 0 < trained < processed:
        metrics["segmentation"]["css_trained_frames"] = evaluator.css_train.summary(classes.names)
        metrics["segmentation"]["css_heldout_frames"] = evaluator.css_heldout.summary(classes.names)
    metrics["timing"] = {
        "load_s": t_load, "fuse_s": t_fuse, "fuse_fps": processed / t_fuse if t_fuse > 0 else None,
        "evaluate_s": t_eval, "evaluate_fps": evaluated_train / t_eval if t_eval > 0 else None,
    }
    plots = make_plots(cfg.out, metrics, evaluator.examples, classes, cfg.ignore_label)
    metrics["timing"]["save_report_s"] = time.perf_counter() - t3
    metrics["timing"]["total_s"] = time.perf_counter() - t0
    write_markdown(cfg.out, metrics, plots)
    (cfg.out / "metrics.json").write_text(json.dumps(_jsonable(metrics), indent=2))
    return metrics


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
    px = metrics.get("pixel_sparsification")
    if px:
        a = px["ause"]
        lines.append("pixel AUSE (lower is better): " + "  ".join(
            f"{k} {a[k]:.4f}" for k in ("expectation", "variance", "evidence", "random") if a.get(k) is not None))
    im = metrics["image_level"].get("spearman")
    if im:
        lines.append("image-level Spearman rho vs error: " + "  ".join(
            f"{k} {v:+.3f}" for k, v in im.items() if v is not None))
    f = metrics["frames"]
    skipped = sum(f["skipped"].values())
    lines.append(f"frames: {f['processed']} processed ({f['trained']} fused), {skipped} skipped; "
                 f"total {metrics['timing']['total_s']:.1f} s")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    """Console entry point; returns the process exit code (0 ok, 1 runtime error, 2 usage error)."""
    parser = build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # argparse already printed the usage message
        return int(exc.code or 0)
    try:
        cfg = resolve_paths(args)
        metrics = run(cfg)
    except CssError as exc:
        print(f"css_replay: error: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"css_replay: error: {exc.strerror or exc}: {exc.filename or ''}".rstrip(": "), file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("css_replay: interrupted", file=sys.stderr)
        return 130
    except Exception as exc:  # noqa: BLE001 - last resort: one line for the user, traceback on request
        if os.environ.get("CSS_REPLAY_DEBUG"):
            raise
        print(f"css_replay: error: unexpected {type(exc).__name__}: {exc} "
              "(set CSS_REPLAY_DEBUG=1 for the traceback)", file=sys.stderr)
        return 1
    print(headline(metrics))
    report = (cfg.out / "report.md").resolve()
    print(f"report: {report}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
