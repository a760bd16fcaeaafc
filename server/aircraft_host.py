"""Where the world's aircraft fly: in the server's process, or spread over worker processes.

JSBSim holds the GIL while it runs (a thread per core gains nothing: measured
slower than one thread), so the only way to put the other cores to work on the
fdm is other processes. The :class:`server.world.World` talks to an aircraft
host with one small interface, and never to an ``Aircraft`` directly:

- :class:`LocalAircraftHost`: the aircraft, their pilots and one
  :class:`fdm.fleet.Fleet` in this process (tests, small exercises, and the
  code every worker runs);
- :class:`ProcessAircraftHost`: ``n`` worker processes, each running a
  LocalAircraftHost behind a pipe. A world tick is sent to every worker at
  once (:meth:`begin_tick`), the world steps its ground vehicles while they
  run, and :meth:`end_tick` gathers their results.

Commands (stick, autopilot targets, hand-over to the autopilot, crash,
removal) are queued and reach the aircraft before the next tick's pilot
updates, in the order given, which is exactly when the local host applies
them; spawning is a request answered at once (so a trim failure is the
caller's error), and a batch of spawns (``spawn_many``) is asked of every
worker before any answer is awaited, so the workers load and trim their
shares at the same time (150 f16s over 2 workers: 5.9 -> 4.1 s). Each
aircraft's trajectory depends only on its own initial conditions, commands
and terrain answers, so it is the same in any worker.

A world begins the next tick as soon as it has ended one (server.world), so
requests may meet a tick under way: its answer is received first and kept
for :meth:`ProcessAircraftHost.end_tick`.

The workers run at a slightly lower CPU priority than the server's process
(``nice`` +WORKER_NICE). A world tick's aircraft run while the server's
process is idle (the next tick is begun as soon as one ends); on a machine
whose cores are all busy, the scheduler then lets the clock thread and the
streams run sooner when they wake, and the workers take the cycles left
over. Measured on 2 cores (90 f16s, 2000 ground vehicles, 32 clients in
real time, 4-5 interleaved runs each; docs/BENCHMARKS.md):

======  ==============================  =========================  ===========================
nice    publish -> client latency p50   latency p99                tick p99 over the whole run
======  ==============================  =========================  ===========================
0       14-17 ms                        25-36 ms                   56-77 ms
+3      12-14 ms                        24-30 ms                   70-93 ms
+10     9.5-11 ms                       20-26 ms                   143-253 ms
======  ==============================  =========================  ===========================

The whole-run column holds the start-up of the 4 load-client processes
beside the server: at +10 the workers starve while other processes of
ordinary priority are busy and the world stalls up to a quarter second. A
simulator's physics must not wait on the rest of its machine, so the
default is the mild +3; ``sortie server --aircraft-worker-nice 10`` trades
those stalls for the lower latency where nothing else runs beside it.

A tick's result, :class:`AirTick`, holds every aircraft's raw state row
(``fdm.state.RAW_PROPERTIES``), its crashed / on-ground flags and its fdm
events. A worker that dies (JSBSim aborting, the OOM killer) loses only its
own aircraft: the tick reports their ids in ``lost`` and the others go on.
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing
import os
import signal
import threading
from dataclasses import dataclass, field

import numpy as np

from fdm.aircraft import Aircraft, InitialConditions
from fdm.autopilot import Autopilot, Targets, WaypointFollower
from fdm.fleet import Fleet
from fdm.state import RAW_WIDTH
from sortie.errors import InvalidArgument, NotFound, SortieError

logger = logging.getLogger(__name__)

# Most worker processes a host starts (each holds JSBSim instances, the
# terrain and its caches: 100-200 MB).
MAX_WORKERS = 64
# Seconds a worker may take to start (imports, terrain) or to answer a request
# other than a tick before it is taken for dead.
WORKER_START_TIMEOUT_S = 120.0
# How much lower the workers' CPU priority is than the server's (os.nice
# increment, 0-19; see the module docstring for the measured trade-off).
# Lowering one's own priority needs no privilege.
WORKER_NICE = 3
# An aircraft on its wheels slower than this when its pilot leaves is parked, not flown (m/s).
PARKED_MPS = 2.0
# Pilots (autopilots, routes) fly at this rate whatever the world's: a world tick longer
# than 1/PILOT_HZ is flown in pieces of at most that, the pilots updated before each (an
# f16's roll loop updated once a second, at a 1 Hz world, circled for good), and each
# update advances the pilot's integrators by the piece's time. 30 Hz: the default world
# rate, where a tick is one piece (fdm.aircraft.CHECK_HZ, the fleet's quiet check, too).
PILOT_HZ = 30.0


@dataclass
class AirTick:
    """Every aircraft after a tick, aligned arrays (order: the host's, stable between spawns)."""

    ids: np.ndarray  # (n,) int64 entity ids
    rows: np.ndarray  # (n, RAW_WIDTH) raw state rows
    crashed: np.ndarray  # (n,) bool
    on_ground: np.ndarray  # (n,) bool
    events: list = field(default_factory=list)  # (entity id, fdm.events.Event)
    lost: list = field(default_factory=list)  # entity ids whose worker died


def _empty_tick(lost=()) -> AirTick:
    return AirTick(np.zeros(0, np.int64), np.zeros((0, RAW_WIDTH)), np.zeros(0, bool), np.zeros(0, bool),
                   lost=list(lost))


def _concat(ticks: list[AirTick]) -> AirTick:
    ticks = [t for t in ticks if t.ids.size or t.events or t.lost]
    if not ticks:
        return _empty_tick()
    if len(ticks) == 1:
        return ticks[0]
    return AirTick(np.concatenate([t.ids for t in ticks]), np.concatenate([t.rows for t in ticks]),
                   np.concatenate([t.crashed for t in ticks]), np.concatenate([t.on_ground for t in ticks]),
                   [e for t in ticks for e in t.events], [i for t in ticks for i in t.lost])


class LocalAircraftHost:
    """Aircraft, pilots and one Fleet in this process.

    ``terrain``: anything with ``heights(lat, lon)`` (see fdm.aircraft). The
    pilot of an aircraft is an :class:`fdm.autopilot.Autopilot`, a
    :class:`fdm.autopilot.WaypointFollower` or None (the stick is a client's).
    """

    def __init__(self, terrain, dt: float, geoid_undulation_m: float = 0.0):
        self.terrain = terrain
        self.dt = float(dt)
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.fleet = Fleet(terrain)
        self._aircraft: dict[int, Aircraft] = {}  # entity id -> aircraft, in spawn order
        self._pilots: dict[int, object] = {}
        self._scenario_pilots: dict[int, object] = {}  # WaypointFollower, Targets or None (see spawn)
        self._rows: dict[int, list] = {}  # entity id -> its raw row as of the last tick's end
        self._result = _empty_tick()

    def __len__(self) -> int:
        return len(self._aircraft)

    def _get(self, entity_id: int) -> Aircraft:
        ac = self._aircraft.get(entity_id)
        if ac is None:
            raise NotFound(f"aircraft entity {entity_id} is not on this host")
        return ac

    # -- requests and commands ------------------------------------------------------------------

    def spawn(self, entity_id: int, type_: str, ic: InitialConditions, *, route=None, hold=None,
              speed_mps: float | None = None) -> str:
        """A new aircraft (trimmed when airborne); its catalog name. ``route``
        [(lat, lon, alt_msl_m), ...] flown at ``speed_mps``, or ``hold``
        {heading_deg, alt_msl_m, speed_mps} held, or neither (stick)."""
        if entity_id in self._aircraft:
            raise InvalidArgument("entity_id", "already has an aircraft on this host", value=entity_id)
        ac = Aircraft(type_, self.terrain, ic, dt=self.dt, geoid_undulation_m=self.geoid_undulation_m)
        speed = speed_mps if speed_mps is not None else max(ic.speed_mps, 1.0)
        pilot = None
        if route:
            pilot = WaypointFollower(ac, route, speed_mps=speed)
        elif hold:
            pilot = Autopilot(ac)
            pilot.set_targets(hold.get("heading_deg", ic.heading_deg), hold.get("alt_msl_m"),
                              hold.get("speed_mps", speed))
        self.fleet.add(ac)
        self._aircraft[entity_id] = ac
        self._pilots[entity_id] = pilot
        # What a vanished pilot hands back to: the route follower, or the hold's targets as
        # spawned (a client's autopilot commands replace the pilot's targets, not these).
        self._scenario_pilots[entity_id] = pilot.targets if isinstance(pilot, Autopilot) else pilot
        return ac.name

    def spawn_many(self, specs: list) -> list:
        """:meth:`spawn` for each ``(entity_id, type_, ic, keywords)`` of ``specs``, in order:
        per spec its catalog name, or the error that refused it (the others are spawned
        regardless)."""
        out = []
        for entity_id, type_, ic, kw in specs:
            try:
                out.append(self.spawn(entity_id, type_, ic, **kw))
            except Exception as exc:  # noqa: BLE001 - this spec's error; the others go on
                out.append(_portable(exc))  # it may cross a pipe
        return out

    def remove(self, entity_id: int) -> None:
        self.fleet.remove(self._get(entity_id))
        del self._aircraft[entity_id]
        del self._pilots[entity_id]
        del self._scenario_pilots[entity_id]
        self._rows.pop(entity_id, None)

    def stick(self, entity_id: int, values: dict) -> None:
        """Validated controls (fdm.aircraft.validate_controls); the pilot lets go of the aircraft."""
        ac = self._get(entity_id)
        self._pilots[entity_id] = None
        ac.set_controls(**values)

    def _hold_present(self, entity_id: int) -> Autopilot:
        ac = self._get(entity_id)
        s = ac.state()
        pilot = Autopilot(ac)
        pilot.set_targets(math.degrees(s.euler_rad[2]) % 360.0, s.alt_msl_m, max(s.airspeed_true_mps, 1.0))
        self._pilots[entity_id] = pilot
        return pilot

    def autopilot(self, entity_id: int, targets: dict) -> None:
        """Autopilot targets (heading_deg, alt_msl_m, speed_mps); one not given keeps the
        autopilot's present target (as StickControls' unset fields and a ground vehicle's
        commands do: a heading alone turns the aircraft and keeps its altitude and speed
        held). An aircraft without an autopilot first gets one holding its present state."""
        pilot = self._pilots.get(entity_id)
        if isinstance(pilot, WaypointFollower):  # off its route, from what its route had it fly
            pilot = self._pilots[entity_id] = pilot.autopilot  # (a climb to the next waypoint goes on)
        elif not isinstance(pilot, Autopilot):
            pilot = self._hold_present(entity_id)
        now = pilot.targets
        pilot.set_targets(*(now_v if targets.get(name) is None else targets[name] for name, now_v in
                            (("heading_deg", now.heading_deg), ("alt_msl_m", now.alt_msl_m),
                             ("speed_mps", now.speed_mps))))

    def hand_to_autopilot(self, entity_id: int) -> None:
        """An aircraft left by its pilot returns to its scenario autopilot, whatever the
        pilot last flew it with (as a ground vehicle returns to its route): its route, from
        the waypoint it was making for when the pilot took it, or its scenario hold. With
        neither, or its route flown, it keeps the autopilot the pilot last set, else holds its
        present heading, altitude and speed; one at rest on the ground stays there, idle with its
        brakes on (an airborne hold of 1 m/s had it taxi off). No change when it has crashed."""
        ac = self._get(entity_id)
        if ac.crashed:
            return
        spawned = self._scenario_pilots.get(entity_id)
        if isinstance(spawned, WaypointFollower) and not spawned.done:
            if self._pilots.get(entity_id) is not spawned:  # (else the pilot never took it off its route)
                resumed = WaypointFollower(ac, spawned.waypoints[spawned.active:], spawned.speed_mps,
                                           spawned.capture_radius_m)
                # The next pilot to leave it hands it back to where this one got to.
                self._pilots[entity_id] = self._scenario_pilots[entity_id] = resumed
        elif isinstance(spawned, Targets):
            if getattr(self._pilots.get(entity_id), "targets", None) is not spawned:
                self._pilots[entity_id] = Autopilot(ac, spawned)
        elif isinstance(self._pilots.get(entity_id), Autopilot):
            pass
        elif ac.on_ground and ac.state().ground_speed_mps < PARKED_MPS:
            self.stick(entity_id, {"throttle": 0.0, "brakes": 1.0})
        else:
            self._hold_present(entity_id)

    def crash(self, entity_id: int, t: float, lat: float, lon: float, alt_m: float, reason: str) -> None:
        """A crash the world found (its segment test): the aircraft stops where it is.
        The world reports the event itself."""
        self._get(entity_id).crash(t, lat, lon, alt_m, reason)

    def controls(self, entity_id: int):
        """The aircraft's present fdm.aircraft.Controls."""
        return self._get(entity_id).controls

    def pilot_kind(self, entity_id: int) -> str:
        """"autopilot", "route" or "stick"."""
        pilot = self._pilots.get(entity_id)
        self._get(entity_id)
        return "stick" if pilot is None else "route" if isinstance(pilot, WaypointFollower) else "autopilot"

    # -- ticking --------------------------------------------------------------------------------

    def begin_tick(self, steps: int) -> None:
        """Every aircraft runs ``steps`` JSBSim steps through the Fleet, in pieces of at most
        1/PILOT_HZ, the pilots updated before each piece (on the first, each on its
        aircraft's row of the last tick when it has one)."""
        piece = max(1, int(round(1.0 / (PILOT_HZ * self.dt))))
        rows = self._rows  # nothing between two ticks changes an aircraft's state (controls are not state)
        with_events = []
        for start in range(0, max(int(steps), 0), piece):
            n = min(piece, steps - start)
            for entity_id, pilot in self._pilots.items():
                ac = self._aircraft[entity_id]
                if pilot is not None and not ac.crashed:
                    pilot.update(rows.get(entity_id) if start == 0 else None, n * self.dt)
            with_events += self.fleet.advance(n)
        events = []
        if with_events:  # rare: the owners are looked up only then
            owner = {id(ac): entity_id for entity_id, ac in self._aircraft.items()}
            events = [(owner[id(ac)], ev) for ac, evs in with_events for ev in evs]
        n = len(self._aircraft)
        ids = np.fromiter(self._aircraft, np.int64, n)
        values = [ac.raw_values() for ac in self._aircraft.values()]
        self._rows = dict(zip(self._aircraft, values))
        rows = np.array(values).reshape(n, RAW_WIDTH)
        crashed = np.fromiter((ac.crashed for ac in self._aircraft.values()), bool, n)
        on_ground = np.fromiter((ac.on_ground for ac in self._aircraft.values()), bool, n)
        self._result = AirTick(ids, rows, crashed, on_ground, events)

    def end_tick(self) -> AirTick:
        result, self._result = self._result, _empty_tick()
        return result

    def close(self) -> None:
        pass


# -- worker processes ---------------------------------------------------------------------------

# What a queued command and a request may call on the worker's LocalAircraftHost (anything
# else is refused there).
_COMMANDS = frozenset({"remove", "stick", "autopilot", "hand_to_autopilot", "crash"})
_REQUESTS = frozenset({"spawn_many", "controls", "pilot_kind", "tick", "close"})


def _worker_main(conn, terrain_factory, dt: float, geoid_undulation_m: float, nice: int = 0) -> None:
    """A worker: a LocalAircraftHost answering (commands, request) messages until closed.

    It leaves SIGINT to the server: a Ctrl-C in a terminal goes to the whole process group,
    and the server, stopping cleanly, closes its workers (a KeyboardInterrupt here printed a
    traceback and lost the worker's aircraft before the server's last tick). A parent gone
    (killed, or stopped while this worker started) ends it quietly: its pipe is broken, so
    nothing can be answered (a BrokenPipeError traceback before)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        if nice:
            os.nice(nice)
        host = LocalAircraftHost(terrain_factory(), dt, geoid_undulation_m)
        conn.send(("ok", os.getpid()))
    except BaseException as exc:  # noqa: BLE001 - reported to the parent, which raises it
        try:
            conn.send(("err", _portable(exc)))
        except OSError:  # the parent has gone
            pass
        return
    while True:
        try:
            commands, (name, args, kwargs) = conn.recv()
        except (EOFError, OSError):
            return  # the parent has gone
        for cmd, cargs in commands:
            try:
                if cmd not in _COMMANDS:
                    raise SortieError(f"not an aircraft command: {cmd!r}")
                getattr(host, cmd)(*cargs)
            except SortieError as exc:  # e.g. a command for an aircraft removed meanwhile
                logger.warning("aircraft worker: %s%r ignored: %s", cmd, cargs, exc)
        try:
            if name == "tick":
                host.begin_tick(*args)
                reply = ("ok", host.end_tick())
            elif name == "close":
                conn.send(("ok", None))
                return
            elif name not in _REQUESTS:
                raise SortieError(f"not an aircraft host request: {name!r}")
            else:
                reply = ("ok", getattr(host, name)(*args, **kwargs))
        except BaseException as exc:  # noqa: BLE001 - the parent raises it as the caller's error
            reply = ("err", _portable(exc))
        try:
            conn.send(reply)
        except OSError:
            return  # the parent has gone


def _portable(exc: BaseException) -> BaseException:
    """The exception if it survives pickling, else a SortieError with its text."""
    import pickle

    try:
        pickle.loads(pickle.dumps(exc))
        return exc
    except Exception:  # noqa: BLE001 - any failure to round-trip
        return SortieError(f"{type(exc).__name__}: {exc}")


@contextlib.contextmanager
def _sigint_ignored():
    """SIGINT ignored while in the block, on the main thread (the only one that may set a
    handler; elsewhere nothing changes): a process started in it inherits the ignored
    disposition, which Python keeps ("SIGINT is translated into a KeyboardInterrupt
    exception if the parent process has not changed it",
    https://docs.python.org/3/library/signal.html), so a Ctrl-C while a worker imports
    interrupts nothing there. A SIGINT to this process inside the block (a few ms) is lost."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler if previous is None else previous)


class _Worker:
    def __init__(self, ctx, index: int, terrain_factory, dt: float, geoid_undulation_m: float, nice: int):
        self.index = index
        self.conn, child = ctx.Pipe()
        self.process = ctx.Process(target=_worker_main, args=(child, terrain_factory, dt, geoid_undulation_m, nice),
                                   name=f"sortie-aircraft-{index}", daemon=True)
        with _sigint_ignored():  # from its first instruction, while it imports (see _worker_main)
            self.process.start()
        child.close()
        self.commands: list = []
        self.ids: set[int] = set()
        self.alive = True
        self.waiting = False  # a tick was sent and not yet received
        self.stash = None  # a tick's result received early (to make way for a request)

    def started(self) -> None:
        if not self.conn.poll(WORKER_START_TIMEOUT_S):
            raise SortieError(f"aircraft worker {self.index} did not start within {WORKER_START_TIMEOUT_S:g} s")
        status, value = self.conn.recv()
        if status == "err":
            raise value

    def send(self, name: str, *args, **kwargs) -> None:
        commands, self.commands = self.commands, []
        self.conn.send((commands, (name, args, kwargs)))

    def receive(self):
        status, value = self.conn.recv()
        if status == "err":
            raise value
        return value

    def request(self, name: str, *args, **kwargs):
        self.ask(name, *args, **kwargs)
        return self.answer(name)

    def ask(self, name: str, *args, **kwargs) -> None:
        """Send a request (:meth:`answer` receives its answer: other workers can be asked between)."""
        if self.waiting:  # a tick is under way: its answer comes first
            self.stash = self.receive()
            self.waiting = False
        self.send(name, *args, **kwargs)

    def answer(self, name: str):
        if not self.conn.poll(WORKER_START_TIMEOUT_S):
            raise SortieError(f"aircraft worker {self.index} did not answer {name} within "
                              f"{WORKER_START_TIMEOUT_S:g} s")
        return self.receive()


class ProcessAircraftHost:
    """The aircraft spread over ``workers`` processes (see the module docstring).

    ``terrain_factory``: a picklable callable with no arguments that opens the
    terrain in a worker (a module-level function, or functools.partial of
    one): the same DEM files, or a client of the same terrain service, so
    that every process gets the same terrain answers. New aircraft go to the
    worker holding the fewest. ``nice``: how much lower the workers' CPU
    priority is than this process's (0-19).
    """

    def __init__(self, terrain_factory, dt: float, geoid_undulation_m: float = 0.0, workers: int = 2,
                 nice: int = WORKER_NICE):
        if not (isinstance(workers, int) and 1 <= workers <= MAX_WORKERS):
            raise InvalidArgument("aircraft_workers", f"must be an integer in [1, {MAX_WORKERS}]", value=workers)
        if not (isinstance(nice, int) and not isinstance(nice, bool) and 0 <= nice <= 19):
            raise InvalidArgument("aircraft_worker_nice", "must be an integer in [0, 19]", value=nice)
        if not callable(terrain_factory):
            raise InvalidArgument("terrain_factory", "must be a picklable callable that opens the terrain",
                                  value=terrain_factory)
        # spawn, not fork: the server's process has gRPC threads, which fork does not survive.
        ctx = multiprocessing.get_context("spawn")
        self._workers = [_Worker(ctx, k, terrain_factory, dt, geoid_undulation_m, nice) for k in range(workers)]
        try:
            for w in self._workers:
                w.started()
        except BaseException:
            self.close()
            raise
        self._where: dict[int, _Worker] = {}
        self._lost: list[int] = []  # ids of aircraft lost since the last end_tick

    def __len__(self) -> int:
        return len(self._where)

    @property
    def pids(self) -> list[int]:
        return [w.process.pid for w in self._workers]

    def _of(self, entity_id: int) -> _Worker:
        w = self._where.get(entity_id)
        if w is None:
            raise NotFound(f"aircraft entity {entity_id} is not on this host")
        return w

    def spawn(self, entity_id: int, type_: str, ic: InitialConditions, *, route=None, hold=None,
              speed_mps: float | None = None) -> str:
        """:meth:`LocalAircraftHost.spawn` on the worker holding the fewest (a batch of one)."""
        name = self.spawn_many([(entity_id, type_, ic, dict(route=route, hold=hold, speed_mps=speed_mps))])[0]
        if isinstance(name, BaseException):
            raise name
        return name

    def spawn_many(self, specs: list) -> list:
        """:meth:`LocalAircraftHost.spawn_many`, the specs shared out over the workers (each
        to the one holding the fewest) and spawned by all of them at once: a scenario's
        aircraft load and trim on every core instead of one after the other."""
        live = [w for w in self._workers if w.alive]
        if not live:
            raise SortieError("every aircraft worker has exited")
        for entity_id, *_ in specs:
            if entity_id in self._where:
                raise InvalidArgument("entity_id", "already has an aircraft on this host", value=entity_id)
        load = {w.index: len(w.ids) for w in live}
        share: dict[int, list[int]] = {w.index: [] for w in live}
        for k in range(len(specs)):
            w = min(live, key=lambda w: (load[w.index], w.index))
            load[w.index] += 1
            share[w.index].append(k)
        out: list = [None] * len(specs)
        asked = []
        for w in live:
            if not share[w.index]:
                continue
            try:
                w.ask("spawn_many", [specs[k] for k in share[w.index]])
                asked.append(w)
            except (EOFError, OSError):
                self._lost += self._lose(w)
                for k in share[w.index]:
                    out[k] = SortieError(f"aircraft worker {w.index} exited; try again")
        for w in asked:  # every answer is received, whatever happened to the others
            try:
                names = w.answer("spawn_many")
            except (EOFError, OSError):
                self._lost += self._lose(w)
                names = [SortieError(f"aircraft worker {w.index} exited; try again")] * len(share[w.index])
            except Exception as exc:  # noqa: BLE001 - the worker's error, for each of its specs
                names = [exc] * len(share[w.index])
            for k, name in zip(share[w.index], names):
                out[k] = name
                if not isinstance(name, BaseException):
                    w.ids.add(specs[k][0])
                    self._where[specs[k][0]] = w
        return out

    def _command(self, entity_id: int, name: str, *args) -> None:
        self._of(entity_id).commands.append((name, (entity_id, *args)))

    def remove(self, entity_id: int) -> None:
        w = self._of(entity_id)
        w.commands.append(("remove", (entity_id,)))
        w.ids.discard(entity_id)
        del self._where[entity_id]

    def stick(self, entity_id: int, values: dict) -> None:
        self._command(entity_id, "stick", values)

    def autopilot(self, entity_id: int, targets: dict) -> None:
        self._command(entity_id, "autopilot", targets)

    def hand_to_autopilot(self, entity_id: int) -> None:
        self._command(entity_id, "hand_to_autopilot")

    def crash(self, entity_id: int, t: float, lat: float, lon: float, alt_m: float, reason: str) -> None:
        self._command(entity_id, "crash", t, lat, lon, alt_m, reason)

    def controls(self, entity_id: int):
        return self._of(entity_id).request("controls", entity_id)

    def pilot_kind(self, entity_id: int) -> str:
        return self._of(entity_id).request("pilot_kind", entity_id)

    def begin_tick(self, steps: int) -> None:
        for w in self._workers:
            if w.alive and (w.ids or w.commands):
                try:
                    w.send("tick", steps)
                    w.waiting = True
                except (BrokenPipeError, OSError):
                    self._lost += self._lose(w)

    def end_tick(self) -> AirTick:
        results = [_empty_tick(self._lost)] if self._lost else []
        self._lost = []
        for w in self._workers:
            if w.stash is not None:
                results.append(w.stash)
                w.stash = None
                continue
            if not w.waiting:
                continue
            w.waiting = False
            try:
                results.append(w.receive())
            except (EOFError, OSError):
                results.append(_empty_tick(self._lose(w)))
        return _concat(results)

    def _lose(self, w: _Worker) -> list[int]:
        """A worker died: forget it and its aircraft; their ids."""
        logger.error("aircraft worker %d (pid %s) exited with %s; its %d aircraft are lost", w.index,
                     w.process.pid, w.process.exitcode, len(w.ids))
        w.alive = False
        lost = sorted(w.ids)
        for entity_id in lost:
            del self._where[entity_id]
        w.ids.clear()
        w.commands.clear()
        return lost

    def close(self) -> None:
        """Stop the workers (politely, then not)."""
        for w in self._workers:
            if w.alive and w.process.is_alive():
                try:
                    w.commands.clear()
                    if w.waiting:
                        w.receive()
                    w.send("close")
                except (EOFError, OSError, SortieError):
                    pass
            w.alive = False
        for w in self._workers:
            w.process.join(5.0)
            if w.process.is_alive():
                w.process.kill()
                w.process.join(1.0)
            w.conn.close()
