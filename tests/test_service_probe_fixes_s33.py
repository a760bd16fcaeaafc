"""Terrain service probe, round 33: what its findings were, and the bound each test holds.

2. The terrain service failed its own health check when busy: with clients' LineOfSight calls in
   flight, `sortie health` (docker-compose's health check of the terrain containers) was refused
   RESOURCE_EXHAUSTED "Concurrent RPC limit exceeded!" (gRPC's maximum_concurrent_rpcs counted
   health with the queries) or ran out of its deadline queued behind the batches on the same
   thread pool (30 clients: 18 of 18 checks failed). Now the queries are admitted in their handlers
   (grpc_common.Admission: a refusal names `concurrent_calls` and the limit) on threads of their
   own, and health and reflection run outside the admission on spare threads, answered at once
   however busy the workers are.
3. Threads sharing one TerrainClient had calls refused far below the batch limits (12 threads
   of 20,000 rays each: 7 refused, a bare ServiceError): each split batch held up to 4 of the
   service's admission slots. Now one client keeps its calls in flight under a bound for all its
   threads, lowered to the limit a refusal names; a refusal is sent again after a backoff, and
   fails as LimitExceeded naming the limit once the attempts run out.

Real gRPC on loopback (ephemeral ports), real terrain: the SRTM tile, the procedural world.
"""

from __future__ import annotations

import threading
import time
from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc

import client.terrain_client as terrain_client
from client.terrain_client import TerrainClient
from server.terrain_service import SERVICE_NAME, create_server
from sortie.errors import LimitExceeded
from sortie.v1 import terrain_pb2 as pb
from sortie.v1 import terrain_pb2_grpc as pb_grpc
from terrain.mosaic import load_sources
from terrain.procedural import ProceduralTerrain
from terrain.terrain import Terrain

# One worker admits 4 calls (ADMITTED_CALLS_PER_WORKER); the long calls fill it.
ADMITTED = 4
# A health check of a service whose every admission slot is taken by long batches is answered
# within this (before: refused at once, or queued behind the batches past its deadline).
HEALTH_MAX_S = 0.5
# Long calls from one channel all reach the service within this.
SETTLE_S = 0.3
# Long calls: three 3-degree diagonals at 3500 m over the procedural world, about 500 new blocks
# (1-2 s of work each on one worker; tests/test_terrain_probe_fixes_s29.py).
_RNG = np.random.default_rng(20)
DIAG_LAT = _RNG.uniform(-60, 60, 3)
DIAG_LON = _RNG.uniform(-170, 170, 3)


def _long_request() -> pb.LineOfSightRequest:
    h = [3500.0] * len(DIAG_LAT)
    return pb.LineOfSightRequest(a_lat_deg=DIAG_LAT, a_lon_deg=DIAG_LON, a_height_msl_m=h,
                                 b_lat_deg=DIAG_LAT + 3.0, b_lon_deg=DIAG_LON + 3.0, b_height_msl_m=h)


@pytest.fixture
def busy():
    """A one-worker service over the procedural world with all its admission slots taken by
    long LineOfSight calls (cancelled at the end): (server, address, stub)."""
    server, port = create_server(Terrain([ProceduralTerrain(1)]), "127.0.0.1:0", max_workers=1)
    server.start()
    channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    stub = pb_grpc.TerrainServiceStub(channel)
    long_calls = [stub.LineOfSight.future(_long_request(), timeout=60) for _ in range(ADMITTED)]
    try:
        time.sleep(SETTLE_S)
        yield server, f"127.0.0.1:{port}", stub
        # A call whose client cancelled leaves the admission once its work stops (queued: at once).
        for call in long_calls:
            call.cancel()
        deadline = time.monotonic() + 10.0
        while server.admission.admitted:
            assert time.monotonic() < deadline, f"{server.admission.admitted} calls still admitted after cancelling"
            time.sleep(0.01)
        assert stub.GetHeights(pb.GetHeightsRequest(lat_deg=[45.0], lon_deg=[7.0]), timeout=10).height_msl_m
    finally:
        channel.close()
        server.stop(0).wait()


def test_a_busy_service_answers_its_health_check_at_once_and_refuses_queries_naming_the_limit(busy):
    server, address, stub = busy
    with grpc.insecure_channel(address) as channel:  # a fresh channel, as `sortie health` opens
        health = health_pb2_grpc.HealthStub(channel)
        for service in ("", SERVICE_NAME) * 5:
            t0 = time.monotonic()
            reply = health.Check(health_pb2.HealthCheckRequest(service=service), timeout=2 * HEALTH_MAX_S)
            took = time.monotonic() - t0
            assert reply.status == health_pb2.HealthCheckResponse.SERVING
            assert took < HEALTH_MAX_S, f"health Check of {service!r} took {took:.3f} s on a busy service"
    assert server.admission.admitted == ADMITTED
    with pytest.raises(grpc.RpcError) as info:
        stub.GetHeights(pb.GetHeightsRequest(lat_deg=[45.0], lon_deg=[7.0]), timeout=10)
    assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert info.value.details().startswith(f"concurrent_calls: {ADMITTED + 1} exceeds the limit of {ADMITTED} (")
    assert server.stats.snapshot()["GetHeights"][2] == {"RESOURCE_EXHAUSTED": 1}


def test_a_refusal_outlasting_the_retries_is_a_limit_exceeded_naming_the_limit(busy, monkeypatch):
    server, address, _ = busy
    monkeypatch.setattr(terrain_client, "ADMISSION_RETRY_MAX_ATTEMPTS", 2, raising=False)  # before: no retry
    with TerrainClient(address, timeout_s=10.0) as client:
        with pytest.raises(LimitExceeded) as info:
            client.heights([45.0], [7.0])
        assert (info.value.field, info.value.limit) == ("concurrent_calls", ADMITTED)
        assert client.retried_refusals == 1
        assert client.slots.limit == ADMITTED  # lowered to the limit the refusal named
    assert server.admission.admitted == ADMITTED


def test_threads_sharing_one_client_are_not_refused_below_the_batch_limits(hgt_alps: Path):
    """The probe's pattern, scaled to a one-worker service (4 calls admitted): 12 threads share a
    client, each a LineOfSight of 20,000 rays (3 chunks; the limit is 100,000). Every call is
    answered, as in process (before: refused RESOURCE_EXHAUSTED, a ServiceError)."""
    terrain = Terrain(load_sources([hgt_alps]))
    rng = np.random.default_rng(33)
    n = 20_000
    a_lat, a_lon = rng.uniform(47.05, 47.9, n), rng.uniform(9.05, 9.9, n)
    rays = (a_lat, a_lon, np.full(n, 1500.0), a_lat + 0.05, a_lon + 0.05, rng.uniform(500.0, 3000.0, n))
    expected = terrain.line_of_sight(*rays)
    server, port = create_server(terrain, "127.0.0.1:0", max_workers=1)
    server.start()
    threads_n = 12
    barrier = threading.Barrier(threads_n)
    results: list = [None] * threads_n
    try:
        with TerrainClient(f"127.0.0.1:{port}", timeout_s=30.0) as client:
            def run(i: int) -> None:
                barrier.wait(timeout=10)
                try:
                    got = client.line_of_sight(*rays)
                    results[i] = (np.array_equal(got.visible, expected.visible)
                                  and np.array_equal(got.status, expected.status))
                except Exception as exc:  # noqa: BLE001 - reported below, per thread
                    results[i] = f"{type(exc).__name__}: {exc}"

            threads = [threading.Thread(target=run, args=(i,)) for i in range(threads_n)]
            for t in threads:
                t.start()
            for t in threads:
                t.join(timeout=120)
            assert results == [True] * threads_n
            assert client.slots.limit == ADMITTED and client.slots.in_flight == 0
    finally:
        server.stop(0).wait()
