"""The gRPC terrain query service (``sortie.v1.TerrainService``).

A thin servicer: each RPC turns a decoded request (numpy arrays, see
:class:`server.grpc_common.PackedCodec`) into one :class:`terrain.terrain.Terrain`
call and its result back into response arrays. Validation of values (NaN,
ranges) is the Terrain's; the servicer checks only what belongs to the wire:
parallel arrays of equal, non-zero length, and the batch limits.

The limits are the ``MAX_*`` constants below (and
``server.grpc_common.MAX_MESSAGE_BYTES``); the proto comments state them and
GetMetadata returns them. A request over one fails with RESOURCE_EXHAUSTED
and a message naming the field. LineOfSight and IntersectSegments also keep to
a per-call cost over synthetic sources (:class:`terrain.terrain.RayBudget`:
raster posts and new procedural blocks, checked before any work and as the
rasters are made), and stop between chunks of their work once the caller's
deadline has passed or it has cancelled (:func:`stoppable_handler`).
"""

from __future__ import annotations

import logging
import math
import os
import threading
import time
from concurrent import futures
from pathlib import Path

import grpc
import numpy as np

from server.grpc_common import (
    MAX_MESSAGE_BYTES,
    Admission,
    CallStats,
    ManagedServer,
    PackedCodec,
    check_batch,
    listen_error,
    server_options,
    tolerant_decoder,
    unary_handler,
)
from sortie import __version__
from sortie.errors import DataFormatError, InvalidArgument, LimitExceeded, NotFound, SortieError
from sortie.v1 import terrain_pb2 as pb
from terrain.dem import file_identity
from terrain.profile import PROFILE_MAX_SAMPLES
from terrain.raster import STATUS_OK
from terrain.terrain import RayBudget

logger = logging.getLogger(__name__)

SERVICE_NAME = "sortie.v1.TerrainService"

# Per GetHeights: 16 MB request, about 25 ms of work over DEMs; over the procedural world each block
# a call generates costs 1.5-4 ms more, at most terrain.procedural.MAX_NEW_BLOCKS_PER_CALL of them.
MAX_HEIGHT_POINTS = 1_000_000
MAX_NORMAL_POINTS = 1_000_000  # per GetNormals: 33 MB response
MAX_PROFILE_SAMPLES = PROFILE_MAX_SAMPLES  # per GetProfile; enforced by terrain.profile
MAX_LOS_RAYS = 100_000  # per LineOfSight: each ray marches the terrain between its ends
MAX_SEGMENTS = 100_000  # per IntersectSegments
MAX_REGION_POSTS = 4 * 1024 * 1024  # per GetRegion: 20 MB response (float32 + class byte)
# The HeightEncoding a GetTile or GetRegion request may name (proto/sortie/v1/terrain.proto; unset
# is FLOAT32). proto3 enums are open: any other number arrives as it is, and is refused, where it
# was served as FLOAT32.
HEIGHT_ENCODINGS = (pb.HEIGHT_ENCODING_UNSPECIFIED, pb.HEIGHT_ENCODING_FLOAT32, pb.HEIGHT_ENCODING_ZSTD_CM)

# Threads answering calls; the numba kernels release the GIL, so batches from
# different clients run in parallel.
DEFAULT_MAX_WORKERS = min(32, (os.cpu_count() or 1) + 4)
# Threads one large height or normal batch is answered on (terrain.terrain._answer_into: a DEM's
# share of a batch of at least 2 x 16,384 points split in parts; the caller's thread is one of them).
QUERY_THREADS_MAX = 4
# Calls admitted at once per worker thread (running or queued); more are refused
# with RESOURCE_EXHAUSTED instead of queueing without bound (grpc_common.Admission).
ADMITTED_CALLS_PER_WORKER = 4
ADMISSION_WHAT = "terrain calls admitted at once, running or queued; sent again later, it may be admitted"
# Threads beyond the admitted calls' for what is not admitted: health checks, reflection, and
# refusals, so a busy service answers its health check at once (docker-compose's healthcheck).
SPARE_THREADS = 4
# Calls gRPC takes at once beyond the admitted ones (health, reflection, calls about to be
# refused): a backstop, refused by gRPC itself before their requests are read.
OTHER_CALLS_AT_ONCE = 64

HEIGHT_REFERENCE = ("heights are metres above mean sea level (each source's vertical_datum, "
                    "the EGM96 geoid for SRTM), not above the WGS84 ellipsoid")

# Terrain parameter names -> request field names, so errors name what the client sent.
_POINT_FIELDS = {"lat": "lat_deg", "lon": "lon_deg"}
_PROFILE_FIELDS = {"lat1": "start_lat_deg", "lon1": "start_lon_deg",
                   "lat2": "end_lat_deg", "lon2": "end_lon_deg"}
_RAY_NAMES = ("a_lat_deg", "a_lon_deg", "a_height_msl_m", "b_lat_deg", "b_lon_deg", "b_height_msl_m")
# As terrain.los names them in its errors.
_RAY_FIELDS = {"a_lat": "a_lat_deg", "a_lon": "a_lon_deg", "a_h": "a_height_msl_m",
               "b_lat": "b_lat_deg", "b_lon": "b_lon_deg", "b_h": "b_height_msl_m"}

# Terrain.describe() keys carried by TerrainSource fields of another name; a key
# matching no field goes to TerrainSource.details as text.
DESCRIBE_TO_FIELD = {"lat_min": "lat_min_deg", "lon_min": "lon_min_deg",
                     "lat_max": "lat_max_deg", "lon_max": "lon_max_deg"}


def limits_message() -> pb.Limits:
    return pb.Limits(
        max_height_points=MAX_HEIGHT_POINTS,
        max_normal_points=MAX_NORMAL_POINTS,
        max_profile_samples=MAX_PROFILE_SAMPLES,
        max_line_of_sight_rays=MAX_LOS_RAYS,
        max_segments=MAX_SEGMENTS,
        max_message_bytes=MAX_MESSAGE_BYTES,
        max_region_posts=MAX_REGION_POSTS,
    )


def source_message(description: dict) -> pb.TerrainSource:
    """One Terrain.describe() entry as a TerrainSource; unknown bounds are NaN."""
    msg = pb.TerrainSource()
    fields = pb.TerrainSource.DESCRIPTOR.fields_by_name
    for name in ("lat_min_deg", "lon_min_deg", "lat_max_deg", "lon_max_deg"):
        setattr(msg, name, math.nan)
    for key, value in description.items():
        name = DESCRIBE_TO_FIELD.get(key, key)
        if name in fields and name != "details" and value is not None:
            setattr(msg, name, type(getattr(msg, name))(value))
        elif value is not None:
            msg.details[key] = str(value)
    return msg


def metadata_message(terrain, dem_files=()) -> pb.GetMetadataResponse:
    """The GetMetadata response for a Terrain: its sources, datum and this server's limits;
    ``dem_files``: terrain.dem.file_identity dicts of the DEM files it was read from."""
    return pb.GetMetadataResponse(
        sources=[source_message(d) for d in terrain.describe()],
        height_reference=HEIGHT_REFERENCE,
        limits=limits_message(),
        server_version=__version__,
        dem_files=[pb.DemFile(**f) for f in dem_files],
    )


_NO_STATUS = np.zeros(0, np.uint8)


def sent_status(status: np.ndarray) -> np.ndarray:
    """A response's status as sent: empty when every point is OK (the proto's
    convention; :func:`received_status` restores it), which saves a byte a point."""
    if status.size and status.min() == STATUS_OK and status.max() == STATUS_OK:
        return _NO_STATUS
    return status


def received_status(status: np.ndarray, n: int) -> np.ndarray:
    """A response's status as received, expanded: n times POINT_STATUS_OK when sent empty."""
    if status.size == 0 and n:
        return np.full(n, STATUS_OK, np.uint8)
    return status


def file_stat(path) -> tuple | None:
    """(size, mtime_ns, inode, device) of a file, None where it cannot be read: what tells a
    file's bytes changed (a rewrite, a replacement by rename) without reading them. Taken before
    a service's DEMs are read, it is what :class:`DemIdentities` checks their hashes against."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return st.st_size, st.st_mtime_ns, st.st_ino, st.st_dev


def _identity(path, loaded: tuple | None) -> dict:
    """file_identity of a DEM file the service read, whose :func:`file_stat` was ``loaded`` when
    it started; the path alone (and its size then) where the file is gone or was changed since
    (its hash now would name bytes the service never served: a mismatch, said in the log)."""
    try:
        ident = file_identity(path)
    except (OSError, SortieError) as exc:
        logger.warning("DEM file %s: %s; named without its hash", path, exc)
        ident = None
    now = file_stat(path)
    if ident is not None and loaded is not None and now == loaded:
        return ident
    if ident is not None:
        logger.warning("DEM file %s changed since the service read it (size, modification time or inode "
                       "%s -> %s): its SHA-256 now is not that of the terrain served; named without it",
                       path, loaded, now)
    bare = {"path": str(Path(path).resolve())}
    if loaded is not None:
        bare["size_bytes"] = loaded[0]
    return bare


class DemIdentities:
    """The identities (path, size, SHA-256) of the DEM files a service read, as GetMetadata names
    them: each file's :func:`file_stat` (size, modification time, inode) as it was read
    (``loaded``: taken before reading, by the caller; None: taken now, the service starting right
    after reading them), and its bytes hashed in a background thread from then on, so start-up
    does not wait for a large DEM set to be hashed and the hash is of the bytes read, not of
    whatever the path holds when a client first asks. A file that changed between its stat and its
    hashing is named without a hash, and the log says so (:func:`_identity`)."""

    def __init__(self, paths, loaded=None):
        self._paths = list(paths)
        self._loaded = [file_stat(p) for p in self._paths] if loaded is None else list(loaded)
        if len(self._loaded) != len(self._paths):
            raise ValueError(f"{len(self._loaded)} file stats for {len(self._paths)} DEM files")
        self._identities: list[dict] = []
        self._thread = threading.Thread(target=self._hash, name="terrain-dem-hash", daemon=True)
        if self._paths:
            self._thread.start()

    def _hash(self) -> None:
        self._identities = [_identity(p, st) for p, st in zip(self._paths, self._loaded)]

    def get(self) -> list[dict]:
        """The identities, once hashed (waits for the background thread)."""
        if self._paths:
            self._thread.join()
        return self._identities


class TerrainServicer:
    """Converts decoded requests to Terrain calls and results to response arrays.

    Request arrays are read-only views of the received message (see
    :func:`serializers`). Point queries ask the Terrain to warm its sources'
    posts into the CPU caches first (``warm=True``): by the time a request has
    arrived, moving it through gRPC has evicted them, and for a large batch one
    streaming pass costs far less than missing on them point by point.
    """

    def __init__(self, terrain, dem_paths=(), dem_stats=None, query_threads: int = 1):
        self.terrain = terrain
        self.query_threads = int(query_threads)
        self._dem_files = DemIdentities(dem_paths, dem_stats)  # hashed in the background from now on
        self._metadata = None
        self._metadata_lock = threading.Lock()

    def GetMetadata(self, request: pb.GetMetadataRequest) -> pb.GetMetadataResponse:
        # Built at the first call, with the hashes taken from start-up on (DemIdentities).
        with self._metadata_lock:
            if self._metadata is None:
                self._metadata = metadata_message(self.terrain, self._dem_files.get())
            return self._metadata

    def GetHeights(self, request: dict) -> dict:
        check_batch(request, ("lat_deg", "lon_deg"), MAX_HEIGHT_POINTS)
        result = self.terrain.heights(request["lat_deg"], request["lon_deg"], warm=True, threads=self.query_threads)
        return {"height_msl_m": result.height_msl_m, "status": sent_status(result.status)}

    def GetNormals(self, request: dict) -> dict:
        check_batch(request, ("lat_deg", "lon_deg"), MAX_NORMAL_POINTS)
        result = self.terrain.normals(request["lat_deg"], request["lon_deg"], warm=True, threads=self.query_threads)
        n = result.normal_enu
        return {"normal_east": n[:, 0], "normal_north": n[:, 1], "normal_up": n[:, 2],
                "slope_deg": result.slope_deg, "status": sent_status(result.status)}

    def GetProfile(self, request: dict) -> dict:
        # n_samples (2 ..= MAX_PROFILE_SAMPLES) is checked by the Terrain before any work.
        result = self.terrain.profile(request["start_lat_deg"], request["start_lon_deg"],
                                      request["end_lat_deg"], request["end_lon_deg"], request["n_samples"])
        return {"lat_deg": result.lat_deg, "lon_deg": result.lon_deg, "distance_m": result.distance_m,
                "height_msl_m": result.height_msl_m, "status": sent_status(result.status)}

    # LineOfSight and IntersectSegments take ``check`` (see stoppable_handler): called between
    # chunks of the work, it raises CallEnded once the caller is gone.

    def LineOfSight(self, request: dict, check=None) -> dict:
        check_batch(request, _RAY_NAMES, MAX_LOS_RAYS)
        result = self.terrain.line_of_sight(*(request[name] for name in _RAY_NAMES), budget=RayBudget(check=check))
        return {"visible": result.visible, "status": sent_status(result.status)}

    def IntersectSegments(self, request: dict, check=None) -> dict:
        check_batch(request, _RAY_NAMES, MAX_SEGMENTS)
        result = self.terrain.intersect(*(request[name] for name in _RAY_NAMES), budget=RayBudget(check=check))
        n = result.normal_enu
        return {"hit": result.hit, "distance_m": result.distance_m, "lat_deg": result.lat_deg,
                "lon_deg": result.lon_deg, "height_msl_m": result.height_msl_m,
                "normal_east": n[:, 0], "normal_north": n[:, 1], "normal_up": n[:, 2],
                "status": sent_status(result.status)}


    # ------------------------------------------------------------ store streaming

    def _stores(self) -> list:
        """The TerrainStores of the terrain's StoreSources, in the terrain's priority order."""
        from terrain.store import StoreSource

        stores = [source.store for source in self.terrain.sources if isinstance(source, StoreSource)]
        if not stores:
            raise NotFound("this terrain service has no terrain store (serve it with --store)")
        return stores

    def GetTile(self, request: pb.GetTileRequest) -> pb.HeightGrid:
        # The first store (in the terrain's order) holding the cell answers, as heights do.
        check_height_encoding(request.encoding)
        cell_id = int(request.cell_id)
        missing = []
        for store in self._stores():
            try:
                level, raster = store.cell_raster(cell_id)
            except NotFound as exc:
                missing.append(str(exc))
                continue
            return height_grid(store, raster, level, cell_id, request.encoding)
        raise NotFound(missing[0] if len(missing) == 1 else
                       f"cell_id: no store holds cell {cell_id} ({'; '.join(missing)})")

    def GetRegion(self, request: pb.GetRegionRequest) -> pb.HeightGrid:
        """The level's posts over the box from every store on one lattice: the first store (in
        the terrain's order) holding part of the box sets the lattice (its level's spacing and
        cell depth), and each later store on the same lattice at that level fills the posts the
        stores before it leave outside (:func:`merge_store_rasters`; the first store's data wins
        where two hold a post, as heights take the first source). A store whose level lies on
        another lattice is not merged (its posts would not line up)."""
        from terrain.profile import check_point

        check_height_encoding(request.encoding)
        stores = self._stores()
        levels = max(store.levels for store in stores)
        if request.level >= levels:
            raise InvalidArgument("level", f"must be below the store's {levels} levels", value=request.level)
        # Each corner checked on its own, so the error names the request's field (not lat[0]).
        check_point("lat_min_deg", request.lat_min_deg, "lon_min_deg", request.lon_min_deg)
        check_point("lat_max_deg", request.lat_max_deg, "lon_max_deg", request.lon_max_deg)
        lat = np.array([request.lat_min_deg, request.lat_max_deg])
        lon = np.array([request.lon_min_deg, request.lon_max_deg])
        if not lat[0] <= lat[1]:
            raise InvalidArgument("lat_min_deg", "the box is inverted: above lat_max_deg",
                                  value=(float(lat[0]), float(lat[1])))
        if not lon[0] <= lon[1]:
            raise InvalidArgument("lon_min_deg", "the box is inverted: east of lon_max_deg (a box across the "
                                  "antimeridian takes lon_max_deg above 180)", value=(float(lon[0]), float(lon[1])))
        level = request.level
        first, lattice, rasters = None, None, []
        for store in stores:
            if level >= store.levels:
                continue
            key = (store.spacing_deg(level), store.cell_depth(level))
            if lattice is not None and key != lattice:
                continue
            dlat, dlon = key[0]
            posts = ((lat[1] - lat[0]) / dlat + 2) * ((lon[1] - lon[0]) / dlon + 2)
            if posts > MAX_REGION_POSTS:
                raise LimitExceeded("region_posts", int(posts), MAX_REGION_POSTS)
            raster = store.raster(level, float(lat[0]), float(lon[0]), float(lat[1]), float(lon[1]))
            if raster is None:
                continue
            if first is None:
                first, lattice = store, key
            rasters.append((store, raster))
        if first is None:
            raise NotFound(f"no region of the {'store' if len(stores) == 1 else f'{len(stores)} stores'} "
                           f"overlaps the box at level {level}")
        raster = merge_store_rasters([r for _, r in rasters])
        return height_grid(first, raster, level, 0, request.encoding,
                           max_error_m=max(st.max_error_m for st, _ in rasters))


def merge_store_rasters(rasters: list):
    """Store rasters of one level's lattice (equal spacing, posts on the same lattice lines; each
    cropped to where its store has data) as one Raster over all of them: each post from the first
    raster that holds it (not NaN), NaN where none does. One raster is returned as it is."""
    from terrain.raster import Georef, Raster

    if len(rasters) == 1:
        return rasters[0]
    g0 = rasters[0].georef
    # Integer offsets of each raster's first post from the first raster's (same lattice: whole
    # numbers up to rounding). Longitudes stay as the stores unrolled them: every store unrolls
    # the box's columns from the same western edge.
    offs = [(int(round((r.georef.y0 - g0.y0) / g0.dy)), int(round((r.georef.x0 - g0.x0) / g0.dx))) for r in rasters]
    r0 = min(o[0] for o in offs)
    c0 = min(o[1] for o in offs)
    r1 = max(o[0] + r.shape[0] for o, r in zip(offs, rasters))
    c1 = max(o[1] + r.shape[1] for o, r in zip(offs, rasters))
    heights = np.full((r1 - r0, c1 - c0), np.nan, np.float32)
    filled = np.zeros(heights.shape, bool)
    for (dr, dc), r in zip(offs, rasters):
        rows, cols = slice(dr - r0, dr - r0 + r.shape[0]), slice(dc - c0, dc - c0 + r.shape[1])
        take = np.isnan(heights[rows, cols]) & ~np.isnan(r.heights)
        heights[rows, cols][take] = r.heights[take]
        if r.filled is not None:
            filled[rows, cols][take] = r.filled[take].astype(bool)
    georef = Georef(g0.crs, g0.x0 + c0 * g0.dx, g0.y0 + r0 * g0.dy, g0.dx, g0.dy)
    return Raster(heights, georef, name=rasters[0].name, vertical_datum=rasters[0].vertical_datum,
                  filled=filled if filled.any() else None, source=rasters[0].source,
                  meta={**rasters[0].meta, "stores": len(rasters)})


def check_height_encoding(encoding: int) -> None:
    """InvalidArgument naming ``encoding`` unless it is one of HEIGHT_ENCODINGS."""
    if encoding not in HEIGHT_ENCODINGS:
        raise InvalidArgument("encoding", "must be one of " + ", ".join(
            f"{pb.HeightEncoding.Name(e)} ({e})" for e in HEIGHT_ENCODINGS), value=encoding)


def height_grid(store, raster, level: int, cell_id: int, encoding: int = pb.HEIGHT_ENCODING_FLOAT32,
                max_error_m: float | None = None) -> pb.HeightGrid:
    """A store raster (row 0 south) as the wire's HeightGrid (row 0 north); ``max_error_m``: the
    bound its heights keep (None: the store's; a grid merged from several stores, the largest)."""
    g = raster.georef
    rows, cols = raster.shape
    heights = np.ascontiguousarray(raster.heights[::-1])
    classes = np.ones(raster.shape, np.uint8)
    classes[np.isnan(raster.heights)] = 0
    if raster.filled is not None:
        classes[raster.filled.astype(bool)] = 2
    grid = pb.HeightGrid(level=level, depth=store.cell_depth(level), rows=rows, cols=cols,
                         lat_north_deg=g.y0 + (rows - 1) * g.dy, lon_west_deg=(g.x0 + 180.0) % 360.0 - 180.0,
                         dlat_deg=g.dy, dlon_deg=g.dx, post_class=np.ascontiguousarray(classes[::-1]).tobytes(),
                         max_error_m=store.max_error_m if max_error_m is None else max_error_m, cell_id=cell_id)
    check_height_encoding(encoding)
    if encoding == pb.HEIGHT_ENCODING_ZSTD_CM:
        import zstandard

        grid.heights_zstd = encode_heights_zstd_cm(heights)
        grid.post_class = zstandard.ZstdCompressor(level=3).compress(grid.post_class)
    else:
        grid.heights_f32 = heights.astype("<f4").tobytes()
    return grid


def encode_heights_zstd_cm(heights: np.ndarray) -> bytes:
    """HEIGHT_ENCODING_ZSTD_CM of a (rows, cols) grid of metres (NaN: 0)."""
    import zstandard

    cm = np.round(np.nan_to_num(np.asarray(heights, np.float64), nan=0.0) * 100.0).astype(np.int64)
    d = np.diff(cm, axis=1, prepend=0).astype("<i4")
    return zstandard.ZstdCompressor(level=3).compress(d.tobytes())


def decode_heights_zstd_cm(data: bytes, rows: int, cols: int) -> np.ndarray:
    """Inverse of :func:`encode_heights_zstd_cm`: float64 metres (rows, cols)."""
    import zstandard

    d = np.frombuffer(zstandard.ZstdDecompressor().decompress(data, max_output_size=4 * rows * cols), "<i4")
    if d.size != rows * cols:
        raise DataFormatError(f"heights_zstd: {d.size} heights for {rows} x {cols} posts")
    return np.cumsum(d.reshape(rows, cols).astype(np.int64), axis=1) / 100.0


# RPC name -> (request class, response class, parameter -> field names). Every
# RPC but GetMetadata, GetTile and GetRegion goes through PackedCodec in both directions.
RPCS = {
    "GetMetadata": (pb.GetMetadataRequest, pb.GetMetadataResponse, {}),
    "GetHeights": (pb.GetHeightsRequest, pb.GetHeightsResponse, _POINT_FIELDS),
    "GetNormals": (pb.GetNormalsRequest, pb.GetNormalsResponse, _POINT_FIELDS),
    "GetProfile": (pb.GetProfileRequest, pb.GetProfileResponse, _PROFILE_FIELDS),
    "LineOfSight": (pb.LineOfSightRequest, pb.LineOfSightResponse, _RAY_FIELDS),
    "IntersectSegments": (pb.IntersectSegmentsRequest, pb.IntersectSegmentsResponse, _RAY_FIELDS),
    "GetTile": (pb.GetTileRequest, pb.HeightGrid, {}),
    "GetRegion": (pb.GetRegionRequest, pb.HeightGrid, {}),
}
PACKED_RPCS = frozenset(RPCS) - {"GetMetadata", "GetTile", "GetRegion"}


def serializers(rpc: str):
    """(request serializer, request deserializer, response serializer, response deserializer).

    The response deserializer (a client's) expands an empty status to every
    point OK (see :func:`received_status`).
    """
    request_class, response_class, _ = RPCS[rpc]
    if rpc not in PACKED_RPCS:
        return (request_class.SerializeToString, request_class.FromString,
                response_class.SerializeToString, response_class.FromString)
    # The server only reads requests: their arrays are views of the received
    # bytes. The client gets copies of the response arrays, which are its own.
    req, resp = PackedCodec(request_class, copy=False), PackedCodec(response_class)
    if "status" not in response_class.DESCRIPTOR.fields_by_name:
        return req.encode, req.decode, resp.encode, resp.decode
    # The response's first per-point field (never empty in an answer) counts the points.
    count_field = next(fd.name for fd in response_class.DESCRIPTOR.fields if fd.is_repeated and fd.name != "status")

    def decode_response(data: bytes) -> dict:
        response = resp.decode(data)
        response["status"] = received_status(response["status"], len(response[count_field]))
        return response

    return req.encode, req.decode, resp.encode, decode_response


# RPCs whose work stops once the caller is gone (their servicer methods take ``check``).
STOPPABLE_RPCS = frozenset({"LineOfSight", "IntersectSegments"})


class CallEnded(BaseException):
    """The caller of a call in progress is gone (its deadline passed, or it cancelled): raised by
    :func:`call_check`'s check to unwind the call's work. A BaseException, so that no handler
    of failures (grpc_common.unary_handler's ``except Exception``) reports it as one."""

    def __init__(self, code: grpc.StatusCode, why: str):
        super().__init__(why)
        self.code = code


def call_check(context):
    """A check for :class:`terrain.terrain.RayBudget`: raises CallEnded (DEADLINE_EXCEEDED once the
    call's deadline has passed, CANCELLED when the client cancelled or went away) and returns
    otherwise."""
    def check() -> None:
        remaining = context.time_remaining()
        if remaining is not None and remaining <= 0.0:
            raise CallEnded(grpc.StatusCode.DEADLINE_EXCEEDED, "the call's deadline passed; its work was stopped")
        if not context.is_active():
            raise CallEnded(grpc.StatusCode.CANCELLED, "the call was cancelled; its work was stopped")

    return check


class _AbortSeen:
    """A ServicerContext that remembers the code it was aborted with (for the call's stats)."""

    def __init__(self, context):
        self._context = context
        self.code = None

    def abort(self, code, details):
        self.code = code
        self._context.abort(code, details)

    def __getattr__(self, name):
        return getattr(self._context, name)


def stoppable_handler(name: str, method, field_names, stats: CallStats | None = None):
    """grpc_common.unary_handler for ``method(request, check)``: ``check`` (:func:`call_check`)
    raises CallEnded once the caller is gone, which ends the call with DEADLINE_EXCEEDED or
    CANCELLED (the client has that status already; the point is that the work stops) and counts
    it under that code; everything else is unary_handler's."""
    short = name.rsplit("/", 1)[-1]

    def behaviour(request, context):
        t0 = time.perf_counter()
        seen = _AbortSeen(context)
        check = call_check(context)
        code = None
        try:
            return unary_handler(name, lambda req: method(req, check), field_names)(request, seen)
        except CallEnded as ended:
            code = ended.code
            logger.debug("%s: %s", name, ended)
            context.abort(ended.code, f"{short}: {ended}")
        finally:
            code = seen.code if seen.code is not None else code
            if stats is not None:
                stats.record(short, time.perf_counter() - t0, None if code is None else code.name)

    return behaviour


def method_handlers(servicer: TerrainServicer, stats: CallStats | None = None,
                    admission: Admission | None = None) -> dict:
    """gRPC method handlers for every RPC of the service, fast-path codecs included;
    ``stats`` counts the calls (the service's metrics); ``admission`` (if given) admits them."""
    handlers = {}
    for rpc, (_, _, field_names) in RPCS.items():
        _, request_deserializer, response_serializer, _ = serializers(rpc)
        make = stoppable_handler if rpc in STOPPABLE_RPCS else unary_handler
        name = f"{SERVICE_NAME}/{rpc}"
        behaviour = make(name, getattr(servicer, rpc), field_names, stats)
        if admission is not None:
            behaviour = admission.wrap(name, behaviour, stats)
        handlers[rpc] = grpc.unary_unary_rpc_method_handler(
            behaviour,
            request_deserializer=tolerant_decoder(request_deserializer),
            response_serializer=response_serializer,
        )
    return handlers


def create_server(terrain, address: str = "127.0.0.1:0", max_workers: int = DEFAULT_MAX_WORKERS,
                  dem_paths=(), dem_stats=None, query_threads: int = 1) -> tuple[ManagedServer, int]:
    """A terrain server bound to ``address`` ("host:port", port 0 for any free one);
    ``query_threads``: threads one large GetHeights or GetNormals batch is answered on (QUERY_THREADS_MAX);
    ``dem_paths``, the DEM files ``terrain`` was read from, are named with their SHA-256
    in GetMetadata (a recording over the service keeps them), hashed from start-up on and checked
    against ``dem_stats`` (their :func:`file_stat` before they were read; None: taken now).

    Returns the server, not yet started (call ``start()``), and the bound port;
    ``server.stats`` (grpc_common.CallStats) counts its calls, ``server.admission``
    (grpc_common.Admission) admits them: ADMITTED_CALLS_PER_WORKER x ``max_workers`` at once,
    ``max_workers`` of them working. Health (SERVING for "" and sortie.v1.TerrainService once
    started) and reflection are registered, outside the admission, on SPARE_THREADS threads of
    their own: a busy service answers them at once.
    """
    admission = Admission(ADMITTED_CALLS_PER_WORKER * max_workers, max_workers, ADMISSION_WHAT)
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=admission.limit + SPARE_THREADS, thread_name_prefix="terrain-rpc"),
        options=server_options(),
        maximum_concurrent_rpcs=admission.limit + OTHER_CALLS_AT_ONCE,
    )
    stats = CallStats()
    server.add_registered_method_handlers(
        SERVICE_NAME, method_handlers(TerrainServicer(terrain, dem_paths, dem_stats, query_threads), stats, admission))
    managed = ManagedServer(server, (SERVICE_NAME,))
    managed.stats = stats
    managed.admission = admission
    try:
        port = server.add_insecure_port(address)
    except RuntimeError as exc:  # in use, or no such interface: with the system's reason
        raise listen_error(address, exc) from exc
    logger.info("terrain service bound to %s (port %d), %d workers", address, port, max_workers)
    return managed, port
