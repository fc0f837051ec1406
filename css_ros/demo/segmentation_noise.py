"""Noisy-segmentation model imitating a real network's errors on ground-truth label images (numpy/scipy only).

Given a label image (H, W) (255 = no label) and its frame index t, :meth:`SegmentationNoise.apply` returns a
corrupted label image and a confidence image. It is deterministic for (seed, t) and random-access: frame t does
not depend on which frames were generated before. All random fields are *smooth in space and time*: white
noise on a coarse grid, Gaussian-blurred and bilinearly upsampled, drawn afresh every ``keyframe_period``
frames and cross-faded in between, so errors drift and morph over frames like a real network's instead of
flickering per pixel.

Stage 0 happens in 3D, before this module sees the image (``css_make_demo`` does it):

0. **View-consistent (systematic) errors** (:data:`DEFAULT_SYSTEMATIC`): selected scene parts are labelled as a
   look-alike class during stretches of frames (a smooth on/off process per rule, "on" with the rule's
   probability): the cabinet as shelf, the top band of the walls as ceiling, the books on the shelf as shelf,
   the door as wall, the window sill as wall. These errors are attached to the surfaces, so they are
   consistent across viewpoints, and fusing many frames cannot simply average them away. The image the
   2D stages start from is rendered from the splat with these labels (:meth:`SegmentationNoise.systematic_active`
   says which rules are on at frame t).

The 2D corruption stages, in order:

1. **Frame severity** s_t: a smooth log-normal drift (knots every 10 frames) times occasional bursts (about one
   bad frame per ~85, up to 2x worse: motion blur, exposure). It scales the rates of stages 2-5. Mean ~1.
2. **Missing small objects**: every connected region of a "small" class is erased with a class-specific
   probability (:data:`DEFAULT_MISS_PROB`: outlet 0.55, lamp 0.3, box 0.2, picture 0.2; x1.6 for regions under
   40 px at 320x240); its pixels take the label of the nearest remaining pixel (an outlet becomes wall).
   Which regions vanish is decided by a smooth field sampled at the region centroid, so an object stays
   missing over consecutive frames.
3. **Look-alike confusion** (:data:`DEFAULT_CONFUSIONS`, rates :data:`DEFAULT_CONFUSION_RATE`): pixels of class c
   inside smooth patches are relabelled to a look-alike class. The patch density is ~rate_c * s_t, raised
   near pixels of a look-alike class and lowered far from them (the network extends the neighbouring
   class: the ceiling creeps down the wall); the new label is, with probability ``context_prob``, the nearest
   look-alike class actually in view, else one drawn from row c of the confusion matrix (wall <-> ceiling,
   wall -> door/window/cabinet/picture, table <-> shelf/cabinet/chair, chair <-> sofa, rug <-> floor,
   box -> shelf, picture <-> window, outlet -> wall, ...), piecewise constant over the patch. In addition a
   whole object region (up to 15 % of the image) is relabelled with probability ``whole_region_prob`` * s_t.
4. **Blobs of wrong labels**: smooth blobs covering ~``blob_fraction`` * s_t of the image take one label per
   blob: mostly the label of a region ~20 px away (bleeding), else a class present in the image, rarely any
   class.
5. **Boundary errors**: the label image is resampled through a smooth displacement field (amplitude
   ``boundary_shift_px`` * s_t pixels, nearest neighbour), so boundaries wobble and thin structures erode or
   dilate, plus 1-2 px jitter on a third of the pixels next to a class boundary.

Pixels without ground truth (255) stay 255. The **confidence** (float32 in [0, 1]) imitates a softmax score,
informative but imperfect: ~0.96 in clean interiors, lowered towards label boundaries (x (1 - 0.45
exp(-d / 2.5 px))), ~0.45 +- 0.15 over most regions corrupted by stages 3-4 (but ``overconfident_fraction``
of them keep a high score), x0.85 where a small object was erased, lower on bad frames; quantised to steps of
1/64 (compresses well in a bag). The systematic errors of stage 0 are *not* flagged by the confidence.
"""
from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np
from scipy import ndimage
from scipy.special import ndtr, ndtri

__all__ = [
    "DEFAULT_CONFUSIONS",
    "DEFAULT_CONFUSION_RATE",
    "DEFAULT_MISS_PROB",
    "DEFAULT_SYSTEMATIC",
    "NoiseConfig",
    "SegmentationNoise",
    "SystematicError",
    "confusion_matrix",
]

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



@dataclass(frozen=True)
class SystematicError:
    """A view-consistent confusion (stage 0): Gaussians of ``source_class`` (optionally only on scene
    primitives whose name starts with ``name_prefix`` and only above ``min_z`` metres) are labelled
    ``target_class`` during stretches of frames that cover a fraction ``probability`` of the sequence."""

    source_class: str
    target_class: str
    probability: float
    name_prefix: str | None = None
    min_z: float | None = None


#: Stage-0 rules of the demo room (names refer to :mod:`css_ros.demo_scene` primitives).
DEFAULT_SYSTEMATIC: tuple[SystematicError, ...] = (
    SystematicError("cabinet", "shelf", 0.5, name_prefix="cabinet"),
    SystematicError("wall", "ceiling", 0.6, min_z=2.3),
    SystematicError("box", "shelf", 0.5, name_prefix="shelf_box"),
    SystematicError("door", "wall", 0.35, name_prefix="door"),
    SystematicError("window", "wall", 0.7, name_prefix="window_sill"),
)


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
        # bilinear upsampling as two small matrix products (separable)
        return _interp_matrix(H, gh, cell) @ g @ _interp_matrix(W, gw, cell).T

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

    def systematic_active(self, frame: int, rule: int, probability: float, period: int = 12) -> bool:
        """Whether stage-0 rule ``rule`` is on at ``frame``: a smooth Gaussian process in time (knots every
        ``period`` frames, cosine-interpolated) thresholded so it is on for ~``probability`` of the frames."""
        if probability <= 0.0:
            return False
        if probability >= 1.0:
            return True
        k, r = divmod(int(frame), period)
        a = self._rng(950 + int(rule), k).standard_normal()
        b = self._rng(950 + int(rule), k + 1).standard_normal()
        w = 0.5 - 0.5 * math.cos(math.pi * r / period)
        g = ((1 - w) * a + w * b) / math.sqrt((1 - w) ** 2 + w ** 2)
        return bool(g < ndtri(probability))

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

    def _miss_small(self, lab: np.ndarray, valid: np.ndarray, frame: int,
                    sev: float) -> tuple[np.ndarray, np.ndarray]:
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
            sizes, iy, ix = _regions(comp, n)
            uc = u[iy, ix]
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
                # (at half resolution: the distance only sets a smooth rate, ~1 px error is irrelevant)
                d2, (iy, ix) = ndimage.distance_transform_edt(~near[::2, ::2], return_indices=True)
                d = _upsample2(d2, H, W) * 2.0
                nearest = _upsample2(lab[::2, ::2][iy, ix], H, W)
                boost = np.exp(-d / (self.config.context_px * W / 320.0))
                rate_map = np.clip(rate * (0.35 + 1.3 * boost), 1e-6, 0.95)
            else:
                rate_map = np.full(lab.shape, rate * 0.35)
            # per-class shift of the shared field so classes are not confused in the same places
            g = np.roll(g_region, shift=(int(c) * 37 % H, int(c) * 53 % W), axis=(0, 1))
            patch = mask & (g > ndtri(1.0 - rate_map))
            # whole-region confusion of objects (decided at the region centroid from a smooth field)
            comp, n = ndimage.label(mask)
            if n:
                idx = np.arange(1, n + 1)
                sizes, iy, ix = _regions(comp, n)
                uc = u_whole[(iy + int(c) * 41) % H, (ix + int(c) * 29) % W]
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
        _, iy, ix = _regions(comp, n)
        cy, cx = iy.astype(np.float64), ix.astype(np.float64)
        u = ndtr(self.smooth_field(lab.shape, frame, 32, scale=0.3))
        v = ndtr(self.smooth_field(lab.shape, frame, 33, scale=0.3))
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

        lab, missed = self._miss_small(lab, valid, frame, sev)
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


def _regions(comp: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Sizes (n,) in pixels and rounded centroid rows/cols (n,) of the regions 1..n of a label image."""
    H, W = comp.shape
    flat = comp.ravel()
    sizes = np.bincount(flat, minlength=n + 1)[1:].astype(np.float64)
    rows = np.repeat(np.arange(H, dtype=np.float64), W)
    cols = np.tile(np.arange(W, dtype=np.float64), H)
    safe = np.maximum(sizes, 1.0)
    cy = np.bincount(flat, weights=rows, minlength=n + 1)[1:] / safe
    cx = np.bincount(flat, weights=cols, minlength=n + 1)[1:] / safe
    return sizes, np.clip(np.rint(cy).astype(int), 0, H - 1), np.clip(np.rint(cx).astype(int), 0, W - 1)


def _upsample2(a: np.ndarray, H: int, W: int) -> np.ndarray:
    """Nearest-neighbour 2x upsampling of a [::2, ::2] subsampled image back to (H, W)."""
    return np.repeat(np.repeat(a, 2, axis=0), 2, axis=1)[:H, :W]


@functools.lru_cache(maxsize=64)
def _interp_matrix(n_out: int, n_in: int, cell: float) -> np.ndarray:
    """(n_out, n_in) linear-interpolation weights sampling a coarse grid (spacing ``cell`` output pixels) at the
    output pixel centres, offset by one coarse cell (so indices stay inside the grid)."""
    pos = (np.arange(n_out) + 0.5) / cell + 1.0
    i0 = np.clip(np.floor(pos).astype(int), 0, n_in - 2)
    f = pos - i0
    M = np.zeros((n_out, n_in))
    M[np.arange(n_out), i0] = 1.0 - f
    M[np.arange(n_out), i0 + 1] = f
    M.setflags(write=False)
    return M


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
