"""``sortie bench server``: capacity, tick time, latency, slow clients, dead reckoning.

The load: the Alps DEM (in-process terrain), 2000 ground vehicles driving
(random types and commands, on land across the tile), N f16s holding
heading, altitude and speed over it, and 32 observer clients (20 km areas
of interest at random points) streaming at 20 Hz from separate processes
(bench/server_clients.py, 8 clients each), all on this machine's 2 cores.

- ``bare_jsbsim_realtime_aircraft``: f16s one core keeps in real time at
  120 Hz with a bare ``FGFDMExec.run()`` loop, same run, measured at the
  same two fleet sizes as the server and fitted the same way (see
  :func:`bench_bare`: the cost of a step grows with the fleet, so a
  4-aircraft loop, ``bare_small_fleet_realtime_aircraft``, overstates it),
  before and after the server's fits, averaged (``..._before`` and
  ``..._after`` show the machine's drift between them).
- ``realtime_aircraft``: f16s the server keeps in real time at that load:
  the world tick (30 Hz, 4 JSBSim steps each, the aircraft in one worker
  process per core as ``sortie server`` runs them; the publish runs beside it on
  the server's publisher thread, the clock waiting only for a publish a whole
  snapshot behind), timed by the clock thread in "fast" mode (as fast as it goes) at two
  fleet sizes (each twice in full runs, in the order A B B A, averaged); the
  tick time is linear in the fleet size, and the fleet whose mean tick
  fills the 33.3 ms budget is the capacity.
  ``capacity_ratio`` = realtime / bare.
- ``tick_p99_ms``: p99 tick time in real time at that fleet size (75 % of
  the capacity, rounded down, to leave the realtime run room) with the
  clients streaming; ``latency_p99_ms``: world tick -> client receipt, the
  wall time the tick ended on the server (its snapshot handed to the
  publisher) against the update's arrival in the client process (one machine
  clock); ``slow_client_tick_ratio``: tick p99
  with one more client that never reads its stream, over the same without it.
  One real-time run on one world serves both: its steady window is cut in
  phases, calm, stalled, stalled, calm (REALTIME_PHASES; FULL_PHASE_REPEATS
  times in full runs, PHASE_S each), the stalled client joining at a stalled phase's start and
  leaving at the next calm one's (bench.server_clients --stall-phases); each
  phase's first PHASE_SETTLE_S are left out, and each kind's ticks are pooled:
  a drift of the machine's speed cancels phase by phase (until the nineteenth
  session: four separate 10 s runs, whose calm p99s alone read 16.5 and
  27.5 ms in one full run). ``tick_p99_ms`` and the latencies are the calm
  phases'; --quick's ratio is the p90s (QUICK_SLOW_CLIENT_PERCENTILE: its ~60
  ticks a kind make a p99 one tick); ``params["realtime_phases_tick_p99_ms"]``
  keeps each phase's own p99, and the ``_whole_run`` figures span every phase;
  ``slow_client_tick_ratio_paired_median``: the median over the pairs of
  neighbouring phases (calm, stalled | stalled, calm | ...) of their p99 ratio.
  Every tick and latency figure (the fits' mean ticks too) is taken over the
  steady window: from STEADY_SKIP_S after every load client is ready (each
  one's first full snapshot) to STEADY_TAIL_S before they stop (closing 32
  channels, writing their logs), as a real exercise streams between its
  joins and its end; ``tick_p99_ms_whole_run`` and
  ``latency_p99_ms_whole_run`` keep the ready-to-stop figures beside them.
- ``latency_floor_p50_ms`` / ``latency_floor_p99_ms`` (full runs only): the
  same 32 clients and message size streamed by a gRPC server that does
  nothing else (bench/stream_floor.py): what the transport allows on this
  machine; ``latency_floor_loaded_*`` the same beside one busy process per
  core at the workers' priority, busy FLOOR_DUTY of each tick.
- dead reckoning: bench/dr.py (``dr_*`` metrics and the bandwidth plot).
- collisions between agents: bench/collisions.py (``collision_*``: one tick's test of
  2350 entities against an all-pairs reference).
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
import time

import numpy as np

from bench.harness import Report

CLIENTS = 32
CLIENTS_PER_PROCESS = 8
GROUND_VEHICLES = 2000
TICK_BUDGET_MS = 1000.0 / 30.0
STEPS_PER_TICK = 4  # 120 Hz JSBSim in a 30 Hz world tick
# The measured window of a load run (see _serve): from this long after every load client is
# ready (their first full snapshots) to this long before they stop (closing, writing logs).
STEADY_SKIP_S = 1.0
STEADY_TAIL_S = 0.5
QUICK_WINDOW = (0.5, 0.25)  # --quick: (skip, tail) of 2 s loads
# The latency floor's stand-in for the aircraft workers: one busy process per core,
# busy this fraction of each tick (the real-time run flies 75 % of the capacity).
FLOOR_DUTY = 0.75
# A real-time run whose world advanced slower than this (world s per wall s) could not carry its
# fleet: the capacity fit overstated it (quick fits at 32 and 96 aircraft extrapolated 3-10x).
REALTIME_RATE_OK = 0.98
# --quick's slow_client_tick_ratio: the percentile of each kind's pooled ticks (two 2 s windows of
# about 37 ticks: a p99 there is the single worst tick, which read 0.17 to 1.44 run to run).
QUICK_SLOW_CLIENT_PERCENTILE = 90
# The real-time run's phases (stalled client present or not), seconds each, and the seconds at each
# phase's start left out (the stalled client joining, its snapshot, its Watch cancelled).
REALTIME_PHASES = (False, True, True, False)
FULL_PHASE_REPEATS = 4  # full runs: 16 phases (a first full run with 2 x 4 phases of 5 s: one slow spell took half)
PHASE_S = 4.0
PHASE_SETTLE_S = 1.0
QUICK_PHASE_S = 1.5
QUICK_PHASE_SETTLE_S = 0.5


def _f16_fleet(terrain, n: int) -> list:
    from fdm.aircraft import Aircraft, InitialConditions

    return [Aircraft("f16", terrain, InitialConditions(47.2 + 0.003 * i, 9.5, 4000.0, heading_deg=0.0,
                                                       speed_mps=200.0)) for i in range(n)]


def _bare_tick_ms(fleet: list, seconds: float, steps: int = STEPS_PER_TICK) -> float:
    """Mean wall time (ms) of one world tick's worth of a bare loop, over ``seconds``
    of running: each aircraft in turn runs ``steps`` FGFDMExec.run() calls (the
    order the world steps them in). A mean over seconds, like the server's
    figure, not a best-of: on a shared machine a best-of catches the quiet
    moments the server's mean does not, and biases the ratio."""
    runs = [a.fdm.run for a in fleet]
    ticks = 0
    t0 = time.perf_counter()
    while ticks < 3 or time.perf_counter() - t0 < seconds:
        for run in runs:
            for _ in range(steps):
                run()
        ticks += 1
    return (time.perf_counter() - t0) / ticks * 1e3


def _capacity(sizes, tick_ms) -> tuple[float, float, float]:
    """(aircraft whose tick fills the budget, ms per aircraft, fixed ms) of a line through two sizes."""
    (n1, n2), (t1, t2) = sizes, tick_ms
    slope = (t2 - t1) / (n2 - n1)
    base = t1 - slope * n1
    return (max(0.0, math.floor((TICK_BUDGET_MS - base) / slope)) if slope > 0 else float("nan")), slope, base


def bench_bare(report: Report, terrain, sizes, quick: bool, measured_between):
    """One core's bare JSBSim capacity at the fleet sizes the server is measured at,
    bracketing ``measured_between()`` (the server's runs), whose result is returned with it.

    A bare loop's cost per step grows with the fleet: a few aircraft keep their
    JSBSim instances in the CPU caches, a hundred do not (measured here: about
    20 us a step for 4 f16s, 50-100 us for 64 or more). So the baseline is
    measured like the server, at the same two fleet sizes, in the same
    stepping order and as a mean over seconds, and the same line fit gives its
    capacity. It is measured before and after the server's runs and the two
    averaged: this VM's speed drifts over minutes (the baseline alone read 132
    to 232 aircraft in full runs an hour apart), and a baseline taken only
    before the server's half minute of runs carried that drift into the ratio.
    Both are reported. The 4-aircraft figure is kept as
    ``bare_small_fleet_realtime_aircraft``.
    """
    fleet = _f16_fleet(terrain, max(sizes))
    seconds = 0.6 if quick else 3.0
    small = _bare_tick_ms(fleet[:4], seconds) / (4 * STEPS_PER_TICK)  # ms per step
    report.metrics["bare_small_fleet_realtime_aircraft"] = float(math.floor(1000.0 / (120.0 * small)))
    before = [_bare_tick_ms(fleet[:n], seconds) for n in sizes]
    result = measured_between()
    after = [_bare_tick_ms(fleet[:n], seconds) for n in sizes]
    ticks = [(a + b) / 2.0 for a, b in zip(before, after)]
    bare, slope, _ = _capacity(sizes, ticks)
    report.metrics["bare_jsbsim_realtime_aircraft"] = float(bare)
    report.metrics["bare_jsbsim_realtime_aircraft_before"] = float(_capacity(sizes, before)[0])
    report.metrics["bare_jsbsim_realtime_aircraft_after"] = float(_capacity(sizes, after)[0])
    report.metrics["bare_us_per_step"] = slope * 1e3 / STEPS_PER_TICK
    report.metrics["bare_small_fleet_us_per_step"] = small * 1e3
    report.params.update(bare_tick_ms=ticks, bare_tick_ms_before=before, bare_tick_ms_after=after)
    del fleet
    return bare, result


def _host(terrain, workers: int):
    from bench.fdm import alps_terrain
    from server.aircraft_host import LocalAircraftHost, ProcessAircraftHost

    if workers == 0:
        return LocalAircraftHost(terrain, 1.0 / 120.0)
    return ProcessAircraftHost(alps_terrain, 1.0 / 120.0, workers=workers)


def _world(terrain, n_aircraft: int, n_ground: int, seed: int = 3, workers: int = 0):
    from fdm.aircraft import InitialConditions
    from fdm.vehicle_types import VEHICLE_TYPES
    from server.world import World

    rng = np.random.default_rng(seed)
    w = World(terrain, aircraft_host=_host(terrain, workers))
    specs = []
    for i in range(n_aircraft):
        lat, lon = rng.uniform(47.1, 47.9), rng.uniform(9.1, 9.9)
        hdg = float(rng.uniform(0, 360))
        specs.append(dict(name=f"f16-{i}", type_="f16", ic=InitialConditions(lat, lon, 4500.0, heading_deg=hdg,
                                                                              speed_mps=200.0),
                          hold={"heading_deg": hdg, "alt_msl_m": 4500.0, "speed_mps": 200.0}))
    for e in w.spawn_aircraft_many(specs):  # every worker loads and trims its share at once
        if isinstance(e, BaseException):
            raise e
    # Ground vehicles on land (above the lake's 395 m and below 1500 m), in one batch.
    lat, lon = rng.uniform(47.05, 47.95, 4 * n_ground), rng.uniform(9.05, 9.95, 4 * n_ground)
    h = terrain.heights(lat, lon).height_msl_m
    ok = np.flatnonzero((h > 400.0) & (h < 1500.0))[:n_ground]
    types = rng.choice(sorted(VEHICLE_TYPES), ok.size).tolist()
    w.spawn_ground([f"g-{k}" for k in range(ok.size)], types, lat[ok], lon[ok], rng.uniform(0, 360, ok.size))
    g = w.ground
    g.set_controls(rng.uniform(2, 10, g.n), rng.uniform(-3, 3, g.n))
    return w


def _clients(address: str, n: int, seconds: float, stall: int = 0, phased: bool = False) -> list:
    """The load clients, CLIENTS_PER_PROCESS to a process (as on separate machines,
    they must not queue on one interpreter lock; the stalled ones in the first, which with
    ``phased`` brings them in and out as its stdin says: bench.server_clients --stall-phases)."""
    procs = []
    for k, first in enumerate(range(0, n, CLIENTS_PER_PROCESS)):
        count = min(CLIENTS_PER_PROCESS, n - first)
        extra = ["--stall-phases"] if phased and k == 0 else []
        procs.append(subprocess.Popen([sys.executable, "-m", "bench.server_clients", address, str(count),
                                       str(seconds), str(7 + k), "--stall", str(stall if k == 0 else 0), *extra],
                                      stdin=subprocess.PIPE if extra else subprocess.DEVNULL,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True))
    for proc in procs:
        line = proc.stderr.readline()
        if "ready" not in line:
            for p in procs:
                p.kill()
            raise RuntimeError(f"load clients failed: {line}{proc.stderr.read()}")
    return procs


def _gather(procs: list, timeout_s: float) -> dict:
    """The load clients' JSON outputs merged (lists concatenated)."""
    merged: dict = {}
    for proc in procs:
        out, _ = proc.communicate(timeout=timeout_s)
        for key, values in json.loads(out).items():
            merged.setdefault(key, []).extend(values)
    return merged


def _command(proc, command: str) -> None:
    """Send a --stall-phases load process ``command`` and wait for its acknowledgement."""
    proc.stdin.write(command + "\n")
    proc.stdin.flush()
    while True:
        line = proc.stderr.readline()
        if not line:
            raise RuntimeError(f"the load process ended before acknowledging {command!r}")
        if line.strip() == f"{command} ok":
            return


def _serve(terrain, n_aircraft: int, clock: str, seconds: float, n_ground: int, stall: int = 0,
           clients: int = CLIENTS, workers: int = 0, window=(STEADY_SKIP_S, STEADY_TAIL_S), world=None,
           phases=None, settle_s: float = 0.0) -> dict:
    """Run a server with the load for ``seconds`` of wall time; tick and latency figures over
    its steady window (``window``: seconds left out after the clients are ready, before they stop).
    ``world``: one of :func:`_world` to serve (left open: the caller's), else a new one.

    ``phases`` (bools: stalled or calm): the steady window cut in that many equal phases, the
    ``stall`` stalled clients present in the stalled ones only (brought in and out by the
    first load process); each phase's ticks after its first ``settle_s`` (the joins, the new
    Watches' snapshots, the cancellations) count for its kind: ``phase_ticks`` {False: calm,
    True: stalled}, ``phase_latency_ms`` the calm phases' latencies, ``phase_tick_p99_ms``
    [(stalled, p99)] in order, ``phase_watching`` the Watch streams open after each settle."""
    skip_s, tail_s = window
    from server.sim_server import ServerConfig, SimulationServer

    own = world is None
    if own:
        world = _world(terrain, n_aircraft, n_ground, workers=workers)
    server = SimulationServer(world, ServerConfig(clock=clock, time_scale=1000.0 if clock == "fast" else 1.0,
                                                  vanished_timeout_s=60.0))
    published = {}  # world time -> wall time its tick ended (the clock hands its snapshot over then)
    original = world.tick

    def tick(*args, **kwargs):  # whatever the server passes on, passed on
        original(*args, **kwargs)
        published[round(world.time_s, 6)] = time.time()

    world.tick = tick
    server.start()
    try:
        procs = _clients(server.address, clients, seconds, stall, phased=bool(phases))
        server.tick_ms.clear()
        t_ready = world.time_s
        # The steady window: every client streaming, after each one's first full snapshot
        # (skip_s) and before they stop (they close their channels and write their logs in
        # the last moments: tail_s). Before it, the other client processes'
        # start-up, imports and joins hold the CPU.
        time.sleep(skip_s)
        first, t_world0, wall0 = len(server.tick_ms), world.time_s, time.monotonic()
        spans = []  # (stalled, first tick, last tick, world time from, to) of each phase
        if phases:
            phase_s = max(seconds - skip_s - tail_s, 0.5) / len(phases)
            for k, stalled in enumerate(phases):
                start = wall0 + k * phase_s
                _command(procs[0], "stall" if stalled else "calm")
                time.sleep(max(0.0, start + settle_s - time.monotonic()))
                a, w_a, watching = len(server.tick_ms), world.time_s, len(server.sessions.watching())
                time.sleep(max(0.0, start + phase_s - time.monotonic()))
                spans.append((stalled, a, len(server.tick_ms), w_a, world.time_s, watching))
            # (its stdin is closed by _gather's communicate: the load process then ends its phases)
        else:
            time.sleep(max(seconds - skip_s - tail_s, 0.5))
        last, t_world1, wall1 = len(server.tick_ms), world.time_s, time.monotonic()
        data = _gather(procs, seconds + 120.0)
        whole = np.array(server.tick_ms)
    finally:
        server.stop(0.5)
        del world.tick  # the world's own again (a caller's world is served again)
        if own:
            world.close()
    ticks = whole[first:last]
    if not len(ticks):  # (once, the first full run after hours idle: a NaN capacity followed)
        raise RuntimeError(f"no world tick in the steady window of a {seconds:g} s {clock} run with "
                           f"{n_aircraft} aircraft ({len(whole)} ticks in the whole run)")

    def latencies(t_from: float, t_to: float) -> np.ndarray:
        return np.array([(wall_rx - published[round(t, 6)]) * 1e3 for log in data["received"] for t, wall_rx in log
                         if t_from <= t <= t_to and round(t, 6) in published])

    phased = {}
    if spans:
        phased["phase_ticks"] = {kind: np.concatenate([whole[a:b] for stalled, a, b, *_ in spans if stalled == kind])
                                 for kind in (False, True)}
        phased["phase_latency_ms"] = np.concatenate([latencies(w_a, w_b) for stalled, _, _, w_a, w_b, _ in spans
                                                     if not stalled])
        phased["phase_tick_p99_ms"] = [(stalled, float(np.percentile(whole[a:b], 99)) if b > a else math.nan)
                                       for stalled, a, b, *_ in spans]
        phased["phase_watching"] = [watching for *_, watching in spans]
    return {**phased, "ticks": ticks, "tick_mean_ms": float(ticks.mean()), "tick_p99_ms": float(np.percentile(ticks, 99)),
            "tick_p99_ms_whole_run": float(np.percentile(whole, 99)),
            "world_rate": (t_world1 - t_world0) / (wall1 - wall0), "latency_ms": latencies(t_world0, t_world1),
            "latency_ms_whole_run": latencies(t_ready, np.inf), "bytes": sum(data["bytes"]),
            "states": sum(data["states"]), "messages": sum(len(log) for log in data["received"]), "entities": len(world.entities), "updates": server.publisher.updates_sent,
            "samples": server.publisher.entity_samples}


def bench_capacity(report: Report, terrain, quick: bool) -> None:
    n_ground = 500 if quick else GROUND_VEHICLES
    clients = 8 if quick else CLIENTS
    seconds = 2.0 if quick else 10.0  # quick: the whole suite within the brief's 60 s
    window = QUICK_WINDOW if quick else (STEADY_SKIP_S, STEADY_TAIL_S)
    sizes = (32, 96) if quick else (64, 192)
    workers = max(1, os.cpu_count() or 1)  # as `sortie server --aircraft-workers auto`
    # Full runs fit each size twice, in the order A B B A (a linear drift of the machine's
    # speed over the four cancels in each size's mean); --quick once.
    order = list(sizes) if quick else [sizes[0], sizes[1], sizes[1], sizes[0]]
    bare, fits = bench_bare(report, terrain, sizes, quick, lambda: [
        (n, _serve(terrain, n, "fast", seconds, n_ground, clients=clients, workers=workers, window=window))
        for n in order])
    fit_ms = [float(np.mean([r["tick_mean_ms"] for m, r in fits if m == n])) for n in sizes]
    realtime, slope, base = _capacity(sizes, fit_ms)
    report.metrics["realtime_aircraft"] = float(realtime)
    report.metrics["capacity_ratio"] = realtime / bare
    report.metrics["tick_ms_per_aircraft"] = slope
    report.metrics["tick_ms_fixed"] = base
    n_rt = max(1, int(0.75 * realtime))
    # One world and one load for the real-time run, whose steady window is cut in phases with
    # and without the stalled client, alternating calm, stalled, stalled, calm (twice in full
    # runs), each phase's first seconds (the stalled client's join, its snapshot, its
    # cancellation) left out. The tick percentiles of each kind pool its phases: a drift of the
    # machine's speed, which moved one kind's p99 more than the stalled client does (separate
    # 10 s runs of the same kind read 16.5 and 27.5 ms), cancels phase by phase.
    phases = REALTIME_PHASES * (1 if quick else FULL_PHASE_REPEATS)
    phase_s, settle_s = (QUICK_PHASE_S, QUICK_PHASE_SETTLE_S) if quick else (PHASE_S, PHASE_SETTLE_S)
    skip_s, tail_s = window
    world = _world(terrain, n_rt, n_ground, workers=workers)
    try:
        run = _serve(terrain, n_rt, "realtime", skip_s + len(phases) * phase_s + tail_s, n_ground, stall=1,
                     clients=clients, workers=workers, window=window, world=world, phases=phases,
                     settle_s=settle_s)
    finally:
        world.close()
    calm = run
    calm_ticks, slow_ticks = run["phase_ticks"][False], run["phase_ticks"][True]
    latency = run["phase_latency_ms"]
    report.metrics["tick_p99_ms"] = float(np.percentile(calm_ticks, 99))
    report.metrics["tick_p99_ms_whole_run"] = run["tick_p99_ms_whole_run"]
    report.metrics["latency_p50_ms"] = float(np.percentile(latency, 50))
    report.metrics["latency_p99_ms"] = float(np.percentile(latency, 99))
    report.metrics["latency_p99_ms_whole_run"] = float(np.percentile(run["latency_ms_whole_run"], 99))
    ratio, what = slow_client_ratio(calm_ticks, slow_ticks, quick)
    report.metrics["slow_client_tick_ratio"] = ratio
    report.params["slow_client_tick_ratio_is"] = what
    # Beside it, each stalled phase against the calm phase next to it (calm, stalled | stalled,
    # calm | ...): the median of those pairs' p99 ratios, which a slow spell of a few phases moves less.
    p99s = [p for _, p in run["phase_tick_p99_ms"]]
    report.metrics["slow_client_tick_ratio_paired_median"] = float(np.median(
        [(p99s[k + 1] / p99s[k]) if not phases[k] else (p99s[k] / p99s[k + 1]) for k in range(0, len(phases) - 1, 2)]))
    report.params.update(realtime_phases_tick_p99_ms=[["stalled" if k else "calm", p] for k, p in
                                                      run["phase_tick_p99_ms"]],
                         realtime_phase_s=phase_s, realtime_phase_settle_s=settle_s)
    if not quick:  # the transport's own floor, same clients and message size (bench/stream_floor.py)
        from bench.stream_floor import measure_floor

        msg_bytes = int(calm["bytes"] / max(calm["messages"], 1))
        idle = measure_floor(clients, CLIENTS_PER_PROCESS, seconds, msg_bytes)
        loaded = measure_floor(clients, CLIENTS_PER_PROCESS, seconds, msg_bytes, duty=FLOOR_DUTY)
        report.metrics["latency_floor_p50_ms"] = float(np.percentile(idle, 50))
        report.metrics["latency_floor_p99_ms"] = float(np.percentile(idle, 99))
        report.metrics["latency_floor_loaded_p50_ms"] = float(np.percentile(loaded, 50))
        report.metrics["latency_floor_loaded_p99_ms"] = float(np.percentile(loaded, 99))
        report.params.update(floor_message_bytes=msg_bytes, floor_duty=FLOOR_DUTY)
    report.metrics["realtime_world_rate"] = run["world_rate"]
    _check_capacity(report, sizes[0], fit_ms[0], n_rt, float(np.mean(calm_ticks)), bare)
    report.metrics["stream_bytes_per_state"] = calm["bytes"] / max(calm["states"], 1)
    report.metrics["server_message_reduction"] = 1.0 - calm["updates"] / max(calm["samples"], 1)
    report.params.update(steady_window_s=list(window),
                         capacity_fleet_sizes=list(sizes), capacity_fit=fit_ms,
                         capacity_fit_runs=[[n, r["tick_mean_ms"]] for n, r in fits],
                         ground_vehicles=n_ground, clients=clients, aircraft_workers=workers, client_aoi_m=20_000.0, seconds=seconds,
                         realtime_run_aircraft=n_rt, entities=calm["entities"], tick_budget_ms=TICK_BUDGET_MS)


def slow_client_ratio(calm_ticks, slow_ticks, quick: bool) -> tuple[float, str]:
    """(tick percentile with a stalled client over the same without it, what it is): p99 over the
    full run's pooled windows, --quick's QUICK_SLOW_CLIENT_PERCENTILE over its shorter ones.
    ``calm_ticks``, ``slow_ticks``: (n,) float, ms, the steady-window ticks of each kind."""
    q = QUICK_SLOW_CLIENT_PERCENTILE if quick else 99
    calm, slow = np.asarray(calm_ticks, np.float64), np.asarray(slow_ticks, np.float64)
    what = (f"p{q} of the stalled-client phases' ticks over p{q} of the calm phases' "
            f"({slow.size} and {calm.size} ticks; one run, phases calm, stalled, stalled, calm, repeated in full runs)")
    return float(np.percentile(slow, q) / np.percentile(calm, q)), what


def _check_capacity(report: Report, n_small: int, tick_small_ms: float, n_rt: int, tick_rt_ms: float,
                    bare: float) -> None:
    """Lower ``realtime_aircraft`` (and ``capacity_ratio``) when the real-time run at 75 % of it
    could not keep real time: the capacity of the line through the smaller fit size and the
    real-time run's mean tick, a point near the capacity (interpolated, not extrapolated from two
    small fleets), or of the world rate (n_rt x rate) when that line does not rise. The fitted
    figure stays in params, and ``capacity_overstated`` says whether it was lowered."""
    rate = report.metrics["realtime_world_rate"]
    fitted = report.metrics["realtime_aircraft"]
    overstated = rate < REALTIME_RATE_OK
    report.params.update(capacity_overstated=overstated, realtime_aircraft_fitted=fitted,
                         realtime_rate_ok=REALTIME_RATE_OK)
    if not overstated:
        return
    checked = (_capacity((n_small, n_rt), (tick_small_ms, tick_rt_ms))[0] if n_rt > n_small else math.nan)
    if not math.isfinite(checked):
        checked = float(math.floor(n_rt * rate))
    report.metrics["realtime_aircraft"] = float(min(fitted, checked))
    report.metrics["capacity_ratio"] = report.metrics["realtime_aircraft"] / bare


def run(quick: bool) -> Report:
    from bench.collisions import run_collisions
    from bench.dr import run_dr
    from bench.fdm import alps_terrain

    report = Report(suite="server", quick=quick)
    terrain = alps_terrain()
    bench_capacity(report, terrain, quick)
    run_dr(report, quick)
    run_collisions(report, quick)
    return report
