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

import threading
from dataclasses import dataclass

import numpy as np

from server.interest import relevant


@dataclass(frozen=True)
class StateRow:
    """One entity's state as sent (see sortie.v1.EntityState)."""

    entity_id: int
    time_s: float
    ecef_m: tuple
    vel: tuple
    acc: tuple
    quat: tuple
    omega: tuple
    algorithm: int


@dataclass
class Pending:
    """What a take() hands the stream: one WatchUpdate's worth."""

    time_s: float
    snapshot: bool
    entered: list  # [(info tuple, StateRow)]
    left: list  # [entity id]
    states: list  # [StateRow]


class ClientQueue:
    """The pending view of one watching session (see the module docstring)."""

    def __init__(self):
        self.cond = threading.Condition()
        self.known: set = set()  # ids the client has been told about (entered and not left)
        self._enter: dict = {}
        self._leave: set = set()
        self._states: dict = {}
        self._time_s = 0.0
        self._snapshot = True
        self._dirty = False
        self.closed = False
        self.merged = 0  # states overwritten before they were read (slow-reader measure)

    def push(self, time_s: float, entered: dict, left, states: dict) -> None:
        """entered: id -> (info, StateRow); left: ids; states: id -> StateRow."""
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
            self._dirty = True
            self.cond.notify_all()

    def take(self, timeout_s: float | None) -> Pending | None:
        """The pending changes (clearing them), waiting up to ``timeout_s`` for some;
        None on timeout or when closed."""
        with self.cond:
            if not self._dirty and not self.closed:
                self.cond.wait(timeout_s)
            if self.closed or not self._dirty:
                return None
            out = Pending(self._time_s, self._snapshot, list(self._enter.values()),
                          [i for i in self._leave if i in self.known], list(self._states.values()))
            self.known |= self._enter.keys()
            self.known -= self._leave
            self._enter, self._leave, self._states = {}, set(), {}
            self._snapshot = False
            self._dirty = False
            return out

    @property
    def needs_snapshot(self) -> bool:
        """True until the first update (the snapshot) has been taken."""
        return self._snapshot

    def close(self) -> None:
        with self.cond:
            self.closed = True
            self.cond.notify_all()


def _f32(a) -> np.ndarray:
    """What a float32 wire field carries back, as float64."""
    return np.asarray(a, np.float32).astype(np.float64)


class Publisher:
    """Runs on the clock thread at the network rate: decides and queues updates.

    ``reckoner`` is a :class:`server.dead_reckoning.DeadReckoner`;
    ``thresholds_of(entity_id)`` gives an entity's
    :class:`server.dead_reckoning.Thresholds` when it first appears. Sessions
    are :class:`server.sim_service.Session` objects (queue, centre, radius,
    own agent, visible set).
    """

    def __init__(self, reckoner, thresholds_of):
        self.reckoner = reckoner
        self.thresholds_of = thresholds_of
        self.updates_sent = 0  # entity updates decided (each goes to every session that sees the entity)
        self.entity_samples = 0  # entity x network ticks seen

    def _track(self, ids: np.ndarray) -> None:
        """Add new entities to the reckoner, drop the gone ones."""
        known = self.reckoner.ids
        gone = np.setdiff1d(known, ids)
        if gone.size:
            self.reckoner.remove(gone)
        for i in np.setdiff1d(ids, known):
            self.reckoner.add([int(i)], self.thresholds_of(int(i)))

    def publish(self, snap, infos: dict, sessions: list) -> None:
        n = snap.ids.size
        self._track(snap.ids)
        self.entity_samples += n
        # The receivers get float32 velocities, accelerations, quaternions and rates: the
        # reckoner models exactly those (positions go as float64).
        vel, acc = _f32(snap.vel_ecef_mps), _f32(snap.acc_ecef_mps2)
        quat, omega = _f32(snap.quat_ecef2body), _f32(snap.body_rates_rps)
        if n:
            due = self.reckoner.due(snap.time_s, snap.ids, snap.ecef_m, snap.quat_ecef2body)
            self.reckoner.mark_sent(snap.time_s, snap.ids, snap.ecef_m, vel, acc, quat, omega, mask=due)
            algorithms = self.reckoner.algorithm(snap.ids)
        else:
            due, algorithms = np.zeros(0, bool), np.zeros(0, np.int64)
        self.updates_sent += int(due.sum())
        if not sessions:
            return
        index = {int(i): k for k, i in enumerate(snap.ids)}
        centres = np.zeros((len(sessions), 3))
        radii = np.full(len(sessions), -1.0)  # no centre (agent gone): sees nothing but its own agent
        for s_k, s in enumerate(sessions):
            c = s.centre_ecef(snap, index)
            if c is not None:
                centres[s_k] = c
                radii[s_k] = s.radius_m
        rel = relevant(centres, radii, snap.ecef_m)
        rows = {}

        def row(k: int) -> StateRow:
            if k not in rows:
                rows[k] = StateRow(int(snap.ids[k]), snap.time_s, tuple(snap.ecef_m[k]), tuple(vel[k]), tuple(acc[k]),
                                   tuple(quat[k]), tuple(omega[k]), int(algorithms[k]))
            return rows[k]

        for s_k, s in enumerate(sessions):
            now = rel[s_k]
            if s.agent_id in index:
                now[index[s.agent_id]] = True
            now_ids = set(snap.ids[now].tolist())
            entered_ids = now_ids - s.visible
            left_ids = s.visible - now_ids
            s.visible = now_ids
            entered = {}
            if entered_ids:
                # A newcomer gets what every other receiver holds: the last state sent, not the
                # current one, so one dead-reckoning model stays true for all of them.
                new = np.array(sorted(i for i in entered_ids if i in infos), np.int64)
                if new.size:
                    last = self.reckoner.last_sent(new)
                    for k, i in enumerate(new.tolist()):
                        entered[i] = (infos[i], StateRow(i, float(last["t0"][k]), tuple(last["pos"][k]),
                                                         tuple(last["vel"][k]), tuple(last["acc"][k]),
                                                         tuple(last["quat"][k]), tuple(last["omega"][k]),
                                                         int(last["algorithm"][k])))
            states = {int(snap.ids[k]): row(int(k)) for k in np.flatnonzero(now & due)
                      if int(snap.ids[k]) not in entered_ids}
            if entered or left_ids or states or s.queue.needs_snapshot:
                s.queue.push(snap.time_s, entered, left_ids, states)
