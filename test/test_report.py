"""css_replay report (issue 13): legends that name exactly the classes shown, a "no label" colour unlike any class,
a per-class IoU table, no overlapping labels at 16 and 40 classes, no empty sections without ground truth."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from css_ros.engine.classes import ClassSet
from css_ros.evaluation import report

ROOT = Path(__file__).resolve().parents[1]
DEMO_CLASSES = ROOT / "bags" / "demo" / "classes.yaml"
IGN = 255


def demo_classes() -> ClassSet:
    if not DEMO_CLASSES.is_file():
        pytest.skip("demo class file not available")
    return ClassSet.from_yaml(DEMO_CLASSES)


def _label(h, w, ids):
    """Label image of vertical stripes, one per id."""
    img = np.empty((h, w), np.int64)
    for k, chunk in enumerate(np.array_split(np.arange(w), len(ids))):
        img[:, chunk] = ids[k]
    return img


def make_examples(gt_ids, input_ids, css_ids, with_gt=True, n=2, h=24, w=32):
    rng = np.random.default_rng(0)
    return [{"index": i, "rgb": rng.integers(0, 255, (h, w, 3), dtype=np.uint8),
             "gt": _label(h, w, gt_ids) if with_gt else None, "input": _label(h, w, input_ids),
             "css": _label(h, w, css_ids), "expectation": rng.random((h, w)).astype(np.float32),
             "variance": (10 ** rng.uniform(-6, -2, (h, w))).astype(np.float32)} for i in range(n)]


def iou_metrics(names, a, b):
    return ({"miou": 0.5, "pixel_accuracy": 0.8, "per_class_iou": dict(zip(names, a))},
            {"miou": 0.6, "pixel_accuracy": 0.9, "per_class_iou": dict(zip(names, b))})


def full_metrics(names, with_gt=True):
    inp, css = iou_metrics(names, [0.5] * len(names), [0.6] * len(names)) if with_gt else (None, None)
    fr = list(np.linspace(0, 0.99, 100))
    px = {"fractions": fr, "num_samples": 1000, "pixels_total": 1000, "subsampled": False,
          "curves": {k: list(np.linspace(0.1, 0.0, 100)) for k in ("expectation", "variance", "evidence",
                                                                    "random", "oracle")},
          "ause": {"expectation": 0.01, "variance": 0.02, "evidence": 0.03, "random": 0.05, "oracle": 0.0}}
    frames = [{"index": i, "trained": i % 2 == 0, "u_var": 1e-5 * (i + 1), "u_exp": 0.1 + 0.01 * i,
               "error": (0.05 + 0.01 * i) if with_gt else None} for i in range(20)]
    il = {"frames": frames, "num_evaluated": 20 if with_gt else 0}
    if with_gt:
        il["spearman"] = {"u_var": 0.5, "u_exp": 0.6}
        il["sparsification"] = {"fractions": fr, "num_samples": 20,
                                "curves": {k: list(np.linspace(0.1, 0.0, 100)) for k in ("u_var", "u_exp",
                                                                                         "random", "oracle")},
                                "ause": {"u_var": 0.01, "u_exp": 0.02, "random": 0.05, "oracle": 0.0}}
    return {
        "bag": "/x/bag", "model": "/x/model.ply", "num_gaussians": 10, "classes": list(names),
        "config": {"topics": {"gt": "/segmentation_gt"}},
        "frames": {"processed": 20, "trained": 20, "evaluated": 20, "skipped": {}, "out_of_range_labels": None},
        "segmentation": {"input": inp, "css": css, "css_online": None},
        "pixel_sparsification": px if with_gt else None, "image_level": il,
        "timing": {"total_s": 1.0, "fuse_fps": 10.0, "evaluate_fps": 10.0, "warmup_s": None,
                   "compilation_excluded": False},
    }


# ---------------------------------------------------------------------------------------- legend
def legend_texts(fig):
    legends = [leg for ax in fig.axes if (leg := ax.get_legend()) is not None] + list(fig.legends)
    assert len(legends) == 1
    return [t.get_text() for t in legends[0].get_texts()]


def test_legend_names_exactly_the_classes_present():
    classes = ClassSet.default(40)
    # 3 only in GT, 7 only in the input, 12 only in CSS; 39 present; 255 and 77 (out of range) are no class
    ex = make_examples([3, 39, IGN], [7, 39, 77], [12, 39, IGN])
    assert report.legend_classes(ex, 40, IGN) == [3, 7, 12, 39]
    fig = report.examples_figure(ex, classes, IGN)
    try:
        assert legend_texts(fig) == ["class_3", "class_7", "class_12", "class_39", "no label"]
    finally:
        report._plt().close(fig)


def test_legend_without_gt_uses_shown_label_images_only_and_drops_the_gt_column():
    classes = ClassSet.default(16)
    ex = make_examples([1], [2, 5], [5], with_gt=False)
    fig = report.examples_figure(ex, classes, IGN)
    try:
        assert legend_texts(fig) == ["class_2", "class_5", "no label"]
        titles = [ax.get_title() for ax in fig.axes if ax.get_title()]
        assert "ground truth" not in titles and "CSS labels" in titles
    finally:
        report._plt().close(fig)


def test_colour_bars_label_and_range():
    ex = make_examples([0], [0], [0])
    fig = report.examples_figure(ex, ClassSet.default(4), IGN)
    try:
        labels = {ax.get_xlabel(): ax for ax in fig.axes}
        assert report.E_LABEL == "E of the argmax class" and report.E_LABEL in labels
        assert report.VAR_LABEL.startswith("Var of the argmax class") and "log scale" in report.VAR_LABEL
        assert report.VAR_LABEL in labels
        assert labels[report.E_LABEL].get_xlim() == (0.0, 1.0)
        assert labels[report.VAR_LABEL].get_xscale() == "log"
    finally:
        report._plt().close(fig)


# ---------------------------------------------------------------------------------------- no label colour
def _min_dist(palette, colour):
    return float(np.sqrt(((palette.astype(float) - np.asarray(colour, float)) ** 2).sum(1)).min())


@pytest.mark.parametrize("which", ["demo", "default40"])
def test_no_label_colour_is_far_from_every_class_colour(which):
    classes = demo_classes() if which == "demo" else ClassSet.default(40)
    c = report.no_label_color(classes.palette)
    assert _min_dist(classes.palette, c) >= 60
    assert report.NO_LABEL_MIN_DISTANCE >= 60


def test_no_label_colour_avoids_a_black_class():
    pal = np.array([[0, 0, 0], [20, 20, 20], [250, 250, 250], [255, 0, 0]], np.uint8)
    c = report.no_label_color(pal)
    assert c != (0, 0, 0) and _min_dist(pal, c) >= 60


def test_colorize_draws_no_label_pixels_in_the_no_label_colour():
    classes = demo_classes()
    nl = report.no_label_color(classes.palette)
    lab = np.array([[0, 1, IGN, 99]])
    rgb, mask = report._colorize(lab, classes.palette, IGN, nl)
    assert mask.tolist() == [[False, False, True, True]]
    assert (rgb[0, 2] == nl).all() and (rgb[0, 3] == nl).all() and (rgb[0, 1] == classes.palette[1]).all()


# ---------------------------------------------------------------------------------------- IoU table
def test_iou_table_rows_and_values():
    names = ["floor", "wall", "lamp", "outlet", "box"]
    inp, css = iou_metrics(names, [0.5, 0.25, None, 0.1, None], [0.75, 0.2, None, None, 0.4])
    rows = report.iou_table(inp, css, names)
    assert rows == [
        "| class | input IoU (%) | CSS IoU (%) | difference (pp) |", "|---|---|---|---|",
        "| floor | 50.0 | 75.0 | +25.0 |",
        "| wall | 25.0 | 20.0 | -5.0 |",
        "| lamp | — | — | — |",
        "| outlet | 10.0 | — | — |",
        "| box | — | 40.0 | — |",
    ]


def test_iou_table_sorted_by_class_id_not_dict_order():
    names = ["a", "b", "c"]
    inp = {"per_class_iou": {"c": 0.3, "a": 0.1, "b": 0.2}}
    css = {"per_class_iou": {"b": 0.2, "c": 0.3, "a": 0.1}}
    assert [r.split(" | ")[0] for r in report.iou_table(inp, css, names)[2:]] == ["| a", "| b", "| c"]


def test_report_md_has_iou_table(tmp_path):
    names = [f"c{i}" for i in range(4)]
    m = full_metrics(names)
    text = report.write_markdown(tmp_path, m, []).read_text()
    assert "## Per-class IoU table" in text and "| c3 | 50.0 | 60.0 | +10.0 |" in text


# ---------------------------------------------------------------------------------------- no ground truth
def test_no_gt_report_has_no_empty_sections(tmp_path):
    names = [f"class_{i}" for i in range(5)]
    m = full_metrics(names, with_gt=False)
    ex = make_examples([0], [1, 2], [2], with_gt=False)
    plots = report.make_plots(tmp_path, m, ex, ClassSet.default(5), IGN)
    assert [f for _, f in plots] == ["examples.png"]
    assert not (tmp_path / "sparsification.png").exists() and not (tmp_path / "per_class_iou.png").exists()
    text = report.write_markdown(tmp_path, m, plots).read_text()
    headings = [ln for ln in text.splitlines() if ln.startswith("#")]
    assert not any("Sparsification" in h or "Per-class IoU" in h or "Segmentation" in h or "Uncertainty" in h
                   for h in headings), headings
    notice = [ln for ln in text.splitlines() if "No ground truth" in ln]
    assert len(notice) == 1 and "not reported" in notice[0] and "/segmentation_gt" in notice[0]
    assert text.lower().count("ground truth") == 1


def test_gt_report_has_sections(tmp_path):
    names = [f"class_{i}" for i in range(5)]
    m = full_metrics(names)
    plots = report.make_plots(tmp_path, m, make_examples([0], [1], [2]), ClassSet.default(5), IGN)
    assert {f for _, f in plots} == {"sparsification.png", "image_uncertainty.png", "per_class_iou.png",
                                     "examples.png"}
    text = report.write_markdown(tmp_path, m, plots).read_text()
    assert "## Segmentation" in text and "## Uncertainty" in text and "No ground truth" not in text


# ---------------------------------------------------------------------------------------- no overlaps
def _boxes(fig, artists):
    r = fig.canvas.get_renderer()
    return [a.get_window_extent(r) for a in artists if a.get_visible() and a.get_text()]


def _overlapping(boxes):
    return [(a, b) for i, a in enumerate(boxes) for b in boxes[i + 1:] if a.overlaps(b)]


def _check_no_overlaps(fig):
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    for ax in fig.axes:
        for axis in (ax.xaxis, ax.yaxis):
            labels = [t for t in axis.get_ticklabels(which="both")]
            assert not _overlapping(_boxes(fig, labels)), f"tick labels overlap in {ax.get_title() or ax}"
    legends = [leg for ax in fig.axes if (leg := ax.get_legend()) is not None] + list(fig.legends)
    axes_with_data = [ax for ax in fig.axes if ax.axison]
    for leg in legends:
        lb = leg.get_window_extent(r)
        fb = fig.bbox
        assert fb.x0 - 1 <= lb.x0 and lb.x1 <= fb.x1 + 1 and fb.y0 - 1 <= lb.y0 and lb.y1 <= fb.y1 + 1, "legend cut"
        for ax in axes_with_data:
            assert not lb.overlaps(ax.get_window_extent(r)) or leg.axes is ax and not ax.has_data(), \
                "legend covers a plot"


@pytest.mark.parametrize("n", [16, 40])
def test_iou_chart_has_no_overlaps(n):
    names = [f"a_rather_long_class_name_{i}" for i in range(n)]
    inp, css = iou_metrics(names, list(np.linspace(0, 1, n)), [None] + list(np.linspace(1, 0, n - 1)))
    fig = report.iou_figure(inp, css, names)
    try:
        _check_no_overlaps(fig)
        ax = fig.axes[0]
        assert [t.get_text() for t in ax.get_yticklabels()] == names
    finally:
        report._plt().close(fig)


@pytest.mark.parametrize("n", [16, 40])
def test_examples_figure_has_no_overlaps(n):
    classes = ClassSet(tuple(f"long_class_name_{i}" for i in range(n)), ClassSet.default(n).palette)
    ids = list(range(n))
    ex = make_examples(ids, ids[::-1], ids + [IGN], n=3, h=30, w=2 * n + 2)
    fig = report.examples_figure(ex, classes, IGN)
    try:
        _check_no_overlaps(fig)
        assert len(legend_texts(fig)) == n + 1
    finally:
        report._plt().close(fig)


def test_sparsification_and_scatter_have_no_overlaps():
    m = full_metrics([f"class_{i}" for i in range(40)])
    for fig in (report.sparsification_figure(m["pixel_sparsification"], m["image_level"]["sparsification"]),
                report.uncertainty_scatter_figure(m["image_level"])):
        try:
            _check_no_overlaps(fig)
        finally:
            report._plt().close(fig)


def test_demo_palette_examples_no_overlaps():
    classes = demo_classes()
    ids = list(range(classes.num_classes))
    fig = report.examples_figure(make_examples(ids, ids, ids + [IGN], n=4), classes, IGN)
    try:
        _check_no_overlaps(fig)
    finally:
        report._plt().close(fig)
