"""Calibration metrics (pure numpy): reliability bins, expected calibration error, Brier score, reliability plot.

A *confidence* is a predicted probability that a label is right (in [0, 1]); *correct* says whether it
was (bool or 0/1, fractional values are allowed and act as a probability of being right). Pairs whose
confidence or correctness is NaN / inf are dropped and counted (``dropped``), never silently ignored.
Confidences outside [0, 1] are kept and fall in the first / last bin. matplotlib is imported only by
:func:`reliability_figure`.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .metrics import finite_or_none

if TYPE_CHECKING:
    from matplotlib.figure import Figure

#: Default number of equal-width confidence bins of the reliability diagram and the ECE.
DEFAULT_ECE_BINS = 15


def _valid_pairs(confidence: np.ndarray, correct: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """(confidence, correct, dropped): flat float64 arrays of the finite pairs and the number of dropped pairs."""
    conf = np.asarray(confidence, dtype=np.float64).ravel()
    corr = np.asarray(correct, dtype=np.float64).ravel()
    if conf.shape != corr.shape:
        raise ValueError(f"confidence and correct sizes differ: {conf.size} vs {corr.size}")
    keep = np.isfinite(conf) & np.isfinite(corr)
    dropped = int(conf.size - np.count_nonzero(keep))
    if dropped:
        conf, corr = conf[keep], corr[keep]
    return conf, corr, dropped


@dataclass
class ReliabilityBins:
    """Per-bin statistics of a reliability diagram over equal-width confidence bins on [0, 1].

    Bin b holds the confidences in [edges[b], edges[b+1]) (the last bin also holds 1.0).
    """

    edges: np.ndarray  # (bins + 1,) float64 bin edges, 0 .. 1
    count: np.ndarray  # (bins,) int64 samples (pixels) per bin
    mean_confidence: np.ndarray  # (bins,) float64 mean confidence per bin, NaN for empty bins
    accuracy: np.ndarray  # (bins,) float64 fraction correct per bin, NaN for empty bins
    dropped: int  # pairs dropped for a NaN / inf confidence or correctness

    @property
    def n(self) -> int:
        """Number of binned (valid) samples."""
        return int(self.count.sum())

    def ece(self) -> float:
        """Expected calibration error Σ_b (n_b / N) |acc_b − conf_b| (NaN if no valid sample)."""
        n = self.n
        if n == 0:
            return float("nan")
        full = self.count > 0
        gap = np.abs(self.accuracy[full] - self.mean_confidence[full])
        return float(np.sum(self.count[full] * gap) / n)

    def to_json(self) -> dict[str, Any]:
        """JSON-ready dict of the bins (None for the NaN statistics of empty bins)."""
        return {
            "edges": [float(e) for e in self.edges],
            "count": [int(c) for c in self.count],
            "mean_confidence": [finite_or_none(v) for v in self.mean_confidence],
            "accuracy": [finite_or_none(v) for v in self.accuracy],
            "dropped": int(self.dropped),
        }

    @classmethod
    def from_json(cls, d: dict[str, Any]) -> "ReliabilityBins":
        """The inverse of :meth:`to_json` (None -> NaN)."""
        nan = lambda v: np.array([np.nan if x is None else x for x in v], dtype=np.float64)  # noqa: E731
        return cls(np.asarray(d["edges"], dtype=np.float64), np.asarray(d["count"], dtype=np.int64),
                   nan(d["mean_confidence"]), nan(d["accuracy"]), int(d["dropped"]))


def reliability_bins(confidence: np.ndarray, correct: np.ndarray, bins: int = DEFAULT_ECE_BINS) -> ReliabilityBins:
    """Reliability statistics of ``confidence`` against ``correct`` (same size, any shape) in ``bins`` equal-width bins.

    Confidence 1.0 falls in the last bin; values below 0 / above 1 fall in the first / last bin; NaN / inf
    pairs are dropped and counted.
    """
    conf, corr, dropped = _valid_pairs(confidence, correct)
    return _bin_pairs(conf, corr, dropped, bins)


def _bin_pairs(conf: np.ndarray, corr: np.ndarray, dropped: int, bins: int) -> ReliabilityBins:
    """ReliabilityBins of already validated flat pairs."""
    if bins < 1:
        raise ValueError("bins must be >= 1")
    edges = np.linspace(0.0, 1.0, bins + 1)
    idx = np.clip(np.searchsorted(edges, conf, side="right") - 1, 0, bins - 1)
    count = np.bincount(idx, minlength=bins).astype(np.int64)
    conf_sum = np.bincount(idx, weights=conf, minlength=bins)
    corr_sum = np.bincount(idx, weights=corr, minlength=bins)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean_conf = np.where(count > 0, conf_sum / count, np.nan)
        accuracy = np.where(count > 0, corr_sum / count, np.nan)
    return ReliabilityBins(edges=edges, count=count, mean_confidence=mean_conf, accuracy=accuracy, dropped=dropped)


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = DEFAULT_ECE_BINS) -> float:
    """ECE = Σ_b (n_b / N) |acc_b − conf_b| over equal-width bins (NaN if no valid sample)."""
    return reliability_bins(confidence, correct, bins).ece()


def brier_score(confidence: np.ndarray, correct: np.ndarray) -> float:
    """Brier score mean_i (conf_i − correct_i)² over the valid pairs (NaN if none)."""
    conf, corr, _ = _valid_pairs(confidence, correct)
    return float(np.mean((conf - corr) ** 2)) if conf.size else float("nan")


def calibration_summary(confidence: np.ndarray, correct: np.ndarray, bins: int = DEFAULT_ECE_BINS) -> dict[str, Any]:
    """JSON-ready dict: ece, brier, mean_confidence, accuracy, n, dropped and the reliability ``bins``."""
    conf, corr, dropped = _valid_pairs(confidence, correct)
    rb = _bin_pairs(conf, corr, dropped, bins)
    n = int(conf.size)
    return {
        "ece": finite_or_none(rb.ece()),
        "brier": finite_or_none(float(np.mean((conf - corr) ** 2)) if n else float("nan")),
        "mean_confidence": finite_or_none(float(conf.mean()) if n else float("nan")),
        "accuracy": finite_or_none(float(corr.mean()) if n else float("nan")),
        "n": n,
        "dropped": rb.dropped,
        "bins": rb.to_json(),
    }


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def reliability_figure(curves: dict[str, ReliabilityBins], title: str) -> "Figure":
    """Reliability diagram of one or more curves; returns the matplotlib Figure (the caller saves / closes it).

    Upper panel: observed accuracy against the mean predicted confidence per bin (one line + markers per
    curve, its ECE in the legend) and the diagonal of perfect calibration. Lower panel: samples (pixels)
    per bin of every curve (log scale).
    """
    plt = _plt()
    fig, (ax, ax_n) = plt.subplots(2, 1, figsize=(6.0, 6.4), sharex=True,
                                   gridspec_kw={"height_ratios": [3, 1], "hspace": 0.08})
    ax.plot([0.0, 1.0], [0.0, 1.0], color="gray", linestyle="--", linewidth=1.0, label="perfect calibration")
    any_count = False
    for i, (name, rb) in enumerate(curves.items()):
        color = f"C{i}"
        full = rb.count > 0
        ece = rb.ece()
        ece_txt = f"ECE {ece:.3f}" if np.isfinite(ece) else "ECE n/a"
        ax.plot(rb.mean_confidence[full], rb.accuracy[full], color=color, marker="o", markersize=4,
                label=f"{name} ({ece_txt})")
        ax_n.stairs(rb.count, rb.edges, color=color, label=name)
        any_count = any_count or bool(full.any())
    ax.set_xlim(0.0, 1.0)
    ax.set_ylim(0.0, 1.0)
    ax.set_ylabel("observed accuracy")
    ax.set_title(title)
    ax.grid(True, alpha=0.3)
    ax.legend(loc="upper left", fontsize="small")
    if any_count:
        ax_n.set_yscale("log")
    ax_n.set_xlabel("predicted probability that the label is right")
    ax_n.set_ylabel("pixels per bin")
    ax_n.grid(True, alpha=0.3)
    return fig
