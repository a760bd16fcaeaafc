"""The ``sortie`` command line: one entry point, a sub-command per service or tool.

Each sub-command lives beside the code it drives and registers itself through
an ``add_parser(subparsers)`` function; this module only assembles them,
applies the configuration file and environment (sortie/config.py) and
configures logging (sortie/logs.py; libraries never do).
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import signal
import sys
import threading

from sortie import __version__, config
from sortie.errors import SortieError
from sortie.logs import FORMATS, configure, line

# Modules that contribute sub-commands, in --help order.
COMMAND_MODULES = (
    "server.terrain_cli",
    "server.sim_cli",
    "server.recording_cli",
    "client.cli",
    "fdm.cli",
    "bench.cli",
    "server.export_cli",
    "server.dis_gateway",
    "server.tacview_live",
    "server.health_cli",
    "client.render_cli",
    "sortie.demo",
)


# Commands whose parser is built alone when they are the one run: health checks run
# every few seconds in every container, and loading every command's module (numba,
# the flight model) costs ~1 s of CPU; `sortie health` alone imports gRPC.
LIGHT_COMMANDS = {"health": "server.health_cli"}


def build_parser(modules=COMMAND_MODULES) -> argparse.ArgumentParser:
    import importlib

    parser = argparse.ArgumentParser(
        prog="sortie",
        description="Sortie battlefield simulation service: terrain, simulation, clients, tools.",
    )
    parser.add_argument("--version", action="version", version=f"sortie {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    parser.add_argument("--log-format", choices=FORMATS, default="text",
                        help="text for people, json lines for log shippers (default %(default)s)")
    parser.add_argument("--config", metavar="FILE",
                        help="TOML file of option defaults, a table per command (see sortie/config.py); "
                             "every option can also be set as SORTIE_<COMMAND>_<OPTION> in the environment")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in modules:
        importlib.import_module(name).add_parser(sub)
    config.bound_ports(parser)
    return parser


def _pre_parse(argv) -> argparse.Namespace:
    """The global options and the command's name, before any command module is loaded."""
    pre = argparse.ArgumentParser(add_help=False)
    pre.add_argument("--config")
    pre.add_argument("-v", "--verbose", action="count")
    pre.add_argument("--log-format")
    pre.add_argument("command", nargs="?")
    return pre.parse_known_args(argv)[0]


# A value of comma-separated numbers whose first is negative ("-33.9,151.2,2000,0,-10").
_NEGATIVE_LIST = re.compile(r"^-(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?(,[-+]?[\d.eE+-]*)+$")


def bind_negative_values(argv: list[str]) -> list[str]:
    """``--camera -33.9,151.2,...`` -> ``--camera=-33.9,151.2,...``.

    argparse takes a word starting with '-' that is not a plain number for an option, so a
    pose-like value (comma-separated numbers, here a southern latitude or a western longitude
    first) would leave its option "expected one argument". Bound with '=', it is the
    option's value. Only such words after a long option are rewritten, before any ``--``: a
    command line that parsed before parses the same."""
    out: list[str] = []
    for i, word in enumerate(argv):
        prev = out[-1] if out else ""
        if "--" in argv[:i]:
            out.extend(argv[i:])
            break
        if prev.startswith("--") and "=" not in prev and _NEGATIVE_LIST.match(word):
            out[-1] = f"{prev}={word}"
        else:
            out.append(word)
    return out


# Commands whose every failure exits 1, not 2: `sortie health` is a container health check, and
# Docker reserves exit status 2 of a health check (docs/DEPLOYMENT.md).
FAILURE_STATUS = {"health": 1}


def _log_format(pre: argparse.Namespace, environ) -> str:
    """The log format asked for before the command's options are parsed (for an error in them):
    the command line's, the environment's, the config file's top level, or text."""
    if pre.log_format:
        return pre.log_format
    if environ.get(config.ENV_PREFIX + "LOG_FORMAT"):
        return environ[config.ENV_PREFIX + "LOG_FORMAT"]
    path = pre.config or environ.get(config.ENV_PREFIX + "CONFIG")
    if path:
        try:
            table = config.read_config_file(path)
        except SortieError:  # reported as what it is by config.apply
            return "text"
        value = table.get("log-format", table.get("log_format"))
        return value if isinstance(value, str) else "text"
    return "text"


def _error(text: str, json_logs: bool) -> None:
    """The one line saying why a command failed, on stderr (a JSON record in json logging)."""
    line(text, stream=sys.stderr, level=logging.ERROR, fmt="json" if json_logs else "text")


def _report_usage_errors(parser: argparse.ArgumentParser, status: int, json_logs: bool) -> None:
    """argparse's errors (an unknown option, a missing one) exit ``status``, as one JSON record in
    json logging (usage and error line as argparse prints them otherwise)."""
    def handler(p):
        def error(message):
            if not json_logs:
                p.print_usage(sys.stderr)
            _error(f"{p.prog}: error: {message}", json_logs)
            sys.exit(status)
        return error

    for p in [parser, *(sub for _, sub in config.command_parsers(parser))]:
        p.error = handler(p)


def _source_of(parser, argv: list[str], exc: SortieError) -> str | None:
    """The environment variable or config key that set the option an error is about; None when
    the error is about something else (a key of a scenario file: its ``file`` is set)."""
    field = getattr(exc, "field", None)
    if not isinstance(field, str) or getattr(exc, "file", None):
        return None
    return config.source_of(parser, argv, field, getattr(exc, "value", None))


# Commands that run until stopped and exit 0 on SIGTERM (README): one stopped before it
# has taken its own signals (while the modules import, the first second or so) exits 0 too.
# Any other command stopped by SIGTERM exits 143 (128 + SIGTERM, the shell's convention).
STOPPED_CLEANLY = frozenset({"server", "resim", "replay", "client", "bot", "dis", "tacview", "view"})
STOPPED_SERVE = "terrain"  # its "serve" sub-command
TERMINATED_STATUS = 128 + signal.SIGTERM


class Terminated(BaseException):
    """SIGTERM came before the command took its own signals (or a command that takes none):
    raised in the main thread by :func:`main`'s handler, so the process unwinds (files closed,
    nothing half-made left) instead of being killed where it stood."""


def _terminated(signum, frame):
    raise Terminated()


# The commands whose world clock SIGUSR1 runs and SIGUSR2 pauses (server.sim_cli.clock_signals).
# One of those signals that comes while their modules import (the first second or so, before the
# command takes them) is remembered here and applied when it does: its default action killed the
# process.
CLOCK_SIGNAL_COMMANDS = frozenset({"server", "resim"})
_early_clock_request: list[str] = []  # "run" / "pause", the latest last


def _early_clock_signal(signum, frame):
    _early_clock_request.append("run" if signum == signal.SIGUSR1 else "pause")


def take_early_clock_request() -> str | None:
    """The clock request ("run" / "pause") of the last SIGUSR1/SIGUSR2 that came before the
    command took those signals, once (None: none came)."""
    wanted = _early_clock_request[-1] if _early_clock_request else None
    _early_clock_request.clear()
    return wanted


def main(argv: list[str] | None = None) -> int:
    """Run one command; its exit status. A Ctrl-C (SIGINT) at any point, while the command
    modules import and the parser is built (the first second or so) as while the command runs,
    exits 130 (128 + SIGINT, the shell's convention) without a traceback. A SIGTERM the command
    does not take itself (services take theirs from their start: grpc_common.stop_signals)
    unwinds the process and exits 0 for a service (STOPPED_CLEANLY), 143 for any other."""
    words = sys.argv[1:] if argv is None else list(argv)
    in_main = threading.current_thread() is threading.main_thread()
    previous = signal.signal(signal.SIGTERM, _terminated) if in_main else None
    clock_previous = {}
    if in_main and _pre_parse(words).command in CLOCK_SIGNAL_COMMANDS:
        clock_previous = {sig: signal.signal(sig, _early_clock_signal) for sig in (signal.SIGUSR1, signal.SIGUSR2)}
    try:
        return _main(argv)
    except KeyboardInterrupt:
        return 130
    except Terminated:
        command = _pre_parse(words).command
        service = command in STOPPED_CLEANLY or (command == STOPPED_SERVE and "serve" in words)
        return 0 if service else TERMINATED_STATUS
    finally:
        if in_main:
            signal.signal(signal.SIGTERM, previous)
            for sig, handler in clock_previous.items():
                signal.signal(sig, handler)


def _main(argv: list[str] | None) -> int:
    argv = bind_negative_values(sys.argv[1:] if argv is None else list(argv))
    pre = _pre_parse(argv)
    status = FAILURE_STATUS.get(pre.command, 2)
    json_logs = _log_format(pre, os.environ) == "json"
    if json_logs or not pre.verbose:
        # gRPC's C core logs to stderr in its own format (a port in use: its own line before
        # ours, which names the cause); it reads this when grpc is imported. -v keeps its log
        # in text logging, and GRPC_VERBOSITY set by the user is left as it is.
        os.environ.setdefault("GRPC_VERBOSITY", "NONE")
    light = LIGHT_COMMANDS.get(pre.command)
    parser = build_parser((light,) if light else COMMAND_MODULES)
    _report_usage_errors(parser, status, json_logs)
    try:
        config.apply(parser, pre.config, strict=light is None)
        args = parser.parse_args(argv)
        config.settle_exclusive(parser, args, argv)
    except SortieError as exc:
        _error(f"sortie: configuration error: {exc}", json_logs)
        return status
    json_logs = args.log_format == "json"
    configure(logging.WARNING - 10 * min(args.verbose, 2), args.log_format)
    try:
        return int(args.func(args) or 0)
    except BrokenPipeError:
        # The reader of our output left (`sortie terrain info --json | head -1`): not an error of
        # the command's. Python's own advice (the signal module's "Note on SIGPIPE"): point stdout
        # at the null device, so the interpreter's final flush does not fail too, and exit 1.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 1
    except SortieError as exc:
        source = _source_of(parser, argv, exc)
        _error(f"sortie {args.command}: error: {exc}" + (f" (set by {source})" if source else ""), json_logs)
        return status
    except OSError as exc:  # a path that cannot be written or read, a socket refused: one line (-v: the traceback)
        if args.verbose and not json_logs:
            raise
        if args.verbose:
            logging.getLogger("sortie").exception("sortie %s: error: %s", args.command, exc)
        else:
            _error(f"sortie {args.command}: error: {exc}", json_logs)
        return status
    except Exception:  # a bug: its traceback, as one JSON record in json logging
        if not json_logs:
            raise
        logging.getLogger("sortie").exception("sortie %s: unexpected error", args.command)
        return 1


if __name__ == "__main__":
    sys.exit(main())
