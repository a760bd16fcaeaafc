"""``sortie client`` (a headless observer printing the live picture; with ``--follow`` or
``--agent-type``, the render client of client/render_cli.py, as ``sortie view``, whose options
--headless, --frames, --fps, --out, --chase are refused without either) and
``sortie bot`` (many autopilot agents in one process, as ordinary clients).

    sortie client --server HOST:PORT [--observe LAT LON RADIUS_M] [--duration S] [--every S]
    sortie bot --server HOST:PORT [--count N] [--profile patrol|racetrack] [--leg-s S] [--duration S]

A bot joins as ROLE_BOT (taking a free controllable agent), watches, and flies
or drives its profile with autopilot commands: "patrol" turns right 90 degrees
after every leg (a closed box), "racetrack" right 180 degrees (two parallel legs
joined by half turns); a leg's --leg-s world seconds count from the moment its
agent is on the leg's heading (an f16 takes ~40 s to turn 90 degrees), so every
side is flown alike. Aircraft fly their legs 300 m above and below the altitude
they had at the first one, in turn, and never lower than 300 m above the highest
terrain their next leg and turn can reach (the terrain the server names in its
WorldInfo, DEM files found here or a terrain service). One below that floor at
the start (parked on a runway) first climbs out on its heading at a speed it
flies (1.3 times its slowest in fdm.catalog's trim survey) and begins its
profile once above it. A bot ends when its agent is lost, on --duration or a
signal (leaving the server), or when the server ends the exercise, which it
reports as ``sortie client`` does.
"""

from __future__ import annotations

import argparse
import functools
import logging
import math
import re
import sys
import signal
import threading
import time

import numpy as np

from sortie.errors import InvalidArgument, SortieError

log = logging.getLogger(__name__)

PROFILES = ("patrol", "racetrack")
MAX_BOTS = 256  # a server's sessions (server/sim_service.py MAX_SESSIONS)
MAX_DURATION_S = 7 * 86_400.0  # a scenario's longest exercise (server/scenario.py DURATION_MAX_S)
LEG_S = (1.0, 3_600.0)  # --leg-s, world seconds
EVERY_S = (0.05, 3_600.0)  # --every, wall seconds
MIN_LEG_WALL_S = 0.2  # a bot looks at its agent (and commands) at most 5 times a wall second, however fast the clock
# A bot's profile. The autopilot turns the shorter way (fdm/autopilot.py; a ground vehicle's
# heading hold, server/world.py), so a turn is commanded in steps of at most TURN_STEP_DEG, the
# next one once the agent is within TURN_STEP_LEAD_DEG of the last (before it rolls out): every
# turn goes right, and a racetrack's half turns do not alternate sides (which would walk it
# sideways by a turn diameter a leg).
TURN_STEP_DEG = 90.0
TURN_STEP_LEAD_DEG = 45.0
ON_HEADING_DEG = 5.0  # a leg's clock starts once the agent's heading is within this of the leg's
# A turn that has not ended after turn / MIN_TURN_RATE_DPS world seconds (a vehicle that cannot
# turn: stopped at a shore) starts its leg anyway. The catalog's slowest turns are a transport's
# at its 25 deg bank limit (fdm/autopilot.py GAINS): at 250 m/s, g tan(bank) / v = 1.05 deg/s
# (a level coordinated turn: Anderson, Introduction to Flight, 7th ed., sec. 6.17); this gives
# them twice that time.
MIN_TURN_RATE_DPS = 0.5
ALT_STEP_M = 300.0  # an aircraft's legs, above and below the altitude of its first leg
# No leg lower than this above the highest terrain its leg and turn can reach (the IFR minimum:
# 300 m, 1000 ft, above the highest obstacle within 8 km of the aircraft; ICAO Annex 2, 5.1.2,
# and SERA.5015(b); here within the bot's reach, :func:`bot_reach_m`).
FLOOR_AGL_M = 300.0
# The speed an aircraft climbs out at: this times the slowest it trims at in level flight in the
# catalog's survey (fdm.catalog.TRIM_SPEEDS_SURVEYED, about its stall speed), the margin over the
# stall of a normal approach (1.3 V_S0: FAA Airplane Flying Handbook, FAA-H-8083-3C, ch. 9).
CLIMB_SPEED_OVER_SLOWEST = 1.3
CLIMB_RESEND_M = 30.0  # a climb-out's altitude is sent again once the floor has raised it this much
STANDING_MPS = 2.0  # slower than this an aircraft stands on the ground (server.aircraft_host.PARKED_MPS)
# A bot's reach: a leg and a turn of its profile at the agent's speed, the turn at the bank limit
# of the slowest-turning classes (fdm/autopilot.py GAINS: light and transport, 25 degrees; a level
# coordinated turn's radius v^2 / (g tan(bank)): Anderson, Introduction to Flight, 7th ed., 6.17).
REACH_BANK_DEG = 25.0
GROUND_GRID = 33  # the highest terrain within a reach: the most of a GROUND_GRID^2 grid over it
EARTH_RADIUS_M = 6_371_008.8  # mean radius (IUGG; Moritz, Geodetic Reference System 1980)
G_MPS2 = 9.80665  # standard gravity (CGPM 1901)
GROUND_SPEED_MPS = 8.0  # a ground bot's speed
STREAM_END_WAIT_S = 5.0  # a bot whose controls the server ended waits this long for its picture to say why
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


def _server_address(text: str) -> str:
    """An argparse type: the simulation server's HOST:PORT, its port in 1..65535
    (server.health_cli.check_address: gRPC keeps a port's low 16 bits, so a mistyped 99999
    joined whatever server listens on 34463)."""
    from server.health_cli import check_address

    try:
        check_address(text)
    except InvalidArgument as exc:
        raise argparse.ArgumentTypeError(f"{exc.message} (got {text!r})") from None
    return text


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
    c.add_argument("--server", required=True, type=_server_address, metavar="HOST:PORT",
                   help="the simulation server (sortie server or sortie replay), port 1-65535")
    c.add_argument("--observe", nargs=3, type=float, metavar=("LAT", "LON", "RADIUS_M"),
                   help="centre and radius of the area of interest (default: the first target area, 100 km or "
                        "the server's observer limit when smaller)")
    c.add_argument("--duration", type=_duration_s, default=10.0, metavar="S",
                   help=f"wall seconds, at most {MAX_DURATION_S:g}; 0 runs until SIGTERM/SIGINT "
                        "(default %(default)s)")
    c.add_argument("--every", type=_seconds_within(*EVERY_S), default=2.0, metavar="S",
                   help=f"print period, wall seconds in [{EVERY_S[0]:g}, {EVERY_S[1]:g}] (default %(default)s)")
    c.add_argument("--name", default="observer",
                   help="the session's name, as the server's join and leave events show it (default %(default)s)")
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
    b.add_argument("--server", required=True, type=_server_address, metavar="HOST:PORT",
                   help="the simulation server, port 1-65535 (waited for 10 s while it starts)")
    b.add_argument("--count", type=_bot_count, default=1, metavar="N",
                   help=f"bots, [1, {MAX_BOTS}] (a server's session limit; default %(default)s)")
    b.add_argument("--profile", choices=PROFILES, default="patrol",
                   help="patrol: a closed box of right turns; racetrack: two parallel legs joined by right half "
                        "turns (default %(default)s)")
    b.add_argument("--leg-s", type=_seconds_within(*LEG_S), default=20.0, metavar="S",
                   help=f"world seconds per leg, [{LEG_S[0]:g}, {LEG_S[1]:g}], counted once the agent has turned "
                        f"onto the leg's heading; a leg lasts at least {MIN_LEG_WALL_S:g} wall seconds whatever "
                        "the clock's speed (default %(default)s)")
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
    centre_lat_deg, centre_lon_deg; with none, the terrain's centre), else (0, 0); 100 km, or the server's observer limit
    (observer_radius_max_m) when that is smaller."""
    radius = DEFAULT_OBSERVE_RADIUS_M
    if w.observer_radius_max_m > 0:  # 0: a server that does not say
        radius = min(radius, w.observer_radius_max_m)
    if w.target_areas:
        a = w.target_areas[0]
        return float(np.mean(a.lat_deg)), _mean_lon_deg(a.lon_deg), radius
    # With no entity, a server gives the terrain's centre (entity_count 0), an older one nothing.
    if w.entity_count > 0 or (w.centre_lat_deg, w.centre_lon_deg) != (0.0, 0.0):
        return float(w.centre_lat_deg), float(w.centre_lon_deg), radius
    return 0.0, 0.0, radius


def stream_end(sim, picture) -> int:
    """Leave the server if it is still there; the exit code: 0 for a stop asked of this
    client or an exercise the server ended, 1 for a server gone (the stream broke), a
    stream its own session ended (ABORTED: superseded, left) or this client's own failure
    (a listener's exception), each with a line that says so (:func:`why_ended`). A picture
    is no longer extrapolated past the stream's end (client/sim_client.py)."""
    if picture.alive:  # stopped here (duration, signal)
        try:
            sim.leave()
        except SortieError:
            pass
        return 0
    ok, why = why_ended(picture)
    print(why, file=sys.stdout if ok else sys.stderr, flush=True)
    return 0 if ok else 1


def why_ended(picture) -> tuple[bool, str]:
    """Why an ended picture's stream ended: (whether that is the exercise's own end, a line
    saying so)."""
    from client.sim_client import PictureFailed, StreamAborted

    at = f"at world time {picture.time_s:.1f} s"
    if picture.error is None:
        return True, f"the server ended the exercise {at}"
    if isinstance(picture.error, PictureFailed):
        return False, f"this client failed {at}: {type(picture.error.cause).__name__}: {picture.error.cause}"
    if isinstance(picture.error, StreamAborted):  # its own session ended it (a new Watch, a leave)
        return False, f"this client's stream was ended {at}: {picture.error}"
    return False, f"the server went away {at}: {picture.error}"


class BotFailure(str):
    """A bot's result line that tells of a failure (``sortie bot`` then exits 1)."""


def _bot(address: str, k: int, profile: str, leg_s: float, duration_s: float, results: list,
         stop: threading.Event) -> None:
    """One bot's thread: its result (k, agent id or None, line) in ``results`` whatever
    happens (a server that goes away mid-run is a line, not a traceback); a failure's line
    is a :class:`BotFailure`."""
    try:
        _fly_bot(address, k, profile, leg_s, duration_s, results, stop)
    except Exception as exc:  # noqa: BLE001 - reported per bot; the other bots go on
        results.append((k, None, BotFailure(f"stopped: {exc}")))


def _fly_bot(address: str, k: int, profile: str, leg_s: float, duration_s: float, results: list,
             stop: threading.Event) -> None:
    from client.sim_client import SimClient

    with SimClient(address) as sim:
        sim.wait_ready()  # a server still starting, as sortie client waits for it
        try:
            agent = sim.join(f"bot-{k}", "bot")
        except Exception as exc:  # noqa: BLE001 - reported per bot
            results.append((k, None, BotFailure(f"could not join: {exc}")))
            return
        try:
            what = _fly_profile(sim, agent, profile, leg_s, duration_s, stop)
        except Exception as exc:  # noqa: BLE001 - reported per bot, its agent named
            what = BotFailure(f"stopped: {exc}")
        results.append((k, agent, what))


def _fly_profile(sim, agent: int, profile: str, leg_s: float, duration_s: float, stop: threading.Event) -> str:
    """Fly or drive ``agent`` (the session's) on ``profile`` until the run ends; the bot's
    result line."""
    from client.sim_client import StreamEnded

    picture = sim.watch()
    picture.wait_for(lambda p: agent in p.infos, 10.0)
    info = picture.infos.get(agent)
    aircraft = info is not None and info.kind == 1
    pilot = BotPilot(profile, leg_s, aircraft=aircraft,
                     climb_speed_mps=climb_speed_mps(info.type) if aircraft else None, name=info.name if info else "")
    controls = sim.controls()
    info_w = getattr(sim, "world_info", None)
    undulation = float(info_w.geoid_undulation_m) if info_w is not None else 0.0
    heights = bot_terrain(info_w.terrain) if aircraft and info_w is not None else None
    sent, sent_s = None, -math.inf  # the last command, and its world time
    seen, speed = None, None  # (world time, ECEF position) at the last look; the speed since (None: unknown)
    end = _until(duration_s)
    while time.monotonic() < end and not stop.is_set() and picture.alive:
        if agent in picture.infos:
            now_s = picture.now_s()
            _, pos, quat = picture.state(ids=[agent])
            if seen is None or now_s > seen[0]:  # (a paused clock: the speed it had)
                if seen is not None:
                    speed = float(np.linalg.norm(pos[0] - seen[1])) / (now_s - seen[0])
                seen = now_s, np.array(pos[0], np.float64)
            lat, lon, h = _geodetic(pos)
            h_msl = float(h[0]) - undulation  # the state's height is above the ellipsoid
            ground = None if heights is None else functools.partial(highest_ground_msl_m, heights, lat[0], lon[0])
            targets = pilot.command(now_s, _heading_deg(pos[0], quat[0]), h_msl, speed, ground)
            if targets is None and sent is not None and now_s - sent_s >= leg_s:
                # Sent again after a leg's time without a command (a long turn): a wreck refuses it
                # (server.world.World.command), so a lost agent is seen within a leg, as before.
                targets = sent
            try:
                if targets is not None:
                    controls.autopilot(**targets)
                    sent, sent_s = targets, now_s
            except InvalidArgument as exc:
                lost = _agent_lost(exc)
                if lost is None:
                    raise
                controls.cancel()
                sim.leave()  # its agent crashed or was destroyed: its flight is over, not failed
                return f"{pilot.legs} legs, then its agent {lost}; {picture.updates} updates"
            except StreamEnded:  # the server ended the exercise: the picture's end says so
                picture.wait_for(lambda p: not p.alive, STREAM_END_WAIT_S)
                break
        stop.wait(min(MIN_LEG_WALL_S, max(end - time.monotonic(), 0.0)))
    if not picture.alive:  # the server ended the exercise, or went away
        ok, why = why_ended(picture)
        if ok:
            accepted = _accepted(controls)
        else:  # a server gone, a stream its own session ended, a failure: no count to wait for
            accepted = None
            controls.cancel()
        counts = f"{accepted} commands accepted, " if accepted is not None else ""
        line = f"{pilot.legs} legs, then {why}; {counts}{picture.updates} updates"
        return line if ok else BotFailure(f"stopped: {line}")
    accepted = controls.close()
    sim.leave()
    return f"{pilot.legs} legs, {accepted} commands accepted, {picture.updates} updates"


def _accepted(controls) -> int | None:
    """The commands the server accepted on a stream it has ended; None when it cannot say."""
    try:
        return controls.close()
    except SortieError:
        return None


def climb_speed_mps(aircraft_type: str) -> float | None:
    """The speed (m/s) a bot climbs an aircraft of ``aircraft_type`` (a JSBSim catalog name) out
    at: CLIMB_SPEED_OVER_SLOWEST times the slowest it trims at in the catalog's survey, within the
    fastest; None for a type the survey has no speeds for."""
    from fdm.catalog import TRIM_SPEEDS_SURVEYED

    speeds = TRIM_SPEEDS_SURVEYED.get(aircraft_type)
    if not speeds:
        return None
    return min(CLIMB_SPEED_OVER_SLOWEST * min(speeds), float(max(speeds)))


def bot_reach_m(speed_mps: float, leg_s: float) -> float:
    """How far (m) an aircraft at ``speed_mps`` goes from where a leg begins, on the leg and its
    turn: the leg's length and a turn's diameter at REACH_BANK_DEG."""
    radius = speed_mps * speed_mps / (G_MPS2 * math.tan(math.radians(REACH_BANK_DEG)))
    return speed_mps * leg_s + 2.0 * radius


def highest_ground_msl_m(heights, lat_deg: float, lon_deg: float, reach_m: float) -> float | None:
    """The highest terrain (m MSL) within ``reach_m`` of (lat, lon) degrees: the most of a
    GROUND_GRID x GROUND_GRID grid over the disc, a post's spacing beyond it (a peak between posts
    is missed by at most the slope times 0.71 spacings, the way to the nearest post: FLOOR_AGL_M is
    the margin); ``heights`` a
    function of (lat (n,), lon (n,)) degrees giving (n,) m MSL, NaN where it has no terrain. None
    where it has none at all."""
    step = 2.0 * reach_m / (GROUND_GRID - 1)
    offsets = np.linspace(-reach_m - step, reach_m + step, GROUND_GRID + 2)
    north, east = np.meshgrid(offsets, offsets, indexing="ij")
    inside = np.hypot(north, east) <= reach_m + step
    lat = lat_deg + np.degrees(north[inside] / EARTH_RADIUS_M)
    lon = lon_deg + np.degrees(east[inside] / (EARTH_RADIUS_M * max(math.cos(math.radians(lat_deg)), 1e-6)))
    h = np.asarray(heights(np.clip(lat, -90.0, 90.0), (lon + 180.0) % 360.0 - 180.0), np.float64)
    return float(np.nanmax(h)) if np.isfinite(h).any() else None


_BOT_TERRAINS: dict = {}  # WorldInfo.terrain -> its heights function (or None), shared by a process's bots
_BOT_TERRAINS_LOCK = threading.Lock()


def bot_terrain(world_terrain: str):
    """A function of (lat (n,), lon (n,)) degrees giving the terrain's heights (n,) m MSL (NaN
    where it has none) of the terrain a server names (WorldInfo.terrain: "dem:<files>" or
    "service:<address>"), opened once per process and shared by its bots; None where it names
    none, its DEM files are not here or its service does not answer (the bot then knows the
    ground only under an aircraft standing on it). The server's target-area insets are left out:
    they refine the DEM by metres, well inside FLOOR_AGL_M."""
    with _BOT_TERRAINS_LOCK:
        if world_terrain not in _BOT_TERRAINS:
            _BOT_TERRAINS[world_terrain] = _open_bot_terrain(world_terrain)
        return _BOT_TERRAINS[world_terrain]


def _open_bot_terrain(world_terrain: str):
    from pathlib import Path

    from server.sim_server import open_terrain_source

    kind, _, rest = world_terrain.partition(":")
    spec = None
    if kind == "service" and rest:
        spec = {"service": rest}
    elif kind == "dem" and rest:
        dem = [f for f in rest.split(",") if f]
        if dem and all(Path(f).exists() for f in dem):
            spec = {"dem": dem}
    if spec is None:
        if world_terrain:
            log.warning("bots cannot open the server's terrain %r here: they fly without a terrain floor",
                        world_terrain)
        return None
    try:
        terrain = open_terrain_source(**spec)
    except (SortieError, OSError) as exc:
        log.warning("bots cannot open the server's terrain %r (%s): they fly without a terrain floor",
                    world_terrain, exc)
        return None
    lock = threading.Lock()  # one query at a time from the process's bot threads

    def heights(lat, lon):
        with lock:
            return terrain.heights(lat, lon).height_msl_m

    return heights


class BotPilot:
    """What a bot commands, from what its agent does (no I/O: :meth:`command` is fed the
    agent's world time, heading, altitude and speed, and a function that finds the terrain).
    Each leg's heading is the last one's plus the profile's turn (the sides of a closed
    figure); a leg's ``leg_s`` world seconds run from the moment the agent is within
    ON_HEADING_DEG of it (or its turn timed out). Aircraft alternate between ALT_STEP_M above
    and below their altitude at the first leg, changing it once on the leg's heading: every turn
    is level, at one speed, so all have one radius (one turn climbing and the next descending
    walked a racetrack ~0.8 km sideways a lap).

    The floor: no aircraft leg lower than FLOOR_AGL_M above the highest terrain within
    :func:`bot_reach_m` of where it begins, and the base altitude at least ALT_STEP_M above that
    (both legs clear it over level terrain). An aircraft below the floor at the start (parked on a
    runway: it took the runway's height for its base, and turned on its take-off roll into a
    crash) first climbs out: on the heading it had, to its first leg's altitude, at
    ``climb_speed_mps`` when slower than that; its profile begins once it is above the floor.
    Without terrain the floor is known only for an aircraft standing on the ground (its own
    height) of a type with a climb speed; an airborne one, or one of a type without, flies its
    legs about its first altitude as it is. One standing below a known floor whose type has no
    climb speed is not taken off (InvalidArgument: the bot stops, its agent left parked)."""

    def __init__(self, profile: str, leg_s: float, aircraft: bool = False, climb_speed_mps: float | None = None,
                 name: str = ""):
        if profile not in PROFILES:
            raise InvalidArgument("profile", f"must be one of {', '.join(PROFILES)}", value=profile)
        self.turn_deg = 90.0 if profile == "patrol" else 180.0
        self.leg_s = leg_s
        self.aircraft = aircraft
        self.climb_speed_mps = climb_speed_mps
        self.name = name  # the agent's, for an error
        self.legs = 0  # legs begun
        self.goal_deg: float | None = None  # the heading of the leg being flown (or turned onto)
        self.short_deg = 0.0  # how far short of it the heading commanded is (the turn's steps)
        self.turn_start_s = 0.0  # world time the turn onto it began
        self.leg_start_s: float | None = None  # world time its clock started (None: still turning)
        self.base_alt_msl_m: float | None = None
        self.floor_msl_m: float | None = None  # the lowest altitude a leg may have (None: unknown)
        self.climb_deg: float | None = None  # a climb-out's heading (None: none begun)
        self.climb_sent: dict | None = None  # the climb-out's last command

    def command(self, now_s: float, heading_deg: float, alt_msl_m: float, speed_mps: float | None = None,
                ground=None) -> dict | None:
        """The autopilot targets to send now (None: nothing new). ``now_s``: world seconds;
        ``heading_deg``: the agent's true heading; ``alt_msl_m``: its altitude, m MSL;
        ``speed_mps``: its speed (None: not known yet, and an aircraft's bot waits for it);
        ``ground``: a function of a distance (m) giving the highest terrain (m MSL) within it of
        the agent, or None where the bot has no terrain."""
        targets = None
        if self.goal_deg is None:  # the first leg: on the heading the agent has
            if self.aircraft and speed_mps is None:
                return None
            if self.aircraft and not self._clear_to_begin(heading_deg, alt_msl_m, speed_mps, ground):
                return self._climb_out(speed_mps)
            targets = self._begin(now_s, heading_deg if self.climb_deg is None else self.climb_deg, 0.0)
        elif self.leg_start_s is not None and now_s - self.leg_start_s >= self.leg_s:
            targets = self._begin(now_s, self.goal_deg, self.turn_deg)
        if self.leg_start_s is not None:
            return targets
        if (abs(_wrap180(self.goal_deg - heading_deg)) <= ON_HEADING_DEG
                or now_s - self.turn_start_s >= self.turn_deg / MIN_TURN_RATE_DPS):
            self.leg_start_s = now_s  # on the leg: its clock runs, an aircraft takes its altitude
            if self.aircraft:
                self._raise_floor(alt_msl_m, speed_mps or 0.0, ground)
                return self._leg_altitude()
            return targets
        if self.short_deg > 0.0 and _wrap180(self._step_deg() - heading_deg) <= TURN_STEP_LEAD_DEG:
            self.short_deg = max(self.short_deg - TURN_STEP_DEG, 0.0)  # the turn's next step
            return self._turn()
        return targets

    def _raise_floor(self, alt_msl_m: float, speed_mps: float, ground) -> None:
        """The floor from the terrain within reach now (it only rises: a climb-out's, or a leg's
        that starts lower, stays); without terrain, a standing aircraft's own height (one a bot can
        take off: of a type with a climb speed)."""
        highest = None if ground is None else ground(bot_reach_m(max(speed_mps, self.climb_speed_mps or 0.0),
                                                                  self.leg_s))
        if (highest is None and speed_mps < STANDING_MPS and self.base_alt_msl_m is None
                and self.climb_speed_mps is not None):
            highest = alt_msl_m  # on the ground where it stands (and above it, the CG's height)
        if highest is not None:
            floor = highest + FLOOR_AGL_M
            self.floor_msl_m = floor if self.floor_msl_m is None else max(self.floor_msl_m, floor)

    def _clear_to_begin(self, heading_deg: float, alt_msl_m: float, speed_mps: float, ground) -> bool:
        """Whether an aircraft begins its profile now: above its floor (or with none known)."""
        self._raise_floor(alt_msl_m, speed_mps, ground)
        if self.base_alt_msl_m is None:
            self.base_alt_msl_m = alt_msl_m
        if self.floor_msl_m is None:
            return True
        self.base_alt_msl_m = max(self.base_alt_msl_m, self.floor_msl_m + ALT_STEP_M)
        if alt_msl_m >= self.floor_msl_m:
            return True
        if self.climb_deg is None:  # the climb-out begins, on the heading the agent has (a runway's)
            if self.climb_speed_mps is None and speed_mps < STANDING_MPS:
                raise InvalidArgument("agent", f"{self.name or 'the agent'} stands on the ground and its type has no "
                                      "speed it flies at in fdm.catalog's trim survey: a bot cannot take it off")
            self.climb_deg = heading_deg
        return False

    def _climb_out(self, speed_mps: float) -> dict | None:
        """The climb-out's command: the first, then again when the floor has raised its altitude
        by CLIMB_RESEND_M (the terrain ahead rises into reach as it climbs: it stays at least
        ALT_STEP_M - CLIMB_RESEND_M above the floor in between)."""
        targets = {"heading_deg": self.climb_deg, "alt_msl_m": self.base_alt_msl_m + ALT_STEP_M}
        if self.climb_sent is None:
            if self.climb_speed_mps is not None and speed_mps < self.climb_speed_mps:
                targets["speed_mps"] = self.climb_speed_mps
        elif targets["alt_msl_m"] < self.climb_sent["alt_msl_m"] + CLIMB_RESEND_M:
            return None
        self.climb_sent = targets
        return targets

    def _begin(self, now_s: float, from_deg: float, turn_deg: float) -> dict:
        self.legs += 1
        self.goal_deg = _wrap360(from_deg + turn_deg)
        self.short_deg = turn_deg - min(turn_deg, TURN_STEP_DEG)
        self.turn_start_s, self.leg_start_s = now_s, None
        return self._turn()

    def _step_deg(self) -> float:
        """The heading commanded: the goal, or a step of the turn short of it."""
        return _wrap360(self.goal_deg - self.short_deg)

    def _turn(self) -> dict:
        if self.aircraft:
            return {"heading_deg": self._step_deg()}
        return {"heading_deg": self._step_deg(), "speed_mps": GROUND_SPEED_MPS}

    def _leg_altitude(self) -> dict:
        up = self.legs % 2 == 1
        alt = self.base_alt_msl_m + (ALT_STEP_M if up else -ALT_STEP_M)
        if self.floor_msl_m is not None:
            alt = max(alt, self.floor_msl_m)
        return {"heading_deg": self.goal_deg, "alt_msl_m": alt}


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


def _wrap180(deg: float) -> float:
    """deg in [-180, 180): a heading difference the short way round."""
    return (deg + 180.0) % 360.0 - 180.0


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
        ok += not isinstance(what, BotFailure)
    return 0 if ok == args.count else 1
