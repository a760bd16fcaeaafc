"""``sortie bench``: run one benchmark suite, print its table, write its JSON."""

from __future__ import annotations

import importlib
from pathlib import Path

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


def _check_writable(option: str, path: Path, directory: bool = False) -> None:
    """InvalidArgument naming ``option`` now, before a run of minutes, when ``path`` (a file,
    or with ``directory`` a folder) cannot be written."""
    from sortie.errors import InvalidArgument

    folder = path if directory else path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        probe = folder / f".{path.name}.write-test" if not directory else folder / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except (FileExistsError, NotADirectoryError):
        raise InvalidArgument(option, f"cannot be written: {folder} is not a folder (a file stands in its path)",
                              value=str(path)) from None
    except OSError as exc:
        raise InvalidArgument(option, f"cannot be written: {exc.strerror or exc}", value=str(path)) from None
    if not directory and path.is_dir():
        raise InvalidArgument(option, "is a directory", value=str(path))


def run(args) -> int:
    from bench import calibration

    if args.json:
        _check_writable("--json", Path(args.json))
    if args.plots:
        _check_writable("--plots", Path(args.plots), directory=True)
    before = calibration.probe()
    report = importlib.import_module(f"bench.{args.suite}").run(quick=args.quick)
    calibration.add_to(report, before, calibration.probe())
    report.print_table()
    if args.json:
        report.write(args.json)
        print(f"wrote {args.json}")
    if args.plots:
        from bench.plots import PLOTTERS

        for path in PLOTTERS[args.suite](report.to_json(), Path(args.plots)):
            print(f"wrote {path}")
    return 0
