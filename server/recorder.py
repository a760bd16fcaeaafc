"""The server's recorder: every tick's states, every input and event, to one file.

The world calls three hooks (server/world.py): ``on_tick`` after each tick
(the snapshot), ``on_input`` for each call that changes the world from
outside (command, claim, release, remove; under the world's lock, with the
tick count it was done at), and ``on_event`` for each event. On the clock
thread a tick costs keeping a reference to its snapshot (the world builds new
arrays every tick and never changes a published snapshot) and, when the
entities changed, noting the new ones. Everything else happens on the
recorder's own thread: the canonical ordering, the XXH3 digest of the
exact float64 states, quantising and residual coding (one compiled pass that
releases the GIL), compression, writing. Measured at 500 entities: 0.24 ms a
tick for ordering and a BLAKE2b digest, which the clock thread paid before
this split and the switch to XXH3.

A chunk closes when one more tick would take it to ``chunk_s`` world seconds
since the previous chunk's last tick (it holds at most ``chunk_s`` - dt: the
tick left over is the time its write and sync take) or when what
it holds first (a tick, an input or an event) is ``chunk_s`` wall seconds old
(a slow or paused clock: inputs made while the clock is paused close in a
chunk of no tick, which readers keep before the chunk of the tick they come
before), and is written, flushed and synced to the disk (fdatasync) at once:
a killed server, or a machine that loses its power, loses at most the open
chunk, at most ``chunk_s`` (1 s by default, at most MAX_CHUNK_S) of world or
wall time. A chunk also closes once it holds MAX_CHUNK_STATES entity states (entities x
ticks), so a long ``chunk_s`` over many entities stays within memory and the format's
chunk body limit. The writer queue holds at most MAX_QUEUED_CHUNKS closed chunks; a
disk slower than that makes the clock wait rather than drop a chunk. A write
error (disk full), or any other error on the writer's thread, stops the
recording, logs it and leaves the exercise running; ``error`` says why.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import os
import queue
import threading
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from server import recording_codec as codec
from terrain.dem import file_identity
from server.recording import FORMAT_VERSION, RecordingWriter, quantization_of, steps_of
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import simulation_pb2 as pb

logger = logging.getLogger(__name__)

DEFAULT_CHUNK_S = 1.0
# The longest chunk (world or wall seconds): an hour loses an hour to a kill, and the wall-age
# deadline (time.monotonic() + chunk_s) stays far inside what the clocks and queue timeouts take
# (a chunk_s of 1e300 overflowed them and killed the writer thread).
MAX_CHUNK_S = 3600.0
# The most entity states (entities x ticks) a chunk holds: one closes at chunk_s or at this,
# whichever comes first. Without it an hour's chunk of the world's 10,000 entities held 1.1e9
# states in memory (160 bytes each in its snapshots, ~400 more while it is coded: 0.6 TB) and
# coded past the format's 1 GiB body (server/recording.py MAX_BODY_BYTES), which stops the
# recording. At most (2^20 + 10,000) x 128 bytes of body (8 bytes a value, 16 values a state:
# recording_codec's coded worst case), 0.13 GiB; at 10,000 entities 105 ticks (3.5 s at 30 Hz).
MAX_CHUNK_STATES = 1 << 20
# The longest the writer thread waits for a chunk before it looks at the open one's wall age.
MAX_POLL_S = 0.25
# The writer thread's nice value (Linux, per thread): its coding runs in the CPU time the clock
# thread and the aircraft workers leave, not in theirs.
WRITER_NICE = 10
MAX_QUEUED_CHUNKS = 64
# Slack (ticks) for chunk_s x rate_hz landing a rounding error below a whole number of ticks.
CHUNK_TICKS_EPS = 1e-9
REPO = Path(__file__).resolve().parents[1]
# The code whose arithmetic a re-simulation repeats (the build id hashes it).
SIMULATION_SOURCES = ("fdm", "terrain", "server/world.py", "server/aircraft_host.py", "server/scenario.py",
                      "server/sim_server.py", "server/dead_reckoning.py", "client/terrain_client.py")


def build_id() -> str:
    """SHA-256 (first 16 hex digits) of the simulation's sources and the jsbsim version."""
    h = hashlib.sha256(_version("jsbsim").encode())
    for name in SIMULATION_SOURCES:
        p = REPO / name
        for f in sorted(p.rglob("*.py")) if p.is_dir() else [p]:
            h.update(f.relative_to(REPO).as_posix().encode())
            h.update(f.read_bytes())
    return h.hexdigest()[:16]


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "unknown"


def terrain_identity(description: str, spec: dict, terrain) -> rpb.TerrainIdentity:
    """What the terrain was: its DEM files' hashes (read in process, or as the terrain service
    reports the files it read) and its sources' description."""
    if "service" in spec:
        files = [rpb.TerrainFile(**f) for f in terrain.metadata().get("dem_files", ())]
    else:
        files = [rpb.TerrainFile(**file_identity(p)) for p in spec.get("dem", ())]
    try:
        sources = terrain.describe()
    except Exception as exc:  # noqa: BLE001 - a terrain without describe() is still recordable
        sources = [{"error": str(exc)}]
    return rpb.TerrainIdentity(description=description, files=files,
                               sources_json=json.dumps(sources, sort_keys=True, default=str))


def recording_header(scenario_path, scenario, world, terrain_desc: str, terrain_spec: dict, terrain,
                     chunk_s: float = DEFAULT_CHUNK_S, steps: codec.Steps = codec.DEFAULT_STEPS,
                     scenario_text: str | None = None, terrain_id: rpb.TerrainIdentity | None = None
                     ) -> rpb.RecordingHeader:
    """The header of a sortie of ``scenario`` (read from ``scenario_path``, unless its
    ``scenario_text`` is given) on ``terrain`` (described by ``terrain_id`` when given: a
    take-over's, as its recording had it)."""
    text = Path(scenario_path).read_text(encoding="utf-8") if scenario_text is None else scenario_text
    ex = scenario.exercise
    return rpb.RecordingHeader(
        format_version=FORMAT_VERSION, sortie_version=_version("sortie"), jsbsim_version=_version("jsbsim"),
        build_id=build_id(), exercise_name=ex.name, start_time=ex.start_time.isoformat().replace("+00:00", "Z"),
        world_rate_hz=1.0 / world.dt, fdm_rate_hz=1.0 / world.fdm_dt, scenario_toml=text,
        scenario_path=str(Path(scenario_path).resolve()),
        scenario_sha256=hashlib.sha256(text.encode("utf-8")).hexdigest(),
        terrain=terrain_id if terrain_id is not None else terrain_identity(terrain_desc, terrain_spec, terrain),
        created_unix_s=time.time(),
        quantization=quantization_of(steps), chunk_s=chunk_s, geoid_undulation_m=world.geoid_undulation_m)


def event_record(tick: int, ev) -> rpb.EventRecord:
    return rpb.EventRecord(tick=tick, event=pb.WorldEvent(
        time_s=ev.time_s, kind=ev.kind, entity_id=ev.entity_id, lat_deg=ev.lat_deg, lon_deg=ev.lon_deg,
        alt_msl_m=ev.alt_msl_m, detail_json=json.dumps(ev.detail, sort_keys=True, default=str)))


def input_record(tick: int, kind: str, entity_id: int, fields: dict) -> rpb.InputRecord:
    r = rpb.InputRecord(tick=tick, kind=kind, entity_id=entity_id)
    if kind == "command":
        r.command = fields["command"]
        r.values_json = json.dumps(fields["values"], sort_keys=True)  # floats as repr: exact
    elif kind == "claim":
        r.client = fields.get("client", "")
    elif kind == "release":
        r.vanished = bool(fields.get("vanished", False))
    elif kind == "remove":
        r.reason = fields.get("reason", "")
    elif kind in ("external", "take_over"):
        r.values_json = json.dumps(fields, sort_keys=True)  # floats as repr: exact
    return r


def check_chunk_s(chunk_s: float, field: str = "chunk_s") -> None:
    """InvalidArgument naming ``field`` unless ``chunk_s`` is a number of seconds in (0, MAX_CHUNK_S]."""
    try:
        ok = math.isfinite(chunk_s) and 0.0 < chunk_s <= MAX_CHUNK_S
    except TypeError:
        ok = False
    if not ok:
        from sortie.errors import InvalidArgument

        raise InvalidArgument(field, f"must be a number of seconds in (0, {MAX_CHUNK_S:g}]", value=chunk_s)


class _OpenChunk:
    def __init__(self):
        self.snapshots: list = []  # server.world.Snapshot (immutable: the world makes new arrays each tick)
        self.inputs: list = []
        self.events: list = []
        self.new_entities: list = []
        self.wall_start = None
        self.states = 0  # entity states in snapshots (MAX_CHUNK_STATES)


class Recorder:
    """Records a world into ``path`` (a new file) with ``header``; see the module docstring."""

    def __init__(self, path, header: rpb.RecordingHeader, chunk_s: float = DEFAULT_CHUNK_S):
        check_chunk_s(chunk_s)
        header.chunk_s = chunk_s
        self.path = Path(path)
        self.header = header
        self.steps = steps_of(header)
        self.rate_hz = header.world_rate_hz
        self.chunk_s = chunk_s
        # A chunk closes at the tick after which one more would take it to chunk_s since the last
        # tick on disk: it holds at most chunk_s - dt of world time, and the dt left over is the
        # write's and fdatasync's time, so a kill -9 loses at most chunk_s (issue #6's bound, with
        # the write included; 30 ticks of 1/30 s lost 1.0 s plus the write, bench kill9_lost_s).
        self.chunk_ticks = max(1, math.floor(chunk_s * self.rate_hz - 1.0 + CHUNK_TICKS_EPS))
        self._writer = RecordingWriter(path, header)
        self._lock = threading.Lock()
        self._open = _OpenChunk()
        self._seen: set = set()
        self._last_ids = np.zeros(0, np.int64)
        self._queue: queue.Queue = queue.Queue(MAX_QUEUED_CHUNKS)
        self.error: Exception | None = None
        self.chunks_coded = 0  # chunks coded and written to the file, not yet necessarily on the disk
        self.chunks_written = 0  # chunks on the disk (fdatasync returned)
        self.cpu_s = 0.0  # CPU time of the writer thread's coding and writing
        self.sync_s = 0.0  # wall time of the writer thread's fdatasync calls (off the clock thread)
        self.closed = False
        self._thread = threading.Thread(target=self._run, name="recorder", daemon=True)
        self._thread.start()

    # -- hooks (server/world.py) ----------------------------------------------------------------

    def on_tick(self, snapshot, infos: dict) -> None:
        """Keep the tick's snapshot (ordering, digest and coding happen on the writer thread;
        the clock thread only looks for entities it has not seen when the ids change)."""
        ids = snapshot.ids
        if not (ids.size == self._last_ids.size and np.array_equal(ids, self._last_ids)):
            self._last_ids = ids
            new = [i for i in ids.tolist() if i not in self._seen and i in infos]
        else:
            new = ()
        with self._lock:
            c = self._started()
            c.snapshots.append(snapshot)
            c.states += ids.size
            for i in new:
                self._seen.add(i)
                _, name, kind, type_, coalition, *external = infos[i]
                c.new_entities.append(pb.EntityInfo(entity_id=i, name=name, kind=kind, type=type_,
                                                    coalition=coalition, external_id="".join(external)))
            if (len(c.snapshots) >= self.chunk_ticks or c.states >= MAX_CHUNK_STATES
                    or time.monotonic() - c.wall_start >= self.chunk_s):
                self._close_open()

    def on_input(self, tick: int, kind: str, entity_id: int, fields: dict) -> None:
        r = input_record(tick, kind, entity_id, fields)
        with self._lock:
            self._started().inputs.append(r)

    def on_event(self, tick: int, ev) -> None:
        r = event_record(tick, ev)
        with self._lock:
            self._started().events.append(r)

    def _started(self) -> _OpenChunk:
        """The open chunk, its wall age counted from now if it is empty (called under the lock):
        inputs made while the clock is paused are written after ``chunk_s`` like ticks."""
        c = self._open
        if c.wall_start is None:
            c.wall_start = time.monotonic()
        return c

    # -- chunks ---------------------------------------------------------------------------------

    def _close_open(self) -> None:
        """Hand the open chunk to the writer thread (called under the lock)."""
        c, self._open = self._open, _OpenChunk()
        self._put(c)

    def _put(self, item) -> None:
        """Queue ``item`` for the writer thread, waiting while the queue is full (a slow disk makes
        the clock wait), but not for a writer thread that stopped, nor a chunk for a recording that
        did (``error`` says why); None, the end, goes to a writer thread that runs."""
        while self._thread.is_alive() and (item is None or self.error is None):
            try:
                self._queue.put(item, timeout=MAX_POLL_S)
                return
            except queue.Full:
                continue

    def _close_if_old(self) -> None:
        """Close the open chunk once what it holds first is ``chunk_s`` wall seconds old: ticks,
        or inputs and events alone (the clock paused or slower than one tick in ``chunk_s``)."""
        with self._lock:
            c = self._open
            if c.wall_start is not None and time.monotonic() - c.wall_start >= self.chunk_s:
                self._close_open()

    def _run(self) -> None:
        try:
            self._write_chunks()
        except Exception as exc:  # noqa: BLE001 - any error stops the recording, never the exercise
            self.error = exc
            logger.error("recording to %s stopped: %s: %s", self.path, type(exc).__name__, exc)

    def _write_chunks(self) -> None:
        try:  # Linux: a thread's own nice value; the clock thread and the fdm workers come first
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICE)
        except (AttributeError, OSError):
            pass
        poll_s = min(self.chunk_s / 4, MAX_POLL_S)
        while True:
            try:
                c = self._queue.get(timeout=poll_s)
            except queue.Empty:
                self._close_if_old()
                continue
            if c is None:
                return
            if self.error is not None:
                continue
            try:
                t0 = time.thread_time()
                head, body = encode_chunk(c, self.steps, self.rate_hz)
                self._writer.write_chunk(head, body)
                self.cpu_s += time.thread_time() - t0
                self.chunks_coded += 1
                t1 = time.perf_counter()
                self._writer.sync(data_only=True)  # on the disk: a power loss loses the open chunk only
                self.sync_s += time.perf_counter() - t1
                self.chunks_written += 1
            except Exception as exc:  # noqa: BLE001 - the exercise goes on without its recording
                self.error = exc
                logger.error("recording to %s stopped: %s", self.path, exc)

    def close(self) -> None:
        """Write what is open, then the footer (idempotent)."""
        if self.closed:
            return
        self.closed = True
        with self._lock:
            if self._open.snapshots or self._open.inputs or self._open.events:
                self._close_open()
        self._put(None)
        self._thread.join()
        if self.error is None:
            try:
                self._writer.close()
            except OSError as exc:
                self.error = exc
                logger.error("recording to %s: footer not written: %s", self.path, exc)

    @property
    def bytes_written(self) -> int:
        return self._writer.bytes_written


def encode_chunk(c: _OpenChunk, steps: codec.Steps, rate_hz: float) -> tuple[rpb.ChunkHead, rpb.ChunkBody]:
    """The head and body of an open chunk's ticks, inputs and events: each tick's states in
    id order (recording_codec.state_matrix), digested exactly, quantised, coded."""
    t_count = len(c.snapshots)
    first_ids = c.snapshots[0].ids if t_count else None
    if t_count and all(s.ids is first_ids or np.array_equal(s.ids, first_ids) for s in c.snapshots):
        ids, states = codec.gather_states(c.snapshots)  # the usual chunk: the same entities throughout
        digests = [codec.digest(ids, m) for m in states]
        present = np.ones((t_count, ids.size), bool)
    else:
        frames = [codec.state_matrix(s) for s in c.snapshots]
        digests = [codec.digest(i, m) for i, m in frames]
        ids = np.unique(np.concatenate([i for i, _ in frames])) if t_count else np.zeros(0, np.int64)
        present = np.zeros((t_count, ids.size), bool)
        states = np.zeros((t_count, ids.size, codec.FIELDS))
        for t, (tick_ids, m) in enumerate(frames):
            cols = np.searchsorted(ids, tick_ids)
            present[t, cols] = True
            states[t, cols] = m
        states = codec.fill_absent(states, present)
    coded, clamped = codec.encode_states_counted(states, steps, rate_hz)
    if clamped:  # recorded at the limit, which readers flag (Recording.check); the recording goes on
        logger.warning("%d recorded values of the chunk from tick %d are beyond the recordable range "
                       "(%d quantisation steps) and were clamped to it", clamped,
                       c.snapshots[0].tick, codec.QUANTUM_LIMIT)
    body = rpb.ChunkBody(entity_ids=ids.tolist(), states=coded, digests=digests, inputs=c.inputs, events=c.events)
    if not present.all():
        body.present = np.packbits(present.reshape(-1)).tobytes()
    s0, s1 = (c.snapshots[0], c.snapshots[-1]) if t_count else (None, None)
    first = s0.tick if t_count else (c.inputs[0].tick + 1 if c.inputs else c.events[0].tick + 1)
    head = rpb.ChunkHead(first_tick=first, ticks=t_count, first_time_s=s0.time_s if t_count else 0.0,
                         last_time_s=s1.time_s if t_count else 0.0, new_entities=c.new_entities,
                         entity_count=ids.size, event_count=len(c.events), input_count=len(c.inputs))
    return head, body
