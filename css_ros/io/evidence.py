"""Evidence exchange between css_nodes of one splat: the packet encoding and the exactly-once ledger (ROS-free).

A node publishes only the evidence it fused itself (never what it received: no echo), as numbered packets
carried in ``std_msgs/UInt8MultiArray`` (``data`` = the bytes below; layout unused). Little endian:

=========  ======  =====================================================================================
offset     type    field
=========  ======  =====================================================================================
0          4 B     magic ``CSSE``
4          u16     format version (1)
6          u8      kind: 0 delta (add these rows), 1 snapshot part (these rows *are* the source's total)
7          u8      reserved (0)
8          32 B    origin id, ASCII, NUL padded (unique per publishing node)
40         32 B    SHA-256 digest of the splat model (``GaussianModel.fingerprint``)
72         u64     sequence number (1, 2, ... per origin; every packet, deltas and snapshot parts alike)
80         u64     snapshot id (the sequence number of the snapshot's first part; 0 for deltas)
88         u32     range start (snapshot: first Gaussian the part covers; 0 for deltas)
92         u32     range end (snapshot: one past the last Gaussian it covers; N for deltas)
96         u32     part index (snapshot), 0 for deltas
100        u32     part count (snapshot), 1 for deltas
104        u32     number of classes C
108        u32     number of rows R (≤ the bound set by the node)
112        f64     prior α_0 of the publishing map
120        R u32   Gaussian ids, strictly increasing, inside the range
120 + 4R   R·C f64 evidence per row and class (κ-weighted label counts, ≥ 0)
=========  ======  =====================================================================================

A snapshot of a source is a run of parts with consecutive sequence numbers whose ranges tile [0, N); a part
replaces that source's evidence on its range (rows left out are zero). A receiver applies deltas of a source
only while it is in step with it (the next sequence number); a gap, or a late start, puts the source out of
step until the last part of the next complete snapshot has been applied. Old or repeated sequence numbers are
refused.
"""
from __future__ import annotations

import struct
from dataclasses import dataclass

import numpy as np
from numba import njit

from ..errors import InputError

__all__ = ["EvidencePacket", "encode_packet", "decode_packet", "EvidenceLedger", "DELTA", "SNAPSHOT",
           "MAX_INCREMENT", "HEADER_SIZE", "ORIGIN_BYTES"]

MAGIC = b"CSSE"
VERSION = 1
DELTA = 0
SNAPSHOT = 1
ORIGIN_BYTES = 32
_HEADER = struct.Struct("<4sHBB32s32sQQIIIIIId")
HEADER_SIZE = _HEADER.size
#: Largest evidence one packet may carry for one Gaussian and class (κ ≤ 1 per pixel: 1e9 is ~100 frames of
#: a 10-megapixel camera on one Gaussian); larger values are refused as corrupt.
MAX_INCREMENT = 1e9
#: Own-evidence changes below this fraction of a Gaussian's total are rounding (own = α - α_0 - received is
#: a difference of float64 sums) and are not published: received evidence never comes back as an echo.
ROUNDING_FRACTION = 1e-12


@dataclass(frozen=True)
class EvidencePacket:
    """One decoded evidence packet (see the module docstring for the fields)."""

    kind: int
    origin: str
    fingerprint_digest: bytes
    seq: int
    snapshot_id: int
    range_start: int
    range_end: int
    part: int
    parts: int
    num_classes: int
    prior: float
    rows: np.ndarray     # (R,) uint32 Gaussian ids
    values: np.ndarray   # (R, C) float64 evidence


def encode_packet(kind: int, origin: str, fingerprint: str, seq: int, rows: np.ndarray, values: np.ndarray,
                  prior: float, num_gaussians: int, snapshot_id: int = 0, range_start: int = 0,
                  range_end: int | None = None, part: int = 0, parts: int = 1) -> bytes:
    """The bytes of one packet. ``fingerprint``: hex SHA-256 of the model; ``values`` (R, C) float64."""
    origin_b = origin.encode("ascii")
    if len(origin_b) > ORIGIN_BYTES or not origin_b:
        raise InputError(f"origin id must be 1..{ORIGIN_BYTES} ASCII characters, got {origin!r}")
    values = np.ascontiguousarray(values, dtype="<f8")
    rows = np.ascontiguousarray(rows, dtype="<u4")
    header = _HEADER.pack(MAGIC, VERSION, kind, 0, origin_b, bytes.fromhex(fingerprint), seq, snapshot_id,
                          range_start, num_gaussians if range_end is None else range_end, part, parts,
                          values.shape[1], len(rows), prior)
    return header + rows.tobytes() + values.tobytes()


def decode_packet(data: bytes, max_rows: int) -> EvidencePacket:
    """Parse and check one packet's structure (sizes, magic, version, kinds, ranges, value sanity).

    Raises:
        InputError: with a short reason (used as the diagnostics key).
    """
    if len(data) < HEADER_SIZE:
        raise InputError("truncated packet")
    (magic, version, kind, _, origin_b, digest, seq, snap, lo, hi, part, parts, c, r,
     prior) = _HEADER.unpack_from(data)
    if magic != MAGIC or version != VERSION:
        raise InputError("not a css evidence packet (magic/version)")
    if kind not in (DELTA, SNAPSHOT):
        raise InputError("unknown packet kind")
    if r > max_rows:
        raise InputError("too many rows in one packet")
    if c < 1 or len(data) != HEADER_SIZE + r * (4 + 8 * c):
        raise InputError("packet size does not match its header")
    if seq < 1 or parts < 1 or part >= parts or lo > hi:
        raise InputError("bad sequence / part / range fields")
    try:
        origin = origin_b.rstrip(b"\0").decode("ascii")
    except UnicodeDecodeError:
        raise InputError("origin id is not ASCII") from None
    if not origin:
        raise InputError("empty origin id")
    rows = np.frombuffer(data, dtype="<u4", count=r, offset=HEADER_SIZE).astype(np.int64)
    values = np.frombuffer(data, dtype="<f8", count=r * c, offset=HEADER_SIZE + 4 * r).reshape(r, c)
    if r and (np.any(np.diff(rows) <= 0) or rows[0] < lo or rows[-1] >= hi):
        raise InputError("row ids not strictly increasing inside the range")
    if not np.all(np.isfinite(values)):
        raise InputError("non-finite evidence")
    if np.any(values < 0):
        raise InputError("negative evidence")
    if np.any(values > MAX_INCREMENT):
        raise InputError("evidence above the per-packet bound")
    return EvidencePacket(kind, origin, digest, seq, snap, lo, hi, part, parts, c, prior, rows,
                          values.astype(np.float64))


@dataclass
class SourceState:
    """What a receiver knows of one source. ``evidence``: (N, C) float64, that source's evidence in the map."""

    evidence: np.ndarray
    last_seq: int = 0
    in_step: bool = False
    snapshot_id: int = 0        # snapshot being received (0: none)
    snapshot_next_part: int = 0
    packets: int = 0


class EvidenceLedger:
    """Exactly-once bookkeeping of the evidence received from other nodes (one per map; not thread-safe).

    ``apply`` changes the map's concentrations and returns None, or returns the reason a packet was refused
    (the map is then unchanged). Memory: 8·N·C bytes per source, at most ``max_sources`` sources.
    """

    def __init__(self, own_origin: str, fingerprint: str, num_gaussians: int, num_classes: int, prior: float,
                 max_sources: int, max_concentration: float = 1e15) -> None:
        self.own_origin = own_origin
        self.digest = bytes.fromhex(fingerprint)
        self.n, self.c, self.prior = num_gaussians, num_classes, prior
        self.max_sources = max_sources
        self.max_concentration = max_concentration
        self.sources: dict[str, SourceState] = {}
        self._total = np.zeros((num_gaussians, num_classes))   # Σ over sources of their evidence, kept in step

    def received_total(self) -> np.ndarray:
        """(N, C) float64 Σ over sources of their evidence in the map, maintained as packets are applied (no
        pass over the sources: the publisher reads it every period). Read-only for the caller."""
        return self._total

    def forget(self) -> None:
        """The map was reset or replaced: every source's evidence in it is gone; each must re-sync by snapshot."""
        for s in self.sources.values():
            s.evidence[...] = 0.0
            s.in_step = False
        self._total[...] = 0.0

    def apply(self, pkt: EvidencePacket, concentrations: np.ndarray) -> str | None:
        """Apply one decoded packet to ``concentrations`` (N, C) in place, or return why it was refused."""
        if pkt.origin == self.own_origin:
            return "own evidence (echo)"
        if pkt.fingerprint_digest != self.digest:
            return "evidence of another splat model"
        if pkt.num_classes != self.c or pkt.prior != self.prior:
            return "evidence of another class count or prior"
        if pkt.range_end > self.n or (pkt.rows.size and pkt.rows[-1] >= self.n):
            return "Gaussian id beyond the model"
        state = self.sources.get(pkt.origin)
        if state is None:
            if len(self.sources) >= self.max_sources:
                return "too many sources"
            state = SourceState(np.zeros((self.n, self.c)))
            self.sources[pkt.origin] = state
        if pkt.seq <= state.last_seq:
            return "replayed or duplicate sequence number"
        rows = pkt.rows
        if pkt.kind == DELTA:
            if not state.in_step or pkt.seq != state.last_seq + 1:
                if state.in_step:
                    state.in_step = False
                state.last_seq = pkt.seq
                return "sequence gap or late start: waiting for a snapshot"
            new_alpha = concentrations[rows] + pkt.values
            if np.any(new_alpha > self.max_concentration):
                return "evidence would exceed the concentration bound"
            concentrations[rows] = new_alpha
            state.evidence[rows] += pkt.values
            self._total[rows] += pkt.values
        else:
            if pkt.part == 0:
                state.snapshot_id, state.snapshot_next_part = pkt.seq, 0
            if pkt.snapshot_id != state.snapshot_id or pkt.part != state.snapshot_next_part:
                state.snapshot_id, state.last_seq = 0, pkt.seq
                state.in_step = False
                return "incomplete snapshot: waiting for the next one"
            lo, hi = pkt.range_start, pkt.range_end
            block = np.zeros((hi - lo, self.c))
            block[rows - lo] = pkt.values
            new_alpha = concentrations[lo:hi] - state.evidence[lo:hi] + block
            if np.any(new_alpha > self.max_concentration):
                return "evidence would exceed the concentration bound"
            concentrations[lo:hi] = np.maximum(new_alpha, self.prior)
            self._total[lo:hi] += block - state.evidence[lo:hi]
            state.evidence[lo:hi] = block
            state.snapshot_next_part += 1
            if state.snapshot_next_part == pkt.parts:
                state.in_step = True
                state.snapshot_id = 0
        state.last_seq = pkt.seq
        state.packets += 1
        return None


class EvidenceOutbox:
    """The packets a node publishes: deltas of its own evidence since the last call, and snapshots of it.

    Own evidence = α - α_0 - (evidence received from other sources): received evidence is never re-published.
    Memory: 8·N·C bytes (what was published so far).
    """

    def __init__(self, origin: str, fingerprint: str, num_gaussians: int, num_classes: int, prior: float,
                 max_rows: int) -> None:
        self.origin, self.fingerprint = origin, fingerprint
        self.n, self.c, self.prior = num_gaussians, num_classes, prior
        self.max_rows = max(1, int(max_rows))
        self.published = np.zeros((num_gaussians, num_classes))
        self.seq = 0
        z = np.zeros((1, 1))
        _grown_rows(z, z, z, 0.0, 0.0, np.empty(1, np.int64))   # compile (or load) now, not under the map lock

    def own(self, concentrations: np.ndarray, received: np.ndarray) -> np.ndarray:
        """(N, C) this node's own evidence (rounding-level values set to 0)."""
        own = concentrations - self.prior - received
        own[own <= ROUNDING_FRACTION * concentrations.sum(axis=1, keepdims=True)] = 0.0
        return own

    def reset(self) -> None:
        """Forget what was published (after a map reset / load: the next snapshot re-states the total)."""
        self.published[...] = 0.0

    def deltas(self, concentrations: np.ndarray, received: np.ndarray) -> list[bytes]:
        """Packets of the own evidence added since the last call (rows that grew), at most ``max_rows`` rows each.

        One fused pass over the map (:func:`_grown_rows`, no (N, C) temporaries): the publisher runs this every
        ``evidence_period`` while holding the map lock. The same rule as :meth:`own` and :meth:`snapshot`: own
        evidence below ROUNDING_FRACTION of a row's total counts as 0, and a row is sent when some class grew by
        more than that.
        """
        changed = _grown_rows(concentrations, received, self.published, self.prior, ROUNDING_FRACTION,
                              np.empty(self.n, np.int64))
        out = []
        for a in range(0, changed.size, self.max_rows):
            rows = changed[a:a + self.max_rows]
            own = self.own(concentrations[rows], received[rows])
            vals = np.maximum(own - self.published[rows], 0.0)
            self.published[rows] += vals
            self.seq += 1
            out.append(encode_packet(DELTA, self.origin, self.fingerprint, self.seq, rows, vals, self.prior, self.n))
        return out

    def snapshot(self, own: np.ndarray) -> list[bytes]:
        """Packets stating this node's whole own evidence (parts tiling [0, N)); deltas continue after it."""
        self.published[...] = own
        nz = np.flatnonzero(np.any(own != 0.0, axis=1))
        chunks = [nz[a:a + self.max_rows] for a in range(0, nz.size, self.max_rows)] or [nz]
        starts = [0] + [int(ch[0]) for ch in chunks[1:]]
        ends = starts[1:] + [self.n]
        first = self.seq + 1
        out = []
        for k, (rows, lo, hi) in enumerate(zip(chunks, starts, ends)):
            self.seq += 1
            out.append(encode_packet(SNAPSHOT, self.origin, self.fingerprint, self.seq, rows, own[rows], self.prior,
                                     self.n, snapshot_id=first, range_start=lo, range_end=hi, part=k,
                                     parts=len(chunks)))
        return out


@njit(cache=True, nogil=True)
def _grown_rows(alpha, received, published, prior, frac, scratch):  # pragma: no cover - compiled
    """Rows n where some class c has own - published > frac * sum_c alpha[n] (own = alpha - prior - received,
    set to 0 at or below that floor), in increasing order: :meth:`EvidenceOutbox.deltas`' test in one pass."""
    m = 0
    for n in range(alpha.shape[0]):
        total = 0.0
        for c in range(alpha.shape[1]):
            total += alpha[n, c]
        floor = frac * total
        for c in range(alpha.shape[1]):
            own = alpha[n, c] - prior - received[n, c]
            if own <= floor:
                own = 0.0
            if own - published[n, c] > floor:
                scratch[m] = n
                m += 1
                break
    return scratch[:m].copy()
