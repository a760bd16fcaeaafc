"""Tacview real-time telemetry of a live exercise (``sortie tacview``, issue #8).

    sortie tacview --server HOST:PORT [--port 42674] [--host 127.0.0.1] [--password P]
                   [--rate-hz 10] [--name NAME] [--geoid-undulation-m N]

A TCP server speaking Tacview's real-time telemetry protocol
(https://www.tacview.net/documentation/realtime/en/), so that Tacview
(Advanced) clients can watch a running Sortie exercise: "Record -> Real-time
telemetry", this host's address and port, and the password if one is set.

The protocol (Tacview's page above; the hash as interoperating hosts and
clients compute it, cited where the constants are defined):

- The third-party program is the host; Tacview connects to it. Right after
  the TCP connection the host sends its handshake, lines of UTF-8 text ended
  by a NUL: ``XtraLib.Stream.0\\n`` (low-level protocol),
  ``Tacview.RealTimeTelemetry.0\\n`` (high-level protocol), the host's name
  and ``\\n``, then ``\\0``. The client answers the same two protocol lines,
  its name, and the hash of the password it was given, then ``\\0``.
- The password hash is the CRC-64/WE (ECMA-182 polynomial, not reflected,
  all ones in and out) of the password's UTF-16LE bytes, written in lowercase
  hexadecimal without padding: an empty password hashes to ``0``. Older
  Tacview versions sent a CRC-32/ISO-HDLC (zlib's) of the same bytes; a
  protected host accepts either. A host without a password accepts any hash.
- Either side unhappy with the handshake closes the connection (here: a
  protocol other than those two lines, a malformed or oversized handshake, no
  handshake within :data:`HANDSHAKE_TIMEOUT_S`, or a wrong password; logged
  with the reason). After a good handshake the host streams plain ACMI 2.2
  text (https://www.tacview.net/documentation/acmi/en/), exactly as a file
  holds it, without a byte-order mark, and the client sends nothing more.

What we stream (the same text as ``sortie export acmi``, server/acmi.py, whose
functions build it):

- One session with the simulation server, as a **gateway** (every entity of
  the exercise, no area of interest): its Watch stream keeps the
  dead-reckoned picture (client.sim_client.Picture), its events stream the
  world events.
- At ``rate_hz`` the picture is sampled once, dead-reckoned to the server's
  world time now (at least a written time unit after the last frame's while
  the clock runs: the estimate steps back when an update comes late; frame
  times increase), as one numpy batch: geodetic position, attitude, rounding and
  change detection for every entity at once, the lines written by the export's
  compiled line writer. The frame's text is built once and the same bytes go
  to every client. A frame is ``#<world seconds since ReferenceTime>``, then
  a full line (``T=`` with every component, Name, Type, Coalition, Color,
  LongName) for each entity new in the picture, a line of the changed ``T=``
  components for each that moved, ``-<hex id>`` for each that left, and
  ``0,Event=...`` lines for the world events received since the last frame
  (crash -> Destroyed, takeoff -> TakenOff, touchdown -> Landed, others
  Message; spawns and removals are the object lines and removals).
- A new client first gets the header (``FileType``, ``FileVersion``,
  ``ReferenceTime`` = the exercise's start time, ``ReferenceLongitude`` and
  ``ReferenceLatitude`` = the whole degrees nearest the median position at
  start (longitude offsets unwrapped into (-180, 180], as the export writes
  them), ``Title``, ``DataSource``, ``DataRecorder``, ``RecordingTime``) and
  a key frame: the last frame's time and a full line of every object as last
  written; from the next frame on it gets the same bytes as everyone else.
- A new full snapshot (``WatchUpdate.snapshot``: a replay's seek or step,
  ``sortie replay``) restarts the frame clock at its world time: the next
  frame is at the new time, its positions the new picture's. Forward, that is
  one more frame. Backward it cannot be streamed: an ACMI stream is a file
  being written, its frame times only increase (Tacview appends what it
  receives to the timeline it shows; the real-time protocol has no message
  to rewind or to start a recording over on the same connection). So every
  client streaming then is told the end of its stream (what it was sent is
  flushed, then the connection is closed, logged), as a simulator that
  restarts ends its stream; on reconnecting it gets a new header and a key
  frame at the new time, as any newcomer does.
- Altitude is metres above MSL: the ellipsoid height minus the geoid
  undulation the server states (WorldInfo ``geoid_undulation_m``), unless
  ``--geoid-undulation-m`` overrides it.

Slow and vanished clients: a client's bytes wait in its own asyncio
transport buffer (frames are written, never awaited), so a client that reads
slowly never delays the others; when its buffer passes ``max_buffer_bytes``
(:data:`DEFAULT_MAX_BUFFER_BYTES`, 4 MiB) it is disconnected (logged) and
what it had not received is thrown away. Its socket's kernel send buffer is
set to the same size (SO_SNDBUF, at most net.core.wmem_max; Linux's
autotuning let a stalled loopback reader absorb 3-8 MB more), so a client
holds at most about twice ``max_buffer_bytes``: 8 MiB by default, some 20 s
of 1,000 moving entities at 10 Hz (42 kB a frame). A client that
disconnects is dropped quietly.

Threads: the SimClient's Watch and events streams run on their own threads;
the TCP server and the frame clock on an asyncio loop in a thread of its own
(:class:`TacviewTelemetry`), frames are built on one more thread so a large
batch never holds the loop. ``sortie tacview`` stops on SIGTERM/SIGINT, or
when the simulation server ends the exercise (exit 0, as ``sortie dis``) or goes
away (exit 1), closing every client's socket and leaving the session.
"""

from __future__ import annotations

import asyncio
import collections
import datetime as dt
import logging
import math
import re
import socket
import sys
import threading
import time
import zlib
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from server.acmi import (FILE_HEADER, T_DECIMALS, attitude_deg, escape, event_line, iso_utc, object_lines,
                         object_properties, pose_integers, reference_point, text_table, time_decimals, time_text)
from sortie import __version__
from sortie.errors import InvalidArgument, SortieError
from sortie.logs import line
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic

log = logging.getLogger(__name__)

# -- protocol constants (https://www.tacview.net/documentation/realtime/en/) ----------------------

DEFAULT_PORT = 42674  # Tacview's default real-time telemetry port
LOW_LEVEL_PROTOCOL = "XtraLib.Stream.0"
HIGH_LEVEL_PROTOCOL = "Tacview.RealTimeTelemetry.0"
HANDSHAKE_END = b"\0"
# The password hash. CRC-64/WE: width 64, poly 0x42F0E1EBA9EA3693, init and xorout all ones, not
# reflected (check("123456789") = 0x62ec59e3f1a4f00a), over the password's UTF-16LE bytes, lowercase
# hex without padding. So do SkyEye (github.com/dharmab/skyeye pkg/telemetry/handshake.go, with the
# test vectors "local" -> 16d6497244e5930b, "zerosugar" -> b8cd9b02e5dcacbd) and NOBlackBox's host
# (github.com/KopterBuzz/NOBlackBox pull 53); CRC-32/ISO-HDLC of the same bytes is what older Tacview
# versions sent (github.com/dharmab/skyeye pull 436 switches between the two).
CRC64_WE_POLY = 0x42F0E1EBA9EA3693
_MASK64 = (1 << 64) - 1
PASSWORD_ENCODING = "utf-16-le"

# -- our limits ---------------------------------------------------------------------------------

HANDSHAKE_TIMEOUT_S = 10.0  # a client that has not sent its handshake by then is closed
MAX_HANDSHAKE_BYTES = 4096  # names are short; anything longer is not Tacview
MAX_NAME_CHARS = 256  # the host name we send
DEFAULT_MAX_BUFFER_BYTES = 4 << 20  # a client's unsent bytes before it is dropped as too slow
MAX_CLIENTS = 64  # connected clients, handshakes under way included
DEFAULT_RATE_HZ = 10.0
MAX_RATE_HZ = 60.0
START_TIMEOUT_S = 15.0  # the simulation server's first snapshot
STOP_TIMEOUT_S = 5.0


class HandshakeError(SortieError):
    """A client's handshake is not Tacview's, or its password hash is wrong."""


# -- the handshake (pure functions) -------------------------------------------------------------

def _crc64_table() -> list[int]:
    table = []
    for byte in range(256):
        crc = byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ CRC64_WE_POLY) & _MASK64 if crc >> 63 else (crc << 1) & _MASK64
        table.append(crc)
    return table


_CRC64_TABLE = _crc64_table()


def crc64_we(data: bytes) -> int:
    """CRC-64/WE of ``data`` (see CRC64_WE_POLY)."""
    crc = _MASK64
    for b in data:
        crc = _CRC64_TABLE[((crc >> 56) ^ b) & 0xFF] ^ ((crc << 8) & _MASK64)
    return crc ^ _MASK64


def password_hash(password: str, algorithm: str = "crc64") -> str:
    """The hash a Tacview client sends for ``password``: "crc64" (Tacview now) or "crc32"
    (older versions) of its UTF-16LE bytes, lowercase hex without padding ("0" for none)."""
    data = password.encode(PASSWORD_ENCODING)
    if algorithm == "crc64":
        return format(crc64_we(data), "x")
    if algorithm == "crc32":
        return format(zlib.crc32(data), "x")
    raise InvalidArgument("algorithm", 'must be "crc64" or "crc32"', value=algorithm)


def host_handshake(host_name: str) -> bytes:
    """What the host sends first: the two protocol lines, its name, NUL."""
    return f"{LOW_LEVEL_PROTOCOL}\n{HIGH_LEVEL_PROTOCOL}\n{host_name}\n".encode() + HANDSHAKE_END


def client_handshake(client_name: str, password: str = "", algorithm: str = "crc64") -> bytes:
    """What a Tacview client answers (used by tests and tools that act as a client)."""
    return (f"{LOW_LEVEL_PROTOCOL}\n{HIGH_LEVEL_PROTOCOL}\n{client_name}\n"
            f"{password_hash(password, algorithm)}").encode() + HANDSHAKE_END


_HEX = re.compile(r"[0-9a-fA-F]{1,16}")


def parse_client_handshake(data: bytes) -> tuple[str, str]:
    """(client name, password hash) of a client's handshake (its bytes before the NUL);
    HandshakeError saying what is wrong. A line end before the NUL and CR LF are tolerated."""
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise HandshakeError("the handshake is not UTF-8 text") from None
    lines = [line.rstrip("\r") for line in text.split("\n")]
    if len(lines) == 5 and lines[4] == "":
        lines.pop()
    if len(lines) != 4:
        raise HandshakeError(f"the handshake has {len(lines)} lines, not 4 (got {text[:80]!r})")
    if lines[0] != LOW_LEVEL_PROTOCOL or lines[1] != HIGH_LEVEL_PROTOCOL:
        raise HandshakeError(f"protocol {lines[0][:40]!r} / {lines[1][:40]!r}, not "
                             f"{LOW_LEVEL_PROTOCOL} / {HIGH_LEVEL_PROTOCOL}")
    if not _HEX.fullmatch(lines[3]):
        raise HandshakeError(f"the password hash {lines[3][:40]!r} is not 1-16 hex digits")
    return lines[2], lines[3]


def password_accepted(password: str, hash_text: str) -> bool:
    """Whether a client's hash fits ``password`` (CRC-64/WE, or the older CRC-32); any hash
    when there is no password."""
    if not password:
        return True
    value = int(hash_text, 16)
    return value in (int(password_hash(password, "crc64"), 16), int(password_hash(password, "crc32"), 16))


def check_host_name(name: str) -> str:
    """The name sent in the handshake: 1-MAX_NAME_CHARS characters, no control characters
    (a line of the handshake); InvalidArgument otherwise."""
    if not (1 <= len(name) <= MAX_NAME_CHARS) or any(not c.isprintable() for c in name):
        raise InvalidArgument("name", f"must be 1-{MAX_NAME_CHARS} printable characters", value=name)
    return name


def check_rate_hz(rate_hz) -> float:
    try:
        rate = float(rate_hz)
    except (TypeError, ValueError):
        raise InvalidArgument("rate_hz", "must be a number of frames per second", value=rate_hz) from None
    if not (math.isfinite(rate) and 0.0 < rate <= MAX_RATE_HZ):
        raise InvalidArgument("rate_hz", f"must be in (0, {MAX_RATE_HZ:g}] frames per second", value=rate_hz)
    return rate


# -- the ACMI text ------------------------------------------------------------------------------

def header_text(world: pb.WorldInfo, ref_lon: int, ref_lat: int, recording_time: str) -> bytes:
    """The stream's header: file type and version, then the global properties (object 0)."""
    lines = [f"0,ReferenceTime={iso_utc(world.start_time, 'the server start_time')}",
             f"0,ReferenceLongitude={ref_lon}", f"0,ReferenceLatitude={ref_lat}"]
    if world.exercise_name:
        lines.append(f"0,Title={escape(world.exercise_name)}")
    lines.append("0,DataSource=Sortie live exercise")
    lines.append(f"0,DataRecorder=Sortie {__version__} (sortie tacview)")
    lines.append(f"0,RecordingTime={recording_time}")
    return (FILE_HEADER.lstrip("\ufeff") + "".join(line + "\n" for line in lines)).encode()


def pose_values(pos_ecef, quat_ecef2body, ref_lon: int, ref_lat: int, geoid_undulation_m: float = 0.0):
    """(n, 6) int64 ``T=`` components in units of their last written decimal (server.acmi
    T_DECIMALS): longitude and latitude offsets from the reference, altitude m MSL, roll,
    pitch, yaw.

    pos_ecef: (n, 3) float64, metres, ECEF; quat_ecef2body: (n, 4) float64 (w, x, y, z),
    rotation ECEF -> body; MSL = ellipsoid height - geoid_undulation_m.
    """
    pos = np.asarray(pos_ecef, dtype=np.float64)
    quat = np.asarray(quat_ecef2body, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3 or quat.shape != (pos.shape[0], 4):
        raise ValueError(f"pos_ecef must be (n, 3) and quat_ecef2body (n, 4), got {pos.shape} and {quat.shape}")
    lat, lon, h = ecef_to_geodetic(pos)
    roll, pitch, yaw = attitude_deg(quat, lat, lon)
    return pose_integers(np.stack([lon, lat, h - geoid_undulation_m, roll, pitch, yaw], axis=-1),
                         ref_lon, ref_lat)


class FrameBuilder:
    """The ACMI text of a live picture, frame by frame: what every client has been told
    (the objects in the stream, sorted by id, and the ``T=`` values last written), the
    next frame's changes, and a key frame of the whole for newcomers. Not thread-safe:
    one thread builds."""

    def __init__(self, ref_lon: int, ref_lat: int, geoid_undulation_m: float = 0.0, decimals: int = 3):
        self.ref = (int(ref_lon), int(ref_lat))
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.decimals = int(decimals)
        self.ids = np.zeros(0, np.int64)  # objects in the stream, ascending
        self.values = np.zeros((0, len(T_DECIMALS)), np.int64)  # their T= values as last written
        self.time_text: str | None = None  # the last frame's time
        self._text: dict[int, tuple[bytes, bytes, str]] = {}  # id -> (hex id, static properties, name)
        self._tables = (text_table([]), text_table([]))  # hex ids and properties, aligned with ids

    def frame(self, t_s: float, ids, pos_ecef, quat_ecef2body, infos: dict, events=(), emit: bool = True) -> bytes:
        """The frame at world time ``t_s`` of the picture (ids (n,) int64; pos_ecef (n, 3) m
        ECEF; quat_ecef2body (n, 4)), whose entity infos (sortie.v1.EntityInfo by id) are
        ``infos``, with the lines of ``events`` (sortie.v1.WorldEvent); b"" when nothing
        changed and the time text is the last frame's. An entity without an info yet waits
        for it (its lines would lack its name). ``emit`` False only updates what was
        written (no client listens)."""
        ids = np.asarray(ids, dtype=np.int64).reshape(-1)
        order = np.argsort(ids, kind="stable")
        ids = ids[order]
        pos = np.asarray(pos_ecef, dtype=np.float64).reshape(-1, 3)[order]
        quat = np.asarray(quat_ecef2body, dtype=np.float64).reshape(-1, 4)[order]
        rows = np.searchsorted(self.ids, ids)
        known = rows < self.ids.size
        known[known] = self.ids[rows[known]] == ids[known]
        if not known.all():  # newcomers without an info wait for it
            keep = known.copy()
            keep[~known] = [int(i) in infos for i in ids[~known]]
            ids, pos, quat, rows, known = ids[keep], pos[keep], quat[keep], rows[keep], known[keep]
        values = pose_values(pos, quat, *self.ref, self.geoid_undulation_m)
        changed = np.ones(values.shape, bool)
        changed[known] = values[known] != self.values[rows[known]]
        fresh = np.flatnonzero(~known)
        moved = np.flatnonzero(known & changed.any(axis=1))
        gone = self.ids[~np.isin(self.ids, ids, assume_unique=True)]
        if fresh.size or gone.size:
            self._relayout(ids, [int(i) for i in ids[fresh]], gone, infos)
        self.ids, self.values = ids, values
        t_text = time_text(t_s, self.decimals)
        same_time, self.time_text = t_text == self.time_text, t_text
        if not emit:
            return b""
        body = [object_lines(fresh, values[fresh], changed[fresh], self._tables[0], self._tables[1])[0],
                object_lines(moved, values[moved], changed[moved], self._tables[0])[0]]
        body += [f"-{int(i):x}\n".encode() for i in gone]
        body += self._event_lines(events, infos)
        if same_time and not any(body):
            return b""
        return f"#{t_text}\n".encode() + b"".join(body)

    def keyframe(self) -> bytes:
        """The last frame's time and a full line of every object as last written (what a
        client that starts now needs to agree with the others); b"" before any frame."""
        if self.time_text is None:
            return b""
        every = np.arange(self.ids.size)
        lines = object_lines(every, self.values, np.ones(self.values.shape, bool), *self._tables)[0]
        return f"#{self.time_text}\n".encode() + lines

    def _relayout(self, ids: np.ndarray, fresh: list[int], gone: np.ndarray, infos: dict) -> None:
        for i in gone.tolist():
            self._text.pop(i, None)
        for i in fresh:
            info = infos[i]
            self._text[i] = (f"{i:x}".encode(), object_properties(info).encode(), info.name or f"entity {i}")
        texts = [self._text[i] for i in ids.tolist()]
        self._tables = (text_table([t[0] for t in texts]), text_table([t[1] for t in texts]))

    def _event_lines(self, events, infos: dict) -> list[bytes]:
        out = []
        for ev in events:
            i = int(ev.entity_id)
            known = self._text.get(i)
            name = known[2] if known else (infos[i].name if i in infos else f"entity {i}" if i else "the world")
            line = event_line(ev, known[0].decode() if known else None, name)
            if line is not None:
                out.append((line + "\n").encode())
        return out


# -- the telemetry host -------------------------------------------------------------------------

@dataclass
class _Client:
    name: str
    peer: str
    writer: asyncio.StreamWriter
    closed: bool = False


class TacviewTelemetry:
    """A Tacview real-time telemetry host fed by one gateway session of a simulation server.

    ``start()`` joins, waits for the first picture, listens and returns the bound port
    (``port=0`` picks a free one); ``stop()`` closes every client and leaves. Counters:
    ``clients`` (streaming now), ``frames`` (frames sent), ``bytes_sent``, ``accepted``,
    ``rejected`` (bad handshakes), ``dropped_slow``; ``build_ms`` the time each frame took
    to sample and build. ``finished`` is set when it stops or its simulation server ends
    the exercise or goes away; ``error`` then says which: None for a clean end of the
    server's streams (the exercise's end, a server stopped by SIGTERM), else the failure.
    """

    def __init__(self, server_address: str, *, host: str = "127.0.0.1", port: int = DEFAULT_PORT,
                 password: str = "", rate_hz: float = DEFAULT_RATE_HZ, name: str = "Sortie",
                 max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES, geoid_undulation_m: float | None = None,
                 session_name: str = "tacview"):
        if not 0 <= int(port) <= 65535:
            raise InvalidArgument("port", "must be in [0, 65535]", value=port)
        if not int(max_buffer_bytes) > 0:
            raise InvalidArgument("max_buffer_bytes", "must be > 0", value=max_buffer_bytes)
        if geoid_undulation_m is not None and not math.isfinite(geoid_undulation_m):
            raise InvalidArgument("geoid_undulation_m", "must be finite", value=geoid_undulation_m)
        self.server_address = server_address
        self.host = host
        self.port = int(port)
        self.password = password
        self.rate_hz = check_rate_hz(rate_hz)
        self.name = check_host_name(name)
        self.max_buffer_bytes = int(max_buffer_bytes)
        self.geoid_undulation_m = geoid_undulation_m
        self.session_name = session_name
        self.clients = 0
        self.frames = 0
        self.bytes_sent = 0
        self.accepted = 0
        self.rejected = 0
        self.dropped_slow = 0
        self.build_ms: collections.deque = collections.deque(maxlen=10_000)
        self.finished = threading.Event()
        self.error: Exception | None = None  # why the server's streams ended, when they failed
        self.world: pb.WorldInfo | None = None
        self._sim = None  # client.sim_client.SimClient
        self._picture = None
        self._infos: dict = {}  # id -> EntityInfo; replaced (never mutated) by the Watch thread
        self._events: collections.deque = collections.deque()  # WorldEvents not yet in a frame
        self._events_thread: threading.Thread | None = None
        self._builder: FrameBuilder | None = None
        self._header = b""
        self._last_t = -math.inf
        self._snapshot_times: collections.deque = collections.deque()  # of full snapshots not yet framed
        self._loop: asyncio.AbstractEventLoop | None = None
        self._loop_thread: threading.Thread | None = None
        self._build_pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="tacview-frame")
        self._server: asyncio.AbstractServer | None = None
        self._frame_task: asyncio.Task | None = None
        self._streaming: list[_Client] = []
        self._newcomers: list[_Client] = []
        self._handshaking = 0  # connections whose handshake is still awaited
        self._stopping = False

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> int:
        """Join the exercise, take its first picture, listen; the bound TCP port."""
        from client.sim_client import SimClient

        self._sim = SimClient(self.server_address)
        try:
            self._sim.wait_ready(START_TIMEOUT_S)  # a SortieError naming the address when none answers
            self._sim.join(self.session_name, "gateway")
            self.world = self._sim.world()
            self._picture = self._sim.watch(listener=self._on_update)
            if not self._picture.snapshot_received.wait(START_TIMEOUT_S):
                raise SortieError(f"no picture from the simulation server at {self.server_address} "
                                  f"within {START_TIMEOUT_S:g} s")
            self._events_thread = threading.Thread(target=self._read_events, name="tacview-events", daemon=True)
            self._events_thread.start()
            self._prepare()
            self._loop = asyncio.new_event_loop()
            self._loop_thread = threading.Thread(target=self._loop.run_forever, name="tacview-loop", daemon=True)
            self._loop_thread.start()
            try:
                self.port = asyncio.run_coroutine_threadsafe(self._listen(), self._loop).result(START_TIMEOUT_S)
            except OSError as exc:
                raise SortieError(f"cannot listen on {self.host}:{self.port}: {exc}") from None
        except BaseException:
            self.stop()
            raise
        log.info("Tacview real-time telemetry on %s:%d for %s (%d entities, %g Hz)", self.host, self.port,
                 self.server_address, len(self._infos), self.rate_hz)
        return self.port

    def _prepare(self) -> None:
        """The reference point, the altitude datum, the header and the frame builder."""
        _, pos, _ = self._picture.state()
        if pos.shape[0]:
            lat, lon, _ = ecef_to_geodetic(pos)
            ref = reference_point(lat, lon)
        elif self.world.target_areas:  # nothing in the exercise yet: the middle of its areas
            a = self.world.target_areas
            ref = reference_point(np.concatenate([x.lat_deg for x in a]), np.concatenate([x.lon_deg for x in a]))
        else:
            ref = (0, 0)
        if self.geoid_undulation_m is None:
            self.geoid_undulation_m = self.world.geoid_undulation_m
        started = dt.datetime.now(dt.timezone.utc).isoformat()
        self._header = header_text(self.world, *ref, iso_utc(started, "now"))
        self._builder = FrameBuilder(*ref, self.geoid_undulation_m, time_decimals(1.0 / self.rate_hz))

    def stop(self) -> None:
        """Close every client, stop listening, leave the exercise (idempotent)."""
        self._stopping = True
        if self._loop is not None and self._loop.is_running():
            try:
                asyncio.run_coroutine_threadsafe(self._shutdown(), self._loop).result(STOP_TIMEOUT_S)
            except Exception:  # noqa: BLE001 - stopping goes on whatever a socket says
                log.exception("closing the Tacview clients")
            self._loop.call_soon_threadsafe(self._loop.stop)
            self._loop_thread.join(STOP_TIMEOUT_S)
            self._loop.close()
        self._build_pool.shutdown(wait=True)
        if self._sim is not None:
            if self._sim.token:
                try:
                    self._sim.leave()
                except SortieError as exc:
                    log.info("leaving the exercise: %s", exc)
            self._sim.close()
        if self._events_thread is not None:
            self._events_thread.join(STOP_TIMEOUT_S)
        self.finished.set()

    @property
    def entities(self) -> int:
        """Entities in the picture now."""
        return len(self._infos)

    def stats(self) -> dict:
        b = np.array(self.build_ms) if self.build_ms else np.zeros(1)
        return {"clients": self.clients, "frames": self.frames, "bytes_sent": self.bytes_sent,
                "accepted": self.accepted, "rejected": self.rejected, "dropped_slow": self.dropped_slow,
                "build_p50_ms": float(np.percentile(b, 50)), "build_p99_ms": float(np.percentile(b, 99))}

    # -- the simulation side (Watch and events threads) -----------------------------------------

    def _on_update(self, picture, update) -> None:
        """Picture listener (the picture's listener thread, not under its lock): the entity infos."""
        if not (update.snapshot or update.left or update.entered):
            return
        if update.snapshot:  # the frame clock restarts at its time (see the module docstring)
            self._snapshot_times.append(update.time_s)
        infos = {} if update.snapshot else dict(self._infos)
        for i in update.left:
            infos.pop(i, None)
        for info in update.entered:
            infos[info.entity_id] = info
        self._infos = infos

    def _read_events(self) -> None:
        """The events stream, until it ends: OK when the server ends the exercise (its streams
        close, as sortie dis and sortie client read them), an error when it goes away."""
        try:
            for ev in self._sim.events():
                self._events.append(ev)
        except SortieError as exc:
            if not self._stopping:
                self.error = exc
                log.warning("the simulation server's events stream failed: %s", exc)
        if not self._stopping:
            self.finished.set()

    # -- frames (the loop, the build thread) ----------------------------------------------------

    def _build(self, emit: bool, want_key: bool) -> tuple[bytes, bytes | None, bool]:
        """Sample the picture now and build the frame (and a key frame when asked); whether
        world time went back (a new snapshot earlier than the last frame: the streams end)."""
        t0 = time.perf_counter()
        snapshots = [self._snapshot_times.popleft() for _ in range(len(self._snapshot_times))]
        back = any(t < self._last_t - 0.5 * 10.0 ** -self._builder.decimals for t in snapshots)
        if snapshots:  # a new picture at its own time: the frame clock starts over there
            self._last_t = -math.inf
        t = self._picture.now_s()
        # The estimate of world time steps back when an update arrives late: frames still
        # advance (by more than a written time unit) while the clock runs, and stay put
        # while it is paused.
        step = 1.5 * 10.0 ** -self._builder.decimals if self._picture.time_scale > 0 else 0.0
        t = max(t, self._last_t + step)
        self._last_t = t
        ids, pos, quat = self._picture.state(t)
        events = [self._events.popleft() for _ in range(len(self._events))]
        delta = self._builder.frame(t, ids, pos, quat, self._infos, events, emit=emit)
        key = self._builder.keyframe() if want_key else None
        self.build_ms.append((time.perf_counter() - t0) * 1e3)
        return delta, key, back

    async def _frames(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        due = loop.time()
        try:
            while True:
                due += period
                wait = due - loop.time()
                if wait < -period:  # fell behind (a long build, a busy machine): skip, do not burst
                    due = loop.time()
                await asyncio.sleep(max(wait, 0.0))
                if self._picture.error is not None:
                    self.error = self.error or self._picture.error
                    log.warning("the simulation server's Watch stream failed: %s", self._picture.error)
                    self.finished.set()
                    return
                newcomers = list(self._newcomers)
                delta, key, back = await loop.run_in_executor(self._build_pool, self._build,
                                                              bool(self._streaming), bool(newcomers))
                if back:  # an ACMI stream cannot go back in time: end those streaming (docstring)
                    for c in list(self._streaming):
                        log.info("Tacview client %r at %s: world time went back (a replay's seek): its stream "
                                 "ends; reconnecting starts a new one at the new time", c.name, c.peer)
                        self._drop(c)
                    delta = b""
                if delta:
                    for c in list(self._streaming):
                        self._send(c, delta)
                    self.frames += 1
                for c in newcomers:
                    if c in self._newcomers:  # else it left while the frame was built
                        self._newcomers.remove(c)
                    if not c.closed:
                        self._streaming.append(c)
                        self._send(c, self._header + key)
                self.clients = len(self._streaming)
        except asyncio.CancelledError:
            raise
        except Exception as exc:  # noqa: BLE001 - a broken frame clock must say why and stop the host
            log.exception("Tacview frames stopped by an error")
            self.error = self.error or exc
            self.finished.set()

    def _send(self, c: _Client, data: bytes) -> None:
        if c.closed:
            return
        c.writer.write(data)
        self.bytes_sent += len(data)
        queued = c.writer.transport.get_write_buffer_size()
        if queued > self.max_buffer_bytes:
            log.warning("Tacview client %r at %s is too slow (%d bytes unsent > %d): disconnected", c.name, c.peer,
                        queued, self.max_buffer_bytes)
            self.dropped_slow += 1
            self._drop(c, abort=True)

    # -- the TCP side (the loop) ----------------------------------------------------------------

    async def _listen(self) -> int:
        self._server = await asyncio.start_server(self._serve_client, self.host, self.port,
                                                  limit=MAX_HANDSHAKE_BYTES)
        self._frame_task = asyncio.get_running_loop().create_task(self._frames())
        return self._server.sockets[0].getsockname()[1]

    async def _serve_client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = "%s:%s" % writer.get_extra_info("peername")[:2]
        if len(self._streaming) + len(self._newcomers) + self._handshaking >= MAX_CLIENTS:
            log.warning("Tacview client at %s refused: %d clients already", peer, MAX_CLIENTS)
            self.rejected += 1
            writer.close()
            return
        writer.write(host_handshake(self.name))
        self._handshaking += 1
        try:
            data = await asyncio.wait_for(reader.readuntil(HANDSHAKE_END), HANDSHAKE_TIMEOUT_S)
            client_name, hash_text = parse_client_handshake(data[:-1])
            if not password_accepted(self.password, hash_text):
                raise HandshakeError(f"client {client_name!r}: wrong password")
        except (HandshakeError, asyncio.TimeoutError, asyncio.IncompleteReadError, asyncio.LimitOverrunError,
                ConnectionError) as exc:
            reason = {asyncio.TimeoutError: f"no handshake within {HANDSHAKE_TIMEOUT_S:g} s",
                      asyncio.IncompleteReadError: "closed before its handshake ended",
                      asyncio.LimitOverrunError: f"handshake longer than {MAX_HANDSHAKE_BYTES} bytes"}.get(
                type(exc), str(exc) or type(exc).__name__)
            log.warning("Tacview client at %s refused: %s", peer, reason)
            self.rejected += 1
            writer.close()
            return
        finally:
            self._handshaking -= 1
        # The kernel's share of a slow client's backlog: as much again as ours (Linux's send
        # buffer autotuning would let it grow to net.ipv4.tcp_wmem's maximum, 4 MiB by default).
        writer.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, self.max_buffer_bytes)
        c = _Client(client_name, peer, writer)
        self.accepted += 1
        self._newcomers.append(c)
        log.info("Tacview client %r connected from %s", client_name, peer)
        try:
            while await reader.read(1 << 16):  # Tacview sends nothing more; the end of it is the client gone
                pass
        except (ConnectionError, OSError):
            pass
        finally:
            if not c.closed:
                log.info("Tacview client %r at %s disconnected", c.name, c.peer)
            self._drop(c)

    def _drop(self, c: _Client, abort: bool = False) -> None:
        if c in self._streaming:
            self._streaming.remove(c)
        if c in self._newcomers:
            self._newcomers.remove(c)
        self.clients = len(self._streaming)
        if c.closed:
            return
        c.closed = True
        if abort:  # its unsent bytes are thrown away
            c.writer.transport.abort()
        else:
            c.writer.close()

    async def _shutdown(self) -> None:
        if self._frame_task is not None:
            self._frame_task.cancel()
            try:
                await self._frame_task
            except asyncio.CancelledError:
                pass
        if self._server is not None:
            self._server.close()
        for c in list(self._streaming) + list(self._newcomers):
            self._drop(c)
        if self._server is not None:
            await self._server.wait_closed()


# -- sortie tacview -------------------------------------------------------------------------------

def add_parser(sub) -> None:
    from server.grpc_common import HOST_HELP

    p = sub.add_parser("tacview", help="serve a live exercise to Tacview (real-time telemetry)",
                       description="Join a simulation server as a gateway and serve Tacview's real-time "
                                   "telemetry protocol (ACMI 2.2 over TCP) until SIGTERM/SIGINT, the server's end "
                                   "of the exercise (exit 0) or the server going away (exit 1); in Tacview: "
                                   "Record > Real-time telemetry, this address and port.")
    p.add_argument("--server", required=True, metavar="HOST:PORT", help="the simulation server")
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port to listen on (default %(default)s; "
                                                                  "0 picks a free one)")
    p.add_argument("--host", default="127.0.0.1", help=f"{HOST_HELP} (default %(default)s)")
    p.add_argument("--password", default="",
                   help="password Tacview clients must give (default none); SORTIE_TACVIEW_PASSWORD in the "
                        "environment keeps it out of the process list (sortie/config.py)")
    p.add_argument("--rate-hz", type=float, default=DEFAULT_RATE_HZ,
                   help=f"frames per second (default %(default)s, at most {MAX_RATE_HZ:g})")
    p.add_argument("--name", default="Sortie", help="host name shown to Tacview (default %(default)s)")
    p.add_argument("--geoid-undulation-m", type=float, metavar="N",
                   help="override the geoid height above the ellipsoid the server states (WorldInfo); "
                        "altitudes are MSL")
    p.set_defaults(func=tacview_command)


def tacview_command(args) -> int:
    from server.grpc_common import stop_signals, wait_for_signal
    from server.grpc_common import bare_host, listen_address

    telemetry = TacviewTelemetry(args.server, host=bare_host(args.host), port=args.port, password=args.password,
                                 rate_hz=args.rate_hz, name=args.name, geoid_undulation_m=args.geoid_undulation_m)
    with stop_signals() as stop:  # before the line that says it listens (grpc_common.stop_signals)
        port = telemetry.start()
        line(f"sortie tacview: Tacview real-time telemetry on {listen_address(args.host, port)} for {args.server} "
             f"({telemetry.entities} entities, {telemetry.rate_hz:g} Hz"
             f"{', password set' if args.password else ''})", logger=__name__)
        try:
            wait_for_signal(telemetry.finished, stop=stop)
        finally:
            ended = telemetry.finished.is_set()  # by the server, not by a signal
            telemetry.stop()
    s = telemetry.stats()
    line(f"sortie tacview stopped: {s['accepted']} clients served, {s['rejected']} refused, "
         f"{s['dropped_slow']} dropped as too slow, {s['frames']} frames, {s['bytes_sent']:,} bytes", logger=__name__)
    if ended and telemetry.error is not None:  # as sortie dis: 1 when the server went away
        line(f"sortie tacview: the simulation server at {args.server} went away: {telemetry.error}",
             stream=sys.stderr, level=logging.ERROR, logger=__name__)
        return 1
    if ended:
        line(f"sortie tacview: the simulation server at {args.server} ended the exercise", logger=__name__)
    return 0
