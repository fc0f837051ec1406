"""css_replay report: matplotlib (Agg) PNG plots and a report.md that embeds them."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Sequence

import numpy as np

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


def plot_sparsification(pixel: dict[str, Any] | None, image: dict[str, Any] | None, path: Path) -> bool:
    """Pixel-level and image-level sparsification curves (error of the kept samples vs fraction removed)."""
    panels = [(t, r) for t, r in (("pixel level", pixel), ("image level", image)) if r]
    if not panels:
        return False
    plt = _plt()
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    for ax, (title, rep) in zip(axes[0], panels):
        x = np.asarray(rep["fractions"])
        for name, curve in rep["curves"].items():
            y = np.array([np.nan if v is None else v for v in curve], dtype=float)
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
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_uncertainty_scatter(image_level: dict[str, Any], path: Path) -> bool:
    """Per-image U_var and U_exp vs per-image error, fused frames and held-out frames in different markers."""
    recs = [r for r in image_level.get("frames", []) if r.get("error") is not None]
    if len(recs) < 2:
        return False
    plt = _plt()
    rho = image_level.get("spearman", {})
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    err = np.array([r["error"] for r in recs])
    trained = np.array([bool(r["trained"]) for r in recs])
    for ax, key in zip(axes, ("u_var", "u_exp")):
        u = np.array([r[key] for r in recs])
        for mask, marker, lab in ((trained, "o", "fused frames"), (~trained, "x", "held-out frames")):
            if mask.any():
                ax.scatter(u[mask], err[mask], s=14, marker=marker, label=lab, alpha=0.8)
        if key == "u_var" and np.all(u > 0):
            ax.set_xscale("log")
        r = rho.get(key)
        ax.set_title(f"{key} vs image error (Spearman rho = {r:+.3f})" if r is not None else f"{key} vs image error")
        ax.set_xlabel(key)
        ax.set_ylabel("per-image error (1 - accuracy)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_iou_bars(input_seg: dict[str, Any] | None, css: dict[str, Any] | None, path: Path) -> bool:
    """Per-class IoU of the input segmentation and of the CSS rendering (classes absent from both are omitted)."""
    if not input_seg or not css:
        return False
    names = [n for n in css["per_class_iou"] if css["per_class_iou"][n] is not None
             or input_seg["per_class_iou"].get(n) is not None]
    if not names:
        return False
    plt = _plt()
    a = np.array([input_seg["per_class_iou"].get(n) or 0.0 for n in names])
    b = np.array([css["per_class_iou"].get(n) or 0.0 for n in names])
    x = np.arange(len(names))
    fig, ax = plt.subplots(figsize=(max(6.0, 0.55 * len(names) + 2), 4.2))
    ax.bar(x - 0.2, a, 0.4, label=f"input (mIoU {100 * input_seg['miou']:.1f}%)", color="tab:gray")
    ax.bar(x + 0.2, b, 0.4, label=f"CSS (mIoU {100 * css['miou']:.1f}%)", color="tab:blue")
    ax.set_xticks(x)
    ax.set_xticklabels(names, rotation=45, ha="right", fontsize=8)
    ax.set_ylabel("IoU")
    ax.set_ylim(0, 1)
    ax.set_title("Per-class IoU vs ground truth")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return True


def plot_examples(examples: Sequence[dict[str, Any]], classes: "ClassSet", ignore_label: int, path: Path) -> bool:
    """Strip of example frames: RGB, GT, input segmentation, CSS labels, expectation, variance (one row each)."""
    if not examples:
        return False
    plt = _plt()
    cols = ("rgb", "gt", "input", "css", "expectation", "variance")
    titles = ("RGB", "ground truth", "input segmentation", "CSS labels", "expectation E", "variance Var")
    fig, axes = plt.subplots(len(examples), len(cols), figsize=(2.6 * len(cols), 2.1 * len(examples)),
                             squeeze=False)
    # colour scale of the variance: 99th percentile over the examples (a few background pixels dominate the max)
    var_max = max(float(np.nanpercentile(e["variance"], 99)) for e in examples) or 1.0
    for r, ex in enumerate(examples):
        row = axes[r]
        for ax, key, title in zip(row, cols, titles):
            img = ex.get(key)
            ax.set_xticks([])
            ax.set_yticks([])
            if img is None:
                ax.text(0.5, 0.5, "n/a", ha="center", va="center", transform=ax.transAxes)
            elif key in ("gt", "input", "css"):
                ax.imshow(classes.colorize(img, ignore_label), interpolation="nearest")
            elif key == "expectation":
                ax.imshow(img, cmap="viridis", vmin=0.0, vmax=1.0, interpolation="nearest")
            elif key == "variance":
                ax.imshow(img, cmap="magma", vmin=0.0, vmax=var_max, interpolation="nearest")
            else:
                ax.imshow(img, interpolation="nearest")
            if key == cols[0]:
                ax.set_ylabel(f"frame {ex['index']}", fontsize=8)
            if r == 0:
                ax.set_title(title, fontsize=9)
    fig.subplots_adjust(left=0.03, right=0.995, bottom=0.01, top=1 - 0.35 / (2.1 * len(examples)),
                        wspace=0.04, hspace=0.06)
    fig.savefig(path, dpi=90)
    plt.close(fig)
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
    if plot_iou_bars(seg.get("input"), seg.get("css"), out / "per_class_iou.png"):
        plots.append(("Per-class IoU", "per_class_iou.png"))
    if plot_examples(examples, classes, ignore_label, out / "examples.png"):
        plots.append(("Example frames", "examples.png"))
    return plots


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
        f"- time: {t['total_s']:.1f} s total (fusion {_f(t.get('fuse_fps'), '.1f')} frames/s, "
        f"evaluation {_f(t.get('evaluate_fps'), '.1f')} frames/s); " + _compile_note(t),
        *_out_of_range_lines(f.get("out_of_range_labels")),
        "",
        "CSS metrics are computed after all training frames are fused: every frame's pose is rendered with the "
        "final map (the paper's protocol). Pixels whose ground truth is the ignore label are excluded; a "
        "'no label' prediction counts as wrong. mIoU averages the classes present in the ground truth or the "
        "prediction.",
        "",
        "## Segmentation (smoothing effect)",
        "",
    ]
    if seg.get("input") and seg.get("css"):
        lines += ["| method | mIoU (%) | accuracy (%) |", "|---|---|---|",
                  f"| input segmentation | {_pct(seg['input']['miou'])} | {_pct(seg['input']['pixel_accuracy'])} |",
                  f"| CSS (fused map) | {_pct(seg['css']['miou'])} | {_pct(seg['css']['pixel_accuracy'])} |"]
        for key, label in (("css_online", "CSS online (per-frame renders in the output bag)"),
                           ("css_trained_frames", "CSS, fused frames only"),
                           ("css_heldout_frames", "CSS, held-out frames only")):
            if seg.get(key):
                lines.append(f"| {label} | {_pct(seg[key]['miou'])} | {_pct(seg[key]['pixel_accuracy'])} |")
    else:
        lines.append("No ground-truth segmentation in the bag: segmentation metrics skipped.")
    lines += ["", "## Uncertainty", ""]
    px = metrics.get("pixel_sparsification")
    if px:
        lines += [f"Pixel-level sparsification over {px['num_samples']} pixels"
                  + (f" (uniform subsample of {px['pixels_total']})" if px.get("subsampled") else "")
                  + ". AUSE = area between the curve and the oracle's (lower is better):", "",
                  "| signal | AUSE |", "|---|---|"]
        lines += [f"| {k} | {_f(v)} |" for k, v in px["ause"].items() if k != "oracle"]
    il = metrics["image_level"]
    if il.get("spearman"):
        sp = il["sparsification"]["ause"]
        lines += ["", f"Image level ({il['num_evaluated']} frames, error = 1 - accuracy):", "",
                  "| signal | Spearman rho vs error | AUSE |", "|---|---|---|"]
        for k in ("u_var", "u_exp"):
            lines.append(f"| {k} | {_f(il['spearman'].get(k), '+.3f')} | {_f(sp.get(k))} |")
        lines.append(f"| random | | {_f(sp.get('random'))} |")
    for title, fname in plots:
        lines += ["", f"## {title}", "", f"![{title}]({fname})"]
    lines += ["", "Raw numbers: `metrics.json`. Output bag: `bag/` (if written). Map: `map.npz`; "
              "splats for 3DGS viewers: `map_semantic.ply` (class colours), `map_uncertainty_variance.ply` (variance "
              "colour map, colour bar in `map_uncertainty_variance_colorbar.png`).", ""]
    path = out / "report.md"
    path.write_text("\n".join(lines))
    return path
