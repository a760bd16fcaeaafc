"""What every Sortie gRPC service shares: the packed-array wire codec, the one
mapping of errors to status codes, message limits, health and reflection, and
a graceful lifecycle.

The wire codec exists for speed. Building a protobuf message from numpy arrays
through the generated classes costs 35 to 70 ns per value (``extend`` walks
Python floats), which for a 100,000-point height batch (7 ms to build the
request, 7 ms the response) is several times the query itself (2.5 ms). A
message made only of packed repeated numbers and scalars has a trivial
encoding (protobuf encoding spec, "Packed Repeated Fields"): per field a tag
varint, a length varint and the values' raw bytes, which for ``double`` are
little-endian IEEE 754. :class:`PackedCodec` writes and reads exactly those
bytes with numpy, so the messages on the wire are the standard ones (grpcurl
and generated stubs interoperate) while the Python side never touches a
per-value object. Anything it does not expect (an unpacked encoding, an
unknown field, a multi-byte enum varint) falls back to the generated class.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import logging
import re
import signal
import struct
import threading
import time
from collections.abc import Callable, Mapping
from concurrent import futures

import grpc
import numpy as np
from google.protobuf.message import DecodeError
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from sortie.errors import InvalidArgument, LimitExceeded, SortieError, grpc_code, message_of

logger = logging.getLogger(__name__)

# Largest request or response, bytes. The biggest batches allowed by any
# service (1,000,000 heights: 16 MB request; 1,000,000 normals: 33 MB
# response) fit with room to spare; anything larger is refused by gRPC itself
# with RESOURCE_EXHAUSTED before it is parsed.
MAX_MESSAGE_BYTES = 64 * 1024 * 1024

# Seconds in-flight calls get to finish after SIGTERM before they are cancelled.
DEFAULT_GRACE_S = 5.0

_WIRE_VARINT = 0
_WIRE_I64 = 1
_WIRE_LEN = 2


def channel_options() -> list[tuple[str, int]]:
    """Options for servers and channels: message size limits both ways."""
    return [
        ("grpc.max_send_message_length", MAX_MESSAGE_BYTES),
        ("grpc.max_receive_message_length", MAX_MESSAGE_BYTES),
    ]


# HTTP/2 keepalive from servers: a PING on each connection with calls in flight every
# KEEPALIVE_TIME_MS, and the connection closed when one is not answered within
# KEEPALIVE_TIMEOUT_MS. A client process that is frozen (stopped, hung) or cut off without a
# FIN keeps its TCP connection open, and its streams with it; without pings its session
# would never count as vanished (gRPC's defaults send none from servers for two hours). The
# ping timeout is gRPC's own option too (60 s by default, whatever the keepalive timeout),
# and pings go on while no data is sent (by default gRPC stops after two).
KEEPALIVE_TIME_MS = 5_000
KEEPALIVE_TIMEOUT_MS = 5_000


def server_options() -> list[tuple[str, int]]:
    """Options for servers: channel_options, keepalive pings (KEEPALIVE_TIME_MS), and no
    SO_REUSEPORT (gRPC sets it by default on Linux, so a second server on a port in use
    would bind silently and share the traffic instead of failing at start)."""
    return channel_options() + [
        ("grpc.so_reuseport", 0),
        ("grpc.keepalive_time_ms", KEEPALIVE_TIME_MS),
        ("grpc.keepalive_timeout_ms", KEEPALIVE_TIMEOUT_MS),
        ("grpc.http2.ping_timeout_ms", KEEPALIVE_TIMEOUT_MS),
        ("grpc.http2.max_pings_without_data", 0),
    ]


# --- wire codec ------------------------------------------------------------------------------

def varint(value: int) -> bytes:
    """Protobuf's base-128 varint of a non-negative int."""
    out = bytearray()
    while value > 0x7F:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)
    return bytes(out)


def _readvarint(data: bytes, pos: int) -> tuple[int, int]:
    """(value, position after it); raises DecodeError on truncation or overlong varints."""
    value = 0
    for shift in range(0, 64, 7):
        if pos >= len(data):
            raise DecodeError("truncated varint")
        byte = data[pos]
        pos += 1
        value |= (byte & 0x7F) << shift
        if byte < 0x80:
            return value, pos
    raise DecodeError("varint longer than 10 bytes")


class _Field:
    """How one field of a flat message goes to and from the wire."""

    def __init__(self, fd):
        t = fd.type
        self.name = fd.name
        self.repeated = fd.is_repeated
        if self.repeated:
            if t == fd.TYPE_DOUBLE:
                self.dtype = np.dtype(np.float64)
            elif t == fd.TYPE_BOOL:
                self.dtype = np.dtype(bool)
            elif t == fd.TYPE_ENUM:
                self.dtype = np.dtype(np.uint8)
            else:
                raise TypeError(f"{fd.full_name}: packed codec has no repeated {fd.type} fields")
            if not fd.is_packed:
                raise TypeError(f"{fd.full_name}: repeated fields must be packed")
            wire = _WIRE_LEN
        elif t == fd.TYPE_DOUBLE:
            wire = _WIRE_I64
        elif t in (fd.TYPE_UINT32, fd.TYPE_UINT64):
            wire = _WIRE_VARINT
            self.mask = (1 << (32 if t == fd.TYPE_UINT32 else 64)) - 1  # parsers truncate wider varints
        else:
            raise TypeError(f"{fd.full_name}: packed codec has no singular {fd.type} fields")
        self.key = (fd.number << 3) | wire
        self.tag = varint(self.key)

    def default(self):
        """The value of an absent field; empty arrays are shared, so read-only."""
        if self.repeated:
            empty = np.zeros(0, self.dtype)
            empty.flags.writeable = False
            return empty
        return 0.0 if self.key & 7 == _WIRE_I64 else 0

    def encode(self, value, parts: list) -> None:
        """Append this field's wire bytes for value (omitted when it is the default)."""
        if self.repeated:
            if self.dtype == np.float64:
                arr = np.ascontiguousarray(value, dtype="<f8")
            else:
                arr = np.asarray(value)
                if arr.dtype != bool and arr.size and not (0 <= arr.min() and arr.max() <= 0x7F):
                    raise ValueError(f"{self.name}: enum values must be within [0, 127] to be one-byte varints")
                arr = np.ascontiguousarray(arr, dtype=np.uint8)  # bool -> 0/1
            if arr.ndim != 1:
                raise ValueError(f"{self.name}: must be 1-D, got shape {arr.shape}")
            if arr.size:
                parts += (self.tag, varint(arr.nbytes), arr)
        elif self.key & 7 == _WIRE_I64:
            raw = struct.pack("<d", value)
            if raw != bytes(8):  # proto3 omits +0.0 only; -0.0 is sent
                parts += (self.tag, raw)
        elif value:
            parts += (self.tag, varint(int(value)))

    def decode_packed(self, data: bytes, pos: int, length: int, copy: bool = True):
        """The values of one packed chunk, or None when only the generic parser can read it.

        copy=False: doubles and enums are read-only views of data where its
        byte order allows (doubles may then be unaligned), not copies.
        """
        if self.dtype == np.float64:
            if length % 8:
                raise DecodeError(f"{self.name}: packed double length {length} is not a multiple of 8")
            values = np.frombuffer(data, "<f8", length // 8, pos)
            return values.astype(np.float64) if copy or not values.dtype.isnative else values
        raw = np.frombuffer(data, np.uint8, length, pos)
        if length and raw.max() > 0x7F:  # multi-byte varints: not one value per byte
            return None
        return raw if not copy and self.dtype == np.uint8 else raw.astype(self.dtype)


class PackedCodec:
    """Serialises a flat protobuf message straight from and to numpy arrays.

    ``message_class`` is a generated message whose fields are all packed
    repeated double / bool / enum, or singular double / uint32 / uint64.
    ``encode(mapping) -> bytes`` takes {field name: array or scalar} (missing
    names are defaults) and produces the same bytes as the generated class's
    ``SerializeToString``. ``decode(bytes) -> dict`` returns every field:
    repeated double as (n,) float64, bool as (n,) bool, enum as (n,) uint8,
    scalars as float or int. Both are usable directly as gRPC serializers.

    copy=False makes ``decode`` return read-only views of the message's bytes
    for doubles and enums instead of copies (doubles possibly unaligned, which
    numpy and numba read at full speed): for a server's requests, which it only
    reads, this saves a copy of every array. A client's responses are copied,
    so that callers get arrays of their own.
    """

    def __init__(self, message_class, copy: bool = True):
        self.message_class = message_class
        self.copy = copy
        fields = sorted(message_class.DESCRIPTOR.fields, key=lambda fd: fd.number)
        self.fields = [_Field(fd) for fd in fields]
        self._by_key = {f.key: f for f in self.fields}
        self._defaults = {f.name: f.default() for f in self.fields}

    def encode(self, values: Mapping[str, object]) -> bytes:
        parts: list = []
        for f in self.fields:
            if f.name in values:
                f.encode(values[f.name], parts)
        return b"".join(parts)

    def decode(self, data: bytes) -> dict:
        out = dict(self._defaults)
        chunks: dict[str, list] = {}
        pos, end = 0, len(data)
        while pos < end:
            key, pos = _readvarint(data, pos)
            f = self._by_key.get(key)
            if f is None:  # unknown field or unpacked repeated: the generic parser handles both
                return self._decode_generic(data)
            if f.repeated:
                length, pos = _readvarint(data, pos)
                if pos + length > end:
                    raise DecodeError(f"{f.name}: truncated packed field")
                values = f.decode_packed(data, pos, length, self.copy)
                if values is None:
                    return self._decode_generic(data)
                chunks.setdefault(f.name, []).append(values)
                pos += length
            elif f.key & 7 == _WIRE_I64:
                if pos + 8 > end:
                    raise DecodeError(f"{f.name}: truncated double")
                out[f.name] = struct.unpack_from("<d", data, pos)[0]
                pos += 8
            else:
                value, pos = _readvarint(data, pos)
                out[f.name] = value & f.mask
        for name, parts in chunks.items():  # a packed field may legally arrive in several chunks
            out[name] = parts[0] if len(parts) == 1 else np.concatenate(parts)
        return out

    def _decode_generic(self, data: bytes) -> dict:
        msg = self.message_class.FromString(data)
        out = {}
        for f in self.fields:
            value = getattr(msg, f.name)
            out[f.name] = np.array(value, dtype=f.dtype) if f.repeated else value
        return out


# --- errors ----------------------------------------------------------------------------------

_WHERE = re.compile(r"^(?P<field>[A-Za-z_][\w.]*)(?:\[(?P<index>\d+)\])?: ")


def wire_message(error: SortieError, field_names: Mapping[str, str]) -> str:
    """The error's message with its field renamed from the domain's name to the wire's.

    Library errors name the function parameter ("lat[7]: ..."); a gRPC client
    knows the proto field ("lat_deg[7]: ..."). Names not in field_names stay.
    """
    text = str(error)
    match = _WHERE.match(text)
    if match and match["field"] in field_names:
        text = field_names[match["field"]] + text[len(match["field"]):]
    return text


class CallStats:
    """Per-method call counters of a service (for its metrics): calls, seconds, errors by
    status code. Thread-safe; one lock hold per call."""

    def __init__(self):
        self._lock = threading.Lock()
        self._by_method: dict[str, list] = {}  # method -> [calls, seconds, {code name: count}]

    def record(self, method: str, seconds: float, code: str | None = None) -> None:
        with self._lock:
            entry = self._by_method.setdefault(method, [0, 0.0, {}])
            entry[0] += 1
            entry[1] += seconds
            if code is not None:
                entry[2][code] = entry[2].get(code, 0) + 1

    def snapshot(self) -> dict:
        """method -> (calls, seconds, {code: errors}), copied."""
        with self._lock:
            return {m: (n, s, dict(codes)) for m, (n, s, codes) in self._by_method.items()}


class Malformed:
    """A request whose bytes did not decode. gRPC maps an exception in a request
    deserializer to INTERNAL ("Exception deserializing request!") and drops its message;
    :func:`tolerant_decoder` hands this to the handler instead, which answers
    INVALID_ARGUMENT with the decoder's reason."""

    def __init__(self, reason: str):
        self.reason = reason


def tolerant_decoder(decode: Callable[[bytes], object]) -> Callable[[bytes], object]:
    """``decode`` that returns :class:`Malformed` where it would raise."""

    def deserialize(data: bytes):
        try:
            return decode(data)
        except Exception as exc:  # noqa: BLE001 - DecodeError, struct and numpy errors alike
            return Malformed(str(exc) or type(exc).__name__)

    deserialize.tolerant = True  # tolerant_handlers leaves handlers decoding with it as they are
    return deserialize


def _malformed_text(method: str, request: Malformed) -> str:
    return message_of(InvalidArgument("request", f"does not decode as a {method} request: {request.reason}"))


def tolerant_handlers(handlers: Mapping[str, grpc.RpcMethodHandler], aio: bool = False) -> dict:
    """``handlers`` ({method: handler}) whose requests that do not decode end INVALID_ARGUMENT,
    naming ``request`` and the decoder's reason, like the Sortie services' own (tolerant_decoder).

    gRPC answers a request deserializer's exception with INTERNAL ("Exception deserializing
    request!"; UNKNOWN "Unexpected <class DecodeError>" on a grpc.aio server) and logs it as an
    ERROR with its traceback: so did health and reflection, and the replay's ReplayService, for
    any client sending bytes that are not their messages. A handler already decoding with
    tolerant_decoder is kept as it is (its behaviour answers Malformed itself); ``aio``: the
    behaviours are coroutines (or async generators) of a grpc.aio server."""
    return {name: _tolerant_handler(name, h, aio) for name, h in handlers.items()}


def _behaviour_kind(handler) -> str:
    """The RpcMethodHandler field holding ``handler``'s behaviour: "unary_unary" ... "stream_stream"."""
    return (("stream_" if handler.request_streaming else "unary_")
            + ("stream" if handler.response_streaming else "unary"))


def _tolerant_handler(method: str, handler, aio: bool):
    decode = handler.request_deserializer
    if decode is None or getattr(decode, "tolerant", False):
        return handler
    kind = _behaviour_kind(handler)
    behaviour = getattr(handler, kind)
    if handler.request_streaming:
        wrapped = _tolerant_stream_behaviour(method, behaviour, aio)
    else:
        wrapped = _tolerant_unary_behaviour(method, behaviour, aio)
    return handler._replace(request_deserializer=tolerant_decoder(decode), **{kind: wrapped})


def _tolerant_unary_behaviour(method: str, behaviour: Callable, aio: bool) -> Callable:
    if not aio:
        def checked(request, context, *args, **kwargs):
            if isinstance(request, Malformed):
                context.abort(grpc.StatusCode.INVALID_ARGUMENT, _malformed_text(method, request))
            return behaviour(request, context, *args, **kwargs)

        # grpcio calls a non-blocking behaviour (health Watch) with a send callback instead
        checked.experimental_non_blocking = getattr(behaviour, "experimental_non_blocking", False)
        return checked
    if inspect.isasyncgenfunction(behaviour):
        async def checked_gen(request, context):
            if isinstance(request, Malformed):
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, _malformed_text(method, request))
            async for response in behaviour(request, context):
                yield response

        return checked_gen

    async def checked_coro(request, context):
        if isinstance(request, Malformed):
            await context.abort(grpc.StatusCode.INVALID_ARGUMENT, _malformed_text(method, request))
        return await behaviour(request, context)

    return checked_coro


def _tolerant_stream_behaviour(method: str, behaviour: Callable, aio: bool) -> Callable:
    """A behaviour whose request iterator ends the call INVALID_ARGUMENT at the first message
    that does not decode (messages before it are handled)."""
    if not aio:
        def checked(request_iterator, context, *args, **kwargs):
            def requests():
                for request in request_iterator:
                    if isinstance(request, Malformed):
                        context.abort(grpc.StatusCode.INVALID_ARGUMENT, _malformed_text(method, request))
                    yield request

            return behaviour(requests(), context, *args, **kwargs)

        return checked

    async def requests(request_iterator, context):
        async for request in request_iterator:
            if isinstance(request, Malformed):
                await context.abort(grpc.StatusCode.INVALID_ARGUMENT, _malformed_text(method, request))
            yield request

    if inspect.isasyncgenfunction(behaviour):
        async def checked_gen(request_iterator, context):
            async for response in behaviour(requests(request_iterator, context), context):
                yield response

        return checked_gen

    async def checked_coro(request_iterator, context):
        return await behaviour(requests(request_iterator, context), context)

    return checked_coro


class _Handlers:
    """Stands for a server in a generated ``add_*Servicer_to_server``: keeps the method handlers
    it registers, so that they can be wrapped (tolerant_handlers) before the real server gets
    them."""

    def __init__(self):
        self.services: dict[str, dict] = {}

    def add_generic_rpc_handlers(self, generic_rpc_handlers) -> None:
        pass  # the generated code registers the same handlers by name too (next method)

    def add_registered_method_handlers(self, service_name: str, method_handlers) -> None:
        self.services[service_name] = dict(method_handlers)


def register(server, service_name: str, handlers: Mapping[str, grpc.RpcMethodHandler]) -> None:
    """``handlers`` as a service of ``server`` (sync or aio), as generated code registers them."""
    server.add_generic_rpc_handlers((grpc.method_handlers_generic_handler(service_name, handlers),))
    server.add_registered_method_handlers(service_name, handlers)


class ReflectionPool:
    """The descriptor pool reflection answers from, which also finds the file of a method.

    The reflection protocol's file_containing_symbol takes "<package>.<service>[.<method>] or
    <package>.<type>" (grpc/reflection/v1alpha/reflection.proto), but protobuf's Python pool
    finds no method by FindFileContainingSymbol: `grpcurl describe
    sortie.v1.TerrainService.GetHeights` answered "Symbol not found". Everything else is the
    wrapped pool's."""

    def __init__(self, pool=None):
        from google.protobuf import descriptor_pool

        self._pool = pool if pool is not None else descriptor_pool.Default()

    def FindFileContainingSymbol(self, symbol: str):  # noqa: N802 - the pool's interface
        try:
            return self._pool.FindFileContainingSymbol(symbol)
        except KeyError:
            try:
                return self._pool.FindMethodByName(symbol).containing_service.file
            except KeyError:
                pass
            raise

    def __getattr__(self, name):
        return getattr(self._pool, name)


def health_and_reflection_handlers(health_servicer, service_names, aio: bool = False) -> dict:
    """{service name: tolerant method handlers} of grpc.health.v1 (``health_servicer``) and of
    server reflection (v1alpha, listing ``service_names``, health and itself; method symbols
    found: ReflectionPool)."""
    from grpc_reflection.v1alpha import reflection_pb2_grpc

    names = (*service_names, health.SERVICE_NAME, reflection.SERVICE_NAME)
    servicer = (reflection.aio.ReflectionServicer if aio else reflection.ReflectionServicer)(names, ReflectionPool())
    captured = _Handlers()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, captured)
    reflection_pb2_grpc.add_ServerReflectionServicer_to_server(servicer, captured)
    missing = {health.SERVICE_NAME, reflection.SERVICE_NAME} - set(captured.services)
    if missing:  # generated code of a grpcio before 1.63 registers generic handlers only
        raise RuntimeError(f"grpcio's generated code did not register {', '.join(sorted(missing))} by name "
                           "(add_registered_method_handlers): grpcio-health-checking and grpcio-reflection "
                           ">= 1.85.1 are required (pyproject.toml)")
    return {name: tolerant_handlers(h, aio) for name, h in captured.services.items()}


def unary_handler(name: str, method: Callable, field_names: Mapping[str, str],
                  stats: CallStats | None = None) -> Callable:
    """Wrap ``method(request) -> response`` into a gRPC behaviour with the one error mapping.

    SortieError -> its status code (grpc_code) and message; anything else ->
    INTERNAL, logged with its traceback. Either way only this call fails.
    ``stats`` counts the calls under ``name``'s last part.
    """
    short = name.rsplit("/", 1)[-1]

    def behaviour(request, context):
        t0 = time.perf_counter()
        code = None
        try:
            if isinstance(request, Malformed):
                raise InvalidArgument("request", f"does not decode as a {short} request: {request.reason}")
            return method(request)
        except SortieError as exc:
            logger.debug("%s rejected: %s", name, exc)
            code = grpc_code(exc).name
            context.abort(grpc_code(exc), message_of(wire_message(exc, field_names)))
        except Exception as exc:
            logger.exception("%s failed", name)
            code = "INTERNAL"
            context.abort(grpc.StatusCode.INTERNAL, message_of(f"{name}: internal error ({type(exc).__name__}: "
                                                               f"{exc})"))
        finally:
            if stats is not None:
                stats.record(short, time.perf_counter() - t0, code)

    return behaviour


# The field a refusal for want of room names (LimitExceeded), which clients retry later
# (client/terrain_client.py).
ADMISSION_FIELD = "concurrent_calls"
# How often a call queued for a worker looks whether its caller is still there.
ADMISSION_POLL_S = 0.05


class Admission:
    """At most ``limit`` calls admitted at once, running or queued for one of ``workers``
    running at once; one more is refused at once (LimitExceeded naming ADMISSION_FIELD and the
    limit: RESOURCE_EXHAUSTED) rather than queued without bound. Thread-safe.

    gRPC's own ``maximum_concurrent_rpcs`` did this before, and counted every call of the server:
    health checks and reflection too, which a busy server then refused ("Concurrent RPC limit
    exceeded!") or queued behind the batches on the same threads past their deadline (a busy
    terrain service failed its container's health check). Admitted calls now hold threads of
    their own (the pool is sized ``limit`` plus spares), of which ``workers`` work at once, so
    the spares answer health, reflection and refusals at once."""

    def __init__(self, limit: int, workers: int, what: str):
        for name, v in (("limit", limit), ("workers", workers)):
            if not (isinstance(v, int) and v >= 1):
                raise InvalidArgument(name, "must be an integer >= 1", value=v)
        self.limit, self.workers, self.what = limit, workers, what
        self._admitted = 0
        self._lock = threading.Lock()
        self._working = threading.BoundedSemaphore(workers)

    @property
    def admitted(self) -> int:
        """Calls admitted now (running or queued)."""
        return self._admitted

    def wrap(self, name: str, behaviour: Callable, stats: CallStats | None = None) -> Callable:
        """``behaviour(request, context)`` admitted first: refused (RESOURCE_EXHAUSTED, counted in
        ``stats`` under ``name``'s last part) when ``limit`` calls are in, else run once one of the
        ``workers`` is free; a call whose caller leaves or whose deadline passes while it waits
        ends CANCELLED / DEADLINE_EXCEEDED without running."""
        short = name.rsplit("/", 1)[-1]

        def admitted(request, context):
            with self._lock:
                full = self._admitted >= self.limit
                if not full:
                    self._admitted += 1
                n = self._admitted + 1
            if full:
                if stats is not None:
                    stats.record(short, 0.0, grpc.StatusCode.RESOURCE_EXHAUSTED.name)
                context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED,
                              message_of(LimitExceeded(ADMISSION_FIELD, n, self.limit, self.what)))
            try:
                while not self._working.acquire(timeout=ADMISSION_POLL_S):
                    remaining = context.time_remaining()
                    if remaining is not None and remaining <= 0.0:
                        context.abort(grpc.StatusCode.DEADLINE_EXCEEDED, f"{short}: the call's deadline passed "
                                      "while it waited for a worker")
                    if not context.is_active():
                        context.abort(grpc.StatusCode.CANCELLED, f"{short}: the call was cancelled while it "
                                      "waited for a worker")
                try:
                    return behaviour(request, context)
                finally:
                    self._working.release()
            finally:
                with self._lock:
                    self._admitted -= 1

        return admitted


# Calls a grpc.aio server (AioManagedServer) takes at once beyond the ones its AioAdmission admits
# (health, reflection, calls about to be refused): a backstop, refused by gRPC itself.
AIO_OTHER_CALLS_AT_ONCE = 64
AIO_ADMISSION_WHAT = ("calls of this server's services open at once, streams included; health and reflection are "
                      "answered beside them")


class AioAdmission:
    """At most ``limit`` calls of a grpc.aio server's own services open at once (streams until
    they end); one more is refused at once with RESOURCE_EXHAUSTED naming ADMISSION_FIELD and
    the limit. Health and reflection are not counted.

    gRPC's ``maximum_concurrent_rpcs`` did this before, and counted health and reflection too:
    one client holding that many client streams open without sending on them (a stock client
    can; no session is needed before the first message) had the simulation server refuse its
    health check ("Concurrent RPC limit exceeded!", naming no limit), so the container was
    taken for dead with every session in it. Behaviours run on the server's one event loop,
    so the count needs no lock."""

    def __init__(self, limit: int, what: str = AIO_ADMISSION_WHAT):
        if not (isinstance(limit, int) and limit >= 1):
            raise InvalidArgument("limit", "must be an integer >= 1", value=limit)
        self.limit, self.what = limit, what
        self.admitted = 0

    def wrap_all(self, handlers: Mapping[str, grpc.RpcMethodHandler]) -> dict:
        """``handlers`` ({method: handler} with coroutine or async generator behaviours), admitted."""
        out = {}
        for name, handler in handlers.items():
            kind = _behaviour_kind(handler)
            out[name] = handler._replace(**{kind: self.wrap(getattr(handler, kind))})
        return out

    async def _admit(self, context) -> None:
        if self.admitted >= self.limit:
            await context.abort(grpc.StatusCode.RESOURCE_EXHAUSTED, message_of(
                LimitExceeded(ADMISSION_FIELD, self.admitted + 1, self.limit, self.what)))
        self.admitted += 1

    def wrap(self, behaviour: Callable) -> Callable:
        if inspect.isasyncgenfunction(behaviour):
            async def admitted_gen(request, context):
                await self._admit(context)
                try:
                    async for response in behaviour(request, context):
                        yield response
                finally:
                    self.admitted -= 1

            return admitted_gen

        async def admitted(request, context):
            await self._admit(context)
            try:
                return await behaviour(request, context)
            finally:
                self.admitted -= 1

        return admitted


def check_batch(request: Mapping[str, np.ndarray], names: tuple[str, ...], limit: int) -> int:
    """Length n of the parallel arrays ``names`` of a decoded request.

    Raises InvalidArgument when they differ in length or are empty, and
    LimitExceeded when n is over ``limit``.
    """
    first = names[0]
    n = len(request[first])
    if n > limit:
        raise LimitExceeded(first, n, limit)
    for name in names[1:]:
        if len(request[name]) != n:
            raise InvalidArgument(name, f"must have as many values as {first} ({n}), got {len(request[name])}")
    if n == 0:
        raise InvalidArgument(first, "must hold at least one value")
    return n


# --- health ----------------------------------------------------------------------------------

_HealthCheckResponse = health_pb2.HealthCheckResponse


def _health_list(status: Mapping[str, int]) -> health_pb2.HealthListResponse:
    """grpc.health.v1 List's answer: every registered name with its status."""
    return health_pb2.HealthListResponse(
        statuses={name: _HealthCheckResponse(status=value) for name, value in status.items()})


class HealthServicer(health_pb2_grpc.HealthServicer):
    """grpc.health.v1 (Check, List, Watch) of a ``grpc.Server``.

    grpcio's own servicer (grpc_health.v1.health) was used before, with two faults:
    List, which reflection advertises, answered UNIMPLEMENTED; and
    ``enter_graceful_shutdown`` sent NOT_SERVING to every Watch stream but left the stream
    open, and ``grpc.Server.stop(grace)`` waits for every open call, so one health watcher
    (a load balancer, a client channel's health check) held every SIGTERM for the whole
    grace. Here a graceful shutdown sends NOT_SERVING, then ends each Watch stream (OK): a
    client channel's health checker has the NOT_SERVING and starts a new Watch (gRPC proposal
    A17, "Client-Side Health Checking"), which a stopping server no longer takes. Check keeps
    grpcio's answers: NOT_FOUND, no details, for a name never registered (gRPC
    doc/health-checking.md).
    """

    def __init__(self):
        # _lock guards the tables; gRPC's callback at a stream's end takes it. _send_lock keeps
        # each watcher's messages in order; the sends wait on gRPC's completion thread, which
        # runs those callbacks, so _lock is never held while sending (grpcio's servicer held
        # its one lock there).
        self._lock = threading.Lock()
        self._send_lock = threading.Lock()
        self._status: dict[str, int] = {}
        self._watchers: dict[str, set] = {}  # service -> the send callbacks of its open Watch streams
        self._shutting_down = False

    def Check(self, request, context):
        with self._lock:
            status = self._status.get(request.service)
        if status is None:
            context.set_code(grpc.StatusCode.NOT_FOUND)
            return _HealthCheckResponse()
        return _HealthCheckResponse(status=status)

    def List(self, request, context):
        with self._lock:
            return _health_list(self._status)

    def Watch(self, request, context, send_response_callback=None):
        """Non-blocking (gRPC calls it with ``send_response_callback`` and holds no thread for
        the stream): the status now, then each change; a callback of None ends the stream."""
        service, send = request.service, send_response_callback
        with self._send_lock:
            with self._lock:
                status = self._status.get(service, _HealthCheckResponse.SERVICE_UNKNOWN)
                ending = self._shutting_down
                if not ending:
                    self._watchers.setdefault(service, set()).add(send)
            send(_HealthCheckResponse(status=status))
            if ending:
                send(None)
                return

        def gone():  # the stream ended, by either side
            with self._lock:
                self._watchers.get(service, set()).discard(send)

        if not context.add_callback(gone):  # it ended already
            gone()

    Watch.experimental_non_blocking = True  # as grpcio's servicer (grpc._server checks the attribute)

    def set(self, service: str, status: int) -> None:
        """``service``'s status, sent to its watchers; ignored once a shutdown has begun."""
        with self._send_lock:
            with self._lock:
                if self._shutting_down:
                    return
                self._status[service] = status
                sends = list(self._watchers.get(service, ()))
            for send in sends:
                send(_HealthCheckResponse(status=status))

    def enter_graceful_shutdown(self) -> None:
        """Every name NOT_SERVING for good: each Watch stream gets it, then ends (OK)."""
        with self._send_lock:
            with self._lock:
                if self._shutting_down:
                    return
                self._shutting_down = True
                for service in self._status:
                    self._status[service] = _HealthCheckResponse.NOT_SERVING
                watchers = [(self._status.get(service, _HealthCheckResponse.SERVICE_UNKNOWN), send)
                            for service, sends in self._watchers.items() for send in sends]
                self._watchers.clear()
            for status, send in watchers:
                send(_HealthCheckResponse(status=status))
                send(None)


class AioHealthServicer(health_pb2_grpc.HealthServicer):
    """:class:`HealthServicer` for a ``grpc.aio`` server: its methods run on the server's
    event loop (one thread, so no lock); Watch streams end once a graceful shutdown has sent
    them NOT_SERVING, as there. grpcio's aio servicer had the same two faults (List
    UNIMPLEMENTED, logged as an error with its traceback at every call; Watch streams held
    ``stop(grace)`` to its end)."""

    def __init__(self):
        self._status: dict[str, int] = {}
        self._changed = asyncio.Event()  # set, and replaced, at every change
        self._shutting_down = False

    async def Check(self, request, context):
        status = self._status.get(request.service)
        if status is None:
            await context.abort(grpc.StatusCode.NOT_FOUND)
        return _HealthCheckResponse(status=status)

    async def List(self, request, context):
        return _health_list(self._status)

    async def Watch(self, request, context):
        last = None
        while True:
            changed = self._changed  # taken before the status: a change during the write wakes us
            status = self._status.get(request.service, _HealthCheckResponse.SERVICE_UNKNOWN)
            if status != last:
                await context.write(_HealthCheckResponse(status=status))
                last = status
                continue  # the status may have changed during the write (a shutdown among them)
            if self._shutting_down:
                return
            await changed.wait()

    def _announce(self) -> None:
        self._changed.set()
        self._changed = asyncio.Event()

    async def set(self, service: str, status: int) -> None:
        """``service``'s status, sent to its watchers; ignored once a shutdown has begun."""
        if self._shutting_down:
            return
        self._status[service] = status
        self._announce()

    async def enter_graceful_shutdown(self) -> None:
        """Every name NOT_SERVING for good: each Watch stream sends it, then ends (OK)."""
        if self._shutting_down:
            return
        self._shutting_down = True
        for service in self._status:
            self._status[service] = _HealthCheckResponse.NOT_SERVING
        self._announce()


# --- lifecycle -------------------------------------------------------------------------------

class ManagedServer:
    """A ``grpc.Server`` with health and reflection registered, and a graceful stop.

    Health reports SERVING for "" and every name in ``service_names`` once
    started, and NOT_SERVING from the moment a stop begins, so load balancers
    and clients drain before in-flight calls are cut off.
    """

    def __init__(self, server, service_names: tuple[str, ...]):
        self.grpc_server = server
        self.health = HealthServicer()
        self._serving = health_pb2.HealthCheckResponse.SERVING
        self._health_names = ("", *service_names)
        for name, handlers in health_and_reflection_handlers(self.health, service_names).items():
            register(server, name, handlers)

    def start(self) -> None:
        self.grpc_server.start()
        for name in self._health_names:
            self.health.set(name, self._serving)

    def stop(self, grace: float | None = DEFAULT_GRACE_S) -> threading.Event:
        """Mark every service NOT_SERVING, then stop; in-flight calls get ``grace`` seconds
        (None: cancelled at once). Returns an event set when the server has stopped.
        Arguments are named as in ``grpc.Server``."""
        self.health.enter_graceful_shutdown()
        return self.grpc_server.stop(grace)

    def wait_for_termination(self, timeout: float | None = None) -> bool:
        """Block until the server stops or ``timeout`` seconds pass; True on timeout."""
        return self.grpc_server.wait_for_termination(timeout)

    def serve_until_signalled(self, grace_s: float = DEFAULT_GRACE_S,
                              signals=(signal.SIGTERM, signal.SIGINT), stop: threading.Event | None = None) -> None:
        """Block (main thread only) until one of ``signals`` (``stop``: as in
        :func:`wait_for_signal`), then stop gracefully."""
        wait_for_signal(signals=signals, stop=stop)
        logger.info("signal received: NOT_SERVING, stopping with %.1f s grace", grace_s)
        self.stop(grace_s).wait()


def listen_error(address: str, exc: Exception) -> SortieError:
    """The start-up error of a server that cannot listen on ``address`` (HOST:PORT): gRPC's own
    message says only "Failed to bind" (its reason goes to gRPC's log, which JSON logging turns
    off), so the reason is asked of the operating system by binding a plain socket there."""
    return SortieError(f"cannot listen on {address}: {listen_cause(address) or exc}")


def listen_cause(address: str) -> str | None:
    """Why a TCP socket cannot listen on ``address`` ("Address already in use", "Cannot assign
    requested address", a host name that does not resolve); None when one can."""
    import socket

    host, _, port = address.rpartition(":")
    host = host[1:-1] if host.startswith("[") and host.endswith("]") else host
    try:
        infos = socket.getaddrinfo(host or None, int(port), type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except (OSError, ValueError, UnicodeError) as exc:
        return f"no such host {host!r} ({getattr(exc, 'strerror', None) or exc})"
    for family, kind, proto, _, sockaddr in infos:
        try:
            with socket.socket(family, kind, proto) as s:
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as gRPC binds
                s.bind(sockaddr)
        except OSError as exc:
            return exc.strerror or str(exc)
    return None


@contextlib.contextmanager
def stop_signals(signals=(signal.SIGTERM, signal.SIGINT)):
    """While in the block (main thread only), ``signals`` set the event it yields instead of
    ending the process; the previous handlers are back after it (a second Ctrl-C during a
    stuck shutdown still interrupts). A service enters it before it says where it listens:
    a supervisor (or a test) that sends SIGTERM as soon as it reads that line then stops it
    cleanly (exit 0), where before the handlers came only after the line, and a SIGTERM in
    between killed it (-15)."""
    stop = threading.Event()
    previous = {sig: signal.signal(sig, lambda signum, frame: stop.set()) for sig in signals}
    try:
        yield stop
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


def wait_for_signal(finished: threading.Event | None = None, signals=(signal.SIGTERM, signal.SIGINT),
                    stop: threading.Event | None = None) -> None:
    """Block (main thread only) until one of ``signals`` arrives or ``finished`` is set;
    ``stop``: the event of an enclosing :func:`stop_signals` (its signals), else its own."""
    if stop is None:
        with stop_signals(signals) as stop:
            wait_for_signal(finished, stop=stop)
        return
    while not stop.is_set() and not (finished is not None and finished.is_set()):
        stop.wait(0.2)


class AioManagedServer:
    """:class:`ManagedServer` for a ``grpc.aio`` server, whose event loop runs on a
    thread of its own, so that the rest of the process (a world's clock
    thread) stays synchronous. Same health, reflection and graceful stop.

    ``handlers_of(blocking pool)``: {method: handler} of one service whose
    behaviours are coroutines (``extra_services``: more (name, handlers_of)
    pairs served beside it); ``blocking_workers``: threads of the pool handlers offload
    blocking calls to (:attr:`blocking`). At most ``max_rpcs`` calls of those services are
    open at once (:class:`AioAdmission`, :attr:`admission`); health and reflection are answered
    beside them. Requests that do not decode end INVALID_ARGUMENT (:func:`tolerant_handlers`).
    """

    def __init__(self, service_name: str, handlers_of, address: str, *, max_rpcs: int,
                 blocking_workers: int = 8, options=None, extra_services=()):
        self.blocking = futures.ThreadPoolExecutor(max_workers=blocking_workers, thread_name_prefix="aio-blocking")
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._run_loop, name="grpc-aio", daemon=True)
        self._thread.start()
        services = [(service_name, handlers_of)] + list(extra_services)  # (name, handlers_of) each
        self._health_names = ("", *(name for name, _ in services))
        self._stopped = threading.Event()
        try:
            self.port = self._call(self._create([(name, h(self.blocking)) for name, h in services], address,
                                                max_rpcs, options if options is not None else server_options()))
        except BaseException:
            self._shutdown_loop()
            raise

    def _run_loop(self) -> None:
        asyncio.set_event_loop(self.loop)
        self.loop.run_forever()

    def _call(self, coro, timeout_s: float = 60.0):
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout_s)

    async def _create(self, services, address, max_rpcs, options) -> int:
        # The services' calls are admitted by AioAdmission (max_rpcs at once); gRPC's own limit,
        # which counts every call, health and reflection among them, is only a backstop above it.
        self.admission = AioAdmission(max_rpcs)
        self.grpc_server = grpc.aio.server(options=options, maximum_concurrent_rpcs=max_rpcs + AIO_OTHER_CALLS_AT_ONCE)
        for name, handlers in services:
            self.grpc_server.add_registered_method_handlers(
                name, self.admission.wrap_all(tolerant_handlers(handlers, aio=True)))
        self.health = AioHealthServicer()
        for name, handlers in health_and_reflection_handlers(self.health, [name for name, _ in services],
                                                             aio=True).items():
            register(self.grpc_server, name, handlers)
        try:
            return self.grpc_server.add_insecure_port(address)
        except RuntimeError as exc:  # in use, or no such interface: a start-up error, one line
            raise listen_error(address, exc) from None

    async def _start(self) -> None:
        await self.grpc_server.start()
        for name in self._health_names:
            await self.health.set(name, health_pb2.HealthCheckResponse.SERVING)

    def start(self) -> None:
        self._call(self._start())

    async def _stop(self, grace) -> None:
        await self.health.enter_graceful_shutdown()
        await self.grpc_server.stop(grace)

    def stop(self, grace: float | None = DEFAULT_GRACE_S) -> threading.Event:
        """NOT_SERVING, then stop with ``grace`` seconds for in-flight calls; the loop
        and its thread end after. Returns an event set when all is stopped."""
        if self.loop.is_closed() or self._stopped.is_set():
            return self._stopped
        future = asyncio.run_coroutine_threadsafe(self._stop(grace), self.loop)

        def done(_):
            self._shutdown_loop()

        future.add_done_callback(done)
        return self._stopped

    def _shutdown_loop(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.blocking.shutdown(wait=False, cancel_futures=True)
        self._stopped.set()


HOST_HELP = "interface to listen on, a name or an address (an IPv6 literal with or without brackets)"


def bare_host(host: str) -> str:
    """``host`` without the brackets of an IPv6 literal ("[::1]" -> "::1"): what sockets,
    getaddrinfo and HTTP servers take."""
    return host[1:-1] if host.startswith("[") and host.endswith("]") else host


def listen_address(host: str, port: int) -> str:
    """The HOST:PORT a gRPC server binds: an IPv6 literal in brackets ("::1" or "[::1]" ->
    "[::1]:50051"), as gRPC's address syntax (and RFC 3986 section 3.2.2) has it, where
    "::1:50051" would not say where the address ends and the port begins."""
    host = bare_host(host)
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
