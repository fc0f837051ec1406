"""Evaluation metrics (pure numpy): confusion matrix, IoU / mIoU / accuracy, sparsification + AUSE, Spearman rho,
AUROC."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from ..engine.photometric import format_psnr, psnr  # noqa: F401  (re-exported: the evaluation API)

#: Default removal fractions of sparsification curves: 0.00, 0.01, ..., 0.99.
DEFAULT_FRACTIONS: np.ndarray = np.round(np.arange(0.0, 1.0, 0.01), 2)


# ----------------------------------------------------------------------------------------------
# Segmentation quality
# ----------------------------------------------------------------------------------------------
class ConfusionMatrix:
    """Accumulates a (C, C + 1) pixel confusion matrix: rows = ground-truth class, columns = prediction.

    Column ``C`` counts pixels whose prediction is not a class id (the "no label" value, negative
    ids or ids >= C): such pixels are always wrong. Ground-truth pixels equal to ``ignore_label``
    or outside 0..C-1 are excluded from every metric.
    """

    def __init__(self, num_classes: int, ignore_label: int = 255) -> None:
        if num_classes < 1:
            raise ValueError("num_classes must be >= 1")
        self.num_classes = int(num_classes)
        self.ignore_label = int(ignore_label)
        self.matrix = np.zeros((self.num_classes, self.num_classes + 1), dtype=np.int64)

    def update(self, gt: np.ndarray, pred: np.ndarray) -> None:
        """Add one image pair; ``gt`` and ``pred`` are integer arrays of the same shape."""
        gt = np.asarray(gt).astype(np.int64, copy=False).ravel()
        pred = np.asarray(pred).astype(np.int64, copy=False).ravel()
        if gt.shape != pred.shape:
            raise ValueError(f"gt and pred shapes differ: {gt.shape} vs {pred.shape}")
        C = self.num_classes
        valid = (gt >= 0) & (gt < C) & (gt != self.ignore_label)
        gt = gt[valid]
        pred = pred[valid]
        pred = np.where((pred >= 0) & (pred < C) & (pred != self.ignore_label), pred, C)
        self.matrix += np.bincount(gt * (C + 1) + pred, minlength=C * (C + 1)).reshape(C, C + 1)

    def __iadd__(self, other: "ConfusionMatrix") -> "ConfusionMatrix":
        self.matrix += other.matrix
        return self

    @property
    def num_pixels(self) -> int:
        """Number of evaluated pixels (pixels with a valid ground-truth label)."""
        return int(self.matrix.sum())

    def pixel_accuracy(self) -> float:
        """Fraction of evaluated pixels whose prediction equals the ground truth (NaN if none)."""
        n = self.matrix.sum()
        return float(np.trace(self.matrix[:, : self.num_classes]) / n) if n else float("nan")

    def iou(self) -> np.ndarray:
        """(C,) float64 per-class IoU = TP / (TP + FP + FN); NaN for classes absent from GT and prediction.

        FN includes ground-truth pixels predicted as "no label"; FP counts pixels predicted as the class.
        """
        C = self.num_classes
        tp = np.diag(self.matrix[:, :C]).astype(np.float64)
        gt_count = self.matrix.sum(axis=1).astype(np.float64)  # TP + FN
        pred_count = self.matrix[:, :C].sum(axis=0).astype(np.float64)  # TP + FP
        union = gt_count + pred_count - tp
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(union > 0, tp / np.where(union > 0, union, 1.0), np.nan)

    def miou(self) -> float:
        """Mean IoU over the classes present in the ground truth OR the prediction (union > 0).

        Classes neither present nor predicted are left out (their IoU is undefined), so a scene
        that only contains a subset of the class file is not penalised for the missing classes,
        while a class that is predicted but absent from the ground truth counts with IoU 0.
        """
        iou = self.iou()
        present = ~np.isnan(iou)
        return float(iou[present].mean()) if present.any() else float("nan")

    def summary(self, class_names: Sequence[str] | None = None) -> dict:
        """JSON-ready dict: pixel_accuracy, miou, per_class_iou {name: IoU or None}, num_pixels."""
        names = list(class_names) if class_names is not None else [f"class_{i}" for i in range(self.num_classes)]
        iou = self.iou()
        return {
            "pixel_accuracy": finite_or_none(self.pixel_accuracy()),
            "miou": finite_or_none(self.miou()),
            "per_class_iou": {names[i]: finite_or_none(iou[i]) for i in range(self.num_classes)},
            "classes_in_miou": int(np.count_nonzero(~np.isnan(iou))),
            "num_pixels": self.num_pixels,
        }


class LabelRangeCounter:
    """Counts label pixels whose id is not a class (>= C or negative) and not ``ignore_label``, per kind.

    Such pixels are excluded from the GT side of every metric and count as wrong predictions on the
    input side, so they must be reported rather than dropped silently.
    """

    def __init__(self, num_classes: int, ignore_label: int = 255) -> None:
        self.num_classes = int(num_classes)
        self.ignore_label = int(ignore_label)
        self.labelled: dict[str, int] = {}
        self.out_of_range: dict[str, int] = {}
        self.ids: dict[str, dict[int, int]] = {}

    def update(self, kind: str, labels: np.ndarray) -> None:
        """Add one (H, W) integer label image of ``kind`` ("segmentation" or "gt")."""
        lab = np.asarray(labels).ravel()
        labelled = lab != self.ignore_label
        bad = labelled & ((lab < 0) | (lab >= self.num_classes))
        self.labelled[kind] = self.labelled.get(kind, 0) + int(labelled.sum())
        n_bad = int(bad.sum())
        self.out_of_range[kind] = self.out_of_range.get(kind, 0) + n_bad
        if n_bad:
            ids, counts = np.unique(lab[bad], return_counts=True)
            seen = self.ids.setdefault(kind, {})
            for i, c in zip(ids.tolist(), counts.tolist()):
                seen[int(i)] = seen.get(int(i), 0) + int(c)

    def share(self, kind: str) -> float:
        """Out-of-range pixels / labelled pixels of ``kind`` (0 when nothing was labelled)."""
        n = self.labelled.get(kind, 0)
        return self.out_of_range.get(kind, 0) / n if n else 0.0

    def summary(self) -> dict:
        """JSON-ready {kind: {pixels, labelled_pixels, share, ids {id: pixels} (10 most frequent)}}."""
        out = {}
        for kind in self.labelled:
            top = sorted(self.ids.get(kind, {}).items(), key=lambda kv: (-kv[1], kv[0]))[:10]
            out[kind] = {"pixels": self.out_of_range.get(kind, 0), "labelled_pixels": self.labelled[kind],
                         "share": self.share(kind), "ids": {str(i): c for i, c in top}}
        return out


def finite_or_none(x: float) -> float | None:
    """float for JSON, None for NaN / inf."""
    x = float(x)
    return x if np.isfinite(x) else None


# ----------------------------------------------------------------------------------------------
# Sparsification
# ----------------------------------------------------------------------------------------------
def sparsification_curve(
    uncertainty: np.ndarray, error: np.ndarray, fractions: np.ndarray = DEFAULT_FRACTIONS
) -> np.ndarray:
    """Mean error of the samples kept after removing the most uncertain fraction f of them.

    Args:
        uncertainty: (M,) higher = less trustworthy.
        error: (M,) per-sample error (0/1 for pixels; any real value, e.g. 1 - accuracy, for images).
        fractions: (F,) removal fractions in [0, 1); k = round(f * M) samples are removed (at
            most M - 1, so at least one sample is kept).

    Returns:
        (F,) float64 mean error of the kept samples.

    Ties in ``uncertainty`` are resolved by their expectation over random tie-breaking: when the
    cut falls inside a group of equal uncertainties, that group contributes its mean error per
    removed sample. This makes the curve exact and independent of the input order.
    """
    u = np.asarray(uncertainty).ravel()
    if not np.issubdtype(u.dtype, np.floating):
        u = u.astype(np.float64)
    e = np.asarray(error, dtype=np.float64).ravel()
    if u.shape != e.shape:
        raise ValueError(f"uncertainty and error shapes differ: {u.shape} vs {e.shape}")
    m = u.size
    fractions = np.asarray(fractions, dtype=np.float64)
    if m == 0:
        return np.full(fractions.shape, np.nan)
    u = np.where(np.isnan(u), np.inf, u)  # NaN uncertainty = maximally uncertain
    # Exact sort (any order within ties is fine: tie groups are handled below). float32 inputs stay float32.
    order = np.argsort(-u)
    u_s = u[order]
    e_s = e[order]
    cum = np.concatenate([[0.0], np.cumsum(e_s)])  # cum[k] = error mass of the first k samples
    # Tie groups: start index of the group containing each sorted position.
    new_group = np.ones(m, dtype=bool)
    new_group[1:] = u_s[1:] != u_s[:-1]
    starts = np.flatnonzero(new_group)
    ends = np.append(starts[1:], m)
    k = np.clip(np.rint(fractions * m).astype(np.int64), 0, m - 1)
    g = np.searchsorted(starts, k, side="right") - 1  # group containing position k (k < m)
    g_start = starts[g]
    g_end = ends[g]
    g_mean = (cum[g_end] - cum[g_start]) / (g_end - g_start)
    removed = cum[g_start] + (k - g_start) * g_mean
    return (cum[m] - removed) / (m - k)


def oracle_curve(error: np.ndarray, fractions: np.ndarray = DEFAULT_FRACTIONS) -> np.ndarray:
    """Sparsification curve of the oracle, which removes the samples with the largest error first."""
    e_s = np.sort(np.asarray(error, dtype=np.float64).ravel())[::-1]
    return _curve_of_sorted(e_s, fractions)


def random_curve(error: np.ndarray, fractions: np.ndarray = DEFAULT_FRACTIONS, seed: int = 0) -> np.ndarray:
    """Sparsification curve of a uniformly random removal order (seeded permutation)."""
    e = np.asarray(error, dtype=np.float64).ravel()
    return _curve_of_sorted(e[np.random.default_rng(seed).permutation(e.size)], fractions)


def _curve_of_sorted(e_s: np.ndarray, fractions: np.ndarray) -> np.ndarray:
    """Mean of e_s[k:] for k = round(f * M), clipped to M - 1 (removal order = array order, no ties)."""
    m = e_s.size
    fractions = np.asarray(fractions, dtype=np.float64)
    if m == 0:
        return np.full(fractions.shape, np.nan)
    cum = np.concatenate([[0.0], np.cumsum(e_s)])
    k = np.clip(np.rint(fractions * m).astype(np.int64), 0, m - 1)
    return (cum[m] - cum[k]) / (m - k)


def ause(curve: np.ndarray, oracle: np.ndarray, fractions: np.ndarray = DEFAULT_FRACTIONS) -> float:
    """Area Under the Sparsification Error: trapezoid integral of (curve - oracle) over the fractions.

    0 for an ordering as good as the oracle; larger is worse. With the default fractions the
    integral spans [0, 0.99].
    """
    diff = np.asarray(curve, dtype=np.float64) - np.asarray(oracle, dtype=np.float64)
    x = np.asarray(fractions, dtype=np.float64)
    return float(np.sum(0.5 * (diff[1:] + diff[:-1]) * np.diff(x)))


def sparsification_report(
    uncertainties: dict[str, np.ndarray],
    error: np.ndarray,
    fractions: np.ndarray = DEFAULT_FRACTIONS,
    random_seed: int | None = 0,
) -> dict:
    """Curves and AUSE for several uncertainty signals, plus the oracle and (optionally) a random ordering.

    Args:
        uncertainties: name -> (M,) uncertainty (higher = less trustworthy).
        error: (M,) per-sample error.
        random_seed: seed of the random-ordering baseline (a seeded random permutation); None = omit.

    Returns:
        {"fractions": [...], "num_samples": M, "curves": {name: [...], "random": [...], "oracle": [...]},
         "ause": {name: float, "random": float, "oracle": 0.0}}
    """
    error = np.asarray(error, dtype=np.float64).ravel()
    oracle = oracle_curve(error, fractions)
    curves: dict[str, np.ndarray] = {}
    for name, u in uncertainties.items():
        curves[name] = sparsification_curve(u, error, fractions)
    if random_seed is not None:
        curves["random"] = random_curve(error, fractions, random_seed)
    curves["oracle"] = oracle
    return {
        "fractions": [float(f) for f in fractions],
        "num_samples": int(error.size),
        "curves": {k: [finite_or_none(v) for v in c] for k, c in curves.items()},
        "ause": {k: finite_or_none(ause(c, oracle, fractions)) for k, c in curves.items()},
    }


@dataclass
class PixelSampler:
    """Uniform random subsample of a stream of per-pixel samples with bounded memory.

    Every pixel pushed is kept with the same probability p = 2**-j: when more than
    ``max_samples`` are held, every held sample is kept with probability 1/2 and p halves. The
    result is a uniform Bernoulli sample of the whole stream (exact when the stream fits).

    Attributes:
        max_samples: cap on held samples (memory stays below ~2x this).
        seed: seed of the sampling RNG (deterministic results).
    """

    max_samples: int = 4_000_000
    seed: int = 0
    keep_probability: float = 1.0
    total_seen: int = 0
    _columns: dict[str, list[np.ndarray]] = field(default_factory=dict)
    _held: int = 0

    def __post_init__(self) -> None:
        self._rng = np.random.default_rng(self.seed)

    def push(self, **columns: np.ndarray) -> None:
        """Add one batch of samples; every keyword is a 1-D array of the same length."""
        arrays = {k: np.asarray(v).ravel() for k, v in columns.items()}
        sizes = {a.size for a in arrays.values()}
        if len(sizes) != 1:
            raise ValueError("all columns must have the same length")
        n = sizes.pop()
        self.total_seen += n
        if self.keep_probability < 1.0:
            keep = self._rng.random(n) < self.keep_probability
            arrays = {k: a[keep] for k, a in arrays.items()}
            n = int(keep.sum())
        if self._columns and set(arrays) != set(self._columns):
            raise ValueError("column names must not change between pushes")
        for k, a in arrays.items():
            self._columns.setdefault(k, []).append(a)
        self._held += n
        while self._held > self.max_samples:
            self._halve()

    def _halve(self) -> None:
        merged = {k: np.concatenate(v) for k, v in self._columns.items()}
        held = next(iter(merged.values())).size
        keep = self._rng.random(held) < 0.5
        self._columns = {k: [a[keep]] for k, a in merged.items()}
        self._held = int(keep.sum())
        self.keep_probability *= 0.5

    def columns(self) -> dict[str, np.ndarray]:
        """The held samples, one concatenated array per column."""
        return {k: np.concatenate(v) if v else np.zeros(0) for k, v in self._columns.items()}

    @property
    def subsampled(self) -> bool:
        return self.keep_probability < 1.0


# ----------------------------------------------------------------------------------------------
# Correlation
# ----------------------------------------------------------------------------------------------
def rankdata(x: np.ndarray) -> np.ndarray:
    """Ranks 1..n of a 1-D array, ties get their average rank (as scipy.stats.rankdata 'average')."""
    x = np.asarray(x, dtype=np.float64).ravel()
    order = np.argsort(x, kind="stable")
    xs = x[order]
    new = np.ones(x.size, dtype=bool)
    new[1:] = xs[1:] != xs[:-1]
    starts = np.flatnonzero(new)
    ends = np.append(starts[1:], x.size)
    avg = 0.5 * (starts + ends - 1) + 1.0  # mean of the 1-based ranks start+1..end
    ranks = np.empty(x.size)
    ranks[order] = np.repeat(avg, ends - starts)
    return ranks


def auroc(positives: np.ndarray, negatives: np.ndarray) -> float:
    """Area under the ROC curve of a score that should be higher on ``positives`` than on ``negatives`` (1-D
    arrays of scores): the probability that a random positive scores above a random negative, ties counting one
    half (Mann-Whitney U / (n1 n0), from average ranks). NaN / inf scores are left out; NaN when either side is
    then empty."""
    pos = np.asarray(positives, dtype=np.float64).ravel()
    neg = np.asarray(negatives, dtype=np.float64).ravel()
    pos, neg = pos[np.isfinite(pos)], neg[np.isfinite(neg)]
    if pos.size == 0 or neg.size == 0:
        return float("nan")
    ranks = rankdata(np.concatenate([pos, neg]))
    u = ranks[: pos.size].sum() - pos.size * (pos.size + 1) / 2.0
    return float(u / (pos.size * neg.size))


def spearman(x: np.ndarray, y: np.ndarray) -> float:
    """Spearman rank correlation (Pearson correlation of average ranks); NaN if undefined (n < 2 or constant)."""
    x = np.asarray(x, dtype=np.float64).ravel()
    y = np.asarray(y, dtype=np.float64).ravel()
    if x.shape != y.shape:
        raise ValueError("x and y must have the same length")
    ok = np.isfinite(x) & np.isfinite(y)
    x, y = x[ok], y[ok]
    if x.size < 2:
        return float("nan")
    rx = rankdata(x) - (x.size + 1) / 2.0
    ry = rankdata(y) - (y.size + 1) / 2.0
    den = np.sqrt(np.sum(rx * rx) * np.sum(ry * ry))
    return float(np.sum(rx * ry) / den) if den > 0 else float("nan")
