"""The simulation server admits every call its sessions may hold open within their documented
limits (acceptance probe: at a 512-call limit, 256 observers with a Watch and an events stream
each filled it, and health, Join and Leave were refused "Concurrent RPC limit exceeded!")."""

import grpc

from fdm.aircraft import FlatTerrain
from server.sim_server import ServerConfig, SimulationServer
from server.sim_service import MAX_SESSIONS
from server.world import World
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc


def test_a_server_full_of_sessions_and_their_streams_still_answers_health_join_and_leave():
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    w = World(FlatTerrain(400.0))
    w.spawn_static("site", "sam_site", 47.0, 9.0)
    srv = SimulationServer(w, ServerConfig(clock="paused"))
    srv.start()
    channels = [grpc.insecure_channel(srv.address) for _ in range(4)]
    streams = []
    try:
        stubs = [pb_grpc.SimulationServiceStub(c) for c in channels]
        tokens = []
        for i in range(MAX_SESSIONS - 1):  # one left for the late Join below
            stub = stubs[i % len(stubs)]
            t = stub.Join(pb.JoinRequest(client_name=f"o{i}", role=pb.ROLE_OBSERVER, observer_lat_deg=47.0,
                                         observer_lon_deg=9.0, observer_radius_m=10_000.0), timeout=10).session_token
            tokens.append(t)
            streams.append(stub.Watch(pb.WatchRequest(session_token=t)))
            streams.append(stub.WatchEvents(pb.WatchEventsRequest(session_token=t)))
            streams.append(stub.WatchEvents(pb.WatchEventsRequest(session_token=t)))
        for s in streams[::97]:  # they are open
            assert not s.done()
        health = health_pb2_grpc.HealthStub(channels[0]).Check(
            health_pb2.HealthCheckRequest(service="sortie.v1.SimulationService"), timeout=10)
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        late = stubs[1].Join(pb.JoinRequest(client_name="late", role=pb.ROLE_OBSERVER, observer_lat_deg=47.0,
                                            observer_lon_deg=9.0, observer_radius_m=10_000.0), timeout=10)
        assert late.session_token
        stubs[2].Leave(pb.LeaveRequest(session_token=tokens[5]), timeout=10)
        assert stubs[3].GetWorld(pb.GetWorldRequest(), timeout=10).exercise_name is not None
    finally:
        for s in streams:
            s.cancel()
        for c in channels:
            c.close()
        srv.stop(0.5)
        w.close()
