"""``sortie fdm``: list the JSBSim aircraft, fly one and summarise its track.

    sortie fdm list [--json]
    sortie fdm fly AIRCRAFT --lat DEG --lon DEG --alt-m M [--agl] --heading-deg DEG --speed-mps V
                   --seconds S [--dem FILE...] [--ground] [--hold] [--dt S] [--json]
    sortie fdm trims [AIRCRAFT...] [--alt-m M] [--speeds MPS...] [--timeout-s S] [--json]
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import math
import os
import sys


def add_parser(sub) -> None:
    fdm = sub.add_parser("fdm", help="JSBSim aircraft: list the catalog, fly one, survey trims",
                         description="List the aircraft of the JSBSim catalog, fly one over a terrain and print "
                                     "a short track summary, or survey the speeds each trims at.")
    commands = fdm.add_subparsers(dest="fdm_command", metavar="SUBCOMMAND", required=True)

    lst = commands.add_parser("list", help="the aircraft the jsbsim wheel ships",
                              description="Print the names of the loadable JSBSim aircraft and their class.")
    lst.add_argument("--json", action="store_true", help="print JSON instead of text")
    lst.set_defaults(func=list_command)

    fly = commands.add_parser("fly", help="fly an aircraft and summarise the track",
                              description="Start AIRCRAFT at (--lat, --lon), trimmed in level flight (or at "
                                          "rest on the ground with --ground), fly it for --seconds with "
                                          "centred controls (or holding heading, altitude and speed with "
                                          "--hold) and print the track summary and events.")
    fly.add_argument("aircraft", help="catalog name, e.g. c172x, f16, A4 (see `sortie fdm list`)")
    fly.add_argument("--lat", type=float, required=True, help="start latitude, degrees WGS84")
    fly.add_argument("--lon", type=float, required=True, help="start longitude, degrees WGS84")
    fly.add_argument("--alt-m", type=float, default=1000.0, help="start altitude, m MSL (default %(default)s)")
    fly.add_argument("--agl", action="store_true", help="--alt-m is above the terrain, not MSL")
    fly.add_argument("--heading-deg", type=float, default=0.0, help="true heading, degrees (default %(default)s)")
    fly.add_argument("--speed-mps", type=float, default=60.0, help="true airspeed, m/s (default %(default)s)")
    fly.add_argument("--seconds", type=float, default=60.0, help="simulated time (default %(default)s)")
    fly.add_argument("--dt", type=float, default=1.0 / 120.0, help="step, s (default 1/120)")
    fly.add_argument("--dem", nargs="+", default=[], metavar="FILE",
                     help="DEM files for the terrain (default: flat at sea level)")
    fly.add_argument("--ground", action="store_true", help="start at rest on the ground")
    fly.add_argument("--hold", action="store_true", help="autopilot: hold start heading, altitude and speed")
    fly.add_argument("--json", action="store_true", help="print JSON instead of text")
    fly.set_defaults(func=fly_command)

    from fdm.trim_survey import add_parser as add_trims

    add_trims(commands)


def list_command(args) -> int:
    from fdm.catalog import aircraft_class, list_aircraft

    names = list_aircraft()
    if args.json:
        print(json.dumps([{"name": n, "class": aircraft_class(n)} for n in names]))
    else:
        for n in names:
            print(f"{n:20s} {aircraft_class(n)}")
    return 0


def fly(aircraft: str, ic, seconds: float, terrain=None, dt: float = 1.0 / 120.0, hold: bool = False) -> dict:
    """Fly and return the track summary (SI) as a dict; the CLI prints it."""
    from fdm.aircraft import Aircraft, FlatTerrain
    from fdm.autopilot import Autopilot
    from sortie.errors import InvalidArgument

    if not (math.isfinite(seconds) and 0 < seconds <= 36_000):
        raise InvalidArgument("--seconds", "must be within (0, 36000]", value=seconds)
    ac = Aircraft(aircraft, terrain or FlatTerrain(0.0), ic, dt=dt)
    start = ac.state()
    ap = None
    if hold:
        ap = Autopilot(ac)
        ap.set_targets(start.heading_deg, start.alt_msl_m, max(start.airspeed_true_mps, 1.0))
    track = [start]
    every = max(1, round(1.0 / dt))
    for k in range(int(round(seconds / dt))):
        if ap:
            ap.update()
        ac.step()
        if k % every == every - 1 or ac.crashed:
            track.append(ac.state())
        if ac.crashed:
            break
    end = ac.state()
    dist = sum(float(((b.ecef_m - a.ecef_m) ** 2).sum() ** 0.5) for a, b in zip(track, track[1:]))
    return {
        "aircraft": ac.name, "class": ac.aircraft_class, "simulated_s": end.time_s,
        "start": _point(start), "end": _point(end),
        "distance_m": dist,
        "alt_msl_m_min": min(s.alt_msl_m for s in track), "alt_msl_m_max": max(s.alt_msl_m for s in track),
        "agl_m_min": min(s.agl_m for s in track),
        "speed_mps_min": min(s.airspeed_true_mps for s in track),
        "speed_mps_max": max(s.airspeed_true_mps for s in track),
        "load_factor_g_max": max(s.load_factor_g for s in track),
        "crashed": ac.crashed,
        "events": [{"kind": e.kind, "time_s": e.time_s, "lat_deg": e.lat_deg, "lon_deg": e.lon_deg,
                    "alt_msl_m": e.alt_msl_m, **e.detail} for e in ac.events],
    }


@contextlib.contextmanager
def _stdout_to_stderr():
    """File descriptor 1 is 2 inside: whatever the flight's native code prints on stdout (JSBSim
    writes some messages with C++ streams, past its logger, which fdm.aircraft routes to Python's
    logging) goes to stderr, and stdout holds only the summary (``--json``: one JSON document)."""
    sys.stdout.flush()
    saved = os.dup(1)
    try:
        os.dup2(2, 1)
        yield
    finally:
        with contextlib.suppress(OSError, AttributeError, TypeError):  # no C library to flush (not POSIX)
            ctypes.CDLL(None).fflush(None)  # C stdio's buffer, written while fd 1 was stderr
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)


def _point(s) -> dict:
    return {"time_s": s.time_s, "lat_deg": s.lat_deg, "lon_deg": s.lon_deg, "alt_msl_m": s.alt_msl_m,
            "agl_m": s.agl_m, "heading_deg": s.heading_deg, "airspeed_mps": s.airspeed_true_mps}


# What a trim failure's advice says here instead of the API's (fdm.aircraft.TRIM_OFF_HINT: fly
# has no untrimmed airborne start); server.sim_server says the same of a scenario.
FLY_TRIM_HINT = "; here give --speed-mps or --alt-m a value it trims at, or start it on the ground (--ground)"


def fly_command(args) -> int:
    from fdm.aircraft import TRIM_OFF_HINT, InitialConditions, TrimFailed
    from fdm.trim_survey import ALT_MAX_M
    from sortie.errors import InvalidArgument

    # The bound `sortie fdm trims` (which a failed trim's advice names) and a scenario's start
    # take: a start past the Karman line, 100 km, is a unit mix-up; it cranked the engine for
    # 16 s, then failed its trim with advice to run a command that refuses the value.
    if not args.alt_m <= ALT_MAX_M:  # NaN too (the finite checks follow in InitialConditions)
        raise InvalidArgument("--alt-m", f"must be at most {ALT_MAX_M:g} m", value=args.alt_m)
    terrain = None
    if args.dem:
        from server.terrain_cli import build_terrain

        terrain = build_terrain(args.dem)
    ic = InitialConditions(args.lat, args.lon, args.alt_m, "agl" if args.agl else "msl", args.heading_deg,
                           0.0 if args.ground else args.speed_mps, on_ground=args.ground)
    try:
        with _stdout_to_stderr():
            summary = fly(args.aircraft, ic, args.seconds, terrain, args.dt, args.hold)
    except TrimFailed as exc:
        raise TrimFailed(str(exc).replace(TRIM_OFF_HINT, FLY_TRIM_HINT)) from None
    if args.json:
        print(json.dumps(summary, indent=2))
        return 0
    s, e = summary["start"], summary["end"]
    print(f"{summary['aircraft']} ({summary['class']}), {summary['simulated_s']:.1f} s simulated")
    print(f"  start  {s['lat_deg']:.6f}, {s['lon_deg']:.6f}  {s['alt_msl_m']:8.1f} m MSL  "
          f"{s['heading_deg']:6.1f} deg  {s['airspeed_mps']:6.1f} m/s")
    print(f"  end    {e['lat_deg']:.6f}, {e['lon_deg']:.6f}  {e['alt_msl_m']:8.1f} m MSL  "
          f"{e['heading_deg']:6.1f} deg  {e['airspeed_mps']:6.1f} m/s  AGL {e['agl_m']:.1f} m")
    print(f"  flown  {summary['distance_m'] / 1000:.2f} km; altitude {summary['alt_msl_m_min']:.1f}.."
          f"{summary['alt_msl_m_max']:.1f} m; speed {summary['speed_mps_min']:.1f}..{summary['speed_mps_max']:.1f}"
          f" m/s; max {summary['load_factor_g_max']:.2f} g")
    for ev in summary["events"]:
        extra = ", ".join(f"{k}={v}" for k, v in ev.items() if k not in ("kind", "time_s", "lat_deg", "lon_deg",
                                                                           "alt_msl_m"))
        print(f"  event  {ev['time_s']:7.2f} s  {ev['kind']}" + (f" ({extra})" if extra else ""))
    return 0
