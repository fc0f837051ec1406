"""The update's per-thread increments (engine/cpu/increments.py): the marks the kernel sets cover every entry it
wrote, for one class a bit (C <= 64) and for blocks of classes (C > 64), with and without a sensor model; the add
that reads only marked entries equals the dense sum of every chunk, and leaves increments and marks zero."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.cpu.increments import (MARK_BITS, Increments, UpdateWorkspace, add_increments, all_marked,
                                           classes_per_mark)
from css_ros.engine.cpu.projection import GaussianGeometry, project
from css_ros.engine.cpu.raster import accumulate_update, bin_tiles
from css_ros.engine.label_input import check_frame_labels
from css_ros.engine.sensor_model import SensorModel
from scenes import camera, random_scene


def _sensor(num_classes: int, confusion: bool) -> SensorModel:
    rng = np.random.default_rng(5)
    edges = np.linspace(0.0, 20.0, 5)
    weight = rng.uniform(0.2, 1.0, (num_classes, 4))
    conf = None
    if confusion:    # sparse rows: the label and two neighbours (a one-hot row would be the paper's update)
        conf = np.zeros((num_classes, 4, num_classes))
        for y in range(num_classes):
            conf[y, :, y] = 0.8
            conf[y, :, (y + 1) % num_classes] = 0.15
            conf[y, :, (y + 7) % num_classes] = 0.05
    return SensorModel(tuple(f"c{i}" for i in range(num_classes)), edges, weight, conf)


def _expected_marks(acc: np.ndarray) -> np.ndarray:
    """(chunks, M) the bits of the class blocks holding a non-zero increment."""
    num_classes = acc.shape[2]
    per = classes_per_mark(num_classes)
    bits = np.uint64(1) << (np.arange(num_classes) // per).astype(np.uint64)
    nz = acc != 0.0
    return np.bitwise_or.reduce(np.where(nz, bits, np.uint64(0)), axis=2)


@pytest.mark.parametrize("num_classes", [5, 64, 70, 150])
@pytest.mark.parametrize("model_kind", [None, "weights", "confusion"])
def test_marks_cover_every_increment_and_the_add_equals_the_dense_sum(num_classes, model_kind):
    model = random_scene(3, n=400)
    cam = camera(width=64, height=48, f=40.0)
    proj = project(GaussianGeometry.from_model(model), cam)
    bins = bin_tiles(proj, cam.width, cam.height)
    labels = np.random.default_rng(4).integers(0, num_classes, (cam.height, cam.width))
    inputs = check_frame_labels(labels, None, labels.shape, num_classes, 255)
    soft = None if model_kind is None else _sensor(num_classes, model_kind == "confusion").soft_labels()
    workspace = UpdateWorkspace()
    inc, counts, _ = accumulate_update(proj, bins, inputs, soft, workspace)
    assert counts[0] > 0 and inc.acc.any()
    expected = _expected_marks(inc.acc)
    assert np.all(inc.marks & expected == expected)           # every non-zero entry is marked
    assert np.count_nonzero(inc.marks) < inc.marks.size       # ... and the marks are not all set
    if num_classes > MARK_BITS:
        assert np.all(inc.marks >> np.uint64(-(-num_classes // classes_per_mark(num_classes))) == 0)
    conc = 1.0 + np.random.default_rng(6).random((model.num_gaussians, num_classes))
    want = conc.copy()
    want[proj.ids] += inc.acc.sum(axis=0) + (inc.base.sum(axis=0)[:, None] if soft is not None else 0.0)
    add_increments(conc, proj.ids, inc)
    workspace.done()
    np.testing.assert_allclose(conc, want, rtol=1e-12)
    assert not inc.acc.any() and not inc.marks.any() and not inc.base.any()   # zero for the next frame


def test_a_workspace_not_given_back_is_zeroed_before_its_next_use():
    workspace = UpdateWorkspace()
    inc = workspace.take(2, 3, 4, True)
    inc.acc[:] = 1.0
    inc.base[:] = 2.0
    inc.marks[:] = 7
    again = workspace.take(2, 3, 4, True)           # no done(): an exception between the update and the add
    assert not again.acc.any() and not again.base.any() and not again.marks.any()


def test_all_marked_increments_are_added_whole():
    rng = np.random.default_rng(2)
    conc = rng.random((9, 70))
    ids = np.array([4, 0, 7])
    acc = rng.random((2, 3, 70))
    want = conc.copy()
    want[ids] += acc.sum(axis=0)
    add_increments(conc, ids, Increments(acc, np.zeros((0, 0)), all_marked(2, 3)))
    np.testing.assert_allclose(conc, want, rtol=1e-12)
    assert not acc.any()
