"""Per-pixel maths, written once for both compiled targets (like :mod:`.splat_math`): the final form of a view and
the sensor model's depth bin.

Plain scalar Python functions: ``engine/cpu/finalize.py`` compiles them with ``numba.njit(inline="always")``
and ``engine/cuda/kernels.py`` with ``numba.cuda.jit(device=True, inline=True)``; numpy callers use the
vectorised forms in :mod:`.final_form`, which the tests hold equal to these.
"""
from __future__ import annotations

import math

#: logit(E) is taken with E clipped to [E_CLIP, 1 - E_CLIP] (sensor_model.ConfidenceMap.features)
E_CLIP = 1e-6
#: the logistic score's argument is clipped to +-Z_CLIP (ConfidenceMap.score)
Z_CLIP = 60.0


def depth_bin(depth, edges):  # type: ignore[no-untyped-def]
    """Bin b of ``depth`` with edges[b] <= depth < edges[b + 1]; below edges[1]: 0, beyond the last edge: B - 1
    (the sensor model's rule, SensorModel.bin_of; B is small, a linear scan). ``edges`` (B + 1,) increasing."""
    b = 0
    last = edges.shape[0] - 2
    while b < last and depth >= edges[b + 1]:
        b += 1
    return b


def to_byte(x):  # type: ignore[no-untyped-def]
    """numpy's ``clip(rint(x * 255), 0, 255)`` as an int (round half to even; NaN and x <= 0 give 0). ``round`` of a
    float is Python's, numba's (``llvm.rint``) and numba-cuda's (``llrint``) round half to even alike, and one
    instruction where compiled (a floor-and-compare version made the CPU's final-form pass 2.4 times slower)."""
    y = x * 255.0
    if not (y > 0.0):
        return 0
    if y >= 255.0:
        return 255
    return int(round(y))


def interp(x, xp, fp):  # type: ignore[no-untyped-def]
    """numpy's ``interp(x, xp, fp)`` for one x (xp strictly increasing; flat beyond the ends)."""
    n = xp.shape[0]
    if not (x > xp[0]):
        return fp[0]
    if x >= xp[n - 1]:
        return fp[n - 1]
    lo = 0
    hi = n - 1
    while hi - lo > 1:  # xp[lo] < x < xp[hi]
        mid = (lo + hi) // 2
        if xp[mid] <= x:
            lo = mid
        else:
            hi = mid
    slope = (fp[lo + 1] - fp[lo]) / (xp[lo + 1] - xp[lo])
    return slope * (x - xp[lo]) + fp[lo]


def confidence_score(expectation, evidence, c0, c1, c2):  # type: ignore[no-untyped-def]
    """The logistic score of sensor_model.ConfidenceMap for one pixel, before its isotonic correction
    (:func:`interp` through the knots): sigmoid(c0 logit(E) + c1 log(1 + evidence) + c2), E clipped to
    [E_CLIP, 1 - E_CLIP], the argument to +-Z_CLIP. Written with explicit comparisons (not min / max, whose NaN
    handling differs between Python, numba and CUDA) so that every backend gives numpy's answer: a NaN input or a
    NaN argument (0 x inf) scores 0.5, +-inf is clipped."""
    e = expectation
    if e < E_CLIP:
        e = E_CLIP
    elif e > 1.0 - E_CLIP:
        e = 1.0 - E_CLIP
    ev = 0.0 if evidence < 0.0 else evidence
    z = c0 * math.log(e / (1.0 - e)) + c1 * math.log1p(ev) + c2
    if z != z:
        z = 0.0
    elif z > Z_CLIP:
        z = Z_CLIP
    elif z < -Z_CLIP:
        z = -Z_CLIP
    return 0.5 * (1.0 + math.tanh(0.5 * z))
