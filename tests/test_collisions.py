"""Collisions between agents (server/collisions.py, World._agent_collisions): the compiled
broad and narrow phases against an independent brute-force reference, and real JSBSim
aircraft and ground vehicles running into each other in a world."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fdm.aircraft import FlatTerrain, InitialConditions
from fdm.catalog import DEFAULT_BODY_RADIUS_M, body_radius_m
from fdm.ground import BLOCKED_COLLISION
from fdm.vehicle_types import VEHICLE_TYPES
from server.collisions import new_contacts
from server.world import STATIC_RADIUS_M, World
from terrain.geodesy import enu_basis, geodetic_to_ecef

LAT0, LON0 = 47.0, 9.0


def _corners(cx, cy, heading_deg, half_l, half_w):
    """A box's four corners on the east/north plane, in order round it."""
    h = math.radians(heading_deg)
    f = np.array([math.sin(h), math.cos(h)])  # forward, east/north
    r = np.array([math.cos(h), -math.sin(h)])  # right
    c = np.array([cx, cy])
    return [c + sf * half_l * f + sr * half_w * r for sf, sr in ((1, 1), (1, -1), (-1, -1), (-1, 1))]


def _segments_cross(a, b, c, d) -> bool:
    def orient(p, q, r):
        return np.sign((q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]))
    return orient(a, b, c) != orient(a, b, d) and orient(c, d, a) != orient(c, d, b)


def _inside(p, poly) -> bool:
    signs = [np.sign((poly[(k + 1) % 4][0] - poly[k][0]) * (p[1] - poly[k][1])
                     - (poly[(k + 1) % 4][1] - poly[k][1]) * (p[0] - poly[k][0])) for k in range(4)]
    return all(s >= 0 for s in signs) or all(s <= 0 for s in signs)


def _polygons_overlap(p, q) -> bool:
    """Two convex quadrilaterals overlap: an edge of one crosses an edge of the other, or one
    holds a corner of the other (independent of the kernel's separating-axis test)."""
    if any(_segments_cross(p[a], p[(a + 1) % 4], q[b], q[(b + 1) % 4]) for a in range(4) for b in range(4)):
        return True
    return _inside(p[0], q) or _inside(q[0], p)


def _reference(p0, p1, radius, heading, half_l, half_w, lat, lon, moves):
    """New contacts by brute force over every pair: spheres by the least distance over
    4001 instants of the tick, boxes by polygon intersection at its start and end.
    Returns (contacts, borderline pairs the sampling cannot decide)."""
    found, unsure = set(), set()
    n = len(radius)
    ts = np.linspace(0.0, 1.0, 4001)[:, None]
    for i in range(n):
        for j in range(i + 1, n):
            if not (moves[i] or moves[j]):
                continue
            rs = radius[i] + radius[j]
            if half_l[i] > 0 and half_l[j] > 0:
                east, north, up = enu_basis(lat[i], lon[i])
                touching = []
                for p in (p0, p1):
                    d = p[j] - p[i]
                    bi = _corners(0.0, 0.0, heading[i], half_l[i], half_w[i])
                    bj = _corners(d @ east, d @ north, heading[j], half_l[j], half_w[j])
                    touching.append(abs(d @ up) < rs and np.linalg.norm(d) < rs and _polygons_overlap(bi, bj))
                if touching[1] and not touching[0]:
                    found.add((i, j))
            else:
                r = (p0[j] - p0[i]) + ts * ((p1[j] - p1[i]) - (p0[j] - p0[i]))
                d = np.linalg.norm(r, axis=1)
                if abs(d.min() - rs) < 0.05 or abs(d[0] - rs) < 0.05:
                    unsure.add((i, j))
                elif d[0] >= rs and d.min() < rs:
                    found.add((i, j))
    return found, unsure


@pytest.mark.parametrize("seed", range(6))
def test_contacts_match_a_brute_force_reference(seed):
    """Random spheres (fast movers, up to 25 m a tick) and boxes (ground vehicles, up to
    1.2 m a tick, any heading) in a 150 m patch: the compiled sweep finds exactly the new
    contacts the brute-force reference finds, with i < j, and never one already touching."""
    rng = np.random.default_rng(seed)
    n = 60
    is_box = rng.random(n) < 0.5
    east_m, north_m = rng.uniform(-75, 75, n), rng.uniform(-75, 75, n)
    alt = np.where(is_box, 500.0, 500.0 + rng.uniform(0, 30, n))
    lat = LAT0 + north_m / 111_200.0
    lon = LON0 + east_m / (111_200.0 * math.cos(math.radians(LAT0)))
    p1 = geodetic_to_ecef(lat, lon, alt)
    step = np.where(is_box, rng.uniform(0, 1.2, n), rng.uniform(0, 25, n))
    direction = rng.normal(size=(n, 3))
    direction[is_box] -= (direction[is_box] * p1[is_box]).sum(1)[:, None] * p1[is_box] / (
        np.linalg.norm(p1[is_box], axis=1) ** 2)[:, None]  # boxes move on the horizontal
    direction /= np.linalg.norm(direction, axis=1)[:, None]
    p0 = p1 - step[:, None] * direction
    half_l = np.where(is_box, rng.uniform(2.0, 4.0, n), 0.0)
    half_w = np.where(is_box, rng.uniform(1.0, 1.8, n), 0.0)
    radius = np.where(is_box, np.hypot(half_l, half_w), rng.uniform(3.0, 10.0, n))
    heading = rng.uniform(0, 360, n)
    moves = rng.random(n) < 0.9
    i, j, t, d = new_contacts(p0, p1, radius, heading_deg=heading, half_length_m=half_l, half_width_m=half_w,
                              moves=moves, lat_deg=lat, lon_deg=lon)
    got = set(zip(i.tolist(), j.tolist()))
    want, unsure = _reference(p0, p1, radius, heading, half_l, half_w, lat, lon, moves)
    assert len(want) >= 3, "the random patch should hold some contacts"
    assert got - unsure == want - unsure
    assert np.all(i < j) and np.all((t >= 0) & (t <= 1))
    assert np.all(d < radius[i] + radius[j])


def test_a_fast_crossing_between_snapshots_is_found():
    """Two spheres of 5 m crossing head-on at 600 m/s relative (20 m a tick at 30 Hz): at
    the tick's start they are 10.2 m apart, at its end 9.8 m on the other side: both ends
    apart, the paths meet half-way. Found, at t = 0.5 within the touching time's bound."""
    p = geodetic_to_ecef(np.array([LAT0, LAT0]), np.array([LON0, LON0]), np.array([1000.0, 1000.0]))
    east, _, _ = enu_basis(LAT0, LON0)
    p0 = np.stack([p[0] - 5.1 * east, p[1] + 5.1 * east])
    p1 = np.stack([p[0] + 4.9 * east, p[1] - 4.9 * east])
    i, j, t, d = new_contacts(p0, p1, [5.0, 5.0])
    assert (i.tolist(), j.tolist()) == ([0], [1])
    assert d[0] < 0.2 + 1e-6
    assert 0.0 <= t[0] <= 0.5  # they touch (10 m apart) at t = 0.01, before the least distance
    assert abs(t[0] - 0.01) < 1e-6
    # Beside each other by 10.5 m: never within the 10 m of the two radii.
    off = np.stack([np.zeros(3), 10.5 * enu_basis(LAT0, LON0)[1]])
    assert new_contacts(p0 + off, p1 + off, [5.0, 5.0])[0].size == 0


def test_boxes_side_by_side_are_not_a_collision():
    """Two tanks 4 m apart centre to centre, side by side (3.66 m wide: 0.34 m of gap),
    driving the same way: their bounding circles (4.3 m radius) overlap, their boxes do
    not; one nudged 0.5 m closer touches."""
    t = VEHICLE_TYPES["m1a2"]
    lat = np.array([LAT0, LAT0])
    east_deg = 4.0 / (111_200.0 * math.cos(math.radians(LAT0)))
    for gap_m, touches in ((4.0, False), (3.5, True)):
        lon = np.array([LON0, LON0 + gap_m / 4.0 * east_deg])
        p1 = geodetic_to_ecef(lat, lon, np.array([400.0, 400.0]))
        north = enu_basis(LAT0, LON0)[1]
        p0 = p1 - 0.5 * north
        p0[1] = geodetic_to_ecef(lat[1:], np.array([LON0 + 6.0 * east_deg]), np.array([400.0]))[0] - 0.5 * north
        r = math.hypot(t.length_m, t.width_m) / 2
        i, _, _, _ = new_contacts(p0, p1, [r, r], heading_deg=[0.0, 0.0], half_length_m=[t.length_m / 2] * 2,
                                  half_width_m=[t.width_m / 2] * 2, lat_deg=lat, lon_deg=lon)
        assert (i.size == 1) is touches, gap_m


def test_body_radius_from_the_model_files():
    """Half the wingspan or more, from the catalog's own files: f16 (9.45 m span, 15 m
    long), 747 (59.6 m span); a name not in the catalog takes the default."""
    assert 4.7 < body_radius_m("f16") < 9.0
    assert 29.0 < body_radius_m("B747") < 40.0
    assert 5.0 < body_radius_m("c172x") < 7.0
    assert body_radius_m("no-such-aircraft") == DEFAULT_BODY_RADIUS_M


def _collisions(events, entity_id):
    return [e for e in events if e.kind == "collision" and e.entity_id == entity_id]


def _run(world, ticks):
    events = []
    for _ in range(ticks):
        events += world.tick()
    return events


def test_head_on_aircraft_collide_and_crash():
    """Two trimmed f16s 3 km apart at the same altitude, head-on at 250 m/s each (8.3 m a
    tick at 30 Hz, closing 16.7 m a tick, against a contact distance of 15 m): each gets one
    collision event naming the other within 0.5 s of 6 s, then a crash for that reason; a
    third pair 300 m to the side flies on."""
    world = World(FlatTerrain(400.0))
    try:
        east_deg = 1500.0 / (111_200.0 * math.cos(math.radians(LAT0)))
        side = 300.0 / 111_200.0
        a = world.spawn_aircraft("a", "f16", InitialConditions(LAT0, LON0 - east_deg, 2000.0, heading_deg=90.0,
                                                                speed_mps=250.0))
        b = world.spawn_aircraft("b", "f16", InitialConditions(LAT0, LON0 + east_deg, 2000.0, heading_deg=270.0,
                                                                speed_mps=250.0))
        c = world.spawn_aircraft("c", "f16", InitialConditions(LAT0 + side, LON0 - east_deg, 2000.0,
                                                                heading_deg=90.0, speed_mps=250.0))
        d = world.spawn_aircraft("d", "f16", InitialConditions(LAT0 + 2 * side, LON0 + east_deg, 2000.0,
                                                                heading_deg=270.0, speed_mps=250.0))
        events = _run(world, 300)  # 10 s
        for me, other in ((a, b), (b, a)):
            hits = _collisions(events, me.id)
            assert len(hits) == 1, hits
            assert hits[0].detail["other_id"] == other.id and hits[0].detail["other_name"] == other.name
            assert abs(hits[0].time_s - 6.0) < 0.5
            assert hits[0].detail["relative_speed_mps"] > 400.0
            crashes = [e for e in events if e.kind == "crash" and e.entity_id == me.id]
            assert [e.detail["reason"] for e in crashes] == [f"collision with {other.name}"]
            assert world.entities[me.id].crashed
        for e in (c, d):
            assert not _collisions(events, e.id) and not world.entities[e.id].crashed
        # The wrecks fall on (fdm.wreck) through each other: no further collision between them.
        assert not [e for e in _run(world, 30) if e.kind == "collision"]
    finally:
        world.close()


def test_ground_vehicles_collide_once_and_stop():
    """Two tanks 60 m apart driving at each other at 10 m/s: one collision event each,
    naming the other, where they met (half-way within a tank length); both stop at once
    (speed 0, blocked "collision"). Two Humvees side by side 2.5 m apart (2.12 m wide)
    driving together north are never a collision."""
    world = World(FlatTerrain(400.0))
    try:
        east_deg = 30.0 / (111_200.0 * math.cos(math.radians(LAT0)))
        a, b = world.spawn_ground(["a", "b"], "m1a2", [LAT0, LAT0], [LON0 - east_deg, LON0 + east_deg], [90.0, 270.0],
                                  controllable=True)
        side = 2.5 / (111_200.0 * math.cos(math.radians(LAT0)))
        c, d = world.spawn_ground(["c", "d"], "hmmwv", [LAT0 + 0.01] * 2, [LON0, LON0 + side], [0.0, 0.0],
                                  controllable=True)
        for e in (a, b, c, d):
            world.command(e.id, "drive", {"speed_mps": 10.0, "yaw_rate_dps": 0.0})
        events, stopped = [], None
        for _ in range(240):  # 8 s
            new = world.tick()
            events += new
            if stopped is None and _collisions(new, a.id):
                idx = world.ground.index_of([a.ground_id, b.ground_id])
                stopped = (world.ground.speed_mps[idx].copy(), world.ground.blocked[idx].copy())
        for me, other in ((a, b), (b, a)):
            hits = _collisions(events, me.id)
            assert len(hits) == 1, hits
            assert hits[0].detail["other_name"] == other.name
            hit_lat, hit_lon, _ = hits[0].lat_deg, hits[0].lon_deg, hits[0].alt_msl_m
            east_m = (hit_lon - LON0) * 111_200.0 * math.cos(math.radians(LAT0))
            assert abs(east_m) < VEHICLE_TYPES["m1a2"].length_m and abs(hit_lat - LAT0) < 1e-5
        assert stopped is not None
        assert np.all(stopped[0] == 0.0) and np.all(stopped[1] == BLOCKED_COLLISION)
        assert not _collisions(events, c.id) and not _collisions(events, d.id)
    finally:
        world.close()


def test_static_target_hit_by_a_vehicle():
    """A truck driven into a static site: a collision event for each of the two; the site
    stays put, the truck stops."""
    world = World(FlatTerrain(400.0))
    try:
        site = world.spawn_static("site", "radar", LAT0, LON0, 400.0)
        truck, = world.spawn_ground(["truck"], "m1083", [LAT0 - 40.0 / 111_200.0], [LON0], [0.0], controllable=True)
        world.command(truck.id, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 0.0})
        events, gap_m = [], None
        for _ in range(240):
            new = world.tick()
            events += new
            if gap_m is None and _collisions(new, truck.id):
                i = world.ground.index_of([truck.ground_id])[0]
                assert world.ground.speed_mps[i] == 0.0
                gap_m = (LAT0 - float(world.ground.lat[i])) * 111_200.0
        assert [e.detail["other_name"] for e in _collisions(events, truck.id)] == ["site"]
        assert [e.detail["other_name"] for e in _collisions(events, site.id)] == ["truck"]
        # Stopped where the truck's circle (its half diagonal) met the site's 10 m one, within a
        # tick's travel (8 m/s at 30 Hz) and the 1 % of the metres-per-degree figure used here.
        t = VEHICLE_TYPES["m1083"]
        want = STATIC_RADIUS_M + math.hypot(t.length_m, t.width_m) / 2
        assert want - 0.3 - 0.01 * want < gap_m < want + 0.01 * want
    finally:
        world.close()


def test_acmi_names_both_sides_of_a_collision():
    """The Tacview export's line for a collision event names the other entity and the speed."""
    import json

    from server.acmi import event_line
    from sortie.v1 import simulation_pb2 as pb

    ev = pb.WorldEvent(time_s=6.0, kind="collision", entity_id=1, detail_json=json.dumps(
        {"other_id": 2, "other_name": "b", "other_kind": "aircraft", "relative_speed_mps": 500.04, "distance_m": 3.0}))
    assert event_line(ev, "a1", "a") == "0,Event=Message|a1|a collided with b at 500.0 m/s"
    ev = pb.WorldEvent(time_s=6.0, kind="destroyed", entity_id=3, detail_json=json.dumps(
        {"reason": "collision with jet"}))
    assert event_line(ev, "c3", "site") == "0,Event=Destroyed|c3|site destroyed: collision with jet"


def test_fast_collisions_destroy_vehicles_and_sites():
    """Two trucks 300 m apart head-on at 14 m/s each (28 m/s relative once at speed, above the
    20 m/s that destroys):
    both destroyed, stopped for good, their commands refused naming the wreck. An f16 flown
    level into a static site: the aircraft crashes, the site is destroyed. A truck driven
    into another site at 8 m/s (below the bound) leaves it unharmed (test above)."""
    from server.world import DESTROY_SPEED_MPS
    from sortie.errors import InvalidArgument

    world = World(FlatTerrain(400.0))
    try:
        east_deg = 150.0 / (111_200.0 * math.cos(math.radians(LAT0)))
        a, b = world.spawn_ground(["a", "b"], "m1083", [LAT0, LAT0], [LON0 - east_deg, LON0 + east_deg],
                                  [90.0, 270.0], controllable=True)
        site = world.spawn_static("site", "radar", LAT0 + 0.02, LON0, 1000.0)
        jet = world.spawn_aircraft("jet", "f16", InitialConditions(LAT0 + 0.02, LON0 - 2 * 1500.0 / (
            111_200.0 * math.cos(math.radians(LAT0))), 1000.0, heading_deg=90.0, speed_mps=250.0))
        for e in (a, b):
            world.command(e.id, "drive", {"speed_mps": 14.0, "yaw_rate_dps": 0.0})
        events = _run(world, 600)  # 20 s
        for me, other in ((a, b), (b, a)):
            hit = _collisions(events, me.id)
            assert len(hit) == 1 and hit[0].detail["relative_speed_mps"] >= DESTROY_SPEED_MPS
            assert [e.detail["reason"] for e in events if e.kind == "destroyed" and e.entity_id == me.id] == [
                f"collision with {other.name}"]
            assert world.entities[me.id].destroyed
            with pytest.raises(InvalidArgument, match="destroyed"):
                world.command(me.id, "drive", {"speed_mps": 5.0, "yaw_rate_dps": 0.0})
        idx = world.ground.index_of([a.ground_id, b.ground_id])
        at = world.ground.lat[idx].copy(), world.ground.lon[idx].copy()
        _run(world, 60)
        assert np.array_equal(world.ground.lat[idx], at[0]) and np.array_equal(world.ground.lon[idx], at[1])
        assert np.all(world.ground.speed_mps[idx] == 0.0)
        assert [e.detail["other_name"] for e in _collisions(events, site.id)] == ["jet"]
        assert [e.kind for e in events if e.entity_id == site.id and e.kind in ("destroyed", "crash")] == ["destroyed"]
        assert [e.detail["reason"] for e in events if e.entity_id == jet.id and e.kind == "crash"] == [
            "collision with site"]
    finally:
        world.close()


def test_bench_scene_agrees_with_the_all_pairs_reference():
    """The bench's battlefield tick (quick: 587 entities, a crowded vehicle park and an
    aircraft furball): the sweep finds exactly the all-pairs reference's contacts, and some."""
    from bench.collisions import all_pairs, scene

    s = scene(quick=True, seed=3)
    i, j, _, _ = new_contacts(**s)
    got = set(zip(i.tolist(), j.tolist()))
    assert len(got) >= 5 and got == all_pairs(s)


@pytest.mark.parametrize("world_rate_hz", [2.0, 5.0])
def test_fast_vehicles_at_a_low_world_rate_do_not_pass_through(world_rate_hz):
    """Two Humvees head-on at 29 m/s each at a world rate of 2 or 5 Hz (up to 29 m of
    relative travel a tick, more than two Humvee lengths): for each of 12 start gaps a
    collision, both destroyed where they met, never past each other (an acceptance tester's
    case: at 2 Hz, 7 of the 12 passed through when boxes were tested at tick ends only)."""
    for k in range(12):
        world = World(FlatTerrain(400.0), fdm_rate_hz=120.0, world_rate_hz=world_rate_hz)
        try:
            half_gap_m = 156.8 + 0.97 * k
            east_deg = half_gap_m / (111_200.0 * math.cos(math.radians(LAT0)))
            a, b = world.spawn_ground(["a", "b"], "hmmwv", [LAT0, LAT0], [LON0 - east_deg, LON0 + east_deg],
                                      [90.0, 270.0], controllable=True)
            for e in (a, b):
                world.command(e.id, "drive", {"speed_mps": 29.0, "yaw_rate_dps": 0.0})
            events = _run(world, int(20 * world_rate_hz))
            assert len(_collisions(events, a.id)) == 1 and len(_collisions(events, b.id)) == 1, half_gap_m
            idx = world.ground.index_of([a.ground_id, b.ground_id])
            east_m = (world.ground.lon[idx] - LON0) * 111_200.0 * math.cos(math.radians(LAT0))
            assert east_m[0] < east_m[1], half_gap_m  # a (from the west) still west of b
        finally:
            world.close()


def test_an_entity_without_a_position_is_in_no_contact():
    """A NaN position (nothing the world publishes, but the kernel must not compare it into
    a contact): the other pairs are found as without it, with their own indices."""
    p = geodetic_to_ecef(np.array([LAT0] * 3), np.array([LON0] * 3), np.array([1000.0] * 3))
    east = enu_basis(LAT0, LON0)[0]
    p1 = np.stack([p[0], p[1] + 8.0 * east, p[2]])
    p0 = np.stack([p[0], p[1] + 30.0 * east, p[2]])
    p0[0] = p1[0] = np.nan
    i, j, _, d = new_contacts(p0, p1, [5.0, 5.0, 5.0])
    assert (i.tolist(), j.tolist()) == ([1], [2]) and np.isfinite(d).all()


HEAD_ON_TOML = """
[exercise]
name = "head-on"
start_time = 2026-06-15T07:00:00Z
clock = "fast"
duration_s = 12.0

[terrain]
dem = ["{dem}"]
geoid_undulation_m = 48.0
{agents}
"""
HEAD_ON_AGENT = """
[[agents]]
name = "{name}"
kind = "aircraft"
coalition = "blue"
type = "f16"
lat_deg = 47.3
lon_deg = {lon}
alt_m = 4000.0
heading_deg = {heading}
speed_mps = 250.0
autopilot = {{ hold = {{ heading_deg = {heading}, alt_msl_m = 4000.0, speed_mps = 250.0 }} }}
"""


def test_a_recorded_collision_replays_with_its_wrecks(tmp_path, hgt_alps):
    """`sortie server` records two f16s colliding head-on (2 km apart at 250 m/s each: 4 s);
    its recording holds the collision and crash events, and a replay seeked past them tells
    a view entering then that both are wrecks (EntityInfo.destroyed), and before them that
    neither is."""
    import subprocess

    from client.sim_client import SimClient
    from server.process import sortie_command
    from server.recording import Recording
    from server.replay import ReplayServer

    east_deg = 1000.0 / (111_200.0 * math.cos(math.radians(47.3)))
    agents = HEAD_ON_AGENT.format(name="a", lon=9.3 - east_deg, heading=90.0) + HEAD_ON_AGENT.format(
        name="b", lon=9.3 + east_deg, heading=270.0)
    scenario = tmp_path / "head_on.toml"
    scenario.write_text(HEAD_ON_TOML.format(dem=str(hgt_alps), agents=agents))
    path = tmp_path / "h.sortie"
    out = subprocess.run(sortie_command() + ["server", "--scenario", str(scenario), "--port", "0", "--record",
                                              str(path)], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    with Recording(path) as rec:
        kinds = [r.event.kind for r in rec.events()]
        crash_tick = min(r.tick for r in rec.events() if r.event.kind == "crash")
        assert kinds.count("collision") == 2 and kinds.count("crash") == 2
        assert abs(crash_tick * rec.dt - 4.0) < 0.5
    server = ReplayServer(path, speed=1.0, playing=False)
    server.start()
    try:
        with SimClient(server.address) as c:
            c.join("debrief", "observer", observer=(47.3, 9.3, 150_000.0))
            pic = c.watch()
            assert pic.snapshot_received.wait(15.0)
            for t_s, wrecked in ((crash_tick * rec.dt - 1.0, False), (crash_tick * rec.dt + 2.0, True)):
                st = c.replay(seek_time_s=t_s)
                assert pic.wait_for(lambda p: abs(p.time_s - st.tick * rec.dt) < 1e-9 and len(p.infos) == 2, 15.0)
                assert [info.destroyed for info in pic.infos.values()] == [wrecked, wrecked], t_s
    finally:
        server.stop()


def _east_m(world, entity):
    lon = world.ground.lon[world.ground.index_of([entity.ground_id])][0]
    return (lon - LON0) * 111_200.0 * math.cos(math.radians(LAT0))


def test_a_vehicle_pushing_on_does_not_pass_through():
    """Two tanks driven at each other at 6 m/s whose drivers keep the throttle on after they
    meet: they stay in contact, west stays west (before, each drove on through the other and
    was 40 m past it 8 s later), each overlaps the other by no more than a tick's travel, and
    no second collision is reported. One driver then reverses: it backs off, free."""
    world = World(FlatTerrain(400.0))
    try:
        east_deg = 20.0 / (111_200.0 * math.cos(math.radians(LAT0)))
        a, b = world.spawn_ground(["a", "b"], "m1a2", [LAT0, LAT0], [LON0 - east_deg, LON0 + east_deg], [90.0, 270.0],
                                  controllable=True)
        for e in (a, b):
            world.command(e.id, "drive", {"speed_mps": 6.0, "yaw_rate_dps": 0.0})
        events = _run(world, 240)  # 8 s: they meet after about 2 s
        length = VEHICLE_TYPES["m1a2"].length_m
        gap = _east_m(world, b) - _east_m(world, a)
        assert length - 2 * 6.0 / 30.0 - 1e-3 <= gap <= length + 1e-3, gap
        assert len(_collisions(events, a.id)) == 1 and len(_collisions(events, b.id)) == 1
        world.command(a.id, "drive", {"speed_mps": -3.0, "yaw_rate_dps": 0.0})
        before = _east_m(world, a)
        _run(world, 90)
        assert _east_m(world, a) < before - 3.0  # backed off: moving out of the overlap is free
    finally:
        world.close()


def test_a_vehicle_driven_into_a_static_site_stays_held():
    """A truck whose driver keeps driving into a radar site: it stays at the site's edge."""
    world = World(FlatTerrain(400.0))
    try:
        world.spawn_static("site", "radar", LAT0, LON0, 400.0)
        truck, = world.spawn_ground(["truck"], "m1083", [LAT0 - 40.0 / 111_200.0], [LON0], [0.0], controllable=True)
        world.command(truck.id, "drive", {"speed_mps": 5.0, "yaw_rate_dps": 0.0})
        _run(world, 300)  # 10 s: 50 m at 5 m/s
        lat = world.ground.lat[world.ground.index_of([truck.ground_id])][0]
        north_m = (lat - LAT0) * 111_200.0
        t = VEHICLE_TYPES["m1083"]
        # Sphere against sphere: the truck's bounding radius plus the site's, less a tick's travel.
        reach = math.hypot(t.length_m / 2, t.width_m / 2) + STATIC_RADIUS_M
        assert -reach - 0.2 <= north_m < -reach + 0.3, north_m
    finally:
        world.close()


def test_a_vehicle_touching_another_can_slide_along_it():
    """Two Humvees parked side by side, touching (1.9 m apart, 2.12 m wide): one drives north
    along the other; its overlap does not deepen, so it is not held."""
    world = World(FlatTerrain(400.0))
    try:
        side = 1.9 / (111_200.0 * math.cos(math.radians(LAT0)))
        c, d = world.spawn_ground(["c", "d"], "hmmwv", [LAT0] * 2, [LON0, LON0 + side], [0.0, 0.0],
                                  controllable=True)
        world.command(c.id, "drive", {"speed_mps": 5.0, "yaw_rate_dps": 0.0})
        _run(world, 150)  # 5 s
        lat = world.ground.lat[world.ground.index_of([c.ground_id])][0]
        assert (lat - LAT0) * 111_200.0 > 15.0
    finally:
        world.close()


def test_a_tank_pivoting_into_its_neighbour_is_held():
    """An M1A2 parked 0.14 m beside another pivots on the spot (speed 0, 30 deg/s): its hull may
    not sweep into the other's (before: it turned 180 degrees through it, 2.4 m deep); it is held
    touching, at the heading where they met, and turning the other way is free."""
    world = World(FlatTerrain(400.0))
    try:
        side = (VEHICLE_TYPES["m1a2"].width_m + 0.14) / (111_200.0 * math.cos(math.radians(LAT0)))
        a, b = world.spawn_ground(["a", "b"], "m1a2", [LAT0, LAT0], [LON0, LON0 + side], [0.0, 0.0],
                                  controllable=True)
        world.command(a.id, "drive", {"speed_mps": 0.0, "yaw_rate_dps": 30.0})
        _run(world, 180)  # 6 s: 180 degrees free
        i = world.ground.index_of([a.ground_id])[0]
        assert world.ground.heading_deg[i] < 10.0  # a few degrees take up the 0.14 m, then held
        world.command(a.id, "drive", {"speed_mps": 0.0, "yaw_rate_dps": -30.0})
        _run(world, 60)
        assert 300.0 < world.ground.heading_deg[i] < 360.0  # away from it: free
    finally:
        world.close()
