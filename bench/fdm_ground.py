"""Ground vehicles for ``sortie bench fdm``: vehicle-steps per second on real terrain, with
the error of terrain following beside it.

:func:`run_ground` adds its metrics to the suite's :class:`bench.harness.Report`:

- ``ground_vehicle_steps_per_s`` (goal >= 2,000,000): 10,000 vehicles of the four
  catalogued types (wheeled and tracked) at random places and commands on the
  Alps tile (SRTM3 N47E009), stepped at 20 Hz in-process on one core
  (single-threaded numba kernels), terrain following included: five terrain
  samples per vehicle per step in one batched call. Best of a few rounds.
- ``ground_vehicle_height_max_abs_err_m``: max |height - terrain height at the
  vehicle| over every step of the timed runs, checked against an independent
  query outside the timing (the model puts its reference point on the surface,
  so this is 0 unless something is wrong).
- ``ground_vehicle_steps_per_s_dt1``: the same at dt = 1 s, where sub-stepping
  (no sub-step longer than half a wheel base) does the extra work.
- ``ground_vehicle_grpc_steps_per_s``: the same vehicles over the terrain
  service in its own process on loopback (the model is source-agnostic).
- ``ground_vehicle_lod_speedup`` and ``ground_vehicle_lod_max_pos_diff_m``: four
  observers, far vehicles stepped at up to 1/8 rate: wall time saved, and after
  ``sync()`` the largest position difference of a free-running vehicle from
  full-rate stepping (speed against error).
- ``route_followers_ms_per_tick``: a world tick's update of 100 route followers
  (two in three convoys of 2-8 vehicles, the others lone vehicles; routes of 2-24
  waypoints) through one ``fdm.convoy.FollowerSet``, as the world does;
  ``route_followers_one_by_one_ms_per_tick`` each follower's own update in turn,
  the same run; ``route_followers_speedup`` their quotient (the commands are the
  same bit for bit: tests/test_fdm_convoy.py).
- ``series["ground_dt_sweep"]``: wall time per simulated second against
  position error after 20 s versus dt = 0.01 s, for dt = 0.02 ... 1 s
  (median, p95, max, and the fraction of vehicles stopped by a terrain limit
  in one run but not the other, which is what sets the max).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from bench.harness import Report, data_file

GROUND_DEM = "N47E009.hgt"
GROUND_VEHICLES = 10_000
GROUND_RATE_HZ = 20.0
GROUND_TYPES = ("m1a2", "m2a3", "hmmwv", "m1083")
# Inside the tile with a margin, so every vehicle stays on the DEM.
BOX = (47.05, 9.05, 47.95, 9.95)


def ground_dem_path() -> Path:
    return data_file("dem", GROUND_DEM)


def fleet(terrain, n: int, seed: int = 7):
    """n vehicles, types cycling over GROUND_TYPES, random places, headings and commands."""
    from fdm.ground import GroundVehicles

    rng = np.random.default_rng(seed)
    lat = rng.uniform(BOX[0], BOX[2], n)
    lon = rng.uniform(BOX[1], BOX[3], n)
    types = [GROUND_TYPES[k % len(GROUND_TYPES)] for k in range(n)]
    g = GroundVehicles(terrain, lat, lon, rng.uniform(0.0, 360.0, n), types)
    rev, fwd = g.speed_limits_mps
    u = rng.uniform(-0.5, 1.0, n)  # a third reverse, two thirds forward
    g.set_controls(np.where(u < 0.0, 2.0 * u * rev, u * fwd),
                   rng.uniform(-1.0, 1.0, n) * 0.5 * g.yaw_rate_limit_dps)
    return g


def timed_steps(g, terrain, dt: float, steps: int, check: bool = True):
    """(wall seconds spent in step(), max |height - terrain|) over `steps` steps."""
    wall = 0.0
    err = 0.0
    for _ in range(steps):
        t0 = time.perf_counter()
        g.step(dt)
        wall += time.perf_counter() - t0
        if check:
            ground = terrain.heights(g.lat, g.lon).height_msl_m
            err = max(err, float(np.abs(g.height_msl_m - ground).max()))
    return wall, err


def _throughput(report: Report, terrain, quick: bool) -> None:
    n = GROUND_VEHICLES
    dt = 1.0 / GROUND_RATE_HZ
    steps = 50 if quick else 200
    rounds = 3 if quick else 5
    best = math.inf
    err = 0.0
    blocked = 0.0
    for r in range(rounds):
        g = fleet(terrain, n, seed=r)
        g.step(dt)  # compile / warm outside the timing
        wall, e = timed_steps(g, terrain, dt, steps)
        best = min(best, wall / steps)
        err = max(err, e)
        blocked = float(np.mean(g.blocked != 0))
    report.metrics["ground_vehicle_steps_per_s"] = n / best
    report.metrics["ground_vehicle_height_max_abs_err_m"] = err
    report.metrics["ground_vehicle_blocked_fraction"] = blocked
    g = fleet(terrain, n, seed=11)
    g.step(1.0)
    wall, e = timed_steps(g, terrain, 1.0, 10 if quick else 30)
    report.metrics["ground_vehicle_steps_per_s_dt1"] = n * (10 if quick else 30) / wall
    report.metrics["ground_vehicle_height_max_abs_err_m"] = max(err, e)
    report.params.update(ground_vehicles=n, ground_rate_hz=GROUND_RATE_HZ, ground_steps=steps,
                         ground_rounds=rounds, ground_dem=GROUND_DEM, ground_types=list(GROUND_TYPES),
                         ground_contacts_per_vehicle=5, ground_threads=1)


def _grpc(report: Report, dem_path: Path, quick: bool) -> None:
    from client.terrain_client import TerrainClient
    from server.process import ServiceProcess

    n = GROUND_VEHICLES
    steps = 20 if quick else 100
    with ServiceProcess(["terrain", "serve", "--dem", str(dem_path)]) as service, \
            TerrainClient(service.address) as client:
        g = fleet(client, n, seed=3)
        g.step(1.0 / GROUND_RATE_HZ)
        wall, _ = timed_steps(g, client, 1.0 / GROUND_RATE_HZ, steps, check=False)
    report.metrics["ground_vehicle_grpc_steps_per_s"] = n * steps / wall
    report.params["ground_grpc_server"] = "separate process on loopback"


def _lod(report: Report, terrain, quick: bool) -> None:
    n = GROUND_VEHICLES // 2
    dt = 1.0 / GROUND_RATE_HZ
    steps = 80 if quick else 240
    observers = ([47.2, 47.8, 47.5, 47.3], [9.2, 9.3, 9.6, 9.8])
    full = fleet(terrain, n, seed=5)
    lod = fleet(terrain, n, seed=5)
    lod.set_observers(*observers, near_m=2000.0, max_divisor=8)
    full.step(dt)
    lod.step(dt)
    t_full, _ = timed_steps(full, terrain, dt, steps, check=False)
    t_lod, err = timed_steps(lod, terrain, dt, steps)
    lod.sync()
    from terrain.geodesy import geodetic_to_ecef

    d = np.linalg.norm(geodetic_to_ecef(lod.lat, lod.lon, 0.0) - geodetic_to_ecef(full.lat, full.lon, 0.0), axis=1)
    free = (lod.blocked == 0) & (full.blocked == 0)
    report.metrics["ground_vehicle_lod_speedup"] = t_full / t_lod
    report.metrics["ground_vehicle_lod_max_pos_diff_m"] = float(d[free].max())
    report.metrics["ground_vehicle_lod_p95_pos_diff_m"] = float(np.quantile(d[free], 0.95))
    report.metrics["ground_vehicle_lod_height_max_abs_err_m"] = err
    report.params.update(ground_lod_vehicles=n, ground_lod_observers=len(observers[0]), ground_lod_near_m=2000.0,
                         ground_lod_max_divisor=8,
                         ground_lod_mean_divisor=float(np.mean(lod.divisor)))


def _dt_sweep(report: Report, terrain, quick: bool) -> None:
    from terrain.geodesy import geodetic_to_ecef

    n = 500 if quick else 2000
    sim_s = 20.0
    ref = None
    rows = []
    for dt in (0.01, 0.02, 0.05, 0.1, 0.2, 0.5, 1.0):
        g = fleet(terrain, n, seed=9)
        steps = int(round(sim_s / dt))
        wall, err = timed_steps(g, terrain, dt, steps, check=False)
        pos = geodetic_to_ecef(g.lat, g.lon, 0.0)
        if ref is None:
            ref, ref_blocked = pos, g.blocked.copy()
            continue
        d = np.linalg.norm(pos - ref, axis=1)
        # The max is set by vehicles that stop at a gradient or side-slope limit in one run and
        # pass its crest a hair below the limit in the other: a threshold, not integration error.
        rows.append({"dt_s": dt, "wall_s_per_sim_s_per_1000": wall / sim_s * 1000.0 / n,
                     "median_pos_err_m": float(np.median(d)), "p95_pos_err_m": float(np.quantile(d, 0.95)),
                     "max_pos_err_m": float(d.max()),
                     "stop_differs_fraction": float(np.mean(g.blocked != ref_blocked))})
    report.series["ground_dt_sweep"] = rows
    report.params.update(ground_dt_sweep_vehicles=n, ground_dt_sweep_sim_s=sim_s, ground_dt_sweep_reference_dt=0.01)


def followers(terrain, routes: int, seed: int = 4):
    """(GroundVehicles, followers): ``routes`` routes of 2 to 24 waypoints over the tile, each
    driven by a convoy (two in three, of 2-8 vehicles) or a lone follower, types mixed."""
    from fdm.convoy import Convoy, Route, RouteFollower
    from fdm.ground import GroundVehicles

    rng = np.random.default_rng(seed)
    lats, lons, heads, specs, types, n0 = [], [], [], [], [], 0
    for k in range(routes):
        nw = int(rng.integers(2, 25))
        lat = BOX[0] + 0.1 + 0.7 * rng.random() + np.cumsum(rng.uniform(0.0003, 0.0008, nw))
        lon = BOX[1] + 0.1 + 0.6 * rng.random() + np.cumsum(rng.uniform(-0.0008, 0.0008, nw))
        route = Route(lat, lon)
        m = int(rng.integers(2, 9)) if k % 3 else 1
        la, lo, hd = route.point_at(np.maximum(route.length_m * rng.uniform(0, 0.8) - 60.0 * np.arange(m), 0.0))
        lats.append(la)
        lons.append(lo)
        heads.append(hd)
        types += [GROUND_TYPES[int(t)] for t in rng.integers(0, len(GROUND_TYPES), m)]
        specs.append((route, np.arange(n0, n0 + m)))
        n0 += m
    g = GroundVehicles(terrain, np.concatenate(lats), np.concatenate(lons), np.concatenate(heads), types)
    return g, [Convoy(g, r, idx, 8.0, 50.0) if idx.size > 1 else RouteFollower(g, r, idx, 8.0) for r, idx in specs]


def _followers(report: Report, terrain, quick: bool) -> None:
    """A world tick's route followers: 100 routes (convoys and lone followers), updated through
    one FollowerSet (as the world does) and, in the same run, one by one."""
    from fdm.convoy import FollowerSet

    g, fs = followers(terrain, 100)
    together = FollowerSet(fs)
    together.update()
    ticks, rounds = (10, 3) if quick else (30, 5)
    each = best = math.inf
    for _ in range(rounds):
        t0 = time.perf_counter()
        for _ in range(ticks):
            for f in fs:
                f.update()
        each = min(each, (time.perf_counter() - t0) / ticks)
        t0 = time.perf_counter()
        for _ in range(ticks):
            together.update()
        best = min(best, (time.perf_counter() - t0) / ticks)
    report.metrics["route_followers_ms_per_tick"] = best * 1e3
    report.metrics["route_followers_one_by_one_ms_per_tick"] = each * 1e3
    report.metrics["route_followers_speedup"] = each / best
    report.params.update(route_followers=len(fs), route_follower_vehicles=g.n)


def run_ground(report: Report, quick: bool) -> None:
    """Add the ground-vehicle metrics (see module doc) to ``report``."""
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    path = ground_dem_path()
    terrain = Terrain([read_dem(path)])
    _throughput(report, terrain, quick)
    _followers(report, terrain, quick)
    _lod(report, terrain, quick)
    _dt_sweep(report, terrain, quick)
    _grpc(report, path, quick)


if __name__ == "__main__":  # python -m bench.fdm_ground [--full]
    import sys

    rep = Report(suite="fdm", quick="--full" not in sys.argv)
    t0 = time.perf_counter()
    run_ground(rep, rep.quick)
    rep.print_table()
    for row in rep.series["ground_dt_sweep"]:
        print(row)
    print(f"{time.perf_counter() - t0:.1f} s")
