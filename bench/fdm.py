"""``sortie bench fdm``: JSBSim hosting cost, aircraft per core, reference and dt convergence.

- ``jsbsim_overhead_ratio``: time per hosted step / time per bare
  ``FGFDMExec.run()``, for the same f16 in the same run, cruising north
  across the Alps DEM (in-process terrain). Blocks of bare ``run()`` calls
  and of hosted steps alternate on the one aircraft (interleaved, so machine
  noise hits both) and the best block of each counts. Hosting is done the way
  the server ticks the world: 30 Hz ticks of 4 steps at 120 Hz, each
  ``Aircraft.advance(4)`` (JSBSim steps, terrain coupling, event checks) plus
  one raw state snapshot (``raw_values``, stacked and converted to SI in bulk
  later: what the server streams and records). Variants:
  ``..._step_by_step`` calls ``Aircraft.step()`` 4 times per tick,
  ``..._state_every_step`` snapshots every step (ticks of 1 step), and
  ``..._near_ground`` is a fresh f16 60 m above a lake each round, where every
  contact point is placed and queried every step.
- ``near_ground_fleet_ratio``: the same per aircraft-step for a fleet of f16s
  60 m over the lake stepped by ``fdm.fleet.Fleet`` (one batched terrain
  query per step for all), in process; ``near_ground_grpc_single_ratio`` and
  ``near_ground_grpc_fleet_ratio`` with the terrain through the terrain
  service (separate process, loopback): one round trip per step for one
  aircraft, shared by the fleet.
- ``aircraft_realtime_120hz``: f16s one core keeps in real time at 120 Hz,
  hosted as above by a Fleet: 1 / (120 x time per aircraft step).
- ``hold_autopilot_us_per_tick`` / ``route_follower_us_per_tick``: one update a
  world tick of a bot's heading/altitude/speed hold and of its route follower
  (the hold plus a geodesic inverse to the waypoint), on the tick's raw row;
  ``route_follower_vs_tick_steps`` the latter over the aircraft's four bare
  JSBSim steps of that tick.
- ``script_max_abs_diff_m``: position difference against JSBSim's own run of
  ``scripts/c172_elevator_doublet.xml`` (see tests/test_fdm_script_reference.py
  for why it is not 0), and ``..._before_doublet_m`` over its first 5 s.
- ``series["dt_convergence"]``: c172x, 60 s of manoeuvring (bank to ±30° over
  14 s, pitch 3° ± 5° over 10 s: the same commands of simulated time at every
  rate, tracked by a stick law evaluated every step, _manoeuvre); ECEF position
  error at the end against dt = 1/1000 s, and wall seconds per simulated second,
  for dt = 1/50 ... 1/480.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from bench.harness import Report, data_file

ALPS_DEM = "N47E009.hgt"
# Northbound across the tile (the DEM spans 47-48 N): a fresh aircraft for each
# measurement stays over real terrain for all of it (~65 km).
CRUISE = dict(lat_deg=47.1, lon_deg=9.5, alt_m=3500.0, heading_deg=0.0, speed_mps=200.0)
LAKE = (47.60, 9.40)  # Lake Constance: flat water at 392 m
STATE_EVERY = 4  # 120 Hz steps per 30 Hz state snapshot
DT_RATES_HZ = (50, 60, 120, 240, 480)  # from the longest step the aircraft take (fdm.catalog.DT_MAX_S)
DT_REFERENCE_HZ = 1000


def alps_dem_path() -> Path:
    return data_file("dem", ALPS_DEM)


def alps_terrain():
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(alps_dem_path())])


def _interleaved_ratio(ac, block: int, rounds: int, tick: int, per_step: bool = False) -> tuple[float, float, float]:
    """(ratio, bare s/step, hosted s/step): best block of each, alternating on one aircraft.

    A block is ``block`` steps in ticks of ``tick`` steps. Bare: ``tick``
    ``FGFDMExec.run()`` calls. Hosted: ``Aircraft.advance(tick)`` (or ``tick``
    calls of ``Aircraft.step()`` when ``per_step``) and one raw state snapshot.
    """
    rows = []
    run = ac.fdm.run
    advance, step = ac.advance, ac.step
    raw = ac.raw_values
    ticks = block // tick
    best_bare = best_hosted = math.inf
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(ticks):
            for _ in range(tick):
                run()
        best_bare = min(best_bare, (time.perf_counter() - t0) / (ticks * tick))
        rows.clear()
        t0 = time.perf_counter()
        if per_step:
            for _ in range(ticks):
                for _ in range(tick):
                    step()
                rows.append(raw())
        else:
            for _ in range(ticks):
                advance(tick)
                rows.append(raw())
        best_hosted = min(best_hosted, (time.perf_counter() - t0) / (ticks * tick))
    return best_hosted / best_bare, best_bare, best_hosted


def bench_overhead(report: Report, terrain, quick: bool) -> None:
    from fdm.aircraft import Aircraft, InitialConditions

    block, rounds = (240, 15) if quick else (480, 40)
    def cruise():
        ac = Aircraft("f16", terrain, InitialConditions(**CRUISE))
        ac.run(1.0)  # warm caches
        return ac

    ratio, bare, hosted = _interleaved_ratio(cruise(), block, rounds, STATE_EVERY)
    report.metrics["jsbsim_overhead_ratio"] = ratio
    report.metrics["f16_bare_run_us"] = bare * 1e6
    report.metrics["f16_hosted_step_us"] = hosted * 1e6
    ratio_all, _, _ = _interleaved_ratio(cruise(), block, rounds, 1)
    report.metrics["jsbsim_overhead_ratio_state_every_step"] = ratio_all
    ratio_step, _, _ = _interleaved_ratio(cruise(), block, rounds, STATE_EVERY, per_step=True)
    report.metrics["jsbsim_overhead_ratio_step_by_step"] = ratio_step
    # Near the ground: a fresh f16 60 m over the lake for each round (trimmed, it
    # drifts down within seconds; a crashed aircraft no longer steps).
    low_bare = low_hosted = math.inf
    for _ in range(max(3, rounds // 2)):
        _, b, h = _interleaved_ratio(low_start(terrain), block // 2, 1, STATE_EVERY)
        low_bare, low_hosted = min(low_bare, b), min(low_hosted, h)
    report.metrics["jsbsim_overhead_ratio_near_ground"] = low_hosted / low_bare
    report.params.update(overhead_block_steps=block, overhead_rounds=rounds, state_out_every_steps=STATE_EVERY,
                         overhead_aircraft="f16", overhead_terrain=ALPS_DEM)


def low_start(terrain, k: int = 0):
    """An f16 60 m above Lake Constance, the k-th of a fleet spread along the lake."""
    from fdm.aircraft import Aircraft, InitialConditions

    return Aircraft("f16", terrain, InitialConditions(LAKE[0] - 0.004 * k, LAKE[1] + 0.01 * k, 60.0, "agl",
                                                      250.0, 150.0))


def _fleet_ratio(fleet, ticks: int) -> tuple[float, float]:
    """(bare s, hosted s) per aircraft-step: every aircraft's bare run() calls,
    then the same ticks through ``Fleet.advance`` with the fleet's snapshot."""
    n = len(fleet)
    runs = [a.fdm.run for a in fleet.aircraft]
    t0 = time.perf_counter()
    for _ in range(ticks):
        for run in runs:
            for _ in range(STATE_EVERY):
                run()
    bare = (time.perf_counter() - t0) / (ticks * STATE_EVERY * n)
    rows = []
    t0 = time.perf_counter()
    for _ in range(ticks):
        fleet.advance(STATE_EVERY)
        rows.append(fleet.raw_values())
    hosted = (time.perf_counter() - t0) / (ticks * STATE_EVERY * n)
    return bare, hosted


def bench_near_ground_fleet(report: Report, terrain, dem_path, quick: bool) -> None:
    """Fleets of f16s 60 m over the lake, in process and through the terrain
    service: the cost per aircraft-step against bare JSBSim, alone and as a fleet."""
    from client.terrain_client import TerrainClient
    from fdm.fleet import Fleet
    from server.process import ServiceProcess

    n = 4 if quick else 16
    rounds = 2 if quick else 4
    ticks = 30  # 1 s

    def measure(source, size):
        bare = hosted = math.inf
        for _ in range(rounds):
            fleet = Fleet(source)
            for k in range(size):
                fleet.add(low_start(source, k))
            b, h = _fleet_ratio(fleet, ticks)
            bare, hosted = min(bare, b), min(hosted, h)
        return hosted / bare

    report.metrics["near_ground_fleet_ratio"] = measure(terrain, n)
    with ServiceProcess(["terrain", "serve", "--dem", str(dem_path)]) as service, \
            TerrainClient(service.address) as client:
        report.metrics["near_ground_grpc_single_ratio"] = measure(client, 1)
        report.metrics["near_ground_grpc_fleet_ratio"] = measure(client, n)
    report.params.update(near_ground_fleet=n, near_ground_ticks=ticks, near_ground_rounds=rounds)


def bench_realtime(report: Report, terrain, quick: bool) -> None:
    from fdm.aircraft import Aircraft, InitialConditions
    from fdm.fleet import Fleet

    n = 8 if quick else 32
    fleet = Fleet(terrain)
    for i in range(n):
        ic = dict(CRUISE, lat_deg=47.1 + 0.5 * i / n, lon_deg=9.1 + 0.8 * i / n)
        fleet.add(Aircraft("f16", terrain, InitialConditions(**ic)))
    rows = []
    ticks = 30 if quick else 60
    best = math.inf
    for _ in range(3 if quick else 5):
        t0 = time.perf_counter()
        for _ in range(ticks):
            fleet.advance(STATE_EVERY)
            rows.append(fleet.raw_values())
        best = min(best, (time.perf_counter() - t0) / (n * ticks * STATE_EVERY))
        rows.clear()
    report.metrics["aircraft_realtime_120hz"] = float(math.floor((1.0 / 120.0) / best))
    report.params.update(realtime_fleet=n, realtime_dt_s=1.0 / 120.0)


def bench_script(report: Report) -> None:
    from fdm.catalog import replay_script

    ours, ref = replay_script("c172_elevator_doublet.xml")
    diff = np.linalg.norm(ours - ref, axis=1)
    report.metrics["script_max_abs_diff_m"] = float(diff.max())
    # Before the first doublet (5 s at dt = 1/120 s) only the start offset shows.
    report.metrics["script_max_abs_diff_before_doublet_m"] = float(diff[:600].max())
    report.params["script"] = "c172_elevator_doublet.xml"


def _manoeuvre(dt: float, seconds: float):
    from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions

    ac = Aircraft("c172x", FlatTerrain(0.0), InitialConditions(47.3, 9.5, 1500.0, heading_deg=90.0,
                                                                speed_mps=50.0), dt=dt)
    # Open-loop stick inputs (this bench's first manoeuvre: pitch 0.15 sin(2 pi t / 10 s), roll
    # 0.4 sin(2 pi t / 14 s)) spiralled into the ground at 31.6 s at every rate, and its figures
    # were the crash sites' differences: an aircraft's spiral mode is unstable, and any open-loop
    # input drifts the bank. The commands here are attitudes, tracked by a proportional-derivative
    # stick law of the state after each step; it keeps the flight within 1500 +- 5 m, 46-50 m/s
    # and 34 deg of bank, so the differences are the integration's.
    fdm = ac.fdm
    t0 = time.perf_counter()
    for _ in range(int(round(seconds / dt))):
        t = ac.time_s
        phi_c = math.radians(30.0) * math.sin(2 * math.pi * t / 14.0)
        theta_c = math.radians(3.0) + math.radians(5.0) * math.sin(2 * math.pi * t / 10.0)
        roll = 2.0 * (phi_c - fdm["attitude/phi-rad"]) - 0.3 * fdm["velocities/p-rad_sec"]
        pitch = 3.0 * (theta_c - fdm["attitude/theta-rad"]) - 0.5 * fdm["velocities/q-rad_sec"]
        ac.set_controls(pitch=min(1.0, max(-1.0, pitch)), roll=min(1.0, max(-1.0, roll)))
        ac.step()
    wall = time.perf_counter() - t0
    if ac.crashed:
        raise RuntimeError(f"the dt manoeuvre crashed at dt = {dt} s")
    return ac.state().ecef_m, wall / seconds


def bench_dt_convergence(report: Report, quick: bool) -> None:
    seconds = 60.0
    ref, ref_cost = _manoeuvre(1.0 / DT_REFERENCE_HZ, seconds)
    series = []
    for hz in DT_RATES_HZ:
        pos, cost = _manoeuvre(1.0 / hz, seconds)
        series.append({"dt_s": 1.0 / hz, "rate_hz": hz, "position_error_m": float(np.linalg.norm(pos - ref)),
                       "cost_s_per_sim_s": cost})
        report.metrics[f"dt_error_m_{hz}hz"] = series[-1]["position_error_m"]
    report.series["dt_convergence"] = series
    report.params.update(dt_reference_hz=DT_REFERENCE_HZ, dt_manoeuvre_s=seconds, dt_aircraft="c172x",
                         dt_reference_cost_s_per_sim_s=ref_cost)


def bench_pilots(report: Report, terrain, quick: bool) -> None:
    """What a bot's autopilot costs a world tick (one update, on the row the host read),
    against the aircraft's four bare JSBSim steps of that tick: a heading/altitude/speed
    hold, and a route follower (the hold plus a geodesic inverse to its waypoint)."""
    from fdm.aircraft import Aircraft, InitialConditions
    from fdm.autopilot import Autopilot, WaypointFollower

    ac = Aircraft("f16", terrain, InitialConditions(**CRUISE))
    ac.run(1.0)
    row = ac.raw_values()
    hold = Autopilot(ac)
    hold.set_targets(heading_deg=10.0, alt_msl_m=CRUISE["alt_m"], speed_mps=CRUISE["speed_mps"])
    route = WaypointFollower(ac, [(47.6, 9.6, CRUISE["alt_m"]), (47.9, 9.4, CRUISE["alt_m"])], CRUISE["speed_mps"])
    run = ac.fdm.run
    n = 300 if quick else 2000

    def per_call(fn) -> float:
        best = math.inf
        for _ in range(5):
            t0 = time.perf_counter()
            for _ in range(n):
                fn()
            best = min(best, (time.perf_counter() - t0) / n)
        return best * 1e6

    steps_us = per_call(lambda: (run(), run(), run(), run()))
    m = report.metrics
    m["hold_autopilot_us_per_tick"] = per_call(lambda: hold.update(row))
    m["route_follower_us_per_tick"] = per_call(lambda: route.update(row))
    m["route_follower_vs_tick_steps"] = m["route_follower_us_per_tick"] / steps_us
    report.params.update(pilot_tick_steps_us=steps_us, pilot_calls=n)


def run(quick: bool) -> Report:
    report = Report(suite="fdm", quick=quick)
    terrain = alps_terrain()
    bench_overhead(report, terrain, quick)
    bench_pilots(report, terrain, quick)
    bench_realtime(report, terrain, quick)
    bench_near_ground_fleet(report, terrain, alps_dem_path(), quick)
    bench_script(report)
    bench_dt_convergence(report, quick)
    try:  # ground vehicles (fdm/ground.py) add their metric when their bench exists
        from bench.fdm_ground import run_ground
    except ImportError:
        pass
    else:
        run_ground(report, quick)
    return report
