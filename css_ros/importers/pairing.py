"""Pair posed views with their label / GT / confidence / colour image files (matched by file stem)."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from .labels import CONFIDENCE_EXTENSIONS, IMAGE_EXTENSIONS, LABEL_EXTENSIONS, index_folder
from .views import ImportFormatError, PosedView


@dataclass(frozen=True)
class ImportFrame:
    """One frame to write: the view and its files (None = not given for this dataset)."""

    view: PosedView
    labels: Path
    gt: Path | None = None
    confidence: Path | None = None
    image: Path | None = None


@dataclass(frozen=True)
class Pairing:
    """Frames with a label file, and the image names of views that have none (left out)."""

    frames: list[ImportFrame]
    without_labels: list[str]


def pair_frames(views: Sequence[PosedView], labels: str | Path, gt: str | Path | None = None,
                confidence: str | Path | None = None, images: str | Path | None = None) -> Pairing:
    """Frames of the views that have a label PNG; optional folders must hold a file for each such frame.

    Raises:
        ImportFormatError: a folder is missing, no view has a label file, or a frame with labels lacks
            its GT / confidence / image file (a partial GT would bias the evaluation silently).
    """
    label_files = index_folder(labels, LABEL_EXTENSIONS, "label")
    optional = {
        "gt": index_folder(gt, LABEL_EXTENSIONS, "ground-truth") if gt else None,
        "confidence": index_folder(confidence, CONFIDENCE_EXTENSIONS, "confidence") if confidence else None,
        "image": index_folder(images, IMAGE_EXTENSIONS, "image") if images else None,
    }
    frames, without = [], []
    for v in views:
        lab = label_files.get(v.stem)
        if lab is None:
            without.append(v.name)
            continue
        extra = {}
        for kind, files in optional.items():
            if files is None:
                continue
            if v.stem not in files:
                raise ImportFormatError(f"no {kind} file for image {v.name} (looked for {v.stem}.* in the "
                                        f"{kind} folder)")
            extra[kind] = files[v.stem]
        frames.append(ImportFrame(view=v, labels=lab, **extra))
    if not frames:
        some = ", ".join(v.stem for v in list(views)[:3])
        raise ImportFormatError(f"no label PNG in {labels} matches an image of the pose file (stems such as {some})")
    return Pairing(frames, without)
