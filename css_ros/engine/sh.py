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


C2_0, C2_1, C2_2, C2_3, C2_4 = SH_C2   # scalars: compiled kernels read module-level floats as constants
C3_0, C3_1, C3_2, C3_3, C3_4, C3_5, C3_6 = SH_C3


def sh_polynomial(coef, k, x, y, z):  # type: ignore[no-untyped-def]
    """sum_{j < k} SH_j(x, y, z) coef[j]: the one definition of the SH colour polynomial.

    Plain arithmetic, so the same function serves numpy and torch arrays (:func:`eval_sh`) and the
    compiled kernels, which compile it for the CPU (``numba.njit``) and the GPU
    (``numba.cuda.jit(device=True)``) with scalar arguments.

    Args:
        coef: indexable by j < k: the coefficients of basis function j (a scalar per colour channel in
            the kernels, ``sh[i, :, c]``; an (M, 3) array per j for arrays).
        k: number of coefficients, 1, 4, 9 or 16 (degree 0-3).
        x, y, z: the unit view direction (Gaussian centre minus camera centre), unused when k = 1.
    Returns:
        The colour before the +0.5 offset and the clamp at 0.
    """
    v = SH_C0 * coef[0]
    if k >= 4:
        v = v - SH_C1 * y * coef[1] + SH_C1 * z * coef[2] - SH_C1 * x * coef[3]
    if k >= 9:
        xx, yy, zz = x * x, y * y, z * z
        v = (v + C2_0 * (x * y) * coef[4] + C2_1 * (y * z) * coef[5]
             + C2_2 * (2.0 * zz - xx - yy) * coef[6] + C2_3 * (x * z) * coef[7]
             + C2_4 * (xx - yy) * coef[8])
    if k >= 16:
        xx, yy, zz = x * x, y * y, z * z
        v = (v + C3_0 * y * (3.0 * xx - yy) * coef[9] + C3_1 * (x * y) * z * coef[10]
             + C3_2 * y * (4.0 * zz - xx - yy) * coef[11]
             + C3_3 * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coef[12]
             + C3_4 * x * (4.0 * zz - xx - yy) * coef[13] + C3_5 * z * (xx - yy) * coef[14]
             + C3_6 * x * (xx - 3.0 * yy) * coef[15])
    return v


def eval_sh(sh: Any, dirs: Any) -> Any:
    """Evaluate view-dependent colour before the +0.5 offset and clamping.

    Works on numpy arrays and torch tensors alike (through :func:`sh_polynomial`).

    Args:
        sh: (M, K, 3) coefficients, K in {1, 4, 9, 16}; index 0 is the DC term.
        dirs: (M, 3) unit view directions (Gaussian mean minus camera centre, normalised), map frame;
            may be None when K = 1.
    Returns:
        (M, 3) sum_k SH_k(dir) * coeff_k; the displayed colour is max(0, result + 0.5).
    """
    k = sh.shape[1]
    coef = sh.swapaxes(0, 1)  # (K, M, 3): coef[j] is basis j's (M, 3) coefficients
    if k < 4:
        return sh_polynomial(coef, k, None, None, None)
    return sh_polynomial(coef, k, dirs[:, 0:1], dirs[:, 1:2], dirs[:, 2:3])
