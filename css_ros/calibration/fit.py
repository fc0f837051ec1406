"""Fitting of the calibrated sensor model (pure numpy, no I/O): isotonic and logistic fits, smoothed rates.

- :func:`isotonic_fit`: monotone (non-decreasing) map from a score to a probability, as interpolation knots.
- :func:`logistic_fit` / :func:`logistic_predict`: L2-regularised logistic regression (Newton / IRLS).
- :func:`smoothed_rates`: per (predicted class, depth bin) outcome rates shrunk toward neighbouring bins
  and the class's overall rate, so that sparsely observed bins stay sensible; bins without data follow their
  neighbours (:func:`fill_empty_bins`).
- :func:`reliability_weight`: the evidence weight of a vote that is right with probability p.
"""
from __future__ import annotations

import heapq

import numpy as np

#: :func:`isotonic_fit` first pools the sorted samples into at most this many quantile bins of x.
ISOTONIC_BINS = 20000
#: Logits are clipped to ±LOGIT_CLIP before the sigmoid (p stays in (1e-15, 1 - 1e-15)).
LOGIT_CLIP = 35.0


# ----------------------------------------------------------------------------------------------
# Isotonic regression
# ----------------------------------------------------------------------------------------------
def _aggregate_sorted(x: np.ndarray, y: np.ndarray, w: np.ndarray,
                      max_bins: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pool x-sorted samples into groups: (x_lo, x_hi, weighted mean y, total weight), each (G,), G <= max_bins.

    Equal x values always share a group (ties are pooled); when there are more than ``max_bins`` distinct
    values, consecutive distinct values are pooled into at most ``max_bins`` quantile bins of about equal
    sample count (a value's bin is set by the rank of its first sample).
    """
    n = x.size
    starts = np.flatnonzero(np.r_[True, x[1:] != x[:-1]])  # first sample of each distinct x
    if starts.size > max_bins:
        bin_of_value = (starts * max_bins) // n  # non-decreasing in the value's rank: bins are contiguous
        starts = starts[np.flatnonzero(np.r_[True, bin_of_value[1:] != bin_of_value[:-1]])]
    ends = np.r_[starts[1:], n] - 1
    wsum = np.add.reduceat(w, starts)
    wysum = np.add.reduceat(w * y, starts)
    return x[starts], x[ends], wysum / wsum, wsum


def _pav(v: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weighted pool-adjacent-violators (a stack) on the values ``v`` (G,) in x order with weights ``w`` (G,) > 0.

    Returns ``(starts, values)``: block b covers input indices starts[b] .. starts[b+1]-1 and has the
    weighted mean ``values[b]``; values are strictly increasing (equal neighbours are pooled too).
    """
    st_start: list[int] = []
    st_sum: list[float] = []  # Σ w v of the block
    st_w: list[float] = []
    for i, (vi, wi) in enumerate(zip(v.tolist(), w.tolist())):
        s, ww, start = vi * wi, wi, i
        while st_w and st_sum[-1] * ww >= s * st_w[-1]:  # previous mean >= this mean (weights > 0)
            s += st_sum.pop()
            ww += st_w.pop()
            start = st_start.pop()
        st_start.append(start)
        st_sum.append(s)
        st_w.append(ww)
    return np.asarray(st_start, dtype=np.int64), np.asarray(st_sum) / np.asarray(st_w)


def _knot_count(x_lo: np.ndarray, x_hi: np.ndarray) -> int:
    """Knots of blocks spanning x_lo .. x_hi: two per block, one where x_lo == x_hi."""
    return int(np.sum(np.where(x_hi > x_lo, 2, 1)))


def _merge_to_knots(x_lo: np.ndarray, x_hi: np.ndarray, v: np.ndarray, w: np.ndarray,
                    max_knots: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Greedily merge adjacent monotone blocks (cheapest rise in weighted squared error first) until the knots fit.

    Merging two neighbours of a non-decreasing sequence replaces them by their weighted mean, which lies
    between them, so the sequence stays non-decreasing. Cost of merging blocks a, b: w_a w_b/(w_a+w_b) (v_a−v_b)².
    """
    m = v.size
    lo, hi, val, wt = x_lo.tolist(), x_hi.tolist(), v.tolist(), w.tolist()
    nxt = list(range(1, m + 1))  # linked list over the live blocks; m = end
    prv = list(range(-1, m - 1))
    alive = [True] * m
    version = [0] * m  # bumped when a block changes: heap entries carrying an older version are stale
    knots = _knot_count(x_lo, x_hi)

    def entry(a: int, b: int) -> tuple[float, int, int, int, int]:
        return wt[a] * wt[b] / (wt[a] + wt[b]) * (val[a] - val[b]) ** 2, a, b, version[a], version[b]

    heap = [entry(i, i + 1) for i in range(m - 1)]
    heapq.heapify(heap)
    while knots > max_knots and heap:
        _, a, b, va, vb = heapq.heappop(heap)
        if not (alive[a] and alive[b] and version[a] == va and version[b] == vb):
            continue
        knots -= (2 if hi[a] > lo[a] else 1) + (2 if hi[b] > lo[b] else 1)
        val[a] = (val[a] * wt[a] + val[b] * wt[b]) / (wt[a] + wt[b])
        wt[a] += wt[b]
        hi[a] = hi[b]
        knots += 2 if hi[a] > lo[a] else 1
        alive[b] = False
        version[a] += 1
        nxt[a] = nxt[b]
        if nxt[a] < m:
            prv[nxt[a]] = a
            heapq.heappush(heap, entry(a, nxt[a]))
        if prv[a] >= 0:
            heapq.heappush(heap, entry(prv[a], a))
    keep = np.flatnonzero(alive)
    return np.asarray(lo)[keep], np.asarray(hi)[keep], np.asarray(val)[keep]


def isotonic_fit(x: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
                 max_knots: int = 64) -> tuple[np.ndarray, np.ndarray]:
    """Weighted isotonic (non-decreasing) regression of ``y`` on ``x``; returns knots ``(xk, yk)``, each (m,) float64.

    Evaluate the fit with ``np.interp(x, xk, yk)``: flat beyond the end knots, linear between blocks.
    ``x``, ``y``, ``weight`` are flat arrays of the same size (any shape, raveled); ``y`` may be 0/1 or
    fractional; samples with a non-finite value or a weight <= 0 are left out.

    Method: sort by x once; pool equal x values; if more than ``ISOTONIC_BINS`` (20000) distinct x values
    remain, pool consecutive ones into at most that many quantile bins of about equal sample count (the
    fit is then the exact isotonic regression among functions constant on each bin — a negligible
    restriction at millions of samples, and it keeps 5e6 samples to about a second, dominated by the
    sort); run weighted pool-adjacent-violators (a stack) on the bins, minimising Σ w (y − f(x))². Each
    resulting block of constant value v spanning x_lo .. x_hi gives the knots (x_lo, v) and (x_hi, v)
    (one knot when x_lo == x_hi), so ``xk`` is strictly increasing and ``yk`` non-decreasing. While there are more than
    ``max_knots`` (>= 2) knots, the adjacent pair of blocks whose merge raises the weighted squared error
    least is replaced by one block with their weighted mean (which keeps the fit monotone).
    """
    if max_knots < 2:
        raise ValueError("max_knots must be >= 2")
    xf = np.asarray(x, dtype=np.float64).ravel()
    yf = np.asarray(y, dtype=np.float64).ravel()
    wf = np.ones_like(xf) if weight is None else np.asarray(weight, dtype=np.float64).ravel()
    if not (xf.size == yf.size == wf.size):
        raise ValueError(f"x, y, weight sizes differ: {xf.size}, {yf.size}, {wf.size}")
    keep = np.isfinite(xf) & np.isfinite(yf) & np.isfinite(wf) & (wf > 0)
    if not keep.all():
        xf, yf, wf = xf[keep], yf[keep], wf[keep]
    if xf.size == 0:
        raise ValueError("isotonic_fit needs at least one sample with a finite value and a positive weight")
    order = np.argsort(xf, kind="stable")
    xs, ys, ws = xf[order], yf[order], wf[order]
    g_lo, g_hi, g_y, g_w = _aggregate_sorted(xs, ys, ws, int(ISOTONIC_BINS))
    starts, values = _pav(g_y, g_w)
    ends = np.r_[starts[1:], g_y.size] - 1
    b_lo, b_hi = g_lo[starts], g_hi[ends]
    b_w = np.add.reduceat(g_w, starts)
    if _knot_count(b_lo, b_hi) > max_knots:
        b_lo, b_hi, values = _merge_to_knots(b_lo, b_hi, values, b_w, max_knots)
    two = b_hi > b_lo
    xk = np.stack([b_lo, b_hi], axis=1).ravel()
    yk = np.repeat(values, 2)
    mask = np.stack([np.ones_like(two), two], axis=1).ravel()
    return xk[mask], yk[mask]


# ----------------------------------------------------------------------------------------------
# Logistic regression
# ----------------------------------------------------------------------------------------------
def _design(features: np.ndarray) -> np.ndarray:
    """(n, k + 1) float64 design matrix: the features (1-D means one feature column) and a column of ones."""
    f = np.asarray(features, dtype=np.float64)
    if f.ndim == 1:
        f = f[:, None]
    if f.ndim != 2:
        raise ValueError(f"features must be (n, k), got shape {f.shape}")
    return np.hstack([f, np.ones((f.shape[0], 1))])


def _sigmoid(z: np.ndarray) -> np.ndarray:
    return 1.0 / (1.0 + np.exp(-np.clip(z, -LOGIT_CLIP, LOGIT_CLIP)))


def logistic_fit(features: np.ndarray, y: np.ndarray, weight: np.ndarray | None = None,
                 l2: float = 1e-3, iters: int = 50) -> np.ndarray:
    """L2-regularised logistic regression by damped Newton (IRLS); returns coef (k + 1,), the intercept last.

    ``features`` (n, k) (a 1-D array is one feature), ``y`` (n,) targets in [0, 1] (0/1 or fractional),
    ``weight`` (n,) >= 0 or None. Minimises the weighted mean log loss plus ``l2``/2 ‖coef[:k]‖²
    (the intercept is not penalised; the loss is normalised by Σ weight, so ``l2`` does not depend on n):

        L(β) = Σ_i w_i [log(1 + e^{z_i}) − y_i z_i] / Σ_i w_i + l2/2 ‖β[:k]‖²,   z = [features, 1] β

    Each step solves the Newton system (a 1e-10 ridge keeps it solvable, e.g. for a constant feature)
    and is halved until L does not increase; stops after ``iters`` steps or when the step is below 1e-10.
    Logits are clipped to ±LOGIT_CLIP in the sigmoid; the loss itself uses log(1 + e^z) computed stably.
    """
    X = _design(features)
    n, k1 = X.shape
    t = np.asarray(y, dtype=np.float64).ravel()
    w = np.ones(n) if weight is None else np.asarray(weight, dtype=np.float64).ravel()
    if t.size != n or w.size != n:
        raise ValueError(f"features, y, weight lengths differ: {n}, {t.size}, {w.size}")
    if n == 0 or not np.all(np.isfinite(X)) or not np.all(np.isfinite(t)) or not np.all(np.isfinite(w)):
        raise ValueError("logistic_fit needs at least one sample and finite features, y and weights")
    if np.any(w < 0) or w.sum() <= 0:
        raise ValueError("weights must be >= 0 with a positive sum")
    w = w / w.sum()
    pen = np.full(k1, float(l2))
    pen[-1] = 0.0

    def loss(beta: np.ndarray) -> float:
        z = X @ beta
        return float(w @ (np.logaddexp(0.0, z) - t * z) + 0.5 * pen @ beta**2)

    beta = np.zeros(k1)
    cur = loss(beta)
    for _ in range(int(iters)):
        p = _sigmoid(X @ beta)
        grad = X.T @ (w * (p - t)) + pen * beta
        hess = (X * (w * p * (1.0 - p))[:, None]).T @ X + np.diag(pen + 1e-10)
        try:
            step = np.linalg.solve(hess, grad)
        except np.linalg.LinAlgError:
            step = np.linalg.lstsq(hess, grad, rcond=None)[0]
        s = 1.0
        while s > 1e-6:
            cand = beta - s * step
            new = loss(cand)
            if new <= cur:
                break
            s *= 0.5
        else:
            break  # no descent along the Newton direction: converged to rounding
        beta, cur = cand, new
        if np.max(np.abs(s * step)) < 1e-10:
            break
    return beta


def logistic_predict(features: np.ndarray, coef: np.ndarray) -> np.ndarray:
    """(n,) float64 probabilities sigmoid([features, 1] · coef) of a :func:`logistic_fit` result."""
    X = _design(features)
    c = np.asarray(coef, dtype=np.float64).ravel()
    if c.size != X.shape[1]:
        raise ValueError(f"coef has {c.size} elements, features need {X.shape[1]} (k + 1)")
    return _sigmoid(X @ c)


# ----------------------------------------------------------------------------------------------
# Smoothed per-(class, depth bin) rates
# ----------------------------------------------------------------------------------------------
def _normalise_rows(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows normalised to sum 1 along the last axis (0 where empty), bool mask of the non-empty rows)."""
    tot = a.sum(axis=-1, keepdims=True)
    ok = tot > 0
    return np.divide(a, tot, out=np.zeros_like(a), where=ok), ok[..., 0]


def smoothing_prior(counts: np.ndarray) -> np.ndarray:
    """(C, B, K) float64 prior rows of :func:`smoothed_rates` (each row sums to 1); see its docstring for the rule."""
    c = np.asarray(counts, dtype=np.float64)
    if c.ndim != 3:
        raise ValueError(f"counts must be (C, B, K), got shape {c.shape}")
    if np.any(c < 0) or not np.all(np.isfinite(c)):
        raise ValueError("counts must be finite and >= 0")
    C, B, K = c.shape
    glob, glob_ok = _normalise_rows(c.sum(axis=(0, 1)))
    if not glob_ok:
        glob = np.full(K, 1.0 / K)  # nothing seen at all: uniform
    cls, cls_ok = _normalise_rows(c.sum(axis=1))  # (C, K) each class over all bins
    cls[~cls_ok] = glob  # a class never seen: the rate of all classes together
    nb = np.zeros_like(c)  # neighbour counts, weight 1/2 each (the one neighbour at an edge)
    if B > 1:
        nb[:, 1:] += 0.5 * c[:, :-1]
        nb[:, :-1] += 0.5 * c[:, 1:]
    nb_rate, nb_ok = _normalise_rows(nb)
    cls_b = np.broadcast_to(cls[:, None, :], c.shape)
    return np.where(nb_ok[..., None], 0.5 * nb_rate + 0.5 * cls_b, cls_b)


def smoothed_rates(counts: np.ndarray, pseudo_count: float = 200.0) -> np.ndarray:
    """(C, B, K) float64 outcome rates per (class y, depth bin b), shrunk toward a prior row; each row sums to 1.

    ``counts[y, b, k]`` (C, B, K) >= 0 counts outcome k among the samples of class y in depth bin b (e.g.
    K = C true classes of the pixels labelled y at depth bin b). With n[y, b] = Σ_k counts[y, b, k] and
    τ = ``pseudo_count`` (>= 0):

        p[y, b] = (counts[y, b] + τ · prior[y, b]) / (n[y, b] + τ)     (= prior[y, b] exactly when n[y, b] = 0)

    The prior row, every component normalised to sum 1 over k before mixing:

    - class rate      R[y]    = Σ_b counts[y, b] normalised; a class never seen (no count in any bin)
      gets the rate of all classes together Σ_{y,b} counts normalised, and if nothing was seen at all,
      the uniform row 1/K;
    - neighbour rate  N[y, b] = (½ counts[y, b−1] + ½ counts[y, b+1]) normalised (the first / last bin
      use their one neighbour);
    - prior[y, b] = ½ N[y, b] + ½ R[y]; when the neighbours hold no count (or B = 1), prior[y, b] = R[y].

    So a row with few samples follows its neighbouring bins and the class's overall rate, and a row with
    n ≫ τ stays at its own frequency (off by at most τ / (n + τ)).

    An empty row (n[y, b] = 0) of a class seen in other bins has no data of its own and follows its neighbours
    (:func:`fill_empty_bins`): between two bins with data it is their linear interpolation (in bin index), beyond
    the first / last bin with data it repeats that bin's row, so unobserved far bins continue the trend instead
    of jumping back to the class rate. A class never seen keeps its prior.
    """
    if not pseudo_count >= 0:
        raise ValueError("pseudo_count must be >= 0")
    c = np.asarray(counts, dtype=np.float64)
    prior = smoothing_prior(c)
    tau = float(pseudo_count)
    n = c.sum(axis=-1, keepdims=True)
    seen = n > 0
    rates = np.where(seen, (c + tau * prior) / np.where(seen, n + tau, 1.0), prior)
    return fill_empty_bins(rates, seen[..., 0])


def fill_empty_bins(rates: np.ndarray, seen: np.ndarray) -> np.ndarray:
    """``rates`` (C, B, K) with each row y's unseen bins (``seen`` (C, B) False) replaced from its seen ones:
    linear interpolation in bin index between seen bins, the nearest seen bin's row beyond them (rows stay
    convex combinations of seen rows: they sum to 1 and never leave the range of their neighbours). Rows of a
    class without any seen bin are returned unchanged."""
    out = np.array(rates, dtype=np.float64)
    bins = np.arange(out.shape[1])
    for y in range(out.shape[0]):
        have = np.flatnonzero(seen[y])
        if have.size == 0 or have.size == bins.size:
            continue
        empty = np.flatnonzero(~seen[y])
        for k in range(out.shape[2]):
            out[y, empty, k] = np.interp(empty, have, out[y, have, k])
    return out


def reliability_weight(p_correct: np.ndarray, floor: float = 0.0) -> np.ndarray:
    """Vote weight max(floor, 2p − 1) clipped to [0, 1] for labels right with probability ``p_correct`` (any shape).

    Under two-way confusion a vote that is right with probability p adds p to its class and 1 − p to
    the other, i.e. net evidence 2p − 1 for its class; votes no better than chance (p <= ½) carry
    ``floor``. NaN stays NaN. Returns float64 of the input's shape.
    """
    p = np.asarray(p_correct, dtype=np.float64)
    return np.clip(np.maximum(float(floor), 2.0 * p - 1.0), 0.0, 1.0)
