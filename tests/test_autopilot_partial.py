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
