"""What both demo generators share (``css_make_demo`` and its ``--robot`` variant): the demo camera's
intrinsics, the renderer of colour / ground-truth / biased labels, the stage-0 rule selections, and writing a
bag into place atomically."""
from __future__ import annotations

import shutil
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterator, Sequence

import numpy as np

from ..errors import CssError
from ..io.bag import BagWriter

GT_CONCENTRATION = 1e4  #: one-hot concentration used to render ground-truth labels
FOV_X_DEG = 64.0  #: horizontal field of view of the demo camera
SCRATCH_DIR = ".css_make_demo.tmp"  #: scratch folder inside OUT while a bag is written


def camera_k(width: int, height: int) -> np.ndarray:
    """(3, 3) intrinsics of the demo camera (FOV_X_DEG horizontal field of view) for a width x height image."""
    from ..engine.camera import intrinsics_from_fov

    return intrinsics_from_fov(width, height, FOV_X_DEG)


@contextmanager
def bag_in_place(out: Path, storage: str = "mcap") -> Iterator[BagWriter]:
    """A writer for ``OUT/bag`` that writes into a scratch folder with the final directory name (rosbags names the
    storage file after it) and moves it into place when the block ends without error, replacing an older bag: an
    interrupted run never leaves a half-written OUT/bag. On error the scratch folder is removed."""
    bag_dir = out / "bag"
    scratch = out / SCRATCH_DIR
    shutil.rmtree(scratch, ignore_errors=True)
    scratch.mkdir()
    try:
        yield BagWriter(scratch / bag_dir.name, storage, zstd_level=19)
    except BaseException:
        shutil.rmtree(scratch, ignore_errors=True)
        raise
    if bag_dir.exists():
        shutil.rmtree(bag_dir)
    (scratch / bag_dir.name).rename(bag_dir)
    scratch.rmdir()


@dataclass
class DemoView:
    """One view of the demo splat (all (H, W), ``rgb`` (H, W, 3) uint8).

    Attributes:
        rgb: colour.
        gt: uint8 ground-truth labels (255 = no surface).
        biased: uint8 labels with the active systematic rules.
        depth: float32 expected depth [m] of the splat along the optical axis (the engine's ``RenderedView.depth``,
            NaN where nothing is rendered).
        changed: uint8, where a rule on at the end of the bag relabels the surface: the label there at the end
            (255 elsewhere); None when no such rule was given.
    """

    rgb: np.ndarray
    gt: np.ndarray
    biased: np.ndarray
    depth: np.ndarray
    changed: np.ndarray | None = None


class DemoRenderer:
    """Renders colour, ground-truth labels and the systematically biased labels of stage 0 (see
    :mod:`css_ros.segmentation_noise`) in one rasterisation per view.

    Each Gaussian belongs to a *group*: its class id, or ``C + r`` if stage-0 rule r selects it. A semantic map
    over the G groups with one-hot concentrations (x 1e4) is rendered with per-group probabilities; summing
    the group channels into class channels gives the ground truth (every group to its own class) or the
    biased labels (groups of active rules to their target class). Pixels whose background weight exceeds 0.5
    get 255 (no surface).

    Args:
        model: the splat (map frame).
        class_ids: (N,) ground-truth class per Gaussian, in [0, C).
        num_classes: C.
        rule_masks: per stage-0 rule, (N,) bool selection of Gaussians (earlier rules win on overlap).
        rule_targets: per rule, the class id the biased labels use.
    """

    def __init__(self, model: Any, class_ids: np.ndarray, num_classes: int,
                 rule_masks: Sequence[np.ndarray] = (), rule_targets: Sequence[int] = (),
                 backend: str = "numba") -> None:
        from ..engine.semantic_map import SemanticMap

        class_ids = np.asarray(class_ids, dtype=np.int64)
        C = int(num_classes)
        group = class_ids.copy()
        source = []
        for r, mask in enumerate(rule_masks):
            sel = np.asarray(mask, dtype=bool) & (group < C)
            group[sel] = C + r
            src = np.unique(class_ids[sel])
            if src.size > 1:
                raise CssError(f"systematic rule {r} selects Gaussians of several classes {src.tolist()}")
            source.append(int(src[0]) if src.size else 0)
        self.num_classes = C
        self.num_groups = C + len(rule_masks)
        self.source = np.asarray(source, dtype=np.int64)
        self.targets = np.asarray(list(rule_targets), dtype=np.int64)
        if self.targets.shape != self.source.shape:
            raise CssError("rule_targets must have one class id per rule mask")
        self.smap = SemanticMap(model, num_classes=self.num_groups, prior=1e-3, ignore_label=255,
                                unknown_threshold=0.5, backend=backend)
        self.smap.concentrations[np.arange(model.num_gaussians), group] = GT_CONCENTRATION

    def _merge(self, active: Sequence[bool]) -> np.ndarray:
        M = np.zeros((self.num_groups, self.num_classes))
        M[np.arange(self.num_classes), np.arange(self.num_classes)] = 1.0
        for r in range(len(self.source)):
            on = bool(active[r]) if r < len(active) else False
            M[self.num_classes + r, self.targets[r] if on else self.source[r]] = 1.0
        return M

    def render(self, camera: Any, active: Sequence[bool] = ()) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(rgb (H,W,3) uint8, gt (H,W) uint8, biased (H,W) uint8) at ``camera``; ``active[r]`` turns rule r on."""
        view = self.render_view(camera, active)
        return view.rgb, view.gt, view.biased

    def render_view(self, camera: Any, active: Sequence[bool] = (), truth: Sequence[bool] = (),
                    final: Sequence[bool] = ()) -> "DemoView":
        """The :class:`DemoView` at ``camera``: ``active[r]`` turns rule r on in the biased labels, ``truth[r]`` in
        the ground truth (a class that really changed); ``final[r]``: the rules on at the end of the bag (the
        pixels they relabel make ``changed``, None when no rule is on there)."""
        view = self.smap.render(camera, probabilities=True, outputs=("labels", "background", "rgb", "depth"))
        assert view.probabilities is not None and view.background is not None and view.depth is not None
        P = view.probabilities.astype(np.float64)
        bg = view.background.astype(np.float64)
        P -= bg[..., None] / self.num_groups  # drop the background Dirichlet's uniform share
        empty = bg > 0.5

        def labels(on: Sequence[bool]) -> np.ndarray:
            out = np.argmax(P @ self._merge(on), axis=-1).astype(np.uint8)
            out[empty] = 255
            return out

        plain = labels(())
        gt = labels(truth) if any(truth) else plain
        biased = labels(active) if any(active) else gt.copy()
        changed = None
        if any(final):
            at_end = labels(final)
            changed = np.where(at_end != plain, at_end, np.uint8(255)).astype(np.uint8)
        return DemoView(view.rgb, gt, biased, view.depth, changed)


def systematic_rule_masks(scene: Any, class_names: Sequence[str], rules: Sequence[Any]
                          ) -> tuple[list[np.ndarray], list[int]]:
    """Per stage-0 rule, the (N,) Gaussian selection in ``scene`` (a demo_scene.SceneArrays) and its target id.

    Rules naming classes that do not exist are skipped (empty selection, target = source)."""
    idx = {n: i for i, n in enumerate(class_names)}
    names = np.array([p.name for p in scene.primitives])
    masks, targets = [], []
    for rule in rules:
        if rule.source_class not in idx or rule.target_class not in idx:
            masks.append(np.zeros(len(scene.class_ids), dtype=bool))
            targets.append(idx.get(rule.source_class, 0))
            continue
        mask = scene.class_ids == idx[rule.source_class]
        if rule.name_prefix is not None:
            ok = np.array([n.startswith(rule.name_prefix) for n in names], dtype=bool)
            mask &= ok[scene.primitive_ids]
        if rule.min_z is not None:
            mask &= scene.means[:, 2] >= rule.min_z
        masks.append(mask)
        targets.append(idx[rule.target_class])
    return masks, targets
