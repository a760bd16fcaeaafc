"""Ground vehicles on real and hand-made terrain: surface, cliffs, shores, slopes, seams, poles.

Every bound is stated where it is asserted. Real DEMs (SRTM3 Alps and
Kattegat tiles) and hand-made rasters through the same Terrain; one check runs
the model over the real gRPC terrain service.
"""

import dataclasses
import math

import numpy as np
import pytest

from fdm.ground import (BLOCKED_SIDE_SLOPE, BLOCKED_SLOPE, BLOCKED_WATER, FREE, GroundVehicles)
from fdm.vehicle_types import G_MPS2, HMMWV, M1A2_ABRAMS, VEHICLE_TYPES
from sortie.errors import InvalidArgument
from terrain.dem import read_dem
from terrain.geodesy import geodetic_to_ecef
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

TYPES4 = ["m1a2", "hmmwv", "m2a3", "m1083"]


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Terrain:
    return Terrain([read_dem(hgt_alps)])


@pytest.fixture(scope="module")
def kattegat(hgt_kattegat) -> Terrain:
    return Terrain([read_dem(hgt_kattegat)])


def _alps_fleet(alps, n=200, seed=1):
    rng = np.random.default_rng(seed)
    lat = rng.uniform(47.1, 47.9, n)
    lon = rng.uniform(9.1, 9.9, n)
    g = GroundVehicles(alps, lat, lon, rng.uniform(0, 360, n), (TYPES4 * n)[:n])
    g.set_controls(rng.uniform(3, 12, n), rng.uniform(-3, 3, n))
    return g


def _ecef(g):
    return geodetic_to_ecef(g.lat, g.lon, g.height_msl_m)


def _grid(heights, lat0=47.0, lon0=9.0, d=0.00005):
    """A hand-made raster: row 0 south, posts d degrees apart (5.6 m N-S, 3.8 m E-W at 47 N)."""
    return Terrain([Raster(np.asarray(heights, np.float32), Georef(CRS_GEOGRAPHIC, lon0, lat0, d, d))])


# --- on the surface at any step size -----------------------------------------------------------

@pytest.mark.parametrize("dt", [0.01, 0.1, 1.0])
def test_stays_on_surface_and_never_jumps(alps, dt):
    """20 s over the Alps: height equals the terrain under the vehicle (bound 1e-9 m) after
    every step, and no vehicle moves faster than its type allows (ECEF distance per step)."""
    g = _alps_fleet(alps)
    vmax = g.speed_limits_mps[1]
    p = _ecef(g)
    for _ in range(int(round(20.0 / dt))):
        g.step(dt)
        ground = alps.heights(g.lat, g.lon).height_msl_m
        assert np.abs(g.height_msl_m - ground).max() <= 1e-9
        q = _ecef(g)
        assert (np.linalg.norm(q - p, axis=1) <= vmax * dt * 1.001 + 1e-6).all()
        p = q
    assert np.isfinite(g.pitch_deg).all() and np.isfinite(g.roll_deg).all()


def test_dt_sweep_converges(alps):
    """Same commands at dt = 0.01, 0.1, 1 s: after 20 s the median vehicle is within 5 cm of
    the dt = 0.01 s run and 95 % within 1 m. The rest differ by the slope-limited speed (it
    reads the previous sub-step's pitch) or by stopping at a side-slope limit in one run while
    passing its crest a hair below the limit in another -- a threshold, not a drift."""
    final = {}
    for dt in (0.01, 0.1, 1.0):
        g = _alps_fleet(alps)
        for _ in range(int(round(20.0 / dt))):
            g.step(dt)
        final[dt] = geodetic_to_ecef(g.lat, g.lon, 0.0)
    for dt in (0.1, 1.0):
        d = np.linalg.norm(final[dt] - final[0.01], axis=1)
        assert np.median(d) < 0.05, (dt, np.median(d))
        assert np.quantile(d, 0.95) < 1.0, (dt, np.quantile(d, 0.95))


def test_pitch_and_roll_from_the_wheel_base(alps):
    """Pitch and roll are atan of the front-rear and left-right height differences of the
    terrain at the contact points (checked against an independent query, 1e-9 m)."""
    g = _alps_fleet(alps, n=40)
    for _ in range(10):
        g.step(0.1)
    lengths = np.array([VEHICLE_TYPES[t].contact_length_m for t in (TYPES4 * 10)])
    m_per_deg_lat = 111_200.0  # at 47 N, enough for an independent placement to 1e-3 m
    psi = np.radians(g.heading_deg)
    dlat = 0.5 * lengths * np.cos(psi) / m_per_deg_lat
    dlon = 0.5 * lengths * np.sin(psi) / (m_per_deg_lat * np.cos(np.radians(g.lat)))
    hf = alps.heights(g.lat + dlat, g.lon + dlon).height_msl_m
    hr = alps.heights(g.lat - dlat, g.lon - dlon).height_msl_m
    # 111.2 km/deg is approximate: the contacts differ by < 1e-2 m, so the gradient by < 0.01.
    np.testing.assert_allclose(np.tan(np.radians(g.pitch_deg)), (hf - hr) / lengths, atol=0.01)
    assert np.abs(g.pitch_deg).max() > 1.0  # the Alps are not flat: the check has teeth


def test_snapshot_rows_are_the_state_in_ecef(alps):
    """GroundVehicles.snapshot_rows (one compiled pass) against the numpy compositions it
    replaced in the world's snapshot: same positions, velocities (along the ground, pitch
    included) and ECEF -> body quaternions to rounding, on rows in any order."""
    from fdm.state import euler_to_quaternion, ned_to_ecef_vectors
    from server.dead_reckoning import ned_to_ecef_quat

    g = _alps_fleet(alps, n=40)
    for _ in range(10):
        g.step(0.1)
    idx = np.random.default_rng(2).permutation(g.n)[:30]
    und = 47.3
    ecef, vel, quat, rates, lat, lon, h = g.snapshot_rows(idx, und)
    assert np.array_equal(lat, g.lat[idx]) and np.array_equal(lon, g.lon[idx])
    assert np.array_equal(h, g.height_msl_m[idx])
    np.testing.assert_allclose(ecef, geodetic_to_ecef(lat, lon, h + und), rtol=0, atol=1e-8)
    np.testing.assert_allclose(vel, ned_to_ecef_vectors(g.velocity_ned()[idx], lat, lon), rtol=0, atol=1e-12)
    q_ned = euler_to_quaternion(np.radians(g.roll_deg[idx]), np.radians(g.pitch_deg[idx]),
                                np.radians(g.heading_deg[idx]))
    np.testing.assert_allclose(quat, ned_to_ecef_quat(q_ned, lat, lon), rtol=0, atol=1e-12)
    np.testing.assert_array_equal(rates[:, :2], 0.0)
    np.testing.assert_allclose(rates[:, 2], np.radians(g.yaw_rate_dps[idx]), rtol=1e-15)
    assert np.abs(g.pitch_deg[idx]).max() > 1.0 and np.abs(vel).max() > 1.0  # not a flat, standing fleet


# --- cliffs, shores, slopes --------------------------------------------------------------------

def _cliff(top=140.0, foot=100.0):
    """Flat foot to the south, a 40 m step between rows 100 and 101 (gradient 7), flat top north."""
    h = np.full((200, 80), foot)
    h[101:] = top
    return _grid(h), 47.0 + 100 * 0.00005, 47.0 + 101 * 0.00005


@pytest.mark.parametrize("dt", [0.05, 1.0])
def test_cliff_stops_the_vehicle_at_its_foot(dt):
    """Driving north into a 40 m cliff at full speed: the vehicle stops (speed 0, blocked by
    slope) with its centre before the foot and its height on the foot's flat (100 m exactly):
    no teleport onto the top, at any step size."""
    ter, foot_lat, _ = _cliff()
    g = GroundVehicles(ter, [47.0 + 40 * 0.00005], [9.002], [0.0], "m1a2")
    g.set_controls([M1A2_ABRAMS.max_speed_mps], [0.0])
    prev = g.lat.copy()
    for _ in range(int(round(30.0 / dt))):
        g.step(dt)
        assert g.lat[0] >= prev[0]  # never thrown back either
        prev = g.lat.copy()
        assert g.height_msl_m[0] == 100.0
    assert g.blocked[0] == BLOCKED_SLOPE and g.speed_mps[0] == 0.0
    assert g.lat[0] < foot_lat
    # Stopped within half a contact length (plus one post) of the foot.
    assert (foot_lat - g.lat[0]) * 111_200.0 < 0.5 * M1A2_ABRAMS.contact_length_m + 5.6


@pytest.mark.parametrize("dt", [0.05, 1.0])
def test_cliff_edge_stops_the_vehicle_on_top(dt):
    """Driving south off the same cliff: it stops at the edge, centre on the top (140 m)."""
    ter, _, top_lat = _cliff()
    g = GroundVehicles(ter, [47.0 + 160 * 0.00005], [9.002], [180.0], "hmmwv")
    g.set_controls([HMMWV.max_speed_mps], [0.0])
    for _ in range(int(round(30.0 / dt))):
        g.step(dt)
        assert g.height_msl_m[0] == 140.0
    assert g.blocked[0] == BLOCKED_SLOPE and g.speed_mps[0] == 0.0 and g.lat[0] > top_lat


@pytest.mark.parametrize("dt", [0.05, 1.0])
def test_sea_coast_stops_the_vehicle_on_land(kattegat, dt):
    """Kattegat coast, driving west towards the sea (heights 0 m): stopped on land, every
    contact point above sea level, reason WATER."""
    lat = 57.0 + 650 / 1200  # row 650: the sea ends at column 1098
    lon = 11.0 + 1110 / 1200
    g = GroundVehicles(kattegat, [lat], [lon], [270.0], "hmmwv")
    g.set_controls([15.0], [0.0])
    for _ in range(int(round(120.0 / dt))):
        g.step(dt)
        assert g.height_msl_m[0] > 0.0
    assert g.blocked[0] == BLOCKED_WATER and g.speed_mps[0] == 0.0
    assert 11.0 + 1098 / 1200 < g.lon[0] < lon
    # The front contact, half the 3.3 m wheelbase ahead (west), is still on land.
    front_lon = g.lon[0] - math.degrees(0.5 * HMMWV.contact_length_m / (6_390_000.0 * math.cos(math.radians(lat))))
    assert kattegat.heights([g.lat[0]], [front_lon]).height_msl_m[0] > 0.0


def test_placing_a_vehicle_in_the_sea_names_it(kattegat):
    with pytest.raises(InvalidArgument) as info:
        GroundVehicles(kattegat, [57.8, 57.2], [11.95, 11.2], [0.0, 0.0], "hmmwv")
    assert info.value.field == "lat" and info.value.index == 1 and "water" in str(info.value)


def _ramp(gradient, rows=400):
    """A plane rising northwards at `gradient` (rise per metre), from 10 m."""
    d = 0.00005
    m_per_post = math.radians(d) * 6_367_000.0  # meridian radius near 47 N, ~0.1 % exact
    h = 10.0 + gradient * m_per_post * np.arange(rows)[:, None] * np.ones((1, 60))
    return _grid(h, d=d)


def test_uphill_speed_is_power_limited():
    """On a 30 % ramp an M1A2 asked for full speed settles at eta P / (m g (f_r cos + sin)),
    within 1 %; on the flat it reaches its maximum."""
    g = GroundVehicles(_ramp(0.30), [47.0 + 20 * 0.00005], [9.0015], [0.0], "m1a2")
    g.set_controls([M1A2_ABRAMS.max_speed_mps], [0.0])
    for _ in range(100):
        g.step(0.1)
    t = M1A2_ABRAMS
    th = math.atan(0.30)
    expect = t.drivetrain_efficiency * t.power_w / (t.mass_kg * G_MPS2 * (t.rolling_resistance * math.cos(th)
                                                                           + math.sin(th)))
    assert expect < t.max_speed_mps
    assert g.speed_mps[0] == pytest.approx(expect, rel=0.01)
    assert math.tan(math.radians(g.pitch_deg[0])) == pytest.approx(0.30, abs=0.005)
    flat = GroundVehicles(_ramp(0.0), [47.001], [9.0015], [0.0], "m1a2")
    flat.set_controls([t.max_speed_mps], [0.0])
    for _ in range(300):
        flat.step(0.1)
    assert flat.speed_mps[0] == pytest.approx(t.max_speed_mps, rel=1e-9)


def test_too_steep_to_climb():
    """A 60 % limit: a flat approach to an 80 % ramp stops at its foot; a 50 % ramp is climbed."""
    d = 0.00005
    m_per_post = math.radians(d) * 6_367_000.0
    for grade, climbs in ((0.8, False), (0.5, True)):
        rise = np.maximum(np.arange(300) - 100, 0) * m_per_post * grade
        ter = _grid(10.0 + rise[:, None] * np.ones((1, 60)))
        g = GroundVehicles(ter, [47.0 + 80 * d], [9.0015], [0.0], "hmmwv")
        g.set_controls([10.0], [0.0])
        for _ in range(400):
            g.step(0.1)
        if climbs:  # ~110 m of flat, then ~27 s at the power-limited 5.4 m/s: 70 m up
            assert g.height_msl_m[0] > 50.0 and g.blocked[0] == FREE
        else:
            assert g.height_msl_m[0] < 10.0 + 0.6 * 4.0 and g.blocked[0] == BLOCKED_SLOPE


def test_side_slope_limit_stops_a_turn():
    """Turning across a 50 % slope: an HMMWV (side slope 40 %) stops once the slope across it
    would exceed 40 %, its roll still within the limit."""
    g = GroundVehicles(_ramp(0.5), [47.0 + 50 * 0.00005], [9.0015], [0.0], "hmmwv")
    g.set_controls([3.0], [15.0])
    for _ in range(200):
        g.step(0.05)
    assert g.blocked[0] == BLOCKED_SIDE_SLOPE
    assert abs(math.tan(math.radians(g.roll_deg[0]))) <= HMMWV.max_side_slope + 1e-12
    assert 40.0 < g.heading_deg[0] < 60.0  # 0.5 sin(heading) reaches 0.4 at 53 degrees


# --- steering ------------------------------------------------------------------------------------

def test_tracked_pivots_wheeled_does_not():
    ter = _ramp(0.0)
    g = GroundVehicles(ter, [47.005, 47.005], [9.001, 9.002], [0.0, 0.0], ["m1a2", "hmmwv"])
    g.set_controls([0.0, 0.0], [20.0, 20.0])
    p = _ecef(g)
    for _ in range(20):
        g.step(0.1)
    assert g.heading_deg[0] == pytest.approx(40.0, abs=1e-6)
    assert g.heading_deg[1] == 0.0
    assert np.linalg.norm(_ecef(g) - p, axis=1).max() < 1e-6


def test_turn_radius_and_lateral_acceleration_limits():
    """Full turn commands: an HMMWV at 3 m/s circles at its 7.6 m minimum radius; at 15 m/s its
    heading rate is held to a_lat / v. Radius from heading rate: v / r."""
    ter = _ramp(0.0, rows=1000)
    g = GroundVehicles(ter, [47.02, 47.02], [9.0012, 9.0025], [0.0, 0.0], "hmmwv")
    lim = g.yaw_rate_limit_dps
    g.set_controls([3.0, 15.0], lim)
    for _ in range(100):
        g.step(0.1)
    r = np.radians(g.yaw_rate_dps)
    assert g.speed_mps[0] / r[0] == pytest.approx(HMMWV.min_turn_radius_m, rel=1e-9)
    assert g.speed_mps[1] * r[1] == pytest.approx(HMMWV.max_lat_accel_mps2, rel=1e-9)


# --- seams and poles ---------------------------------------------------------------------------

def test_antimeridian_crossing_is_continuous():
    """A raster straddling 180 E; a vehicle driving east across it at 60 N. Every step moves
    v dt (to 1 mm), longitude stays in [-180, 180) and flips sign once."""
    h = np.full((40, 200), 50.0)
    ter = _grid(h, lat0=59.999, lon0=179.995, d=0.00005)
    g = GroundVehicles(ter, [60.0], [179.9993], [90.0], "hmmwv")  # 39 m west of 180
    g.set_controls([10.0], [0.0])
    for _ in range(30):  # reach 10 m/s
        g.step(0.2)
    p = _ecef(g)
    lons = []
    for _ in range(20):
        g.step(0.1)
        q = _ecef(g)
        assert np.linalg.norm(q - p) == pytest.approx(1.0, abs=1e-3)
        p = q
        lons.append(g.lon[0])
        assert -180.0 <= g.lon[0] < 180.0
    assert lons[0] > 0 > lons[-1] and g.blocked[0] == FREE


def test_driving_over_the_pole():
    """A flat cap over the north pole (lat >= 89.99, every longitude); a tank drives north
    across the pole: continuous (each 1 m step moves 1 m, to 1 mm), finite, and heading south
    afterwards on the opposite meridian."""
    nx = 361
    ter = Terrain([Raster(np.full((21, nx), 20.0, np.float32),
                          Georef(CRS_GEOGRAPHIC, -180.0, 89.99, 1.0, 0.0005))])
    g = GroundVehicles(ter, [89.9997], [10.0], [0.0], "m1a2")
    g.set_controls([10.0], [0.0])
    for _ in range(50):
        g.step(0.2)
    p = _ecef(g)
    assert g.speed_mps[0] == pytest.approx(10.0)
    for _ in range(100):
        g.step(0.1)
        q = _ecef(g)
        assert np.linalg.norm(q - p) == pytest.approx(1.0, abs=1e-3)
        p = q
        assert np.isfinite(g.lat).all() and g.lat[0] <= 90.0
    assert g.heading_deg[0] == pytest.approx(180.0, abs=0.01)
    assert abs(((g.lon[0] - 190.0 + 180.0) % 360.0) - 180.0) < 1e-6


# --- determinism, controls, level of detail ----------------------------------------------------

def test_bit_identical_reruns(alps):
    runs = []
    for _ in range(2):
        g = _alps_fleet(alps, n=100)
        for k in range(60):
            if k == 30:
                g.set_controls(np.linspace(-2, 10, 100), np.linspace(-10, 10, 100))
            g.step(0.1 if k % 2 else 0.25)
        runs.append(g.state())
    for name in runs[0].__dataclass_fields__:
        assert np.array_equal(getattr(runs[0], name), getattr(runs[1], name)), name


def test_controls_are_validated_before_any_is_applied(alps):
    g = _alps_fleet(alps, n=8)
    before = (g.speed_cmd_mps.copy(), g.yaw_rate_cmd_dps.copy())
    bad_speed = np.full(8, 5.0)
    bad_speed[3] = np.nan
    for kwargs, field, index in (
        (dict(speed_mps=bad_speed, yaw_rate_dps=np.zeros(8)), "speed_mps", 3),
        (dict(speed_mps=np.full(8, 5.0), yaw_rate_dps=[0, 0, 0, 0, 0, np.inf, 0, 0]), "yaw_rate_dps", 5),
        (dict(speed_mps=[5, 5, 50, 5, 5, 5, 5, 5]), "speed_mps", 2),  # above every type's maximum
        (dict(speed_mps=[5, -40, 5, 5, 5, 5, 5, 5]), "speed_mps", 1),  # beyond reverse
        (dict(yaw_rate_dps=[0, 0, 0, 0, 0, 0, 0, 500.0]), "yaw_rate_dps", 7),
        (dict(speed_mps=[1.0, 2.0], index=[0, 8]), "index", 1),
        (dict(speed_mps=[1.0, 2.0, 3.0]), "speed_mps", None),  # wrong length
    ):
        with pytest.raises(InvalidArgument) as info:
            g.set_controls(**kwargs)
        assert info.value.field == field and info.value.index == index, kwargs
        assert np.array_equal(g.speed_cmd_mps, before[0]) and np.array_equal(g.yaw_rate_cmd_dps, before[1])
    for dt in (0.0, -1.0, np.nan, np.inf, 1e6):
        with pytest.raises(InvalidArgument):
            g.step(dt)
    g.set_controls([7.0], [1.0], index=[2])
    assert g.speed_cmd_mps[2] == 7.0 and g.yaw_rate_cmd_dps[2] == 1.0


def test_far_vehicles_step_less_often_and_catch_up(alps):
    """An observer at one end: vehicles within 2 km step every tick, those past 8 km every 8th;
    all stay on the surface, and after sync() a far vehicle on gentle ground stands within 1 m
    of where full-rate stepping puts it."""
    n = 60
    lat = np.full(n, 47.25)
    lon = np.linspace(9.52, 9.64, n)  # Rhine valley floor, ~9 km west to east
    # Heading north-north-east up the valley, gentle speed.
    full = GroundVehicles(alps, lat, lon, np.full(n, 20.0), "hmmwv")
    lod = GroundVehicles(alps, lat, lon, np.full(n, 20.0), "hmmwv")
    for g in (full, lod):
        g.set_controls(np.full(n, 6.0), np.zeros(n))
    lod.set_observers([47.25], [9.52], near_m=2000.0, max_divisor=8)
    for _ in range(160):
        full.step(0.05)
        lod.step(0.05)
        ground = alps.heights(lod.lat, lod.lon).height_msl_m
        assert np.abs(lod.height_msl_m - ground).max() <= 1e-9
    assert lod.divisor[0] == 1 and lod.divisor[-1] == 8
    assert lod.vehicle_steps < 0.6 * full.vehicle_steps
    lod.sync()
    assert (lod.last_time_s == lod.time_s).all()
    d = np.linalg.norm(geodetic_to_ecef(lod.lat, lod.lon, 0) - geodetic_to_ecef(full.lat, full.lon, 0), axis=1)
    ok = (full.blocked == FREE) & (lod.blocked == FREE)
    assert ok.sum() > n // 2
    assert d[ok].max() < 1.0
    assert np.array_equal(d[:5], np.zeros(5))  # the near ones are stepped identically


def test_same_trajectory_over_the_grpc_terrain_service(alps):
    """The model over the real terrain service (loopback gRPC) matches the in-process run bit
    for bit: the wire carries float64 heights exactly."""
    from client.terrain_client import TerrainClient
    from server.terrain_service import create_server

    server, port = create_server(alps, "127.0.0.1:0", max_workers=2)
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}", timeout_s=20.0) as client:
            runs = []
            for ter in (alps, client):
                g = _alps_fleet(ter, n=50)
                for _ in range(20):
                    g.step(0.1)
                runs.append(g.state())
    finally:
        server.stop(0).wait()
    for name in runs[0].__dataclass_fields__:
        assert np.array_equal(getattr(runs[0], name), getattr(runs[1], name)), name


def test_adding_and_removing_vehicles_mid_run(alps, kattegat):
    # Vehicles do not interact, so the survivors of a fleet that grows and shrinks
    # drive exactly the trajectories they drive in a fleet that never changes, and
    # vehicles added mid-run those of a fleet started at that moment.
    ref = _alps_fleet(alps, n=40)
    g = _alps_fleet(alps, n=40)
    rng = np.random.default_rng(5)
    lat, lon, hdg = rng.uniform(47.2, 47.8, 6), rng.uniform(9.2, 9.8, 6), rng.uniform(0, 360, 6)
    for _ in range(10):
        ref.step(0.1)
        g.step(0.1)
    # A type the fleet does not have yet: a slower HMMWV variant.
    slow = dataclasses.replace(HMMWV, name="hmmwv-slow", max_speed_mps=8.0)
    late = GroundVehicles(alps, lat, lon, hdg, slow)
    new_ids = g.add(lat, lon, hdg, slow)
    assert len(g.types) == 5 and g.speed_limits_mps[1][-1] == 8.0
    assert list(new_ids) == list(range(40, 46)) and g.n == 46
    g.remove([3, 17, 41])
    assert g.n == 43 and list(g.index_of([40, 42, 45])) == [38, 39, 42]
    late.set_controls(7.0, 2.0)
    late_keep = np.array([0, 2, 3, 4, 5])
    g.set_controls(7.0, 2.0, index=g.index_of(new_ids[late_keep]))
    for _ in range(20):
        ref.step(0.1)
        g.step(0.1)
        late.step(0.1)
    survivors = g.index_of([i for i in range(40) if i not in (3, 17)])
    keep_ref = np.array([i for i in range(40) if i not in (3, 17)])
    for name in ("lat", "lon", "height_msl_m", "heading_deg", "speed_mps", "pitch_grad", "roll_grad"):
        assert np.array_equal(getattr(g, name)[survivors], getattr(ref, name)[keep_ref]), name
        assert np.array_equal(getattr(g, name)[g.index_of(new_ids[late_keep])], getattr(late, name)[late_keep]), name
    # Bad ids and bad placements change nothing.
    with pytest.raises(InvalidArgument) as e:
        g.remove([0, 3])
    assert e.value.field == "ids" and e.value.index == 1 and g.n == 43
    with pytest.raises(InvalidArgument):
        g.add([56.5], [11.5], [0.0])  # outside this terrain (the Kattegat is not in the Alps tile)
    assert g.n == 43
    sea = GroundVehicles(kattegat, [57.8], [11.95], [0.0], "hmmwv")
    with pytest.raises(InvalidArgument, match="water"):
        sea.add([57.2], [11.2], [0.0], "hmmwv")
    assert sea.n == 1
    g.remove(g.ids)
    assert g.n == 0 and g.step(0.1) == 0


@pytest.mark.parametrize("lat0", [47.3, -71.0, 84.0])
def test_sub_step_contacts_match_exact_placement(alps, lat0):
    """A sub-step places its contact points from the move's own radii and a rotated
    heading (no sines and cosines of their own): they equal the exact placement at the
    proposed pose to well under a micrometre, on any heading and turn rate."""
    import fdm.ground as gm

    n = 400
    rng = np.random.default_rng(4)
    flat = _grid(np.full((5, 5), 300.0), lat0 - 0.5, 8.5, 0.25)
    g = GroundVehicles(flat, lat0 + rng.uniform(-0.2, 0.2, n), 9.0 + rng.uniform(-0.2, 0.2, n),
                       rng.uniform(0.0, 360.0, n), "hmmwv")
    g.set_controls(rng.uniform(-5.0, 29.0, n), rng.uniform(-1.0, 1.0, n) * g.yaw_rate_limit_dps)
    for _ in range(5):
        g.step(0.5)
    idx = np.arange(n, dtype=np.int64)
    sub_dt = np.full(n, 0.25)
    p = [np.zeros(n) for _ in range(6)]
    pts_lat, pts_lon = np.zeros(5 * n), np.zeros(5 * n)
    gm._propose_kernel(idx, sub_dt, g.lat, g.lon, g.heading_deg, g.speed_mps, g.pitch_grad, g.type_id,
                       g.speed_cmd_mps, g.yaw_rate_cmd_dps, g.table, *p, pts_lat, pts_lon)
    exact_lat, exact_lon = np.zeros(5 * n), np.zeros(5 * n)
    gm._place_kernel(p[0], p[1], np.degrees(p[2]), g.type_id, g.table, exact_lat, exact_lon)
    metres = np.radians(1.0) * 6.4e6
    assert np.abs(pts_lat - exact_lat).max() * metres < 1e-6
    assert np.abs(pts_lon - exact_lon).max() * metres * math.cos(math.radians(lat0)) < 1e-6


@pytest.mark.parametrize("gradient", [1.0, 3.0])
def test_a_vehicle_placed_on_a_face_too_steep_does_not_climb_it_but_can_drive_off(gradient):
    """Placed on a 100 % (45 deg) or 300 % (72 deg) face, full speed uphill: it stays put,
    blocked by the slope (it climbed 60-150 m in a minute before); reversing downhill, away
    from the face's steepness, it drives."""
    for type_ in ("m1a2", "hmmwv"):
        g = GroundVehicles(_ramp(gradient), [47.0 + 200 * 0.00005], [9.0015], [0.0], type_)
        h0 = g.height_msl_m[0]
        g.set_controls(g.speed_limits_mps[1], [0.0])
        for _ in range(100):
            g.step(0.1)
        assert g.height_msl_m[0] - h0 < 0.01 and g.blocked[0] == BLOCKED_SLOPE, type_
        g.set_controls(-g.speed_limits_mps[0], [0.0])  # reverse: downhill
        for _ in range(50):
            g.step(0.1)
        assert g.height_msl_m[0] < h0 - 1.0, type_
