"""Evidence exchange between css_nodes of one splat: the packet encoding and the exactly-once ledger (ROS-free).

A node publishes only the evidence it fused itself (never what it received: no echo), as numbered packets
carried in ``std_msgs/UInt8MultiArray`` (``data`` = the bytes below; layout unused). Little endian (format 2;
format 1 packets, of css_ros before the epoch and frame fields, are refused):

=========  ======  =====================================================================================
offset     type    field
=========  ======  =====================================================================================
0          4 B     magic ``CSSE``
4          u16     format version (2)
6          u8      kind: 0 delta (add these rows), 1 snapshot part (these rows *are* the source's total),
                   2 return part (a snapshot part of the *subject*'s evidence as the sender holds it)
7          u8      flags: bit 0 "resumed" (a snapshot of a node restarted with resume: peers holding more
                   frames of its previous epoch send it a return); other bits 0
8          32 B    origin id, ASCII, NUL padded (unique per publishing node)
40         32 B    SHA-256 digest of the splat model (``GaussianModel.fingerprint``)
72         u64     sequence number (1, 2, ... per origin and epoch; every packet, deltas and snapshot parts)
80         u64     snapshot id (the sequence number of the snapshot's first part; 0 for deltas)
88         u32     range start (snapshot: first Gaussian the part covers; 0 for deltas)
92         u32     range end (snapshot: one past the last Gaussian it covers; N for deltas)
96         u32     part index (snapshot), 0 for deltas
100        u32     part count (snapshot), 1 for deltas
104        u32     number of classes C
108        u32     number of rows R (≤ the bound set by the node)
112        f64     prior α_0 of the publishing map
120        u64     epoch: one id per start of the publishing node (and per map reset / load), ns since 1970
128        u64     frames: how many frames the source's evidence holds (its map's ``frames_observed``)
136        R u32   Gaussian ids, strictly increasing, inside the range
136 + 4R   R·C f64 evidence per row and class (κ-weighted label counts, ≥ 0)
end        32 B    return parts only: the subject's origin id, ASCII, NUL padded
=========  ======  =====================================================================================

A return (kind 2) gives a restarted node back its own evidence of its previous epoch as a peer holds it (the
frames it fused and published before a ``kill -9``, after its last checkpoint). Its origin is the sender (so the
allow-list and rate limits apply), epoch / frames are the subject's old epoch and frames, sequence numbers count
the return's parts (1, 2, ...; not the sender's stream), and the parts tile [0, N) as a snapshot's do. Only the
subject uses it (:class:`EvidenceRecovery`); other receivers ignore it.

A snapshot of a source is a run of parts with consecutive sequence numbers whose ranges tile [0, N); a part
replaces that source's evidence on its range (rows left out are zero). A receiver applies deltas of a source
only while it is in step with it (the same epoch and the next sequence number); a gap, a late start or a new
epoch (the source restarted, or reset / loaded its map) puts the source out of step until the last part of its
next complete snapshot has been applied. A snapshot re-states the source whatever its sequence number and epoch
(so a restart, or one forged packet with sequence 2^64 - 1, costs at most one snapshot period); old or repeated
sequence numbers of deltas are refused. A packet that is refused changes nothing (no source slot, no sequence
number). Bounds (``max_frame_evidence`` P = the largest image in pixels, since one frame adds at most one unit
of evidence per pixel, spread over the Gaussians it sees): a delta adds at most P·f per Gaussian, f = frames
since the source's previous delta; a source holds at most P·F in total, F = the frames it claims; within one
epoch F grows at most at ``max_frame_rate`` frames/s (plus a burst of FRAME_BURST_S seconds).
"""
from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable, Mapping

import numpy as np
from numba import njit

from ..engine.map_file import MAX_RECEIVED_SOURCES, SourceEvidence
from ..engine.spec import MAX_FRAMES
from ..errors import InputError
from ..engine.kernel_cache import bind_sources

if TYPE_CHECKING:
    from ..engine.semantic_map import SemanticMap

__all__ = ["EvidencePacket", "encode_packet", "decode_packet", "EvidenceLedger", "DELTA", "SNAPSHOT",
           "MAX_INCREMENT", "HEADER_SIZE", "ORIGIN_BYTES", "own_evidence", "new_epoch", "received_sources",
           "RETURN", "FLAG_RESUMED", "encode_return", "EvidenceRecovery", "RETURN_WINDOW_S",
           "NOT_NEEDED_REASON", "OriginBuckets", "FLOOD_REASON", "RETURN_AMPLIFICATION", "return_bytes",
           "WITHHELD_BUDGET", "WITHHELD_RATE", "DEFAULT_MAX_ROWS"]

MAGIC = b"CSSE"
VERSION = 2
DELTA = 0
SNAPSHOT = 1
RETURN = 2
FLAG_RESUMED = 1
#: Seconds a resumed node flags its snapshots "resumed" and accepts returns, counted from the first packet of a peer
#: that it applies (the start of the exchange: a peer discovered late, on a loaded host, still gets the whole window;
#: a refused packet, e.g. of another splat or a junk origin, does not start it).
RETURN_WINDOW_S = 60.0
ORIGIN_BYTES = 32
_HEADER = struct.Struct("<4sHBB32s32sQQIIIIIIdQQ")
HEADER_SIZE = _HEADER.size
#: Largest evidence one packet may carry for one Gaussian and class (κ ≤ 1 per pixel: 1e9 is ~100 frames of
#: a 10-megapixel camera on one Gaussian); larger values are refused as corrupt.
MAX_INCREMENT = 1e9
#: Own-evidence changes below this fraction of a Gaussian's total are rounding (own = α - α_0 - received is
#: a difference of float64 sums) and are not published: received evidence never comes back as an echo.
ROUNDING_FRACTION = 1e-12
#: Seconds of frames (at ``max_frame_rate``) a source may claim ahead of the time since its epoch was adopted.
FRAME_BURST_S = 5.0
#: Relative slack of the evidence bounds (the sender's float64 sums round).
BOUND_SLACK = 1e-9
BOUND_REASON = "evidence above what its frames can add (max_image_pixels per frame)"
LATE_REASON = "sequence gap or late start: waiting for a snapshot"
SNAPSHOT_REASON = "incomplete snapshot: waiting for the next one"
NOT_NEEDED_REASON = "return holds no more than this node's evidence"
FRAMES_REASON = "frame count above what any map holds"
RETURN_FRAMES_REASON = "return claims more frames than this node could have fused since its checkpoint"
#: Returns sent to one restarted source: a burst of RETURN_BURST, then one per RETURN_INTERVAL_S seconds (it flags
#: every snapshot "resumed" for a minute; a forged stream of such snapshots is answered at this pace, not per packet).
RETURN_INTERVAL_S = 5.0
RETURN_BURST = 3
#: The returns sent to one source total at most this many times the bytes of the packets it sent since it began
#: flagging its snapshots "resumed" (its "resumed" run; what it sent before, under its previous epoch, buys none): a
#: source cannot make the node send more than 10 bytes per byte it sends, whatever flags and epochs it claims.
RETURN_AMPLIFICATION = 10.0
#: Why a due return was not sent (``evidence_returns_withheld[<reason>]``).
WITHHELD_BUDGET = "byte budget: more than 10 x the bytes the source sent since it resumed"
WITHHELD_RATE = "rate: more than 3 at once or 1 per 5 s"
#: Default of ``evidence_max_rows``: most Gaussians per packet (sent and accepted).
DEFAULT_MAX_ROWS = 20_000
FLOOD_REASON = "flood: more than evidence_max_rate packets/s from one source"


def new_epoch(previous: int = 0) -> int:
    """An epoch id for a start (or a map reset / load) of a publishing node: wall-clock ns, above ``previous``."""
    return max(time.time_ns(), previous + 1)


def own_evidence(concentrations: np.ndarray, prior: float, received: np.ndarray) -> np.ndarray:
    """(N, C) a node's own evidence α - α_0 - received, rounding-level values (below ROUNDING_FRACTION of a
    Gaussian's total) set to 0."""
    own = concentrations - prior - received
    own[own <= ROUNDING_FRACTION * concentrations.sum(axis=1, keepdims=True)] = 0.0
    return own


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
    epoch: int
    frames: int
    rows: np.ndarray     # (R,) uint32 Gaussian ids
    values: np.ndarray   # (R, C) float64 evidence
    flags: int = 0       # FLAG_RESUMED
    subject: str = ""    # return parts: whose evidence it is

    @property
    def nbytes(self) -> int:
        """The size of the encoded packet [bytes] (what its sender sent)."""
        return HEADER_SIZE + self.rows.size * (4 + 8 * self.num_classes) + (ORIGIN_BYTES if self.kind == RETURN else 0)


def return_bytes(rows: int, num_classes: int, max_rows: int) -> int:
    """The bytes of a return of ``rows`` Gaussians (:func:`encode_return`: parts of at most ``max_rows`` rows, one
    part when empty)."""
    parts = max(1, -(-rows // max(1, max_rows)))
    return rows * (4 + 8 * num_classes) + parts * (HEADER_SIZE + ORIGIN_BYTES)


def encode_packet(kind: int, origin: str, fingerprint: str, seq: int, rows: np.ndarray, values: np.ndarray,
                  prior: float, num_gaussians: int, snapshot_id: int = 0, range_start: int = 0,
                  range_end: int | None = None, part: int = 0, parts: int = 1, *, epoch: int,
                  frames: int, flags: int = 0, subject: str = "") -> bytes:
    """The bytes of one packet. ``fingerprint``: hex SHA-256 of the model; ``values`` (R, C) float64."""
    origin_b = origin.encode("ascii")
    if len(origin_b) > ORIGIN_BYTES or not origin_b:
        raise InputError(f"origin id must be 1..{ORIGIN_BYTES} ASCII characters, got {origin!r}")
    values = np.ascontiguousarray(values, dtype="<f8")
    rows = np.ascontiguousarray(rows, dtype="<u4")
    tail = b""
    if kind == RETURN:
        tail = subject.encode("ascii")
        if len(tail) > ORIGIN_BYTES or not tail:
            raise InputError(f"subject id must be 1..{ORIGIN_BYTES} ASCII characters, got {subject!r}")
        tail = tail.ljust(ORIGIN_BYTES, b"\0")
    header = _HEADER.pack(MAGIC, VERSION, kind, flags, origin_b, bytes.fromhex(fingerprint), seq, snapshot_id,
                          range_start, num_gaussians if range_end is None else range_end, part, parts,
                          values.shape[1], len(rows), prior, epoch, frames)
    return header + rows.tobytes() + values.tobytes() + tail


def decode_packet(data: bytes, max_rows: int) -> EvidencePacket:
    """Parse and check one packet's structure (sizes, magic, version, kinds, ranges, value sanity).

    Raises:
        InputError: with a short reason (used as the diagnostics key).
    """
    if len(data) < HEADER_SIZE:
        raise InputError("truncated packet")
    (magic, version, kind, flags, origin_b, digest, seq, snap, lo, hi, part, parts, c, r,
     prior, epoch, frames) = _HEADER.unpack_from(data)
    if magic == MAGIC and version == 1:
        raise InputError("packet format 1 (an older css_ros): update every node of the exchange")
    if magic != MAGIC or version != VERSION:
        raise InputError("not a css evidence packet (magic/version)")
    if kind not in (DELTA, SNAPSHOT, RETURN):
        raise InputError("unknown packet kind")
    if flags & ~FLAG_RESUMED:
        raise InputError("unknown packet flags")
    if r > max_rows:
        raise InputError("too many rows in one packet")
    tail = ORIGIN_BYTES if kind == RETURN else 0
    if c < 1 or len(data) != HEADER_SIZE + r * (4 + 8 * c) + tail:
        raise InputError("packet size does not match its header")
    if seq < 1 or parts < 1 or part >= parts or lo > hi:
        raise InputError("bad sequence / part / range fields")
    if frames > MAX_FRAMES:
        raise InputError(FRAMES_REASON)
    try:
        origin = origin_b.rstrip(b"\0").decode("ascii")
    except UnicodeDecodeError:
        raise InputError("origin id is not ASCII") from None
    if not origin:
        raise InputError("empty origin id")
    subject = ""
    if kind == RETURN:
        try:
            subject = data[len(data) - ORIGIN_BYTES:].rstrip(b"\0").decode("ascii")
        except UnicodeDecodeError:
            raise InputError("origin id is not ASCII") from None
        if not subject:
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
    return EvidencePacket(kind, origin, digest, seq, snap, lo, hi, part, parts, c, prior, epoch, frames, rows,
                          values.astype(np.float64), flags, subject)


@dataclass
class _Snapshot:
    """A snapshot being received: its epoch, id, frames, next part / sequence number / range start, sum so far."""

    epoch: int
    snapshot_id: int
    frames: int
    next_part: int = 0
    next_seq: int = 0
    next_start: int = 0
    total: float = 0.0


@dataclass
class SourceState(SourceEvidence):
    """What a receiver knows of one source (``evidence``: (N, C) float64, that source's evidence in the map)."""

    total: float = 0.0                          # Σ of evidence, kept in step
    frames_base: int = 0                        # frames before the latest increase (a delta covers frames - base)
    clock: tuple[int, float] | None = None      # (frames, time.monotonic()) when the epoch was adopted (None: free)
    pending: _Snapshot | None = None
    packets: int = 0
    #: (epoch, frames, evidence) of the source's previous epoch, kept when it restarted "resumed":
    #: sent back to it as a return on its resumed snapshots (dropped at its first unflagged one)
    returnable: tuple[int, int, np.ndarray] | None = None
    #: the source's latest snapshot was flagged "resumed" (evidence it holds only so is never returned)
    flagged: bool = False
    #: returns the source may still be sent now, as of time.monotonic() ``returned_at`` (a token bucket)
    return_tokens: float = float(RETURN_BURST)
    returned_at: float = -math.inf
    #: bytes of returns the source may still be sent: RETURN_AMPLIFICATION x the bytes of its packets applied since
    #: its "resumed" run began, less the returns sent to it since (0 outside a run)
    return_credit: float = 0.0
    #: rows of ``returnable`` holding evidence (the return's size without a pass over it)
    returnable_rows: int = 0
    #: (N,) bool: the rows where ``evidence`` is nonzero, kept in step (a snapshot part finds the rows the source
    #: held in its range without a pass over (N, C) arrays); None: taken from ``evidence`` once
    held: np.ndarray | None = None
    held_rows: int = 0
    #: time.monotonic() of the source's latest applied packet (which source without evidence gives its slot first)
    active_at: float = -math.inf

    def __post_init__(self) -> None:
        if self.held is None:
            self.held = np.any(self.evidence != 0.0, axis=1)
        self.held_rows = int(np.count_nonzero(self.held))

    def rows_in(self, lo: int, hi: int) -> np.ndarray:
        """(k,) int64 the rows in [lo, hi) where this source holds evidence (none: no pass at all)."""
        if not self.held_rows:
            return np.zeros(0, np.int64)
        assert self.held is not None
        return np.flatnonzero(self.held[lo:hi]) + lo

    def mark(self, rows: np.ndarray, values: np.ndarray) -> None:
        """``evidence[rows] = values`` was set for ``rows`` (sorted, distinct): keep ``held`` in step."""
        assert self.held is not None
        now = np.any(values != 0.0, axis=1)
        before = self.held[rows]
        self.held[rows] = now
        self.held_rows += int(np.count_nonzero(now)) - int(np.count_nonzero(before))


class EvidenceLedger:
    """Exactly-once bookkeeping of the evidence received from other nodes (one per map; not thread-safe).

    ``apply`` changes the map's concentrations and returns None, or returns the reason a packet was refused
    (the map and the ledger are then unchanged: a refused packet takes no source slot and moves no sequence
    number). Memory: 8·N·C + N bytes per source, at most ``max_sources`` sources (at most MAX_RECEIVED_SOURCES,
    what a map file keeps; those of ``received``, the sources a loaded map holds, are kept even beyond
    ``max_sources``). A source holding no evidence gives its slot to a new one.
    Consistency: on every row a snapshot part changes, α is recomputed as α_0 + own + Σ sources (own = what α held
    above α_0 and the sources before, rounding-level values set to 0, as :func:`own_evidence`), never as α − old +
    new, which loses the small evidence of one source to the rounding of another's large one; deltas only add. So
    Σ received ≤ α − α_0 up to float64 rounding of α (a few ulp: the loader allows 1e-9 α), and the map file the
    node writes loads. A snapshot part costs O((rows sent + rows the source held in its range) · C · sources
    holding evidence there), plus a scan of N/8 bytes of a bool mask when the source holds any row.
    ``max_frame_evidence``: the most evidence one frame adds (pixels of the largest image);
    ``max_frame_rate``: the most frames per second a source may claim within one epoch.
    Returns (``returns_due``) go only to a source that held evidence here from unflagged packets, per source at
    most RETURN_BURST at once and one per ``return_interval`` seconds after (at most ``max_sources`` times that in
    all), and only while the bytes of the returns sent to it stay within RETURN_AMPLIFICATION times the bytes of
    the packets it sent since its "resumed" run began (``max_rows``: rows per return part, as sent). A return due
    but not sent is listed in ``returns_withheld`` as (origin, reason, bytes) for the caller to count.
    """

    def __init__(self, own_origin: str, fingerprint: str, num_gaussians: int, num_classes: int, prior: float,
                 max_sources: int, max_concentration: float = 1e15, max_frame_evidence: float = 4096.0 ** 2,
                 max_frame_rate: float = 100.0, received: Mapping[str, SourceEvidence] | None = None,
                 return_interval: float = RETURN_INTERVAL_S, max_rows: int = DEFAULT_MAX_ROWS) -> None:
        self.own_origin = own_origin
        self.return_interval = float(return_interval)
        self.max_rows = max(1, int(max_rows))
        self.digest = bytes.fromhex(fingerprint)
        self.n, self.c, self.prior = num_gaussians, num_classes, prior
        self.max_sources = min(int(max_sources), MAX_RECEIVED_SOURCES)
        self.max_concentration = max_concentration
        self.max_frame_evidence, self.max_frame_rate = float(max_frame_evidence), float(max_frame_rate)
        self.sources: dict[str, SourceState] = {}
        #: origins whose returnable evidence is due to be sent back (the caller drains it after apply)
        self.returns_due: list[str] = []
        #: (origin, reason, bytes) of each return due but not sent (WITHHELD_BUDGET / WITHHELD_RATE; drained likewise)
        self.returns_withheld: list[tuple[str, str, int]] = []
        self._total = np.zeros((num_gaussians, num_classes))   # Σ over sources of their evidence, kept in step
        for name, src in (received or {}).items():
            ev = np.array(src.evidence, dtype=np.float64).reshape(num_gaussians, num_classes)
            self.sources[name] = SourceState(ev, src.epoch, src.last_seq, src.frames, src.in_step,
                                             total=float(ev.sum()), frames_base=src.frames)
            self._total += ev

    def received_total(self) -> np.ndarray:
        """(N, C) float64 Σ over sources of their evidence in the map, maintained as packets are applied (no
        pass over the sources: the publisher reads it every period). Read-only for the caller."""
        return self._total

    def forget(self) -> None:
        """The map was reset: every source's evidence in it is gone; each must re-sync by snapshot."""
        for s in self.sources.values():
            s.evidence[...] = 0.0
            s.in_step, s.pending, s.total = False, None, 0.0
            assert s.held is not None
            s.held[...] = False
            s.held_rows = 0
        self._total[...] = 0.0

    def holders(self) -> list[str]:
        """The sources whose evidence the map holds now (a source whose evidence went to 0 is not one)."""
        return [name for name, s in self.sources.items() if s.held_rows]

    def apply(self, pkt: EvidencePacket, concentrations: np.ndarray, now: float | None = None) -> str | None:
        """Apply one decoded packet to ``concentrations`` (N, C) in place, or return why it was refused.
        ``now``: time.monotonic() (the frame-rate bound)."""
        if pkt.origin == self.own_origin:
            return "own evidence (echo)"
        if pkt.fingerprint_digest != self.digest:
            return "evidence of another splat model"
        if pkt.num_classes != self.c or pkt.prior != self.prior:
            return "evidence of another class count or prior"
        if pkt.range_end > self.n or (pkt.rows.size and pkt.rows[-1] >= self.n):
            return "Gaussian id beyond the model"
        now = time.monotonic() if now is None else now
        if pkt.kind == RETURN:
            return "return packet (for its subject only)"
        if pkt.kind == DELTA:
            reason = self._delta(self.sources.get(pkt.origin), pkt, concentrations, now)
        else:
            reason = self._snapshot_part(pkt, concentrations, now)
        state = self.sources.get(pkt.origin)
        if reason is None and state is not None and state.flagged and not (pkt.kind == SNAPSHOT and pkt.part == 0):
            state.return_credit += RETURN_AMPLIFICATION * pkt.nbytes   # part 0 is counted by _note_resumed
        return reason

    def _allowed_frames(self, state: SourceState, now: float) -> float:
        """The most frames ``state``'s source may claim now (its epoch's start plus the rate, plus a burst)."""
        if state.clock is None:
            state.clock = (state.frames, now)
        frames0, t0 = state.clock
        return frames0 + self.max_frame_rate * (now - t0 + FRAME_BURST_S)

    def _bound(self, frames: int) -> float:
        return self.max_frame_evidence * frames * (1.0 + BOUND_SLACK)

    def _delta(self, state: SourceState | None, pkt: EvidencePacket, conc: np.ndarray, now: float) -> str | None:
        if state is None:
            return LATE_REASON
        if pkt.epoch != state.epoch:
            return "packet of another start (epoch) of this source: waiting for its snapshot"
        if pkt.seq <= state.last_seq:
            return "replayed or duplicate sequence number"
        if not state.in_step or pkt.seq != state.last_seq + 1:
            return LATE_REASON
        if pkt.frames < state.frames:
            return "frame count went back"
        if pkt.frames > self._allowed_frames(state, now):
            return "frames claimed faster than evidence_max_frame_rate"
        since = pkt.frames - (state.frames if pkt.frames > state.frames else state.frames_base)
        rows, values = pkt.rows, pkt.values
        added = float(values.sum())
        if (values.size and float(values.sum(axis=1).max()) > self._bound(since)) or \
                state.total + added > self._bound(pkt.frames):
            return BOUND_REASON
        new_alpha = conc[rows] + values
        if np.any(new_alpha > self.max_concentration):
            return "evidence would exceed the concentration bound"
        conc[rows] = new_alpha
        state.evidence[rows] += values
        state.mark(rows, state.evidence[rows])
        self._total[rows] += values
        state.total += added
        if pkt.frames > state.frames:
            state.frames_base, state.frames = state.frames, pkt.frames
        state.last_seq = pkt.seq
        state.packets += 1
        return None

    def _snapshot_part(self, pkt: EvidencePacket, conc: np.ndarray, now: float) -> str | None:
        state = self.sources.get(pkt.origin)
        lo, hi = pkt.range_start, pkt.range_end
        if pkt.part == 0:
            if pkt.snapshot_id != pkt.seq or lo != 0:
                return "bad sequence / part / range fields"
            new_epoch = state is None or pkt.epoch != state.epoch or state.clock is None   # free first claim
            if state is not None and not new_epoch and pkt.frames > self._allowed_frames(state, now):
                return "frames claimed faster than evidence_max_frame_rate"
            if state is None and len(self.sources) >= self.max_sources and not self._free_slot(pkt.origin):
                return "too many sources"
            snap: _Snapshot | None = _Snapshot(pkt.epoch, pkt.seq, pkt.frames)
        else:
            snap = state.pending if state is not None else None
            if snap is None or (pkt.epoch, pkt.snapshot_id, pkt.frames, pkt.part, pkt.seq, lo) != \
                    (snap.epoch, snap.snapshot_id, snap.frames, snap.next_part, snap.next_seq, snap.next_start):
                return SNAPSHOT_REASON
        assert snap is not None
        if pkt.part == pkt.parts - 1 and hi != self.n:
            return "bad sequence / part / range fields"
        rows, values = pkt.rows, pkt.values
        block_total = float(values.sum())
        if (values.size and float(values.sum(axis=1).max()) > self._bound(pkt.frames)) or \
                snap.total + block_total > self._bound(pkt.frames):
            return BOUND_REASON
        # only the rows sent and the rows the source held in the range change (no pass over the range)
        held = state.rows_in(lo, hi) if state is not None else np.zeros(0, np.int64)
        touched = np.union1d(held, rows) if held.size else rows
        new = np.zeros((touched.size, self.c))
        new[np.searchsorted(touched, rows)] = values
        old = state.evidence[touched] if state is not None else np.zeros_like(new)
        alpha = conc[touched]
        own = own_evidence(alpha, self.prior, self._total[touched])
        total = new.copy()                                  # Σ over the sources, summed afresh on these rows
        for name, other in self.sources.items():
            if name != pkt.origin and other.held_rows:
                total += other.evidence[touched]
        new_alpha = self.prior + own + total
        if np.any(new_alpha > self.max_concentration):
            return "evidence would exceed the concentration bound"
        if state is None:
            state = self.sources[pkt.origin] = SourceState(np.zeros((self.n, self.c)),
                                                           held=np.zeros(self.n, dtype=bool))
        if pkt.part == 0:
            self._note_resumed(state, pkt, now)
        conc[touched] = new_alpha
        self._total[touched] = total
        state.total += block_total - float(old.sum())
        state.evidence[touched] = new
        state.mark(touched, new)
        if pkt.part == 0:
            if new_epoch:
                # a resumed source may claim the frames of its previous epoch at once (it adopts their return)
                back = state.returnable[1] if state.returnable is not None else 0
                state.clock = (max(pkt.frames, back), now)
            state.epoch, state.in_step = pkt.epoch, False
        snap.next_part, snap.next_seq, snap.next_start = pkt.part + 1, pkt.seq + 1, hi
        snap.total += block_total
        state.pending = snap
        state.last_seq = pkt.seq
        state.packets += 1
        state.active_at = now
        if snap.next_part == pkt.parts:
            state.in_step, state.pending, state.total = True, None, snap.total
            state.frames = state.frames_base = pkt.frames
        return None

    def _note_resumed(self, state: SourceState, pkt: EvidencePacket, now: float) -> None:
        """Part 0 of a snapshot, before it is applied: keep the source's previous epoch's evidence when it comes back
        "resumed" (a new epoch; the source, which knows its checkpoint, decides whether it holds more), and mark a
        return due on its resumed snapshots (a token bucket: RETURN_BURST, then one per ``return_interval``; and a
        byte budget: RETURN_AMPLIFICATION x the bytes the source sent since its "resumed" run began, this packet
        included, less the returns it was sent); an unflagged snapshot ends that.
        Evidence the source stated only in flagged snapshots is never kept for a return (a stream of "resumed"
        snapshots of new epochs from an origin that never held evidence here is answered by nothing)."""
        was_flagged, state.flagged = state.flagged, bool(pkt.flags & FLAG_RESUMED)
        if not pkt.flags & FLAG_RESUMED:
            state.returnable, state.return_credit = None, 0.0
            return
        if not was_flagged:
            state.return_credit = 0.0      # a new "resumed" run: what the source sent before buys no return
        state.return_credit += RETURN_AMPLIFICATION * pkt.nbytes
        # kept while the source stays resumed (killed again before it took the copy back: the same copy)
        if state.returnable is None and pkt.epoch != state.epoch and state.in_step and state.pending is None \
                and state.total > 0.0 and not was_flagged:
            rows = state.rows_in(0, self.n)          # a sparse copy: no pass over (N, C) per resumed snapshot
            kept = np.zeros((self.n, self.c))
            kept[rows] = state.evidence[rows]
            state.returnable, state.returnable_rows = (state.epoch, state.frames, kept), int(rows.size)
        if state.returnable is not None and state.returnable[0] != pkt.epoch:
            size = return_bytes(state.returnable_rows, self.c, self.max_rows)
            tokens = min(float(RETURN_BURST), state.return_tokens + (now - state.returned_at) / self.return_interval)
            if size > state.return_credit:
                self.returns_withheld.append((pkt.origin, WITHHELD_BUDGET, size))
            elif tokens < 1.0:
                self.returns_withheld.append((pkt.origin, WITHHELD_RATE, size))
            else:
                state.return_tokens, state.returned_at = tokens - 1.0, now
                state.return_credit -= size
                self.returns_due.append(pkt.origin)

    def return_packets(self, subject: str, max_rows: int | None = None) -> list[bytes]:
        """The return parts of ``subject``'s kept previous-epoch evidence (empty when none is kept); ``max_rows``:
        rows per part (None: the ledger's, which the byte budget counts with)."""
        state = self.sources.get(subject)
        if state is None or state.returnable is None:
            return []
        epoch, frames, evidence = state.returnable
        return encode_return(self.own_origin, subject, self.digest.hex(), epoch, frames, evidence, self.prior,
                             self.max_rows if max_rows is None else max_rows)

    def _free_slot(self, newcomer: str) -> bool:
        """Drop one source that holds no evidence, so that ``newcomer`` may take its slot; False when every source
        holds some. A source with no snapshot under way goes first; else the one whose unfinished snapshot (its parts
        so far empty: nothing of it is in the map) was active least recently, so unfinished snapshots (junk part 0s, a
        peer killed between parts) never lock new sources out."""
        idle = [(s.pending is not None, s.active_at, name) for name, s in self.sources.items() if not s.held_rows]
        if not idle:
            return False
        del self.sources[min(idle)[2]]
        return True


def encode_return(sender: str, subject: str, fingerprint: str, epoch: int, frames: int, evidence: np.ndarray,
                  prior: float, max_rows: int) -> list[bytes]:
    """The return parts (kind RETURN) giving ``subject`` back its evidence ``evidence`` (N, C) of ``epoch``."""
    n = evidence.shape[0]
    nz = np.flatnonzero(np.any(evidence != 0.0, axis=1))
    chunks = [nz[a:a + max_rows] for a in range(0, nz.size, max(1, max_rows))] or [nz]
    starts = [0] + [int(ch[0]) for ch in chunks[1:]]
    ends = starts[1:] + [n]
    return [encode_packet(RETURN, sender, fingerprint, k + 1, rows, evidence[rows], prior, n, snapshot_id=1,
                          range_start=lo, range_end=hi, part=k, parts=len(chunks), epoch=epoch, frames=frames,
                          subject=subject)
            for k, (rows, lo, hi) in enumerate(zip(chunks, starts, ends))]


class EvidenceRecovery:
    """A node restarted with ``resume``: takes back, from a peer's return, its own evidence of the epoch it ran
    before (the frames fused and published after its last checkpoint, which a ``kill -9`` lost).

    Accepted only until ``window`` seconds after the first peer packet the node applied (:meth:`heard`; open until
    then: a refused packet does not start it), for the subject = this node's origin, an epoch at or
    after its checkpoint's (``checkpoint_epoch``; 0: no checkpoint, any earlier epoch) and before its current one,
    and more (epoch, frames) than it holds (the checkpoint's, then the best return adopted); the parts must tile
    [0, N) and keep the ledger's bounds (P per frame and row, P·F in total). The frames claimed are at most what
    this node could have fused since its checkpoint: its checkpoint's frames plus ``max_frame_rate`` times the seconds
    from the checkpoint's epoch (or, without one, the return's epoch) to the current one, plus FRAME_BURST_S
    seconds' worth (epochs are wall-clock ns). Several peers: the best one wins
    (equal ones after it are refused as "no more"). ``offer`` returns (reason refused or None, the complete
    (epoch, frames, evidence) to adopt or None)."""

    def __init__(self, origin: str, fingerprint: str, num_gaussians: int, num_classes: int, prior: float,
                 checkpoint_epoch: int, checkpoint_frames: int, current_epoch: int, max_frame_evidence: float,
                 max_sources: int, now: float, window: float = RETURN_WINDOW_S,
                 max_frame_rate: float = 100.0) -> None:
        self.origin, self.digest = origin, bytes.fromhex(fingerprint)
        self.n, self.c, self.prior = num_gaussians, num_classes, prior
        self.first_epoch, self.current_epoch = checkpoint_epoch, current_epoch
        self.best = (checkpoint_epoch, checkpoint_frames)
        self.max_frame_evidence, self.max_sources = float(max_frame_evidence), max_sources
        self.window, self.until = window, math.inf
        self.checkpoint_frames, self.max_frame_rate = int(checkpoint_frames), float(max_frame_rate)
        self._pending: dict[str, tuple[int, int, int, int, np.ndarray]] = {}   # sender -> epoch, frames, part, start
        self._active: dict[str, int] = {}   # sender -> order of its latest part (the oldest pending gives way)
        self._clock = 0

    def heard(self, now: float) -> None:
        """A peer packet was applied at ``now`` (time.monotonic()): the window runs from the first one."""
        if self.until == math.inf:
            self.until = now + self.window

    def open(self, now: float) -> bool:
        return now < self.until

    def frames_limit(self, epoch: int) -> float:
        """The most frames a return of ``epoch`` may claim (see the class docstring)."""
        start = self.first_epoch or epoch
        seconds = max(0, self.current_epoch - start) / 1e9
        return min(float(MAX_FRAMES), self.checkpoint_frames + self.max_frame_rate * (seconds + FRAME_BURST_S))

    def offer(self, pkt: EvidencePacket, now: float) -> tuple[str | None, tuple[int, int, np.ndarray] | None]:
        if pkt.kind != RETURN or pkt.subject != self.origin:
            return "return for another node", None
        if not self.open(now):
            self._pending.clear()
            self._active.clear()
            return "return after the recovery window", None
        if pkt.fingerprint_digest != self.digest:
            return "evidence of another splat model", None
        if pkt.num_classes != self.c or pkt.prior != self.prior:
            return "evidence of another class count or prior", None
        if pkt.range_end > self.n or (pkt.rows.size and pkt.rows[-1] >= self.n):
            return "Gaussian id beyond the model", None
        if pkt.epoch < self.first_epoch or pkt.epoch >= self.current_epoch:
            return "return of an epoch this node did not run last", None
        if (pkt.epoch, pkt.frames) <= self.best:
            return NOT_NEEDED_REASON, None
        if pkt.frames > self.frames_limit(pkt.epoch):
            return RETURN_FRAMES_REASON, None
        lo, hi = pkt.range_start, pkt.range_end
        if pkt.part == 0:
            if lo != 0 or pkt.seq != 1:
                return "bad sequence / part / range fields", None
            if pkt.origin not in self._pending and len(self._pending) >= self.max_sources:
                # the return least recently continued gives way (unfinished forged returns never block a real one)
                oldest = min(self._pending, key=lambda k: self._active.get(k, -1))
                del self._pending[oldest]
                self._active.pop(oldest, None)
            cur = (pkt.epoch, pkt.frames, 0, 0, np.zeros((self.n, self.c)))
        else:
            cur = self._pending.get(pkt.origin)   # type: ignore[assignment]
            if cur is None or (pkt.epoch, pkt.frames, pkt.part, lo) != cur[:4] or pkt.seq != pkt.part + 1:
                return SNAPSHOT_REASON, None
        if pkt.part == pkt.parts - 1 and hi != self.n:
            return "bad sequence / part / range fields", None
        bound = self.max_frame_evidence * pkt.frames * (1.0 + BOUND_SLACK)
        buf = cur[4]
        if (pkt.values.size and float(pkt.values.sum(axis=1).max()) > bound) or \
                float(buf.sum()) + float(pkt.values.sum()) > bound:
            return BOUND_REASON, None
        buf[pkt.rows] = pkt.values
        if pkt.part + 1 < pkt.parts:
            self._pending[pkt.origin] = (pkt.epoch, pkt.frames, pkt.part + 1, hi, buf)
            self._active[pkt.origin] = self._clock
            self._clock += 1
            return None, None
        self._pending.pop(pkt.origin, None)
        self._active.pop(pkt.origin, None)
        self.best = (pkt.epoch, pkt.frames)
        return None, (pkt.epoch, pkt.frames, buf)


def received_sources(smap: "SemanticMap", own_origin: str) -> dict[str, SourceEvidence]:
    """The received sources a node's ledger starts from, for a map resumed, loaded or kept (``smap.received``;
    the rest of its evidence is the node's own). A map whose own evidence was published under another origin id
    (``smap.evidence_origin``) keeps it as that origin's, never re-published under ``own_origin``; evidence of
    ``own_origin`` that another node held (a file saved by a peer) is own. A map of an older css_ros (no
    ``evidence_origin``) holds only own evidence."""
    received = dict(smap.received)
    if smap.evidence_origin and smap.evidence_origin != own_origin and smap.evidence_origin not in received:
        conc = smap.concentrations_readonly
        total = sum((s.evidence for s in received.values()), np.zeros(conc.shape))
        received[smap.evidence_origin] = SourceEvidence(own_evidence(conc, smap.prior, total),
                                                        frames=smap.frames_observed)
    received.pop(own_origin, None)
    if len(received) > MAX_RECEIVED_SOURCES:
        # a file of MAX_RECEIVED_SOURCES sources saved under another origin: that origin makes one more. Sources
        # holding no evidence are dropped first (they re-sync by their next snapshot), then the smallest ones are
        # kept as part of the file origin's evidence (never as own: nothing is re-published under own_origin; the
        # peer's next snapshot re-states it): the map this node saves keeps at most MAX_RECEIVED_SOURCES
        for name in [k for k, s in received.items() if not s.evidence.any() and k != smap.evidence_origin]:
            if len(received) <= MAX_RECEIVED_SOURCES:
                break
            del received[name]
        if len(received) > MAX_RECEIVED_SOURCES:
            keep = received[smap.evidence_origin]
            by_size = sorted((k for k in received if k != smap.evidence_origin),
                             key=lambda k: float(received[k].evidence.sum()))
            folded = keep.evidence.copy()
            for name in by_size[:len(received) - MAX_RECEIVED_SOURCES]:
                folded += received.pop(name).evidence
            received[smap.evidence_origin] = SourceEvidence(folded, keep.epoch, keep.last_seq, keep.frames,
                                                            keep.in_step)
    return received


class OriginBuckets:
    """Token buckets per origin: ``rate`` packets/s, bursts up to one second's worth (ROS-free; the node keeps one).

    At most ``capacity`` buckets of origins that are not ``protected`` (a callable: the origins holding a source
    slot in the ledger or named in evidence_allowed_origins) are kept; a new origin beyond that evicts the least
    recently used unprotected bucket. A protected origin's bucket is never evicted, so a flood under many other
    origins (also of packets refused later) cannot lock a peer out; their number is bounded by the ledger's slots
    and the allow-list. Evicting a bucket forgets its debt (an origin cycling through many ids gets each one's
    burst: the per-origin bound is no bound on the total rate, as with any forged origin)."""

    def __init__(self, rate: float, capacity: int, protected: Callable[[str], bool]) -> None:
        self.rate, self.capacity, self.protected = float(rate), max(1, int(capacity)), protected
        self._buckets: dict[str, tuple[float, float]] = {}   # origin -> (tokens, time of last use); LRU first
        self.evicted = 0

    def __len__(self) -> int:
        return len(self._buckets)

    def __contains__(self, origin: str) -> bool:
        return origin in self._buckets

    def allow(self, origin: str, now: float) -> bool:
        """One packet of ``origin`` at ``now`` (time.monotonic()): True when its bucket holds a token (taken)."""
        bucket = self._buckets.pop(origin, None)
        if bucket is None:
            self._make_room()
            bucket = (self.rate, now)
        tokens, last = bucket
        tokens = min(self.rate, tokens + max(0.0, now - last) * self.rate)
        ok = tokens >= 1.0
        self._buckets[origin] = (tokens - 1.0 if ok else tokens, now)   # re-inserted: most recently used
        return ok

    def _make_room(self) -> None:
        unprotected = [o for o in self._buckets if not self.protected(o)]   # LRU first
        for origin in unprotected[:max(0, len(unprotected) - self.capacity + 1)]:
            del self._buckets[origin]
            self.evicted += 1


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
        self.epoch = new_epoch()
        z = np.zeros((1, 1))
        _grown_rows(z, z, z, 0.0, 0.0, np.empty(1, np.int64))   # compile (or load) now, not under the map lock

    def own(self, concentrations: np.ndarray, received: np.ndarray) -> np.ndarray:
        """(N, C) this node's own evidence (rounding-level values set to 0)."""
        return own_evidence(concentrations, self.prior, received)

    def reset(self) -> None:
        """Forget what was published and start a new epoch (after a map reset / load: the next snapshot, of the
        new epoch, re-states the total and may hold fewer frames)."""
        self.published[...] = 0.0
        self.seq, self.epoch = 0, new_epoch(self.epoch)

    def deltas(self, concentrations: np.ndarray, received: np.ndarray, frames: int) -> list[bytes]:
        """Packets of the own evidence added since the last call (rows that grew), at most ``max_rows`` rows each.

        One fused pass over the map (:func:`_grown_rows`, no (N, C) temporaries): the publisher runs this every
        ``evidence_period`` while holding the map lock. The same rule as :meth:`own` and :meth:`snapshot`: own
        evidence below ROUNDING_FRACTION of a row's total counts as 0, and a row is sent when some class grew by
        more than that. ``frames``: the map's frames_observed (read under the same lock).
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
            out.append(encode_packet(DELTA, self.origin, self.fingerprint, self.seq, rows, vals, self.prior, self.n,
                                     epoch=self.epoch, frames=frames))
        return out

    def snapshot(self, own: np.ndarray, frames: int, flags: int = 0) -> list[bytes]:
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
                                     parts=len(chunks), epoch=self.epoch, frames=frames, flags=flags))
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


bind_sources(globals())  # cached kernels recompile when any module they are built from changes
