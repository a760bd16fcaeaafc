"""Dead reckoning for ``sortie bench server``: messages saved against the receivers' error.

Manoeuvring bots are recorded first -- four real JSBSim aircraft (c172x and
f16 on :class:`fdm.autopilot.WaypointFollower` routes with turns and climbs,
two over the Alps DEM, two over flat ground) and a convoy of six ground
vehicles on a zig-zag route up the Rhine valley floor (N47E009) -- and their
true states sampled at 20 Hz (the network rate) for 60 s (quick: 20 s). The
samples are then replayed through :class:`server.dead_reckoning.DeadReckoner`
(the sender) and :class:`server.dead_reckoning.Extrapolator` (a receiver), as
the server would stream them.

What a sample carries. ECEF position (float64); ECEF velocity (JSBSim's NED
velocity, the ground model's ground velocity, rotated); ECEF acceleration as
the backward difference of velocity over the last model step (1/120 s for
aircraft, 1/20 s for ground vehicles: one rule for every kind of entity,
lagging the instantaneous value by half a step); the ECEF -> body quaternion
(:func:`server.dead_reckoning.ned_to_ecef_quat` of the NED attitude); body
rates: JSBSim's p, q, r (relative to ECEF, body axes; they match the
attitude's change over a step to 1.4e-5 rad/s) and, for ground vehicles,
:func:`server.dead_reckoning.body_rates_between` the last two attitudes.
Velocity, acceleration, quaternion and rates are rounded to float32 before
they are "sent", as ``EntityState`` carries them, so sender and receiver hold
the same bits.

Metrics (thresholds 1 m / 3 deg / 5 s; each kind's algorithm from
``server.dead_reckoning.THRESHOLDS_BY_KIND``: RVW for aircraft and ground vehicles):

- ``dr_message_reduction``: 1 - updates / (entities x 20 Hz samples); also per kind;
- ``dr_p99_position_error_m``, ``dr_max_position_error_m``,
  ``dr_p99_orientation_error_deg``: the receiver's error at every 20 Hz
  sample, taken *before* that sample's update arrives (the worst it showed).
  The receiver was within the thresholds at the previous sample, so anything
  over them is growth within one 50 ms sample period (also
  ``dr_max_orientation_error_deg``, ``dr_messages_per_entity_s``, ``dr_bytes_per_entity_s``);
- ``dr_bytes_per_update``: mean serialized size of the ``sortie.v1.EntityState``
  of each update sent (fields the algorithm does not use are left empty),
  plus its tag and length inside ``WatchUpdate.states``; a fixed layout
  (FALLBACK_LAYOUT_BYTES) when the generated code is absent;
- ``series["dr_thresholds"]``: for position thresholds POSITION_SWEEP_M
  (orientation 3 deg): messages and bytes per entity-second, p99 and max
  position error (bandwidth against error; :func:`plot_dr` draws it);
- ``series["dr_algorithms"]``: messages, bytes and errors per kind for FPW,
  RPW, RVW and FVW at the default thresholds: the measurement behind each
  kind's algorithm (``params["dr_fewest_bytes_<kind>"]`` names the winner).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from bench.harness import Report

RATE_HZ = 20.0
SECONDS = 60.0
QUICK_SECONDS = 20.0
POSITION_SWEEP_M = (0.25, 0.5, 1.0, 2.0, 5.0, 10.0)
# (name, terrain, start (lat, lon, alt MSL m, heading deg), speed m/s, legs (north km, east km, climb m)
# from the start, one per waypoint). The starts point away from the first waypoint: they turn at once.
AIRCRAFT = (
    ("f16", "alps", (47.30, 9.30, 4500.0, 0.0), 180.0,
     ((-1.0, 4.0, 300.0), (-3.0, 8.0, -200.0), (2.0, 11.0, 200.0), (6.0, 9.0, -300.0), (8.0, 3.0, 0.0))),
    ("c172x", "alps", (47.58, 9.55, 1200.0, 0.0), 50.0,
     ((0.3, 1.2, 100.0), (-0.8, 1.8, -50.0), (-1.2, 0.5, 100.0), (-0.2, -0.5, 0.0))),
    ("f16", "flat", (47.30, 9.50, 3000.0, 180.0), 180.0,
     ((2.0, 3.0, -300.0), (6.0, 1.0, 300.0), (7.0, -4.0, 0.0), (2.0, -7.0, 300.0), (-3.0, -5.0, 0.0))),
    ("c172x", "flat", (47.30, 9.50, 1000.0, 90.0), 50.0,
     ((0.8, -0.3, 150.0), (1.4, 0.8, -100.0), (0.4, 1.6, 100.0), (-0.5, 0.8, 0.0))),
)
AIRCRAFT_DT_S = 1.0 / 120.0
# The Rhine valley floor between Oberriet and Lustenau (about 430 m): legs of 150-250 m,
# turns of 40-70 degrees, so the column turns every 15-20 s.
CONVOY_ROUTE = ([47.2600, 47.2620, 47.2625, 47.2645, 47.2650, 47.2672, 47.2678, 47.2700, 47.2705, 47.2728],
                [9.5450, 9.5465, 9.5495, 9.5510, 9.5540, 9.5552, 9.5585, 9.5597, 9.5630, 9.5642])
CONVOY_TYPES = ("hmmwv", "m2a3", "m2a3", "m1083", "m1a2", "hmmwv")
CONVOY_SPACING_M = 30.0
CONVOY_CRUISE_MPS = 10.0
# EntityState as a fixed layout when sortie.v1.simulation_pb2 is absent: id u64, time f64,
# position f64 x3, velocity, acceleration f32 x3, quaternion f32 x4, rates f32 x3, algorithm u8.
FALLBACK_LAYOUT_BYTES = 8 + 8 + 24 + 12 + 12 + 16 + 12 + 1


@dataclass
class Tracks:
    """True states of n entities at k samples of RATE_HZ: times (k,) s; pos (k, n, 3)
    ECEF m; vel (k, n, 3) ECEF m/s; acc (k, n, 3) ECEF m/s^2; quat (k, n, 4)
    ECEF -> body; omega (k, n, 3) body rad/s; kind (n,) "aircraft" or "ground"."""

    times: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    acc: np.ndarray
    quat: np.ndarray
    omega: np.ndarray
    kind: np.ndarray


def _waypoints(start, legs):
    from terrain.geodesy import radii_of_curvature

    lat0, lon0, alt0, _ = start
    m, n = radii_of_curvature(lat0)
    return [(lat0 + math.degrees(dn * 1e3 / m), lon0 + math.degrees(de * 1e3 / (n * math.cos(math.radians(lat0)))),
             alt0 + dz) for dn, de, dz in legs]


def fly(name: str, terrain, start, speed_mps: float, legs, seconds: float) -> dict:
    """One aircraft on its waypoint route; the sample arrays (k, 3)/(k, 4) of :class:`Tracks`."""
    from fdm.aircraft import Aircraft, InitialConditions
    from fdm.autopilot import WaypointFollower
    from fdm.state import state_arrays
    from server.dead_reckoning import ned_to_ecef_quat

    lat, lon, alt, heading = start
    ac = Aircraft(name, terrain, InitialConditions(lat, lon, alt, heading_deg=heading, speed_mps=speed_mps),
                  dt=AIRCRAFT_DT_S)
    follower = WaypointFollower(ac, _waypoints(start, legs), speed_mps=speed_mps)
    every = round(1.0 / (RATE_HZ * AIRCRAFT_DT_S))
    rows = [ac.raw_values()]
    before = []  # the state one model step before each sample, for the acceleration
    for k in range(round(seconds * RATE_HZ)):
        for j in range(every):
            if j == every - 1:
                before.append(ac.raw_values())
            follower.update()
            ac.step()
        rows.append(ac.raw_values())
    if ac.crashed or ac.events:
        raise RuntimeError(f"{name} on its route: {ac.events}")
    s = state_arrays(np.array(rows))
    vel_before = state_arrays(np.array(before))["vel_ecef_mps"]
    acc = np.concatenate([np.zeros((1, 3)), (s["vel_ecef_mps"][1:] - vel_before) / AIRCRAFT_DT_S])
    return {"pos": s["ecef_m"], "vel": s["vel_ecef_mps"], "acc": acc,
            "quat": ned_to_ecef_quat(s["quat_wxyz"], s["lat_deg"], s["lon_deg"]), "omega": s["body_rates_rps"]}


def _ground_sample(vehicles):
    from fdm.state import euler_to_quaternion, ned_to_ecef_vectors
    from server.dead_reckoning import ned_to_ecef_quat
    from terrain.geodesy import geodetic_to_ecef

    lat, lon = vehicles.lat, vehicles.lon
    q_ned = euler_to_quaternion(np.radians(vehicles.roll_deg), np.radians(vehicles.pitch_deg),
                                np.radians(vehicles.heading_deg))
    return (geodetic_to_ecef(lat, lon, vehicles.height_msl_m), ned_to_ecef_vectors(vehicles.velocity_ned(), lat, lon),
            ned_to_ecef_quat(q_ned, lat, lon))


def drive(terrain, seconds: float) -> dict:
    """The convoy on CONVOY_ROUTE, stepped at RATE_HZ; arrays (k, n, ...) of :class:`Tracks`."""
    from fdm.convoy import Convoy, Route
    from fdm.ground import GroundVehicles
    from server.dead_reckoning import body_rates_between

    route = Route(*CONVOY_ROUTE)
    n = len(CONVOY_TYPES)
    lat, lon, heading = route.point_at(CONVOY_SPACING_M * np.arange(n - 1, -1, -1, dtype=float) + 5.0)
    vehicles = GroundVehicles(terrain, lat, lon, heading, list(CONVOY_TYPES))
    convoy = Convoy(vehicles, route, np.arange(n), cruise_mps=CONVOY_CRUISE_MPS, spacing_m=CONVOY_SPACING_M)
    dt = 1.0 / RATE_HZ
    samples = [_ground_sample(vehicles)]
    for _ in range(round(seconds * RATE_HZ)):
        convoy.update()
        vehicles.step(dt)
        samples.append(_ground_sample(vehicles))
    if vehicles.blocked.any():
        raise RuntimeError(f"convoy blocked: {vehicles.blocked}")
    pos, vel, quat = (np.stack(a) for a in zip(*samples))
    acc = np.concatenate([np.zeros((1, n, 3)), np.diff(vel, axis=0) / dt])
    omega = np.concatenate([np.zeros((1, n, 3)), body_rates_between(quat[:-1], quat[1:], dt)])
    return {"pos": pos, "vel": vel, "acc": acc, "quat": quat, "omega": omega}


def record(seconds: float, aircraft=AIRCRAFT) -> Tracks:
    """The bots' true states at RATE_HZ for ``seconds``: aircraft first, then the convoy."""
    from bench.fdm import alps_terrain
    from fdm.aircraft import FlatTerrain

    terrains = {"alps": alps_terrain(), "flat": FlatTerrain(0.0)}
    flown = [fly(name, terrains[where], start, speed, legs, seconds) for name, where, start, speed, legs in aircraft]
    ground = drive(terrains["alps"], seconds)
    k = round(seconds * RATE_HZ) + 1
    arrays = {key: np.concatenate([np.stack([f[key] for f in flown], axis=1), ground[key]], axis=1)
              for key in ("pos", "vel", "acc", "quat", "omega")}
    kind = np.array(["aircraft"] * len(flown) + ["ground"] * len(CONVOY_TYPES))
    return Tracks(times=np.arange(k) / RATE_HZ, kind=kind, **arrays)


def _f32(a: np.ndarray) -> np.ndarray:
    """Rounded to float32 as the wire carries it, back in float64."""
    return a.astype(np.float32).astype(np.float64)


@dataclass
class Replay:
    """One replay: sent (k, n) bool; the receiver's errors before each sample's
    update, pos_err_m and ori_err_rad (k, n), NaN at the first sample; the
    algorithm of each entity (n,)."""

    sent: np.ndarray
    pos_err_m: np.ndarray
    ori_err_rad: np.ndarray
    algorithm: np.ndarray


def replay(tracks: Tracks, thresholds) -> Replay:
    """Stream the tracks through a DeadReckoner into an Extrapolator.

    thresholds: one :class:`server.dead_reckoning.Thresholds` per entity.
    """
    from server.dead_reckoning import DeadReckoner, Extrapolator, rotation_angle

    k, n = tracks.pos.shape[:2]
    ids = np.arange(1, n + 1)
    sender, receiver = DeadReckoner(), Extrapolator()
    for i, th in enumerate(thresholds):
        sender.add(ids[i:i + 1], th)
    sent = np.zeros((k, n), bool)
    pos_err = np.full((k, n), np.nan)
    ori_err = np.full((k, n), np.nan)
    for j, t in enumerate(tracks.times):
        pos, quat = tracks.pos[j], _f32(tracks.quat[j])
        if j:
            p_r, q_r = receiver.state(t, ids)
            pos_err[j] = np.linalg.norm(p_r - pos, axis=1)
            ori_err[j] = rotation_angle(q_r, tracks.quat[j])
        vel, acc, omega = _f32(tracks.vel[j]), _f32(tracks.acc[j]), _f32(tracks.omega[j])
        send = sender.update(t, ids, pos, vel, acc, quat, omega)
        if send.any():
            receiver.receive(t, ids[send], pos[send], vel[send], acc[send], quat[send], omega[send],
                             sender.algorithm(ids[send]))
        sent[j] = send
    return Replay(sent, pos_err, ori_err, sender.algorithm(ids))


def update_bytes(tracks: Tracks, result: Replay) -> tuple[np.ndarray, str]:
    """(bytes of each update sent, (k, n), 0 where none was; where the sizes come from)."""
    sizes = np.zeros(result.sent.shape)
    try:
        from sortie.v1.simulation_pb2 import EntityState
    except ImportError:
        sizes[result.sent] = FALLBACK_LAYOUT_BYTES
        return sizes, "fixed layout (FALLBACK_LAYOUT_BYTES)"
    from server.dead_reckoning import FVW, RPW, RVW, STATIC

    for j, i in zip(*np.nonzero(result.sent)):
        alg = int(result.algorithm[i])
        msg = EntityState(entity_id=int(i) + 1, time_s=float(tracks.times[j]), ecef_x_m=tracks.pos[j, i, 0],
                          ecef_y_m=tracks.pos[j, i, 1], ecef_z_m=tracks.pos[j, i, 2],
                          orientation_wxyz=tracks.quat[j, i].tolist(), dead_reckoning=alg)
        if alg != STATIC:
            msg.velocity_ecef_mps.extend(tracks.vel[j, i].tolist())
        if alg in (RVW, FVW):
            msg.acceleration_ecef_mps2.extend(tracks.acc[j, i].tolist())
        if alg in (RPW, RVW):
            msg.angular_velocity_body_rps.extend(tracks.omega[j, i].tolist())
        body = msg.ByteSize()
        sizes[j, i] = body + 1 + _varint_len(body)  # tag and length inside WatchUpdate.states
    return sizes, "sortie.v1.EntityState serialized, inside WatchUpdate.states"


def _varint_len(v: int) -> int:
    return max(1, (v.bit_length() + 6) // 7)


def summary(tracks: Tracks, result: Replay, select=None) -> dict:
    """Messages, bytes and errors of a replay over the entities ``select`` (n,) bool (default all).

    Rates per entity-second leave out the first sample (every entity's first update).
    """
    sel = np.ones(tracks.pos.shape[1], bool) if select is None else select
    per_entity_s = 1.0 / (sel.sum() * (tracks.times[-1] - tracks.times[0]))
    sent = result.sent[:, sel]
    sizes, _ = update_bytes(tracks, result)
    pos = result.pos_err_m[1:, sel].ravel()
    ori = np.degrees(result.ori_err_rad[1:, sel].ravel())
    return {"updates": int(sent.sum()), "samples": int(sent.size),
            "message_reduction": float(1.0 - sent.sum() / sent.size),
            "messages_per_entity_s": float(sent[1:].sum() * per_entity_s),
            "bytes_per_update": float(sizes[:, sel][sent].mean()),
            "bytes_per_entity_s": float(sizes[1:, sel].sum() * per_entity_s),
            "p99_position_error_m": float(np.quantile(pos, 0.99)), "max_position_error_m": float(pos.max()),
            "p99_orientation_error_deg": float(np.quantile(ori, 0.99)), "max_orientation_error_deg": float(ori.max())}


def run_dr(report: Report, quick: bool, seconds: float | None = None, aircraft=AIRCRAFT) -> None:
    """Record the bots, replay them through dead reckoning, add metrics and series to ``report``.

    ``seconds`` and ``aircraft`` shrink the run for smoke tests.
    """
    from server.dead_reckoning import (ALGORITHM_NAMES, DEFAULT_HEARTBEAT_S, DEFAULT_ORIENTATION_THRESHOLD_RAD,
                                       DEFAULT_POSITION_THRESHOLD_M, FPW, FVW, RPW, RVW, THRESHOLDS_BY_KIND, Thresholds)

    seconds = seconds if seconds is not None else (QUICK_SECONDS if quick else SECONDS)
    tracks = record(seconds, aircraft)
    per_kind = [THRESHOLDS_BY_KIND[k] for k in tracks.kind]
    n = tracks.pos.shape[1]
    orientation_deg = math.degrees(DEFAULT_ORIENTATION_THRESHOLD_RAD)

    main = replay(tracks, per_kind)
    s = summary(tracks, main)
    m = report.metrics
    m["dr_message_reduction"] = s["message_reduction"]
    for kind in ("aircraft", "ground"):
        m[f"dr_message_reduction_{kind}"] = summary(tracks, main, tracks.kind == kind)["message_reduction"]
    for key in ("p99_position_error_m", "max_position_error_m", "p99_orientation_error_deg",
                "max_orientation_error_deg", "messages_per_entity_s", "bytes_per_update", "bytes_per_entity_s"):
        m[f"dr_{key}"] = s[key]

    sweep = []
    for threshold in POSITION_SWEEP_M:
        result = main if threshold == DEFAULT_POSITION_THRESHOLD_M else \
            replay(tracks, [replace(t, position_m=threshold) for t in per_kind])
        r = summary(tracks, result)
        sweep.append({"position_threshold_m": threshold, "orientation_threshold_deg": orientation_deg,
                      **{key: r[key] for key in ("messages_per_entity_s", "bytes_per_entity_s", "p99_position_error_m",
                                                 "max_position_error_m", "p99_orientation_error_deg")}})
    report.series["dr_thresholds"] = sweep

    algorithms = []
    for code in (FPW, RPW, RVW, FVW):
        result = replay(tracks, [Thresholds(algorithm=code)] * n)
        for kind in ("aircraft", "ground"):
            algorithms.append({"kind": kind, "algorithm": ALGORITHM_NAMES[code],
                               **summary(tracks, result, tracks.kind == kind)})
    report.series["dr_algorithms"] = algorithms
    best = {kind: min((a for a in algorithms if a["kind"] == kind), key=lambda a: a["bytes_per_entity_s"])
            for kind in ("aircraft", "ground")}

    report.params.update(
        dr_rate_hz=RATE_HZ, dr_seconds=seconds, dr_entities=n,
        dr_aircraft=[f"{a[0]} over {a[1]}" for a in aircraft], dr_ground=list(CONVOY_TYPES),
        dr_position_threshold_m=DEFAULT_POSITION_THRESHOLD_M, dr_orientation_threshold_deg=orientation_deg,
        dr_heartbeat_s=DEFAULT_HEARTBEAT_S,
        dr_algorithm_aircraft=ALGORITHM_NAMES[THRESHOLDS_BY_KIND["aircraft"].algorithm],
        dr_algorithm_ground=ALGORITHM_NAMES[THRESHOLDS_BY_KIND["ground"].algorithm],
        dr_fewest_bytes_aircraft=best["aircraft"]["algorithm"], dr_fewest_bytes_ground=best["ground"]["algorithm"],
        dr_bytes_source=update_bytes(tracks, main)[1],
        dr_error_taken="at each 20 Hz sample, before that sample's update")


def plot_dr(report: dict, out_dir: Path) -> list[Path]:
    """Bandwidth (bytes per entity-second) against the p99 and max receiver
    position error, from ``series["dr_thresholds"]``, log axes; the files written."""
    from bench.plots import _pyplot, _save

    rows = report.get("series", {}).get("dr_thresholds")
    if not rows:
        return []
    plt = _pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    fig, ax = plt.subplots(figsize=(6.5, 4.5))
    ax.set_xscale("log")
    ax.set_yscale("log")
    bw = [r["bytes_per_entity_s"] for r in rows]
    ax.plot(bw, [r["p99_position_error_m"] for r in rows], "o-", color="tab:blue", label="p99")
    ax.plot(bw, [r["max_position_error_m"] for r in rows], "s--", color="tab:orange", label="max")
    for r, x in zip(rows, bw):
        ax.annotate(f"{r['position_threshold_m']:g} m", (x, r["p99_position_error_m"]), fontsize=7,
                    xytext=(4, 4), textcoords="offset points")
    ax.set_xlabel("bytes per entity-second (EntityState updates)")
    ax.set_ylabel("receiver position error at 20 Hz samples (m)")
    ax.set_title("Dead reckoning: bandwidth against error\n(labels: position threshold; orientation 3 deg)",
                 fontsize=9)
    ax.legend(fontsize=8)
    _save(fig, out_dir / "dr_bandwidth_vs_error.png", written)
    return written
