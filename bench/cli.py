"""``sortie bench``: run one benchmark suite, print its table, write its JSON."""

from __future__ import annotations

import importlib

SUITES = ("terrain", "fdm", "server", "recording", "render", "store")


def add_parser(sub) -> None:
    p = sub.add_parser("bench", help="run a benchmark suite", description=(
        "Run one benchmark suite, print a table and optionally write "
        '{"suite", "quick", "metrics", "params"} JSON.'))
    p.add_argument("suite", choices=SUITES, help="which suite to run")
    p.add_argument("--quick", action="store_true", help="smaller run that finishes in under 60 s")
    p.add_argument("--json", metavar="PATH", help="write the report as JSON to PATH")
    p.add_argument("--plots", metavar="DIR", help="write speed-against-error plots (PNG) to DIR")
    p.set_defaults(func=run)


def run(args) -> int:
    from bench import calibration

    before = calibration.probe()
    report = importlib.import_module(f"bench.{args.suite}").run(quick=args.quick)
    calibration.add_to(report, before, calibration.probe())
    report.print_table()
    if args.json:
        report.write(args.json)
        print(f"wrote {args.json}")
    if args.plots:
        from pathlib import Path

        from bench.plots import PLOTTERS

        for path in PLOTTERS[args.suite](report.to_json(), Path(args.plots)):
            print(f"wrote {path}")
    return 0
