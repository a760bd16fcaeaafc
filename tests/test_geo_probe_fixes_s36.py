"""The simulation's geography hard cases (acceptance probe, session 36): ground vehicles near a pole.

A ground vehicle's heading is from true north where it stands; near a pole two vehicles metres
apart have norths tens of degrees apart (the meridians' convergence: 11 m from the pole, 3.4 m
east is 18 degrees of longitude). The agent collision test (server/collisions.py) and the path
search (server/obstacles.py) took the other vehicle's heading as if it were from the first's
north: two Humvees side by side and parallel, 0.3 m apart, 11 m from the north pole were found
touching (0.17 m deep; 3.3 m from it, 0.88 m), and a convoy crossing the pole braked for the
vehicle ahead of it as for one met head-on once that one was past the pole, heading "south"
(12 m spacing at 10 m/s: the followers fell to 5.8 m/s and the gaps opened to 21 m). Now the
other's heading is carried onto the first's horizontal through ECEF. Oracle: GeographicLib
(Karney, "Algorithms for geodesics", J. Geodesy 87, 2013) places the vehicles and measures the
gaps.

Controls for entities at these places: World.command refused numpy's numbers with "must be a
finite number" (np.float32(100.0)), crashed with OverflowError on an integer beyond any float,
took a bool as a number, and took fields a command does not have without a word: a drive
command {"speed": 5} stopped the vehicle (what it does not give is 0). Now each is an
InvalidArgument naming the field, or taken as the float it is."""

from __future__ import annotations

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic

from fdm.aircraft import FlatTerrain, InitialConditions
from fdm.vehicle_types import VEHICLE_TYPES
from server.collisions import new_contacts, overlap_depth
from server.obstacles import clearance_ahead
from server.world import World
from sortie.errors import InvalidArgument
from terrain.geodesy import geodetic_to_ecef
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

WGS84 = Geodesic.WGS84
HMMWV = VEHICLE_TYPES["hmmwv"]
HALF_L, HALF_W = HMMWV.length_m / 2, HMMWV.width_m / 2
RADIUS = float(np.hypot(HALF_L, HALF_W))
# Depths are the boxes' geometry on the tangent plane: good to rounding, but the two vehicles'
# horizontals differ by the angle between their normals (3 m apart: 5e-7 rad), so 1 mm.
DEPTH_TOL_M = 1e-3


@pytest.fixture(scope="module")
def north_cap() -> Terrain:
    """Flat ground 20 m high over the north polar cap (89 to 90 N), every longitude."""
    d = 0.05
    return Terrain([Raster(np.full((21, 7201), 20.0, np.float32), Georef(CRS_GEOGRAPHIC, -180.0, 89.0, d, d))])


def _side_by_side(lat, lon, centres_m):
    """Vehicle i at (lat, lon) heading north, vehicle j ``centres_m`` to its right, parallel to
    it (the geodesic's azimuth at j less 90 degrees: the direction i's heading has there);
    (ECEF (2, 3), lat (2,), lon (2,), heading (2,))."""
    g = WGS84.Direct(lat, lon, 90.0, centres_m)
    la, lo, hd = np.array([lat, g["lat2"]]), np.array([lon, g["lon2"]]), np.array([0.0, (g["azi2"] - 90.0) % 360.0])
    return geodetic_to_ecef(la, lo, np.zeros(2)), la, lo, hd


@pytest.mark.parametrize("lat", [60.0, 89.99, 89.9999, 89.99997])
@pytest.mark.parametrize("gap_m", [0.3, -0.2])
def test_boxes_side_by_side_near_a_pole_touch_as_they_do_anywhere(lat, gap_m):
    """Two Humvees side by side and parallel, ``gap_m`` apart (negative: overlapping), at 60 N
    and 1.1 km, 11 m and 3.3 m from the north pole (where j's north is 0.1, 12 and 36 degrees
    off i's): overlap_depth is -gap_m to DEPTH_TOL_M, and the collision test finds them in
    contact (an ongoing one) exactly when they overlap. Before, 0.3 m apart 11 m from the pole
    they were 0.17 m deep, and touching."""
    p, la, lo, hd = _side_by_side(lat, 0.0, 2 * HALF_W + gap_m)
    depth = overlap_depth((p[1] - p[0])[None], la[:1], lo[:1], hd[:1], hd[1:], HALF_L, HALF_W, HALF_L, HALF_W,
                          RADIUS, RADIUS, la[1:], lo[1:])
    assert depth[0] == pytest.approx(-gap_m, abs=DEPTH_TOL_M)
    i, j, t, _ = new_contacts(p, p, RADIUS, heading_deg=hd, half_length_m=HALF_L, half_width_m=HALF_W,
                              lat_deg=la, lon_deg=lo, ongoing=True)
    assert (i.size == 1) == (gap_m < 0), (i, j, t)


def test_a_column_member_past_the_pole_is_not_in_its_followers_path():
    """A convoy's leader 6 m past the north pole (heading 180 from its own north: going on the
    way its follower goes), its follower 6 m short of it (heading 0): the follower's path search
    ignores it as the column's, as anywhere else. Before, it was "met head-on": in the path,
    4.9 m clear."""
    lat0 = 90.0 - 6.0 / 111_694.0  # 6 m from the pole (the meridian's metres per degree there)
    p = geodetic_to_ecef(np.array([lat0, lat0]), np.array([180.0, 0.0]), np.zeros(2))
    clear, row, _, _, _ = clearance_ahead(p, [lat0, lat0], [180.0, 0.0], [180.0, 0.0], RADIUS, HALF_L, HALF_W,
                                          np.array([0, 0]), [1], [50.0], place=np.array([0, 1]))
    assert row[0] == -1 and clear[0] == np.inf
    # Out of its column it is what it is: a vehicle 12 m ahead, 7.3 m clear of its front.
    clear, row, _, _, _ = clearance_ahead(p, [lat0, lat0], [180.0, 0.0], [180.0, 0.0], RADIUS, HALF_L, HALF_W,
                                          np.array([-1, -1]), [1], [50.0])
    assert row[0] == 0 and clear[0] == pytest.approx(12.0 - 2 * HALF_L, abs=0.01)


def test_a_convoy_crosses_the_pole_at_its_spacing(north_cap):
    """Four Humvees 12 m apart at 10 m/s on a route over the north pole (from 111 m short of
    it to 111 m past, on the opposite meridian), all crossing it within the 12 s watched: every
    gap stays 12 m to 0.05 m and every speed 10 m/s to 0.05 m/s, as on any straight road.
    Before, each follower braked for the one ahead once that one was past the pole (to
    5.8 m/s) and the gaps opened to 21 m."""
    world = World(north_cap)
    try:
        starts = [WGS84.Direct(90.0, 0.0, 180.0, 50.0 + 12.0 * k)["lat2"] for k in range(4)]
        column = world.spawn_ground([f"c{k}" for k in range(4)], "hmmwv", starts, [0.0] * 4, [0.0] * 4,
                                    route=[(89.999, 0.0), (89.999, 180.0)], cruise_mps=10.0, spacing_m=12.0,
                                    speed_mps=10.0)
        rows = world.ground.index_of([e.ground_id for e in column])
        gaps, speeds = [], []
        for _ in range(30 * 12):
            world.tick()
            lat, lon = world.ground.lat[rows], world.ground.lon[rows]
            gaps.append([WGS84.Inverse(lat[k], lon[k], lat[k + 1], lon[k + 1])["s12"] for k in range(3)])
            speeds.append(world.ground.speed_mps[rows].copy())
        assert np.abs(np.array(gaps) - 12.0).max() < 0.05
        assert np.abs(np.array(speeds) - 10.0).max() < 0.05
        # All four are past the pole, on the route's far meridian.
        assert np.all(np.abs(np.abs(world.ground.lon[rows]) - 180.0) < 1e-6)
        assert not [e for e in world.events if e.kind in ("collision", "blocked")]
    finally:
        world.close()


@pytest.fixture(scope="module")
def far_world():
    """An f16 and a Humvee, both controllable, on the antimeridian at 60 N and 11 m from the
    north pole."""
    world = World(FlatTerrain(10.0))
    jet = world.spawn_aircraft("jet", "f16", InitialConditions(60.0, 180.0, 3000.0, heading_deg=0.0,
                                                                speed_mps=200.0), controllable=True)
    car, = world.spawn_ground(["car"], "hmmwv", [89.9999], [-180.0], [10.0], controllable=True)
    yield world, jet, car
    world.close()


@pytest.mark.parametrize("who, kind, values, message", [
    ("car", "drive", {"speed": 5.0}, "drive.speed: unknown field; known: speed_mps, yaw_rate_dps (got 5.0)"),
    ("jet", "autopilot", {"heading": 90.0},
     "autopilot.heading: unknown field; known: heading_deg, alt_msl_m, speed_mps (got 90.0)"),
    ("car", "drive", {"speed_mps": True}, "drive.speed_mps: must be a finite number (got True)"),
    ("jet", "autopilot", {"heading_deg": True}, "autopilot.heading_deg: must be a finite number (got True)"),
    ("car", "drive", {"speed_mps": 10 ** 400},
     "drive.speed_mps: must be a finite number (an integer beyond any float)"),
    ("jet", "autopilot", {"speed_mps": -10 ** 400},
     "autopilot.speed_mps: must be a finite number (an integer beyond any float)"),
    ("car", "drive", {"yaw_rate_dps": np.float32("nan")}, "drive.yaw_rate_dps: must be a finite number (got nan)"),
])
def test_bad_command_values_are_refused_naming_the_field(far_world, who, kind, values, message):
    world, jet, car = far_world
    with pytest.raises(InvalidArgument) as exc:
        world.command((jet if who == "jet" else car).id, kind, values)
    assert str(exc.value) == message


def test_numpy_numbers_are_commands_like_floats(far_world):
    """np.float32 / np.int64 targets are taken (as floats: the recording's journal is JSON):
    the Humvee near the pole is driven at 3 m/s and then held at 4 m/s on 090, the jet on the
    antimeridian holds 150 m/s."""
    world, jet, car = far_world
    world.command(car.id, "drive", {"speed_mps": np.int64(3), "yaw_rate_dps": np.float32(0.0)})
    world.tick()
    i = world.ground.index_of([car.ground_id])[0]
    assert world.ground.speed_cmd_mps[i] == 3.0
    world.command(car.id, "autopilot", {"heading_deg": np.float32(90.0), "speed_mps": np.float64(4.0)})
    world.command(jet.id, "autopilot", {"speed_mps": np.float32(150.0)})
    world.tick()
    assert world._ground_heading_hold[car.id] == {"heading_deg": 90.0, "speed_mps": 4.0}
    assert all(type(v) is float for v in world._ground_heading_hold[car.id].values())
