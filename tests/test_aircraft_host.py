"""Aircraft hosts: the world's aircraft in worker processes fly exactly as in process,
worker errors reach the caller typed, and a dead worker loses only its own aircraft."""

from __future__ import annotations

import functools
import os
import pickle
import signal
import time

import numpy as np
import pytest

from fdm.aircraft import FlatTerrain, InitialConditions
from server.aircraft_host import LocalAircraftHost, ProcessAircraftHost
from server.scenario import ScenarioError
from server.world import World
from sortie.errors import InvalidArgument, LimitExceeded, NotFound

FLAT = functools.partial(FlatTerrain, 400.0)
DT = 1.0 / 120.0


@pytest.fixture(scope="module")
def workers():
    host = ProcessAircraftHost(FLAT, DT, workers=2)
    yield host
    host.close()


def _exercise(world: World) -> list:
    """Spawn a mix of aircraft and pilots, command them mid-run; every snapshot."""
    world.spawn_aircraft("hold", "f16", InitialConditions(47.0, 9.0, 2500.0, heading_deg=30.0, speed_mps=200.0),
                         hold={"heading_deg": 90.0, "alt_msl_m": 2600.0})
    world.spawn_aircraft("route", "c172x", InitialConditions(47.01, 9.0, 1200.0, heading_deg=0.0, speed_mps=50.0),
                         route=[(47.05, 9.02, 1300.0), (47.05, 9.1, 1300.0)], speed_mps=50.0)
    stick = world.spawn_aircraft("stick", "f16", InitialConditions(47.02, 9.0, 3000.0, heading_deg=180.0,
                                                                   speed_mps=220.0), controllable=True)
    ap = world.spawn_aircraft("ap", "c172x", InitialConditions(47.03, 9.0, 1500.0, heading_deg=270.0,
                                                              speed_mps=55.0), controllable=True)
    snaps = []
    for k in range(120):
        if k == 10:
            world.command(stick.id, "stick", {"pitch": 0.05, "roll": -0.2, "throttle": 0.9})
            world.command(ap.id, "autopilot", {"heading_deg": 200.0, "alt_msl_m": 1600.0})
        if k == 60:
            world.claim(stick.id, "someone")
            world.release(stick.id)  # to the autopilot, holding what it has now
        world.tick()
        snaps.append(world.snapshot)
    return snaps


def test_workers_fly_bit_identical_to_in_process(workers):
    local = World(FlatTerrain(400.0), aircraft_host=LocalAircraftHost(FlatTerrain(400.0), DT))
    remote = World(FlatTerrain(400.0), aircraft_host=workers)
    try:
        a, b = _exercise(local), _exercise(remote)
        assert len(workers) == 4
        assert sorted(len(w.ids) for w in workers._workers) == [2, 2]  # spread over both
        for sa, sb in zip(a, b):
            oa, ob = np.argsort(sa.ids), np.argsort(sb.ids)
            assert np.array_equal(sa.ids[oa], sb.ids[ob])
            for name in ("ecef_m", "vel_ecef_mps", "acc_ecef_mps2", "quat_ecef2body", "body_rates_rps"):
                assert np.array_equal(getattr(sa, name)[oa], getattr(sb, name)[ob]), name
        stick = next(e for e in remote.entities.values() if e.name == "stick")
        assert remote.pilot_kind(stick.id) == "autopilot"
        assert local.aircraft_controls(stick.id) == remote.aircraft_controls(stick.id)
    finally:
        for e in list(remote.entities):
            remote.remove(e)
        remote.tick()  # the removals reach the workers


def test_worker_errors_reach_the_caller_typed(workers):
    world = World(FlatTerrain(400.0), aircraft_host=workers)
    with pytest.raises(NotFound, match="nosuchplane"):
        world.spawn_aircraft("x", "nosuchplane", InitialConditions(47.0, 9.0, 2000.0))
    with pytest.raises(InvalidArgument) as info:
        world.spawn_aircraft("y", "f16", InitialConditions(47.0, 9.0, 2000.0, speed_mps=-5.0))
    assert info.value.field.endswith("speed_mps")
    with pytest.raises(NotFound):
        workers.controls(12345)
    assert len(workers) == 0  # nothing half-made


@pytest.mark.parametrize("where", ["local", "workers"])
def test_a_batch_spawn_answers_per_aircraft_and_flies_as_one_by_one(where):
    """World.spawn_aircraft_many (both workers load and trim their share at once): an entity
    per spec, or the typed error of the one that cannot start (a J3 Cub trimmed at 220 m/s),
    the others spawned regardless; the same ids and trajectories as spawning them one by
    one; a name twice in a batch refuses the whole batch."""
    from fdm.aircraft import TrimFailed

    def specs():
        return [dict(name=f"f{k}", type_="f16", ic=InitialConditions(47.0 + 0.01 * k, 9.0, 2500.0, heading_deg=30.0 * k,
                                                                      speed_mps=200.0),
                     hold={"heading_deg": 30.0 * k, "alt_msl_m": 2500.0}) for k in range(3)] + [
            dict(name="cub", type_="J3Cub", ic=InitialConditions(47.1, 9.0, 2000.0, speed_mps=220.0)),
            dict(name="c172", type_="c172x", ic=InitialConditions(47.2, 9.0, 1500.0, speed_mps=50.0),
                 route=[(47.25, 9.02, 1500.0)], speed_mps=50.0, controllable=True)]

    # A host of its own: a world begins its next tick as soon as one ends, so a host shared
    # with a previous world would hand this one that world's last tick first.
    host = ProcessAircraftHost(FLAT, DT, workers=2) if where == "workers" else LocalAircraftHost(FlatTerrain(400.0), DT)
    batch = World(FlatTerrain(400.0), aircraft_host=host)
    single = World(FlatTerrain(400.0), aircraft_host=LocalAircraftHost(FlatTerrain(400.0), DT))
    try:
        got = batch.spawn_aircraft_many(specs())
        assert isinstance(got[3], TrimFailed) and "J3Cub" in str(got[3])
        assert [e.name for e in got if not isinstance(e, Exception)] == ["f0", "f1", "f2", "c172"]
        assert len(host) == 4
        if where == "workers":  # shared out in turn: f0 f2 c172 on one, f1 and the refused cub on the other
            assert sorted(len(w.ids) for w in host._workers) == [1, 3]
        for spec in specs():
            if spec["name"] != "cub":
                single.spawn_aircraft(**{k: v for k, v in spec.items() if k not in ("name", "type_", "ic")},
                                      name=spec["name"], type_=spec["type_"], ic=spec["ic"])
        by_name = {e.name: e for e in single.entities.values()}
        for _ in range(20):
            batch.tick()
            single.tick()
        a, b = batch.snapshot, single.snapshot
        for e in batch.entities.values():
            ka, kb = int(np.flatnonzero(a.ids == e.id)[0]), int(np.flatnonzero(b.ids == by_name[e.name].id)[0])
            assert np.array_equal(a.ecef_m[ka], b.ecef_m[kb]), e.name
        with pytest.raises(InvalidArgument, match="twice"):
            batch.spawn_aircraft_many([specs()[0] | {"name": "dup"}, specs()[1] | {"name": "dup"}])
        assert len(host) == 4
    finally:
        batch.close()
        single.close()


def test_sortie_errors_survive_pickling():
    for exc in (InvalidArgument("lat_deg", "must be finite", index=3, value=float("nan")),
                LimitExceeded("points", 10, 5), ScenarioError("agents[1].type", "unknown", value="x", file="a.toml")):
        back = pickle.loads(pickle.dumps(exc))
        assert type(back) is type(exc) and str(back) == str(exc)


def test_a_dead_worker_loses_only_its_aircraft():
    host = ProcessAircraftHost(FLAT, DT, workers=2)
    world = World(FlatTerrain(400.0), aircraft_host=host)
    try:
        for i in range(4):
            world.spawn_aircraft(f"a{i}", "f16", InitialConditions(47.0 + 0.01 * i, 9.0, 2000.0, speed_mps=200.0),
                                 hold={"alt_msl_m": 2000.0})
        world.tick()
        victim = host._workers[0]
        doomed = set(victim.ids)
        os.kill(victim.process.pid, signal.SIGKILL)
        victim.process.join(5.0)
        events = []
        for _ in range(3):  # the tick under way when it died may still have been answered
            events += world.tick()
            if events:
                break
        gone = {ev.entity_id for ev in events if ev.kind == "remove"}
        assert gone == doomed and all(ev.detail["reason"] == "fdm worker exited" for ev in events)
        assert set(world.entities) == {1, 2, 3, 4} - doomed
        before = world.snapshot.ecef_m.copy()
        for _ in range(3):
            world.tick()
        assert world.snapshot.ids.size == 2 and not np.array_equal(before, world.snapshot.ecef_m)  # still flying
        world.spawn_aircraft("late", "f16", InitialConditions(47.1, 9.0, 2000.0, speed_mps=200.0))  # survivor
        assert host._where[world.entities[max(world.entities)].id] is host._workers[1]
    finally:
        t0 = time.monotonic()
        world.close()
        assert time.monotonic() - t0 < 10.0
        assert not any(w.process.is_alive() for w in host._workers)


def test_workers_run_at_a_lower_cpu_priority(workers):
    """Off the critical path, the workers yield the CPU to the server's process (nice +WORKER_NICE)."""
    from server.aircraft_host import WORKER_NICE

    mine = os.getpriority(os.PRIO_PROCESS, 0)
    assert WORKER_NICE > 0
    for pid in workers.pids:
        assert os.getpriority(os.PRIO_PROCESS, pid) == min(mine + WORKER_NICE, 19)


@pytest.mark.parametrize("nice", [-1, 20, 2.5, True, "10"])
def test_worker_nice_out_of_range_is_rejected(nice):
    with pytest.raises(InvalidArgument, match="aircraft_worker_nice"):
        ProcessAircraftHost(FLAT, DT, workers=1, nice=nice)
