"""The flight and ground part of ``sortie demo`` (issue #3).

A c172x and an f16 fly waypoint routes on autopilot and a convoy of four
ground vehicles drives a route up the Rhine valley, all over the Alps DEM
(N47E009) and all coupled to the terrain through the terrain service's client
library, as a server would host them. Writes one CSV track per agent and
returns a summary per agent (distance, heights, clearance, events, convoy gaps).
"""

from __future__ import annotations

import csv
import math
import time
from pathlib import Path

import numpy as np
from geographiclib.geodesic import Geodesic

# Routes inside N47E009 (47..48 N, 9..10 E): the Rhine valley, Lake Constance, the Alpstein.
C172_START = (47.40, 9.62, 1500.0, 0.0, 50.0)  # lat, lon, alt MSL m, heading deg, speed m/s
C172_ROUTE = [(47.415, 9.62, 1500.0), (47.415, 9.65, 1500.0), (47.40, 9.65, 1500.0)]
F16_START = (47.30, 9.30, 4500.0, 90.0, 220.0)
F16_ROUTE = [(47.30, 9.55, 4500.0), (47.45, 9.70, 4000.0), (47.60, 9.45, 4000.0)]
CONVOY_ROUTE = ([47.24, 47.26, 47.28, 47.28, 47.30], [9.522, 9.537, 9.552, 9.58, 9.60])
CONVOY_TYPES = ["hmmwv", "m2a3", "m2a3", "m1083"]
CONVOY_SPACING_M = 50.0
CONVOY_CRUISE_MPS = 12.0
FLIGHT_S = 150.0
GROUND_S = 120.0
GROUND_DT_S = 0.1
TRACK_EVERY_S = 1.0


def _write_track(path: Path, header: list[str], rows: list) -> None:
    with open(path, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(header)
        w.writerows(rows)


def fly(name: str, start, route, terrain, out: Path) -> dict:
    """Fly ``route`` on the waypoint autopilot for FLIGHT_S; a track CSV and a summary."""
    from fdm.aircraft import Aircraft, InitialConditions
    from fdm.autopilot import WaypointFollower

    lat, lon, alt, heading, speed = start
    ac = Aircraft(name, terrain, InitialConditions(lat, lon, alt, heading_deg=heading, speed_mps=speed))
    follower = WaypointFollower(ac, route, speed_mps=speed)
    every = max(1, int(round(TRACK_EVERY_S / ac.dt)))
    rows, events = [], []
    t0 = time.perf_counter()
    for k in range(int(round(FLIGHT_S / ac.dt))):
        follower.update()
        events.extend(ac.step())
        if k % every == 0 or ac.crashed:
            s = ac.state()
            rows.append((round(s.time_s, 3), s.lat_deg, s.lon_deg, s.alt_msl_m, s.agl_m,
                         math.degrees(s.euler_rad[2]) % 360.0, s.airspeed_true_mps))
        if ac.crashed:
            break
    wall = time.perf_counter() - t0
    _write_track(out / f"track-{name}.csv", ["time_s", "lat_deg", "lon_deg", "alt_msl_m", "agl_m",
                                             "heading_deg", "tas_mps"], rows)
    track = np.array([r[1:5] for r in rows])
    return {
        "agent": name, "simulated_s": rows[-1][0], "wall_s": wall,
        "distance_km": _path_length_m(track[:, 0], track[:, 1]) / 1e3,
        "alt_min_m": float(track[:, 2].min()), "alt_max_m": float(track[:, 2].max()),
        "min_agl_m": float(track[:, 3].min()),
        "waypoints_passed": f"{len(follower.passed)}/{len(route)}",
        "events": [str(e) for e in events], "track_csv": str(out / f"track-{name}.csv"),
    }


def drive_convoy(terrain, out: Path) -> dict:
    """A convoy along CONVOY_ROUTE for GROUND_S; a track CSV and a summary."""
    from fdm.convoy import Convoy, Route
    from fdm.ground import GroundVehicles

    route = Route(*CONVOY_ROUTE)
    n = len(CONVOY_TYPES)
    s0 = CONVOY_SPACING_M * np.arange(n - 1, -1, -1, dtype=float) + 10.0
    lat, lon, heading = route.point_at(s0)
    vehicles = GroundVehicles(terrain, lat, lon, heading, CONVOY_TYPES)
    convoy = Convoy(vehicles, route, np.arange(n), cruise_mps=CONVOY_CRUISE_MPS, spacing_m=CONVOY_SPACING_M)
    every = max(1, int(round(TRACK_EVERY_S / GROUND_DT_S)))
    rows, gaps = [], []
    t0 = time.perf_counter()
    for k in range(int(round(GROUND_S / GROUND_DT_S))):
        convoy.update()
        vehicles.step(GROUND_DT_S)
        if k % every == 0:
            st = vehicles.state()
            gaps.append(np.array(convoy.gaps_m))
            for i in range(n):
                rows.append((round((k + 1) * GROUND_DT_S, 3), i, CONVOY_TYPES[i], st.lat_deg[i], st.lon_deg[i],
                             st.height_msl_m[i], st.speed_mps[i], st.pitch_deg[i], st.roll_deg[i]))
    wall = time.perf_counter() - t0
    path = out / "track-convoy.csv"
    _write_track(path, ["time_s", "vehicle", "type", "lat_deg", "lon_deg", "height_msl_m", "speed_mps",
                        "pitch_deg", "roll_deg"], rows)
    lead = np.array([(r[3], r[4]) for r in rows if r[1] == 0])
    settled = np.array(gaps[len(gaps) // 2:])
    return {
        "agent": f"convoy of {n} ({', '.join(CONVOY_TYPES)})", "simulated_s": GROUND_S, "wall_s": wall,
        "distance_km": _path_length_m(lead[:, 0], lead[:, 1]) / 1e3,
        "alt_min_m": float(min(r[5] for r in rows)), "alt_max_m": float(max(r[5] for r in rows)),
        "gap_mean_m": float(np.mean(settled)) if settled.size else math.nan,
        "gap_max_error_m": float(np.max(np.abs(settled - CONVOY_SPACING_M))) if settled.size else math.nan,
        "blocked_at_end": int(np.count_nonzero(vehicles.blocked)), "track_csv": str(path),
    }


def _path_length_m(lat, lon) -> float:
    g = Geodesic.WGS84
    return float(sum(g.Inverse(lat[i], lon[i], lat[i + 1], lon[i + 1])["s12"] for i in range(len(lat) - 1)))


def run_agents(terrain, out: Path) -> list[dict]:
    """Every agent of the demo, one after another, on ``terrain`` (a TerrainClient or Terrain)."""
    return [fly("c172x", C172_START, C172_ROUTE, terrain, out),
            fly("f16", F16_START, F16_ROUTE, terrain, out),
            drive_convoy(terrain, out)]
