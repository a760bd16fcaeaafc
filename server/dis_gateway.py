"""``sortie dis``: a DIS (IEEE 1278.1) gateway between a simulation server and a DIS exercise.

    sortie dis --server ADDRESS [--port 3000] [--exercise N] [--host 127.255.255.255]
               [--site S --application A] [--remote-timeout-s 15] [--heartbeat-s 5]

Out. The gateway joins the server as a gateway session (every entity of the
exercise, no area of interest) and turns each state the Watch stream brings
into one Entity State PDU (server/dis.py): the server already sends a state
only when DIS-style dead reckoning drifts past 1 m / 3 degrees or its 5 s
heartbeat is due, which are the DIS rules for issuing Entity State PDUs (IEEE
1278.1-2012: DRA_POS_THRESH, DRA_ORIENT_THRESH, HBT_PDU_ENTITY_STATE; Annex E), so
nothing is re-decided here. The entity id is
(--site, --application, Sortie's entity id); an entity whose id does not fit a
DIS entity number (above 65534) is refused with one log line. An entity that
leaves the exercise gets one last PDU with the appearance's "deactivated"
bit; so does every entity when the gateway stops. If the server sends
nothing about an entity for --heartbeat-s wall seconds (a paused or slowed
clock), a heartbeat PDU says where it is now, so DIS receivers do not time it
out: its last state dead-reckoned to the world time now (the Watch stream's
estimate), with that time's timestamp. While the world clock is paused
(WatchUpdate.time_scale 0) every PDU, heartbeats included, says the entity
stands still (velocity, acceleration and body rates 0), sent to every entity
the moment the pause (and its end) is known, so DIS receivers freeze it where
the world holds it instead of dead-reckoning it on.
Entities that came from outside (``EntityInfo.external_id`` set, e.g. from
this very gateway) are never sent back out. The gateway also reads the
server's events: an entity that crashes or is destroyed is sent at once, and
from then on, with the appearance's damage "destroyed"; each collision event of an entity
it speaks for is issued as a Collision PDU (IEEE 1278.1-2012 §7.2.3) naming
the other entity (a DIS entity by its own id) with the issuer's velocity at
the collision (its last state at or before the event, not the last PDU, which
may be the wreck's at rest: the events come on a stream of their own), so
every DIS simulation hears of the collision from the owner of each entity in
it, as the standard has it.

In. PDUs of our exercise from other (site, application) pairs are decoded
and each Entity State PDU is published into the exercise through the
session's PublishExternal stream as the external entity "dis:<site>.<app>.<entity>"
(name = marking, kind and type from the entity type, coalition from the force,
the PDU's own dead reckoning, body axes included, which the world
extrapolates natively: server/external.py; a static entity's with no motion;
a damage "destroyed" appearance makes it a wreck). DIS markings are not
unique and world names are: a
marking another entity already has becomes "<marking> <site>.<app>.<entity>"
(dis.unique_name). The server ends a PublishExternal stream at the first
update it refuses; the gateway then opens another, sends the update that met
the ended stream again, and keeps tracking every remote entity it published
(they stay in the world under the gateway's session), so one refused entity
never costs another its update, timeout or removal. A remote entity is removed when its PDU says
deactivated or after --remote-timeout-s without a PDU: by default 15 s, the
three missed 5 s heartbeats issue #8 asks for (IEEE 1278.1-2012's own
default is HBT_TIMEOUT_MPLIER 2.4 times HBT_PDU_ENTITY_STATE, 12 s; 15 s
keeps a remote entity through one more late heartbeat). Other PDU types,
other exercises and our own PDUs are counted as ignored; so is a foreign
simulation's PDU that carries our own site and application (its entities
cannot be told from ours: one warning names them and the options that set
ours). Malformed ones -- undecodable, of an unsupported protocol version (4
and older), or naming no one entity (a reserved Entity ID such as
65535.65535.65535 ALL_ENTITIES, logged once per id) -- are counted and logged
(at most one line per LOG_EVERY_S) and never stop the gateway; one bad PDU
of a datagram never costs the others in it (dis.read_datagram).

Network. One UDP socket bound to (--host, --port) with SO_REUSEADDR and
SO_REUSEPORT receives; PDUs go out to the same address and port. A burst of
PDUs (a simulation joining with a thousand entities) must not overflow the
socket: it asks for an 8 MiB receive buffer (RECEIVE_BUFFER_BYTES: without
CAP_NET_ADMIN Linux grants at most twice net.core.rmem_max, and the gateway
logs what it got, with a warning when that is less) and
one thread does nothing but move datagrams from the socket into a bounded
queue that another thread decodes and publishes. What is lost anyway is
counted (pdus_dropped) and logged: the kernel's own count of datagrams the
full socket dropped (SO_RXQ_OVFL, Linux) and the queue's overflow. The default
host 127.255.255.255 is the loopback broadcast address: datagrams sent there
are delivered to every socket bound to it on this machine (several gateways,
a DIS viewer, tests) and to nothing outside it. A unicast host such as
127.0.0.1 works for a single receiver only: the kernel hands a unicast
datagram to one of the sockets sharing a port. A LAN broadcast address
(e.g. 192.168.1.255) joins a DIS exercise on that network.

Counters (:class:`DisGateway`): pdus_sent; pdus_received (every PDU that
arrived, our own looped-back broadcasts included); pdus_ignored (other
exercise, our own, not an Entity State PDU); pdus_malformed; pdus_dropped
(datagrams lost before they were read); and the number of remote and local
entities.
"""

from __future__ import annotations

import bisect
import collections
import dataclasses
import datetime as dt
import json
import logging
import socket
import sys
import threading
import time

import grpc
import numpy as np

from server import dis
from server.dead_reckoning import FVW, RVW, extrapolate
from server.external import external_state
from sortie.errors import DataFormatError, InvalidArgument, SortieError
from sortie.logs import line
from sortie.v1 import simulation_pb2 as pb

log = logging.getLogger(__name__)

DEFAULT_HOST = "127.255.255.255"  # loopback broadcast: every socket on the port, this machine only
DEFAULT_EXERCISE = 1
DEFAULT_SITE = 1
DEFAULT_APPLICATION = 1
# Three missed HBT_PDU_ENTITY_STATE (5 s) heartbeats, as issue #8 asks; IEEE 1278.1-2012's default
# timeout is HBT_TIMEOUT_MPLIER (2.4) heartbeats, 12 s (the module docstring).
DEFAULT_REMOTE_TIMEOUT_S = 15.0
DEFAULT_HEARTBEAT_S = 5.0  # IEEE 1278.1-2012 HBT_PDU_ENTITY_STATE
MAX_ENTITY_NUMBER = 65534  # 0 is NO_ENTITY and 65535 ALL_ENTITIES (IEEE 1278.1-2012 Entity Identifier)
RECEIVE_BYTES = 65536  # a UDP datagram's largest payload
# Linux charges a datagram its buffer's true size: about 830 bytes for a 144-byte Entity State
# PDU on loopback (the default SO_RCVBUF, 212,992 bytes, held 256 of a burst).
KERNEL_BYTES_PER_PDU = 830
# The receive buffer asked for: a burst of about 10,000 Entity State PDUs. Linux books twice
# what is asked (half for its own overhead); SO_RCVBUF grants at most net.core.rmem_max
# (212,992 bytes by default), SO_RCVBUFFORCE (option 33, include/uapi/asm-generic/socket.h;
# Python's socket module does not name it) any size, to a process with CAP_NET_ADMIN (root),
# as systemd-journald sizes its sockets.
RECEIVE_BUFFER_BYTES = 8 << 20
SO_RCVBUFFORCE = 33
# Datagrams read from the socket and not yet decoded, at most (bytes): a burst the decoding
# thread has not caught up with, without letting a flood of 64 KiB datagrams take the memory.
RECEIVE_QUEUE_BYTES = 16 << 20
# Linux include/uapi/asm-generic/socket.h: with this option set, a received datagram carries a
# SOL_SOCKET control message with the socket's count of datagrams dropped so far (u32); Python's
# socket module does not name it.
SO_RXQ_OVFL = 40
# Reserved Entity IDs logged one line each, at most; beyond, through the throttled malformed log.
MAX_LOGGED_IDS = 256
POLL_S = 0.2  # how often the threads look at the stop flag, heartbeats and timeouts
LOG_EVERY_S = 5.0  # at most one line per kind of receive problem per this many seconds
# States kept per local entity, newest last, for the velocity of a Collision PDU: the events stream
# runs on its own, so a collision's event may come after states of later ticks (a wreck's, at rest).
# The Watch stream brings a state at most per network update (20 Hz by default) and the event
# follows its tick's states within one: 16 is over half a second of updates.
STATE_HISTORY = 16
KINDS = {pb.ENTITY_KIND_AIRCRAFT: "aircraft", pb.ENTITY_KIND_GROUND: "ground", pb.ENTITY_KIND_STATIC: "static"}


class _Throttled:
    """A warning that says itself at most once per ``every_s`` and counts what it held back."""

    def __init__(self, every_s: float = LOG_EVERY_S):
        self.every_s = every_s
        self._next = 0.0
        self._held = 0

    def warn(self, message: str, *args) -> None:
        now = time.monotonic()
        if now < self._next:
            self._held += 1
            return
        if self._held:
            message += f" ({self._held} more since the last report)"
        log.warning(message, *args)
        self._next, self._held = now + self.every_s, 0


class _Inbox:
    """Datagrams between the socket's reader and their decoder: first in, first out, at most
    ``max_bytes`` held (put() says False when one would not fit: the caller counts it)."""

    def __init__(self, max_bytes: int | None = None):
        self.max_bytes = RECEIVE_QUEUE_BYTES if max_bytes is None else max_bytes
        self._items: collections.deque = collections.deque()
        self._bytes = 0
        self._cond = threading.Condition()

    def put(self, data: bytes) -> bool:
        with self._cond:
            if self._bytes + len(data) > self.max_bytes:
                return False
            self._items.append(data)
            self._bytes += len(data)
            self._cond.notify()
            return True

    def get(self, timeout_s: float) -> bytes | None:
        """The oldest datagram, or None after ``timeout_s`` with none."""
        with self._cond:
            if not self._items and not self._cond.wait(timeout_s):
                return None
            if not self._items:
                return None
            data = self._items.popleft()
            self._bytes -= len(data)
            return data


@dataclasses.dataclass
class _Local:
    """A Sortie entity the gateway speaks for: what does not change, the last PDU sent."""

    kind: str
    type_name: str
    coalition: str
    name: str
    pdu: dis.EntityStatePdu | None = None
    wire: bytes = b""
    sent_wall_s: float = 0.0
    state: pb.EntityState | None = None  # the server's last state of it, which heartbeats dead-reckon
    paused: bool = False  # whether its last PDU described a paused world (standing still)
    appearance: int = 0  # what every PDU of it carries (dis.APPEARANCE_DESTROYED once it crashed)
    # Its last states received, oldest first: (world time s, velocity ECEF m/s (3,), acceleration
    # ECEF m/s^2 (3,), dead-reckoning algorithm); see :func:`velocity_at`.
    history: collections.deque = dataclasses.field(default_factory=lambda: collections.deque(maxlen=STATE_HISTORY))


def _check(name: str, value, lo: float, hi: float, integer: bool = False):
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and lo <= value <= hi
    if not ok or (integer and int(value) != value):
        raise InvalidArgument(name, f"must be {'an integer' if integer else 'a number'} in [{lo:g}, {hi:g}]",
                              value=value)
    return value


class DisGateway:
    """The gateway between a simulation server at ``server`` and the DIS exercise
    ``exercise`` on UDP (host, port); start(), stop() (also a context manager)."""

    def __init__(self, server: str, *, port: int = dis.DEFAULT_PORT, exercise: int = DEFAULT_EXERCISE,
                 host: str = DEFAULT_HOST, site: int = DEFAULT_SITE, application: int = DEFAULT_APPLICATION,
                 remote_timeout_s: float = DEFAULT_REMOTE_TIMEOUT_S, heartbeat_s: float = DEFAULT_HEARTBEAT_S,
                 client_name: str = "dis-gateway"):
        self.server = server
        self.port = _check("port", port, 0, 65535, integer=True)
        self.exercise = _check("exercise", exercise, 0, 255, integer=True)
        self.host = host
        self.site = _check("site", site, 1, MAX_ENTITY_NUMBER, integer=True)
        self.application = _check("application", application, 1, MAX_ENTITY_NUMBER, integer=True)
        self.remote_timeout_s = _check("remote_timeout_s", remote_timeout_s, 0.01, 3600.0)
        self.heartbeat_s = _check("heartbeat_s", heartbeat_s, 0.01, 3600.0)
        self.client_name = client_name
        self.pdus_sent = 0
        self.pdus_received = 0
        self.pdus_ignored = 0
        self.pdus_malformed = 0
        self.pdus_dropped = 0  # datagrams lost before they were read: a full socket or queue
        self.receive_buffer_bytes = 0  # SO_RCVBUF granted (Linux reports twice what it books for data)
        self.finished = threading.Event()  # set when the server's stream ends
        self._stop = threading.Event()
        self._lock = threading.Lock()  # locals, remotes, counters of the sending side, the stream
        self._locals: dict[int, _Local] = {}
        self._refused: set[int] = set()
        self._remotes: dict[str, float] = {}  # external id -> wall time of its last PDU
        self._names: dict[str, str] = {}  # external id -> its (unique) world name
        self._malformed_log = _Throttled()
        self._publish_log = _Throttled()
        self._dropped_log = _Throttled()
        self._inbox = _Inbox()
        self._kernel_drops = 0  # the socket's SO_RXQ_OVFL count last seen
        self._overflow_counted = False  # whether the socket reports it
        self._reserved_logged: set = set()  # reserved Entity IDs refused and logged
        self._own_ids_warned = False  # a foreign simulation using our site and application was reported
        self._sent_markings: dict[int, bytes] = {}  # our entity number -> the marking its PDUs carry
        self._paused = False  # whether the world clock was paused at the last Watch update
        self._client = None
        self._picture = None
        self._stream = None
        self._sock: socket.socket | None = None
        self._threads: list[threading.Thread] = []
        self._hour_offset_s = 0.0
        self._events_call = None
        self._event_number = 0  # the last Collision PDU's event number
        self._wrecks: set[int] = set()  # entities the events said crashed or were destroyed

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> DisGateway:
        """Open the DIS socket, join the server, start streaming both ways (stop() undoes
        whatever was done when this raises)."""
        try:
            return self._start()
        except BaseException:
            self.stop()
            raise

    def _start(self) -> DisGateway:
        from client.sim_client import SimClient

        self._sock = self._open_socket()
        self.port = self._sock.getsockname()[1]
        self._client = SimClient(self.server)
        self._client.join(self.client_name, "gateway")
        self._hour_offset_s = seconds_past_hour(self._client.world_info.start_time)
        self._stream = self._client.external()
        self._events_call = self._client.stub.WatchEvents(pb.WatchEventsRequest(session_token=self._client.token))
        self._threads = [threading.Thread(target=self._receive_loop, name="dis-receive", daemon=True),
                         threading.Thread(target=self._ingest_loop, name="dis-ingest", daemon=True),
                         threading.Thread(target=self._housekeeping_loop, name="dis-heartbeat", daemon=True),
                         threading.Thread(target=self._events_loop, name="dis-events", daemon=True)]
        for t in self._threads:
            t.start()
        self._picture = self._client.watch(listener=self._on_update)
        return self

    def stop(self) -> None:
        """Deactivate our entities on DIS, remove the remote ones from the exercise, leave."""
        self._stop.set()
        if self._events_call is not None:
            self._events_call.cancel()
        for t in self._threads:
            t.join(timeout=5.0)
        if self._picture is not None:
            self._picture.cancel()
        with self._lock:
            for entity_id in list(self._locals):
                self._deactivate(entity_id)
            self._close_stream()
        if self._client is not None:
            try:
                if self._client.token:
                    self._client.leave()
            except SortieError as exc:
                log.info("leaving the server: %s", exc)
            self._client.close()
        if self._sock is not None:
            self._sock.close()

    def __enter__(self) -> DisGateway:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    @property
    def remote_entities(self) -> int:
        with self._lock:
            return len(self._remotes)

    @property
    def local_entities(self) -> int:
        with self._lock:
            return len(self._locals)

    def stats(self) -> dict:
        return {"pdus_sent": self.pdus_sent, "pdus_received": self.pdus_received, "pdus_ignored": self.pdus_ignored,
                "pdus_malformed": self.pdus_malformed, "pdus_dropped": self.pdus_dropped,
                "remote_entities": self.remote_entities,
                "local_entities": self.local_entities}

    def _open_socket(self) -> socket.socket:
        """The DIS socket, bound (InvalidArgument naming --host when the address is not one this
        machine can bind), with the receive buffer of RECEIVE_BUFFER_BYTES it could get."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            if hasattr(socket, "SO_REUSEPORT"):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            linux = sys.platform.startswith("linux")
            if not (linux and _forced_receive_buffer(sock)):
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER_BYTES)
            if linux:
                sock.setsockopt(socket.SOL_SOCKET, SO_RXQ_OVFL, 1)
                self._overflow_counted = True
            sock.settimeout(POLL_S)
            try:
                sock.bind((self.host, self.port))
            except OSError as exc:  # gaierror (a name that does not resolve) included
                raise InvalidArgument("host", f"cannot bind the DIS socket to {self.host}:{self.port}: "
                                              f"{exc.strerror or exc} (give an address of this machine: the "
                                              "loopback broadcast 127.255.255.255, or a broadcast or unicast "
                                              "address of one of its networks)", value=self.host) from None
        except BaseException:
            sock.close()
            raise
        self.receive_buffer_bytes = sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        holds = self.receive_buffer_bytes // KERNEL_BYTES_PER_PDU
        if self.receive_buffer_bytes < RECEIVE_BUFFER_BYTES:
            log.warning("DIS receive buffer: %d bytes granted of the %d asked (net.core.rmem_max caps it; raise it, "
                        "or run with CAP_NET_ADMIN): a burst of more than about %d Entity State PDUs may be dropped",
                        self.receive_buffer_bytes, RECEIVE_BUFFER_BYTES, holds)
        else:
            log.info("DIS receive buffer: %d bytes, a burst of about %d Entity State PDUs",
                     self.receive_buffer_bytes, holds)
        return sock

    # -- out: Sortie -> DIS ---------------------------------------------------------------------

    def _on_update(self, picture, update: pb.WatchUpdate) -> None:
        """Watch listener (the picture's listener thread; updates that came while it was busy arrive
        merged: each entity's latest state): one PDU per entered or updated state; when the
        world clock has just paused or resumed, a PDU of every other entity at once, standing
        still or moving again (module docstring)."""
        with self._lock:
            if self._stop.is_set():
                return
            was_paused, self._paused = self._paused, picture is not None and picture.time_scale == 0.0
            if update.snapshot:  # a new full picture (a replay's seek): whatever is not in it is gone
                for entity_id in set(self._locals) - {info.entity_id for info in update.entered}:
                    self._deactivate(entity_id)
            for entity_id in update.left:
                self._deactivate(entity_id)
            for info in update.entered:
                if self._admit(info):
                    self._send_state(info.entity_id, info.state)
            for state in update.states:
                if state.entity_id in self._locals:
                    self._send_state(state.entity_id, state)
            if self._paused != was_paused:
                for entity_id, local in self._locals.items():
                    if local.state is not None and local.paused != self._paused:  # not sent in this update
                        self._heartbeat(entity_id, local, picture)

    def _admit(self, info: pb.EntityInfo) -> bool:
        """Whether the gateway speaks for this entity (not external, a DIS entity number)."""
        if info.external_id:
            return False
        if info.entity_id > MAX_ENTITY_NUMBER:
            if info.entity_id not in self._refused:
                self._refused.add(info.entity_id)
                log.warning("entity %d (%s) not sent on DIS: its id is above the largest DIS entity number %d",
                            info.entity_id, info.name, MAX_ENTITY_NUMBER)
            return False
        wreck = info.destroyed or info.entity_id in self._wrecks
        local = _Local(KINDS.get(info.kind, "static"), info.type, info.coalition, info.name,
                       appearance=dis.APPEARANCE_DESTROYED if wreck else 0)
        old = self._locals.get(info.entity_id)
        if old is not None:  # in a new full picture (a replay's seek or step): its states so far still count
            local.history = old.history
        self._locals[info.entity_id] = local
        return True

    def _send_state(self, entity_id: int, state: pb.EntityState) -> None:
        local = self._locals[entity_id]
        if local.history and state.time_s < local.history[-1][0]:  # a replay went back: another past
            local.history.clear()
        local.history.append((state.time_s, tuple(state.velocity_ecef_mps), tuple(state.acceleration_ecef_mps2),
                              state.dead_reckoning))
        local.state = state
        self._send_at(entity_id, local, state.time_s)

    def _heartbeat(self, entity_id: int, local: _Local, picture) -> None:
        """A PDU of a local entity now: its last state dead-reckoned to the world time now
        (``picture``'s estimate, client.sim_client.Picture.now_s)."""
        if local.state is None or picture is None:
            self._send(local)
            return
        self._send_at(entity_id, local, max(picture.now_s(), local.state.time_s))

    def _send_at(self, entity_id: int, local: _Local, time_s: float) -> None:
        """The PDU of ``local``'s last state dead-reckoned to world time ``time_s`` (by the
        algorithm the server sent it with, as every receiver of the stream does), stamped with
        that time; standing still while the world is paused."""
        s = local.state
        pos, vel, acc = (s.ecef_x_m, s.ecef_y_m, s.ecef_z_m), s.velocity_ecef_mps, s.acceleration_ecef_mps2
        quat, rates = s.orientation_wxyz, s.angular_velocity_body_rps
        try:
            dt_s = time_s - s.time_s
            if dt_s > 0.0:
                p, q = extrapolate(s.dead_reckoning, s.time_s, np.array([pos]), np.array([vel]), np.array([acc]),
                                   np.array([quat]), np.array([rates]), time_s)
                pos, quat = p[0], q[0]
                if s.dead_reckoning in (RVW, FVW):
                    vel = np.asarray(vel) + np.asarray(acc) * dt_s
            if self._paused:
                vel = acc = rates = (0.0, 0.0, 0.0)
            pdu = dis.entity_state_pdu(
                exercise_id=self.exercise, entity_id=(self.site, self.application, entity_id), kind=local.kind,
                type_name=local.type_name, coalition=local.coalition, name=local.name, ecef_m=pos,
                vel_ecef_mps=vel, acc_ecef_mps2=acc, quat_wxyz=quat, body_rates_rps=rates,
                algorithm=s.dead_reckoning, appearance=local.appearance,
                timestamp=dis.dis_timestamp(self._hour_offset_s + time_s, absolute=False))
            wire = dis.encode_pdu(pdu)
        except (InvalidArgument, ValueError) as exc:
            self._publish_log.warn("entity %d (%s) not sent: %s", entity_id, local.name, exc)
            return
        local.pdu, local.wire, local.paused = pdu, wire, self._paused
        self._sent_markings[entity_id] = pdu.marking
        self._send(local)

    def _send(self, local: _Local) -> None:
        try:
            self._sock.sendto(local.wire, (self.host, self.port))
        except OSError as exc:
            self._publish_log.warn("sending to %s:%d: %s", self.host, self.port, exc)
            return
        local.sent_wall_s = time.monotonic()
        self.pdus_sent += 1

    def _deactivate(self, entity_id: int) -> None:
        """Forget a local entity after its last PDU, with the deactivated appearance bit."""
        local = self._locals.pop(entity_id, None)
        if local is None or local.pdu is None:
            return
        local.pdu = dataclasses.replace(local.pdu, appearance=local.pdu.appearance | dis.APPEARANCE_DEACTIVATED)
        local.wire = dis.encode_pdu(local.pdu)
        self._send(local)

    def _events_loop(self) -> None:
        """The server's events (the events stream's thread): a crash or a destruction marks
        the entity destroyed on DIS, a collision is issued as a Collision PDU."""
        try:
            for event in self._events_call:
                if event.kind in ("crash", "destroyed", "collision"):
                    with self._lock:
                        if self._stop.is_set():
                            return
                        if event.kind != "collision":
                            self._destroyed(event.entity_id)
                        else:
                            self._send_collision(event)
        except grpc.RpcError as exc:
            if exc.code() != grpc.StatusCode.CANCELLED:
                log.warning("the server's events stream ended: %s", exc.details())

    def _destroyed(self, entity_id: int) -> None:
        """A local entity crashed or was destroyed: its PDUs from now on carry the appearance's damage
        "destroyed" (SISO-REF-010), the first one at once."""
        self._wrecks.add(entity_id)  # for when it enters later (the events stream may run ahead)
        local = self._locals.get(entity_id)
        if local is None:
            return
        local.appearance |= dis.APPEARANCE_DESTROYED
        if local.pdu is not None:
            local.pdu = dataclasses.replace(local.pdu, appearance=local.pdu.appearance | dis.APPEARANCE_DESTROYED)
            local.wire = dis.encode_pdu(local.pdu)
            self._send(local)

    def _dis_id(self, entity_id: int) -> tuple[int, int, int]:
        """The DIS Entity ID of a world entity: a DIS entity's own (its external id), ours for
        one we speak for or could, (0, 0, 0) (no entity) for anything else."""
        info = next((i for i in self._world_infos() if i.entity_id == entity_id), None)
        if info is not None and info.external_id:
            return dis.entity_id_of(info.external_id) or (0, 0, 0)
        return (self.site, self.application, entity_id) if 0 < entity_id <= MAX_ENTITY_NUMBER else (0, 0, 0)

    def _send_collision(self, event: pb.WorldEvent) -> None:
        """A Collision PDU issued by the local entity of a collision event (the other one's
        event issues its own, as every DIS simulation issues one per entity it owns). The
        velocity is the entity's at the collision (IEEE 1278.1-2012 §7.2.3: the issuing
        entity's velocity when the collision is detected, world coordinates), from its last
        state received at or before the event's time (:func:`velocity_at`), not the last one
        received: the events stream runs on its own, and a wreck's states at rest may come
        first. The mass and the contact point on the entity are not modelled (0 and its
        origin)."""
        local = self._locals.get(event.entity_id)
        if local is None:
            return
        try:
            other = int(json.loads(event.detail_json or "{}").get("other_id", 0))
        except (ValueError, TypeError, AttributeError):
            other = 0
        self._event_number = self._event_number % 65535 + 1
        pdu = dis.CollisionPdu(
            exercise_id=self.exercise, issuing_entity_id=(self.site, self.application, event.entity_id),
            colliding_entity_id=self._dis_id(other), event_id=(self.site, self.application, self._event_number),
            collision_type=dis.COLLISION_INELASTIC,
            velocity=velocity_at(local.history, event.time_s),
            timestamp=dis.dis_timestamp(self._hour_offset_s + event.time_s, absolute=False))
        try:
            self._sock.sendto(dis.encode_collision_pdu(pdu), (self.host, self.port))
        except (OSError, InvalidArgument) as exc:
            self._publish_log.warn("collision of entity %d not sent: %s", event.entity_id, exc)
            return
        self.pdus_sent += 1

    # -- in: DIS -> Sortie ----------------------------------------------------------------------

    def _receive_loop(self) -> None:
        """The socket's reader (its own thread, so a burst never waits on decoding): every
        datagram into the inbox, and the kernel's count of those it dropped (SO_RXQ_OVFL)."""
        ancillary = socket.CMSG_SPACE(4) if self._overflow_counted else 0
        while not self._stop.is_set():
            try:
                data, messages, _, _ = self._sock.recvmsg(RECEIVE_BYTES, ancillary)
            except socket.timeout:
                continue
            except OSError:
                if self._stop.is_set():
                    return
                raise
            for level, kind, value in messages:
                if level == socket.SOL_SOCKET and kind == SO_RXQ_OVFL and len(value) >= 4:
                    self._kernel_dropped(int.from_bytes(value[:4], sys.byteorder))
            if not self._inbox.put(data):
                self._dropped(1, f"the gateway's receive queue is full ({self._inbox.max_bytes} bytes)")

    def _kernel_dropped(self, count: int) -> None:
        """The socket's drop count (u32, since it opened) as a datagram reports it."""
        new = (count - self._kernel_drops) % (1 << 32)
        if new and new < (1 << 31):  # a datagram queued before a later one reported more: not news
            self._kernel_drops = count
            self._dropped(new, f"the socket's receive buffer ({self.receive_buffer_bytes} bytes) was full")

    def _dropped(self, count: int, why: str) -> None:
        self.pdus_dropped += count
        self._dropped_log.warn("%d DIS datagrams dropped, %d in all: %s", count, self.pdus_dropped, why)

    def _ingest_loop(self) -> None:
        """The inbox's decoder (its own thread): each datagram's PDUs into the exercise."""
        while not self._stop.is_set():
            data = self._inbox.get(POLL_S)
            if data is not None:
                self._take_datagram(data)

    def _take_datagram(self, data: bytes) -> None:
        pdus, problems = dis.read_datagram(data)
        self.pdus_received += len(pdus) + len(problems)
        for exc in problems:
            self._malformed(exc)
        for pdu in pdus:
            self._take(pdu)

    def _malformed(self, exc: Exception) -> None:
        self.pdus_malformed += 1
        self._malformed_log.warn("malformed DIS PDU ignored: %s", exc)

    def _take(self, data: bytes) -> None:
        try:
            header = dis.decode_header(data)
            if header.exercise_id != self.exercise or header.pdu_type != dis.PDU_TYPE_ENTITY_STATE:
                self.pdus_ignored += 1
                return
            pdu = dis.decode_pdu(data)
            reserved = dis.reserved_entity_id(pdu.entity_id)
            if reserved is not None:
                self._reserved(pdu, reserved)
                return
            if pdu.entity_id[:2] == (self.site, self.application):
                self.pdus_ignored += 1
                if self._sent_markings.get(pdu.entity_id[2]) != pdu.marking:
                    self._foreign_with_our_ids(pdu)
                return
            xid = dis.external_id(pdu.entity_id)
            state = None if pdu.deactivated else dis.sortie_state(pdu)
            if state is not None:
                _validate(state)
        except (DataFormatError, InvalidArgument) as exc:
            self._malformed(exc)
            return
        with self._lock:
            self._publish(xid, state)

    def _reserved(self, pdu: dis.EntityStatePdu, why: str) -> None:
        """An Entity State PDU whose Entity ID names no one entity: malformed, logged once per id."""
        self.pdus_malformed += 1
        if pdu.entity_id in self._reserved_logged:
            return
        message = (f"DIS Entity State PDU of entity {'.'.join(map(str, pdu.entity_id))} ({pdu.marking_text!r}) "
                   f"refused: {why}, not one entity (IEEE 1278.1-2012 §6.2.28)")
        if len(self._reserved_logged) >= MAX_LOGGED_IDS:
            self._malformed_log.warn("%s", message)
            return
        self._reserved_logged.add(pdu.entity_id)
        log.warning("%s", message)

    def _foreign_with_our_ids(self, pdu: dis.EntityStatePdu) -> None:
        """A PDU with our site and application that is not one of ours: another simulation uses
        them (its entities cannot be told from ours): said once."""
        if self._own_ids_warned:
            return
        self._own_ids_warned = True
        log.warning("another DIS simulation in exercise %d uses this gateway's own site %d and application %d "
                    "(entity %d, %r): its entities are ignored; give the gateway a site and application of "
                    "its own with --site and --application", self.exercise, self.site, self.application,
                    pdu.entity_id[2], pdu.marking_text)

    def _publish(self, xid: str, state: dict | None) -> None:
        """Add, move (state) or remove (None) a remote entity on the PublishExternal stream."""
        if self._stream is None:
            return
        if state is None:
            self._names.pop(xid, None)
            if self._remotes.pop(xid, None) is not None:
                self._on_stream(xid, lambda stream: stream.remove(xid))
            return
        name = self._names.get(xid) or dis.unique_name(state["name"], xid, self._taken_names(xid))
        self._names[xid] = name
        if self._on_stream(xid, lambda stream: stream.update(xid, **{**state, "name": name})):
            self._remotes[xid] = time.monotonic()

    def _on_stream(self, xid: str, call) -> bool:
        """``call(stream)``; when the server has ended the stream (it refused an earlier update,
        which its error names), open another and call again there. Whether it was sent."""
        for _ in range(2):
            try:
                call(self._stream)
                return True
            except SortieError as exc:
                self._publish_log.warn("the server ended the external stream (%s): reopened, %s sent again",
                                       exc, xid)
                self._reopen_stream()
        return False

    def _reopen_stream(self) -> None:
        """A new PublishExternal stream. The remote entities in the world stay tracked (the world
        keeps them under our session, so their updates, timeouts and removals go on); those it
        does not show (the refused one, or one not shown yet) are forgotten until their next PDU
        publishes them again, so that no removal of an entity the world lacks ends the stream."""
        in_world = self._world_external_ids()
        for xid in [x for x in self._remotes if x not in in_world]:
            del self._remotes[xid]
            self._names.pop(xid, None)
        self._stream = self._client.external()

    def _world_infos(self) -> list:
        picture = self._picture
        return list(picture.infos.values()) if picture is not None else []

    def _world_external_ids(self) -> set:
        return {info.external_id for info in self._world_infos() if info.external_id}

    def _taken_names(self, xid: str) -> set:
        """Every world name but ``xid``'s own: the entities the gateway sees and the names it gave."""
        taken = {info.name for info in self._world_infos() if info.external_id != xid}
        return taken | {n for x, n in self._names.items() if x != xid}

    # -- heartbeats and timeouts ----------------------------------------------------------------

    def _housekeeping_loop(self) -> None:
        while not self._stop.wait(POLL_S):
            now = time.monotonic()
            with self._lock:
                for entity_id, local in self._locals.items():
                    if local.wire and now - local.sent_wall_s >= self.heartbeat_s:
                        self._heartbeat(entity_id, local, self._picture)
                for xid in [x for x, t in self._remotes.items() if now - t > self.remote_timeout_s]:
                    self._publish(xid, None)
            picture = self._picture
            if picture is not None and not picture.alive:  # the Watch stream ended
                if picture.error is not None:
                    log.warning("the server's stream ended: %s", picture.error)
                self.finished.set()
                return

    def _close_stream(self) -> None:
        if self._stream is None:
            return
        try:
            for xid in list(self._remotes):
                self._stream.remove(xid)
            self._stream.close()
        except SortieError as exc:
            log.info("closing the external stream: %s", exc)
        self._remotes.clear()
        self._names.clear()
        self._stream = None


def _forced_receive_buffer(sock: socket.socket) -> bool:
    """Whether SO_RCVBUFFORCE set RECEIVE_BUFFER_BYTES (False without CAP_NET_ADMIN)."""
    try:
        sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RECEIVE_BUFFER_BYTES)
    except PermissionError:
        return False
    return True


def velocity_at(history, time_s: float) -> tuple[float, float, float]:
    """An entity's velocity (ECEF m/s) at world time ``time_s`` from its states ``history``
    ((time s, velocity (3,), acceleration (3,), algorithm), oldest first): the last state at or
    before it, extrapolated to it as the receivers dead-reckon it (IEEE 1278.1-2012 Annex E:
    V0 + A0 dt for RVW and FVW, V0 for the others); the first state after it when none is
    before; 0 when there is none."""
    if not history:
        return (0.0, 0.0, 0.0)
    times = [h[0] for h in history]
    k = bisect.bisect_right(times, time_s + 1e-9) - 1  # a state at the event's tick counts as at it
    t0, vel, acc, algorithm = history[max(k, 0)]
    dt_s = time_s - t0
    if k < 0 or dt_s <= 0.0 or algorithm not in (RVW, FVW) or len(acc) != 3:
        return tuple(float(v) for v in vel) if len(vel) == 3 else (0.0, 0.0, 0.0)
    return tuple(float(v) + float(a) * dt_s for v, a in zip(vel, acc))


def _validate(state: dict) -> None:
    """The server's checks of an external state (server.world.external_state), here, so a bad
    PDU counts as malformed instead of ending the PublishExternal stream."""
    external_state(0.0, state["ecef_m"], state["vel_ecef_mps"], state["acc_ecef_mps2"], state["quat_wxyz"],
                   state["body_rates_rps"], state["algorithm"])


def seconds_past_hour(iso_utc: str) -> float:
    """Seconds past the hour of an ISO 8601 UTC time (the exercise's start, WorldInfo.start_time)."""
    try:
        t = dt.datetime.fromisoformat(iso_utc)
    except ValueError:
        log.warning("start time %r is not ISO 8601: timestamps count from the hour", iso_utc)
        return 0.0
    return t.minute * 60.0 + t.second + t.microsecond * 1e-6


# -- command line ---------------------------------------------------------------------------------

def add_parser(sub) -> None:
    p = sub.add_parser("dis", help="bridge a simulation server and a DIS exercise (IEEE 1278.1)",
                       description="Send every entity of the server's exercise as DIS Entity State PDUs and "
                                   "publish the entities of other DIS simulations into it, until SIGTERM/SIGINT.")
    p.add_argument("--server", required=True, metavar="ADDRESS", help="the simulation server, HOST:PORT")
    p.add_argument("--port", type=int, default=dis.DEFAULT_PORT, help="DIS UDP port (default %(default)s)")
    p.add_argument("--exercise", type=int, default=DEFAULT_EXERCISE, help="DIS exercise id (default %(default)s)")
    p.add_argument("--host", default=DEFAULT_HOST,
                   help="address to send to and bind: the default loopback broadcast reaches every DIS program "
                        "on this machine and nothing beyond it; a LAN broadcast address joins that network "
                        "(default %(default)s)")
    p.add_argument("--site", type=int, default=DEFAULT_SITE, help="our DIS site number (default %(default)s)")
    p.add_argument("--application", type=int, default=DEFAULT_APPLICATION,
                   help="our DIS application number, unique per site (default %(default)s)")
    p.add_argument("--remote-timeout-s", type=float, default=DEFAULT_REMOTE_TIMEOUT_S,
                   help="remove a DIS entity silent this long (default %(default)s: three missed 5 s heartbeats; "
                        "IEEE 1278.1's own default is 2.4, 12 s)")
    p.add_argument("--heartbeat-s", type=float, default=DEFAULT_HEARTBEAT_S,
                   help="send an entity's PDU, its last state dead-reckoned to now, after this long without an "
                        "update (default %(default)s)")
    p.set_defaults(func=dis_command)


def dis_command(args) -> int:
    from server.grpc_common import stop_signals, wait_for_signal

    gateway = DisGateway(args.server, port=args.port, exercise=args.exercise, host=args.host, site=args.site,
                         application=args.application, remote_timeout_s=args.remote_timeout_s,
                         heartbeat_s=args.heartbeat_s)
    with stop_signals() as stop:  # before the line that says it listens (grpc_common.stop_signals)
        gateway.start()
        line(f"sortie dis: exercise {gateway.exercise} on {gateway.host}:{gateway.port} as site {gateway.site} "
             f"application {gateway.application}, server {args.server}", logger=__name__)
        try:
            wait_for_signal(gateway.finished, stop=stop)
        finally:
            picture = gateway._picture  # noqa: SLF001 - why it finished, before stop() lets it go
            ended = gateway.finished.is_set()
            gateway.stop()
    s = gateway.stats()
    line(f"sortie dis: stopped; {s['pdus_sent']} PDUs sent, {s['pdus_received']} received "
         f"({s['pdus_ignored']} ignored, {s['pdus_malformed']} malformed)", logger=__name__)
    if ended and picture is not None and picture.error is not None:  # as sortie tacview: 1 when the server went
        line(f"sortie dis: the simulation server at {args.server} went away: {picture.error}", stream=sys.stderr,
             level=logging.ERROR, logger=__name__)
        return 1
    if ended:
        line(f"sortie dis: the simulation server at {args.server} ended the exercise", logger=__name__)
    return 0
