"""``sortie terrain``: serve the terrain query service, describe a terrain, query a server.

    sortie terrain serve (--dem FILE... | --store PATH...) [--procedural SEED [--procedural-max-height-m M]
                         [--procedural-exponent E] [--procedural-water W]] --port N [--host H] [--max-workers K]
    sortie terrain info  (--dem FILE... | --store PATH... [--procedural SEED ...] | --address HOST:PORT) [--json]
    sortie terrain query --address HOST:PORT LAT LON [LAT LON ...]
    sortie terrain import FILES... -o STORE [--resolution ARCSEC] [--step M | --lossless] [--add-detail KIND]
    sortie terrain texture (--dem FILE... | --store PATH...) --bbox ... --time ISO8601 -o DIR
    sortie terrain mesh (--dem FILE... | --store PATH...) --bbox ... [--spacing-m M] -o FILE.glb|.obj|.ply|.stl
"""

from __future__ import annotations

import argparse
import json
import logging

from server.grpc_common import DEFAULT_GRACE_S, stop_signals
from server.terrain_service import DEFAULT_MAX_WORKERS, QUERY_THREADS_MAX
from sortie.config import MAX_GRACE_S, grace_seconds
from sortie.errors import InvalidArgument
from sortie.logs import line
from terrain.mesh_cli import add_mesh_parser
from terrain.procedural import (DEFAULT_LEVEL_EXPONENT, DEFAULT_MAX_HEIGHT_M, DEFAULT_WATER, LEVEL_EXPONENT_MAX,
                                MAX_HEIGHT_MAX_M, check_parameters, check_seed)
from terrain.store_cli import add_import_parser
from terrain.texture_cli import add_texture_parser


# The procedural world's options, the paper's M, E and W (terrain/procedural.py, §3): option ->
# (its argparse dest, the ProceduralTerrain parameter it sets), in check_parameters' order.
PROCEDURAL_OPTIONS = {"--procedural-max-height-m": ("procedural_max_height_m", "max_height_m"),
                      "--procedural-exponent": ("procedural_exponent", "level_exponent"),
                      "--procedural-water": ("procedural_water", "water")}


def build_terrain(dem_paths, procedural_seed: int | None = None, store_paths=(), procedural_params=None):
    """A Terrain over the DEM files (in priority order), then the terrain stores,
    then a procedural world if a seed is given; ``procedural_params``: its
    ProceduralTerrain keyword arguments (max_height_m, level_exponent, water), or
    None for the defaults."""
    from terrain.terrain import Terrain

    sources = []
    if dem_paths:
        from terrain.mosaic import load_sources

        sources.extend(load_sources(dem_paths))
    if store_paths:
        from terrain.store import StoreSource, open_store

        sources.extend(StoreSource(open_store(p)) for p in store_paths)
    if procedural_seed is not None:
        from terrain.procedural import ProceduralTerrain

        sources.append(ProceduralTerrain(seed=procedural_seed, **(procedural_params or {})))
    if not sources:
        raise InvalidArgument("--dem", "give at least one DEM file, --store PATH or --procedural SEED")
    return Terrain(sources)


def add_terrain_source_args(parser: argparse.ArgumentParser) -> None:
    """The terrain of a command that only asks heights: files (add_terrain_args) or a running
    terrain service (--address), so an analyst needs no copy of the DEMs."""
    add_terrain_args(parser)
    parser.add_argument("--address", metavar="HOST:PORT",
                        help="ask a running terrain service (sortie terrain serve) instead of loading files")


def check_one_terrain_source(args) -> None:
    """--address with terrain files, a store or a procedural world (or its options) is refused,
    naming --address: a command answers from one terrain."""
    if args.dem or args.store or args.procedural is not None:
        raise InvalidArgument("--address", "give a service address or terrain files, not both",
                              value=args.address)
    procedural_params(args)  # options of a procedural world without one: an error


def terrain_source(args):
    """The terrain of :func:`add_terrain_source_args`: a TerrainClient of --address (ready), or
    the files' Terrain."""
    if args.address:
        check_one_terrain_source(args)
        from client.terrain_client import TerrainClient

        client = TerrainClient(args.address)
        client.wait_ready(10.0)
        return client
    return terrain_of_args(args)


def procedural_params(args) -> dict | None:
    """The ProceduralTerrain parameters of the --procedural-* options (None when none is
    given: the defaults), checked against the paper's ranges: InvalidArgument naming the
    option and its value, as for one given without --procedural SEED."""
    given = {flag: getattr(args, dest) for flag, (dest, _) in PROCEDURAL_OPTIONS.items()
             if getattr(args, dest, None) is not None}
    if not given:
        return None
    if args.procedural is None:
        flag, value = next(iter(given.items()))
        raise InvalidArgument(flag, "shapes a procedural world: give --procedural SEED too", value=value)
    values = [given.get(flag, default) for flag, default in
              zip(PROCEDURAL_OPTIONS, (DEFAULT_MAX_HEIGHT_M, DEFAULT_LEVEL_EXPONENT, DEFAULT_WATER))]
    checked = check_parameters(*values, names=tuple(PROCEDURAL_OPTIONS))
    return {param: value for (_, param), value in zip(PROCEDURAL_OPTIONS.values(), checked)}


def terrain_of_args(args):
    """The Terrain of :func:`add_terrain_args`' options (a bad --procedural SEED is an error naming
    the option, as for the --procedural-* options)."""
    if args.procedural is not None:
        check_seed(args.procedural, "--procedural")
    return build_terrain(args.dem, args.procedural, args.store, procedural_params(args))


def add_parser(sub) -> None:
    from server.grpc_common import HOST_HELP  # here, not at the top: aircraft workers import build_terrain alone

    terrain = sub.add_parser("terrain",
                             help="terrain query service and store: serve, info, query, import, texture, mesh",
                             description="The terrain query service and its tools: serve it, describe a terrain (info), query "
                                         "heights (query), build a compressed terrain store (import), "
                                         "synthesise an aerial texture (texture) or a mesh (mesh) of a box.")
    commands = terrain.add_subparsers(dest="terrain_command", metavar="SUBCOMMAND", required=True)

    serve = commands.add_parser("serve", help="run the gRPC terrain service until SIGTERM/SIGINT",
                                description="Run sortie.v1.TerrainService (with health and reflection) "
                                            "until SIGTERM or SIGINT; prints the bound address.")
    add_terrain_args(serve)
    serve.add_argument("--port", type=int, required=True, help="TCP port; 0 picks a free one")
    serve.add_argument("--host", default="127.0.0.1", help=f"{HOST_HELP} (default %(default)s)")
    serve.add_argument("--max-workers", type=_positive_int, default=DEFAULT_MAX_WORKERS,
                       help="threads answering calls (default %(default)s)")
    serve.add_argument("--query-threads", type=_query_threads, default=default_query_threads(),
                       help="threads one large height or normal batch (32,768 points or more) is answered on, "
                            "1-4 (default: this machine's CPUs, at most 4: %(default)s)")
    serve.add_argument("--grace-s", type=grace_seconds, default=DEFAULT_GRACE_S,
                       help=f"seconds in-flight calls get to finish on shutdown, 0-{MAX_GRACE_S:g} "
                            "(default %(default)s)")
    serve.add_argument("--insets", nargs="+", metavar="SCENARIO",
                       help="answer inside these scenarios' target areas from their high-detail insets "
                            "(terrain/inset.py), as a server with [terrain] insets = true does")
    serve.add_argument("--metrics-port", type=int, metavar="N",
                       help="serve Prometheus metrics (calls, errors, seconds per method) on http://HOST:N/metrics; "
                            "0 picks a free port")
    serve.set_defaults(func=serve_command)

    info = commands.add_parser("info", help="print the metadata of a terrain or of a running service",
                               description="Print sources, bounds, resolution, vertical datum and limits, "
                                           "of a terrain built from files or of a service at --address.")
    add_terrain_args(info)
    info.add_argument("--address", metavar="HOST:PORT", help="ask a running service instead of loading files")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(func=info_command)

    query = commands.add_parser("query", help="print heights from a running service",
                                description="Print the height (m above MSL) and status of each "
                                            "(LAT, LON) point, degrees WGS84, from a running service.")
    query.add_argument("--address", metavar="HOST:PORT", required=True, help="the terrain service")
    query.add_argument("latlon", nargs="+", type=float, metavar="LAT LON",
                       help="pairs of latitude and longitude, degrees")
    query.set_defaults(func=query_command)

    add_import_parser(commands)
    add_texture_parser(commands)
    add_mesh_parser(commands)


def default_query_threads() -> int:
    """--query-threads' default: the CPUs this process may run on, at most QUERY_THREADS_MAX."""
    from terrain.threads import cpu_count

    return max(1, min(QUERY_THREADS_MAX, cpu_count()))


def _query_threads(text: str) -> int:
    value = int(text)
    if not 1 <= value <= QUERY_THREADS_MAX:
        raise argparse.ArgumentTypeError(f"must be 1-{QUERY_THREADS_MAX}, got {value}")
    return value


def _positive_int(text: str) -> int:
    value = int(text)
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def add_terrain_args(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--dem", nargs="+", default=[], metavar="FILE",
                        help="DEM files (.hgt, .asc, .tif, or a .zip holding one), highest priority first "
                             "(raw 16-bit posts need their georeference: the Python API, terrain.dem.read_raw16)")
    parser.add_argument("--store", nargs="+", default=[], metavar="PATH",
                        help="terrain stores (sortie terrain import), under the DEMs")
    parser.add_argument("--procedural", type=int, metavar="SEED",
                        help="add a procedural world with this seed under the DEMs and stores")
    parser.add_argument("--procedural-max-height-m", type=float, metavar="M",
                        help=f"the procedural world's maximum height M (Ammeter & Mikhailyuk §3), metres, in "
                             f"(0, {MAX_HEIGHT_MAX_M:g}] (default {DEFAULT_MAX_HEIGHT_M:g})")
    parser.add_argument("--procedural-exponent", type=float, metavar="E",
                        help=f"its level exponent E (roughness: smaller is rougher), in (1, {LEVEL_EXPONENT_MAX:g}] "
                             f"(default {DEFAULT_LEVEL_EXPONENT:g})")
    parser.add_argument("--procedural-water", type=float, metavar="W",
                        help=f"its water W (more lakes and sea), in [0, 1] (default {DEFAULT_WATER:g})")


def serve_command(args) -> int:
    """Serve until SIGTERM/SIGINT, caught from the start: one that comes while the terrain loads
    (a store, insets: seconds) ends the start there and exits 0, as once serving."""
    from server.grpc_common import bare_host, listen_address
    from server.terrain_service import create_server, file_stat

    with stop_signals() as stop:  # before the line that says it listens (grpc_common.stop_signals)
        stats = [file_stat(p) for p in args.dem] if args.dem else None  # before reading: what is served
        terrain = terrain_of_args(args)
        if args.insets and not stop.is_set():
            from server.scenario import load_scenario
            from terrain.inset import INSET_SEED, with_insets

            areas = [a for path in args.insets for a in load_scenario(path).target_areas]
            terrain = with_insets(terrain, areas, INSET_SEED)
            line(f"insets over {len(areas)} target areas: {', '.join(a.name for a in areas)}", logger=__name__)
        if not stop.is_set():  # the query kernels compiled before the first call needs them (Terrain.warm_up)
            logging.getLogger(__name__).info("query kernels ready in %.2f s", terrain.warm_up())
        if stop.is_set():
            line("sortie terrain service stopped while starting", logger=__name__)
            return 0
        server, port = create_server(terrain, listen_address(args.host, args.port), max_workers=args.max_workers,
                                     dem_paths=args.dem, dem_stats=stats, query_threads=args.query_threads)  # SortieError naming the system's reason when it cannot listen
        metrics = None
        if args.metrics_port is not None:
            from server.metrics import MetricsServer, terrain_metrics

            metrics = MetricsServer(lambda: terrain_metrics(server.stats), bare_host(args.host),
                                    args.metrics_port).start()
        server.start()
        line(f"sortie terrain service listening on {listen_address(args.host, port)}", logger=__name__)
        if metrics is not None:
            line(f"metrics on http://{metrics.address}/metrics", logger=__name__)
        server.serve_until_signalled(grace_s=args.grace_s, stop=stop)
    if metrics is not None:
        metrics.stop()
    line("sortie terrain service stopped", logger=__name__)
    return 0


def info_command(args) -> int:
    if args.address:
        check_one_terrain_source(args)  # (--dem beside --address was silently left out)
        from client.terrain_client import TerrainClient

        with TerrainClient(args.address) as client:
            meta = client.metadata()
    else:
        from client.terrain_client import metadata_dict
        from server.terrain_service import metadata_message

        from terrain.dem import file_identity

        terrain = terrain_of_args(args)
        meta = metadata_dict(metadata_message(terrain, [file_identity(p) for p in args.dem]))
    print(json.dumps(meta, indent=2) if args.json else format_metadata(meta))
    return 0


def format_metadata(meta: dict) -> str:
    """Readable text for a metadata dict (see client.terrain_client.metadata_dict)."""
    from client.terrain_client import SOURCE_KEYS

    lines = [meta["height_reference"]]
    for i, s in enumerate(meta["sources"], 1):
        lines.append(f"source {i}: {s['name']} ({s['kind']}, {s['crs']}) {s['source']}".rstrip())
        lines.append(f"  bounds: lat {s['lat_min']:.6f} .. {s['lat_max']:.6f} deg, "
                     f"lon {s['lon_min']:.6f} .. {s['lon_max']:.6f} deg")
        if s["rows"]:
            lines.append(f"  posts: {s['rows']} rows x {s['cols']} cols")
        lines.append(f"  spacing: {s['spacing_east_m']:.1f} m east x {s['spacing_north_m']:.1f} m north")
        lines.append(f"  vertical datum: {s['vertical_datum']}; filled posts: {s['filled_posts']}")
        lines.extend(f"  {key}: {value}" for key, value in s.items() if key not in SOURCE_KEYS)
    lines.extend(f"file: {f['path']} ({f['size_bytes']:,} bytes, sha256 {f['sha256'] or 'unknown'})"
                 for f in meta.get("dem_files", ()))
    lines.append("limits: " + ", ".join(f"{key} {value:,}" for key, value in meta["limits"].items()))
    return "\n".join(lines)


def query_command(args) -> int:
    from client.terrain_client import TerrainClient
    from sortie.v1 import terrain_pb2 as pb

    if len(args.latlon) % 2:
        raise InvalidArgument("LAT LON", f"needs pairs of numbers, got {len(args.latlon)} values")
    lat, lon = args.latlon[0::2], args.latlon[1::2]
    with TerrainClient(args.address) as client:
        result = client.heights(lat, lon)
    print(f"{'lat_deg':>12} {'lon_deg':>12} {'height_msl_m':>12} status")
    for la, lo, h, st in zip(lat, lon, result.height_msl_m, result.status):
        print(f"{la:12.6f} {lo:12.6f} {h:12.2f} {pb.PointStatus.Name(st).removeprefix('POINT_STATUS_')}")
    return 0
