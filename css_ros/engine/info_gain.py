"""Information gain of a candidate view for the Dirichlet map (docs/spec.md "Information gain of a view").

Per Gaussian n with concentrations alpha_n plus the scoring prior (``spec.INFO_GAIN_PRIOR`` / C per class; total
S = sum_c alpha^c, Q = sum_c (alpha^c)^2), the uncertainty is the summed variance of its class probabilities,
V(S, Q) = (1 - Q / S^2) / (S + 1). Observing a view adds m_n units of
evidence to it (m_n = sum_i kappa_in w_i over the view's pixels, w_i the sensor model's net vote weight, 1 without
one), all of one label drawn from the map's own predictive E[theta_n] = alpha_n / S. The expected summed variance after
is a closed form in (S, Q, m) (see :func:`expected_variance_after`), and the gain of the view is

    info_gain = sum_n importance_n * (V(S_n, Q_n) - E[V after m_n])

counted once per Gaussian per view. It falls like 1 / S_n: poorly observed Gaussians are where a view teaches most.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .spec import INFO_GAIN_PRIOR

__all__ = ["MomentSums", "SelectedViews", "expected_variance_after", "summed_variance", "variance_drop",
           "view_gain"]


def summed_variance(total: np.ndarray, sq_sum: np.ndarray) -> np.ndarray:
    """V = sum_c Var[theta^c] = (1 - Q / S^2) / (S + 1) of Dirichlets with totals S and squared sums Q."""
    return (1.0 - sq_sum / (total * total)) / (total + 1.0)


def expected_variance_after(total: np.ndarray, sq_sum: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """E[V] after adding ``mass`` units of one label c ~ alpha / S: alpha' = alpha + m e_c, so
    E[Q'] = Q + 2 m Q / S + m^2 and V' = (1 - Q' / (S + m)^2) / (S + m + 1)."""
    t = total + mass
    q = sq_sum + 2.0 * mass * sq_sum / total + mass * mass
    return (1.0 - q / (t * t)) / (t + 1.0)


def variance_drop(total: np.ndarray, sq_sum: np.ndarray, mass: np.ndarray) -> np.ndarray:
    """V before - E[V after] (>= 0) per Gaussian."""
    return np.maximum(summed_variance(total, sq_sum) - expected_variance_after(total, sq_sum, mass), 0.0)


@dataclass
class MomentSums:
    """Per-Gaussian (S, Q) of the map, the only moments the gain needs; :meth:`observe_expected` moves them as an
    observation of ``mass`` units of a label drawn from the predictive would, on average (the greedy batch)."""

    total: np.ndarray   # (N,) float64 S_n
    sq_sum: np.ndarray  # (N,) float64 Q_n

    @classmethod
    def of(cls, concentrations: np.ndarray, prior_total: float = INFO_GAIN_PRIOR) -> "MomentSums":
        """(S, Q) of alpha + prior_total / C per class (the scoring prior, spec.INFO_GAIN_PRIOR)."""
        c = np.asarray(concentrations, dtype=np.float64)
        extra = float(prior_total) / c.shape[1]
        total = c.sum(axis=1)
        sq = np.einsum("nc,nc->n", c, c)
        return cls(total + prior_total, sq + 2.0 * extra * total + c.shape[1] * extra * extra)

    def observe_expected(self, ids: np.ndarray, mass: np.ndarray) -> None:
        """alpha_n += m_n E[theta_n] (the mean stays, the total grows): S += m, Q += 2 m Q / S + m^2 Q / S^2."""
        s, q = self.total[ids], self.sq_sum[ids]
        self.sq_sum[ids] = q + 2.0 * mass * q / s + mass * mass * q / (s * s)
        self.total[ids] = s + mass


def view_gain(moments: MomentSums, ids: np.ndarray, mass: np.ndarray, importance: np.ndarray | None) -> float:
    """sum_n importance_n (V_n - E[V_n after mass_n]) over the view's Gaussians ``ids`` (importance None = 1)."""
    if ids.size == 0:
        return 0.0
    drop = variance_drop(moments.total[ids], moments.sq_sum[ids], mass)
    if importance is not None:
        drop = drop * importance[ids]
    return float(drop.sum())


@dataclass(frozen=True)
class SelectedViews:
    """A greedy batch of views (``SemanticMap.select_views``).

    Attributes:
        indices: (k,) int64 indices into the candidate list, in the order chosen.
        gains: (k,) float64 each view's info gain when it was chosen (given the views chosen before it).
    """

    indices: np.ndarray
    gains: np.ndarray
