"""The area-of-interest acceptance probe's replay finding, round 33 (/tmp/probes33/aoi): a replay's
observer stood at mean sea level, not on the ground as live (the proto: "the centre is on the ground
there"), so a replay showed another picture: over the Alps tile (433.8 m there, N = 48 m) a vehicle
at 20 m/s entered a 500 m observer's view 13 s later and left it 11 s earlier than live.

Real parts: a `SimulationServer` over the embedded SRTM tile records a HMMWV driving past an observer
(radius 300 m, centre 150 m off its track: from mean sea level, some 430 m below, it is never in view),
the observer watching over gRPC on loopback; the recording is served by `ReplayServer` (ports
53550-53551) and the same observer watches it; `sortie replay` is run as a command for its options.

Bounds: the replay's enter and leave times are live's within one publish interval of the replay
(speed / network rate of world time, doubled for a clock thread woken late on a shared machine),
live's coming first; where the recorded terrain cannot be found, the observer stands at mean sea
level plus the geoid undulation, exactly.
"""

from __future__ import annotations

import math
import subprocess
import sys
import threading
import time

import grpc
import numpy as np
import pytest

from conftest import EMBEDDED_DEM

LIVE_PORT, REPLAY_PORT = 53550, 53551
NETWORK_RATE_HZ = 30.0
LIVE_TIME_SCALE = 20.0
REPLAY_SPEED = 8.0
SPEED_MPS = 20.0
HEADING_DEG = 27.1
START = (47.24, 9.522)  # the probe's runner: on the valley floor, east of the Rhine
RADIUS_M = 300.0
OFFSET_M = 150.0  # the observer's centre, right of the runner's track
BEFORE_M = 60.0  # the runner starts this far before the observer's circle
GEOID_UNDULATION_M = 48.0
DURATION_S = 32.0  # the runner leaves the circle at about 29 s


def _moved(lat: float, lon: float, north_m: float, east_m: float) -> tuple[float, float]:
    """(lat, lon) metres away on the WGS84 ellipsoid's local radii (ample for a few hundred metres)."""
    from terrain.geodesy import WGS84_A_M, WGS84_E2

    s = math.sin(math.radians(lat))
    n = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * s * s)
    m = n * (1.0 - WGS84_E2) / (1.0 - WGS84_E2 * s * s)
    return lat + math.degrees(north_m / m), lon + math.degrees(east_m / (n * math.cos(math.radians(lat))))


def _observer() -> tuple[float, float, float]:
    """The observer's (lat, lon, radius): OFFSET_M right of the track, BEFORE_M + half the chord along it."""
    along = BEFORE_M + math.sqrt(RADIUS_M ** 2 - OFFSET_M ** 2)
    h, r = math.radians(HEADING_DEG), math.radians(HEADING_DEG + 90.0)
    north_m, east_m = along * math.cos(h) + OFFSET_M * math.cos(r), along * math.sin(h) + OFFSET_M * math.sin(r)
    lat, lon = _moved(*START, north_m, east_m)
    return lat, lon, RADIUS_M


SCENARIO = f"""[exercise]
name = "replay observer on the ground"
start_time = 2026-06-15T07:00:00Z
world_rate_hz = 30
network_rate_hz = {NETWORK_RATE_HZ:g}
clock = "paused"
duration_s = {DURATION_S}
[terrain]
dem = ["{EMBEDDED_DEM / 'N47E009.hgt'}"]
geoid_undulation_m = {GEOID_UNDULATION_M}
[[agents]]
name = "runner"
kind = "ground"
type = "hmmwv"
coalition = "blue"
lat_deg = {START[0]}
lon_deg = {START[1]}
heading_deg = {HEADING_DEG}
speed_mps = {SPEED_MPS}
"""


class _Watcher:
    """An observer's raw Watch stream on a thread: (world time, entered names, left ids) per update."""

    def __init__(self, address: str):
        from client.sim_client import SimClient
        from sortie.v1 import simulation_pb2 as pb
        from sortie.v1 import simulation_pb2_grpc as pbg

        self.client = SimClient(address)
        self.client.__enter__()
        self.client.wait_ready(10.0)
        self.client.join("obs", "observer", observer=_observer())
        self.updates: list = []
        self.first = threading.Event()

        def read():
            try:
                for u in pbg.SimulationServiceStub(self.client.channel).Watch(
                        pb.WatchRequest(session_token=self.client.token)):
                    self.updates.append((u.time_s, [e.name for e in u.entered], list(u.left)))
                    self.first.set()
            except grpc.RpcError:
                pass

        self.thread = threading.Thread(target=read, daemon=True)
        self.thread.start()
        assert self.first.wait(10.0), "no snapshot"

    def crossings(self) -> list:
        """[("enter" | "leave", world time)] of the runner (the only entity), in order."""
        out = []
        for t, entered, left in self.updates:
            out += [("enter", t) for name in entered if name == "runner"] + [("leave", t) for _ in left]
        return out

    def close(self) -> None:
        self.client.__exit__(None, None, None)
        self.thread.join(5.0)


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    """(recording path, the live observer's crossings): the exercise run live at x20 and recorded."""
    from server.recorder import Recorder, recording_header
    from server.scenario import load_scenario
    from server.sim_server import SimulationServer, build_world, open_terrain, server_config, terrain_spec

    d = tmp_path_factory.mktemp("replay_ground")
    scenario_path, path = d / "runner.toml", d / "runner.sortie"
    scenario_path.write_text(SCENARIO)
    scenario = load_scenario(scenario_path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    recorder = Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain),
                        1.0)
    srv = SimulationServer(world, server_config(scenario, desc), f"127.0.0.1:{LIVE_PORT}", recorder=recorder)
    srv.start()
    try:
        watcher = _Watcher(srv.address)
        srv.set_clock("fast", LIVE_TIME_SCALE)
        assert srv.finished.wait(60.0), "the live exercise did not end"
        time.sleep(0.3)  # the last updates reach the reader
        watcher.close()
    finally:
        srv.stop(0.5)
        world.close()
    crossings = watcher.crossings()
    assert [k for k, _ in crossings] == ["enter", "leave"], crossings  # the geometry this test is built on
    return path, crossings


def test_a_replay_observer_stands_on_the_recorded_terrain_and_sees_what_live_saw(live):
    """The probe's case, 150 m off the track of a 300 m observer: live sees the runner enter at
    ~3 s and leave at ~29 s. Old: the replay's observer stood at mean sea level, 400 m below, and
    never saw it. Now its enter and leave times are live's, within one publish interval."""
    from server.replay import ReplayServer

    path, crossings = live
    replay = ReplayServer(path, f"127.0.0.1:{REPLAY_PORT}", speed=REPLAY_SPEED, playing=False)
    replay.start()
    try:
        watcher = _Watcher(replay.address)
        watcher.client.replay(play=True)
        deadline = time.monotonic() + 60.0
        while watcher.client.replay_status().playing and time.monotonic() < deadline:
            time.sleep(0.1)
        time.sleep(0.3)
        watcher.close()
    finally:
        replay.stop(0.5)
    seen = watcher.crossings()
    interval_s = 2.0 * REPLAY_SPEED / NETWORK_RATE_HZ
    assert [k for k, _ in seen] == [k for k, _ in crossings], (seen, crossings)
    for (kind, t_live), (_, t_replay) in zip(crossings, seen):
        assert 0.0 <= t_replay - t_live <= interval_s + 1e-9, (kind, t_live, t_replay)


def _short_recording(d, dem) -> str:
    """A 1 s recording (in process) of the scenario over the DEM file ``dem``."""
    from server.recorder import Recorder, recording_header
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, terrain_spec

    scenario_path, path = d / "short.toml", d / "short.sortie"
    scenario_path.write_text(SCENARIO.replace(str(EMBEDDED_DEM / "N47E009.hgt"), str(dem)))
    scenario = load_scenario(scenario_path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    rec = Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    try:
        for _ in range(30):
            world.tick()
    finally:
        rec.close()
        world.close()
    return str(path)


def test_a_replay_observer_stands_where_a_live_one_does_or_at_sea_level_without_the_terrain(tmp_path, caplog):
    """The observer's centre in a replay is the live server's (Sessions._ground_point over the
    scenario's terrain), to the bit; where the recorded DEM is gone (a recording moved to another
    machine) the replay still serves, its observer at mean sea level plus the geoid undulation,
    with one warning that names the way out; --dem names the terrain instead; a given DEM file
    that is not there is an error (NotFound naming it)."""
    import shutil

    from server.replay import ReplayServer
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain
    from server.sim_service import Sessions
    from sortie.errors import NotFound
    from sortie.v1 import simulation_pb2 as pb
    from terrain.geodesy import geodetic_to_ecef

    dem = tmp_path / "N47E009.hgt"
    shutil.copy(EMBEDDED_DEM / "N47E009.hgt", dem)
    path = _short_recording(tmp_path, dem)
    lat, lon, radius = _observer()
    scenario = load_scenario(tmp_path / "short.toml")
    terrain, _, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    try:
        live_centre = Sessions(world, lambda *a: None)._ground_point(lat, lon)
    finally:
        world.close()
    sea_centre = np.asarray(geodetic_to_ecef(lat, lon, GEOID_UNDULATION_M), float).reshape(3)
    assert np.linalg.norm(live_centre - sea_centre) > 400.0

    def centre(**options) -> np.ndarray:
        replay = ReplayServer(path, "127.0.0.1:0", playing=False, **options)
        replay.start()
        try:
            return replay.sessions.join("obs", pb.ROLE_OBSERVER, "", (lat, lon, radius)).observer_ecef
        finally:
            replay.stop(0.0)

    assert np.array_equal(centre(), live_centre)
    dem.unlink()
    with caplog.at_level("WARNING", logger="server.replay"):
        assert np.array_equal(centre(), sea_centre)
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING" and "sea level" in r.getMessage()]
    assert len(warnings) == 1 and "--dem" in warnings[0], warnings
    assert np.array_equal(centre(dem=[EMBEDDED_DEM / "N47E009.hgt"]), live_centre)
    with pytest.raises(NotFound, match="N47E009.hgt"):
        ReplayServer(path, "127.0.0.1:0", dem=[dem])


def test_sortie_replay_takes_dem_and_terrain_options(tmp_path):
    """`sortie replay` takes --dem and --terrain as `sortie resim` does (one or the other): a DEM
    file that is not there ends it at once with exit 2 and a line naming the file."""
    dem = tmp_path / "N47E009.hgt"
    dem.write_bytes((EMBEDDED_DEM / "N47E009.hgt").read_bytes())
    path = _short_recording(tmp_path, dem)
    sortie = [sys.executable, "-m", "sortie.cli"]
    out = subprocess.run([*sortie, "replay", path, "--port", "0", "--dem", str(tmp_path / "gone.hgt")],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "gone.hgt' does not exist" in out.stderr, (out.returncode, out.stderr)
    out = subprocess.run([*sortie, "replay", path, "--port", "0", "--dem", str(dem), "--terrain", "127.0.0.1:1"],
                         capture_output=True, text=True, timeout=60)
    assert out.returncode == 2 and "not allowed with" in out.stderr, (out.returncode, out.stderr)
