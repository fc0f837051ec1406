"""What css_calibrate learns from labelled frames: label x depth statistics, the sensor model, the confidence map.

Two passes over the labelled frames of one or more bags (each bag on its own splat model):

1. **Label statistics.** Each frame is rendered at its pose (an empty map: only the expected depth image
   ``RenderedView.depth`` is used), and every pixel with an input label y < C, a ground-truth label c < C and a
   rendered depth d adds one to ``counts[y, bin(d), c]``. Pixels without a rendered depth are counted apart
   (the update adds nothing for them either). With a measured depth, pixels nearer than the rendered surface by
   more than the map's depth tolerance (:func:`in_front_of_map`: a passer-by, which the static ground truth does not
   show) are counted apart too: the update adds nothing for them. Every ``heldout_every``-th frame goes into
   held-out counts instead.
2. **Confidence map.** The frames are fused again in order with the new sensor model and the measured depth (as
   css_node / css_replay would); each online render's pixels give (E of the argmax, evidence, label right?) samples,
   from which the
   :class:`~css_ros.engine.sensor_model.ConfidenceMap` is fitted on the fitting frames and judged on the held-out ones.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np

from ..engine.change_rules import DEFAULT_DEPTH_TOLERANCE, DEFAULT_DEPTH_TOLERANCE_RELATIVE
from ..engine.sensor_model import ConfidenceMap, SensorModel, depth_bins
from ..evaluation.calibration_metrics import calibration_summary
from ..evaluation.metrics import PixelSampler
from .fit import isotonic_fit, logistic_fit, reliability_weight, smoothed_rates

if TYPE_CHECKING:
    from ..engine.semantic_map import RenderedView, SemanticMap

#: Every this-many-th labelled frame is held out (index % HELDOUT_EVERY == HELDOUT_EVERY - 1).
DEFAULT_HELDOUT_EVERY = 5
#: Depth bins: this width [m] from 0 to DEFAULT_MAX_DEPTH (deeper pixels fall in the last bin).
DEFAULT_BIN_WIDTH = 0.5
DEFAULT_MAX_DEPTH = 8.0
#: Pseudo-count τ of the smoothing of sparse (label, depth bin) rows (fit.smoothed_rates) [pixels].
DEFAULT_PSEUDO_COUNT = 200.0
#: Weight of a vote no better than chance (2p - 1 <= floor): far-only surfaces still get a label, and one
#: reliable near view (w ~ 0.9) outweighs ~ 0.9 / floor of them.
DEFAULT_WEIGHT_FLOOR = 0.02
#: Fewest labelled pixels (with depth) in the fitting frames css_calibrate accepts.
MIN_LABELLED_PIXELS = 20_000
#: Most per-pixel samples kept for the confidence fit (uniform subsample beyond).
MAX_CONFIDENCE_SAMPLES = 2_000_000


def is_heldout(index: int, every: int) -> bool:
    """True when labelled frame ``index`` (0-based, per bag) is held out of the fits."""
    return every > 0 and index % every == every - 1


def in_front_of_map(measured: np.ndarray, rendered: np.ndarray, tol_abs: float = DEFAULT_DEPTH_TOLERANCE,
                    tol_rel: float = DEFAULT_DEPTH_TOLERANCE_RELATIVE) -> np.ndarray:
    """(H, W) bool: the pixels whose measured depth is nearer than the map's rendered depth by more than
    max(tol_abs, tol_rel x measured) (both (H, W) metres): the pixels
    :func:`css_ros.engine.change_rules.depth_gate` calls occluded. Without a measurement (not finite or <= 0) or a
    rendered depth (NaN): False."""
    m = np.asarray(measured, dtype=np.float64)
    r = np.asarray(rendered, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        has = (m > 0) & (m != np.inf) & ~np.isnan(r)
        return has & (m < r - np.maximum(tol_abs, tol_rel * m))


@dataclass
class LabelDepthCounts:
    """Pixel counts of (input label y, depth bin b, ground truth c) for fitting and held-out frames.

    Attributes:
        fit, heldout: (C, B, C) int64.
        no_depth: labelled pixels without rendered depth (not counted above).
        in_front: labelled pixels whose measured depth is nearer than the map's surface (not counted above).
        frames_fit, frames_heldout: frames that added to each.
    """

    num_classes: int
    edges: np.ndarray
    fit: np.ndarray = field(init=False)
    heldout: np.ndarray = field(init=False)
    no_depth: int = 0
    in_front: int = 0
    frames_fit: int = 0
    frames_heldout: int = 0

    def __post_init__(self) -> None:
        b = self.edges.size - 1
        self.fit = np.zeros((self.num_classes, b, self.num_classes), dtype=np.int64)
        self.heldout = np.zeros_like(self.fit)

    def add(self, labels: np.ndarray, gt: np.ndarray, depth: np.ndarray, heldout: bool,
            in_front: np.ndarray | None = None) -> None:
        """Count one frame: labels, gt (H, W) ints; depth (H, W) rendered metres (NaN = none); ``in_front`` (H, W)
        bool, the pixels to leave out as in front of the map's surface (:func:`in_front_of_map`), or None."""
        c, b = self.num_classes, self.edges.size - 1
        lab = labels.astype(np.int64).ravel()
        tru = gt.astype(np.int64).ravel()
        d = depth.astype(np.float64).ravel()
        valid = (lab >= 0) & (lab < c) & (tru >= 0) & (tru < c)
        if in_front is not None:
            front = np.asarray(in_front, dtype=bool).ravel()
            self.in_front += int(np.count_nonzero(valid & front))
            valid &= ~front
        has_depth = np.isfinite(d)
        self.no_depth += int(np.count_nonzero(valid & ~has_depth))
        keep = valid & has_depth
        bins = depth_bins(self.edges, d[keep])
        flat = (lab[keep] * b + bins) * c + tru[keep]
        target = self.heldout if heldout else self.fit
        target += np.bincount(flat, minlength=c * b * c).reshape(c, b, c)
        if heldout:
            self.frames_heldout += 1
        else:
            self.frames_fit += 1


def depth_reliability(counts: np.ndarray, pseudo_count: float = DEFAULT_PSEUDO_COUNT) -> np.ndarray:
    """(B,) fraction of right labels per depth bin over all classes, smoothed like the per-class rates."""
    c = counts.shape[0]
    right = counts[np.arange(c), :, np.arange(c)].sum(axis=0).astype(np.float64)   # (B,)
    total = counts.sum(axis=(0, 2)).astype(np.float64)
    two = np.stack([right, total - right], axis=-1)[None]                             # (1, B, 2)
    return smoothed_rates(two, pseudo_count)[0, :, 0]


#: How the sensor-model YAML describes the values of depth bins without data (its ``calibration.extrapolated``).
EXTRAPOLATION_RULE = ("no labelled pixel in these depth bins: their values follow the neighbouring bins with data "
                      "(linear between them, the last bin's value beyond), not measured")


def extrapolated_bins(counts: np.ndarray, edges: np.ndarray, class_names: Iterable[str],
                      per_class: bool = False) -> dict[str, Any]:
    """The depth bins whose p and w are extrapolated (no fitting pixel), for the YAML's ``calibration`` section:
    ``depth_bins`` (indices) and ``depths_m`` ([lo, hi] metres) of the bins without any labelled pixel; with
    ``per_class`` also ``per_label`` (label name -> bins without a pixel of that label; labels never seen, which
    keep the prior, are left out)."""
    n = counts.sum(axis=2)                 # (C, B) pixels per label and bin
    empty = np.flatnonzero(n.sum(axis=0) == 0)
    out: dict[str, Any] = {"rule": EXTRAPOLATION_RULE, "depth_bins": [int(b) for b in empty],
                           "depths_m": [[float(edges[b]), float(edges[b + 1])] for b in empty]}
    if per_class:
        out["per_label"] = {name: [int(b) for b in np.flatnonzero(n[y] == 0)]
                            for y, name in enumerate(class_names) if n[y].any() and not n[y].all()}
    return out


#: How a vote is spread over the classes (css_calibrate --votes).
VOTE_KINDS = ("symmetric", "onehot", "confusion")
DEFAULT_VOTES = "symmetric"


def symmetric_votes(p_right: np.ndarray) -> np.ndarray:
    """(C, B, C) vote rows: p_right[y, b] on the label y, the rest spread evenly over the other C - 1 classes
    (a label that is right with probability p is, when wrong, equally likely any other class)."""
    c, b = p_right.shape
    if c == 1:
        return np.ones((1, b, 1))
    rows = np.repeat(((1.0 - p_right) / (c - 1))[:, :, None], c, axis=2)
    rows[np.arange(c), :, np.arange(c)] = p_right
    return rows


def fit_sensor_model(counts: LabelDepthCounts, class_names: Iterable[str], votes: str = DEFAULT_VOTES,
                     per_class: bool = False, pseudo_count: float = DEFAULT_PSEUDO_COUNT,
                     weight_floor: float = DEFAULT_WEIGHT_FLOOR) -> SensorModel:
    """The sensor model of the fitting counts.

    p = the fraction of right labels at depth bin b over all classes (default; the same for every label) or, with
    ``per_class``, of label y alone (fit.smoothed_rates). Weight w(y, b) = max(floor, 2 p - 1)
    (fit.reliability_weight). Votes (``votes``): "symmetric" puts p on the label and (1 - p) / (C - 1) on every
    other class, so that a map seen only through unreliable labels has a low E even when those labels agree;
    "onehot" votes for the label only; "confusion" uses the smoothed confusion rows p(c | y, b).
    """
    if votes not in VOTE_KINDS:
        raise ValueError(f"votes must be one of {VOTE_KINDS}, got {votes!r}")
    rates = smoothed_rates(counts.fit.astype(np.float64), pseudo_count)
    c = counts.num_classes
    if per_class:
        p_right = rates[np.arange(c), :, np.arange(c)]  # (C, B)
    else:
        p_right = np.broadcast_to(depth_reliability(counts.fit, pseudo_count), (c, counts.edges.size - 1))
    weight = reliability_weight(p_right, weight_floor)
    table = {"symmetric": symmetric_votes(np.array(p_right)), "onehot": None, "confusion": rates}[votes]
    return SensorModel(tuple(class_names), counts.edges.copy(), np.array(weight), table)


def label_samples(counts: np.ndarray, p_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per labelled pixel of (C, B, C) counts: (predicted p(label right | label, depth bin) from ``p_right`` (C, B),
    1.0 if right else 0.0)."""
    c = counts.shape[0]
    n = counts.sum(axis=2)                               # (C, B) pixels per cell
    right = counts[np.arange(c), :, np.arange(c)]        # (C, B)
    p = p_right
    cells = n > 0
    conf = np.repeat(p[cells], n[cells])
    parts = [np.r_[np.ones(int(r)), np.zeros(int(t - r))] for r, t in zip(right[cells], n[cells])]
    return conf, np.concatenate(parts) if parts else np.zeros(0)


def right_rates(counts: np.ndarray, pseudo_count: float = DEFAULT_PSEUDO_COUNT) -> np.ndarray:
    """(C, B) smoothed fraction of right labels per label and depth bin (fit.smoothed_rates of the counts)."""
    c = counts.shape[0]
    return smoothed_rates(counts.astype(np.float64), pseudo_count)[np.arange(c), :, np.arange(c)]


def label_reliability(conf: np.ndarray, correct: np.ndarray) -> dict[str, Any]:
    """Held-out calibration of "the input label is right": the paper's assumption (probability 1) against the
    fitted p(label right | label, depth bin), from the per-pixel samples of :func:`label_samples`
    (calibration_summary)."""
    if conf.size == 0:
        return {"before": None, "after": None}
    return {"before": calibration_summary(np.ones_like(conf), correct),
            "after": calibration_summary(conf, correct), "pixels": int(conf.size)}


@dataclass
class ConfidenceSamples:
    """Per-pixel (E, evidence, right) samples of online renders, split into fitting and held-out frames."""

    fit: PixelSampler = field(default_factory=lambda: PixelSampler(max_samples=MAX_CONFIDENCE_SAMPLES, seed=1))
    heldout: PixelSampler = field(default_factory=lambda: PixelSampler(max_samples=MAX_CONFIDENCE_SAMPLES, seed=2))

    def add(self, view: "RenderedView", gt: np.ndarray, num_classes: int, ignore_label: int, heldout: bool) -> None:
        valid = (gt >= 0) & (gt < num_classes) & (gt != ignore_label)
        if not np.any(valid):
            return
        right = (view.labels[valid] == gt[valid]).astype(np.uint8)
        (self.heldout if heldout else self.fit).push(
            expectation=view.expectation[valid].astype(np.float32), evidence=view.evidence[valid].astype(np.float32),
            right=right)


def _features(expectation: np.ndarray, evidence: np.ndarray) -> np.ndarray:
    """(n, 2) features of the confidence map's logistic score (ConfidenceMap.features)."""
    return np.column_stack(ConfidenceMap.features(expectation, evidence))


def fit_confidence(samples: ConfidenceSamples) -> tuple[ConfidenceMap, dict[str, Any]]:
    """Fit the confidence map on the fitting samples; judge E and the calibrated confidence on the held-out ones
    (and on the fitting ones when nothing was held out). Returns (map, {"before": ..., "after": ...})."""
    cols = samples.fit.columns()
    coef = logistic_fit(_features(cols["expectation"], cols["evidence"]), cols["right"].astype(np.float64))
    cmap = ConfidenceMap(coef, np.array([0.0, 1.0]), np.array([0.0, 1.0]))
    score = cmap.score(cols["expectation"], cols["evidence"])
    kx, ky = isotonic_fit(score, cols["right"].astype(np.float64))
    kx, ky = np.clip(kx, 0.0, 1.0), np.clip(ky, 0.0, 1.0)
    keep = np.r_[True, np.diff(kx) > 0]
    cmap = ConfidenceMap(coef, kx[keep], np.maximum.accumulate(ky[keep]))
    test = samples.heldout.columns() if samples.heldout.total_seen else cols
    right = test["right"].astype(np.float64)
    report = {"before": calibration_summary(test["expectation"].astype(np.float64), right),
              "after": calibration_summary(cmap(test["expectation"], test["evidence"]), right),
              "judged_on": "held-out frames" if samples.heldout.total_seen else "the fitting frames (none held out)"}
    return cmap, report


def fused_frames(smap: "SemanticMap", frames: Iterable[Any], samples: ConfidenceSamples, heldout_every: int) -> int:
    """Observe every frame in order (online renders feed ``samples``); returns the frames fused."""
    n = 0
    for frame in frames:
        view = smap.observe(frame.camera, frame.labels, frame.confidence, depth=frame.depth)
        if frame.gt is not None:
            samples.add(view, frame.gt, smap.num_classes, smap.ignore_label, is_heldout(frame.index, heldout_every))
        n += 1
    return n
