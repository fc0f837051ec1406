"""The update's per-thread increments (engine/cpu/increments.py): a chunk's increment of a Gaussian and class is its
slot's value (two slots a Gaussian, filled in order) plus its dense entry, which is marked whenever the flush wrote
it (one class a bit up to 8 classes, blocks of classes beyond); with and without a sensor model, the add equals the
dense sum of every chunk and leaves slots, marks and increments clear for the next frame."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.engine.cpu.increments import (EMPTY, MARK_BITS, SLOTS, Increments, UpdateWorkspace, add_increments,
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
    if confusion:    # sparse rows: the label and two others (a one-hot row would be the paper's update)
        conf = np.zeros((num_classes, 4, num_classes))
        for y in range(num_classes):
            conf[y, :, y] += 0.8
            conf[y, :, (y + 1) % num_classes] += 0.15
            conf[y, :, (y + 7) % num_classes] += 0.05
    return SensorModel(tuple(f"c{i}" for i in range(num_classes)), edges, weight, conf)


def _dense(inc: Increments) -> np.ndarray:
    """(chunks, M, C) every chunk's increments: the dense entries plus the slots' values."""
    out = inc.acc.copy()
    ch, j, s = np.nonzero(inc.slot_class != EMPTY)
    np.add.at(out, (ch, j, inc.slot_class[ch, j, s].astype(np.int64)), inc.slot_value[ch, j, s])
    return out


def _marks_of(acc: np.ndarray) -> np.ndarray:
    """(chunks, M) the bits of the class blocks holding a non-zero dense entry."""
    num_classes = acc.shape[2]
    bits = np.uint8(1) << (np.arange(num_classes) // classes_per_mark(num_classes)).astype(np.uint8)
    return np.bitwise_or.reduce(np.where(acc != 0.0, bits, np.uint8(0)), axis=2)


@pytest.mark.parametrize("num_classes", [3, 8, 20, 150])
@pytest.mark.parametrize("model_kind", [None, "weights", "confusion"])
def test_slots_and_marked_entries_hold_every_increment_and_the_add_equals_the_dense_sum(num_classes, model_kind):
    model = random_scene(3, n=400)
    cam = camera(width=64, height=48, f=40.0)
    proj = project(GaussianGeometry.from_model(model), cam)
    bins = bin_tiles(proj, cam.width, cam.height)
    labels = np.random.default_rng(4).integers(0, num_classes, (cam.height, cam.width))   # many classes a Gaussian
    inputs = check_frame_labels(labels, None, labels.shape, num_classes, 255)
    soft = None if model_kind is None else _sensor(num_classes, model_kind == "confusion").soft_labels()
    workspace = UpdateWorkspace()
    inc, counts, _ = accumulate_update(proj, bins, inputs, soft, workspace)
    assert counts[0] > 0
    cls = inc.slot_class
    spread = np.count_nonzero(soft.resid, axis=1) if soft is not None else np.ones(1)
    assert np.all(spread > SLOTS) or np.all(spread <= SLOTS)
    if spread[0] > SLOTS:     # rows of more classes than the slots (confusion, C > 3): the dense rows take them
        assert np.all(cls == EMPTY) and inc.acc.any()
    else:   # slots fill in order, hold distinct classes, and the dense row is used only once both are taken
        assert np.all((cls[..., 0] != EMPTY) | (cls[..., 1] == EMPTY))
        assert not np.any((cls[..., 0] == cls[..., 1]) & (cls[..., 0] != EMPTY))
        full = np.all(cls != EMPTY, axis=2)
        assert not inc.acc[~full].any() and inc.acc[full].any() and full.mean() < 0.9
    expected = _marks_of(inc.acc)
    assert np.all(inc.marks & expected == expected)           # every non-zero dense entry is marked
    assert np.count_nonzero(inc.marks) < inc.marks.size       # ... and the marks are not all set
    if num_classes > MARK_BITS:
        assert np.all(inc.marks.astype(np.int64) >> -(-num_classes // classes_per_mark(num_classes)) == 0)
    conc = 1.0 + np.random.default_rng(6).random((model.num_gaussians, num_classes))
    want = conc.copy()
    want[proj.ids] += _dense(inc).sum(axis=0) + (inc.base.sum(axis=0)[:, None] if soft is not None else 0.0)
    add_increments(conc, proj.ids, inc)
    workspace.done()
    np.testing.assert_allclose(conc, want, rtol=1e-12)
    assert not inc.acc.any() and not inc.marks.any() and not inc.base.any() and np.all(inc.slot_class == EMPTY)


def test_a_workspace_not_given_back_is_cleared_before_its_next_use():
    workspace = UpdateWorkspace()
    inc = workspace.take(2, 3, 4, True)
    assert inc.slot_class.shape == (2, 4, SLOTS) and np.all(inc.slot_class == EMPTY)
    inc.acc[:] = 1.0
    inc.base[:] = 2.0
    inc.marks[:] = 7
    inc.slot_class[:] = 1
    again = workspace.take(2, 3, 4, True)           # no done(): an exception between the update and the add
    assert not again.acc.any() and not again.base.any() and not again.marks.any()
    assert np.all(again.slot_class == EMPTY)


@pytest.mark.parametrize("decay", [1.0, 0.5])
def test_slots_dense_entries_and_the_decay_of_a_row_that_received(decay):
    """Gaussian 0 gets a class in a slot of chunk 0 and another in chunk 1's dense row, Gaussian 1 only a zero
    increment, Gaussian 2 nothing: with forgetting, rows 0 is decayed first, 1 and 2 are not."""
    prior = 1.0
    conc = np.full((3, 10), 3.0)
    ids = np.array([0, 1, 2])
    inc = UpdateWorkspace().take(2, 10, 3, False)
    inc.slot_class[0, 0, 0], inc.slot_value[0, 0, 0] = 4, 0.25
    inc.slot_class[1, 0, :] = (1, 2)              # chunk 1's slots taken by zeros; class 9 went to the dense row
    inc.acc[1, 0, 9] = 0.5
    inc.marks[1, 0] = np.uint8(1) << np.uint8(9 // classes_per_mark(10))
    inc.slot_class[0, 1, 0] = 6                    # a slot holding zero: nothing received
    add_increments(conc, ids, inc, decay, prior)
    row0 = np.full(10, prior + (3.0 - prior) * decay)
    row0[4] += 0.25
    row0[9] += 0.5
    np.testing.assert_allclose(conc[0], row0, rtol=1e-15)
    np.testing.assert_array_equal(conc[1:], 3.0)
    assert np.all(inc.slot_class == EMPTY) and not inc.acc.any() and not inc.marks.any()
