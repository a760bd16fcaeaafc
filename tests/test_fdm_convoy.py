"""Route following and convoy spacing, with stated bounds, on the Alps DEM and hand-made ground."""

import math

import numpy as np
import pytest

from fdm.convoy import Convoy, Route, RouteFollower
from fdm.ground import FREE, GroundVehicles
from sortie.errors import InvalidArgument
from terrain.dem import read_dem
from terrain.geodesy import geodetic_to_ecef, radii_of_curvature
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

# The Rhine valley floor between Oberriet and Lustenau (N47E009): under 4 % gradient along it,
# two nearly collinear legs, a 35 degree right turn, then a 2.1 km leg east.
RHINE = ([47.24, 47.26, 47.28, 47.28], [9.522, 9.537, 9.552, 9.58])


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Terrain:
    return Terrain([read_dem(hgt_alps)])


def _flat(lat0=47.0, lon0=9.0, rows=400, cols=400, d=0.0005):
    return Terrain([Raster(np.full((rows, cols), 100.0, np.float32), Georef(CRS_GEOGRAPHIC, lon0, lat0, d, d))])


# --- the route -----------------------------------------------------------------------------------

def test_project_inverts_point_at():
    route = Route(*RHINE)
    s = np.linspace(0.0, route.length_m, 501)
    lat, lon, _ = route.point_at(s)
    s2, x, _ = route.project(lat, lon)
    np.testing.assert_allclose(s2, s, atol=1e-6)
    np.testing.assert_allclose(x, 0.0, atol=1e-6)
    # Leg lengths agree with geodesic distances between the waypoints (GeographicLib) to 0.1 m.
    from geographiclib.geodesic import Geodesic

    for k in range(3):
        ref = Geodesic.WGS84.Inverse(RHINE[0][k], RHINE[1][k], RHINE[0][k + 1], RHINE[1][k + 1])["s12"]
        assert route.seg_len[k] == pytest.approx(ref, abs=0.1)


def test_route_across_the_antimeridian():
    route = Route([60.0, 60.0], [179.99, -179.99])
    assert route.length_m == pytest.approx(math.radians(0.02) * 6_394_000 * math.cos(math.radians(60)), rel=2e-3)
    lat, lon, heading = route.point_at([0.0, route.length_m / 2, route.length_m])
    assert lon[1] == pytest.approx(-180.0, abs=1e-9) or lon[1] == pytest.approx(180.0, abs=1e-9)
    from geographiclib.geodesic import Geodesic
    geo = Geodesic.WGS84.Inverse(60.0, 179.99, 60.0, -179.99)  # a geodesic leg: 0.0087 deg north of east, east mid-leg
    np.testing.assert_allclose(heading, [geo["azi1"], 90.0, geo["azi2"]], atol=1e-4)
    s, x, _ = route.project([60.0001], [-179.995])
    assert s[0] == pytest.approx(0.75 * route.length_m, rel=1e-3) and x[0] < 0  # north of an eastward leg: left


def test_route_validation_names_field_and_index():
    with pytest.raises(InvalidArgument) as info:
        Route([47.0, 47.0, 47.1], [9.0, 9.0, 9.1])
    assert info.value.field == "route_lat" and info.value.index == 1
    with pytest.raises(InvalidArgument) as info:
        Route([47.0, np.nan], [9.0, 9.1])
    assert info.value.field == "route_lat" and info.value.index == 1
    with pytest.raises(InvalidArgument):
        Route([47.0], [9.0])


# --- route following -----------------------------------------------------------------------------

@pytest.mark.parametrize("vehicle_type", ["hmmwv", "m1a2"])
def test_follower_converges_onto_the_route(vehicle_type):
    """Starting 20 m beside a straight route, heading 30 degrees off it: within 40 s the
    cross-track error is under 0.05 m, it never overshoots beyond 2 m to the other side, and
    the vehicle stops within 2 m of the end."""
    ter = _flat()
    route = Route([47.01, 47.15], [9.05, 9.05])  # 15.6 km north
    start_lat, start_lon, _ = route.point_at([100.0])
    east = 20.0 / (radii_of_curvature(start_lat[0])[1] * math.cos(math.radians(start_lat[0])))
    g = GroundVehicles(ter, start_lat, start_lon + math.degrees(east), [330.0], vehicle_type)
    f = RouteFollower(g, route, [0], cruise_mps=10.0)
    # East of a northward leg is right (+). The leg's frame takes its east scale at the leg's
    # mid-latitude, 0.07 deg north of here: 0.13 % of 20 m.
    assert f.cross_track_m[0] == pytest.approx(20.0, abs=0.03)
    worst_overshoot = 0.0
    for k in range(400):
        f.update()
        g.step(0.1)
        worst_overshoot = max(worst_overshoot, -f.cross_track_m[0])
    f.locate()
    assert abs(f.cross_track_m[0]) < 0.05 and worst_overshoot < 2.0
    short = Route([47.01, 47.014], [9.05, 9.05])  # 445 m: to the end and stop
    g2 = GroundVehicles(ter, [47.01], [9.05], [0.0], vehicle_type)
    f2 = RouteFollower(g2, short, [0], cruise_mps=10.0)
    for _ in range(1200):
        f2.update()
        g2.step(0.1)
    end = geodetic_to_ecef(47.014, 9.05, 0.0)
    assert np.linalg.norm(geodetic_to_ecef(g2.lat[0], g2.lon[0], 0.0) - end) < 2.0
    assert g2.speed_mps[0] == 0.0


def test_follower_rejects_bad_arguments():
    ter = _flat()
    g = GroundVehicles(ter, [47.01], [9.05], [0.0], "hmmwv")
    route = Route([47.01, 47.02], [9.05, 9.05])
    with pytest.raises(InvalidArgument) as info:
        RouteFollower(g, route, [0], cruise_mps=100.0)
    assert info.value.field == "cruise_mps"
    with pytest.raises(InvalidArgument) as info:
        RouteFollower(g, route, [0, 3], cruise_mps=5.0)
    assert info.value.field == "index" and info.value.index == 1
    with pytest.raises(InvalidArgument) as info:
        Convoy(g, route, [0], cruise_mps=5.0, spacing_m=-1.0)
    assert info.value.field == "spacing_m"


# --- convoy spacing on real terrain ----------------------------------------------------------------

def test_convoy_keeps_its_spacing_through_the_rhine_valley(alps):
    """Four mixed vehicles (wheeled and tracked) start 70, 30 and 90 m apart and are asked for
    50 m at 12 m/s over the real DEM:

    - settled on the straight (60 s on, before the corner): |gap - 50| <= 0.5 m, cross-track
      <= 0.05 m;
    - through the 35 degree corner: cross-track <= 3 m, |gap - 50| <= 40 m;
    - 90 s after the last vehicle leaves the corner: |gap - 50| <= 0.5 m again;
    - at the route's end all stop, the leader within 2 m of the last waypoint, gaps 50 +- 1.5 m;
    - nobody is ever blocked by terrain.
    """
    route = Route(*RHINE)
    corner = route.cum[2]
    s0 = np.array([3800.0, 3730.0, 3700.0, 3610.0])
    lat, lon, heading = route.point_at(s0)
    g = GroundVehicles(alps, lat, lon, heading, ["hmmwv", "m1083", "m2a3", "m1a2"])
    c = Convoy(g, route, np.arange(4), cruise_mps=12.0, spacing_m=50.0)
    dt = 0.1
    t_left_corner = None
    straight_gap = straight_xt = corner_gap = corner_xt = after_gap = 0.0
    for k in range(int(360 / dt)):
        c.update()
        g.step(dt)
        assert (g.blocked == FREE).all()
        t = (k + 1) * dt
        err = np.abs(c.gaps_m - 50.0)
        if t >= 60.0 and c.s[0] < corner - 100.0:
            straight_gap = max(straight_gap, err.max())
            straight_xt = max(straight_xt, np.abs(c.cross_track_m).max())
        if c.s[0] >= corner - 100.0 and t_left_corner is None:
            corner_gap = max(corner_gap, err.max())
            corner_xt = max(corner_xt, np.abs(c.cross_track_m).max())
            if c.s[-1] > corner + 100.0:
                t_left_corner = t
        if t_left_corner is not None and t > t_left_corner + 90.0 and c.s[0] < route.length_m - 300.0:
            after_gap = max(after_gap, err.max())
    assert t_left_corner is not None and after_gap > 0.0
    assert straight_gap <= 0.5 and straight_xt <= 0.05
    assert corner_xt <= 3.0 and corner_gap <= 40.0
    assert after_gap <= 0.5
    assert (g.speed_mps == 0.0).all()
    end = geodetic_to_ecef(RHINE[0][-1], RHINE[1][-1], 0.0)
    assert np.linalg.norm(geodetic_to_ecef(g.lat[0], g.lon[0], 0.0) - end) < 2.0
    assert np.abs(c.gaps_m - 50.0).max() <= 1.5


def _corner_ceiling_oracle(route, s, lookahead_m, lat_accel_mps2, brake_mps2):
    """Route.corner_speed_ceiling as first written: every corner, as numpy over the vehicles."""
    from fdm.convoy import LOOKAHEAD_MIN_M

    s = np.asarray(s, dtype=np.float64)
    out = np.full(np.broadcast(s, lookahead_m, lat_accel_mps2, brake_mps2).shape, np.inf)
    if route.seg_len.size < 2:
        return out
    psi = np.arctan2(route.seg_de, route.seg_dn)
    turn = np.abs((np.diff(psi) + np.pi) % (2 * np.pi) - np.pi)
    for w in range(turn.size):
        if turn[w] < 1e-6:
            continue
        at = route.cum[w + 1]
        v_c = np.sqrt(lat_accel_mps2 * LOOKAHEAD_MIN_M / turn[w])
        d = np.maximum(at - lookahead_m - s, 0.0)
        out = np.where(s <= at, np.minimum(out, np.sqrt(v_c * v_c + 2.0 * brake_mps2 * d)), out)
    return out


@pytest.mark.parametrize("waypoints", [2, 3, 40, 1000])
def test_corner_ceiling_walk_equals_every_corner(waypoints):
    """The compiled corner ceiling stops walking corners once none further on can lower it:
    bit for bit the ceiling over every corner, for vehicles before, along and past the route,
    scalar or per-vehicle limits, no braking at all, and straight stretches (no corner)."""
    rng = np.random.default_rng(waypoints)
    lat = 47.2 + np.cumsum(rng.uniform(0.0003, 0.002, waypoints))
    lon = 9.5 + np.cumsum(rng.choice([0.0, 1.0], waypoints) * rng.uniform(-0.002, 0.002, waypoints))
    route = Route(lat, lon)
    s = np.concatenate([rng.uniform(-50.0, route.length_m + 50.0, 300), route.cum, [0.0, route.length_m]])
    lookahead = rng.uniform(12.0, 40.0, s.size)
    for lat_accel, brake in ((2.0, 3.0), (rng.uniform(0.5, 4.0, s.size), rng.uniform(0.5, 6.0, s.size)),
                             (1.5, 0.0)):
        got = route.corner_speed_ceiling(s, lookahead, lat_accel, brake)
        want = _corner_ceiling_oracle(route, s, lookahead, lat_accel, brake)
        assert got.shape == want.shape and np.array_equal(got, want)
    one = route.corner_speed_ceiling(float(s[0]), 20.0, 2.0, 3.0)
    assert np.shape(one) == () and one == _corner_ceiling_oracle(route, s[0], 20.0, 2.0, 3.0)
    assert (waypoints <= 2) == bool(np.isinf(route.corner_speed_ceiling(s, lookahead, 2.0, 3.0)).all())


def test_a_follower_set_gives_every_followers_own_commands_bit_for_bit(alps):
    """FollowerSet (what a world tick uses) against each follower's own update, over 20 s of
    a mixed world: convoys and lone followers, stopping at the end or not, routes of 2 to 24
    waypoints, four vehicle types, vehicles started off their route and heading: the same
    commands and trajectories, bit for bit."""
    from fdm.convoy import FollowerSet

    def world():
        rng = np.random.default_rng(4)
        lats, lons, heads, specs, types, n0 = [], [], [], [], [], 0
        for k in range(14):
            nw = int(rng.integers(2, 25))
            lat = 47.05 + 0.9 * rng.random() + np.cumsum(rng.uniform(0.0003, 0.0008, nw))
            lon = 9.05 + 0.8 * rng.random() + np.cumsum(rng.uniform(-0.0008, 0.0008, nw))
            route = Route(lat, lon)
            m = int(rng.integers(1, 7))
            la, lo, hd = route.point_at(np.maximum(route.length_m * rng.uniform(0, 0.8) - 60.0 * np.arange(m), 0.0))
            lats.append(la + rng.normal(0, 1e-4, m))
            lons.append(lo)
            heads.append(hd + rng.normal(0, 30, m))
            types += list(rng.choice(["hmmwv", "m1a2", "m2a3", "m1083"], m))
            specs.append((route, np.arange(n0, n0 + m), m > 1 and k % 3 != 0, bool(k % 4)))
            n0 += m
        g = GroundVehicles(alps, np.concatenate(lats), np.concatenate(lons), np.concatenate(heads) % 360, types)
        fs = [Convoy(g, r, idx, 9.0, 40.0, stop_at_end=stop) if convoy else
              RouteFollower(g, r, idx, 8.0, stop_at_end=stop) for r, idx, convoy, stop in specs]
        return g, fs

    (g1, each), (g2, fs2) = world(), world()
    together = FollowerSet(fs2)
    assert any(isinstance(f, Convoy) for f in each) and any(not isinstance(f, Convoy) for f in each)
    for _ in range(600):
        for f in each:
            f.update()
        together.update()
        assert np.array_equal(g1.speed_cmd_mps, g2.speed_cmd_mps)
        assert np.array_equal(g1.yaw_rate_cmd_dps, g2.yaw_rate_cmd_dps)
        g1.step(1 / 30)
        g2.step(1 / 30)
    assert np.array_equal(g1.lat, g2.lat) and np.array_equal(g1.lon, g2.lon)
    assert all(np.array_equal(a.s, b.s) and np.array_equal(a._hint, b._hint) for a, b in zip(each, fs2))
    assert float(np.abs(g1.speed_mps).max()) > 1.0  # they drove
    FollowerSet([]).update()  # a world without routes
    other = GroundVehicles(alps, [47.3], [9.5], [0.0], ["hmmwv"])
    with pytest.raises(InvalidArgument, match="same GroundVehicles"):
        FollowerSet([each[0], RouteFollower(other, each[0].route, [0], 5.0)])


def test_an_out_and_back_route_is_driven_out_and_back():
    """A -> B -> A, 500 m each way, its legs on one line: the vehicle turns at B and drives back
    to A (it orbited B before: its closest point flipped between the legs by rounding, and a
    goal right behind it gave pure pursuit no curvature). Within 2 m of the route throughout,
    and s never runs backwards by more than the turn's clamp at B."""
    from fdm.convoy import Route, RouteFollower
    from terrain.raster import STATUS_OK
    from terrain.terrain import HeightResult

    class Flat:
        def heights(self, lat, lon):
            lat = np.asarray(lat, float)
            return HeightResult(np.full(lat.shape, 100.0), np.full(lat.shape, STATUS_OK, np.uint8))

    east = 111_132.0 * math.cos(math.radians(45.0))  # metres a degree of longitude, ~0.3 %
    route = Route([45.0, 45.0, 45.0], [7.0, 7.0 + 500.0 / east, 7.0])
    for vehicle in ("hmmwv", "m1a2"):
        gv = GroundVehicles(Flat(), [45.0], [7.0 + 1.0 / east], [90.0], vehicle)
        follower = RouteFollower(gv, route, [0], 10.0)
        far, s_max = 0.0, 0.0
        for _ in range(3000):
            follower.update()
            gv.step(0.05)
            far = max(far, abs(follower.cross_track_m[0]))
            s_max = max(s_max, follower.s[0])
        assert s_max > route.length_m - 20.0 and follower.s[0] > route.length_m - 20.0, vehicle
        assert abs(gv.lon[0] - 7.0) * east < 20.0, vehicle  # back at A
        assert far < 25.0, vehicle  # the turn at B, within its turning circle
