"""What css_replay measures about a changing world (README "A changing world"): how much of the final map shows a
transient class, its accuracy against the static ground truth, how much of an object whose class changed shows the
new class at the end, and how well ``RenderedView.surprise`` singles out the changed pixels when the change is first
seen. Pure numpy; every figure that cannot be made is None with the reason beside it (never left out silently).

Inputs per frame (all (H, W), the segmentation's resolution):

- ``gt``: the static ground truth (the world without passers-by: what the map should show), ignore_label = none;
- ``gt_changed``: for the pixels of an object whose class changes during the bag, its class at the end of the bag
  (ignore_label elsewhere); the pixels where ``gt`` already equals it show the object after the change.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from .metrics import auroc, finite_or_none

#: How the figures are defined (metrics.json and report.md repeat these words).
DEFINITIONS = {
    "renders": "every frame's pose rendered with the final map (the renders the CSS accuracy is measured on)",
    "transient_share": "share of the rendered pixels with a label whose label is a transient class",
    "static_accuracy": "rendered label == static ground truth, over the pixels the static ground truth labels",
    "others_accuracy": "the same over the pixels that show no object whose class changes",
    "changed_accuracy": "share of the pixels of objects whose class changed that show their class at the end of "
                        "the bag (at every pose, also where the object was seen only before its change)",
    "changed_accuracy_after": "the same at the poses that see the object after its change (where the ground "
                              "truth already shows the new class)",
    "surprise_auroc": "AUROC of the surprise image of the first fused frame that shows a changed object's new class "
                      "(after it was seen with its old one): its changed pixels against every other pixel with a "
                      "surprise value (1 = every changed pixel more surprising than any other)",
}


def _valid(labels: np.ndarray, num_classes: int, ignore_label: int) -> np.ndarray:
    lab = np.asarray(labels)
    return (lab >= 0) & (lab < num_classes) & (lab != ignore_label)


def _figure(value: float | None, reason: str | None = None, **extra: Any) -> dict[str, Any]:
    """A reported figure: its value (None: not measured) and why not."""
    out: dict[str, Any] = {"value": value if value is None else finite_or_none(value)}
    if out["value"] is None:
        out["reason"] = reason or "undefined (no pixel to measure it on)"
    out.update(extra)
    return out


class ChangeTally:
    """Accumulates the changing-world figures of one map over a replay.

    Args:
        num_classes: C.
        ignore_label: "no label" of label images and renders.
        transient_ids: the transient classes the map was given (may be empty).
        class_names: the C class names (for the report).
    """

    def __init__(self, num_classes: int, ignore_label: int, transient_ids: Sequence[int],
                 class_names: Sequence[str]) -> None:
        self.num_classes = int(num_classes)
        self.ignore_label = int(ignore_label)
        self.transient_ids = sorted({int(c) for c in transient_ids})
        self.class_names = list(class_names)
        #: (C,) rendered pixels per label of the final-map renders
        self.rendered = np.zeros(self.num_classes, dtype=np.int64)
        #: (C,) pixels per class of the static ground truth (which classes the static world holds)
        self.gt_pixels = np.zeros(self.num_classes, dtype=np.int64)
        #: (C,) pixels per class of the input segmentation (every frame of the bag)
        self.input_pixels = np.zeros(self.num_classes, dtype=np.int64)
        self.static = np.zeros(2, dtype=np.int64)    # right, total
        self.others = np.zeros(2, dtype=np.int64)
        self.changed = np.zeros(2, dtype=np.int64)
        self.changed_after = np.zeros(2, dtype=np.int64)
        self.have_gt = False
        self.have_changed = False
        self._seen_before = False                      # a changed object seen with its old class
        self.first_changed: int | None = None
        self._auroc: dict[str, Any] | None = None
        self._no_surprise = 0                          # changed frames observed without a surprise image

    def add_render(self, labels: np.ndarray, gt: np.ndarray | None, gt_changed: np.ndarray | None) -> None:
        """One final-map render (``labels`` (H, W)) with its frame's static and changed ground truth (or None)."""
        lab = np.asarray(labels).astype(np.int64, copy=False)
        has = _valid(lab, self.num_classes, self.ignore_label)
        self.rendered += np.bincount(lab[has], minlength=self.num_classes)
        changed = np.zeros(lab.shape, dtype=bool)
        if gt_changed is not None:
            self.have_changed = True
            changed = _valid(gt_changed, self.num_classes, self.ignore_label)
            right = changed & (lab == gt_changed)
            self.changed += (int(right.sum()), int(changed.sum()))
            if gt is not None:
                after = changed & (gt == gt_changed)
                self.changed_after += (int((right & after).sum()), int(after.sum()))
        if gt is not None:
            self.have_gt = True
            ok = _valid(gt, self.num_classes, self.ignore_label)
            right = ok & (lab == gt)
            self.gt_pixels += np.bincount(np.asarray(gt)[ok].astype(np.int64), minlength=self.num_classes)
            self.static += (int(right.sum()), int(ok.sum()))
            self.others += (int((right & ~changed).sum()), int((ok & ~changed).sum()))

    def add_input(self, labels: np.ndarray) -> None:
        """One frame's input segmentation (H, W) (which classes the segmentation sees)."""
        lab = np.asarray(labels).astype(np.int64, copy=False)
        self.input_pixels += np.bincount(lab[_valid(lab, self.num_classes, self.ignore_label)],
                                         minlength=self.num_classes)

    def add_observation(self, index: int, gt: np.ndarray | None, gt_changed: np.ndarray | None,
                        surprise: np.ndarray | None) -> None:
        """A fused frame in bag order: finds the first one that shows a changed object's new class after its old
        one was seen, and measures the AUROC of its ``surprise`` image (None: the map made none)."""
        if self.first_changed is not None or gt is None or gt_changed is None:
            return
        obj = _valid(gt_changed, self.num_classes, self.ignore_label) & _valid(gt, self.num_classes,
                                                                               self.ignore_label)
        new = obj & (gt == gt_changed)
        if self._seen_before and new.any():
            self.first_changed = int(index)
            if surprise is None:
                self._no_surprise += 1
                return
            s = np.asarray(surprise, dtype=np.float64)
            finite = np.isfinite(s)
            self._auroc = {"value": auroc(s[new & finite], s[~new & finite]), "frame": int(index),
                           "changed_pixels": int((new & finite).sum()), "other_pixels": int((~new & finite).sum())}
            return
        self._seen_before |= bool((obj & (gt != gt_changed)).any())

    def _transient_share(self) -> dict[str, Any]:
        total = int(self.rendered.sum())
        if self.transient_ids:
            ids, basis = self.transient_ids, "the map's transient classes (--transient-classes)"
        elif self.have_gt:
            ids = [c for c in range(self.num_classes) if self.gt_pixels[c] == 0 and self.input_pixels[c] > 0]
            basis = ("no --transient-classes given: the classes the segmentation holds and the static ground truth "
                     "never does")
            if not ids:
                return _figure(None, "no --transient-classes given and no class of the segmentation is absent from "
                                     "the static ground truth: no class to count", basis=basis, classes=[])
        else:
            return _figure(None, "no --transient-classes given and no static ground truth to tell which classes "
                                 "never occur", classes=[])
        names = [self.class_names[c] for c in ids]
        if total == 0:
            return _figure(None, "no rendered pixel has a label", basis=basis, classes=names)
        n = int(self.rendered[ids].sum())
        return _figure(n / total, basis=basis, classes=names, pixels=n, rendered_pixels=total)

    def _ratio(self, counts: np.ndarray, missing: str | None) -> dict[str, Any]:
        if missing is not None:
            return _figure(None, missing, pixels=0)
        right, total = int(counts[0]), int(counts[1])
        return _figure(right / total if total else None, None if total else "no pixel to measure it on",
                       pixels=total)

    def _surprise(self) -> dict[str, Any]:
        if not self.have_changed:
            return _figure(None, "no changed-class ground truth (--gt-changed-topic) in the bag")
        if self.first_changed is None:
            return _figure(None, "no fused frame shows a changed object's new class after its old one was seen")
        if self._auroc is None:
            return _figure(None, "the map made no surprise image (the backend does not make one)",
                           frame=self.first_changed)
        rec = dict(self._auroc)
        return _figure(rec.pop("value"), "the first changed frame has no changed pixel or no other pixel with a "
                                         "surprise value", **rec)

    def summary(self) -> dict[str, Any]:
        """metrics.json's ``changing_world`` figures (each {value, reason when None, ...})."""
        no_gt = None if self.have_gt else "no static ground truth (--gt-topic) in the bag"
        no_changed = None if self.have_changed else "no changed-class ground truth (--gt-changed-topic) in the bag"
        return {
            "definitions": DEFINITIONS,
            "rendered_pixels_per_class": {self.class_names[c]: int(n) for c, n in enumerate(self.rendered)},
            "transient_share": self._transient_share(),
            "static_accuracy": self._ratio(self.static, no_gt),
            "others_accuracy": self._ratio(self.others, no_gt or no_changed),
            "changed_accuracy": self._ratio(self.changed, no_changed),
            "changed_accuracy_after": self._ratio(self.changed_after, no_changed or no_gt),
            "surprise_auroc": self._surprise(),
        }
