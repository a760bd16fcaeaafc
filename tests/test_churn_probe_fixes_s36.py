"""Fixes from the acceptance probe of the simulation server under churn and at its lifecycle's
edges (issue #4), each over real gRPC on loopback with a real world (JSBSim aircraft, ground
vehicles, the Alps DEM):

- An exercise that ends (duration_s) gives every watcher its last state: the final tick's world
  time and every entity within its dead-reckoning thresholds of the world's last snapshot (the
  picture stopped at its last update's, 1 s earlier and 213 m off for an f16 at 3 Hz); and a
  Watch that had not yet taken the last push when the server's end closed its queue dropped it.
- An entity removed while the clock is paused leaves every picture at once (it stayed on every
  watcher's picture until the clock ran again: a paused world's snapshot is its last tick's).
- A vanished session times out while the clock is paused (its agent was held, no other client
  could take it, until the clock ran again).
- A server that stops while clients take new Watches stops at once (it waited out its whole
  grace, 5 s: a Watch that began after the streams were closed was served by no clock and
  ended by nobody).
"""

import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from client.sim_client import SimClient
from server.sim_server import ServerConfig, SimulationServer
from terrain.geodesy import geodetic_to_ecef
from test_sim_fixes_streams import alps, small_world  # noqa: F401 - the alps fixture, the small world

WIDE = (47.35, 9.45, 150_000.0)  # an observer seeing every entity of the world below
REPO = Path(__file__).resolve().parents[1]


def _serve(alps, **config) -> SimulationServer:
    """The streams tests' small world (two aircraft, viper1 controllable; tank1, controllable; sam1), served."""
    srv = SimulationServer(small_world(alps), ServerConfig(**config))
    srv.start()
    return srv


@pytest.mark.parametrize("network_rate_hz, duration_s", [(3.0, 4.05), (30.0, 2.0)])
def test_an_exercise_that_ends_gives_every_watcher_its_last_state(alps, network_rate_hz, duration_s):
    """Fast x5, the world at 30 Hz. At 3 Hz the last tick (4.067 s) is no network tick: the
    pictures ended at 3.0 s, the f16 213 m and the Cessna 53 m from where the world left them.
    At 30 Hz every tick is one, but a tick where no entity is off its thresholds sends nothing:
    the pictures ended before the last tick too. Now every watcher ends at the world's last
    time, every entity within its dead-reckoning position threshold (+ 1 cm for the wire's
    float32 velocities), with no error."""
    srv = _serve(alps, clock="fast", time_scale=5.0, network_rate_hz=network_rate_hz, duration_s=duration_s)
    clients, pictures = [], []
    try:
        for k in range(3):
            c = SimClient(srv.address)
            clients.append(c)
            c.join(f"w{k}", "observer", observer=WIDE)
            pictures.append(c.watch())
        assert srv.finished.wait(30.0)
        last = srv.world.snapshot
        srv.stop(2.0)  # as `sortie server` does at the exercise's end
        for p in pictures:
            p.wait_for(lambda p: False, 5.0)
            assert not p.alive and p.error is None  # the end of the exercise
            assert p.time_s == pytest.approx(last.time_s, abs=1e-9)
            ids, pos, _ = p.state()
            assert sorted(ids.tolist()) == sorted(last.ids.tolist())
            row = last.index()
            for i, xyz in zip(ids.tolist(), pos):
                bound = srv.params_of(i).thresholds.position_m + 0.01
                off_m = float(np.linalg.norm(xyz - last.ecef_m[row[i]]))
                assert off_m <= bound, (i, off_m)
    finally:
        for c in clients:
            c.close()
        srv.stop(0.5)


def test_an_entity_removed_while_paused_leaves_every_picture(alps):
    """A gateway's external entity, removed while the clock is paused: it leaves the watching
    observer's picture within a second (it stayed there until the clock ran again), and a
    newcomer never sees it."""
    srv = _serve(alps, clock="realtime", network_rate_hz=10.0)
    obs, gw = SimClient(srv.address), SimClient(srv.address)
    try:
        obs.join("o", "observer", observer=WIDE)
        pic = obs.watch()
        gw.join("gw", "gateway")
        ext = gw.external()
        ext.update("x1", ecef_m=np.asarray(geodetic_to_ecef(47.35, 9.45, 3000.0)).ravel(), vel_ecef_mps=(0, 0, 0),
                   quat_wxyz=(1, 0, 0, 0), name="ext1")
        assert pic.wait_for(lambda p: any(i.name == "ext1" for i in p.infos.values()), 10.0)
        srv.set_clock("paused")
        time.sleep(0.3)
        paused_at = srv.world.time_s
        ext.remove("x1")
        assert ext.close() == 2
        assert pic.wait_for(lambda p: all(i.name != "ext1" for i in p.infos.values()), 2.0), \
            sorted(i.name for i in pic.infos.values())
        assert srv.world.time_s == paused_at  # still paused
        assert sorted(pic.dr.ids.tolist()) == sorted(srv.world.entities)
        ids, _, _ = pic.state()
        assert sorted(ids.tolist()) == sorted(srv.world.entities)
        # GetWorld's count (sortie client's default area) leaves it out too: it counted the
        # paused snapshot's entities, the removed one among them.
        assert obs.world().entity_count == len(srv.world.entities)
    finally:
        obs.close()
        gw.close()
        srv.stop(0.5)


def test_a_vanished_session_times_out_while_the_clock_is_paused(alps):
    """A driver that joined a paused exercise and vanished (no Leave, no stream): after the
    session timeout (1 s) its tank is free for another driver, the clock still paused (it was
    refused "is not free to control" until the clock ran again)."""
    srv = _serve(alps, clock="paused", network_rate_hz=10.0, vanished_timeout_s=1.0)
    try:
        gone = SimClient(srv.address)
        gone.join("gone", "driver", agent_name="tank1")
        gone.close()  # vanished: no Leave
        deadline = time.monotonic() + 5.0
        while len(srv.sessions) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert len(srv.sessions) == 0
        with SimClient(srv.address) as other:
            tank1 = next(e.id for e in srv.world.entities.values() if e.name == "tank1")
            assert other.join("other", "driver", agent_name="tank1") == tank1
        assert srv.world.tick_count == 1  # (the paused server's first tick only)
    finally:
        srv.stop(0.5)


def test_the_last_update_pushed_before_the_servers_end_is_sent(alps):
    """The server's end closes every Watch's queue right after the clock's last publish pushed
    to it (SimulationServer.stop); a Watch stream that had not yet taken that push ended without
    it. Here the push and the close come back to back, the interpreter held between them (a
    1 s switch interval) and the stream woken by the close alone: the stream still sends the
    pushed update (its world time) and ends with no error. A queue closed for its session's
    reason (a new Watch) hands nothing over."""
    from server.streaming import ClientQueue

    srv = _serve(alps, clock="paused", network_rate_hz=10.0)
    try:
        with SimClient(srv.address) as c:
            c.join("w", "observer", observer=WIDE)
            pic = c.watch()
            assert pic.snapshot_received.wait(10.0)
            (session,) = srv.sessions.watching()
            interval = sys.getswitchinterval()
            sys.setswitchinterval(1.0)
            try:
                # As the publisher pushes (its wake_all comes after); the close wakes the stream.
                session.queue.push(123.25, {}, [], {}, wake=False, time_scale=0.0)
                session.queue.close()
            finally:
                sys.setswitchinterval(interval)
            pic.wait_for(lambda p: False, 5.0)
            assert not pic.alive and pic.error is None
            assert pic.time_s == 123.25
    finally:
        srv.stop(0.5)
    q = ClientQueue()
    q.push(1.0, {}, [], {})
    q.close("superseded by a new Watch of this session")
    assert q.take(0.0) is None


REWATCHER = textwrap.dedent("""
    import sys, threading, time
    from client.sim_client import SimClient

    def loop(k):
        c = SimClient(sys.argv[1])
        c.join(f"rw{k}", "observer", observer=(47.35, 9.45, 150000.0))
        while True:  # a new Watch of the session every 2 ms, each superseding the one before
            try:
                c.watch()
            except Exception:
                return
            time.sleep(0.002)

    for k in range(6):
        threading.Thread(target=loop, args=(k,), daemon=True).start()
    print("ready", flush=True)
    time.sleep(60)
""")


def test_a_server_stopping_while_clients_take_new_watches_stops_at_once(alps, tmp_path):
    """Six sessions (another process) each taking a new Watch every 2 ms: stop(grace 5 s) took
    the whole grace in 6 of 6 tries (the Watches begun after its streams were closed were
    served by no clock and ended by nobody); now under 2.5 s. A Watch that begins once the
    servicer has closed (the server stopping) ends at once, with no error."""
    srv = _serve(alps, clock="realtime", network_rate_hz=20.0)
    script = tmp_path / "rewatcher.py"
    script.write_text(REWATCHER)
    proc = subprocess.Popen([sys.executable, str(script), srv.address], stdout=subprocess.PIPE, text=True,
                            cwd=str(REPO))
    try:
        assert proc.stdout.readline().strip() == "ready"
        time.sleep(1.5)
        t0 = time.monotonic()
        srv.stop(5.0)
        assert time.monotonic() - t0 < 2.5, time.monotonic() - t0
    finally:
        proc.kill()
        proc.wait()
        srv.stop(0.5)
    srv = _serve(alps, clock="realtime", network_rate_hz=20.0)
    try:
        with SimClient(srv.address) as c:
            c.join("late", "observer", observer=WIDE)
            srv.servicer.close()  # as stop() does, after it closed the streams open then
            pic = c.watch()
            pic.wait_for(lambda p: False, 2.0)
            assert not pic.alive and pic.error is None and pic.updates == 0
    finally:
        srv.stop(0.5)


def test_a_client_keeps_only_the_streams_still_running(alps):
    """A client taking a new Watch again and again (each supersedes the one before) keeps the
    ended pictures no longer (SimClient._streams held every one until close())."""
    srv = _serve(alps, clock="fast", time_scale=2.0)
    try:
        with SimClient(srv.address) as c:
            c.join("w", "observer", observer=WIDE)
            pictures = []
            for _ in range(6):
                pictures.append(c.watch())
                assert pictures[-1].wait_for(lambda p: len(p) > 0, 10.0)
            deadline = time.monotonic() + 10.0
            while any(p.alive for p in pictures[:-1]) and time.monotonic() < deadline:
                time.sleep(0.05)
            c.watch()  # keeping one more drops the ended ones
            assert len(c._streams) <= 2, len(c._streams)
    finally:
        srv.stop(0.5)


def test_top_speeds_of_a_few_vehicles_are_those_of_every_vehicle(alps):
    """fdm.ground.GroundVehicles.top_speed_mps(index): speed_limits_mps[1][index], bit for bit."""
    from fdm.ground import GroundVehicles

    types = ["m1a2", "hmmwv", "m2a3", "m1083"] * 5
    g = GroundVehicles(alps, np.full(20, 47.3), np.linspace(9.3, 9.6, 20), np.zeros(20), types)
    idx = np.array([3, 0, 19, 7, 7])
    assert np.array_equal(g.top_speed_mps(idx), g.speed_limits_mps[1][idx])
