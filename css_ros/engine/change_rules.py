"""What a changing world changes in the update (docs/changing_world.md): measured depth, transient classes,
forgetting and surprise. One definition of each rule; the backends compile the scalar ones (numba on the CPU,
numba-cuda on the GPU) or vectorise them (the torch twin). numba's on-disk cache of the CPU kernels is keyed on
their own module (engine/cpu/raster.py), not on this one: after editing a rule here, delete that folder's
``__pycache__`` (a fresh install has none).

The rules, per labelled pixel i that :func:`~css_ros.engine.label_input.pixel_vote` makes a vote of class y:

- **Transient class** (``transient[y]``): the pixel adds no evidence and is counted TRANSIENT (it still counts in the
  input's statistics: its label is an input like any other).
- **Measured depth** d_i (metres along the optical axis, registered to the labels; NaN, inf or <= 0: none). With the
  tolerance tau_i = max(tol_abs, tol_rel * d_i) and the map's rendered depth r_i = sum_n kappa_in z_n / sum_n kappa_in
  (metres, the same as ``RenderedView.depth``):
  - d_i < r_i - tau_i (something nearer than the splat's surface, which the splat does not hold: a person, a new
    object): the pixel adds no evidence and is counted OCCLUDED;
  - r_i < d_i - tau_i (the splat's surface is in front of the measured one: the splat holds something there that is
    no longer there): a contribution of Gaussian n with z_n < d_i - tau_i adds no evidence, the others add theirs;
  - otherwise (the measurement agrees with the splat's surface) the pixel votes as usual. Gaussians' centres are not
    compared where the surfaces agree: a broad Gaussian seen at a grazing angle has its centre well off the ray.
  A pixel without a measurement, or that no Gaussian covers, is voted as without depth.
- **Forgetting** (``evidence_half_life`` h, in observations): a Gaussian whose increment from a frame is non-zero
  in some class first has its accumulated evidence multiplied by 2^(-1/h): alpha <- alpha_0 + (alpha - alpha_0)
  2^(-1/h) + increment. None (the default) is the paper's update.
- **Surprise** of a voted pixel (transient and occluded ones included): 1 - E[theta_y](x_i) of its label y under the
  map before the frame's update, E^y(x) = sum_n kappa_n alpha_n^y / S_n + kappa_b / C (SPEC §5); NaN where the pixel
  has no label (ignored or out of range).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..errors import MapError

#: measured-depth tolerance: max(DEFAULT_DEPTH_TOLERANCE m, DEFAULT_DEPTH_TOLERANCE_RELATIVE x depth)
DEFAULT_DEPTH_TOLERANCE = 0.05
DEFAULT_DEPTH_TOLERANCE_RELATIVE = 0.03
#: largest accepted tolerances (metres, fraction of depth)
MAX_DEPTH_TOLERANCE = 100.0
MAX_DEPTH_TOLERANCE_RELATIVE = 10.0
#: evidence half-life bounds (observations)
MIN_HALF_LIFE = 0.01
MAX_HALF_LIFE = 1e9


def depth_gate(measured, rendered, tol_abs, tol_rel):  # type: ignore[no-untyped-def]
    """(occluded, front) of one pixel, metres: ``occluded`` when the measured depth is nearer than the rendered one
    by more than the tolerance; ``front``: when the rendered depth is nearer than the measured one by more than the
    tolerance, contributions of Gaussians nearer than it (camera z in metres) add no evidence (else -inf: all add).
    Without a measurement (not finite, or <= 0) or without a rendered depth (NaN): (False, -inf).
    Plain scalar code for numba / numba-cuda (see the module docstring)."""
    if not (measured > 0.0) or measured == math.inf or not (rendered == rendered):
        return False, -math.inf
    tol = max(tol_abs, tol_rel * measured)
    if measured < rendered - tol:
        return True, -math.inf
    if rendered < measured - tol:
        return False, measured - tol
    return False, -math.inf


def decay_factor(half_life: float | None) -> float:
    """2^(-1/h), the factor on a Gaussian's accumulated evidence each time it receives more; 1.0 without forgetting."""
    return 1.0 if half_life is None else float(2.0 ** (-1.0 / half_life))


@dataclass(frozen=True)
class ChangeRules:
    """A map's rules for a changing world, as the backends apply them (constant for a map).

    Attributes:
        transient: (C,) bool, classes whose pixels never add evidence.
        tol_abs, tol_rel: measured-depth tolerance max(tol_abs m, tol_rel x depth).
        depth_scale: metres per splat unit (a Gaussian's camera z in metres is z * depth_scale).
        decay: 2^(-1/h) with the evidence half-life h; 1.0 = the paper's update (no forgetting).
        prior: alpha_0 (forgetting shrinks alpha - alpha_0).
    """

    transient: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.bool_))
    tol_abs: float = DEFAULT_DEPTH_TOLERANCE
    tol_rel: float = DEFAULT_DEPTH_TOLERANCE_RELATIVE
    depth_scale: float = 1.0
    decay: float = 1.0
    prior: float = 1.0

    @property
    def any_transient(self) -> bool:
        return bool(self.transient.any())

    def transient_ids(self) -> list[int]:
        return [int(c) for c in np.flatnonzero(self.transient)]


def check_transient_classes(classes: object, num_classes: int) -> np.ndarray:
    """(C,) bool mask of the transient class ids ``classes`` (an iterable of ints in 0..C-1; names are resolved to
    ids by :func:`css_ros.engine.classes.class_ids`).

    Raises:
        MapError: not an iterable of integers, or an id outside 0..C-1.
    """
    if classes is None:
        classes = ()
    if isinstance(classes, (str, bytes)) or not hasattr(classes, "__iter__"):
        raise MapError(f"transient_classes must be a list of class ids, got {classes!r}")
    mask = np.zeros(num_classes, dtype=np.bool_)
    for c in classes:  # type: ignore[attr-defined]
        if isinstance(c, bool) or not isinstance(c, (int, np.integer)):
            raise MapError(f"transient_classes must be class ids (integers), got {c!r}")
        if not 0 <= int(c) < num_classes:
            raise MapError(f"transient class {int(c)} is outside 0..{num_classes - 1}")
        mask[int(c)] = True
    return mask


def check_half_life(half_life: object) -> float | None:
    """None or a half-life in observations, within [MIN_HALF_LIFE, MAX_HALF_LIFE].

    Raises:
        MapError: not a number, not finite, or out of bounds."""
    if half_life is None:
        return None
    if isinstance(half_life, bool) or not isinstance(half_life, (int, float, np.integer, np.floating)):
        raise MapError(f"evidence_half_life must be a number of observations or None, got {half_life!r}")
    h = float(half_life)
    if not (MIN_HALF_LIFE <= h <= MAX_HALF_LIFE):
        raise MapError(f"evidence_half_life must be in [{MIN_HALF_LIFE:g}, {MAX_HALF_LIFE:g}] observations (None: no "
                       f"forgetting), got {half_life!r}")
    return h


def check_tolerance(value: object, name: str, upper: float) -> float:
    """A depth tolerance in [0, upper].

    Raises:
        MapError: not a finite number in range."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise MapError(f"{name} must be a number, got {value!r}")
    v = float(value)
    if not (0.0 <= v <= upper):
        raise MapError(f"{name} must be in [0, {upper:g}], got {value!r}")
    return v


def make_rules(num_classes: int, transient_classes: Sequence[int] | None, half_life: float | None,
               tol_abs: float, tol_rel: float, depth_scale: float, prior: float) -> ChangeRules:
    """The checked :class:`ChangeRules` of a map's arguments (see :class:`~css_ros.engine.semantic_map.SemanticMap`)."""
    return ChangeRules(check_transient_classes(transient_classes, num_classes),
                       check_tolerance(tol_abs, "depth_tolerance", MAX_DEPTH_TOLERANCE),
                       check_tolerance(tol_rel, "depth_tolerance_relative", MAX_DEPTH_TOLERANCE_RELATIVE),
                       float(depth_scale), decay_factor(check_half_life(half_life)), float(prior))
