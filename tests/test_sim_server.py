"""The simulation server over real gRPC on loopback: sessions and tokens, commands,
interest management, dead reckoning at the receiver, slow clients, hostile input,
shutdown. Real JSBSim, real ground vehicles, the Alps DEM."""

import math
import signal
import subprocess
import threading
import time

import grpc
import numpy as np
import pytest

from client.sim_client import SimClient
from fdm.aircraft import InitialConditions
from server.dead_reckoning import Extrapolator
from server.sim_server import ServerConfig, SimulationServer
from server.world import World
from sortie.errors import InvalidArgument, LimitExceeded, Unauthenticated
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc
from terrain.geodesy import geodetic_to_ecef
from server_helpers import PublishTap

REPO_SCENARIO = "data/scenarios/alps.toml"


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def small_world(alps):
    w = World(alps)
    w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     controllable=True, coalition="blue")
    w.spawn_aircraft("viper2", "f16", InitialConditions(47.32, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     controllable=True, coalition="blue")
    w.spawn_aircraft("cessna", "c172x", InitialConditions(47.45, 9.45, 1500.0, heading_deg=0.0, speed_mps=50.0),
                     route=[(47.50, 9.45, 1500.0), (47.50, 9.55, 1600.0), (47.45, 9.50, 1500.0)])
    w.spawn_ground(["c1", "c2", "c3"], "hmmwv", [47.2412, 47.2408, 47.2404], [9.5229, 9.5226, 9.5223], 27.0,
                   route=[(47.24, 9.522), (47.26, 9.537), (47.28, 9.552)], cruise_mps=10.0, spacing_m=50.0)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, controllable=True)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45)
    w.spawn_static("far-radar", "radar", 47.95, 9.95)  # ~ 60 km from the others
    return w


@pytest.fixture()
def server(alps):
    w = small_world(alps)
    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=2.0, vanished_timeout_s=1.5))
    srv.tap = PublishTap(srv.publisher)
    srv.start()
    yield srv
    srv.stop(0.5)


def test_observer_gets_a_snapshot_then_updates_and_sees_only_its_area(server):
    # Centre on the sam site, 20 km: everything but the far radar (and anything that flies out).
    centre = (47.35, 9.45, 20_000.0)
    with SimClient(server.address) as obs:
        assert obs.join("obs", "observer", observer=centre) == 0
        pic = obs.watch()
        assert pic.snapshot_received.wait(10.0)
        assert pic.wait_for(lambda p: p.updates >= 20, 20.0)
        names = {i.name for i in pic.infos.values()}
        assert "far-radar" not in names and {"sam1", "cessna", "c1", "tank1"} <= names
        # Never an entity outside the area (radius x (1 + hysteresis)) in the picture, checked
        # on what the server knew at the time of the last update.
        c = np.asarray(geodetic_to_ecef(centre[0], centre[1], 0.0)).reshape(3)
        snap = server.world.snapshot
        index = snap.index()
        for i in list(pic.infos):
            if i in index:
                assert np.linalg.norm(snap.ecef_m[index[i]] - c) <= 20_000.0 * 1.05 + 300.0
        # Always every entity well inside.
        inside = [int(i) for k, i in enumerate(snap.ids) if np.linalg.norm(snap.ecef_m[k] - c) < 15_000.0]
        assert set(inside) <= set(pic.infos)


def test_tokens_permissions_and_hostile_input(server):
    with SimClient(server.address) as obs, SimClient(server.address) as pilot, SimClient(server.address) as p2:
        obs.join("obs", "observer", observer=(47.35, 9.45, 100_000.0))
        pic = obs.watch()
        assert pic.snapshot_received.wait(10.0)
        agent = pilot.join("pilot", "pilot", agent_name="viper1")
        pilot.watch()  # an open stream keeps the session alive through the slow cases below
        other = p2.join("pilot2", "pilot")
        assert agent != other and other != 0
        stub = pb_grpc.SimulationServiceStub(pilot.channel)

        def send(*msgs):
            return stub.SendControls(iter(msgs), timeout=5.0)

        with pytest.raises(grpc.RpcError) as e:  # forged token
            send(pb.ControlInput(session_token="forged", agent_id=agent, stick=pb.StickControls(pitch=0.1)))
        assert e.value.code() == grpc.StatusCode.UNAUTHENTICATED
        with pytest.raises(grpc.RpcError) as e:  # someone else's agent
            send(pb.ControlInput(session_token=pilot.token, agent_id=other, stick=pb.StickControls(pitch=0.1)))
        assert e.value.code() == grpc.StatusCode.PERMISSION_DENIED
        with pytest.raises(grpc.RpcError) as e:  # NaN stick: the field is named
            send(pb.ControlInput(session_token=pilot.token, agent_id=agent, stick=pb.StickControls(pitch=math.nan)))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "pitch" in e.value.details()
        with pytest.raises(grpc.RpcError) as e:  # drive commands to an aircraft
            send(pb.ControlInput(session_token=pilot.token, agent_id=agent, drive=pb.DriveControls(speed_mps=3)))
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT
        with pytest.raises(grpc.RpcError) as e:  # oversized message: refused by gRPC before parsing
            stub.Leave(pb.LeaveRequest(session_token="x" * (65 * 1024 * 1024)), timeout=10.0)
        assert e.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        with pytest.raises(InvalidArgument, match="client_name"):
            SimClient(server.address).join("", "observer", observer=(47.0, 9.0, 1000.0))
        with pytest.raises(InvalidArgument, match="observer_radius_m"):
            SimClient(server.address).join("o", "observer", observer=(47.0, 9.0, 1e9))
        with pytest.raises(LimitExceeded):  # both controllable aircraft are taken
            SimClient(server.address).join("p3", "pilot")
        # Valid commands work after all that, and the observer was served throughout.
        before = pic.updates
        with pilot.controls() as c:
            c.stick(pitch=0.2, throttle=1.0)
        assert pic.wait_for(lambda p: p.updates > before + 5, 10.0)
        assert server.world.aircraft_controls(agent).pitch == 0.2


def test_receivers_dead_reckoning_stays_within_the_thresholds(server):
    # Every update the observer receives is replayed into an Extrapolator in arrival
    # order; at each network tick the server published, the receiver's extrapolation of
    # every entity it held must be within the entity's position threshold of the truth
    # (float32 velocities on the wire are modelled by the server, so no slack but 1 cm).
    with SimClient(server.address) as obs:
        obs.join("obs", "observer", observer=(47.35, 9.45, 100_000.0))
        log = []
        stub = pb_grpc.SimulationServiceStub(obs.channel)
        call = stub.Watch(pb.WatchRequest(session_token=obs.token))
        t_end = time.monotonic() + 8.0
        for u in call:
            log.append(u)
            if time.monotonic() > t_end:
                call.cancel()
                break
    dr = Extrapolator()
    checked = 0
    worst = 0.0
    # A slow read merges publishes into one WatchUpdate, so states apply at their own
    # time (when the server decided them), departures at their update's.
    timeline = sorted([(st.time_s, 0, st) for u in log for st in [i.state for i in u.entered] + list(u.states)]
                      + [(u.time_s, 1, list(u.left)) for u in log if u.left], key=lambda x: (x[0], x[1]))
    end_s = log[-1].time_s
    k = 0
    for snap in server.tap.snaps:
        while k < len(timeline) and timeline[k][0] <= snap.time_s + 1e-9:
            _, what, item = timeline[k]
            if what == 0:
                dr.receive(item.time_s, [item.entity_id], [[item.ecef_x_m, item.ecef_y_m, item.ecef_z_m]],
                           [list(item.velocity_ecef_mps)], [list(item.acceleration_ecef_mps2)],
                           [list(item.orientation_wxyz)], [list(item.angular_velocity_body_rps)],
                           item.dead_reckoning)
            else:
                dr.remove([i for i in item if i in set(dr.ids.tolist())])
            k += 1
        if snap.time_s > end_s or len(dr) == 0:
            continue  # before the stream started, or after it ended
        index = snap.index()
        ids = [int(i) for i in dr.ids if int(i) in index]
        pos, _ = dr.state(snap.time_s, ids)
        err = np.linalg.norm(pos - snap.ecef_m[[index[i] for i in ids]], axis=1)
        worst = max(worst, float(err.max()))
        checked += len(ids)
    assert checked > 200
    assert worst <= 1.0 + 0.01, worst
    # and dead reckoning saved most messages (manoeuvring aircraft, a convoy, statics)
    assert server.publisher.updates_sent < 0.5 * server.publisher.entity_samples


def test_a_stalled_client_does_not_hold_anyone_up(server):
    with SimClient(server.address) as slow, SimClient(server.address) as fast:
        slow.join("slow", "observer", observer=(47.35, 9.45, 100_000.0))
        fast.join("fast", "observer", observer=(47.35, 9.45, 100_000.0))
        stub = pb_grpc.SimulationServiceStub(slow.channel)
        stalled = stub.Watch(pb.WatchRequest(session_token=slow.token))
        next(stalled)  # the snapshot; then never read again
        pic = fast.watch()
        assert pic.snapshot_received.wait(10.0)
        t0_world, t0 = server.world.time_s, time.monotonic()
        s0, p0 = pic.states_received, server.publisher.updates_sent
        time.sleep(4.0)
        world_rate = (server.world.time_s - t0_world) / (time.monotonic() - t0)
        assert world_rate > 0.8 * server.config.time_scale  # the clock kept pace
        # The other client kept getting every update the server decided to send (it sees
        # every entity), and its picture is current.
        sent = server.publisher.updates_sent - p0
        assert sent >= 5 and pic.states_received - s0 >= 0.8 * sent
        assert server.world.time_s - pic.time_s < 2.0
        session = next(s for s in server.sessions.watching() if s.name == "slow")
        q = session.queue
        with q.cond:  # the stalled queue holds at most one entry per entity
            assert len(q._states) + len(q._enter) <= len(server.world.entities)
        stalled.cancel()


def test_leave_and_vanish_hand_the_agent_to_its_autopilot(server):
    c = SimClient(server.address)
    agent = c.join("pilot", "pilot", agent_name="viper2")
    with c.controls() as ctl:
        ctl.stick(roll=0.3)
    c.leave()
    e = server.world.entities[agent]
    assert e.owner is None and server.world.pilot_kind(agent) == "autopilot"  # autopilot holds heading, altitude, speed
    ctl = c.controls()  # the token no longer works
    ctl.stick(roll=0.0)
    with pytest.raises(Unauthenticated):
        ctl.close()
    # A driver who vanishes (no stream, no calls) loses the tank after the timeout.
    d = SimClient(server.address)
    tank = d.join("driver", "driver")
    assert server.world.entities[tank].owner is not None
    deadline = time.monotonic() + 10.0
    while server.world.entities[tank].owner is not None and time.monotonic() < deadline:
        time.sleep(0.2)
    assert server.world.entities[tank].owner is None
    kinds = [ev.kind for ev in server.world.events]
    assert "leave" in kinds and "vanished" in kinds
    c.close()
    d.close()


def test_events_stream_reports_joins(server):
    with SimClient(server.address) as watcher, SimClient(server.address) as joiner:
        watcher.join("w", "observer", observer=(47.35, 9.45, 1000.0))
        got = []

        def read():
            for ev in watcher.events():
                got.append(ev)
                if ev.kind == "join":
                    return

        t = threading.Thread(target=read, daemon=True)
        t.start()
        time.sleep(0.5)
        joiner.join("late", "driver")
        t.join(10.0)
        assert any(ev.kind == "join" for ev in got)


def test_server_command_runs_the_scenario_and_stops_on_sigterm(tmp_path):
    from server.process import free_port, sortie_command, wait_serving

    port = free_port()
    recording = tmp_path / "sortie.sortie"
    proc = subprocess.Popen([*sortie_command(), "server", "--scenario", REPO_SCENARIO, "--port", str(port),
                             "--record", str(recording)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        wait_serving(f"127.0.0.1:{port}", proc, timeout_s=60.0)
        with SimClient(f"127.0.0.1:{port}") as obs:
            obs.join("obs", "observer", observer=(47.4, 9.5, 100_000.0))
            pic = obs.watch()
            assert pic.wait_for(lambda p: len(p) >= 10, 20.0)
            assert obs.world().exercise_name.startswith("Alpine Shield")
        proc.send_signal(signal.SIGTERM)
        out, _ = proc.communicate(timeout=30.0)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == 0, out
    assert "stopped at world time" in out
    from server.recording import Recording

    with Recording(recording) as rec:  # recorded by default, closed whole on SIGTERM
        report = rec.check()
        assert report.ok and report.footer and report.ticks > 0 and report.entities == 12, report


def test_a_fast_mover_cannot_tunnel_through_a_thin_pillar():
    # Flat ground at 0 m with one post rising to 5000 m: a pillar ~22 m wide (posts
    # 0.0001 deg apart), far steeper than the 45-degree slopes the fdm's far-field
    # refresh assumes. An f16 at 3000 m MSL flies east straight at it at 250 m/s
    # (8 m per world tick). The world's segment check (tick to tick, against the
    # exact bilinear surface) stops it at the pillar: a crash within 50 m of it,
    # never the far side.
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
    from terrain.terrain import Terrain

    d = 0.0001
    h = np.zeros((201, 401), np.float32)
    h[100, 300] = 5000.0
    terrain = Terrain([Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, d, d))])
    pillar_lat, pillar_lon = 47.0 + 100 * d, 9.0 + 300 * d
    w = World(terrain)
    e = w.spawn_aircraft("fast", "f16", InitialConditions(pillar_lat, 9.0 + 20 * d, 3000.0, heading_deg=90.0,
                                                          speed_mps=250.0))
    for _ in range(12 * 30):  # 12 s: the pillar is 2.1 km ahead
        w.tick()
        if e.crashed:
            break
    assert e.crashed and w.air.fleet.aircraft[0].crashed
    crash = [ev for ev in w.events if ev.kind == "crash"][-1]
    assert crash.entity_id == e.id and crash.detail["reason"] == "terrain collision (segment)"
    assert abs(crash.lat_deg - pillar_lat) * 111_200 < 50.0
    assert abs(crash.lon_deg - pillar_lon) * 111_200 * math.cos(math.radians(47.01)) < 50.0
    assert crash.alt_msl_m < 3100.0


def test_watch_updates_assembled_from_bytes_parse_as_the_generated_message():
    from server.streaming import Pending, encode_info, encode_states, encode_watch_update

    z3 = [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    states = encode_states([5, 300], [1.5, 1.25], [[1e6, 2e6, 3e6], [4e6, 5e6, 6e6]], [[1.0, 2.0, 3.0], [4, 5, 6]],
                           z3, [[1.0, 0, 0, 0], [0, 1.0, 0, 0]], [[0.5, 0, 0], [0, 0, -0.25]], [4, 2])

    def state(i, t, p, v, q, w, alg):
        return pb.EntityState(entity_id=i, time_s=t, ecef_x_m=p[0], ecef_y_m=p[1], ecef_z_m=p[2],
                              velocity_ecef_mps=v, acceleration_ecef_mps2=[0, 0, 0], orientation_wxyz=q,
                              angular_velocity_body_rps=w, dead_reckoning=alg)

    s0 = state(5, 1.5, (1e6, 2e6, 3e6), [1, 2, 3], [1, 0, 0, 0], [0.5, 0, 0], 4)
    s1 = state(300, 1.25, (4e6, 5e6, 6e6), [4, 5, 6], [0, 1, 0, 0], [0, 0, -0.25], 2)
    info = encode_info((7, "viper", 1, "f16", "blue"))
    got = pb.WatchUpdate.FromString(encode_watch_update(Pending(2.0, True, [(info, states[0])], [9, 70000],
                                                                [states[1]], 8.0)))
    want = pb.WatchUpdate(time_s=2.0, snapshot=True, left=[9, 70000], states=[s1], time_scale=8.0,
                          entered=[pb.EntityInfo(entity_id=7, name="viper", kind=1, type="f16", coalition="blue",
                                                 state=s0)])
    assert got == want
    assert pb.WatchUpdate.FromString(encode_watch_update(Pending(3.0, False, [], [], [], 0.0))) == \
        pb.WatchUpdate(time_s=3.0, time_scale=0.0)


def test_an_error_in_the_world_tick_stops_the_clock_and_says_why(alps):
    """The clock thread records what stopped it (``sortie server`` then exits non-zero with
    it), instead of a world that silently stops moving; the server still stops cleanly."""
    w = World(alps)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45)
    ticks = []

    def before_tick(world):
        ticks.append(world.time_s)
        if len(ticks) == 5:
            raise RuntimeError("a broken tick")

    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=10.0), before_tick=before_tick)
    srv.start()
    try:
        assert srv.finished.wait(10.0)
        assert isinstance(srv.error, RuntimeError) and "a broken tick" in str(srv.error)
        assert len(ticks) == 5
    finally:
        srv.stop(0.5)
        w.close()


def test_ground_autopilot_holds_follow_every_change(alps):
    """Ground vehicles' autopilot holds (heading and speed), whose arrays the world caches
    between changes: a new target, a hold without a heading (keeps the one it has), a switch
    to direct driving and a removal are each obeyed from the next tick."""
    w = World(alps)
    try:
        ids = [e.id for e in w.spawn_ground(["a", "b", "c"], ["hmmwv"] * 3, [47.30, 47.31, 47.32],
                                            [9.60, 9.60, 9.60], [0.0, 0.0, 0.0])]

        def run(seconds):
            for _ in range(int(seconds * 30)):
                w.tick()

        def heading(i):
            return float(w.ground.heading_deg[w.ground.index_of([w.entities[i].ground_id])][0])

        w.command(ids[0], "autopilot", {"heading_deg": 90.0, "speed_mps": 5.0})
        w.command(ids[1], "autopilot", {"speed_mps": 4.0})  # no heading: keeps north
        run(20.0)
        assert abs(heading(ids[0]) - 90.0) < 1.0 and abs((heading(ids[1]) + 180.0) % 360.0 - 180.0) < 1.0
        w.command(ids[0], "autopilot", {"heading_deg": 200.0})  # the speed target stays
        w.command(ids[2], "autopilot", {"heading_deg": 300.0, "speed_mps": 3.0})
        run(25.0)
        assert abs(heading(ids[0]) - 200.0) < 1.0 and abs(heading(ids[2]) - 300.0) < 1.0
        assert abs(float(w.ground.speed_mps[w.ground.index_of([w.entities[ids[0]].ground_id])][0]) - 5.0) < 0.2
        w.command(ids[0], "drive", {"speed_mps": 0.0, "yaw_rate_dps": 0.0})  # out of the autopilot
        w.remove(ids[1])
        run(5.0)
        assert abs(heading(ids[0]) - 200.0) < 5.0
        assert abs(float(w.ground.speed_mps[w.ground.index_of([w.entities[ids[0]].ground_id])][0])) < 0.2
        assert abs(heading(ids[2]) - 300.0) < 1.0
    finally:
        w.close()
