"""``sortie export``: recordings into other tools' formats (``acmi``: Tacview, server/acmi.py)."""

from __future__ import annotations

from server.acmi import check_rate, export_acmi, output_kind


def add_parser(sub) -> None:
    export = sub.add_parser("export", help="convert a recording for other tools: acmi (Tacview)",
                            description="Convert a Sortie recording into another tool's format.")
    formats = export.add_subparsers(dest="export_format", metavar="FORMAT", required=True)
    acmi = formats.add_parser(
        "acmi", help="Tacview ACMI 2.2 (.acmi text or .zip.acmi)",
        description="Write a recording as a Tacview ACMI 2.2 file: every entity's position (WGS84, "
                    "altitude MSL) and attitude, written only where it changed, plus removals and "
                    "events (crash, take-off, touchdown, messages). The output's name chooses the "
                    "form: .acmi is UTF-8 text, .zip.acmi a zip archive holding that text.")
    acmi.add_argument("recording", metavar="FILE", help="the recording (a .sortie file written by sortie server)")
    acmi.add_argument("-o", "--output", metavar="OUT", required=True,
                      help="the ACMI file to write: NAME.acmi (text) or NAME.zip.acmi (zipped); replaced "
                           "if it exists")
    acmi.add_argument("--rate", metavar="HZ", type=float, default=None,
                      help="frames per second of world time: keeps the first recorded tick of each "
                           "1/HZ s (and the last tick); default: every recorded tick")
    acmi.set_defaults(func=acmi_command)


def acmi_command(args) -> int:
    from server.recording import Recording

    rate = check_rate(args.rate)
    output_kind(args.output)
    with Recording(args.recording) as r:
        stats = export_acmi(r, args.output, rate)
    print(f"{stats.path}: {stats.objects} objects, {stats.frames} frames, {stats.events} events, "
          f"{stats.bytes_written} bytes ({stats.states} states in {stats.seconds:.2f} s)")
    return 0
