"""``sortie bench recording``: seeking, size, recording overhead, crash loss, re-simulation.

The load (``long`` in params): a synthetic scenario over the Alps DEM
(bench/fdm.py's tile), written as TOML and run through ``load_scenario`` and
``build_world`` like ``sortie server`` does: aircraft flying circuits on
waypoint routes (f16s at 150-220 m/s, 3-5 km; a c172x), a ground convoy on
a route, ground bots (vehicles without a route that :class:`GroundBots`
drives with the API's ``autopilot`` command: a new heading and speed every
minute, recorded as inputs like a client's) and static sites. The world is
ticked as fast as it goes (aircraft in one worker process) with a
server.recorder.Recorder attached. Full run: 1 hour of world time at 30 Hz,
500 entities (5 aircraft, 12 vehicles in a convoy, 473 bots, 10 statics);
quick: 2 minutes, 100 entities. The mix is set by what this 2-core machine
records in minutes: an aircraft costs ~0.3 ms a tick (4 JSBSim steps, its
autopilot's geodesics, the terrain-collision segment) and a convoy on a
route ~0.5-1 ms a tick whatever its size (fdm/convoy.py's per-corner
loops), against ~2 ms for all 473 bots; the full run's recording takes ~8
minutes, its every-tick ACMI export ~2.5, the whole run ~12.

- ``seek_p99_ms`` / ``seek_p50_ms``: the recording opened once, then
  ``Recording.frame(Recording.tick_at(t))`` at random times, the decoded-chunk
  cache cleared before each (the file's pages stay in the OS cache: it was
  just written). ``seek_disk_cold_p99_ms``: the same with the file's pages
  dropped from the OS cache before each seek (posix_fadvise DONTNEED).
  ``open_ms``: opening the file (header and footer index).
- ``replay_seek_p99_ms``: through ``sortie replay FILE --paused`` (its own
  process): ``SimClient.replay(seek_time_s=t)``, then GetWorld every 2 ms
  until the world time is the sought tick's (the replay clock has decoded and
  shown it), at random times.
- ``bytes_per_entity_second``: file size / sum over ticks of the entities
  present x the tick (dt).
- ``size_vs_acmi_zip``: file size / the ``.zip.acmi`` Tacview export
  (server/acmi.py) of the same recording at every recorded tick;
  ``size_vs_acmi_zip_10hz``: against the export at 10 Hz (the two exports run
  at once, one in a subprocess: this machine has 2 cores);
  ``export_acmi_states_per_s``: the every-tick export's speed;
  ``export_gltf_1hz_points_per_s``: the glTF debrief scene's (server/gltf.py,
  tracks and animated markers, no terrain) at 1 Hz, in track points a second.
- ``record_overhead_ratio``: mean wall time of a world tick (bots' commands
  included: they are journaled) with a recorder attached / without, on the
  long run's scenario (aircraft workers as ``sortie server --aircraft-workers
  auto``), in alternating blocks (ABBA order) of whole chunks; the recorder's
  thread runs throughout, and after each recorded block the time until its
  last chunk is written counts to that block. In params,
  ``overhead_on_tick_hook_ms``: the part spent in the recorder's tick hook on
  the clock thread; the rest is the recorder thread's work (ordering,
  digests, quantising, coding, zstd), which competes with the clock thread
  for the interpreter lock and the cores.
- ``record_encode_states_per_s``, ``record_write_mb_per_s``,
  ``record_encode_core_fraction_realtime``: the recorder thread's work on
  chunks of the long recording (their ticks handed to a new Recorder), alone:
  states per second, compressed MB out per second, and the fraction of a core
  it takes while the world runs in real time.
- ``kill9_lost_s``: ``sortie server --record FILE --clock realtime`` (the long
  scenario, aircraft in the server's process) killed with SIGKILL right after
  a GetWorld poll: at a random moment (polls every 20 ms), and at the worst
  phase (polls every 2 ms, killed at the first that shows the tick closing
  the open chunk, before its write lands); lost = world time at the kill (the
  poll's time + the wall time since the poll was sent x time scale) - the
  last time in the recovered file. The max over every kill;
  ``kill9_lost_mean_s`` the random ones' mean, ``kill9_lost_edge_s`` the
  worst-phase ones' max.
- ``resim_max_abs_diff_m``, ``resim_bit_exact``, ``resim_ticks_per_s``: a
  smaller scenario recorded with inputs (a pilot claims an aircraft, flies it
  by stick and releases it; autopilot commands; a driver claims a vehicle and
  drives it; a convoy member is driven off its route; a static is removed;
  the ground bots), re-simulated by server.resim.resimulate.
"""

from __future__ import annotations

import gc
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.harness import Report, percentile

REPO = Path(__file__).resolve().parents[1]

# The tile of the Alps DEM (N47E009), less a margin; ground agents on land
# (above Lake Constance's 395 m, below 1500 m), as bench/server.py places them.
LAT, LON = (47.05, 47.95), (9.05, 9.95)
LAND_M = (400.0, 1500.0)
GROUND_TYPES = ("hmmwv", "m1083", "m2a3", "m1a2")  # every catalogued vehicle type
# (type, speed range m/s, altitude range m MSL, circuit radius m): mostly fighters, a light aircraft.
AIRCRAFT_TYPES = (("f16", (150.0, 220.0), (3000.0, 5000.0), 12_000.0),) * 4 + (
    ("c172x", (50.0, 55.0), (2700.0, 3200.0), 4_000.0),)
CONVOY_SPACING_M = 40.0
M_PER_DEG_LAT = 111_200.0  # near enough for placing agents
WORLD_RATE_HZ = 30
GLTF_RATE_HZ = 1.0  # the glTF debrief scene's track points and animation keys a second


def _toml(value) -> str:
    """A TOML value (strings, numbers, booleans, lists, inline tables)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + " }"
    raise TypeError(f"no TOML for {type(value).__name__}")


def scenario_toml(data: dict) -> str:
    """TOML text of a scenario dict: top-level tables and ``[[agents]]`` (inline sub-tables)."""
    lines = []
    for key, table in data.items():
        if isinstance(table, dict):
            lines.append(f"[{key}]")
            lines += [f"{k} = {_toml(v)}" for k, v in table.items()]
            lines.append("")
    for key, rows in data.items():
        if isinstance(rows, list):
            for row in rows:
                lines.append(f"[[{key}]]")
                lines += [f"{k} = {_toml(v)}" for k, v in row.items()]
                lines.append("")
    return "\n".join(lines)


def _land_points(terrain, rng, n: int) -> np.ndarray:
    """(n, 2) random (lat, lon) on land across the tile."""
    out = np.zeros((0, 2))
    while len(out) < n:
        lat, lon = rng.uniform(*LAT, 8 * n), rng.uniform(*LON, 8 * n)
        h = np.asarray(terrain.heights(lat, lon).height_msl_m)
        ok = (h > LAND_M[0]) & (h < LAND_M[1])
        out = np.concatenate([out, np.column_stack([lat[ok], lon[ok]])])
    return out[:n]


def _ground_route(terrain, rng, start, length_m: float, step_m: float = 15_000.0) -> list:
    """A wandering route from ``start`` of at least ``length_m`` over land in the tile:
    legs of ``step_m`` turning at most 45 degrees, a leg that would leave the land or
    the tile tried again in another direction."""
    pts = [tuple(start)]
    heading = rng.uniform(0.0, 2 * math.pi)
    m_per_deg_lat = M_PER_DEG_LAT
    m_per_deg_lon = m_per_deg_lat * math.cos(math.radians(47.5))
    while len(pts) < 2 or (len(pts) - 1) * step_m < length_m:
        lat, lon = pts[-1]
        for attempt in range(64):
            h = heading + rng.uniform(-1, 1) * (math.pi / 4 if attempt < 16 else math.pi)
            la = lat + step_m * math.cos(h) / m_per_deg_lat
            lo = lon + step_m * math.sin(h) / m_per_deg_lon
            if LAT[0] < la < LAT[1] and LON[0] < lo < LON[1]:
                z = float(np.asarray(terrain.heights(np.array([la]), np.array([lo])).height_msl_m)[0])
                if LAND_M[0] < z < LAND_M[1] or attempt >= 48:
                    break
        else:  # boxed in: turn back
            h = heading + math.pi
            la = lat + step_m * math.cos(h) / m_per_deg_lat
            lo = lon + step_m * math.sin(h) / m_per_deg_lon
        heading = h
        pts.append((round(la, 6), round(lo, 6)))
    return pts


def _circuit(rng, length_m: float, alt_m: float, radius_m: float, corners: int = 6) -> tuple[list, list]:
    """(waypoints of a polygonal circuit, laps enough for ``length_m``; its corners)."""
    lat0, lon0 = rng.uniform(47.3, 47.7), rng.uniform(9.3, 9.7)
    alt = round(alt_m, 1)
    m_per_deg_lat = M_PER_DEG_LAT
    m_per_deg_lon = m_per_deg_lat * math.cos(math.radians(lat0))
    phase = rng.uniform(0, 2 * math.pi)
    sign = rng.choice([-1.0, 1.0])
    ring = [(lat0 + radius_m * math.cos(phase + sign * 2 * math.pi * k / corners) / m_per_deg_lat,
             lon0 + radius_m * math.sin(phase + sign * 2 * math.pi * k / corners) / m_per_deg_lon)
            for k in range(corners)]
    perimeter = 2 * corners * radius_m * math.sin(math.pi / corners)
    laps = int(math.ceil(length_m / perimeter)) + 1
    pts = [(round(la, 6), round(lo, 6), alt) for _ in range(laps) for la, lo in ring]
    return pts[:1000], ring


def synthetic_scenario(terrain, dem_path, n_aircraft: int, n_ground: int, n_static: int, duration_s: float,
                       n_convoys: int = 2, convoy_size: int = 12, seed: int = 11, controllable: int = 0) -> dict:
    """A scenario dict (server/scenario.py schema): ``n_aircraft`` flying circuits on
    waypoint routes (AIRCRAFT_TYPES), ``n_convoys`` ground convoys of ``convoy_size`` on
    wandering routes long enough to keep them driving for ``duration_s``, the rest of
    the ``n_ground`` vehicles without a route (bot-*: :class:`GroundBots` drives them),
    ``n_static`` sites on land. The first ``controllable`` aircraft and bots may be claimed."""
    rng = np.random.default_rng(seed)
    agents = []
    for i in range(n_aircraft):
        type_, speeds, alts, radius = AIRCRAFT_TYPES[i % len(AIRCRAFT_TYPES)]
        speed = round(float(rng.uniform(*speeds)), 3)
        route, ring = _circuit(rng, speed * duration_s * 1.1, float(rng.uniform(*alts)), radius)
        # Start half a leg before the first corner, heading for it.
        (la0, lo0), (la1, lo1) = ring[-1], ring[0]
        la, lo = (la0 + la1) / 2, (lo0 + lo1) / 2
        hdg = math.degrees(math.atan2((lo1 - lo0) * math.cos(math.radians(la)), la1 - la0)) % 360.0
        agents.append({"name": f"air-{i}", "kind": "aircraft", "type": type_, "coalition": ("blue", "red")[i % 2],
                       "lat_deg": round(la, 6), "lon_deg": round(lo, 6), "alt_m": route[0][2],
                       "heading_deg": round(hdg, 3) % 360.0, "speed_mps": speed, "controllable": i < controllable,
                       "autopilot": {"route": [list(p) for p in route], "speed_mps": speed}})
    n_convoys = min(n_convoys, n_ground // max(convoy_size, 2))
    n_free = n_ground - n_convoys * convoy_size
    starts = _land_points(terrain, rng, n_convoys + n_static + n_free)
    for c, start in enumerate(starts[:n_convoys]):
        cruise = round(float(rng.uniform(5.0, 12.0)), 3)
        route = _ground_route(terrain, rng, start, cruise * duration_s * 1.1 + 2000.0)
        (la0, lo0), (la1, lo1) = route[0], route[1]
        m_lon = M_PER_DEG_LAT * math.cos(math.radians(la0))
        dn, de = (la1 - la0) * M_PER_DEG_LAT, (lo1 - lo0) * m_lon
        d = math.hypot(dn, de)
        for k in range(convoy_size):  # in column behind the leader, on the first leg's line
            agents.append({"name": f"convoy{c}-{k}", "kind": "ground",
                           "type": GROUND_TYPES[(c + k) % len(GROUND_TYPES)], "coalition": ("blue", "red")[c % 2],
                           "lat_deg": round(la0 - k * CONVOY_SPACING_M * dn / d / M_PER_DEG_LAT, 7),
                           "lon_deg": round(lo0 - k * CONVOY_SPACING_M * de / d / m_lon, 7),
                           "heading_deg": round(math.degrees(math.atan2(de, dn)), 3) % 360.0,
                           "autopilot": {"route": [list(p) for p in route], "cruise_mps": cruise,
                                         "convoy": f"convoy{c}", "spacing_m": CONVOY_SPACING_M}})
    for k, (la, lo) in enumerate(starts[n_convoys + n_static:]):
        agents.append({"name": f"bot-{k}", "kind": "ground", "type": GROUND_TYPES[k % len(GROUND_TYPES)],
                       "coalition": ("blue", "red")[k % 2], "lat_deg": round(float(la), 6),
                       "lon_deg": round(float(lo), 6), "heading_deg": round(float(rng.uniform(0, 360)), 2),
                       "controllable": k < controllable})
    for k, (la, lo) in enumerate(starts[n_convoys:n_convoys + n_static]):
        agents.append({"name": f"site-{k}", "kind": "static", "type": ("sam_site", "radar")[k % 2],
                       "coalition": "red", "lat_deg": round(float(la), 6), "lon_deg": round(float(lo), 6)})
    return {
        "exercise": {"name": f"bench recording ({len(agents)} agents)", "start_time": "2026-06-15T07:00:00Z",
                     "fdm_rate_hz": 4 * WORLD_RATE_HZ, "world_rate_hz": WORLD_RATE_HZ, "network_rate_hz": 20,
                     "clock": "realtime", "duration_s": float(max(2.0 * duration_s, 600.0))},
        "terrain": {"dem": [str(dem_path)], "geoid_undulation_m": 48.0},
        "agents": agents,
    }


def write_scenario(directory: Path, name: str, terrain, **kw) -> Path:
    """:func:`synthetic_scenario` written as ``directory/name.toml``."""
    from bench.fdm import alps_dem_path

    path = Path(directory) / f"{name}.toml"
    path.write_text(scenario_toml(synthetic_scenario(terrain, alps_dem_path().resolve(), **kw)))
    return path


class GroundBots:
    """Bots driving the ground vehicles named bot-* through the API's ``autopilot``
    command (the world holds the heading and speed): every ``period_s`` of world time
    each takes a new heading (a turn of up to 60 degrees; towards the tile's middle
    near its edge) and speed (3-12 m/s), staggered, so a command every few ticks. The
    commands are inputs to the world, recorded like a client's."""

    def __init__(self, world, period_s: float = 60.0, seed: int = 5):
        self.world = world
        self.rng = np.random.default_rng(seed)
        self.ids = np.array(sorted(i for i, e in world.entities.items() if e.name.startswith("bot-")), np.int64)
        self.period_ticks = max(1, int(round(period_s / world.dt)))
        self.phase = self.rng.integers(0, self.period_ticks, self.ids.size)
        self.heading = self.rng.uniform(0.0, 360.0, self.ids.size)
        self.commands = 0

    def __call__(self) -> None:
        """Command the bots whose turn it is (call before each tick; all of them at tick 0)."""
        w = self.world
        due = np.flatnonzero((w.tick_count + self.phase) % self.period_ticks == 0) if w.tick_count else \
            np.arange(self.ids.size)
        snap = w.snapshot
        for j in due.tolist():
            i = int(self.ids[j])
            if i not in w.entities:
                continue
            hdg = (self.heading[j] + self.rng.uniform(-60.0, 60.0)) % 360.0
            k = np.flatnonzero(snap.ids == i)
            if k.size:
                lat, lon = float(snap.lat_deg[k[0]]), float(snap.lon_deg[k[0]])
                if not (LAT[0] + 0.05 < lat < LAT[1] - 0.05 and LON[0] + 0.07 < lon < LON[1] - 0.07):
                    mid_lat, mid_lon = (LAT[0] + LAT[1]) / 2, (LON[0] + LON[1]) / 2
                    hdg = math.degrees(math.atan2((mid_lon - lon) * math.cos(math.radians(lat)), mid_lat - lat)) % 360
            self.heading[j] = hdg
            # Rounded, then wrapped: 359.96 rounds to 360.0, which the command refuses ([0, 360)).
            w.command(i, "autopilot", {"heading_deg": round(float(hdg), 1) % 360.0,
                                       "speed_mps": round(float(self.rng.uniform(3.0, 12.0)), 2)})
            self.commands += 1


# -- the runs ---------------------------------------------------------------------------------------

FULL = dict(duration_s=3600.0, n_aircraft=5, n_ground=485, n_static=10, n_convoys=1, convoy_size=12,
            seeks=300, replay_seeks=100, overhead_rounds=80, overhead_block_ticks=30, resim_s=90.0, kill_runs=5,
            kill_after_s=(2.0, 5.0), kill_edge_runs=3, encode_chunks=40)
# --quick: 2 minutes of world time and 20 overhead rounds keep the suite near 40 s here
# (3 minutes and 30 rounds took 48-50 s, close to the brief's 60).
QUICK = dict(duration_s=120.0, n_aircraft=2, n_ground=96, n_static=2, n_convoys=1, convoy_size=8,
             seeks=200, replay_seeks=40, overhead_rounds=20, overhead_block_ticks=30, resim_s=20.0, kill_runs=2,
             kill_after_s=(1.5, 3.0), kill_edge_runs=1, encode_chunks=20)
RESIM = dict(n_aircraft=3, n_ground=40, n_static=2, n_convoys=1, convoy_size=8, controllable=1)
LONG_WORKERS = 1  # aircraft worker processes of the long recording (recordings are the same for any number)


def _log(msg: str) -> None:
    print(f"[bench recording] {msg}", file=sys.stderr, flush=True)


def open_world(scenario_path: Path, workers: int):
    """(world, scenario, terrain, description) of a scenario file, as ``sortie server`` builds it."""
    from server.scenario import load_scenario
    from server.sim_server import aircraft_host, build_world, open_terrain

    scenario = load_scenario(scenario_path)
    terrain, desc, factory = open_terrain(scenario)
    return build_world(scenario, terrain, aircraft_host(scenario, terrain, factory, workers)), scenario, terrain, desc


def new_recorder(path: Path, scenario_path: Path, world, scenario, terrain, desc):
    from server.recorder import Recorder, recording_header
    from server.sim_server import terrain_spec

    return Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain))


def record_world(scenario_path: Path, path: Path, duration_s: float, workers: int, script=None) -> dict:
    """Tick the scenario's world as fast as it goes for ``duration_s`` with a recorder
    attached; before each tick the ground bots and ``script(world)`` (``script`` is
    made by calling it with the world first, when given) make their inputs."""
    world, scenario, terrain, desc = open_world(scenario_path, workers)
    rec = None
    try:
        bots = GroundBots(world)
        script = script(world) if script is not None else None
        rec = new_recorder(path, scenario_path, world, scenario, terrain, desc)
        world.attach_recorder(rec)
        ticks = int(round(duration_s / world.dt))
        present = 0
        t0 = time.perf_counter()
        report_every = max(1, ticks // 12)
        for k in range(ticks):
            if script is not None:
                script(world)
            bots()
            world.tick()
            present += world.snapshot.ids.size
            if ticks > 20_000 and k and k % report_every == 0:
                el = time.perf_counter() - t0
                _log(f"recorded {world.time_s:.0f} of {duration_s:.0f} s world time in {el:.0f} s "
                     f"({el / k * 1e3:.2f} ms/tick)")
        tick_s = time.perf_counter() - t0
        rec.close()
        wall = time.perf_counter() - t0
        if rec.error is not None:
            raise RuntimeError(f"recording failed: {rec.error}")
        return {"ticks": ticks, "dt": world.dt, "entities": len(world.entities), "entity_ticks": present,
                "wall_s": wall, "tick_ms": tick_s / ticks * 1e3, "bytes": path.stat().st_size,
                "bot_commands": bots.commands}
    finally:
        if rec is not None:
            rec.close()
        world.close()


def _drop_page_cache(path: Path) -> bool:
    """Drop this file's pages from the OS cache (clean pages only); False if unsupported."""
    if not hasattr(os, "posix_fadvise"):
        return False
    fd = os.open(path, os.O_RDONLY)
    try:
        os.posix_fadvise(fd, 0, 0, os.POSIX_FADV_DONTNEED)
    finally:
        os.close(fd)
    return True


def bench_seek(report: Report, path: Path, n: int, seed: int = 1) -> None:
    from server.recording import Recording

    t0 = time.perf_counter()
    rec = Recording(path)
    open_ms = (time.perf_counter() - t0) * 1e3
    rng = np.random.default_rng(seed)
    times = rng.uniform(rec.first_time_s, rec.last_time_s, n)
    warm, cold, sizes = [], [], []
    try:
        rec.frame(rec.tick_at(times[0]))  # imports and first-use costs out of the way
        for t in times:
            rec._cache.clear()
            t0 = time.perf_counter()
            f = rec.frame(rec.tick_at(t))
            warm.append((time.perf_counter() - t0) * 1e3)
            sizes.append(f.ids.size)
        can_drop = _drop_page_cache(path)
        if can_drop:
            for t in rng.uniform(rec.first_time_s, rec.last_time_s, n):
                rec._cache.clear()
                _drop_page_cache(path)
                t0 = time.perf_counter()
                rec.frame(rec.tick_at(t))
                cold.append((time.perf_counter() - t0) * 1e3)
        chunk_bytes = (rec.size - rec._data_start) / max(rec.chunk_count, 1)
    finally:
        rec.close()
    report.metrics["seek_p50_ms"] = percentile(warm, 50)
    report.metrics["seek_p99_ms"] = percentile(warm, 99)
    if cold:
        report.metrics["seek_disk_cold_p99_ms"] = percentile(cold, 99)
    report.metrics["open_ms"] = open_ms
    report.params.update(seeks=n, seek_max_ms=max(warm), seek_entities_per_frame=[min(sizes), max(sizes)],
                         mean_chunk_bytes=chunk_bytes)
    if cold:
        report.params["seek_disk_cold_p50_ms"] = percentile(cold, 50)
    report.series["seek_ms"] = sorted(round(x, 4) for x in warm)
    if cold:
        report.series["seek_disk_cold_ms"] = sorted(round(x, 4) for x in cold)


def bench_replay_seek(report: Report, path: Path, n: int, tmp: Path, seed: int = 2, poll_s: float = 0.002) -> None:
    """Seek through ``sortie replay FILE --paused`` (its own process, as deployed): the
    control call, then GetWorld every ``poll_s`` until the world time is the sought
    tick's. Random times across the recording, so its decoded-chunk cache (8 chunks)
    rarely holds the one needed. (Polling without a pause doubles the figure: the
    replay's gRPC thread answering ~1000 calls a second holds the interpreter lock
    its clock thread needs to decode the chunk.)"""
    from client.sim_client import SimClient
    from server.process import ServiceProcess
    from server.recording import Recording

    with Recording(path) as rec:
        first, last, dt = rec.first_time_s, rec.last_time_s, rec.dt
        tick_at = rec.tick_at
        rng = np.random.default_rng(seed)
        targets = [(float(t), tick_at(t) * dt) for t in rng.uniform(first, last, n + 5)]
    samples, polls = [], 0
    with ServiceProcess(["replay", str(path), "--paused"], log=tmp / "replay.log") as svc, \
            SimClient(svc.address) as client:
        client.world()
        for t, want in targets:
            t0 = time.perf_counter()
            client.replay(seek_time_s=t)
            while abs(client.world().time_s - want) > 1e-6:
                polls += 1
                if time.perf_counter() - t0 > 10.0:
                    raise RuntimeError(f"the replay did not show t = {want} s within 10 s of the seek")
                time.sleep(poll_s)
            samples.append((time.perf_counter() - t0) * 1e3)
    samples = samples[5:]  # the first few: connection and first-use warm-up
    report.metrics["replay_seek_p50_ms"] = percentile(samples, 50)
    report.metrics["replay_seek_p99_ms"] = percentile(samples, 99)
    report.params.update(replay_seeks=len(samples), replay_seek_polls_per_seek=polls / len(targets),
                         replay_seek_poll_interval_s=poll_s)
    report.series["replay_seek_ms"] = sorted(round(x, 4) for x in samples)


_EXPORT_SCRIPT = """
import json, sys
from server.acmi import export_acmi
from server.recording import Recording
with Recording(sys.argv[1]) as rec:
    s = export_acmi(rec, sys.argv[2], rate_hz=float(sys.argv[3]))
print(json.dumps({"bytes": s.bytes_written, "text_bytes": s.text_bytes, "states": s.states, "seconds": s.seconds}))
"""


def bench_size(report: Report, path: Path, made: dict, tmp: Path) -> None:
    """Bytes per entity second, and the size against Tacview's .zip.acmi export."""
    from server.acmi import export_acmi
    from server.recording import Recording

    size = path.stat().st_size
    entity_s = made["entity_ticks"] * made["dt"]
    report.metrics["bytes_per_entity_second"] = size / entity_s
    full, ten = tmp / "every_tick.zip.acmi", tmp / "rate_10hz.zip.acmi"
    # The 10 Hz export in a subprocess on the other core while this one exports every tick.
    proc = subprocess.Popen([sys.executable, "-c", _EXPORT_SCRIPT, str(path), str(ten), "10"], cwd=REPO,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        with Recording(path) as rec:
            stats = export_acmi(rec, full)
        out, err = proc.communicate(timeout=3600)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    report.metrics["size_vs_acmi_zip"] = size / stats.bytes_written
    report.metrics["export_acmi_states_per_s"] = stats.states_per_s
    sizes = {"sortie": size, "acmi_zip": stats.bytes_written, "acmi_text": stats.text_bytes}
    if proc.returncode == 0:
        ten_stats = json.loads(out.strip().splitlines()[-1])
        report.metrics["size_vs_acmi_zip_10hz"] = size / ten_stats["bytes"]
        sizes["acmi_zip_10hz"] = ten_stats["bytes"]
        report.params["export_10hz_s"] = ten_stats["seconds"]
    else:
        report.params["export_10hz_error"] = err.strip().splitlines()[-1] if err.strip() else f"exit {proc.returncode}"
    report.params.update(file_bytes=size, entity_seconds=entity_s, acmi_zip_bytes=stats.bytes_written,
                         acmi_text_bytes=stats.text_bytes, acmi_states=stats.states, export_s=stats.seconds,
                         acmi_states_match_recorded=stats.states == made["entity_ticks"])
    report.series["bytes_per_entity_second"] = {k: v / entity_s for k, v in sizes.items()}
    # The glTF debrief scene (tracks and animated markers, no terrain) at 1 Hz.
    from server.gltf import export_gltf

    scene = tmp / "rate_1hz.glb"
    t0 = time.perf_counter()
    with Recording(path) as rec:
        g = export_gltf(rec, scene, rate_hz=GLTF_RATE_HZ)
    seconds = time.perf_counter() - t0
    report.metrics["export_gltf_1hz_points_per_s"] = g.track_points / seconds
    report.params.update(gltf_1hz_bytes=g.bytes_written, gltf_1hz_points=g.track_points, gltf_1hz_s=seconds,
                         gltf_1hz_markers=g.markers)
    for p in (full, ten, scene):
        p.unlink(missing_ok=True)


def bench_encode(report: Report, path: Path, n_chunks: int, tmp: Path) -> None:
    """The recorder thread's work (ordering, digests, quantising, coding, zstd, writing) on
    ``n_chunks`` chunks of the long recording, alone: their ticks handed to a new
    Recorder as snapshots (as the world does), timed until ``close()`` has written them."""
    from server import recording_codec as codec
    from server.recorder import Recorder
    from server.recording import Recording
    from server.world import Snapshot
    from sortie.v1 import recording_pb2 as rpb

    with Recording(path) as rec:
        picks = np.unique(np.linspace(1, rec.chunk_count - 2, n_chunks).astype(int)).tolist()
        snapshots = []
        for k in picks:
            c = rec.chunk(k)
            if c.ticks != rec.chunk(1).ticks:
                continue  # a short chunk would shift the new recorder's chunk boundaries
            for j in range(c.ticks):
                here = c.present[j]
                s = codec.dequantize(c.q[j, here], rec.steps)
                n = int(here.sum())
                snapshots.append(Snapshot(time_s=(c.first_tick + j) * rec.dt, tick=c.first_tick + j,
                                          ids=c.entity_ids[here], ecef_m=s[:, 0:3], vel_ecef_mps=s[:, 3:6],
                                          acc_ecef_mps2=s[:, 6:9], quat_ecef2body=s[:, 9:13],
                                          body_rates_rps=s[:, 13:16], lat_deg=np.zeros(n), lon_deg=np.zeros(n),
                                          alt_msl_m=np.zeros(n)))
        infos = {i: (i, e.name, e.kind, e.type, e.coalition) for i, e in rec.entities.items()}
        header = rpb.RecordingHeader()
        header.CopyFrom(rec.header)
        dt = rec.dt
    out = tmp / "encode.sortie"
    recorder = Recorder(out, header, chunk_s=header.chunk_s or 1.0)
    start = recorder.bytes_written
    t0 = time.perf_counter()
    for snap in snapshots:
        recorder.on_tick(snap, infos)
    recorder.close()
    wall = time.perf_counter() - t0
    written = recorder.bytes_written - start  # the chunks (bytes_written is not moved by the footer)
    out.unlink()
    chunks = len(snapshots) / max(recorder.chunk_ticks, 1)
    report.metrics["record_encode_states_per_s"] = sum(sn.ids.size for sn in snapshots) / wall
    report.metrics["record_write_mb_per_s"] = written / wall / 1e6
    report.metrics["record_encode_core_fraction_realtime"] = wall / (len(snapshots) * dt)
    report.params.update(encode_chunks=chunks, encode_ms_per_chunk=wall / chunks * 1e3)


def bench_overhead(report: Report, scenario_path: Path, tmp: Path, rounds: int, block: int) -> None:
    """The server's tick cost with a recorder attached / without, two ways.

    ``record_overhead_ratio``: wall time of the ticks, one world, blocks of one
    chunk alternating ABBA (short blocks, many rounds: this machine's speed
    drifts by 20 % over seconds, which longer blocks alias into the ratio); a
    recording block includes waiting for its chunk to be coded and written to
    the file (the recorder thread's CPU, charged whole although a live server
    codes a chunk during the next ticks), not for its fdatasync: that is the
    disk's latency on the recorder's thread, which the clock never waits for
    (until MAX_QUEUED_CHUNKS are queued), 4-12 ms a chunk on this VM's disk
    against a 70 ms block. Each block still waits for its fdatasync before the
    next begins, outside the count; ``params.overhead_ratio_waiting_for_sync``
    is the ratio counting that wait too (the figure before the twentieth
    session), ``params.overhead_sync_ms_per_chunk`` the wait itself.
    ``record_overhead_cpu_ratio``: the same blocks' process CPU time (the
    clock thread, the recorder's thread and, with the aircraft in process, the
    aircraft). ``record_cost_share``: the recorder's own CPU (the tick hook +
    its thread's coding and writing, measured by thread CPU clocks) over the
    ticks' wall time without it: the cost the recorder adds, free of the
    machine's drift.
    """
    from server.sim_cli import aircraft_workers

    workers = aircraft_workers("auto")
    world, scenario, terrain, desc = open_world(scenario_path, workers)
    try:
        bots = GroundBots(world)
        for _ in range(60):  # the bots' first commands and the caches
            bots()
            world.tick()
        gc.collect()  # what the server does at start (SimulationServer.start): the world's objects
        gc.freeze()  # leave the cyclic collector, whose full passes would otherwise land in either block
        rec = new_recorder(tmp / "overhead.sortie", scenario_path, world, scenario, terrain, desc)
        chunk_ticks = rec.chunk_ticks
        block = max(chunk_ticks, block // chunk_ticks * chunk_ticks)  # whole chunks: none left open
        hook = rec.on_tick
        hook_s = [0.0]

        def timed_on_tick(snapshot, infos):
            t0 = time.thread_time()
            hook(snapshot, infos)
            hook_s[0] += time.thread_time() - t0

        rec.on_tick = timed_on_tick
        world.attach_recorder(rec)
        for _ in range(2 * chunk_ticks):  # the coder's first chunks (numba's cache) outside the count
            bots()
            world.tick()
        closed = 2
        while rec.chunks_written < closed and rec.error is None:
            time.sleep(0.0005)
        world.recorder = None
        hook_s[0], rec.cpu_s = 0.0, 0.0
        wall = {True: [], False: []}
        cpu = {True: [], False: []}
        synced = []  # recording blocks' wall up to their chunks' fdatasync
        try:
            for r in range(rounds):
                for recording in ((True, False) if r % 2 == 0 else (False, True)):
                    world.recorder = rec if recording else None
                    w0, c0 = time.perf_counter(), time.process_time()
                    for _ in range(block):
                        bots()
                        world.tick()
                    if recording:
                        world.recorder = None
                        closed += block // chunk_ticks
                        while rec.chunks_coded < closed and rec.error is None:
                            time.sleep(0.0002)
                    wall[recording].append(time.perf_counter() - w0)
                    cpu[recording].append(time.process_time() - c0)
                    if recording:
                        while rec.chunks_written < closed and rec.error is None:
                            time.sleep(0.0002)
                        synced.append(time.perf_counter() - w0)
        finally:
            world.recorder = None
            rec.close()
            (tmp / "overhead.sortie").unlink(missing_ok=True)
    finally:
        world.close()
    ticks = rounds * block
    without_s = sum(wall[False])
    own_s = hook_s[0] + rec.cpu_s
    report.metrics["record_overhead_ratio"] = sum(wall[True]) / without_s
    report.metrics["record_overhead_cpu_ratio"] = sum(cpu[True]) / sum(cpu[False])
    report.metrics["record_cost_share"] = own_s / without_s
    pairs = [a / b for a, b in zip(wall[True], wall[False])]
    report.params.update(overhead_ratio_waiting_for_sync=sum(synced) / without_s,
                         overhead_sync_ms_per_chunk=(sum(synced) - sum(wall[True])) / (ticks / chunk_ticks) * 1e3,
                         overhead_tick_ms_with=sum(wall[True]) / ticks * 1e3,
                         overhead_tick_ms_without=without_s / ticks * 1e3,
                         overhead_on_tick_hook_ms=hook_s[0] / ticks * 1e3,
                         overhead_writer_cpu_ms_per_tick=rec.cpu_s / ticks * 1e3,
                         overhead_median_round_ratio=float(np.median(pairs)),
                         overhead_round_ratio_p10_p90=[float(np.percentile(pairs, 10)), float(np.percentile(pairs, 90))],
                         overhead_rounds=rounds, overhead_block_ticks=block, overhead_aircraft_workers=workers)


class PilotScript:
    """The inputs of the re-simulation recording, by world time (done before the tick):
    a pilot claims air-0, flies it by stick for 8 s and lets go (its autopilot takes it
    back); air-1 gets new autopilot targets; a driver claims bot-0, drives it and lets
    go; a convoy member is driven off its route; site-0 is removed."""

    def __init__(self, world):
        self.by_name = {e.name: i for i, e in world.entities.items()}

    def __call__(self, world) -> None:
        t, k, ids = world.time_s, world.tick_count, self.by_name
        if k == 60:
            world.claim(ids["air-0"], "bench-token", "bench-pilot")
        if 60 <= k < 300 and k % 3 == 0:
            world.command(ids["air-0"], "stick", {"pitch": 0.15 * math.sin(t), "roll": 0.4 * math.sin(0.7 * t),
                                                  "throttle": 0.9})
        if k == 300:
            world.release(ids["air-0"])
        if k == 90:
            world.command(ids["air-1"], "autopilot", {"heading_deg": 200.0, "alt_msl_m": 3500.0, "speed_mps": 180.0})
        if k == 150:
            world.claim(ids["bot-0"], "bench-token-2", "bench-driver")
        if 150 <= k < 450 and k % 15 == 0:
            world.command(ids["bot-0"], "drive", {"speed_mps": 8.0, "yaw_rate_dps": 6.0 * math.sin(0.3 * t)})
        if k == 450:
            world.release(ids["bot-0"])
        if k == 210:
            world.command(ids["convoy0-3"], "drive", {"speed_mps": 4.0, "yaw_rate_dps": 2.0})
        if k == 270:
            world.remove(ids["site-0"], "bench")


def bench_resim(report: Report, tmp: Path, terrain, duration_s: float) -> None:
    from server.recording import Recording
    from server.resim import resimulate

    scenario_path = write_scenario(tmp, "resim", terrain, duration_s=duration_s, seed=23, **RESIM)
    path = tmp / "resim.sortie"
    made = record_world(scenario_path, path, duration_s, 0, PilotScript)
    with Recording(path) as rec:
        inputs = rec.index.input_count
    r = resimulate(path)
    path.unlink()
    report.metrics["resim_max_abs_diff_m"] = r.max_abs_diff_m
    report.metrics["resim_bit_exact"] = 1.0 if r.bit_exact else 0.0
    report.metrics["resim_ticks_per_s"] = r.ticks / r.wall_s
    report.params.update(resim_world_s=duration_s, resim_entities=made["entities"], resim_ticks=r.ticks,
                         resim_bit_exact_ticks=r.bit_exact_ticks, resim_inputs=inputs, resim_wall_s=r.wall_s,
                         resim_first_divergence=str(r.first_divergence) if r.first_divergence else None,
                         resim_notes=list(r.notes), resim_record_tick_ms=made["tick_ms"])


# The worst-phase kill: it reads the live recording's chunks from this world time on (two chunks
# on disk), polls GetWorld this often (a tick is 33 ms; the probe that found the edge polled at
# 2 ms), and gives up on the edge after this many wall seconds.
KILL9_EDGE_AFTER_WORLD_S = 2.0
KILL9_EDGE_POLL_S = 0.002
KILL9_EDGE_TIMEOUT_S = 20.0


def _chunk_edge(path: Path) -> tuple[float, float, float] | None:
    """(world time of the last tick on disk, of the tick that will close the open chunk, of a
    tick) of the live recording at ``path``, a chunk's length read from its last whole chunk;
    None while it has fewer than two chunks (the first may hold tick 0 besides a chunk's)."""
    from server.recording import Recording

    with Recording(path) as rec:
        if rec.chunk_count < 2:
            return None
        first, last = rec.chunk_ticks(rec.chunk_count - 1)
        return rec.last_time_s, rec.last_time_s + (last - first + 1) * rec.dt, rec.dt


def _kill9_once(scenario_path: Path, tmp: Path, run: int, kill_after_s: float | None) -> dict:
    """SIGKILL a recording ``sortie server`` right after a GetWorld poll, ``kill_after_s`` wall
    seconds in, or (None) at the worst phase: the first poll that shows the tick closing the open
    chunk, before its write and fdatasync land (the last tick on disk is then a whole chunk old,
    and the write's time comes on top). The world time lost, and what the recording held."""
    from client.sim_client import SimClient
    from server.process import ServiceProcess
    from server.recording import Recording

    path = tmp / f"kill9-{run}.sortie"
    svc = ServiceProcess(["server", "--scenario", str(scenario_path), "--record", str(path), "--clock",
                          "realtime", "--aircraft-workers", "0"], log=tmp / f"kill9-{run}.log",
                         start_timeout_s=120.0)
    edge = None
    with svc:
        with SimClient(svc.address) as client:
            scale = client.world().time_scale or 1.0
            started = time.monotonic()
            while True:
                sent = time.monotonic()
                world_t = client.world().time_s
                if kill_after_s is not None:
                    if sent - started >= kill_after_s:
                        break
                    time.sleep(max(0.0, 0.02 - (time.monotonic() - sent)))
                    continue
                if sent - started >= KILL9_EDGE_TIMEOUT_S:
                    break  # never saw the edge (a stalled clock): a kill like any other
                if edge is not None and world_t > edge[1] + 0.5 * edge[2]:
                    edge = None  # the closing tick went by between polls: the next chunk's
                if edge is not None and world_t >= edge[1] - 0.5 * edge[2]:
                    break  # half a tick: the closing tick's time, whatever its rounding
                if edge is None and world_t >= KILL9_EDGE_AFTER_WORLD_S:
                    edge = _chunk_edge(path)
                time.sleep(KILL9_EDGE_POLL_S)
            svc.proc.kill()
            killed = time.monotonic()
            svc.proc.wait()
    with Recording(path) as rec:
        last = rec.last_time_s
        recovered = rec.recovered
    at_kill = world_t + (killed - sent) * scale
    detail = {"phase": "random" if kill_after_s is not None else "chunk_edge", "world_s_at_kill": round(at_kill, 4),
              "recorded_to_s": round(last, 4), "recovered": recovered, "bytes": path.stat().st_size}
    if edge is not None:
        detail["closing_tick_s"] = round(edge[1], 4)
    path.unlink()
    return {"lost_s": at_kill - last, "detail": detail}


def bench_kill9(report: Report, scenario_path: Path, tmp: Path, runs: int, after_s: tuple, edge_runs: int,
                seed: int = 3) -> None:
    """World time a SIGKILL loses: ``runs`` kills at random wall times ``after_s`` in (the typical
    loss) and ``edge_runs`` at the worst phase (_kill9_once); ``kill9_lost_s`` is the worst of all."""
    rng = np.random.default_rng(seed)
    at_random = [_kill9_once(scenario_path, tmp, k, float(rng.uniform(*after_s))) for k in range(runs)]
    edge = [_kill9_once(scenario_path, tmp, runs + k, None) for k in range(edge_runs)]
    lost = [r["lost_s"] for r in at_random + edge]
    report.metrics["kill9_lost_s"] = max(lost)
    report.metrics["kill9_lost_mean_s"] = float(np.mean([r["lost_s"] for r in at_random]))
    report.metrics["kill9_lost_edge_s"] = max(r["lost_s"] for r in edge)
    report.params.update(kill9_runs=runs, kill9_edge_runs=edge_runs, kill9_detail=[r["detail"] for r in at_random + edge],
                         kill9_lost_s_is="the worst of the random-phase and chunk-edge kills; kill9_lost_mean_s "
                                         "the mean of the random-phase ones",
                         kill9_server="sortie server --clock realtime --aircraft-workers 0, chunk 1 s")


def run(quick: bool) -> Report:
    from bench.fdm import alps_terrain

    cfg = QUICK if quick else FULL
    report = Report(suite="recording", quick=quick)
    stages = report.params.setdefault("stage_wall_s", {})
    clock = [time.perf_counter()]

    def stage(name: str) -> None:
        now = time.perf_counter()
        stages[name] = round(now - clock[0], 2)
        clock[0] = now

    terrain = alps_terrain()
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="sortie-bench-recording-") as tmp_name:
        tmp = Path(tmp_name)
        scenario_path = write_scenario(tmp, "long", terrain, n_aircraft=cfg["n_aircraft"], n_ground=cfg["n_ground"],
                                       n_static=cfg["n_static"], n_convoys=cfg["n_convoys"],
                                       convoy_size=cfg["convoy_size"], duration_s=cfg["duration_s"])
        path = tmp / "long.sortie"
        _log(f"recording {cfg['duration_s']:.0f} s of world time, "
             f"{cfg['n_aircraft'] + cfg['n_ground'] + cfg['n_static']} entities")
        stage("setup")
        made = record_world(scenario_path, path, cfg["duration_s"], LONG_WORKERS)
        report.params["long"] = {
            "world_s": made["ticks"] * made["dt"], "world_rate_hz": 1.0 / made["dt"], "entities": made["entities"],
            "aircraft": cfg["n_aircraft"], "ground_on_routes": cfg["n_convoys"] * cfg["convoy_size"],
            "convoys": cfg["n_convoys"], "ground_bots": cfg["n_ground"] - cfg["n_convoys"] * cfg["convoy_size"],
            "static": cfg["n_static"], "bot_commands": made["bot_commands"], "record_wall_s": made["wall_s"],
            "record_tick_ms": made["tick_ms"], "aircraft_workers": LONG_WORKERS, "file_bytes": made["bytes"]}
        stage("record_long")
        _log(f"recorded in {made['wall_s']:.0f} s ({made['tick_ms']:.2f} ms a tick); seeking")
        bench_seek(report, path, cfg["seeks"])
        stage("seek")
        bench_replay_seek(report, path, cfg["replay_seeks"], tmp)
        stage("replay_seek")
        bench_encode(report, path, cfg["encode_chunks"], tmp)
        stage("encode")
        _log("exporting ACMI")
        bench_size(report, path, made, tmp)
        path.unlink()
        stage("acmi_export")
        _log("recording overhead")
        bench_overhead(report, scenario_path, tmp, cfg["overhead_rounds"], cfg["overhead_block_ticks"])
        stage("overhead")
        _log("re-simulation")
        bench_resim(report, tmp, terrain, cfg["resim_s"])
        stage("resim")
        _log("kill -9")
        bench_kill9(report, scenario_path, tmp, cfg["kill_runs"], cfg["kill_after_s"], cfg["kill_edge_runs"])
        stage("kill9")
    report.params["total_wall_s"] = time.perf_counter() - t_start
    return report
