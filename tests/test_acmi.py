"""Tacview ACMI export (server/acmi.py, ``sortie export acmi``).

Oracles: the recording itself, read back through two ACMI readers that share
no code with the writer: ``pyacmi`` (a published parser) and ``parse_acmi``
below, a small reader written from the ACMI 2.2 specification for what pyacmi
gets wrong. Both also read a real Tacview file (../shared/data/acmi) to show
they handle real-world syntax.

pyacmi 1.2.4, where it is wrong (so the spec reader checks those parts):
- ``0,Event=...`` lines are not kept (printed as "Unknown global property");
- escaped commas (``\\,``) in values are not unescaped;
- ``get_value(field, t)`` before a field's first value returns the first
  *later* value instead of none;
- ``-id`` of an object never declared raises KeyError;
- its import needs ``constantly``, which it does not declare.

Error bounds of the export against the recorded states (rounding to the
written decimals, plus float text round-off): longitude and latitude 0.5e-7
degrees (1e-6 asked), altitude 0.005 m MSL (0.01 asked), roll, pitch and yaw
0.05 degrees (0.1 asked), yaw and roll compared on the circle. The attitude
conversion itself is checked against Euler angles turned into ECEF
quaternions by fdm.state and server.dead_reckoning: 1e-6 degrees, and within
0.02 degrees through the recording's 2^-16 quaternion quantisation for
|pitch| <= 60 degrees (near +-90 degrees roll and yaw are ill-conditioned).
"""

from __future__ import annotations

import contextlib
import datetime as dt
import hashlib
import io
import subprocess
import sys
import types
import zipfile

import numpy as np
import pytest

from fdm.state import euler_to_quaternion
from server import acmi
from server import recording_codec as codec
from server.dead_reckoning import ned_to_ecef_quat
from server.recorder import Recorder, encode_chunk, recording_header
from server.world import Snapshot
from server.process import sortie_command
from server.recording import Recording, RecordingWriter, quantization_of
from sortie.errors import InvalidArgument, NotFound
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import geodetic_to_ecef, wrap_lon_deg

from conftest import REPO, shared_or_embedded

SCENARIO = REPO / "data" / "scenarios" / "alps.toml"
SAMPLE = shared_or_embedded("kavinsky_simple-acmi.txt.acmi", "acmi")  # a real DCS World recording
TICKS = 150
LONLAT_TOL_DEG = 0.5e-7 + 1e-10
ALT_TOL_M = 0.005 + 1e-9
ANGLE_TOL_DEG = 0.05 + 1e-9


# -- a reader following the ACMI 2.2 specification -------------------------------------------------

class SpecAcmi:
    """What an ACMI text holds: global properties, per-object series, removals, events."""

    T_FIELDS = {3: ("Longitude", "Latitude", "Altitude"), 5: ("Longitude", "Latitude", "Altitude", "U", "V"),
                6: ("Longitude", "Latitude", "Altitude", "Roll", "Pitch", "Yaw"),
                9: ("Longitude", "Latitude", "Altitude", "Roll", "Pitch", "Yaw", "U", "V", "Heading")}

    def __init__(self, text: str):
        self.globals: dict[str, str] = {}
        self.series: dict[str, dict[str, list]] = {}  # id -> field -> [(t, value)]
        self.removed: dict[str, float] = {}
        self.events: list[tuple[float, str]] = []
        self.times: list[float] = []
        t = 0.0
        lines = text.lstrip("\ufeff").split("\n")
        assert lines[0].strip() == "FileType=text/acmi/tacview" and lines[1].strip().startswith("FileVersion=2.")
        for line in self._logical(lines[2:]):
            if not line or line.startswith("//"):
                continue
            if line.startswith("#"):
                t = float(line[1:])
                self.times.append(t)
            elif line.startswith("-"):
                self.removed[line[1:]] = t
            else:
                self._properties(line, t)

    @staticmethod
    def _logical(lines):
        """Lines with their continuations (a line ending in a backslash goes on)."""
        held = ""
        for raw in lines:
            line = held + raw.rstrip("\r")
            if line.endswith("\\") and not line.endswith("\\\\"):
                held = line[:-1] + "\n"
                continue
            held = ""
            yield line.strip()

    def _properties(self, line: str, t: float) -> None:
        fields = [f.replace("\\,", ",") for f in _split_unescaped(line)]
        oid, props = fields[0], [f.split("=", 1) for f in fields[1:]]
        if oid == "0":
            for key, value in props:
                if key == "Event":
                    self.events.append((t, value))
                else:
                    self.globals[key] = value
            return
        obj = self.series.setdefault(oid, {})
        for key, value in props:
            if key == "T":
                parts = value.split("|")
                for name, v in zip(self.T_FIELDS[len(parts)], parts):
                    if v:
                        ref = {"Longitude": "ReferenceLongitude", "Latitude": "ReferenceLatitude"}.get(name)
                        offset = float(self.globals.get(ref, 0)) if ref else 0.0
                        obj.setdefault(name, []).append((t, offset + float(v)))
            else:
                obj.setdefault(key, []).append((t, value))

    def value(self, oid: str, field: str, t: float | None = None):
        """The field's last value at or before t (the last of all when t is None); None if none."""
        found = None
        for when, v in self.series.get(oid, {}).get(field, []):
            if t is not None and when > t:
                break
            found = v
        return found


def _split_unescaped(line: str) -> list[str]:
    out, start, i = [], 0, 0
    while i < len(line):
        if line[i] == "\\":
            i += 2
            continue
        if line[i] == ",":
            out.append(line[start:i])
            start = i + 1
        i += 1
    out.append(line[start:])
    return out


def parse_acmi(path) -> SpecAcmi:
    """The spec reader over a .acmi text or a .zip.acmi archive."""
    if zipfile.is_zipfile(path):
        with zipfile.ZipFile(path) as z:
            (name,) = z.namelist()
            return SpecAcmi(z.read(name).decode("utf-8-sig"))
    return SpecAcmi(open(path, encoding="utf-8-sig").read())


def load_pyacmi(path):
    """pyacmi's reading of a file (its chatter about unknown properties swallowed)."""
    from pyacmi import Acmi

    a = Acmi()
    with contextlib.redirect_stdout(io.StringIO()):
        a.load_acmi(str(path))
    return a


# -- recordings -------------------------------------------------------------------------------------

def record_alps(path, ticks: int = TICKS) -> None:
    """The alps world for ``ticks`` with a pilot's stick input, a client joining, a patrol
    vehicle removed at tick 60 (as the server records a sortie)."""
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, terrain_spec

    scenario = load_scenario(SCENARIO)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain))
    world.attach_recorder(rec)
    by_name = {e.name: e.id for e in world.entities.values()}
    try:
        for k in range(ticks):
            if k == 30:
                world.command(by_name["viper1"], "stick", {"pitch": 0.3, "roll": -0.4, "throttle": 1.0})
                world.emit("join", by_name["viper1"], client="tester, the", role="PILOT")
            if k == 60:
                world.remove(by_name["patrol1"], "destroyed by the test")
            world.tick()
    finally:
        rec.close()
        world.close()


def write_synthetic(path, tracks: dict, ticks: int, rate_hz: float = 30.0, events=(), terrain=None,
                    scenario: tuple[str, str] | None = None) -> None:
    """A recording of made-up entities: tracks {id: (EntityInfo or None for none,
    f(tick) -> (lat, lon, h_msl, roll, pitch, yaw) degrees / m, or None when absent)},
    one chunk per second; ``terrain``: the header's TerrainIdentity (default none);
    ``scenario``: the header's scenario (text, path; default none)."""
    header = rpb.RecordingHeader(format_version=1, sortie_version="test", exercise_name="synthetic, made up",
                                 start_time="2026-01-02T03:04:05.250Z", world_rate_hz=rate_hz,
                                 quantization=quantization_of(codec.DEFAULT_STEPS), geoid_undulation_m=10.0,
                                 terrain=terrain)
    if scenario is not None:
        header.scenario_toml, header.scenario_path = scenario
        header.scenario_sha256 = hashlib.sha256(scenario[0].encode("utf-8")).hexdigest()
    writer = RecordingWriter(path, header)
    per_chunk = int(rate_hz)
    for first in range(1, ticks + 1, per_chunk):
        c = types.SimpleNamespace(snapshots=[], inputs=[],
                                  events=[e for e in events if first <= max(e.tick, 1) < first + per_chunk],
                                  new_entities=[i for i, _ in tracks.values() if i] if first == 1 else [])
        for tick in range(first, min(first + per_chunk, ticks + 1)):
            poses = {i: f(tick) for i, (_, f) in tracks.items()}
            ids = np.array(sorted(i for i, p in poses.items() if p is not None), np.int64)
            states = np.zeros((ids.size, codec.FIELDS))
            for row, i in enumerate(ids):
                lat, lon, h, roll, pitch, yaw = poses[i]
                states[row, codec.POS] = geodetic_to_ecef(lat, lon, h + header.geoid_undulation_m)
                q_nb = euler_to_quaternion(*np.radians([roll, pitch, yaw]))
                states[row, codec.QUAT] = ned_to_ecef_quat(q_nb, lat, lon)
            z = np.zeros(ids.size)
            c.snapshots.append(Snapshot(tick / rate_hz, tick, ids, states[:, codec.POS], states[:, codec.VEL],
                                        states[:, codec.ACC], states[:, codec.QUAT], states[:, codec.RATE], z, z, z))
        writer.write_chunk(*encode_chunk(c, codec.DEFAULT_STEPS, rate_hz))
    writer.close()


def info(entity_id: int, name: str, kind: int, type_: str, coalition: str = "blue"):
    return pb.EntityInfo(entity_id=entity_id, name=name, kind=kind, type=type_, coalition=coalition)


@pytest.fixture(scope="module")
def alps(tmp_path_factory):
    """(recording path, plain export, zipped export) of the alps world."""
    d = tmp_path_factory.mktemp("acmi")
    rec = d / "alps.sortie"
    record_alps(rec)
    with Recording(rec) as r:
        acmi.export_acmi(r, d / "alps.acmi")
        acmi.export_acmi(r, d / "alps.zip.acmi")
    return rec, d / "alps.acmi", d / "alps.zip.acmi"


# -- the attitude conversion -------------------------------------------------------------------------

def _angle_error(a, b, turn=360.0):
    d = (np.asarray(a) - np.asarray(b)) % turn
    return np.minimum(d, turn - d)


def _euler_grid():
    lat = np.array([0.0, 47.3, -33.9, 89.0, -89.0, 60.0])
    lon = np.array([0.0, 9.5, 179.9, -179.9, -75.0, 180.0])
    yaw = np.array([0.0, 0.04, 359.96, 90.0, 180.0, 270.5])
    pitch = np.array([-89.9, -30.0, 0.0, 45.0, 89.9])
    roll = np.array([-179.9, -90.0, 0.0, 60.0, 179.9])
    g = np.meshgrid(np.arange(lat.size), yaw, pitch, roll, indexing="ij")
    return lat[g[0].ravel()], lon[g[0].ravel()], g[1].ravel(), g[2].ravel(), g[3].ravel()


def test_attitude_comes_back_from_ecef_quaternions_everywhere():
    lat, lon, yaw, pitch, roll = _euler_grid()
    q_eb = ned_to_ecef_quat(euler_to_quaternion(*np.radians([roll, pitch, yaw])), lat, lon)
    r, p, y = acmi.attitude_deg(q_eb, lat, lon)
    assert np.all((y >= 0.0) & (y < 360.0)) and np.all(np.abs(p) <= 90.0) and np.all(np.abs(r) <= 180.0)
    assert _angle_error(y, yaw).max() < 1e-6
    assert np.abs(p - pitch).max() < 1e-6
    assert _angle_error(r, roll).max() < 1e-6


def test_attitude_through_the_recorded_quantisation():
    lat, lon, yaw, pitch, roll = _euler_grid()
    keep = np.abs(pitch) <= 60.0
    lat, lon, yaw, pitch, roll = (a[keep] for a in (lat, lon, yaw, pitch, roll))
    q_eb = ned_to_ecef_quat(euler_to_quaternion(*np.radians([roll, pitch, yaw])), lat, lon)
    step = codec.DEFAULT_STEPS.quaternion
    r, p, y = acmi.attitude_deg(np.round(q_eb / step) * step, lat, lon)
    assert max(_angle_error(y, yaw).max(), np.abs(p - pitch).max(), _angle_error(r, roll).max()) < 0.02


def test_written_angles_wrap_at_a_whole_turn():
    pose = np.array([[9.0, 47.0, 0.0, -179.96, 0.0, 359.96], [9.0, 47.0, 0.0, 179.96, 0.0, 0.04]])
    v = acmi.pose_integers(pose, 9, 47)
    assert v[:, 5].tolist() == [0, 0] and v[:, 3].tolist() == [1800, 1800]


def test_pose_of_states_at_the_antimeridian_and_near_the_pole():
    lat = np.array([10.0, -10.0, 89.0, -89.0])
    lon = np.array([179.9, -179.9, 45.0, -135.0])
    states = np.zeros((4, codec.FIELDS))
    states[:, codec.POS] = geodetic_to_ecef(lat, lon, np.array([100.0, 200.0, 300.0, 400.0]) + 10.0)
    states[:, codec.QUAT] = ned_to_ecef_quat(euler_to_quaternion(0.1, 0.2, np.radians(350.0)), lat, lon)
    pose = acmi.pose_of_states(states, geoid_undulation_m=10.0)
    assert np.allclose(pose[:, 0], lon, atol=1e-9) and np.allclose(pose[:, 1], lat, atol=1e-9)
    assert np.allclose(pose[:, 2], [100.0, 200.0, 300.0, 400.0], atol=1e-6)
    assert np.allclose(pose[:, 3:], np.degrees([0.1, 0.2, np.radians(350.0)]), atol=1e-6)


# -- text ----------------------------------------------------------------------------------------------

def test_numbers_are_written_as_the_shortest_exact_decimals():
    rng = np.random.default_rng(7)
    values = np.concatenate([rng.integers(-10**10, 10**10, (200, 6)),
                             np.array([[0, 1, -1, 10**9, -5 * 10**7, 1800]]),
                             np.array([[3600000000, -3600000000, 123456, 7, -7, 1]])])
    ids = acmi.text_table([b"1", b"abc"])
    slots = np.arange(values.shape[0]) % 2
    changed = rng.random(values.shape) < 0.7
    data, ends = acmi.object_lines(slots, values, changed, ids)
    lines = data.decode().split("\n")[:-1]
    assert len(lines) == values.shape[0] and ends[-1] == len(data)
    for line, row, mask, s in zip(lines, values, changed, slots):
        oid, t = line.split(",T=")
        assert oid == ["1", "abc"][s]
        expected = [_decimal(v, d) if m else "" for v, d, m in zip(row, acmi.T_DECIMALS, mask)]
        assert t.split("|") == expected


def _decimal(v: int, decimals: int) -> str:
    sign = "-" if v < 0 else ""
    whole, frac = divmod(abs(int(v)), 10 ** decimals)
    text = f"{sign}{whole}.{frac:0{decimals}d}".rstrip("0").rstrip(".")
    return text


def test_types_coalitions_and_escaping():
    assert acmi.acmi_type(1, "f16") == "Air+FixedWing"
    assert acmi.acmi_type(2, "m1a2") == "Ground+Heavy+Armor+Vehicle+Tank"
    assert acmi.acmi_type(2, "m2a3") == "Ground+Heavy+Armor+Vehicle"
    assert acmi.acmi_type(2, "hmmwv") == "Ground+Vehicle"
    assert acmi.acmi_type(2, "light_tank") == "Ground+Heavy+Armor+Vehicle+Tank"
    assert acmi.acmi_type(2, "tanker_truck") == "Ground+Vehicle"  # words, not substrings
    assert acmi.acmi_type(3, "sam_site") == "Ground+AntiAircraft"
    assert acmi.acmi_type(3, "SA-6 SAM") == "Ground+AntiAircraft"
    assert acmi.acmi_type(3, "radar") == "Ground+Static+Building"
    props = acmi.object_properties(info(5, "a, b", 3, "depot", "neutral"))
    assert props == ",Type=Ground+Static+Building,Name=a\\, b,LongName=depot,Coalition=Neutrals,Color=Grey"


# -- the export, read back ---------------------------------------------------------------------------

def _check_against_recording(rec_path, acmi_path, rate_hz=None):
    """Every object's T components at every exported frame (pyacmi's reading, and the spec
    reader's at every 5th frame and the last), against the recording; returns both readings."""
    py, spec = load_pyacmi(acmi_path), parse_acmi(acmi_path)
    with Recording(rec_path) as r:
        start = acmi.iso_utc(r.header.start_time, "start_time")
        assert spec.globals["ReferenceTime"] == start
        assert py.reference_time == dt.datetime.fromisoformat(start.rstrip("Z"))
        ticks = np.arange(r.first_tick, r.last_tick + 1)
        exported = ticks[acmi.selected_ticks(ticks, r.rate_hz, rate_hz, r.first_tick, r.last_tick)]
        checked = 0
        for n, tick in enumerate(exported):
            t = round(float(tick * r.dt), acmi.time_decimals(r.dt))
            frame = r.frame(int(tick))
            pose = acmi.pose_of_states(frame.states, r.header.geoid_undulation_m)
            for i, want in zip(frame.ids, pose):
                oid = f"{i:x}"
                o = py.objects[oid]
                got = [o.longitude(t), o.latitude(t), o.altitude(t), o.roll(t), o.pitch(t), o.yaw(t)]
                if n % 5 == 0 or tick == exported[-1]:
                    fields = ("Longitude", "Latitude", "Altitude", "Roll", "Pitch", "Yaw")
                    assert [spec.value(oid, f, t) for f in fields] == pytest.approx(got, abs=1e-12)
                d = np.array(got[:2]) - want[:2]
                d[0] = (d[0] + 180.0) % 360.0 - 180.0  # reference + offset may run past +-180 (the antimeridian)
                assert np.abs(d).max() <= LONLAT_TOL_DEG, (tick, oid)
                assert abs(got[2] - want[2]) <= ALT_TOL_M, (tick, oid)
                assert _angle_error(got[3], want[3]) <= ANGLE_TOL_DEG and abs(got[4] - want[4]) <= ANGLE_TOL_DEG
                assert _angle_error(got[5], want[5]) <= ANGLE_TOL_DEG, (tick, oid)
                checked += 1
        assert checked > 0
    return py, spec


def test_round_trip_through_pyacmi_and_the_spec_reader(alps):
    rec, plain, _ = alps
    py, spec = _check_against_recording(rec, plain)
    with Recording(rec) as r:
        assert py.title == r.header.exercise_name and py.data_source == f"Sortie {r.header.sortie_version}"
        assert set(py.objects) == {f"{i:x}" for i in r.entities}
        for i, e in r.entities.items():
            o = py.objects[f"{i:x}"]
            assert (o.name, o.tags, o.get_value("LongName")) == (e.name, acmi.acmi_type(e.kind, e.type), e.type)
            assert o.coalition() == {"blue": "Blue", "red": "Red", "neutral": "Neutrals"}[e.coalition]
        patrol = next(i for i, e in r.entities.items() if e.name == "patrol1")
        assert set(spec.removed) == {f"{patrol:x}"} and py.objects[f"{patrol:x}"].removed_at == spec.removed[
            f"{patrol:x}"] == pytest.approx(61 / 30, abs=1e-3)
        viper = next(i for i, e in r.entities.items() if e.name == "viper1")
    # pyacmi keeps no events: the spec reader checks them.
    joined = f"Message|{viper:x}|tester, the joined viper1 as pilot"
    assert spec.events == [(pytest.approx(30 / 30, abs=1e-3), joined)]


def test_the_spec_reader_and_pyacmi_read_a_real_tacview_file():
    py, spec = load_pyacmi(SAMPLE), parse_acmi(SAMPLE)
    assert spec.globals["ReferenceTime"] == "1990-05-01T06:00:00Z" and py.reference_longitude == 33.0
    assert "Tacan 74 X, ICLS" in spec.globals["Briefing"] and "\n" in spec.globals["Briefing"]
    assert set(py.objects) == set(spec.series) and len(py.timeframes) == len(spec.times)
    d01 = py.objects["d01"]  # the player's F-14B: its first line has 9 T components
    assert (d01.longitude(0.01), d01.latitude(0.01), d01.altitude(0.01)) == (33 + 3.8608779, 39 + 6.001753, 4569.69)
    assert (d01.yaw(0.01), d01.heading(0.01), d01.name) == (121.3, 118.6, "F-14B")
    for oid, fields in spec.series.items():
        for field in ("Longitude", "Latitude", "Altitude", "Roll", "Pitch", "Yaw", "Heading", "Name"):
            if field in fields:
                for t in (spec.times[len(spec.times) // 3], spec.times[-1]):
                    if spec.value(oid, field, t) is not None:  # pyacmi answers a later value before the first
                        assert py.objects[oid].get_value(field, t) == spec.value(oid, field, t), (oid, field, t)
    assert [e for _, e in spec.events] == ["TestEvent|hahaha:test|hohoho:test|itsAValue"] * 2


def test_zip_holds_the_same_text(alps):
    _, plain, zipped = alps
    with zipfile.ZipFile(zipped) as z:
        assert z.testzip() is None
        (name,) = z.namelist()
        assert name == "alps.txt.acmi"
        assert z.read(name) == plain.read_bytes()
    assert zipped.stat().st_size < plain.stat().st_size / 3
    assert plain.read_bytes().startswith(b"\xef\xbb\xbfFileType=text/acmi/tacview\nFileVersion=2.2\n")


def test_statics_are_written_once(alps):
    rec, plain, _ = alps
    text = plain.read_text(encoding="utf-8-sig")
    with Recording(rec) as r:
        for i, e in r.entities.items():
            if e.kind == acmi.STATIC:
                assert sum(line.startswith(f"{i:x},T=") for line in text.split("\n")) == 1, e.name


def test_only_changes_are_written_and_absences_remove(tmp_path):
    """A paused object writes nothing; one that leaves is removed and comes back as new;
    one present only between exported ticks is not written; antimeridian and 89 degrees."""
    def mover(tick):  # crosses the antimeridian at tick 10
        return 10.0, float(wrap_lon_deg(179.99 + 1e-3 * tick)), 500.0, 0.0, 2.0, 90.0

    def paused(tick):  # climbs, stands still from tick 10 to 40, climbs again
        return 89.0, -179.9, 1000.0 + min(tick, 10) + max(tick - 40, 0), 5.0, -3.0, 359.99

    def blinker(tick):
        return None if 20 <= tick < 30 else (-45.0, 170.0, 10.0, 0.0, 0.0, 180.0)

    def flash(tick):
        return (-45.0, 171.0, 10.0, 0.0, 0.0, 0.0) if tick == 44 else None

    tracks = {1: (info(1, "mover", 1, "f16"), mover),
              2: (info(2, "paused", 2, "hmmwv", "red"), paused),
              3: (info(3, "blinker", 3, "sam_site", "red"), blinker),
              4: (info(4, "flash", 2, "m1a2"), flash),
              5: (None, lambda tick: (0.0, 0.0, 0.0, 0.0, 0.0, 0.0))}  # not described by the recording
    crash = rpb.EventRecord(tick=50, event=pb.WorldEvent(time_s=50 / 30, kind="crash", entity_id=1,
                                                         detail_json='{"reason": "terrain"}'))
    rec = tmp_path / "synthetic.sortie"
    write_synthetic(rec, tracks, ticks=60, events=[crash])
    out = tmp_path / "synthetic.acmi"
    with Recording(rec) as r:
        stats = acmi.export_acmi(r, out, rate_hz=10.0)
    _check_against_recording(rec, out, rate_hz=10.0)
    spec = parse_acmi(out)
    assert stats.ticks == 21 and stats.objects == 4 and "4" not in spec.series  # flash: between frames
    assert (spec.value("5", "Type"), spec.value("5", "Name")) == ("Misc+Minor", "entity 5")
    paused_times = [t for series in spec.series["2"].values() for t, _ in series]
    assert not [t for t in paused_times if 13 / 30 < t < 41 / 30]  # ticks 15 to 39: nothing written
    assert min(abs(t - 12 / 30) for t in paused_times) < 1e-3 and min(abs(t - 42 / 30) for t in paused_times) < 1e-3
    assert spec.series["3"]["Name"] == [(pytest.approx(1 / 30, abs=1e-3), "blinker"),
                                        (pytest.approx(30 / 30, abs=1e-3), "blinker")]
    assert spec.removed == {"3": pytest.approx(21 / 30, abs=1e-3)}  # blinker's removal (it came back)
    # The crash at tick 50, between exported ticks 48 and 51, in a frame at its own time.
    assert spec.events == [(pytest.approx(50 / 30, abs=1e-3), "Destroyed|1|mover crashed: terrain")]
    assert spec.globals["ReferenceTime"] == "2026-01-02T03:04:05.250Z"
    assert spec.globals["Title"] == "synthetic, made up"
    lon = np.array([v for _, v in spec.series["1"]["Longitude"]])  # across the antimeridian without a jump:
    assert lon.min() < 180.0 < lon.max() and 0.0 < np.diff(lon).min() and np.diff(lon).max() < 0.01  # past 180


# -- arguments and the command line -------------------------------------------------------------------

@pytest.mark.parametrize("rate", [0, -1.0, float("nan"), float("inf"), "fast"])
def test_a_bad_rate_is_an_invalid_argument(rate):
    with pytest.raises(InvalidArgument) as err:
        acmi.check_rate(rate)
    assert err.value.field == "rate"


def test_output_name_chooses_the_form(alps, tmp_path):
    assert acmi.output_kind("a/b.ACMI") == "plain" and acmi.output_kind("x.zip.acmi") == "zip"
    with pytest.raises(InvalidArgument, match="output"):
        acmi.output_kind("x.zip")
    with Recording(alps[0]) as r, pytest.raises(NotFound, match="nowhere"):
        acmi.export_acmi(r, tmp_path / "nowhere" / "x.acmi")


def test_command_line_export_and_a_missing_file(alps, tmp_path):
    rec, plain, _ = alps
    out = tmp_path / "cli.acmi"
    done = subprocess.run([*sortie_command(), "export", "acmi", str(rec), "-o", str(out)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == plain.read_bytes()
    missing = tmp_path / "nowhere.sortie"
    done = subprocess.run([*sortie_command(), "export", "acmi", str(missing), "-o", str(out)], capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 2 and str(missing) in done.stderr and "does not exist" in done.stderr


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
