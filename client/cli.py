"""``sortie client`` (a headless observer printing the live picture; with ``--follow`` or
``--agent-type``, the render client of client/render_cli.py, as ``sortie view``, whose options
--headless, --frames, --fps, --out, --chase are refused without either) and
``sortie bot`` (many autopilot agents in one process, as ordinary clients).

    sortie client --server HOST:PORT [--observe LAT LON RADIUS_M] [--duration S] [--every S]
    sortie bot --server HOST:PORT [--count N] [--profile patrol|racetrack] [--leg-s S] [--duration S]

A bot joins as ROLE_BOT (taking a free controllable agent), watches, and flies
or drives its profile with autopilot commands: "patrol" turns 90 degrees
every leg (a box), "racetrack" 180 degrees (out and back); aircraft also step
their altitude by +-300 m each leg.
"""

from __future__ import annotations

import argparse
import math
import re
import sys
import signal
import threading
import time

import numpy as np

from sortie.errors import InvalidArgument

PROFILES = ("patrol", "racetrack")
MAX_BOTS = 256  # a server's sessions (server/sim_service.py MAX_SESSIONS)
MAX_DURATION_S = 7 * 86_400.0  # a scenario's longest exercise (server/scenario.py DURATION_MAX_S)
LEG_S = (1.0, 3_600.0)  # --leg-s, world seconds
EVERY_S = (0.05, 3_600.0)  # --every, wall seconds
MIN_LEG_WALL_S = 0.2  # a bot commands at most 5 times a wall second, however fast the clock
DEFAULT_OBSERVE_RADIUS_M = 100_000.0
# sortie client's render options (with --follow or --agent-type), and what they are when not given.
RENDER_DEFAULTS = {"headless": False, "frames": 100, "fps": 10.0, "out": "frames", "chase": False}


def _finite(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number (got {text!r})") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number (got {text!r})")
    return value


def _seconds_within(lo: float, hi: float):
    """An argparse type: a finite number of seconds in [lo, hi]."""
    def parse(text: str) -> float:
        value = _finite(text)
        if not lo <= value <= hi:
            raise argparse.ArgumentTypeError(f"must be within [{lo:g}, {hi:g}] s (got {text!r})")
        return value
    return parse


def _duration_s(text: str) -> float:
    """An argparse type: 0 (until a signal) or wall seconds in (0, MAX_DURATION_S]."""
    value = _finite(text)
    if not 0.0 <= value <= MAX_DURATION_S:
        raise argparse.ArgumentTypeError(f"must be 0 (until SIGTERM/SIGINT) or within (0, {MAX_DURATION_S:g}] s "
                                         f"(got {text!r})")
    return value


def _bot_count(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a whole number (got {text!r})") from None
    if not 1 <= value <= MAX_BOTS:
        raise argparse.ArgumentTypeError(f"must be within [1, {MAX_BOTS}] (got {text!r})")
    return value


def add_parser(sub) -> None:
    c = sub.add_parser("client", help="headless observer: print the live picture",
                       description="Join a simulation server as an observer and print what it sees "
                                   "(dead-reckoned positions) every --every seconds.")
    c.add_argument("--server", required=True, metavar="HOST:PORT")
    c.add_argument("--observe", nargs=3, type=float, metavar=("LAT", "LON", "RADIUS_M"),
                   help="centre and radius of the area of interest (default: the first target area, 100 km or "
                        "the server's observer limit when smaller)")
    c.add_argument("--duration", type=_duration_s, default=10.0, metavar="S",
                   help=f"wall seconds, at most {MAX_DURATION_S:g}; 0 runs until SIGTERM/SIGINT "
                        "(default %(default)s)")
    c.add_argument("--every", type=_seconds_within(*EVERY_S), default=2.0, metavar="S",
                   help=f"print period, wall seconds in [{EVERY_S[0]:g}, {EVERY_S[1]:g}] (default %(default)s)")
    c.add_argument("--name", default="observer")
    render = c.add_argument_group("rendering (issue #5's thin client: the same as sortie view)")
    who = render.add_mutually_exclusive_group()
    who.add_argument("--follow", metavar="AGENT", help="render, following this agent (see sortie view --help)")
    who.add_argument("--agent-type", choices=("aircraft", "ground"), help="render, following the first of this kind")
    # (Defaults None, filled in by client_command: given without --follow/--agent-type they are refused.)
    render.add_argument("--headless", action="store_true", default=None,
                        help="render offscreen (EGL); the only mode on machines without a display")
    render.add_argument("--frames", type=int, default=None, metavar="N",
                        help=f"frames to render (default {RENDER_DEFAULTS['frames']})")
    render.add_argument("--fps", type=float, default=None,
                        help=f"frames per wall second, at most (default {RENDER_DEFAULTS['fps']:g})")
    render.add_argument("--out", default=None, metavar="DIR",
                        help=f"where the frames go (default {RENDER_DEFAULTS['out']})")
    render.add_argument("--chase", action="store_true", default=None, help="chase camera (default: cockpit)")
    c.set_defaults(func=client_command)

    b = sub.add_parser("bot", help="run N autopilot bots as clients of a simulation server",
                       description="Each bot joins as ROLE_BOT, takes a free controllable agent and flies or "
                                   "drives a profile with autopilot commands.")
    b.add_argument("--server", required=True, metavar="HOST:PORT")
    b.add_argument("--count", type=_bot_count, default=1, metavar="N",
                   help=f"bots, [1, {MAX_BOTS}] (a server's session limit; default %(default)s)")
    b.add_argument("--profile", choices=PROFILES, default="patrol")
    b.add_argument("--leg-s", type=_seconds_within(*LEG_S), default=20.0, metavar="S",
                   help=f"world seconds per leg, [{LEG_S[0]:g}, {LEG_S[1]:g}]; a leg lasts at least "
                        f"{MIN_LEG_WALL_S:g} wall seconds whatever the clock's speed (default %(default)s)")
    b.add_argument("--duration", type=_duration_s, default=30.0, metavar="S",
                   help=f"wall seconds, at most {MAX_DURATION_S:g}; 0 runs until SIGTERM/SIGINT "
                        "(default %(default)s)")
    b.set_defaults(func=bot_command)


def _geodetic(pos):
    from terrain.geodesy import ecef_to_geodetic

    return ecef_to_geodetic(np.asarray(pos, float).reshape(-1, 3))


def _until(duration_s: float) -> float:
    """The monotonic time a run of ``duration_s`` wall seconds ends (0: never)."""
    return time.monotonic() + duration_s if duration_s > 0 else math.inf


def _stop_on_signals() -> threading.Event:
    """An event SIGTERM and SIGINT set (main thread): the clients leave cleanly and exit 0."""
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda signum, frame: stop.set())
    return stop


def client_command(args) -> int:
    given = [f"--{name}" for name in RENDER_DEFAULTS if getattr(args, name) is not None]
    if not (args.follow or args.agent_type) and given:  # the text observer would ignore them
        are = "is a rendering option" if len(given) == 1 else "are rendering options"
        raise InvalidArgument(given[0], f"{', '.join(given)} {are}: rendering needs --follow AGENT or --agent-type "
                                        "aircraft|ground (without either, sortie client prints the picture as text)",
                              value=getattr(args, given[0][2:]))
    for name, default in RENDER_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.follow or args.agent_type:  # the render client (client/render_cli.py)
        from sortie.cli import main

        who = ["--follow", args.follow] if args.follow else ["--agent-type", args.agent_type]
        return main(["view", "--server", args.server, *who, "--frames", str(args.frames), "--fps", str(args.fps),
                     "--out", args.out, "--name", args.name, *(["--chase"] if args.chase else [])])
    from client.sim_client import SimClient

    stop = _stop_on_signals()
    with SimClient(args.server) as sim:
        sim.wait_ready()
        observe = args.observe if args.observe is not None else default_observe(sim.world())
        sim.join(args.name, "observer", observer=tuple(observe))
        print(f"observing {sim.world_info.exercise_name!r} around ({observe[0]:.4f}, {observe[1]:.4f}), "
              f"{observe[2] / 1000:.0f} km", flush=True)
        picture = sim.watch()
        end = _until(args.duration)
        while time.monotonic() < end and not stop.is_set() and picture.alive:
            picture.wait_for(lambda p: stop.is_set(), min(args.every, max(end - time.monotonic(), 0.0)))
            if not picture.alive:
                break
            ids, pos, _ = picture.state()
            print(f"t = {picture.now_s():7.1f} s  {len(ids)} entities  ({picture.updates} updates, "
                  f"{picture.states_received} states, {picture.bytes} bytes)", flush=True)
            if len(ids):
                lat, lon, h = _geodetic(pos)
                for k, i in enumerate(ids):
                    info = picture.infos.get(int(i))
                    name = info.name if info else str(i)
                    kind = info.type if info else ""
                    print(f"  {name:14s} {kind:10s} {lat[k]:9.5f} {lon[k]:9.5f} {h[k]:8.1f} m (ellipsoid)", flush=True)
        return stream_end(sim, picture)


def _mean_lon_deg(lon_deg) -> float:
    """The mean of longitudes (degrees) taken the short way round: the mean of their offsets,
    wrapped into [-180, 180), from the first, in [-180, 180) (an area across the antimeridian,
    179.97 .. -179.97, is at 180, not 0)."""
    lon = np.asarray(lon_deg, np.float64)
    if lon.size == 0:
        return 0.0
    offsets = (lon - lon[0] + 180.0) % 360.0 - 180.0
    return float((lon[0] + offsets.mean() + 180.0) % 360.0 - 180.0)


def default_observe(w) -> tuple[float, float, float]:
    """(lat, lon, radius_m) an observer watches without --observe: the centre of the world's
    (a WorldInfo) first target area, else where its entities are (entity_count,
    centre_lat_deg, centre_lon_deg), else (0, 0); 100 km, or the server's observer limit
    (observer_radius_max_m) when that is smaller."""
    radius = DEFAULT_OBSERVE_RADIUS_M
    if w.observer_radius_max_m > 0:  # 0: a server that does not say
        radius = min(radius, w.observer_radius_max_m)
    if w.target_areas:
        a = w.target_areas[0]
        return float(np.mean(a.lat_deg)), _mean_lon_deg(a.lon_deg), radius
    if w.entity_count > 0:
        return float(w.centre_lat_deg), float(w.centre_lon_deg), radius
    return 0.0, 0.0, radius


def stream_end(sim, picture) -> int:
    """Leave the server if it is still there; the exit code: 0 for a stop asked of this
    client or an exercise the server ended, 1 for a server gone (the stream broke) or a
    stream its own session ended (ABORTED: superseded, left), each with a line that says
    so. A picture is no longer extrapolated past the stream's end."""
    from sortie.errors import SortieError

    if picture.alive:  # stopped here (duration, signal)
        try:
            sim.leave()
        except SortieError:
            pass
        return 0
    if picture.error is None:
        print(f"the server ended the exercise at world time {picture.time_s:.1f} s", flush=True)
        return 0
    from client.sim_client import StreamAborted

    if isinstance(picture.error, StreamAborted):  # its own session ended it (a new Watch, a leave)
        print(f"this client's stream was ended at world time {picture.time_s:.1f} s: {picture.error}",
              file=sys.stderr, flush=True)
        return 1
    print(f"the server went away at world time {picture.time_s:.1f} s: {picture.error}", file=sys.stderr,
          flush=True)
    return 1


def _bot(address: str, k: int, profile: str, leg_s: float, duration_s: float, results: list,
         stop: threading.Event) -> None:
    """One bot's thread: its result line in ``results`` whatever happens (a server that goes
    away mid-run is a line, not a traceback)."""
    try:
        _fly_bot(address, k, profile, leg_s, duration_s, results, stop)
    except Exception as exc:  # noqa: BLE001 - reported per bot; the other bots go on
        results.append((k, None, f"stopped: {exc}"))


def _fly_bot(address: str, k: int, profile: str, leg_s: float, duration_s: float, results: list,
             stop: threading.Event) -> None:
    from client.sim_client import SimClient

    turn = 90.0 if profile == "patrol" else 180.0
    with SimClient(address) as sim:
        try:
            agent = sim.join(f"bot-{k}", "bot")
        except Exception as exc:  # noqa: BLE001 - reported per bot
            results.append((k, None, f"could not join: {exc}"))
            return
        picture = sim.watch()
        picture.wait_for(lambda p: agent in p.infos, 10.0)
        info = picture.infos.get(agent)
        aircraft = info is not None and info.kind == 1
        controls = sim.controls()
        info_w = getattr(sim, "world_info", None)
        undulation = float(info_w.geoid_undulation_m) if info_w is not None else 0.0
        legs = 0
        end = _until(duration_s)
        heading = None
        while time.monotonic() < end and not stop.is_set():
            ids, pos, quat = picture.state(ids=[agent]) if agent in picture.infos else (None, None, None)
            if pos is not None and heading is None:
                heading = _heading_deg(pos[0], quat[0])
            if heading is None:
                stop.wait(0.1)
                continue
            heading = _wrap360(heading + turn) if legs else heading
            targets = {"heading_deg": heading}
            if aircraft:  # the state's height is above the ellipsoid; the autopilot holds MSL
                _, _, h = _geodetic(pos)
                msl = float(h[0]) - undulation
                targets["alt_msl_m"] = msl + (300.0 if legs % 2 == 0 else -300.0)
            else:
                targets["speed_mps"] = 8.0
            try:
                controls.autopilot(**targets)
            except InvalidArgument as exc:
                lost = _agent_lost(exc)
                if lost is None:
                    raise
                sim.leave()  # its agent crashed or was destroyed: its flight is over, not failed
                results.append((k, agent, f"{legs} legs, then its agent {lost}; {picture.updates} updates"))
                return
            legs += 1
            wait_end = time.monotonic() + max(leg_s / max(picture.time_scale, 1e-6), MIN_LEG_WALL_S)
            while time.monotonic() < min(wait_end, end) and not stop.is_set():
                stop.wait(0.2)
        accepted = controls.close()
        sim.leave()
        results.append((k, agent, f"{legs} legs, {accepted} commands accepted, {picture.updates} updates"))


_WRECK = re.compile(r" (has crashed|is destroyed)\b")


def _agent_lost(exc: InvalidArgument) -> str | None:
    """"crashed" or "was destroyed" when a refused command says the bot's agent is a wreck
    (server.world.World.command: "command: NAME has crashed (got ...)"), else None."""
    m = _WRECK.search(exc.message) if exc.field == "command" else None
    return None if m is None else "crashed" if m[1] == "has crashed" else "was destroyed"


def _heading_deg(pos, quat) -> float:
    """True heading of an ECEF -> body quaternion at an ECEF position."""
    from server.dead_reckoning import ecef_to_ned_quat, quat_conjugate, quat_multiply
    from terrain.geodesy import ecef_to_geodetic

    lat, lon, _ = ecef_to_geodetic(np.asarray(pos, float).reshape(1, 3))
    # q_ecef2body = q_ecef2ned * q_ned2body (server.dead_reckoning.ned_to_ecef_quat)
    q_ned2body = quat_multiply(quat_conjugate(ecef_to_ned_quat(lat[0], lon[0])), quat)
    w, x, y, z = np.asarray(q_ned2body, float).reshape(4)
    return _wrap360(math.degrees(math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))))


def _wrap360(deg: float) -> float:
    """deg in [0, 360), as the autopilot command takes it (``x % 360.0`` is 360.0 for a tiny
    negative x)."""
    deg = deg % 360.0
    return 0.0 if deg >= 360.0 else deg


def bot_command(args) -> int:
    results: list = []
    stop = _stop_on_signals()
    threads = [threading.Thread(target=_bot, args=(args.server, k, args.profile, args.leg_s, args.duration, results,
                                                   stop), daemon=True) for k in range(args.count)]
    for t in threads:
        t.start()
    end = _until(args.duration)
    while any(t.is_alive() for t in threads) and time.monotonic() < end + 30.0:
        stop.wait(0.2)  # the main thread stays free for the signal handlers
        if stop.is_set():
            for t in threads:
                t.join(30.0)
    ok = 0
    for k, agent, what in sorted(results, key=lambda r: r[0]):
        print(f"bot-{k}: agent {agent}: {what}", flush=True)
        ok += agent is not None
    return 0 if ok == args.count else 1
