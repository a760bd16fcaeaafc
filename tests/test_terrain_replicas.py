"""Terrain replicas behind one TerrainClient: round robin, health-aware, retried.

Two real ``sortie terrain serve`` processes on loopback; client threads query
heights without pause while one replica is killed (SIGKILL: calls in flight on
it die with the connection) or stopped (SIGTERM: it drains). No query may fail
or differ from an in-process Terrain's answer. Each replica's own call
counter (its Prometheus /metrics) shows that both served before the stop.
gRPC's channelz counts the calls made on the channel and the streams each
replica's connection carried (the calls' attempts and the health checks'
Watch streams): their difference grows by the retried attempts.
"""

from __future__ import annotations

import json
import re
import signal
import threading
import time
import urllib.request

import numpy as np
import pytest

from client.terrain_client import ServiceError, TerrainClient, replica_target
from server.process import ServiceProcess, free_port
from sortie.errors import InvalidArgument, SortieError
from terrain.mosaic import load_sources
from terrain.terrain import Terrain

# Batch sizes: one point, a typical fleet round, and a batch whose request (640 kB)
# is over gRPC's default retry buffer (256 KiB), which the client raises.
BATCH_POINTS = (1, 2_000, 40_000)
CLIENT_THREADS = 2
CALLS_PER_REPLICA_BEFORE_STOP = 20
SECONDS_AFTER_STOP = 2.0


def test_replica_lists_become_one_static_target():
    assert replica_target("127.0.0.1:5001,127.0.0.1:5002") == "ipv4:127.0.0.1:5001,127.0.0.1:5002"
    assert replica_target(" localhost:5001 , 127.0.0.1:5002") == "ipv4:127.0.0.1:5001,127.0.0.1:5002"
    assert replica_target("[::1]:5001,[::1]:5002") == "ipv6:[::1]:5001,[::1]:5002"
    with TerrainClient("127.0.0.1:5001") as one:  # a single address: the channel as before
        assert one.target == "127.0.0.1:5001"
    for bad, why in (("127.0.0.1:5001,,127.0.0.1:5002", "empty entry"),
                     ("127.0.0.1:5001,127.0.0.1:0", "port in"),
                     ("127.0.0.1:5001,::1:5002", "host:port"),
                     ("127.0.0.1:5001,[::1]:5002", "address family")):
        with pytest.raises(InvalidArgument, match=why):
            TerrainClient(bad)
    with pytest.raises(ServiceError, match="cannot resolve"):
        TerrainClient("127.0.0.1:5001,no-such-host.invalid:5002")


def _heights_calls(metrics_port: int) -> int:
    """GetHeights calls a replica has answered, from its /metrics."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5).read().decode()
    m = re.search(r'^sortie_terrain_calls_total\{method="GetHeights"\} (\d+)$', text, re.M)
    return int(m[1]) if m else 0


def _channelz(target: str) -> tuple[int, dict]:
    """(calls made on the channel to ``target``, {replica: calls its connection carried}).

    gRPC's channelz counters, read through the same functions the grpcio-channelz
    servicer calls (gRPC exposes retries nowhere else). A replica's count holds
    the attempts sent to it and the health check's Watch streams."""
    from grpc._cython import cygrpc

    for ch in json.loads(cygrpc.channelz_get_top_channels(0)).get("channel", []):
        if ch["data"].get("target") == target:
            attempts = {}
            for ref in ch.get("subchannelRef", []):
                sub = json.loads(cygrpc.channelz_get_subchannel(int(ref["subchannelId"])))["subchannel"]["data"]
                attempts[sub["target"].removeprefix("ipv4:")] = int(sub.get("callsStarted", 0))
            return int(ch["data"].get("callsStarted", 0)), attempts
    pytest.fail(f"no channel to {target} in gRPC's channelz")


@pytest.mark.parametrize("stop_signal", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_queries_survive_a_replica_stopping(hgt_alps, tmp_path, stop_signal):
    rng = np.random.default_rng(8)
    batches = [(47.0 + rng.random(n), 9.0 + rng.random(n)) for n in BATCH_POINTS]
    local = Terrain(load_sources([hgt_alps]))
    expected = [local.heights(lat, lon) for lat, lon in batches]
    metrics = [free_port(), free_port()]
    replicas = [ServiceProcess(["terrain", "serve", "--dem", str(hgt_alps), "--metrics-port", str(m)],
                               log=tmp_path / f"replica{k}.log") for k, m in enumerate(metrics)]
    with replicas[0] as a, replicas[1] as b:
        client = TerrainClient(f"{a.address},{b.address}", timeout_s=20.0)
        client.wait_ready(30.0)
        for lat, lon in batches * 2:  # round robin: each replica answers each batch once (warm caches)
            client.heights(lat, lon)
        made_before, carried_before = _channelz(client.target)  # nothing in flight
        calls: list = []  # (start, latency s, batch) of every answered query
        failures: list = []
        mismatches: list = []
        done = threading.Event()

        def query(worker: int) -> None:
            k = worker
            while not done.is_set():
                k = (k + 1) % len(batches)
                t0 = time.monotonic()
                try:
                    got = client.heights(*batches[k])
                except SortieError as exc:
                    failures.append(f"{BATCH_POINTS[k]} points, {time.monotonic() - t0:.3f} s: {exc}")
                    continue
                calls.append((t0, time.monotonic() - t0, k))
                if not (np.array_equal(got.height_msl_m, expected[k].height_msl_m, equal_nan=True)
                        and np.array_equal(got.status, expected[k].status)):
                    mismatches.append(k)

        threads = [threading.Thread(target=query, args=(w,), daemon=True) for w in range(CLIENT_THREADS)]
        for t in threads:
            t.start()
        try:
            deadline = time.monotonic() + 60.0
            while min(_heights_calls(m) for m in metrics) < CALLS_PER_REPLICA_BEFORE_STOP:
                assert time.monotonic() < deadline, f"replicas served {[_heights_calls(m) for m in metrics]} calls"
                assert not failures, failures
                time.sleep(0.1)
            served_before = [_heights_calls(m) for m in metrics]
            t_stop = time.monotonic()
            b.proc.send_signal(stop_signal)
            time.sleep(SECONDS_AFTER_STOP)
        finally:
            done.set()
            for t in threads:
                t.join(30.0)
        made, attempts = _channelz(client.target)
        client.close()
        served_after = _heights_calls(metrics[0])
        assert b.proc.wait(30.0) == (-signal.SIGKILL if stop_signal == signal.SIGKILL else 0)

    after = [c for c in calls if c[0] >= t_stop]
    # Latency of the calls in flight during the second after the stop, against the second before it.
    across = [lat for start, lat, _ in calls if start + lat >= t_stop and start < t_stop + 1.0]
    before = [lat for start, lat, _ in calls if t_stop - 1.0 <= start and start + lat < t_stop]
    retries = (sum(attempts.values()) - made) - (sum(carried_before.values()) - made_before)
    print(f"\n{signal.Signals(stop_signal).name}: {len(calls)} queries ({len(after)} after the stop), "
          f"{len(failures)} failed, {retries} attempts retried by gRPC, {client.resent_calls} calls resent; "
          f"GetHeights per replica before the stop {served_before}; "
          f"latency max {max(across) * 1e3:.0f} ms in the second after the stop, "
          f"max {max(before, default=0) * 1e3:.0f} ms / median {np.median(before or [0]) * 1e3:.0f} ms "
          f"in the second before")
    assert not failures, failures
    assert not mismatches, f"answers differing from the in-process Terrain's, batches {sorted(set(mismatches))}"
    assert all(n >= CALLS_PER_REPLICA_BEFORE_STOP for n in served_before), served_before  # both served
    assert len(after) >= 10, f"only {len(after)} queries after the stop"
    assert served_after > served_before[0], "the surviving replica took no calls after the stop"
    assert retries >= 0 and set(attempts) == {a.address, b.address}, attempts
