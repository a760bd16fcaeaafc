"""``sortie terrain import``: build a terrain store from DEM files (terrain/store_import.py)."""

from __future__ import annotations

import json

from sortie.errors import InvalidArgument


def add_import_parser(commands) -> None:
    p = commands.add_parser(
        "import", help="convert DEM files into a compressed terrain store",
        description="Mosaic DEM files (.hgt, .asc, .tif, highest priority first), resample them onto the "
                    "store's quad-tree lattice (bilinear, averaged when reducing), optionally add synthetic "
                    "detail, and write the compressed pyramid (docs/STORE.md). Re-running an interrupted "
                    "import with the same arguments resumes it.")
    p.add_argument("files", nargs="+", metavar="FILE", help="DEM files")
    p.add_argument("-o", "--output", required=True, metavar="STORE", help="the store directory to write")
    p.add_argument("--resolution", type=float, metavar="ARCSEC",
                   help="finest latitude spacing wanted, arc-seconds (the store takes the next power-of-two "
                        "lattice at or below it); default: the finest source's")
    q = p.add_mutually_exclusive_group()
    q.add_argument("--step", type=float, default=1.0, metavar="M",
                   help="vertical quantisation step, metres: every post within step/2 of the resampled "
                        "value at every level (default %(default)s)")
    q.add_argument("--lossless", action="store_true", help="keep the resampled heights to the centimetre")
    p.add_argument("--add-detail", choices=("fractal", "cellular"),
                   help="synthesise detail below the sources' spacing (thesis §3.1.9 / §3.3.3)")
    p.add_argument("--detail-seed", type=int, default=0, help="seed of the synthetic detail (default %(default)s)")
    p.add_argument("--name", help="the store's name (default: the directory's)")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=import_command)


# The importer's parameters as `sortie terrain import` spells them, for its errors.
IMPORT_OPTIONS = {"output": "--output", "step": "--step", "resolution": "--resolution", "add_detail": "--add-detail",
                  "files": "FILE"}


def import_command(args) -> int:
    from terrain.store_import import import_dems

    try:
        summary = import_dems(args.files, args.output, resolution_arcsec=args.resolution, step_m=args.step,
                              lossless=args.lossless, add_detail=args.add_detail, detail_seed=args.detail_seed,
                              name=args.name, progress=not args.no_progress and not args.json)
    except InvalidArgument as exc:  # named as the command line names it (step: ... read as --step: ...)
        if exc.field not in IMPORT_OPTIONS:
            raise
        raise exc.with_field(IMPORT_OPTIONS[exc.field]) from None
    if args.json:
        print(json.dumps(summary.to_json(), indent=2))
        return 0
    s = summary
    print(f"terrain store {s.store}: {s.regions} region(s), {s.levels} levels, finest depth {s.depth} "
          f"({s.spacing_arcsec[0]:.3f}\" x {s.spacing_arcsec[1]:.3f}\")")
    made = "from measured data" if s.add_detail else "measured"
    detail = f"; {s.add_detail} detail added, seed {s.detail_seed}" if s.add_detail else ""
    print(f"  posts {s.posts:,} ({s.measured_posts:,} {made}, {s.filled_posts:,} filled voids{detail}); "
          f"{s.stored_bytes:,} bytes, {s.ratio_vs_int16:.2f}:1 against int16")
    print(f"  quantisation step {s.step_m:g} m: max error {s.max_quantisation_error_m:.3f} m, "
          f"RMS {s.rms_quantisation_error_m:.3f} m")
    print(f"  against the source posts (resampling + quantisation): max {s.max_error_vs_source_m:.2f} m, "
          f"RMS {s.rms_error_vs_source_m:.2f} m")
    print(f"  {s.seconds:.1f} s, {s.samples_per_s / 1e6:.2f} M posts/s")
    for b in s.bounds:
        print(f"  region lat {b[0]:.5f}..{b[2]:.5f}, lon {b[1]:.5f}..{b[3]:.5f}")
    return 0
