"""The segmenter's sensor model: how much a labelled pixel is worth, by its label and depth (docs/spec.md
"Sensor model").

A :class:`SensorModel` holds, per predicted class y and depth bin b (bins of the pixel's rendered depth d,
metres):

- a reliability weight w(y, b) in [0, 1] (how much evidence one such pixel carries), and
- optionally a confusion row p(c | y, b) (the distribution of the true class c given the label y at that depth).

The update of SPEC §4 then adds ``kappa_in * conf_i * w(y_i, b_i) * p(c | y_i, b_i)`` to alpha_n^c (fractional
counts: still closed form and additive). Without a confusion model p(. | y, b) is the one-hot of y.

It may also hold a :class:`ConfidenceMap`: the probability that a rendered label is right, from the rendered
expectation E and evidence of that pixel (``RenderedView.confidence``, css_node's ``~/confidence``).

Files are YAML (``css_calibrate`` writes them, :meth:`SensorModel.load` reads them with every check of
docs/spec.md: classes, shapes, finiteness, ranges, normalisation, bin order, file size).
"""
from __future__ import annotations

import errno
import hashlib
import math
import os
import stat
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from yaml import YAMLError

from ..errors import SensorModelError
from .atomic import atomic_file
from .pixel_math import E_CLIP, Z_CLIP

SENSOR_MODEL_FORMAT = "css_ros.sensor_model"
SENSOR_MODEL_VERSION = 1
#: Largest sensor-model file read [bytes] (a model of 256 classes x 64 bins with confusion is ~10 MB of YAML).
MAX_SENSOR_MODEL_BYTES = 32 * 1024 * 1024
#: Most depth bins a sensor model may have.
MAX_DEPTH_BINS = 256
#: Most numbers (YAML scalars) a sensor-model file may hold: 256 classes x 64 bins x 256 classes of confusion
#: (4.2 M, ~100 MB of YAML, beyond the file cap) fit; the parsed lists then take at most ~140 MB.
MAX_YAML_SCALARS = 2**22
#: Deepest nesting of lists / mappings in a sensor-model file (the confusion table is 4 deep).
MAX_YAML_DEPTH = 16
#: Most characters of an integer in a sensor-model file (a version, a pixel count: 2^64 has 20 digits).
MAX_YAML_INT_CHARS = 32
#: Most characters of any other non-string scalar (a float: css_calibrate writes at most 24, ``-1.2345678901234567e-308``;
#: a bool, null, date). Longer ones are refused before they are converted: PyYAML turns a 33 MB YAML 1.1
#: sexagesimal float (``1:59:59:...``) into 11 M floats (1.4 GB).
MAX_YAML_NUMBER_CHARS = 64
#: Largest magnitude of a confidence-map coefficient (css_calibrate's L2-regularised fits are O(1-10)). With the
#: features bounded (|logit E| <= 13.9, log(1 + evidence) <= 710 for any finite float64), |z| stays below 1e9: the
#: logistic score never overflows, on any backend.
MAX_CONFIDENCE_COEF = 1e6
#: Smallest largest weight of a sensor model: below it every vote is (nearly) worthless and the map would stay at
#: its prior whatever it sees (css_calibrate writes no weight below its --weight-floor, 0.02 by default).
MIN_LARGEST_WEIGHT = 1e-6
#: Most entries of the dense vote table, classes x depth bins x classes (``SoftLabels.table``; the update builds ~4
#: float64 arrays of this size): 2^24 entries (~0.5 GB in all) hold 256 classes x 256 bins or 512 classes x 64 bins;
#: 1500 classes x 256 bins would need 4.3 GB per array.
MAX_VOTE_TABLE_ENTRIES = 2**24
#: Most characters of a value (a class name, a version, a key) quoted in an error message.
MAX_SHOWN_CHARS = 60
#: Most characters of a file name quoted in an error message (longer ones are cut, e.g. a 5000-character path).
MAX_SHOWN_PATH_CHARS = 1024
#: Tolerance on the sum of a confusion row.
ROW_SUM_TOLERANCE = 1e-6
#: Fingerprint of the paper's update (no sensor model), as stored in map files.
NO_SENSOR_MODEL = ""


@dataclass(frozen=True)
class ConfidenceMap:
    """Calibrated probability that a rendered label is right, from the pixel's E and evidence.

    ``p = isotonic(sigmoid(a * logit(E) + b * log(1 + evidence) + c))``: a two-feature logistic score
    (E of the argmax class, clipped to [1e-6, 1 - 1e-6]; evidence = the kappa-weighted Dirichlet total of
    ``RenderedView.evidence``), then a monotone piecewise-linear correction through the knots (flat beyond
    them), both fitted by ``css_calibrate`` on online renders of labelled frames.

    Attributes:
        coef: (3,) float64 (a, b, c).
        knots_x, knots_y: (K,) float64, knots_x strictly increasing in [0, 1], knots_y non-decreasing in [0, 1].
    """

    coef: np.ndarray
    knots_x: np.ndarray
    knots_y: np.ndarray

    def __post_init__(self) -> None:
        for name in ("coef", "knots_x", "knots_y"):
            object.__setattr__(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        self.check("confidence map")

    def check(self, where: str) -> None:
        """Raise SensorModelError (naming ``where``) unless the coefficients and knots are usable: 3 finite
        coefficients within +-MAX_CONFIDENCE_COEF, knots finite, x strictly increasing and y non-decreasing in
        [0, 1]."""
        coef, kx, ky = self.coef, self.knots_x, self.knots_y
        if coef.shape != (3,):
            raise SensorModelError(f"{where}.coef: expected 3 numbers, got {coef.size}")
        if kx.ndim != 1 or kx.shape != ky.shape or kx.size < 1:
            raise SensorModelError(f"{where}: knots_x and knots_y must be non-empty and of one length")
        for name, a in (("coef", coef), ("knots_x", kx), ("knots_y", ky)):
            if not np.all(np.isfinite(a)):
                raise SensorModelError(f"{where}.{name} must be finite numbers, got {_short(a)}")
        if np.any(np.abs(coef) > MAX_CONFIDENCE_COEF):
            raise SensorModelError(f"{where}.coef must be within +-{MAX_CONFIDENCE_COEF:g} (css_calibrate fits "
                                   f"values of order 1; larger ones overflow the logistic score), got {_short(coef)}")
        if np.any(np.diff(kx) <= 0) or kx[0] < 0 or kx[-1] > 1:
            raise SensorModelError(f"{where}.knots_x must be strictly increasing within [0, 1]")
        if np.any(np.diff(ky) < 0) or ky[0] < 0 or ky[-1] > 1:
            raise SensorModelError(f"{where}.knots_y must be non-decreasing within [0, 1]")

    @staticmethod
    def features(expectation: np.ndarray, evidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(logit E with E clipped to [1e-6, 1 - 1e-6], log(1 + evidence)), float64, the inputs' shape: the two
        features of the logistic score (css_calibrate fits its coefficients on these)."""
        e = np.clip(np.asarray(expectation, dtype=np.float64), E_CLIP, 1.0 - E_CLIP)
        return np.log(e / (1.0 - e)), np.log1p(np.maximum(np.asarray(evidence, dtype=np.float64), 0.0))

    def score(self, expectation: np.ndarray, evidence: np.ndarray) -> np.ndarray:
        """The logistic score before the isotonic correction (same shape as the inputs, float64): a NaN argument
        (a NaN input, 0 x inf evidence) scores 0.5 and +-inf is clipped to +-Z_CLIP, as in
        :func:`.pixel_math.confidence_score` (the compiled backends), without a RuntimeWarning."""
        logit_e, log_ev = self.features(expectation, evidence)
        with np.errstate(over="ignore", invalid="ignore"):
            z = self.coef[0] * logit_e + self.coef[1] * log_ev + self.coef[2]
        z = np.clip(np.nan_to_num(z, nan=0.0, posinf=Z_CLIP, neginf=-Z_CLIP), -Z_CLIP, Z_CLIP)
        return 0.5 * (1.0 + np.tanh(0.5 * z))

    def __call__(self, expectation: np.ndarray, evidence: np.ndarray) -> np.ndarray:
        """Probability that the label is right (float32, same shape as ``expectation``)."""
        p = np.interp(self.score(expectation, evidence), self.knots_x, self.knots_y)
        return p.astype(np.float32)

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "logistic_isotonic", "features": ["logit(E)", "log(1 + evidence)", "1"],
                "coef": [float(v) for v in self.coef], "knots_x": [float(v) for v in self.knots_x],
                "knots_y": [float(v) for v in self.knots_y]}

    @classmethod
    def from_dict(cls, d: Any, where: str) -> "ConfidenceMap":
        if not isinstance(d, dict) or d.get("kind") != "logistic_isotonic":
            raise SensorModelError(f"{where}: confidence must be a mapping with kind: logistic_isotonic")
        coef = _array(d.get("coef"), where + ".coef", 1)
        kx = _array(d.get("knots_x"), where + ".knots_x", 1)
        ky = _array(d.get("knots_y"), where + ".knots_y", 1)
        cmap = cls.__new__(cls)
        for name, a in (("coef", coef), ("knots_x", kx), ("knots_y", ky)):
            object.__setattr__(cmap, name, a)
        cmap.check(where)            # naming the file (the constructor's own check would say "confidence map")
        return cmap


@dataclass(frozen=True)
class SoftLabels:
    """What an update kernel needs of a sensor model, in the splat's units.

    Attributes:
        edges: (B + 1,) float64 depth-bin edges in splat units (metres / depth_scale), increasing.
        table: (C * B, C) float64; row y * B + b = w(y, b) * p(. | y, b).
        base, resid: the table split as table = base[:, None] + resid, base (C * B,) the most common entry of each
            row (0 for a one-hot row; the share of every other class for a symmetric one), so that resid is
            sparse and the CPU update adds the common part once per Gaussian instead of once per class.
    """

    edges: np.ndarray
    table: np.ndarray
    base: np.ndarray = field(default_factory=lambda: np.zeros(0))
    resid: np.ndarray = field(default_factory=lambda: np.zeros((0, 0)))

    def __post_init__(self) -> None:
        if self.base.size == 0:
            base = np.array([_row_mode(row) for row in self.table])
            object.__setattr__(self, "base", base)
            object.__setattr__(self, "resid", np.ascontiguousarray(self.table - base[:, None]))

    @property
    def num_bins(self) -> int:
        return int(self.edges.size - 1)


@dataclass(frozen=True)
class SensorModel:
    """Reliability weights (and optionally a confusion model and a confidence map) per label and depth bin.

    Attributes:
        class_names: the C class names, in class-id order (must equal the map's class file).
        depth_edges: (B + 1,) float64 metres, strictly increasing, edges[0] >= 0. A pixel of depth d is in bin
            b with edges[b] <= d < edges[b + 1]; depths below edges[0] use bin 0, beyond edges[-1] bin B - 1.
        weight: (C, B) float64 in [0, 1], w(y, b).
        confusion: (C, B, C) float64 rows summing to 1, p(c | y, b), or None (one-hot).
        confidence: the calibrated confidence map, or None.
        info: what css_calibrate measured (bags, pixel counts, held-out calibration); informational.
    """

    class_names: tuple[str, ...]
    depth_edges: np.ndarray
    weight: np.ndarray
    confusion: np.ndarray | None = None
    confidence: ConfidenceMap | None = None
    info: dict[str, Any] = field(default_factory=dict)
    source: str | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "class_names", tuple(self.class_names))
        object.__setattr__(self, "depth_edges", np.asarray(self.depth_edges, dtype=np.float64))
        object.__setattr__(self, "weight", np.asarray(self.weight, dtype=np.float64))
        if self.confusion is not None:
            object.__setattr__(self, "confusion", np.asarray(self.confusion, dtype=np.float64))
        self.validate(self.source or "sensor model")

    def __repr__(self) -> str:
        """One line: classes, depth bins, votes, confidence map, fingerprint; never the tables."""
        e = self.depth_edges
        return (f"SensorModel({self.num_classes} classes, {self.num_bins} depth bins {e[0]:g}-{e[-1]:g} m, "
                f"{'vote rows' if self.confusion is not None else 'one-hot votes'}, "
                f"{'calibrated confidence' if self.confidence is not None else 'no confidence map'}, "
                f"fingerprint {self.fingerprint[:12]})")

    # ------------------------------------------------------------------ facts
    @property
    def num_classes(self) -> int:
        return len(self.class_names)

    @property
    def num_bins(self) -> int:
        return int(self.depth_edges.size - 1)

    @property
    def fingerprint(self) -> str:
        """SHA-256 of what changes the map (class names, bin edges, weights, confusion): maps fused with
        different fingerprints hold evidence of different units and are not merged. The confidence map and
        ``info`` are left out (they change only what is published)."""
        h = hashlib.sha256()
        h.update(f"{SENSOR_MODEL_FORMAT}/{SENSOR_MODEL_VERSION}\n".encode())
        h.update("\n".join(self.class_names).encode())
        for a in (self.depth_edges, self.weight, self.confusion):
            h.update(b"|" if a is None else np.ascontiguousarray(a, dtype="<f8").tobytes())
        return h.hexdigest()

    def bin_of(self, depth: np.ndarray) -> np.ndarray:
        """Depth bin (int64, same shape) of depths in metres (NaN -> bin 0)."""
        return depth_bins(self.depth_edges, np.nan_to_num(np.asarray(depth, dtype=np.float64), nan=0.0))

    def label_distribution(self) -> np.ndarray:
        """(C, B, C) p(c | y, b): the confusion model, or the one-hot of y."""
        if self.confusion is not None:
            return self.confusion
        eye = np.eye(self.num_classes)
        return np.repeat(eye[:, None, :], self.num_bins, axis=1)

    def soft_labels(self, depth_scale: float = 1.0) -> SoftLabels:
        """The update's tables for a splat whose unit is ``depth_scale`` metres."""
        table = (self.weight[:, :, None] * self.label_distribution()).reshape(self.num_classes * self.num_bins,
                                                                               self.num_classes)
        return SoftLabels(np.ascontiguousarray(self.depth_edges / float(depth_scale)), np.ascontiguousarray(table))

    def describe(self) -> str:
        """One line for logs: bins, confusion, confidence map, fingerprint."""
        e = self.depth_edges
        name = self.source or "sensor model"
        name = name if name.startswith("sensor model") else f"sensor model {name}"
        return (f"{name} ({self.num_classes} classes, {self.num_bins} depth bins "
                f"{e[0]:g}-{e[-1]:g} m, {'vote rows' if self.confusion is not None else 'one-hot votes'}, "
                f"{'calibrated confidence' if self.confidence is not None else 'no confidence map'}, "
                f"fingerprint {self.fingerprint[:12]})")

    # ------------------------------------------------------------------ checks
    def validate(self, where: str) -> None:
        """Raise SensorModelError (naming ``where``) unless every table is well formed."""
        c = len(self.class_names)
        if c < 1 or not all(isinstance(n, str) and n for n in self.class_names):
            raise SensorModelError(f"{where}: classes must be a non-empty list of names")
        e = self.depth_edges
        if e.ndim != 1 or not 2 <= e.size <= MAX_DEPTH_BINS + 1:
            raise SensorModelError(f"{where}: depth_edges must list 2..{MAX_DEPTH_BINS + 1} numbers")
        if not np.all(np.isfinite(e)) or e[0] < 0 or np.any(np.diff(e) <= 0):
            raise SensorModelError(f"{where}: depth_edges must be finite, >= 0 and strictly increasing, got "
                                   f"{_short(e)}")
        b = e.size - 1
        table_error = vote_table_error(c, b)
        if table_error is not None:
            raise SensorModelError(f"{where}: {table_error}")
        if self.weight.shape != (c, b):
            raise SensorModelError(f"{where}: weight has shape {self.weight.shape}, expected ({c} classes, {b} bins)")
        if not np.all(np.isfinite(self.weight)) or np.any(self.weight < 0) or np.any(self.weight > 1):
            raise SensorModelError(f"{where}: weight entries must be finite and in [0, 1]")
        if not self.weight.max() >= MIN_LARGEST_WEIGHT:
            raise SensorModelError(f"{where}: every weight is below {MIN_LARGEST_WEIGHT:g} (largest "
                                   f"{self.weight.max():g}): no label would add evidence and the map would stay at its "
                                   "prior")
        if self.confusion is not None:
            p = self.confusion
            if p.shape != (c, b, c):
                raise SensorModelError(f"{where}: confusion has shape {p.shape}, expected ({c}, {b}, {c})")
            if not np.all(np.isfinite(p)) or np.any(p < 0):
                raise SensorModelError(f"{where}: confusion entries must be finite and >= 0")
            bad = np.abs(p.sum(axis=2) - 1.0) > ROW_SUM_TOLERANCE
            if np.any(bad):
                y, bb = np.argwhere(bad)[0]
                raise SensorModelError(f"{where}: confusion row of label {_quote(self.class_names[y])}, depth bin {bb} "
                                       f"sums to {p[y, bb].sum():.6g}, not 1")

    def check_classes(self, class_names: Sequence[str], where: str | None = None) -> None:
        """Refuse a model made for other classes than ``class_names`` (the map's class file)."""
        names = tuple(class_names)
        if names != self.class_names:
            where = where or self.source or "sensor model"
            if len(names) != len(self.class_names):
                raise SensorModelError(f"{where} is for {len(self.class_names)} classes, the map has {len(names)}")
            diff = next(i for i, (a, b) in enumerate(zip(names, self.class_names)) if a != b)
            raise SensorModelError(f"{where}: class {diff} is {_quote(self.class_names[diff])}, the map's class file "
                                   f"says {_quote(names[diff])}")

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        d: dict[str, Any] = {
            "format": SENSOR_MODEL_FORMAT, "version": SENSOR_MODEL_VERSION,
            "fingerprint": self.fingerprint,
            "classes": list(self.class_names),
            "depth_edges": [float(v) for v in self.depth_edges],
            "weight": self.weight.tolist(),
            "confusion": None if self.confusion is None else self.confusion.tolist(),
            "confidence": None if self.confidence is None else self.confidence.to_dict(),
        }
        if self.info:
            d["calibration"] = self.info
        return d

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the YAML file atomically (temporary file, fsync, rename): never a partial file."""
        import yaml

        path = Path(path)
        text = yaml.safe_dump(self.to_dict(), sort_keys=False, default_flow_style=None, width=120)
        with atomic_file(path, "w") as fh:
            fh.write(text)
        return path

    @classmethod
    def from_dict(cls, d: Any, where: str) -> "SensorModel":
        if not isinstance(d, dict) or d.get("format") != SENSOR_MODEL_FORMAT:
            raise SensorModelError(f"{where} is not a css_ros sensor model (no 'format: {SENSOR_MODEL_FORMAT}'; "
                                   "css_calibrate writes these files)")
        version = d.get("version")
        if type(version) is not int:             # not True (== 1), 1.0 or "1"
            raise SensorModelError(f"{where}: version must be an integer, got {_quote(version)} "
                                   f"({_kind(version)})")
        if version != SENSOR_MODEL_VERSION:
            raise SensorModelError(f"{where} has version {_quote(version)}, this css_ros reads "
                                   f"{SENSOR_MODEL_VERSION}")
        names = d.get("classes")
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            raise SensorModelError(f"{where}: classes must be a list of class names")
        weight = _array(d.get("weight"), f"{where}: weight", 2)
        conf = d.get("confusion")
        confusion = None if conf is None else _array(conf, f"{where}: confusion", 3)
        cmap = d.get("confidence")
        info = d.get("calibration")
        model = cls(tuple(names), _array(d.get("depth_edges"), f"{where}: depth_edges", 1), weight, confusion,
                    None if cmap is None else ConfidenceMap.from_dict(cmap, f"{where}: confidence"),
                    info if isinstance(info, dict) else {}, source=where)
        stated = d.get("fingerprint")
        if stated is not None and stated != model.fingerprint:
            raise SensorModelError(f"{where}: its tables do not match its fingerprint (edited by hand or "
                                   "corrupted); recalibrate, or delete the fingerprint line to accept the edit")
        return model

    @classmethod
    def load(cls, path: str | os.PathLike[str], class_names: Sequence[str] | None = None) -> "SensorModel":
        """Read and check a sensor-model YAML file (and, given ``class_names``, that it fits the map's classes).

        Raises:
            SensorModelError: one line naming the file: missing, unreadable (any OSError: permission, name too
                long, ...), not a regular file (a directory, a FIFO or a device: never opened), too large, not YAML,
                YAML beyond what
                :func:`read_plain_yaml` reads (aliases, deep nesting, huge integers, too many values), not a sensor
                model, or any failed check of :meth:`validate` / :meth:`check_classes` / the confidence map.
        """
        if isinstance(path, str) and not path:
            raise SensorModelError("sensor model path is empty")
        path = Path(path)
        where = f"sensor model {shorten(str(path), MAX_SHOWN_PATH_CHARS)}"
        raw = read_regular_file(path, where, MAX_SENSOR_MODEL_BYTES)
        try:
            d = read_plain_yaml(raw.decode("utf-8"), where)
        except (UnicodeDecodeError, YAMLError, ValueError, OverflowError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise SensorModelError(f"{where} is not a readable YAML file ({shorten(first, 200)})") from None
        model = cls.from_dict(d, where)
        if class_names is not None:
            model.check_classes(class_names)
        return model


def read_plain_yaml(text: str, where: str) -> Any:
    """The one document of ``text`` as plain Python values (dict, list, str, int, float, bool, None), read event by
    event (no node graph is built; libyaml's parser when installed). Refused with SensorModelError naming ``where``:
    aliases (``*name``: a few kB of them expand to GBs), nesting deeper than MAX_YAML_DEPTH, more than
    MAX_YAML_SCALARS scalars, integers of more than MAX_YAML_INT_CHARS characters, other non-string scalars of more
    than MAX_YAML_NUMBER_CHARS, sexagesimal numbers (``1:30``), binary data, other than the standard tags, mappings as
    keys, a key given twice in one mapping, several documents.
    Memory: the text plus ~32 bytes per scalar. yaml.YAMLError: bad syntax."""
    import yaml
    from yaml.constructor import SafeConstructor
    from yaml.resolver import Resolver

    loader = getattr(yaml, "CSafeLoader", yaml.SafeLoader)(text)
    constructor, resolver = SafeConstructor(), Resolver()
    stack: list[list[Any]] = []   # open collections: [list] or [dict, key or _NO_KEY]
    result: list[Any] = []
    scalars = documents = 0

    def add(value: Any) -> None:
        if not stack:
            result.append(value)
        elif isinstance(stack[-1][0], list):
            stack[-1][0].append(value)
        elif stack[-1][1] is _NO_KEY:
            if isinstance(value, (list, dict)):
                raise SensorModelError(f"{where}: a list or mapping as a mapping key is not accepted")
            if value in stack[-1][0]:
                raise SensorModelError(f"{where}: key {_quote(value)} given twice")
            stack[-1][1] = value
        else:
            stack[-1][0][stack[-1][1]] = value
            stack[-1][1] = _NO_KEY

    try:
        while loader.check_event():
            event = loader.get_event()
            if isinstance(event, yaml.AliasEvent):
                raise SensorModelError(f"{where}: YAML aliases (*{event.anchor}) are not accepted")
            if isinstance(event, yaml.DocumentStartEvent):
                documents += 1
                if documents > 1:
                    raise SensorModelError(f"{where}: holds more than one YAML document")
            elif isinstance(event, (yaml.SequenceStartEvent, yaml.MappingStartEvent)):
                seq = isinstance(event, yaml.SequenceStartEvent)
                if event.tag not in (None, "!", "tag:yaml.org,2002:" + ("seq" if seq else "map")):
                    raise SensorModelError(f"{where}: YAML tag {event.tag} is not accepted")
                if len(stack) >= MAX_YAML_DEPTH:
                    raise SensorModelError(f"{where}: nested deeper than {MAX_YAML_DEPTH} levels")
                stack.append([[]] if seq else [{}, _NO_KEY])
            elif isinstance(event, (yaml.SequenceEndEvent, yaml.MappingEndEvent)):
                add(stack.pop()[0])
            elif isinstance(event, yaml.ScalarEvent):
                scalars += 1
                if scalars > MAX_YAML_SCALARS:
                    raise SensorModelError(f"{where}: holds more than {MAX_YAML_SCALARS} values")
                if event.tag in (None, "!"):
                    _check_plain(event.value, where)
                tag = event.tag if event.tag not in (None, "!") else \
                    resolver.resolve(yaml.ScalarNode, event.value, event.implicit)
                _check_scalar(tag, event.value, where)
                construct = SafeConstructor.yaml_constructors.get(tag)
                if tag is None or construct is None or tag.endswith((":set", ":omap", ":pairs", ":seq", ":map",
                                                                     ":binary")):
                    raise SensorModelError(f"{where}: YAML tag {tag} is not accepted")
                add(construct(constructor, yaml.ScalarNode(tag, event.value, style=event.style)))
    finally:
        loader.dispose()
    return result[0] if result else None


_NO_KEY = object()
#: First characters of a plain scalar that PyYAML may resolve to an int, float or timestamp.
_NUMBER_STARTS = frozenset("0123456789+-.")
_INT_TAG, _FLOAT_TAG, _STR_TAG = ("tag:yaml.org,2002:" + t for t in ("int", "float", "str"))


def _check_scalar(tag: str | None, text: str, where: str) -> None:
    """Refuse, before it is converted, a scalar whose conversion would be costly or surprising: an integer of more
    than MAX_YAML_INT_CHARS characters, any other non-string scalar of more than MAX_YAML_NUMBER_CHARS, a YAML 1.1
    sexagesimal number (``1:30``: base 60)."""
    if tag == _STR_TAG:
        return
    if tag == _INT_TAG and len(text) > MAX_YAML_INT_CHARS:
        raise SensorModelError(f"{where}: an integer of {len(text)} characters (at most {MAX_YAML_INT_CHARS})")
    if len(text) > MAX_YAML_NUMBER_CHARS:
        raise SensorModelError(f"{where}: a number of {len(text)} characters (at most {MAX_YAML_NUMBER_CHARS})")
    if tag in (_INT_TAG, _FLOAT_TAG) and ":" in text:
        raise SensorModelError(f"{where}: the sexagesimal number {_quote(text)} (YAML 1.1 base 60) is not accepted; "
                               "write plain decimal numbers")


def _check_plain(text: str, where: str) -> None:
    """Refuse, before the resolver sees it, a long untagged scalar that starts like a number and holds ':': PyYAML's
    YAML 1.1 rules try it as a sexagesimal number (``1:59:59...``), whose regular expression takes ~60 bytes per
    character (1.2 GB for 20 MB) even to fail. Any other long scalar is resolved in linear time and memory."""
    if len(text) > MAX_YAML_NUMBER_CHARS and text[:1] in _NUMBER_STARTS and ":" in text:
        raise SensorModelError(f"{where}: a number of {len(text)} characters (at most {MAX_YAML_NUMBER_CHARS}; a "
                               "value that starts with a digit and holds ':' reads as a YAML 1.1 sexagesimal number: "
                               "quote it if it is text)")


def shorten(text: str, limit: int = MAX_SHOWN_CHARS) -> str:
    """``text`` itself when at most ``limit`` characters, else its first ``limit`` and '…' (for messages)."""
    return text if len(text) <= limit else text[:limit] + "…"


def _quote(value: Any) -> str:
    """``repr(value)`` for a message, at most about MAX_SHOWN_CHARS characters (a 30 MB class name is not echoed)."""
    if isinstance(value, str):
        return repr(value) if len(value) <= MAX_SHOWN_CHARS else repr(value[:MAX_SHOWN_CHARS]) + "…"
    if isinstance(value, (list, dict)):
        return f"a {'list' if isinstance(value, list) else 'mapping'} of {len(value)}"
    return shorten(repr(value))


def _kind(value: Any) -> str:
    """The YAML kind of a plain value, for messages."""
    kinds = {bool: "a boolean", str: "a string", float: "a float", int: "an integer", bytes: "binary data",
             list: "a list", dict: "a mapping", type(None): "null"}
    return kinds.get(type(value), type(value).__name__)


def vote_table_error(num_classes: int, num_bins: int) -> str | None:
    """Why a model of ``num_classes`` x ``num_bins`` is refused (its dense vote table, classes x bins x classes,
    beyond MAX_VOTE_TABLE_ENTRIES), or None."""
    entries = num_classes * num_bins * num_classes
    if entries <= MAX_VOTE_TABLE_ENTRIES:
        return None
    return (f"{num_classes} classes x {num_bins} depth bins need a vote table of {entries} entries ("
            f"{entries * 8 / 1e9:.1f} GB per copy), more than {MAX_VOTE_TABLE_ENTRIES} (2^24): use fewer depth bins "
            "or classes")


#: What a file that is not a regular file is, by its st_mode type test.
_FILE_KINDS = ((stat.S_ISDIR, "is a directory"), (stat.S_ISFIFO, "is a FIFO (named pipe)"),
               (stat.S_ISCHR, "is a character device"), (stat.S_ISBLK, "is a block device"),
               (stat.S_ISSOCK, "is a socket"))


def _not_regular(mode: int) -> str | None:
    """'is a directory' / 'is a FIFO (named pipe)' / ... for a file mode that is not a regular file, else None."""
    if stat.S_ISREG(mode):
        return None
    return next((what for test, what in _FILE_KINDS if test(mode)), "is not a regular file")


def _os_reason(exc: OSError) -> str:
    """How an OSError on a file reads after its name: 'does not exist' (ENOENT only), 'cannot be read: ...'."""
    if exc.errno == errno.ENOENT:
        return "does not exist"
    if exc.errno == errno.ENOTDIR:
        return "does not exist (a part of its path is not a directory)"
    if exc.errno == errno.ELOOP:
        return "cannot be read: symlink loop (too many levels of symbolic links)"
    reason = exc.strerror or type(exc).__name__
    return f"cannot be read: {reason[:1].lower()}{reason[1:]}"


def read_regular_file(path: Path, where: str, max_bytes: int) -> bytes:
    """The bytes of the regular file ``path``, at most ``max_bytes``. SensorModelError naming ``where`` otherwise:
    any OSError (missing, permission denied, name too long, symlink loop, I/O error), a directory, FIFO, device or
    socket (checked with ``os.stat`` before opening and again with ``fstat`` after a non-blocking open, so a FIFO
    is never waited on nor a device read), a file larger than ``max_bytes``."""
    try:
        st = os.stat(path)
    except OSError as exc:
        raise SensorModelError(f"{where} {_os_reason(exc)}") from None
    except ValueError as exc:                 # a NUL byte in the name
        raise SensorModelError(f"{where} cannot be read: {exc}") from None
    what = _not_regular(st.st_mode)
    if what is not None:
        raise SensorModelError(f"{where} {what}, not a regular file")
    if st.st_size > max_bytes:
        raise SensorModelError(f"{where} is {st.st_size} bytes, larger than {max_bytes}")
    try:
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0))
        with os.fdopen(fd, "rb") as fh:
            what = _not_regular(os.fstat(fh.fileno()).st_mode)   # replaced between the stat and the open
            if what is not None:
                raise SensorModelError(f"{where} {what}, not a regular file")
            raw = fh.read(max_bytes + 1)
    except OSError as exc:
        raise SensorModelError(f"{where} {_os_reason(exc)}") from None
    if len(raw) > max_bytes:
        raise SensorModelError(f"{where} is larger than {max_bytes} bytes")
    return raw


def _row_mode(row: np.ndarray) -> float:
    """The most frequent value of a row (ties: the smallest), 0.0 when no value repeats (nothing to share)."""
    values, counts = np.unique(row, return_counts=True)
    i = int(np.argmax(counts))
    return float(values[i]) if counts[i] > 1 else 0.0


def _array(value: Any, where: str, ndim: int) -> np.ndarray:
    """A float64 array of ``ndim`` dimensions from nested YAML lists (SensorModelError otherwise)."""
    if value is None:
        raise SensorModelError(f"{where} is missing")
    _check_numbers(value, where)
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SensorModelError(f"{where} must be nested lists of numbers of one shape") from None
    if a.ndim != ndim:
        raise SensorModelError(f"{where} must have {ndim} dimension(s), got shape {a.shape}")
    return a


def _check_numbers(value: Any, where: str) -> None:
    """Refuse nested lists whose leaves are not YAML integers or floats: a string ("0.5"), a boolean (true is 1),
    binary data, a date or null would otherwise be converted by numpy without a word."""
    todo = [value]
    while todo:
        v = todo.pop()
        if type(v) is list:
            if all(type(x) is float or type(x) is int for x in v):
                continue
            for x in v:
                if type(x) is list:
                    todo.append(x)
                elif type(x) is not float and type(x) is not int:
                    raise SensorModelError(f"{where} must hold numbers, found {_quote(x)} ({_kind(x)})")
        elif type(v) is not float and type(v) is not int:
            raise SensorModelError(f"{where} must hold numbers, found {_quote(v)} ({_kind(v)})")


def _short(a: np.ndarray) -> str:
    vals = ", ".join(f"{v:g}" for v in a[:6])
    return f"[{vals}{', ...' if a.size > 6 else ''}]"


def depth_bins(edges: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Bin b (int64, ``depth``'s shape) with edges[b] <= depth < edges[b + 1] of increasing ``edges`` (B + 1,);
    depths below edges[1] are in bin 0, beyond the last edge in bin B - 1 (the update kernels' rule too)."""
    return np.clip(np.searchsorted(edges, depth, side="right") - 1, 0, edges.size - 2)


def uniform_bin_count(max_depth: float, bin_width: float) -> float:
    """How many bins of ``bin_width`` reach ``max_depth`` (ceil, 1e-9 of slack), at least 1, as a float: inf when the
    quotient overflows (``8 / 1e-320``), so that callers compare it with MAX_DEPTH_BINS and never raise."""
    ratio = max_depth / bin_width - 1e-9
    return float(max(1, math.ceil(ratio))) if math.isfinite(ratio) else math.inf


def uniform_edges(max_depth: float, bin_width: float) -> np.ndarray:
    """Depth-bin edges 0, w, 2w, ..., >= max_depth [m] (SensorModelError beyond MAX_DEPTH_BINS bins)."""
    n = uniform_bin_count(max_depth, bin_width)
    if not n <= MAX_DEPTH_BINS:
        raise SensorModelError(f"depth {max_depth:g} m in bins of {bin_width:g} m needs more than {MAX_DEPTH_BINS} bins")
    return np.arange(int(n) + 1, dtype=np.float64) * bin_width
