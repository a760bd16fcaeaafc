"""Simulation server findings of the acceptance probe (session 30):

1. a very low (legal) network_rate_hz left joiners without a picture: a Watch's first update
   (its snapshot) waited for the next network tick (1e-300 Hz: never; 0.1 Hz: 6.4 world s),
   and heartbeats (5 s) could not be met. What cannot wait (a Watch's snapshot, an entity
   come or gone, a change of the clock's rate, a heartbeat due) is now published at the next
   world tick; at the usual rates the network ticks are what they were;
2. a static agent whose type is also an aircraft or vehicle name ("f16") took the aircraft's
   (the vehicle's) network parameters on the server instead of its own kind's under the type
   table: the server's parameters are keyed (kind, type), exactly as the scenario resolves them;
3. a refused autopilot speed showed the limit to 3 significant digits ("within [0, 18.8]
   ... (got 18.8)" for an m1a2's 18.77568 m/s): a limit is shown so that it never reads as
   admitting the refused value;
4. a start time with RFC 3339's lower-case "t" / "z" (2026-03-01T00:00:00z) was refused in
   YAML (unquoted or quoted) and as a TOML string, though TOML's own date-time took it.

Real parts: the Alps SRTM tile, real worlds (JSBSim where an aircraft is needed, the ground
vehicle model), the gRPC service on loopback with the real client library, scenarios parsed
from real TOML and YAML text.
"""

from __future__ import annotations

import dataclasses
import math
import re
import threading
import time
from datetime import datetime, timezone

import numpy as np
import pytest

from client.sim_client import SimClient
from conftest import REPO
from server.dead_reckoning import ALGORITHM_NAMES, Thresholds
from server.sim_server import DEFAULT_PARAMS, ServerConfig, SimulationServer, TypeParams
from server.world import World
from server_helpers import PublishTap
from sortie.errors import InvalidArgument

DEM = REPO / "data" / "dem" / "N47E009.hgt"
SAM = (47.35, 9.45)  # the sites and vehicles stand within 10 km of it
WATCH_RADIUS_M = 30_000.0


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _ground_world(alps) -> World:
    """Two statics and two ground vehicles (one on a route): no aircraft, quick to build."""
    w = World(alps)
    w.spawn_static("sam1", "sam_site", *SAM)
    w.spawn_static("radar1", "radar", 47.36, 9.47)
    w.spawn_ground(["truck1"], "hmmwv", [47.30], [9.50], 45.0, route=[(47.30, 9.50), (47.31, 9.52)], cruise_mps=10.0)
    w.spawn_ground(["tank1"], "m1a2", [47.32], [9.48], 0.0, controllable=True)
    return w


def _params(heartbeat_s: float) -> dict:
    """ServerConfig.params with every kind's heartbeat ``heartbeat_s``."""
    return {k: TypeParams(p.aoi_radius_m, dataclasses.replace(p.thresholds, heartbeat_s=heartbeat_s))
            for k, p in DEFAULT_PARAMS.items()}


def _serve(world, **config) -> SimulationServer:
    srv = SimulationServer(world, ServerConfig(**config))
    srv.tap = PublishTap(srv.publisher)
    srv.start()
    return srv


def _wait_world(srv, t_s: float, timeout_s: float = 30.0) -> None:
    deadline = time.monotonic() + timeout_s
    while srv.world.time_s < t_s:
        assert time.monotonic() < deadline, f"world time {srv.world.time_s} s short of {t_s} s"
        time.sleep(0.02)


class _Log:
    """Every update a watcher receives: (update time, {entity id: state time}), and names."""

    def __init__(self):
        self.updates: list = []
        self.names: dict = {}
        self.lock = threading.Lock()

    def __call__(self, picture, u) -> None:
        with self.lock:
            states = {s.entity_id: s.time_s for s in u.states}
            for info in u.entered:
                self.names[info.entity_id] = info.name
                states[info.entity_id] = info.state.time_s
            self.updates.append((u.time_s, states))

    def state_times(self, entity_id: int) -> list:
        with self.lock:
            return [s[entity_id] for _, s in self.updates if entity_id in s]


# -- 1. a low network rate: snapshot, entities coming and going, clock rate, heartbeats -------------

def test_a_joiner_gets_its_snapshot_at_the_next_tick_whatever_the_network_rate(alps):
    """1e-300 Hz (the probe's case): the network tick after the first is never. Bound: the
    snapshot's world time within 1 s (real time: a tick and the RPCs' latency) of the Watch
    call; it never came before."""
    srv = _serve(_ground_world(alps), network_rate_hz=1e-300, clock="realtime", params=_params(3600.0))
    try:
        _wait_world(srv, 1.0)  # the first (and only) regular network tick is long past
        with SimClient(srv.address) as obs:
            obs.join("obs", "observer", observer=(*SAM, WATCH_RADIUS_M))
            t_watch = srv.world.time_s
            pic = obs.watch()
            assert pic.snapshot_received.wait(5.0), "no snapshot within 5 wall s"
            assert pic.time_s - t_watch <= 1.0, (pic.time_s, t_watch)
            assert {i.name for i in pic.infos.values()} == {"sam1", "radar1", "truck1", "tank1"}
    finally:
        srv.stop(0.5)


def test_entities_coming_and_going_and_the_clock_rate_reach_watchers_at_the_next_tick(alps):
    """0.001 Hz, heartbeats of an hour: a spawned entity enters, a removed one leaves and a
    resumed clock's rate arrives within 2 wall s (each waited for the next network tick,
    1000 world s, before)."""
    world = _ground_world(alps)
    srv = _serve(world, network_rate_hz=0.001, clock="fast", time_scale=2.0, params=_params(3600.0))
    try:
        with SimClient(srv.address) as obs:
            obs.join("obs", "observer", observer=(*SAM, WATCH_RADIUS_M))
            pic = obs.watch()
            assert pic.snapshot_received.wait(5.0)
            late = world.spawn_static("late1", "radar", 47.34, 9.44)
            assert pic.wait_for(lambda p: late.id in p.infos, 2.0), "the new entity never entered"
            world.remove(late.id)
            assert pic.wait_for(lambda p: late.id not in p.infos, 2.0), "the removed entity never left"
            srv.set_clock("paused")
            assert pic.wait_for(lambda p: p.time_scale == 0.0, 2.0)
            srv.set_clock("fast")
            assert pic.wait_for(lambda p: p.time_scale > 0.0, 2.0), "the resumed clock's rate never came"
    finally:
        srv.stop(0.5)


@pytest.mark.parametrize("network_rate_hz", [0.01, 0.1])
def test_heartbeats_are_met_when_the_network_period_is_longer(alps, network_rate_hz):
    """Heartbeat 1 s, network period 10 s and 100 s: every entity's consecutive states are at
    most a heartbeat and one world tick apart (they were a network period apart), and the
    clock publishes about once a heartbeat (at most twice: a change of the achieved clock rate
    publishes too), not every tick."""
    heartbeat_s, run_s = 1.0, 6.0
    world = _ground_world(alps)
    srv = _serve(world, network_rate_hz=network_rate_hz, clock="fast", time_scale=5.0, params=_params(heartbeat_s))
    log = _Log()
    try:
        with SimClient(srv.address) as obs:
            obs.join("obs", "observer", observer=(*SAM, WATCH_RADIUS_M))
            pic = obs.watch(listener=log)
            assert pic.snapshot_received.wait(5.0)
            t_start = srv.world.time_s
            _wait_world(srv, t_start + run_s)
            published = [s.time_s for s in srv.tap.snaps if t_start <= s.time_s <= t_start + run_s]
    finally:
        srv.stop(0.5)
    assert set(log.names.values()) == {"sam1", "radar1", "truck1", "tank1"}
    for entity_id, name in log.names.items():
        times = np.array(log.state_times(entity_id))
        assert times.size >= run_s / heartbeat_s - 1, (name, times)
        gaps = np.diff(times)
        assert gaps.max() <= heartbeat_s + world.dt + 1e-6, (name, gaps.max())
    assert len(published) <= 2 * run_s / heartbeat_s + 4, published


def test_the_usual_network_rate_publishes_on_its_schedule_alone(alps):
    """20 Hz network, 30 Hz world, 5 s heartbeats, a watcher with its snapshot: the publishes
    fall on the network schedule (at most 2 of about 60 off it, where a loaded machine changes
    the achieved clock rate), so a tick costs what it did; publishing every tick would put 30
    off it."""
    world = _ground_world(alps)
    srv = _serve(world, network_rate_hz=20.0, clock="realtime")
    try:
        with SimClient(srv.address) as obs:
            obs.join("obs", "observer", observer=(*SAM, WATCH_RADIUS_M))
            pic = obs.watch()
            assert pic.snapshot_received.wait(5.0)
            assert pic.wait_for(lambda p: p.updates >= 2, 5.0)
            first = srv.world.tick_count + 1
            _wait_world(srv, srv.world.time_s + 3.0)
            ticks = [s.tick for s in srv.tap.snaps if s.tick >= first]
    finally:
        srv.stop(0.5)
    schedule, next_net = set(), 0.0
    for tick in range(1, max(ticks) + 1):  # the clock thread's network ticks
        if tick * world.dt + 1e-9 >= next_net:
            schedule.add(tick)
            next_net += 1.0 / 20.0
    assert len(ticks) > 40 and len(set(ticks) - schedule) <= 2, sorted(set(ticks) - schedule)


# -- 2. a type table applies under the agent's own kind --------------------------------------------

SCENARIO = f"""
[exercise]
name = "kinds and types"
start_time = 2026-03-01T00:00:00Z
clock = "paused"

[terrain]
dem = ["{DEM}"]

[agent_types.static]
heartbeat_s = 60.0
[agent_types.aircraft]
heartbeat_s = 2.0
[agent_types.ground]
aoi_radius_m = 7000.0
[agent_types.f16]
aoi_radius_m = 120000.0
[agent_types.hmmwv]
dr_position_m = 2.5

[[agents]]
name = "viper1"
kind = "aircraft"
type = "f16"
coalition = "blue"
lat_deg = 47.30
lon_deg = 9.30
alt_m = 3500.0
speed_mps = 200.0

[[agents]]
name = "decoy"
kind = "static"
type = "f16"
coalition = "red"
lat_deg = 47.35
lon_deg = 9.45

[[agents]]
name = "tent"
kind = "static"
type = "hmmwv"
coalition = "red"
lat_deg = 47.36
lon_deg = 9.46

[[agents]]
name = "truck1"
kind = "ground"
type = "hmmwv"
coalition = "blue"
lat_deg = 47.30
lon_deg = 9.50

[[agents]]
name = "sam1"
kind = "static"
type = "sam_site"
coalition = "red"
lat_deg = 47.37
lon_deg = 9.44
"""


def test_a_static_agent_typed_like_an_aircraft_or_vehicle_takes_its_own_kinds_parameters(tmp_path):
    """The oracle is the scenario's own resolution (kind default < [agent_types.<kind>] <
    [agent_types.<type>], the agent's own kind): the server applies exactly that to every
    entity. The static "f16" decoy took the aircraft's 2 s RVW, the static "hmmwv" tent the
    ground vehicles' RVW and 7 km before."""
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, server_config

    path = tmp_path / "kinds.toml"
    path.write_text(SCENARIO)
    scenario = load_scenario(path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    srv = SimulationServer(world, server_config(scenario, desc))
    srv.start()
    code = {name: c for c, name in ALGORITHM_NAMES.items()}
    try:
        assert len(world.entities) == 5
        for e in world.entities.values():
            want = scenario.agent_type(scenario.agent(e.name))
            got = srv.params_of(e.id)
            assert got.aoi_radius_m == want.aoi_radius_m, e.name
            assert got.thresholds == Thresholds(want.dr_position_m, math.radians(want.dr_orientation_deg),
                                                want.heartbeat_s, code[want.dr_algorithm]), e.name
        by_name = {e.name: srv.params_of(e.id) for e in world.entities.values()}
        assert by_name["decoy"].thresholds.heartbeat_s == 60.0 and by_name["decoy"].aoi_radius_m == 120_000.0
        assert algorithm(by_name["decoy"]) == algorithm(by_name["tent"]) == "STATIC"
        assert by_name["viper1"].thresholds.heartbeat_s == 2.0 and by_name["viper1"].aoi_radius_m == 120_000.0
        assert by_name["truck1"].thresholds.position_m == by_name["tent"].thresholds.position_m == 2.5
        assert by_name["truck1"].aoi_radius_m == 7000.0 and by_name["tent"].aoi_radius_m == 50_000.0
    finally:
        srv.stop(0.5)
        world.close()


def algorithm(params: TypeParams) -> str:
    return ALGORITHM_NAMES[params.thresholds.algorithm]


# -- 3. a refusal's limit never reads as admitting the refused value ------------------------------

def test_a_refused_ground_autopilot_speed_shows_a_limit_below_it(alps):
    """m1a2 top speed 18.77568 m/s: 18.8 was refused as "within [0, 18.8]"; at 6 digits 18.7757
    would read "within [0, 18.7757]". Bound: the limit shown reads back below the refused
    value and within 1e-6 of the true limit."""
    from fdm.vehicle_types import VEHICLE_TYPES

    world = _ground_world(alps)
    try:
        tank = next(e.id for e in world.entities.values() if e.name == "tank1")
        top = VEHICLE_TYPES["m1a2"].max_speed_mps
        for speed in (18.8, 18.7757, float(np.nextafter(top, math.inf)), top + 1e-3, 1000.0):
            with pytest.raises(InvalidArgument) as exc:
                world.command(tank, "autopilot", {"speed_mps": speed})
            shown = float(re.search(r"must be within \[0, ([^\]]+)\] m/s for tank1 \(m1a2", str(exc.value)).group(1))
            assert top - 1e-6 * top <= shown < speed, (speed, str(exc.value))
        world.command(tank, "autopilot", {"speed_mps": top})  # the limit itself is allowed
    finally:
        world.close()


@pytest.mark.parametrize("bound, refused, shown", [
    (18.77568, 18.8, "18.7757"),  # 6 digits separate them
    (18.77568, 18.7757, "18.77568"),  # 6 digits would round onto the refused value
    (18.77568, 18.775681, "18.77568"),
    (-8.333333333333334, -8.4, "-8.33333"),  # a lower limit
    (-8.333336, -8.333338, "-8.333336"),  # 6 digits (-8.33334) would put it below the refused value
    (30.0, 30.0004, "30"),
])
def test_bound_text(bound, refused, shown):
    from sortie.errors import bound_text

    assert bound_text(bound, refused) == shown


# -- 4. RFC 3339's lower-case "t" and "z" ---------------------------------------------------------

UTC_START = datetime(2026, 3, 1, tzinfo=timezone.utc)


def _parse(text: str, suffix: str):
    from server.scenario import parse_scenario, scenario_data

    return parse_scenario(scenario_data(text, "x" + suffix), REPO)


def _yaml(start: str, name: str = "x") -> str:
    return f"exercise:\n  name: {name}\n  start_time: {start}\nterrain:\n  dem: ['{DEM}']\n"


def _toml(start: str, name: str = '"x"') -> str:
    return f'[exercise]\nname = {name}\nstart_time = {start}\n[terrain]\ndem = ["{DEM}"]\n'


@pytest.mark.parametrize("start", ["2026-03-01T00:00:00z", "2026-03-01t00:00:00z", "2026-03-01t00:00:00Z",
                                   "'2026-03-01T00:00:00z'", "'2026-03-01t00:00:00z'", "2026-03-01T01:00:00+01:00"])
def test_a_yaml_start_time_takes_lower_case_t_and_z(start):
    assert _parse(_yaml(start), ".yaml").exercise.start_time == UTC_START


@pytest.mark.parametrize("start", ["2026-03-01t00:00:00z", '"2026-03-01t00:00:00z"', '"2026-03-01T00:00:00z"',
                                   '"2026-03-01t00:00:00Z"'])
def test_a_toml_start_time_takes_lower_case_t_and_z_as_a_string_too(start):
    assert _parse(_toml(start), ".toml").exercise.start_time == UTC_START


def test_a_lower_case_z_date_time_is_a_date_time_in_yaml_as_in_toml():
    """Anywhere in the file: a name written as a date-time is refused in both formats alike."""
    from server.scenario import ScenarioError

    for text, suffix in ((_yaml("2026-03-01T00:00:00Z", "2026-03-01T00:00:00z"), ".yaml"),
                         (_toml("2026-03-01T00:00:00Z", "2026-03-01T00:00:00z"), ".toml")):
        with pytest.raises(ScenarioError, match=r"exercise\.name: must be a string \(got '2026-03-01T00:00:00\+00:00'"):
            _parse(text, suffix)


@pytest.mark.parametrize("start, message", [
    ("'2026-03-01T00:00:00'", "needs a UTC offset"),
    ("'2026-03-01x00:00:00z'", "must be an ISO 8601 date-time"),
    ("'now'", "must be an ISO 8601 date-time"),
    ("'2026-03-01T00:00:00zz'", "must be an ISO 8601 date-time"),
])
def test_other_start_times_are_still_refused(start, message):
    from server.scenario import ScenarioError

    with pytest.raises(ScenarioError, match=rf"exercise\.start_time: {message}"):
        _parse(_yaml(start), ".yaml")


def test_a_refused_drive_speed_shows_a_limit_below_it(alps):
    """The same for a driver's command (fdm.ground.check_controls): 18.8 was refused as
    "within [-8.33, 18.8]"."""
    from fdm.vehicle_types import VEHICLE_TYPES

    world = _ground_world(alps)
    try:
        tank = next(e.id for e in world.entities.values() if e.name == "tank1")
        top = VEHICLE_TYPES["m1a2"].max_speed_mps
        for speed in (18.8, 18.7757, top + 1e-3):
            with pytest.raises(InvalidArgument) as exc:
                world.command(tank, "drive", {"speed_mps": speed, "yaw_rate_dps": 0.0})
            shown = float(re.search(r"must be within \[[^,]+, ([^\]]+)\] m/s", str(exc.value)).group(1))
            assert top - 1e-6 * top <= shown < speed, (speed, str(exc.value))
    finally:
        world.close()


def test_a_present_hold_heading_is_within_the_commands_range(alps):
    """A vehicle's heading a hair below 0 wrapped to 360.0 (-1e-15 % 360 in floating point), a
    value its own autopilot command refuses ([0, 360)): the hold a partial command completes."""
    world = _ground_world(alps)
    try:
        tank = next(e for e in world.entities.values() if e.name == "tank1")
        i = world.ground.index_of([tank.ground_id])[0]
        world.ground.heading_deg[i] = -1e-15
        hold = world._present_hold(tank)
        assert 0.0 <= hold["heading_deg"] < 360.0, hold
        world.command(tank.id, "autopilot", dict(hold))  # accepted as it stands
    finally:
        world.close()
