"""State streaming: dead reckoning decides *when* an entity is sent, interest
management *to whom*, and per-client queues keep a slow reader from slowing
anyone else.

Data flow at each network tick (run by the clock thread right after a world
tick, never waiting on a client):

    Snapshot --DeadReckoner.due--> entities whose receivers' extrapolation is
             off by more than their thresholds (or heartbeat due, or new)
             --interest.relevant--> per session: entered / left / updated
             --ClientQueue.push--> merged into that session's pending view

One DeadReckoner serves every receiver (as in DIS, the sender models the one
extrapolation all receivers make from its last update). A session that newly
sees an entity gets, in the `entered` list, the entity's last *sent* state
(what every other receiver extrapolates from), so the one model stays true
for all receivers and the thresholds hold for the newcomer too.

ClientQueue is bounded by construction: at most one pending entry per entity
(entered, left, or latest state), merged on push. A reader that falls behind
loses intermediate states and never the latest; the clock thread's push is a
few dict operations under a lock no reader holds while sending.
"""

from __future__ import annotations

import asyncio
import struct
import threading
from dataclasses import dataclass

import numpy as np

from server.grpc_common import varint
from server.interest import changes
from server.world import rows_of


@dataclass
class Pending:
    """What a take() hands the stream: one WatchUpdate's worth, already encoded
    (see :func:`encode_watch_update`)."""

    time_s: float
    snapshot: bool
    entered: list  # [(EntityInfo fields 1-5 bytes, EntityState bytes)]
    left: list  # [entity id]
    states: list  # [EntityState bytes]
    time_scale: float = 1.0  # world seconds per wall second (0: paused)


class ClientQueue:
    """The pending view of one watching session (see the module docstring).

    A reader on an asyncio loop passes ``loop``: each push or close then also
    sets :attr:`ready` (an asyncio.Event) from the pushing thread, through
    the loop, and the reader awaits it instead of blocking on the condition.
    """

    def __init__(self, loop=None):
        self.loop = loop
        self.ready = asyncio.Event() if loop is not None else None
        self.cond = threading.Condition()
        self.known: set = set()  # ids the client has been told about (entered and not left)
        self._enter: dict = {}
        self._leave: set = set()
        self._states: dict = {}
        self._time_s = 0.0
        self._time_scale = 1.0
        self._snapshot = True
        self._dirty = False
        self.closed = False
        self.close_reason: str | None = None  # see close()
        self.merged = 0  # states overwritten before they were read (slow-reader measure)

    def push(self, time_s: float, entered: dict, left, states: dict, wake: bool = True,
             time_scale: float = 1.0) -> None:
        """entered: id -> (encoded info, encoded state); left: ids; states: id -> encoded state;
        time_scale: world seconds per wall second now (0: paused). wake=False leaves waking an
        asyncio reader to the caller (:func:`wake_all`)."""
        with self.cond:
            for i in left:
                self._states.pop(i, None)
                if self._enter.pop(i, None) is None or i in self.known:
                    self._leave.add(i)
            for i, item in entered.items():
                self._leave.discard(i)
                self._states.pop(i, None)
                self._enter[i] = item
            for i, row in states.items():
                if i in self._enter:
                    self._enter[i] = (self._enter[i][0], row)
                else:
                    if i in self._states:
                        self.merged += 1
                    self._states[i] = row
            self._time_s = time_s
            self._time_scale = time_scale
            self._dirty = True
            self.cond.notify_all()
        if wake:
            self._wake()

    def _wake(self) -> None:
        if self.loop is not None:
            try:
                self.loop.call_soon_threadsafe(self.ready.set)
            except RuntimeError:  # the loop has closed: nobody is reading
                pass

    def take(self, timeout_s: float | None) -> Pending | None:
        """The pending changes (clearing them), waiting up to ``timeout_s`` for some;
        None on timeout, with nothing pending, or when closed for a reason (see close()).
        A queue the server's end closed still hands over what was pushed before: the
        exercise's last state (the clock's last publish comes just before the close)."""
        with self.cond:
            if not self._dirty and not self.closed:
                self.cond.wait(timeout_s)
            if not self._dirty or self.close_reason is not None:
                return None
            out = Pending(self._time_s, self._snapshot, list(self._enter.values()),
                          [i for i in self._leave if i in self.known], list(self._states.values()),
                          self._time_scale)
            self.known |= self._enter.keys()
            self.known -= self._leave
            self._enter, self._leave, self._states = {}, set(), {}
            self._snapshot = False
            self._dirty = False
            return out

    def resnapshot(self) -> None:
        """Start over (a replay's seek): drop what is pending and what the client was told;
        the next update is a full snapshot, which the client takes in place of its picture."""
        with self.cond:
            self.known = set()
            self._enter, self._leave, self._states = {}, set(), {}
            self._snapshot = True
            self._dirty = False

    @property
    def needs_snapshot(self) -> bool:
        """True until the first update (the snapshot) has been taken."""
        return self._snapshot

    def close(self, reason: str | None = None) -> None:
        """End the stream; ``reason``: why, when it is not the server's end (the stream then
        ends ABORTED with it: a new Watch of the session, the session left)."""
        with self.cond:
            if not self.closed:
                self.close_reason = reason
            self.closed = True
            self.cond.notify_all()
        self._wake()


def _f32(a) -> np.ndarray:
    """What a float32 wire field carries back, as float64."""
    return np.asarray(a, np.float32).astype(np.float64)


# -- the wire: each entity's message encoded once per network tick, then fanned out --------------
#
# Protobuf's encoding of a message is the concatenation of its fields, and a
# repeated message field is the concatenation of (tag, length, bytes) of each
# element (https://protobuf.dev/programming-guides/encoding/). So the
# publisher encodes each EntityState and EntityInfo once with the generated
# classes, and each stream's WatchUpdate is assembled by joining bytes: the
# cost per receiver is a join, not a message build.

def _field(tag: int, payload: bytes) -> bytes:
    """A length-delimited field (wire type 2) of field number ``tag``."""
    return varint(tag << 3 | 2) + varint(len(payload)) + payload


def encode_states(ids, t, pos, vel, acc, quat, omega, algorithm) -> list[bytes]:
    """sortie.v1.EntityState bytes of each row (positions and t float64, the rest
    as the wire's float32)."""
    from sortie.v1 import simulation_pb2 as pb

    t = np.broadcast_to(np.asarray(t, np.float64), (len(ids),)).tolist()
    return [pb.EntityState(entity_id=i, time_s=tk, ecef_x_m=p[0], ecef_y_m=p[1], ecef_z_m=p[2],
                           velocity_ecef_mps=v, acceleration_ecef_mps2=a, orientation_wxyz=q,
                           angular_velocity_body_rps=w, dead_reckoning=alg).SerializeToString()
            for i, tk, p, v, a, q, w, alg in zip(np.asarray(ids).tolist(), t, np.asarray(pos).tolist(),
                                                 np.asarray(vel).tolist(), np.asarray(acc).tolist(),
                                                 np.asarray(quat).tolist(), np.asarray(omega).tolist(),
                                                 np.asarray(algorithm).tolist())]


def encode_info(info: tuple, destroyed: bool = False) -> bytes:
    """EntityInfo fields 1-5, 7 and 8 (id, name, kind, type, coalition[, external_id], and
    whether it is a wreck) of an info tuple (server.world.World.infos); the state (field 6) is
    appended per update by :func:`encode_watch_update` (field order does not matter on the wire)."""
    from sortie.v1 import simulation_pb2 as pb

    return pb.EntityInfo(entity_id=info[0], name=info[1], kind=info[2], type=info[3], coalition=info[4],
                         external_id=info[5] if len(info) > 5 else "", destroyed=destroyed).SerializeToString()


def encode_watch_update(p: Pending) -> bytes:
    """The sortie.v1.WatchUpdate of a Pending, as bytes."""
    out = [b"\x09" + struct.pack("<d", p.time_s)]  # field 1, double
    if p.snapshot:
        out.append(b"\x10\x01")  # field 2, bool
    out += [_field(3, info + _field(6, state)) for info, state in p.entered]
    if p.left:
        out.append(_field(4, b"".join(varint(int(i)) for i in p.left)))  # packed uint64
    out += [_field(5, state) for state in p.states]
    out.append(b"\x31" + struct.pack("<d", p.time_scale))  # field 6, double (optional: always sent)
    return b"".join(out)


def _spans(idx: np.ndarray, start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """idx[start[i]:start[i] + count[i]] of every i, concatenated."""
    if not count.any():
        return np.zeros(0, np.int64)
    return np.concatenate([idx[a:a + c] for a, c in zip(start.tolist(), count.tolist()) if c])


def wake_all(queues) -> None:
    """Wake the asyncio readers of ``queues`` with one call per loop: a publisher that
    pushed to every session with wake=False hands the loop all its writes at once,
    instead of being interrupted by the loop after each push."""
    by_loop: dict = {}
    for q in queues:
        if q.loop is not None:
            by_loop.setdefault(q.loop, []).append(q.ready)
    for loop, events in by_loop.items():
        try:
            loop.call_soon_threadsafe(lambda events=events: [e.set() for e in events])
        except RuntimeError:  # the loop has closed
            pass


class Publisher:
    """Runs on the clock thread at the network rate: decides and queues updates.

    ``reckoner`` is a :class:`server.dead_reckoning.DeadReckoner`;
    ``thresholds_of(entity_id)`` gives an entity's
    :class:`server.dead_reckoning.Thresholds` when it first appears. Sessions
    are :class:`server.sim_service.Session` objects (queue, centre, radius,
    own agent, visible ids, view lock).

    Every receiver's view is decided at once, as (sessions x entities) boolean
    matrices: relevant now, visible before, entered, left, updated. Each
    session keeps the ids it sees, and its row of the last matrix while the
    snapshot's entity layout stays the same (the usual tick). A session's
    view and queue are read, and later recorded and pushed to, under its
    ``view_lock``; a session whose queue changed in between (a new Watch,
    :meth:`server.sim_service.Session.begin_stream`) is left for the next
    publish, where its new stream starts from nothing seen.
    """

    def __init__(self, reckoner, thresholds_of):
        self.reckoner = reckoner
        self.thresholds_of = thresholds_of
        self.updates_sent = 0  # entity updates decided (each goes to every session that sees the entity)
        self.entity_samples = 0  # entity x network ticks seen
        self._ids = np.zeros(0, np.int64)  # the entity layout of the last publish
        self._layout = 0  # bumped when it changes
        self._slots = np.zeros(0, np.int64)  # the reckoner's rows of self._ids
        self._time_scale = 1.0  # of the last publish: a change goes to every session
        # Load (or compile) the compiled passes now, not on the clock thread's first publish.
        z3 = np.zeros((0, 3))
        changes(z3, np.zeros(0), z3, np.zeros((0, 0), bool), np.zeros(0, np.int64), np.zeros(0, bool))
        reckoner.publish_rows(0.0, np.zeros(0, np.int64), z3, z3, z3, np.zeros((0, 4)), z3)

    def reset(self) -> None:
        """Forget what was sent (a replay's seek): at the next publish every entity is
        new to the reckoner, so every session gets a fresh state of each one it sees."""
        self.reckoner.remove(self.reckoner.ids)
        self._ids = np.zeros(0, np.int64)
        self._slots = np.zeros(0, np.int64)
        self._layout += 1

    def _track(self, ids: np.ndarray) -> None:
        """Add new entities to the reckoner (in one call per thresholds), drop the gone ones."""
        known = self.reckoner.ids
        gone = np.setdiff1d(known, ids)
        if gone.size:
            self.reckoner.remove(gone)
        groups: dict = {}
        for i in np.setdiff1d(ids, known).tolist():
            groups.setdefault(self.thresholds_of(i), []).append(i)
        for thresholds, new in groups.items():
            self.reckoner.add(new, thresholds)

    def _previous(self, sessions: list, ids: np.ndarray) -> tuple[np.ndarray, list, list]:
        """(sessions x entities) visible before this publish, per session the visible ids
        no longer in the world (removed: they leave), and per session the queue that view
        belongs to (read together under the session's view_lock; see publish)."""
        prev = np.zeros((len(sessions), ids.size), bool)
        gone = [()] * len(sessions)
        queues = [None] * len(sessions)
        for s_k, s in enumerate(sessions):
            with s.view_lock:
                queues[s_k] = s.queue
                if s.visible_layout == self._layout and s.visible_mask is not None:
                    prev[s_k] = s.visible_mask
                elif s.visible_ids.size:
                    prev[s_k] = np.isin(ids, s.visible_ids)
                    gone[s_k] = np.setdiff1d(s.visible_ids, ids).tolist()
        return prev, gone, queues

    def publish(self, snap, infos: dict, sessions: list, time_scale: float = 1.0, wrecks=frozenset()) -> None:
        """Decide and queue the updates of ``snap`` for ``sessions``; ``time_scale``: world
        seconds per wall second now (0: paused), sent with every update and to every
        session when it changes; ``wrecks``: the ids of entities crashed or destroyed (their
        EntityInfo says so when they enter a view)."""
        n = snap.ids.size
        rescaled = time_scale != self._time_scale
        self._time_scale = time_scale
        if not np.array_equal(snap.ids, self._ids):
            self._track(snap.ids)
            self._ids = snap.ids.copy()
            self._slots = self.reckoner.slots(snap.ids)  # the reckoner's rows change only in _track
            self._layout += 1
        self.entity_samples += n
        # The receivers get float32 velocities, accelerations, quaternions and rates: the
        # reckoner models exactly those (positions go as float64).
        vel, acc = _f32(snap.vel_ecef_mps), _f32(snap.acc_ecef_mps2)
        quat, omega = _f32(snap.quat_ecef2body), _f32(snap.body_rates_rps)
        if n:
            due, algorithms = self.reckoner.publish_rows(snap.time_s, self._slots, snap.ecef_m, vel, acc, quat, omega)
        else:
            due, algorithms = np.zeros(0, bool), np.zeros(0, np.int64)
        self.updates_sent += int(due.sum())
        if not sessions:
            return
        # Where each session's own agent is in the snapshot (-1: not there).
        k, found = rows_of(snap.ids, [s.agent_id for s in sessions])
        agent_k = np.where(found, k, -1)
        centres = np.zeros((len(sessions), 3))
        radii = np.full(len(sessions), -1.0)  # no centre (agent gone): sees nothing but its own agent
        for s_k, s in enumerate(sessions):
            c = s.observer_ecef if not s.agent_id else snap.ecef_m[agent_k[s_k]] if agent_k[s_k] >= 0 else None
            if c is not None:
                centres[s_k] = c
                radii[s_k] = s.radius_m
        prev, gone, queues = self._previous(sessions, snap.ids)
        # Each session's view, with the hysteresis at its area's edge: who enters, leaves, updates.
        now, counts, ptr, idx = changes(centres, radii, snap.ecef_m, prev, agent_k, due)

        # Encode once: the due states, and each newcomer's last *sent* state (what every
        # other receiver extrapolates from, so one model stays true for all of them).
        due_k = np.flatnonzero(due)
        state_of = dict(zip(due_k.tolist(), encode_states(snap.ids[due_k], snap.time_s, snap.ecef_m[due_k],
                                                          vel[due_k], acc[due_k], quat[due_k], omega[due_k],
                                                          algorithms[due_k])))
        entering = np.zeros(n, bool)
        entering[_spans(idx, ptr[:, 0], counts[:, 0])] = True
        new_k = np.array([k for k in np.flatnonzero(entering).tolist() if int(snap.ids[k]) in infos], np.int64)
        enter_of = {}
        if new_k.size:
            last = self.reckoner.last_sent(snap.ids[new_k])
            sent = encode_states(snap.ids[new_k], last["t0"], last["pos"], last["vel"], last["acc"], last["quat"],
                                 last["omega"], last["algorithm"])
            enter_of = {k: (encode_info(infos[int(snap.ids[k])], int(snap.ids[k]) in wrecks), b)
                        for k, b in zip(new_k.tolist(), sent)}

        ids_list = snap.ids.tolist()
        idx_list = idx.tolist()
        pushed = []
        busy = counts.any(axis=1).tolist()
        for s_k, s in enumerate(sessions):
            with s.view_lock:
                queue = queues[s_k]
                if s.queue is not queue:  # a new stream took the session over since _previous:
                    continue  # it starts from nothing seen, at the next publish
                s.visible_mask = now[s_k]
                s.visible_ids = snap.ids[now[s_k]]
                s.visible_layout = self._layout
                if not (busy[s_k] or gone[s_k] or queue.needs_snapshot or rescaled):
                    continue
                (e0, l0, u0), (ne, nl, nu) = ptr[s_k].tolist(), counts[s_k].tolist()
                ent = {ids_list[k]: enter_of[k] for k in idx_list[e0:e0 + ne] if k in enter_of}
                states = {ids_list[k]: state_of[k] for k in idx_list[u0:u0 + nu]}
                left_ids = [ids_list[k] for k in idx_list[l0:l0 + nl]] + list(gone[s_k])
                queue.push(snap.time_s, ent, left_ids, states, wake=False, time_scale=time_scale)
            pushed.append(queue)
        wake_all(pushed)
