"""Scenario authoring (acceptance probe, round s31): what a scenario says is what the world
does. A convoy member keeps its own coalition and controllability; a ground vehicle's
speed_mps is the speed it starts at and holds; an aircraft started at an altitude above
ground holds the altitude it started at; a convoy's spacing leaves room for its vehicles;
agents may not start inside each other; an aircraft started below the ground is told the
scenario's key, not the Python API's."""

from __future__ import annotations

import copy
import math
import time
from pathlib import Path

import numpy as np
import pytest

from fdm.aircraft import terrain_msl_m
from fdm.convoy import OBSTACLE_STANDOFF_M
from fdm.vehicle_types import VEHICLE_TYPES
from server.scenario import ScenarioError, parse_scenario
from server.sim_server import SimulationServer, _aircraft_spec, build_world, open_terrain, server_config
from sortie.errors import InvalidArgument
from terrain.geodesy import radii_of_curvature

REPO = Path(__file__).resolve().parents[1]
DEM = REPO / "data" / "dem" / "N47E009.hgt"
ROUTE = [[47.24, 9.522], [47.26, 9.537], [47.28, 9.552]]


def scenario_doc(agents: list) -> dict:
    return {"exercise": {"name": "author probe", "start_time": "2026-06-15T07:00:00Z"},
            "terrain": {"dem": [str(DEM)], "geoid_undulation_m": 48.0}, "agents": copy.deepcopy(agents)}


def world_of(agents: list, tmp_path):
    scenario = parse_scenario(scenario_doc(agents), tmp_path)
    terrain, desc, _ = open_terrain(scenario)
    return build_world(scenario, terrain), scenario, terrain, desc


def column(n: int, spacing_m: float, vehicle_type: str = "m1a2", **member) -> list:
    """n convoy members on ROUTE's first leg extended back from its first waypoint,
    ``spacing_m`` apart centre to centre, heading along the leg."""
    m, e = radii_of_curvature(ROUTE[0][0])
    north = math.radians(ROUTE[1][0] - ROUTE[0][0]) * m
    east = math.radians(ROUTE[1][1] - ROUTE[0][1]) * e * math.cos(math.radians(ROUTE[0][0]))
    un, ue = north / math.hypot(north, east), east / math.hypot(north, east)
    heading = math.degrees(math.atan2(ue, un)) % 360.0
    out = []
    for k in range(n):
        back = -k * spacing_m
        out.append({"name": f"c{k}", "kind": "ground", "type": vehicle_type, "coalition": "blue",
                    "lat_deg": ROUTE[0][0] + math.degrees(back * un / m),
                    "lon_deg": ROUTE[0][1] + math.degrees(back * ue / (e * math.cos(math.radians(ROUTE[0][0])))),
                    "heading_deg": heading,
                    "autopilot": {"route": ROUTE, "cruise_mps": 10.0, "convoy": "col", "spacing_m": spacing_m},
                    **member})
    return out


# -- 1. a convoy member keeps its own coalition and controllable -----------------------------------

def test_convoy_members_keep_their_own_coalition_and_controllable(tmp_path):
    """The probe's convoy: c0 blue and controllable, c1 red with controllable unset (and its
    own start speed). Each entity has its scenario's values (c1 was blue and controllable, the
    first member's), and a
    driver session is refused c1 (controllable = false is opt-in: no session takes a bot by
    accident) over gRPC, while c0 is joinable."""
    from client.sim_client import SimClient

    agents = column(2, 50.0, "hmmwv")
    agents[0].update(coalition="blue", controllable=True)
    agents[1].update(coalition="red", type="m2a3", speed_mps=4.0)
    world, scenario, _, desc = world_of(agents, tmp_path)
    # Start speeds as spawned, before the server's clock ticks (c0 starts to move at its first tick).
    speeds = {e.name: world.ground.speed_mps[world.ground.index_of([e.ground_id])[0]]
              for e in world.entities.values()}
    assert speeds["c0"] == 0.0 and speeds["c1"] == 4.0  # its own start speed
    srv = SimulationServer(world, server_config(scenario, desc))
    srv.start()
    try:
        got = {e.name: (e.coalition, e.controllable) for e in world.entities.values()}
        assert got == {"c0": ("blue", True), "c1": ("red", False)}
        assert {i[1]: i[4] for i in world.infos.values()} == {"c0": "blue", "c1": "red"}
        with SimClient(srv.address) as driver:
            with pytest.raises(Exception, match="not free to control"):
                driver.join("probe-c1", "driver", "c1")
        with SimClient(srv.address) as driver:
            assert driver.join("probe-c0", "driver", "c0") == world.entities[1].id
    finally:
        srv.stop(0.5)
        world.close()


# -- 2. a ground vehicle's speed_mps is the speed it starts at and holds ---------------------------

def test_a_ground_vehicle_starts_at_its_speed_mps_and_holds_it_on_its_heading(tmp_path):
    """The probe's ``lone`` m1a2 (speed_mps = 5, heading 45, no autopilot) stood still for 60 s.
    Now it starts at 5 m/s and holds speed and heading: after 30 s of world time it has gone
    150 m +- 5 % on 45 deg +- 1 deg, at 5 m/s +- 0.05."""
    world, *_ = world_of([{"name": "lone", "kind": "ground", "type": "m1a2", "coalition": "red",
                           "lat_deg": 47.29, "lon_deg": 9.59, "heading_deg": 45.0, "speed_mps": 5.0}], tmp_path)
    try:
        assert world.ground.speed_mps[0] == 5.0  # at spawn, before any tick
        world.tick()
        lat0, lon0 = world.snapshot.lat_deg[0], world.snapshot.lon_deg[0]
        while world.time_s < 30.0 + 1e-9:
            world.tick()
        m, e = radii_of_curvature(lat0)
        north = math.radians(world.snapshot.lat_deg[0] - lat0) * m
        east = math.radians(world.snapshot.lon_deg[0] - lon0) * e * math.cos(math.radians(lat0))
        moved, track = math.hypot(north, east), math.degrees(math.atan2(east, north)) % 360.0
        print(f"\nlone: {moved:.1f} m on {track:.2f} deg, {world.ground.speed_mps[0]:.3f} m/s")
        assert abs(moved - 150.0) < 7.5 and abs(track - 45.0) < 1.0
        assert abs(world.ground.speed_mps[0] - 5.0) < 0.05 and abs(world.ground.heading_deg[0] - 45.0) < 1.0
    finally:
        world.close()


def test_spawn_ground_checks_start_speeds_and_adds_nothing_it_refuses(tmp_path):
    """World.spawn_ground's speeds: negative, NaN or above the type's top speed is an
    InvalidArgument naming speed_mps and the vehicle, and no vehicle or entity is added."""
    world, *_ = world_of([], tmp_path)
    try:
        top = VEHICLE_TYPES["hmmwv"].max_speed_mps
        for speed in (-1.0, math.nan, top + 1.0):
            with pytest.raises(InvalidArgument, match=r"speed_mps.*(v2|>= 0|within)"):
                world.spawn_ground(["v1", "v2"], "hmmwv", [47.29, 47.2905], [9.59, 9.59], 0.0,
                                   speed_mps=[0.0, speed])
            assert not world.entities and (world.ground is None or world.ground.n == 0)
        world.spawn_ground(["v1"], "hmmwv", [47.29], [9.59], 0.0)
        with pytest.raises(InvalidArgument, match="speed_mps"):
            world.spawn_ground(["v2"], "hmmwv", [47.2905], [9.59], 0.0, speed_mps=top + 1.0)
        assert [e.name for e in world.entities.values()] == ["v1"] and world.ground.n == 1
    finally:
        world.close()


# -- 3. an aircraft started at an altitude above ground holds the altitude it started at ----------

def test_an_agl_aircraft_without_an_autopilot_holds_the_altitude_it_started_at(tmp_path):
    """The probe's twins (c172x at 50 m/s, no autopilot table): the one given 608 m above
    ground over Lake Constance (surface 392 m) starts at 1000 m MSL and held no altitude (it
    climbed to 1995 m in 300 s); now its hold is surface + alt_m, and over 60 s it stays within
    15 m of its start, as its MSL twin does."""
    agents = [{"name": "agl", "kind": "aircraft", "type": "c172x", "coalition": "neutral", "lat_deg": 47.60,
               "lon_deg": 9.40, "alt_m": 608.0, "alt_ref": "agl", "heading_deg": 270.0, "speed_mps": 50.0},
              {"name": "msl", "kind": "aircraft", "type": "c172x", "coalition": "neutral", "lat_deg": 47.55,
               "lon_deg": 9.40, "alt_m": 1000.0, "heading_deg": 270.0, "speed_mps": 50.0}]
    world, scenario, terrain, _ = world_of(agents, tmp_path)
    try:
        surface = float(terrain_msl_m(terrain, [47.60], [9.40])[0])  # as the aircraft meets it
        world.tick()
        start = world.snapshot.alt_msl_m.copy()
        assert abs(start[0] - (surface + 608.0)) < 0.5
        worst = np.zeros(2)
        while world.time_s < 60.0:
            world.tick()
            worst = np.maximum(worst, np.abs(world.snapshot.alt_msl_m - start))
        print(f"\nagl start {start[0]:.1f} m MSL, worst {worst[0]:.1f} m; msl worst {worst[1]:.1f} m")
        assert (worst < 15.0).all()
    finally:
        world.close()
    spec = _aircraft_spec(scenario.agents[0], "autopilot", surface)
    assert spec["hold"] == {"heading_deg": 270.0, "speed_mps": 50.0, "alt_msl_m": surface + 608.0}


# -- 4. a convoy's spacing leaves room for its vehicles --------------------------------------------

def test_a_convoy_spacing_shorter_than_its_vehicles_is_refused(tmp_path):
    """3 m between 7.92 m M1A2s rammed the column every 14 s. The least spacing is the longest
    member's length plus the 4 m standoff a driver keeps (fdm.convoy.OBSTACLE_STANDOFF_M);
    below it the error names agents[i].autopilot.spacing_m, the value and the longest member."""
    least = VEHICLE_TYPES["m1a2"].length_m + OBSTACLE_STANDOFF_M
    agents = column(3, 3.0)
    agents[1]["type"] = agents[2]["type"] = "hmmwv"
    with pytest.raises(ScenarioError) as info:
        parse_scenario(scenario_doc(agents), tmp_path)
    assert info.value.field == "agents[0].autopilot.spacing_m" and info.value.value == 3.0
    assert f"at least {least:g} m" in str(info.value) and "agents[0] 'c0' (m1a2)" in str(info.value)
    for a in agents:
        a["autopilot"]["spacing_m"] = least - 0.01
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.autopilot\.spacing_m"):
        parse_scenario(scenario_doc(agents), tmp_path)
    for a in agents:
        a["autopilot"]["spacing_m"] = least
    assert parse_scenario(scenario_doc(agents), tmp_path).convoys[0].spacing_m == least
    from server.scenario import convoy_spacing_min_m

    assert convoy_spacing_min_m(["hmmwv", "m1a2"]) == least


def test_a_convoy_at_the_least_spacing_drives_its_route_without_a_collision(tmp_path):
    """The bound is enough: three M1A2s at exactly the least spacing (11.92 m) drive 120 s of
    their route (corners included) with no collision among them."""
    world, *_ = world_of(column(3, VEHICLE_TYPES["m1a2"].length_m + OBSTACLE_STANDOFF_M), tmp_path)
    try:
        while world.time_s < 120.0:
            world.tick()
        events, _ = world.events_since(0)
        assert [(e.kind, e.time_s) for e in events if e.kind in ("collision", "destroyed", "blocked")] == []
    finally:
        world.close()


# -- 5. agents may not start inside each other ----------------------------------------------------

AIR = {"kind": "aircraft", "type": "f16", "coalition": "red", "lat_deg": 47.6, "lon_deg": 9.3, "alt_m": 3000.0,
       "heading_deg": 90.0, "speed_mps": 200.0}
TANK = {"kind": "ground", "type": "m1a2", "coalition": "red", "lat_deg": 47.29, "lon_deg": 9.59}
SITE = {"kind": "static", "type": "sam_site", "coalition": "red", "lat_deg": 47.29, "lon_deg": 9.59}


@pytest.mark.parametrize("first, second, overlap", [
    (AIR, {**AIR, "coalition": "blue", "heading_deg": 270.0}, "0.00 m apart"),  # head-on at one point
    (TANK, {**TANK, "coalition": "blue"}, "0.00 m apart"),
    (TANK, {**TANK, "lat_deg": 47.29 + 6.0 / 111_200.0}, "6.00 m apart"),  # nose to tail, 7.92 m long
    (TANK, SITE, "0.00 m apart"),
    (AIR, {**AIR, "alt_m": 3010.0}, "10.00 m apart"),  # 10 m below: within the two 7.5 m spheres
], ids=["aircraft", "tanks", "tanks-6m", "tank-site", "aircraft-10m-apart-vertically"])
def test_agents_starting_inside_each_other_are_refused_naming_both(tmp_path, first, second, overlap):
    """The probe's f16s at one point on opposite headings flew through each other at 400 m/s,
    its tanks on one spot never collided. Building the world refuses them (before any
    aircraft is loaded), naming the later agent's key path, the earlier one and the distance."""
    agents = [{"name": "one", **first}, {"name": "two", **second}]
    scenario = parse_scenario(scenario_doc(agents), tmp_path)
    terrain, _, _ = open_terrain(scenario)
    with pytest.raises(ScenarioError) as info:
        build_world(scenario, terrain)
    assert info.value.field == "agents[1]", str(info.value)
    assert "starts inside agents[0] 'one'" in str(info.value) and overlap in str(info.value), str(info.value)


@pytest.mark.parametrize("first, second", [
    (AIR, {**AIR, "alt_m": 3100.0, "heading_deg": 270.0}),  # 100 m above
    (TANK, {**TANK, "lat_deg": 47.29 + 9.0 / 111_200.0}),  # nose to tail, 1 m apart
    (TANK, {**TANK, "lon_deg": 9.59 + 4.0 / 75_400.0}),  # side by side, 0.3 m apart
    (SITE, {**SITE, "type": "radar"}),  # two statics never meet (neither moves)
    (TANK, {**AIR, "lat_deg": 47.29, "lon_deg": 9.59, "alt_m": 100.0, "alt_ref": "agl"}),  # overhead
], ids=["aircraft-stacked", "tanks-in-line", "tanks-abreast", "two-statics", "aircraft-over-tank"])
def test_agents_clear_of_each_other_are_accepted(tmp_path, first, second):
    from server.sim_server import _check_spawn_overlaps, _surfaces_msl_m

    scenario = parse_scenario(scenario_doc([{"name": "one", **first}, {"name": "two", **second}]), tmp_path)
    terrain, _, _ = open_terrain(scenario)
    _check_spawn_overlaps(scenario, _surfaces_msl_m(scenario, terrain))


def test_the_overlap_check_scales_to_the_scenario_limit(tmp_path):
    """10,000 agents (the scenario limit: tanks 20 m apart on a grid, one last one dropped
    onto the first): the check finds that one pair in under a second (a sort and sweep, not
    every pair)."""
    from server.sim_server import _check_spawn_overlaps, _surfaces_msl_m

    lat0, lon0 = 47.29, 9.55
    k = np.arange(9_999)
    agents = [{"name": f"t{i}", **TANK, "lat_deg": lat0 + (i // 100) * 20.0 / 111_200.0,
               "lon_deg": lon0 + (i % 100) * 20.0 / 75_400.0} for i in k.tolist()]
    agents.append({"name": "dropped", **TANK, "lat_deg": lat0 + 1.0 / 111_200.0, "lon_deg": lon0})
    scenario = parse_scenario(scenario_doc(agents), tmp_path)
    terrain, _, _ = open_terrain(scenario)
    surface = _surfaces_msl_m(scenario, terrain)
    clear = parse_scenario(scenario_doc(agents[:-1]), tmp_path)
    _check_spawn_overlaps(clear, surface[:-1])  # the compiled pass loaded
    t0 = time.perf_counter()
    _check_spawn_overlaps(clear, surface[:-1])
    took = time.perf_counter() - t0
    with pytest.raises(ScenarioError, match=r"agents\[9999\]: 'dropped' \(m1a2\) starts inside agents\[0\] 't0'"):
        _check_spawn_overlaps(scenario, surface)
    print(f"\n{len(agents) - 1} agents clear of each other checked in {took * 1e3:.0f} ms")
    assert took < 1.0


# -- 6. an aircraft started below the ground is told the scenario's key ---------------------------

def test_an_aircraft_below_the_ground_is_told_the_scenario_key(tmp_path):
    """The probe's f16 at 1500 m MSL under a 2457 m summit was told "use on_ground=True" (the
    Python keyword); the scenario's key is ``on_ground = true``, and the message names the
    agent's key path."""
    agents = [{**AIR, "name": "mole", "lat_deg": 47.2493, "lon_deg": 9.3433, "alt_m": 1500.0}]
    scenario = parse_scenario(scenario_doc(agents), tmp_path)
    terrain, _, _ = open_terrain(scenario)
    with pytest.raises(ScenarioError) as info:
        build_world(scenario, terrain)
    text = str(info.value)
    assert info.value.field == "agents[0]" and text.startswith("agents[0]: 'mole' (f16) cannot start: alt_m: "), text
    assert "on_ground=True" not in text and "(on_ground = true)" in text, text
    assert "give it an alt_m above that" in text, text
