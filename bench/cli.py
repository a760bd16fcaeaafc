"""``sortie bench``: run one benchmark suite, print its table, write its JSON."""

from __future__ import annotations

import importlib
import os
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


def _check_writable(option: str, text: str, directory: bool = False) -> None:
    """InvalidArgument naming ``option`` now, before a run of minutes, when the path ``text`` (a
    file, or with ``directory`` a folder) cannot be written: an empty path names nothing, and a
    file's path ending in a separator names a folder (``Path`` would drop the separator and write
    a file of the folder's name)."""
    from sortie.errors import InvalidArgument

    if not text:
        raise InvalidArgument(option, "is empty: give a path", value=text)
    if not directory and text.endswith(tuple(s for s in (os.sep, os.altsep) if s)):
        raise InvalidArgument(option, "ends in a path separator: give a file's path, not a folder's", value=text)
    path = Path(text)
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

    if args.json is not None:
        _check_writable("--json", args.json)
    if args.plots is not None:
        _check_writable("--plots", args.plots, directory=True)
    before = calibration.probe()
    report = importlib.import_module(f"bench.{args.suite}").run(quick=args.quick)
    calibration.add_to(report, before, calibration.probe())
    report.print_table()
    if args.json is not None:
        report.write(args.json)
        print(f"wrote {args.json}")
    if args.plots is not None:
        from bench.plots import PLOTTERS

        for path in PLOTTERS[args.suite](report.to_json(), Path(args.plots)):
            print(f"wrote {path}")
    return 0
