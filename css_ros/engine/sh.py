"""Real spherical-harmonics colour evaluation (degrees 0-3, INRIA 3DGS constants and ordering)."""
from __future__ import annotations

from typing import Any

SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005,
         -1.0925484305920792, 0.5462742152960396)
SH_C3 = (-0.5900435899266435, 2.890611442640554, -0.4570457994644658, 0.3731763325901154,
         -0.4570457994644658, 1.445305721320277, -0.5900435899266435)


def num_sh_coeffs(degree: int) -> int:
    """Number of SH coefficients per colour channel for ``degree`` (1, 4, 9 or 16)."""
    return (degree + 1) ** 2


def eval_sh(sh: Any, dirs: Any) -> Any:
    """Evaluate view-dependent colour before the +0.5 offset and clamping.

    Works on numpy arrays and torch tensors alike (plain arithmetic and slicing only).

    Args:
        sh: (M, K, 3) coefficients, K in {1, 4, 9, 16}; index 0 is the DC term.
        dirs: (M, 3) unit view directions (Gaussian mean minus camera centre, normalised), map frame.
    Returns:
        (M, 3) sum_k SH_k(dir) * coeff_k; the displayed colour is max(0, result + 0.5).
    """
    k = sh.shape[1]
    result = SH_C0 * sh[:, 0]
    if k < 4:
        return result
    x, y, z = dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3]
    result = result - SH_C1 * y * sh[:, 1] + SH_C1 * z * sh[:, 2] - SH_C1 * x * sh[:, 3]
    if k < 9:
        return result
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    result = (result + SH_C2[0] * xy * sh[:, 4] + SH_C2[1] * yz * sh[:, 5]
              + SH_C2[2] * (2.0 * zz - xx - yy) * sh[:, 6] + SH_C2[3] * xz * sh[:, 7]
              + SH_C2[4] * (xx - yy) * sh[:, 8])
    if k < 16:
        return result
    return (result + SH_C3[0] * y * (3.0 * xx - yy) * sh[:, 9] + SH_C3[1] * xy * z * sh[:, 10]
            + SH_C3[2] * y * (4.0 * zz - xx - yy) * sh[:, 11]
            + SH_C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * sh[:, 12]
            + SH_C3[4] * x * (4.0 * zz - xx - yy) * sh[:, 13] + SH_C3[5] * z * (xx - yy) * sh[:, 14]
            + SH_C3[6] * x * (xx - 3.0 * yy) * sh[:, 15])
