"""Client library (acceptance probe, round 31), against real in-process servers: a client
leaves no thread behind.

A client stream's messages are read by a gRPC thread blocked in the stream's queue until
the next one. SimClient.close() cancelled only the Watch and events streams, and a
controls or external stream's thread waited on after its call had ended: six threads
leaked per round of six bots that closed their client (the documented ``with`` block)
without closing their controls first, and `sortie bot` leaked one per bot whose server went
away.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
import traceback
from pathlib import Path

import pytest

from client import cli
from client.sim_client import SimClient, StreamEnded
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from sortie.errors import SortieError
from terrain.geodesy import geodetic_to_ecef

REPO = Path(__file__).resolve().parent.parent
SETTLE_S = 3.0  # a stream's thread ends at once; this allows for a loaded machine
TANK_LAT_DEG, TANK_LON_DEG = 47.29, 9.59


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _tank_world(alps) -> World:
    """A world of one controllable m1a2 (entity 1): cheap to run."""
    w = World(alps)
    w.spawn_ground(["tank1"], "m1a2", [TANK_LAT_DEG], [TANK_LON_DEG], 45.0, controllable=True)
    return w


def _threads_left(before: set, timeout_s: float = SETTLE_S) -> list[str]:
    """The threads alive ``timeout_s`` on that were not in ``before`` (none: at once), each
    with where it waits."""
    deadline = time.monotonic() + timeout_s
    while True:
        left = [t for t in threading.enumerate() if t not in before]
        if not left or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    frames = sys._current_frames()
    return [f"{t.name} in " + " <- ".join(f"{Path(f.filename).name}:{f.name}" for f in
                                           reversed(traceback.extract_stack(frames[t.ident])[-3:]))
            for t in left if t.ident in frames]


def _publish_one(gateway: SimClient):
    """A gateway's external stream with one entity published on it (left open)."""
    external = gateway.external()
    pos = geodetic_to_ecef(TANK_LAT_DEG, TANK_LON_DEG + 0.01, 3000.0)
    external.update("x:1", ecef_m=pos, vel_ecef_mps=(0.0, 0.0, 0.0), quat_wxyz=(1.0, 0.0, 0.0, 0.0), name="X1")
    return external


# The probe's bot process (tmp/probes/bots/leak.py), with a gateway's external stream beside
# the controls: the client's own thread count, exact in a process of its own.
ROUNDS_SCRIPT = """
import json, sys, threading, time
from client.sim_client import SimClient
from terrain.geodesy import geodetic_to_ecef

address = sys.argv[1]

def settled(n0):
    deadline = time.monotonic() + float(sys.argv[2])
    while threading.active_count() > n0 and time.monotonic() < deadline:
        time.sleep(0.05)
    return threading.active_count()

with SimClient(address) as sim:  # gRPC's process-wide threads start with the first call
    sim.wait_ready()
    sim.world()
n0 = threading.active_count()
counts = []
for r in range(3):
    for k in range(2):
        with SimClient(address) as sim:
            sim.join(f"drv-{k}", "driver")
            picture = sim.watch()
            sim.controls().drive(3.0)  # never closed: the client's close ends it
            picture.wait_for(lambda p: len(p) > 0, 5.0)
            sim.leave()
        with SimClient(address) as gw:
            gw.join(f"gw-{k}", "gateway")
            gw.external().update("x:1", ecef_m=geodetic_to_ecef(47.29, 9.6, 3000.0), vel_ecef_mps=(0, 0, 0),
                                 quat_wxyz=(1, 0, 0, 0))
    counts.append(settled(n0))
print(json.dumps({"start": n0, "rounds": counts, "names": sorted(t.name for t in threading.enumerate())}))
"""


def test_closing_a_client_ends_its_open_controls_and_external_streams(alps):
    """Three rounds of two drivers (join, watch, drive, leave) and two gateways (publish),
    each a ``with SimClient`` block that never closes its client stream: the client process's
    thread count is back at its start within SETTLE_S of every round (it grew by two a
    round here, six in the probe's, the streams' threads waiting forever)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    try:
        run = subprocess.run([sys.executable, "-c", ROUNDS_SCRIPT, srv.address, str(SETTLE_S)], cwd=REPO,
                             capture_output=True, text=True, timeout=60.0)
    finally:
        srv.stop(0.1)
        w.close()
    assert run.returncode == 0, run.stderr[-3000:]
    counts = json.loads(run.stdout.strip().splitlines()[-1])
    assert counts["rounds"] == [counts["start"]] * 3, counts


def test_a_closed_clients_streams_refuse_messages_with_stream_ended(alps):
    """After SimClient.close() a message for its controls or external stream, or the
    stream's close(), raises StreamEnded naming the stream (not gRPC's own exception), and
    no thread of the client is left (the server stopped: its threads end)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    try:
        before = set(threading.enumerate())
        with SimClient(srv.address) as driver, SimClient(srv.address) as gateway:
            driver.join("d", "driver")
            gateway.join("g", "gateway")
            controls, external = driver.controls(), _publish_one(gateway)
            controls.drive(2.0)
            driver.watch()
        with pytest.raises(StreamEnded, match=r"^SendControls: the stream has ended \(this client cancelled it.*"
                                              r"this message was not sent$"):
            controls.drive(3.0)
        with pytest.raises(StreamEnded, match=r"^PublishExternal: the stream has ended \(this client cancelled it"):
            external.close()
        srv.stop(0.1)  # its pool's threads too
        assert _threads_left(before) == []
    finally:
        srv.stop(0.1)
        w.close()


@pytest.mark.parametrize("end", ["exercise ended", "server gone"])
def test_a_client_stream_the_server_ended_leaves_no_thread_while_the_client_is_open(alps, end):
    """The server ends the exercise (its streams end OK) or goes away (the connection
    drops): a driver's controls and watch and a gateway's external stream, their clients
    still open, leave no thread within SETTLE_S (the streams' threads waited forever)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    driver, gateway = SimClient(srv.address), SimClient(srv.address)
    try:
        before = set(threading.enumerate())
        driver.join("d", "driver")
        gateway.join("g", "gateway")
        picture = driver.watch()
        controls, external = driver.controls(), _publish_one(gateway)
        controls.drive(2.0)
        assert picture.wait_for(lambda p: len(p) > 0, 5.0)
        if end == "exercise ended":
            srv.stop(0.5)
        else:
            srv.grpc.stop(0).wait()
            srv.stop(0.1)
        assert _threads_left(before) == []
        with pytest.raises(SortieError, match=r"^SendControls: the stream has ended|UNAVAILABLE"):
            controls.drive(3.0)  # a stream that has ended refuses a message, as before
    finally:
        driver.close()
        gateway.close()
        srv.stop(0.1)
        w.close()


def test_a_bot_whose_server_goes_away_leaves_no_thread(alps):
    """`sortie bot`'s path where its server goes away: once the bot's thread has ended,
    none of its client's threads is left (its controls stream's was, for good)."""
    w = _tank_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.start()
    results, stop = [], threading.Event()
    before = set(threading.enumerate())
    bot = threading.Thread(target=cli._bot, args=(srv.address, 0, "patrol", 2.0, 0.0, results, stop), daemon=True)
    bot.start()
    try:
        deadline = time.monotonic() + 10.0
        while w.entities[1].owner is None and time.monotonic() < deadline:
            time.sleep(0.05)
        assert w.entities[1].owner is not None, "the bot never took its agent"
        srv.grpc.stop(0).wait()  # no OK end of the streams: the connection drops
        bot.join(15.0)
        assert not bot.is_alive(), "the bot ran on after its server went away"
        srv.stop(0.1)
        assert _threads_left(before) == []
    finally:
        stop.set()
        srv.stop(0.1)
        w.close()
    (_, agent, what), = results
    assert agent == 1 and isinstance(what, cli.BotFailure), results
