"""css_replay report: matplotlib (Agg) PNG plots and a report.md that embeds them."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

from .comparison import comparison_rows
from .report_guide import CAPTIONS, TERMS

if TYPE_CHECKING:
    from ..engine.classes import ClassSet

#: plot style per sparsification signal
_STYLE = {
    "expectation": dict(color="tab:blue", label="expectation (-E)"),
    "variance": dict(color="tab:orange", label="variance (Var)"),
    "evidence": dict(color="tab:green", label="observation count (-evidence)"),
    "u_var": dict(color="tab:orange", label="U_var"),
    "u_exp": dict(color="tab:blue", label="U_exp"),
    "random": dict(color="gray", linestyle="--", label="random"),
    "oracle": dict(color="black", linestyle=":", label="oracle"),
}


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


#: "no label" (ignore / unknown / out-of-range ids) in label images: this colour with a light-grey diagonal hatch.
#: Black unless a class colour lies within NO_LABEL_MIN_DISTANCE of it (see :func:`no_label_color`).
NO_LABEL_COLOR = (0, 0, 0)
NO_LABEL_HATCH = "////"
NO_LABEL_HATCH_COLOR = (0.75, 0.75, 0.75)
#: smallest RGB (L2, 0..255) distance between the "no label" colour and any class colour
NO_LABEL_MIN_DISTANCE = 60.0


def no_label_color(palette: np.ndarray) -> tuple[int, int, int]:
    """RGB colour for "no label" pixels: black, or (when a class colour is within NO_LABEL_MIN_DISTANCE of black)
    the colour of the 0/64/128/192/255 grid farthest from every class colour."""
    pal = np.asarray(palette, dtype=float).reshape(-1, 3)
    if pal.size == 0:
        return NO_LABEL_COLOR

    def dist(c) -> float:
        return float(np.sqrt(((pal - np.asarray(c, float)) ** 2).sum(1)).min())

    if dist(NO_LABEL_COLOR) >= NO_LABEL_MIN_DISTANCE:
        return NO_LABEL_COLOR
    levels = (0, 64, 128, 192, 255)
    grid = [(r, g, b) for r in levels for g in levels for b in levels]
    return max(grid, key=dist)


def _colorize(labels: np.ndarray, palette: np.ndarray, ignore_label: int,
              no_label: tuple[int, int, int]) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) uint8 RGB of a label image and the (H, W) bool mask of its "no label" pixels."""
    labels = np.asarray(labels)
    valid = (labels >= 0) & (labels < len(palette)) & (labels != ignore_label)
    out = np.empty(labels.shape + (3,), dtype=np.uint8)
    out[...] = np.asarray(no_label, dtype=np.uint8)
    out[valid] = np.asarray(palette, dtype=np.uint8)[labels[valid]]
    return out, ~valid


def legend_classes(examples: Sequence[dict[str, Any]], num_classes: int, ignore_label: int,
                   keys: Sequence[str] = ("gt", "input", "css")) -> list[int]:
    """Sorted ids of the classes that occur in the shown label images (``keys`` of every example)."""
    present = np.zeros(num_classes, dtype=bool)
    for ex in examples:
        for k in keys:
            img = ex.get(k)
            if img is None:
                continue
            ids = np.unique(np.asarray(img))
            ids = ids[(ids >= 0) & (ids < num_classes) & (ids != ignore_label)]
            present[ids.astype(np.int64)] = True
    return [int(i) for i in np.flatnonzero(present)]


def _save(fig, path: Path, dpi: int = 110) -> None:
    fig.savefig(path, dpi=dpi)
    _plt().close(fig)


def _fractions_and_curves(rep: dict[str, Any]):
    x = np.asarray(rep["fractions"])
    for name, curve in rep["curves"].items():
        yield name, x, np.array([np.nan if v is None else v for v in curve], dtype=float)


def sparsification_figure(pixel: dict[str, Any] | None, image: dict[str, Any] | None):
    """Figure of the pixel- and image-level sparsification curves; None when there is neither."""
    panels = [(t, r) for t, r in (("pixel level", pixel), ("image level", image)) if r]
    if not panels:
        return None
    plt = _plt()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.8 * len(panels), 5.0), squeeze=False, layout="constrained")
    for ax, (title, rep) in zip(axes[0], panels):
        for name, x, y in _fractions_and_curves(rep):
            style = dict(_STYLE.get(name, dict(label=name)))
            a = rep["ause"].get(name)
            if a is not None and name != "oracle":
                style["label"] = f"{style['label']} (AUSE {a:.3f})"
            ax.plot(x, y, **style)
        ax.set_xlabel("fraction removed (most uncertain first)")
        ax.set_ylabel("error of the remaining (1 - accuracy)")
        ax.set_title(f"Sparsification, {title} (n={rep['num_samples']})")
        ax.set_xlim(0, 1)
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        # below the axes, so that it never hides a curve
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    return fig


def plot_sparsification(pixel: dict[str, Any] | None, image: dict[str, Any] | None, path: Path) -> bool:
    """Pixel-level and image-level sparsification curves (error of the kept samples vs fraction removed)."""
    fig = sparsification_figure(pixel, image)
    if fig is None:
        return False
    _save(fig, path)
    return True


def _log_axis(ax, values: np.ndarray) -> None:
    """Log x axis whose tick labels do not collide: 1-2-5 labels over at most two decades, decades only beyond."""
    from matplotlib.ticker import LogFormatterSciNotation, LogLocator, NullFormatter

    ax.set_xscale("log")
    decades = np.log10(values.max() / values.min())
    if decades <= 2:
        ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
        ax.xaxis.set_major_formatter(LogFormatterSciNotation(labelOnlyBase=False))
    ax.xaxis.set_minor_formatter(NullFormatter())


def uncertainty_scatter_figure(image_level: dict[str, Any]):
    """Figure of per-image U_var / U_exp vs per-image error; None with fewer than two frames with an error."""
    recs = [r for r in image_level.get("frames", []) if r.get("error") is not None]
    if len(recs) < 2:
        return None
    plt = _plt()
    rho = image_level.get("spearman", {})
    fig, axes = plt.subplots(1, 2, figsize=(11.5, 4.6), layout="constrained")
    err = np.array([r["error"] for r in recs])
    trained = np.array([bool(r["trained"]) for r in recs])
    for ax, key in zip(axes, ("u_var", "u_exp")):
        u = np.array([r[key] for r in recs])
        for mask, marker, lab in ((trained, "o", "fused frames"), (~trained, "x", "held-out frames")):
            if mask.any():
                ax.scatter(u[mask], err[mask], s=14, marker=marker, label=lab, alpha=0.8)
        if key == "u_var" and np.all(u > 0) and u.max() > u.min():
            _log_axis(ax, u)
        r = rho.get(key)
        ax.set_title(f"{key} vs image error (Spearman rho = {r:+.3f})" if r is not None else f"{key} vs image error")
        ax.set_xlabel(key + (" (log scale)" if ax.get_xscale() == "log" else ""))
        ax.set_ylabel("per-image error (1 - accuracy)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, frameon=False)
    return fig


def plot_uncertainty_scatter(image_level: dict[str, Any], path: Path) -> bool:
    """Per-image U_var and U_exp vs per-image error, fused frames and held-out frames in different markers."""
    fig = uncertainty_scatter_figure(image_level)
    if fig is None:
        return False
    _save(fig, path)
    return True


def iou_rows(input_seg: dict[str, Any] | None, css: dict[str, Any] | None,
             class_names: Sequence[str] | None = None) -> list[tuple[int, str, float | None, float | None]]:
    """(class id, name, input IoU, CSS IoU) per class in class-id order; IoU None = class absent (from the GT and
    that prediction). ``class_names`` gives the id order (default: the order of ``css['per_class_iou']``)."""
    a = (input_seg or {}).get("per_class_iou", {})
    b = (css or {}).get("per_class_iou", {})
    names = list(class_names) if class_names is not None else list(dict.fromkeys([*b, *a]))
    return [(i, n, a.get(n), b.get(n)) for i, n in enumerate(names)]


def iou_figure(input_seg: dict[str, Any] | None, css: dict[str, Any] | None,
               class_names: Sequence[str] | None = None):
    """Horizontal bar chart of per-class IoU (input vs CSS), one row per class present in either, class id order
    from top to bottom; None when there is nothing to show."""
    if not input_seg or not css:
        return None
    rows = [r for r in iou_rows(input_seg, css, class_names) if r[2] is not None or r[3] is not None]
    if not rows:
        return None
    plt = _plt()
    n = len(rows)
    longest = max(len(r[1]) for r in rows)
    fig, ax = plt.subplots(figsize=(7.0 + 0.07 * longest, 1.6 + 0.32 * n), layout="constrained")
    y = np.arange(n)
    a = np.array([np.nan if r[2] is None else r[2] for r in rows])
    b = np.array([np.nan if r[3] is None else r[3] for r in rows])
    ax.barh(y - 0.2, np.nan_to_num(a), 0.4, label=f"input (mIoU {100 * input_seg['miou']:.1f}%)", color="tab:gray")
    ax.barh(y + 0.2, np.nan_to_num(b), 0.4, label=f"CSS (mIoU {100 * css['miou']:.1f}%)", color="tab:blue")
    for yy, v, off in [(yy, v, -0.2) for yy, v in zip(y, a)] + [(yy, v, 0.2) for yy, v in zip(y, b)]:
        if np.isnan(v):  # absent from the GT and this prediction: no bar, not a zero
            ax.text(0.01, yy + off, "—", va="center", ha="left", fontsize=7)
    ax.set_yticks(y)
    ax.set_yticklabels([r[1] for r in rows], fontsize=8)
    ax.invert_yaxis()
    ax.set_ylim(n - 0.5, -0.5)
    ax.set_xlabel("IoU")
    ax.set_xlim(0, 1)
    ax.set_title("Per-class IoU vs ground truth (classes absent from both omitted; — = absent)", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    fig.legend(loc="outside lower center", ncol=2, fontsize=8, frameon=False)
    return fig


def plot_iou_bars(input_seg: dict[str, Any] | None, css: dict[str, Any] | None, path: Path,
                  class_names: Sequence[str] | None = None) -> bool:
    """Per-class IoU of the input segmentation and of the CSS rendering (classes absent from both are omitted)."""
    fig = iou_figure(input_seg, css, class_names)
    if fig is None:
        return False
    _save(fig, path)
    return True


_EX_COLS = ("rgb", "gt", "input", "css", "expectation", "variance")
_EX_TITLES = {"rgb": "RGB", "gt": "ground truth", "input": "input segmentation", "css": "CSS labels",
              "expectation": "expectation E", "variance": "variance Var"}
E_LABEL = "E of the argmax class"
VAR_LABEL = "Var of the argmax class (log scale)"


def _var_norm(examples: Sequence[dict[str, Any]]):
    """LogNorm of the variance column: up to the 99.5th percentile, down to 1e-4 of that (values outside are
    clipped to the ends of the colour bar)."""
    from matplotlib.colors import LogNorm

    vals = np.concatenate([np.asarray(e["variance"], float).ravel() for e in examples if e.get("variance") is not None]
                          or [np.ones(1)])
    vals = vals[np.isfinite(vals) & (vals > 0)]
    vmax = float(np.percentile(vals, 99.5)) if vals.size else 1.0
    vmin = max(float(np.percentile(vals, 1)) if vals.size else vmax * 1e-4, vmax * 1e-4)
    if not vmax > vmin:
        vmin, vmax = vmax / 10 if vmax > 0 else 1e-4, vmax if vmax > 0 else 1.0
    return LogNorm(vmin=vmin, vmax=vmax, clip=True)


def examples_figure(examples: Sequence[dict[str, Any]], classes: "ClassSet", ignore_label: int = 255):
    """Figure of example frames (one row each): RGB, GT, input segmentation, CSS labels, E, Var; a class legend
    (classes in the shown label images + "no label") and colour bars for E and Var below. Columns without data in
    every example (e.g. GT when the bag has none) are left out. None when there are no examples."""
    if not examples:
        return None
    from matplotlib.patches import Patch

    plt = _plt()
    cols = [c for c in _EX_COLS if any(e.get(c) is not None for e in examples)]
    label_cols = [c for c in cols if c in ("gt", "input", "css")]
    nl = no_label_color(classes.palette)
    nl_f = tuple(v / 255 for v in nl)
    present = legend_classes(examples, classes.num_classes, ignore_label, label_cols)
    handles = [Patch(facecolor=classes.palette[i] / 255.0, edgecolor="0.3", linewidth=0.5, label=classes.names[i])
               for i in present]
    handles.append(Patch(facecolor=nl_f, edgecolor=NO_LABEL_HATCH_COLOR, hatch=NO_LABEL_HATCH, linewidth=0.5,
                         label="no label"))
    # legend geometry: columns of about the longest name's width, rows as needed
    legend_w = 2.6 * max(len(label_cols) + (1 if "rgb" in cols else 0), 2)
    longest = max(len(h.get_label()) for h in handles)
    ncol = max(1, min(len(handles), int(legend_w / (0.55 + 0.085 * longest))))
    nrow = -(-len(handles) // ncol)
    row_h, col_w = 2.1, 2.6
    footer = 0.45 + 0.24 * nrow
    n = len(examples)
    fig_h = row_h * n + 0.35 + footer
    fig = plt.figure(figsize=(col_w * len(cols), fig_h))
    gs = fig.add_gridspec(n + 1, len(cols), height_ratios=[row_h] * n + [footer],
                          left=0.03, right=0.995, bottom=0.01, top=1 - 0.35 / fig_h, wspace=0.04, hspace=0.06)
    vnorm = _var_norm(examples) if "variance" in cols else None
    mappables: dict[str, Any] = {}
    for r, ex in enumerate(examples):
        for c, key in enumerate(cols):
            ax = fig.add_subplot(gs[r, c])
            img = ex.get(key)
            ax.set_xticks([])
            ax.set_yticks([])
            if img is None:
                ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
            elif key in ("gt", "input", "css"):
                rgb, mask = _colorize(img, classes.palette, ignore_label, nl)
                ax.imshow(rgb, interpolation="nearest")
                if mask.any():  # hatch over the "no label" pixels (vector, independent of the image resolution)
                    cs = ax.contourf(mask.astype(float), levels=[0.5, 1.5], colors="none", hatches=[NO_LABEL_HATCH])
                    cs.set_edgecolor(NO_LABEL_HATCH_COLOR)
                    cs.set_linewidth(0)
            elif key == "expectation":
                mappables[key] = ax.imshow(img, cmap="viridis", vmin=0.0, vmax=1.0, interpolation="nearest")
            elif key == "variance":
                mappables[key] = ax.imshow(np.clip(np.nan_to_num(np.asarray(img, float)), vnorm.vmin, vnorm.vmax),
                                           cmap="magma", norm=vnorm, interpolation="nearest")
            else:
                ax.imshow(img, interpolation="nearest")
            if c == 0:
                ax.set_ylabel(f"frame {ex['index']}", fontsize=8)
            if r == 0:
                ax.set_title(_EX_TITLES[key], fontsize=9)
    # footer: colour bars under their columns, the class legend under the label columns
    for key, label in (("expectation", E_LABEL), ("variance", VAR_LABEL)):
        if key in mappables:
            c = cols.index(key)
            sub = gs[n, c].subgridspec(3, 1, height_ratios=[0.25, 0.2, 0.55])
            cax = fig.add_subplot(sub[1])
            cb = fig.colorbar(mappables[key], cax=cax, orientation="horizontal")
            cb.set_label(label, fontsize=8)
            cb.ax.tick_params(labelsize=7)
    leg_cols = [i for i, k in enumerate(cols) if k not in ("expectation", "variance")] or [0]
    lax = fig.add_subplot(gs[n, leg_cols[0]:leg_cols[-1] + 1])
    lax.axis("off")
    lax.legend(handles=handles, loc="center", ncol=ncol, fontsize=8, frameon=False, handlelength=1.6,
               columnspacing=1.0, title="classes in the label images", title_fontsize=8)
    return fig


def plot_examples(examples: Sequence[dict[str, Any]], classes: "ClassSet", ignore_label: int, path: Path) -> bool:
    """Strip of example frames: RGB, GT, input segmentation, CSS labels, expectation, variance (one row each),
    with a class legend and colour bars; "no label" pixels are :data:`NO_LABEL_COLOR` with a light hatch."""
    fig = examples_figure(examples, classes, ignore_label)
    if fig is None:
        return False
    _save(fig, path, dpi=90)
    return True


def _pct(x: float | None) -> str:
    return "n/a" if x is None else f"{100 * x:.1f}"


def _f(x: float | None, fmt: str = ".4f") -> str:
    return "n/a" if x is None else format(x, fmt)


def make_plots(out: Path, metrics: dict[str, Any], examples: Sequence[dict[str, Any]], classes: "ClassSet",
               ignore_label: int = 255) -> list[tuple[str, str]]:
    """Write the PNG plots into ``out``; return (title, file name) of each plot written."""
    out = Path(out)
    seg = metrics["segmentation"]
    image_level = metrics["image_level"]
    plots: list[tuple[str, str]] = []
    if plot_sparsification(metrics.get("pixel_sparsification"), image_level.get("sparsification"),
                           out / "sparsification.png"):
        plots.append(("Sparsification curves", "sparsification.png"))
    if plot_uncertainty_scatter(image_level, out / "image_uncertainty.png"):
        plots.append(("Image-level uncertainty vs error", "image_uncertainty.png"))
    if plot_iou_bars(seg.get("input"), seg.get("css"), out / "per_class_iou.png", metrics.get("classes")):
        plots.append(("Per-class IoU", "per_class_iou.png"))
    if plot_examples(examples, classes, ignore_label, out / "examples.png"):
        plots.append(("Example frames", "examples.png"))
    if plot_reliability(metrics.get("calibration"), out / "reliability.png"):
        plots.append(("Reliability diagram (is the rendered label right?)", "reliability.png"))
    return plots


def plot_reliability(cal: dict[str, Any] | None, path: Path) -> bool:
    """Reliability diagrams of E and the calibrated confidence, online and fused renders; False if no data."""
    from .calibration_metrics import ReliabilityBins

    if not cal:
        return False
    panels = []
    for key, title in (("online", "online renders (~/semantic per frame)"), ("fused", "final map (fused renders)")):
        rec = cal.get(key)
        if not rec:
            continue
        curves = {}
        for sig, name in (("expectation", "expectation E of the label"), ("confidence", "calibrated confidence")):
            if rec.get(sig):
                curves[name] = ReliabilityBins.from_json(rec[sig]["bins"])
        panels.append((title, curves))
    if not panels:
        return False
    from .calibration_plots import reliability_panels_figure

    _save(reliability_panels_figure(panels), path)
    return True


def _compile_note(timing: dict[str, Any]) -> str:
    """Whether the timings include kernel compilation (one sentence)."""
    if timing.get("compilation_excluded"):
        return (f"timings exclude kernel compilation (kernels warmed up on a tiny frame beforehand in "
                f"{timing['warmup_s']:.1f} s)")
    return "timings may include kernel compilation (no warm-up run)"


def _out_of_range_lines(rec: dict[str, Any] | None) -> list[str]:
    """Report lines on label ids that are not classes (none when there are none)."""
    if not rec:
        return []
    lines = []
    for kind, r in rec.get("kinds", {}).items():
        if r["pixels"]:
            ids = ", ".join(f"{i} ({n} px)" for i, n in r["ids"].items())
            lines.append(f"- **out-of-range labels** ({kind}): {r['pixels']} of {r['labelled_pixels']} labelled "
                         f"pixels ({100 * r['share']:.2f} %) hold ids that are no class: {ids}. GT pixels with such "
                         "ids are excluded from every metric; input pixels count as wrong.")
    return lines


def has_ground_truth(metrics: dict[str, Any]) -> bool:
    """Whether the run had ground truth (segmentation metrics of the input and of CSS)."""
    seg = metrics.get("segmentation") or {}
    return bool(seg.get("input") and seg.get("css"))


def no_ground_truth_notice(metrics: dict[str, Any]) -> str:
    """The one line that says there was no ground truth and what is therefore not reported."""
    topic = ((metrics.get("config") or {}).get("topics") or {}).get("gt")
    where = f"topic `{topic}` not in the bag" if topic else "ground-truth topic disabled"
    return (f"**No ground truth** ({where}): segmentation metrics (mIoU, accuracy, per-class IoU), sparsification "
            "curves / AUSE and uncertainty-vs-error correlations are therefore not reported; the example frames "
            "show the input segmentation, the CSS labels and the uncertainty maps.")


def _pp(x: float | None) -> str:
    return "—" if x is None else f"{100 * x:.1f}"


def iou_table(input_seg: dict[str, Any], css: dict[str, Any], class_names: Sequence[str] | None = None) -> list[str]:
    """Markdown rows of the per-class IoU table (class | input IoU | CSS IoU | difference), class-id order;
    "—" where a class is absent (IoU None), the difference only where both are defined."""
    rows = ["| class | input IoU (%) | CSS IoU (%) | difference (pp) |", "|---|---|---|---|"]
    for _, name, a, b in iou_rows(input_seg, css, class_names):
        diff = "—" if a is None or b is None else f"{100 * (b - a):+.1f}"
        rows.append(f"| {name} | {_pp(a)} | {_pp(b)} | {diff} |")
    return rows


def _figure_text(rec: dict[str, Any], pct: bool = True) -> str:
    """A changing-world figure: its value, or "n/a" and why not."""
    if rec.get("value") is None:
        return f"n/a ({rec.get('reason', 'not measured')})"
    return f"{100 * rec['value']:.2f} %" if pct else f"{rec['value']:.3f}"


def changing_world_lines(cw: dict[str, Any] | None) -> list[str]:
    """report.md's "A changing world" section from metrics.json's ``changing_world`` (none without it)."""
    if not cw:
        return []
    rules = cw["rules"]
    d = cw["definitions"]
    held = cw["fused_pixels_without_evidence"]
    ts = cw["transient_share"]
    half = rules["evidence_half_life"]
    lines = ["", "## A changing world", "",
             f"- rules: transient classes {', '.join(rules['transient_classes']) or 'none'}; measured depth "
             + (f"`{rules['depth_topic']}` (tolerance max({rules['depth_tolerance']:g} m, "
                f"{rules['depth_tolerance_relative']:g} x depth))" if rules["depth_topic"] else "none")
             + f"; evidence half-life {'none (the paper update)' if half is None else f'{half:g} observations'}",
             f"- fused labelled pixels that added no evidence: {held['transient']} of a transient class, "
             f"{held['occluded']} in front of the map's surface (measured depth)", "",
             f"Renders: {d['renders']}.", "", "| figure | value | definition |", "|---|---|---|",
             f"| transient share | {_figure_text(ts)} | {d['transient_share']}"
             + (f"; classes: {', '.join(ts['classes'])} ({ts['basis']})" if ts.get("classes") else "") + " |"]
    for key, name in (("static_accuracy", "accuracy vs the static ground truth"),
                      ("others_accuracy", "accuracy, pixels of unchanged objects"),
                      ("changed_accuracy", "changed objects in their new class"),
                      ("changed_accuracy_after", "the same, poses after the change")):
        lines.append(f"| {name} | {_figure_text(cw[key])} | {d[key]} |")
    sa = cw["surprise_auroc"]
    where = f" (frame {sa['frame']})" if sa.get("frame") is not None else ""
    lines.append(f"| surprise AUROC{where} | {_figure_text(sa, pct=False)} | {d['surprise_auroc']} |")
    return lines


def write_markdown(out: Path, metrics: dict[str, Any], plots: Sequence[tuple[str, str]]) -> Path:
    """Write ``report.md`` (tables from ``metrics`` + the given plots) into ``out``; return its path."""
    out = Path(out)
    seg = metrics["segmentation"]
    f = metrics["frames"]
    t = metrics["timing"]
    lines = [
        "# css_replay report",
        "",
        f"- bag: `{metrics['bag']}`",
        f"- model: `{metrics['model']}` ({metrics['num_gaussians']} Gaussians), {len(metrics['classes'])} classes",
        f"- frames: {f['processed']} processed, {f['trained']} fused into the map, {f['evaluated']} evaluated; "
        f"skipped: {sum(f['skipped'].values())}" + (f" ({', '.join(f'{k}: {v}' for k, v in f['skipped'].items())})"
                                                     if f["skipped"] else ""),
        f"- update: {(metrics.get('sensor_model') or {}).get('description') or 'the paper update (no sensor model)'}",
        f"- time: {t['total_s']:.1f} s total (fusion {_f(t.get('fuse_fps'), '.1f')} frames/s, "
        f"evaluation {_f(t.get('evaluate_fps'), '.1f')} frames/s); " + _compile_note(t),
        *_out_of_range_lines(f.get("out_of_range_labels")),
        "",
    ]
    if has_ground_truth(metrics):
        lines += ["CSS metrics are computed after all training frames are fused: every frame's pose is rendered with "
                  "the final map (the paper's protocol). Pixels whose ground truth is the ignore label are excluded; "
                  "a 'no label' prediction counts as wrong. mIoU averages the classes present in the ground truth or "
                  "the prediction.", "",
                  "## Segmentation (smoothing effect)", "",
                  "| method | mIoU (%) | accuracy (%) |", "|---|---|---|",
                  f"| input segmentation | {_pct(seg['input']['miou'])} | {_pct(seg['input']['pixel_accuracy'])} |",
                  f"| CSS (fused map) | {_pct(seg['css']['miou'])} | {_pct(seg['css']['pixel_accuracy'])} |"]
        for key, label in (("css_online", "CSS online (per-frame renders in the output bag)"),
                           ("css_trained_frames", "CSS, fused frames only"),
                           ("css_heldout_frames", "CSS, held-out frames only")):
            if seg.get(key):
                lines.append(f"| {label} | {_pct(seg[key]['miou'])} | {_pct(seg[key]['pixel_accuracy'])} |")
        comparison = comparison_rows(metrics)
        if comparison:
            lines += ["", "### Paper update vs the sensor model (same frames, one run)", "",
                      "Both maps fuse the same frames; the paper's update counts every labelled pixel as one vote, "
                      "the sensor model weights it by its depth. Bold: the better of the two.", "", *comparison]
        lines += ["", "## Per-class IoU table", "",
                  "IoU in %, difference = CSS - input in percentage points; — = the class is absent from the "
                  "ground truth and that prediction (classes absent from both are not counted as 0).", "",
                  *iou_table(seg["input"], seg["css"], metrics.get("classes"))]
    else:
        lines.append(no_ground_truth_notice(metrics))
    lines += changing_world_lines(metrics.get("changing_world"))
    unc = []
    px = metrics.get("pixel_sparsification")
    if px:
        unc += [f"Pixel-level sparsification over {px['num_samples']} pixels"
                + (f" (uniform subsample of {px['pixels_total']})" if px.get("subsampled") else "")
                + ". AUSE = area between the curve and the oracle's (lower is better):", "",
                "| signal | AUSE |", "|---|---|"]
        unc += [f"| {k} | {_f(v)} |" for k, v in px["ause"].items() if k != "oracle"]
    il = metrics["image_level"]
    if il.get("spearman"):
        sp = il["sparsification"]["ause"]
        unc += ["", f"Image level ({il['num_evaluated']} frames, error = 1 - accuracy):", "",
                "| signal | Spearman rho vs error | AUSE |", "|---|---|---|"]
        for k in ("u_var", "u_exp"):
            unc.append(f"| {k} | {_f(il['spearman'].get(k), '+.3f')} | {_f(sp.get(k))} |")
        unc.append(f"| random | | {_f(sp.get('random'))} |")
    cal = metrics.get("calibration")
    if cal and (cal.get("online") or cal.get("fused")):
        unc += ["", "Calibration of 'the rendered label is right' (ECE over 15 equal bins, lower is better; Brier "
                "score):", "", "| renders | signal | ECE | Brier | mean predicted | accuracy |", "|---|---|---|---|---|---|"]
        for key in ("online", "fused"):
            rec = cal.get(key) or {}
            for sig in ("expectation", "confidence"):
                r = rec.get(sig)
                if r:
                    unc.append(f"| {key} | {'E' if sig == 'expectation' else 'calibrated confidence'} | "
                               f"{_f(r['ece'])} | {_f(r['brier'])} | {_f(r['mean_confidence'], '.3f')} | "
                               f"{_f(r['accuracy'], '.3f')} |")
        dropped = {f"{key} {sig}": int((cal.get(key) or {}).get(sig, {}).get("dropped") or 0)
                   for key in ("online", "fused") for sig in ("expectation", "confidence")
                   if (cal.get(key) or {}).get(sig)}
        if any(dropped.values()):
            unc += ["", "Pixels left out of these rows for a NaN / inf value: " + ", ".join(
                f"{k} {n}" for k, n in dropped.items() if n) + "."]
    if unc:
        lines += ["", "## Uncertainty", "", *unc, "", *TERMS]
    for title, fname in plots:
        lines += ["", f"## {title}", "", f"![{title}]({fname})"]
        if fname in CAPTIONS:
            lines += ["", CAPTIONS[fname]]
    lines += ["", "Raw numbers: `metrics.json`. Output bag: `bag/` (if written). Map: `map.npz`; "
              "splats for 3DGS viewers: `map_semantic.ply` (class colours), `map_uncertainty_variance.ply` (variance "
              "colour map, colour bar in `map_uncertainty_variance_colorbar.png`).", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
