"""What css_node publishes for a live viewer (``css_view --live``), ROS-free: message layouts and quantisation.

- ``~/view/info`` (std_msgs/String, JSON, transient local): model size and fingerprint, class names and
  palette, chunk size, min_evidence.
- ``~/view/model`` (PointCloud2 chunks, transient local, sent once): per Gaussian ``index`` (uint32),
  ``x y z`` [m, map frame], the covariance ``c00 c01 c02 c11 c12 c22`` [m²], ``rgb`` (packed uint32,
  degree-0 colour), ``opacity`` (float32): 48 bytes a Gaussian.
- ``~/view/semantics`` (PointCloud2, reliable): only the Gaussians whose semantics changed visibly since
  they were last sent, at most ``view_max_changes`` a message: ``index`` (uint32), ``label`` (uint8, 255 =
  unobserved), ``expectation`` (uint8, E of the argmax class × 255), ``evidence`` (float32, S_n − Cα₀):
  10 bytes a Gaussian. Var follows from E and S_n (SPEC §4): Var = E(1 − E)/(1 + S_n).
"""
from __future__ import annotations

import json
from typing import Any

import numba
import numpy as np

from .clouds import pack_cloud, pack_rgb
from ..engine.kernel_cache import bind_sources

MODEL_FIELDS = ("index", "x", "y", "z", "c00", "c01", "c02", "c11", "c12", "c22", "rgb", "opacity")
SEMANTIC_FIELDS = ("index", "label", "expectation", "evidence")
MODEL_CHUNK = 65_536           # Gaussians per ~/view/model message (3 MB)
EVIDENCE_STEPS_PER_OCTAVE = 8  # a Gaussian is re-sent when its evidence moved by 1/8 of a doubling (≈ 9 %)


def info_json(num_gaussians: int, fingerprint: str, names, palette: np.ndarray, min_evidence: float,
              prior: float) -> str:
    return json.dumps({"num_gaussians": int(num_gaussians), "fingerprint": fingerprint, "classes": list(names),
                       "palette": np.asarray(palette).astype(int).tolist(), "chunk": MODEL_CHUNK,
                       "min_evidence": float(min_evidence), "prior": float(prior)})


def parse_info(text: str) -> dict[str, Any]:
    info = json.loads(text)
    for key in ("num_gaussians", "fingerprint", "classes", "palette", "chunk", "min_evidence", "prior"):
        if key not in info:
            raise ValueError(f"view info lacks {key!r}")
    return info


def model_chunks(means: np.ndarray, covariances: np.ndarray, rgb01: np.ndarray, opacity: np.ndarray):
    """Yield the ``~/view/model`` cloud columns, MODEL_CHUNK Gaussians at a time."""
    n = len(means)
    for start in range(0, n, MODEL_CHUNK):
        s = slice(start, min(n, start + MODEL_CHUNK))
        cov = covariances[s]
        rgb = np.clip(np.rint(rgb01[s] * 255.0), 0, 255).astype(np.uint8)
        yield pack_cloud({
            "index": np.arange(s.start, s.stop, dtype=np.uint32),
            "x": means[s, 0].astype(np.float32), "y": means[s, 1].astype(np.float32),
            "z": means[s, 2].astype(np.float32),
            "c00": cov[:, 0, 0].astype(np.float32), "c01": cov[:, 0, 1].astype(np.float32),
            "c02": cov[:, 0, 2].astype(np.float32), "c11": cov[:, 1, 1].astype(np.float32),
            "c12": cov[:, 1, 2].astype(np.float32), "c22": cov[:, 2, 2].astype(np.float32),
            "rgb": pack_rgb(rgb), "opacity": opacity[s].astype(np.float32)})


def semantic_keys(label: np.ndarray, expectation: np.ndarray, evidence: np.ndarray) -> np.ndarray:
    """(N,) int64 key of what the viewer shows of each Gaussian: equal keys look the same on the page."""
    lab = np.where((label >= 0) & (label < 255), label, 255).astype(np.int64)
    e_q = np.clip(np.rint(expectation * 255.0), 0, 255).astype(np.int64)
    s_q = np.rint(np.log2(1.0 + np.maximum(evidence, 0.0)) * EVIDENCE_STEPS_PER_OCTAVE).astype(np.int64)
    return (s_q << 16) | (e_q << 8) | lab


def semantics_columns(index: np.ndarray, label: np.ndarray, expectation: np.ndarray,
                      evidence: np.ndarray) -> dict[str, Any]:
    """``~/view/semantics`` cloud fields of the Gaussians ``index``."""
    lab = np.where((label >= 0) & (label < 255), label, 255).astype(np.uint8)
    return pack_cloud({"index": index.astype(np.uint32), "label": lab,
                       "expectation": np.clip(np.rint(expectation * 255.0), 0, 255).astype(np.uint8),
                       "evidence": evidence.astype(np.float32)})


@numba.njit(parallel=True, cache=True, nogil=True)
def _update_keys(conc, prior, min_evidence, ignore_label, keys):  # pragma: no cover - compiled
    n, c = conc.shape
    changed = np.zeros(n, dtype=np.bool_)
    for i in numba.prange(n):
        s = 0.0
        best = 0
        top = conc[i, 0]
        for k in range(c):
            v = conc[i, k]
            s += v
            if v > top:
                top = v
                best = k
        evidence = s - c * prior
        lab = best if evidence >= min_evidence else ignore_label
        e_q = np.int64(np.rint(min(max(top / s, 0.0), 1.0) * 255.0))
        s_q = np.int64(np.rint(np.log2(1.0 + max(evidence, 0.0)) * EVIDENCE_STEPS_PER_OCTAVE))
        key = (s_q << 16) | (e_q << 8) | lab
        if key != keys[i]:
            keys[i] = key
            changed[i] = True
    return changed


def changed_gaussians(concentrations: np.ndarray, prior: float, min_evidence: float, ignore_label: int,
                      keys: np.ndarray) -> np.ndarray:
    """Indices of the Gaussians whose :func:`semantic_keys` differ from ``keys`` (N,) int64; ``keys`` is
    updated in place to the current ones. One parallel pass over the (N, C) float64 concentrations."""
    return np.flatnonzero(_update_keys(concentrations, float(prior), float(min_evidence), int(ignore_label), keys))


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
