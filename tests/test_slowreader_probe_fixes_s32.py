"""A slow Watch reader (acceptance probe, session 32), against real in-process servers.

Issue #4: "a slow or stalled client loses intermediate updates (never the latest state)". A
client-library Picture ran its listeners on the thread that reads the stream, so a listener
taking 0.5 s per update made the picture a slow reader: gRPC held what the server sent in
the client's own process (the server's latest-wins merge never started), and the picture
fell behind by 0.75-0.9 s per second (26 s behind after 40 s; 775 s in a 13-minute soak),
its state() dead-reckoned from ever older states. Now the stream's thread only reads and
applies updates, and listeners run on a thread of their own that is handed the updates
that came while it was busy merged into one (client.sim_client.PendingUpdate): each
entity's latest state, every entity that came or went, snapshots, in order.

Real parts: the Alps SRTM tile, a real world (the ground vehicle model), the gRPC service on
loopback with the real client library; PendingUpdate on real sortie.v1 messages.
"""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest

from client.sim_client import PendingUpdate, SimClient
from server.sim_server import DEFAULT_PARAMS, ServerConfig, SimulationServer, TypeParams
from server.world import World
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import geodetic_to_ecef

TANK = (47.29, 9.59)
WATCH_RADIUS_M = 10_000.0
LISTENER_S = 0.5  # the probe's slow listener (a renderer, a gateway on a busy host): per update
STREAM_HEARTBEAT_S = 0.05  # every vehicle's state on every network tick: a 20 Hz stream


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _serve(alps) -> SimulationServer:
    """One controllable m1a2 (entity 1), realtime, ground states sent at every network tick."""
    w = World(alps)
    w.spawn_ground(["tank1"], "m1a2", [TANK[0]], [TANK[1]], 45.0, controllable=True)
    ground = DEFAULT_PARAMS["ground"]
    params = dict(DEFAULT_PARAMS, ground=TypeParams(
        ground.aoi_radius_m, dataclasses.replace(ground.thresholds, heartbeat_s=STREAM_HEARTBEAT_S)))
    srv = SimulationServer(w, ServerConfig(clock="realtime", network_rate_hz=20.0, params=params))
    srv.start()
    return srv


def _stop(srv) -> None:
    srv.stop(0.1)
    srv.world.close()


# -- the picture keeps up whatever its listener takes ------------------------------------------------

def test_a_picture_with_a_slow_listener_stays_at_the_newest_state(alps):
    """The probe's case: a listener taking 0.5 s per update on a 20 Hz stream, 12 s. Bounds:
    the picture's newest update within 2 s of the world's time throughout (it fell 0.9 s
    behind per second: 10 s at the end), its dead-reckoned tank within 2 m of a listener-less
    reference picture's (a tank turning at 10 m/s, 6 deg/s: tens of metres off when behind),
    and every update a listener is given within 2 s of the world's time when it is given."""
    srv = _serve(alps)
    given: list = []  # (world time when the listener got it, the update's world time)

    def slow(picture, update):
        given.append((srv.world.time_s, update.time_s))
        time.sleep(LISTENER_S)

    try:
        with SimClient(srv.address) as driver, SimClient(srv.address) as ref:
            driver.join("d", "driver")
            with driver.controls() as controls:
                controls.drive(10.0, yaw_rate_dps=6.0)
            ref.join("ref", "observer", observer=(*TANK, WATCH_RADIUS_M))
            reference = ref.watch()
            picture = driver.watch(slow)
            assert picture.snapshot_received.wait(5.0) and reference.snapshot_received.wait(5.0)
            lags, offsets = [], []
            end = time.monotonic() + 12.0
            while time.monotonic() < end:
                time.sleep(0.25)
                lags.append(srv.world.time_s - picture.time_s)
                t = reference.now_s()
                _, mine, _ = picture.state(t, [1])
                _, theirs, _ = reference.state(t, [1])
                offsets.append(float(np.linalg.norm(mine - theirs)))
            assert picture.alive and picture.error is None
    finally:
        _stop(srv)
    assert max(lags) < 2.0, f"the picture fell behind the world by up to {max(lags):.1f} s"
    assert max(offsets) < 2.0, f"its tank up to {max(offsets):.1f} m from the reference picture's"
    ages = [now - t for now, t in given]
    assert len(given) >= 12.0 / LISTENER_S - 4 and max(ages) < 2.0, (len(given), max(ages))


def test_a_slow_listener_sees_every_come_and_go_in_order(alps):
    """Entities that come and go (a gateway's, 0.15 s apart, each in view for 0.15 s) while
    the listener takes 0.5 s an update, then the clock paused: the listener is given the
    snapshot first, each entity's coming before its going and none missed, the pause, and
    what it rebuilds from the updates (left, then entered) is the picture's own entities."""
    srv = _serve(alps)
    came, went, seen, scales = {}, {}, set(), []
    order = []  # ("snapshot" | "came" | "went", entity id) as given
    lock = threading.Lock()

    def slow(picture, update):
        with lock:
            if update.snapshot:
                order.append(("snapshot", 0))
                seen.clear()
            for i in update.left:
                order.append(("went", i))
                went[i] = len(order)
                seen.discard(i)
            for info in update.entered:
                order.append(("came", info.entity_id))
                came.setdefault(info.entity_id, len(order))
                seen.add(info.entity_id)
            if update.HasField("time_scale"):
                scales.append(update.time_scale)
        time.sleep(LISTENER_S)

    try:
        with SimClient(srv.address) as obs, SimClient(srv.address) as gateway:
            obs.join("obs", "observer", observer=(*TANK, WATCH_RADIUS_M))
            picture = obs.watch(slow)
            assert picture.snapshot_received.wait(5.0)
            gateway.join("gw", "gateway")
            external = gateway.external()
            pos = geodetic_to_ecef(TANK[0], TANK[1] + 0.01, 3000.0)
            ids = []
            for k in range(6):
                external.update(f"x:{k}", ecef_m=pos, vel_ecef_mps=(0.0, 0.0, 0.0), quat_wxyz=(1.0, 0.0, 0.0, 0.0),
                                name=f"X{k}")
                assert picture.wait_for(lambda p: len(p.infos) == 2, 5.0), "the external entity never came"
                ids.append(next(i for i in picture.infos if i != 1))
                time.sleep(0.15)
                external.remove(f"x:{k}")
                assert picture.wait_for(lambda p: len(p.infos) == 1, 5.0), "the external entity never went"
                time.sleep(0.15)
            external.close()
            srv.set_clock("paused")
            assert picture.wait_for(lambda p: p.time_scale == 0.0, 5.0)
            deadline = time.monotonic() + 10.0
            while time.monotonic() < deadline and not (scales and scales[-1] == 0.0):
                time.sleep(0.1)
            with lock:
                assert order[0] == ("snapshot", 0) and order.count(("snapshot", 0)) == 1, order
                for i in ids:
                    assert i in came and i in went and came[i] < went[i], (i, order)
                assert seen == set(picture.infos) == {1}, (seen, order)
                assert scales and scales[-1] == 0.0, scales
                assert len(order) >= 1 + 2 * len(ids)
    finally:
        _stop(srv)


def test_closing_the_client_drops_what_a_busy_listener_has_not_had(alps):
    """SimClient.close() while the listener is busy and updates are pending: the listener is
    not called again after its call under way, and the picture's threads end within a second
    of it (no thread of a closed client waits on)."""
    srv = _serve(alps)
    calls, started = [], threading.Event()
    before = set(threading.enumerate())

    def slow(picture, update):
        calls.append(time.monotonic())
        started.set()
        time.sleep(LISTENER_S)

    try:
        with SimClient(srv.address) as obs:
            obs.join("obs", "observer", observer=(*TANK, WATCH_RADIUS_M))
            picture = obs.watch(slow)
            assert started.wait(5.0)
            time.sleep(0.3)  # updates pending behind the call under way
        closed = time.monotonic()
        assert picture.wait_for(lambda p: not p.alive, LISTENER_S + 1.0)
        assert not picture.alive and picture.error is None
        assert not [t.name for t in threading.enumerate() if t not in before and t.name.startswith("watch")]
        assert len(calls) == 1 and calls[0] < closed
    finally:
        _stop(srv)


# -- PendingUpdate: the merge a slow listener is given ------------------------------------------------

def _state(entity_id: int, t: float) -> pb.EntityState:
    return pb.EntityState(entity_id=entity_id, time_s=t, ecef_x_m=t, velocity_ecef_mps=[1.0, 0.0, 0.0],
                          acceleration_ecef_mps2=[0.0, 0.0, 0.0], orientation_wxyz=[1.0, 0.0, 0.0, 0.0],
                          angular_velocity_body_rps=[0.0, 0.0, 0.0])


def _info(entity_id: int, t: float) -> pb.EntityInfo:
    return pb.EntityInfo(entity_id=entity_id, name=f"e{entity_id}", state=_state(entity_id, t))


def test_one_update_alone_is_handed_over_as_it_came():
    u = pb.WatchUpdate(time_s=1.0, snapshot=True, entered=[_info(1, 1.0)], time_scale=1.0)
    assert PendingUpdate(u).update() is u


def test_merged_updates_keep_the_latest_state_and_every_come_and_go():
    """Each entity's latest state (earlier ones lost), the latest time and clock rate (kept
    when a later update lacks it); a state before its entity left is dropped; an entity that
    left and came back is in both lists (applied left, then entered)."""
    p = PendingUpdate(pb.WatchUpdate(time_s=1.0, states=[_state(1, 1.0), _state(2, 1.0)], time_scale=1.0))
    assert p.merge(pb.WatchUpdate(time_s=1.05, states=[_state(1, 1.05)], left=[2], time_scale=0.0))
    assert p.merge(pb.WatchUpdate(time_s=1.1, states=[_state(1, 1.1)], entered=[_info(3, 1.1)]))
    assert p.merge(pb.WatchUpdate(time_s=1.15, left=[4]))
    assert p.merge(pb.WatchUpdate(time_s=1.2, entered=[_info(4, 1.2)], states=[_state(3, 1.2)]))
    u = p.update()
    assert p.count == 5 and u.time_s == 1.2 and not u.snapshot
    assert u.HasField("time_scale") and u.time_scale == 0.0
    assert {s.entity_id: s.time_s for s in u.states} == {1: 1.1, 3: 1.2}
    assert list(u.left) == [2, 4] and [i.entity_id for i in u.entered] == [3, 4]
    assert u.entered[0].state.time_s == 1.1 and u.entered[0].name == "e3"
    assert pb.WatchUpdate.FromString(u.SerializeToString()) == u


def test_a_come_and_go_or_a_snapshot_is_never_merged_away():
    """An entity that entered in the updates held and now leaves, and a snapshot, each start
    the next PendingUpdate (the listener sees it come, then go; each new picture)."""
    p = PendingUpdate(pb.WatchUpdate(time_s=1.0, entered=[_info(5, 1.0)]))
    assert not p.merge(pb.WatchUpdate(time_s=1.05, left=[5]))
    assert not p.merge(pb.WatchUpdate(time_s=1.05, snapshot=True, entered=[_info(1, 1.05)]))
    assert p.merge(pb.WatchUpdate(time_s=1.05, states=[_state(5, 1.05)]))
    assert not p.merge(pb.WatchUpdate(time_s=1.1, left=[5]))  # also once merged
    u = p.update()
    assert [i.entity_id for i in u.entered] == [5] and not u.left and u.time_s == 1.05
