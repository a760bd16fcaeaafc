"""``sortie terrain mesh``: a lat/lon box of terrain as a textured triangle mesh (terrain/mesh.py).

    sortie terrain mesh (--dem FILE... | --store PATH... | --procedural SEED)
                        (--bbox LAT_MIN LON_MIN LAT_MAX LON_MAX | --cell CELL_ID)
                        [--size COLSxROWS | --spacing-m M] [--time ISO8601 | --no-texture]
                        [--max-error-m M] [--geoid-undulation-m N] [--seed N] -o FILE.glb|.gltf|.obj|.ply|.stl

One vertex at each pixel centre of the grid ``sortie terrain texture`` samples (the same
--bbox/--cell and --size/--spacing-m rules), so the synthesized texture (land classes, light
map and shadows for --time) lies one texel a vertex. glTF embeds it as the base colour, PLY
takes it as vertex colours, OBJ writes it beside the file (NAME.mtl, NAME.png), STL
is geometry alone. Without --time the sun stands at local mean noon at the box's centre on
21 June 2026.

Registered under ``sortie terrain`` by :func:`add_mesh_parser`; numpy, trimesh and the terrain
are imported when the command runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
from datetime import datetime, timedelta, timezone

from sortie.errors import InvalidArgument


def add_mesh_parser(commands) -> argparse.ArgumentParser:
    """Add ``mesh`` to the sub-commands of ``sortie terrain`` (server/terrain_cli.py's ``commands``)."""
    from server.terrain_cli import add_terrain_source_args
    from terrain.texture_cli import add_grid_args

    p = commands.add_parser(
        "mesh", help="write a lat/lon box of terrain as a textured mesh (glTF, OBJ, PLY, STL)",
        description="Sample the terrain on a regular lat/lon grid and write it as a triangle mesh in a "
                    "local east-north-up frame at the box's centre (glTF: x east, y up, z south), "
                    "textured with the synthesized land classes and light map of `sortie terrain "
                    "texture`. At most 4,194,304 (2048 x 2048) vertices (terrain/mesh.py, MAX_VERTICES); "
                    "with --max-error-m, a grid of at most 2049 x 2049 (MAX_ADAPTIVE_SIDE).")
    add_terrain_source_args(p)
    add_grid_args(p, "vertices", "at most 4,194,304 in all; with --max-error-m at most 2049 a side")
    light = p.add_mutually_exclusive_group()
    light.add_argument("--time", metavar="ISO8601", help="UTC instant of the texture's sun, e.g. 2026-06-21T12:00:00Z "
                                                          "(default: local mean noon at the centre, 21 June 2026)")
    light.add_argument("--no-texture", action="store_true", help="geometry alone (no texture, no colours)")
    p.add_argument("--max-error-m", type=float, metavar="M",
                   help="an adaptive mesh (right-triangulated irregular network, terrain/rtin.py) within M "
                        "metres of every sampled post (vertically in the mesh's ENU frame, so the Earth's curvature counts): the grid becomes 2^k + 1 posts a side (at most 2049), at "
                        "least --size or --spacing-m asks, and keeps only the triangles the bound needs")
    p.add_argument("--geoid-undulation-m", type=float, default=0.0, metavar="N",
                   help="ellipsoidal height = MSL height + N, as the simulation world's (default %(default)s)")
    p.add_argument("--seed", type=int, default=0, help="noise seed of the texture (default %(default)s)")
    p.add_argument("-o", "--output", required=True, metavar="FILE",
                   help="the mesh file; its suffix picks the format: .glb, .gltf, .obj, .ply or .stl")
    p.set_defaults(func=mesh_command)
    return p


def grid_limit(max_error_m: float | None, error_field: str = "--max-error-m"):
    """The vertex limit of a mesh's grid (terrain.texture_cli.GridLimit, for texture_request):
    terrain.mesh.MAX_VERTICES for a regular mesh; for an adaptive one (``max_error_m`` given, by
    ``error_field``) the largest RTIN grid, MAX_ADAPTIVE_SIDE a side (:func:`adaptive_request`
    checks the side)."""
    from terrain.mesh import MAX_ADAPTIVE_SIDE, MAX_VERTICES
    from terrain.texture_cli import GridLimit

    if max_error_m is None:
        return GridLimit("vertices", MAX_VERTICES, "2048 x 2048")
    return GridLimit("vertices", MAX_ADAPTIVE_SIDE ** 2,
                     f"{MAX_ADAPTIVE_SIDE} x {MAX_ADAPTIVE_SIDE} with {error_field}: an adaptive mesh")


def adaptive_request(req, max_error_m: float, error_field: str, size_field: str, size_value):
    """The request of an adaptive mesh (terrain/rtin.py): the grid made 2^k + 1 posts a side, at
    least as many as ``req`` asks either way, at most terrain.mesh.MAX_ADAPTIVE_SIDE; InvalidArgument
    naming the option at fault (``size_field``, and ``error_field`` in its message)."""
    from terrain.mesh import MAX_ADAPTIVE_SIDE
    from terrain.rtin import grid_size_for

    if not (math.isfinite(max_error_m) and max_error_m >= 0.0):
        raise InvalidArgument(error_field, "must be a finite number of metres, 0 or more", value=max_error_m)
    side = grid_size_for(max(req.cols, req.rows))
    if side > MAX_ADAPTIVE_SIDE:
        raise InvalidArgument(size_field, f"{req.cols}x{req.rows} with {error_field} makes an adaptive mesh's grid "
                                          f"{side} x {side} (2^k + 1 posts a side, at least as many as asked), over "
                                          f"its limit of {MAX_ADAPTIVE_SIDE} a side", value=size_value)
    return dataclasses.replace(req, cols=side, rows=side)


def checked_request(req, max_error_m: float | None, error_field: str, size_field: str, size_value):
    """``req`` within the mesh limits: an adaptive mesh's grid (:func:`adaptive_request`), or a
    regular one of at most terrain.mesh.MAX_VERTICES; InvalidArgument naming the option at fault."""
    if max_error_m is not None:
        return adaptive_request(req, max_error_m, error_field, size_field, size_value)
    limit = grid_limit(None)
    if req.cols * req.rows > limit.max_count:
        raise InvalidArgument(size_field, f"{req.cols}x{req.rows} = {req.cols * req.rows:,} vertices is over the limit "
                                          f"of {limit.text()}", value=size_value)
    return req


def sample_mesh(terrain, req, max_error_m: float | None = None, *, frame=None, geoid_undulation_m: float = 0.0,
                texture: bool = True, seed: int = 0):
    """(mesh, texture summary, image): the terrain sampled on ``req``'s grid, meshed (regular, or
    adaptive within ``max_error_m``) and, with ``texture``, its synthesized texture (else None
    and None)."""
    from terrain.mesh import build_adaptive_mesh, build_mesh
    from terrain.texture_cli import make_texture, sample_heights

    sampled = sample_heights(terrain, req)
    summary = image = None
    if texture:
        tex, summary = make_texture(terrain, req, seed=seed, sampled=sampled)
        image = tex.image
    if max_error_m is None:
        mesh = build_mesh(*sampled, frame=frame, geoid_undulation_m=geoid_undulation_m)
    else:
        mesh = build_adaptive_mesh(*sampled, max_error_m, frame=frame, geoid_undulation_m=geoid_undulation_m)
    return mesh, summary, image


def local_noon(lon_deg: float) -> str:
    """The UTC instant of local mean noon at a longitude on 21 June 2026, ISO 8601 ('Z')."""
    when = datetime(2026, 6, 21, 12, tzinfo=timezone.utc) - timedelta(hours=lon_deg / 15.0)
    return when.replace(microsecond=0).isoformat().replace("+00:00", "Z")


def mesh_command(args) -> int:
    import numpy as np

    from server.terrain_cli import terrain_source
    from terrain.mesh import MAX_GEOID_UNDULATION_M, centre_error, output_format, write_mesh
    from terrain.texture_cli import box_of, check_output_path, texture_request

    output_format(args.output)
    check_output_path(args.output, folder=False)  # before the work: a folder or an unwritable place
    if not (math.isfinite(args.geoid_undulation_m) and abs(args.geoid_undulation_m) <= MAX_GEOID_UNDULATION_M):
        raise InvalidArgument("--geoid-undulation-m", f"must be within +-{MAX_GEOID_UNDULATION_M:g} m",
                              value=args.geoid_undulation_m)
    bbox = box_of(args)
    centre_lon = 0.5 * (bbox[1] + bbox[3]) if len(bbox) == 4 and all(map(math.isfinite, bbox)) else 0.0
    req = texture_request(bbox, args.size, args.spacing_m, args.time or local_noon(centre_lon),
                          limit=grid_limit(args.max_error_m))
    req = checked_request(req, args.max_error_m, "--max-error-m", "--size" if args.size else "--spacing-m",
                          args.size or args.spacing_m)
    terrain = terrain_source(args)
    mesh, summary, image = sample_mesh(terrain, req, args.max_error_m, geoid_undulation_m=args.geoid_undulation_m,
                                       texture=not args.no_texture, seed=args.seed)
    extras = {"time_utc": None} if summary is None else {
        "time_utc": summary["time_utc"], "sun": summary["sun"], "class_histogram": summary["class_histogram"]}
    if len(mesh.faces) == 0:
        raise InvalidArgument("--bbox" if args.cell is None else "--cell",
                              "holds no terrain data: no cell has heights at its four corners", value=list(bbox))
    path = write_mesh(mesh, args.output, image, extras={"bbox": list(bbox), "max_error_m": args.max_error_m, **extras})
    f = mesh.frame
    err = centre_error(mesh, terrain)
    print(f"{path}: {len(mesh.vertices):,} vertices of a {req.cols}x{req.rows} grid, {len(mesh.faces):,} triangles, "
          f"{path.stat().st_size:,} bytes; origin {f.lat_deg:.6f}, {f.lon_deg:.6f} (WGS84, ellipsoid); "
          + (f"off the terrain at the cells' centres by {np.sqrt(np.mean(err ** 2)):.2f} m RMS, "
             f"{err.max():.2f} m at most" if err.size else "no cell with data")
          + ("" if image is None else f"; textured for {extras['time_utc']}"))
    return 0
