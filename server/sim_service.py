"""``sortie.v1.SimulationService``: sessions, commands in, Watch streams out.

Sessions. Join returns an unguessable token (``secrets.token_urlsafe``, 128
bits); every later call presents it. An unknown token is UNAUTHENTICATED; a
command for an agent the session does not hold is PERMISSION_DENIED. A
session is alive while it has a stream open (Watch, events, or a controls or
external stream that has carried one of its messages) or has called within
``vanished_timeout_s``; after that its agent is released (to its autopilot or
removed, per the scenario) and the token stops working. A client frozen or cut
off with a stream open is found by HTTP/2 keepalive pings, which end its streams.

Limits (all explicit): MAX_SESSIONS sessions; client names of 1-64 printable
characters, agent names of at most 64 (a scenario's limit); MAX_EVENT_STREAMS
events streams per session; the controls stream validates each message before
applying it and ends the stream with INVALID_ARGUMENT on the first bad one,
naming the field (the session and everyone else carry on); gRPC's message size
limit (grpc_common.MAX_MESSAGE_BYTES) refuses oversized messages before
parsing, and bytes that do not decode are INVALID_ARGUMENT with the decoder's
reason. An error message shows a bad value cut short (sortie.errors.shown).

Streams end with a status that says why: OK when the server stops (the end of
the exercise; a Watch first sends what was queued for it, the exercise's last
state, and one begun as the server stops ends at once), ABORTED when a new
Watch of the session supersedes a Watch ("superseded by a new Watch of this
session") or the session leaves while a stream is open ("session left").

No stream holds a thread while it waits: a Watch stream awaits its queue's
asyncio event (set by the publisher), an events stream an event that one
thread per servicer (:class:`EventBell`) sets for all of them when the world
emits; the thread pool is left to Join, Leave and commands.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import secrets
import threading
import time
from dataclasses import dataclass, field

import grpc
import numpy as np

from server.external import COALITIONS, EXTERNAL_ALGORITHM_NAMES, external_state
from server.grpc_common import Malformed, tolerant_decoder
from server.streaming import ClientQueue, encode_watch_update
from server.world import AIRCRAFT, GROUND, World
from sortie.errors import (InvalidArgument, LimitExceeded, PermissionDenied, SortieError, Unauthenticated, grpc_code,
                           message_of)
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import geodetic_to_ecef

logger = logging.getLogger(__name__)

SERVICE_NAME = "sortie.v1.SimulationService"
MAX_SESSIONS = 256
MAX_NAME_CHARS = 64  # client names, and agent names (a scenario's agent names are at most 64 characters)
MAX_EVENT_STREAMS = 4  # WatchEvents streams open at once per session
# Calls one session holds open at once within its limits: a Watch, its events streams, a
# controls and an external-entities stream, and one call (Join, Leave, GetWorld, health) in
# flight. The servers admit MAX_SESSIONS of them (MAX_CONCURRENT_RPCS): at 512, 256 observers
# with a Watch and an events stream each filled the limit, and health, Join and Leave were
# refused with gRPC's "Concurrent RPC limit exceeded!" (a busy server failed its health check).
CALLS_PER_SESSION = 1 + MAX_EVENT_STREAMS + 2 + 1
MAX_CONCURRENT_RPCS = MAX_SESSIONS * CALLS_PER_SESSION  # (streams are coroutines: cheap)
# How long a stream waits for changes before checking that it is still wanted (on the event
# loop: the wait holds no thread).
STREAM_POLL_S = 0.25
SUPERSEDED = "superseded by a new Watch of this session"
SESSION_LEFT = "session left"
# What an ExternalEntityUpdate's unset fields mean (proto3 sends no zero or empty field, so a
# gateway that leaves them out sends these): dead_reckoning 0 (DEAD_RECKONING_ALGORITHM_UNSPECIFIED)
# is FPW, constant velocity in world axes (IEEE 1278.1-2012 Annex E), and coalition "" neutral.
UNSET_DEAD_RECKONING = pb.DEAD_RECKONING_ALGORITHM_FPW
UNSET_COALITION = "neutral"


def status_of(error: Exception):
    return grpc_code(error) if isinstance(error, SortieError) else grpc.StatusCode.INTERNAL


@dataclass
class Session:
    token: str
    name: str
    role: int
    agent_id: int = 0
    observer_ecef: np.ndarray | None = None
    radius_m: float = 0.0
    last_seen: float = field(default_factory=time.monotonic)
    open_streams: int = 0
    event_streams: int = 0  # WatchEvents streams open (at most MAX_EVENT_STREAMS)
    left: bool = False  # set by Sessions.leave: its streams end (ABORTED "session left")
    queue: ClientQueue | None = None
    # What the session's stream has been told it sees (server.streaming.Publisher):
    # the ids, and the same as a mask over the publisher's entity layout number visible_layout.
    visible_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    visible_mask: np.ndarray | None = None
    visible_layout: int | None = None
    # Held while a new stream takes over the session (begin_stream, on the event loop) and
    # while the publisher (on the clock thread) records and queues what the session sees,
    # so neither sees half of the other: see begin_stream.
    view_lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)

    def reset_visible(self) -> None:
        """A new stream starts from nothing seen (its first update is the full snapshot)."""
        self.visible_ids, self.visible_mask, self.visible_layout = np.zeros(0, np.int64), None, None

    def begin_stream(self, queue: ClientQueue) -> ClientQueue | None:
        """Make ``queue`` the session's stream, starting from nothing seen; returns the queue
        it replaces (None if none).

        The publisher decides a session's view from what it saw before and then records and
        queues the new view (server.streaming.Publisher.publish); a Watch arriving in between
        (the event loop runs whenever the clock thread lets go of the interpreter) used to
        have its reset overwritten, and its first update was a snapshot with no entities
        entered, the entities it saw never entered later. Under ``view_lock`` the publisher
        queues only to the queue whose view it decided, so a new stream's first update is
        always its whole picture."""
        with self.view_lock:
            old, self.queue = self.queue, queue
            self.reset_visible()
        return old


class Sessions:
    """The session table (thread-safe)."""

    def __init__(self, world: World, params_of, vanished_timeout_s: float = 10.0):
        self.world = world
        self.params_of = params_of
        self.vanished_timeout_s = float(vanished_timeout_s)
        self._by_token: dict[str, Session] = {}
        self._lock = threading.Lock()

    def join(self, name: str, role: int, agent_name: str = "", observer=None) -> Session:
        if not (1 <= len(name) <= MAX_NAME_CHARS and name.isprintable()):
            raise InvalidArgument("client_name", f"must be 1-{MAX_NAME_CHARS} printable characters", value=name)
        if role not in (pb.ROLE_PILOT, pb.ROLE_DRIVER, pb.ROLE_OBSERVER, pb.ROLE_BOT, pb.ROLE_GATEWAY):
            raise InvalidArgument("role", "must be ROLE_PILOT, ROLE_DRIVER, ROLE_OBSERVER, ROLE_BOT or ROLE_GATEWAY",
                                  value=role)
        if len(agent_name) > MAX_NAME_CHARS:
            raise InvalidArgument("agent_name", f"must be at most {MAX_NAME_CHARS} characters (no scenario agent "
                                                "has a longer name)", value=agent_name)
        centre = None
        if role == pb.ROLE_OBSERVER:
            lat, lon, radius = observer
            if not (math.isfinite(lat) and abs(lat) <= 90.0):
                raise InvalidArgument("observer_lat_deg", "must be within [-90, 90]", value=lat)
            if not (math.isfinite(lon) and abs(lon) <= 540.0):
                raise InvalidArgument("observer_lon_deg", "must be within [-540, 540]", value=lon)
            limit = self.params_of(None, "observer").aoi_radius_m
            if not (math.isfinite(radius) and 0.0 < radius <= limit):
                raise InvalidArgument("observer_radius_m", f"must be in (0, {limit:g}] m", value=radius)
            # Outside the table's lock, which every call takes: the ground may be a terrain
            # service's answer, or a replay's terrain still opening (server/replay.py).
            centre = self._ground_point(lat, lon)
        with self._lock:
            if len(self._by_token) >= MAX_SESSIONS:
                raise LimitExceeded("sessions", len(self._by_token) + 1, MAX_SESSIONS)
            token = secrets.token_urlsafe(16)
            s = Session(token, name, role)
            if role == pb.ROLE_OBSERVER:
                s.observer_ecef = centre
                s.radius_m = float(radius)
            elif role == pb.ROLE_GATEWAY:  # sees everything: an infinite area of interest
                s.observer_ecef = np.zeros(3)
                s.radius_m = math.inf
            else:
                e = self._pick_agent(role, agent_name)
                self.world.claim(e.id, token, name)
                s.agent_id = e.id
                s.radius_m = self.params_of(e.id).aoi_radius_m
            self._by_token[token] = s
        self.world.emit("join", s.agent_id, client=name, role=pb.Role.Name(role))
        return s

    def _ground_point(self, lat: float, lon: float) -> np.ndarray:
        """ECEF of the ground at (lat, lon): an observer stands on the terrain (its MSL height
        plus the world's geoid undulation; the sea where there is no terrain), so a radius
        smaller than the terrain's height still holds what is around it. A world without a
        terrain (a replay whose recorded terrain did not open: server/replay.py) puts it at
        mean sea level."""
        terrain = getattr(self.world, "terrain", None)
        h = math.nan if terrain is None else float(np.asarray(
            terrain.heights(np.array([lat], float), np.array([lon], float)).height_msl_m)[0])
        h = (0.0 if h != h else h) + self.world.geoid_undulation_m
        return np.asarray(geodetic_to_ecef(lat, lon, h), float).reshape(3)

    def _pick_agent(self, role: int, agent_name: str):
        kinds = {pb.ROLE_PILOT: (AIRCRAFT,), pb.ROLE_DRIVER: (GROUND,), pb.ROLE_BOT: (AIRCRAFT, GROUND)}[role]
        entities = list(self.world.entities.values())
        if agent_name:
            for e in entities:
                if e.name == agent_name:
                    if e.kind not in kinds:
                        raise InvalidArgument("agent_name", f"is not an agent a {pb.Role.Name(role)} can take",
                                              value=agent_name)
                    if not e.controllable or e.owner is not None:
                        raise InvalidArgument("agent_name", "is not free to control", value=agent_name)
                    return e
            raise InvalidArgument("agent_name", "no agent of this name", value=agent_name)
        fit = [e for e in entities if e.kind in kinds and e.controllable and not self.world.is_wreck(e)]
        for e in fit:
            if e.owner is None:
                return e
        what = {pb.ROLE_PILOT: "aircraft", pb.ROLE_DRIVER: "ground vehicle"}.get(role, "aircraft or ground vehicle")
        raise LimitExceeded(f"{pb.Role.Name(role)[5:].lower()}_agents", len(fit) + 1, len(fit),
                            f"no free agent: every controllable {what} of the scenario is taken")

    def get(self, token: str) -> Session:
        with self._lock:
            s = self._by_token.get(token)
        if s is None:
            raise Unauthenticated("unknown or expired session token")
        s.last_seen = time.monotonic()
        return s

    def leave(self, token: str, vanished: bool = False) -> None:
        with self._lock:
            s = self._by_token.pop(token, None)
        if s is None:
            raise Unauthenticated("unknown or expired session token")
        s.left = True
        if s.queue is not None:
            s.queue.close(SESSION_LEFT)
        if s.agent_id:
            self.world.release(s.agent_id, vanished=vanished)
        if s.role == pb.ROLE_GATEWAY:
            self.world.remove_owned_external(s.token)
        self.world.emit("vanished" if vanished else "leave", s.agent_id, client=s.name)

    def watching(self) -> list[Session]:
        with self._lock:
            return [s for s in self._by_token.values() if s.queue is not None and not s.queue.closed]

    def expire(self) -> list[str]:
        """Release the sessions silent for longer than the timeout; their names."""
        now = time.monotonic()
        with self._lock:
            gone = [s for s in self._by_token.values()
                    if s.open_streams == 0 and now - s.last_seen > self.vanished_timeout_s]
        for s in gone:
            try:
                self.leave(s.token, vanished=True)
            except Unauthenticated:
                pass
        return [s.name for s in gone]

    def __len__(self) -> int:
        return len(self._by_token)


class EventBell:
    """Wakes the events streams when the world emits, as the publisher wakes the Watch streams.

    Each stream is a coroutine that awaits an asyncio.Event of its own (:meth:`add`). One
    thread waits on the event log's condition for all of them and, when the log grows, sets
    every stream's event with one call per event loop; so a waiting stream holds no thread
    (they used to wait on the thread pool Join, Leave and commands run on: 40 streams made
    each of those take 1.0-1.3 s). The thread runs while a stream is registered and ends
    within a second of the last one leaving.
    """

    def __init__(self, log):
        self.log = log  # server.world.EventLog: events_total, event_cond
        self._lock = threading.Lock()
        self._events: dict = {}  # asyncio.Event -> its loop
        self._thread: threading.Thread | None = None

    def add(self, loop) -> asyncio.Event:
        """A new stream's event (set on ``loop`` whenever the log grows); :meth:`remove` it after."""
        event = asyncio.Event()
        with self._lock:
            self._events[event] = loop
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="events-bell", daemon=True)
                self._thread.start()
        return event

    def remove(self, event) -> None:
        with self._lock:
            self._events.pop(event, None)

    def ring_all(self) -> None:
        """Wake every stream now (the server is stopping: they see it and end)."""
        with self._lock:
            for event, loop in list(self._events.items()):
                try:
                    loop.call_soon_threadsafe(event.set)
                except RuntimeError:  # its loop has closed
                    pass

    def _run(self) -> None:
        log = self.log
        seen = log.events_total
        while True:
            with log.event_cond:
                if log.events_total == seen:
                    log.event_cond.wait(1.0)
                total = log.events_total
            with self._lock:
                if not self._events:
                    self._thread = None  # under the lock: add() starts a new one from here on
                    return
                by_loop: dict = {}
                if total != seen:
                    for event, loop in self._events.items():
                        by_loop.setdefault(loop, []).append(event)
            seen = total
            for loop, events in by_loop.items():
                try:
                    loop.call_soon_threadsafe(lambda events=events: [e.set() for e in events])
                except RuntimeError:  # the loop has closed: nobody is reading
                    pass


def _decoded(request, what: str):
    """``request``, or INVALID_ARGUMENT with the decoder's reason when its bytes did not decode
    (grpc_common.tolerant_decoder; gRPC alone would answer UNKNOWN or INTERNAL)."""
    if isinstance(request, Malformed):
        raise InvalidArgument("request", f"does not decode as a {what}: {request.reason}")
    return request


@dataclass
class StreamStats:
    """What the Watch streams wrote (updated on the servicer's event loop only)."""

    messages: int = 0
    bytes: int = 0


class SimulationServicer:
    """The RPC handlers, as coroutines of one asyncio loop (grpc.aio).

    Every Watch stream is a coroutine, not a thread: at each network tick the
    publisher's pushes wake the loop once and it writes each stream's update
    in turn, with none of the per-message thread hand-offs of a thread-pool
    server (measured: with 32 streams those spread one tick's updates over
    about 14 ms). Calls that may wait on the world's lock (joining claims an
    agent, leaving releases one, commands queue under it while a tick runs)
    go to a small thread pool (``blocking``), so the loop never waits on a
    tick. ``world_info`` gives world info (time, rates, mode).
    """

    def __init__(self, sessions: Sessions, world_info, blocking=None, stream_stats: StreamStats | None = None):
        self.sessions = sessions
        self.stream_stats = stream_stats if stream_stats is not None else StreamStats()
        self.world = sessions.world
        self.world_info = world_info
        self.blocking = blocking  # concurrent.futures executor for calls that may block (None: the loop's default)
        self.bell = EventBell(self.world)
        # Set by close() (the server stops): events and client streams end OK at once, as Watch
        # streams do when their queues close, not when gRPC's grace runs out (UNAVAILABLE after 5 s).
        self.closed = False
        self._client_streams: dict = {}  # the tasks of the client streams open now -> their loops
        self._streams_lock = threading.Lock()

    def close(self) -> None:
        """The server is stopping: every stream this servicer serves ends now, OK (thread-safe):
        events streams see ``closed`` when the bell wakes them; client streams are cancelled where
        they wait for their next message, and answer with what they accepted (:meth:`_consume`)."""
        self.closed = True
        self.bell.ring_all()
        with self._streams_lock:
            streams = list(self._client_streams.items())
        for task, loop in streams:
            try:
                loop.call_soon_threadsafe(task.cancel)
            except RuntimeError:  # the loop has closed
                pass

    async def _offload(self, fn, *args):
        return await asyncio.get_running_loop().run_in_executor(self.blocking, fn, *args)

    @staticmethod
    async def _fail(context, error: Exception):
        code = status_of(error)
        if code == grpc.StatusCode.INTERNAL:
            logger.error("internal error in a simulation RPC", exc_info=error)
        await context.abort(code, message_of(error))

    async def Join(self, request, context):
        try:
            _decoded(request, "Join request")
            s = await self._offload(self.sessions.join, request.client_name, request.role, request.agent_name,
                                    (request.observer_lat_deg, request.observer_lon_deg, request.observer_radius_m))
            return pb.JoinResponse(session_token=s.token, agent_id=s.agent_id, world=self.world_info())
        except Exception as exc:  # noqa: BLE001 - every error becomes a status
            await self._fail(context, exc)

    async def Leave(self, request, context):
        try:
            _decoded(request, "Leave request")
            await self._offload(self.sessions.leave, request.session_token)
            return pb.LeaveResponse()
        except Exception as exc:  # noqa: BLE001
            await self._fail(context, exc)

    def _command(self, msg) -> None:
        s = self.sessions.get(msg.session_token)
        if not s.agent_id or msg.agent_id != s.agent_id:
            raise PermissionDenied(f"session {s.name!r} does not control entity {msg.agent_id}")
        which = msg.WhichOneof("command")
        if which is None:
            raise InvalidArgument("command", "set one of stick, autopilot, drive")
        sub = getattr(msg, which)
        self.world.command(s.agent_id, which, {f.name: v for f, v in sub.ListFields()}, owner=s.token)

    async def _consume(self, request_iterator, context, handle, response_class):
        """A client stream: each message handled in turn (on the thread pool); the first
        failure ends the stream with its status; else ``response_class(accepted=n)``."""
        accepted = 0
        what = f"{response_class.DESCRIPTOR.name.removesuffix('Response')} message"
        held: dict = {}  # the sessions whose messages this stream carried: alive while it is open
        task = asyncio.current_task()
        with self._streams_lock:
            self._client_streams[task] = asyncio.get_running_loop()
        try:
            if self.closed:
                return response_class(accepted=0)
            async for msg in request_iterator:
                await self._offload(handle, _decoded(msg, what))
                accepted += 1
                if msg.session_token not in held:
                    s = self.sessions.get(msg.session_token)  # handled: a session that exists
                    s.open_streams += 1
                    held[msg.session_token] = s
            return response_class(accepted=accepted)
        except asyncio.CancelledError:
            if not self.closed:
                raise
            return response_class(accepted=accepted)  # the server stops (close): the stream ends OK
        except Exception as exc:  # noqa: BLE001 - every error becomes a status
            await self._fail(context, exc)
        finally:
            with self._streams_lock:
                self._client_streams.pop(task, None)
            for s in held.values():
                s.open_streams -= 1
                s.last_seen = time.monotonic()  # its timeout runs from the stream's end

    async def SendControls(self, request_iterator, context):
        return await self._consume(request_iterator, context, self._command, pb.SendControlsResponse)

    def _publish_external(self, msg) -> None:
        s = self.sessions.get(msg.session_token)
        if s.role != pb.ROLE_GATEWAY:
            raise PermissionDenied(f"session {s.name!r} is not a gateway: only ROLE_GATEWAY sessions publish "
                                   "external entities")
        owner = self.world.external_owner(msg.external_id)
        if owner is not None and owner != s.token:
            raise PermissionDenied(f"external entity {msg.external_id!r} belongs to another gateway")
        if msg.remove:
            self.world.publish_external(msg.external_id, s.token, remove=True)
            return
        if not msg.HasField("state"):
            raise InvalidArgument("state", "is required unless remove is set")
        st = msg.state
        # The wire's unset values are accepted, as their refusals say (external_state and the
        # world, called from Python, take no unset value).
        if st.dead_reckoning != 0 and st.dead_reckoning not in EXTERNAL_ALGORITHM_NAMES:
            codes = ", ".join(f"{code} {name}" for code, name in sorted(EXTERNAL_ALGORITHM_NAMES.items()))
            raise InvalidArgument("state.dead_reckoning", f"must be a DIS dead-reckoning code ({codes}), or unset "
                                  f"(0) for {EXTERNAL_ALGORITHM_NAMES[UNSET_DEAD_RECKONING]}",
                                  value=st.dead_reckoning)
        if owner is None and msg.coalition not in ("", *COALITIONS):  # read on the first update only
            raise InvalidArgument("coalition", f"must be one of {', '.join(COALITIONS)}, or unset (\"\") for "
                                  f"{UNSET_COALITION}", value=msg.coalition)
        state = external_state(0.0, (st.ecef_x_m, st.ecef_y_m, st.ecef_z_m), st.velocity_ecef_mps,
                               st.acceleration_ecef_mps2 or (0.0, 0.0, 0.0), st.orientation_wxyz,
                               st.angular_velocity_body_rps or (0.0, 0.0, 0.0),
                               st.dead_reckoning or UNSET_DEAD_RECKONING)
        self.world.publish_external(msg.external_id, s.token, state, msg.name, msg.kind, msg.type,
                                    msg.coalition or UNSET_COALITION, destroyed=msg.destroyed)

    async def PublishExternal(self, request_iterator, context):
        return await self._consume(request_iterator, context, self._publish_external, pb.PublishExternalResponse)

    async def Watch(self, request, context):
        try:
            s = self.sessions.get(_decoded(request, "Watch request").session_token)
        except Exception as exc:  # noqa: BLE001
            await self._fail(context, exc)
            return
        if self.closed:  # the server is stopping: its clock publishes no more (the stream ends OK)
            return
        queue = ClientQueue(asyncio.get_running_loop())
        old = s.begin_stream(queue)
        if old is not None:
            old.close(SUPERSEDED)
        if s.left:  # a Leave between the token's check and begin_stream: nobody would close this queue
            queue.close(SESSION_LEFT)
        s.open_streams += 1
        try:
            while not context.done():
                queue.ready.clear()
                p = queue.take(0.0)  # at the server's end, what was pushed before it (the last state)
                s.last_seen = time.monotonic()
                if p is not None:
                    data = encode_watch_update(p)
                    await context.write(data)
                    self.stream_stats.messages += 1
                    self.stream_stats.bytes += len(data)
                    continue
                if queue.closed or self.closed:  # (a Watch that began as the server stopped: no queue close)
                    break
                try:  # asyncio.timeout, not wait_for: no task made per wait (3.11)
                    async with asyncio.timeout(STREAM_POLL_S):
                        await queue.ready.wait()
                except TimeoutError:
                    pass
        finally:
            s.open_streams -= 1
            queue.close()
        if queue.close_reason is not None:  # not the server's end: say why this stream ends
            await context.abort(grpc.StatusCode.ABORTED, queue.close_reason)

    async def WatchEvents(self, request, context):
        try:
            s = self.sessions.get(_decoded(request, "WatchEvents request").session_token)
            if s.event_streams >= MAX_EVENT_STREAMS:
                raise LimitExceeded("events_streams", s.event_streams + 1, MAX_EVENT_STREAMS,
                                    "WatchEvents streams open at once per session")
        except Exception as exc:  # noqa: BLE001
            await self._fail(context, exc)
            return
        s.open_streams += 1
        s.event_streams += 1
        log = self.world
        bell = self.bell.add(asyncio.get_running_loop())
        count = log.events_total  # events from now on
        try:
            while not context.done() and not s.left and not self.closed:
                bell.clear()
                s.last_seen = time.monotonic()
                if log.events_total != count:
                    events, count = log.events_since(count)
                    for ev in events:
                        await context.write(pb.WorldEvent(
                            time_s=ev.time_s, kind=ev.kind, entity_id=ev.entity_id, lat_deg=ev.lat_deg,
                            lon_deg=ev.lon_deg, alt_msl_m=ev.alt_msl_m,
                            detail_json=json.dumps(ev.detail, sort_keys=True, default=str)))
                    continue
                try:  # on the loop: a waiting stream holds no thread
                    async with asyncio.timeout(STREAM_POLL_S):
                        await bell.wait()
                except TimeoutError:
                    pass
        finally:
            self.bell.remove(bell)
            s.open_streams -= 1
            s.event_streams -= 1
        if s.left:
            await context.abort(grpc.StatusCode.ABORTED, SESSION_LEFT)

    async def GetWorld(self, request, context):
        try:
            _decoded(request, "GetWorld request")
            return self.world_info()
        except Exception as exc:  # noqa: BLE001
            await self._fail(context, exc)


def method_handlers(servicer: SimulationServicer) -> dict:
    def unary(fn, req):
        return grpc.unary_unary_rpc_method_handler(fn, request_deserializer=tolerant_decoder(req.FromString),
                                                   response_serializer=lambda m: m.SerializeToString())

    # Every request decoder is tolerant: undecodable bytes reach the handler as a
    # grpc_common.Malformed, which it answers INVALID_ARGUMENT with the decoder's reason.
    return {
        "Join": unary(servicer.Join, pb.JoinRequest),
        "Leave": unary(servicer.Leave, pb.LeaveRequest),
        "GetWorld": unary(servicer.GetWorld, pb.GetWorldRequest),
        "SendControls": grpc.stream_unary_rpc_method_handler(
            servicer.SendControls, request_deserializer=tolerant_decoder(pb.ControlInput.FromString),
            response_serializer=lambda m: m.SerializeToString()),
        "PublishExternal": grpc.stream_unary_rpc_method_handler(
            servicer.PublishExternal, request_deserializer=tolerant_decoder(pb.ExternalEntityUpdate.FromString),
            response_serializer=lambda m: m.SerializeToString()),
        "Watch": grpc.unary_stream_rpc_method_handler(
            servicer.Watch, request_deserializer=tolerant_decoder(pb.WatchRequest.FromString),
            response_serializer=bytes),  # updates come encoded (server.streaming.encode_watch_update)
        "WatchEvents": grpc.unary_stream_rpc_method_handler(
            servicer.WatchEvents, request_deserializer=tolerant_decoder(pb.WatchEventsRequest.FromString),
            response_serializer=lambda m: m.SerializeToString()),
    }
