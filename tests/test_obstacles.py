"""Autopilot drivers brake for what is in their path (server/obstacles.py, fdm.convoy's
obstacle ceiling, World._obstacle_ceiling): the compiled search against a brute-force
reference, and route followers in a world stopping short of a site, queueing behind a slower
vehicle, passing one parked beside the road, with no collision."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdm.aircraft import FlatTerrain
from fdm.convoy import OBSTACLE_STANDOFF_M, PASS_MAX_OFFSET_M
from fdm.vehicle_types import VEHICLE_TYPES
from server.obstacles import PATH_MARGIN_M, clearance_ahead
from server.world import STATIC_RADIUS_M, World
from terrain.geodesy import enu_basis, geodetic_to_ecef
from tests.test_collisions import _east_m, _run

LAT0, LON0 = 47.0, 9.0
M_PER_DEG_LON = 111_200.0 * math.cos(math.radians(LAT0))


def _reference(p, lat, lon, heading, radius, half_l, half_w, group, rows, reach):
    """Every entity against every asking vehicle, in numpy, by the module docstring's rules."""
    clear, across_of, need = np.full(rows.size, np.inf), np.full(rows.size, np.nan), np.full(rows.size, np.nan)
    for k, i in enumerate(rows):
        e, n, u = (b for b in enu_basis(lat[i], lon[i]))
        fwd = np.sin(np.radians(heading[i])) * e + np.cos(np.radians(heading[i])) * n
        right = np.cos(np.radians(heading[i])) * e - np.sin(np.radians(heading[i])) * n
        for j in range(p.shape[0]):
            # j's heading is from its own north: compared on i's horizontal through ECEF.
            ej, nj, _ = enu_basis(lat[j], lon[j])
            fwd_j = np.sin(np.radians(heading[j])) * ej + np.cos(np.radians(heading[j])) * nj
            if j == i or (group[i] >= 0 and group[j] == group[i] and fwd @ fwd_j > 0):
                continue
            d = p[j] - p[i]
            if abs(d @ u) > radius[i] + radius[j]:
                continue
            ahead, across = d @ fwd, d @ right
            if half_l[j] > 0:
                rel = np.arctan2(fwd_j @ right, fwd_j @ fwd)
                ext_along = half_l[j] * abs(np.cos(rel)) + half_w[j] * abs(np.sin(rel))
                ext_across = half_l[j] * abs(np.sin(rel)) + half_w[j] * abs(np.cos(rel))
            else:
                ext_along, ext_across = radius[j] + radius[i] - half_l[i], radius[j] + radius[i] - half_w[i]
            c = ahead - half_l[i] - ext_along
            if abs(across) <= half_w[i] + ext_across + PATH_MARGIN_M and ahead >= half_l[i] and c <= reach[k]:
                if c < clear[k]:
                    clear[k], across_of[k], need[k] = c, across, half_w[i] + ext_across
    return clear, across_of, need


@pytest.mark.parametrize("seed", range(4))
def test_clearance_matches_a_brute_force_reference(seed):
    """300 entities (boxes of the catalog's types and spheres) in a 400 m square, some in
    groups; 80 of them ask. Equal to the reference to rounding."""
    rng = np.random.default_rng(seed)
    n = 300
    lat = LAT0 + rng.uniform(0, 400, n) / 111_200.0
    lon = LON0 + rng.uniform(0, 400, n) / M_PER_DEG_LON
    h = 400.0 + rng.uniform(0, 3, n)
    h[:10] += rng.uniform(5, 200, 10)  # a few above the others: aircraft overhead
    p = geodetic_to_ecef(lat, lon, h)
    heading = rng.uniform(0, 360, n)
    types = list(VEHICLE_TYPES.values())
    box = rng.random(n) < 0.8
    half_l = np.where(box, [types[k % len(types)].length_m / 2 for k in range(n)], 0.0)
    half_w = np.where(box, [types[k % len(types)].width_m / 2 for k in range(n)], 0.0)
    radius = np.where(box, np.hypot(half_l, half_w), rng.uniform(3, 12, n))
    group = np.where(rng.random(n) < 0.3, rng.integers(0, 5, n), -1)
    rows = np.flatnonzero(box)[:80]
    reach = rng.uniform(10, 120, rows.size)
    clear, row, across, need, _ = clearance_ahead(p, lat, lon, heading, radius, half_l, half_w, group, rows, reach)
    ref, ref_across, ref_need = _reference(p, lat, lon, heading, radius, half_l, half_w, group, rows, reach)
    np.testing.assert_allclose(clear, ref, atol=1e-6)
    np.testing.assert_allclose(across, ref_across, atol=1e-6)
    np.testing.assert_allclose(need, ref_need, atol=1e-9)
    assert np.isfinite(ref).sum() > 10  # the scene has obstacles in many paths
    assert (row[np.isfinite(clear)] >= 0).all() and (row[~np.isfinite(clear)] == -1).all()


def _route_east(m_from, m_to, lat=LAT0):
    return [(lat, LON0 + m_from / M_PER_DEG_LON), (lat, LON0 + m_to / M_PER_DEG_LON)]



def test_a_vehicle_holding_its_heading_stops_short_of_a_site():
    """A Humvee on autopilot (heading 090, 12 m/s) towards a radar site stops OBSTACLE_STANDOFF_M
    (within a metre) short of it, with no collision; before, it drove into it."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_static("site", "radar", LAT0, LON0 + 200.0 / M_PER_DEG_LON, 400.0)
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], controllable=True)
        world.command(car.id, "autopilot", {"heading_deg": 90.0, "speed_mps": 12.0})
        events = _run(world, 900)  # 30 s
        assert not [e for e in events if e.kind == "collision"]
        front = _east_m(world, car) + VEHICLE_TYPES["hmmwv"].length_m / 2
        clear = 200.0 - STATIC_RADIUS_M - front
        assert OBSTACLE_STANDOFF_M - 1.0 < clear < OBSTACLE_STANDOFF_M + 1.0, clear
        assert world.ground.speed_mps[world.ground.index_of([car.ground_id])][0] == pytest.approx(0.0, abs=0.05)
    finally:
        world.close()


def _north_m(world, e):
    return (world.ground.lat[world.ground.index_of([e.ground_id])][0] - LAT0) * 111_200.0


def test_a_route_follower_drives_around_a_site_on_its_route():
    """A Humvee at 12 m/s on a route through a radar site drives around it with no collision
    (before, it drove into it), no farther off its route than the pass needs and PASS_MAX_OFFSET_M,
    and is back on its route 150 m past it."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_static("site", "radar", LAT0, LON0 + 200.0 / M_PER_DEG_LON, 400.0)
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 800),
                                  cruise_mps=12.0)
        events, off = [], []
        for _ in range(1200):  # 40 s
            events += world.tick()
            off.append(_north_m(world, car))
            if _east_m(world, car) > 350.0:
                break
        assert not [e for e in events if e.kind == "collision"]
        assert _east_m(world, car) > 350.0
        need = VEHICLE_TYPES["hmmwv"].width_m / 2 + STATIC_RADIUS_M
        assert need < max(np.abs(off)) <= PASS_MAX_OFFSET_M + 1.0
        assert abs(off[-1]) < 1.0
    finally:
        world.close()


def test_two_vehicles_meeting_head_on_keep_right_and_pass():
    """Two trucks driving one road from opposite ends at 10 m/s: each keeps right, they pass
    with no collision and both reach the far end (before: they met head-on and stopped)."""
    world = World(FlatTerrain(400.0))
    try:
        west, = world.spawn_ground(["west"], "m1083", [LAT0], [LON0], [90.0], route=_route_east(0, 600),
                                   cruise_mps=10.0)
        east, = world.spawn_ground(["east"], "m1083", [LAT0], [LON0 + 600.0 / M_PER_DEG_LON], [270.0],
                                   route=_route_east(600, 0), cruise_mps=10.0)
        events, abreast = [], None
        for _ in range(2700):  # 90 s
            events += world.tick()
            if abreast is None and _east_m(world, west) > _east_m(world, east):
                abreast = (_north_m(world, west), _north_m(world, east))
        assert not [e for e in events if e.kind == "collision"]
        assert abreast is not None and abreast[0] < -1.0 and abreast[1] > 1.0  # each on its right
        assert _east_m(world, west) > 590.0 and _east_m(world, east) < 10.0
    finally:
        world.close()


def test_a_faster_follower_queues_behind_a_slower_one():
    """Two route followers on one road, the one behind at 14 m/s and the one ahead at 5: it
    closes up, then follows at the slower one's speed, a standoff behind, and never hits it."""
    world = World(FlatTerrain(400.0))
    try:
        slow, = world.spawn_ground(["slow"], "m1083", [LAT0], [LON0 + 60.0 / M_PER_DEG_LON], [90.0],
                                   route=_route_east(60, 2000), cruise_mps=5.0)
        fast, = world.spawn_ground(["fast"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 2000),
                                   cruise_mps=14.0)
        events = _run(world, 1200)  # 40 s
        assert not [e for e in events if e.kind == "collision"]
        gap = (_east_m(world, slow) - VEHICLE_TYPES["m1083"].length_m / 2
               - _east_m(world, fast) - VEHICLE_TYPES["hmmwv"].length_m / 2)
        assert OBSTACLE_STANDOFF_M - 1.0 < gap < 25.0, gap
        idx = world.ground.index_of([slow.ground_id, fast.ground_id])
        assert world.ground.speed_mps[idx][1] == pytest.approx(5.0, abs=1.0)
        assert _east_m(world, fast) > 150.0  # it drove on behind the slow one, not stopped
    finally:
        world.close()


def test_a_vehicle_parked_beside_the_road_is_passed():
    """A truck parked 5 m to the side of the route (beyond the path's half width, 1.06 + 1.22 +
    0.75 m): the follower drives past it at cruise speed."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_ground(["parked"], "m1083", [LAT0 - 5.0 / 111_200.0], [LON0 + 100.0 / M_PER_DEG_LON], [90.0])
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 600),
                                  cruise_mps=10.0)
        events = _run(world, 600)  # 20 s
        assert not [e for e in events if e.kind == "collision"]
        assert _east_m(world, car) > 150.0
    finally:
        world.close()


def test_a_vehicle_the_terrain_stops_says_so_once():
    """A Humvee driven east towards the sea (a coast 100 m ahead) is stopped at the shore: one
    "blocked" event (reason water) where it stands, though its driver pushes on for 10 s; it
    backs off, drives free for 2 s and on to the shore again: a second event."""
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
    from terrain.terrain import Terrain

    d = 1.0 / 3600.0
    h = np.full((200, 400), 3.0, np.float32)
    h[:, 100:] = np.maximum(3.0 - 0.5 * np.arange(300), -2.0)  # a beach from the start east into the sea
    coast = Raster(h, Georef(CRS_GEOGRAPHIC, LON0 - 100 * d, LAT0 - 100 * d, d, d), name="coast")
    world = World(Terrain([coast]))
    try:
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], controllable=True)
        world.command(car.id, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 0.0})
        events = _run(world, 600)  # 20 s: the shore is about 100 m east
        blocked = [e for e in events if e.kind == "blocked"]
        assert len(blocked) == 1 and blocked[0].entity_id == car.id and blocked[0].detail["reason"] == "water"
        east_m = (world.ground.lon[world.ground.index_of([car.ground_id])][0] - blocked[0].lon_deg) * M_PER_DEG_LON
        assert 0.0 <= east_m < 1.0  # at the shore: pushing on, it creeps no more than its last sub-steps allow
        world.command(car.id, "drive", {"speed_mps": -4.0, "yaw_rate_dps": 0.0})
        _run(world, 90)
        world.command(car.id, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 0.0})
        events = _run(world, 300)
        assert [e.detail["reason"] for e in events if e.kind == "blocked"] == ["water"]
    finally:
        world.close()


def _route_xy(points):
    """A route through (east m, north m) points from (LAT0, LON0)."""
    return [(LAT0 + n / 111_200.0, LON0 + e / M_PER_DEG_LON) for e, n in points]


def _spawn_on(world, name, typ, points, cruise):
    (e0, n0), (e1, n1) = points[0], points[1]
    heading = math.degrees(math.atan2(e1 - e0, n1 - n0)) % 360.0
    return world.spawn_ground([name], typ, [LAT0 + n0 / 111_200.0], [LON0 + e0 / M_PER_DEG_LON], [heading],
                              route=_route_xy(points), cruise_mps=cruise)[0]


@pytest.mark.parametrize("corner_deg", [90.0, 45.0])
def test_two_vehicles_meeting_head_on_at_a_corner_get_past_each_other(corner_deg):
    """A Humvee and a truck on one route with a corner, from its two ends, meeting at the corner:
    no collision, and both reach the far end within 4 minutes (before: they met nose to nose at
    the corner, too close to steer round, and stood there for good; the one that backs off
    first lets them pass)."""
    a = math.radians(corner_deg)
    pts = [(0.0, 0.0), (500.0, 0.0), (500.0 + 500.0 * math.cos(a), -500.0 * math.sin(a))]
    world = World(FlatTerrain(400.0))
    try:
        car = _spawn_on(world, "car", "hmmwv", pts, 12.0)
        truck = _spawn_on(world, "truck", "m1083", pts[::-1], 12.0)
        events = _run(world, 30 * 240)
        assert not [e for e in events if e.kind == "collision"]
        g = world.ground
        end_car, end_truck = _route_xy(pts[-1:])[0], _route_xy(pts[:1])[0]
        for e, (lat, lon) in ((car, end_car), (truck, end_truck)):
            i = g.index_of([e.ground_id])[0]
            assert math.hypot((g.lat[i] - lat) * 111_200.0, (g.lon[i] - lon) * M_PER_DEG_LON) < 5.0, e.name
    finally:
        world.close()


def test_crossing_traffic_yields_to_the_right():
    """Two columns of three trucks on perpendicular roads, timed to meet at the crossing: the
    right-hand rule (server/obstacles.py) lets one column through first; no collision (before:
    13-18 m/s collisions, then gridlock), and every truck is through the crossing and queued at
    its road's end."""
    world = World(FlatTerrain(400.0))
    try:
        east = [_spawn_on(world, f"e{k}", "m1083", [(-300.0 - 30.0 * k, 0.0), (400.0, 0.0)], 10.0)
                for k in range(3)]
        north = [_spawn_on(world, f"n{k}", "m1083", [(0.0, -300.0 - 30.0 * k), (0.0, 400.0)], 10.0)
                 for k in range(3)]
        events = _run(world, 30 * 150)
        assert not [e for e in events if e.kind == "collision"]
        g = world.ground
        for k, e in enumerate(east):  # queued at the end: each about a truck and the standoff behind
            assert _east_m(world, e) > 390.0 - 12.0 * k, e.name
        for k, e in enumerate(north):
            assert (g.lat[g.index_of([e.ground_id])[0]] - LAT0) * 111_200.0 > 390.0 - 12.0 * k, e.name
    finally:
        world.close()


def test_a_vehicle_queued_by_traffic_says_so():
    """Three followers bound for one road end, 30 m apart: the first reaches it, the others
    queue behind without passing it (it is not parked, it has arrived: they would jostle), with
    no collision; each held at a standstill for 10 s gives one "blocked" event, reason traffic."""
    world = World(FlatTerrain(400.0))
    try:
        cars = [world.spawn_ground([f"c{k}"], "hmmwv", [LAT0], [LON0 - 30.0 * k / M_PER_DEG_LON], [90.0],
                                   route=_route_east(-30.0 * k, 200.0), cruise_mps=10.0)[0] for k in range(3)]
        events = _run(world, 30 * 60)
        assert not [e for e in events if e.kind == "collision"]
        traffic = [e for e in events if e.kind == "blocked" and e.detail["reason"] == "traffic"]
        assert sorted(world.entities[e.entity_id].name for e in traffic) == ["c1", "c2"]
        assert _east_m(world, cars[0]) > 199.0 and _east_m(world, cars[1]) < _east_m(world, cars[0]) - 4.0
    finally:
        world.close()


def test_a_pass_waits_for_the_oncoming_lane_to_clear():
    """A truck parked 1 m right of the road's centre line; a Humvee east-bound would pass it on
    the left, into the lane of a truck coming west that reaches the parked one about then: the
    Humvee waits behind the parked truck until the oncoming one is by, then passes; no collision
    (before: they met in that lane at 3 m/s and stood there)."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_ground(["parked"], "m1083", [LAT0 - 1.0 / 111_200.0], [LON0 + 300.0 / M_PER_DEG_LON], [90.0])
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 900),
                                  cruise_mps=12.0)
        other, = world.spawn_ground(["other"], "m1083", [LAT0], [LON0 + 596.0 / M_PER_DEG_LON], [270.0],
                                    route=_route_east(596, -300), cruise_mps=12.0)
        events = _run(world, 30 * 180)
        assert not [e for e in events if e.kind == "collision"]
        assert _east_m(world, car) > 890.0 and _east_m(world, other) < -290.0
    finally:
        world.close()


def test_a_convoy_listed_back_to_front_forms_up_by_its_place_on_the_route():
    """Four Humvees listed rear first (the first name 120 m behind the last) on a road east:
    the one in front leads and the others follow in their order along the road, with no
    collision (before, the first name led and drove into the three ahead of it)."""
    world = World(FlatTerrain(400.0))
    try:
        column = world.spawn_ground([f"c{k}" for k in range(4)], "hmmwv", [LAT0] * 4,
                                    [LON0 + 40.0 * k / M_PER_DEG_LON for k in range(4)], [90.0] * 4,
                                    route=_route_east(0, 3000), cruise_mps=10.0, spacing_m=40.0)
        events = _run(world, 900)  # 30 s
        assert not [e for e in events if e.kind == "collision"]
        east = [_east_m(world, e) for e in column]
        assert east == sorted(east)  # still in column, the last name in front
        assert east[0] > 200.0  # every one drove on
        assert np.diff(east) == pytest.approx([40.0] * 3, abs=6.0)
    finally:
        world.close()


@pytest.mark.parametrize("rate_hz", [1.0, 2.0, 4.0, 30.0])
def test_followers_stop_at_the_end_and_pass_a_site_whatever_the_world_rate(rate_hz):
    """A Humvee at 29 m/s on a 3 km road stops within 0.5 m of the road's end at a 1-30 Hz
    world tick (it stopped 4.4 m past it at 1 Hz when its braking did not look one step
    ahead), and another passes a radar site standing on its road with no collision (at
    1-4 Hz it clipped the site: the pass kept its half width clear of the site's sphere, the
    collision test the circle round its footprint)."""
    world = World(FlatTerrain(400.0), fdm_rate_hz=120.0, world_rate_hz=rate_hz)
    try:
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 3000),
                                  cruise_mps=29.0)
        world.spawn_static("site", "radar", LAT0 + 0.02, LON0 + 1500.0 / M_PER_DEG_LON)
        truck, = world.spawn_ground(["truck"], "hmmwv", [LAT0 + 0.02], [LON0], [90.0],
                                    route=_route_east(0, 3000, lat=LAT0 + 0.02), cruise_mps=29.0)
        events = [e for _ in range(int(200 * rate_hz)) for e in world.tick()]
        assert not [e for e in events if e.kind == "collision"]
        assert _east_m(world, car) == pytest.approx(3000.0, abs=0.5)
        assert _east_m(world, truck) == pytest.approx(3000.0, abs=0.5)
    finally:
        world.close()


def test_a_follower_waiting_to_pass_keeps_room_to_swing_out():
    """A truck parked 1 m right of the road; a Humvee going east must pass it on the left,
    but a truck coming west reaches it first. The Humvee waits where it has room to swing
    out from a standstill (fdm.convoy.swing_room_m), then passes and reaches its road's
    end (it had waited at the 4 m standoff, then stood against the parked truck's corner)."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_ground(["parked"], "m1083", [LAT0 - 1.0 / 111_200.0], [LON0 + 300.0 / M_PER_DEG_LON], [90.0])
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=_route_east(0, 900),
                                  cruise_mps=12.0)
        world.spawn_ground(["oncoming"], "m1083", [LAT0], [LON0 + 620.0 / M_PER_DEG_LON], [270.0],
                           route=_route_east(620, -300), cruise_mps=12.0)
        events = _run(world, 30 * 120)
        assert not [e for e in events if e.kind == "collision"]
        assert _east_m(world, car) == pytest.approx(900.0, abs=1.0)
    finally:
        world.close()


@pytest.mark.parametrize("turn_deg", [90.0, -90.0])
def test_a_truck_parked_just_after_a_corner_is_passed(turn_deg):
    """A truck parked on the road 50 m after a 90-degree corner: the Humvee, off its road by
    the corner it cut (pure pursuit), passes it and reaches its road's end (it took the shift
    from where it stood, not from the road, passed 1.9 m too close and stood behind the truck
    for good)."""
    from fdm.convoy import Route

    turn = math.radians(turn_deg)
    corner = (300.0, 0.0)
    end = (corner[0] + 400.0 * math.cos(-turn), corner[1] + 400.0 * math.sin(-turn))
    pts = [(LAT0 + n / 111_200.0, LON0 + e / M_PER_DEG_LON) for e, n in [(0.0, 0.0), corner, end]]
    route = Route(*np.array(pts).T)
    world = World(FlatTerrain(400.0))
    try:
        lat, lon, hdg = route.point_at(350.0)
        world.spawn_ground(["parked"], "m1083", lat, lon, hdg)
        car, = world.spawn_ground(["car"], "hmmwv", [LAT0], [LON0], [90.0], route=pts, cruise_mps=12.0)
        events = _run(world, 30 * 90)
        assert not [e for e in events if e.kind in ("collision", "blocked")]
        i = world.ground.index_of([car.ground_id])
        s, _, _ = route.project(world.ground.lat[i], world.ground.lon[i])
        assert s[0] == pytest.approx(route.length_m, abs=1.0)
    finally:
        world.close()


@pytest.mark.parametrize("rate_hz", [1.0, 30.0])
def test_a_convoy_slowing_for_a_corner_keeps_its_spacing_at_any_world_rate(rate_hz):
    """Six trucks 30 m apart at 20 m/s round a 90-degree corner to their road's end. An
    acceptance probe: at a 1 Hz world followers read the one ahead's speed a tick late, ran at
    21 m/s into leaders slowing to 6 m/s for the corner, and rear-ended them. Each now follows
    the lower of the one ahead's speed and its command this tick: no collision, no gap under
    half the spacing, and all 30 m apart at the end."""
    from fdm.convoy import Route

    pts = [(LAT0 + n / 111_200.0, LON0 + e / M_PER_DEG_LON) for e, n in [(0.0, 0.0), (0.0, 400.0), (300.0, 400.0)]]
    route = Route(*np.array(pts).T)
    world = World(FlatTerrain(400.0), fdm_rate_hz=120.0, world_rate_hz=rate_hz)
    try:
        column = world.spawn_ground([f"c{k}" for k in range(6)], "m1083",
                                    [LAT0 + 30.0 * k / 111_200.0 for k in range(6)], [LON0] * 6, [0.0] * 6,
                                    route=pts, cruise_mps=20.0, spacing_m=30.0)
        idx = world.ground.index_of([e.ground_id for e in column])
        least = np.inf
        events = []
        for _ in range(int(150 * rate_hz)):
            events += world.tick()
            s, _, _ = route.project(world.ground.lat[idx], world.ground.lon[idx])
            least = min(least, float(np.min(np.diff(np.sort(s)))))
        assert not [e for e in events if e.kind == "collision"]
        assert least > 15.0
        s, _, _ = route.project(world.ground.lat[idx], world.ground.lon[idx])
        assert np.diff(np.sort(s)) == pytest.approx([30.0] * 5, abs=1.0)
    finally:
        world.close()


def test_a_column_out_of_order_never_drives_into_itself():
    """Four Humvees 40 m apart on a road east, their column put out of order (its leader the
    one at the back, as a column staged behind its route's start was ordered): the leader
    brakes for the members in its path (a member behind it in the column is traffic), with
    no collision, and stops at the standoff behind the one ahead of it. Before, members of one
    convoy going the same way ignored each other and it drove into the one ahead at 10 m/s."""
    world = World(FlatTerrain(400.0))
    try:
        route = [(LAT0, LON0), (LAT0, LON0 + 3000.0 / M_PER_DEG_LON)]
        column = world.spawn_ground([f"c{k}" for k in range(4)], "hmmwv", [LAT0] * 4,
                                    [LON0 + 40.0 * k / M_PER_DEG_LON for k in range(4)], [90.0] * 4,
                                    route=route, cruise_mps=10.0, spacing_m=40.0)
        spec, ids = world.routes[-1]
        world.routes[-1] = (spec, ids[::-1])  # the rearmost leads
        world._rebuild_followers()
        events = [e for _ in range(30 * 20) for e in world.tick()]
        assert not [e for e in events if e.kind == "collision"]
        east = [(world.ground.lon[world.ground.index_of([e.ground_id])][0] - LON0) * M_PER_DEG_LON for e in column]
        assert east == sorted(east)
        assert east[1] - east[0] == pytest.approx(4.7 + 4.0, abs=1.5)  # its length and the standoff
    finally:
        world.close()
