"""``sortie terrain texture``: synthesize an aerial texture of a lat/lon box (terrain/texture.py).

    sortie terrain texture (--dem FILE... | --store PATH... | --procedural SEED)
                           (--bbox LAT_MIN LON_MIN LAT_MAX LON_MAX | --cell CELL_ID)
                           [--size COLSxROWS | --spacing-m M] --time 2026-06-21T12:00:00Z -o DIR
                           [--seed N] [--soft-px N] [--no-refraction]

Samples the terrain at the pixel centres of a regular lat/lon grid (row 0
north), then writes into DIR: classes.png (palette image of the land
classes), slope.png (8-bit, 255 = 90 degrees), diffuse.png, lightmap.png
(8-bit, 255 = full light), shadow.png (255 = in shadow), composite.png and
texture.json (box, size, spacings, sun, class histogram, files).

Each row of pixels has its own metre spacings (terrain.texture.row_spacing:
a row's east-west spacing is N(phi) cos(phi) dlon at its own latitude), and
slopes, normals, sky view and shadows take them, so a tall box (30 to 75 N)
or a polar one has the true slope in every row. texture.json's spacing_m
gives the centre's ("east", "north", as --spacing-m means them) and the
rows' range ("east_rows", "north_rows"). The land classes' noise is placed
by world position (ECEF on the ellipsoid), so every box draws the same
classes at the same place, whatever its extent, however its longitude is
written, and across the antimeridian.

The sun is placed at every pixel (terrain/sun.py at the pixel's centre),
with refraction (the apparent sun) unless --no-refraction. Where its
direction differs by less than SUN_UNIFORM_DEG across the box (a 1-degree
box differs by about 1 degree), the centre's sun lights the whole box and
shadows take the one-sun sweep. Otherwise each pixel's ambient light (and
its twilight ramp), N.L and day or night are its own, so a box wide enough
to span day and night is lit on its day side and dark on its night side,
and each pixel's shadow ray runs straight toward its own sun
(terrain.texture.cast_shadow), whatever the box's width; no box is refused
or tiled for its width. texture.json gives the sun at the box's centre,
whether it was per pixel, and the range of its elevation over the pixels.
--time takes an ISO 8601 instant with a zone (Z, z or an offset), 24:00 as
the end of the day and a leap second :60 as :59; one outside the years 1 to
9999 once in UTC is an error naming --time.

Water over a lossy terrain store: the class map counts as water every pixel
within the store's quantisation bound (half its step) of sea level
(terrain/texture.py's module docstring). The bound comes from the terrain's
sources (:func:`water_tolerance_m`): a local store's, or the terrain
service's metadata (TerrainSource.details ``store_quantisation_m``) with
--address. DEMs, lossless stores and procedural worlds have bound 0.
texture.json gives it as ``water_tolerance_m``.

-o names a folder: it is created if missing; an existing file there, or a
path that cannot be made or written, is an error naming -o (exit status 2,
like every invalid input), as is a box with no terrain data under any pixel
(naming --bbox or --cell, as ``sortie terrain mesh`` does).

Registered under ``sortie terrain`` by :func:`add_texture_parser`; only
argparse and json are imported until the command runs.
"""

from __future__ import annotations

import argparse
import json
import math
import re
from dataclasses import dataclass
from datetime import datetime, timedelta, timezone

from sortie.errors import InvalidArgument

# The largest texture one command makes: 16 Mpixel (4096 x 4096). Peak memory is
# about 115 bytes a pixel (measured: 480 MB above the interpreter's for 2048 x 2048),
# some 2 GB there, and a minute or so of CPU.
MAX_PIXELS = 4096 * 4096
MIN_SIDE_PX = 2  # slopes need two posts along each axis
DEFAULT_LONG_SIDE_PX = 1024  # neither --size nor --spacing-m: the longer side gets this many pixels
# Longitudes as terrain.validate accepts them (one extra turn either way).
LON_ABS_MAX_DEG = 540.0

# Where the sun's direction differs by less than this (degrees) across the whole box, the box is
# lit by the sun at its centre (one direction: the exact digital-line shadow sweep, as before the
# per-pixel sun); a 1-degree box at mid-latitudes differs by about 1 degree.
SUN_UNIFORM_DEG = 0.5
SIZE_PATTERN = re.compile(r"^\s*(\d+)\s*[xX]\s*(\d+)\s*$")


@dataclass(frozen=True)
class GridLimit:
    """What a command's grid points are ("pixels" of a texture, "vertices" of a mesh), the most it
    takes (``max_count`` in all) and how that limit reads in its errors (``note``, e.g. "16 Mpixel")."""

    what: str
    max_count: int
    note: str = ""

    def text(self) -> str:
        return f"{self.max_count:,} {self.what}" + (f" ({self.note})" if self.note else "")


TEXTURE_LIMIT = GridLimit("pixels", MAX_PIXELS, "16 Mpixel")


@dataclass(frozen=True)
class TextureRequest:
    """A validated request: the box (degrees), the grid and the UTC instant."""

    lat_min: float
    lon_min: float
    lat_max: float
    lon_max: float
    cols: int
    rows: int
    when: datetime


def add_texture_parser(commands) -> argparse.ArgumentParser:
    """Add ``texture`` to the sub-commands of ``sortie terrain`` (server/terrain_cli.py's ``commands``)."""
    p = commands.add_parser(
        "texture", help="synthesize an aerial texture (classes, light map, shadows) of a lat/lon box",
        description="Synthesize aerial imagery of a lat/lon box from the terrain alone, after Flight "
                    "Simulator X: a land-class map from elevation, water and slope, procedural class "
                    "textures, and a light map (sky exposure, sun, cast shadows) for the given UTC time. "
                    "The sun is each pixel's own (a box may span day and night), and so is each shadow ray; "
                    "slopes and light take each row's own metre spacing. Writes classes.png, slope.png, diffuse.png, "
                    "lightmap.png, shadow.png, composite.png and texture.json into DIR. A box with no terrain "
                    "data is refused.")
    from server.terrain_cli import add_terrain_source_args  # loaded by now: it registers this command

    add_terrain_source_args(p)
    add_grid_args(p, "pixels", f"at most {MAX_PIXELS:,} in all")
    p.add_argument("--time", required=True, metavar="ISO8601",
                   help="instant with its zone, e.g. 2026-06-21T12:00:00Z or 2026-06-21T14:00:00+02:00")
    p.add_argument("--no-refraction", action="store_true", help="geometric sun elevation (no refraction)")
    p.add_argument("--seed", type=int, default=0, help="noise seed of the textures and bands (default %(default)s)")
    p.add_argument("--soft-px", type=int, default=0, metavar="N",
                   help="blend class edges over about N pixels (default %(default)s: hard stencil)")
    p.add_argument("-o", "--output", required=True, metavar="DIR",
                   help="folder for the images (created if missing; an existing file is an error)")
    p.set_defaults(func=texture_command)
    return p


def add_grid_args(p, what: str, limit: str) -> None:
    """The box (--cell or --bbox) and the grid's size (--size or --spacing-m) of a command that
    samples a lat/lon grid; ``what`` names its points ("pixels"), ``limit`` their limit."""
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--cell", type=int, metavar="CELL_ID",
                       help="the box of one quad-tree cell (terrain/quadtree.py id; e.g. a store tile's cell)")
    where.add_argument("--bbox", nargs=4, type=float,
                       metavar=("LAT_MIN", "LON_MIN", "LAT_MAX", "LON_MAX"), help="the box, degrees WGS84")
    size = p.add_mutually_exclusive_group()
    size.add_argument("--size", metavar="COLSxROWS",
                      help=f"{what} across and down ({limit}); default: {DEFAULT_LONG_SIDE_PX} along the longer "
                           "side, square cells")
    size.add_argument("--spacing-m", type=float, metavar="M", help=f"{what}' spacing in metres at the box's centre")


def box_of(args) -> list:
    """The box of --bbox, or of --cell's quad-tree cell (InvalidArgument naming --cell)."""
    if args.cell is None:
        return args.bbox
    from terrain import quadtree

    try:
        return list(quadtree.bounds(args.cell))
    except InvalidArgument as e:
        raise InvalidArgument("--cell", f"{e.message} of the quad tree", value=args.cell) from None


# The time of day of an ISO 8601 instant in its extended form (hh:mm[:ss[.fff]]), after the date.
TIME_OF_DAY = re.compile(r"^(?P<date>[^Tt ]+[Tt ])(?P<h>\d\d):(?P<m>\d\d)(?::(?P<s>\d\d)(?P<frac>[.,]\d+)?)?"
                         r"(?P<zone>.*)$")


def parse_time(text: str) -> datetime:
    """An ISO 8601 instant with a zone ('Z', 'z' or +hh:mm), as an aware UTC datetime.

    ISO 8601's end of day 24:00[:00] is the next day's 00:00; a leap second hh:mm:60 (RFC 3339
    section 5.6 allows it) is read as hh:mm:59 (the sun moves 0.004 degrees in a second, below
    the sun model's accuracy). An instant outside the years 1 to 9999 once in UTC is refused."""
    shown = text
    text = text.strip()
    next_day = False
    m = TIME_OF_DAY.match(text)
    if m is not None and m["h"] == "24":
        if m["m"] != "00" or (m["s"] or "00") != "00" or (m["frac"] and m["frac"][1:].strip("0")):
            raise InvalidArgument("--time", "hour 24 is only 24:00:00, the end of a day", value=shown)
        text, next_day = f"{m['date']}00:00:00{m['zone']}", True
    elif m is not None and m["s"] == "60":
        text = f"{m['date']}{m['h']}:{m['m']}:59{m['frac'] or ''}{m['zone']}"
    if text.endswith("z"):
        text = text[:-1] + "Z"
    try:
        when = datetime.fromisoformat(text)
    except ValueError:
        raise InvalidArgument("--time", "must be an ISO 8601 instant such as 2026-06-21T12:00:00Z",
                              value=shown) from None
    if when.tzinfo is None or when.utcoffset() is None:
        raise InvalidArgument("--time", "needs a zone: end it with Z (UTC) or an offset like +02:00", value=shown)
    try:
        return (when + timedelta(days=1) if next_day else when).astimezone(timezone.utc)
    except OverflowError:
        raise InvalidArgument("--time", "is outside the years 1 to 9999 once converted to UTC", value=shown) from None


def check_bbox(bbox) -> tuple[float, float, float, float]:
    """(lat_min, lon_min, lat_max, lon_max), finite, in range and not inverted."""
    if len(bbox) != 4:
        raise InvalidArgument("--bbox", "needs LAT_MIN LON_MIN LAT_MAX LON_MAX", value=list(bbox))
    lat_min, lon_min, lat_max, lon_max = (float(v) for v in bbox)
    shown = [lat_min, lon_min, lat_max, lon_max]
    if not all(math.isfinite(v) for v in shown):
        raise InvalidArgument("--bbox", "must be finite numbers", value=shown)
    if not (-90.0 <= lat_min <= 90.0 and -90.0 <= lat_max <= 90.0):
        raise InvalidArgument("--bbox", "latitudes must be within [-90, 90] degrees", value=shown)
    if not (abs(lon_min) <= LON_ABS_MAX_DEG and abs(lon_max) <= LON_ABS_MAX_DEG):
        raise InvalidArgument("--bbox", f"longitudes must be within [-{LON_ABS_MAX_DEG:g}, {LON_ABS_MAX_DEG:g}] "
                                        "degrees", value=shown)
    if lat_min >= lat_max:
        raise InvalidArgument("--bbox", f"is inverted: LAT_MIN {lat_min:g} must be below LAT_MAX {lat_max:g}",
                              value=shown)
    if lon_min >= lon_max:
        raise InvalidArgument("--bbox", f"is inverted: LON_MIN {lon_min:g} must be below LON_MAX {lon_max:g} "
                                        "(a box across the antimeridian takes LON_MAX above 180)", value=shown)
    if lon_max - lon_min > 360.0:
        raise InvalidArgument("--bbox", "spans more than 360 degrees of longitude", value=shown)
    return lat_min, lon_min, lat_max, lon_max


def grid_size(bbox, size: str | None, spacing_m: float | None,
              default_long_side: int = DEFAULT_LONG_SIDE_PX, limit: GridLimit = TEXTURE_LIMIT) -> tuple[int, int]:
    """(cols, rows) from --size, or --spacing-m, or the default; at least MIN_SIDE_PX each way and
    ``limit.max_count`` in all, the errors naming the option and counting in ``limit.what`` (a
    texture's pixels, a mesh's vertices: terrain/mesh_cli.py)."""
    from terrain.texture import metre_spacing

    what = limit.what
    lat_min, lon_min, lat_max, lon_max = bbox
    width_m, height_m = metre_spacing(lat_min, lat_max, lat_max - lat_min, lon_max - lon_min)
    if size is not None:
        m = SIZE_PATTERN.match(size)
        if m is None:
            raise InvalidArgument("--size", "must be COLSxROWS, e.g. 1024x768", value=size)
        cols, rows = int(m.group(1)), int(m.group(2))
        field = "--size"
    elif spacing_m is not None:
        if not (math.isfinite(spacing_m) and spacing_m > 0.0):
            raise InvalidArgument("--spacing-m", "must be a positive number of metres", value=spacing_m)
        # In floats first: a tiny spacing makes counts thousands of digits long, or infinite.
        across, down = width_m / spacing_m, height_m / spacing_m
        if not across * down <= 2 * limit.max_count:
            raise InvalidArgument("--spacing-m", f"{spacing_m:g} m makes about {across:.3g} x {down:.3g} {what} over "
                                                 f"the box, over the limit of {limit.text()}", value=spacing_m)
        cols = max(MIN_SIDE_PX, round(width_m / spacing_m))
        rows = max(MIN_SIDE_PX, round(height_m / spacing_m))
        field = "--spacing-m"
    else:
        scale = default_long_side / max(width_m, height_m)
        cols = max(MIN_SIDE_PX, round(width_m * scale))
        rows = max(MIN_SIDE_PX, round(height_m * scale))
        field = "--size"
    if min(cols, rows) < MIN_SIDE_PX:
        raise InvalidArgument(field, f"needs at least {MIN_SIDE_PX} {what} each way, got {cols}x{rows}",
                              value=size)
    if cols * rows > limit.max_count:
        raise InvalidArgument(field, f"{cols}x{rows} = {cols * rows:,} {what} is over the limit of {limit.text()}",
                              value=size if size is not None else spacing_m)
    return cols, rows


def texture_request(bbox, size: str | None, spacing_m: float | None, time_text: str,
                    default_long_side: int = DEFAULT_LONG_SIDE_PX, limit: GridLimit = TEXTURE_LIMIT) -> TextureRequest:
    """Validate the command's inputs; every failure is InvalidArgument naming the option and value.
    ``limit``: the grid's (a texture's pixels by default; a mesh passes its vertices')."""
    box = check_bbox(bbox)
    when = parse_time(time_text)
    cols, rows = grid_size(box, size, spacing_m, default_long_side, limit)
    return TextureRequest(*box, cols=cols, rows=rows, when=when)


def sample_heights(terrain, req: TextureRequest):
    """(heights, lat, lon): heights (rows, cols) float64 m MSL at the pixel centres, NaN where
    no source covers (status OUTSIDE); lat (rows,) north to south, lon (cols,) west to east."""
    import numpy as np

    from terrain.raster import STATUS_OUTSIDE
    from terrain.texture import grid_latlon

    lat, lon = grid_latlon(req.lat_min, req.lon_min, req.lat_max, req.lon_max, req.rows, req.cols)
    heights = np.empty((req.rows, req.cols))
    # A band of rows at a time keeps the (lat, lon) query arrays small on big textures.
    band = max(1, (1 << 20) // req.cols)
    for r0 in range(0, req.rows, band):
        r1 = min(req.rows, r0 + band)
        la = np.repeat(lat[r0:r1], req.cols)
        lo = np.tile(lon, r1 - r0)
        res = terrain.heights(la, lo)
        h = np.where(res.status == STATUS_OUTSIDE, np.nan, res.height_msl_m)
        heights[r0:r1] = h.reshape(r1 - r0, req.cols)
    return heights, lat, lon


# The store format's height unit (terrain.store.DEFAULT_UNIT_M, not imported here: it loads numba),
# for a terrain service whose metadata predates store_quantisation_m.
_STORE_UNIT_M = 0.01


def water_tolerance_m(terrain) -> float:
    """The height tolerance of the class map's water test for a terrain: the largest
    quantisation bound of its sources. A store source (``describe()`` kind "store", local or a
    TerrainClient's metadata, whose details are text) gives ``store_quantisation_m`` (half its
    step, 0 when lossless), else its ``store_step_m`` halved in whole units; any other source 0.
    A terrain of several sources takes the largest bound for every pixel (pixels a DEM answers
    too: those within it of sea level are drawn as water). No terrain (heights given as such): 0."""
    bound = 0.0
    for source in (terrain.describe() if terrain is not None else ()):
        if source.get("kind") != "store":
            continue
        value = source.get("store_quantisation_m")
        if value is None and source.get("store_step_m") is not None:
            value = (round(float(source["store_step_m"]) / _STORE_UNIT_M) // 2) * _STORE_UNIT_M
        if value is not None and math.isfinite(float(value)):
            bound = max(bound, float(value))
    return bound


def make_texture(terrain, req: TextureRequest, *, seed: int = 0, soft_px: int = 0, refraction: bool = True,
                 sampled=None):
    """(Texture, summary dict) for a request over a Terrain (see terrain.texture.synthesize);
    ``sampled``: :func:`sample_heights`'s result for the request, if the caller has it. Water takes the
    terrain's quantisation bound as its height tolerance (:func:`water_tolerance_m`)."""
    import numpy as np

    from terrain.sun import sun_position
    from terrain.texture import (CLASS_COLOURS_RGB, CLASS_NAMES, class_histogram, metre_spacing,
                                 noise_positions, row_spacing, synthesize)

    heights, lat, lon = sample_heights(terrain, req) if sampled is None else sampled
    dlat, dlon = (req.lat_max - req.lat_min) / req.rows, (req.lon_max - req.lon_min) / req.cols
    # Each row's own spacings for slopes, normals, sky view and shadows; the centre's for texture.json.
    dx, dy = row_spacing(lat, dlat, dlon)
    dx_c, dy_c = metre_spacing(req.lat_min, req.lat_max, dlat, dlon)
    lat_c, lon_c = 0.5 * (req.lat_min + req.lat_max), 0.5 * (req.lon_min + req.lon_max)
    sun = sun_position(req.when, lat_c, lon_c, refraction=refraction)
    az, el = float(sun.azimuth_deg), float(sun.elevation_deg)
    # Each pixel's own sun, unless it is the centre's within SUN_UNIFORM_DEG everywhere.
    from terrain.sun import sun_direction_enu

    field = sun_position(req.when, lat[:, None], lon[None, :], refraction=refraction)
    az_px, el_px = np.broadcast_arrays(field.azimuth_deg, field.elevation_deg)
    cos_apart = np.clip(sun_direction_enu(az_px, el_px) @ sun_direction_enu(az, el), -1.0, 1.0)
    per_pixel = bool(np.degrees(np.arccos(cos_apart.min())) >= SUN_UNIFORM_DEG)
    az_lit, el_lit = (az_px, el_px) if per_pixel else (az, el)
    # Noise placed by world position (ECEF on the ellipsoid), so every box draws the same bands
    # and woodlots at the same place, however its longitude is written and across the antimeridian.
    water_tol = water_tolerance_m(terrain)
    tex = synthesize(heights, dx, dy, az_lit, el_lit, lat[:, None], seed=seed, soft_px=soft_px,
                     noise_xyz_m=noise_positions(lat[:, None], lon[None, :]), water_tolerance_m=water_tol)
    finite = heights[np.isfinite(heights)]
    hist = class_histogram(tex.classes)
    summary = {
        "bbox": {"lat_min": req.lat_min, "lon_min": req.lon_min, "lat_max": req.lat_max, "lon_max": req.lon_max},
        "size": {"cols": req.cols, "rows": req.rows},
        "spacing_m": {"east": dx_c, "north": dy_c, "east_rows": [float(dx.min()), float(dx.max())],
                      "north_rows": [float(dy.min()), float(dy.max())]},
        "time_utc": req.when.isoformat().replace("+00:00", "Z"),
        "sun": {"azimuth_deg": az, "elevation_deg": el, "refraction": refraction,
                "at": {"lat": lat_c, "lon": lon_c}, "per_pixel": per_pixel,
                "elevation_deg_min": float(el_px.min()), "elevation_deg_max": float(el_px.max()),
                "daylit_fraction": float((el_px > 0.0).mean())},
        "height_msl_m": {"min": float(finite.min()) if finite.size else None,
                         "max": float(finite.max()) if finite.size else None,
                         "nodata_pixels": int(heights.size - finite.size)},
        "class_histogram": hist,
        "water_tolerance_m": water_tol,
        "classes": [{"code": k, "name": name, "rgb": CLASS_COLOURS_RGB[k].tolist()}
                    for k, name in enumerate(CLASS_NAMES)],
        "shadow_fraction": float(tex.light.shadow.mean()),
        "seed": seed,
        "soft_px": soft_px,
        "slope_png_deg_per_level": 90.0 / 255.0,
        "files": list(IMAGE_FILES),
    }
    return tex, summary


IMAGE_FILES = ("classes.png", "slope.png", "diffuse.png", "lightmap.png", "shadow.png", "composite.png")


def _nearest_existing(path):
    """The path itself or its nearest ancestor that exists (a Path)."""
    from pathlib import Path

    p = Path(path).absolute()
    while not p.exists() and p != p.parent:
        p = p.parent
    return p


def check_output_path(path, *, folder: bool, field: str = "output") -> None:
    """Refuse, before any work, an output -o cannot take: for a ``folder`` (texture) an existing
    file; for a file (mesh) an existing folder; for either, an ancestor that is a file or a
    folder that cannot be written into. InvalidArgument naming ``field`` and -o with the value."""
    import os
    from pathlib import Path

    p = Path(path)
    shown = str(path)
    if folder and p.exists() and not p.is_dir():
        raise InvalidArgument(field, "-o names the folder the images go into, and this is a file", value=shown)
    if not folder and p.is_dir():
        raise InvalidArgument(field, "cannot be written: -o names the mesh file, and this is a folder", value=shown)
    base = _nearest_existing(p if folder else p.parent)
    if not base.is_dir():
        raise InvalidArgument(field, f"cannot be written: -o's path runs through {base}, a file, not a folder",
                              value=shown)
    if not os.access(base, os.W_OK | os.X_OK):
        raise InvalidArgument(field, f"cannot be written: no permission to write in {base} (-o)", value=shown)


def write_texture(tex, summary: dict, out_dir) -> list:
    """Write the six PNGs and texture.json into out_dir (created); returns the paths written.
    A folder that cannot be made or written is InvalidArgument naming -o (field ``output``)."""
    from pathlib import Path

    import numpy as np
    from PIL import Image

    from terrain.texture import CLASS_COLOURS_RGB

    out = Path(out_dir)
    check_output_path(out, folder=True)
    classes = Image.fromarray(np.ascontiguousarray(tex.classes, dtype=np.uint8))
    classes.putpalette(CLASS_COLOURS_RGB.ravel().tolist())  # makes it a palette ("P") image
    slope = np.rint(np.nan_to_num(tex.slope_deg) * (255.0 / 90.0)).clip(0, 255).astype(np.uint8)
    images = {
        "classes.png": classes,
        "slope.png": Image.fromarray(slope),
        "diffuse.png": Image.fromarray(np.rint(tex.diffuse * 255.0).clip(0, 255).astype(np.uint8)),
        "lightmap.png": Image.fromarray(np.rint(tex.light.light * 255.0).clip(0, 255).astype(np.uint8)),
        "shadow.png": Image.fromarray(np.where(tex.light.shadow, 255, 0).astype(np.uint8)),
        "composite.png": Image.fromarray(tex.image),
    }
    paths = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name in IMAGE_FILES:
            images[name].save(out / name)
            paths.append(out / name)
        (out / "texture.json").write_text(json.dumps(summary, indent=2) + "\n")
    except OSError as exc:
        raise InvalidArgument("output", f"cannot be written: {exc.strerror or exc} (-o)", value=str(out_dir)) from None
    paths.append(out / "texture.json")
    return paths


def texture_command(args) -> int:
    import numpy as np

    from server.terrain_cli import terrain_source

    bbox = box_of(args)
    req = texture_request(bbox, args.size, args.spacing_m, args.time)
    if args.soft_px < 0:
        raise InvalidArgument("--soft-px", "must be 0 or more", value=args.soft_px)
    check_output_path(args.output, folder=True)
    terrain = terrain_source(args)
    sampled = sample_heights(terrain, req)
    if not np.isfinite(sampled[0]).any():
        raise InvalidArgument("--bbox" if args.cell is None else "--cell",
                              "holds no terrain data: no pixel has a height", value=list(bbox))
    tex, summary = make_texture(terrain, req, seed=args.seed, soft_px=args.soft_px,
                                refraction=not args.no_refraction, sampled=sampled)
    write_texture(tex, summary, args.output)
    sun = summary["sun"]
    # As make_texture lit it (texture.json's sun.per_pixel): each pixel's sun, or the centre's for the box.
    which = ("each pixel its own" if sun["per_pixel"] else
             f"the centre's sun for the whole box, within {SUN_UNIFORM_DEG} deg of each pixel's")
    print(f"{req.cols}x{req.rows} texture in {args.output}: sun at the centre azimuth {sun['azimuth_deg']:.1f} deg, "
          f"elevation {sun['elevation_deg']:.1f} deg ({which}: {sun['elevation_deg_min']:.1f} to "
          f"{sun['elevation_deg_max']:.1f} deg, {sun['daylit_fraction']:.1%} of the box in daylight), "
          f"{summary['shadow_fraction']:.1%} in shadow")
    return 0
