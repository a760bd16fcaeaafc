"""Ground routes near the poles and across the antimeridian (acceptance probe, session 30).

The probe drove a Humvee along legs from (-89.98, 0) to (-89.98, lon): each leg was a straight
line in latitude and longitude, so it went half way round the pole along the parallel (7018 m
for a 4468 m geodesic), and the leg spanning exactly 180 degrees of longitude was never
finished (the vehicle's longitude offset was wrapped apart from the leg's, so its arc length
fell from 6999 m to 0 as it crossed the antimeridian). Oracles: GeographicLib (Karney,
"Algorithms for geodesics", J. Geodesy 87, 2013)."""

import math

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic

from fdm.convoy import FollowerSet, Route, RouteFollower
from fdm.ground import FREE, GroundVehicles
from sortie.errors import InvalidArgument
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

WGS84 = Geodesic.WGS84


@pytest.fixture(scope="module")
def south_cap() -> Terrain:
    """Flat ground 2800 m high over the south polar cap (-90 to -89.5), every longitude."""
    d = 0.05
    return Terrain([Raster(np.full((11, 7201), 2800.0, np.float32), Georef(CRS_GEOGRAPHIC, -180.0, -90.0, d, d))])


def _geodesic_m(lat, lon) -> float:
    return sum(WGS84.Inverse(lat[i], lon[i], lat[i + 1], lon[i + 1])["s12"] for i in range(len(lat) - 1))


def _drive(terrain, lat, lon, seconds, dt=0.1):
    """A Humvee at 15 m/s along the route from its first waypoint, heading along the first
    leg: (route, ground driven (m, geodesic steps), its largest |cross-track| (m), its distance
    from the last waypoint (m), the time it stopped there (s; None: it did not))."""
    route = Route(lat, lon)
    heading = WGS84.Inverse(lat[0], lon[0], lat[1], lon[1])["azi1"] % 360.0
    g = GroundVehicles(terrain, [lat[0]], [lon[0]], [heading], "hmmwv")
    f = RouteFollower(g, route, [0], 15.0)
    driven, worst_x, prev, stopped = 0.0, 0.0, (lat[0], lon[0]), None
    for k in range(int(round(seconds / dt))):
        f.update()
        g.step(dt)
        assert g.blocked[0] == FREE
        driven += WGS84.Inverse(prev[0], prev[1], g.lat[0], g.lon[0])["s12"]
        prev = (float(g.lat[0]), float(g.lon[0]))
        worst_x = max(worst_x, abs(float(f.cross_track_m[0])))
        if g.speed_mps[0] == 0.0 and f.s[0] > route.length_m - 1.0:
            stopped = (k + 1) * dt
            break
    end = WGS84.Inverse(g.lat[0], g.lon[0], lat[-1], lon[-1])["s12"]
    return route, driven, worst_x, end, stopped


# --- the legs are geodesics ------------------------------------------------------------------------

@pytest.mark.parametrize("lat0", [-89.98, -60.0, 0.0, 47.0, 80.0, 89.99])
def test_legs_are_geodesics_at_any_latitude(lat0):
    """Legs of 100 m to 50 km in twelve directions from (lat0, 170) (across the antimeridian,
    and over the pole from 89.99 and -89.98): each leg's length is the geodesic's to 1e-6,
    its points a quarter, half and three quarters along lie within 2e-5 of its length of the
    geodesic's (0.5 m at 50 km: the split along it; sideways under 0.2 m), and the route's
    heading there is the geodesic's azimuth to 0.001 degrees (points over 1 km from a pole,
    where a heading is defined well enough to compare). The probe's legs near the pole were
    up to 57 % long."""
    for az in range(0, 360, 30):
        for d in (100.0, 2000.0, 20000.0, 50000.0):
            end = WGS84.Direct(lat0, 170.0, az, d)
            route = Route([lat0, end["lat2"]], [170.0, end["lon2"]])
            inv = WGS84.Inverse(lat0, 170.0, end["lat2"], end["lon2"])
            assert route.length_m == pytest.approx(inv["s12"], rel=1e-6), (az, d)
            frac = np.array([0.25, 0.5, 0.75])
            lat, lon, heading = route.point_at(frac * route.length_m)
            for f, la, lo, hd in zip(frac, lat, lon, heading):
                want = WGS84.Direct(lat0, 170.0, inv["azi1"], f * inv["s12"])
                assert WGS84.Inverse(la, lo, want["lat2"], want["lon2"])["s12"] <= 2e-5 * d, (az, d, f)
                if WGS84.Inverse(la, lo, math.copysign(90.0, lat0), 0.0)["s12"] > 1000.0:
                    assert abs((hd - want["azi2"] + 180.0) % 360.0 - 180.0) <= 1e-3, (az, d, f)


def test_the_probes_polar_legs_have_their_geodesic_lengths():
    """The probe's legs from (-89.98, 0) to (-89.98, lon): 90, 170, 179, 180 and -180 degrees
    (the last two the same leg, over the pole) are 3159 to 4468 m, as GeographicLib's, to 1 mm
    (they were 3509 to 7018 m); projecting the leg's own points gives back their arc lengths."""
    for lon1 in (90.0, 170.0, 179.0, 180.0, -180.0):
        route = Route([-89.98, -89.98], [0.0, lon1])
        assert route.length_m == pytest.approx(_geodesic_m([-89.98, -89.98], [0.0, lon1]), abs=1e-3), lon1
        s = np.linspace(0.0, route.length_m, 101)
        lat, lon, _ = route.point_at(s)
        s2, x, _ = route.project(lat, lon)
        np.testing.assert_allclose(s2, s, atol=1e-6)
        np.testing.assert_allclose(x, 0.0, atol=1e-6)


# --- driving them ----------------------------------------------------------------------------------

@pytest.mark.parametrize("lon1", [180.0, -180.0, 90.0])
def test_a_polar_leg_is_driven_to_its_end(south_cap, lon1):
    """From (-89.98, 0) to (-89.98, lon1) at 15 m/s: the Humvee stops within 1 m of the last
    waypoint in under 330 s (the 4468 m over the pole take about 305 s), having driven at
    most 0.5 % more than the geodesic and never more than 1 m off its route. Along the leg
    of exactly 180 degrees it was still hunting at 15 m/s 88 m from the end after 1200 s."""
    lat, lon = [-89.98, -89.98], [0.0, lon1]
    route, driven, worst_x, end, stopped = _drive(south_cap, lat, lon, 330.0)
    assert stopped is not None and end < 1.0, (stopped, end)
    assert driven <= 1.005 * _geodesic_m(lat, lon), driven
    assert worst_x < 1.0, worst_x


def test_a_corner_beside_the_pole_is_the_corner_it_is(south_cap):
    """The probe's route (-89.95, -45) -> (-89.99, 135) -> (-89.95, 100): the first leg runs
    over the pole, and the route turns 42.8 degrees at the second waypoint. The route's turn
    there is the geodesics' (from the first's azimuth on arrival to the second's on departure)
    to 0.01 degrees, where the difference of the legs' headings at their midpoints (the
    meridians converging between them) said 88.4 degrees; driven, the Humvee stops within 1 m
    of the end having driven at most 0.5 % more than the geodesics (the route was 16.4 km for
    11.4 km), and takes the corner within 5 m of the route."""
    lat, lon = [-89.95, -89.99, -89.95], [-45.0, 135.0, 100.0]
    route = Route(lat, lon)
    arrive = WGS84.Inverse(lat[0], lon[0], lat[1], lon[1])["azi2"]
    leave = WGS84.Inverse(lat[1], lon[1], lat[2], lon[2])["azi1"]
    turn = abs((leave - arrive + 180.0) % 360.0 - 180.0)
    assert route.corner_turn.size == 1 and math.degrees(route.corner_turn[0]) == pytest.approx(turn, abs=0.01)
    route, driven, worst_x, end, stopped = _drive(south_cap, lat, lon, 900.0)
    assert stopped is not None and end < 1.0, (stopped, end)
    assert driven <= 1.005 * _geodesic_m(lat, lon), driven
    assert worst_x < 5.0, worst_x


def test_a_pass_beside_the_pole_shifts_the_goal_sideways(south_cap):
    """A goal point shifted to pass an obstacle (FollowerSet, world passing) moves the asked
    metres to the right of the route's direction there, also 20 m from the pole, where a
    shift made in latitude and longitude degrees went elsewhere: 3 m to within 1 mm, at 90
    degrees to the route's heading to within 0.05 degrees."""
    route = Route([-89.98, -89.98], [0.0, 180.0])
    g = GroundVehicles(south_cap, [-89.98], [0.0], [180.0], "hmmwv")
    fs = FollowerSet([RouteFollower(g, route, [0], 10.0)])
    for s in (1000.0, route.length_m / 2 - 20.0, route.length_m / 2 + 5.0):
        goal, direction = route.normals_at([s])
        lat, lon, heading = route.point_at([s])
        fs._shift_goals(np.array([3.0]), goal, direction)
        la = math.degrees(math.atan2(goal[0, 2], math.hypot(goal[0, 0], goal[0, 1])))
        lo = math.degrees(math.atan2(goal[0, 1], goal[0, 0]))
        moved = WGS84.Inverse(lat[0], lon[0], la, lo)
        assert moved["s12"] == pytest.approx(3.0, abs=1e-3), s
        assert (moved["azi1"] - heading[0]) % 360.0 == pytest.approx(90.0, abs=0.05), s


def test_a_leg_of_a_quarter_circle_or_more_is_refused():
    """A leg is the shorter arc between its waypoints; one spanning 90 degrees of arc or more
    (antipodes: no shorter arc at all) is refused, naming the field, the waypoint and the
    value."""
    Route([0.0, 0.0], [0.0, 89.9])
    for lat, lon in (([0.0, 0.0], [0.0, 90.0]), ([10.0, 20.0, -20.0], [5.0, 5.0, -175.0])):
        with pytest.raises(InvalidArgument) as info:
            Route(lat, lon)
        assert info.value.field == "route_lat" and info.value.index == len(lat) - 1
        assert info.value.value == lat[-1]
