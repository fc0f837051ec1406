"""Noisy-segmentation model imitating a real network's errors on ground-truth label images (numpy/scipy only).

Given a ground-truth label image (H, W) (255 = no label) and its frame index t, :meth:`SegmentationNoise.apply`
returns a corrupted label image and a confidence image. It is deterministic for (seed, t) and random-access:
frame t does not depend on which frames were generated before. All random fields are *smooth in space and
time*: white noise at coarse resolution, Gaussian-blurred and bilinearly upsampled, drawn afresh every
``keyframe_period`` frames and cross-faded in between, so errors drift and morph over frames like a real
network's rather than flickering per pixel.

The corruption stages, in order:

1. **Frame severity** s_t: a smooth log-normal process (periodic in nothing, drawn per 10-frame knot) times
   occasional bursts (about one bad frame every ~30, 1.8-2.5x worse: motion blur, exposure changes). It scales
   the rates of stages 2-5. Mean ~1.
2. **Missing small objects**: every connected region of a "small" class (outlet, picture, box, lamp by
   default) is erased with a class-specific probability (outlet 0.55, lamp 0.3, box 0.3, picture 0.2, higher
   for regions under 40 px); its pixels take the label of the nearest remaining pixel (the surroundings, e.g.
   an outlet becomes wall). Which regions vanish is decided by a smooth field sampled at the region centroid,
   so an object stays missing over consecutive frames.
3. **Look-alike confusion**: pixels of class c inside smooth patches covering a fraction ~rate_c * s_t of the
   image are relabelled to a look-alike class drawn from row c of the confusion matrix (wall <-> ceiling,
   wall -> door/window, table <-> shelf/cabinet, chair <-> sofa/table, rug <-> floor, box -> shelf,
   picture -> window, plant -> chair, ...); the target is piecewise constant (a second smooth field quantised
   into the row's cumulative probabilities). In addition, a whole region is relabelled with probability
   ``whole_region_prob`` * s_t (a cabinet seen entirely as a shelf).
4. **Blobs of wrong labels**: smooth blobs covering ~``blob_fraction`` * s_t of the image take one label
   per blob: mostly the label of a neighbouring region ~20 px away (bleeding), else a random class.
5. **Boundary errors**: the label image is resampled through a smooth displacement field (amplitude
   ``boundary_shift_px`` * s_t pixels, nearest neighbour), so boundaries wobble and thin structures erode
   or dilate, plus 1-2 px per-pixel jitter on pixels next to a class boundary.

Pixels without ground truth (255) stay 255. The **confidence** (float32 in [0, 1]) imitates a softmax score,
informative but imperfect: ~0.95 in clean interiors, lowered towards label boundaries (exp(-d / 2.5 px)),
lowered in most corrupted regions (but ``overconfident_fraction`` of the errors keep a high score),
lowered on bad frames, with mild smooth variation; quantised to steps of 1/64.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage
from scipy.special import ndtr, ndtri

__all__ = ["DEFAULT_CONFUSIONS", "DEFAULT_MISS_PROB", "NoiseConfig", "SegmentationNoise", "confusion_matrix"]

#: Look-alike confusions by class name: source -> {target: relative weight}. Rows are normalised.
DEFAULT_CONFUSIONS: dict[str, dict[str, float]] = {
    "wall": {"ceiling": 0.3, "door": 0.2, "window": 0.1, "cabinet": 0.2, "picture": 0.2},
    "ceiling": {"wall": 1.0},
    "floor": {"rug": 0.7, "table": 0.3},
    "rug": {"floor": 1.0},
    "door": {"wall": 0.5, "cabinet": 0.3, "shelf": 0.2},
    "window": {"wall": 0.5, "picture": 0.5},
    "table": {"shelf": 0.35, "cabinet": 0.25, "chair": 0.4},
    "chair": {"sofa": 0.45, "table": 0.55},
    "shelf": {"table": 0.3, "cabinet": 0.4, "box": 0.3},
    "sofa": {"chair": 0.7, "rug": 0.3},
    "cabinet": {"shelf": 0.5, "wall": 0.3, "table": 0.2},
    "lamp": {"plant": 0.4, "chair": 0.6},
    "picture": {"window": 0.6, "wall": 0.4},
    "outlet": {"wall": 1.0},
    "plant": {"chair": 0.5, "sofa": 0.5},
    "box": {"shelf": 0.6, "table": 0.4},
}
#: Fraction of a class's pixels affected by look-alike confusion on an average frame.
DEFAULT_CONFUSION_RATE: dict[str, float] = {
    "wall": 0.08, "ceiling": 0.25, "floor": 0.06, "rug": 0.18, "door": 0.2, "window": 0.15, "table": 0.18,
    "chair": 0.2, "shelf": 0.2, "sofa": 0.12, "cabinet": 0.22, "lamp": 0.2, "picture": 0.2, "outlet": 0.2,
    "plant": 0.15, "box": 0.2,
}
#: Probability that a region of a small class is missed entirely on an average frame.
DEFAULT_MISS_PROB: dict[str, float] = {"outlet": 0.55, "lamp": 0.3, "box": 0.2, "picture": 0.2}


def confusion_matrix(class_names: Sequence[str],
                     confusions: Mapping[str, Mapping[str, float]] | None = None) -> np.ndarray:
    """(C, C) row-stochastic look-alike matrix P[c, c'] (zero diagonal; rows without entries are all zero).

    Names missing from ``class_names`` are ignored, so the same table works for any class set.
    """
    confusions = DEFAULT_CONFUSIONS if confusions is None else confusions
    idx = {n: i for i, n in enumerate(class_names)}
    C = len(class_names)
    P = np.zeros((C, C))
    for src, row in confusions.items():
        if src not in idx:
            continue
        for dst, w in row.items():
            if dst in idx and dst != src:
                P[idx[src], idx[dst]] = float(w)
    sums = P.sum(axis=1, keepdims=True)
    return np.divide(P, sums, out=np.zeros_like(P), where=sums > 0)


@dataclass
class NoiseConfig:
    """Parameters of the noise model (see the module docstring). Rates are per average frame."""

    keyframe_period: int = 6           # frames between independent draws of the smooth fields
    field_scale: float = 0.12          # correlation length of the smooth fields, fraction of the image width
    severity_log_std: float = 0.3      # std of log severity
    burst_prob: float = 0.35           # probability of a bad-frame burst per 30-frame block
    miss_prob: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_MISS_PROB))
    tiny_region_px: int = 40           # regions smaller than this (at 320x240) are missed more often
    confusion_rate: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_CONFUSION_RATE))
    whole_region_prob: float = 0.08    # probability that a whole object region is confused on an average frame
    whole_region_max_area: float = 0.15  # ... for regions up to this fraction of the image (not floor, walls)
    context_px: float = 25.0           # decay length (px at 320x240) of confusion near a look-alike class
    context_prob: float = 0.6          # probability that the confused label is the nearby look-alike class
    blob_fraction: float = 0.04       # image fraction covered by wrong-label blobs on an average frame
    blob_random_class_prob: float = 0.35
    boundary_shift_px: float = 2.0     # amplitude of the smooth boundary displacement, pixels at 320x240
    boundary_jitter_prob: float = 0.35
    overconfident_fraction: float = 0.35  # fraction of corrupted area whose confidence stays high


class SegmentationNoise:
    """Deterministic, temporally coherent segmentation corruption (see module docstring).

    Args:
        class_names: names of the C classes (ids = index); confusion and miss tables are looked up by name.
        seed: base seed; frame t uses streams derived from (seed, t) only.
        config: :class:`NoiseConfig`.
        confusions: source -> {target: weight} table (default :data:`DEFAULT_CONFUSIONS`).
        ignore_label: the "no label" value of inputs and outputs.
    """

    def __init__(self, class_names: Sequence[str], seed: int = 0, config: NoiseConfig | None = None,
                 confusions: Mapping[str, Mapping[str, float]] | None = None, ignore_label: int = 255) -> None:
        self.class_names = tuple(class_names)
        self.num_classes = len(self.class_names)
        self.seed = int(seed)
        self.config = config or NoiseConfig()
        self.ignore_label = int(ignore_label)
        self.confusion = confusion_matrix(self.class_names, confusions)
        self._cum = np.cumsum(self.confusion, axis=1)
        idx = {n: i for i, n in enumerate(self.class_names)}
        self.rate = np.zeros(self.num_classes)
        for n, r in self.config.confusion_rate.items():
            if n in idx:
                self.rate[idx[n]] = r
        self.rate[self.confusion.sum(axis=1) == 0] = 0.0
        self.miss = np.zeros(self.num_classes)
        for n, p in self.config.miss_prob.items():
            if n in idx:
                self.miss[idx[n]] = p

    # ---------------------------------------------------------------------------------------------- fields
    def _rng(self, *key: int) -> np.random.Generator:
        # keys are shifted so that small negative indices (block -1) stay valid SeedSequence entropy
        return np.random.default_rng([self.seed, *[int(k) + 1000 for k in key]])

    def _field_at_key(self, shape: tuple[int, int], tag: int, key: int, scale: float) -> np.ndarray:
        H, W = shape
        cell = max(2.0, scale * W / 3.0)  # ~3 coarse cells per correlation length
        gh, gw = int(math.ceil(H / cell)) + 3, int(math.ceil(W / cell)) + 3
        g = self._rng(tag, key, gh, gw).standard_normal((gh, gw))
        g = ndimage.gaussian_filter(g, 1.0, mode="wrap")
        g /= 0.28209479177387814  # std of unit white noise after a sigma=1 Gaussian blur is 1/(2 sqrt(pi))
        ys = (np.arange(H) + 0.5) / cell + 1.0
        xs = (np.arange(W) + 0.5) / cell + 1.0
        return ndimage.map_coordinates(g, np.meshgrid(ys, xs, indexing="ij"), order=1, mode="nearest")

    def smooth_field(self, shape: tuple[int, int], frame: int, tag: int, scale: float | None = None) -> np.ndarray:
        """Zero-mean, ~unit-std random field (H, W), smooth in space (correlation ~``scale`` x width) and in
        time (cross-fade between independent draws every ``keyframe_period`` frames)."""
        scale = self.config.field_scale if scale is None else scale
        P = max(1, self.config.keyframe_period)
        k, r = divmod(int(frame), P)
        w = 0.5 - 0.5 * math.cos(math.pi * r / P)
        f0 = self._field_at_key(shape, tag, k, scale)
        if w == 0.0:
            return f0
        f1 = self._field_at_key(shape, tag, k + 1, scale)
        return ((1.0 - w) * f0 + w * f1) / math.sqrt((1.0 - w) ** 2 + w ** 2)

    def severity(self, frame: int) -> float:
        """Frame severity s_t > 0 (mean ~1): smooth log-normal drift times occasional bursts."""
        cfg = self.config
        k, r = divmod(int(frame), 10)
        a = self._rng(901, k).standard_normal()
        b = self._rng(901, k + 1).standard_normal()
        w = 0.5 - 0.5 * math.cos(math.pi * r / 10)
        s = math.exp(cfg.severity_log_std * ((1 - w) * a + w * b) - 0.5 * cfg.severity_log_std ** 2)
        burst = 0.0
        blk = int(frame) // 30
        for b_ in (blk - 1, blk, blk + 1):
            rng = self._rng(902, b_)
            if rng.random() < cfg.burst_prob:
                centre = b_ * 30 + rng.uniform(0, 30)
                amp = rng.uniform(0.5, 1.0)
                burst += amp * math.exp(-0.5 * ((frame - centre) / 1.2) ** 2)
        return s * (1.0 + burst)

    # ---------------------------------------------------------------------------------------------- stages
    def _fill_from_nearest(self, labels: np.ndarray, holes: np.ndarray) -> np.ndarray:
        if not holes.any() or holes.all():
            return labels
        _, (iy, ix) = ndimage.distance_transform_edt(holes, return_indices=True)
        return labels[iy, ix]

    def _miss_small(self, lab: np.ndarray, valid: np.ndarray, frame: int, sev: float,
                    scale_px: float) -> tuple[np.ndarray, np.ndarray]:
        H, W = lab.shape
        missed = np.zeros(lab.shape, dtype=bool)
        u = None
        area_scale = (W * H) / (320 * 240)
        for c in np.nonzero(self.miss)[0]:
            mask = lab == c
            if not mask.any():
                continue
            if u is None:  # uniform-ish [0, 1] field from a smooth Gaussian field (probability integral)
                g = self.smooth_field(lab.shape, frame, 11, scale=0.2)
                u = ndtr(g)
            comp, n = ndimage.label(mask)
            if n == 0:
                continue
            idx = np.arange(1, n + 1)
            sizes = ndimage.sum_labels(np.ones_like(lab, dtype=np.float64), comp, idx)
            cy, cx = np.array(ndimage.center_of_mass(mask, comp, idx)).reshape(-1, 2).T
            uc = u[np.clip(np.rint(cy).astype(int), 0, H - 1), np.clip(np.rint(cx).astype(int), 0, W - 1)]
            p = np.clip(self.miss[c] * sev * np.where(sizes < self.config.tiny_region_px * area_scale, 1.6, 1.0),
                        0.0, 0.95)
            drop = idx[uc < p]
            if drop.size:
                missed |= np.isin(comp, drop)
        if missed.any():
            filled = self._fill_from_nearest(lab, missed | ~valid)
            lab = np.where(missed, filled, lab)
        return lab, missed

    def _confuse(self, lab: np.ndarray, valid: np.ndarray, frame: int, sev: float) -> tuple[np.ndarray, np.ndarray]:
        H, W = lab.shape
        out = lab.copy()
        changed = np.zeros(lab.shape, dtype=bool)
        present = np.unique(lab[valid])
        g_region = self.smooth_field(lab.shape, frame, 21)
        u_target = ndtr(self.smooth_field(lab.shape, frame, 22, scale=0.3))
        u_whole = ndtr(self.smooth_field(lab.shape, frame, 23, scale=0.25))
        max_whole = self.config.whole_region_max_area * H * W
        for c in present:
            if self.rate[c] <= 0:
                continue
            mask = (lab == c) & valid
            rate = min(0.9, self.rate[c] * sev)
            targets = np.nonzero(self.confusion[c] > 0)[0]
            near = np.isin(lab, targets) & valid
            nearest = None
            if near.any():
                # contextual: errors concentrate where a look-alike class is close (the net extends it)
                d, (iy, ix) = ndimage.distance_transform_edt(~near, return_indices=True)
                boost = np.exp(-d / (self.config.context_px * W / 320.0))
                rate_map = np.clip(rate * (0.35 + 1.3 * boost), 1e-6, 0.95)
                nearest = lab[iy, ix]
            else:
                rate_map = np.full(lab.shape, rate * 0.35)
            # per-class shift of the shared field so classes are not confused in the same places
            g = np.roll(g_region, shift=(int(c) * 37 % H, int(c) * 53 % W), axis=(0, 1))
            patch = mask & (g > ndtri(1.0 - rate_map))
            # whole-region confusion of objects (decided at the region centroid from a smooth field)
            comp, n = ndimage.label(mask)
            if n:
                idx = np.arange(1, n + 1)
                sizes = ndimage.sum_labels(np.ones(lab.shape), comp, idx)
                cy, cx = np.array(ndimage.center_of_mass(mask, comp, idx)).reshape(-1, 2).T
                uw = np.roll(u_whole, shift=(int(c) * 41 % H, int(c) * 29 % W), axis=(0, 1))
                uc = uw[np.clip(np.rint(cy).astype(int), 0, H - 1), np.clip(np.rint(cx).astype(int), 0, W - 1)]
                whole = idx[(uc < min(0.5, self.config.whole_region_prob * sev)) & (sizes <= max_whole)]
                if whole.size:
                    patch |= np.isin(comp, whole)
            if not patch.any():
                continue
            ut = u_target[patch]
            tgt = np.searchsorted(self._cum[c], ut * self._cum[c, -1], side="right")
            tgt = np.minimum(tgt, self.num_classes - 1)
            if nearest is not None:
                # mostly the look-alike class that is actually nearby, else one drawn from the row
                use_near = np.roll(u_target, shift=(H // 3, W // 3), axis=(0, 1))[patch] < self.config.context_prob
                tgt = np.where(use_near, nearest[patch], tgt)
            out[patch] = tgt
            changed |= patch
        return out, changed

    def _blobs(self, lab: np.ndarray, valid: np.ndarray, frame: int, sev: float) -> tuple[np.ndarray, np.ndarray]:
        H, W = lab.shape
        frac = min(0.3, self.config.blob_fraction * sev)
        g = self.smooth_field(lab.shape, frame, 31, scale=0.15)
        blob = (g > ndtri(1.0 - frac)) & valid
        if not blob.any():
            return lab, blob
        comp, n = ndimage.label(blob)
        idx = np.arange(1, n + 1)
        cy, cx = np.array(ndimage.center_of_mass(blob, comp, idx)).reshape(-1, 2).T
        u = ndtr(self.smooth_field(lab.shape, frame, 32, scale=0.3))
        v = ndtr(self.smooth_field(lab.shape, frame, 33, scale=0.3))
        iy = np.clip(np.rint(cy).astype(int), 0, H - 1)
        ix = np.clip(np.rint(cx).astype(int), 0, W - 1)
        uc, vc = u[iy, ix], v[iy, ix]
        # bleeding: label of the region ~20 px away in direction angle(v); else a random class
        ang = 2 * math.pi * vc
        dist = 20.0 * W / 320.0
        sy = np.clip(np.rint(cy + dist * np.sin(ang)).astype(int), 0, H - 1)
        sx = np.clip(np.rint(cx + dist * np.cos(ang)).astype(int), 0, W - 1)
        bleed = lab[sy, sx]
        present = np.unique(lab[valid & (lab < self.num_classes)])
        w = (vc * 7919.0) % 1.0
        any_cls = np.minimum((w * self.num_classes).astype(int), self.num_classes - 1)
        in_img = present[np.minimum((w * len(present)).astype(int), len(present) - 1)] if len(present) else any_cls
        rand_cls = np.where(uc < 0.3 * self.config.blob_random_class_prob, any_cls, in_img)
        use_rand = (uc < self.config.blob_random_class_prob) | (bleed == self.ignore_label) | \
            (bleed == lab[iy, ix])
        blob_cls = np.where(use_rand, rand_cls, bleed)
        table = np.concatenate([[0], blob_cls])
        out = np.where(blob, table[comp], lab)
        return out, blob & (out != lab)

    def _boundaries(self, lab: np.ndarray, frame: int, sev: float, rng: np.random.Generator) -> np.ndarray:
        H, W = lab.shape
        amp = self.config.boundary_shift_px * sev * W / 320.0
        dy = amp * self.smooth_field(lab.shape, frame, 41, scale=0.06)
        dx = amp * self.smooth_field(lab.shape, frame, 42, scale=0.06)
        yy, xx = np.meshgrid(np.arange(H), np.arange(W), indexing="ij")
        sy = np.clip(np.rint(yy + dy).astype(int), 0, H - 1)
        sx = np.clip(np.rint(xx + dx).astype(int), 0, W - 1)
        out = lab[sy, sx]
        edge = _boundary_mask(out)
        jitter = edge & (rng.random(lab.shape) < self.config.boundary_jitter_prob)
        if jitter.any():
            jy = np.clip(yy[jitter] + rng.integers(-2, 3, jitter.sum()), 0, H - 1)
            jx = np.clip(xx[jitter] + rng.integers(-2, 3, jitter.sum()), 0, W - 1)
            out = out.copy()
            out[jitter] = out[jy, jx]
        return out

    # ---------------------------------------------------------------------------------------------- public
    def apply(self, gt: np.ndarray, frame: int) -> tuple[np.ndarray, np.ndarray]:
        """Corrupt a ground-truth label image.

        Args:
            gt: (H, W) integer class ids; ``ignore_label`` = no ground truth.
            frame: frame index t (>= 0); drives the temporal evolution of every random field.
        Returns:
            (labels (H, W) uint8, confidence (H, W) float32 in [0, 1]); labels keep ``ignore_label`` where gt has it.
        """
        gt = np.asarray(gt)
        if gt.ndim != 2:
            raise ValueError(f"gt must be (H, W), got {gt.shape}")
        H, W = gt.shape
        cfg = self.config
        valid = (gt != self.ignore_label) & (gt >= 0) & (gt < self.num_classes)
        lab = np.where(valid, gt, self.ignore_label).astype(np.int64)
        sev = self.severity(frame)
        rng = self._rng(777, frame)

        lab, missed = self._miss_small(lab, valid, frame, sev, cfg.field_scale * W)
        lab, confused = self._confuse(lab, valid, frame, sev)
        lab, blobbed = self._blobs(lab, valid, frame, sev)
        lab = self._boundaries(lab, frame, sev, rng)
        if (~valid).any():  # the warp may move labels into unlabelled pixels and back: keep GT's mask
            lab = np.where(valid, lab, self.ignore_label)
            holes = valid & (lab == self.ignore_label)
            if holes.any():
                lab = np.where(holes, self._fill_from_nearest(lab, lab == self.ignore_label), lab)
                lab = np.where(valid, lab, self.ignore_label)

        # confidence
        dist = ndimage.distance_transform_edt(~_boundary_mask(lab))
        conf = 0.96 - 0.04 * np.clip(self.smooth_field(lab.shape, frame, 51, scale=0.2), -2, 2)
        conf *= 1.0 - 0.45 * np.exp(-dist / (2.5 * W / 320.0))
        corrupted = confused | blobbed
        detected = ndimage.binary_dilation(corrupted, iterations=2) & \
            (self.smooth_field(lab.shape, frame, 52, scale=0.15) > ndtri(cfg.overconfident_fraction))
        low = 0.45 + 0.15 * self.smooth_field(lab.shape, frame, 53, scale=0.1)
        conf = np.where(detected, np.minimum(conf, low), conf)
        conf = np.where(missed, conf * 0.85, conf)
        conf *= 1.0 / (1.0 + 0.25 * max(0.0, sev - 1.0))
        conf = np.round(np.clip(conf, 1.0 / 64.0, 1.0) * 64.0) / 64.0  # 1/64 steps: compresses well in a bag
        conf = np.where(valid, conf, 0.0)
        return lab.astype(np.uint8), conf.astype(np.float32)

    __call__ = apply


def _boundary_mask(lab: np.ndarray) -> np.ndarray:
    """Pixels (H, W) bool whose 4-neighbourhood contains another label."""
    edge = np.zeros(lab.shape, dtype=bool)
    dv = lab[1:, :] != lab[:-1, :]
    dh = lab[:, 1:] != lab[:, :-1]
    edge[1:, :] |= dv
    edge[:-1, :] |= dv
    edge[:, 1:] |= dh
    edge[:, :-1] |= dh
    return edge
