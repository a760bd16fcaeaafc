"""Autopilot commands that set some targets keep the others, and an aircraft its pilot leaves
returns to its scenario autopilot (acceptance probe: a heading alone released the altitude
and speed holds, and an f16 at 4500 m flew into the ground 79 s later; leaving it so, it kept
diving, since an aircraft with any autopilot was not handed back)."""

import numpy as np
import pytest

from fdm.aircraft import FlatTerrain, InitialConditions
from server.aircraft_host import LocalAircraftHost
from server.world import World

DT = 1.0 / 120.0
ALT = 3000.0
SPEED = 200.0


@pytest.fixture()
def world():
    w = World(FlatTerrain(400.0), aircraft_host=LocalAircraftHost(FlatTerrain(400.0), DT))
    held = w.spawn_aircraft("held", "f16", InitialConditions(47.0, 9.0, ALT, heading_deg=0.0, speed_mps=SPEED),
                            controllable=True, hold={"heading_deg": 0.0, "alt_msl_m": ALT, "speed_mps": SPEED})
    routed = w.spawn_aircraft("routed", "f16", InitialConditions(47.2, 9.0, ALT, heading_deg=90.0, speed_mps=SPEED),
                              controllable=True, route=[(47.2, 10.0, ALT), (47.2, 11.0, ALT)], speed_mps=SPEED)
    yield w, held.id, routed.id
    w.close()


def _state(w, entity_id):
    return w.air._get(entity_id).state()


def _fly(w, seconds):
    for _ in range(int(seconds / w.dt)):
        w.tick()


def test_a_heading_alone_keeps_the_altitude_and_speed_held(world):
    w, held, _ = world
    w.claim(held, "token")
    w.command(held, "autopilot", {"heading_deg": 270.0})
    _fly(w, 60.0)
    s = _state(w, held)
    assert abs(s.alt_msl_m - ALT) < 100.0  # the hold's altitude (it dived 2000 m in 60 s before)
    assert abs(s.airspeed_true_mps - SPEED) < 0.1 * SPEED
    assert abs((np.degrees(s.euler_rad[2]) - 270.0 + 180.0) % 360.0 - 180.0) < 5.0  # and it turned
    w.command(held, "autopilot", {"alt_msl_m": ALT + 300.0})  # a new altitude keeps the new heading
    _fly(w, 40.0)
    s = _state(w, held)
    assert abs(s.alt_msl_m - (ALT + 300.0)) < 100.0
    assert abs((np.degrees(s.euler_rad[2]) - 270.0 + 180.0) % 360.0 - 180.0) < 5.0


def test_a_pilot_leaving_hands_the_aircraft_back_to_its_scenario_autopilot(world):
    w, held, routed = world
    for e in (held, routed):
        w.claim(e, "token")
        w.command(e, "autopilot", {"heading_deg": 200.0, "alt_msl_m": ALT - 500.0})
    _fly(w, 20.0)
    for e in (held, routed):
        w.release(e, vanished=True)
    assert w.pilot_kind(routed) == "route"
    _fly(w, 60.0)
    s = _state(w, held)
    assert abs((np.degrees(s.euler_rad[2]) + 180.0) % 360.0 - 180.0) < 5.0  # the scenario's heading, north
    assert abs(s.alt_msl_m - ALT) < 150.0
    r = _state(w, routed)
    assert abs(r.alt_msl_m - ALT) < 150.0
    assert r.lon_deg > 9.0 and abs((np.degrees(r.euler_rad[2]) - 90.0 + 180.0) % 360.0 - 180.0) < 20.0  # east again


def test_a_wreck_is_not_handed_out_claimed_or_commanded(world):
    """(Acceptance probe: a Join naming no agent got a crashed aircraft while a flyable one
    was free, and its commands were accepted.)"""
    from server.sim_server import type_params
    from server.sim_service import Sessions
    from sortie.errors import InvalidArgument
    from sortie.v1 import simulation_pb2 as pb

    w, held, routed = world
    w.tick()
    s = _state(w, held)
    w.air.crash(held, w.time_s, s.lat_deg, s.lon_deg, s.alt_msl_m, "the test")
    for _ in range(3):  # the crash is flown in the tick after the one under way
        w.tick()
    assert w.is_wreck(w.entities[held])
    sessions = Sessions(w, lambda i, kind=None: type_params({}, w.entities, i, kind))
    assert sessions.join("p1", pb.ROLE_PILOT).agent_id == routed  # the free aircraft that flies
    with pytest.raises(InvalidArgument, match="has crashed"):
        w.claim(held, "token")
    with pytest.raises(InvalidArgument, match="held has crashed"):
        w.command(held, "autopilot", {"heading_deg": 10.0})


def test_partial_commands_in_one_tick_add_up(world):
    """(Acceptance probe: a heading and then an altitude sent within one tick kept only the
    altitude; flaps then throttle lost the flaps.)"""
    w, held, routed = world
    w.claim(held, "token")
    w.command(held, "autopilot", {"heading_deg": 270.0})
    w.command(held, "autopilot", {"alt_msl_m": ALT + 200.0})
    w.tick()
    w.tick()
    t = w.air._pilots[held].targets
    assert (t.heading_deg, t.alt_msl_m, t.speed_mps) == (270.0, ALT + 200.0, SPEED)
    w.claim(routed, "token")
    w.command(routed, "stick", {"flaps": 1.0})
    w.command(routed, "stick", {"throttle": 0.2})
    w.tick()
    w.tick()
    c = w.air.controls(routed)
    assert (c.flaps, c.throttle) == (1.0, 0.2)


def test_a_partial_command_off_a_route_keeps_what_the_route_flew(world):
    """(Acceptance probe: a speed alone given to an f16 climbing on its route to its next
    waypoint levelled it off where it was: the hold came from its state, not its targets.)"""
    w, _, routed = world
    w.air._pilots[routed].waypoints[0] = (47.2, 10.0, ALT + 1500.0)  # a climb to the first waypoint
    _fly(w, 3.0)
    w.claim(routed, "token")
    w.command(routed, "autopilot", {"speed_mps": 180.0})
    _fly(w, 2.0)
    t = w.air._pilots[routed].targets
    assert t.alt_msl_m == ALT + 1500.0 and t.speed_mps == 180.0
    assert abs(t.heading_deg - 90.0) < 5.0  # the heading to the waypoint


def test_a_parked_aircraft_its_pilot_leaves_stays_parked():
    """(Acceptance probe: the fallback hold of 1 m/s had a c172x at rest taxi off, 15 m in 60 s.)"""
    w = World(FlatTerrain(400.0), aircraft_host=LocalAircraftHost(FlatTerrain(400.0), DT))
    try:
        e = w.spawn_aircraft("parked", "c172x", InitialConditions(47.0, 9.0, 0.0, heading_deg=0.0, speed_mps=0.0,
                                                                 on_ground=True), controllable=True)
        _fly(w, 2.0)
        w.claim(e.id, "token")
        w.command(e.id, "stick", {"throttle": 0.0, "brakes": 0.0})
        _fly(w, 2.0)
        start = _state(w, e.id).ecef_m.copy()
        w.release(e.id, vanished=True)
        _fly(w, 30.0)
        s = _state(w, e.id)
        assert np.linalg.norm(s.ecef_m - start) < 0.5 and s.ground_speed_mps < 0.1
        assert w.air.controls(e.id).throttle == 0.0
    finally:
        w.close()


def test_a_ground_vehicle_given_a_heading_alone_keeps_its_speed():
    """(Acceptance probe: a Humvee on its route at 10 m/s given a heading alone stopped,
    half-way through the turn: its hold's missing speed read as 0.)"""
    w = World(FlatTerrain(400.0))
    try:
        (e,) = w.spawn_ground(["jeep"], ["hmmwv"], np.array([47.0]), np.array([9.0]), np.array([0.0]),
                              controllable=True, route=[(47.0, 9.0), (47.2, 9.0)], cruise_mps=10.0)
        _fly(w, 10.0)
        w.claim(e.id, "token")
        w.command(e.id, "autopilot", {"heading_deg": 90.0})
        _fly(w, 20.0)
        i = w.ground.index_of([e.ground_id])[0]
        assert w.ground.speed_mps[i] > 8.0
        assert abs((w.ground.heading_deg[i] - 90.0 + 180.0) % 360.0 - 180.0) < 3.0
    finally:
        w.close()


def test_a_bot_whose_aircraft_crashes_says_so_and_leaves(hgt_alps):
    """A bot's aircraft that crashes takes no more commands (above): the bot ends its flight
    with a line saying so, not as a failure ("stopped: command: viper1 has crashed")."""
    import threading

    from client import cli
    from server.sim_server import ServerConfig, SimulationServer
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    alps = Terrain([read_dem(hgt_alps)])
    w = World(alps)
    jet = w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                           controllable=True)

    def crash_once_flown(world):  # on the clock thread, before a tick
        e = world.entities[jet.id]
        if e.owner is not None and world.time_s > 2.0 and not world.is_wreck(e):
            s = world.air._get(jet.id).state()
            world.air.crash(jet.id, world.time_s, s.lat_deg, s.lon_deg, s.alt_msl_m, "the test")

    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=4.0), before_tick=crash_once_flown)
    srv.start()
    try:
        results = []
        cli._fly_bot(srv.address, 0, "patrol", 1.0, 30.0, results, threading.Event())
        (k, agent, what), = results
        assert agent == jet.id and "then its agent crashed" in what, what
        assert srv.world.entities[jet.id].owner is None  # it left
    finally:
        srv.stop(0.5)
        w.close()
