"""css_calibrate's and css_replay's calibration figures, checked through matplotlib's objects: how many curves,
which legend entries, marker sizes against the pixel counts, and bounding boxes that do not collide."""
from __future__ import annotations

import numpy as np
import pytest

from css_ros.calibration.learn import LabelDepthCounts, fit_sensor_model
from css_ros.calibration.plots import (TICK_FONTSIZE, _plt, confusion_bands_figure, reliability_by_depth_figure)
from css_ros.engine.classes import ClassSet
from css_ros.engine.sensor_model import uniform_edges
from css_ros.evaluation.calibration_metrics import calibration_summary, ReliabilityBins
from css_ros.evaluation.calibration_plots import MAX_MARKER_AREA, reliability_panels_figure
from css_ros.export.birdseye import EMPTY_LABEL, birdseye_figure

C = 16


def _classes(n: int = C) -> ClassSet:
    return ClassSet(tuple(f"a_long_class_name_{i}" for i in range(n)), ClassSet.default(n).palette)


def _counts(n: int = C) -> LabelDepthCounts:
    """Labels right 95 % near falling to 40 % at 7 m; nothing beyond 7 m; label i seen only in the first 4 + i bins."""
    rng = np.random.default_rng(0)
    counts = LabelDepthCounts(n, uniform_edges(8.0, 0.5))
    right = np.linspace(0.95, 0.4, 14)
    for y in range(n):
        for b in range(min(14, 4 + y)):
            px = int(rng.integers(200, 3000))
            counts.fit[y, b, y] = int(px * right[b])
            counts.fit[y, b, (y + 1) % n] = px - int(px * right[b])
    return counts


def _draw(fig):
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def _close(fig):
    _plt().close(fig)


def _legend_texts(fig) -> list[str]:
    legends = list(fig.legends) + [leg for ax in fig.axes if (leg := ax.get_legend()) is not None]
    return [t.get_text() for leg in legends for t in leg.get_texts()]


@pytest.mark.parametrize("per_class", [False, True])
def test_reliability_by_depth_draws_one_curve_per_model_row(per_class):
    counts = _counts()
    model = fit_sensor_model(counts, _classes().names, per_class=per_class)
    fig = reliability_by_depth_figure(model, counts.fit, _classes())
    try:
        left, right = fig.axes[:2]
        expected = C if per_class else 1        # a per-depth model has one curve, not one per label
        assert len(right.get_lines()) == expected and len(left.get_lines()) == expected
        if not per_class:
            np.testing.assert_allclose(right.get_lines()[0].get_ydata(), model.weight[0])
        # the left panel's dots: one scatter per label, area ~ pixels of (label, bin)
        n = counts.fit.sum(axis=2)
        assert len(left.collections) == C
        for coll in left.collections:
            sizes = coll.get_sizes()
            y = _classes().names.index(coll.get_label())
            seen = n[y][n[y] > 0]
            assert sizes.size == seen.size
            np.testing.assert_allclose((sizes - 4.0) / seen, 60.0 / n.max(), rtol=1e-9)   # area = 4 + 60 n / n_max
        texts = _legend_texts(fig)
        assert "no data: extrapolated" in texts                  # bins 7-8 m hold no pixel
        assert all(name in texts for name in _classes().names)   # the dots' colours are explained
        r = _draw(fig)
        for leg in fig.legends:
            box = leg.get_window_extent(r)
            assert all(not box.overlaps(ax.get_window_extent(r)) for ax in fig.axes), "legend covers a panel"
    finally:
        _close(fig)


def test_extrapolated_bins_are_shaded_where_no_pixel_was_counted():
    counts = _counts()
    model = fit_sensor_model(counts, _classes().names)
    fig = reliability_by_depth_figure(model, counts.fit, _classes())
    try:
        for ax in fig.axes[:2]:
            spans = sorted((p.get_x(), p.get_x() + p.get_width()) for p in ax.patches)
            assert spans == [(7.0, 7.5), (7.5, 8.0)]
    finally:
        _close(fig)


def test_reliability_marker_area_follows_the_bin_count_and_no_blank_band():
    rng = np.random.default_rng(1)
    conf = np.r_[rng.uniform(0.6, 1.0, 20000), [0.2]]          # one pixel alone at 0.2
    right = rng.uniform(0, 1, conf.size) < conf
    rb = ReliabilityBins.from_json(calibration_summary(conf, right)["bins"])
    fig = reliability_panels_figure([("online", {"E": rb}), ("fused", {"E": rb})])
    try:
        diagrams = [ax for ax in fig.axes if ax.get_ylabel() == "observed accuracy"]
        assert len(diagrams) == 2
        for ax in diagrams:
            (coll,) = ax.collections
            full = rb.count[rb.count > 0]
            np.testing.assert_allclose(coll.get_sizes(), MAX_MARKER_AREA * full / full.max())
            assert coll.get_sizes().min() < MAX_MARKER_AREA / 1000   # the lone pixel is a speck
            (line,) = [ln for ln in ax.get_lines() if ln.get_label() != "perfect calibration"]
            assert 0.2 not in np.round(line.get_xdata(), 1)            # and no line leads the eye to it
            assert len(line.get_xdata()) == int(np.sum(rb.count >= 0.01 * rb.count.max()))
        r = _draw(fig)
        top = max(ax.get_tightbbox(r).y1 for ax in fig.axes)
        bottom = min(ax.get_tightbbox(r).y0 for ax in fig.axes)
        assert fig.bbox.y1 - top < 0.06 * fig.bbox.height, "blank band above the panels"
        assert bottom - fig.bbox.y0 < 0.06 * fig.bbox.height
    finally:
        _close(fig)


@pytest.mark.parametrize("n", [6, 16, 40])
def test_confusion_titles_and_tick_labels_do_not_collide(n):
    counts = _counts(n)
    fig = confusion_bands_figure(counts.fit, counts.edges, _classes(n))
    try:
        r = _draw(fig)
        panels = [ax for ax in fig.axes if ax.get_xlabel() == "true class"]
        assert len(panels) == 3
        assert [ax.get_ylabel() for ax in panels] == ["input label", "", ""]
        for ax in panels:
            labels = [t for t in ax.get_xticklabels() + ax.get_yticklabels() if t.get_visible() and t.get_text()]
            assert all(t.get_fontsize() >= TICK_FONTSIZE for t in labels)
        for i, a in enumerate(panels):
            own = [a.xaxis.label, a.yaxis.label, a.title]
            for j, b in enumerate(panels):
                if i == j:
                    continue
                ticks = [t for t in b.get_xticklabels() + b.get_yticklabels() if t.get_visible() and t.get_text()]
                for t in own:
                    if t.get_text():
                        box = t.get_window_extent(r)
                        assert not any(box.overlaps(k.get_window_extent(r)) for k in ticks), \
                            f"{t.get_text()!r} of panel {i} runs into panel {j}'s tick labels"
        for a, b in zip(panels, panels[1:]):
            assert a.get_tightbbox(r).x1 <= b.get_tightbbox(r).x0 + 1
    finally:
        _close(fig)


def test_birdseye_legend_explains_white():
    classes = _classes(3)
    rgb = np.full((20, 30, 3), 255, np.uint8)
    rgb[:, :10] = classes.palette[2]
    fig = birdseye_figure(rgb, (0.0, 3.0, 0.0, 2.0), classes, [2])
    texts = _legend_texts(fig)
    assert texts == [classes.names[2], EMPTY_LABEL]
    assert "white" in EMPTY_LABEL and "unobserved" in EMPTY_LABEL
    (leg,) = [ax.get_legend() for ax in fig.axes if ax.get_legend()]
    white = leg.legend_handles[-1].get_facecolor()
    assert tuple(white[:3]) == (1.0, 1.0, 1.0)
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    FigureCanvasAgg(fig)   # the picture's Figure has no pyplot canvas
    r = _draw(fig)
    box, page = leg.get_window_extent(r), fig.bbox
    assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1, "legend cut off"
