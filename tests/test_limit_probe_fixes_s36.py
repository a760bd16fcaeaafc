"""Documented limits exercised at the limit (limit probe, round s36).

- The world's 10,000 entities (server/world.py MAX_ENTITIES) with ground vehicles each on a
  route of its own, as a scenario of 10,000 route-following agents spawns them (one
  ``spawn_ground`` per agent): every spawn made every route's follower again, Route geometry
  included (0.4 ms each), so n spawns cost n^2 / 2 of them: 1,000 took 165 s, 10,000 hours.
  Now the Route is made once per route and the followers once before the next tick.
- A ground spawn the world refuses (one past MAX_ENTITIES, a name given twice or taken) left
  its vehicles in the ground model without an entity: stepped and queried every tick, never
  seen, never removable (10,001 rows for 10,000 entities after one refusal).
- A chunk of ``--record-chunk-s`` up to its documented 3600 s at the world's 10,000 entities
  kept 1.1e9 entity states in memory (0.6 TB with their coding) and coded past the format's
  1 GiB chunk body: now a chunk also closes at server/recorder.py MAX_CHUNK_STATES states.
"""

from __future__ import annotations

import time

import numpy as np
import pytest

from server.recorder import MAX_CHUNK_STATES, Recorder
from server.recording import Recording, quantization_of
from server.recording_codec import DEFAULT_STEPS
from server.world import MAX_ENTITIES, Snapshot, World
from sortie.errors import InvalidArgument, LimitExceeded
from sortie.v1 import recording_pb2 as rpb
from terrain.mosaic import load_sources
from terrain.terrain import Terrain

POSTS = 1201  # an SRTM-3 tile: S34W071 spans 34-33 S, 71-70 W
FLAT_M = 100
LAT0, LON0 = -33.9, -70.9
GRID_DEG = 0.0008  # vehicles 89 m (north) x 74 m (east) apart: none touches another
# Spawning 10,000 vehicles on routes of their own, one call each (what sim_server._spawn does
# for a scenario), and their first tick: about 8 s here (2 cores); hours before the fix.
SPAWN_BUDGET_S = 60.0


@pytest.fixture(scope="module")
def flat(tmp_path_factory) -> Terrain:
    path = tmp_path_factory.mktemp("flat") / "S34W071.hgt"
    np.full((POSTS, POSTS), FLAT_M, ">i2").tofile(path)  # SRTM .hgt: big-endian int16
    return Terrain(load_sources([path]))


def _grid(n: int) -> tuple[np.ndarray, np.ndarray]:
    """(lat, lon) degrees of n places on a grid in the flat tile."""
    k = int(np.ceil(np.sqrt(n)))
    i, j = np.divmod(np.arange(n), k)
    return LAT0 + i * GRID_DEG, LON0 + j * GRID_DEG


def test_ten_thousand_vehicles_on_routes_of_their_own_spawn_and_follow(flat):
    world = World(flat, fdm_rate_hz=120, world_rate_hz=30)
    lat, lon = _grid(MAX_ENTITIES)
    t0 = time.monotonic()
    for k in range(MAX_ENTITIES):
        route = [(lat[k], lon[k]), (lat[k] + 0.0005, lon[k] + 0.0003), (lat[k] + 0.001, lon[k])]
        world.spawn_ground([f"v{k}"], "hmmwv", lat[k:k + 1], lon[k:k + 1], [30.0], route=route, cruise_mps=5.0)
        assert time.monotonic() - t0 < SPAWN_BUDGET_S, f"{k + 1} vehicles spawned in {SPAWN_BUDGET_S} s"
    for _ in range(3):
        world.tick()
    assert time.monotonic() - t0 < SPAWN_BUDGET_S
    assert len(world.entities) == world.ground.n == MAX_ENTITIES
    assert world.routes and len(world._current_followers().index) == MAX_ENTITIES
    assert (world.ground.speed_mps > 0.0).all()  # every one drives off along its route
    # One past the limit is refused, naming it; the world is unchanged and ticks on.
    with pytest.raises(LimitExceeded, match=r"^entities: 10001 exceeds the limit of 10000"):
        world.spawn_ground(["extra"], "hmmwv", [LAT0 - 0.05], [LON0], [0.0], route=[(LAT0 - 0.05, LON0),
                                                                                 (LAT0 - 0.04, LON0)])
    # A driver takes one off its route: the others follow on, it does not.
    taken = world.entities[1]
    world.command(taken.id, "drive", {"speed_mps": 0.0, "yaw_rate_dps": 0.0})
    world.tick()
    assert taken.id not in world._followed and len(world._current_followers().index) == MAX_ENTITIES - 1
    assert world.ground.n == len(world.entities) == MAX_ENTITIES


def test_a_refused_ground_spawn_leaves_no_vehicle_behind(flat):
    world = World(flat, fdm_rate_hz=120, world_rate_hz=30)
    lat, lon = _grid(MAX_ENTITIES + 1)
    n = MAX_ENTITIES - 2
    world.spawn_ground([f"v{k}" for k in range(n)], "hmmwv", lat[:n], lon[:n], np.zeros(n))
    two = dict(lat=lat[n:n + 2], lon=lon[n:n + 2], heading_deg=[0.0, 0.0])
    # a name given twice, or one an entity has: refused whole, nothing added
    with pytest.raises(InvalidArgument, match=r"^name: appears twice among the vehicles spawned"):
        world.spawn_ground(["a", "a"], "hmmwv", **two)
    with pytest.raises(InvalidArgument, match=r"^name: an entity of this name exists \(got 'v3'\)"):
        world.spawn_ground(["b", "v3"], "hmmwv", **two)
    # one past the limit (three where two places are left)
    with pytest.raises(LimitExceeded, match=r"^entities: 10001 exceeds the limit of 10000"):
        world.spawn_ground(["c", "d", "e"], "hmmwv", lat[n:n + 3], lon[n:n + 3], [0.0] * 3, speed_mps=3.0)
    assert world.ground.n == len(world.entities) == n
    # a route the follower refuses (cruise over the type's top speed): nothing added
    with pytest.raises(InvalidArgument, match=r"^cruise_mps: "):
        world.spawn_ground(["f"], "hmmwv", lat[n:n + 1], lon[n:n + 1], [0.0],
                           route=[(lat[n], lon[n]), (lat[n] + 0.001, lon[n])], cruise_mps=500.0)
    assert world.ground.n == len(world.entities) == n and not world.routes
    # at the limit: the last places are taken, and the world ticks with every vehicle in it
    world.spawn_ground(["last", "but-one"], "hmmwv", **two, speed_mps=3.0)
    world.tick()
    assert world.ground.n == len(world.entities) == MAX_ENTITIES == world.snapshot.ids.size


def test_an_hour_chunk_of_ten_thousand_entities_is_written_in_bounded_chunks(tmp_path):
    """--record-chunk-s 3600 (MAX_CHUNK_S) at MAX_ENTITIES: chunks close at MAX_CHUNK_STATES
    entity states (within one tick's entities), every tick is read back, none lost."""
    header = rpb.RecordingHeader(format_version=1, exercise_name="limit", world_rate_hz=30.0,
                                 quantization=quantization_of(DEFAULT_STEPS))
    path = tmp_path / "hour.sortie"
    rec = Recorder(path, header, 3600.0)
    e = MAX_ENTITIES
    ids = np.arange(1, e + 1, dtype=np.int64)
    pos = np.column_stack([np.full(e, 4.0e6), np.arange(e) * 10.0, np.full(e, 4.0e6)])
    z3, quat = np.zeros((e, 3)), np.tile([1.0, 0.0, 0.0, 0.0], (e, 1))
    lat = lon = alt = np.zeros(e)
    ticks = MAX_CHUNK_STATES // e + 10  # past one chunk's worth
    infos = {int(i): (int(i), f"e{i}", 2, "hmmwv", "blue") for i in ids}
    for t in range(1, ticks + 1):
        rec.on_tick(Snapshot(t / 30.0, t, ids, pos, z3, z3, quat, z3, lat, lon, alt), infos)
    rec.close()
    assert rec.error is None
    with Recording(path) as r:
        assert r.problems == []
        heads = [r.chunk_head(k) for k in range(r.chunk_count)]
        assert r.chunk_count >= 2
        assert all(h.ticks * h.entity_count <= MAX_CHUNK_STATES + e for h in heads)
        assert sum(h.ticks for h in heads) == ticks and r.last_tick == ticks
