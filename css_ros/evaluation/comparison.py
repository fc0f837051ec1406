"""report.md's side-by-side table of the paper's update and the sensor model, fused on the same frames in one run."""
from __future__ import annotations

from typing import Any, Callable

#: (row label, getter of the value from a metrics-like dict, higher is better, percent)
_Row = tuple[str, Callable[[dict[str, Any]], "float | None"], bool, bool]


def _get(*keys: str) -> Callable[[dict[str, Any]], float | None]:
    def get(d: dict[str, Any]) -> float | None:
        for k in keys:
            if not isinstance(d, dict):
                return None
            d = d.get(k)  # type: ignore[assignment]
        return d if isinstance(d, (int, float)) else None
    return get


ROWS: list[_Row] = [
    ("online pixel accuracy (the per-frame `~/semantic`), %", _get("segmentation", "online", "pixel_accuracy"),
     True, True),
    ("fused pixel accuracy (every pose rendered with the final map), %", _get("segmentation", "fused",
                                                                              "pixel_accuracy"), True, True),
    ("online mIoU, %", _get("segmentation", "online", "miou"), True, True),
    ("fused mIoU, %", _get("segmentation", "fused", "miou"), True, True),
    ("pixel AUSE of E (fused renders)", _get("pixel_sparsification", "ause", "expectation"), False, False),
    ("pixel AUSE of Var", _get("pixel_sparsification", "ause", "variance"), False, False),
    ("pixel AUSE of the observation count (-evidence)", _get("pixel_sparsification", "ause", "evidence"), False,
     False),
    ("pixel AUSE of the calibrated confidence", _get("pixel_sparsification", "ause", "confidence"), False, False),
    ("pixel AUSE of a random ordering (reference)", _get("pixel_sparsification", "ause", "random"), False, False),
    ("ECE of E, online renders", _get("calibration", "online", "expectation", "ece"), False, False),
    ("ECE of E, fused renders", _get("calibration", "fused", "expectation", "ece"), False, False),
    ("ECE of the calibrated `~/confidence`, online renders", _get("calibration", "online", "confidence", "ece"),
     False, False),
    ("ECE of the calibrated `~/confidence`, fused renders", _get("calibration", "fused", "confidence", "ece"),
     False, False),
]


def sensor_model_view(metrics: dict[str, Any]) -> dict[str, Any]:
    """The main map's numbers in the layout of ``metrics['paper_update']`` (online / fused segmentation,
    sparsification, calibration)."""
    seg = metrics.get("segmentation") or {}
    return {"segmentation": {"online": seg.get("css_online"), "fused": seg.get("css")},
            "pixel_sparsification": metrics.get("pixel_sparsification"),
            "calibration": metrics.get("calibration")}


def _cell(v: float | None, percent: bool, bold: bool) -> str:
    if v is None:
        return "—"
    text = f"{100 * v:.1f}" if percent else f"{v:.4f}"
    return f"**{text}**" if bold else text


def comparison_rows(metrics: dict[str, Any]) -> list[str]:
    """Markdown lines of the comparison (empty without ``metrics['paper_update']``): one row per measure, columns
    input segmentation / paper update / sensor model; the better of the two updates in bold (where the difference
    shows at the printed precision; the random-ordering row is a reference, never bold)."""
    paper = metrics.get("paper_update")
    if not paper:
        return []
    seg = metrics.get("segmentation") or {}
    inp = {"segmentation": {"online": seg.get("input")}}
    ours = sensor_model_view(metrics)
    lines = ["| measure | input segmentation | paper update | sensor model |", "|---|---|---|---|"]
    for label, get, higher, percent in ROWS:
        a, b = get(paper), get(ours)
        if a is None and b is None:
            continue
        fmt = (lambda v: round(100 * v, 1)) if percent else (lambda v: round(v, 4))
        best_a = best_b = False
        if a is not None and b is not None and fmt(a) != fmt(b) and "random" not in label:
            better_b = (b > a) if higher else (b < a)
            best_a, best_b = not better_b, better_b
        lines.append(f"| {label} | {_cell(get(inp), percent, False)} | {_cell(a, percent, best_a)} | "
                     f"{_cell(b, percent, best_b)} |")
    return lines
