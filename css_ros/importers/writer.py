"""Write an imported dataset in the layout css_replay and css_demo read::

    OUT/model.ply      the splat model (copied, or a symbolic link with ``link_model``)
    OUT/classes.yaml   the class file (copied after validation, or anonymous classes)
    OUT/bag/           rosbag2 MCAP with the demo bag's topics (BAG_TOPICS but depth and gt_changed)

OUT is complete or untouched: everything is written into a temporary folder beside OUT
(``.<OUT name>.css_import-*``) and moved into OUT by renames at the end; a failure (full disk, a bad
label file, SIGINT/SIGTERM) removes the temporary folder and leaves an earlier import in OUT as it was.

Every frame i gets the stamp ``BAG_START_NS + round(i * 1e9 / rate_hz)`` on all its messages; frame ids
are the demo's (``camera_optical`` for images and camera_info, ``map`` for the pose).
"""
from __future__ import annotations

import os
import shutil
import signal
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..engine.classes import ClassSet
from ..errors import BagError, CssError
from ..io.bag import BagWriter
from ..io.params_file import PARAMS_FILE_NAME, write_params_file
from ..io.topics import BAG_CAMERA_FRAME, BAG_MAP_FRAME, BAG_START_NS, BAG_TOPICS, POSE_SOURCES, TF_TOPIC
from .labels import LabelDecoder, read_confidence, read_rgb
from .pairing import ImportFrame
from .views import ImportFormatError, PosedView

#: What an import writes into OUT (each is replaced as a whole by a rename).
OUTPUTS = ("bag", "model.ply", "classes.yaml", PARAMS_FILE_NAME)


@dataclass
class ImportSummary:
    """What was written: frame count, label statistics and the output paths."""

    frames: int
    labelled_pixels: int
    out_of_range_pixels: int
    unknown_color_pixels: int
    segmentation_encoding: str
    bag: Path
    model: Path
    classes: Path


def stamps_ns(n: int, rate_hz: float) -> np.ndarray:
    """(n,) int64 stamps [ns]: frame i at ``BAG_START_NS + round(i * 1e9 / rate_hz)``."""
    if not (np.isfinite(rate_hz) and rate_hz > 0):
        raise ImportFormatError(f"--rate must be > 0 Hz, got {rate_hz}")
    return BAG_START_NS + np.rint(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def write_dataset(out: str | Path, frames: Sequence[ImportFrame], model: str | Path, classes: ClassSet,
                  classes_file: str | Path | None, decoder: LabelDecoder, rate_hz: float = 10.0,
                  ignore_label: int = 255, link_model: bool = False,
                  progress: Callable[[int], None] | None = None,
                  node_params: dict | None = None, poses_on: str = "topic") -> ImportSummary:
    """Write OUT/model.ply, OUT/classes.yaml and OUT/bag (see the module docstring).

    Args:
        out: output folder (created; model.ply, classes.yaml and bag/ in it are replaced).
        frames: frames in output order.
        model: INRIA 3DGS PLY in the frame and scale of the poses.
        classes: the class set (C classes); ``classes_file`` is copied verbatim when given, else
            ``classes`` is written.
        decoder: turns label/GT PNGs into ids (colour mapping, remap).
        rate_hz: frame rate of the stamps [Hz].
        ignore_label: "no label" id (not counted as out of range).
        link_model: symlink the model instead of copying it.
        progress: called with 1 after each frame.
        node_params: css_node parameters (e.g. ``splat_to_map``) written to ``OUT/css_node.yaml``.
        poses_on: "topic" (a geometry_msgs/PoseStamped on ``/pose`` per frame) or "tf" (the camera's pose as the
            transform map -> camera_optical on ``/tf`` at each frame's stamp, as a TF robot records it).

    Raises:
        ImportFormatError: an image whose size differs from its camera, ids that do not fit the encoding.
    """
    out = Path(out)
    model = Path(model)
    if poses_on not in POSE_SOURCES:
        raise ImportFormatError(f"poses_on must be one of {', '.join(POSE_SOURCES)}, got {poses_on!r}")
    if not model.is_file():
        raise ImportFormatError(f"model not found: {model}")
    if out.exists() and not out.is_dir():
        raise ImportFormatError(f"--out {out} exists and is not a folder")
    try:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.css_import-", dir=out.parent))
        umask = os.umask(0o022)
        os.umask(umask)
        tmp.chmod(0o777 & ~umask)  # mkdtemp's 0700 would become OUT's mode
    except OSError as exc:
        raise CssError(f"cannot create the output folder beside {out}: {exc.strerror or exc}") from None
    try:
        summary = _write_into(tmp, out, frames, model, classes, classes_file, decoder, rate_hz, ignore_label,
                              link_model, progress, node_params, poses_on)
        # No SIGINT/SIGTERM between the renames: OUT never holds a mix of the old and the new import.
        blocked = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})
        try:
            _move_into(tmp, out)
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, blocked)
    except (OSError, BagError) as exc:
        detail = exc.strerror or str(exc) if isinstance(exc, OSError) else str(exc)
        if isinstance(exc, OSError) and exc.filename2:  # shutil's copy errors name the source first
            detail += f" (while copying {exc.filename})"
        raise CssError(f"writing the import into {out} failed: {detail}; {out} was left as it was") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return summary


def _move_into(tmp: Path, out: Path) -> None:
    """Move the finished outputs from ``tmp`` into ``out`` by renames (same file system: no copying)."""
    if not out.exists():
        os.rename(tmp, out)
        return
    old = tmp / ".replaced"
    old.mkdir()
    for name in OUTPUTS:
        new = tmp / name
        if not (new.exists() or new.is_symlink()):
            continue  # e.g. the model already lies in OUT
        target = out / name
        if target.exists() or target.is_symlink():
            os.rename(target, old / name)
        os.rename(new, target)


def _write_into(tmp: Path, out: Path, frames: Sequence[ImportFrame], model: Path, classes: ClassSet,
                classes_file: str | Path | None, decoder: LabelDecoder, rate_hz: float, ignore_label: int,
                link_model: bool, progress: Callable[[int], None] | None,
                node_params: dict | None = None, poses_on: str = "topic") -> ImportSummary:
    """Write the import into the empty folder ``tmp``; the summary names the final paths in ``out``."""
    C = classes.num_classes
    wide = C > 255 or ignore_label > 255
    enc, dtype, limit = ("mono16", np.uint16, 65535) if wide else ("mono8", np.uint8, 255)
    stamps = stamps_ns(len(frames), rate_hz)
    labelled = out_of_range = 0
    with BagWriter(tmp / "bag") as bag:
        bag.set_custom_data("generator", "css_import")
        for f, stamp in zip(frames, stamps):
            v, s = f.view, int(stamp)
            seg = _ids(decoder.read(f.labels), v, f.labels, limit, dtype)
            valid = seg != ignore_label
            labelled += int(valid.sum())
            out_of_range += int((valid & (seg >= C)).sum())
            bag.write_camera_info(BAG_TOPICS["camera_info"], v.K, v.width, v.height, s, BAG_CAMERA_FRAME)
            if poses_on == "tf":
                bag.write_tf(TF_TOPIC, s, [(BAG_MAP_FRAME, BAG_CAMERA_FRAME, s, v.position, v.quaternion_xyzw)])
            else:
                bag.write_pose(BAG_TOPICS["pose"], v.position, v.quaternion_xyzw, s, BAG_MAP_FRAME)
            if f.image is not None:
                bag.write_image(BAG_TOPICS["image"], _sized(read_rgb(f.image), v, f.image), "rgb8", s, BAG_CAMERA_FRAME)
            bag.write_image(BAG_TOPICS["segmentation"], seg, enc, s, BAG_CAMERA_FRAME)
            if f.confidence is not None:
                conf = _sized(read_confidence(f.confidence), v, f.confidence)
                bag.write_image(BAG_TOPICS["confidence"], conf, "32FC1", s, BAG_CAMERA_FRAME)
            if f.gt is not None:
                bag.write_image(BAG_TOPICS["gt"], _ids(decoder.read(f.gt), v, f.gt, limit, dtype), enc, s,
                                BAG_CAMERA_FRAME)
            if progress is not None:
                progress(1)
    model_out = out / "model.ply"
    if model.resolve() != model_out.resolve():
        if link_model:
            os.symlink(model.resolve(), tmp / "model.ply")
        else:
            shutil.copyfile(model, tmp / "model.ply")
    classes_out = out / "classes.yaml"
    if classes_file is not None and Path(classes_file).resolve() != classes_out.resolve():
        shutil.copyfile(classes_file, tmp / "classes.yaml")
    elif classes_file is None:
        classes.to_yaml(tmp / "classes.yaml")
    if node_params:
        write_params_file(tmp / PARAMS_FILE_NAME, node_params,
                          comment="css_import: the node parameters of this import (css_replay reads this file)")
    for name in OUTPUTS:  # on disk before the renames make them visible
        if (tmp / name).is_file() and not (tmp / name).is_symlink():
            with open(tmp / name, "rb") as fh:
                os.fsync(fh.fileno())
    return ImportSummary(frames=len(frames), labelled_pixels=labelled, out_of_range_pixels=out_of_range,
                         unknown_color_pixels=decoder.unknown_color_pixels, segmentation_encoding=enc,
                         bag=out / "bag", model=model_out, classes=classes_out)


def _sized(arr: np.ndarray, view: PosedView, path: Path) -> np.ndarray:
    """``arr`` unchanged if its (H, W) equals the camera's, else ImportFormatError."""
    if arr.shape[:2] != (view.height, view.width):
        raise ImportFormatError(f"{path}: image is {arr.shape[1]}x{arr.shape[0]} but camera {view.name} is "
                                f"{view.width}x{view.height} (images must have the calibrated size)")
    return arr


def _ids(ids: np.ndarray, view: PosedView, path: Path, limit: int, dtype: type) -> np.ndarray:
    """(H, W) ids checked against the camera size and the encoding's largest value, as ``dtype``."""
    ids = _sized(ids, view, path)
    if ids.size and int(ids.max()) > limit:
        raise ImportFormatError(f"{path}: label id {int(ids.max())} does not fit the {limit + 1}-value label "
                                "encoding of this class file (use a remap file)")
    return ids.astype(dtype)
