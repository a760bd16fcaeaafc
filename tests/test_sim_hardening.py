"""What acceptance probing of the simulation server found, held as tests: a driver's command
beyond its vehicle's limits is refused at once (it used to stop the world at the next tick);
a wreck is at rest; an observer's area of interest stands on the ground; a vanished
client's agent returns to its scenario route; a frozen client's connection is found dead by
keepalive pings; a paused clock resumes on SIGUSR1; bad --duration / --time-scale values and
agents placed by ground height outside the terrain are refused. Real JSBSim, real vehicles,
the Alps DEM, real gRPC on loopback and real processes."""

from __future__ import annotations

import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from client.sim_client import SimClient
from server.process import ServiceProcess, sortie_command
from server.scenario import ScenarioError, load_scenario
from server.sim_server import build_world, open_terrain
from sortie.errors import InvalidArgument
from terrain.geodesy import ecef_to_geodetic

from conftest import REPO

DEM = REPO / "data" / "dem" / "N47E009.hgt"


def scenario_file(tmp_path, agents: str, exercise: str = "") -> str:
    text = textwrap.dedent(f"""\
        [exercise]
        name = "hardening"
        start_time = 2026-06-15T09:00:00Z
        vanished_client_timeout_s = 1.0
        {exercise}
        [terrain]
        dem = ["{DEM}"]
        geoid_undulation_m = 48.0
        """) + textwrap.dedent(agents)
    path = tmp_path / "s.toml"
    path.write_text(text)
    return str(path)


AGENTS = """
    [[agents]]
    name = "jet"
    kind = "aircraft"
    type = "f16"
    coalition = "blue"
    lat_deg = 47.30
    lon_deg = 9.30
    alt_m = 4500.0
    heading_deg = 90.0
    speed_mps = 220.0
    controllable = true
    [agents.autopilot]
    route = [[47.30, 9.55, 4500.0], [47.45, 9.70, 4000.0]]
    speed_mps = 220.0

    [[agents]]
    name = "jeep"
    kind = "ground"
    type = "hmmwv"
    coalition = "red"
    lat_deg = 47.38
    lon_deg = 9.64
    heading_deg = 30.0
    controllable = true
    [agents.autopilot]
    route = [[47.38, 9.64], [47.40, 9.655], [47.42, 9.66]]
    cruise_mps = 10.0

    [[agents]]
    name = "tank"
    kind = "ground"
    type = "m1a2"
    coalition = "blue"
    lat_deg = 47.29
    lon_deg = 9.59
    heading_deg = 45.0
    controllable = true

    [[agents]]
    name = "radar"
    kind = "static"
    type = "radar"
    coalition = "red"
    lat_deg = 47.40
    lon_deg = 9.50
"""


@pytest.fixture
def world(tmp_path):
    scenario = load_scenario(scenario_file(tmp_path, AGENTS))
    w = build_world(scenario, open_terrain(scenario)[0])
    yield w, {e.name: e for e in w.entities.values()}
    w.close()


def test_ground_commands_beyond_the_vehicles_limits_are_refused_before_the_tick(world):
    """Each is refused naming the command's field, nothing is kept, and the world ticks on."""
    w, by_name = world
    tank = by_name["tank"].id
    w.claim(tank, "token")
    for kind, values, field in (("drive", {"speed_mps": 50.0}, "drive.speed_mps"),
                                ("drive", {"speed_mps": -50.0}, "drive.speed_mps"),
                                ("drive", {"speed_mps": 5.0, "yaw_rate_dps": 1e9}, "drive.yaw_rate_dps"),
                                ("autopilot", {"speed_mps": 50.0}, "autopilot.speed_mps"),
                                ("autopilot", {"heading_deg": 720.0}, "autopilot.heading_deg")):
        with pytest.raises(InvalidArgument, match=f"^{field}") as refused:
            w.command(tank, kind, values)
        if kind == "drive":  # named by the agent, not the vehicle model's internal row
            assert "for tank (m1a2)" in str(refused.value) and "vehicle 0" not in str(refused.value)
    w.command(tank, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 3.0})  # within the m1a2's limits
    for _ in range(30):
        w.tick()
    i = w.ground.index_of([by_name["tank"].ground_id])[0]
    assert 0.5 < w.ground.speed_mps[i] <= 8.0


@pytest.mark.parametrize("values, field", [({"heading_deg": 720.0}, "autopilot.heading_deg"),
                                           ({"heading_deg": -90.0}, "autopilot.heading_deg"),
                                           ({"alt_msl_m": -1e6}, "autopilot.alt_msl_m"),
                                           ({"alt_msl_m": 1e9}, "autopilot.alt_msl_m"),
                                           ({"speed_mps": 1e9}, "autopilot.speed_mps"),
                                           ({"speed_mps": 0.0}, "autopilot.speed_mps")])
def test_aircraft_autopilot_targets_are_range_checked_as_the_scenario_checks_them(world, values, field):
    w, by_name = world
    with pytest.raises(InvalidArgument, match=f"^{field}"):
        w.command(by_name["jet"].id, "autopilot", values)


def test_a_wreck_is_at_rest_where_it_came_down(world):
    """From the crash on, velocity, acceleration and body rates are 0 and the position stays:
    receivers dead-reckoning it see it stay (it was published at 220 m/s before). A crash of
    a surface contact (a crash clear of the surface falls first: tests/test_fdm_wreck.py)."""
    w, by_name = world
    jet = by_name["jet"].id
    for _ in range(3):
        w.tick()
    row = list(w.snapshot.ids).index(jet)
    before = w.snapshot.ecef_m[row].copy()
    lat, lon, h = ecef_to_geodetic(before)
    w.air.crash(jet, w.time_s, float(lat), float(lon), float(h), "terrain penetration")
    for _ in range(4):
        w.tick()
    snap = w.snapshot
    row = list(snap.ids).index(jet)
    assert np.array_equal(snap.vel_ecef_mps[row], np.zeros(3))
    assert np.array_equal(snap.body_rates_rps[row], np.zeros(3))
    assert np.linalg.norm(snap.ecef_m[row] - before) < 220.0 / 30 * 2  # at most the tick it crashed in
    still = snap.ecef_m[row].copy()
    w.tick()
    assert np.array_equal(w.snapshot.ecef_m[list(w.snapshot.ids).index(jet)], still)
    assert np.array_equal(w.snapshot.acc_ecef_mps2[list(w.snapshot.ids).index(jet)], np.zeros(3))


def test_a_vanished_driver_hands_the_vehicle_back_to_its_route_and_a_pilot_the_jet_to_its_route(world):
    w, by_name = world
    jeep, jet, tank = by_name["jeep"], by_name["jet"], by_name["tank"]
    for e in (jeep, jet, tank):
        w.claim(e.id, "token")
    w.command(jeep.id, "drive", {"speed_mps": 3.0, "yaw_rate_dps": 15.0})
    w.command(tank.id, "drive", {"speed_mps": 6.0, "yaw_rate_dps": 0.0})
    w.command(jet.id, "stick", {"pitch": 0.0, "roll": 0.0, "throttle": 0.8})
    for _ in range(60):
        w.tick()
    assert jeep.id not in w._followed and w.pilot_kind(jet.id) == "stick"
    t = w.ground.index_of([tank.ground_id])[0]
    speed = w.ground.speed_mps[t]
    assert speed > 1.0
    for e in (jeep, jet, tank):
        w.release(e.id, vanished=True)
    assert jeep.id in w._followed and w.pilot_kind(jet.id) == "route"
    for _ in range(90):
        w.tick()
    i, t = w.ground.index_of([jeep.ground_id, tank.ground_id])
    assert abs(w.ground.yaw_rate_dps[i]) < 15.0  # no longer circling on its last command
    heading = w.ground.heading_deg[t]
    for _ in range(60):
        w.tick()
    assert abs((w.ground.heading_deg[t] - heading + 180.0) % 360.0 - 180.0) < 1.0  # the tank holds its heading
    assert abs(w.ground.speed_mps[t] - speed) < 0.05  # and its speed when its driver vanished


def test_an_observer_stands_on_the_ground_not_on_the_ellipsoid(tmp_path):
    """Over the Alps (the radar's post at ~500-2500 m), a 300 m area around the radar's own
    point holds it: the centre is on the terrain plus the geoid, not at ellipsoid height 0."""
    path = scenario_file(tmp_path, AGENTS)
    with ServiceProcess(["server", "--scenario", path, "--aircraft-workers", "0", "--no-record"],
                        log=tmp_path / "server.log") as server, SimClient(server.address) as sim:
        sim.join("obs", "observer", observer=(47.40, 9.50, 300.0))
        picture = sim.watch()
        assert picture.wait_for(lambda p: any(i.name == "radar" for i in p.infos.values()), 10.0)
        assert {i.name for i in picture.infos.values()} == {"radar"}


def test_a_paused_clock_resumes_on_sigusr1_and_pauses_on_sigusr2(tmp_path):
    path = scenario_file(tmp_path, AGENTS, 'clock = "paused"')
    with ServiceProcess(["server", "--scenario", path, "--aircraft-workers", "0", "--no-record"],
                        log=tmp_path / "server.log") as server, SimClient(server.address) as sim:
        time.sleep(0.5)
        # Paused after the world's first tick (a world that never ticked has no picture to show).
        assert sim.world().time_s == pytest.approx(1 / 30) and sim.world().clock == "paused"
        server.proc.send_signal(signal.SIGUSR1)
        time.sleep(1.5)
        info = sim.world()
        assert info.clock == "realtime" and info.time_s > 0.5
        server.proc.send_signal(signal.SIGUSR2)
        time.sleep(0.5)
        paused_at = sim.world().time_s
        time.sleep(0.7)
        assert sim.world().clock == "paused" and sim.world().time_s == paused_at


@pytest.mark.parametrize("option, value, message", [("--duration", "nan", "duration: must be within (0, "),
                                                    ("--duration", "0", "duration: must be within (0, "),
                                                    ("--duration", "-5", "duration: must be within (0, "),
                                                    ("--time-scale", "0", "time_scale: must be within (0, ")])
def test_bad_duration_and_time_scale_overrides_are_refused(tmp_path, option, value, message):
    path = scenario_file(tmp_path, AGENTS)
    done = subprocess.run([*sortie_command(), "server", "--scenario", path, "--port", "0", "--no-record",
                           "--aircraft-workers", "0", f"{option}={value}"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and message in done.stderr, done.stderr


@pytest.mark.parametrize("agent", [
    'kind = "aircraft"\ntype = "c172x"\non_ground = true',
    'kind = "aircraft"\ntype = "c172x"\nalt_m = 500.0\nalt_ref = "agl"\nspeed_mps = 50.0',
    'kind = "static"\ntype = "radar"',
])
def test_agents_placed_by_the_ground_outside_the_terrain_are_refused(tmp_path, agent):
    path = scenario_file(tmp_path, '[[agents]]\nname = "lost"\ncoalition = "red"\nlat_deg = 50.0\nlon_deg = 9.5\n'
                         + agent + "\n")
    scenario = load_scenario(path)
    with pytest.raises(ScenarioError, match=r"agents\[0\]: 'lost' is placed .* outside the terrain"):
        build_world(scenario, open_terrain(scenario)[0])


def test_a_frozen_client_is_found_dead_by_keepalive_and_its_agent_freed(tmp_path):
    """A client process that stops (SIGSTOP) keeps its TCP connection and its Watch stream
    open, so it never counted as vanished; the server's keepalive pings go unanswered, the
    connection is closed, and after the vanished timeout the pilot's jet is free again."""
    from server.grpc_common import KEEPALIVE_TIME_MS, KEEPALIVE_TIMEOUT_MS
    from server.sim_server import SimulationServer, server_config

    scenario = load_scenario(scenario_file(tmp_path, AGENTS))
    world = build_world(scenario, open_terrain(scenario)[0])
    config = server_config(scenario)  # vanished_client_timeout_s = 1
    server = SimulationServer(world, config, "127.0.0.1:0")
    client = textwrap.dedent("""\
        import sys, time
        from client.sim_client import SimClient
        sim = SimClient(sys.argv[1])
        sim.join("frozen", "pilot", agent_name="jet")
        sim.watch()
        print("joined", flush=True)
        time.sleep(600)
        """)
    server.start()
    frozen = subprocess.Popen([sys.executable, "-c", client, server.address], cwd=REPO, stdout=subprocess.PIPE,
                              text=True)
    try:
        assert frozen.stdout.readline().strip() == "joined"
        frozen.send_signal(signal.SIGSTOP)
        t0 = time.monotonic()
        limit = 2 * (KEEPALIVE_TIME_MS + KEEPALIVE_TIMEOUT_MS) / 1e3 + config.vanished_timeout_s + 5.0
        with SimClient(server.address) as probe:
            while True:
                try:
                    probe.join("probe", "pilot", agent_name="jet")
                    break
                except InvalidArgument:
                    assert time.monotonic() - t0 < limit, "the frozen client kept the jet"
                    time.sleep(0.5)
        assert any(e.kind == "vanished" for e in world.events_since(0)[0])
    finally:
        frozen.kill()
        frozen.wait()
        server.stop(0.5)
        world.close()


def test_bots_whose_server_dies_each_say_so_and_exit_non_zero(tmp_path):
    """No raw thread tracebacks: a line per bot, exit 1. And more bots than agents are told
    that every controllable agent is taken."""
    path = scenario_file(tmp_path, AGENTS)  # three controllable agents
    server = ServiceProcess(["server", "--scenario", path, "--aircraft-workers", "0", "--no-record"],
                            log=tmp_path / "server.log")
    server.__enter__()
    try:
        bots = subprocess.Popen([*sortie_command(), "bot", "--server", server.address, "--count", "4",
                                 "--duration", "60"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(10.0)  # the bots join and fly a first leg
    finally:
        server.proc.kill()
        server.stop()
    out, err = bots.communicate(timeout=60)
    assert bots.returncode == 1
    assert "Traceback" not in err, err
    lines = sorted(line for line in out.splitlines() if line.startswith("bot-"))
    assert len(lines) == 4, out
    assert sum(": stopped: " in line for line in lines) == 3, out
    assert sum("every controllable aircraft or ground vehicle of the scenario is taken" in line
               for line in lines) == 1, out
