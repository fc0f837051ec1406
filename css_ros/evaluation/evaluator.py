"""Accumulates the CSS-vs-GT metrics of rendered views (pixel and image level) and the report's example frames."""
from __future__ import annotations

from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from ..engine.classes import ClassSet
from .metrics import ConfusionMatrix, PixelSampler, finite_or_none, psnr, sparsification_report, spearman

if TYPE_CHECKING:
    from ..engine.semantic_map import RenderedView
    from .config import ReplayConfig
    from .source import Frame


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
            out["spearman"] = {"u_var": finite_or_none(spearman(uv, err)), "u_exp": finite_or_none(spearman(ue, err))}
            out["sparsification"] = sparsification_report({"u_var": uv, "u_exp": ue}, err, random_seed=self.cfg.seed)
            out["error_definition"] = "per-image error = 1 - pixel accuracy of the CSS labels vs GT"
        return out
