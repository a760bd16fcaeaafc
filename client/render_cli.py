"""``sortie render`` (one frame from a pose) and ``sortie view`` (a headless client that
follows an agent of a running exercise and writes frames).

    sortie render (--dem FILE... | --terrain HOST:PORT) --camera LAT,LON,ALT,HEADING,PITCH[,ROLL]
                  --out frame.png [--time ISO8601] [--size 960x540] [--fov-deg 60] [--window-km 20]
                  [--horizon-km 80]
    sortie view --server HOST:PORT (--follow AGENT_NAME | --agent-type aircraft|ground) [--chase]
                [--dem FILE... | --terrain HOST:PORT] --frames N --fps F --out DIR [--size WxH]

``sortie view`` joins as a **gateway** session by default: a gateway sees
every entity of the exercise, so the followed agent never leaves the picture
however far it flies, and no observer radius has to be guessed (the
scenario's observer limit is not published in WorldInfo). ``--role observer``
joins as an observer instead, centred on the first target area (or 0, 0)
with ``--observe-radius-km`` (at most the scenario's observer radius). Without
``--dem``/``--terrain`` the terrain is the server's own (WorldInfo.terrain:
the same DEM files, or a client of the same terrain service). Each frame the
followed agent's pose is dead-reckoned to the picture's estimate of world
time now (client.sim_client.Picture); the camera sits at its eye (cockpit)
or, with ``--chase``, behind and above it. A HUD line per frame goes to
stdout; ``summary.json`` in --out holds the run's figures.

The sun: ``sortie view`` lights the terrain with the sun of the exercise's clock, at the
camera's position: WorldInfo.start_time (a live server's scenario, a replay's recording) plus
the picture's world time, updated once a world second (client/render/shading.py).
``sortie render`` takes the instant as ``--time`` (ISO 8601 with a zone, parsed as ``sortie
terrain texture --time``); without it, a fixed light from the north-west, 45 degrees up.

Altitudes are metres MSL; N, the geoid undulation (ellipsoid = MSL + N),
must be the server's for entities to sit on the terrain: ``sortie view``
reads it from WorldInfo.geoid_undulation_m (0 from a server that does not
send it) unless ``--geoid-undulation-m`` is given.
"""

from __future__ import annotations

import contextlib
import json
import logging
import math
import re
import signal
import threading
import time
from datetime import datetime, timezone
from pathlib import Path

import numpy as np

from sortie.errors import InvalidArgument, LimitExceeded, NotFound

log = logging.getLogger(__name__)

DEFAULT_SIZE = "960x540"
# Cockpit eye in body axes (x forward, y right, z down), metres; chase offsets (back, up), metres.
COCKPIT_EYE_BODY_M = {1: (0.0, 0.0, -1.0), 2: (0.0, 0.0, -3.0), 3: (0.0, 0.0, -12.0)}
CHASE_BACK_UP_M = {1: (60.0, 15.0), 2: (30.0, 10.0), 3: (60.0, 30.0)}
FOLLOW_WAIT_S = 15.0
# --fps's floor: a frame a day. The wait between frames is a threading wait, whose timeout Python
# turns into nanoseconds of the platform's time_t (threading.TIMEOUT_MAX, about 9.2e9 s): 1e-12
# fps waited 1e12 s and raised OverflowError after the first frame.
FPS_MIN = 1.0 / 86_400.0
# --camera's altitude bound, metres MSL: 100,000 km, from where the whole Earth is 6.9 degrees across
# (2 asin(6371 / 106371); about 110 pixels of a 960-pixel frame at 60 degrees); float32 offsets from
# the rebased origin still place its vertices within 6 m there (2^-24 of the distance,
# client/render/camera.py). Beyond it a frame shows a shrinking dot.
ALT_MSL_ABS_MAX_M = 1.0e8


def add_parser(sub) -> None:
    from client.render.shading import DEFAULT_SUN_AZIMUTH_DEG, DEFAULT_SUN_ELEVATION_DEG

    r = sub.add_parser("render", help="render one frame of the terrain from a camera pose (headless)",
                       description="Render one frame (terrain mesh, sea, sky) from a pose to a PNG, headless "
                                   "(EGL; Mesa llvmpipe without a GPU).")
    _terrain_args(r, required=True)
    r.add_argument("--camera", required=True, metavar="LAT,LON,ALT,HEADING,PITCH[,ROLL]",
                   help="degrees, metres MSL, degrees (heading true, pitch nose up, roll right wing down); "
                        "a southern latitude as is, e.g. --camera -33.9,151.2,2000,0,-10")
    r.add_argument("--out", required=True, type=Path, help="PNG to write")
    r.add_argument("--time", metavar="ISO8601",
                   help="light the terrain with the sun at this instant (a zone is required: Z or an offset, e.g. "
                        "2026-06-15T07:00:00Z), where the camera is (terrain/sun.py; at night, ambient light only); "
                        f"default: a fixed light from azimuth {DEFAULT_SUN_AZIMUTH_DEG:g} degrees (north-west), "
                        f"{DEFAULT_SUN_ELEVATION_DEG:g} degrees up, whatever the place")
    _view_args(r)
    r.set_defaults(func=render_command)

    v = sub.add_parser("view", help="headless render client: follow an agent of a running exercise",
                       description="Join a simulation server, follow an agent's dead-reckoned pose (cockpit or "
                                   "chase camera), draw the terrain and the other entities, write PNG frames, a "
                                   "HUD line per frame and summary.json. The terrain is lit by the sun of the "
                                   "exercise's clock (its start_time plus world time, a replay's too) where the "
                                   "camera is.")
    v.add_argument("--server", required=True, metavar="HOST:PORT",
                   help="the simulation server (sortie server or sortie replay)")
    who = v.add_mutually_exclusive_group(required=True)
    who.add_argument("--follow", metavar="AGENT_NAME", help="the agent's scenario name")
    who.add_argument("--agent-type", choices=("aircraft", "ground"), help="follow the first agent of this kind")
    v.add_argument("--chase", action="store_true", help="camera behind and above the agent (default: cockpit)")
    v.add_argument("--views", metavar="VIEW[,VIEW]",
                   help="several views of the agent per frame from one renderer sharing its terrain textures, "
                        "e.g. cockpit,chase (frames frame_NNNN_<view>.png); overrides --chase")
    _terrain_args(v, required=False)
    v.add_argument("--frames", type=int, required=True, metavar="N", help="frames to render, at least 1")
    v.add_argument("--fps", type=float, required=True, metavar="F", help="frames per wall second (at most)")
    v.add_argument("--out", type=Path, required=True, metavar="DIR",
                   help="folder for the PNG frames and summary.json (created if missing)")
    v.add_argument("--role", choices=("gateway", "observer"), default="gateway",
                   help="session role (default %(default)s: sees every entity)")
    v.add_argument("--observe-radius-km", type=float, default=100.0,
                   help="observer role: radius of the area of interest (default %(default)s)")
    v.add_argument("--name", default="render-client",
                   help="the session's name, 1-64 printable characters (default %(default)s)")
    _view_args(v)
    v.set_defaults(func=view_command)


def _terrain_args(p, required: bool) -> None:
    g = p.add_mutually_exclusive_group(required=required)
    g.add_argument("--dem", nargs="+", metavar="FILE", help="DEM files, in priority order")
    g.add_argument("--terrain", metavar="HOST:PORT[,HOST:PORT...]", help="a terrain service (or replicas of one)")
    g.add_argument("--store", metavar="PATH", help="a terrain store (sortie terrain import): clipmap levels are "
                                                   "decoded from the store's own levels")


def _view_args(p) -> None:
    from client.render.profiles import PROFILES

    p.add_argument("--size", default=DEFAULT_SIZE, metavar="WxH", help="pixels (default %(default)s)")
    p.add_argument("--terrain-renderer", choices=("clipmap", "mesh"), default="clipmap",
                   help="geometry clipmap (default) or the full-resolution reference mesh")
    p.add_argument("--profile", choices=sorted(PROFILES),
                   help="the clipmap's level-of-detail profile (client/render/profiles.py; default: the "
                        "followed agent's, observer for sortie render)")
    p.add_argument("--pixel-error", type=float, default=None, metavar="PX",
                   help="clipmap: draw a block with fewer posts where that moves its surface by at most PX "
                        "pixels, 0 for every post (default: the profile's)")
    p.add_argument("--fov-deg", type=float, default=60.0, help="horizontal field of view (default %(default)s)")
    p.add_argument("--window-km", type=float, default=20.0,
                   help="mesh (and the clipmap near a pole, where it draws the mesh): half-width of the "
                        "full-resolution terrain window (default %(default)s)")
    p.add_argument("--horizon-km", type=float, default=80.0,
                   help="mesh (and the clipmap near a pole): half-width of the coarser horizon ring, 0 for none "
                        "(default %(default)s)")
    p.add_argument("--geoid-undulation-m", type=float, default=None, metavar="N",
                   help="ellipsoid height = MSL + N, metres (render: default 0; view: default the server's)")
    p.add_argument("--no-fog", action="store_true", help="no distance fog (default: fog hides the terrain's end)")
    p.add_argument("--land-classes", action="store_true",
                   help="colour the clipmap terrain by land class (water, beach, farmland, forest, alpine, rock, "
                        "snow from height, slope and latitude; terrain/texture.py) instead of the height tint")


# -- argument parsing ----------------------------------------------------------------------------

def parse_size(text: str) -> tuple[int, int]:
    """"960x540" -> (960, 540), each side in [1, the renderer's MAX_IMAGE_SIDE]."""
    from client.render.renderer import MAX_IMAGE_SIDE

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InvalidArgument("--size", "expected WIDTHxHEIGHT in pixels, e.g. 960x540", value=text) from None
    if not (0 < w <= MAX_IMAGE_SIDE and 0 < h <= MAX_IMAGE_SIDE):
        raise InvalidArgument("--size", f"width and height must be in [1, {MAX_IMAGE_SIDE}] pixels", value=text)
    return w, h


def parse_pose(text: str) -> tuple[float, ...]:
    """"LAT,LON,ALT,HEADING,PITCH[,ROLL]" -> six floats (roll 0 when absent)."""
    try:
        values = [float(v) for v in text.split(",")]
    except ValueError:
        values = []
    if len(values) not in (5, 6):
        raise InvalidArgument("--camera", "expected LAT,LON,ALT_MSL_M,HEADING_DEG,PITCH_DEG[,ROLL_DEG]", value=text)
    from terrain.validate import LON_ABS_MAX_DEG

    # (Camera.from_geodetic's and the terrain's own checks name their parameters, lat_deg, lon[0].)
    # Heading and roll within a turn either way (1e300 is no angle a camera can take).
    bounds = {"LAT": (90.0, "degrees"), "LON": (LON_ABS_MAX_DEG, "degrees"), "ALT_MSL_M": (ALT_MSL_ABS_MAX_M, "m"),
              "HEADING_DEG": (360.0, "degrees"), "PITCH_DEG": (90.0, "degrees"), "ROLL_DEG": (360.0, "degrees")}
    for name, v in zip(("LAT", "LON", "ALT_MSL_M", "HEADING_DEG", "PITCH_DEG", "ROLL_DEG"), values):
        if not math.isfinite(v):
            raise InvalidArgument("--camera", f"{name} must be a finite number (LAT,LON,ALT_MSL_M,HEADING_DEG,"
                                              "PITCH_DEG[,ROLL_DEG])", value=text)
        if name in bounds and abs(v) > bounds[name][0]:
            bound, unit = bounds[name]
            raise InvalidArgument("--camera", f"{name} {v:g} must be within [-{bound:g}, {bound:g}] {unit}",
                                  value=text)
    return tuple(values + [0.0] * (6 - len(values)))


def check_image_path(option: str, path: Path) -> None:
    """An image file to write: not a directory, in a directory that is or can be made, and named
    with an extension Pillow writes an RGB image in (.png, .jpg, ...), which picks the format;
    checked before a frame is rendered. The format is tried on a 1 x 1 RGB image in memory:
    Pillow registers savers that take only other modes (.xbm: 1-bit, .palm: palette, .blp) or
    need a plugin it does not ship (.h5, .bufr, .grib), and those fail only on the save."""
    import io

    from PIL import Image

    if path.is_dir():
        raise InvalidArgument(option, "is a directory: give an image file to write, e.g. frame.png", value=str(path))
    Image.init()
    fmt = Image.registered_extensions().get(path.suffix.lower())
    if fmt is None or fmt not in Image.SAVE:
        raise InvalidArgument(option, "must name an image file with an extension the format is taken from, e.g. "
                                      ".png or .jpg", value=str(path))
    try:
        Image.new("RGB", (1, 1)).save(io.BytesIO(), format=fmt)
    except Exception as exc:  # noqa: BLE001 - whatever the format's saver raises: it cannot write a frame
        raise InvalidArgument(option, f"Pillow cannot write an RGB frame as {fmt} ({type(exc).__name__}: {exc}); "
                                      "give another extension, e.g. .png or .jpg", value=str(path)) from None
    check_writable_dir(option, path.parent)


def check_writable_dir(option: str, directory: Path) -> None:
    """``directory`` exists and is one this process may write in, or can be made: its nearest
    existing ancestor is a directory it may write in (the frames are written after rendering)."""
    import os

    existing = directory
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        raise InvalidArgument(option, f"{str(existing)!r} is a file, not a directory", value=str(directory))
    if not os.access(existing, os.W_OK | os.X_OK):
        raise InvalidArgument(option, f"cannot write in the directory {str(existing)!r}", value=str(directory))


def check_render_options(args) -> None:
    """The numeric options of render and view, each named as given on the command line (a
    renderer's own check names its parameter, window_m, not --window-km), with the camera's and
    the renderer's own bounds."""
    from client.render.camera import FOV_X_RANGE_DEG
    from server.scenario import GEOID_UNDULATION_ABS_MAX_M  # the renderer's bound (a scenario's too)

    if getattr(args, "size", None) is not None:  # (a namespace of some options only: those)
        parse_size(args.size)
    lo, hi = FOV_X_RANGE_DEG
    if not (lo <= getattr(args, "fov_deg", lo) <= hi):  # NaN fails too
        raise InvalidArgument("--fov-deg", f"must be within [{lo:g}, {hi:g}] degrees", value=args.fov_deg)
    n_max = GEOID_UNDULATION_ABS_MAX_M
    if args.geoid_undulation_m is not None and not (math.isfinite(args.geoid_undulation_m)
                                                    and abs(args.geoid_undulation_m) <= n_max):
        raise InvalidArgument("--geoid-undulation-m", f"must be finite and within [-{n_max:g}, {n_max:g}] m (the "
                                                     "geoid departs from WGS84 by -107 to +86 m)",
                              value=args.geoid_undulation_m)
    window, horizon = args.window_km, args.horizon_km  # client/render/terrain_mesh.py's bounds, in km
    if not (math.isfinite(window) and 0.0 < window <= 1000.0):
        raise InvalidArgument("--window-km", "must be in (0, 1000] km", value=window)
    if not (horizon == 0.0 or (math.isfinite(horizon) and window < horizon <= 2000.0)):
        raise InvalidArgument("--horizon-km", "must be 0 (none) or in (--window-km, 2000] km", value=horizon)
    if getattr(args, "pixel_error", None) is not None:
        check_pixel_error(args.pixel_error)


def check_pixel_error(px: float) -> None:
    """--pixel-error: a number of pixels in [0, 100] (0: every post)."""
    if not (math.isfinite(px) and 0.0 <= px <= 100.0):
        raise InvalidArgument("--pixel-error", "must be a number of pixels in [0, 100] (0: every post)", value=px)


def open_terrain(dem=None, service: str | None = None, world_terrain: str = "", store: str | None = None):
    """(terrain, description): DEM files in process, a terrain store, a terrain service client,
    or the server's terrain as WorldInfo.terrain names it ("dem:<a>,<b>" or "service:<address>")."""
    from server.sim_server import open_terrain_source

    if store:
        from terrain.store import StoreSource, open_store
        from terrain.terrain import Terrain

        return Terrain([StoreSource(open_store(store))]), f"store:{store}"

    if not dem and not service and world_terrain:
        kind, _, rest = world_terrain.partition(":")
        if kind == "service":
            service = rest
        elif kind == "dem":
            dem = [p for p in rest.split(",") if p]
            missing = [p for p in dem if not Path(p).exists()]
            if missing:
                raise NotFound(f"the server's DEM files are not here: {', '.join(missing)}; give --dem or --terrain")
    if service:
        return open_terrain_source(service=service), f"service:{service}"
    if dem:
        return open_terrain_source(dem=dem), "dem:" + ",".join(map(str, dem))
    raise InvalidArgument("--dem", "give --dem FILE... or --terrain HOST:PORT (the server names no terrain)")


def _renderer(args, terrain, geoid_undulation_m: float, profile_name: str = "observer", insets=(), sun_time=None):
    from client.render.clipmap_layer import clipmap_factory
    from client.render.profiles import profile
    from client.render.renderer import Renderer

    w, h = parse_size(args.size)
    layer_args = profile(args.profile or profile_name).layer_args()
    px = getattr(args, "pixel_error", None)
    if px is not None:
        check_pixel_error(px)
        layer_args["pixel_error"] = px or None
    factory = None
    if args.terrain_renderer == "clipmap" and terrain is not None:
        factory = clipmap_factory(terrain, geoid_undulation_m=geoid_undulation_m, insets=insets,
                                  land_classes=args.land_classes, polar_window_m=args.window_km * 1000.0,
                                  polar_horizon_m=args.horizon_km * 1000.0, **layer_args)
    return Renderer(terrain, w, h, window_m=args.window_km * 1000.0, horizon_m=args.horizon_km * 1000.0,
                    geoid_undulation_m=geoid_undulation_m, fog=not args.no_fog, terrain_layer_factory=factory,
                    insets=insets, sun_time=sun_time)


def world_insets(terrain, world_info):
    """(terrain, insets): the target areas' insets when the server's terrain has them
    (WorldInfo.terrain_insets): rebuilt from a terrain service that serves them, or built over
    DEM files (terrain/inset.py; the same bits as the server's)."""
    if not getattr(world_info, "terrain_insets", False) or not world_info.target_areas:
        return terrain, []
    from terrain.inset import INSET_SEED, InsetSource, insets_of, with_insets

    areas = [(a.name, tuple(zip(a.lat_deg, a.lon_deg)), a.detail_m) for a in world_info.target_areas]
    if hasattr(terrain, "sources"):  # in process: the DEMs
        terrain = with_insets(terrain, areas, INSET_SEED)
        return terrain, insets_of(terrain)
    return terrain, [InsetSource.from_inset_terrain(terrain, polygon, detail_m, INSET_SEED, name=name)
                     for name, polygon, detail_m in areas]


@contextlib.contextmanager
def mesh_area_named(args, renderer):
    """A terrain limit the reference mesh's requests run into (the procedural world's new blocks
    a call, a service's batch) names the options that set the area it asks for: every post within
    --window-km and a ring of coarser posts to --horizon-km. (The clipmap's requests are budgeted;
    near a pole it draws the mesh too, ClipmapLayer.polar.)"""
    try:
        yield
    except LimitExceeded as exc:
        polar = bool(getattr(renderer.terrain_layer, "polar", False))
        if args.terrain_renderer != "mesh" and not polar:
            raise
        whose = "the clipmap's mesh near a pole" if polar else "the reference mesh"
        hint = (f"{whose} asks for every post within --window-km {args.window_km:g} and a ring to "
                f"--horizon-km {args.horizon_km:g} at once: give smaller ones")
        raise LimitExceeded(exc.field, exc.size, exc.limit, f"{exc.why}; {hint}" if exc.why else hint) from None


def _close(terrain) -> None:
    close = getattr(terrain, "close", None)
    if close is not None:
        close()


# -- sortie render -------------------------------------------------------------------------------

def render_command(args) -> int:
    from PIL import Image

    from client.render.camera import Camera

    lat, lon, alt, heading, pitch, roll = parse_pose(args.camera)
    check_render_options(args)
    check_image_path("--out", args.out)
    sun_time = None
    if args.time is not None:
        from terrain.texture_cli import parse_time  # sortie terrain texture --time's parsing and errors

        sun_time = parse_time(args.time)
    undulation = args.geoid_undulation_m or 0.0
    camera = Camera.from_geodetic(lat, lon, alt, heading, pitch, roll, geoid_undulation_m=undulation,
                                  fov_x_deg=args.fov_deg)
    terrain, desc = open_terrain(args.dem, args.terrain, store=args.store)
    try:
        ground = float(np.asarray(terrain.heights(np.array([lat]), np.array([lon])).height_msl_m)[0])
        what = "the terrain there"
        if math.isnan(ground):  # no data: the renderer draws the sea at 0 m MSL there
            ground, what = 0.0, "sea level there (no terrain data: the sea is drawn)"
        if alt < ground:  # a frame from inside the terrain shows nothing meaningful
            raise InvalidArgument("--camera", f"altitude {alt:g} m MSL is below {what} "
                                              f"({ground:.1f} m MSL at {lat:g}, {lon:g})", value=args.camera)
        with _renderer(args, terrain, undulation, sun_time=sun_time) as r, mesh_area_named(args, r):
            image = r.render(camera)
            s = r.stats
    finally:
        _close(terrain)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(args.out)
    lifted = (f"; eye raised {s.eye_lift_m:.2f} m to stand over the terrain's triangles there, which rise above its "
              "surface" if s.eye_lift_m > 0 else "")
    print(f"wrote {args.out} ({image.shape[1]}x{image.shape[0]}) from {desc}: {s.frame_ms:.0f} ms "
          f"(terrain {args.terrain_renderer} update {s.update_ms:.0f} ms), {s.triangles:,} triangles, "
          f"{s.vertices:,} vertices{lifted}; {sun_text(s, sun_time)}", flush=True)
    return 0


def sun_text(stats, sun_time) -> str:
    """What lit a frame, for its report line: the sun in the camera's sky (renderer.FrameStats)."""
    where = (f"sun at {sun_time.isoformat().replace('+00:00', 'Z')}" if isinstance(sun_time, datetime)
             else "sun of the exercise's clock" if sun_time is not None else "fixed light (no --time)")
    night = ": below the horizon, ambient light only" if stats.sun_elevation_deg <= 0.0 else ""
    return (f"{where}, azimuth {stats.sun_azimuth_deg:.1f} elevation {stats.sun_elevation_deg:.1f} "
            f"degrees{night}")


# -- sortie view ---------------------------------------------------------------------------------

def _pick(picture, name: str | None, kind: int | None):
    """The id of the agent to follow in the picture (by name, or the lowest id of a kind), or None."""
    for i in sorted(picture.infos):
        info = picture.infos[i]
        if (name is not None and info.name == name) or (name is None and info.kind == kind):
            return i
    return None


def follow_camera(pos, quat, kind: int, chase: bool, fov_x_deg: float):
    """The camera for a followed entity at pos (3,) ECEF with ECEF -> body quat (4,)."""
    from client.render.camera import Camera, chase_camera, quat_to_matrix

    r = quat_to_matrix(quat)
    if chase:
        back, up = CHASE_BACK_UP_M.get(kind, CHASE_BACK_UP_M[1])
        return chase_camera(pos, r, back, up, fov_x_deg=fov_x_deg)
    eye = np.asarray(pos, np.float64) + r @ np.asarray(COCKPIT_EYE_BODY_M.get(kind, (0.0, 0.0, 0.0)))
    return Camera(eye, r, fov_x_deg=fov_x_deg)


def _percentiles(values) -> dict:
    v = np.asarray(values, np.float64)
    if v.size == 0:
        return {}
    return {"mean": float(v.mean()), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "max": float(v.max())}


def view_command(args) -> int:
    from client.render.entities import kind_from_name

    if args.frames < 1:
        raise InvalidArgument("--frames", "must be >= 1", value=args.frames)
    if not (args.fps >= FPS_MIN):  # NaN fails too
        raise InvalidArgument("--fps", f"must be at least {FPS_MIN:.3g} (a frame a day)", value=args.fps)
    if args.role == "observer":
        check_observe_radius(args)
    check_render_options(args)
    _views(args)  # --views named as given, before joining
    check_session_name(args.name)
    check_writable_dir("--out", Path(args.out))  # a file there, or no way to make it: before joining
    kind = None if args.agent_type is None else kind_from_name(args.agent_type)
    stop = threading.Event()
    previous = {}
    if threading.current_thread() is threading.main_thread():  # SIGTERM/SIGINT end the run cleanly
        for sig in (signal.SIGTERM, signal.SIGINT):
            previous[sig] = signal.signal(sig, lambda signum, frame: stop.set())
    try:
        return _view(args, kind, stop)
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def check_observe_radius(args) -> None:
    """--observe-radius-km as the observer role's area needs it: a finite number of km above 0
    (the server's observer_radius_m bound, in km; its upper bound is the scenario's, which
    WorldInfo does not carry: the server checks it on join, :func:`_join`)."""
    radius = args.observe_radius_km
    if not (math.isfinite(radius) and radius > 0.0):
        raise InvalidArgument("--observe-radius-km", "must be a finite number of km > 0", value=radius)


def check_session_name(name: str) -> None:
    """--name as the server takes a session's client_name (server/sim_service.py's rule), named
    as given, before joining (the server's own error names client_name, after connecting)."""
    from server.sim_service import MAX_NAME_CHARS

    if not (1 <= len(name) <= MAX_NAME_CHARS and name.isprintable()):
        raise InvalidArgument("--name", f"must be 1-{MAX_NAME_CHARS} printable characters", value=name)


_SERVER_RADIUS_BOUND = re.compile(r"must be in \(0, (?P<limit_m>[0-9.e+]+)\] m")


def _join(sim, args) -> None:
    sim.wait_ready()
    if args.role == "gateway":
        sim.join(args.name, "gateway")
        return
    w = sim.world()
    centre = ((float(np.mean(w.target_areas[0].lat_deg)), float(np.mean(w.target_areas[0].lon_deg)))
              if w.target_areas else (0.0, 0.0))
    try:
        sim.join(args.name, "observer", observer=(*centre, args.observe_radius_km * 1000.0))
    except InvalidArgument as exc:  # over the scenario's observer radius: named as given, in km
        m = _SERVER_RADIUS_BOUND.search(exc.message) if exc.field == "observer_radius_m" else None
        if m is None:
            raise
        raise InvalidArgument("--observe-radius-km", f"must be in (0, {float(m['limit_m']) / 1000.0:g}] km (the "
                                                     "scenario's observer radius)",
                              value=args.observe_radius_km) from None


def _not_seen(args) -> str:
    """Why the agent to follow never showed in the picture: a gateway sees every entity, so it is
    not in the exercise; an observer sees only its area, so it may be outside it."""
    what = f"agent {args.follow!r}" if args.follow else f"an agent of kind {args.agent_type}"
    if args.role == "gateway":
        return f"{what} is not in the exercise (waited {FOLLOW_WAIT_S:g} s)"
    return (f"{what} is not within the observed area, --observe-radius-km {args.observe_radius_km:g} km around the "
            f"first target area (or 0, 0), after {FOLLOW_WAIT_S:g} s: it is outside it or not in the exercise; give "
            "a larger --observe-radius-km (up to the scenario's observer radius) or --role gateway, which sees "
            "every entity")


def _picture_so_far(picture, most: int = 12) -> str:
    """What the picture held when the wait for the agent ended: its update count and the names
    it saw (the first ``most``), so a wrong name or an empty stream shows in the error."""
    names = sorted(str(info.name) for info in picture.infos.values())
    listed = ", ".join(repr(n) for n in names[:most]) + (f", ... ({len(names)} in all)" if len(names) > most else "")
    return f"; the picture had {picture.updates} updates and {len(names)} entities" + (f": {listed}" if names else "")


def _view(args, kind: int | None, stop: threading.Event) -> int:
    from client.render.entities import KIND_NAMES
    from client.sim_client import SimClient

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with SimClient(args.server) as sim:
        _join(sim, args)
        picture = sim.watch()
        if not picture.wait_for(lambda p: _pick(p, args.follow, kind) is not None, FOLLOW_WAIT_S):
            ended = picture.error  # the stream's own end, if it ended before the wait did
            sim.leave()
            raise NotFound(_not_seen(args) + _picture_so_far(picture)
                           + (f" (the state stream ended: {ended})" if ended is not None else ""))
        target = _pick(picture, args.follow, kind)
        info = picture.infos[target]
        terrain, desc = open_terrain(args.dem, args.terrain, sim.world_info.terrain, store=args.store)
        terrain, insets = world_insets(terrain, sim.world_info)
        undulation = (args.geoid_undulation_m if args.geoid_undulation_m is not None
                      else float(getattr(sim.world_info, "geoid_undulation_m", 0.0)))
        from client.render.profiles import profile_for

        lod = args.profile or profile_for(KIND_NAMES.get(int(info.kind), ""), info.type).name
        start = exercise_start(sim.world_info.start_time)
        print(f"following {info.name!r} ({KIND_NAMES.get(int(info.kind), '?')} {info.type}, id {target}), "
              f"{', '.join(_views(args))} camera, terrain {desc} ({args.terrain_renderer}, profile {lod}), "
              f"{'sun of ' + sim.world_info.start_time + ' + world time' if start is not None else 'fixed light'}",
              flush=True)
        try:
            with _renderer(args, terrain, undulation, lod, insets) as r, mesh_area_named(args, r):
                frames, stats = _frames(args, picture, target, r, out, stop, undulation, start)
        finally:
            _close(terrain)
        from client.cli import stream_end

        code = stream_end(sim, picture)
    summary = {
        "server": args.server, "follow": info.name, "entity_id": int(target),
        "kind": KIND_NAMES.get(int(info.kind), str(info.kind)), "camera": ",".join(_views(args)),
        "terrain_renderer": args.terrain_renderer, "profile": lod,
        "role": args.role, "terrain": desc, "start_time": sim.world_info.start_time,
        "sun": "exercise clock" if start is not None else "fixed", "geoid_undulation_m": undulation,
        "insets": [s.name for s in insets],
        "size": list(parse_size(args.size)), "fov_x_deg": args.fov_deg,
        "window_km": args.window_km, "horizon_km": args.horizon_km, "frames": len(stats),
        "requested_frames": args.frames, "requested_fps": args.fps,
        "achieved_fps": achieved_fps([s["started_s"] for s in stats]),
        **{key: _percentiles([s[key] for s in stats]) for key in ("frame_ms", "update_ms", "triangles", "vertices",
                                                                  "entities_drawn", "terrain_samples",
                                                                  "levels_active")},
        "mesh_rebuilds": stats[-1]["mesh_rebuilds"] if stats else 0,
        "rebases": sum(bool(s["rebased"]) for s in stats),
        "out": str(out), "pngs": frames, "per_frame": stats,
    }
    (out / "summary.json").write_text(json.dumps(summary, indent=1))
    print(f"{len(stats)} frames ({len(frames)} images) in {out}, summary {out / 'summary.json'}", flush=True)
    return code if frames else 1


VIEWS = ("cockpit", "chase")


def exercise_start(start_time: str) -> np.datetime64 | None:
    """WorldInfo.start_time (ISO 8601 with a zone, UTC as the server and a recording write it)
    as a UTC numpy datetime64 in microseconds, to which world seconds add without datetime's
    year 9999 limit; None, with a warning, when the server sent none or one that does not read
    (the frames keep the fixed light)."""
    try:
        start = datetime.fromisoformat(start_time.strip().upper())  # (RFC 3339 allows "t" and "z")
        if start.tzinfo is None or start.utcoffset() is None:
            raise ValueError("no zone")
        start = start.astimezone(timezone.utc).replace(tzinfo=None)
    except (ValueError, OverflowError) as exc:
        log.warning("the server's start_time %r is not an ISO 8601 instant with a zone (%s): the terrain is lit "
                    "by the fixed light", start_time, exc)
        return None
    return np.datetime64(start, "us")


def exercise_instant(start: np.datetime64, world_time_s: float) -> np.datetime64:
    """The UTC instant world_time_s world seconds after the exercise's start (exercise_start)."""
    return start + np.timedelta64(int(round(world_time_s * 1e6)), "us")


def _views(args) -> list[str]:
    if not getattr(args, "views", None):
        return ["chase" if args.chase else "cockpit"]
    views = [v.strip() for v in args.views.split(",") if v.strip()]
    bad = [v for v in views if v not in VIEWS]
    if bad or not views or len(set(views)) != len(views):
        raise InvalidArgument("--views", f"must be distinct names among {', '.join(VIEWS)}", value=args.views)
    return views


def achieved_fps(started_s) -> float | None:
    """Frames a wall second from the frames' start times (seconds, ascending): (n - 1) intervals
    over the time from the first start to the last; None for fewer than two frames (no interval).
    Counting n frames over the run's whole time overstates it: n frames span n - 1 intervals (2
    frames at --fps 1 read as 2 fps)."""
    if len(started_s) < 2 or started_s[-1] <= started_s[0]:
        return None
    return (len(started_s) - 1) / (started_s[-1] - started_s[0])


# How a frame's figures combine its views' (renderer.FrameStats, one per view): work and counts
# add up (the frame cost all of it), the rest is the frame's as a whole.
FRAME_STATS_SUMMED = ("frame_ms", "update_ms", "triangles", "vertices", "entities_drawn", "terrain_samples")
FRAME_STATS_MAX = ("levels_active", "eye_lift_m")


def frame_stats(per_view: dict) -> dict:
    """One frame's figures from its views' FrameStats dicts ({view: stats}, in drawing order): the
    sums of FRAME_STATS_SUMMED over the views, the largest of FRAME_STATS_MAX, ``rebased`` if any
    view rebased, ``mesh_rebuilds`` (a running count) the last view's."""
    views = list(per_view.values())
    out = dict(views[-1])
    for key in FRAME_STATS_SUMMED:
        out[key] = sum(v[key] for v in views)
    for key in FRAME_STATS_MAX:
        out[key] = max(v[key] for v in views)
    out["rebased"] = any(v["rebased"] for v in views)
    return out


def _frames(args, picture, target: int, renderer, out: Path, stop: threading.Event, undulation: float,
            start: np.datetime64 | None = None):
    """Render up to args.frames frames at most args.fps a wall second, each in every view (one
    renderer: the views share its terrain layer, centred on the followed agent), lit by the sun
    of the exercise's start plus the frame's world time (:func:`exercise_start`; the fixed light
    when ``start`` is None); (png paths, per-frame stats dicts: one a frame, whatever the views
    (:func:`frame_stats`: times and counts summed over them, each view's own under ``views`` when
    there are several), its start ``started_s`` and its end ``wall_s`` in seconds from the first
    frame's start)."""
    from PIL import Image

    from client.render.camera import heading_pitch_roll_deg, quat_to_matrix
    from client.render.entities import EntitySet
    from terrain.geodesy import ecef_to_geodetic

    info = picture.infos[target]
    frames, stats = [], []
    t_start = next_due = time.monotonic()
    for k in range(args.frames):
        if stop.is_set():
            break
        if not picture.alive:  # no frame of a world that is no longer streamed (stream_end says why)
            break
        t = picture.now_s()
        try:
            _, pos, quat = picture.state(t, ids=[target])
        except NotFound:
            print(f"frame {k:04d}: {info.name!r} left the exercise", flush=True)
            break
        started = time.monotonic() - t_start
        if start is not None:
            renderer.sun_time = exercise_instant(start, t)
        views = _views(args)
        layer = renderer.terrain_layer
        if hasattr(layer, "focus_lat_lon"):  # every view's terrain is centred on the agent
            layer.focus_lat_lon = tuple(float(v) for v in ecef_to_geodetic(pos[0])[:2])
        per_view = {}
        for view in views:
            chase = view == "chase"
            camera = follow_camera(pos[0], quat[0], int(info.kind), chase, args.fov_deg)
            image = renderer.render(camera, EntitySet.from_picture(picture, t, exclude=() if chase else (target,)))
            per_view[view] = renderer.stats.as_dict()
            path = out / (f"frame_{k:04d}.png" if len(views) == 1 else f"frame_{k:04d}_{view}.png")
            Image.fromarray(image).save(path)
            frames.append(str(path))
        s = frame_stats(per_view)
        lat, lon, h = (float(v) for v in ecef_to_geodetic(pos[0]))
        hdg, pitch, roll = heading_pitch_roll_deg(pos[0], quat_to_matrix(quat[0]))
        elapsed = time.monotonic() - t_start
        stats.append({**s, "world_time_s": t, "started_s": started, "wall_s": elapsed, "lat_deg": lat,
                      "lon_deg": lon, "alt_msl_m": h - undulation, "heading_deg": hdg,
                      **({"views": per_view} if len(views) > 1 else {})})
        span = started - stats[0]["started_s"]  # k intervals between frame starts (achieved_fps)
        fps = k / span if k and span > 0 else None
        print(f"frame {k:04d} t={t:8.2f} s  fps {'-' if fps is None else f'{fps:.2f}':>5}  {s['frame_ms']:6.1f} ms  "
              f"tri {s['triangles']:,}  samples {s['terrain_samples']:,}  levels {s['levels_active']}  "
              f"entities {s['entities_drawn']}  sun {s['sun_azimuth_deg']:.0f}/{s['sun_elevation_deg']:.0f}  "
              f"{info.name} {lat:.5f} {lon:.5f} {h - undulation:.0f} m hdg {hdg:.0f} pitch {pitch:.0f} "
              f"roll {roll:.0f}", flush=True)
        next_due = max(next_due + 1.0 / args.fps, time.monotonic())
        if k + 1 < args.frames:
            stop.wait(max(0.0, next_due - time.monotonic()))
    return frames, stats
