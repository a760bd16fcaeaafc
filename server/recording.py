"""The recording file: one file per sortie, chunked, compressed, indexed.

Layout (format version 1; proto/sortie/v1/recording.proto has the messages,
docs/RECORDING.md the whole description)::

    "SORTREC1" | u32 n | RecordingHeader (n bytes)
             RecordingHeader's first 6 bytes: its header_crc32 field, crc32(n + the header after it, but the
             scenario text, which its SHA-256 checks)
    chunk*:  "CHNK" | u32 head | u32 body | u32 crc32(head bytes + body bytes) | ChunkHead | zstd(ChunkBody)
             ChunkHead's last 5 bytes: its head_crc32 field, crc32(the two lengths + the head before it)
    footer:  "INDX" | u32 n | u32 0 | u32 crc32(index) | RecordingIndex | u64 offset of "INDX" | "SORTEND1"

A chunk holds up to ``chunk_s`` world seconds of consecutive ticks: the
states of every entity (server/recording_codec.py: each chunk starts from
absolute values, so it decodes alone), the per-tick digests of the exact
states, and the inputs and events of its span. The writer flushes each chunk
as it closes; the footer is written on a clean close. Reading uses the
footer's index once every chunk it names is where it says, holding the ticks
it says (their heads checked on opening); a file without one (the server was
killed), or whose index does not match the chunks (swapped or moved, the
footer kept), is indexed by walking the chunk frames (their heads are
uncompressed), and everything up to the last whole chunk replays. A whole
footer (its index's CRC, its back offset and end marker) followed by other
bytes is still the footer: the bytes after it are a problem naming them. The
walk ends at a whole footer only; an INDX magic that starts none (a chunk's
damaged magic, a damaged footer) is a damaged stretch like any other.

Damage. A chunk's own CRC covers its head and body; the head also ends with a
CRC of its own (over the frame's lengths and the head), so a chunk whose body
is damaged keeps a trusted head: its tick span, the entities it introduced,
its counts and where the next chunk starts. The walk goes on past a chunk
that does not check: it trusts the frame's lengths when the next frame
checks, and otherwise scans for the next chunk magic whose frame checks. The
whole chunks are indexed in tick order (a recording runs on from FIRST_TICK): a
chunk out of place in the file is read in its place, a copy or an overlap is left
out, and ticks that no chunk holds are indexed as one lost chunk per gap, the
damaged stretch between the chunks either side when there is one, else missing
(reading it is a DataFormatError naming its offset); its inputs and events are
lost. Bytes between chunks of consecutive ticks held no chunk: a problem only
(docs/RECORDING.md, "Crash safety"). States need nothing from other chunks (each
chunk starts from absolute values); entity descriptions are in the head of the chunk that
first holds them, repeated in the next RECENT_CHUNKS heads (recent_entities),
so a lost head loses none; an entity that no readable head describes (older
files) reads with an empty description, listed in :attr:`Recording.undescribed`.
Recordings written before the head CRC and the repeats read as before: their
heads are trusted through the chunk's CRC alone.

The header. Its CRC (header_crc32, field 17) is written before its other fields, so
that a header without it is told apart: one from before header CRCs starts with its
format version and reads unchecked (:attr:`Recording.notes`); any other is damaged. A
damaged header (CRC, fields, or fields beyond a recording's ranges,
:func:`header_range_problems`) is a DataFormatError naming the file: no reader goes on
with a start time, geoid undulation, rate or quantisation step it cannot trust.

Seeking is a bisection in the index and the decoding of one chunk.

Limits: a header or chunk head of at most 64 MiB, a chunk body of at most
1 GiB (the writer refuses more); a reader meeting larger claims reports the
file as corrupt at that offset.
"""

from __future__ import annotations

import bisect
import hashlib
import math
import os
import re
import struct
import threading
import zlib
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path

import numpy as np
import zstandard

from server import recording_codec as codec
from sortie.errors import DataFormatError, InvalidArgument, NotFound
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import simulation_pb2 as pb

FORMAT_VERSION = 1
MAGIC = b"SORTREC1"
END_MAGIC = b"SORTEND1"
CHUNK_MAGIC = b"CHNK"
INDEX_MAGIC = b"INDX"
FRAME = struct.Struct("<4sIII")  # magic, head length, body length, crc32
HEAD_CRC_TAG = (15 << 3) | 5  # ChunkHead.head_crc32: field 15, fixed32, appended last
HEAD_CRC = struct.Struct("<BI")  # its 5 bytes: the tag, the CRC
# RecordingHeader.header_crc32: field 17, fixed32, written first (protobuf reads fields in any order; its tag
# is two varint bytes, 0x8d 0x01). Recordings from before it have none: their headers start with their
# format_version field (OLD_HEADER_START) and are unchecked but for their ranges and the scenario's hash.
HEADER_CRC_FIELD = 17
HEADER_CRC_TAG = b"\x8d\x01"  # (17 << 3) | 5 = 141 as a varint
HEADER_CRC = struct.Struct("<2sI")  # its 6 bytes: the tag, the CRC
OLD_HEADER_START = b"\x08\x01"  # format_version = 1: field 1, varint, first as protobuf writes fields
SCENARIO_TEXT_FIELD = 9  # RecordingHeader.scenario_toml: its text is checked by its SHA-256, not the CRC
# Chunk heads after the one that introduced an entity that describe it again (recent_entities).
RECENT_CHUNKS = 4
# The quantisation steps a header may hold (server/recording_codec.py's defaults are 1e-4 .. 1e-2):
# finer, and QUANTUM_LIMIT steps would not span the Earth's ECEF positions; coarser, and replay is useless.
MIN_STEP = 1e-8
MAX_STEP = 1.0
SCAN_BLOCK = 1 << 20  # bytes read at a time when looking for the next chunk after a damaged one
HEAD_PROBE_BYTES = 512  # read with a frame when checking the footer index (a longer head: a 2nd read)
MAX_HEAD_BYTES = 64 << 20
MAX_BODY_BYTES = 1 << 30
# zstd level 1: measured on 500 entities' chunks, 1.0 ms and 116 kB against level 2's 1.15 ms and
# 109 kB and level 3's 1.8 ms and 102 kB; the recorder's thread competes with the clock for two
# cores, and the file is half the size of Tacview's zipped ACMI either way.
ZSTD_LEVEL = 1
DECODED_CHUNK_CACHE = 8
# A recording's first tick: the recorder is attached to a world at tick 0 (server/sim_server.py,
# server/resim.py take_over), and the world's first tick is tick 1 (server/world.py).
FIRST_TICK = 1


def steps_of(header: rpb.RecordingHeader) -> codec.Steps:
    q = header.quantization
    return codec.Steps(q.position_m, q.velocity_mps, q.acceleration_mps2, q.quaternion, q.body_rate_rps)


def quantization_of(steps: codec.Steps) -> rpb.Quantization:
    return rpb.Quantization(position_m=steps.position_m, velocity_mps=steps.velocity_mps,
                            acceleration_mps2=steps.acceleration_mps2, quaternion=steps.quaternion,
                            body_rate_rps=steps.body_rate_rps)


def _add_to_index(index: rpb.RecordingIndex, head: rpb.ChunkHead, offset: int, entities: dict) -> None:
    """Append a chunk to an index (its entities to ``entities``: id -> EntityInfo)."""
    if head.ticks:
        if not index.ticks:
            index.first_time_s = head.first_time_s
        index.last_time_s = head.last_time_s
    index.chunk_first_tick.append(head.first_tick)
    index.chunk_offset.append(offset)
    index.chunk_time_s.append(head.first_time_s)
    index.ticks += head.ticks
    index.event_count += head.event_count
    index.input_count += head.input_count
    for e in head.recent_entities:
        entities.setdefault(e.entity_id, e)
    for e in head.new_entities:
        entities[e.entity_id] = e


def sealed_head(head_bytes: bytes, body_length: int) -> bytes:
    """A serialised ChunkHead with its head_crc32 field appended (see :func:`head_checks`)."""
    nh = len(head_bytes) + HEAD_CRC.size
    crc = zlib.crc32(head_bytes, zlib.crc32(struct.pack("<II", nh, body_length)))
    return head_bytes + HEAD_CRC.pack(HEAD_CRC_TAG, crc)


def _wire_fields(data: bytes) -> list[tuple[int, int, int, int, int]]:
    """The top-level fields of a serialised protobuf message: (number, wire type, offset, start,
    end) of each, in order (the offset of its tag, then of its value's bytes and past them);
    ValueError when the bytes are no such fields (wire types 0, 1, 2 and 5 only: what the
    RecordingHeader's fields are written as)."""
    out, pos, size = [], 0, len(data)

    def varint(pos: int) -> tuple[int, int]:
        value, shift = 0, 0
        while pos < size and shift < 70:
            b = data[pos]
            value |= (b & 0x7F) << shift
            pos += 1
            if b < 0x80:
                return value, pos
            shift += 7
        raise ValueError(f"a varint cut short or too long at byte {pos}")

    while pos < size:
        key, start = varint(pos)
        number, wire = key >> 3, key & 7
        if number == 0:
            raise ValueError(f"field number 0 at byte {pos}")
        if wire == 0:
            _, end = varint(start)
        elif wire == 1:
            end = start + 8
        elif wire == 5:
            end = start + 4
        elif wire == 2:
            length, start = varint(start)
            end = start + length
        else:
            raise ValueError(f"wire type {wire} (field {number}) at byte {pos}")
        if end > size:
            raise ValueError(f"field {number} at byte {pos} runs past the header's end")
        out.append((number, wire, pos, start, end))
        pos = end
    return out


def header_crc(n: int, body: bytes, fields: list | None = None) -> int:
    """CRC-32 of a RecordingHeader of ``n`` bytes whose ``body`` (its bytes after the 6 of the
    header_crc32 field) are ``fields`` (:func:`_wire_fields`): over "u32 n" and the body but the
    scenario text's bytes (field 9's value; its tag and length are covered), which its SHA-256
    (scenario_sha256) checks, so a damaged scenario text reads as before (a problem, not a lost
    recording)."""
    crc, pos = zlib.crc32(struct.pack("<I", n)), 0
    for number, wire, _, start, end in _wire_fields(body) if fields is None else fields:
        if number == SCENARIO_TEXT_FIELD and wire == 2:
            crc, pos = zlib.crc32(body[pos:start], crc), end
    return zlib.crc32(body[pos:], crc)


def sealed_header(header: rpb.RecordingHeader) -> bytes:
    """A RecordingHeader's bytes as the writer writes them: its header_crc32 field
    (:func:`header_crc`), then its other fields (the scenario's SHA-256 filled in when missing).
    First, so that a header that does not start with it is one from before it (or damaged)."""
    h = rpb.RecordingHeader()
    h.CopyFrom(header)
    h.DiscardUnknownFields()  # a header read from a file: no second header_crc32
    if "header_crc32" in h.DESCRIPTOR.fields_by_name:  # once recording.proto declares it
        h.ClearField("header_crc32")
    if h.scenario_toml and not h.scenario_sha256:
        h.scenario_sha256 = hashlib.sha256(h.scenario_toml.encode("utf-8")).hexdigest()
    body = h.SerializeToString()
    n = len(body) + HEADER_CRC.size
    return HEADER_CRC.pack(HEADER_CRC_TAG, header_crc(n, body)) + body


def head_checks(lengths: bytes, head_bytes: bytes) -> bool:
    """Whether a chunk head (its bytes, after the frame's 8 bytes of ``lengths``) ends with a
    head_crc32 that matches: then its fields and the lengths are as written."""
    if len(head_bytes) < HEAD_CRC.size:
        return False
    tag, crc = HEAD_CRC.unpack(head_bytes[-HEAD_CRC.size:])
    return tag == HEAD_CRC_TAG and zlib.crc32(head_bytes[:-HEAD_CRC.size], zlib.crc32(lengths)) == crc


# -- writing --------------------------------------------------------------------------------------

class RecordingWriter:
    """Appends chunks to a new file and writes the footer on :meth:`close`.

    Not thread-safe: one writer thread owns it (server/recorder.py)."""

    def __init__(self, path, header: rpb.RecordingHeader):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "xb")  # never overwrite a recording
        data = sealed_header(header)
        if len(data) > MAX_HEAD_BYTES:
            self._f.close()
            self.path.unlink()
            raise DataFormatError(f"header of {len(data)} bytes is over the format's limit ({MAX_HEAD_BYTES})")
        self._f.write(MAGIC + struct.pack("<I", len(data)) + data)
        self._f.flush()
        self._zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self.index = rpb.RecordingIndex()
        self._entities: dict[int, object] = {}
        self._recent: deque = deque(maxlen=RECENT_CHUNKS)  # the last chunks' new entities
        self.bytes_written = self._f.tell()
        self.closed = False

    def write_chunk(self, head: rpb.ChunkHead, body: rpb.ChunkBody) -> None:
        """Append a chunk; ``head`` gets the recent chunks' new entities (recent_entities) and
        its own CRC (head_crc32, appended to its bytes)."""
        head.ClearField("recent_entities")
        head.ClearField("head_crc32")
        for entities in self._recent:
            head.recent_entities.extend(entities)
        body_b = self._zstd.compress(body.SerializeToString())
        head_b = sealed_head(head.SerializeToString(), len(body_b))
        if len(head_b) > MAX_HEAD_BYTES or len(body_b) > MAX_BODY_BYTES:
            raise DataFormatError(f"chunk of {len(head_b)} + {len(body_b)} bytes is over the format's limits")
        self._recent.append(list(head.new_entities))
        offset = self._f.tell()
        crc = zlib.crc32(body_b, zlib.crc32(head_b))
        self._f.write(FRAME.pack(CHUNK_MAGIC, len(head_b), len(body_b), crc) + head_b + body_b)
        self._f.flush()
        self.bytes_written = self._f.tell()
        _add_to_index(self.index, head, offset, self._entities)

    def sync(self, data_only: bool = False) -> None:
        """Make what was written durable (fsync; ``data_only``: fdatasync, which leaves out
        metadata that reading the data back does not need, such as the modification time),
        beyond surviving a killed process: a power loss too."""
        (os.fdatasync if data_only and hasattr(os, "fdatasync") else os.fsync)(self._f.fileno())

    def close(self) -> None:
        if self.closed:
            return
        self.index.entities.extend(self._entities[i] for i in sorted(self._entities))
        data = self.index.SerializeToString()
        offset = self._f.tell()
        self._f.write(FRAME.pack(INDEX_MAGIC, len(data), 0, zlib.crc32(data)) + data
                      + struct.pack("<Q", offset) + END_MAGIC)
        self._f.flush()
        self.sync()
        self.bytes_written = self._f.tell()  # the whole file, its footer included
        self._f.close()
        self.closed = True


# -- reading --------------------------------------------------------------------------------------

NO_FOOTER = "no footer (the recording was not closed): chunks found by walking the file"


def scenario_problems(header: rpb.RecordingHeader) -> list[str]:
    """What is wrong with the header's scenario: its text against the SHA-256 the recorder
    stored with it (the header has no CRC of its own; the hash is its check). A header
    without a stored hash is not checked."""
    if not header.scenario_sha256:
        return []
    actual = hashlib.sha256(header.scenario_toml.encode("utf-8")).hexdigest()
    if actual == header.scenario_sha256:
        return []
    return [f"scenario SHA-256 mismatch: the header's scenario text is damaged (stored "
            f"{header.scenario_sha256[:16]}..., the text's {actual[:16]}...)"]


def header_range_problems(header: rpb.RecordingHeader) -> list[str]:
    """The header's fields outside the ranges a recording can have (those the scenario allows,
    server/scenario.py, and the recorder writes): each "field value: why". A field left unset
    (0 or empty: hand-made headers, older writers) is not checked, but the world rate and the
    quantisation steps, which every reader needs."""
    from server.scenario import FDM_RATE_MAX_HZ, GEOID_UNDULATION_ABS_MAX_M, MAX_EXERCISE_NAME_CHARS

    out = []
    slack = 1.0 + 1e-9  # the recorder writes 1 / dt: within an ulp or so of the scenario's integer
    world, fdm = header.world_rate_hz, header.fdm_rate_hz
    if not (math.isfinite(world) and 0.0 < world <= FDM_RATE_MAX_HZ * slack):
        out.append(f"world_rate_hz {world!r}: must be within (0, {FDM_RATE_MAX_HZ}] Hz")
    if fdm and not (math.isfinite(fdm) and 0.0 < fdm <= FDM_RATE_MAX_HZ * slack and fdm * slack >= world):
        out.append(f"fdm_rate_hz {fdm!r}: must be within [world_rate_hz, {FDM_RATE_MAX_HZ}] Hz")
    g = header.geoid_undulation_m
    if not (math.isfinite(g) and abs(g) <= GEOID_UNDULATION_ABS_MAX_M):
        out.append(f"geoid_undulation_m {g!r}: must be within [-{GEOID_UNDULATION_ABS_MAX_M:g}, "
                   f"{GEOID_UNDULATION_ABS_MAX_M:g}] m")
    for name in ("position_m", "velocity_mps", "acceleration_mps2", "quaternion", "body_rate_rps"):
        v = getattr(header.quantization, name)
        if not (math.isfinite(v) and MIN_STEP <= v <= MAX_STEP):
            out.append(f"quantization.{name} {v!r}: must be within [{MIN_STEP:g}, {MAX_STEP:g}]")
    if not (math.isfinite(header.chunk_s) and header.chunk_s >= 0.0):
        out.append(f"chunk_s {header.chunk_s!r}: must be a finite number of seconds")
    if not (math.isfinite(header.created_unix_s) and header.created_unix_s >= 0.0):
        out.append(f"created_unix_s {header.created_unix_s!r}: must be a finite Unix time")
    name = header.exercise_name
    if len(name) > MAX_EXERCISE_NAME_CHARS or not name.isprintable():
        out.append(f"exercise_name {name[:40]!r}: must be at most {MAX_EXERCISE_NAME_CHARS} printable characters")
    if header.start_time:
        try:
            start = datetime.fromisoformat(header.start_time)
        except ValueError:
            start = None
        if start is None or start.utcoffset() is None:
            out.append(f"start_time {header.start_time[:40]!r}: must be an ISO 8601 date-time with an offset")
    return out


@dataclass
class Chunk:
    """One decoded chunk: ``q`` (ticks, entities, 16) quantised states, ``present``
    (ticks, entities) bool, aligned with ``entity_ids`` (ascending)."""

    first_tick: int
    ticks: int
    entity_ids: np.ndarray
    present: np.ndarray
    q: np.ndarray
    digests: np.ndarray  # (ticks,) uint64
    inputs: list
    events: list


@dataclass
class Frame:
    """Every entity's recorded state at one tick, ids ascending."""

    tick: int
    time_s: float
    ids: np.ndarray
    states: np.ndarray  # (n, 16) float64, recording_codec column order
    q: np.ndarray  # (n, 16) int64, the recorded integers
    digest: int


@dataclass
class CheckReport:
    path: str
    size_bytes: int
    footer: bool
    chunks: int
    ticks: int
    first_time_s: float
    last_time_s: float
    entities: int
    events: int
    inputs: int
    problems: list = field(default_factory=list)  # what is wrong, with offsets
    readable_bytes: int = 0  # the file up to the end of the last good chunk (or the footer)
    damaged_chunks: int = 0  # indexed chunks that do not decode (lost ones only, without decode)
    replays: list = field(default_factory=list)  # (first, last) world times of the stretches that replay
    lost_ticks: int = 0  # ticks in chunks that do not read, and those lost before the first chunk
    notes: list = field(default_factory=list)  # not problems: a header from before header CRCs (unchecked)
    header_checked: bool = True  # the header's CRC checked (False: a recording from before header CRCs)

    @property
    def ok(self) -> bool:
        return not self.problems


class Recording:
    """A recording opened for reading (thread-safe for readers of decoded chunks).

    ``Recording(path)`` raises NotFound for a missing file and DataFormatError
    for one that is not a recording or whose header is damaged; a missing or
    damaged footer is not an error (the file is walked; :attr:`recovered` says so).
    :attr:`lost`: the chunks the walk found damaged (index -> what is lost);
    :attr:`undescribed`: entities no readable chunk head describes (id -> why; their
    :attr:`entities` entry is empty but for the id).
    """

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_file():
            if self.path.is_dir():
                raise DataFormatError(f"recording {str(self.path)!r} is a directory, not a recording file")
            if self.path.exists():
                raise DataFormatError(f"recording {str(self.path)!r} is not a regular file")
            raise NotFound(f"recording {str(self.path)!r} does not exist")
        self._f = open(self.path, "rb")
        try:
            self._open()
        except BaseException:
            self._f.close()
            raise

    def _open(self) -> None:
        self.size = self.path.stat().st_size
        self.problems: list[str] = []
        self.lost: dict[int, str] = {}
        self.lost_before = 0  # ticks before the first chunk that the walk found lost (out of index.ticks)
        self.undescribed: dict[int, str] = {}
        self.notes: list[str] = []  # not problems: a header from before header CRCs
        self.header = self._read_header()
        if self.header.format_version != FORMAT_VERSION:
            raise DataFormatError(f"{self.path}: format version {self.header.format_version}; this build reads "
                                  f"version {FORMAT_VERSION}")
        bad = header_range_problems(self.header)
        if bad:
            raise DataFormatError(f"{self.path}: damaged header: " + "; ".join(bad))
        self.problems += scenario_problems(self.header)
        self.steps = steps_of(self.header)
        self.rate_hz = self.header.world_rate_hz
        self.dt = 1.0 / self.rate_hz
        self.index, self.recovered = self._read_footer(), False
        if self.index is not None and not self._index_matches_heads(self.index):
            self.index = None
        if self.index is None:
            self.index, self.recovered = self._walk(), True
        if not self.index.ticks:
            self.problems.append("no chunks: the recording holds no ticks (nothing replays)")
        self._first_ticks = list(self.index.chunk_first_tick)
        self.entities = {e.entity_id: e for e in self.index.entities}
        self._cache: OrderedDict[int, Chunk] = OrderedDict()
        self._cache_lock = threading.Lock()  # the replay's clock and control threads both read chunks
        # A decompressor per thread: python-zstandard's may not be used from two threads at once
        # (the replay's clock and its control calls read chunks together: an acceptance probe saw
        # intact chunks read as corrupt, and the process die of SIGSEGV).
        self._zstd_of_thread = threading.local()
        if self.lost:
            self._describe_lost()

    def close(self) -> None:
        self._f.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()

    # -- structure ------------------------------------------------------------------------------

    def _read_at(self, offset: int, n: int) -> bytes:
        """n bytes at ``offset`` (fewer at the end of the file); pread: no shared file position,
        so threads may read at once."""
        out = []
        while n > 0:
            data = os.pread(self._f.fileno(), n, offset)
            if not data:
                break
            out.append(data)
            offset, n = offset + len(data), n - len(data)
        return b"".join(out)

    def _read_header(self) -> rpb.RecordingHeader:
        """The header, its CRC checked (:func:`header_crc`; a recording from before header CRCs
        gets a note, :attr:`header_checked` False). DataFormatError naming the file and the
        header when it is damaged: its CRC does not match, its fields do not decode, or it starts
        with neither its CRC nor (older recordings) its format version."""
        start = self._read_at(0, 12)
        if len(start) < 12 or start[:8] != MAGIC:
            raise DataFormatError(f"{self.path}: not a Sortie recording (no {MAGIC.decode()} magic)")
        (n,) = struct.unpack("<I", start[8:])
        damaged = f"{self.path}: damaged header (bytes 12..{12 + n} of the file)"
        if n > MAX_HEAD_BYTES or 12 + n > self.size:
            raise DataFormatError(f"{self.path}: header of {n} bytes does not fit the file ({self.size} bytes)")
        data = self._read_at(12, n)
        self.header_checked = data[:2] == HEADER_CRC_TAG and n >= HEADER_CRC.size
        if self.header_checked:
            _, stored = HEADER_CRC.unpack(data[:HEADER_CRC.size])
            data = data[HEADER_CRC.size:]
        else:
            self._unchecked_header(n, data, damaged)
        try:
            fields = _wire_fields(data)
        except ValueError as exc:
            raise DataFormatError(f"{damaged}: its fields do not decode ({exc})") from None
        if self.header_checked:
            actual = header_crc(n, data, fields)
            if actual != stored:
                raise DataFormatError(f"{damaged}: CRC-32 mismatch (stored {stored:08x}, the bytes' {actual:08x})")
        try:
            header = rpb.RecordingHeader.FromString(data)
        except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
            header = self._header_of_damaged_text(data, fields)
            if header is None:
                raise DataFormatError(f"{damaged}: {exc}") from None
        self._data_start = 12 + n
        return header

    @staticmethod
    def _header_of_damaged_text(data: bytes, fields: list) -> rpb.RecordingHeader | None:
        """The header whose bytes (``data``, walked into ``fields``) do not decode because its
        scenario text is not UTF-8 (damaged): the text decoded with replacement characters, so
        its SHA-256 mismatch is the problem it is when the text is valid UTF-8; None when the
        rest does not decode either."""
        text, rest, pos = b"", [], 0
        for number, wire, at, start, end in fields:
            if number == SCENARIO_TEXT_FIELD and wire == 2:
                rest.append(data[pos:at])
                text, pos = data[start:end], end
        if not rest:
            return None
        rest.append(data[pos:])
        try:
            header = rpb.RecordingHeader.FromString(b"".join(rest))
        except Exception:  # noqa: BLE001 - the damage is elsewhere too
            return None
        header.scenario_toml = text.decode("utf-8", "replace")
        return header

    def _unchecked_header(self, n: int, data: bytes, damaged: str) -> None:
        """A header of ``n`` bytes (``data``) that does not start with its CRC: one from before
        header CRCs (a note) when it starts with its format version, as those did. Else it is
        damaged (DataFormatError): its CRC's tag, when the 4 bytes after it are still the CRC
        of the rest, or its first field."""
        if n >= HEADER_CRC.size:
            try:
                crc = header_crc(n, data[HEADER_CRC.size:])
            except ValueError:
                crc = None
            if crc is not None and struct.pack("<I", crc) == data[2:HEADER_CRC.size]:
                raise DataFormatError(f"{damaged}: its CRC field's tag is damaged")
        if data[:2] != OLD_HEADER_START:
            raise DataFormatError(f"{damaged}: it starts with neither its CRC (field {HEADER_CRC_FIELD}) nor, as "
                                  "recordings from before header CRCs do, its format version (field 1)")
        self.notes.append("the header has no CRC (recorded before header CRCs): its fields are unchecked but "
                          "for their ranges (the scenario text is checked by its SHA-256)")

    def _footer_end(self, offset: int) -> int | None:
        """Where the footer starting at ``offset`` ends, when a whole one does: its INDX frame,
        the index its CRC checks, the offset of "INDX" back at ``offset`` and the end marker;
        None otherwise (an INDX magic alone is 4 bytes of a damaged chunk, or anything)."""
        frame = self._read_at(offset, FRAME.size) if offset < self.size else b""
        if len(frame) < FRAME.size:
            return None
        magic, n, _, crc = FRAME.unpack(frame)
        if magic != INDEX_MAGIC or n > MAX_HEAD_BYTES or offset + FRAME.size + n + 16 > self.size:
            return None
        data = self._read_at(offset + FRAME.size, n + 16)
        if zlib.crc32(data[:n]) != crc or data[n:] != struct.pack("<Q", offset) + END_MAGIC:
            return None
        return offset + FRAME.size + n + 16

    def _footer_past_chunks(self) -> int | None:
        """The offset of a whole footer that the chunk frames lead to from the header, hopping by
        their lengths (nothing else read: 16 bytes a chunk), when the file does not end with one
        (bytes appended after it); None when the hop meets anything else first."""
        offset = self._data_start
        while offset + FRAME.size <= self.size:
            magic, nh, nb, _ = FRAME.unpack(self._read_at(offset, FRAME.size))
            if magic == INDEX_MAGIC:
                return offset if self._footer_end(offset) is not None else None
            if magic != CHUNK_MAGIC or nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
                return None
            offset += FRAME.size + nh + nb
        return None

    def _note_bytes_after_footer(self, offset: int, end: int) -> None:
        """The bytes after the whole footer at ``offset`` (ending at ``end``): a problem, once."""
        if end < self.size and not self._after_footer_noted:
            self._after_footer_noted = True
            self.problems.append(f"{self.size - end} bytes after the footer at offset {offset} (the recording ends "
                                 f"at byte {end}): not part of the recording, left unread")

    def _read_footer(self) -> rpb.RecordingIndex | None:
        """The footer's index: the file's last bytes, or a whole footer followed by other bytes
        (appended: a problem naming them); None (a problem) when there is none or it is
        damaged: the file is walked."""
        self._after_footer_noted = False
        if self.size < self._data_start + FRAME.size + 16:
            self.problems.append(NO_FOOTER)
            return None
        tail = self._read_at(self.size - 16, 16)
        offset = struct.unpack("<Q", tail[:8])[0] if tail[8:] == END_MAGIC else None
        end = self._footer_end(offset) if offset is not None else None
        if end is None:  # no footer at the end: one followed by appended bytes, or none
            found = self._footer_past_chunks()
            if found is not None:
                offset, end = found, self._footer_end(found)
            elif offset is None:
                self.problems.append(NO_FOOTER)
                return None
        if end is not None:
            self._note_bytes_after_footer(offset, end)
        frame = self._read_at(offset, FRAME.size) if offset < self.size else b""
        if len(frame) == FRAME.size:
            magic, n, _, crc = FRAME.unpack(frame)
            data = self._read_at(offset + FRAME.size, n) if magic == INDEX_MAGIC and n <= MAX_HEAD_BYTES else b""
            if len(data) == n and zlib.crc32(data) == crc and end is not None:
                try:
                    index = rpb.RecordingIndex.FromString(data)
                except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError: CRC-valid, not an index
                    self.problems.append(f"damaged footer at offset {offset}: its index does not decode ({exc}); "
                                         "chunks found by walking the file")
                    return None
                firsts = list(index.chunk_first_tick)
                if len(index.chunk_offset) != len(firsts) or any(b < a for a, b in zip(firsts, firsts[1:])):
                    self.problems.append(f"damaged footer at offset {offset}: its index is not in tick order; "
                                         "chunks found by walking the file")
                    return None
                self._index_end = offset
                return index
        self.problems.append(f"damaged footer at offset {offset}: chunks found by walking the file")
        return None

    def _index_matches_heads(self, index: rpb.RecordingIndex) -> bool:
        """Whether every chunk the footer's index names is where it says, holding the ticks it
        says: a chunk frame at its offset whose head's first tick and tick count are the index's
        (each chunk's ticks run to the next one's first; the last's to the index's total). A
        footer that points at the wrong chunk (chunks swapped or moved, the footer kept) is a
        problem, and False: the file is walked instead, which reads every chunk in its place.
        Only the frames and heads are read (nothing decompressed). A head that does not check
        (damaged, or one from before head CRCs that does not decode) says nothing against the
        index: reading that chunk reports its damage."""
        firsts, offsets = index.chunk_first_tick, index.chunk_offset
        n = len(firsts)
        for k in range(n):
            offset = offsets[k]
            end_tick = firsts[k + 1] if k + 1 < n else firsts[0] + index.ticks
            data = self._read_at(offset, FRAME.size + HEAD_PROBE_BYTES) if offset < self.size else b""
            wrong = None
            if len(data) < FRAME.size:
                wrong = "is past the end of the file"
            else:
                magic, nh, nb, _ = FRAME.unpack(data[:FRAME.size])
                if magic != CHUNK_MAGIC or nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
                    wrong = "holds no chunk frame"
                else:
                    head_b = data[FRAME.size:FRAME.size + nh]
                    if len(head_b) < nh:
                        head_b = self._read_at(offset + FRAME.size, nh)
                    head = self._head_of(data[4:12], head_b)
                    if head is not None and (head.first_tick, head.ticks) != (firsts[k], end_tick - firsts[k]):
                        held = (f"ticks {head.first_tick}..{head.first_tick + head.ticks - 1}" if head.ticks
                                else f"no tick (from tick {head.first_tick})")
                        wrong = f"holds {held}"
            if wrong is not None:
                says = (f"ticks {firsts[k]}..{end_tick - 1}" if end_tick > firsts[k]
                        else f"no tick (from tick {firsts[k]})")
                self.problems.append(f"the footer's index does not match the file: its chunk {k} at offset {offset} "
                                     f"({says}) {wrong} there; chunks found by walking the file")
                return False
        return True

    @staticmethod
    def _head_of(lengths: bytes, head_b: bytes) -> rpb.ChunkHead | None:
        """A chunk head (its bytes, after the frame's 8 bytes of ``lengths``) that can be read
        without its body: one whose own CRC checks, or, from before head CRCs (no head_crc32
        tag at its end), one that decodes; None otherwise."""
        own_crc = len(head_b) >= HEAD_CRC.size and head_b[-HEAD_CRC.size] == HEAD_CRC_TAG
        if own_crc and not head_checks(lengths, head_b):
            return None
        try:
            return rpb.ChunkHead.FromString(head_b)
        except Exception:  # noqa: BLE001 - protobuf's DecodeError: damaged; reading it says so
            return None

    def _probe(self, offset: int):
        """The chunk at ``offset``: (its head, the offset after it) when it is whole and its head
        can be trusted (the head's own CRC checks, or the chunk's); else why not (text)."""
        frame = self._read_at(offset, FRAME.size)
        if len(frame) < FRAME.size:
            return f"cut short ({len(frame)} of {FRAME.size} frame bytes)"
        magic, nh, nb, crc = FRAME.unpack(frame)
        if magic == INDEX_MAGIC:  # the walk stops at a whole footer (_at_footer): this is none
            return "is no chunk frame (an INDX magic, but no whole footer there)"
        if magic != CHUNK_MAGIC:
            return "is no chunk frame (no CHNK magic)"
        if nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
            return f"has a bad frame ({nh} + {nb} bytes claimed, over the format's limits)"
        end = offset + FRAME.size + nh + nb
        if end > self.size:
            return f"cut short ({self.size - offset - FRAME.size} of {nh + nb} bytes)"
        head_b = self._read_at(offset + FRAME.size, nh)
        if not head_checks(frame[4:12], head_b):
            if zlib.crc32(self._read_at(offset + FRAME.size + nh, nb), zlib.crc32(head_b)) != crc:
                return "fails its CRC"
        try:
            return rpb.ChunkHead.FromString(head_b), end
        except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError: CRC-valid, not a chunk head
            return f"has a head that does not decode ({exc})"

    def _resync(self, offset: int):
        """Where the walk goes on after the damaged chunk at ``offset``: (offset, _probe's answer)
        of the next whole chunk, or (None, None) when none follows. After it by its frame's
        lengths when a whole chunk starts there; else the first chunk magic after ``offset``
        whose chunk checks (the lengths were damaged too)."""
        frame = self._read_at(offset, FRAME.size)
        if len(frame) == FRAME.size:
            magic, nh, nb, _ = FRAME.unpack(frame)
            end = offset + FRAME.size + nh + nb
            if magic == CHUNK_MAGIC and nh <= MAX_HEAD_BYTES and nb <= MAX_BODY_BYTES and end <= self.size:
                if end == self.size or self._at_footer(end):
                    return None, None  # the last chunk, or the one before the footer
                got = self._probe(end)
                if not isinstance(got, str):
                    return end, got
        pos = offset + 1
        while pos < self.size:
            block = self._read_at(pos, SCAN_BLOCK + len(CHUNK_MAGIC) - 1)
            for i in (m.start() for m in re.finditer(re.escape(CHUNK_MAGIC) + b"|" + re.escape(INDEX_MAGIC), block)):
                if block[i:i + 4] == INDEX_MAGIC:
                    if self._at_footer(pos + i):
                        return None, None  # a whole footer: the recording ends there
                    continue
                got = self._probe(pos + i)
                if not isinstance(got, str):
                    return pos + i, got
            pos += SCAN_BLOCK
        return None, None

    def _at_footer(self, offset: int) -> bool:
        """Whether a whole footer starts at ``offset`` (:meth:`_footer_end`); bytes after it are a
        problem (:meth:`_note_bytes_after_footer`)."""
        if self._read_at(offset, len(INDEX_MAGIC)) != INDEX_MAGIC:
            return False
        end = self._footer_end(offset)
        if end is None:
            return False
        self._note_bytes_after_footer(offset, end)
        return True

    def _walk(self) -> rpb.RecordingIndex:
        """Index the chunks by their frames. A chunk that does not check is skipped (see
        :meth:`_resync`); the whole chunks found are indexed in tick order (:meth:`_index_walked`).
        Everything wrong is said in :attr:`problems`, with its offset."""
        found: list = []  # (offset, head) of whole chunks; (offset, why, next offset) of damaged stretches
        offset, got = self._data_start, None
        self._index_end = offset
        while offset < self.size:
            if self._at_footer(offset):  # not an INDX magic alone: a damaged chunk's is a damaged stretch
                break
            got = self._probe(offset) if got is None else got
            if not isinstance(got, str):
                head, end = got
                found.append((offset, head))
                offset, got, self._index_end = end, None, end
                continue
            nxt, got_next = self._resync(offset)
            found.append((offset, got, nxt))
            if nxt is None:
                break
            offset, got = nxt, got_next
        return self._index_walked(found)

    def _kept(self, found: list) -> list[int]:
        """The whole chunks of the walk (indices into ``found``) that the index holds, in tick
        order. A chunk that holds a tick one before it in the file holds (a copy, or an overlap)
        is left out: the first in the file is kept. A chunk out of place that overlaps none is
        kept, in its place (each chunk reads alone, and its trusted head says its ticks). A chunk
        with no tick (inputs and events done after tick F - 1, F its first tick: the writer's last,
        or one closed on wall time while the clock was paused or slow) is kept, in file order
        among those of the same F, before the chunk that holds tick F, when no chunk before it in
        the file holds tick F or later, nor ticks either side of F, and it is no copy of one kept
        (the same frame CRC). What is left out is a problem."""
        starts: list[int] = []  # first ticks of the chunks kept that hold ticks, ascending
        spans: list[tuple[int, int, int]] = []  # their (first tick, end tick (exclusive), index in found)
        empty = []  # (index in found, the end tick of the chunks before it in the file)
        reach = FIRST_TICK  # the end tick (exclusive) of the chunks with ticks met so far in the file
        for i, item in enumerate(found):
            if len(item) != 2:
                continue
            head = item[1]
            a, b = head.first_tick, head.first_tick + head.ticks
            if not head.ticks:
                empty.append((i, reach))
                continue
            p = bisect.bisect_right(starts, a)
            clash = spans[p - 1] if p and spans[p - 1][1] > a else (
                spans[p] if p < len(spans) and spans[p][0] < b else None)
            if clash is None:
                if p < len(spans):
                    c, d, j = spans[p]
                    self.problems.append(
                        f"chunk at offset {item[0]} holds ticks {a}..{b - 1} (t = {a * self.dt:.2f} .. "
                        f"{(b - 1) * self.dt:.2f} s), before those of the chunk at offset {found[j][0]} (ticks "
                        f"{c}..{d - 1}), which comes first in the file: a chunk out of place, read in its place")
                starts.insert(p, a)
                spans.insert(p, (a, b, i))
                reach = max(reach, b)
                continue
            self.problems.append(
                f"chunk at offset {item[0]} holds ticks {a}..{b - 1} (t = {a * self.dt:.2f} .. "
                f"{(b - 1) * self.dt:.2f} s), and the chunk at offset {found[clash[2]][0]}, before it in the file, "
                f"holds ticks {clash[0]}..{clash[1] - 1}: a copy or a chunk out of place, left out with its inputs "
                "and events")
        order = [(a, 1, i) for a, _, i in spans]
        kept_crcs: dict[int, set] = {}  # first tick -> frame CRCs of the chunks with no tick kept
        for i, reach_before in empty:
            offset, head = found[i]
            f = head.first_tick
            crc = FRAME.unpack(self._read_at(offset, FRAME.size))[3]
            inside = next((s for s in spans if s[0] < f < s[1]), None)
            if f >= reach_before and inside is None and crc not in kept_crcs.get(f, ()):
                kept_crcs.setdefault(f, set()).add(crc)
                order.append((f, 0, i))
                continue
            if crc in kept_crcs.get(f, ()):
                why = "a copy of a chunk before it in the file"
            elif inside is not None:
                why = (f"the chunk at offset {found[inside[2]][0]} holds ticks {inside[0]}..{inside[1] - 1}, either "
                       "side of them")
            else:
                why = f"chunks before it in the file go on to tick {reach_before - 1}"
            self.problems.append(f"chunk at offset {offset} holds no tick, only inputs and events done after tick "
                                 f"{f - 1}, and {why}: left out with them")
        return [i for _, _, i in sorted(order)]

    def _index_walked(self, found: list) -> rpb.RecordingIndex:
        """The index of what the walk found, in file order: (offset, head) of whole chunks,
        (offset, why, next offset) of damaged stretches. The whole chunks kept (:meth:`_kept`)
        are indexed in tick order; a recording's ticks run on from FIRST_TICK, and ticks that no
        chunk kept holds are lost: each gap is indexed as one lost chunk (:attr:`lost`), put
        down to the damaged stretch between the chunks either side of it in the file when one
        lies there, else missing. The gap before the first chunk kept stays out of the index's
        ticks (the recording's first tick is that chunk's; :attr:`lost_before` counts them). A
        damaged stretch that holds no gap (its chunks either side hold consecutive ticks: a
        chunk holds at least one tick, but the writer's last) or that no chunk kept follows
        is a problem only."""
        kept = self._kept(found)
        is_kept = set(kept)
        after: list = [None] * len(found)  # the next chunk kept in the file after each item
        nxt = None
        for i in range(len(found) - 1, -1, -1):
            after[i] = nxt
            if i in is_kept:
                nxt = i
        stretches, by_sides, before = [], {}, None
        for i, item in enumerate(found):
            if i in is_kept:
                before = i
            elif len(item) == 3:
                stretches.append((i, before, after[i]))
                if item[2] is not None and after[i] is not None:
                    by_sides.setdefault((before, after[i]), i)
        index = rpb.RecordingIndex()
        entities: dict = {}
        expected, before, used = FIRST_TICK, None, set()
        for i in kept:
            offset, head = found[i]
            if head.first_tick > expected:
                d = by_sides.get((before, i))
                if d is not None:
                    used.add(d)
                self._add_lost(index, expected, head.first_tick, before is None, found[d] if d is not None else None,
                               offset)
            _add_to_index(index, head, offset, entities)
            expected, before = head.first_tick + head.ticks, i
        for i, b, a in stretches:
            if i not in used:
                self._skipped(found[i], found[b][1] if b is not None else None, found[a][1] if a is not None else None)
        index.entities.extend(entities[i] for i in sorted(entities))
        return index

    def _skipped(self, item: tuple, before, after) -> None:
        """A damaged stretch of the walk (offset, why, next offset) that the index holds no lost
        chunk for, between the heads of the chunks kept ``before`` and ``after`` it in the file
        (None: none): a problem."""
        offset, why, nxt = item
        if nxt is None:
            tail = ": a partial chunk" if why.startswith("cut short") else (
                f"; {self.size - offset} bytes skipped (no whole chunk after it)")
            self.problems.append(f"chunk at offset {offset} {why}{tail}")
            return
        if why.startswith("cut short"):  # a whole chunk after it: the frame's lengths are what is wrong
            why = "has damaged frame lengths (they claim more bytes than the file has)"
        text = f"chunk at offset {offset} {why}: {nxt - offset} bytes skipped to the next whole chunk, at offset {nxt}"
        last = before.first_tick + before.ticks - 1 if before is not None else FIRST_TICK - 1
        if after is not None and after.first_tick == last + 1:
            sides = (f"the chunks either side hold consecutive ticks ({last} then {last + 1})" if before is not None
                     else f"the chunk after it holds the recording's first tick ({FIRST_TICK})")
            text += f"; {sides}, so no chunk is lost there (no tick, input or event)"
        self.problems.append(text)

    def _add_lost(self, index: rpb.RecordingIndex, first: int, stop: int, leading: bool, stretch, at: int) -> None:
        """Ticks ``first`` .. ``stop`` - 1 that no chunk kept holds, indexed as a lost chunk:
        the damaged stretch of the walk (offset, why, next offset) that held them, or None (the
        chunk is missing; ``at``: the offset of the chunk after it). ``leading``: before the
        first chunk kept (the gap stays out of the index's ticks; :attr:`lost_before`)."""
        k = len(index.chunk_first_tick)
        last = stop - 1
        if leading:
            ticks = f"the ticks before tick {stop} (t = {stop * self.dt:.2f} s)"
            self.lost_before = stop - first
        else:
            ticks = f"ticks {first}..{last} (t = {first * self.dt:.2f} .. {last * self.dt:.2f} s)"
        if stretch is not None:
            offset, why, nxt = stretch
            if why.startswith("cut short"):  # a whole chunk after it: the frame's lengths are what is wrong
                why = "has damaged frame lengths (they claim more bytes than the file has)"
            text = (f"chunk {k} at offset {offset} {why}: {ticks} are lost, and the inputs and events recorded "
                    f"with them; {nxt - offset} bytes skipped to the next whole chunk, at offset {nxt}")
        else:
            offset = at
            start = f"; a recording starts at tick {FIRST_TICK}" if leading else ""
            text = (f"chunk {k} at offset {offset} is missing: no chunk in the file holds {ticks}, so they are lost, "
                    f"and the inputs and events recorded with them (the chunk at offset {offset} goes on from tick "
                    f"{stop}{start})")
        self.lost[k] = text
        self.problems.append(text)
        if leading:
            first = stop
        elif not index.ticks:
            index.first_time_s = first * self.dt
        index.chunk_first_tick.append(first)
        index.chunk_offset.append(offset)
        index.chunk_time_s.append(first * self.dt)
        index.ticks += stop - first

    def _describe_lost(self) -> None:
        """The entities a lost chunk may have been the first to hold: those of the next chunk
        that reads that no readable head describes get an empty description (their id only),
        listed in :attr:`undescribed` and :attr:`problems`. (Entities never come back once gone,
        so an entity first held by a lost chunk is in the next chunk or nowhere after it.)"""
        for k in sorted(self.lost):
            ids: list = []
            for j in range(k + 1, self.chunk_count):
                if j in self.lost:
                    continue
                try:
                    ids = self.chunk_body(j)[1].entity_ids
                    break
                except DataFormatError:
                    continue
            new = [int(i) for i in ids if int(i) not in self.entities]
            if not new:
                continue
            where = f"chunk {k} at offset {self.index.chunk_offset[k]}"
            for i in new:
                self.undescribed[i] = f"first held by the lost {where}"
                self.entities[i] = pb.EntityInfo(entity_id=i)
            shown = ", ".join(map(str, new[:10])) + (f" and {len(new) - 10} more" if len(new) > 10 else "")
            self.problems.append(f"{where} was the first to hold {len(new)} "
                                 f"{'entity' if len(new) == 1 else 'entities'} that no chunk that reads describes "
                                 f"(ids {shown}): their states read, their name, kind, type and coalition are "
                                 "unknown")

    # -- contents -------------------------------------------------------------------------------

    @property
    def chunk_count(self) -> int:
        return len(self._first_ticks)

    @property
    def first_tick(self) -> int:
        return self._first_ticks[0] if self._first_ticks else 0

    @property
    def last_tick(self) -> int:
        return self.first_tick + self.index.ticks - 1 if self._first_ticks else -1

    @property
    def first_time_s(self) -> float:
        return self.index.first_time_s

    @property
    def last_time_s(self) -> float:
        return self.index.last_time_s

    @property
    def duration_s(self) -> float:
        return self.last_time_s - self.first_time_s if self._first_ticks else 0.0

    def _chunk_bytes(self, k: int, head_only: bool = False) -> tuple[bytes, int, str]:
        """(the k-th chunk's head + body bytes, head length, where) with its frame and CRC
        checked (not the CRC when ``head_only``: then only the head is read)."""
        if not 0 <= k < self.chunk_count:
            raise NotFound(f"chunk {k} (the recording has {self.chunk_count})")
        if k in self.lost:
            raise DataFormatError(f"{self.path.name}: {self.lost[k]}")
        offset = self.index.chunk_offset[k]
        where = f"{self.path.name}: chunk {k} at offset {offset}"
        frame = self._read_at(offset, FRAME.size)
        if len(frame) < FRAME.size:
            raise DataFormatError(f"{where}: cut short")
        magic, nh, nb, crc = FRAME.unpack(frame)
        if magic != CHUNK_MAGIC or nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
            raise DataFormatError(f"{where}: no chunk frame there")
        data = self._read_at(offset + FRAME.size, nh if head_only else nh + nb)
        if len(data) < (nh if head_only else nh + nb):
            raise DataFormatError(f"{where}: damaged (cut short)")
        if not head_only and zlib.crc32(data) != crc:
            raise DataFormatError(f"{where}: damaged ({self._what_is_lost(k, frame, data[:nh])})")
        return data, nh, where

    def _what_is_lost(self, k: int, frame: bytes, head_b: bytes) -> str:
        """What a chunk that fails its CRC loses: with a head that checks, its ticks, inputs and
        events (its body is what is damaged)."""
        if not head_checks(frame[4:12], head_b):
            return "CRC mismatch"
        try:
            head = rpb.ChunkHead.FromString(head_b)
        except Exception:  # noqa: BLE001 - as good as no head
            return "CRC mismatch"
        first, last = self.chunk_ticks(k)
        span = f"ticks {first}..{last} (t = {first * self.dt:.2f} .. {last * self.dt:.2f} s)" if last >= first \
            else "no tick"
        return (f"CRC mismatch in its body; its head checks: {span}, {head.input_count} inputs and "
                f"{head.event_count} events lost")

    def trusted_head(self, k: int) -> rpb.ChunkHead | None:
        """The k-th chunk's head when it can be trusted (its own CRC checks, or the whole
        chunk's), even if its body is damaged; None for a lost chunk, or a damaged chunk
        whose head has no CRC of its own (recordings from before it)."""
        if k in self.lost:
            return None
        got = self._probe(self.index.chunk_offset[k])
        return None if isinstance(got, str) else got[0]

    def chunk_ticks(self, k: int) -> tuple[int, int]:
        """(first, last) tick of the k-th chunk's span (last < first: none)."""
        first = self._first_ticks[k]
        last = self._first_ticks[k + 1] - 1 if k + 1 < self.chunk_count else self.last_tick
        return first, max(first - 1, last)

    def inputs_after_tick(self, k: int) -> int:
        """The earliest tick after which the inputs kept with the k-th chunk may have been done
        (-1: from the start, for a lost chunk before the first whole one): a re-simulation that
        runs past it needs them."""
        return -1 if k == 0 and k in self.lost else self._first_ticks[k] - 1

    def spans(self, unreadable=()) -> list[tuple[int, int]]:
        """The stretches of consecutive ticks (first, last) in chunks neither lost nor in
        ``unreadable`` (indices of chunks that do not decode)."""
        out: list[list[int]] = []
        for k in range(self.chunk_count):
            first, last = self.chunk_ticks(k)
            if last < first or k in self.lost or k in unreadable:
                continue
            if out and out[-1][1] + 1 == first:
                out[-1][1] = last
            else:
                out.append([first, last])
        return [(a, b) for a, b in out]

    def mentions(self, k: int) -> bool:
        """Whether :attr:`problems` already names the k-th chunk (a lost one)."""
        return re.search(rf"chunk {k} at offset {self.index.chunk_offset[k]}(?!\d)", "\n".join(self.problems)) \
            is not None

    def lost_ticks(self, unreadable=()) -> int:
        """The ticks of the recording that do not replay: those of the chunks lost, or in
        ``unreadable`` (indices of chunks that do not decode), and those before the first chunk
        that the walk found lost (:attr:`lost_before`; a recording starts at FIRST_TICK)."""
        return self.index.ticks - sum(b - a + 1 for a, b in self.spans(unreadable)) + self.lost_before

    def chunk_head(self, k: int) -> rpb.ChunkHead:
        """The k-th chunk's head, read alone (nothing decompressed)."""
        data, nh, where = self._chunk_bytes(k, head_only=True)
        try:
            return rpb.ChunkHead.FromString(data[:nh])
        except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError
            raise DataFormatError(f"{where}: damaged head: {exc}") from None

    def chunk_body(self, k: int) -> tuple[rpb.ChunkHead, rpb.ChunkBody]:
        """The k-th chunk's head and body, decompressed and parsed but its states not
        decoded (inputs and events are read this way)."""
        data, nh, where = self._chunk_bytes(k)
        try:
            return rpb.ChunkHead.FromString(data[:nh]), rpb.ChunkBody.FromString(self._decompressor().decompress(data[nh:]))
        except Exception as exc:  # noqa: BLE001 - zstd and protobuf errors
            raise DataFormatError(f"{where}: cannot be decoded: {exc}") from None

    def _decompressor(self) -> zstandard.ZstdDecompressor:
        """This thread's zstd decompressor (see _open)."""
        d = getattr(self._zstd_of_thread, "d", None)
        if d is None:
            d = self._zstd_of_thread.d = zstandard.ZstdDecompressor()
        return d

    def chunk(self, k: int) -> Chunk:
        """The k-th chunk decoded (cached); DataFormatError naming its offset if damaged."""
        with self._cache_lock:
            c = self._cache.get(k)
            if c is not None:
                self._cache.move_to_end(k)
                return c
        head, body = self.chunk_body(k)
        where = f"{self.path.name}: chunk {k} at offset {self.index.chunk_offset[k]}"
        try:
            ids = np.array(body.entity_ids, np.int64)
            t_count, e_count = head.ticks, ids.size
            if body.present:
                bits = np.unpackbits(np.frombuffer(body.present, np.uint8), count=t_count * e_count)
                present = bits.reshape(t_count, e_count).astype(bool)
            else:
                present = np.ones((t_count, e_count), bool)
            q = codec.decode(body.states, t_count, e_count, self.steps, self.rate_hz)
            digests = np.array(body.digests, np.uint64)
            if digests.size != t_count:
                raise DataFormatError(f"{digests.size} digests for {t_count} ticks")
        except DataFormatError as exc:
            raise DataFormatError(f"{where}: {exc}") from None
        except Exception as exc:  # noqa: BLE001 - numpy errors on malformed fields
            raise DataFormatError(f"{where}: cannot be decoded: {exc}") from None
        c = Chunk(head.first_tick, t_count, ids, present, q, digests, list(body.inputs), list(body.events))
        with self._cache_lock:
            self._cache[k] = c
            if len(self._cache) > DECODED_CHUNK_CACHE:
                self._cache.popitem(last=False)
        return c

    def chunk_of_tick(self, tick: int) -> int:
        """Index of the chunk holding ``tick`` (clamped to the recording)."""
        if not self._first_ticks:
            raise NotFound(f"{self.path.name}: the recording holds no ticks")
        return max(0, bisect.bisect_right(self._first_ticks, tick) - 1)

    def tick_at(self, time_s: float) -> int:
        """The recorded tick at or just before world time ``time_s`` (clamped; +-inf are the
        ends, NaN is an InvalidArgument). World time is exactly tick / world rate
        (server/world.py), so frames carry no time of their own."""
        time_s = float(time_s)
        if math.isnan(time_s):
            raise InvalidArgument("time_s", "must be a number", value=time_s)
        if math.isinf(time_s):
            return self.first_tick if time_s < 0 else self.last_tick
        tick = int(np.floor(time_s * self.rate_hz + 1e-6))
        return min(max(tick, self.first_tick), self.last_tick)

    def frame(self, tick: int) -> Frame:
        """Every entity's state at ``tick`` (clamped to the recording): one chunk decoded.
        NotFound when the recording holds no tick; DataFormatError naming the chunk when it
        does not read (or does not hold the tick its index says it does)."""
        if self.last_tick < self.first_tick:
            raise NotFound(f"{self.path.name}: the recording holds no ticks")
        tick = min(max(int(tick), self.first_tick), self.last_tick)
        k = self.chunk_of_tick(tick)
        c = self.chunk(k)
        j = tick - c.first_tick
        if not 0 <= j < c.ticks:
            raise DataFormatError(f"{self.path.name}: chunk {k} at offset {self.index.chunk_offset[k]} holds ticks "
                                  f"{c.first_tick}..{c.first_tick + c.ticks - 1}, not tick {tick} (its index entry "
                                  "says it does)")
        here = c.present[j]
        q = c.q[j, here]
        return Frame(tick, tick * self.dt, c.entity_ids[here], codec.dequantize(q, self.steps), q,
                     int(c.digests[j]))

    def frames(self, first: int | None = None, last: int | None = None):
        """Frames from tick ``first`` to ``last`` (inclusive; default: all)."""
        first = self.first_tick if first is None else max(first, self.first_tick)
        last = self.last_tick if last is None else min(last, self.last_tick)
        for tick in range(first, last + 1):
            yield self.frame(tick)

    def inputs(self):
        """Every InputRecord, in the order they were done. Inputs and events done after
        tick k (InputRecord.tick = k) are kept with the chunk of tick k + 1, so the last
        tick of a chunk may have its inputs and events in the next chunk."""
        for k in range(self.chunk_count):
            yield from self.chunk_body(k)[1].inputs

    def events(self, skipped: list | None = None):
        """Every EventRecord, in the order they were emitted. With ``skipped`` (a list), the
        events of a chunk that does not read are left out and its problem appended to it;
        without, such a chunk raises DataFormatError."""
        for k in range(self.chunk_count):
            try:
                body = self.chunk_body(k)[1]
            except DataFormatError as exc:
                if skipped is None:
                    raise
                skipped.append(str(exc))
                continue
            yield from body.events

    def readable_chunks(self, skipped: list):
        """(k, Chunk) of every chunk that reads, in order; a lost or damaged one is left out and
        its problem appended to ``skipped``: what the exports read, so a damaged chunk costs
        an export its own ticks only."""
        for k in range(self.chunk_count):
            try:
                c = self.chunk(k)
            except DataFormatError as exc:
                skipped.append(str(exc))
                continue
            yield k, c

    # -- checking -------------------------------------------------------------------------------

    def _range_problems(self, k: int, c: Chunk) -> list[str]:
        """The k-th chunk's states recorded at the codec's limit (clamped when recorded)."""
        bad = codec.out_of_range(c.q) & c.present[:, :, None]
        if not bad.any():
            return []
        t, e, f = (int(x[0]) for x in np.nonzero(bad))
        return [f"chunk {k} at offset {self.index.chunk_offset[k]}: {int(bad.sum())} state values beyond the "
                f"recordable range (clamped to {codec.QUANTUM_LIMIT} steps when recorded), the first: entity "
                f"{int(c.entity_ids[e])} field {f} at tick {c.first_tick + t}"]

    def check(self, decode: bool = True) -> CheckReport:
        """What the file holds and what is wrong with it; with ``decode`` every chunk is
        decoded (and its CRC checked), not only walked."""
        problems, unreadable = list(self.problems), set(self.lost)
        events, inputs = self.index.event_count, self.index.input_count  # the index's, unless decoded
        if decode:  # then those of the chunks that read (a damaged chunk is left out of the counts)
            events = inputs = 0
            for k in range(self.chunk_count):
                try:
                    c = self.chunk(k)
                except DataFormatError as exc:
                    unreadable.add(k)
                    if not self.mentions(k):  # not twice
                        problems.append(str(exc))
                    continue
                problems += self._range_problems(k, c)
                events, inputs = events + len(c.events), inputs + len(c.inputs)
        end = getattr(self, "_index_end", self._data_start)
        spans = self.spans(unreadable)
        replays = [(a * self.dt, b * self.dt) for a, b in spans]
        lost_ticks = self.lost_ticks(unreadable)
        return CheckReport(str(self.path), self.size, not self.recovered, self.chunk_count, self.index.ticks,
                           self.first_time_s, self.last_time_s, len(self.entities), events, inputs,
                           problems, end, len(unreadable), replays, lost_ticks, list(self.notes), self.header_checked)
