"""Accumulates the CSS-vs-GT metrics of rendered views (pixel and image level) and the report's example frames."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ..engine.classes import ClassSet
from .calibration_metrics import calibration_summary
from .change_metrics import ChangeTally
from .metrics import ConfusionMatrix, PixelSampler, finite_or_none, psnr, sparsification_report, spearman

if TYPE_CHECKING:
    from ..engine.semantic_map import RenderedView
    from .config import ReplayConfig
    from .source import Frame


def push_calibration(sampler: PixelSampler, gt: np.ndarray, view: RenderedView, num_classes: int,
                     ignore_label: int) -> None:
    """Add one rendered view's (right, E, confidence) pixel samples (GT-labelled pixels only) to ``sampler``."""
    valid = (gt >= 0) & (gt < num_classes) & (gt != ignore_label)
    if not np.any(valid):
        return
    cols = {"right": (view.labels[valid] == gt[valid]).astype(np.uint8),
            "expectation": view.expectation[valid].astype(np.float32)}
    if view.confidence is not None:
        cols["confidence"] = view.confidence[valid].astype(np.float32)
    sampler.push(**cols)


def calibration_report(sampler: PixelSampler) -> dict[str, Any] | None:
    """ECE / Brier / reliability bins of E and (when present) the calibrated confidence, from ``sampler``."""
    cols = sampler.columns()
    if not cols or cols["right"].size == 0:
        return None
    right = cols["right"].astype(np.float64)
    out = {"expectation": calibration_summary(cols["expectation"].astype(np.float64), right),
           "confidence": None, "pixels": int(right.size), "pixels_total": sampler.total_seen}
    if "confidence" in cols:
        out["confidence"] = calibration_summary(cols["confidence"].astype(np.float64), right)
    return out


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
        #: (right, E, confidence) of the fused renders, for the calibration report (ECE, reliability diagram)
        self.calibration_pixels = PixelSampler(max_samples=cfg.max_pixels, seed=cfg.seed + 2)
        self.images: list[dict[str, Any]] = []
        self.example_indices = set(example_indices)
        self.examples: list[dict[str, Any]] = []
        #: the changing-world figures of the same renders (transient share, static / changed accuracy)
        self.change = ChangeTally(C, cfg.ignore_label, cfg.transient_classes, classes.names)

    def add(self, frame: Frame, view: RenderedView, trained: bool) -> None:
        rec: dict[str, Any] = {
            "index": frame.index, "stamp_ns": frame.stamp_ns, "trained": trained,
            "u_var": float(view.u_var), "u_exp": float(view.u_exp), "error": None, "psnr": None,
        }
        self.change.add_render(view.labels, frame.gt, frame.gt_changed)
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
                cols = {"wrong": wrong.astype(np.uint8), "expectation": -view.expectation[valid].astype(np.float32),
                        "variance": view.variance[valid].astype(np.float32),
                        "evidence": -view.evidence[valid].astype(np.float32)}
                if view.confidence is not None:
                    cols["confidence"] = -view.confidence[valid].astype(np.float32)
                self.pixels.push(**cols)
                push_calibration(self.calibration_pixels, gt, view, self.classes.num_classes, self.cfg.ignore_label)
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
        signals = {k: cols[k] for k in ("expectation", "variance", "evidence", "confidence") if k in cols}
        rep = sparsification_report(signals, cols["wrong"], random_seed=self.cfg.seed)
        rep["uncertainty_definition"] = {"expectation": "-E (of the argmax class)", "variance": "Var (argmax class)",
                                         "evidence": "-evidence (observation-count baseline)",
                                         "confidence": "-calibrated confidence (sensor model's confidence map)",
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
            out["spearman"] = {"u_var": finite_or_none(spearman(uv, err)), "u_exp": finite_or_none(spearman(ue, err))}
            out["sparsification"] = sparsification_report({"u_var": uv, "u_exp": ue}, err, random_seed=self.cfg.seed)
            out["error_definition"] = "per-image error = 1 - pixel accuracy of the CSS labels vs GT"
        return out
