"""A "retrained" variant of a splat for the transfer tests and benchmark (independent of the engine's transfer).

Imitates what retraining / densification does to a 3DGS model: a fraction of the Gaussians is split in two
(INRIA densification: children sampled from the parent's own Gaussian, standard deviations / 1.6), a fraction
is pruned, every centre moves a little and the order is shuffled.
"""
from __future__ import annotations

import numpy as np

from css_ros import GaussianModel
from css_ros.engine.gaussians import rotation_matrices_wxyz


def retrained_variant(model: GaussianModel, seed: int = 0, split: float = 0.3, prune: float = 0.1,
                      jitter: float = 0.01) -> GaussianModel:
    """Split ``split`` of the Gaussians, prune ``prune`` of them, jitter every centre by ``jitter`` m
    (standard deviation per axis) and shuffle the order."""
    rng = np.random.default_rng(seed)
    n = model.num_gaussians
    role = rng.permutation(n)
    n_split, n_prune = int(split * n), int(prune * n)
    split_idx, keep_idx = role[:n_split], role[n_split + n_prune:]
    R = rotation_matrices_wxyz(model.quats_wxyz[split_idx])
    sigma = model.scales[split_idx].astype(np.float64)
    children = []
    for _ in range(2):
        offset = np.einsum("nij,nj->ni", R, sigma * rng.normal(size=sigma.shape))
        children.append(offset + model.means[split_idx])
    means = np.concatenate([model.means[keep_idx], *children])
    log_scales = np.concatenate([model.log_scales[keep_idx]] + [model.log_scales[split_idx] - np.log(1.6)] * 2)
    take = np.concatenate([keep_idx, split_idx, split_idx])
    means = means + rng.normal(scale=jitter, size=means.shape)
    order = rng.permutation(len(take))
    return GaussianModel(means[order], model.sh[take][order], model.opacity_logits[take][order],
                         log_scales[order], model.rotations[take][order])
