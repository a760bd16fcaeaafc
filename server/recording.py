"""The recording file: one file per sortie, chunked, compressed, indexed.

Layout (format version 1; proto/sortie/v1/recording.proto has the messages,
docs/RECORDING.md the whole description)::

    "SORTREC1" | u32 n | RecordingHeader (n bytes)
    chunk*:  "CHNK" | u32 head | u32 body | u32 crc32(head bytes + body bytes) | ChunkHead | zstd(ChunkBody)
    footer:  "INDX" | u32 n | u32 0 | u32 crc32(index) | RecordingIndex | u64 offset of "INDX" | "SORTEND1"

A chunk holds up to ``chunk_s`` world seconds of consecutive ticks: the
states of every entity (server/recording_codec.py: each chunk starts from
absolute values, so it decodes alone), the per-tick digests of the exact
states, and the inputs and events of its span. The writer flushes each chunk
as it closes; the footer is written on a clean close. Reading uses the
footer's index; a file without one (the server was killed) is indexed by
walking the chunk frames (their heads are uncompressed), and everything up to
the last whole chunk replays. Seeking is a bisection in the index and the
decoding of one chunk.

Limits: a header or chunk head of at most 64 MiB, a chunk body of at most
1 GiB (the writer refuses more); a reader meeting larger claims reports the
file as corrupt at that offset.
"""

from __future__ import annotations

import bisect
import hashlib
import math
import os
import struct
import threading
import zlib
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import zstandard

from server import recording_codec as codec
from sortie.errors import DataFormatError, InvalidArgument, NotFound
from sortie.v1 import recording_pb2 as rpb

FORMAT_VERSION = 1
MAGIC = b"SORTREC1"
END_MAGIC = b"SORTEND1"
CHUNK_MAGIC = b"CHNK"
INDEX_MAGIC = b"INDX"
FRAME = struct.Struct("<4sIII")  # magic, head length, body length, crc32
MAX_HEAD_BYTES = 64 << 20
MAX_BODY_BYTES = 1 << 30
# zstd level 1: measured on 500 entities' chunks, 1.0 ms and 116 kB against level 2's 1.15 ms and
# 109 kB and level 3's 1.8 ms and 102 kB; the recorder's thread competes with the clock for two
# cores, and the file is half the size of Tacview's zipped ACMI either way.
ZSTD_LEVEL = 1
DECODED_CHUNK_CACHE = 8


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
    for e in head.new_entities:
        entities[e.entity_id] = e


# -- writing --------------------------------------------------------------------------------------

class RecordingWriter:
    """Appends chunks to a new file and writes the footer on :meth:`close`.

    Not thread-safe: one writer thread owns it (server/recorder.py)."""

    def __init__(self, path, header: rpb.RecordingHeader):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._f = open(self.path, "xb")  # never overwrite a recording
        data = header.SerializeToString()
        self._f.write(MAGIC + struct.pack("<I", len(data)) + data)
        self._f.flush()
        self._zstd = zstandard.ZstdCompressor(level=ZSTD_LEVEL)
        self.index = rpb.RecordingIndex()
        self._entities: dict[int, object] = {}
        self.bytes_written = self._f.tell()
        self.closed = False

    def write_chunk(self, head: rpb.ChunkHead, body: rpb.ChunkBody) -> None:
        head_b = head.SerializeToString()
        body_b = self._zstd.compress(body.SerializeToString())
        if len(head_b) > MAX_HEAD_BYTES or len(body_b) > MAX_BODY_BYTES:
            raise DataFormatError(f"chunk of {len(head_b)} + {len(body_b)} bytes is over the format's limits")
        offset = self._f.tell()
        crc = zlib.crc32(body_b, zlib.crc32(head_b))
        self._f.write(FRAME.pack(CHUNK_MAGIC, len(head_b), len(body_b), crc) + head_b + body_b)
        self._f.flush()
        self.bytes_written = self._f.tell()
        _add_to_index(self.index, head, offset, self._entities)

    def sync(self) -> None:
        """Make what was written durable (fsync), beyond surviving a killed process."""
        import os

        os.fsync(self._f.fileno())

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
    damaged_chunks: int = 0  # indexed chunks that do not decode (counted with decode only)

    @property
    def ok(self) -> bool:
        return not self.problems


class Recording:
    """A recording opened for reading (thread-safe for readers of decoded chunks).

    ``Recording(path)`` raises NotFound for a missing file and DataFormatError
    for one that is not a recording or whose header is damaged; a missing or
    damaged footer is not an error (the file is walked; :attr:`recovered` says so).
    """

    def __init__(self, path):
        self.path = Path(path)
        if not self.path.is_file():
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
        self.header = self._read_header()
        self.problems += scenario_problems(self.header)
        if self.header.format_version != FORMAT_VERSION:
            raise DataFormatError(f"{self.path}: format version {self.header.format_version}; this build reads "
                                  f"version {FORMAT_VERSION}")
        self.steps = steps_of(self.header)
        self.rate_hz = self.header.world_rate_hz
        if not self.rate_hz > 0:
            raise DataFormatError(f"{self.path}: header world_rate_hz must be > 0 (got {self.rate_hz})")
        self.dt = 1.0 / self.rate_hz
        self.index, self.recovered = self._read_footer(), False
        if self.index is None:
            self.index, self.recovered = self._walk(), True
        if not self.index.ticks:
            self.problems.append("no chunks: the recording holds no ticks (nothing replays)")
        self._first_ticks = list(self.index.chunk_first_tick)
        self.entities = {e.entity_id: e for e in self.index.entities}
        self._cache: OrderedDict[int, Chunk] = OrderedDict()
        self._cache_lock = threading.Lock()  # the replay's clock and control threads both read chunks
        self._zstd = zstandard.ZstdDecompressor()

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
        start = self._read_at(0, 12)
        if len(start) < 12 or start[:8] != MAGIC:
            raise DataFormatError(f"{self.path}: not a Sortie recording (no {MAGIC.decode()} magic)")
        (n,) = struct.unpack("<I", start[8:])
        if n > MAX_HEAD_BYTES or 12 + n > self.size:
            raise DataFormatError(f"{self.path}: header of {n} bytes does not fit the file ({self.size} bytes)")
        try:
            header = rpb.RecordingHeader.FromString(self._read_at(12, n))
        except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError and friends
            raise DataFormatError(f"{self.path}: damaged header: {exc}") from None
        self._data_start = 12 + n
        return header

    def _read_footer(self) -> rpb.RecordingIndex | None:
        if self.size < self._data_start + FRAME.size + 16:
            self.problems.append(NO_FOOTER)
            return None
        tail = self._read_at(self.size - 16, 16)
        if tail[8:] != END_MAGIC:
            self.problems.append(NO_FOOTER)
            return None
        (offset,) = struct.unpack("<Q", tail[:8])
        frame = self._read_at(offset, FRAME.size) if offset < self.size else b""
        if len(frame) == FRAME.size:
            magic, n, _, crc = FRAME.unpack(frame)
            data = self._read_at(offset + FRAME.size, n) if magic == INDEX_MAGIC and n <= MAX_HEAD_BYTES else b""
            if len(data) == n and zlib.crc32(data) == crc and offset + FRAME.size + n + 16 == self.size:
                try:
                    index = rpb.RecordingIndex.FromString(data)
                except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError: CRC-valid, not an index
                    self.problems.append(f"damaged footer at offset {offset}: its index does not decode ({exc}); "
                                         "chunks found by walking the file")
                    return None
                self._index_end = offset
                return index
        self.problems.append(f"damaged footer at offset {offset}: chunks found by walking the file")
        return None

    def _walk(self) -> rpb.RecordingIndex:
        """Index the chunks by their frames: stops at the first frame that is cut short or
        fails its CRC (what follows cannot be trusted), and says so in :attr:`problems`."""
        index = rpb.RecordingIndex()
        entities = {}
        offset = self._data_start
        while offset < self.size:
            frame = self._read_at(offset, FRAME.size)
            if len(frame) < FRAME.size:
                self.problems.append(f"{self.size - offset} bytes cut short at offset {offset} (a partial chunk)")
                break
            magic, nh, nb, crc = FRAME.unpack(frame)
            if magic == INDEX_MAGIC:
                break
            if magic != CHUNK_MAGIC or nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
                self.problems.append(f"no chunk at offset {offset} (bad frame); {self.size - offset} bytes skipped")
                break
            data = self._read_at(offset + FRAME.size, nh + nb)
            if len(data) < nh + nb:
                self.problems.append(f"chunk at offset {offset} cut short ({len(data)} of {nh + nb} bytes): "
                                     "a partial chunk")
                break
            if zlib.crc32(data) != crc:
                self.problems.append(f"chunk at offset {offset} fails its CRC; {self.size - offset} bytes skipped")
                break
            try:
                head = rpb.ChunkHead.FromString(data[:nh])
            except Exception as exc:  # noqa: BLE001 - protobuf's DecodeError: CRC-valid, not a chunk head
                self.problems.append(f"chunk at offset {offset} has a head that does not decode ({exc}); "
                                     f"{self.size - offset} bytes skipped")
                break
            _add_to_index(index, head, offset, entities)
            offset += FRAME.size + nh + nb
        self._index_end = offset
        index.entities.extend(entities[i] for i in sorted(entities))
        return index

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
        offset = self.index.chunk_offset[k]
        where = f"{self.path.name}: chunk {k} at offset {offset}"
        frame = self._read_at(offset, FRAME.size)
        if len(frame) < FRAME.size:
            raise DataFormatError(f"{where}: cut short")
        magic, nh, nb, crc = FRAME.unpack(frame)
        if magic != CHUNK_MAGIC or nh > MAX_HEAD_BYTES or nb > MAX_BODY_BYTES:
            raise DataFormatError(f"{where}: no chunk frame there")
        data = self._read_at(offset + FRAME.size, nh if head_only else nh + nb)
        if len(data) < (nh if head_only else nh + nb) or (not head_only and zlib.crc32(data) != crc):
            raise DataFormatError(f"{where}: damaged (CRC mismatch or cut short)")
        return data, nh, where

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
            return rpb.ChunkHead.FromString(data[:nh]), rpb.ChunkBody.FromString(self._zstd.decompress(data[nh:]))
        except Exception as exc:  # noqa: BLE001 - zstd and protobuf errors
            raise DataFormatError(f"{where}: cannot be decoded: {exc}") from None

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
        """Every entity's state at ``tick`` (clamped to the recording): one chunk decoded."""
        tick = min(max(int(tick), self.first_tick), self.last_tick)
        c = self.chunk(self.chunk_of_tick(tick))
        j = tick - c.first_tick
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

    def events(self):
        """Every EventRecord, in the order they were emitted."""
        for k in range(self.chunk_count):
            yield from self.chunk_body(k)[1].events

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
        problems, damaged = list(self.problems), 0
        if decode:
            for k in range(self.chunk_count):
                try:
                    c = self.chunk(k)
                except DataFormatError as exc:
                    damaged += 1
                    if f"offset {self.index.chunk_offset[k]}" not in " ".join(self.problems):  # not twice
                        problems.append(str(exc))
                    continue
                problems += self._range_problems(k, c)
        end = getattr(self, "_index_end", self._data_start)
        return CheckReport(str(self.path), self.size, not self.recovered, self.chunk_count, self.index.ticks,
                           self.first_time_s, self.last_time_s, len(self.entities), self.index.event_count,
                           self.index.input_count, problems, end, damaged)
