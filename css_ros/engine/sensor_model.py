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

import hashlib
import math
import os
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

    @staticmethod
    def features(expectation: np.ndarray, evidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(logit E with E clipped to [1e-6, 1 - 1e-6], log(1 + evidence)), float64, the inputs' shape: the two
        features of the logistic score (css_calibrate fits its coefficients on these)."""
        e = np.clip(np.asarray(expectation, dtype=np.float64), E_CLIP, 1.0 - E_CLIP)
        return np.log(e / (1.0 - e)), np.log1p(np.maximum(np.asarray(evidence, dtype=np.float64), 0.0))

    def score(self, expectation: np.ndarray, evidence: np.ndarray) -> np.ndarray:
        """The logistic score before the isotonic correction (same shape as the inputs, float64)."""
        logit_e, log_ev = self.features(expectation, evidence)
        z = self.coef[0] * logit_e + self.coef[1] * log_ev + self.coef[2]
        return 0.5 * (1.0 + np.tanh(0.5 * np.clip(z, -Z_CLIP, Z_CLIP)))

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
        if coef.shape != (3,):
            raise SensorModelError(f"{where}.coef: expected 3 numbers, got {coef.size}")
        if kx.shape != ky.shape or kx.size < 1:
            raise SensorModelError(f"{where}: knots_x and knots_y must be non-empty and of one length")
        for name, a in (("coef", coef), ("knots_x", kx), ("knots_y", ky)):
            if not np.all(np.isfinite(a)):
                raise SensorModelError(f"{where}.{name} must be finite numbers, got {_short(a)}")
        if np.any(np.diff(kx) <= 0) or kx[0] < 0 or kx[-1] > 1:
            raise SensorModelError(f"{where}.knots_x must be strictly increasing within [0, 1]")
        if np.any(np.diff(ky) < 0) or ky[0] < 0 or ky[-1] > 1:
            raise SensorModelError(f"{where}.knots_y must be non-decreasing within [0, 1]")
        return cls(coef, kx, ky)


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
        if self.weight.shape != (c, b):
            raise SensorModelError(f"{where}: weight has shape {self.weight.shape}, expected ({c} classes, {b} bins)")
        if not np.all(np.isfinite(self.weight)) or np.any(self.weight < 0) or np.any(self.weight > 1):
            raise SensorModelError(f"{where}: weight entries must be finite and in [0, 1]")
        if self.confusion is not None:
            p = self.confusion
            if p.shape != (c, b, c):
                raise SensorModelError(f"{where}: confusion has shape {p.shape}, expected ({c}, {b}, {c})")
            if not np.all(np.isfinite(p)) or np.any(p < 0):
                raise SensorModelError(f"{where}: confusion entries must be finite and >= 0")
            bad = np.abs(p.sum(axis=2) - 1.0) > ROW_SUM_TOLERANCE
            if np.any(bad):
                y, bb = np.argwhere(bad)[0]
                raise SensorModelError(f"{where}: confusion row of label {self.class_names[y]!r}, depth bin {bb} "
                                       f"sums to {p[y, bb].sum():.6g}, not 1")

    def check_classes(self, class_names: Sequence[str], where: str | None = None) -> None:
        """Refuse a model made for other classes than ``class_names`` (the map's class file)."""
        names = tuple(class_names)
        if names != self.class_names:
            where = where or self.source or "sensor model"
            if len(names) != len(self.class_names):
                raise SensorModelError(f"{where} is for {len(self.class_names)} classes, the map has {len(names)}")
            diff = next(i for i, (a, b) in enumerate(zip(names, self.class_names)) if a != b)
            raise SensorModelError(f"{where}: class {diff} is {self.class_names[diff]!r}, the map's class file says "
                                   f"{names[diff]!r}")

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
        if d.get("version") != SENSOR_MODEL_VERSION:
            raise SensorModelError(f"{where} has version {d.get('version')!r}, this css_ros reads "
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
            SensorModelError: one line naming the file: missing, too large, not YAML, YAML beyond what
                :func:`read_plain_yaml` reads (aliases, deep nesting, huge integers, too many values), not a sensor
                model, or any failed check of :meth:`validate` / :meth:`check_classes` / the confidence map.
        """
        path = Path(path)
        if not path.is_file():
            raise SensorModelError(f"sensor model {path} does not exist")
        size = path.stat().st_size
        if size > MAX_SENSOR_MODEL_BYTES:
            raise SensorModelError(f"sensor model {path} is {size} bytes, larger than {MAX_SENSOR_MODEL_BYTES}")
        try:
            with open(path, "rb") as fh:
                raw = fh.read(MAX_SENSOR_MODEL_BYTES + 1)
            d = read_plain_yaml(raw.decode("utf-8"), f"sensor model {path}")
        except (OSError, UnicodeDecodeError, YAMLError, ValueError, OverflowError) as exc:
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            raise SensorModelError(f"sensor model {path} is not a readable YAML file ({first})") from None
        model = cls.from_dict(d, f"sensor model {path}")
        if class_names is not None:
            model.check_classes(class_names)
        return model


def read_plain_yaml(text: str, where: str) -> Any:
    """The one document of ``text`` as plain Python values (dict, list, str, int, float, bool, None), read event by
    event (no node graph is built; libyaml's parser when installed). Refused with SensorModelError naming ``where``:
    aliases (``*name``: a few kB of them expand to GBs), nesting deeper than MAX_YAML_DEPTH, more than
    MAX_YAML_SCALARS scalars, integers of more than MAX_YAML_INT_CHARS characters, other than the standard tags,
    mappings as keys, several documents. Memory: the text plus ~32 bytes per scalar. yaml.YAMLError: bad syntax."""
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
                tag = event.tag if event.tag not in (None, "!") else \
                    resolver.resolve(yaml.ScalarNode, event.value, event.implicit)
                if tag == "tag:yaml.org,2002:int" and len(event.value) > MAX_YAML_INT_CHARS:
                    raise SensorModelError(f"{where}: an integer of {len(event.value)} characters (at most "
                                           f"{MAX_YAML_INT_CHARS})")
                construct = SafeConstructor.yaml_constructors.get(tag)
                if tag is None or construct is None or tag.endswith((":set", ":omap", ":pairs", ":seq", ":map")):
                    raise SensorModelError(f"{where}: YAML tag {tag} is not accepted")
                add(construct(constructor, yaml.ScalarNode(tag, event.value, style=event.style)))
    finally:
        loader.dispose()
    return result[0] if result else None


_NO_KEY = object()


def _row_mode(row: np.ndarray) -> float:
    """The most frequent value of a row (ties: the smallest), 0.0 when no value repeats (nothing to share)."""
    values, counts = np.unique(row, return_counts=True)
    i = int(np.argmax(counts))
    return float(values[i]) if counts[i] > 1 else 0.0


def _array(value: Any, where: str, ndim: int) -> np.ndarray:
    """A float64 array of ``ndim`` dimensions from nested YAML lists (SensorModelError otherwise)."""
    if value is None:
        raise SensorModelError(f"{where} is missing")
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError):
        raise SensorModelError(f"{where} must be nested lists of numbers of one shape") from None
    if a.ndim != ndim:
        raise SensorModelError(f"{where} must have {ndim} dimension(s), got shape {a.shape}")
    return a


def _short(a: np.ndarray) -> str:
    vals = ", ".join(f"{v:g}" for v in a[:6])
    return f"[{vals}{', ...' if a.size > 6 else ''}]"


def depth_bins(edges: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Bin b (int64, ``depth``'s shape) with edges[b] <= depth < edges[b + 1] of increasing ``edges`` (B + 1,);
    depths below edges[1] are in bin 0, beyond the last edge in bin B - 1 (the update kernels' rule too)."""
    return np.clip(np.searchsorted(edges, depth, side="right") - 1, 0, edges.size - 2)


def uniform_edges(max_depth: float, bin_width: float) -> np.ndarray:
    """Depth-bin edges 0, w, 2w, ..., >= max_depth [m]."""
    n = max(1, int(math.ceil(max_depth / bin_width - 1e-9)))
    return np.arange(n + 1, dtype=np.float64) * bin_width
