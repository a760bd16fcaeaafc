"""The server benchmark's measuring path (bench/server.py) against the real server: the
load clients' receipts must match the publishes it taps, or every latency and tick
figure of ``sortie bench server`` is lost (a change to the publisher's signature once
stopped the world clock of the bench without any test noticing)."""

import numpy as np


def test_serve_measures_ticks_and_latencies_of_a_small_load(hgt_alps):
    from bench.server import _serve
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(hgt_alps)])
    # 1000 ground vehicles: dead reckoning lets few updates through once a vehicle's motion is
    # steady, and the steady window is 1 s of world time that starts later on a slow machine;
    # with 20 vehicles the window sometimes held none (CI, stop 18), with 1000 it holds ~50.
    r = _serve(terrain, 2, "realtime", 2.5, 1000, clients=4, workers=0)
    lat = r["latency_ms"]
    assert lat.size >= 1, r  # the updates dead reckoning lets through to 4 random areas
    assert np.all(np.isfinite(lat)) and np.all(lat > 0.0) and np.all(lat < 5_000.0)
    assert np.isfinite(r["tick_mean_ms"]) and 0.0 < r["tick_mean_ms"] <= r["tick_p99_ms"]
    assert 0.5 < r["world_rate"] < 1.5  # real time
    assert r["states"] > 0 and r["bytes"] > 0 and r["entities"] == 1002


def test_stream_floor_measures_trigger_to_receipt():
    """The transport-floor stand-in streams to real gRPC clients and times each message."""
    from bench.stream_floor import WARM_MESSAGES, measure_floor

    lat = measure_floor(clients=3, per_process=2, seconds=2.0, msg_bytes=1500, duty=0.3)
    assert lat.size >= 3 * (30 - WARM_MESSAGES)  # ~40 messages each in 2 s at 20 Hz
    assert np.all(np.isfinite(lat)) and lat.min() > 0.0 and np.median(lat) < 1000.0


def test_phases_bring_the_stalled_client_in_and_out_and_pool_each_kinds_ticks(hgt_alps):
    """slow_client_tick_ratio's run: calm, stalled, stalled, calm phases on one world; the
    stalled client's Watch is open in the stalled phases only, and each kind's ticks and the
    calm phases' latencies are collected."""
    from bench.server import _serve
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(hgt_alps)])
    phases = (False, True, True, False)
    r = _serve(terrain, 2, "realtime", 0.5 + 4 * 1.5 + 0.25, 1000, stall=1, clients=3, workers=0,
               window=(0.5, 0.25), phases=phases, settle_s=0.5)
    assert r["phase_watching"] == [3, 4, 4, 3]
    assert [k for k, _ in r["phase_tick_p99_ms"]] == list(phases)
    for kind in (False, True):  # ~30 ticks a phase after its settle, two phases a kind
        assert r["phase_ticks"][kind].size >= 20 and np.all(r["phase_ticks"][kind] > 0.0)
    assert r["phase_latency_ms"].size >= 1 and np.all(r["phase_latency_ms"] > 0.0)
