"""The ``sortie`` command line: one entry point, a sub-command per service or tool.

Each sub-command lives beside the code it drives and registers itself through
an ``add_parser(subparsers)`` function; this module only assembles them and
configures logging (libraries never do).
"""

from __future__ import annotations

import argparse
import logging
import sys

from sortie import __version__
from sortie.errors import SortieError

# Modules that contribute sub-commands, in --help order.
COMMAND_MODULES = (
    "server.terrain_cli",
    "server.sim_cli",
    "server.recording_cli",
    "client.cli",
    "fdm.cli",
    "bench.cli",
    "server.export_cli",
    "sortie.demo",
)


def build_parser() -> argparse.ArgumentParser:
    import importlib

    parser = argparse.ArgumentParser(
        prog="sortie",
        description="Sortie battlefield simulation service: terrain, simulation, clients, tools.",
    )
    parser.add_argument("--version", action="version", version=f"sortie {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more logging (-vv for debug)")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name in COMMAND_MODULES:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args) or 0)
    except SortieError as exc:
        print(f"sortie {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
