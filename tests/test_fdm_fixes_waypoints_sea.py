"""Acceptance-probe fixes (fdm.md bugs 4 and 5), on real JSBSim and real DEMs.

4. A route waypoint inside the turning circle is passed abeam (its along-track distance
   turns positive) instead of being circled for good: in open sky, across the antimeridian
   and at a pole; the route then goes on and captures its next waypoint as before.
5. A landplane's wheels on the sea (N57E011: the Kattegat at 0 m) are a crash, "ditched",
   and an ``on_ground`` start there is refused; on land nearby the same landing and start
   are as before; the catalog's flying boat (Boeing314) may start on the water.
"""

import math

import numpy as np
import pytest

from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from fdm.autopilot import Autopilot, WaypointFollower
from fdm.events import CRASH, TOUCHDOWN
from sortie.errors import InvalidArgument
from terrain.dem import read_dem
from terrain.terrain import Terrain

R_EARTH_M = 6378137.0


def _fly_route(name, speed, start, heading, waypoints, seconds):
    ac = Aircraft(name, FlatTerrain(0.0), InitialConditions(*start, 3000.0, heading_deg=heading, speed_mps=speed))
    wf = WaypointFollower(ac, waypoints, speed_mps=speed)
    wf.run(seconds)
    assert not ac.crashed and ac.events == [], ac.events
    return ac, wf


@pytest.mark.parametrize("name, speed, offset_m, seconds", [("f16", 200.0, 1500.0, 40.0),
                                                             ("c172x", 50.0, 300.0, 25.0)])
def test_a_waypoint_inside_the_turning_circle_is_passed_abeam(name, speed, offset_m, seconds):
    """The probe's r1: a first waypoint beside a northbound aircraft, nearer than its turn
    radius (f16 about 4 km, c172x 550 m). Before, it orbited it (after 300 s: active 0,
    nothing passed); now it passes it abeam, reported in ``passed`` like a capture with its
    miss distance, beyond the capture radius, and turns for the next one."""
    wlon = math.degrees(offset_m / R_EARTH_M)
    ac, wf = _fly_route(name, speed, (0.0, 0.0), 0.0, [(0.0, wlon, 3000.0), (0.0, 1.0, 3000.0)], seconds)
    assert wf.active == 1 and [p[0] for p in wf.passed] == [0], wf.passed
    index, t, miss = wf.passed[0]
    assert 0.0 < t < seconds and miss > wf.capture_radius_m
    # Passed abeam: beyond the waypoint's meridian (the leg ran east from the start), flying on east.
    assert ac.state().lon_deg > wlon


def test_after_a_pass_abeam_the_route_goes_on_and_captures_its_next_waypoint():
    """c172x: a first waypoint 300 m to its side (passed abeam), then one 3 km east of it,
    captured within the capture radius as every ordinary waypoint is."""
    w0 = math.degrees(300.0 / R_EARTH_M)
    w1 = math.degrees(3300.0 / R_EARTH_M)
    ac, wf = _fly_route("c172x", 50.0, (0.0, 0.0), 0.0, [(0.0, w0, 3000.0), (0.0, w1, 3000.0)], 120.0)
    assert wf.done and [p[0] for p in wf.passed] == [0, 1], wf.passed
    assert wf.passed[0][2] > wf.capture_radius_m > wf.passed[1][2]


def test_a_waypoint_across_the_antimeridian_is_passed_abeam():
    """An f16 northbound at 179.99 E with its waypoint 1.5 km east, across the antimeridian
    (at -179.996): passed abeam, with geodesic azimuths (a longitude difference would put it
    360 degrees away)."""
    w = ((179.99 + math.degrees(1500.0 / R_EARTH_M)) + 180.0) % 360.0 - 180.0
    assert w < 0.0
    ac, wf = _fly_route("f16", 200.0, (0.0, 179.99), 0.0, [(0.0, w, 3000.0), (0.0, -179.0, 3000.0)], 40.0)
    assert wf.active == 1 and wf.passed[0][2] > wf.capture_radius_m, wf.passed


def test_a_waypoint_on_the_pole_is_passed_abeam():
    """An f16 eastbound 1.1 km from the north pole, its waypoint the pole itself (inside its
    turning circle): passed abeam, by the azimuths at the pole (GeographicLib's limit
    convention), and it flies on to the next waypoint, 50 km down the 90 W meridian."""
    ac, wf = _fly_route("f16", 200.0, (89.99, 0.0), 90.0, [(90.0, 0.0, 3000.0), (89.55, -90.0, 3000.0)], 40.0)
    assert wf.active == 1 and wf.passed[0][2] > wf.capture_radius_m, wf.passed
    s = ac.state()
    assert np.isfinite(s.lat_deg) and np.isfinite(s.lon_deg)


# -- 5: landplanes and the sea ---------------------------------------------------------------

SEA = (57.5, 11.2)  # the Kattegat, 0 m in N57E011.hgt
LAND = (57.81, 11.9)  # flat land near the coast, 5 m


@pytest.fixture(scope="module")
def kattegat(hgt_kattegat):
    return Terrain([read_dem(hgt_kattegat)])


def _land(terrain, lat, lon):
    """The probe's a2: a c172x 20 m above the ground at 35 m/s, gear down, descending on the
    autopilot at 30 m/s, then braking on the ground; up to 40 s."""
    h0 = float(terrain.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
    ac = Aircraft("c172x", terrain, InitialConditions(lat, lon, 20.0, "agl", heading_deg=0.0, speed_mps=35.0,
                                                      gear_down=True))
    ap = Autopilot(ac)
    ap.set_targets(0.0, h0 - 5.0, 30.0)
    for _ in range(int(40.0 / ac.dt)):
        if ac.on_ground:
            ac.set_controls(throttle=0.0, brakes=1.0, pitch=0.0)
        else:
            ap.update()
        ac.step()
        if ac.crashed:
            break
    return ac


def test_a_landplane_touching_down_on_the_sea_ditches(kattegat):
    """Before, the c172x touched down on the sea (sink 1.65 m/s) and braked to a stop on the
    water. Now the touchdown is followed, at once, by a crash "ditched" naming the wheels in
    the water; the same approach onto land nearby still touches down and rolls out."""
    ac = _land(kattegat, *SEA)
    kinds = [(e.kind, e.detail.get("reason")) for e in ac.events]
    assert kinds == [(TOUCHDOWN, None), (CRASH, "ditched")], kinds
    crash = ac.events[-1]
    assert crash.time_s == ac.events[0].time_s and crash.detail["terrain_msl_m"] <= 0.0
    assert crash.detail["gear_units"] and ac.crashed
    land = _land(kattegat, *LAND)
    assert [e.kind for e in land.events] == [TOUCHDOWN] and not land.crashed
    assert land.on_ground and land.state().ground_speed_mps < 0.5


def test_an_on_ground_start_on_the_sea_is_refused_but_not_for_a_flying_boat(kattegat):
    """As a ground vehicle placed in the water is: InvalidArgument naming the field and
    value. On land it starts as before; the Boeing314, a flying boat (its hull is its gear),
    may start on the water and sits there."""
    with pytest.raises(InvalidArgument, match="lat_deg.*water") as err:
        Aircraft("c172x", kattegat, InitialConditions(*SEA, on_ground=True))
    assert err.value.field == "lat_deg" and err.value.value == SEA[0]
    on_land = Aircraft("c172x", kattegat, InitialConditions(*LAND, on_ground=True))
    on_land.run(1.0)
    assert not on_land.crashed and on_land.on_ground
    boat = Aircraft("Boeing314", kattegat, InitialConditions(*SEA, on_ground=True))
    boat.run(2.0)
    assert not boat.crashed and boat.events == []
