"""Range-dependent, view-consistent segmentation errors: a second error model for the demo bags (``--errors range``).

A real segmentation network is mostly right on surfaces close to the camera and increasingly wrong on far ones
(few pixels per object, no texture detail), and its mistakes on a far surface repeat in every far view of it:
the same far cabinet is "shelf" in all of them, the far outlet is always swallowed by the wall. Fusing many
views cannot average such errors away; only near views of the surface can correct them. This module imitates
that (numpy/scipy plus the engine's CPU rasteriser; deterministic for a seed, frame t random-access).

**Inputs per frame**: the ground-truth label image ``gt`` (H, W) (255 = no surface), the camera (pinhole K,
T_map_cam of the optical frame) and the frame index t. The pixel depth d [m] is the camera z of the surface:
with the sparse kappa_in of the view (:func:`css_ros.engine.cpu.raster.kappa_lists`, model Gaussian ids),
d = sum kappa z_G / sum kappa, z_G = third row of inverse(T_map_cam) applied to the Gaussian mean.

**Consistent errors** (decided per Gaussian, i.e. attached to the surface, then rendered):

* error probability (the *declared curve*, :meth:`RangeNoise.p_err`), a logistic in ln d with a ceiling::

      p_err(d, c, s_t) = min(p_cap, s_t * p_max * sigmoid(slope * ln(d / d50) + bias_c))

  with p_max = 0.85, d50 = 2.0 m, slope = 4.0 (bias 0: 5 % at 1 m, 20 % at 1.5 m, 42 % at 2 m, 60 % at
  2.5 m, 71 % at 3 m, 80 % at 4 m; a wall, bias -0.4: 3 % at 1 m, 34 % at 2 m, 66 % at 3 m), class logit offsets
  bias_c (:data:`RANGE_CLASS_BIAS`: floor -0.6, wall -0.4, ceiling -0.3 ... picture +0.9, box +1.0, lamp +1.0,
  outlet +1.6) and a mild per-frame severity s_t (log-normal, std 0.15, smooth over ``severity_period`` = 10
  frames, mean 1), p_cap = 0.95: near, clear views are mostly right, beyond ~2 m most labels are wrong.
* a smooth random field u(x) in [0, 1] fixed for the whole bag and attached to the surface point x: a sum of
  ``num_waves`` = 64 random 3D cosines with a Gaussian spectrum (covariance exp(-r^2 / (2 l^2)),
  l = ``error_length_m`` = 0.3 m, so an object of ~1 m holds several independent patches), made exactly
  uniform within each class by its ranks over that class's Gaussians (one realisation of a smooth field is
  far from uniform over a single object: without this, the only door of a room could be right or wrong from
  every distance). Gaussian G (class c_G, camera depth z_G) is *wrong* in a view iff
  u(x_G) < p_err(z_G, c_G, s_t): the same surface seen from far is wrong in every far view and right in the
  near ones; wrong patches are ~0.3-0.6 m across. Over a whole path the realised error rate per depth band
  scatters around the declared curve (a few dozen independent patches are seen at each depth).
* its wrong label is fixed per surface patch by a second field u2 (l = ``target_length_m`` = 1 m, so that
  neighbouring wrong patches mostly agree and a far wall region becomes one thing): small objects
  (:data:`ABSORB_PROB`: outlet 1.0, box 0.75, picture 0.7, lamp 0.5, plant 0.5) become, with that
  probability, the class they sit on (the class of the nearest Gaussian of a class that is not small:
  outlet, picture -> wall, box -> shelf / table / cabinet); otherwise a look-alike class drawn from row c of
  :data:`RANGE_CONFUSIONS` at u2 (wall -> ceiling / cabinet / door ..., floor -> rug, cabinet -> shelf ...,
  chair -> sofa / table ...; like ``segmentation_noise.DEFAULT_CONFUSIONS`` with fewer, more dominant
  targets).
* a pixel takes the consistent wrong label when the wrong Gaussians hold more than half of its kappa (the label
  is their kappa-weighted vote), else its ground truth.

**Per-frame noise on top** (seeded by (seed, t); fields from
:meth:`~css_ros.demo.segmentation_noise.SegmentationNoise.smooth_field`, drifting over frames): small blobs
(~``blob_fraction`` * s_t = 2 % of the image, ~0.05 x width across) take a look-alike label of the class under
them, and 35 % of the pixels next to a class boundary copy a label 1-2 px away.

**Confidence** (float32 in [0, 1], quantised to 1/64) imitates an overconfident network, informative only
weakly: 0.95 in clean interiors, x (1 - 0.45 exp(-dist / 1.5 px)) next to label boundaries,
x (1 - 0.12 min(d / 6 m, 1)) with depth, x (1 - 0.15 m) where the surface is close to its wrong/right decision
(m = kappa-weighted exp(-|u - p_err| / 0.05)), and 0.35-0.55 over half of the per-frame blobs. Far wrong
patches deep inside their error region stay confident (on the demo path the confidence separates right from
wrong pixels with an AUROC of ~0.72, against ~0.84 for the ``frame`` model).

On the shipped room trajectory (``css_make_demo --errors range``) about two thirds of the labelled pixels are
right; the bag README lists the accuracy per depth band.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Mapping, Sequence

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.special import expit, ndtri

from ..engine.sensor_model import depth_bins
from .segmentation_noise import SegmentationNoise, _boundary_mask, confusion_matrix

if TYPE_CHECKING:
    from ..engine.camera import Camera
    from ..engine.cpu.raster import KappaLists
    from ..engine.gaussians import GaussianModel

__all__ = [
    "ABSORB_PROB",
    "DEPTH_BANDS_M",
    "RANGE_CLASS_BIAS",
    "RANGE_CONFUSIONS",
    "RangeFrame",
    "RangeNoise",
    "RangeNoiseConfig",
    "SurfaceDepth",
    "band_label",
    "depth_band_counts",
    "support_classes",
    "uniform_ranks",
    "wave_field",
]

#: Logit offsets of p_err per class name (positive = more errors); classes not listed get 0.
RANGE_CLASS_BIAS: dict[str, float] = {
    "floor": -0.6, "wall": -0.4, "ceiling": -0.3, "door": 0.2, "window": 0.0, "rug": 0.0, "table": 0.3,
    "chair": 0.5, "shelf": 0.3, "sofa": 0.0, "cabinet": 0.4, "lamp": 1.0, "picture": 0.9, "outlet": 1.6,
    "plant": 0.8, "box": 1.0,
}
#: Look-alike table of far-range confusions: source -> {target: relative weight} (rows normalised). Fewer, more
#: dominant targets than ``segmentation_noise.DEFAULT_CONFUSIONS``: a far wall region becomes one thing.
RANGE_CONFUSIONS: dict[str, dict[str, float]] = {
    "floor": {"rug": 0.8, "wall": 0.2},
    "wall": {"ceiling": 0.35, "cabinet": 0.25, "door": 0.2, "window": 0.1, "picture": 0.1},
    "ceiling": {"wall": 1.0},
    "door": {"wall": 0.6, "cabinet": 0.4},
    "window": {"wall": 0.5, "picture": 0.5},
    "rug": {"floor": 1.0},
    "table": {"chair": 0.4, "shelf": 0.3, "cabinet": 0.3},
    "chair": {"sofa": 0.5, "table": 0.5},
    "shelf": {"cabinet": 0.6, "table": 0.2, "box": 0.2},
    "sofa": {"chair": 0.8, "rug": 0.2},
    "cabinet": {"shelf": 0.6, "wall": 0.2, "table": 0.2},
    "lamp": {"wall": 0.4, "plant": 0.3, "chair": 0.3},
    "picture": {"window": 1.0},
    "outlet": {"wall": 1.0},
    "plant": {"chair": 0.5, "sofa": 0.5},
    "box": {"shelf": 0.6, "table": 0.4},
}
#: Probability (per surface patch) that a wrong small object takes the class it sits on.
ABSORB_PROB: dict[str, float] = {"outlet": 1.0, "box": 0.75, "picture": 0.7, "lamp": 0.5, "plant": 0.5}
#: Depth band edges [m] of the accuracy tables (the last band is open).
DEPTH_BANDS_M: tuple[float, ...] = (0.0, 1.0, 2.0, 3.0, 4.0, 6.0, math.inf)


@dataclass(frozen=True)
class RangeNoiseConfig:
    """Parameters of the range model (see the module docstring; lengths in metres)."""

    p_max: float = 0.85                 # ceiling of the logistic
    d50: float = 2.0                    # m: depth where the logistic (bias 0) is at one half
    slope: float = 4.0                  # logistic slope per unit of ln(depth)
    p_cap: float = 0.95                 # hard cap after the severity
    class_bias: Mapping[str, float] = field(default_factory=lambda: dict(RANGE_CLASS_BIAS))
    absorb_prob: Mapping[str, float] = field(default_factory=lambda: dict(ABSORB_PROB))
    error_length_m: float = 0.3         # correlation length of the error field u
    target_length_m: float = 1.0        # correlation length of the wrong-label field u2
    num_waves: int = 64                 # cosines per 3D field
    severity_log_std: float = 0.15      # std of log s_t
    severity_period: int = 10           # frames between independent severity knots
    blob_fraction: float = 0.02         # image fraction of per-frame blobs at s_t = 1
    blob_scale: float = 0.05            # blob field correlation, fraction of the image width
    blob_low_conf_prob: float = 0.5     # fraction of blobs whose confidence drops
    jitter_prob: float = 0.35           # boundary pixels that copy a label 1-2 px away
    jitter_px: int = 2
    conf_base: float = 0.95
    conf_boundary_drop: float = 0.45    # at the boundary, decaying over conf_boundary_px
    conf_boundary_px: float = 1.5
    conf_depth_drop: float = 0.12       # at conf_depth_m and beyond
    conf_depth_m: float = 6.0
    conf_margin_drop: float = 0.15      # where u is within ~conf_margin of p_err
    conf_margin: float = 0.05


@dataclass(frozen=True)
class RangeFrame:
    """One corrupted frame (H, W arrays of the image).

    Attributes:
        labels: uint8 class ids (255 where the ground truth has no surface).
        confidence: float32 in [0, 1] (0 where no surface).
        depth: float32 surface depth [m] (camera z), NaN where nothing was rendered.
        consistent_wrong: bool, pixels carrying a view-consistent (3D) error before the per-frame noise.
        p_err: float32 declared error probability of the pixel (its depth, ground-truth class and s_t).
        severity: s_t.
    """

    labels: np.ndarray
    confidence: np.ndarray
    depth: np.ndarray
    consistent_wrong: np.ndarray
    p_err: np.ndarray
    severity: float


# ---------------------------------------------------------------------------------------------- 3D fields
def wave_field(points: np.ndarray, rng: np.random.Generator, length_m: float, num_waves: int = 64,
               chunk: int = 65536) -> np.ndarray:
    """Smooth zero-mean, unit-variance random field at ``points`` (N, 3) [m]: sqrt(2/K) sum_k cos(k.x + phi_k)
    with K = ``num_waves`` wave vectors drawn from N(0, I / length^2) (covariance exp(-r^2 / (2 length^2)))."""
    k = rng.normal(0.0, 1.0 / float(length_m), (int(num_waves), 3))
    phase = rng.uniform(0.0, 2.0 * math.pi, int(num_waves))
    pts = np.asarray(points, dtype=np.float64)
    out = np.empty(len(pts))
    for i in range(0, len(pts), chunk):
        out[i:i + chunk] = np.cos(pts[i:i + chunk] @ k.T + phase).sum(axis=1)
    return out * math.sqrt(2.0 / max(1, int(num_waves)))


def uniform_ranks(values: np.ndarray, groups: np.ndarray) -> np.ndarray:
    """(N,) values mapped to (0, 1) by their ranks within each group (``groups`` (N,) int): exactly uniform over
    every group's members, order (hence smoothness within a group) preserved."""
    values = np.asarray(values, dtype=np.float64)
    groups = np.asarray(groups, dtype=np.int64)
    order = np.lexsort((values, groups))                 # by group, then by value
    sizes = np.bincount(groups[order])
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]])
    g_sorted = groups[order]
    rank_in_group = np.arange(len(values)) - starts[g_sorted]
    out = np.empty(len(values))
    out[order] = (rank_in_group + 0.5) / sizes[g_sorted]
    return out


def support_classes(means: np.ndarray, class_ids: np.ndarray, small: np.ndarray) -> np.ndarray:
    """(N,) per Gaussian of a small class (``small`` (C,) bool), the class of the nearest Gaussian of a class that
    is not small (what the object sits on); other Gaussians keep their own class."""
    class_ids = np.asarray(class_ids, dtype=np.int64)
    out = class_ids.copy()
    is_small = small[class_ids]
    if is_small.any() and (~is_small).any():
        tree = cKDTree(means[~is_small])
        _, idx = tree.query(means[is_small])
        out[is_small] = class_ids[~is_small][idx]
    return out


def _wrong_targets(class_ids: np.ndarray, u2: np.ndarray, support: np.ndarray, absorb: np.ndarray,
                   confusion: np.ndarray) -> np.ndarray:
    """(N,) wrong label per Gaussian: the support class if u2 < absorb[c], else the confusion row c drawn at the
    rescaled u2 (own class when the row is empty)."""
    a = absorb[class_ids]
    use_support = u2 < a
    v = np.clip((u2 - a) / np.maximum(1.0 - a, 1e-9), 0.0, 1.0 - 1e-12)
    cum = np.cumsum(confusion, axis=1)[class_ids]           # (N, C)
    has_row = cum[:, -1] > 0
    drawn = np.minimum((v[:, None] * cum[:, -1:] >= cum).sum(axis=1), confusion.shape[0] - 1)
    return np.where(use_support, support, np.where(has_row, drawn, class_ids)).astype(np.int64)


# ---------------------------------------------------------------------------------------------- depth
class SurfaceDepth:
    """Per-view sparse kappa and pixel depth from the engine's CPU rasteriser (the model's own projection).

    Args:
        model: the splat (map frame, metres).
    """

    def __init__(self, model: "GaussianModel") -> None:
        from ..engine.cpu.projection import GaussianGeometry

        self.geometry = GaussianGeometry.from_model(model)
        self.means = np.asarray(model.means, dtype=np.float64)

    def kappa(self, camera: "Camera") -> "KappaLists":
        """Sparse kappa_in of the view (pixel = v * W + u, model Gaussian ids)."""
        from ..engine.cpu.projection import project
        from ..engine.cpu.raster import bin_tiles, kappa_lists

        proj = project(self.geometry, camera, view_colors=False)
        bins = bin_tiles(proj, int(camera.width), int(camera.height))
        return kappa_lists(proj, bins, int(camera.width), int(camera.height))

    def gaussian_depths(self, T_map_cam: np.ndarray) -> np.ndarray:
        """(N,) camera z [m] of every Gaussian mean (third row of inverse(T_map_cam))."""
        T = np.asarray(T_map_cam, dtype=np.float64)
        R, t = T[:3, :3], T[:3, 3]
        row = R[:, 2]  # (R^T)[2] : the optical axis in the map frame
        return (self.means - t) @ row

    def depth(self, camera: "Camera", kl: "KappaLists | None" = None) -> np.ndarray:
        """(H, W) float32 depth [m] = sum kappa z / sum kappa; NaN where nothing was rendered."""
        kl = self.kappa(camera) if kl is None else kl
        z = self.gaussian_depths(camera.T_map_cam)
        n = int(camera.width) * int(camera.height)
        w = np.bincount(kl.pixel, kl.kappa, n)
        d = np.bincount(kl.pixel, kl.kappa * z[kl.gaussian], n)
        out = np.full(n, np.nan)
        ok = w > 1e-6
        out[ok] = d[ok] / w[ok]
        return out.reshape(int(camera.height), int(camera.width)).astype(np.float32)


# ---------------------------------------------------------------------------------------------- the model
class RangeNoise:
    """Range-dependent, view-consistent segmentation errors (see the module docstring).

    Args:
        model: the splat the frames are rendered from (map frame, metres).
        class_ids: (N,) ground-truth class per Gaussian, in [0, C).
        class_names: the C class names (bias, absorb and confusion tables are looked up by name).
        seed: base seed; the 3D fields depend on it only, frame t's noise on (seed, t).
        config: :class:`RangeNoiseConfig`.
        confusions: look-alike table source -> {target: weight} (default :data:`RANGE_CONFUSIONS`).
        ignore_label: the "no surface" label of inputs and outputs.
    """

    def __init__(self, model: "GaussianModel", class_ids: np.ndarray, class_names: Sequence[str], seed: int = 0,
                 config: RangeNoiseConfig | None = None,
                 confusions: Mapping[str, Mapping[str, float]] | None = None, ignore_label: int = 255) -> None:
        self.config = config or RangeNoiseConfig()
        self.class_names = tuple(class_names)
        self.num_classes = len(self.class_names)
        self.seed = int(seed)
        self.ignore_label = int(ignore_label)
        self.class_ids = np.asarray(class_ids, dtype=np.int64)
        self.surface = SurfaceDepth(model)
        if len(self.class_ids) != len(self.surface.means):
            raise ValueError(f"class_ids has {len(self.class_ids)} entries for {len(self.surface.means)} Gaussians")
        self.bias = self._per_class(self.config.class_bias)
        absorb = np.clip(self._per_class(self.config.absorb_prob), 0.0, 1.0)
        confusion = confusion_matrix(self.class_names, RANGE_CONFUSIONS if confusions is None else confusions)
        self.confusion = confusion
        means = self.surface.means
        self.u_err = uniform_ranks(wave_field(means, self._rng(1), self.config.error_length_m, self.config.num_waves),
                                   self.class_ids)
        u2 = uniform_ranks(wave_field(means, self._rng(2), self.config.target_length_m, self.config.num_waves),
                           self.class_ids)
        self.support = support_classes(means, self.class_ids, absorb > 0)
        self.target = _wrong_targets(self.class_ids, u2, self.support, absorb, confusion)
        self._noise2d = SegmentationNoise(self.class_names, seed=self.seed + 7919, ignore_label=self.ignore_label)

    def _per_class(self, table: Mapping[str, float]) -> np.ndarray:
        return np.array([float(table.get(n, 0.0)) for n in self.class_names])

    def _rng(self, *key: int) -> np.random.Generator:
        return np.random.default_rng([self.seed, 4242, *[int(k) + 1000 for k in key]])

    # ------------------------------------------------------------------------------------------ curves
    def severity(self, frame: int) -> float:
        """s_t > 0 (mean ~1): log-normal, knots every ``severity_period`` frames, cosine-interpolated."""
        cfg = self.config
        k, r = divmod(int(frame), max(1, cfg.severity_period))
        a = self._rng(901, k).standard_normal()
        b = self._rng(901, k + 1).standard_normal()
        w = 0.5 - 0.5 * math.cos(math.pi * r / max(1, cfg.severity_period))
        g = ((1 - w) * a + w * b) / math.sqrt((1 - w) ** 2 + w ** 2)
        return math.exp(cfg.severity_log_std * g - 0.5 * cfg.severity_log_std ** 2)

    def p_err(self, depth: np.ndarray, class_ids: np.ndarray | int, severity: float = 1.0) -> np.ndarray:
        """The declared error probability p_err(d, c, s) (see the module docstring); depth [m], any shape
        broadcastable with ``class_ids``; depths <= 0 or NaN give 0."""
        cfg = self.config
        d = np.asarray(depth, dtype=np.float64)
        safe = np.where(np.isfinite(d) & (d > 0), d, 1.0)
        logit = cfg.slope * np.log(safe / cfg.d50) + self.bias[np.asarray(class_ids, dtype=np.int64)]
        p = np.minimum(cfg.p_cap, severity * cfg.p_max * expit(logit))
        return np.where(np.isfinite(d) & (d > 0), p, 0.0)

    # ------------------------------------------------------------------------------------------ per frame
    def _consistent(self, gt: np.ndarray, camera: "Camera", sev: float
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """(labels with the 3D errors, consistent-wrong mask, depth, margin term), all (H, W)."""
        H, W = gt.shape
        n = H * W
        kl = self.surface.kappa(camera)
        z = self.surface.gaussian_depths(camera.T_map_cam)             # per Gaussian (N,), cheap
        p_all = self.p_err(z, self.class_ids, sev)
        wrong_all = (self.u_err < p_all) & (self.target != self.class_ids)
        margin_all = np.exp(-np.abs(self.u_err - p_all) / self.config.conf_margin)
        gid, pix, kap = kl.gaussian, kl.pixel, kl.kappa
        # one gather of the per-Gaussian columns (z, margin, wrong), then kappa-weighted sums per pixel
        cols = np.stack([z, margin_all, wrong_all.astype(np.float64)], axis=1)[gid] * kap[:, None]
        wsum = 1.0 - kl.background                                       # sum of kappa = 1 - final transmittance
        inv = np.where(wsum > 1e-6, 1.0 / np.maximum(wsum, 1e-12), 0.0)
        depth = np.where(wsum > 1e-6, np.bincount(pix, cols[:, 0], n) * inv, np.nan)
        margin = np.bincount(pix, cols[:, 1], n) * inv
        wrong_frac = np.bincount(pix, cols[:, 2], n) * inv
        valid = (gt.ravel() != self.ignore_label) & (gt.ravel() < self.num_classes)
        is_wrong = valid & (wrong_frac > 0.5)
        labels = gt.ravel().astype(np.int64).copy()
        if is_wrong.any():
            C = self.num_classes
            sel = is_wrong[pix]
            sel[sel] = wrong_all[gid[sel]]
            vote = np.bincount(pix[sel] * C + self.target[gid[sel]], kap[sel], n * C).reshape(n, C)
            labels[is_wrong] = np.argmax(vote[is_wrong], axis=1)
        is_wrong &= labels != gt.ravel()
        return (labels.reshape(H, W), is_wrong.reshape(H, W), depth.reshape(H, W), margin.reshape(H, W))

    def _blobs(self, lab: np.ndarray, valid: np.ndarray, frame: int, sev: float,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Per-frame blobs with a look-alike label: (labels, (H, W) confidence ceiling of the flagged blobs, 0
        elsewhere)."""
        cfg = self.config
        frac = min(0.3, cfg.blob_fraction * sev)
        if frac <= 0:
            return lab, np.zeros(lab.shape)
        g = self._noise2d.smooth_field(lab.shape, frame, 61, scale=cfg.blob_scale)
        blob = (g > ndtri(1.0 - frac)) & valid
        comp, n = ndimage.label(blob)
        if n == 0:
            return lab, np.zeros(lab.shape)
        # the class under each blob: its most frequent label
        counts = np.zeros((n + 1, self.num_classes))
        np.add.at(counts, (comp[blob], lab[blob]), 1.0)
        under = np.argmax(counts[1:], axis=1)
        u = rng.random(n)
        cum = np.cumsum(self.confusion, axis=1)[under]
        drawn = np.minimum((u[:, None] * cum[:, -1:] >= cum).sum(axis=1), self.num_classes - 1)
        new = np.where(cum[:, -1] > 0, drawn, under)
        table = np.concatenate([[-1], new])
        out = np.where(blob, table[comp], lab)
        # about half of the blobs are flagged: their confidence drops to 0.35-0.55 (0 = not flagged)
        flag = rng.random(n) < cfg.blob_low_conf_prob
        low = np.concatenate([[0.0], np.where(flag, rng.uniform(0.35, 0.55, n), 0.0)])[comp]
        return out, low

    def _jitter(self, lab: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Boundary pixels copy the label ``1..jitter_px`` pixels away with probability ``jitter_prob``."""
        H, W = lab.shape
        edge = _boundary_mask(lab)
        pick = edge & (rng.random(lab.shape) < self.config.jitter_prob)
        if not pick.any():
            return lab
        yy, xx = np.nonzero(pick)
        r = self.config.jitter_px
        jy = np.clip(yy + rng.integers(-r, r + 1, len(yy)), 0, H - 1)
        jx = np.clip(xx + rng.integers(-r, r + 1, len(xx)), 0, W - 1)
        out = lab.copy()
        out[yy, xx] = lab[jy, jx]
        return out

    def _confidence(self, lab: np.ndarray, valid: np.ndarray, depth: np.ndarray, margin: np.ndarray,
                    low: np.ndarray) -> np.ndarray:
        """(H, W) float32 confidence of the final labels (see the module docstring)."""
        cfg = self.config
        dist = ndimage.distance_transform_edt(~_boundary_mask(lab))
        conf = cfg.conf_base * (1.0 - cfg.conf_boundary_drop * np.exp(-dist / cfg.conf_boundary_px))
        d = np.nan_to_num(depth, nan=0.0)
        conf *= 1.0 - cfg.conf_depth_drop * np.clip(d / cfg.conf_depth_m, 0.0, 1.0)
        conf *= 1.0 - cfg.conf_margin_drop * np.clip(margin, 0.0, 1.0)
        conf = np.where(low > 0, np.minimum(conf, low), conf)
        conf = np.round(np.clip(conf, 1.0 / 64.0, 1.0) * 64.0) / 64.0
        return np.where(valid, conf, 0.0).astype(np.float32)

    def apply(self, gt: np.ndarray, camera: "Camera", frame: int) -> RangeFrame:
        """Corrupt the ground truth ``gt`` (H, W) of the view ``camera`` (its width x height) at frame ``frame``."""
        gt = np.asarray(gt)
        if gt.shape != (int(camera.height), int(camera.width)):
            raise ValueError(f"gt {gt.shape} does not match the camera {camera.height}x{camera.width}")
        sev = self.severity(frame)
        rng = self._rng(777, frame)
        valid = (gt != self.ignore_label) & (gt < self.num_classes)
        lab, wrong3d, depth, margin = self._consistent(gt, camera, sev)
        lab, low = self._blobs(lab, valid, frame, sev, rng)
        lab = self._jitter(lab, rng)
        lab = np.where(valid, lab, self.ignore_label)
        holes = valid & ((lab == self.ignore_label) | (lab < 0))  # jitter may copy a no-surface label inwards
        if holes.any():
            lab = np.where(holes, gt, lab)
        conf = self._confidence(lab, valid, depth, margin, low)
        p = np.where(valid, self.p_err(depth, np.where(valid, gt, 0), sev), 0.0).astype(np.float32)
        return RangeFrame(labels=lab.astype(np.uint8), confidence=conf, depth=depth.astype(np.float32),
                          consistent_wrong=wrong3d, p_err=p, severity=sev)

    __call__ = apply


# ---------------------------------------------------------------------------------------------- statistics
def depth_band_counts(labels: np.ndarray, gt: np.ndarray, depth: np.ndarray,
                      bands: Sequence[float] = DEPTH_BANDS_M, ignore_label: int = 255) -> np.ndarray:
    """(B, 2) int64 per depth band [edges ``bands``, m]: (correct, labelled) pixel counts of one frame."""
    edges = np.asarray(bands, dtype=np.float64)
    valid = (np.asarray(gt) != ignore_label) & np.isfinite(depth)
    b = depth_bins(edges, np.asarray(depth)[valid])
    ok = (np.asarray(labels)[valid] == np.asarray(gt)[valid]).astype(np.int64)
    out = np.zeros((len(edges) - 1, 2), dtype=np.int64)
    out[:, 0] = np.bincount(b, ok, len(edges) - 1).astype(np.int64)
    out[:, 1] = np.bincount(b, minlength=len(edges) - 1)
    return out


def band_label(lo: float, hi: float) -> str:
    """'2-3 m' or '> 6 m'."""
    return f"> {lo:g} m" if not math.isfinite(hi) else f"{lo:g}-{hi:g} m"
