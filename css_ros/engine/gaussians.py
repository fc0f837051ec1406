"""3D Gaussian Splatting model container with validated INRIA PLY load/save (SPEC section 1)."""
from __future__ import annotations

import hashlib
import os
import re
import tempfile
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import ModelError
from .atomic import new_file_mode
from .sh import SH_C0, num_sh_coeffs

__all__ = ["GaussianModel", "SH_C0", "num_sh_coeffs", "sh_degree_from_rest_count"]


_REST_COUNT_TO_DEGREE = {0: 0, 9: 1, 24: 2, 45: 3}
_SCALE_FIELDS = ("scale_0", "scale_1", "scale_2")
#: Largest log standard deviation accepted (e^20 m = 4.9e8 m; beyond, covariances overflow float32).
LOG_SCALE_MAX = 20.0
_ROT_FIELDS = ("rot_0", "rot_1", "rot_2", "rot_3")
_POS_FIELDS = ("x", "y", "z")
_NORMAL_FIELDS = ("nx", "ny", "nz")
_DC_FIELDS = ("f_dc_0", "f_dc_1", "f_dc_2")
_REST_RE = re.compile(r"^f_rest_(\d+)$")
_PLY_SCALAR_DTYPES = {
    np.dtype(t) for t in ("i1", "u1", "i2", "u2", "i4", "u4", "f4", "f8")
}


def sh_degree_from_rest_count(count: int) -> int:
    """SH degree from the number of ``f_rest_*`` fields (0, 9, 24, 45 -> 0..3); ValueError otherwise."""
    try:
        return _REST_COUNT_TO_DEGREE[int(count)]
    except KeyError:
        raise ValueError(
            f"{count} f_rest_* fields; expected 0, 9, 24 or 45 (SH degree 0..3)") from None


def _as_f32(name: str, value: np.ndarray, shape: tuple) -> np.ndarray:
    """Convert to a C-contiguous float32 array and check its shape (-1 = any length)."""
    try:
        arr = np.ascontiguousarray(np.asarray(value, dtype=np.float32))
    except (TypeError, ValueError) as exc:
        raise ModelError(f"GaussianModel.{name}: cannot convert to float32 ({exc})") from None
    if arr.ndim != len(shape) or any(s != -1 and s != a for s, a in zip(shape, arr.shape)):
        raise ModelError(
            f"GaussianModel.{name}: expected shape {tuple('N' if s == -1 else s for s in shape)}, "
            f"got {arr.shape}")
    return arr


def rotation_matrices_wxyz(q: np.ndarray) -> np.ndarray:
    """(N, 3, 3) float64 rotation matrices of unit quaternions (N, 4) in the PLY order (w, x, y, z) (SPEC §1)."""
    w, x, y, z = np.asarray(q, dtype=np.float64).T
    R = np.empty((len(w), 3, 3))
    R[:, 0, 0] = 1 - 2 * (y * y + z * z)
    R[:, 0, 1] = 2 * (x * y - w * z)
    R[:, 0, 2] = 2 * (x * z + w * y)
    R[:, 1, 0] = 2 * (x * y + w * z)
    R[:, 1, 1] = 1 - 2 * (x * x + z * z)
    R[:, 1, 2] = 2 * (y * z - w * x)
    R[:, 2, 0] = 2 * (x * z - w * y)
    R[:, 2, 1] = 2 * (y * z + w * x)
    R[:, 2, 2] = 1 - 2 * (x * x + y * y)
    return R


@dataclass(frozen=True, eq=False)
class GaussianModel:
    """A 3DGS model in the map frame, stored RAW exactly as in the INRIA PLY (so saving round-trips bit-exactly).

    Fields (all float32, C-contiguous; N Gaussians, K = (d+1)^2 SH coefficients per channel):

    - ``means`` (N, 3): centres in the map frame, metres.
    - ``sh`` (N, K, 3): SH coefficients; ``sh[:, 0, :]`` is the DC term (``f_dc_0..2``), ``sh[:, k, c]``
      for k >= 1 is file field ``f_rest_{c*(K-1) + k-1}`` (channel-major in the file).
    - ``opacity_logits`` (N,): pre-sigmoid opacity (file field ``opacity``).
    - ``log_scales`` (N, 3): natural log of the standard deviations in metres (``scale_0..2``).
    - ``rotations`` (N, 4): raw, possibly unnormalised quaternion (w, x, y, z) = ``rot_0..3``.
    - ``normals`` (N, 3): ``nx ny nz`` if present in the file, zeros otherwise (unused by rendering).

    Arrays must not be modified in place: ``fingerprint`` is computed once and cached.
    """

    means: np.ndarray
    sh: np.ndarray
    opacity_logits: np.ndarray
    log_scales: np.ndarray
    rotations: np.ndarray
    normals: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        means = _as_f32("means", self.means, (-1, 3))
        n = means.shape[0]
        if n == 0:
            raise ModelError("GaussianModel: the model has zero Gaussians")
        sh = _as_f32("sh", self.sh, (n, -1, 3))
        if sh.shape[1] not in (1, 4, 9, 16):
            raise ModelError(
                f"GaussianModel.sh: {sh.shape[1]} coefficients per channel; expected 1, 4, 9 or 16 "
                "(SH degree 0..3)")
        logits = _as_f32("opacity_logits", self.opacity_logits, (n,))
        log_scales = _as_f32("log_scales", self.log_scales, (n, 3))
        rotations = _as_f32("rotations", self.rotations, (n, 4))
        if self.normals is None:
            normals = np.zeros((n, 3), dtype=np.float32)
        else:
            normals = _as_f32("normals", self.normals, (n, 3))
        for name, arr in (("means", means), ("sh", sh), ("opacity_logits", logits),
                          ("log_scales", log_scales), ("rotations", rotations)):
            bad = int(arr.size - np.count_nonzero(np.isfinite(arr)))
            if bad:
                raise ModelError(f"GaussianModel.{name}: {bad} non-finite value(s)")
        too_big = int(np.count_nonzero(log_scales > LOG_SCALE_MAX))
        if too_big:
            raise ModelError(f"GaussianModel.log_scales: {too_big} value(s) above {LOG_SCALE_MAX:g} (standard "
                             f"deviation above {np.exp(LOG_SCALE_MAX):.3g} m; max {float(log_scales.max()):g})")
        qnorm = np.linalg.norm(rotations.astype(np.float64), axis=1)
        if np.any(qnorm == 0.0):
            raise ModelError(
                f"GaussianModel.rotations: {int(np.count_nonzero(qnorm == 0.0))} zero quaternion(s)")
        object.__setattr__(self, "means", means)
        object.__setattr__(self, "sh", sh)
        object.__setattr__(self, "opacity_logits", logits)
        object.__setattr__(self, "log_scales", log_scales)
        object.__setattr__(self, "rotations", rotations)
        object.__setattr__(self, "normals", normals)

    def __repr__(self) -> str:
        """One line: N, SH degree and the bounding box of the means (metres); never the arrays."""
        lo, hi = self.means.min(axis=0), self.means.max(axis=0)
        box = " x ".join(f"[{a:.3g}, {b:.3g}]" for a, b in zip(lo, hi))
        return f"GaussianModel({self.num_gaussians} Gaussians, SH degree {self.sh_degree}, means in {box} m)"

    # ------------------------------------------------------------------ properties
    @property
    def num_gaussians(self) -> int:
        """Number of Gaussians N."""
        return int(self.means.shape[0])

    @property
    def sh_degree(self) -> int:
        """Spherical-harmonic degree d (0..3)."""
        return int(round(np.sqrt(self.sh.shape[1]))) - 1

    @property
    def opacities(self) -> np.ndarray:
        """(N,) float32 opacities in (0, 1): sigmoid(opacity_logits)."""
        x = self.opacity_logits.astype(np.float64)
        return (0.5 * (1.0 + np.tanh(0.5 * x))).astype(np.float32)  # overflow-free sigmoid

    @property
    def scales(self) -> np.ndarray:
        """(N, 3) float32 standard deviations in metres: exp(log_scales)."""
        return np.exp(self.log_scales)

    @property
    def quats_wxyz(self) -> np.ndarray:
        """(N, 4) float64 unit quaternions (w, x, y, z) (normalised ``rotations``)."""
        q = self.rotations.astype(np.float64)
        return q / np.linalg.norm(q, axis=1, keepdims=True)

    @property
    def base_colors(self) -> np.ndarray:
        """(N, 3) float32 view-independent RGB in [0, 1]: max(0, C0 * f_dc + 0.5) clipped to 1 (degree-0 colour)."""
        return np.clip(SH_C0 * self.sh[:, 0, :] + 0.5, 0.0, 1.0).astype(np.float32)

    @cached_property
    def fingerprint(self) -> str:
        """Hex SHA-256 over the shapes and raw bytes of means, sh, opacity_logits, log_scales, rotations.

        Identifies the model a semantic map was built on (normals are excluded: they do not affect rendering).
        """
        h = hashlib.sha256()
        h.update(f"css_ros-gaussians-v1 N={self.num_gaussians} K={self.sh.shape[1]}".encode())
        for arr in (self.means, self.sh, self.opacity_logits, self.log_scales, self.rotations):
            h.update(np.ascontiguousarray(arr, dtype="<f4").tobytes())
        return h.hexdigest()

    def covariances(self) -> np.ndarray:
        """(N, 3, 3) float64 world-frame covariances R S S^T R^T in m^2 (SPEC section 1)."""
        R = rotation_matrices_wxyz(self.quats_wxyz)
        M = R * self.scales.astype(np.float64)[:, None, :]
        return M @ np.swapaxes(M, 1, 2)

    def select(self, index: np.ndarray) -> "GaussianModel":
        """New model holding the Gaussians picked by ``index``: a bool mask (N,) or 1-D integer indices in [0, N)
        (repeats allowed, at most N of them). A mask must have dtype bool: a uint8 0/1 array is read as indices, as
        numpy reads it.

        Raises:
            ModelError: ``index`` is None, not bool/integer (floats included), a list mixing bools and integers, not
                1-D, a mask of another length, more than N indices, indices outside [0, N), or no Gaussian selected.
        """
        n = self.num_gaussians
        if isinstance(index, (list, tuple)) and any(isinstance(v, (bool, np.bool_)) for v in index) and \
                not all(isinstance(v, (bool, np.bool_)) for v in index):
            raise ModelError("select: index mixes bools and integers (True would be read as index 1): give a bool "
                             "mask or integer indices")
        try:
            idx = np.asarray(index)
        except (TypeError, ValueError) as exc:
            raise ModelError(f"select: index is not an array ({exc})") from None
        if idx.dtype.kind not in "biu" and idx.size > 0:
            raise ModelError(f"select: index must be a bool mask or integer indices, got "
                             f"{type(index).__name__} of dtype {idx.dtype}")
        if idx.ndim != 1:
            raise ModelError(f"select: index must be 1-D (a bool mask ({n},) or integer indices), got shape {idx.shape}")
        if idx.size == 0:
            raise ModelError("select: the index selects no Gaussian")
        if idx.dtype.kind == "b":
            if idx.shape != (n,):
                raise ModelError(f"select: bool mask has length {idx.size}, the model has {n} Gaussians")
            if not idx.any():
                raise ModelError("select: the index selects no Gaussian")
        elif idx.size > n:
            raise ModelError(f"select: {idx.size} indices for a model of {n} Gaussians (at most {n})")
        elif int(idx.min()) < 0 or int(idx.max()) >= n:
            raise ModelError(f"select: indices must be in [0, {n}), got values in [{int(idx.min())}, {int(idx.max())}]")
        return GaussianModel(self.means[idx], self.sh[idx], self.opacity_logits[idx],
                             self.log_scales[idx], self.rotations[idx], self.normals[idx])

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_activated(cls, means: np.ndarray, scales: np.ndarray, quats_wxyz: np.ndarray,
                       opacities: np.ndarray, colors: np.ndarray) -> "GaussianModel":
        """Build an SH-degree-0 model from activated quantities.

        Args:
            means: (N, 3) centres in the map frame, metres.
            scales: (N, 3) standard deviations in metres, > 0.
            quats_wxyz: (N, 4) rotations (w, x, y, z); normalised here.
            opacities: (N,) in (0, 1); clipped to [1e-6, 1 - 1e-6] before the logit.
            colors: (N, 3) RGB in [0, 1]; stored as f_dc = (color - 0.5) / C0.
        """
        means = np.asarray(means, dtype=np.float64)
        n = means.shape[0] if means.ndim == 2 else -1
        scales = np.asarray(scales, dtype=np.float64)
        q = np.asarray(quats_wxyz, dtype=np.float64)
        o = np.asarray(opacities, dtype=np.float64)
        c = np.asarray(colors, dtype=np.float64)
        for name, arr, shape in (("means", means, (n, 3)), ("scales", scales, (n, 3)),
                                 ("quats_wxyz", q, (n, 4)), ("opacities", o, (n,)),
                                 ("colors", c, (n, 3))):
            if arr.shape != shape or n < 0:
                raise ModelError(f"from_activated: {name} has shape {arr.shape}, expected {shape} "
                                 "(N taken from means (N, 3))")
            if not np.all(np.isfinite(arr)):
                raise ModelError(f"from_activated: {name} holds non-finite values")
        if np.any(scales <= 0):
            raise ModelError("from_activated: scales must be > 0 (standard deviations in metres)")
        qn = np.linalg.norm(q, axis=1, keepdims=True)
        if np.any(qn == 0):
            raise ModelError("from_activated: quats_wxyz contains a zero quaternion")
        o = np.clip(o, 1e-6, 1.0 - 1e-6)
        sh = ((c - 0.5) / SH_C0)[:, None, :]
        return cls(means=means, sh=sh, opacity_logits=np.log(o / (1.0 - o)),
                   log_scales=np.log(scales), rotations=q / qn)

    @classmethod
    def from_ply(cls, path: str | os.PathLike) -> "GaussianModel":
        """Load an INRIA-layout 3DGS PLY (binary little/big endian or ASCII).

        SH degree is inferred from the number of ``f_rest_*`` fields; extra fields are ignored; ``nx ny nz`` are
        optional. Raises ModelError (naming the file and the field) for a missing/unreadable/truncated file, a
        missing ``vertex`` element or required field, zero vertices, or non-finite values in a required field.
        """
        from plyfile import PlyData  # local import keeps module import light

        p = Path(path)
        if not p.is_file():
            raise ModelError(f"{p}: splat model file does not exist (or is not a regular file)")
        try:
            with open(p, "rb") as fh:
                ply = PlyData.read(fh, mmap="r")  # memory-mapped: fast for large binary files
        except Exception as exc:  # plyfile raises many types for malformed/truncated files
            raise ModelError(f"{p}: cannot parse as PLY ({type(exc).__name__}: {exc}); "
                             "the file may be truncated (declares more vertices than it holds) "
                             "or not a PLY file") from exc
        try:
            vertex = ply["vertex"]
        except KeyError:
            names = [e.name for e in ply.elements]
            raise ModelError(f"{p}: no 'vertex' element (elements: {names})") from None
        data = vertex.data
        names = list(data.dtype.names or ())
        if vertex.count == 0 or len(data) == 0:
            raise ModelError(f"{p}: the 'vertex' element has zero vertices")
        if len(data) != vertex.count:
            raise ModelError(f"{p}: header declares {vertex.count} vertices but {len(data)} were read "
                             "(truncated file)")

        rest_idx = sorted(int(m.group(1)) for m in map(_REST_RE.match, names) if m)
        try:
            degree = sh_degree_from_rest_count(len(rest_idx))
        except ValueError as exc:
            raise ModelError(f"{p}: field 'f_rest_*': {exc}") from None
        k = num_sh_coeffs(degree)
        rest_fields = tuple(f"f_rest_{i}" for i in range(3 * (k - 1)))
        required = _POS_FIELDS + _DC_FIELDS + rest_fields + ("opacity",) + _SCALE_FIELDS + _ROT_FIELDS
        for name in required:
            if name not in names:
                raise ModelError(f"{p}: required vertex field '{name}' is missing")
            kind = data.dtype[name].kind
            if kind not in "fiu" or data.dtype[name].shape != ():
                raise ModelError(f"{p}: vertex field '{name}' must be a scalar number, "
                                 f"got dtype {data.dtype[name]}")

        def stack(fields: tuple[str, ...]) -> np.ndarray:
            out = np.empty((len(data), len(fields)), dtype=np.float32)
            for j, f in enumerate(fields):
                col = np.asarray(data[f])
                bad = int(col.size - np.count_nonzero(np.isfinite(col)))
                if bad:
                    raise ModelError(f"{p}: vertex field '{f}' has {bad} non-finite value(s) "
                                     f"(NaN/Inf) out of {col.size}")
                out[:, j] = col
            if not np.all(np.isfinite(out)):
                bad_f = [f for j, f in enumerate(fields) if not np.all(np.isfinite(out[:, j]))]
                raise ModelError(f"{p}: vertex field(s) {bad_f} overflow float32")
            return out

        means = stack(_POS_FIELDS)
        dc = stack(_DC_FIELDS)
        sh = np.empty((len(data), k, 3), dtype=np.float32)
        sh[:, 0, :] = dc
        if k > 1:
            rest = stack(rest_fields).reshape(len(data), 3, k - 1)  # channel-major
            sh[:, 1:, :] = rest.transpose(0, 2, 1)
        logits = stack(("opacity",))[:, 0]
        log_scales = stack(_SCALE_FIELDS)
        rotations = stack(_ROT_FIELDS)
        normals = None
        if all(f in names for f in _NORMAL_FIELDS):
            normals = np.stack([np.asarray(data[f], dtype=np.float32) for f in _NORMAL_FIELDS], axis=1)
        try:
            model = cls(means=means, sh=sh, opacity_logits=logits, log_scales=log_scales,
                        rotations=rotations, normals=normals)
        except ModelError as exc:
            raise ModelError(f"{p}: {exc}") from None
        object.__setattr__(model, "source", p)  # the file it came from, named by error messages (not compared)
        return model

    # ------------------------------------------------------------------ saving
    def ply_fields(self) -> list[str]:
        """Names of the INRIA-layout vertex fields this model writes, in file order."""
        k = self.sh.shape[1]
        return (list(_POS_FIELDS) + list(_NORMAL_FIELDS) + list(_DC_FIELDS)
                + [f"f_rest_{i}" for i in range(3 * (k - 1))] + ["opacity"]
                + list(_SCALE_FIELDS) + list(_ROT_FIELDS))

    def to_ply(self, path: str | os.PathLike, binary: bool = True,
               extra_fields: dict[str, np.ndarray] | None = None) -> None:
        """Write the model as an INRIA-layout PLY, atomically (temp file in the same dir + os.replace).

        Layout: ``x y z nx ny nz f_dc_0..2 f_rest_* opacity scale_0..2 rot_0..3`` (float32), then each of
        ``extra_fields`` (name -> (N,) array, dtype kept: int8/uint8/int16/uint16/int32/uint32/float32/float64;
        bool is written as uint8, int64/uint64 must fit int32/uint32). ``binary=False`` writes ASCII.
        """
        from plyfile import PlyData, PlyElement

        p = Path(path)
        n = self.num_gaussians
        base = self.ply_fields()
        extras: list[tuple[str, np.ndarray]] = []
        for name, values in (extra_fields or {}).items():
            if not isinstance(name, str) or not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
                raise ModelError(f"to_ply({p}): extra field name {name!r} is not a valid PLY property name")
            if name in base:
                raise ModelError(f"to_ply({p}): extra field '{name}' clashes with a model field")
            arr = np.asarray(values)
            if arr.shape != (n,):
                raise ModelError(f"to_ply({p}): extra field '{name}' has shape {arr.shape}, expected ({n},)")
            if arr.dtype == np.bool_:
                arr = arr.astype(np.uint8)
            elif arr.dtype in (np.dtype(np.int64), np.dtype(np.uint64)):
                target = np.int32 if arr.dtype.kind == "i" else np.uint32
                info = np.iinfo(target)
                if arr.size and (arr.min() < info.min or arr.max() > info.max):
                    raise ModelError(f"to_ply({p}): extra field '{name}' does not fit {np.dtype(target)}")
                arr = arr.astype(target)
            if arr.dtype.kind in "iuf":
                arr = arr.astype(arr.dtype.newbyteorder("="), copy=False)
            if arr.dtype not in _PLY_SCALAR_DTYPES:
                raise ModelError(f"to_ply({p}): extra field '{name}' has unsupported dtype {arr.dtype}")
            extras.append((name, arr))

        dtype = [(f, "<f4") for f in base] + [(name, arr.dtype.newbyteorder("<").str) for name, arr in extras]
        rec = np.empty(n, dtype=dtype)
        k = self.sh.shape[1]
        for j, f in enumerate(_POS_FIELDS):
            rec[f] = self.means[:, j]
        for j, f in enumerate(_NORMAL_FIELDS):
            rec[f] = self.normals[:, j]
        for j, f in enumerate(_DC_FIELDS):
            rec[f] = self.sh[:, 0, j]
        for c in range(3):
            for kk in range(1, k):
                rec[f"f_rest_{c * (k - 1) + kk - 1}"] = self.sh[:, kk, c]
        rec["opacity"] = self.opacity_logits
        for j, f in enumerate(_SCALE_FIELDS):
            rec[f] = self.log_scales[:, j]
        for j, f in enumerate(_ROT_FIELDS):
            rec[f] = self.rotations[:, j]
        for name, arr in extras:
            rec[name] = arr

        ply = PlyData([PlyElement.describe(rec, "vertex")], text=not binary, byte_order="<")
        directory = p.parent if str(p.parent) else Path(".")
        tmp_name = None
        try:
            with tempfile.NamedTemporaryFile("wb", dir=directory, prefix=f".{p.name}.",
                                             suffix=".tmp", delete=False) as fh:
                tmp_name = fh.name
                ply.write(fh)
                fh.flush()
                os.fsync(fh.fileno())
            os.chmod(tmp_name, (p.stat().st_mode & 0o777) if p.exists() else new_file_mode())
            os.replace(tmp_name, p)
            tmp_name = None
        except OSError as exc:
            raise ModelError(f"to_ply({p}): cannot write ({exc})") from exc
        finally:
            if tmp_name is not None:
                try:
                    os.unlink(tmp_name)
                except OSError:
                    pass
