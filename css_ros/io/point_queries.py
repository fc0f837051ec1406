"""Point queries over topics, ROS-free: the request cloud (x y z) in, the answer cloud's columns out.

A request is a PointCloud2 with float fields ``x y z`` (map frame, metres); its header stamp is the
request id and is echoed by the answer. The answer holds, per requested point and in request order,
``x y z label expectation variance`` and then one float32 field per class holding E of that class
(SPEC §9), named after the class (:func:`class_field_names`).
"""
from __future__ import annotations

import re
from typing import Any, Sequence

import numpy as np

from .clouds import unpack_cloud

#: Fields of an answer before the per-class ones.
ANSWER_FIELDS = ("x", "y", "z", "label", "expectation", "variance")


def class_field_names(class_names: Sequence[str]) -> list[str]:
    """PointField names of the per-class columns: the class name in lower case with every run of
    characters other than letters, digits and '_' replaced by '_'; a name that is empty, starts with a
    digit, repeats an earlier one or clashes with :data:`ANSWER_FIELDS` gets the prefix ``class<id>_``."""
    out: list[str] = []
    for i, name in enumerate(class_names):
        field = re.sub(r"[^0-9a-zA-Z_]+", "_", str(name).strip()).strip("_").lower()
        if not field or field[0].isdigit() or field in out or field in ANSWER_FIELDS:
            field = f"class{i}_{field}".rstrip("_")
        out.append(field)
    return out


def request_points(msg: Any) -> np.ndarray:
    """(M, 3) float64 query points [m, map frame] of a request cloud (rows may be non-finite: the caller
    answers those as unknown).

    Raises:
        InputError: fields x, y, z missing or unreadable, or truncated data.
    """
    pts = unpack_cloud(msg, ("x", "y", "z"))
    return np.stack([pts["x"], pts["y"], pts["z"]], axis=1).astype(np.float64).reshape(-1, 3)


def answer_columns(xyz: np.ndarray, labels: np.ndarray, expectation: np.ndarray, variance: np.ndarray,
                   class_names: Sequence[str]) -> dict[str, np.ndarray]:
    """Columns of the answer cloud.

    Args:
        xyz: (M, 3) query points [m]; labels: (M,) label of each point (ignore label = unknown);
        expectation, variance: (M, C) E and Var of every class at each point (SPEC §9). The answer's
        ``expectation``/``variance`` are those of the argmax class, also where the label is unknown
        (as the render's E and Var images).
    """
    m = len(xyz)
    lab = np.asarray(labels).reshape(m)
    top = np.argmax(expectation, axis=1)  # the label before the unknown test, as the render's E/Var images
    rows = np.arange(m)
    e_top, v_top = expectation[rows, top], variance[rows, top]
    cols: dict[str, np.ndarray] = {
        "x": xyz[:, 0].astype(np.float32), "y": xyz[:, 1].astype(np.float32), "z": xyz[:, 2].astype(np.float32),
        "label": lab.astype(np.uint16),
        "expectation": e_top.astype(np.float32),
        "variance": v_top.astype(np.float32),
    }
    for c, name in enumerate(class_field_names(class_names)):
        cols[name] = expectation[:, c].astype(np.float32)
    return cols
