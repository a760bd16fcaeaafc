"""``sortie server``: run the simulation server of a scenario.

    sortie server --scenario FILE [--dem FILE... | --terrain HOST:PORT] --port N [--host H]
                  [--clock realtime|fast|paused] [--time-scale X] [--duration S]
                  [--aircraft-workers N|auto] [--aircraft-worker-nice N]
                  [--record FILE | --record-dir DIR | --no-record] [--record-chunk-s S]

Every sortie is recorded by default, into ``recordings/<exercise>-<UTC time>.sortie``
(server/recorder.py; read it with ``sortie recording``, ``sortie replay``,
``sortie resim``, ``sortie export acmi``); a take-over (``sortie resim --take-over``)
too, with the same options (:func:`add_recording_options`).

Runs until SIGTERM/SIGINT (graceful: NOT_SERVING, streams closed, in-flight
calls get --grace-s) or until the scenario's (or --duration's) end. SIGUSR1 runs
the world clock (a "paused" exercise resumes in real time), SIGUSR2 pauses it, from the
first step of the start (:class:`ClockSignals`).
"""

from __future__ import annotations

import contextlib
import logging
import math
import os
import signal
import sys
import time
import unicodedata
from pathlib import Path

from server.grpc_common import DEFAULT_GRACE_S, HOST_HELP, bare_host, listen_address, stop_signals, wait_for_signal
from server.scenario import DURATION_MAX_S, TIME_SCALE_MAX, ScenarioError, service_address
from server.sim_server import CLOCKS
from sortie.config import MAX_GRACE_S, grace_seconds
from sortie.errors import InvalidArgument
from sortie.logs import line

logger = logging.getLogger(__name__)

def add_parser(sub) -> None:
    p = sub.add_parser("server", help="run the simulation server of a scenario",
                       description="Run sortie.v1.SimulationService (with health and reflection) for a scenario "
                                   "until SIGTERM/SIGINT or the exercise's end; prints the bound address.")
    p.add_argument("--scenario", required=True, metavar="FILE",
                   help="scenario file, .toml or the same tables in .yaml/.yml (see server/scenario.py)")
    terrain = p.add_mutually_exclusive_group()
    terrain.add_argument("--dem", nargs="+", metavar="FILE", help="DEM files instead of the scenario's terrain")
    terrain.add_argument("--terrain", metavar="HOST:PORT[,HOST:PORT...]",
                         help="a terrain service (or replicas of one, round robin) instead of the scenario's terrain")
    p.add_argument("--port", type=int, required=True, help="TCP port; 0 picks a free one")
    p.add_argument("--host", default="127.0.0.1", help=f"{HOST_HELP} (default %(default)s)")
    p.add_argument("--clock", choices=CLOCKS, help="override the scenario's clock")
    p.add_argument("--time-scale", type=float,
                   help=f"world seconds per wall second of the fast clock, (1, {TIME_SCALE_MAX:g}] "
                        "(realtime and paused: 1 only)")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S world seconds")
    p.add_argument("--aircraft-workers", default="auto", metavar="N|auto",
                   help="processes the aircraft's JSBSim runs in: 0 = in the server's process; auto = "
                        "one per CPU core (%(default)s); see server/aircraft_host.py")
    p.add_argument("--aircraft-worker-nice", type=int, metavar="N",
                   help="how much lower the aircraft workers' CPU priority is than the server's, 0-19 "
                        "(default: server.aircraft_host.WORKER_NICE, 3); higher lowers stream latency "
                        "on a busy machine but lets other processes stall the physics")
    add_recording_options(p)
    p.add_argument("--grace-s", type=grace_seconds, default=DEFAULT_GRACE_S,
                   help=f"seconds in-flight calls get on shutdown, 0-{MAX_GRACE_S:g} (default %(default)s)")
    p.add_argument("--metrics-port", type=int, metavar="N",
                   help="serve Prometheus metrics on http://HOST:N/metrics (tick time, sessions, entities, "
                        "bytes sent; see docs/DEPLOYMENT.md); 0 picks a free port")
    p.set_defaults(func=server_command)


class ClockSignals:
    """SIGUSR1 runs the world clock (a "paused" exercise resumes in real time, others in their
    own clock) and SIGUSR2 pauses it: an operator's control of the clock (`kill -USR1 PID`), as
    the scenario's clock = "paused" promises. Taken from a service's first step, as its SIGTERM
    is (grpc_common.stop_signals): a signal that comes while the server starts (loading the
    terrain, starting and trimming the aircraft, re-simulating a take-over: seconds) is
    remembered and applied by :meth:`attach`, where its default action killed the process
    (exit 138/140, the aircraft workers orphaned) -- an acceptance probe. The last signal wins.

    The handlers run in the main thread between bytecodes, and may interrupt :meth:`attach`
    or each other: :meth:`_settle` applies the latest request until no newer one came while it
    did, so an older request never lands after a newer one."""

    def __init__(self):
        self.server = None
        self.wanted: str | None = None  # "run" or "pause": the latest signal's request (None: none yet)
        self._requests = 0  # signals taken so far

    def request(self, wanted: str) -> None:
        """A signal's handler: remember ``wanted`` ("run" / "pause"); apply it once attached."""
        self.wanted = wanted
        self._requests += 1
        self._settle()

    def attach(self, server) -> None:
        """Control ``server`` (a SimulationServer, before or after its start) from now on,
        applying the request that came while it was being built."""
        self.server = server
        self._settle()

    def clock(self, configured: str) -> str:
        """The clock a server configured with ``configured`` runs under the signals so far."""
        if self.wanted is None:
            return configured
        if self.wanted == "pause":
            return "paused"
        return "realtime" if configured == "paused" else configured

    def _settle(self) -> None:
        server = self.server
        if server is None or self.wanted is None:
            return
        while True:
            seen = self._requests
            server.set_clock(self.clock(server.config.clock))
            if self._requests == seen:
                return


@contextlib.contextmanager
def clock_signals():
    """:class:`ClockSignals` taking SIGUSR1 and SIGUSR2 while in the block (main thread only);
    the previous handlers are back after it."""
    from sortie.cli import take_early_clock_request

    control = ClockSignals()
    early = take_early_clock_request()  # one that came while the modules imported (sortie.cli)
    if early is not None:
        control.request(early)
    previous = {signal.SIGUSR1: signal.signal(signal.SIGUSR1, lambda signum, frame: control.request("run")),
                signal.SIGUSR2: signal.signal(signal.SIGUSR2, lambda signum, frame: control.request("pause"))}
    try:
        yield control
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def aircraft_workers(value: str) -> int:
    """--aircraft-workers: a count in [0, MAX_WORKERS], or "auto" (one per CPU core)."""
    from server.aircraft_host import MAX_WORKERS

    if value == "auto":
        return max(1, min(os.cpu_count() or 1, MAX_WORKERS))
    try:
        n = int(value)
    except ValueError:
        n = -1
    if not 0 <= n <= MAX_WORKERS:
        raise InvalidArgument("aircraft_workers", f"must be an integer in [0, {MAX_WORKERS}] or auto", value=value)
    return n


def add_recording_options(p, only: str = "") -> None:
    """The options saying where a sortie is recorded (every sortie is, by default): ``sortie
    server``'s, and ``sortie resim --take-over``'s (``only``: "with --take-over: ")."""
    rec = p.add_mutually_exclusive_group()
    rec.add_argument("--record", metavar="FILE", help=f"{only}record the sortie into FILE (a new file)")
    rec.add_argument("--record-dir", metavar="DIR", default="recordings",
                     help=f"{only}record into DIR/<exercise>-<UTC time>.sortie (default %(default)s)")
    rec.add_argument("--no-record", action="store_true", help=f"{only}do not record the sortie")
    p.add_argument("--record-chunk-s", type=float, default=1.0, metavar="S",
                   help=f"{only}world seconds per recording chunk, at most 3600: what a killed server "
                        "may lose (default %(default)s)")


MAX_SLUG_BYTES = 120  # of a recording's default file name (UTF-8): with its time, suffix and ".sortie", under 255
MAX_NAME_SUFFIX = 999  # "-2" .. "-999" after a default name already taken


def recording_slug(exercise_name: str) -> str:
    """The exercise's name as the start of a file name: accents dropped (NFKD, combining marks
    removed), letters and digits kept (any script's: str.isalnum), every other run a hyphen,
    lower case, at most MAX_SLUG_BYTES of UTF-8; "sortie" if nothing is left."""
    bare = "".join(c for c in unicodedata.normalize("NFKD", exercise_name) if not unicodedata.combining(c))
    words = "".join(c if c.isalnum() else " " for c in bare).lower().split()
    slug = unicodedata.normalize("NFC", "-".join(words))  # Hangul and the like recomposed
    slug = slug.encode("utf-8")[:MAX_SLUG_BYTES].decode("utf-8", "ignore")
    return slug.strip("-") or "sortie"


def recording_path(args, exercise_name: str) -> Path | None:
    """Where a sortie is recorded by the options of :func:`add_recording_options` (None:
    --no-record): --record's file, or a name chosen in --record-dir (:func:`new_recording`
    makes it unique)."""
    if args.no_record:
        return None
    if args.record:
        return Path(args.record)
    stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime())
    return Path(args.record_dir) / f"{recording_slug(exercise_name)}-{stamp}.sortie"


def recording_option(args) -> str:
    """The option that said where the sortie is recorded: "record" (a file of the user's, never
    renamed) or "record_dir" (a name the server chooses)."""
    return "record" if args.record else "record_dir"


def check_recording(args, exercise_name: str) -> Path | None:
    """Where the options of :func:`add_recording_options` record a sortie (None: --no-record),
    checked: --record-chunk-s, the folder (or what is there of it) a folder, and no file at a
    --record path already (recordings are never overwritten; a chosen name takes a suffix)."""
    path = recording_path(args, exercise_name)
    if path is None:
        return None
    from server.recorder import check_chunk_s

    check_chunk_s(args.record_chunk_s, "--record-chunk-s")
    option = recording_option(args)
    try:
        _check_folder(path.parent, option, args.record if args.record else args.record_dir)
        exists = bool(args.record) and path.exists()
    except OSError as exc:  # a name the file system cannot hold (ENAMETOOLONG), a folder it may not search
        raise InvalidArgument(option, f"cannot be written: {exc.strerror or exc}",
                              value=str(exc.filename or path)) from None
    if exists:
        raise InvalidArgument("record", "the file exists (recordings are never overwritten)", value=str(path))
    return path


def _check_folder(folder: Path, option: str, value) -> None:
    """InvalidArgument naming ``option`` unless the nearest existing folder of ``folder`` (itself
    or an ancestor: the others are made) is a folder."""
    for f in (folder, *folder.parents):
        if f.exists():
            if not f.is_dir():
                where = "" if f == folder else f" ({f} is not a folder)"
                raise InvalidArgument(option, f"is not a folder{where}" if option == "record_dir"
                                      else f"cannot be made: {f} is not a folder", value=str(value))
            return


def new_recording(path: Path, header, chunk_s: float, option: str = "record"):
    """A Recorder into ``path`` (checked by :func:`check_recording`), created exclusively. A
    name the server chose (``option`` "record_dir") that exists (another server of the same
    exercise started in the same second) takes the first free suffix -2, -3, ... (the
    Recorder's ``path`` is the one made); a --record file made since it was checked is an
    error as one there before. When it cannot be made, the file and the folders it made are
    removed before its error is raised; an OSError is an InvalidArgument naming ``option``."""
    from server.recorder import Recorder

    made = _missing_folders(path)
    candidates = [path] if option == "record" else [path] + [path.with_name(f"{path.stem}-{k}{path.suffix}")
                                                             for k in range(2, MAX_NAME_SUFFIX + 1)]
    candidate = None  # the file being made (removed if this fails), once the header is built
    try:
        h = header()
        for candidate in candidates:
            try:
                return Recorder(candidate, h, chunk_s)
            except FileExistsError:
                if option == "record" or not candidate.parent.is_dir():
                    candidate = None  # someone else's, made since it was checked: not removed
                    raise
        candidate = None
        raise InvalidArgument("record_dir", f"holds recordings of this name and every suffix up to "
                                            f"-{MAX_NAME_SUFFIX}", value=str(path))
    except BaseException as exc:
        remove_recording(candidate, made)
        if isinstance(exc, FileExistsError) and option == "record":
            raise InvalidArgument("record", "the file exists (recordings are never overwritten)",
                                  value=str(path)) from None
        if isinstance(exc, OSError):
            raise InvalidArgument(option, f"cannot be written: {exc.strerror or exc}",
                                  value=str(exc.filename or path)) from None
        raise


def _missing_folders(path: Path) -> list[Path]:
    """The folders above ``path`` that do not exist yet, deepest first."""
    out = []
    for folder in path.parents:
        if folder.exists():
            break
        out.append(folder)
    return out


def remove_recording(path: Path | None, folders=()) -> None:
    """Remove a recording this run made (and ``folders``, the folders made for it, where empty):
    a server that fails to start leaves nothing behind for `sortie replay` to pick. A file
    that is not there is no error, whatever the unlink says: a read-only file system (EROFS)
    or a name too long (ENAMETOOLONG) refuses to unlink the file it refused to make, and
    that error replaced the one saying why the recording could not be made."""
    if path is not None:
        try:
            path.unlink()
        except OSError as exc:
            if os.path.lexists(path):  # False for a name the file system cannot hold
                logger.warning("could not remove the recording %s: %s", path, exc.strerror or exc)
    for folder in folders:
        try:
            folder.rmdir()
        except OSError:
            break


def check_run_options(args) -> None:
    """--time-scale, --duration and --terrain, before anything is built (--grace-s is checked
    by argparse). --terrain takes the rule of a scenario's [terrain] service (a port beyond
    65535 reached another port's server: gRPC keeps its low 16 bits; a name with no port waited
    10 s to say there was no terrain service)."""
    terrain = getattr(args, "terrain", None)  # sortie resim --take-over has it too
    if terrain is not None:
        try:
            service_address(terrain, "--terrain")
        except ScenarioError as exc:
            raise InvalidArgument("--terrain", exc.message, value=terrain) from None
    if args.time_scale is not None and not (math.isfinite(args.time_scale)
                                            and 0.0 < args.time_scale <= TIME_SCALE_MAX):
        raise InvalidArgument("time_scale", f"must be within (0, {TIME_SCALE_MAX:g}]", value=args.time_scale)
    if args.duration is not None and not (math.isfinite(args.duration) and 0.0 < args.duration <= DURATION_MAX_S):
        raise InvalidArgument("duration", f"must be within (0, {DURATION_MAX_S:g}] s", value=args.duration)


def run_clock(clock: str, time_scale: float, clock_opt: str | None, time_scale_opt: float | None):
    """The (clock, time_scale) a server runs: the scenario's, overridden by --clock and
    --time-scale. A --clock other than the scenario's brings its own rate, as a scenario's
    clock does (fast x DEFAULT_FAST_TIME_SCALE, realtime and paused x1: the scenario's x10
    of a fast exercise run with --clock realtime ran ten times real time, labelled
    "realtime"), unless --time-scale gives one; realtime and paused (which resumes in real
    time) run only at x1 and fast only faster, within (1, TIME_SCALE_MAX], as in a scenario.
    InvalidArgument naming the option otherwise."""
    from server.scenario import DEFAULT_FAST_TIME_SCALE

    if clock_opt is not None and clock_opt != clock:
        clock, time_scale = clock_opt, DEFAULT_FAST_TIME_SCALE if clock_opt == "fast" else 1.0
    if time_scale_opt is not None:
        time_scale = time_scale_opt
    if clock != "fast" and time_scale != 1.0:
        raise InvalidArgument("time_scale", f'must be 1.0 with the {clock} clock (use --clock fast)',
                              value=time_scale)
    if clock == "fast" and not 1.0 < time_scale <= TIME_SCALE_MAX:  # the scenario's rule (server.scenario)
        raise InvalidArgument("time_scale", f"must be within (1, {TIME_SCALE_MAX:g}] with the fast clock "
                                            "(1.0: use --clock realtime)", value=time_scale)
    return clock, time_scale


class StoppedWhileStarting(Exception):
    """SIGTERM/SIGINT came while the server was starting: the start was abandoned (exit 0)."""


def server_command(args) -> int:
    """Start-up in an order that leaves nothing behind when it fails: every option checked, the
    scenario and its world built, the gRPC port and the metrics port bound, and only then the
    recording made; a failure on the way closes what was opened and removes that recording.

    SIGTERM/SIGINT are caught from the first step (grpc_common.stop_signals): one that comes
    while the server starts (loading the terrain, starting the aircraft workers and trimming
    the aircraft take seconds) abandons the start after the step under way, as a failure
    would but exiting 0 with a line, where it killed the process (-15) and left its workers
    to die on a broken pipe. SIGUSR1/SIGUSR2 are caught from the first step too, to the end
    of the shutdown (a recording's footer): one that comes while the server starts runs or
    pauses the clock it starts with (:class:`ClockSignals`)."""
    with clock_signals() as clock:
        with stop_signals() as stop:
            try:
                server, world, metrics, recorder, path = _start(args, stop, clock)
            except StoppedWhileStarting:
                line("sortie server: stopped while starting (nothing served or recorded)", logger=__name__)
                return 0
            line(f"sortie simulation server listening on {server.address} ({len(world.entities)} agents, "
                 f"clock {clock.clock(server.config.clock)})", logger=__name__)
            if metrics is not None:
                line(f"metrics on http://{metrics.address}/metrics", logger=__name__)
            if recorder is not None:
                line(f"recording to {path}", logger=__name__)
            wait_for_signal(server.finished, stop=stop)
        server.stop(args.grace_s)
        world.close()
        if metrics is not None:
            metrics.stop()
    stats = server.tick_stats()
    line(f"sortie simulation server stopped at world time {world.time_s:.1f} s "
         f"({stats['ticks']} ticks, p99 {stats['tick_p99_ms']:.1f} ms)", logger=__name__)
    if recorder is not None:
        state = f"failed: {recorder.error}" if recorder.error else f"{path.stat().st_size:,} bytes"  # the footer too
        line(f"recording {path}: {state}", logger=__name__)
    if server.error is not None:  # the world's clock died: not a clean end of the exercise
        line(f"sortie server: error: the world clock stopped: {type(server.error).__name__}: {server.error}",
             stream=sys.stderr, level=logging.ERROR, logger=__name__)
        return 1
    return 0


def _start(args, stop, signals: ClockSignals):
    """(server started, world, metrics server or None, recorder or None, its path) of
    :func:`server_command`; StoppedWhileStarting, everything opened closed, when ``stop`` is
    set after any step (before the recording is made, so a stopped start records nothing).
    ``signals`` control its clock from just before its start (its first tick)."""
    from server.recorder import recording_header
    from server.scenario import load_scenario
    from server.sim_server import (SimulationServer, aircraft_host, build_world, open_terrain, server_config,
                                   terrain_spec)

    def check_stop() -> None:
        if stop.is_set():
            raise StoppedWhileStarting

    workers = aircraft_workers(args.aircraft_workers)
    check_run_options(args)
    scenario = load_scenario(args.scenario)
    clock = run_clock(scenario.exercise.clock, scenario.exercise.time_scale, args.clock, args.time_scale)
    check_recording(args, scenario.exercise.name)  # before the world is built; again when it is, for the time
    check_stop()
    terrain, desc, factory = open_terrain(scenario, args.dem, args.terrain)
    host = world = server = metrics = recorder = path = None
    made: list[Path] = []
    metrics_started = False
    try:
        check_stop()
        host = aircraft_host(scenario, terrain, factory, workers, args.aircraft_worker_nice)
        check_stop()
        world = build_world(scenario, terrain, host)
        check_stop()
        path = check_recording(args, scenario.exercise.name)
        config = server_config(scenario, desc)
        config.clock, config.time_scale = clock
        if args.duration is not None:
            config.duration_s = args.duration
        server = SimulationServer(world, config, listen_address(args.host, args.port))  # SortieError: cannot listen
        if args.metrics_port is not None:
            from server.metrics import MetricsServer, simulation_metrics

            metrics = MetricsServer(lambda: simulation_metrics(server), bare_host(args.host), args.metrics_port)
        check_stop()
        if path is not None:
            made = _missing_folders(path)
            recorder = new_recording(path, lambda: recording_header(
                args.scenario, scenario, world, desc, terrain_spec(scenario, args.dem, args.terrain), terrain),
                args.record_chunk_s, recording_option(args))
            path = recorder.path  # a chosen name may have taken a suffix
            server.recorder = recorder  # closed by server.stop()
            world.attach_recorder(recorder)
        if metrics is not None:
            metrics.start()
            metrics_started = True
        signals.attach(server)
        server.start()
    except BaseException:
        _abandon_start(server, metrics, metrics_started, recorder, path, made, world, host)
        raise
    return server, world, metrics, recorder, path


def _abandon_start(server, metrics, metrics_started: bool, recorder, path, made, world, host=None) -> None:
    """Undo a start that failed or was stopped (see :func:`server_command`); errors on the way
    are logged, the start-up error is the one reported. ``host``: the aircraft host, closed
    with the world or alone when no world was built on it (its worker processes reaped)."""
    steps = []
    if metrics is not None:
        steps.append(metrics.stop if metrics_started else metrics.httpd.server_close)
    if server is not None:
        steps.append(lambda: server.grpc.stop(0).wait(10.0))
    if world is not None:
        steps.append(world.close)
    elif host is not None:
        steps.append(host.close)
    if recorder is not None:
        steps.append(recorder.close)
        steps.append(lambda: remove_recording(path, made))
    for step in steps:
        try:
            step()
        except Exception:  # noqa: BLE001 - the start-up error matters, not this one
            logger.warning("while abandoning the start", exc_info=True)
