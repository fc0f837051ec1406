"""The map file format: what :meth:`SemanticMap.save` writes, :meth:`SemanticMap.load` and ``css_map`` read.

A map file is an ``.npz`` of plain arrays (no pickles: ``allow_pickle=False``), written atomically. Every member is
checked from its npy header (dtype, shape, byte count) before any data is read, so a crafted or broken file is
refused before it allocates anything large.
"""
from __future__ import annotations

import os
import zipfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Mapping

import numpy as np

from ..errors import MapError
from .atomic import atomic_file
from .map_args import MAX_CLASSES, MAX_CONCENTRATION, MIN_CONCENTRATION
from .change_rules import MAX_HALF_LIFE, MIN_HALF_LIFE
from .sensor_model import NO_SENSOR_MODEL
from .spec import MAX_FRAMES

if TYPE_CHECKING:
    from .gaussians import GaussianModel

__all__ = ["MAP_FORMAT_VERSION", "MAX_SOURCES", "MAX_RECEIVED_SOURCES", "MapContents", "MapHeader", "MapInfo",
           "SourceEvidence", "check_map_headers", "read_map_file", "read_map_info", "write_map_file"]

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
    # forgetting (docs/changing_world.md): the evidence half-life in observations the map was fused with, 0 = none
    "evidence_half_life": ("f", ()),
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
_OPTIONAL_MEMBERS = ("frames_observed", "sources", "sensor_model", "evidence_half_life", "evidence_origin", "evidence_epoch",
                     "received_sources", "received_state", "received_counts", "received_rows", "received_evidence")
_RECEIVED_MEMBERS = ("received_sources", "received_state", "received_counts", "received_rows", "received_evidence")
#: Most contributing sources a map file may list (origin ids of the nodes whose evidence it holds).
MAX_SOURCES = 4096
#: Most received sources whose evidence a map file keeps apart (each becomes an (N, C) float64 array when loaded).
MAX_RECEIVED_SOURCES = 64
#: Largest byte size of a scalar member of a map file (the fingerprint string is 64 characters of 4 bytes).
_MAX_SCALAR_BYTES = 4096
#: What reading a broken archive or npy member raises besides MapError (each becomes a MapError naming the file).
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile, RuntimeError, zlib.error)


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


@dataclass
class MapContents:
    """The values of one map file (what :func:`write_map_file` writes and :func:`read_map_file` returns checked).

    Attributes:
        fingerprint: SHA-256 of the splat model the map was made on (``GaussianModel.fingerprint``).
        concentrations: (N, C) float64 Dirichlet α per Gaussian and class, finite, in (0, MAX_CONCENTRATION].
        prior: α_0 per class.
        background: α_b per class.
        frames_observed: frames fused into the map (summed over merged maps).
        sources: origin ids of the css_node sources whose evidence the map holds (as stored: sorted when written).
        sensor_model: fingerprint of the sensor model the evidence was fused with ("" = the paper's update).
        evidence_origin: origin id under which css_node publishes the map's own evidence ("": none / not known).
        evidence_epoch: epoch of that own evidence when the map was saved (0: none / not known).
        received: evidence of other nodes held in ``concentrations``, per origin id.
        evidence_half_life: the half-life in observations the evidence was fused with (None: the paper's update,
            evidence adds up; stored as 0).
    """

    fingerprint: str
    concentrations: np.ndarray
    prior: float
    background: float
    frames_observed: int = 0
    sources: list[str] = field(default_factory=list)
    sensor_model: str = NO_SENSOR_MODEL
    evidence_origin: str = ""
    evidence_epoch: int = 0
    received: Mapping[str, SourceEvidence] = field(default_factory=dict)
    evidence_half_life: float | None = None

    @property
    def num_gaussians(self) -> int:
        """N."""
        return int(self.concentrations.shape[0])

    @property
    def num_classes(self) -> int:
        """C."""
        return int(self.concentrations.shape[1])


@dataclass(frozen=True)
class MapHeader:
    """The scalars :func:`check_map_headers` reads before any large member: N, C and the model's fingerprint."""

    num_gaussians: int
    num_classes: int
    fingerprint: str


# ---------------------------------------------------------------------------------------------------- writing
def write_map_file(path: Path, contents: MapContents) -> None:
    """Write ``contents`` as a versioned ``.npz`` of plain arrays, atomically (:func:`~.atomic.atomic_file`: a crash
    at any moment leaves the old or the new file). OSError from the file system is the caller's to report."""
    with atomic_file(path) as fh:
        np.savez(
            fh,
            format_version=np.int64(MAP_FORMAT_VERSION),
            concentrations=contents.concentrations,
            prior=np.float64(contents.prior),
            background=np.float64(contents.background),
            num_classes=np.int64(contents.num_classes),
            num_gaussians=np.int64(contents.num_gaussians),
            model_fingerprint=np.array(contents.fingerprint),
            frames_observed=np.int64(contents.frames_observed),
            sources=np.array(sorted(contents.sources), dtype=str).reshape(-1),
            sensor_model=np.array(contents.sensor_model),
            evidence_half_life=np.float64(contents.evidence_half_life or 0.0),
            evidence_origin=np.array(contents.evidence_origin),
            evidence_epoch=np.uint64(contents.evidence_epoch),
            **_received_members(contents.received, contents.num_classes),
        )


def _received_members(received: Mapping[str, SourceEvidence], num_classes: int) -> dict[str, Any]:
    """The ``received_*`` members of a map file: each source's nonzero rows, in sorted source order."""
    names = sorted(received)
    rows = [np.flatnonzero(np.any(received[n].evidence != 0.0, axis=1)) for n in names]
    return dict(
        received_sources=np.array(names, dtype=str).reshape(-1),
        received_state=np.array([[s.epoch, s.last_seq, s.frames, int(s.in_step)]
                                 for s in (received[n] for n in names)], dtype=np.uint64).reshape(-1, 4),
        received_counts=np.array([r.size for r in rows], dtype=np.int64),
        received_rows=np.concatenate(rows + [np.zeros(0, np.int64)]).astype(np.int64),
        received_evidence=np.concatenate([received[n].evidence[r] for n, r in zip(names, rows)]
                                         + [np.zeros((0, num_classes))]),
    )


# ---------------------------------------------------------------------------------------------------- reading
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


def _member_shapes(path: Path) -> dict[str, tuple]:
    """Declared shape of every member present, each member's dtype, dimensions and byte count checked from its npy
    header (see :func:`check_map_headers`)."""
    if not zipfile.is_zipfile(path):
        raise MapError(f"map file {path} is not an .npz archive")
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
                raise MapError(f"map file {path}: {name} holds {info.file_size} bytes, its header declares {declared}")
            if shape == ("S",) and dshape[0] > MAX_SOURCES:
                raise MapError(f"map file {path} lists {dshape[0]} sources, at most {MAX_SOURCES}")
            if not shape and declared > _MAX_SCALAR_BYTES:
                raise MapError(f"map file {path}: {name} is a scalar of {declared} bytes")
            shapes[name] = dshape
    return shapes


def check_map_headers(path: Path, model: "GaussianModel | None" = None, num_classes: int | None = None) -> MapHeader:
    """Check every member's declared dtype, shape and size from the npy headers, and the file's own
    model fingerprint and class count, before reading any large data.

    Refuses (MapError naming ``path``) a file that is not a zip, lacks members, declares other dtypes
    (complex, bool, object, ...) or shapes, whose members hold another number of bytes than their
    headers declare, or whose scalars are larger than :data:`_MAX_SCALAR_BYTES`; a map of another model
    ("this map belongs to model <fingerprint>, not <model file>"); concentrations whose declared shape
    is not (the model's N, the file's own ``num_classes``) (a decompression bomb or a header declaring a
    huge array is refused here, without the caller passing C); with ``num_classes`` given, a map of
    another class count. A corrupt compressed stream is a MapError too. ``model`` None (css_map reading a map
    without its model): the file's own number of Gaussians (>= 1) is taken, no fingerprint check. Returns the
    file's N, C and model fingerprint (only headers and scalars were read).
    """
    try:
        shapes = _member_shapes(path)
        # The scalars are a few bytes each (checked above): read them before the concentrations.
        with np.load(path, allow_pickle=False) as data:
            file_gaussians = int(data["num_gaussians"])
            fingerprint = str(data["model_fingerprint"])
            file_classes = int(data["num_classes"])
    except MapError:
        raise
    except _READ_ERRORS as exc:
        raise MapError(f"cannot read map file {path}: {exc}") from exc
    if model is None:
        if file_gaussians < 1:
            raise MapError(f"map file {path}: num_gaussians={file_gaussians}, at least 1 expected")
        n_model = file_gaussians
    elif fingerprint != model.fingerprint or file_gaussians != model.num_gaussians:
        source = getattr(model, "source", None) or "the given model"
        raise MapError(f"map file {path}: this map belongs to model {fingerprint[:16]}, not {source} (model "
                       f"{model.fingerprint[:16]}; {file_gaussians} vs {model.num_gaussians} Gaussians)")
    else:
        n_model = model.num_gaussians
    if not 1 <= file_classes <= MAX_CLASSES:
        raise MapError(f"map file {path}: num_classes={file_classes} outside 1..{MAX_CLASSES}")
    dshape = shapes["concentrations"]
    if tuple(dshape) != (n_model, file_classes):
        raise MapError(f"map file {path}: concentrations have shape {dshape}, the file's own num_classes and "
                       f"the model give ({n_model}, {file_classes})")
    if num_classes is not None and file_classes != num_classes:
        raise MapError(f"map file {path} has {file_classes} classes, expected {num_classes}")
    _check_received_shapes(path, shapes, n_model, file_classes)
    return MapHeader(n_model, file_classes, fingerprint)


def _check_received_shapes(path: Path, shapes: dict[str, tuple], n: int, c: int) -> None:
    """The ``received_*`` members: all or none, at most MAX_RECEIVED_SOURCES sources, consistent shapes."""
    present = [k for k in _RECEIVED_MEMBERS if k in shapes]
    if present and len(present) != len(_RECEIVED_MEMBERS):
        raise MapError(f"map file {path} has {', '.join(present)} but not all of {', '.join(_RECEIVED_MEMBERS)}")
    if not present:
        return
    s, r = shapes["received_sources"][0], shapes["received_rows"][0]
    if s > MAX_RECEIVED_SOURCES:
        raise MapError(f"map file {path} keeps the evidence of {s} received sources, at most {MAX_RECEIVED_SOURCES}")
    if (tuple(shapes["received_state"]) != (s, 4) or tuple(shapes["received_counts"]) != (s,)
            or tuple(shapes["received_evidence"]) != (r, c) or r > s * n):
        raise MapError(f"map file {path}: received evidence of inconsistent shapes (sources {s}, state "
                       f"{shapes['received_state']}, counts {shapes['received_counts']}, rows {r}, evidence "
                       f"{shapes['received_evidence']}; at most {n} rows per source)")


def read_map_file(path: Path, model: "GaussianModel | None" = None, num_classes: int | None = None,
                  received: bool = True) -> MapContents:
    """The checked contents of a map file written by :func:`write_map_file`.

    Args:
        path: the file (a regular file: the callers check the path first).
        model: the splat model the map must belong to; None: no fingerprint check (css_map without the model).
        num_classes: refuse a map with another number of classes before reading it (None: any).
        received: read the received sources' evidence (an (N, C) float64 array per source, up to
            MAX_RECEIVED_SOURCES; their shapes are checked either way); False: ``received`` stays empty.
    Raises:
        MapError (naming ``path``): everything :func:`check_map_headers` refuses; an unknown format version;
            concentrations not finite or outside (0, MAX_CONCENTRATION]; prior or background outside
            [MIN_CONCENTRATION, MAX_CONCENTRATION]; frames_observed outside [0, MAX_FRAMES]; received evidence
            that is malformed or exceeds what the concentrations hold.
    """
    check_map_headers(path, model, num_classes)
    try:
        with np.load(path, allow_pickle=False) as data:
            version = int(data["format_version"])
            if version != MAP_FORMAT_VERSION:
                raise MapError(f"map file {path} has format version {version}, this css_ros reads {MAP_FORMAT_VERSION}")
            files = set(data.files)
            fingerprint = str(data["model_fingerprint"])
            num_gaussians, c = int(data["num_gaussians"]), int(data["num_classes"])
            prior, background = float(data["prior"]), float(data["background"])
            frames = int(data["frames_observed"]) if "frames_observed" in files else 0
            sources = [str(v) for v in data["sources"]] if "sources" in files else []
            sensor_model = str(data["sensor_model"]) if "sensor_model" in files else NO_SENSOR_MODEL
            half_life = float(data["evidence_half_life"]) if "evidence_half_life" in files else 0.0
            evidence_origin = str(data["evidence_origin"]) if "evidence_origin" in files else ""
            evidence_epoch = int(data["evidence_epoch"]) if "evidence_epoch" in files else 0
            members = {k: np.array(data[k]) for k in _RECEIVED_MEMBERS if k in files and received}
            conc = np.array(data["concentrations"], dtype=np.float64)
    except MapError:
        raise
    except _READ_ERRORS as exc:
        raise MapError(f"cannot read map file {path}: {exc}") from exc
    if conc.shape != (num_gaussians, c) or not np.all(np.isfinite(conc)) or np.any(conc <= 0) \
            or np.any(conc > MAX_CONCENTRATION):
        raise MapError(f"map file {path} holds invalid concentrations (shape {conc.shape}, expected ({num_gaussians}, "
                       f"{c}), all finite, > 0 and <= {MAX_CONCENTRATION:g})")
    for name, value in (("prior", prior), ("background", background)):
        if not (np.isfinite(value) and MIN_CONCENTRATION <= value <= MAX_CONCENTRATION):
            raise MapError(f"map file {path}: {name}={value!r} outside [{MIN_CONCENTRATION:g}, {MAX_CONCENTRATION:g}]")
    if not 0 <= frames <= MAX_FRAMES:
        raise MapError(f"map file {path}: frames_observed={frames} outside [0, {MAX_FRAMES}]")
    if half_life != 0.0 and not MIN_HALF_LIFE <= half_life <= MAX_HALF_LIFE:
        raise MapError(f"map file {path}: evidence_half_life={half_life!r} is neither 0 (none) nor in "
                       f"[{MIN_HALF_LIFE:g}, {MAX_HALF_LIFE:g}]")
    return MapContents(fingerprint=fingerprint, concentrations=conc, prior=prior, background=background,
                       frames_observed=frames, sources=sources, sensor_model=sensor_model,
                       evidence_origin=evidence_origin, evidence_epoch=evidence_epoch,
                       received=_received_sources(path, members, conc, prior),
                       evidence_half_life=half_life or None)


def _received_sources(path: Path, members: dict[str, np.ndarray], conc: np.ndarray,
                      prior: float) -> dict[str, SourceEvidence]:
    """The received sources of a map file (``received_*`` members, shapes checked by :func:`check_map_headers`):
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


# ---------------------------------------------------------------------------------------------------- summary
@dataclass(frozen=True)
class MapInfo:
    """Summary of one map file (``css_map info``, merge checks).

    Attributes:
        path: the file.
        fingerprint: SHA-256 of the splat model the map was made on (``GaussianModel.fingerprint``).
        num_gaussians: N.
        num_classes: C.
        prior: α_0 per class.
        background: α_b per class.
        frames_observed: frames fused into the map (summed over merged maps).
        sources: origin ids of the css_node sources whose evidence the map holds (sorted; may be empty).
        evidence_total: Σ_n Σ_c (α_n^c - α_0): the κ-weighted label count fused so far [pixels].
        evidence_per_class: (C,) float64 the same per class.
        observed_gaussians: Gaussians whose evidence S_n - C α_0 is > 0.
        evidence_max: largest per-Gaussian evidence S_n - C α_0.
        sensor_model: fingerprint of the sensor model the evidence was fused with ("" = the paper's update).
    """

    path: Path
    fingerprint: str
    num_gaussians: int
    num_classes: int
    prior: float
    background: float
    frames_observed: int
    sources: list[str]
    evidence_total: float
    evidence_per_class: np.ndarray = field(repr=False)
    observed_gaussians: int
    evidence_max: float
    sensor_model: str = NO_SENSOR_MODEL


def read_map_info(path: str | os.PathLike[str]) -> MapInfo:
    """Read and check a map file written by :meth:`SemanticMap.save`, without its model (the checks of
    :func:`read_map_file`, but for the model's fingerprint).

    Raises:
        MapError: a folder, a missing file; an unreadable, corrupt or crafted file; invalid values.
    """
    path = Path(path)
    if path.is_dir():
        raise MapError(f"{path} is a folder, not a map file (a css_replay output folder holds map.npz)")
    if not path.is_file():
        raise MapError(f"map file not found: {path}")
    m = read_map_file(path, received=False)   # a summary: the received sources' (N, C) arrays are not needed
    evidence = m.concentrations - m.prior
    per_gaussian = evidence.sum(axis=1)
    return MapInfo(path=path, fingerprint=m.fingerprint, num_gaussians=m.num_gaussians, num_classes=m.num_classes,
                   prior=m.prior, background=m.background, frames_observed=m.frames_observed,
                   sources=sorted(m.sources), evidence_total=float(per_gaussian.sum()),
                   evidence_per_class=evidence.sum(axis=0), observed_gaussians=int(np.count_nonzero(per_gaussian > 0)),
                   evidence_max=float(per_gaussian.max()), sensor_model=m.sensor_model)
