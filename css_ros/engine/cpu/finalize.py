"""The numba backend's final-form pass: one compiled, parallel sweep turns the raw float64 render buffers into a
view's final outputs (:mod:`css_ros.engine.final_form`) and reduces U_var / U_exp, instead of a dozen numpy passes."""
from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numba import njit, prange

from ..final_form import FrameImages, RenderSettings, uncertainty_from_sums
from ..pixel_math import confidence_score, interp, to_byte
from ..spec import VAR_FLOOR
from ..kernel_cache import bind_sources

if TYPE_CHECKING:
    from ..buffers import RenderBuffers

_to_byte = njit(inline="always")(to_byte)
_interp = njit(inline="always")(interp)
_confidence_score = njit(inline="always")(confidence_score)


@njit(inline="always")
def _uncertainty_terms(e, var):  # pragma: no cover
    """A pixel's terms of U_var and U_exp: (log max(Var, VAR_FLOOR), E)."""
    return math.log(max(var, VAR_FLOOR)), e


@njit(parallel=True, cache=True, nogil=True)
def _finalize_kernel(lab, exp, var, bg, ev, rgb, depth, thr, ignore, depth_scale, coef, knots_x, knots_y,
                     want_conf, out_lab, out_exp, out_var, out_bg, out_ev, out_rgb, out_depth,
                     out_conf, sums):  # pragma: no cover
    """Per pixel: the thresholded label and the float32 / uint8 forms of the raw buffers, written where the output
    array is not empty; per row, sums[v] of :func:`_row_sums` (in the same pass: the raw rows are read once)."""
    height, width = lab.shape
    for v in prange(height):
        s_lv = 0.0
        s_e = 0.0
        for u in range(width):
            lv, te = _uncertainty_terms(exp[v, u], var[v, u])
            s_lv += lv
            s_e += te
            label = lab[v, u]
            if bg[v, u] > thr:
                label = ignore
            e = exp[v, u]
            if out_lab.shape[0]:
                out_lab[v, u] = label
            if out_exp.shape[0]:
                out_exp[v, u] = e
            if out_var.shape[0]:
                out_var[v, u] = var[v, u]
            if out_bg.shape[0]:
                out_bg[v, u] = bg[v, u]
            if out_ev.shape[0]:
                out_ev[v, u] = ev[v, u]
            if out_rgb.shape[0]:
                for ch in range(3):
                    out_rgb[v, u, ch] = _to_byte(rgb[v, u, ch])
            if out_depth.shape[0]:
                out_depth[v, u] = depth[v, u] * depth_scale
            if want_conf:
                conf = 0.0
                if label != ignore:
                    conf = _interp(_confidence_score(e, ev[v, u], coef[0], coef[1], coef[2]), knots_x, knots_y)
                out_conf[v, u] = conf
        sums[v, 0] = s_lv
        sums[v, 1] = s_e


@njit(parallel=True, cache=True, nogil=True)
def _row_sums(exp, var):  # pragma: no cover
    """Per image row: (sum log max(Var, VAR_FLOOR), sum E), float64."""
    height, width = exp.shape
    out = np.zeros((height, 2))
    for v in prange(height):
        s_lv = 0.0
        s_e = 0.0
        for u in range(width):
            lv, te = _uncertainty_terms(exp[v, u], var[v, u])
            s_lv += lv
            s_e += te
        out[v, 0] = s_lv
        out[v, 1] = s_e
    return out


def uncertainty(expectation: np.ndarray, variance: np.ndarray) -> tuple[float, float]:
    """(U_var, U_exp) of SPEC §6 from (H, W) float64 E and Var: per-row sums in parallel, then the rows in order,
    so the result does not depend on the number of threads (a render and a score of one view give the same
    numbers)."""
    return _from_row_sums(_row_sums(expectation, variance), expectation.size)


def _from_row_sums(sums: np.ndarray, pixels: int) -> tuple[float, float]:
    """(U_var, U_exp) from the (H, 2) per-row sums of a view of ``pixels`` pixels, the rows added in order."""
    return uncertainty_from_sums(float(sums[:, 0].sum()), float(sums[:, 1].sum()), pixels)


def finalize(buf: "RenderBuffers", settings: RenderSettings) -> FrameImages:
    """The view's requested outputs from the numba render's raw buffers (same values as
    :func:`css_ros.engine.final_form.finalize_host`; confidence within float32 rounding)."""
    s = settings
    h, w = buf.labels.shape

    def plane(name: str, dtype: type, *extra: int) -> np.ndarray:
        if s.wants(name):
            return np.empty((h, w, *extra), dtype=dtype)
        return np.zeros((0,) * (2 + len(extra)), dtype=dtype)

    out = {"labels": plane("labels", np.int32), "expectation": plane("expectation", np.float32),
           "variance": plane("variance", np.float32), "background": plane("background", np.float32),
           "evidence": plane("evidence", np.float32), "rgb": plane("rgb", np.uint8, 3),
           "depth": plane("depth", np.float32), "confidence": plane("confidence", np.float32)}
    cmap = s.confidence
    want_conf = cmap is not None and s.wants("confidence")
    coef = np.zeros(3) if cmap is None else np.asarray(cmap.coef, dtype=np.float64)
    kx = np.zeros(1) if cmap is None else np.asarray(cmap.knots_x, dtype=np.float64)
    ky = np.zeros(1) if cmap is None else np.asarray(cmap.knots_y, dtype=np.float64)
    depth = buf.depth if buf.depth is not None else np.full((h, w), np.nan)
    sums = np.empty((h, 2))
    _finalize_kernel(buf.labels, buf.expectation, buf.variance, buf.background, buf.evidence, buf.rgb,
                     depth, float(s.unknown_threshold), int(s.ignore_label), float(s.depth_scale), coef,
                     kx, ky, want_conf, out["labels"], out["expectation"], out["variance"],
                     out["background"], out["evidence"], out["rgb"], out["depth"], out["confidence"], sums)
    u_var, u_exp = _from_row_sums(sums, h * w)
    images = FrameImages(u_var=u_var, u_exp=u_exp,
                         probabilities=None if not s.probabilities or buf.probabilities is None
                         else buf.probabilities.astype(np.float32))
    for name, arr in out.items():
        if arr.shape[0] or (h == 0 and s.wants(name)):
            setattr(images, name, arr)
    return images


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
