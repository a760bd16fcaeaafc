"""The ``sortie`` command line: one entry point, a sub-command per service or tool.

Each sub-command lives beside the code it drives and registers itself through
an ``add_parser(subparsers)`` function; this module only assembles them,
applies the configuration file and environment (sortie/config.py) and
configures logging (sortie/logs.py; libraries never do).
"""

from __future__ import annotations

import argparse
import logging
import re
import sys

from sortie import __version__, config
from sortie.errors import SortieError
from sortie.logs import FORMATS, configure

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


def main(argv: list[str] | None = None) -> int:
    argv = bind_negative_values(sys.argv[1:] if argv is None else list(argv))
    pre = _pre_parse(argv)
    light = LIGHT_COMMANDS.get(pre.command)
    parser = build_parser((light,) if light else COMMAND_MODULES)
    try:
        config.apply(parser, pre.config, strict=light is None)
    except SortieError as exc:
        print(f"sortie: configuration error: {exc}", file=sys.stderr)
        return 2
    args = parser.parse_args(argv)
    config.settle_exclusive(parser, args, argv)
    configure(logging.WARNING - 10 * min(args.verbose, 2), args.log_format)
    try:
        return int(args.func(args) or 0)
    except SortieError as exc:
        source = config.source_of(parser, argv, exc.field) if getattr(exc, "field", None) else None
        print(f"sortie {args.command}: error: {exc}" + (f" (set by {source})" if source else ""), file=sys.stderr)
        return 2
    except OSError as exc:  # a path that cannot be written or read, a socket refused: one line (-v: the traceback)
        if args.verbose:
            raise
        print(f"sortie {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
