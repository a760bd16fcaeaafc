"""Tacview real-time telemetry (server/tacview_live.py, ``sortie tacview``, issue #8).

Real parts: a simulation server in process on a free port (real JSBSim
aircraft, ground vehicles on the embedded SRTM tile, realtime clock), the
telemetry host on a real TCP socket, and :class:`TacviewReader` below, a
small Tacview client written from the protocol's documentation
(https://www.tacview.net/documentation/realtime/en/) and the ACMI 2.2
specification (https://www.tacview.net/documentation/acmi/en/), sharing no
code with the host's ACMI writer: exact handshake bytes both ways, the
password hash, and an incremental reader of the stream.

Error bound of a streamed position (checked at every frame for every entity):
the frame shows the server's dead reckoning at the frame's world time t; the
truth is the world's state at t, interpolated linearly between the two ticks
around it (1/30 s apart: under 2 mm from the path at the accelerations here).
The server sends a new state when the dead-reckoned position would be more
than 1 m off (DR threshold, checked at the 20 Hz network rate); between two
checks, and from the last one to t (the network period plus the delivery:
<= 0.1 s of world time), the error goes on growing at its rate of change,
under 8 m/s for these aircraft and vehicles (+0.8 m); the text is rounded to
1e-7 degrees (1.1 cm) and 1 cm. Bound: POSITION_TOL_M = 1 + 0.8 + 0.2 m of
margin = 2 m (seen: 0.93-1.34 m). Attitude: the 3 degree DR threshold, the
0.1 degree text and half a tick of the body rates (seen: 2.2 degrees).
"""

from __future__ import annotations

import math
import os
import re
import signal
import socket
import subprocess
import time
import zlib

import numpy as np
import pytest

from fdm.aircraft import InitialConditions
from fdm.state import euler_to_quaternion
from server import tacview_live as tl
from server.dead_reckoning import ned_to_ecef_quat, rotation_angle
from server.process import free_port, sortie_command
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from terrain.geodesy import geodetic_to_ecef

GEOID_UNDULATION_M = 48.0  # the alps scenario's: altitudes are MSL = ellipsoid height - 48 m
START_TIME = "2026-06-15T07:00:00Z"
EXERCISE = "Live, Tacview"  # a comma: escaped in the header's Title
POSITION_TOL_M = 2.0
ATTITUDE_TOL_DEG = 3.0 + 0.1 + 0.2
HOST_NAME = "Sortie test"
PASSWORD = "zérø secret"  # not ASCII: the hash is over UTF-16LE
EXPECTED_TYPES = {"viper1": "Air+FixedWing", "cessna": "Air+FixedWing", "tank1": "Ground+Heavy+Armor+Vehicle+Tank",
                  "sam1": "Ground+AntiAircraft", "far-radar": "Ground+Static+Building"}  # Tacview's type tags


# -- the simulation server ------------------------------------------------------------------------

@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _world(alps) -> World:
    w = World(alps, geoid_undulation_m=GEOID_UNDULATION_M)
    w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     coalition="blue", route=[(47.30, 9.60, 3500.0), (47.45, 9.70, 3500.0)])
    w.spawn_aircraft("cessna", "c172x", InitialConditions(47.45, 9.45, 1500.0, heading_deg=0.0, speed_mps=50.0),
                     route=[(47.50, 9.45, 1500.0), (47.50, 9.55, 1600.0), (47.45, 9.50, 1500.0)])
    w.spawn_ground(["c1", "c2", "c3"], "hmmwv", [47.2412, 47.2408, 47.2404], [9.5229, 9.5226, 9.5223], 27.0,
                   route=[(47.24, 9.522), (47.26, 9.537), (47.28, 9.552)], cruise_mps=10.0, spacing_m=50.0)
    n = 24  # trucks driving up the flat Rhine valley: traffic in every frame
    trucks = w.spawn_ground([f"truck{k}" for k in range(n)], "hmmwv", 47.33 + 0.001 * (np.arange(n) // 6),
                            9.57 + 0.001 * (np.arange(n) % 6), 20.0, coalition="red")
    for e in trucks:
        w.command(e.id, "autopilot", {"heading_deg": 20.0, "speed_mps": 15.0})
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, coalition="red")
    w.spawn_static("sam1", "sam_site", 47.35, 9.45, coalition="red")
    w.spawn_static("far-radar", "radar", 47.95, 9.95)
    return w


class Truth:
    """Every world tick's snapshot (the clock thread calls world.tick)."""

    def __init__(self, world: World):
        self.snaps = []
        original = world.tick

        def tick():
            events = original()
            self.snaps.append(world.snapshot)
            return events

        world.tick = tick

    def at(self, t: float, entity_id: int):
        """(ECEF position interpolated at world time t, quaternion and body rates of the
        nearest tick, ticks apart) of an entity; None when t is not bracketed yet."""
        snaps = self.snaps
        times = [s.time_s for s in snaps]
        k = int(np.searchsorted(times, t))
        if k == 0 or k >= len(snaps):
            return None
        a, b = snaps[k - 1], snaps[k]
        ia, ib = a.index().get(entity_id), b.index().get(entity_id)
        if ia is None or ib is None:
            return None
        f = (t - a.time_s) / (b.time_s - a.time_s)
        pos = (1 - f) * a.ecef_m[ia] + f * b.ecef_m[ib]
        near, i = (a, ia) if f < 0.5 else (b, ib)
        return pos, near.quat_ecef2body[i], near.body_rates_rps[i], b.time_s - a.time_s


@pytest.fixture(scope="module")
def sim(alps):
    w = _world(alps)
    srv = SimulationServer(w, ServerConfig(exercise_name=EXERCISE, start_time=START_TIME, clock="realtime"))
    srv.truth = Truth(w)
    srv.start()
    yield srv
    srv.stop(0.5)
    w.close()


@pytest.fixture()
def telemetry(sim):
    started = []

    def start(**kw):
        kw.setdefault("name", HOST_NAME)
        t = tl.TacviewTelemetry(sim.address, port=0, **kw)  # the server states its geoid undulation
        t.start()
        started.append(t)
        return t

    yield start
    for t in started:
        t.stop()


# -- a Tacview client -----------------------------------------------------------------------------

def crc64_we_bitwise(data: bytes) -> int:
    """CRC-64/WE straight from its definition (poly 0x42F0E1EBA9EA3693, init and xorout all
    ones, not reflected), one bit at a time: the oracle of the host's table version."""
    crc = (1 << 64) - 1
    for byte in data:
        crc ^= byte << 56
        for _ in range(8):
            crc = ((crc << 1) ^ 0x42F0E1EBA9EA3693) if crc >> 63 else crc << 1
            crc &= (1 << 64) - 1
    return crc ^ ((1 << 64) - 1)


def client_hello(name: str, password: str = "", crc: str = "crc64") -> bytes:
    data = password.encode("utf-16-le")
    value = crc64_we_bitwise(data) if crc == "crc64" else zlib.crc32(data)
    return f"XtraLib.Stream.0\nTacview.RealTimeTelemetry.0\n{name}\n{value:x}".encode() + b"\0"


T_NAMES = ("lon", "lat", "alt", "roll", "pitch", "yaw")


class TacviewReader:
    """A Tacview client: handshake, then an incremental ACMI 2.2 reader of the stream.

    Keeps the header lines, the global properties, every frame time, each object's
    properties and present T= values (longitude and latitude made absolute with the
    reference), and, at every frame, every present object's T= values."""

    def __init__(self, port: int, hello: bytes | None = None, rcvbuf: int | None = None):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(5.0)
        self.sock.connect(("127.0.0.1", port))
        self.host_hello = b""
        while not self.host_hello.endswith(b"\0"):
            chunk = self.sock.recv(1)
            if not chunk:
                break
            self.host_hello += chunk
        if hello is not None:
            self.sock.sendall(hello)
        self.raw = b""  # everything received after the host's handshake
        self.closed = False
        self._pending = b""
        self.lines: list[str] = []
        self.globals: dict[str, str] = {}
        self.objects: dict[str, dict] = {}  # hex id -> {property: value, "T": [6 floats]}
        self.frames: list[float] = []
        self.samples: list[tuple] = []  # (frame time, hex id, lon, lat, alt, roll, pitch, yaw)
        self.removed: list[tuple[float, str]] = []
        self.events: list[tuple[float, str]] = []
        self.t = None

    def pump(self, seconds: float) -> None:
        """Read for ``seconds`` (or until the host closes)."""
        end = time.monotonic() + seconds
        while not self.closed and time.monotonic() < end:
            self.sock.settimeout(max(0.01, min(0.2, end - time.monotonic())))
            try:
                chunk = self.sock.recv(1 << 16)
            except socket.timeout:
                continue
            except ConnectionResetError:
                chunk = b""
            if not chunk:
                self.closed = True
                break
            self.raw += chunk
            self._feed(chunk)

    def until(self, predicate, timeout_s: float = 10.0) -> bool:
        end = time.monotonic() + timeout_s
        while not predicate(self) and not self.closed and time.monotonic() < end:
            self.pump(0.1)
        return bool(predicate(self))

    def close(self) -> None:
        self.sock.close()

    def _feed(self, chunk: bytes) -> None:
        *complete, self._pending = (self._pending + chunk).split(b"\n")
        for raw in complete:
            line = raw.decode("utf-8")
            self.lines.append(line)
            self._line(line)

    def _line(self, line: str) -> None:
        if len(self.lines) <= 2:  # FileType, FileVersion
            return
        if line.startswith("#"):
            if self.t is not None:
                self._sample()
            self.t = float(line[1:])
            self.frames.append(self.t)
        elif line.startswith("-"):
            self.removed.append((self.t, line[1:]))
            self.objects.pop(line[1:], None)
        else:
            oid, *props = re.split(r"(?<!\\),", line)
            for prop in props:
                key, value = prop.split("=", 1)
                value = value.replace("\\,", ",")
                if oid == "0":
                    if key == "Event":
                        self.events.append((self.t, value))
                    else:
                        self.globals[key] = value
                elif key == "T":
                    obj = self.objects.setdefault(oid, {"T": [math.nan] * 6})
                    for j, v in enumerate(value.split("|")):
                        if v:
                            ref = {0: "ReferenceLongitude", 1: "ReferenceLatitude"}.get(j)
                            obj["T"][j] = float(v) + (float(self.globals[ref]) if ref else 0.0)
                else:
                    self.objects.setdefault(oid, {"T": [math.nan] * 6})[key] = value

    def _sample(self) -> None:
        for oid, obj in self.objects.items():
            self.samples.append((self.t, oid, *obj["T"]))


# -- tests ----------------------------------------------------------------------------------------

def test_password_hash_is_crc64_we_of_utf16le_as_tacview_clients_send_it():
    assert tl.crc64_we(b"123456789") == 0x62EC59E3F1A4F00A  # the CRC-64/WE check value
    # Published vectors (github.com/dharmab/skyeye pkg/telemetry/handshake_test.go).
    assert tl.password_hash("") == "0"
    assert tl.password_hash("local") == "16d6497244e5930b"
    assert tl.password_hash("zerosugar") == "b8cd9b02e5dcacbd"
    for pw in ("a", PASSWORD, "x" * 200):
        assert tl.password_hash(pw) == format(crc64_we_bitwise(pw.encode("utf-16-le")), "x")
        assert tl.password_hash(pw, "crc32") == format(zlib.crc32(pw.encode("utf-16-le")), "x")
    assert tl.password_accepted(PASSWORD, tl.password_hash(PASSWORD))
    assert tl.password_accepted(PASSWORD, tl.password_hash(PASSWORD, "crc32"))  # older Tacview
    assert not tl.password_accepted(PASSWORD, tl.password_hash("guess"))
    assert not tl.password_accepted(PASSWORD, "0")
    assert tl.password_accepted("", "0") and tl.password_accepted("", "16d6497244e5930b")
    assert tl.client_handshake("me", PASSWORD) == client_hello("me", PASSWORD)


def _entity_hex(sim) -> dict[str, str]:
    return {f"{e.id:x}": e.name for e in sim.world.entities.values()}


def test_handshake_header_and_every_entity_where_the_server_has_it(sim, telemetry):
    t = telemetry(password=PASSWORD, rate_hz=10)
    c = TacviewReader(t.port, client_hello("pytest client", PASSWORD))
    try:
        assert c.host_hello == b"XtraLib.Stream.0\nTacview.RealTimeTelemetry.0\nSortie test\n\0"
        assert c.until(lambda r: len(r.frames) >= 30, 15.0), (len(c.frames), c.raw[:300])
        # The header, as a file starts (without the byte-order mark).
        assert c.raw.startswith(b"FileType=text/acmi/tacview\nFileVersion=2.2\n")
        assert c.globals["ReferenceTime"] == "2026-06-15T07:00:00Z"
        assert c.globals["ReferenceLongitude"] == "10" and c.globals["ReferenceLatitude"] == "47"
        assert c.globals["Title"] == EXERCISE
        assert "0,Title=Live\\, Tacview" in c.lines
        # Frame times: world seconds, increasing; 10 Hz of a realtime clock.
        times = np.array(c.frames)
        assert np.all(np.diff(times) > 0)
        assert 0.05 < np.median(np.diff(times)) < 0.15
        assert abs(times[-1] - sim.world.time_s) < 1.0
        # Every entity, with its static properties.
        names = _entity_hex(sim)
        assert set(c.objects) == set(names)
        by_name = {e.name: e for e in sim.world.entities.values()}
        for oid, obj in c.objects.items():
            e = by_name[names[oid]]
            assert obj["Name"] == e.name and obj["LongName"] == e.type
            assert obj["Coalition"] == {"blue": "Blue", "red": "Red", "neutral": "Neutrals"}[e.coalition]
            assert obj["Color"] == {"blue": "Blue", "red": "Red", "neutral": "Grey"}[e.coalition]
            assert obj["Type"] == EXPECTED_TYPES.get(e.name, "Ground+Vehicle"), e.name  # trucks: Ground+Vehicle
        # Only changes: a static object's line is written once.
        sam = [k for k, v in names.items() if v == "sam1"][0]
        assert sum(1 for line in c.lines if line.startswith(f"{sam},")) == 1
        # Positions and attitudes against the world's ticks at the frame times.
        time.sleep(0.2)  # ticks after the last frame, to interpolate
        worst_m, worst_deg, checked = 0.0, 0.0, 0
        for ft, oid, lon, lat, alt, roll, pitch, yaw in c.samples:
            truth = sim.truth.at(ft, int(oid, 16))
            if truth is None:
                continue
            pos, quat, rates, dt = truth
            got = np.asarray(geodetic_to_ecef(lat, lon, alt + GEOID_UNDULATION_M), float).reshape(3)
            err = float(np.linalg.norm(got - pos))
            assert err <= POSITION_TOL_M, (names[oid], ft, err)
            q_ned = euler_to_quaternion(math.radians(roll), math.radians(pitch), math.radians(yaw))
            q = ned_to_ecef_quat(np.asarray(q_ned, float), lat, lon)
            angle = math.degrees(float(rotation_angle(q, quat)))
            allowed = ATTITUDE_TOL_DEG + math.degrees(float(np.linalg.norm(rates))) * dt / 2
            assert angle <= allowed, (names[oid], ft, angle, allowed)
            worst_m, worst_deg, checked = max(worst_m, err), max(worst_deg, angle), checked + 1
        assert checked >= 20 * len(names)
        print(f"{checked} states checked: worst position {worst_m:.3f} m, attitude {worst_deg:.2f} deg; "
              f"frame build p50 {t.stats()['build_p50_ms']:.2f} ms for {len(names)} entities")
        assert t.stats()["clients"] == 1 and t.stats()["accepted"] == 1
    finally:
        c.close()


def test_spawn_crash_and_removal_come_as_acmi(sim, telemetry):
    t = telemetry(rate_hz=20)
    c = TacviewReader(t.port, client_hello("pytest"))
    w = sim.world
    assert c.until(lambda r: len(r.frames) >= 3)
    target = w.spawn_static("target7", "bunker", 47.36, 9.46, coalition="red")
    # 8 m above the ground, gear up, not trimmed: its belly hits the ground within ~2 s.
    ic = InitialConditions(47.40, 9.62, 8.0, alt_ref="agl", heading_deg=90.0, speed_mps=100.0, trim=False,
                           gear_down=False)
    diver = w.spawn_aircraft("diver", "f16", ic, coalition="red")
    t_hex, d_hex = f"{target.id:x}", f"{diver.id:x}"
    try:
        # Spawns: new objects with their static properties.
        assert c.until(lambda r: t_hex in r.objects and d_hex in r.objects)
        assert c.objects[t_hex]["Name"] == "target7" and c.objects[t_hex]["Coalition"] == "Red"
        assert c.objects[d_hex]["Name"] == "diver" and c.objects[d_hex]["Type"] == "Air+FixedWing"
        # The crash (structure contact within ~2 s): a Destroyed event naming the object.
        assert c.until(lambda r: any(v.startswith(f"Destroyed|{d_hex}|") for _, v in r.events), 10.0), c.events
        ev_t, ev = [(et, v) for et, v in c.events if v.startswith("Destroyed|")][0]
        assert ev == f"Destroyed|{d_hex}|diver crashed: structure contact"
        crash = [e for e in w.events if e.kind == "crash" and e.entity_id == diver.id][0]
        assert crash.time_s <= ev_t < crash.time_s + 1.0
        # A removal: -id in a frame after it, and the object gone from the stream.
        w.remove(target.id, "destroyed by the test")
        assert c.until(lambda r: any(h == t_hex for _, h in r.removed), 5.0)
        n = len(c.frames)
        assert c.until(lambda r: len(r.frames) >= n + 3)
        assert not any(line.startswith(f"{t_hex},") for line in c.lines[-50:])
    finally:
        c.close()
        for e in (target, diver):
            if e.id in w.entities:
                w.remove(e.id)


def _state_at(reader: TacviewReader, t: float) -> dict:
    return {oid: tuple(v) for ft, oid, *v in reader.samples if ft == t}


def test_bad_handshakes_are_closed_without_acmi_while_a_good_client_streams(sim, telemetry):
    t = telemetry(password=PASSWORD)
    good = TacviewReader(t.port, client_hello("good", PASSWORD))
    try:
        assert good.until(lambda r: len(r.frames) >= 2)
        bad = [client_hello("wrong", "guess"),  # wrong password
               client_hello("none"),  # no password: "0"
               client_hello("v1", PASSWORD).replace(b"Stream.0", b"Stream.1"),  # another protocol
               b"GET / HTTP/1.1\r\nHost: x\r\n\r\n\0",  # not Tacview at all
               b"X" * (tl.MAX_HANDSHAKE_BYTES + 10)]  # no NUL, too long
        for hello in bad:
            frames_before = len(good.frames)
            c = TacviewReader(t.port, hello)
            c.pump(3.0)
            assert c.closed, hello[:40]
            assert c.host_hello == b"XtraLib.Stream.0\nTacview.RealTimeTelemetry.0\nSortie test\n\0"
            assert c.raw == b"", (hello[:40], c.raw[:100])  # not a byte of ACMI
            c.close()
            good.pump(0.3)
            assert len(good.frames) > frames_before  # the good client kept streaming meanwhile
        assert t.rejected == len(bad) and t.accepted == 1
        # The older CRC-32 hash is let in. Joining late, it gets the header and a key frame,
        # then the same frames as the client there from the start: both hold the same objects
        # with the same values at every later frame.
        old = TacviewReader(t.port, client_hello("old tacview", PASSWORD, crc="crc32"))
        assert old.until(lambda r: len(r.frames) >= 10) and old.raw.startswith(b"FileType=text/acmi/tacview\n")
        good.pump(0.5)
        common = sorted(set(old.frames[:-1]) & set(good.frames[:-1]))
        assert len(common) >= 8
        for ft in common:
            assert _state_at(old, ft) == _state_at(good, ft), ft
        old.close()
        assert good.until(lambda r: r.frames[-1] > 0 and t.stats()["clients"] == 1, 5.0)
    finally:
        good.close()


def test_a_stalled_client_is_dropped_and_never_slows_the_others(sim, telemetry):
    rate_hz, limit = 30, 16 << 10
    t = telemetry(rate_hz=rate_hz, max_buffer_bytes=limit)
    good = TacviewReader(t.port, client_hello("reader"))
    stalled = TacviewReader(t.port, client_hello("stalled"), rcvbuf=4096)  # never reads
    try:
        assert good.until(lambda r: len(r.frames) >= 5)
        start, n0 = time.monotonic(), len(good.frames)
        assert good.until(lambda r: t.dropped_slow == 1, 15.0), t.stats()
        window = time.monotonic() - start
        # The reader got its frames at the rate all along (70 %: a loaded machine's clock slips).
        assert len(good.frames) - n0 >= 0.7 * rate_hz * window, (len(good.frames) - n0, window)
        n = len(good.frames)
        assert good.until(lambda r: len(r.frames) >= n + 10, 3.0)
        assert t.stats()["clients"] == 1
        stalled.pump(5.0)  # what was in the kernel's buffers, then the reset
        assert stalled.closed
        # What it could hold: ours (the limit) and the kernel's (as much again, doubled for
        # bookkeeping), plus the frame that overflowed.
        assert len(stalled.raw) <= 4 * limit + 16384, len(stalled.raw)
        print(f"stalled client dropped after {window:.1f} s, {len(stalled.raw):,} bytes received; "
              f"the reader got {len(good.frames) - n0} frames meanwhile; {t.bytes_sent:,} bytes sent in all")
    finally:
        good.close()
        stalled.close()


def test_stop_closes_every_client(sim, telemetry):
    t = telemetry()
    a, b = TacviewReader(t.port, client_hello("a")), TacviewReader(t.port, client_hello("b"))
    assert a.until(lambda r: len(r.frames) >= 1) and b.until(lambda r: len(r.frames) >= 1)
    t.stop()
    a.pump(3.0)
    b.pump(3.0)
    assert a.closed and b.closed and t.finished.is_set()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", t.port), timeout=1.0).recv(1)


def test_the_command_serves_until_sigterm(sim):
    port = free_port()
    proc = subprocess.Popen([*sortie_command(), "tacview", "--server", sim.address, "--port", str(port),
                             "--name", "cli host", "--geoid-undulation-m", str(GEOID_UNDULATION_M)],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env={**os.environ, "SORTIE_TACVIEW_PASSWORD": PASSWORD})
    try:
        first = proc.stdout.readline()
        assert f"on 127.0.0.1:{port}" in first and "password set" in first, first
        c = TacviewReader(port, client_hello("pytest", PASSWORD))
        assert c.host_hello.endswith(b"\ncli host\n\0")
        assert c.until(lambda r: len(r.frames) >= 2 and len(r.objects) >= 10)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(15.0) == 0
        c.pump(2.0)
        assert c.closed
        out = proc.stdout.read()
        assert "sortie tacview stopped: 1 clients served" in out, out
    finally:
        if proc.poll() is None:
            proc.kill()
        proc.wait()
