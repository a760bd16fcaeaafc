"""gRPC stock-client probe, round 36: what its findings were, and what each test holds.

A stock client (grpcio-reflection's ProtoReflectionDescriptorDatabase, protobuf's descriptor
pool and message factory, raw bytes; none of Sortie's client code) against `terrain serve` and
`server`:

1. grpc.health.v1 (Check, List, Watch) and server reflection answered bytes that are not their
   messages with INTERNAL "Exception deserializing request!" (terrain service) or UNKNOWN
   "Unexpected <class DecodeError>" (simulation and replay servers, and the replay's
   ReplayService), each logged as an ERROR with its traceback: now INVALID_ARGUMENT naming
   `request` and the decoder's reason, nothing logged, the service serving on.
2. Reflection's file_containing_symbol of a method ("sortie.v1.TerrainService.GetHeights",
   which the reflection protocol names as a symbol: `grpcurl describe` of a method) answered
   NOT_FOUND: now the file that declares the method's service.
3. One client holding the simulation server's call limit of client streams open, without a
   message on them (no session is needed for that), had gRPC's maximum_concurrent_rpcs refuse
   the health check too ("Concurrent RPC limit exceeded!", naming no limit): the container was
   taken for dead. Now the server's own calls are admitted up to the limit and one more is
   refused with RESOURCE_EXHAUSTED naming `concurrent_calls` and the limit, while health and
   reflection are answered beside them; the streams' end frees their room.

Real gRPC on loopback (ephemeral ports), a real DEM (N47E009), a real simulation server.
"""

from __future__ import annotations

import logging
import queue
import time

import grpc
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc
from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

from server.grpc_common import ADMISSION_FIELD
from server.sim_server import ServerConfig, SimulationServer
from server.terrain_service import create_server
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc

from test_sim_fixes_streams import alps, small_world  # noqa: F401 (fixture)

NOT_A_MESSAGE = b"\xff\xff"  # a field-number varint cut short: no protobuf parser reads it
HEALTH = "/grpc.health.v1.Health/"
REFLECTION = "/grpc.reflection.v1alpha.ServerReflection/ServerReflectionInfo"
SERVING = health_pb2.HealthCheckResponse.SERVING


@pytest.fixture(scope="module")
def servers(alps):  # noqa: F811
    """(terrain service address, simulation server address), both started."""
    terrain, port = create_server(alps)
    terrain.start()
    sim = SimulationServer(small_world(alps), ServerConfig(clock="paused"))
    sim.start()
    yield f"127.0.0.1:{port}", sim.address
    sim.stop(0.5)
    terrain.stop(0).wait()


def _raw(channel, path: str, kind: str):
    identity = dict(request_serializer=lambda b: b, response_deserializer=lambda b: b)
    return getattr(channel, kind)(path, **identity)


def _code_and_details(call) -> tuple:
    with pytest.raises(grpc.RpcError) as info:
        call()
    return info.value.code(), info.value.details()


# -- 1. undecodable bytes to health and reflection ------------------------------------------------

@pytest.mark.parametrize("which", [0, 1], ids=["terrain", "simulation"])
def test_health_and_reflection_refuse_undecodable_bytes_naming_the_request(servers, which, caplog):
    address = servers[which]
    with caplog.at_level(logging.ERROR), grpc.insecure_channel(address) as channel:
        calls = {
            "Check": lambda: _raw(channel, HEALTH + "Check", "unary_unary")(NOT_A_MESSAGE, timeout=10),
            "List": lambda: _raw(channel, HEALTH + "List", "unary_unary")(NOT_A_MESSAGE, timeout=10),
            "Watch": lambda: list(_raw(channel, HEALTH + "Watch", "unary_stream")(NOT_A_MESSAGE, timeout=10)),
            "ServerReflectionInfo": lambda: list(
                _raw(channel, REFLECTION, "stream_stream")(iter([NOT_A_MESSAGE]), timeout=10)),
        }
        for method, call in calls.items():
            code, details = _code_and_details(call)
            assert code == grpc.StatusCode.INVALID_ARGUMENT, (method, code, details)
            assert details.startswith(f"request: does not decode as a {method} request: "), details
        # and they still answer what does decode
        reply = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(), timeout=10)
        assert reply.status == SERVING
        listed = next(reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(
            iter([reflection_pb2.ServerReflectionRequest(list_services="")]), timeout=10))
        assert "grpc.health.v1.Health" in {s.name for s in listed.list_services_response.service}
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR], caplog.text


# -- 2. reflection of a method symbol -------------------------------------------------------------

@pytest.mark.parametrize("which, method", [(0, "sortie.v1.TerrainService.GetHeights"),
                                           (1, "sortie.v1.SimulationService.SendControls"),
                                           (1, "grpc.health.v1.Health.Watch")], ids=["terrain", "sim", "health"])
def test_reflection_finds_the_file_declaring_a_method(servers, which, method):
    with grpc.insecure_channel(servers[which]) as channel:
        reply = next(reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(
            iter([reflection_pb2.ServerReflectionRequest(file_containing_symbol=method)]), timeout=10))
        assert reply.WhichOneof("message_response") == "file_descriptor_response", reply
        files = [descriptor_pb2.FileDescriptorProto.FromString(raw)
                 for raw in reply.file_descriptor_response.file_descriptor_proto]
        service_name, method_name = method.rsplit(".", 1)
        declared = {f"{f.package}.{s.name}.{m.name}" for f in files for s in f.service for m in s.method}
        assert method in declared
        # a stock client resolves it the way grpcurl does, and a symbol that is not there stays NOT_FOUND
        pool = descriptor_pool.DescriptorPool(ProtoReflectionDescriptorDatabase(channel))
        assert pool.FindMethodByName(method).containing_service.full_name == service_name
        missing = next(reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(
            iter([reflection_pb2.ServerReflectionRequest(file_containing_symbol=service_name + ".Nope")]),
            timeout=10))
        assert missing.error_response.error_code == grpc.StatusCode.NOT_FOUND.value[0]


# -- 3. idle client streams beyond the simulation server's call limit -----------------------------

LIMIT = 8  # calls the server under test admits (SimulationServer's max_workers)


def test_idle_client_streams_past_the_call_limit_are_refused_naming_it_and_health_still_answers(alps):  # noqa: F811
    srv = SimulationServer(small_world(alps), ServerConfig(clock="paused"), max_workers=LIMIT)
    srv.start()
    hostile, other = grpc.insecure_channel(srv.address), grpc.insecure_channel(srv.address)
    # A stock client's request class, from reflection: a stream that never sends one holds its call.
    pool = descriptor_pool.DescriptorPool(ProtoReflectionDescriptorDatabase(other))
    control_input = message_factory.GetMessageClass(pool.FindMessageTypeByName("sortie.v1.ControlInput"))
    send_controls = hostile.stream_unary("/sortie.v1.SimulationService/SendControls",
                                         request_serializer=control_input.SerializeToString,
                                         response_deserializer=pb.SendControlsResponse.FromString)
    feeds, streams = [], []
    try:
        for _ in range(LIMIT + 3):
            feed = queue.Queue()
            feeds.append(feed)
            streams.append(send_controls.future(iter(feed.get, None), timeout=60))
        deadline = time.monotonic() + 10.0
        while sum(s.done() for s in streams) < 3 and time.monotonic() < deadline:
            time.sleep(0.05)
        refused = [s for s in streams if s.done()]
        assert len(refused) == 3
        for s in refused:
            assert s.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
            assert s.details().startswith(f"{ADMISSION_FIELD}: {LIMIT + 1} exceeds the limit of {LIMIT}"), s.details()
        # health (before: "Concurrent RPC limit exceeded!") and reflection answer beside them
        health = health_pb2_grpc.HealthStub(other)
        for service in ("", "sortie.v1.SimulationService"):
            assert health.Check(health_pb2.HealthCheckRequest(service=service), timeout=5).status == SERVING
        assert pool.FindServiceByName("sortie.v1.SimulationService").methods_by_name["Join"]
        stub = pb_grpc.SimulationServiceStub(other)
        code, details = _code_and_details(lambda: stub.GetWorld(pb.GetWorldRequest(), timeout=5))
        assert code == grpc.StatusCode.RESOURCE_EXHAUSTED and ADMISSION_FIELD in details
        # the idle streams ending free their room
        for feed in feeds:
            feed.put(None)
        for s in streams:
            try:
                s.result(timeout=10)
            except grpc.RpcError:
                pass
        assert stub.GetWorld(pb.GetWorldRequest(), timeout=5).exercise_name is not None
        token = stub.Join(pb.JoinRequest(client_name="after", role=pb.ROLE_GATEWAY), timeout=10).session_token
        stub.Leave(pb.LeaveRequest(session_token=token), timeout=10)
    finally:
        for feed in feeds:
            feed.put(None)
        hostile.close()
        other.close()
        srv.stop(0.5)
