"""Spherical-harmonics basis: orthonormal real SH of degree <= 3 with the INRIA sign convention."""
from __future__ import annotations

import numpy as np
import torch

from css_ros.engine.sh import SH_C0, eval_sh


def basis(dirs):
    """Evaluate the 16 basis functions by feeding unit coefficient vectors."""
    n = len(dirs)
    out = np.empty((n, 16))
    for k in range(16):
        sh = np.zeros((n, 16, 3))
        sh[:, k, 0] = 1.0
        out[:, k] = eval_sh(sh, dirs)[:, 0]
    return out


def test_basis_is_orthonormal_on_the_sphere():
    # Fibonacci sphere: near-uniform quadrature, integral = 4 pi * mean
    n = 200_000
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    phi = np.pi * (1 + 5 ** 0.5) * i
    r = np.sqrt(1 - z * z)
    dirs = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    b = basis(dirs)
    gram = 4 * np.pi * (b.T @ b) / n
    np.testing.assert_allclose(gram, np.eye(16), atol=2e-3)


def test_degree_and_sign_convention():
    d = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    b = basis(d)
    np.testing.assert_allclose(b[:, 0], SH_C0)
    c1 = np.sqrt(3 / (4 * np.pi))
    # INRIA order: -C1*y, +C1*z, -C1*x
    np.testing.assert_allclose(b[0, 1:4], [0, c1, 0], atol=1e-12)
    np.testing.assert_allclose(b[1, 1:4], [0, 0, -c1], atol=1e-12)
    np.testing.assert_allclose(b[2, 1:4], [-c1, 0, 0], atol=1e-12)
    # basis k has degree l(k): Y(-d) = (-1)^l Y(d)
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(50, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    degree = np.array([0] + [1] * 3 + [2] * 5 + [3] * 7)
    np.testing.assert_allclose(basis(-dirs), basis(dirs) * (-1.0) ** degree, atol=1e-12)


def test_numpy_and_torch_agree():
    rng = np.random.default_rng(1)
    sh = rng.normal(size=(30, 16, 3))
    dirs = rng.normal(size=(30, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    np.testing.assert_allclose(eval_sh(torch.tensor(sh), torch.tensor(dirs)).numpy(), eval_sh(sh, dirs), atol=1e-12)
