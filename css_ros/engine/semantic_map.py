"""The CSS semantic map: Dirichlet concentrations per Gaussian, closed-form update (SPEC §4),
probabilistic rendering (SPEC §5), image-level uncertainty (SPEC §6) and atomic persistence."""
from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable, Literal, Mapping, Sequence

import numpy as np

from ..errors import MapError, SensorModelError
from .atomic import atomic_file
from .backends import make_backend
from .final_form import RenderSettings, check_outputs
from .label_input import FrameLabels, check_frame_labels
from .sensor_model import NO_SENSOR_MODEL
from .field3d import FieldIndex, FieldQuery, GaussianSemantics, gaussian_semantics, query_field
from .spec import (DEFAULT_BACKGROUND, DEFAULT_IGNORE_LABEL, DEFAULT_MIN_EVIDENCE, DEFAULT_PRIOR,
                   DEFAULT_QUERY_BACKGROUND_WEIGHT, DEFAULT_UNKNOWN_THRESHOLD)
from .spec import MAX_FRAMES
from . import map_args, view_args
from .map_args import MAX_CLASSES, MAX_CONCENTRATION, MIN_CONCENTRATION

if TYPE_CHECKING:
    from .camera import Camera
    from .gaussians import GaussianModel
    from .info_gain import SelectedViews
    from .final_form import FrameImages
    from .raster_backend import UpdateCounts
    from .sensor_model import SensorModel, SoftLabels

MAP_FORMAT_VERSION = 1
#: npz members of a map file: name -> (dtype kinds accepted, shape; "G"/"C" = Gaussians / classes).
_MAP_MEMBERS: dict[str, tuple[str, tuple[Any, ...]]] = {
    "format_version": ("iu", ()),
    "concentrations": ("f", ("G", "C")),
    "prior": ("f", ()),
    "background": ("f", ()),
    "num_classes": ("iu", ()),
    "num_gaussians": ("iu", ()),
    "model_fingerprint": ("U", ()),
    "frames_observed": ("iu", ()),
    "sources": ("U", ("S",)),
    "sensor_model": ("U", ()),
    # evidence exchange (css_node, docs/maps.md): the origin id of the map's own evidence and, per received source,
    # its id, (epoch, last sequence number, frames, in step) and its evidence as sparse rows (counts per source)
    "evidence_origin": ("U", ()),
    "evidence_epoch": ("u", ()),
    "received_sources": ("U", ("S",)),
    "received_state": ("u", ("S", 4)),
    "received_counts": ("iu", ("S",)),
    "received_rows": ("iu", ("R",)),
    "received_evidence": ("f", ("R", "C")),
}
_OPTIONAL_MEMBERS = ("frames_observed", "sources", "sensor_model", "evidence_origin", "evidence_epoch",
                     "received_sources", "received_state", "received_counts", "received_rows", "received_evidence")
_RECEIVED_MEMBERS = ("received_sources", "received_state", "received_counts", "received_rows", "received_evidence")
#: Most contributing sources a map file may list (origin ids of the nodes whose evidence it holds).
MAX_SOURCES = 4096
#: Most received sources whose evidence a map file keeps apart (each becomes an (N, C) float64 array when loaded).
MAX_RECEIVED_SOURCES = 64


#: Largest byte size of a scalar member of a map file (the fingerprint string is 64 characters of 4 bytes).
_MAX_SCALAR_BYTES = 4096


def _read_npy_header(zf: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path, name: str) -> tuple[tuple, np.dtype, int]:
    """(shape, dtype, header length [bytes]) of one npy member (only its first bytes are inflated)."""
    from numpy.lib import format as npformat

    with zf.open(info) as fh:
        version = npformat.read_magic(fh)
        if version == (1, 0):
            dshape, _fortran, dtype = npformat.read_array_header_1_0(fh)
        elif version in ((2, 0), (3, 0)):
            dshape, _fortran, dtype = npformat.read_array_header_2_0(fh)
        else:
            raise MapError(f"map file {path}: {name} has npy format version {version}")
        return dshape, dtype, fh.tell()


def _check_map_headers(path: Path, model: "GaussianModel | int", num_classes: int | None = None) -> None:
    """Check every member's declared dtype, shape and size from the npy headers, and the file's own
    model fingerprint and class count, before reading any large data.

    Refuses (MapError naming ``path``) a file that is not a zip, lacks members, declares other dtypes
    (complex, bool, object, ...) or shapes, whose members hold another number of bytes than their
    headers declare, or whose scalars are larger than :data:`_MAX_SCALAR_BYTES`; a map of another model
    ("this map belongs to model <fingerprint>, not <model file>"); concentrations whose declared shape
    is not (the model's N, the file's own ``num_classes``) (a decompression bomb or a header declaring a
    huge array is refused here, without the caller passing C); with ``num_classes`` given, a map of
    another class count. A corrupt compressed stream is a MapError too. ``model`` may be just its number of
    Gaussians (css_map reading a map without its model: no fingerprint check).
    """
    if not zipfile.is_zipfile(path):
        raise MapError(f"map file {path} is not an .npz archive")
    try:
        with zipfile.ZipFile(path) as zf:
            infos = {i.filename[:-4]: i for i in zf.infolist() if i.filename.endswith(".npy")}
            missing = [k for k in _MAP_MEMBERS if k not in infos and k not in _OPTIONAL_MEMBERS]
            if missing:
                raise MapError(f"map file {path} lacks {', '.join(missing)}")
            shapes: dict[str, tuple] = {}
            for name, (kinds, shape) in _MAP_MEMBERS.items():
                info = infos.get(name)
                if info is None:
                    continue
                dshape, dtype, header_len = _read_npy_header(zf, info, path, name)
                if dtype.kind not in kinds or dtype.hasobject:
                    raise MapError(f"map file {path}: {name} has dtype {dtype}, expected kind {kinds}")
                if len(dshape) != len(shape):
                    raise MapError(f"map file {path}: {name} has shape {dshape}, expected {len(shape)} dimension(s)")
                declared = int(np.prod(dshape, dtype=np.int64)) * dtype.itemsize + header_len
                if info.file_size != declared:
                    raise MapError(f"map file {path}: {name} holds {info.file_size} bytes, its header declares "
                                   f"{declared}")
                if shape == ("S",) and dshape[0] > MAX_SOURCES:
                    raise MapError(f"map file {path} lists {dshape[0]} sources, at most {MAX_SOURCES}")
                if not shape and declared > _MAX_SCALAR_BYTES:
                    raise MapError(f"map file {path}: {name} is a scalar of {declared} bytes")
                shapes[name] = dshape
            # The scalars are a few bytes each (checked above): read them before the concentrations.
            with np.load(path, allow_pickle=False) as data:
                file_gaussians = int(data["num_gaussians"])
                fingerprint = str(data["model_fingerprint"])
                file_classes = int(data["num_classes"])
    except MapError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, RuntimeError, zlib.error) as exc:
        raise MapError(f"cannot read map file {path}: {exc}") from exc
    n_model = model if isinstance(model, int) else model.num_gaussians
    if isinstance(model, int):
        if file_gaussians != n_model:
            raise MapError(f"map file {path}: {file_gaussians} Gaussians declared, {n_model} expected")
    elif fingerprint != model.fingerprint or file_gaussians != model.num_gaussians:
        source = getattr(model, "source", None) or "the given model"
        raise MapError(f"map file {path}: this map belongs to model {fingerprint[:16]}, not {source} (model "
                       f"{model.fingerprint[:16]}; {file_gaussians} vs {model.num_gaussians} Gaussians)")
    if not 1 <= file_classes <= MAX_CLASSES:
        raise MapError(f"map file {path}: num_classes={file_classes} outside 1..{MAX_CLASSES}")
    dshape = shapes["concentrations"]
    if tuple(dshape) != (n_model, file_classes):
        raise MapError(f"map file {path}: concentrations have shape {dshape}, the file's own num_classes and "
                       f"the model give ({n_model}, {file_classes})")
    if num_classes is not None and file_classes != num_classes:
        raise MapError(f"map file {path} has {file_classes} classes, expected {num_classes}")
    present = [k for k in _RECEIVED_MEMBERS if k in shapes]
    if present and len(present) != len(_RECEIVED_MEMBERS):
        raise MapError(f"map file {path} has {', '.join(present)} but not all of {', '.join(_RECEIVED_MEMBERS)}")
    if present:
        s, r = shapes["received_sources"][0], shapes["received_rows"][0]
        if s > MAX_RECEIVED_SOURCES:
            raise MapError(f"map file {path} keeps the evidence of {s} received sources, at most {MAX_RECEIVED_SOURCES}")
        if (tuple(shapes["received_state"]) != (s, 4) or tuple(shapes["received_counts"]) != (s,)
                or tuple(shapes["received_evidence"]) != (r, file_classes) or r > s * n_model):
            raise MapError(f"map file {path}: received evidence of inconsistent shapes (sources {s}, state "
                           f"{shapes['received_state']}, counts {shapes['received_counts']}, rows {r}, evidence "
                           f"{shapes['received_evidence']}; at most {n_model} rows per source)")

def _received_sources(path: Path, members: dict[str, np.ndarray], conc: np.ndarray,
                      prior: float) -> dict[str, SourceEvidence]:
    """The received sources of a map file (``received_*`` members, shapes checked by :func:`_check_map_headers`):
    ids of 1..32 ASCII characters, each once; rows strictly increasing per source; evidence finite, >= 0, and in
    total at most what the concentrations hold above the prior, up to the rounding of float64 sums: 1e-9 of α per
    Gaussian and class. css_node keeps that by construction (css_ros/io/evidence.py: α is recomputed as
    α_0 + own + Σ sources on every row a snapshot changes; deltas and frames only add, each rounding by at most
    half an ulp of α). An old file without them: none."""
    if not members:
        return {}
    names, state, counts = members["received_sources"], members["received_state"], members["received_counts"]
    rows, values = members["received_rows"].astype(np.int64), members["received_evidence"].astype(np.float64)
    n, c = conc.shape
    ids = [str(v) for v in names]
    if len(set(ids)) != len(ids) or not all(0 < len(i) <= 32 and i.isascii() for i in ids):
        raise MapError(f"map file {path}: received source ids must be distinct, 1..32 ASCII characters")
    if np.any(counts < 0) or int(counts.sum()) != rows.size:
        raise MapError(f"map file {path}: received_counts do not add up to the {rows.size} received rows")
    if not np.all(np.isfinite(values)) or np.any(values < 0) or np.any(values > MAX_CONCENTRATION):
        raise MapError(f"map file {path}: received evidence must be finite and in [0, {MAX_CONCENTRATION:g}]")
    out: dict[str, SourceEvidence] = {}
    total = np.zeros((n, c))
    start = 0
    for k, name in enumerate(ids):
        r = rows[start:start + int(counts[k])]
        if r.size and (np.any(np.diff(r) <= 0) or r[0] < 0 or r[-1] >= n):
            raise MapError(f"map file {path}: rows of received source {name!r} not increasing within 0..{n - 1}")
        ev = np.zeros((n, c))
        ev[r] = values[start:start + r.size]
        total += ev
        epoch, seq, frames, in_step = (int(v) for v in state[k])
        if frames > MAX_FRAMES:
            raise MapError(f"map file {path}: received source {name!r} claims {frames} frames (> {MAX_FRAMES})")
        out[name] = SourceEvidence(ev, epoch, seq, frames, bool(in_step))
        start += r.size
    if np.any(total > (conc - prior) + 1e-9 * conc):   # 1e-9 α: rounding only (see the docstring)
        raise MapError(f"map file {path}: the received evidence exceeds what the concentrations hold")
    return out


def _update_name(fingerprint: str) -> str:
    """How logs name the update a map was fused with."""
    return f"sensor model {fingerprint[:12]}" if fingerprint else "the paper's update (no sensor model)"


BackendName = Literal["numba", "torch", "cuda"]


@dataclass
class RenderedView:
    """Everything rendered for one camera view (H, W = the camera's image size).

    The image fields hold numpy arrays in their final dtypes, made by the backend (on the GPU for backend cuda)
    and copied to the host once per view. An image not asked for (``outputs`` of :meth:`SemanticMap.observe` /
    :meth:`SemanticMap.render`) is None and costs no copy; u_var and u_exp are always there. The arrays belong
    to the view: later frames never change them.

    Attributes:
        labels: (H, W) int32 argmax class per pixel; ``ignore_label`` where the background weight
            kappa_b exceeds ``unknown_threshold``.
        expectation: (H, W) float32 E_i of the argmax class (SPEC §5).
        variance: (H, W) float32 Var_i of the argmax class (SPEC §5).
        background: (H, W) float32 kappa_b, the weight of the background Dirichlet.
        evidence: (H, W) float32 kappa-weighted Dirichlet total sum_n kappa_in S_n + kappa_b S_b
            (the paper's observation-count confidence baseline; larger = more observed).
        rgb: (H, W, 3) uint8 colour render.
        u_var: geometric mean of the variance image (SPEC §6).
        u_exp: one minus the mean of the expectation image (SPEC §6).
        probabilities: (H, W, C) float32 full per-class E_i^c, only when requested.
        depth: (H, W) float32 expected depth sum_n kappa_in z_n / sum_n kappa_in of the rendered Gaussians
            (camera z, metres: splat units times the map's ``depth_scale``); NaN where nothing is rendered.
        confidence: (H, W) float32 calibrated probability that ``labels`` is right (the sensor model's
            :class:`~css_ros.engine.sensor_model.ConfidenceMap` of E and evidence; 0 where the label is
            ``ignore_label``), or None when the map has no calibrated confidence.
    """

    labels: np.ndarray
    expectation: np.ndarray
    variance: np.ndarray
    background: np.ndarray
    evidence: np.ndarray
    rgb: np.ndarray
    u_var: float
    u_exp: float
    probabilities: np.ndarray | None = None
    depth: np.ndarray | None = None
    confidence: np.ndarray | None = None


@dataclass
class SourceEvidence:
    """The evidence of one other node (source) that a map holds (css_node's evidence exchange, docs/maps.md).

    ``evidence`` is that source's (N, C) float64 part of the concentrations; ``epoch``, ``last_seq`` and ``frames``
    are those of its last packet applied, ``in_step`` whether the next delta of that epoch can be applied. Saved
    with the map so that a resumed node knows which evidence is its own and which it received.
    """

    evidence: np.ndarray
    epoch: int = 0
    last_seq: int = 0
    frames: int = 0
    in_step: bool = False


@dataclass(frozen=True)
class UpdateStats:
    """Pixel counts of one update: used (labelled, weight > 0), ignored (ignore value or zero
    confidence), out_of_range (ids >= C or negative, treated as ignored) and, with a sensor model,
    no_depth (used pixels that no Gaussian covers: they have no rendered depth and add nothing)."""

    used: int
    ignored: int
    out_of_range: int
    no_depth: int = 0


class SemanticMap:
    """Dirichlet semantic state over the Gaussians of a pretrained splat model.

    Concentrations are float64: a long run adds many small kappa-weighted counts (often < 1e-3) to
    totals that reach 1e4 and more, which float32 would round away (its spacing at 1e4 is ~1e-3).
    The (N, C) array costs 8 N C bytes (152 MB for 1M Gaussians x 19 classes).

    Args:
        model: the pretrained splat (map frame).
        num_classes: C.
        prior: alpha_0, initial concentration of every class of every Gaussian (> 0).
        background: alpha_b, concentration per class of the background Dirichlet (> 0).
        ignore_label: label value meaning "no label" in inputs and "unknown" in rendered labels.
        unknown_threshold: rendered pixels whose background weight kappa_b exceeds this get
            ``ignore_label`` (default 0.5: the pixel is mostly empty space). Use 1.0 to never do so.
        backend: "numba" (compiled CPU kernels, default), "torch" (plain PyTorch twin) or "cuda"
            (numba-cuda kernels, concentrations kept on the GPU; docs/cuda.md).
        background_rgb: colour behind all Gaussians, RGB in [0, 1].
        device: GPU index for backend "cuda" (default: the current device).
        sensor_model: the segmenter's sensor model (docs/spec.md "Sensor model"): each labelled pixel adds
            kappa * confidence * w(y, d) * p(. | y, d) instead of kappa * confidence * onehot(y). None (default):
            the paper's update, bit for bit.
        depth_scale: metres per splat unit (the scale of ``splat_to_map``): the sensor model's depth bins
            and ``RenderedView.depth`` are in metres.
    Raises:
        MapError: an argument of the wrong type or outside its bounds (:mod:`css_ros.engine.map_args`: C in
            1..MAX_CLASSES, prior and background in (0, MAX_CONCENTRATION], the bounds a map file is loaded with).
    """

    def __init__(self, model: "GaussianModel", num_classes: int, prior: float = DEFAULT_PRIOR,
                 background: float = DEFAULT_BACKGROUND, ignore_label: int = DEFAULT_IGNORE_LABEL,
                 unknown_threshold: float = DEFAULT_UNKNOWN_THRESHOLD,
                 backend: BackendName = "numba", background_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0),
                 device: int | None = None, sensor_model: "SensorModel | None" = None,
                 depth_scale: float = 1.0) -> None:
        self.model = map_args.check_model(model)
        self.num_classes = map_args.check_num_classes(num_classes)
        self.prior = map_args.check_concentration(prior, "prior")
        self.background = map_args.check_concentration(background, "background")
        self.ignore_label = map_args.check_ignore_label(ignore_label)
        self.unknown_threshold = map_args.check_unknown_threshold(unknown_threshold)
        self.background_rgb = map_args.check_background_rgb(background_rgb)
        depth_scale = map_args.check_depth_scale(depth_scale)
        if not isinstance(backend, str):
            raise MapError(f"backend must be a name (numba, torch or cuda), got {type(backend).__name__}")
        cuda_index = isinstance(device, (int, np.integer)) and not isinstance(device, bool) and device >= 0
        if device is not None and not (backend == "cuda" and cuda_index):
            raise MapError(f"device must be None or, with backend 'cuda', a GPU index >= 0; got {device!r} with "
                           f"backend {backend!r}")
        self.backend_name = backend
        self._backend = make_backend(backend, model, **({} if device is None else {"device": int(device)}))
        self._concentrations = np.full((model.num_gaussians, self.num_classes), self.prior, dtype=np.float64)
        self.depth_scale = float(depth_scale)
        #: pixel counts of the latest update (``observe`` returns the view, this keeps its counts); None before
        self.last_update: UpdateStats | None = None
        self._sensor_model: SensorModel | None = None
        self._soft: SoftLabels | None = None
        self.frames_observed = 0
        #: fingerprint of the sensor model the evidence was fused with ("" = the paper's update); kept from the
        #: file by :meth:`load`, compared by merges (maps fused with different sensor models are not merged)
        self.fused_sensor_model = NO_SENSOR_MODEL
        self.sensor_model = sensor_model
        #: origin ids of the sources whose evidence this map holds (css_node's own and received ones), sorted
        self.sources: list[str] = []
        #: origin id under which css_node publishes this map's own evidence ("": none / not known)
        self.evidence_origin = ""
        #: epoch under which css_node published the own evidence when this map was saved (0: none / not known)
        self.evidence_epoch = 0
        #: evidence of other nodes held in ``concentrations``, per origin id (css_node's evidence ledger keeps it)
        self.received: Mapping[str, SourceEvidence] = {}
        self._field_index: FieldIndex | None = None  # SPEC §9 spatial index, built on first query

    def __repr__(self) -> str:
        """One line: size, backend, frames fused and the update's sensor model; never the arrays."""
        fp = self.sensor_fingerprint
        return (f"SemanticMap({self.model.num_gaussians} Gaussians x {self.num_classes} classes, "
                f"backend {self.backend_name}, {self.frames_observed} frames observed, prior {self.prior:g}, "
                f"{'sensor model ' + fp[:12] if fp else 'paper update'})")

    # ------------------------------------------------------------------ state
    @property
    def sensor_model(self) -> "SensorModel | None":
        """The active sensor model (None: the paper's update)."""
        return self._sensor_model

    @sensor_model.setter
    def sensor_model(self, model: "SensorModel | None") -> None:
        from .sensor_model import SensorModel

        if model is not None and not isinstance(model, SensorModel):
            raise SensorModelError(f"sensor_model must be a SensorModel (SensorModel.load(path)) or None, got "
                                   f"{type(model).__name__}")
        if model is not None and model.num_classes != self.num_classes:
            raise SensorModelError(f"{model.source or 'sensor model'} is for {model.num_classes} classes, the map "
                                   f"has {self.num_classes}")
        self._sensor_model = model
        self._soft = None if model is None else model.soft_labels(self.depth_scale)
        if self.frames_observed == 0:
            self.fused_sensor_model = self.sensor_fingerprint

    @property
    def sensor_fingerprint(self) -> str:
        """Fingerprint of the update's sensor model ("" = the paper's update), as stored in map files."""
        return NO_SENSOR_MODEL if self._sensor_model is None else self._sensor_model.fingerprint

    @property
    def concentrations(self) -> np.ndarray:
        """(N, C) float64 alpha, for writing: a backend that keeps them on a device brings this host
        array up to date first and treats it as modified afterwards (re-uploads it). Read through
        :attr:`concentrations_readonly` when not writing."""
        return self._backend.host_write(self._concentrations)

    @concentrations.setter
    def concentrations(self, value: np.ndarray) -> None:
        self._concentrations = value

    @property
    def concentrations_readonly(self) -> np.ndarray:
        """(N, C) float64 alpha, up to date, read-only (no re-upload to a device afterwards)."""
        return self._backend.host_read(self._concentrations)

    def reset(self) -> None:
        """Forget every observation: all concentrations back to the prior."""
        self.concentrations[...] = self.prior
        self.frames_observed = 0
        for src in self.received.values():   # their evidence is gone too; each must re-state it by a snapshot
            src.evidence[...] = 0.0
            src.in_step = False
        self.fused_sensor_model = self.sensor_fingerprint

    def _background_moments(self) -> tuple[float, float, float]:
        c = self.num_classes
        s_b = c * self.background
        e_b = 1.0 / c
        return e_b, e_b * (1.0 - e_b) / (1.0 + s_b), s_b

    # ------------------------------------------------------------------ inputs
    def _frame_labels(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None) -> FrameLabels:
        """The frame's labels and confidence checked (shape, dtype) and handed on as they came
        (:mod:`css_ros.engine.label_input`): the backend's compiled pass applies the label rule and counts."""
        return check_frame_labels(labels, confidence, (camera.height, camera.width), self.num_classes,
                                  self.ignore_label)

    # ------------------------------------------------------------------ engine
    def _update_frame(self, frame: Any, camera: "Camera", labels: np.ndarray,
                      confidence: np.ndarray | None) -> "UpdateCounts":
        """Update with one frame; the counts may still be on a device (:meth:`_finish_update` reads them)."""
        inputs = self._frame_labels(camera, labels, confidence)
        pending = self._backend.update(frame, inputs, self._concentrations, self._soft)
        self.frames_observed += 1
        return pending

    def _finish_update(self, pending: "UpdateCounts") -> UpdateStats:
        used, ignored, out_of_range, no_depth = pending.get()
        stats = UpdateStats(used, ignored, out_of_range, no_depth if self._soft is not None else 0)
        self.last_update = stats
        return stats

    def render_settings(self, outputs: Iterable[str] | None = None, probabilities: bool = False) -> RenderSettings:
        """What a backend needs to deliver a view's outputs in final form (:mod:`css_ros.engine.final_form`).

        Raises:
            InputError: an unknown output name."""
        e_b, v_b, s_b = self._background_moments()
        bg = self.background_rgb
        return RenderSettings(e_b, v_b, s_b, (float(bg[0]), float(bg[1]), float(bg[2])), self.unknown_threshold,
                              self.ignore_label, self.depth_scale,
                              None if self._sensor_model is None else self._sensor_model.confidence,
                              check_outputs(outputs), bool(probabilities))

    @staticmethod
    def _view(img: "FrameImages") -> RenderedView:
        return RenderedView(labels=img.labels, expectation=img.expectation, variance=img.variance,  # type: ignore[arg-type]
                            background=img.background, evidence=img.evidence, rgb=img.rgb,  # type: ignore[arg-type]
                            u_var=img.u_var, u_exp=img.u_exp, probabilities=img.probabilities, depth=img.depth,
                            confidence=img.confidence)

    # ------------------------------------------------------------------ public API
    def update(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None = None) -> UpdateStats:
        """Fuse one segmentation (SPEC §4): alpha_n^c += sum_i kappa_in y_i^c at ``camera``'s pose.

        Args:
            camera: pose (T_map_cam of the optical frame) and intrinsics of the segmented image.
            labels: (H, W) integer class ids; ``ignore_label`` and ids >= C (or < 0) add nothing.
            confidence: optional (H, W) float weights in [0, 1] (NaN counts as 0); y_i = conf_i * onehot.
        Raises:
            InputError: wrong shape or dtype (confidence: real numbers; masked arrays refused).
            CameraError: ``camera`` is not a Camera.
        """
        frame = self._backend.prepare(map_args.check_camera(camera, "update"))
        return self._finish_update(self._update_frame(frame, camera, labels, confidence))

    def observe(self, camera: "Camera", labels: np.ndarray, confidence: np.ndarray | None = None,
                probabilities: bool = False, outputs: Iterable[str] | None = None) -> RenderedView:
        """SPEC §7 per observed frame: rasterise once, update, then render at the same pose.

        ``outputs``: the images to deliver (names of :data:`css_ros.engine.final_form.IMAGE_OUTPUTS`; None = all);
        the others are None in the view and cost no copy from the device."""
        settings = self.render_settings(outputs, probabilities)
        camera = map_args.check_camera(camera, "observe")
        inputs = self._frame_labels(camera, labels, confidence)
        img, pending = self._backend.observe_view(camera, inputs, self._concentrations, self._soft, settings)
        self.frames_observed += 1
        self._finish_update(pending)  # a device backend's counts came with the view's one copy
        return self._view(img)

    def render(self, camera: "Camera", probabilities: bool = False,
               outputs: Iterable[str] | None = None) -> RenderedView:
        """Render labels, E, Var, colour and U at ``camera`` without changing the map (query view); ``outputs`` as
        in :meth:`observe`."""
        settings = self.render_settings(outputs, probabilities)
        camera = map_args.check_camera(camera, "render")
        return self._view(self._backend.render_query(camera, self._concentrations, settings))

    def score_views(self, cameras: Sequence["Camera"], importance: np.ndarray | None = None,
                    pixel_scale: float = 1.0) -> np.ndarray:
        """U_var, U_exp (SPEC §6) and the information gain of many query views, e.g. the candidates of an
        active-perception planner: U_var and U_exp are the same numbers as ``render(cam).u_var`` / ``.u_exp``, without
        building the images, with the Dirichlet moments computed once per batch of views.

        info_gain (docs/spec.md "Information gain of a view") is the expected drop of the map's summed class variance
        if the view were observed: each Gaussian's evidence from the view (kappa mass, times the sensor model's net
        vote weight at the pixel's label and depth when one is set) through the closed form of
        :mod:`css_ros.engine.info_gain`, weighted by ``importance`` ((N,) >= 0 per Gaussian; None = 1, see
        :meth:`task_importance`, :meth:`class_importance`). ``pixel_scale``: pixels of the image that would be
        observed per scored pixel (1 / f**2 for candidates rendered at ``cam.scaled(f)``): the evidence counts as the
        full-resolution observation would add it. Every backend computes the gain (cuda on the device).

        Returns:
            (len(cameras), 3) float64, columns (U_var, U_exp, info_gain), in the order of ``cameras`` (columns 0 and
            1 are what earlier versions returned).
        """
        cameras = view_args.check_cameras(cameras, "score_views")
        imp = self._check_importance(importance)
        scale = self._check_pixel_scale(pixel_scale)
        e_b, v_b, s_b = self._background_moments()
        return self._backend.score_views(list(cameras), self._concentrations, e_b, v_b, s_b, self._mass_weights(),
                                         imp, scale)

    @staticmethod
    def _check_pixel_scale(pixel_scale: float) -> float:
        return view_args.check_pixel_scale(pixel_scale)

    def select_views(self, cameras: Sequence["Camera"], k: int, importance: np.ndarray | None = None,
                     pixel_scale: float = 1.0) -> "SelectedViews":
        """A greedy batch of ``k`` views for a planner that will visit several: the first has the largest info gain;
        each next one the largest gain given the views before it were observed (their evidence added to the map's
        moments as the expected observation would add it: alpha_n += m_n E[theta_n]), so views that see the same
        surfaces as an earlier pick lose their shared gain. The map is not changed. ``pixel_scale`` as in
        :meth:`score_views`. At most ``view_args.MAX_SELECT_CANDIDATES`` (1024) cameras per call: each candidate's
        visible Gaussians and evidence are kept for the greedy re-scoring (memory linear in the candidates); more are
        refused (CameraError).

        Returns:
            :class:`~css_ros.engine.info_gain.SelectedViews` (indices into ``cameras`` in the order chosen, and each
            one's gain when chosen). Fewer than ``k`` when there are fewer cameras.
        Raises:
            MapError: bad k, importance or pixel_scale, or more than view_args.MAX_SELECT_CANDIDATES cameras (named).
        """
        cameras = view_args.check_cameras(cameras, "select_views", view_args.MAX_SELECT_CANDIDATES)
        k = view_args.check_k(k)
        imp = self._check_importance(importance)
        scale = self._check_pixel_scale(pixel_scale)
        e_b, v_b, s_b = self._background_moments()
        return self._backend.select_views(list(cameras), self._concentrations, e_b, v_b, s_b, self._mass_weights(),
                                          imp, scale, int(k))

    def task_importance(self, task_cameras: Sequence["Camera"]) -> np.ndarray:
        """(N,) float64 per-Gaussian importance = its kappa mass summed over ``task_cameras`` (the views a robot
        will later take or act from), for ``score_views`` / ``select_views``: surfaces no task view sees count 0."""
        task_cameras = view_args.check_cameras(task_cameras, "task_importance")
        imp = np.zeros(self.model.num_gaussians)
        unit = (np.array([0.0, 1.0]), np.ones(self.num_classes))
        e_b, v_b, s_b = self._background_moments()
        for ids, mass in self._backend.view_masses(list(task_cameras), self._concentrations, e_b, v_b, s_b, unit):
            np.add.at(imp, ids, mass)
        return imp

    def class_importance(self, class_id: int) -> np.ndarray:
        """(N,) float64 per-Gaussian importance = E[theta_n^c], the map's probability that Gaussian n is of class
        ``class_id`` (views of surfaces likely to be that class score higher)."""
        class_id = view_args.check_class_id(class_id, self.num_classes)
        conc = self.concentrations_readonly
        return conc[:, int(class_id)] / conc.sum(axis=1)

    def _check_importance(self, importance: np.ndarray | None) -> np.ndarray | None:
        return view_args.check_importance(importance, self.model.num_gaussians)

    def _mass_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """(depth-bin edges in splat units, net vote weight per (label, bin)) of one more observation: without a
        sensor model one bin and weight 1 (a pixel's kappa); with one, the row's share on the label minus its mean
        share on the other classes (w p - w (1 - p) / (C - 1) for a symmetric vote; w for a one-hot one)."""
        if self._soft is None:
            return np.array([0.0, 1.0]), np.ones(self.num_classes)
        table = self._soft.table
        c, nb = self.num_classes, self._soft.num_bins
        labels = np.repeat(np.arange(c), nb)
        own = table[np.arange(c * nb), labels]
        others = (table.sum(axis=1) - own) / max(c - 1, 1)
        return self._soft.edges, np.ascontiguousarray(np.maximum(own - others, 0.0))

    # ------------------------------------------------------------------ the map in 3D (SPEC §9)
    def gaussian_semantics(self, min_evidence: float = DEFAULT_MIN_EVIDENCE) -> GaussianSemantics:
        """Label, E and Var of the label, S_n and the observed flag of every Gaussian (SPEC §9).

        Unobserved Gaussians (S_n - C α_0 < ``min_evidence``) get ``ignore_label``.
        """
        min_evidence = map_args.check_real(min_evidence, "min_evidence")
        return gaussian_semantics(self.concentrations_readonly, self.prior, min_evidence, self.ignore_label)

    def query_points(self, xyz: np.ndarray,
                     background_weight: float = DEFAULT_QUERY_BACKGROUND_WEIGHT) -> FieldQuery:
        """The continuous semantic field at points (SPEC §9), without changing the map.

        Args:
            xyz: (M, 3) points in the map frame, metres.
            background_weight: w_b of the background Dirichlet.
        Returns:
            :class:`FieldQuery` (labels (M,) int32 with ``ignore_label`` where κ_b > ``unknown_threshold``,
            expectation and variance (M, C) float32, background κ_b (M,) float32).
            The spatial index of the model is built on the first call (O(N)) and reused.
        Raises:
            InputError: points not an (M, 3) array of real numbers, more than ``map_args.MAX_QUERY_VALUES`` / C
                points, or a background weight that is not a positive finite number.
        """
        xyz = map_args.check_query_points(xyz, self.num_classes)
        background_weight = map_args.check_background_weight(background_weight)
        if self._field_index is None:
            self._field_index = FieldIndex.from_model(self.model)
        e_b, v_b, _ = self._background_moments()
        return query_field(self._field_index, self.concentrations_readonly, xyz, background_weight, (e_b, v_b),
                           self.unknown_threshold, self.ignore_label)

    # ------------------------------------------------------------------ persistence
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the map as a versioned ``.npz`` of plain arrays, atomically.

        The file is written to a temporary name in the same directory, flushed and fsync'ed, then
        renamed over ``path``: a crash at any moment leaves either the old or the new file intact. The file gets the
        mode a plain ``open()`` gives (0666 less the umask).

        Raises:
            MapError (naming ``path``): a path that is no str/PathLike, holds NUL or is a directory; a map that
                :meth:`load` would refuse (concentrations not finite or outside (0, MAX_CONCENTRATION], frames
                beyond MAX_FRAMES: nothing is written); the file system's refusal (permission, name too long, disk
                full: the old file stays).
        """
        path = map_args.check_map_path(path, reading=False)
        conc = self.concentrations_readonly
        if not (np.all(np.isfinite(conc)) and np.all(conc > 0) and np.all(conc <= MAX_CONCENTRATION)):
            raise MapError(f"cannot save the map to {path}: its concentrations are not all finite and in (0, "
                           f"{MAX_CONCENTRATION:g}] (a map file must be loadable)")
        if not 0 <= self.frames_observed <= MAX_FRAMES:
            raise MapError(f"cannot save the map to {path}: frames_observed={self.frames_observed} outside "
                           f"[0, {MAX_FRAMES}]")
        try:
            self._write(path)
        except OSError as exc:
            raise MapError(f"cannot save the map to {path}: {exc.strerror or exc}") from exc
        return path

    def _write(self, path: Path) -> None:
        """The npz members of :meth:`save`, written atomically to ``path``."""
        with atomic_file(path) as fh:
            np.savez(
                fh,
                format_version=np.int64(MAP_FORMAT_VERSION),
                concentrations=self.concentrations_readonly,
                prior=np.float64(self.prior),
                background=np.float64(self.background),
                num_classes=np.int64(self.num_classes),
                num_gaussians=np.int64(self.model.num_gaussians),
                model_fingerprint=np.array(self.model.fingerprint),
                frames_observed=np.int64(self.frames_observed),
                sources=np.array(sorted(self.sources), dtype=str).reshape(-1),
                sensor_model=np.array(self.fused_sensor_model),
                evidence_origin=np.array(self.evidence_origin),
                evidence_epoch=np.uint64(self.evidence_epoch),
                **self._received_members(),
            )

    def _received_members(self) -> dict[str, Any]:
        """The ``received_*`` members of a map file: each source's nonzero rows, in sorted source order."""
        names = sorted(self.received)
        rows = [np.flatnonzero(np.any(self.received[n].evidence != 0.0, axis=1)) for n in names]
        return dict(
            received_sources=np.array(names, dtype=str).reshape(-1),
            received_state=np.array([[s.epoch, s.last_seq, s.frames, int(s.in_step)]
                                     for s in (self.received[n] for n in names)], dtype=np.uint64).reshape(-1, 4),
            received_counts=np.array([r.size for r in rows], dtype=np.int64),
            received_rows=np.concatenate(rows + [np.zeros(0, np.int64)]).astype(np.int64),
            received_evidence=np.concatenate([self.received[n].evidence[r] for n, r in zip(names, rows)]
                                             + [np.zeros((0, self.num_classes))]),
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str], model: "GaussianModel", expected_classes: int | None = None,
             **kwargs: Any) -> "SemanticMap":
        """Load a map saved by :meth:`save` onto ``model``.

        Every member's declared dtype, shape and size is checked from the npy headers before any data
        is read (no pickles, no decompression bombs, no huge allocations). ``expected_classes``: refuse
        a map with another number of classes before reading it. Extra keyword arguments
        (ignore_label, unknown_threshold, backend, ...) go to the constructor; prior, background and
        num_classes come from the file.
        Raises:
            MapError (naming ``path``): a path that does not exist or is not a regular file, prior /
                background / num_classes passed as arguments (they come from the file), a bad
                ``expected_classes``; unreadable/corrupt/crafted file (also a corrupt compressed
                stream), unknown format version, a map of another model ("this map belongs to model
                <fingerprint>, not <model file>"), or invalid values.
        """
        path = map_args.check_map_path(path, reading=True)
        map_args.check_model(model)
        if expected_classes is not None:
            expected_classes = map_args.check_num_classes(expected_classes, "expected_classes")
        fixed = sorted({"prior", "background", "num_classes"} & set(kwargs))
        if fixed:
            raise MapError(f"load takes {', '.join(fixed)} from the map file, not as an argument")
        _check_map_headers(path, model, expected_classes)
        try:
            with np.load(path, allow_pickle=False) as data:
                version = int(data["format_version"])
                if version != MAP_FORMAT_VERSION:
                    raise MapError(f"map file {path} has format version {version}, "
                                   f"this css_ros reads {MAP_FORMAT_VERSION}")
                fingerprint = str(data["model_fingerprint"])
                num_classes = int(data["num_classes"])
                num_gaussians = int(data["num_gaussians"])
                prior = float(data["prior"])
                background = float(data["background"])
                frames = int(data["frames_observed"]) if "frames_observed" in data.files else 0
                sources = [str(v) for v in data["sources"]] if "sources" in data.files else []
                fused_sm = str(data["sensor_model"]) if "sensor_model" in data.files else NO_SENSOR_MODEL
                evidence_origin = str(data["evidence_origin"]) if "evidence_origin" in data.files else ""
                evidence_epoch = int(data["evidence_epoch"]) if "evidence_epoch" in data.files else 0
                received = {k: np.array(data[k]) for k in _RECEIVED_MEMBERS if k in data.files}
                if fingerprint != model.fingerprint or num_gaussians != model.num_gaussians:
                    raise MapError(f"map file {path}: this map belongs to model {fingerprint[:16]}, not "
                                   f"{getattr(model, 'source', None) or 'the given model'}")
                conc = np.array(data["concentrations"], dtype=np.float64)
        except MapError:
            raise
        except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, RuntimeError, zlib.error) as exc:
            raise MapError(f"cannot read map file {path}: {exc}") from exc
        if conc.shape != (num_gaussians, num_classes) or not np.all(np.isfinite(conc)) or np.any(conc <= 0) \
                or np.any(conc > MAX_CONCENTRATION):
            raise MapError(f"map file {path} holds invalid concentrations (shape {conc.shape}, "
                           f"expected ({num_gaussians}, {num_classes}), all finite, > 0 and <= "
                           f"{MAX_CONCENTRATION:g})")
        for name, value in (("prior", prior), ("background", background)):
            if not (np.isfinite(value) and MIN_CONCENTRATION <= value <= MAX_CONCENTRATION):
                raise MapError(f"map file {path}: {name}={value!r} outside [{MIN_CONCENTRATION:g}, "
                               f"{MAX_CONCENTRATION:g}]")
        if not 0 <= frames <= MAX_FRAMES:
            raise MapError(f"map file {path}: frames_observed={frames} outside [0, {MAX_FRAMES}]")
        smap = cls(model, num_classes, prior=prior, background=background, **kwargs)
        has_evidence = bool(np.any(conc != prior))
        if "sensor_model" in kwargs and fused_sm != smap.sensor_fingerprint and has_evidence:
            raise MapError(f"map file {path} was fused with {_update_name(fused_sm)}, this map uses "
                           f"{_update_name(smap.sensor_fingerprint)}: their evidence is not in the same units (start a new "
                           "map, or use the sensor model it was made with)")
        smap.concentrations[...] = conc
        smap.frames_observed = frames
        smap.sources = sources
        smap.evidence_origin = evidence_origin
        smap.evidence_epoch = evidence_epoch
        smap.received = _received_sources(path, received, conc, prior)
        # a map holding only the prior carries no evidence of any update: it takes the sensor model the caller names
        empty = "sensor_model" in kwargs and not has_evidence
        smap.fused_sensor_model = smap.sensor_fingerprint if empty else fused_sm
        return smap
