"""Client library for the terrain query service (``sortie.v1.TerrainService``).

:class:`TerrainClient` answers the same queries as :class:`terrain.terrain.Terrain`
with the same result types, so a bot, a client or the server can swap an
in-process Terrain for a remote one. Requests and responses go through the
numpy wire codec (:class:`server.grpc_common.PackedCodec`): no per-value Python
objects on either side. Failures arrive as :mod:`sortie.errors` exceptions
carrying the server's message ("lat_deg[7]: must be within [-90, 90] degrees").

Argument order is always (lat, lon), degrees WGS84; heights are metres above
mean sea level.

Replicas. ``TerrainClient("host1:port,host2:port")`` spreads its calls over
several replicas of one terrain service through a single gRPC channel: the
addresses become one static target (``ipv4:a:p,b:p``; host names are resolved
once, here, and a name with several addresses contributes them all), with
gRPC's ``round_robin`` policy, client-side health checking (a replica leaves
the rotation as soon as its health says NOT_SERVING, i.e. when it starts to
drain on SIGTERM) and a retry policy for UNAVAILABLE (a replica that died
with calls in flight: they are sent again to another one); a call gRPC does
not retry because the dead replica had begun to answer, or that a stopping
replica cancelled, is sent once more by the client. Terrain queries are read-only, so a repeated call is harmless.
See :func:`replica_service_config` for the numbers and docs/DEPLOYMENT.md for
what was measured. One address behaves as it always has: a plain channel, no
retries of UNAVAILABLE.

Sharing. All the threads of a client together keep at most ``max_calls_in_flight`` calls in
flight (chunks of a split batch included), lowered to the service's admission limit (times
the replicas) once a refusal names it; a call the service refuses for want of room (its
admission, RESOURCE_EXHAUSTED naming ``concurrent_calls``, or gRPC's own "Concurrent RPC limit
exceeded!") is sent again after a backoff, at most ADMISSION_RETRY_MAX_ATTEMPTS attempts, and
then fails as LimitExceeded naming the limit. Before, one call of 20,000 rays took 3 of a
service's 24 admission slots at once, and 12 threads sharing a client had 7 of their calls
refused as a bare ServiceError.
"""

from __future__ import annotations

import ipaddress
import json
import random
import re
import socket
import threading
import time
from collections import deque
from dataclasses import dataclass

import grpc
import numpy as np

from server.grpc_common import ADMISSION_FIELD, MAX_MESSAGE_BYTES, channel_options
from server.terrain_service import DESCRIBE_TO_FIELD, MAX_HEIGHT_POINTS, RPCS, SERVICE_NAME, serializers
from sortie.errors import (DataFormatError, InvalidArgument, LimitExceeded, NotFound, PermissionDenied, SortieError,
                           Unauthenticated)
from sortie.v1 import terrain_pb2 as pb
from terrain.terrain import HeightResult, LosResult, NormalResult, ProfileResult, SegmentResult
from terrain.profile import check_n_samples
from terrain.validate import as_1d_f64

DEFAULT_TIMEOUT_S = 30.0
# Batches larger than these are split into chunks and the chunks pipelined, at
# most MAX_IN_FLIGHT at a time, so a batch of any size fits the service's
# per-call limits. Points go in chunks as large as the service allows: a call
# costs about 0.3 ms of gRPC overhead, more than a 32k-point chunk's work
# (measured on loopback: 100k heights in 4 chunks took 1.3x as long as in one).
# A ray costs the server about 5 us, so ray chunks are small enough for the
# server's threads to march several at once and large enough to hide the overhead.
CHUNK_POINTS = MAX_HEIGHT_POINTS
CHUNK_RAYS = 8_192
MAX_IN_FLIGHT = 4
# Calls one client keeps in flight at once, all its threads together, until a refusal names the
# service's admission limit (then that limit times the replicas, if lower). A service admits
# server.terrain_service.ADMITTED_CALLS_PER_WORKER (4) calls per worker thread, and has
# min(32, cores + 4) of them by default: at least 20 calls, which 16 leave room in for another
# client; 16 keep four split batches (MAX_IN_FLIGHT chunks each) in flight at once.
MAX_CALLS_IN_FLIGHT = 16
# Attempts of a call refused for want of room (the service's admission, or gRPC's own limit),
# the n-th retry after the replicas' backoff below (RETRY_*: a random wait in [0, min(0.05 x
# 2^(n-1), 1)] s, gRFC A6's formula; "full jitter", so that clients refused together do not come
# back together): at most 3.55 s of waiting in all, 1.8 s on average.
ADMISSION_RETRY_MAX_ATTEMPTS = 8
# gRPC's refusal of a call over a server's maximum_concurrent_rpcs (grpc/_server.py, grpc.aio's
# server): how a terrain service refused its admission before it named the limit, and how it
# still refuses a flood beyond its OTHER_CALLS_AT_ONCE.
GRPC_CONCURRENCY_REFUSAL = "Concurrent RPC limit exceeded!"

# Retries of a call to replicas (gRFC A6 retryPolicy): up to RETRY_MAX_ATTEMPTS
# attempts in all, the n-th retry after a random wait in [0, min(initial x
# multiplier^(n-1), max)] seconds: at most 0.75 s of waiting when every replica
# is down, 25 ms on average before the first retry (to a live replica). The
# deadline (timeout_s) covers every attempt.
RETRY_MAX_ATTEMPTS = 5
RETRY_INITIAL_BACKOFF_S = 0.05
RETRY_MAX_BACKOFF_S = 1.0
RETRY_BACKOFF_MULTIPLIER = 2.0
# A request is kept for a retry only while it fits this buffer: gRPC's default, 256 KiB
# a call, is less than a 16,384-point height batch (such calls failed when a replica was
# killed); requests are at most MAX_MESSAGE_BYTES.
RETRY_BUFFER_PER_CALL_BYTES = MAX_MESSAGE_BYTES


class ServiceError(SortieError):
    """A call failed for a reason other than the request's content (unavailable,
    deadline exceeded, internal error); ``code`` is the grpc.StatusCode."""

    def __init__(self, code, message: str):
        super().__init__(f"{code.name}: {message}")
        self.code = code


_INVALID = re.compile(r"^(?P<field>[A-Za-z_][\w.]*)(?:\[(?P<index>\d+)\])?: (?P<message>.*)$", re.S)
# A limit's field may say what it counts: "segments (procedural raster posts)".
_LIMIT = re.compile(r"^(?P<field>[A-Za-z_][\w.]*(?: \([^()]*\))?): (?P<size>\d+) exceeds the limit of (?P<limit>\d+)"
                    r"(?: \((?P<why>.*)\))?$", re.S)


def admission_refusal(error: grpc.RpcError) -> int | None:
    """The admission limit a refusal of a call for want of room names (0: gRPC's own refusal,
    which names none); None when ``error`` is no such refusal (a batch over its limit, a message
    too large: sending it again would not help)."""
    if error.code() != grpc.StatusCode.RESOURCE_EXHAUSTED:
        return None
    details = error.details() or ""
    if details == GRPC_CONCURRENCY_REFUSAL:
        return 0
    m = _LIMIT.match(details)
    return int(m["limit"]) if m and m["field"] == ADMISSION_FIELD else None


def retry_backoff_s(retry: int) -> float:
    """The wait before the ``retry``-th retry (1, 2, ...): uniform in [0, min(RETRY_INITIAL_BACKOFF_S
    x RETRY_BACKOFF_MULTIPLIER^(retry-1), RETRY_MAX_BACKOFF_S)] (gRFC A6; full jitter)."""
    cap = min(RETRY_INITIAL_BACKOFF_S * RETRY_BACKOFF_MULTIPLIER ** (retry - 1), RETRY_MAX_BACKOFF_S)
    return random.uniform(0.0, cap)


class CallSlots:
    """The calls a client has in flight at once, all its threads together: at most ``limit``,
    which :meth:`lower` may lower (never below 1). A slot is released when its call ends,
    from whichever thread gRPC ends it on, so a thread waiting for one while its own split
    batch is in flight cannot wait on itself. Thread-safe."""

    def __init__(self, limit: int):
        self.limit = limit
        self.in_flight = 0
        self._free = threading.Condition()

    def acquire(self, timeout_s: float | None) -> None:
        """Take a slot; ServiceError(DEADLINE_EXCEEDED) when none frees within ``timeout_s``."""
        with self._free:
            if not self._free.wait_for(lambda: self.in_flight < self.limit, timeout_s):
                raise ServiceError(grpc.StatusCode.DEADLINE_EXCEEDED,
                                   f"none of the client's {self.limit} calls in flight ended within {timeout_s} s")
            self.in_flight += 1

    def release(self, _call=None) -> None:
        """Give a slot back (a gRPC future's done callback, hence the argument)."""
        with self._free:
            self.in_flight -= 1
            self._free.notify()

    def lower(self, limit: int) -> None:
        with self._free:
            self.limit = max(1, min(self.limit, limit))


def error_from_rpc(error: grpc.RpcError) -> SortieError:
    """The sortie.errors exception for a failed call; its text is the server's message."""
    code, details = error.code(), error.details() or ""
    if code == grpc.StatusCode.INVALID_ARGUMENT:
        m = _INVALID.match(details)
        if m:
            index = int(m["index"]) if m["index"] is not None else None
            return InvalidArgument(m["field"], m["message"], index=index)
        return InvalidArgument("request", details)
    if code == grpc.StatusCode.RESOURCE_EXHAUSTED:
        m = _LIMIT.match(details)
        if m:
            return LimitExceeded(m["field"], int(m["size"]), int(m["limit"]), m["why"] or "")
    if code == grpc.StatusCode.NOT_FOUND:
        return NotFound(details)
    if code == grpc.StatusCode.UNAUTHENTICATED:
        return Unauthenticated(details)
    if code == grpc.StatusCode.PERMISSION_DENIED:
        return PermissionDenied(details)
    if code == grpc.StatusCode.FAILED_PRECONDITION:
        return DataFormatError(details)
    return ServiceError(code, details)


_FIELD_TO_DESCRIBE = {field: key for key, field in DESCRIBE_TO_FIELD.items()}
# The keys every source dict has (besides its details), in proto order.
SOURCE_KEYS = tuple(_FIELD_TO_DESCRIBE.get(fd.name, fd.name)
                    for fd in pb.TerrainSource.DESCRIPTOR.fields if fd.name != "details")


def metadata_dict(msg: pb.GetMetadataResponse) -> dict:
    """GetMetadata as plain Python.

    {"sources": [dict per source, keyed like Terrain.describe(): name, kind,
    source, crs, lat_min, lon_min, lat_max, lon_max (degrees), rows, cols,
    spacing_east_m, spacing_north_m, vertical_datum, filled_posts, then the
    source's details as text], "height_reference": str, "limits": {Limits
    field: int}, "server_version": str, "dem_files": [{"path", "size_bytes", "sha256"}
    per DEM file the service read, in the order given]}.
    """
    sources = []
    for s in msg.sources:
        entry = {key: getattr(s, DESCRIBE_TO_FIELD.get(key, key)) for key in SOURCE_KEYS}
        entry.update(sorted(s.details.items()))
        sources.append(entry)
    return {
        "sources": sources,
        "height_reference": msg.height_reference,
        "limits": {fd.name: getattr(msg.limits, fd.name) for fd in msg.limits.DESCRIPTOR.fields},
        "server_version": msg.server_version,
        "dem_files": [{"path": f.path, "size_bytes": f.size_bytes, "sha256": f.sha256} for f in msg.dem_files],
    }


def replica_service_config() -> dict:
    """The gRPC service config of a channel to several replicas: round robin over the
    healthy ones, UNAVAILABLE retried (see the RETRY_* constants)."""
    return {
        "loadBalancingConfig": [{"round_robin": {}}],
        "healthCheckConfig": {"serviceName": SERVICE_NAME},
        "methodConfig": [{
            "name": [{"service": SERVICE_NAME}],
            "retryPolicy": {
                "maxAttempts": RETRY_MAX_ATTEMPTS,
                "initialBackoff": f"{RETRY_INITIAL_BACKOFF_S}s",
                "maxBackoff": f"{RETRY_MAX_BACKOFF_S}s",
                "backoffMultiplier": RETRY_BACKOFF_MULTIPLIER,
                "retryableStatusCodes": ["UNAVAILABLE"],
            },
        }],
    }


def _split_address(entry: str) -> tuple[str, int]:
    """("host", port) of "host:port" or "[v6]:port"; InvalidArgument naming the entry."""
    host, sep, port = entry.rpartition(":")
    bare = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    if (not sep or not bare or (":" in bare and bare == host) or not (port.isascii() and port.isdigit())
            or not 1 <= int(port) <= 65535):  # ASCII digits: str.isdigit() takes "²" and "１２３" too
        raise InvalidArgument("address", 'each replica must be "host:port" with a port in [1, 65535] '
                                         '("[::1]:50051" for IPv6)', value=entry)
    return bare, int(port)


def _ips(host: str, port: int) -> dict[int, list[str]]:
    """{address family: [IP, ...]} of a literal IP or a host name (resolved now)."""
    try:
        ip = ipaddress.ip_address(host)
        return {socket.AF_INET if ip.version == 4 else socket.AF_INET6: [str(ip)]}
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(host, port, proto=socket.IPPROTO_TCP)
    except socket.gaierror as exc:
        raise ServiceError(grpc.StatusCode.UNAVAILABLE, f"cannot resolve terrain replica {host!r}: {exc}") from None
    out: dict[int, list[str]] = {}
    for family, _, _, _, sockaddr in infos:
        if family in (socket.AF_INET, socket.AF_INET6) and sockaddr[0] not in out.get(family, []):
            out.setdefault(family, []).append(sockaddr[0])
    return out


def replica_target(addresses: str) -> str:
    """The gRPC target of a comma-separated list of "host:port" replicas:
    ``ipv4:ip:port,...`` (or ``ipv6:[ip]:port,...`` when some replica has no IPv4
    address). Host names are resolved now; a name with several addresses gives
    them all. InvalidArgument for a malformed entry or a list mixing replicas
    reachable only over IPv4 with some reachable only over IPv6."""
    entries = [e.strip() for e in addresses.split(",")]
    if any(not e for e in entries):
        raise InvalidArgument("address", "empty entry in the list of replicas", value=addresses)
    resolved = [(port, _ips(host, port)) for host, port in map(_split_address, entries)]
    for family, scheme in ((socket.AF_INET, "ipv4"), (socket.AF_INET6, "ipv6")):
        if all(family in ips for _, ips in resolved):
            targets = [f"{ip}:{port}" if family == socket.AF_INET else f"[{ip}]:{port}"
                       for port, ips in resolved for ip in ips[family]]
            return f"{scheme}:" + ",".join(dict.fromkeys(targets))
    raise InvalidArgument("address", "the replicas must share an address family (all IPv4 or all IPv6)",
                          value=addresses)


class TerrainClient:
    """A connection to a terrain service; use as a context manager or call close().

    address: "host:port", or "host:port,host:port,..." for replicas of one
    terrain (round robin, retries; see the module docstring). timeout_s:
    deadline of each call, seconds (gRPC's retries included; a call sent again
    after UNAVAILABLE or a refusal gets a deadline of its own; the wait for a
    slot of ``max_calls_in_flight`` is bounded by it too). Methods take (n,)
    array-likes (scalars are one point) and return the Terrain's result
    dataclasses with numpy arrays. Thread-safe: many threads (bots) may share
    one client, which keeps at most ``max_calls_in_flight`` calls in flight for
    all of them (``max_in_flight``: chunks of one split batch) and sends a call
    the service refused for want of room again later (see the module docstring).
    ``target`` is the channel's gRPC target; ``resent_calls`` counts the calls
    a client of replicas sent again after UNAVAILABLE or CANCELLED, and
    ``retried_refusals`` those sent again after a refusal for want of room.
    """

    def __init__(self, address: str, timeout_s: float = DEFAULT_TIMEOUT_S, chunk_points: int = CHUNK_POINTS,
                 chunk_rays: int = CHUNK_RAYS, max_in_flight: int = MAX_IN_FLIGHT,
                 max_calls_in_flight: int = MAX_CALLS_IN_FLIGHT):
        for name, value in (("chunk_points", chunk_points), ("chunk_rays", chunk_rays),
                            ("max_in_flight", max_in_flight), ("max_calls_in_flight", max_calls_in_flight)):
            if not (isinstance(value, int) and value >= 1):
                raise InvalidArgument(name, "must be an integer >= 1", value=value)
        self.address = address
        self.timeout_s = timeout_s
        self.chunk_points = chunk_points
        self.chunk_rays = chunk_rays
        self.max_in_flight = max_in_flight
        self.slots = CallSlots(max_calls_in_flight)
        self.replicated = "," in address
        self.resent_calls = 0
        self.retried_refusals = 0
        self._count_lock = threading.Lock()
        self._replicas = 1
        if self.replicated:
            self.target = replica_target(address)
            self._replicas = len(self.target.split(","))
            options = channel_options() + [
                ("grpc.service_config", json.dumps(replica_service_config())),
                ("grpc.enable_retries", 1),
                ("grpc.per_rpc_retry_buffer_size", RETRY_BUFFER_PER_CALL_BYTES),
            ]
        else:
            self.target, options = address, channel_options()
        self._channel = grpc.insecure_channel(self.target, options=options)
        self._calls = {}
        for rpc in RPCS:
            request_serializer, _, _, response_deserializer = serializers(rpc)
            self._calls[rpc] = self._channel.unary_unary(
                f"/{SERVICE_NAME}/{rpc}",
                request_serializer=request_serializer,
                response_deserializer=response_deserializer,
            )

    def __enter__(self) -> TerrainClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._channel.close()

    def wait_ready(self, timeout_s: float | None = None) -> None:
        """Block until the channel is connected; ServiceError(UNAVAILABLE) after timeout_s."""
        try:
            grpc.channel_ready_future(self._channel).result(
                timeout=self.timeout_s if timeout_s is None else timeout_s)
        except grpc.FutureTimeoutError:
            raise ServiceError(grpc.StatusCode.UNAVAILABLE, f"no terrain service at {self.address}") from None

    def _send(self, rpc: str, request):
        """One call, in a slot of the client's (:class:`CallSlots`)."""
        self.slots.acquire(self.timeout_s)
        try:
            return self._calls[rpc](request, timeout=self.timeout_s)
        finally:
            self.slots.release()

    def _send_future(self, rpc: str, request) -> grpc.Future:
        """One call sent, not waited for, in a slot of the client's given back when it ends."""
        self.slots.acquire(self.timeout_s)
        try:
            future = self._calls[rpc].future(request, timeout=self.timeout_s)
        except BaseException:
            self.slots.release()
            raise
        future.add_done_callback(self.slots.release)
        return future

    def _count(self, counter: str) -> None:
        with self._count_lock:
            setattr(self, counter, getattr(self, counter) + 1)

    def _call(self, rpc: str, request, failed: grpc.RpcError | None = None):
        """The answer to ``request``, sent now unless ``failed`` is how a first attempt already
        sent failed; failures as sortie.errors exceptions.

        A refusal for want of room (:func:`admission_refusal`) lowers the client's bound to the
        limit it names (times the replicas) and is sent again after a backoff
        (:func:`retry_backoff_s`), at most ADMISSION_RETRY_MAX_ATTEMPTS attempts in all; then it
        fails as the service said it (LimitExceeded naming ``concurrent_calls`` and the limit).

        On a client of replicas, a call that failed UNAVAILABLE (or CANCELLED by a stopping
        replica) is sent once more. gRPC's retry policy never retries a call once its response
        has begun to arrive (it cannot know the call is safe to repeat), so a replica killed
        while sending an answer fails that call (an unretried UNAVAILABLE was seen once in about
        twenty SIGKILLs in tests/test_terrain_replicas.py). Terrain queries are read-only:
        sending it again is safe, and round robin sends it to another replica."""
        attempts, resent = 1, False
        while True:
            if failed is None:
                try:
                    return self._send(rpc, request)
                except grpc.RpcError as exc:
                    failed = exc
            limit = admission_refusal(failed)
            if limit is not None and attempts < ADMISSION_RETRY_MAX_ATTEMPTS:
                if limit:
                    self.slots.lower(limit * self._replicas)
                time.sleep(retry_backoff_s(attempts))
                attempts += 1
                self._count("retried_refusals")
            # CANCELLED too: a replica shutting down cancels the calls that reach it as it stops
            # (seen once in a CI run of tests/test_terrain_replicas.py: a 5 ms call, SIGTERM);
            # this client never cancels its own calls (its deadline is DEADLINE_EXCEEDED).
            elif (self.replicated and not resent
                  and failed.code() in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.CANCELLED)):
                resent = True
                self._count("resent_calls")
            else:
                raise error_from_rpc(failed) from None
            failed = None

    def _call_chunked(self, rpc: str, request: dict, chunk: int) -> dict:
        """One logical call over parallel arrays, sent as pipelined chunks of at most ``chunk``.

        Results are concatenated in order; an error in a chunk is raised with
        its index shifted to the whole batch's, so it names the caller's point.
        Arrays of unequal length go whole, for the server to reject.
        """
        lengths = {v.shape[0] for v in request.values()}
        n = lengths.pop() if len(lengths) == 1 else -1
        if n == 0:  # as the in-process Terrain answers: empty results (the service refuses empty batches)
            return serializers(rpc)[3](b"")
        if n <= chunk:
            return self._call(rpc, request)
        starts = list(range(0, n, chunk))
        parts: list = [None] * len(starts)
        pending: deque = deque()

        def collect() -> None:
            k, future, part = pending.popleft()
            try:
                parts[k] = future.result()
            except grpc.RpcError as exc:
                try:
                    parts[k] = self._call(rpc, part, exc)
                except InvalidArgument as error:
                    if error.index is None:
                        raise
                    text = str(error).split(": ", 1)[1]
                    raise InvalidArgument(error.field, text, index=error.index + starts[k]) from None

        try:
            for k, s in enumerate(starts):
                if len(pending) >= self.max_in_flight:
                    collect()
                part = {name: v[s:s + chunk] for name, v in request.items()}
                pending.append((k, self._send_future(rpc, part), part))
            while pending:
                collect()
        except BaseException:
            for _, other, _ in pending:
                other.cancel()
            raise
        first = parts[0]
        return {name: (np.concatenate([p[name] for p in parts]) if isinstance(value, np.ndarray) else value)
                for name, value in first.items()}

    def metadata(self) -> dict:
        """Sources, height reference and limits of the service (see :func:`metadata_dict`)."""
        return metadata_dict(self._call("GetMetadata", pb.GetMetadataRequest()))

    def describe(self) -> list[dict]:
        """One dict per source, keyed like Terrain.describe() (details as text)."""
        return self.metadata()["sources"]

    def heights(self, lat, lon) -> HeightResult:
        """Heights (m above MSL, NaN where OUTSIDE) at (lat, lon) degrees, (n,) each."""
        r = self._call_chunked("GetHeights", {"lat_deg": as_1d_f64("lat", lat), "lon_deg": as_1d_f64("lon", lon)},
                               self.chunk_points)
        return HeightResult(r["height_msl_m"], r["status"])

    def normals(self, lat, lon) -> NormalResult:
        """Unit surface normals (n, 3) ENU and slope (deg) at (lat, lon) degrees."""
        r = self._call_chunked("GetNormals", {"lat_deg": as_1d_f64("lat", lat), "lon_deg": as_1d_f64("lon", lon)},
                               self.chunk_points)
        normal = np.stack([r["normal_east"], r["normal_north"], r["normal_up"]], axis=-1)
        return NormalResult(normal, r["slope_deg"], r["status"])

    def profile(self, lat1: float, lon1: float, lat2: float, lon2: float, n_samples: int) -> ProfileResult:
        """Heights at n_samples points along the geodesic (lat1, lon1) -> (lat2, lon2), degrees."""
        r = self._call("GetProfile", {"start_lat_deg": float(lat1), "start_lon_deg": float(lon1),
                                      "end_lat_deg": float(lat2), "end_lon_deg": float(lon2),
                                      "n_samples": check_n_samples(n_samples)})
        return ProfileResult(r["lat_deg"], r["lon_deg"], r["distance_m"], r["height_msl_m"], r["status"])

    def line_of_sight(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> LosResult:
        """Whether each b (lat, lon degrees, height m MSL) is visible from its a."""
        r = self._call_chunked("LineOfSight", _rays(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl), self.chunk_rays)
        return LosResult(r["visible"], r["status"])

    def intersect(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> SegmentResult:
        """First terrain hit of each straight segment a -> b (lat, lon degrees, height m MSL)."""
        r = self._call_chunked("IntersectSegments", _rays(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl),
                               self.chunk_rays)
        normal = np.stack([r["normal_east"], r["normal_north"], r["normal_up"]], axis=-1)
        return SegmentResult(r["hit"], r["distance_m"], r["lat_deg"], r["lon_deg"], r["height_msl_m"],
                             normal, r["status"])


    def get_tile(self, cell_id: int, compressed: bool = True) -> HeightGrid:
        """One tile of the service's terrain store by quad-tree cell id (terrain.quadtree).
        compressed: heights travel as zstd of centimetre row differences (lossless to 1 cm,
        about a fifth of the bytes) instead of float32."""
        return HeightGrid.from_message(self._call("GetTile", pb.GetTileRequest(
            cell_id=int(cell_id), encoding=_encoding(compressed))))

    def get_region(self, level: int, lat_min: float, lon_min: float, lat_max: float, lon_max: float,
                   compressed: bool = True) -> HeightGrid:
        """The store's posts of one level covering a box (degrees), merged from every store region
        holding part of it (class 0, NaN, where none does); a box across the antimeridian takes
        lon_max above 180. compressed as for get_tile."""
        return HeightGrid.from_message(self._call("GetRegion", pb.GetRegionRequest(
            level=int(level), lat_min_deg=lat_min, lon_min_deg=lon_min, lat_max_deg=lat_max, lon_max_deg=lon_max,
            encoding=_encoding(compressed))))


def _encoding(compressed: bool) -> int:
    return pb.HEIGHT_ENCODING_ZSTD_CM if compressed else pb.HEIGHT_ENCODING_FLOAT32


@dataclass(frozen=True)
class HeightGrid:
    """Store posts as streamed: heights (rows, cols) float32 metres MSL, row 0 north,
    NaN outside the data; classes (rows, cols) uint8 (0 outside, 1 measured, 2 filled);
    post (i, j) at (lat_north_deg - i dlat_deg, lon_west_deg + j dlon_deg)."""

    heights: np.ndarray
    classes: np.ndarray
    wire_bytes: int  # the heights' and classes' bytes as they travelled
    lat_north_deg: float
    lon_west_deg: float
    dlat_deg: float
    dlon_deg: float
    level: int
    depth: int
    cell_id: int
    max_error_m: float

    @classmethod
    def from_message(cls, m) -> HeightGrid:
        from server.terrain_service import decode_heights_zstd_cm

        shape = (m.rows, m.cols)
        raw_class = m.post_class
        if m.heights_zstd:
            import zstandard

            raw_class = zstandard.ZstdDecompressor().decompress(raw_class, max_output_size=m.rows * m.cols)
        classes = np.frombuffer(raw_class, np.uint8)
        if classes.size != m.rows * m.cols:
            raise DataFormatError(f"HeightGrid: {classes.size} classes for {m.rows} x {m.cols} posts")
        classes = classes.reshape(shape)
        if m.heights_zstd:
            heights = decode_heights_zstd_cm(m.heights_zstd, m.rows, m.cols).astype(np.float32)
            heights[classes == 0] = np.nan
        else:
            heights = np.frombuffer(m.heights_f32, "<f4")
            if heights.size != m.rows * m.cols:
                raise DataFormatError(f"HeightGrid: {heights.size} heights for {m.rows} x {m.cols} posts")
            heights = heights.reshape(shape)
        wire = len(m.heights_zstd) + len(m.heights_f32) + len(m.post_class)
        return cls(heights, classes, wire, m.lat_north_deg, m.lon_west_deg, m.dlat_deg, m.dlon_deg, m.level,
                   m.depth, m.cell_id, m.max_error_m)


def _rays(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> dict:
    values = {"a_lat_deg": a_lat, "a_lon_deg": a_lon, "a_height_msl_m": a_h_msl,
              "b_lat_deg": b_lat, "b_lon_deg": b_lon, "b_height_msl_m": b_h_msl}
    return {name: as_1d_f64(name, v) for name, v in values.items()}
