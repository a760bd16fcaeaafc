"""``sortie export``: recordings into other tools' formats (``acmi``: Tacview, server/acmi.py;
``gltf``: a 3-D debrief scene of tracks, events and terrain, server/gltf.py)."""

from __future__ import annotations

import sys

from server.acmi import check_rate, export_acmi, output_kind


def add_parser(sub) -> None:
    export = sub.add_parser("export", help="convert a recording for other tools: acmi (Tacview), gltf (3-D scene)",
                            description="Convert a Sortie recording into another tool's format: acmi (Tacview ACMI "
                                        "2.2) or gltf (a 3-D debrief scene, glTF 2.0).")
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

    gltf = formats.add_parser(
        "gltf", help="a 3-D debrief scene: tracks, events and the terrain under them (.glb or .gltf)",
        description="Write a recording as a glTF 2.0 scene: every entity's track as a line strip coloured "
                    "by coalition, a marker per entity animated along it (position and attitude; any glTF "
                    "viewer plays the sortie back), the events as points, and the terrain under the tracks "
                    "(plus a margin) "
                    "as a mesh textured for the sortie's start time, in one local east-north-up frame "
                    "(glTF axes: x east, y up, z south; the origin's WGS84 position in the scene's extras).")
    gltf.add_argument("recording", metavar="FILE", help="the recording (a .sortie file written by sortie server)")
    gltf.add_argument("-o", "--output", metavar="OUT", required=True,
                      help="the scene to write: NAME.glb (one binary file) or NAME.gltf (JSON); replaced if it exists")
    gltf.add_argument("--rate", metavar="HZ", type=float, default=None,
                      help="track points and animation keys per second of world time (default: every "
                           "recorded tick)")
    where = gltf.add_mutually_exclusive_group()
    where.add_argument("--dem", nargs="+", metavar="FILE", help="the DEM files (default: the recorded ones)")
    where.add_argument("--terrain", metavar="HOST:PORT", help="a terrain service serving the recorded terrain")
    where.add_argument("--no-terrain", action="store_true", help="tracks and events alone")
    gltf.add_argument("--margin-m", type=float, default=2000.0, metavar="M",
                      help="terrain around the tracks' box, metres (default %(default)s)")
    size = gltf.add_mutually_exclusive_group()
    size.add_argument("--size", metavar="COLSxROWS", help="terrain vertices across and down (default: 512 along the "
                                                          "longer side)")
    size.add_argument("--spacing-m", type=float, metavar="M", help="terrain vertex spacing, metres")
    gltf.add_argument("--max-error-m", type=float, metavar="M",
                      help="an adaptive terrain mesh within M metres of every sampled post (vertically in the mesh's ENU frame, so "
                           "the Earth's curvature counts; far fewer triangles "
                           "where the ground is smooth; terrain/rtin.py)")
    gltf.add_argument("--no-texture", action="store_true", help="the terrain untextured")
    gltf.set_defaults(func=gltf_command)


def acmi_command(args) -> int:
    from server.recording import Recording
    from sortie.errors import InvalidArgument

    try:
        rate = check_rate(args.rate)
        output_kind(args.output)
    except InvalidArgument as e:
        raise _as_option(e) from None
    with Recording(args.recording) as r:
        stats = export_acmi(r, args.output, rate)
    print(f"{stats.path}: {stats.objects} objects, {stats.frames} frames, {stats.events} events, "
          f"{stats.bytes_written} bytes ({stats.states} states in {stats.seconds:.2f} s)")
    return _report_skipped(stats.skipped)


def _report_skipped(skipped: list) -> int:
    """Say on stderr which damaged chunks an export left out (the file is written without
    their ticks and events, as a player skips a damaged stretch of a video); exit status 0."""
    for problem in skipped:
        print(f"sortie export: left out: {problem}", file=sys.stderr)
    return 0


# export_acmi's and export_gltf's parameters as the commands' options, for their errors.
GLTF_OPTIONS = {"rate": "--rate", "margin_m": "--margin-m", "size": "--size", "spacing_m": "--spacing-m",
                "max_error_m": "--max-error-m", "output": "--output"}


def gltf_command(args) -> int:
    from server.gltf import check_output, export_gltf
    from server.recording import Recording
    from sortie.errors import InvalidArgument

    try:
        check_output(args.output)
        rate = check_rate(args.rate)
    except InvalidArgument as e:
        raise _as_option(e) from None
    if args.no_terrain:
        given = [o for o, v in (("--size", args.size), ("--spacing-m", args.spacing_m),
                                ("--max-error-m", args.max_error_m), ("--no-texture", args.no_texture or None))
                 if v is not None]
        if given:
            raise InvalidArgument("--no-terrain", f"leaves no terrain for {', '.join(given)} to shape")
    with Recording(args.recording) as r:
        terrain = None
        if not args.no_terrain:
            from server.resim import recorded_terrain_spec
            from server.sim_server import open_terrain_source

            spec, notes = recorded_terrain_spec(r, args.dem, args.terrain)
            for note in notes:
                print(note)
            if r.header.scenario_toml:  # the insets the world answered from, as resim opens them
                from server.resim import recorded_scenario, with_insets

                with_insets(spec, recorded_scenario(r))
            terrain = open_terrain_source(**spec)
        try:
            stats = export_gltf(r, args.output, terrain, rate_hz=rate, margin_m=args.margin_m, size=args.size,
                                spacing_m=args.spacing_m, texture=not args.no_texture, max_error_m=args.max_error_m)
        except InvalidArgument as e:
            raise _as_option(e) from None
    if stats.terrain_vertices:
        error = stats.terrain_centre_error_m_max
        shown = "" if error is None else f" off the terrain by {error:.2f} m at most at the cells' centres"
        terrain_text = f"terrain {stats.terrain_vertices:,} vertices{shown}, "
    else:
        terrain_text = "no terrain, " if terrain is None else \
            "no terrain mesh (no grid cell with terrain data at its four corners: a finer --size?), "
    print(f"{stats.path}: {stats.tracks} tracks ({stats.track_points} points), {stats.markers} animated markers, "
          f"{stats.target_areas} target areas, {stats.events} events, {terrain_text}{stats.bytes_written:,} bytes")
    return _report_skipped(stats.skipped)


def _as_option(e):
    """An InvalidArgument of export_acmi's or export_gltf's parameter as the command's option."""
    from sortie.errors import InvalidArgument

    if e.field not in GLTF_OPTIONS:
        return e
    return InvalidArgument(GLTF_OPTIONS[e.field], e.message, e.index, e.value)
