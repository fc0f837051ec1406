#!/usr/bin/env python3
"""Active mapping on the demo room: which next-view strategy builds the best semantic map from few views?

A mobile robot starts with 2 fused views (fixed per seed). At every step it is offered M random candidate poses
(camera height 0.5-1.5 m, pitch -30..+10 degrees, any yaw, in the free space of the room: inside the walls, off the
furniture footprints, no Gaussian closer than 0.2 m to the camera), picks one by a strategy, segments it (the ground
truth rendered by ``DemoRenderer``, corrupted by the error model) and fuses it with ``SemanticMap.update``.
Strategies (all see the same candidates and the same noise for a seed):

* ``random``         - a candidate drawn at random (the same draw for every error kind);
* ``u_var``          - the largest U_var (geometric mean of the rendered variance);
* ``u_exp``          - the largest U_exp (1 - mean rendered expectation);
* ``coverage``       - the most visible Gaussians not yet observed (S_n - C alpha_0 < 0.5; visible: kappa mass
  >= 0.1 in the candidate view, from ``css_ros.engine.cpu.raster.kappa_lists``);
* ``info_gain``      - the largest expected reduction of the map's uncertainty (``score_views`` column 2, with the
  map's sensor model when it has one);
* ``info_gain_task`` - the same, weighted by ``task_importance`` (the kappa mass of each Gaussian) of 10 fixed "task"
  poses: a robot driving west along the room's north corridor (y = 2 m, x = 2.6 .. -2.4 m, camera 1 m high, pitch
  -10 degrees, sweeping +-20 degrees about the direction of travel); ties (no candidate sees the task region) are
  broken by the unweighted gain.

Error kinds: ``frame`` (``SegmentationNoise`` plus the demo's view-consistent stage-0 rules, frame index = view
number + 1000 x seed, as ``css_make_demo --errors frame``) and ``range`` (``RangeNoise``: errors growing with depth,
one surface field per seed, as ``css_make_demo --errors range``). Range errors are fused twice: with the paper's
update and with a sensor model calibrated once on ``bags/calib_range/bag`` (another scene; ``css_calibrate``).
Every labelled pixel is fused with the segmenter's confidence image, as css_replay and css_node do.

The maps are evaluated after 2 (the start views: the same for every strategy), 6, 12, 18 and 24 fused views at 40
fixed held-out poses (fixed for the scene, not per seed; drawn like the candidates) and at the 10 task poses: mIoU
and pixel accuracy of ``smap.render`` labels against the rendered ground truth (``ConfusionMatrix``; ground truth
255 excluded, "unknown" predictions count as wrong).

Outputs (``--out``, default ``out/active_mapping``): ``results.json`` (per setting x strategy x view count: mean,
std, min, max and the per-seed values of mIoU, accuracy and task-view mIoU / accuracy; the chosen candidates; the
configuration and wall time), ``results.md`` (the tables printed at the end), ``miou_frame.png`` and
``miou_range.png`` (mIoU vs fused views, mean +- one standard deviation over seeds).

    python benchmarks/active_mapping.py                      # the full run (8 seeds, 32 candidates, 24 views)
    python benchmarks/active_mapping.py --quick              # a smoke run (2 seeds, 8 candidates, 6 views) in ~30 s
    python benchmarks/active_mapping.py --seeds 4 --errors range --strategies random info_gain

Scores come from ``SemanticMap.score_views(cameras, importance=None)`` (columns U_var, U_exp, info_gain; docs/spec.md
"Information gain of a view") and the task weights from ``SemanticMap.task_importance(cameras)``.
"""
from __future__ import annotations

import argparse
import json
import math
import os
import platform
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from css_ros.engine.spec import DEFAULT_MIN_EVIDENCE

REPO = Path(__file__).resolve().parents[1]
STRATEGIES: tuple[str, ...] = ("random", "u_var", "u_exp", "coverage", "info_gain", "info_gain_task")
ERROR_KINDS: tuple[str, ...] = ("frame", "range")
#: setting -> (error kind, sensor model used, label)
SETTINGS: dict[str, tuple[str, bool, str]] = {
    "frame": ("frame", False, "per-frame errors"),
    "range": ("range", False, "range errors, paper update"),
    "range_sensor": ("range", True, "range errors, calibrated sensor model"),
}
NUM_GAUSSIANS = 50_000           # the shipped demo room's size
SCENE_SEED = 0                   # the shipped demo room
NUM_CLASSES = 16
START_VIEWS = 2
EVAL_POSE_SEED = 20_240_901      # the held-out poses: one fixed draw for the scene
FRAME_OFFSET_PER_SEED = 1000     # frame index of view v for seed s: v + 1000 s (noise streams per seed)
HEIGHT_RANGE_M = (0.5, 1.5)
PITCH_RANGE_DEG = (-30.0, 10.0)
ROBOT_RADIUS_M = 0.25            # footprints are inflated by this; the walls keep it too (+ 0.1 m)
CLEARANCE_M = 0.2                # no Gaussian centre closer than this to the camera ("not inside an object")
VISIBLE_KAPPA = 0.1              # coverage: a Gaussian is visible in a view when its kappa mass reaches this
UNOBSERVED_EVIDENCE = DEFAULT_MIN_EVIDENCE   # coverage: S_n - C alpha_0 below this = not yet observed (SPEC §9)
#: the task poses: a robot driving west along the north corridor (y = 2 m), its camera sweeping +-20 deg
TASK_CORRIDOR_Y = 2.0
TASK_X = tuple(np.linspace(2.6, -2.4, 10).round(3))
TASK_YAW_DEG = (180.0, 200.0, 160.0) * 3 + (180.0,)
TASK_PITCH_DEG = -10.0
TASK_HEIGHT_M = 1.0
CALIB_BAG = REPO / "bags" / "calib_range" / "bag"
DEFAULT_OUT = REPO / "out" / "active_mapping"

FULL = {"seeds": 8, "views": (6, 12, 18, 24), "candidates": 32, "eval_poses": 40, "fused": (128, 96),
        "candidate_size": (96, 72)}
QUICK = {"seeds": 2, "views": (4, 6), "candidates": 8, "eval_poses": 8, "fused": (96, 72), "candidate_size": (64, 48)}


# ---------------------------------------------------------------------------------------------------- poses
def pose_matrix(x: float, y: float, z: float, yaw_deg: float, pitch_deg: float) -> np.ndarray:
    """(4, 4) T_map_cam of an optical frame at (x, y, z) looking along yaw (0 = +x, ccw) and pitch (up > 0)."""
    from css_ros.demo.trajectory import look_at_rotation

    yaw, pitch = math.radians(yaw_deg), math.radians(pitch_deg)
    fwd = np.array([math.cos(pitch) * math.cos(yaw), math.cos(pitch) * math.sin(yaw), math.sin(pitch)])
    T = np.eye(4)
    T[:3, :3] = look_at_rotation(fwd)
    T[:3, 3] = (x, y, z)
    return T


class FreeSpace:
    """Where the robot's camera may be: inside the room's walls, outside the inflated furniture footprints (the rug
    is drivable), with no Gaussian centre within ``CLEARANCE_M`` of the camera."""

    def __init__(self, means: np.ndarray, layout: str = "room") -> None:
        from scipy.spatial import cKDTree

        from css_ros.demo.scene import obstacle_footprints, room_bounds

        lo, hi = room_bounds(layout)
        margin = ROBOT_RADIUS_M + 0.1
        self.x_range = (float(lo[0]) + margin, float(hi[0]) - margin)
        self.y_range = (float(lo[1]) + margin, float(hi[1]) - margin)
        r = ROBOT_RADIUS_M
        self.boxes = np.array([(x0 - r, y0 - r, x1 + r, y1 + r)
                               for name, (x0, y0, x1, y1) in sorted(obstacle_footprints(layout).items()) if name != "rug"])
        self.tree = cKDTree(means)

    def free(self, x: float, y: float, z: float) -> bool:
        if not (self.x_range[0] <= x <= self.x_range[1] and self.y_range[0] <= y <= self.y_range[1]):
            return False
        b = self.boxes
        if np.any((b[:, 0] <= x) & (x <= b[:, 2]) & (b[:, 1] <= y) & (y <= b[:, 3])):
            return False
        dist, _ = self.tree.query([x, y, z])
        return bool(dist >= CLEARANCE_M)

    def sample(self, rng: np.random.Generator, n: int) -> list[np.ndarray]:
        """n random reachable poses (T_map_cam); deterministic for the generator's state."""
        out: list[np.ndarray] = []
        while len(out) < n:
            x, y = rng.uniform(*self.x_range), rng.uniform(*self.y_range)
            z = rng.uniform(*HEIGHT_RANGE_M)
            yaw, pitch = rng.uniform(0.0, 360.0), rng.uniform(*PITCH_RANGE_DEG)
            if self.free(x, y, z):
                out.append(pose_matrix(x, y, z, yaw, pitch))
        return out


def task_poses(space: FreeSpace) -> list[np.ndarray]:
    poses = []
    for x, yaw in zip(TASK_X, TASK_YAW_DEG):
        if not space.free(x, TASK_CORRIDOR_Y, TASK_HEIGHT_M):
            raise RuntimeError(f"task pose at x={x} is not in free space")
        poses.append(pose_matrix(x, TASK_CORRIDOR_Y, TASK_HEIGHT_M, yaw, TASK_PITCH_DEG))
    return poses


# ---------------------------------------------------------------------------------------------------- scene
@dataclass
class KappaView:
    """Map-independent facts of one candidate view: the Gaussians it sees and their kappa mass."""

    ids: np.ndarray
    mass: np.ndarray
    visible: np.ndarray  # ids with mass >= VISIBLE_KAPPA


class Bench:
    """The demo room, its renderer, the free space, the fixed evaluation and task poses and their ground truth."""

    def __init__(self, fused: tuple[int, int], cand: tuple[int, int], num_eval: int,
                 sensor_model: Any | None) -> None:
        from dataclasses import replace

        from css_ros.demo.range_noise import SurfaceDepth
        from css_ros.demo.renderer import DemoRenderer, camera_k, systematic_rule_masks
        from css_ros.demo.scene import CLASS_NAMES, build_scene_arrays
        from css_ros.demo.segmentation_noise import DEFAULT_SYSTEMATIC
        from css_ros.engine.gaussians import GaussianModel

        self.arrays = build_scene_arrays(NUM_GAUSSIANS, SCENE_SEED, layout="room")
        a = self.arrays
        model = GaussianModel.from_activated(a.means, a.scales, a.quats_wxyz, a.opacities, a.colors)
        self.model = replace(model, normals=a.normals)
        self.class_ids = a.class_ids
        self.class_names = CLASS_NAMES
        self.rules = DEFAULT_SYSTEMATIC
        masks, targets = systematic_rule_masks(a, CLASS_NAMES, self.rules)
        self.renderer = DemoRenderer(self.model, a.class_ids, NUM_CLASSES, masks, targets)
        self.surface = SurfaceDepth(self.model)
        self.fused, self.cand = fused, cand
        self.K_fused, self.K_cand = camera_k(*fused), camera_k(*cand)
        self.space = FreeSpace(a.means)
        self.sensor_model = sensor_model
        self.eval_poses = self.space.sample(np.random.default_rng(EVAL_POSE_SEED), num_eval)
        self.task_poses = task_poses(self.space)
        self.eval_gt = [self.gt(T) for T in self.eval_poses]
        self.task_gt = [self.gt(T) for T in self.task_poses]
        self._kappa_cache: dict[bytes, KappaView] = {}

    def camera(self, T: np.ndarray, candidate: bool = False) -> Any:
        from css_ros.engine.camera import Camera

        w, h = self.cand if candidate else self.fused
        return Camera(self.K_cand if candidate else self.K_fused, w, h, T)

    def gt(self, T: np.ndarray) -> np.ndarray:
        return self.renderer.render(self.camera(T))[1]

    def kappa_view(self, cam: Any) -> KappaView:
        """Sparse kappa of a candidate view summed per Gaussian (cached by pose and size)."""
        key = cam.T_map_cam.tobytes() + np.array([cam.width, cam.height]).tobytes()
        kv = self._kappa_cache.get(key)
        if kv is not None:
            return kv
        kl = self.surface.kappa(cam)    # css_ros.engine.cpu.raster.kappa_lists of the view
        mass_all = np.bincount(kl.gaussian, kl.kappa, self.model.num_gaussians)
        ids = np.flatnonzero(mass_all > 0)
        kv = KappaView(ids, mass_all[ids], ids[mass_all[ids] >= VISIBLE_KAPPA])
        if len(self._kappa_cache) > 20_000:
            self._kappa_cache.clear()
        self._kappa_cache[key] = kv
        return kv

    def new_map(self, with_sensor: bool) -> Any:
        from css_ros import SemanticMap

        return SemanticMap(self.model, NUM_CLASSES, sensor_model=self.sensor_model if with_sensor else None)


# ---------------------------------------------------------------------------------------------------- a seed
class SeedData:
    """Everything a seed fixes for every strategy: start poses, candidates per step, the random strategy's draws and
    the noise (the noisy labels of a (step, candidate) are computed once and shared by the strategies)."""

    def __init__(self, bench: Bench, seed: int, num_candidates: int, max_views: int, kinds: Sequence[str]) -> None:
        from css_ros.demo.range_noise import RangeNoise
        from css_ros.demo.segmentation_noise import SegmentationNoise

        self.bench, self.seed = bench, int(seed)
        self.start = bench.space.sample(np.random.default_rng([seed, 3]), START_VIEWS)
        self.candidates = {k: bench.space.sample(np.random.default_rng([seed, 5, k]), num_candidates)
                           for k in range(START_VIEWS, max_views)}
        self.candidate_cams = {k: [bench.camera(T, candidate=True) for T in v] for k, v in self.candidates.items()}
        self.random_choice = {k: int(np.random.default_rng([seed, 11, k]).integers(num_candidates))
                              for k in range(START_VIEWS, max_views)}
        self.frame_noise = SegmentationNoise(bench.class_names, seed=seed) if "frame" in kinds else None
        self.range_noise = (RangeNoise(bench.model, bench.class_ids, bench.class_names, seed=seed)
                            if "range" in kinds else None)
        self._labels: dict[tuple[str, int, int], tuple[np.ndarray, np.ndarray]] = {}
        #: per (kind, view, choice): (input accuracy of the noisy labels, median surface depth [m]) of that view
        self.view_facts: dict[tuple[str, int, int], tuple[float, float]] = {}

    def frame_index(self, view: int) -> int:
        return view + FRAME_OFFSET_PER_SEED * self.seed

    def pose(self, view: int, choice: int) -> np.ndarray:
        return self.start[view] if view < START_VIEWS else self.candidates[view][choice]

    def labels(self, kind: str, view: int, choice: int) -> tuple[np.ndarray, np.ndarray]:
        """(noisy labels, confidence) of the view-th fused view (candidate ``choice``; start views: choice -1)."""
        key = (kind, view, choice)
        hit = self._labels.get(key)
        if hit is not None:
            return hit
        b = self.bench
        cam = b.camera(self.pose(view, choice))
        t = self.frame_index(view)
        if kind == "frame":
            assert self.frame_noise is not None
            active = [self.frame_noise.systematic_active(t, r, rule.probability) for r, rule in enumerate(b.rules)]
            _, gt, biased = b.renderer.render(cam, active)
            seg, conf = self.frame_noise.apply(biased, t)
            depth = b.surface.depth(cam)
        else:
            assert self.range_noise is not None
            _, gt, _ = b.renderer.render(cam)
            fr = self.range_noise.apply(gt, cam, t)
            seg, conf, depth = fr.labels, fr.confidence, fr.depth
        self._labels[key] = (seg, conf)
        valid = gt != 255
        self.view_facts[key] = (float(np.mean(seg[valid] == gt[valid])) if valid.any() else float("nan"),
                                float(np.nanmedian(depth[valid])) if np.isfinite(depth[valid]).any() else float("nan"))
        return seg, conf


# ---------------------------------------------------------------------------------------------------- a run
def evaluate(bench: Bench, smap: Any) -> dict[str, float]:
    from css_ros.evaluation.metrics import ConfusionMatrix

    out = {}
    for name, poses, gts in (("", bench.eval_poses, bench.eval_gt), ("task_", bench.task_poses, bench.task_gt)):
        cm = ConfusionMatrix(NUM_CLASSES, ignore_label=255)
        for T, gt in zip(poses, gts):
            cm.update(gt, smap.render(bench.camera(T)).labels)
        out[name + "miou"] = cm.miou()
        out[name + "accuracy"] = cm.pixel_accuracy()
    return out


def _argmax(x: np.ndarray) -> int:
    return int(np.argmax(np.where(np.isfinite(x), x, -np.inf)))


def choose(strategy: str, smap: Any, data: SeedData, view: int, importance: np.ndarray) -> int:
    cams = data.candidate_cams[view]
    if strategy == "random":
        return data.random_choice[view]
    if strategy in ("u_var", "u_exp", "info_gain"):
        col = {"u_var": 0, "u_exp": 1, "info_gain": 2}[strategy]
        return _argmax(smap.score_views(cams)[:, col])
    if strategy == "coverage":
        alpha = smap.concentrations_readonly
        unobserved = alpha.sum(axis=1) - smap.num_classes * smap.prior < UNOBSERVED_EVIDENCE
        counts = np.array([np.count_nonzero(unobserved[data.bench.kappa_view(c).visible]) for c in cams], float)
        return _argmax(counts)
    if strategy == "info_gain_task":
        gain = smap.score_views(cams, importance=importance)[:, 2]
        g = np.where(np.isfinite(gain), gain, -np.inf)
        best = np.flatnonzero(g >= g.max() - 1e-12 * max(1.0, abs(float(g.max()))))
        if best.size == 1:
            return int(best[0])
        plain = smap.score_views([cams[i] for i in best])[:, 2]     # ties (e.g. all 0): the unweighted gain
        return int(best[_argmax(plain)])
    raise ValueError(f"unknown strategy {strategy!r}")


def run_strategy(bench: Bench, data: SeedData, setting: str, strategy: str, checkpoints: Sequence[int],
                 importance: np.ndarray) -> tuple[dict[int, dict[str, float]], list[int], dict[str, float]]:
    """Fuse the start views and one chosen view per step; (evaluations by view count, chosen candidate per step,
    mean input accuracy and median depth of the chosen views)."""
    kind, with_sensor, _ = SETTINGS[setting]
    smap = bench.new_map(with_sensor)
    evals: dict[int, dict[str, float]] = {}
    choices: list[int] = []
    for view in range(max(checkpoints)):
        choice = -1
        if view >= START_VIEWS:
            choice = choose(strategy, smap, data, view, importance)
            choices.append(choice)
        seg, conf = data.labels(kind, view, choice)
        smap.update(bench.camera(data.pose(view, choice)), seg, conf)
        if view + 1 in checkpoints:
            evals[view + 1] = evaluate(bench, smap)
    facts = np.array([data.view_facts[(kind, v, c)] for v, c in enumerate(choices, start=START_VIEWS)])
    chosen = {"input_accuracy": float(np.nanmean(facts[:, 0])), "median_depth_m": float(np.nanmean(facts[:, 1]))}
    return evals, choices, chosen


# ---------------------------------------------------------------------------------------------------- output
def stats(values: Sequence[float]) -> dict[str, Any]:
    v = np.asarray(values, dtype=np.float64)
    return {"mean": float(np.nanmean(v)), "std": float(np.nanstd(v)), "min": float(np.nanmin(v)),
            "max": float(np.nanmax(v)), "per_seed": [float(x) for x in v]}


METRICS = ("miou", "accuracy", "task_miou", "task_accuracy")


def summarise(raw: dict[str, dict[str, list[dict[int, dict[str, float]]]]], checkpoints: Sequence[int]
              ) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for setting, per_strategy in raw.items():
        out[setting] = {}
        for strategy, runs in per_strategy.items():
            out[setting][strategy] = {
                metric: {str(n): stats([r[n][metric] for r in runs]) for n in checkpoints} for metric in METRICS}
    return out


def _cell(s: dict[str, Any]) -> str:
    return f"{100 * s['mean']:.1f} ± {100 * s['std']:.1f}"


def _setting_label(s: str) -> str:
    """A setting's column label: its error model, ``+SM`` with the sensor model."""
    return f"{SETTINGS[s][0]}{'+SM' if SETTINGS[s][1] else ''}"


def _table(head: list[str], rows: list[list[str]]) -> list[str]:
    """Markdown lines of a table with header ``head``."""
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


def markdown_tables(summary: dict[str, Any], settings: Sequence[str], strategies: Sequence[str],
                    views: Sequence[int], chosen_views: dict[str, Any]) -> str:
    lines = ["mIoU [%] at the 40 held-out poses, mean ± std over seeds, by fused views "
             f"({START_VIEWS} start views + one per step):", ""]
    lines += _table(["strategy"] + [f"{_setting_label(s)} {n}" for s in settings for n in views],
                    [[st] + [_cell(summary[s][st]["miou"][str(n)]) for s in settings for n in views]
                     for st in strategies])
    last = str(views[-1])
    lines += ["", f"At {last} views: pixel accuracy [%] (held-out poses) and mIoU [%] at the 10 task poses:", ""]
    lines += _table(["strategy"] + [f"{_setting_label(s)} {m}" for s in settings for m in ("acc", "task mIoU")],
                    [[st] + [c for s in settings for c in (_cell(summary[s][st]["accuracy"][last]),
                                                          _cell(summary[s][st]["task_miou"][last]))]
                     for st in strategies])
    lines += ["", "The views each strategy chose (steps after the start views, mean over seeds): input accuracy [%] of "
              "their noisy segmentation, median surface depth [m]:", ""]
    lines += _table(["strategy"] + [f"{_setting_label(s)} {m}" for s in settings for m in ("input acc", "depth")],
                    [[st] + [c for s in settings for c in (
                        f"{100 * chosen_views[s][st]['input_accuracy']['mean']:.1f}",
                        f"{chosen_views[s][st]['median_depth_m']['mean']:.2f}")]
                     for st in strategies])
    lines += ["", "Settings: " + "; ".join(f"`{_setting_label(s)}` = {SETTINGS[s][2]}" for s in settings) + "."]
    return "\n".join(lines) + "\n"


def plot(summary: dict[str, Any], settings: Sequence[str], strategies: Sequence[str], views: Sequence[int],
         out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    colors = dict(zip(STRATEGIES, plt.get_cmap("tab10").colors))
    written = []
    for kind in ERROR_KINDS:
        rows = [s for s in settings if SETTINGS[s][0] == kind]
        if not rows:
            continue
        fig, axes = plt.subplots(len(rows), 2, figsize=(11, 4.0 * len(rows)), squeeze=False, sharex=True)
        for r, setting in enumerate(rows):
            for c, (metric, where) in enumerate((("miou", "40 held-out poses"), ("task_miou", "10 task poses"))):
                ax = axes[r][c]
                for st in strategies:
                    s = summary[setting][st][metric]
                    mean = np.array([s[str(n)]["mean"] for n in views]) * 100
                    std = np.array([s[str(n)]["std"] for n in views]) * 100
                    ax.plot(views, mean, "o-", color=colors[st], label=st, lw=1.6, ms=3.5)
                    ax.fill_between(views, mean - std, mean + std, color=colors[st], alpha=0.13, lw=0)
                ax.set_title(f"{SETTINGS[setting][2]}: mIoU at the {where}", fontsize=10)
                ax.set_ylabel("mIoU [%]")
                ax.grid(alpha=0.3)
                if r == len(rows) - 1:
                    ax.set_xlabel("fused views")
                ax.set_xticks(list(views))
        axes[0][0].legend(fontsize=8, loc="lower right")
        fig.suptitle(f"Active mapping on the demo room, {kind} errors (mean ± std over seeds)", fontsize=11)
        fig.tight_layout()
        path = out / f"miou_{kind}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        written.append(path)
    return written


# ---------------------------------------------------------------------------------------------------- main
def load_sensor_model(path: Path, class_names: Sequence[str], quiet: bool) -> Any:
    """The sensor model at ``path``, calibrated once on bags/calib_range/bag with css_calibrate when missing."""
    from css_ros.engine.sensor_model import SensorModel

    if not path.is_file():
        path.parent.mkdir(parents=True, exist_ok=True)
        cmd = ["css_calibrate", str(CALIB_BAG), "--out", str(path)] + (["--quiet"] if quiet else [])
        print(f"calibrating the sensor model once: {' '.join(cmd)}", flush=True)
        from css_ros.calibration.cli import main as calibrate_main

        rc = calibrate_main(cmd[1:])
        if rc != 0 or not path.is_file():
            raise SystemExit(f"active_mapping: css_calibrate failed (exit {rc})")
    return SensorModel.load(path, class_names)


def _git_commit() -> str:
    try:
        r = subprocess.run(["git", "-C", str(REPO), "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                           timeout=10)
        return r.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def _cpu() -> str:
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from bench_frame import cpu_model  # the one /proc/cpuinfo reader of the benchmarks

    return cpu_model()


def _size(text: str) -> tuple[int, int]:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH, got {text!r}") from None
    if w < 16 or h < 16:
        raise argparse.ArgumentTypeError(f"image size must be at least 16x16, got {text!r}")
    return w, h


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="active_mapping.py", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true",
                   help="smoke run: 2 seeds, 8 candidates, views 4 6, 8 held-out poses, 96x72 / 64x48 images "
                        "(other options still override)")
    p.add_argument("--seeds", type=int, default=None, metavar="N", help=f"seeds 0..N-1 ({FULL['seeds']})")
    p.add_argument("--first-seed", type=int, default=0, metavar="S", help="first seed (0)")
    p.add_argument("--steps", type=int, nargs="+", default=None, metavar="V",
                   help="fused-view counts at which the maps are evaluated; the run ends at the largest "
                        f"({' '.join(map(str, FULL['views']))}; the {START_VIEWS} start views are always evaluated)")
    p.add_argument("--candidates", type=int, default=None, metavar="M",
                   help=f"random candidate poses per step ({FULL['candidates']})")
    p.add_argument("--eval-poses", type=int, default=None, metavar="P",
                   help=f"fixed held-out evaluation poses ({FULL['eval_poses']})")
    p.add_argument("--fused-size", type=_size, default=None, metavar="WxH",
                   help="size of the fused (segmented) and evaluated images (128x96)")
    p.add_argument("--candidate-size", type=_size, default=None, metavar="WxH",
                   help="size at which candidates are scored (96x72)")
    p.add_argument("--strategies", nargs="+", choices=STRATEGIES, default=list(STRATEGIES), metavar="S",
                   help=f"strategies to run ({' '.join(STRATEGIES)})")
    p.add_argument("--errors", nargs="+", choices=ERROR_KINDS, default=list(ERROR_KINDS), metavar="E",
                   help="error kinds: frame, range (both)")
    p.add_argument("--no-sensor-model", action="store_true",
                   help="range errors with the paper's update only (no calibrated sensor-model runs)")
    p.add_argument("--sensor-model", type=Path, default=DEFAULT_OUT / "sensor_model.yaml", metavar="YAML",
                   help="sensor model for the range runs; calibrated on bags/calib_range/bag with css_calibrate when "
                        "the file does not exist (out/active_mapping/sensor_model.yaml)")
    p.add_argument("--out", type=Path, default=None, metavar="DIR",
                   help="output folder (out/active_mapping; with --quick out/active_mapping_quick)")
    p.add_argument("--no-plots", action="store_true", help="skip the PNG plots")
    p.add_argument("--quiet", action="store_true", help="no per-run progress lines")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    base = QUICK if args.quick else FULL
    num_seeds = base["seeds"] if args.seeds is None else args.seeds
    views = sorted(set(base["views"] if args.steps is None else args.steps))
    num_cand = base["candidates"] if args.candidates is None else args.candidates
    num_eval = base["eval_poses"] if args.eval_poses is None else args.eval_poses
    fused = base["fused"] if args.fused_size is None else args.fused_size
    cand = base["candidate_size"] if args.candidate_size is None else args.candidate_size
    out = args.out or (REPO / "out" / ("active_mapping_quick" if args.quick else "active_mapping"))
    if num_seeds < 1 or num_cand < 1 or num_eval < 1:
        print("active_mapping.py: error: --seeds, --candidates and --eval-poses must be >= 1", file=sys.stderr)
        return 2
    if views[0] <= START_VIEWS:
        print(f"active_mapping.py: error: --steps must be > {START_VIEWS} (the start views)", file=sys.stderr)
        return 2
    checkpoints = [START_VIEWS] + views
    settings = [s for s, (kind, sm, _) in SETTINGS.items()
                if kind in args.errors and not (sm and args.no_sensor_model)]
    strategies = [s for s in STRATEGIES if s in args.strategies]
    seeds = list(range(args.first_seed, args.first_seed + num_seeds))
    out.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()

    import numba

    from css_ros.demo.scene import CLASS_NAMES

    sensor = None
    sensor_path = None
    if any(SETTINGS[s][1] for s in settings):
        sensor_path = args.sensor_model
        sensor = load_sensor_model(sensor_path, CLASS_NAMES, args.quiet)
    bench = Bench(fused, cand, num_eval, sensor)
    importance = bench.new_map(False).task_importance([bench.camera(T) for T in bench.task_poses])
    t_setup = time.perf_counter() - t_start
    print(f"active mapping: room ({NUM_GAUSSIANS} Gaussians, {NUM_CLASSES} classes), seeds {seeds[0]}..{seeds[-1]}, "
          f"{num_cand} candidates/step, views {START_VIEWS} -> {views[-1]} (evaluated at {checkpoints}), fused "
          f"{fused[0]}x{fused[1]}, candidates {cand[0]}x{cand[1]}, {num_eval} held-out + {len(bench.task_poses)} task "
          f"poses; settings {', '.join(settings)}; set-up {t_setup:.1f} s",
          flush=True)

    raw: dict[str, dict[str, list[dict[int, dict[str, float]]]]] = {s: {st: [] for st in strategies} for s in settings}
    choices: dict[str, dict[str, dict[str, list[int]]]] = {s: {st: {} for st in strategies} for s in settings}
    run_seconds: dict[str, dict[str, float]] = {s: {st: 0.0 for st in strategies} for s in settings}
    facts: dict[str, dict[str, list[dict[str, float]]]] = {s: {st: [] for st in strategies} for s in settings}
    total_runs = len(seeds) * len(settings) * len(strategies)
    done = 0
    t_runs = time.perf_counter()
    kinds = sorted({SETTINGS[s][0] for s in settings})
    for seed in seeds:
        data = SeedData(bench, seed, num_cand, views[-1], kinds)
        for setting in settings:
            for strategy in strategies:
                t0 = time.perf_counter()
                evals, chosen, view_facts = run_strategy(bench, data, setting, strategy, checkpoints, importance)
                dt = time.perf_counter() - t0
                raw[setting][strategy].append(evals)
                choices[setting][strategy][str(seed)] = chosen
                facts[setting][strategy].append(view_facts)
                run_seconds[setting][strategy] += dt
                done += 1
                if not args.quiet:
                    elapsed = time.perf_counter() - t_runs
                    eta = elapsed / done * (total_runs - done)
                    curve = " ".join(f"{100 * evals[n]['miou']:.1f}" for n in checkpoints)
                    print(f"[{done:3d}/{total_runs}] seed {seed} {setting:<12} {strategy:<14} mIoU % at "
                          f"{checkpoints}: {curve}  ({dt:.1f} s; elapsed {elapsed / 60:.1f} min, "
                          f"ETA {eta / 60:.1f} min)", flush=True)
    summary = summarise(raw, checkpoints)
    chosen_views = {s: {st: {k: stats([f[k] for f in facts[s][st]]) for k in ("input_accuracy", "median_depth_m")}
                        for st in strategies} for s in settings}
    wall = time.perf_counter() - t_start
    table = markdown_tables(summary, settings, strategies, views, chosen_views)
    command = "python benchmarks/active_mapping.py " + " ".join(sys.argv[1:] if argv is None else list(argv))
    result = {
        "benchmark": "active_mapping",
        "command": command.strip(),
        "git_commit": _git_commit(),
        "machine": {"cpu": _cpu(), "cores": os.cpu_count(), "numba_threads": numba.get_num_threads(),
                    "python": platform.python_version()},
        "config": {
            "scene": "room", "num_gaussians": NUM_GAUSSIANS, "num_classes": NUM_CLASSES, "seeds": seeds,
            "start_views": START_VIEWS, "views": views, "checkpoints": checkpoints, "candidates": num_cand,
            "eval_poses": num_eval, "task_poses": len(bench.task_poses), "fused_size": list(fused),
            "candidate_size": list(cand), "strategies": strategies, "settings": settings,
            "setting_labels": {s: SETTINGS[s][2] for s in settings},
            "sensor_model": None if sensor_path is None else str(sensor_path),
            "sensor_model_fingerprint": None if sensor is None else sensor.fingerprint,
            "height_range_m": list(HEIGHT_RANGE_M), "pitch_range_deg": list(PITCH_RANGE_DEG),
            "robot_radius_m": ROBOT_RADIUS_M, "clearance_m": CLEARANCE_M, "visible_kappa": VISIBLE_KAPPA,
            "unobserved_evidence": UNOBSERVED_EVIDENCE, "frame_offset_per_seed": FRAME_OFFSET_PER_SEED,
            "confidence_weighted": True,
        },
        "wall_time_s": wall,
        "setup_time_s": t_setup,
        "run_time_s": run_seconds,
        "results": summary,
        "chosen_views": chosen_views,
        "choices": choices,
        "eval_poses": [T.tolist() for T in bench.eval_poses],
        "task_poses": [T.tolist() for T in bench.task_poses],
    }
    (out / "results.json").write_text(json.dumps(result, indent=1))
    (out / "results.md").write_text(f"# Active mapping\n\n`{result['command']}` (wall time "
                                    f"{wall / 60:.1f} min)\n\n" + table)
    pngs = [] if args.no_plots else plot(summary, settings, strategies, checkpoints, out)
    print()
    print(table)
    print(f"wall time {wall:.0f} s ({wall / 60:.1f} min); wrote {out / 'results.json'}, {out / 'results.md'}"
          + "".join(f", {p}" for p in pngs), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
