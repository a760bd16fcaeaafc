"""Client library of the simulation service: join, command, watch, listen.

Used alike by bots, renderers, observers and tests::

    with SimClient("127.0.0.1:50051") as sim:
        sim.join("viper", "pilot")                      # takes a free aircraft
        picture = sim.watch()                           # background stream
        with sim.controls() as c:
            c.autopilot(heading_deg=270.0, alt_msl_m=2500.0)
        picture.wait_for(lambda p: len(p) > 0)
        ids, pos, quat = picture.state()                # dead-reckoned to now

:class:`Picture` is the receiver's side of the server's dead reckoning: the
last update of every entity in view, extrapolated on demand (server
dead_reckoning.Extrapolator) to the server's world time (estimated from the
stream: the last update's time plus the wall time since it arrived, times the
clock's scale).

How a stream ends: the server's end of the exercise ends it with no error
(:attr:`Picture.error` None); the server ends it with :class:`StreamAborted`
when it was superseded by a newer Watch of the same session or the session
left (the exercise goes on); :class:`PictureFailed` is this client's own failure
(a listener that raised: the call is cancelled); anything else (a server gone)
is the error of the failed call. An ended picture stays at the world time of
its last update (it is not extrapolated past it). A client stream
(:meth:`SimClient.controls`, :meth:`SimClient.external`) the server has ended
refuses further messages with its error, or :class:`StreamEnded`.

A picture never falls behind its stream (issue #4: a slow client loses intermediate
updates, never the latest state). Its stream's thread only reads and applies each update
(:meth:`Picture.state` is always the newest received); listeners run on a thread of their
own, and a listener slower than the stream is handed the updates that came meanwhile merged
into one (:class:`PendingUpdate`: each entity's latest state, every entity that came or
went, in order). Reading the stream at its rate matters: gRPC lets a reader that reads
slower than the stream fall behind without bound (it holds what the server sent in the
reader's own process, so the server's latest-wins merge never starts).

Closing a client (:meth:`SimClient.close`, the end of its ``with`` block) ends
everything it opened: its pictures and event iterators are cancelled, and its
controls and external streams that are still open are cancelled too (what they
had not sent yet is dropped: close a stream first to have the server take it
all). No thread of a closed client waits on.
"""

from __future__ import annotations

import collections
import queue
import threading
import time
from typing import TYPE_CHECKING

import grpc
import numpy as np

from client.terrain_client import ServiceError, error_from_rpc
from server.dead_reckoning import Extrapolator
from server.grpc_common import channel_options
from sortie.errors import InvalidArgument, SortieError
from sortie.v1 import simulation_pb2 as pb
from sortie.v1 import simulation_pb2_grpc as pb_grpc

if TYPE_CHECKING:
    from sortie.v1 import recording_pb2 as rpb

ROLES = {"pilot": pb.ROLE_PILOT, "driver": pb.ROLE_DRIVER, "observer": pb.ROLE_OBSERVER, "bot": pb.ROLE_BOT,
         "gateway": pb.ROLE_GATEWAY}
DEFAULT_TIMEOUT_S = 10.0


class StreamAborted(ServiceError):
    """The server ended a stream of this session for the session's own reason (a newer
    Watch of the session superseded it, the session left); the exercise goes on."""


class StreamEnded(SortieError):
    """A message for a client stream that has ended without an error (the server ended it:
    the exercise is over or the server stops; or this client closed it): it was not sent."""


class PictureFailed(SortieError):
    """A picture stopped by this client's own failure while applying an update (a listener
    raised, or the update could not be read): the original exception is ``cause``."""

    def __init__(self, time_s: float, cause: Exception):
        super().__init__(f"the picture stopped at world time {time_s:.1f} s: {type(cause).__name__}: {cause}")
        self.time_s = time_s
        self.cause = cause


def stream_error(error: grpc.RpcError):
    """The sortie error for a stream that failed: :class:`StreamAborted` for ABORTED."""
    if error.code() == grpc.StatusCode.ABORTED:
        return StreamAborted(grpc.StatusCode.ABORTED, error.details() or "")
    return error_from_rpc(error)


class SimClient:
    """One session with a simulation server."""

    def __init__(self, address: str, timeout_s: float = DEFAULT_TIMEOUT_S):
        """``address``: HOST:PORT, the port in 1..65535 (else InvalidArgument "address": gRPC
        keeps a port's low 16 bits, so 99999 would join the server on 34463), or a gRPC target
        with a scheme (unix:PATH)."""
        from server.health_cli import check_address

        check_address(address)
        self.address = address
        self.timeout_s = timeout_s
        self.channel = grpc.insecure_channel(address, options=channel_options())
        self.stub = pb_grpc.SimulationServiceStub(self.channel)
        self.token = ""
        self.agent_id = 0
        self.world_info: pb.WorldInfo | None = None
        self._streams: list = []  # the server streams: pictures (Watch) and WatchEvents calls
        self._request_streams: set = set()  # the client streams still open (_RequestStream)
        self._request_streams_lock = threading.Lock()  # they leave the set on gRPC's thread

    def __enter__(self) -> SimClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _keep_stream(self, stream) -> None:
        """Keep a server stream for close(), dropping those that have ended (a client taking a
        new Watch now and then kept every picture it ever had)."""
        self._streams = [s for s in self._streams if (s.alive if isinstance(s, Picture) else not s.done())]
        self._streams.append(stream)

    def close(self) -> None:
        """End every stream this client opened (server streams and client streams still
        open: cancelled, a client stream's unsent messages dropped), then the channel."""
        for s in self._streams:
            s.cancel()
        with self._request_streams_lock:
            open_streams = list(self._request_streams)
        for r in open_streams:
            r.cancel()
        self.channel.close()

    def _track(self, stream: _RequestStream, is_open: bool) -> None:
        """A client stream opened (is_open) or ended: the ones close() must end."""
        with self._request_streams_lock:
            if is_open:
                self._request_streams.add(stream)
            else:
                self._request_streams.discard(stream)

    def wait_ready(self, timeout_s: float = 10.0) -> None:
        """Block until the channel is connected; ServiceError(UNAVAILABLE) after timeout_s."""
        try:
            grpc.channel_ready_future(self.channel).result(timeout=timeout_s)
        except grpc.FutureTimeoutError:
            raise ServiceError(grpc.StatusCode.UNAVAILABLE,
                               f"no simulation server at {self.address} within {timeout_s:g} s") from None

    def _call(self, fn, request):
        try:
            return fn(request, timeout=self.timeout_s)
        except grpc.RpcError as exc:
            raise error_from_rpc(exc) from None

    # -- session --------------------------------------------------------------------------------

    def join(self, name: str, role: str = "observer", agent_name: str = "",
             observer: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> int:
        """Join as "pilot", "driver", "bot", "observer" (observer = (lat, lon, radius_m)) or
        "gateway" (sees every entity, publishes external ones: :meth:`external`); the agent
        id (0 for observers and gateways)."""
        if role not in ROLES:
            raise InvalidArgument("role", f"must be one of {', '.join(ROLES)}", value=role)
        r = self._call(self.stub.Join, pb.JoinRequest(client_name=name, role=ROLES[role], agent_name=agent_name,
                                                      observer_lat_deg=observer[0], observer_lon_deg=observer[1],
                                                      observer_radius_m=observer[2]))
        self.token, self.agent_id, self.world_info = r.session_token, r.agent_id, r.world
        return self.agent_id

    def leave(self) -> None:
        self._call(self.stub.Leave, pb.LeaveRequest(session_token=self.token))
        self.token = ""

    def world(self) -> pb.WorldInfo:
        return self._call(self.stub.GetWorld, pb.GetWorldRequest())

    # -- replay controls (sortie replay: sortie.v1.ReplayService) --------------------------------

    def replay(self, **action) -> "rpb.ReplayStatus":
        """One replay control: play=True, pause=True, speed=X (0.1-64), seek_time_s=S or
        step_ticks=N (pauses); the replay's status after it. UNIMPLEMENTED on a live server."""
        from sortie.v1 import recording_pb2 as rpb
        from sortie.v1 import recording_pb2_grpc as rpb_grpc

        if len(action) != 1:
            raise InvalidArgument("action", "give exactly one of play, pause, speed, seek_time_s, step_ticks",
                                  value=sorted(action))
        return self._call(rpb_grpc.ReplayServiceStub(self.channel).Control, rpb.ReplayControl(**action))

    def replay_status(self) -> "rpb.ReplayStatus":
        from sortie.v1 import recording_pb2 as rpb
        from sortie.v1 import recording_pb2_grpc as rpb_grpc

        return self._call(rpb_grpc.ReplayServiceStub(self.channel).GetStatus, rpb.GetReplayStatusRequest())

    # -- commands -------------------------------------------------------------------------------

    def controls(self) -> ControlStream:
        """A client-streaming controls call; send with .stick/.autopilot/.drive, close() when done."""
        return ControlStream(self)

    def external(self) -> ExternalStream:
        """A gateway's client stream of external entities; close() when done."""
        return ExternalStream(self)

    # -- watching -------------------------------------------------------------------------------

    def watch(self, listener=None) -> Picture:
        """Start the Watch stream in a background thread; the live picture it maintains.
        ``listener(picture, update)`` is called with the updates in order, the snapshot first,
        those that came while it was busy merged into one (see Picture.listeners)."""
        call = self.stub.Watch(pb.WatchRequest(session_token=self.token))
        picture = Picture(call, self.world_info.time_scale if self.world_info else 1.0)
        self._keep_stream(picture)  # close() cancels it: what its listeners have not had is dropped
        if listener is not None:
            picture.listeners.append(listener)
        picture.start()
        return picture

    def events(self):
        """Iterator over world events from now on (a server stream; cancel by close())."""
        call = self.stub.WatchEvents(pb.WatchEventsRequest(session_token=self.token))
        self._keep_stream(call)
        try:
            yield from call
        except grpc.RpcError as exc:
            if exc.code() != grpc.StatusCode.CANCELLED:
                raise stream_error(exc) from None


class _RequestStream:
    """One client-streaming call fed from a queue: messages go out in order on gRPC's
    thread; :meth:`close` ends the stream and returns the server's answer, :meth:`cancel`
    ends it at once (SimClient.close() cancels the ones still open). A message for a
    stream that has ended raises (the stream's error, else :class:`StreamEnded`): the server
    reads no more of it, so it would be lost."""

    def __init__(self, client: SimClient, rpc, name: str):
        self.client = client
        self.name = name  # the RPC, for messages
        self._closed_here = False  # close() or cancel() ended the stream, not the server
        self._q: queue.Queue = queue.Queue()
        self._future = rpc.future(self._messages())
        client._track(self, True)
        # gRPC reads _messages on a thread of its own (grpc/_channel.py consume_request_iterator)
        # that looks at the call's state only between messages: blocked in the queue's get(), it
        # waited forever once the call had ended (the server ended it, it failed, it was
        # cancelled). So the call's end ends the messages (at once if it has ended already).
        self._future.add_done_callback(self._ended)

    def _ended(self, _future) -> None:
        self._q.put(None)
        self.client._track(self, False)

    def _messages(self):
        while True:
            msg = self._q.get()
            if msg is None:
                return
            yield msg

    def _put(self, msg) -> None:
        if self._future.done():  # ended: a failed stream's error (e.g. a bad message) says why
            try:
                accepted = self.close()
            except StreamEnded as exc:  # cancelled here: no count
                raise StreamEnded(f"{exc}: this message was not sent") from None
            who = ("this client closed it" if self._closed_here
                   else "the server ended it: the exercise is over or the server stops")
            raise StreamEnded(f"{self.name}: the stream has ended ({who}; {accepted} messages accepted): this "
                              "message was not sent")
        self._q.put(msg)

    def _finish(self):
        self._closed_here = self._closed_here or not self._future.done()
        self._q.put(None)
        try:
            return self._future.result(timeout=self.client.timeout_s)
        except grpc.FutureCancelledError:
            raise StreamEnded(f"{self.name}: the stream has ended (this client cancelled it: SimClient.close() or "
                              "cancel(); the server's count of accepted messages is unknown)") from None
        except grpc.RpcError as exc:
            raise error_from_rpc(exc) from None

    def close(self) -> int:
        """End the stream; the number of messages the server accepted (raises its error)."""
        return self._finish().accepted

    def cancel(self) -> None:
        """End the stream now, without the server's answer: messages not yet sent are
        dropped (a stream that has ended is left as it is)."""
        self._closed_here = self._closed_here or not self._future.done()
        self._q.put(None)  # gRPC's thread ends now, not when (if: the channel may close first) the call's end comes
        self._future.cancel()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


class ControlStream(_RequestStream):
    """Latest-wins commands for the session's agent over one client stream."""

    def __init__(self, client: SimClient):
        super().__init__(client, client.stub.SendControls, "SendControls")

    def _send(self, **command) -> None:
        self._put(pb.ControlInput(session_token=self.client.token, agent_id=self.client.agent_id, **command))

    def stick(self, **values) -> None:
        self._send(stick=pb.StickControls(**values))

    def autopilot(self, **targets) -> None:
        self._send(autopilot=pb.AutopilotTargets(**targets))

    def drive(self, speed_mps: float, yaw_rate_dps: float = 0.0) -> None:
        self._send(drive=pb.DriveControls(speed_mps=speed_mps, yaw_rate_dps=yaw_rate_dps))


KINDS = {"aircraft": pb.ENTITY_KIND_AIRCRAFT, "ground": pb.ENTITY_KIND_GROUND, "static": pb.ENTITY_KIND_STATIC}


class ExternalStream(_RequestStream):
    """A gateway's external entities (PublishExternal): :meth:`update` adds or moves one,
    :meth:`remove` takes it out."""

    def __init__(self, client: SimClient):
        super().__init__(client, client.stub.PublishExternal, "PublishExternal")

    def update(self, external_id: str, *, ecef_m, vel_ecef_mps, quat_wxyz, acc_ecef_mps2=(0.0, 0.0, 0.0),
               body_rates_rps=(0.0, 0.0, 0.0), algorithm: int = pb.DEAD_RECKONING_ALGORITHM_FPW, name: str = "",
               kind: str = "aircraft", type: str = "", coalition: str = "neutral",  # noqa: A002
               destroyed: bool = False) -> None:
        """The entity's state now: ecef_m (3,) m, vel_ecef_mps (3,), acc_ecef_mps2 (3,) ECEF
        (body axes for a body-axis algorithm); quat_wxyz (4,) ECEF -> body; body_rates_rps (3,)
        body axes; a DIS algorithm (1-5 world axes, 6-9 body axes). name, kind ("aircraft",
        "ground", "static"), type and coalition are read on the entity's first update.
        destroyed: its simulation says it is destroyed (a wreck from then on)."""
        if kind not in KINDS:
            raise InvalidArgument("kind", f"must be one of {', '.join(KINDS)}", value=kind)
        x, y, z = (float(v) for v in ecef_m)
        state = pb.EntityState(ecef_x_m=x, ecef_y_m=y, ecef_z_m=z, velocity_ecef_mps=list(map(float, vel_ecef_mps)),
                               acceleration_ecef_mps2=list(map(float, acc_ecef_mps2)),
                               orientation_wxyz=list(map(float, quat_wxyz)),
                               angular_velocity_body_rps=list(map(float, body_rates_rps)), dead_reckoning=algorithm)
        self._put(pb.ExternalEntityUpdate(session_token=self.client.token, external_id=external_id, name=name,
                                          kind=KINDS[kind], type=type, coalition=coalition, state=state,
                                          destroyed=bool(destroyed)))

    def remove(self, external_id: str) -> None:
        self._put(pb.ExternalEntityUpdate(session_token=self.client.token, external_id=external_id, remove=True))


def _copy(message):
    """A message of its own (a sub-message read from an update keeps the whole update's
    memory alive: one entity's latest state could hold a minutes-old update)."""
    c = type(message)()
    c.CopyFrom(message)
    return c


class PendingUpdate:
    """Consecutive WatchUpdates not yet handed to a picture's listeners, as one update: what
    a listener slower than the stream gets (issue #4: intermediate updates may be lost, never
    the latest state).

    Merged: the latest world time and clock rate (``time_scale``, when one of them carried
    it); each entity's latest state (its earlier ones are lost); every entity that entered
    (its info as it came) and every one that left, with its states before leaving dropped,
    so a listener that reads ``left``, then ``entered``, then ``states`` (the order an update
    is applied in) ends with the picture the updates end with. Not merged: a snapshot (a new
    picture: it starts a PendingUpdate of its own), and an update where an entity leaves that
    entered in the updates held (the listener would never see it come and go: it goes in the
    next PendingUpdate). So nothing that comes or goes, and no snapshot, is lost, and those
    stay in order; a pause or resume shows as the latest ``time_scale``. Held while the
    listener is busy: one state per entity in view in each PendingUpdate, and a PendingUpdate
    more for each snapshot or come-and-go meanwhile."""

    def __init__(self, update: pb.WatchUpdate):
        self._alone: pb.WatchUpdate | None = update  # handed over as it came while nothing joins it
        self.count = 1  # updates merged
        self.time_s = update.time_s
        self.snapshot = update.snapshot
        self.time_scale = update.time_scale if update.HasField("time_scale") else None
        self._entered: dict[int, pb.EntityInfo] = {}
        self._left: dict[int, None] = {}  # ordered, unique
        self._states: dict[int, pb.EntityState] = {}

    def _unpack(self) -> None:
        u, self._alone = self._alone, None
        self._entered = {i.entity_id: _copy(i) for i in u.entered}
        self._left = dict.fromkeys(u.left)
        self._states = {s.entity_id: _copy(s) for s in u.states}

    def merge(self, update: pb.WatchUpdate) -> bool:
        """Take ``update`` (the next one of the stream) in; False where it must be handed
        over on its own, after this one (a snapshot, or one of the entities that entered
        here leaving)."""
        if update.snapshot:
            return False
        if update.left:
            entered = self._entered if self._alone is None else {e.entity_id for e in self._alone.entered}
            if any(i in entered for i in update.left):
                return False
        if self._alone is not None:
            self._unpack()
        for i in update.left:
            self._states.pop(i, None)
            self._left[i] = None
        for info in update.entered:
            self._entered[info.entity_id] = _copy(info)
        for state in update.states:
            self._states[state.entity_id] = _copy(state)
        self.time_s = update.time_s
        if update.HasField("time_scale"):
            self.time_scale = update.time_scale
        self.count += 1
        return True

    def update(self) -> pb.WatchUpdate:
        """The merged update (the one update itself while nothing joined it)."""
        if self._alone is not None:
            return self._alone
        u = pb.WatchUpdate(time_s=self.time_s, snapshot=self.snapshot, entered=list(self._entered.values()),
                           left=list(self._left), states=list(self._states.values()))
        if self.time_scale is not None:
            u.time_scale = self.time_scale
        return u


class Picture:
    """What one session sees: entity infos and their dead-reckoned states."""

    def __init__(self, call, time_scale: float):
        self._call = call
        self.time_scale = time_scale
        self.infos: dict[int, pb.EntityInfo] = {}
        self.dr = Extrapolator()
        self.updates = 0  # WatchUpdate messages received
        self.states_received = 0
        self.entered = 0
        self.left = 0
        self.bytes = 0
        self.time_s = 0.0  # world time of the last update
        self._wall = time.monotonic()
        self.wall_log: list = []  # (world time of the update, time.time() it arrived): latency measurements
        # Why the stream ended, once it has: None for the server's end of the exercise,
        # StreamAborted for a newer Watch of the session or the session's Leave, PictureFailed
        # for this client's own failure (a listener's exception), else the call's error.
        self.error: Exception | None = None
        self.snapshot_received = threading.Event()
        # Called as fn(picture, update) for the updates in order, on the picture's listener
        # thread (one a picture, started with the first update that finds a listener here),
        # not under the picture's lock: the stream's thread never waits for a listener, so the
        # picture may already hold newer updates than the one a listener is given. A listener
        # still busy when updates come gets them merged into one (PendingUpdate: each entity's
        # latest state; what came or went, and snapshots, all in order). Updates a listener
        # has not had yet are dropped when the picture is cancelled (SimClient.close()), and
        # handed over when the stream ends otherwise.
        self.listeners: list = []
        self._cond = threading.Condition()
        self._thread = threading.Thread(target=self._run, name="watch", daemon=True)
        self._handover = threading.Condition()  # the updates for the listeners, and their thread's end
        self._pending: collections.deque[PendingUpdate] = collections.deque()
        self._stream_over = False
        self._listener_thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread.start()

    def __len__(self) -> int:
        return len(self.infos)

    def _receive(self, states) -> None:
        if not states:
            return
        ids, algorithms, rows = [], [], []  # rows: Extrapolator.receive_rows' 17 columns, flat
        for s in states:  # [:] copies a repeated field to a list, several times faster than iterating it
            v, a, q, w = (s.velocity_ecef_mps[:], s.acceleration_ecef_mps2[:], s.orientation_wxyz[:],
                          s.angular_velocity_body_rps[:])
            if len(v) != 3 or len(a) != 3 or len(q) != 4 or len(w) != 3:
                break  # a field of the wrong length: the field-by-field path below names it
            ids.append(s.entity_id)
            algorithms.append(s.dead_reckoning)
            rows += (s.time_s, s.ecef_x_m, s.ecef_y_m, s.ecef_z_m, *v, *a, *q, *w)
        else:
            self.dr.receive_rows(np.array(ids, np.int64), np.array(rows, np.float64).reshape(-1, 17),
                                 np.array(algorithms, np.int64))
            return
        self.dr.receive(np.array([s.time_s for s in states]), np.array([s.entity_id for s in states], np.int64),
                        np.array([[s.ecef_x_m, s.ecef_y_m, s.ecef_z_m] for s in states]),
                        np.array([s.velocity_ecef_mps for s in states], np.float64),
                        np.array([s.acceleration_ecef_mps2 for s in states], np.float64),
                        np.array([s.orientation_wxyz for s in states], np.float64),
                        np.array([s.angular_velocity_body_rps for s in states], np.float64),
                        np.array([s.dead_reckoning for s in states], np.int64))

    def _run(self) -> None:
        try:
            for u in self._call:
                now, arrived = time.monotonic(), time.time()  # on receipt, before any processing
                with self._cond:
                    self.bytes += u.ByteSize()
                    if u.snapshot and self.infos:  # a new snapshot (a replay's seek) replaces the picture
                        self.dr.remove(self.dr.ids)
                        self.infos = {}
                    for i in u.left:
                        self.infos.pop(i, None)
                    if u.left:
                        held = set(self.dr.ids.tolist())
                        gone = [i for i in u.left if i in held]
                        if gone:
                            self.dr.remove(gone)
                    for info in u.entered:
                        self.infos[info.entity_id] = info
                    self._receive([info.state for info in u.entered] + list(u.states))
                    self.updates += 1
                    self.states_received += len(u.states)
                    self.entered += len(u.entered)
                    self.left += len(u.left)
                    self.time_s, self._wall = u.time_s, now
                    if u.HasField("time_scale"):  # the server's clock rate now (0: paused)
                        self.time_scale = u.time_scale
                    self.wall_log.append((u.time_s, arrived))
                    if len(self.wall_log) > 100_000:
                        del self.wall_log[:50_000]
                    if u.snapshot:
                        self.snapshot_received.set()
                    self._cond.notify_all()
                if self.listeners:
                    self._hand_over(u)
        except grpc.RpcError as exc:
            cancelled = exc.code() == grpc.StatusCode.CANCELLED
            if not cancelled:
                with self._cond:
                    if self.error is None:  # a listener's failure came first: it stays the reason
                        self.error = stream_error(exc)  # StreamAborted: superseded, or the session left
            self._end_listening(drop=cancelled)
        except Exception as exc:  # noqa: BLE001 - this client's own failure ends its picture, said in error
            with self._cond:
                if self.error is None:
                    self.error = PictureFailed(self.time_s, exc)
            self._call.cancel()  # the server stops sending to a picture that no longer reads
            self._end_listening(drop=False)  # the updates before this one are the listeners' still
        else:
            self._end_listening(drop=False)
        finally:
            with self._cond:
                # Nothing is known past the last update: its world time is the picture's from now on
                # (now_s() and state() do not extrapolate beyond the stream's end).
                self.time_scale = 0.0
                self._cond.notify_all()

    def _hand_over(self, update: pb.WatchUpdate) -> None:
        """Give an update to the listener thread: merged into the one it has not taken yet
        where it can be (PendingUpdate.merge), else after it."""
        with self._handover:
            if self._stream_over:  # cancelled: the listeners are given nothing more
                return
            if not (self._pending and self._pending[-1].merge(update)):
                self._pending.append(PendingUpdate(update))
            if self._listener_thread is None:
                self._listener_thread = threading.Thread(target=self._listen, name="watch-listeners", daemon=True)
                self._listener_thread.start()
            self._handover.notify()

    def _end_listening(self, drop: bool) -> None:
        """The stream has ended: the listener thread ends once it has handed over what is
        pending (at once, the pending dropped, where ``drop``)."""
        with self._handover:
            if drop:
                self._pending.clear()
            self._stream_over = True
            self._handover.notify()

    def _listen(self) -> None:
        """The listener thread: each pending update to every listener, in order, until the
        stream has ended and nothing is pending; a listener that raises ends the picture
        (PictureFailed, the call cancelled, what is pending dropped)."""
        try:
            while True:
                with self._handover:
                    while not self._pending and not self._stream_over:
                        self._handover.wait()
                    if not self._pending:
                        return
                    update = self._pending.popleft().update()
                try:
                    for fn in list(self.listeners):
                        fn(self, update)
                except Exception as exc:  # noqa: BLE001 - this client's own failure ends its picture, said in error
                    with self._cond:  # it came before whatever ended the stream since: it is the reason
                        if not isinstance(self.error, PictureFailed):
                            self.error = PictureFailed(update.time_s, exc)
                    self._end_listening(drop=True)
                    self._call.cancel()  # the server stops sending to a picture that no longer reads
                    return
                with self._cond:  # wait_for's predicates may look at what listeners did
                    self._cond.notify_all()
        finally:
            with self._cond:
                self._cond.notify_all()

    @property
    def alive(self) -> bool:
        """Whether the stream is still running, or its listeners still have updates to take
        (False once the server ended it or it failed, and they have had them: see
        :attr:`error`)."""
        listening = self._listener_thread
        return self._thread.is_alive() or (listening is not None and listening.is_alive())

    def now_s(self) -> float:
        """Estimated world time now (last update's time + scaled wall time since); once the
        stream has ended, the last update's time."""
        return self.time_s + (time.monotonic() - self._wall) * self.time_scale

    def state(self, t: float | None = None, ids=None):
        """(ids, pos (n, 3) ECEF m, quat (n, 4) ECEF -> body) dead-reckoned to world time t (default now)."""
        with self._cond:
            ids = self.dr.ids if ids is None else np.asarray(ids, np.int64)
            if ids.size == 0:
                return ids, np.zeros((0, 3)), np.zeros((0, 4))
            pos, quat = self.dr.state(self.now_s() if t is None else t, ids)
            return ids, pos, quat

    def wait_for(self, predicate, timeout_s: float = 10.0) -> bool:
        """Wait until predicate(self) holds (checked on every update); whether it did."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while not predicate(self):
                left = deadline - time.monotonic()
                if left <= 0 or not self.alive:
                    return bool(predicate(self))
                self._cond.wait(min(left, 0.5))
            return True

    def cancel(self) -> None:
        """End the stream now; the listeners are given nothing more (a call under way
        finishes)."""
        self._end_listening(drop=True)
        self._call.cancel()
