"""A new Watch taking a session over while the publisher is deciding that session's view.

The publisher (clock thread) reads what each session saw, decides the new views, then records
and queues them; a Watch (event loop) may take the session over at any point in between, as
the loop runs whenever the clock thread lets go of the interpreter (its compiled passes do).
The new stream's first update must be its whole picture: every entity it sees entered. Before
Session.begin_stream and the publisher's view_lock, the publisher overwrote the new stream's
reset, and its first update was a snapshot with nothing entered (seen once in about a hundred
superseding Watches by the acceptance probe; forced here every time)."""

import numpy as np
import pytest

import server.streaming as streaming
from fdm.aircraft import FlatTerrain
from server.dead_reckoning import DeadReckoner, Thresholds
from server.sim_service import Session
from server.streaming import ClientQueue, Publisher
from server.world import World
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import geodetic_to_ecef


@pytest.fixture()
def scene():
    world = World(FlatTerrain(400.0))
    n = 6
    world.spawn_ground([f"g{k}" for k in range(n)], ["hmmwv"] * n, np.full(n, 47.0), 9.0 + 0.001 * np.arange(n),
                       np.zeros(n))
    world.tick()
    session = Session("token", "watcher", pb.ROLE_OBSERVER,
                      observer_ecef=np.array(geodetic_to_ecef(47.0, 9.0, 400.0), np.float64).ravel(),
                      radius_m=20_000.0)
    yield world, session
    world.close()


def _ids(update):
    return sorted(info.entity_id for info in update.entered)


def _decoded(queue):
    p = queue.take(0.0)
    return None if p is None else pb.WatchUpdate.FromString(streaming.encode_watch_update(p))


def test_a_watch_taking_over_mid_publish_gets_the_whole_picture(scene, monkeypatch):
    world, s = scene
    publisher = Publisher(DeadReckoner(), lambda i: Thresholds())
    first = ClientQueue()
    assert s.begin_stream(first) is None
    publisher.publish(world.snapshot, world.infos, [s])
    everyone = sorted(world.snapshot.ids.tolist())
    assert _ids(_decoded(first)) == everyone  # the first stream's snapshot

    world.tick()
    second = ClientQueue()
    changes = streaming.changes

    def changes_then_take_over(*args):  # the event loop runs a new Watch in the middle
        out = changes(*args)
        assert s.begin_stream(second) is first
        return out

    monkeypatch.setattr(streaming, "changes", changes_then_take_over)
    publisher.publish(world.snapshot, world.infos, [s])
    monkeypatch.setattr(streaming, "changes", changes)
    assert second.take(0.0) is None  # nothing decided for the new stream's view yet

    world.tick()
    publisher.publish(world.snapshot, world.infos, [s])
    update = _decoded(second)
    assert update.snapshot
    assert _ids(update) == everyone  # the whole picture, entered
    assert sorted(s.visible_ids.tolist()) == everyone
