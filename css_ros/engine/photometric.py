"""Photometric comparison of rendered and camera images (used by the node's diagnostics and by the
evaluation; lives in the engine so that the node does not depend on the evaluation layer)."""
from __future__ import annotations

import numpy as np


def psnr(a: np.ndarray, b: np.ndarray, peak: float = 255.0) -> float:
    """Peak signal-to-noise ratio in dB of two same-shape images (inf when identical)."""
    d = np.asarray(a, dtype=np.float64) - np.asarray(b, dtype=np.float64)
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else float(10.0 * np.log10(peak * peak / mse))


def format_psnr(db: float) -> str:
    """PSNR for people: "12.3 dB", "identical" for an error-free render (inf), "n/a" when unknown (NaN)."""
    if db == float("inf"):
        return "identical"
    return "n/a" if not np.isfinite(db) else f"{db:.1f} dB"
