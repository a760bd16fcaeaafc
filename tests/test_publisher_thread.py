"""The publish runs beside the world's ticks (server/sim_server.py: the publisher thread), and
the entities' centre a client watches by default is the largest group's.

- A slow publish no longer lengthens the ticks: with every publish made 60 ms slower than the
  30 Hz tick, a real-time world still keeps real time and its ticks stay short, and every
  snapshot handed over is published, in order.
- A "fast" clock faster than its publishes waits for them: none is dropped.
- The server's stop publishes the last tick's snapshot with the clock stopped (rate 0).
- An error in a publish stops the clock as one in a tick does (``server.error``).
- entities_centre over two groups far apart is the larger group's median, in any order.
"""

import itertools
import time

import numpy as np
import pytest

from fdm.aircraft import InitialConditions
from server.sim_server import ServerConfig, SimulationServer, entities_centre, largest_group
from server.world import World


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _world(alps) -> World:
    w = World(alps)
    w.spawn_aircraft("cessna", "c172x", InitialConditions(47.45, 9.45, 1500.0, heading_deg=0.0, speed_mps=50.0),
                     hold={"heading_deg": 0.0, "alt_msl_m": 1500.0, "speed_mps": 50.0})
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, controllable=True)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45)
    return w


def _slow_publishes(srv: SimulationServer, delay_s: float) -> list:
    """Make every publish ``delay_s`` slower; returns the list of (world time, rate advertised)
    of the publishes, filled as they run (the stop's last one at rate 0)."""
    seen = []
    original = srv.publisher.publish

    def publish(snap, infos, sessions, rate=1.0, *args, **kwargs):
        seen.append((snap.time_s, rate))
        time.sleep(delay_s)
        return original(snap, infos, sessions, rate, *args, **kwargs)

    srv.publisher.publish = publish
    return seen


def test_a_slow_publish_does_not_hold_up_the_world_ticks(alps):
    """Real time at 30 Hz, network 10 Hz, each publish 60 ms slower (two ticks): the world keeps
    real time within 5 % over 2 s and its ticks stay far under the publish's 60 ms (on the clock
    thread, every third tick took 62 ms: tick p90 62.3 ms against 2.1 ms now).
    Every network tick's snapshot is published (a publish 60 ms long, one a 100 ms network
    period: none waits), in order of world time."""
    srv = SimulationServer(_world(alps), ServerConfig(clock="realtime", network_rate_hz=10.0))
    seen = _slow_publishes(srv, 0.060)
    srv.start()
    try:
        time.sleep(0.5)
        w0, t0 = srv.world.time_s, time.monotonic()
        n0 = len(srv.tick_ms)
        time.sleep(2.0)
        rate = (srv.world.time_s - w0) / (time.monotonic() - t0)
        ticks = np.array(srv.tick_ms[n0:])
    finally:
        srv.stop(0.5)
    assert rate > 0.95, rate
    assert np.percentile(ticks, 90) < 40.0, np.percentile(ticks, 90)
    # The stop's own publish last: the last tick's snapshot, the clock stopped (rate 0).
    assert seen[-1] == (srv.world.time_s, 0.0), (seen[-1], srv.world.time_s)
    times = [t for t, r in seen[:-1]]
    assert times == sorted(times) and len(set(times)) == len(times)
    # 10 Hz of a 30 Hz world: every third tick (its snapshot at 1/30 s after a multiple of 0.1 s)
    gaps = np.diff(times[3:])
    assert np.all(np.abs(gaps - 0.1) < 0.01), gaps
    assert len(srv.publish_ms) == len(seen) and min(srv.publish_ms[1:]) >= 60.0


def test_a_fast_clock_waits_for_its_publishes_and_drops_none(alps):
    """As fast as it goes with every publish 20 ms slower than a tick takes: the clock waits for
    the publisher (at most one snapshot handed over and not yet taken), so every network tick is
    published, each once, in order."""
    srv = SimulationServer(_world(alps), ServerConfig(clock="fast", time_scale=1000.0, network_rate_hz=30.0))
    seen = _slow_publishes(srv, 0.020)
    srv.start()
    try:
        time.sleep(1.5)
    finally:
        srv.stop(0.5)
    assert seen[-1] == (srv.world.time_s, 0.0)  # the stop's own publish: the last tick, clock stopped
    times = np.array([t for t, _ in seen[:-1]])
    assert times.size >= 20
    # A 30 Hz network on a 30 Hz world: one publish a tick, none skipped, none twice.
    assert np.all(np.abs(np.diff(times) - 1.0 / 30.0) < 1e-6), np.diff(times)
    assert srv.world.tick_count - times.size <= 3  # the last ticks' snapshots may be waiting at the stop


def test_an_error_in_a_publish_stops_the_clock_and_says_why(alps):
    srv = SimulationServer(_world(alps), ServerConfig(clock="fast", time_scale=10.0))

    def publish(*args, **kwargs):
        raise RuntimeError("the publish broke")

    srv.publisher.publish = publish
    srv.start()
    try:
        assert srv.finished.wait(10.0)
        assert isinstance(srv.error, RuntimeError) and "the publish broke" in str(srv.error)
        ticks = srv.world.tick_count
        time.sleep(0.3)
        assert srv.world.tick_count == ticks  # the clock stopped
    finally:
        srv.stop(0.5)


def test_the_entities_centre_is_the_largest_groups():
    """Three entities over Sweden's coast and two over Boulder, 7,000 km apart (a scenario over two
    DEMs: the centre of all five lay mid-Atlantic, where `sortie client` saw nothing): the centre
    is the Swedish group's median, in any order; the count is all five."""
    lat = [57.5, 57.6, 57.7, 40.0, 40.1]
    lon = [11.9, 12.0, 12.1, -105.3, -105.2]
    centres = {entities_centre([lat[k] for k in p], [lon[k] for k in p]) for p in itertools.permutations(range(5))}
    assert centres == {(5, 57.6, 12.0)}
    # Two groups of the same size: the same one, whatever the order (the one holding the least cube)
    lat2, lon2 = [57.5, 57.6, 40.0, 40.1], [11.9, 12.0, -105.3, -105.2]
    centres = {entities_centre([lat2[k] for k in p], [lon2[k] for k in p]) for p in itertools.permutations(range(4))}
    assert len(centres) == 1
    # Entities 250 km apart (under the 300 km cubes' edge) are one group: the median of both.
    assert entities_centre([0.0, 0.0], [10.0, 12.25]) == (2, 0.0, 11.125)
    # A chain of entities 200 km apart over 2,000 km is one group too.
    chain = np.linspace(0.0, 18.0, 11)
    assert largest_group(np.zeros(11), chain).all()


def test_a_world_with_no_entities_is_watched_at_its_terrains_centre(alps):
    """No entity and no target area: GetWorld's centre is the middle of the terrain's first
    source (entity_count 0), where `sortie client` watches (it watched (0, 0), in the Atlantic)."""
    from client.cli import default_observe
    from terrain.terrain import source_boxes

    srv = SimulationServer(World(alps), ServerConfig(clock="paused"))
    info = srv.world_info()
    assert info.entity_count == 0
    (lat0, lon0, lat1, lon1), = source_boxes(alps.describe())
    assert (info.centre_lat_deg, info.centre_lon_deg) == (0.5 * (lat0 + lat1), 0.5 * (lon0 + lon1))
    lat, lon, _ = default_observe(info)
    assert 47.49 < lat < 47.51 and 9.49 < lon < 9.51
    # A source with no finite box (a description without one) is passed over.
    assert source_boxes([{"lat_min": None}, {"lat_min": "1", "lon_min": "2", "lat_max": "3", "lon_max": "4.5"}]) \
        == [(1.0, 2.0, 3.0, 4.5)]
