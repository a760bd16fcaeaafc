"""Fixes from the acceptance probe of the simulation server's streams, each over real gRPC on
loopback: events streams hold no thread (joins, leaves and commands stay fast however many are
open), a server started paused shows the whole picture, error messages cut bad values short,
undecodable requests are INVALID_ARGUMENT, the advertised clock rate is the achieved one, and
a stream ended by its own session says why (ABORTED)."""

import statistics
import threading
import time

import grpc
import numpy as np
import pytest

from client.sim_client import SimClient, StreamAborted
from fdm.aircraft import InitialConditions
from server.sim_server import ServerConfig, SimulationServer
from server.sim_service import MAX_EVENT_STREAMS, MAX_NAME_CHARS
from server.world import World
from sortie.errors import MAX_MESSAGE_CHARS, InvalidArgument, LimitExceeded, message_of, shown
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc

WIDE = (47.35, 9.45, 150_000.0)  # an observer seeing every entity of the world below


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def small_world(alps):
    w = World(alps)
    w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     controllable=True, coalition="blue")
    w.spawn_aircraft("cessna", "c172x", InitialConditions(47.45, 9.45, 1500.0, heading_deg=0.0, speed_mps=50.0),
                     route=[(47.50, 9.45, 1500.0), (47.50, 9.55, 1600.0)])
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0, controllable=True)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45)
    return w


def serve(alps, **config):
    srv = SimulationServer(small_world(alps), ServerConfig(**config))
    srv.start()
    return srv


@pytest.fixture()
def server(alps):
    srv = serve(alps, clock="fast", time_scale=2.0)
    yield srv
    srv.stop(0.5)


# -- H1: events streams wait on the event loop, not on the handlers' thread pool ------------------

def _join_leave_s(address: str) -> float:
    with SimClient(address) as c:
        t0 = time.monotonic()
        c.join("probe", "observer", observer=WIDE)
        c.leave()
        return time.monotonic() - t0


def test_open_events_streams_do_not_slow_joins_leaves_or_commands(server):
    # 24 streams: each used to hold one of the 8 pool threads for 0.25 s at a time, so a Join
    # or a Leave waited ~0.75 s behind them (measured 1.0-1.3 s with 40).
    n = 24
    readers, got = [], []
    for k in range(n // MAX_EVENT_STREAMS):
        c = SimClient(server.address)
        c.join(f"reader{k}", "observer", observer=WIDE)
        readers.append(c)
        for _ in range(MAX_EVENT_STREAMS):
            stream = c.events()

            def read(stream=stream):
                try:
                    for ev in stream:
                        got.append((ev.kind, time.monotonic()))
                except Exception:  # noqa: BLE001 - cancelled at the end
                    pass

            threading.Thread(target=read, daemon=True).start()
    try:
        time.sleep(1.0)  # every stream open and waiting
        t_first = time.monotonic()
        took = [_join_leave_s(server.address) for _ in range(3)]
        assert statistics.median(took) < 0.15, took
        # Every reader hears each join promptly (woken when the world emits, not polled).
        deadline = time.monotonic() + 5.0
        while sum(kind == "join" for kind, _ in got) < 3 * n and time.monotonic() < deadline:
            time.sleep(0.05)
        joins = [t for kind, t in got if kind == "join"]
        assert len(joins) >= 3 * n
        assert max(joins) - t_first < 1.5
        # A pilot's commands at 20 Hz all get through, and the stream closes at once.
        with SimClient(server.address) as pilot:
            pilot.join("pilot", "pilot", agent_name="viper1")
            ctl = pilot.controls()
            for _ in range(20):
                ctl.stick(roll=0.1)
                time.sleep(0.05)
            t0 = time.monotonic()
            assert ctl.close() == 20
            assert time.monotonic() - t0 < 0.5
    finally:
        for c in readers:
            c.close()


def test_events_streams_per_session_are_limited(server):
    with SimClient(server.address) as c:
        c.join("many", "observer", observer=WIDE)
        stub = pb_grpc.SimulationServiceStub(c.channel)
        calls = [stub.WatchEvents(pb.WatchEventsRequest(session_token=c.token)) for _ in range(MAX_EVENT_STREAMS)]
        time.sleep(0.5)  # all open on the server
        extra = stub.WatchEvents(pb.WatchEventsRequest(session_token=c.token), timeout=5.0)
        with pytest.raises(grpc.RpcError) as info:
            next(extra)
        assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
        assert "events_streams" in info.value.details()
        calls[0].cancel()
        time.sleep(0.5)  # one closed: room for another
        again = stub.WatchEvents(pb.WatchEventsRequest(session_token=c.token), timeout=10.0)
        time.sleep(0.5)
        with SimClient(server.address) as other:
            other.join("joiner", "observer", observer=WIDE)
            assert any(ev.kind == "join" for ev in again)  # DEADLINE_EXCEEDED if it never came
        for call in calls[1:] + [again]:
            call.cancel()


# -- H2: a server started paused --------------------------------------------------------------

def test_a_server_started_paused_shows_every_entity_and_the_pilots_own_agent(alps):
    srv = serve(alps, clock="paused")
    try:
        world = srv.world
        with SimClient(srv.address) as obs, SimClient(srv.address) as pilot:
            obs.join("obs", "observer", observer=WIDE)
            pic = obs.watch()
            assert pic.snapshot_received.wait(10.0)
            assert pic.wait_for(lambda p: len(p) == len(world.entities), 5.0), (len(pic), len(world.entities))
            assert pic.time_scale == 0.0
            agent = pilot.join("pilot", "pilot", agent_name="viper1")
            own = pilot.watch()
            assert own.wait_for(lambda p: agent in p.infos, 5.0)
            t = world.time_s
            assert t == pytest.approx(world.dt)  # the first tick only: the clock stands still
            time.sleep(0.5)
            assert world.time_s == t and obs.world().clock == "paused"
            assert obs.world().time_scale == 0.0  # world seconds per wall second, as the stream says
            srv.set_clock("fast")
            deadline = time.monotonic() + 10.0
            while world.time_s < t + 1.0 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert world.time_s >= t + 1.0
            assert pic.wait_for(lambda p: p.time_scale > 0, 5.0)
    finally:
        srv.stop(0.5)


# -- M2: error messages cut bad values short ----------------------------------------------------

def test_long_names_are_invalid_argument_with_the_value_cut_short(server):
    stub = pb_grpc.SimulationServiceStub(grpc.insecure_channel(server.address, options=[
        ("grpc.max_send_message_length", 64 * 1024 * 1024)]))
    for n in (20_000, 5_000_000):
        for request, field in ((pb.JoinRequest(client_name="x" * n, role=pb.ROLE_OBSERVER, observer_radius_m=10.0),
                                "client_name"),
                               (pb.JoinRequest(client_name="ok", role=pb.ROLE_PILOT, agent_name="y" * n),
                                "agent_name")):
            with pytest.raises(grpc.RpcError) as info:
                stub.Join(request, timeout=20.0)
            details = info.value.details()
            assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT, details[:200]
            assert details.startswith(f"{field}: ") and f"({n:,} characters)" in details
            assert len(details) < 500
    # An agent name at the limit is looked up as before.
    with pytest.raises(grpc.RpcError) as info:
        stub.Join(pb.JoinRequest(client_name="ok", role=pb.ROLE_PILOT, agent_name="z" * MAX_NAME_CHARS), timeout=10)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "no agent of this name" in info.value.details()


def test_errors_show_values_cut_short_and_messages_bounded():
    assert str(InvalidArgument("f", "bad", value="abc")) == "f: bad (got 'abc')"
    long = InvalidArgument("name", "too long", value="n" * 10_000)
    assert str(long) == f"name: too long (got {shown('n' * 10_000)})" and "(10,000 characters)" in str(long)
    assert len(str(long)) < 320 and long.value == "n" * 10_000  # the value itself is kept
    assert "(300 items)" in shown(list(range(300)))
    assert message_of(LimitExceeded("x", 2, 1)) == "x: 2 exceeds the limit of 1"
    assert len(message_of("m" * 100_000)) < MAX_MESSAGE_CHARS + 60


# -- L1: undecodable requests -----------------------------------------------------------------

@pytest.mark.parametrize("method, stream_in, stream_out", [
    ("Join", False, False), ("Leave", False, False), ("GetWorld", False, False), ("Watch", False, True),
    ("WatchEvents", False, True), ("SendControls", True, False), ("PublishExternal", True, False)])
def test_undecodable_request_bytes_are_invalid_argument(server, method, stream_in, stream_out):
    channel = grpc.insecure_channel(server.address)
    path = f"/sortie.v1.SimulationService/{method}"
    garbage = b"\x0a\x7fshort"  # field 1, 127 bytes long, of which 5 came
    kind = {(False, False): channel.unary_unary, (False, True): channel.unary_stream,
            (True, False): channel.stream_unary}[(stream_in, stream_out)]
    call = kind(path, request_serializer=lambda b: b, response_deserializer=lambda b: b)
    with pytest.raises(grpc.RpcError) as info:
        if stream_out:
            list(call(garbage, timeout=10.0))
        else:
            call(iter([garbage]) if stream_in else garbage, timeout=10.0)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT, info.value.details()
    assert info.value.details().startswith("request: does not decode as a ")
    channel.close()


# -- M1: the advertised clock rate is the achieved one -------------------------------------------

def test_a_fast_clock_that_cannot_keep_up_advertises_the_rate_it_achieves(alps):
    srv = serve(alps, clock="fast", time_scale=1000.0)  # far beyond what this world ticks at
    try:
        with SimClient(srv.address) as c:
            c.join("gw", "gateway")
            pic = c.watch()
            assert pic.snapshot_received.wait(10.0)
            time.sleep(2.5)  # a measuring window
            w0, t0 = c.world(), time.monotonic()
            time.sleep(2.0)
            w1 = c.world()
            achieved = (w1.time_s - w0.time_s) / (time.monotonic() - t0)
            assert achieved < 500.0  # the premise: it cannot keep up
            assert w1.time_scale == pytest.approx(achieved, rel=0.35), (w1.time_scale, achieved)
            assert pic.time_scale == pytest.approx(achieved, rel=0.35)  # the stream's clock follows it
            # The receiver's estimate of world time stays near the world's (it ran seconds ahead).
            assert abs(pic.now_s() - c.world().time_s) < 0.2 * achieved
    finally:
        srv.stop(0.5)


def test_a_clock_that_keeps_up_advertises_its_set_rate(server):
    with SimClient(server.address) as c:
        c.join("o", "observer", observer=WIDE)
        pic = c.watch()
        time.sleep(2.0)
        assert c.world().time_scale == 2.0 and pic.time_scale == 2.0


# -- L4: a stream its own session ends says why ---------------------------------------------------

def test_a_superseded_watch_and_a_left_session_end_aborted_with_the_reason(server):
    with SimClient(server.address) as c:
        c.join("w", "observer", observer=WIDE)
        first = c.watch()
        assert first.snapshot_received.wait(10.0)
        second = c.watch()
        assert second.snapshot_received.wait(10.0)
        assert first.wait_for(lambda p: False, 2.0) is False and not first.alive
        assert isinstance(first.error, StreamAborted) and first.error.code == grpc.StatusCode.ABORTED
        assert "superseded by a new Watch of this session" in str(first.error)
        assert second.alive
        got = []

        def read():
            try:
                for ev in c.events():
                    got.append(ev)
            except StreamAborted as exc:
                got.append(exc)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        time.sleep(0.5)
        c.leave()
        reader.join(5.0)
        assert not reader.is_alive() and isinstance(got[-1], StreamAborted) and "session left" in str(got[-1])
        second.wait_for(lambda p: False, 2.0)
        assert not second.alive and isinstance(second.error, StreamAborted) and "session left" in str(second.error)


def test_a_server_that_stops_ends_the_watch_with_no_error(alps):
    srv = serve(alps, clock="fast", time_scale=2.0)
    with SimClient(srv.address) as c:
        c.join("w", "observer", observer=WIDE)
        pic = c.watch()
        assert pic.snapshot_received.wait(10.0)
        srv.stop(0.5)
        pic.wait_for(lambda p: False, 3.0)
        assert not pic.alive and pic.error is None  # the end of the exercise


def test_a_server_that_stops_ends_events_and_controls_streams_at_once_with_no_error(alps):
    """An acceptance probe: with an events stream and a pilot's controls stream open, SIGTERM
    took gRPC's whole grace (5 s) and ended both UNAVAILABLE. Now they end OK, at once."""
    srv = serve(alps, clock="fast", time_scale=2.0)
    ended = {}
    with SimClient(srv.address) as c, SimClient(srv.address) as pilot:
        c.join("w", "observer", observer=WIDE)
        events = c.events()
        pilot.join("p", "pilot", agent_name="viper1")
        controls = pilot.controls()
        controls.autopilot(heading_deg=10.0)

        def read():
            try:
                for _ in events:
                    pass
                ended["events"] = "OK"
            except Exception as exc:  # noqa: BLE001 - the test reports it
                ended["events"] = repr(exc)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        time.sleep(0.5)
        t0 = time.monotonic()
        srv.stop(5.0)
        assert time.monotonic() - t0 < 2.0
        reader.join(3.0)
        assert ended.get("events") == "OK"
        assert controls.close() == 1  # the stream's response: the one command accepted


def test_a_session_whose_only_stream_is_its_controls_is_alive_while_it_is_open(alps):
    """An acceptance probe: drivers with only a controls stream open were declared vanished
    (and their agents removed) 3 s after their last message, their connection alive. An open
    controls stream that has carried the session's messages keeps it; once closed, the
    timeout runs."""
    srv = serve(alps, clock="fast", time_scale=2.0, vanished_timeout_s=1.0)
    try:
        with SimClient(srv.address) as pilot:
            pilot.join("p", "pilot", agent_name="viper1")
            controls = pilot.controls()
            controls.autopilot(heading_deg=10.0)
            time.sleep(3.0)
            assert len(srv.sessions) == 1  # still there, 3 s after its last message
            assert controls.close() == 1
            deadline = time.monotonic() + 6.0
            while len(srv.sessions) and time.monotonic() < deadline:
                time.sleep(0.1)
            assert len(srv.sessions) == 0  # closed: it vanished after the timeout
    finally:
        srv.stop(0.5)


def test_world_info_says_the_observer_radius_a_join_accepts(alps):
    """WorldInfo.observer_radius_max_m is the scenario's observer area limit, and `sortie client`'s
    default area (client.cli.default_observe) keeps within it; a Join at that radius is accepted."""
    from client.cli import default_observe
    from server.sim_server import DEFAULT_PARAMS, TypeParams

    params = dict(DEFAULT_PARAMS)
    params["observer"] = TypeParams(50_000.0, DEFAULT_PARAMS["observer"].thresholds)
    srv = serve(alps, clock="fast", time_scale=2.0, params=params)
    try:
        with SimClient(srv.address) as c:
            c.wait_ready()
            info = c.world()
            assert info.observer_radius_max_m == 50_000.0
            lat, lon, radius = default_observe(info)
            assert radius == 50_000.0
            c.join("watcher", "observer", observer=(47.35, 9.45, radius))
            c.leave()
    finally:
        srv.stop(0.5)


def test_world_info_says_where_the_entities_are(alps):
    """With no target area, WorldInfo's entity_count and centre (the median of the entities'
    positions) give `sortie client`'s default area: it sees the world's entities, not (0, 0)."""
    from client.cli import default_observe
    from server.sim_server import entities_centre

    srv = serve(alps, clock="fast", time_scale=2.0)
    try:
        with SimClient(srv.address) as c:
            c.wait_ready()
            deadline = time.monotonic() + 10.0
            info = c.world()
            while info.entity_count == 0 and time.monotonic() < deadline:
                time.sleep(0.05)
                info = c.world()
            assert not info.target_areas and info.entity_count == 4
            lat, lon, radius = default_observe(info)
            assert 47.28 < lat < 47.47 and 9.28 < lon < 9.62
            c.join("watcher", "observer", observer=(lat, lon, radius))
            picture = c.watch()
            deadline = time.monotonic() + 10.0
            while len(picture) < 4 and time.monotonic() < deadline:
                time.sleep(0.05)
            assert len(picture) == 4
            c.leave()
    finally:
        srv.stop(0.5)
    # Across the antimeridian the median is among them, not half a world away.
    count, lat, lon = entities_centre([10.0, 10.2, 9.9], [179.9, -179.8, 179.7])
    assert count == 3 and abs(lat - 10.0) < 1e-9 and abs(abs(lon) - 179.9) < 1e-9
    assert entities_centre([np.nan], [0.0]) == (0, 0.0, 0.0)
