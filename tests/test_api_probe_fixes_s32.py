"""API fuzz probe, round 32: what its findings were, and the bound each test holds.

1. An open grpc.health.v1 Watch held a graceful stop for the whole grace (`terrain serve` and
   `server`, SIGTERM + grace): now the Watch gets NOT_SERVING and ends (OK), and the stop
   takes what the in-flight calls take.
2. A HeightEncoding out of range (3, 99, -1) was served as FLOAT32 by GetTile and GetRegion:
   now INVALID_ARGUMENT naming `encoding`, the value and the encodings there are.
3. ReplayControl{play: false} played and {pause: false} paused: now INVALID_ARGUMENT naming
   the field, the replay left as it was.
4. An external entity's unset dead_reckoning (0) was taken as FPW and an unset coalition as
   neutral while the refusals of other values listed only 1-9 and blue/red/neutral: the
   refusals now say what unset means.
5. grpc.health.v1 Health/List, which reflection advertises, was UNIMPLEMENTED (and logged an
   ERROR traceback per call on the simulation and replay servers): now every registered name
   with its status.
6. A refusal of 1e308 (a numpy scalar) printed a RuntimeWarning (overflow) in bound_text.

Real gRPC on loopback (ephemeral ports), real DEMs, a real store import, real JSBSim, a real
recording.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

from client.sim_client import SimClient
from server.terrain_service import SERVICE_NAME as TERRAIN_SERVICE
from server.terrain_service import create_server
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import recording_pb2_grpc as rpb_grpc
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc
from sortie.v1 import terrain_pb2 as tpb
from sortie.v1 import terrain_pb2_grpc as tpb_grpc
from terrain.geodesy import geodetic_to_ecef

from test_sim_fixes_streams import alps, serve  # noqa: F401 (fixture)

SIM_SERVICE = "sortie.v1.SimulationService"
# The grace each stop is given, and the most it may take with a Watch open and nothing else in
# flight: before, the stop took the whole grace (6.0 s in the probe).
GRACE_S = 6.0
STOP_WITH_WATCH_MAX_S = 2.0
SERVING, NOT_SERVING = health_pb2.HealthCheckResponse.SERVING, health_pb2.HealthCheckResponse.NOT_SERVING


def _watch(address: str, service: str) -> tuple[list, threading.Event, threading.Thread]:
    """A Watch of ``service`` read on a thread: (statuses received then "END <code>", the
    event set once the first status came, the thread)."""
    seen, first = [], threading.Event()
    channel = grpc.insecure_channel(address)

    def read():
        try:
            for reply in health_pb2_grpc.HealthStub(channel).Watch(
                    health_pb2.HealthCheckRequest(service=service), timeout=30):
                seen.append(reply.status)
                first.set()
            seen.append("END OK")
        except grpc.RpcError as exc:
            seen.append(f"END {exc.code().name}")
        finally:
            first.set()
            channel.close()

    thread = threading.Thread(target=read, daemon=True)
    thread.start()
    return seen, first, thread


def _stop_seconds_with_watches(address: str, names: tuple[str, ...], stop) -> tuple[float, list]:
    watches = [_watch(address, name) for name in names]
    for _, first, _ in watches:
        assert first.wait(10.0)
    t0 = time.monotonic()
    stop()
    took = time.monotonic() - t0
    for _, _, thread in watches:
        thread.join(5.0)
    return took, [seen for seen, _, _ in watches]


# -- 1. a Watch no longer holds the graceful stop --------------------------------------------------

def test_an_open_health_watch_no_longer_holds_a_terrain_services_stop(alps):  # noqa: F811
    server, port = create_server(alps)
    server.start()
    took, seen = _stop_seconds_with_watches(f"127.0.0.1:{port}", ("", TERRAIN_SERVICE),
                                            lambda: server.stop(GRACE_S).wait(30.0))
    assert took < STOP_WITH_WATCH_MAX_S, f"stop with two Watch streams open took {took:.2f} s of {GRACE_S} s grace"
    assert seen == [[SERVING, NOT_SERVING, "END OK"]] * 2


def test_an_open_health_watch_no_longer_holds_a_simulation_servers_stop(alps):  # noqa: F811
    srv = serve(alps, clock="fast", time_scale=2.0)
    took, seen = _stop_seconds_with_watches(srv.address, ("", SIM_SERVICE), lambda: srv.stop(GRACE_S))
    assert took < STOP_WITH_WATCH_MAX_S, f"stop with two Watch streams open took {took:.2f} s of {GRACE_S} s grace"
    assert seen == [[SERVING, NOT_SERVING, "END OK"]] * 2


# -- 5. Health/List ----------------------------------------------------------------------------------

def _health_list(address: str) -> dict:
    with grpc.insecure_channel(address) as channel:
        reply = health_pb2_grpc.HealthStub(channel).List(health_pb2.HealthListRequest(), timeout=10)
    return {name: s.status for name, s in reply.statuses.items()}


def test_health_list_answers_every_registered_name_on_every_kind_of_server(alps, caplog):  # noqa: F811
    server, port = create_server(alps)
    server.start()
    try:
        assert _health_list(f"127.0.0.1:{port}") == {"": SERVING, TERRAIN_SERVICE: SERVING}
        with grpc.insecure_channel(f"127.0.0.1:{port}") as channel:  # Check as before: NOT_FOUND, no details
            with pytest.raises(grpc.RpcError) as info:
                health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service="bogus"), timeout=10)
        assert info.value.code() == grpc.StatusCode.NOT_FOUND and not info.value.details()
    finally:
        server.stop(0).wait()
    srv = serve(alps, clock="fast", time_scale=2.0)
    try:
        with caplog.at_level(logging.ERROR):
            assert _health_list(srv.address) == {"": SERVING, SIM_SERVICE: SERVING}
        assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text
    finally:
        srv.stop(0.5)


# -- 2. HeightEncoding out of range ------------------------------------------------------------------

@pytest.fixture(scope="module")
def store_address(tmp_path_factory, asc_boulder):
    from terrain.store import StoreSource, TerrainStore
    from terrain.store_import import import_dems
    from terrain.terrain import Terrain

    tmp = tmp_path_factory.mktemp("store")
    import_dems([asc_boulder], tmp / "store")
    store = TerrainStore(tmp / "store")
    server, port = create_server(Terrain([StoreSource(store)]))
    server.start()
    yield f"127.0.0.1:{port}", store
    server.stop(0).wait()


@pytest.mark.parametrize("encoding", [3, 99, -1])
def test_a_height_encoding_out_of_range_is_refused_naming_it(store_address, encoding):
    from terrain.quadtree import cell_at

    address, store = store_address
    lat, lon = 40.02, -105.3  # on the Boulder DEM
    with grpc.insecure_channel(address) as channel:
        stub = tpb_grpc.TerrainServiceStub(channel)
        cell = int(cell_at(lat, lon, store.cell_depth(0)))
        for ok in (0, 1, 2):  # the encodings there are still answer
            assert stub.GetTile(tpb.GetTileRequest(cell_id=cell, encoding=ok), timeout=10).rows > 0
        calls = {"GetTile": lambda: stub.GetTile(tpb.GetTileRequest(cell_id=cell, encoding=encoding), timeout=10),
                 "GetRegion": lambda: stub.GetRegion(tpb.GetRegionRequest(
                     level=0, lat_min_deg=lat, lon_min_deg=lon, lat_max_deg=lat + 0.01, lon_max_deg=lon + 0.01,
                     encoding=encoding), timeout=10)}
        for name, call in calls.items():
            with pytest.raises(grpc.RpcError) as info:
                call()
            assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT, (name, info.value.details())
            assert info.value.details() == (
                "encoding: must be one of HEIGHT_ENCODING_UNSPECIFIED (0), HEIGHT_ENCODING_FLOAT32 (2), "
                f"HEIGHT_ENCODING_ZSTD_CM (1) (got {encoding})"), name


# -- 3. ReplayControl's bools -----------------------------------------------------------------------

@pytest.fixture(scope="module")
def replay(tmp_path_factory):
    from server.replay import ReplayServer
    from test_recording import record_alps

    path = tmp_path_factory.mktemp("replay") / "alps.sortie"
    record_alps(path, ticks=60, inputs=False)
    server = ReplayServer(path, speed=1.0, playing=False)
    server.start()
    yield server
    server.stop(0.5)


def test_replay_control_refuses_play_false_and_pause_false_and_keeps_its_state(replay):
    with grpc.insecure_channel(replay.address) as channel:
        stub = rpb_grpc.ReplayServiceStub(channel)
        assert stub.Control(rpb.ReplayControl(pause=True), timeout=10).playing is False
        for field, opposite in (("play", "pause"), ("pause", "play")):
            if field == "pause":
                assert stub.Control(rpb.ReplayControl(play=True), timeout=10).playing is True
            playing = stub.GetStatus(rpb.GetReplayStatusRequest(), timeout=10).playing
            with pytest.raises(grpc.RpcError) as info:
                stub.Control(rpb.ReplayControl(**{field: False}), timeout=10)
            assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
            assert info.value.details() == (f"{field}: must be true (false is not an action; set {opposite}: true "
                                             f"to {opposite}) (got False)")
            assert stub.GetStatus(rpb.GetReplayStatusRequest(), timeout=10).playing is playing
        assert stub.Control(rpb.ReplayControl(pause=True), timeout=10).playing is False


# -- 4. an external entity's unset fields -------------------------------------------------------------

def test_external_refusals_say_what_unset_dead_reckoning_and_coalition_mean(alps):  # noqa: F811
    srv = serve(alps, clock="fast", time_scale=2.0)
    try:
        with SimClient(srv.address) as gateway:
            gateway.join("g", "gateway")
            stub = pb_grpc.SimulationServiceStub(gateway.channel)
            x, y, z = (float(v) for v in geodetic_to_ecef([47.4], [9.5], [3000.0])[0])

            def publish(external_id, dead_reckoning, coalition):
                msg = pb.ExternalEntityUpdate(
                    session_token=gateway.token, external_id=external_id, name=external_id, kind=1,
                    coalition=coalition, state=pb.EntityState(
                        ecef_x_m=x, ecef_y_m=y, ecef_z_m=z, velocity_ecef_mps=[100, 0, 0],
                        orientation_wxyz=[1, 0, 0, 0], dead_reckoning=dead_reckoning))
                try:
                    return stub.PublishExternal(iter([msg]), timeout=10).accepted
                except grpc.RpcError as exc:
                    assert exc.code() == grpc.StatusCode.INVALID_ARGUMENT, exc.details()
                    return exc.details()

            assert publish("unset", 0, "") == 1  # unset: FPW, neutral (existing gateways keep working)
            entity = next(e for e in srv.world.entities.values() if e.name == "unset")
            assert entity.coalition == "neutral" and srv.world._external[entity.id].algorithm == 2  # FPW
            codes = "1 STATIC, 2 FPW, 3 RPW, 4 RVW, 5 FVW, 6 FPB, 7 RPB, 8 RVB, 9 FVB"
            for code in (10, 99, -1):
                assert publish(f"dr{code}", code, "red") == (
                    f"state.dead_reckoning: must be a DIS dead-reckoning code ({codes}), or unset (0) for FPW "
                    f"(got {code})")
            for coalition in ("green", "BLUE"):
                assert publish(coalition, 2, coalition) == (
                    f"coalition: must be one of blue, red, neutral, or unset (\"\") for neutral (got '{coalition}')")
    finally:
        srv.stop(0.5)


# -- 6. bound_text of huge values ------------------------------------------------------------------

@pytest.mark.parametrize("bound, refused, shown", [
    (np.float64(1e5), np.float64(1e308), "100000"),
    (np.float64(-1e5), np.float64(-1e308), "-100000"),
    (np.float64(1e308), np.float64(-1e308), "1e+308"),
    (18.77568, 18.8, "18.7757"),       # the cases it was made for, unchanged
    (18.77568, 18.7757, "18.77568"),
    (5.0, float("nan"), "5.0"),
])
def test_bound_text_compares_without_overflow(bound, refused, shown):
    from sortie.errors import bound_text

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow's RuntimeWarning fails the test
        assert bound_text(bound, refused) == shown
