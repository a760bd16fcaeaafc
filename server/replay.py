"""``sortie replay``: a recording served through the live streaming API.

Clients, renderers and bots join and watch a replay exactly as a live
exercise (sortie.v1.SimulationService: Join as an observer, Watch with the
full snapshot first, interest management, dead reckoning, WatchEvents,
GetWorld), because the same code serves them: :class:`ReplayWorld` stands
in for server.world.World (its snapshot comes from the recording's frames
instead of the physics) and the same Sessions, Publisher and servicer run
over it. Replay controls are a second service on the same port,
sortie.v1.ReplayService: play, pause, speed 0.1x-64x, seek to any time,
step by ticks.

An observer stands on the recorded terrain, as live (its area of interest is
centred on the ground: sim_service.Sessions._ground_point): the terrain is
found as ``sortie resim`` and ``sortie export gltf`` find it (the header's DEM
files, or those its terrain service read, with the scenario's insets; or
``--dem`` / ``--terrain``) and opened on a thread of its own from the start
(:class:`RecordedTerrain`), so a large terrain delays no start and only an
observer's Join waits for it. Where none can be opened, observers stand at
mean sea level (the geoid's undulation above the ellipsoid), with one warning.

The replay clock thread runs at the exercise's network rate in *wall*
time: each period it moves the replay position by speed x the wall time
elapsed, shows the recorded tick at that position (one chunk decoded per
second of world time; seeking is the index's bisection and one chunk) and
publishes, so at 64x each update jumps 3.2 world seconds and dead reckoning
decides what changed enough to send. Events recorded between the ticks shown
go out on WatchEvents as they are passed while playing or stepping forward
(not when seeking); playing, an update stops at a tick with a crash, a
destruction or a collision (its states and its events) and goes on past it at
the next one, so no later state (a wreck's, at rest) is published with the
event, as live (:meth:`ReplayWorld.next_stop`). After a seek or a step,
forward or back, every Watch stream starts over: its next update is a full
snapshot (``snapshot = true``, which a client takes in place of what it
holds), with every visible entity's state at the new time. Only observers may
join: a replay has no agents to command (take-over is ``sortie resim
--take-over``).
"""

from __future__ import annotations

import bisect
import functools
import logging
import math
import sys
import threading
import time

import grpc
import numpy as np

from server.grpc_common import (DEFAULT_GRACE_S, HOST_HELP, AioManagedServer, listen_address, stop_signals,
                                wait_for_signal)
from server.recording import Recording
from server.sim_service import (MAX_CONCURRENT_RPCS, SERVICE_NAME, Sessions, SimulationServicer, method_handlers,
                                status_of)
from server.streaming import Publisher
from server.world import KIND_NAMES, STATIC, Entity, EventLog, Snapshot, WorldEvent, _empty_snapshot
from sortie.config import MAX_GRACE_S, grace_seconds
from sortie.errors import DataFormatError, InvalidArgument, NotFound, PermissionDenied
from sortie.logs import line
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic

logger = logging.getLogger(__name__)

REPLAY_SERVICE = "sortie.v1.ReplayService"
# The longest a Watch waits for its snapshot, whatever the recording's network rate (s).
REPLAY_POLL_S = 0.1
MIN_SPEED, MAX_SPEED = 0.1, 64.0
MAX_STEP_TICKS = 1_000_000
# Events after which an entity's states mean something else (a wreck from then on, at rest; a
# collision's velocity is the one before it): playback shows each tick of one with its events
# before any later tick (ReplayWorld.next_stop).
STOP_EVENT_KINDS = ("crash", "destroyed", "collision")


class RecordedTerrain:
    """The terrain a replay's observers stand on: ``spec`` (the arguments of
    server.sim_server.open_terrain_source; None: none to open) opened on a thread of its own
    by :meth:`start`, which :meth:`get` waits for. One that does not open is None, with one
    warning naming why: observers stand at mean sea level then."""

    def __init__(self, spec: dict | None, what: str = "the recorded terrain"):
        self.spec = spec
        self.what = what
        self._terrain = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._opened = threading.Event()

    def start(self) -> None:
        """Begin opening it (once; at once done when there is nothing to open)."""
        with self._lock:
            if self._thread is not None or self._opened.is_set():
                return
            if self.spec is None:
                self._opened.set()
                return
            self._thread = threading.Thread(target=self._open, name="replay-terrain", daemon=True)
            self._thread.start()

    def _open(self) -> None:
        from server.sim_server import open_terrain_source

        try:
            self._terrain = open_terrain_source(**self.spec)
            logger.info("replay: observers stand on %s", self.what)
        except Exception as exc:  # noqa: BLE001 - any failure leaves observers at mean sea level, said once
            logger.warning("replay: %s does not open (%s): observers stand at mean sea level", self.what, exc)
        finally:
            self._opened.set()

    def get(self):
        """The terrain (``heights(lat, lon)``) once opened, None where it did not open."""
        self.start()
        self._opened.wait()
        return self._terrain

    def close(self) -> None:
        """Close it if it opened and holds a connection (a terrain service's client); a thread
        still opening it is left to end on its own (a daemon)."""
        if self._opened.is_set() and hasattr(self._terrain, "close"):
            self._terrain.close()


class ReplayWorld(EventLog):
    """What the session service and the publisher read from a World, fed by a recording.

    :meth:`show` puts one recorded tick on display (and emits the events
    recorded since the last tick shown, when asked). ``recorded_terrain`` (a
    :class:`RecordedTerrain`, or None) is the ground observers stand on."""

    def __init__(self, rec: Recording, recorded_terrain: RecordedTerrain | None = None):
        super().__init__()
        self.rec = rec
        self.recorded_terrain = recorded_terrain
        self.dt = rec.dt
        self.geoid_undulation_m = rec.header.geoid_undulation_m
        described = {i: _described(i, e) for i, e in rec.entities.items()}
        self.entities = {i: Entity(i, *d[1:5]) for i, d in described.items()}
        self.infos = described
        self.tick_count = rec.first_tick - 1
        self.time_s = self.tick_count * self.dt
        self.snapshot = _empty_snapshot(self.time_s, self.tick_count)
        self.damaged: dict[int, str] = {}  # chunk -> why it does not read (each logged once)
        self._wreck_ticks: dict[int, int] | None = None  # entity -> tick of its crash/destruction
        self._stop_ticks: list[int] = []  # ticks of STOP_EVENT_KINDS events, ascending (with _wreck_ticks)

    def _read_wrecks(self) -> None:
        """The recording's crash, destroyed and collision events, read once, on first need (one
        pass over the chunks that read, as ``sortie recording check`` makes)."""
        if self._wreck_ticks is not None:
            return
        ticks: dict[int, int] = {}
        stops: set[int] = set()
        for r in self.rec.events(skipped=[]):
            if r.event.kind in STOP_EVENT_KINDS:
                stops.add(int(r.tick))
                if r.event.kind != "collision":
                    ticks.setdefault(int(r.event.entity_id), int(r.tick))
        self._stop_ticks = sorted(stops)
        self._wreck_ticks = ticks

    @property
    def wrecks(self) -> frozenset:
        """Entities crashed or destroyed by the tick shown (as World.wrecks: a view they enter is
        told so)."""
        self._read_wrecks()
        return frozenset(i for i, t in self._wreck_ticks.items() if t <= self.tick_count)

    def next_stop(self, after: int, before: int) -> int | None:
        """The first tick in (``after``, ``before``) with a crash, destruction or collision
        event (STOP_EVENT_KINDS), None if none: playing forward, the replay shows that tick
        (its states and its events) and goes on past it at the next network update, so no
        state after such an event is published with it. Live, the world publishes each
        tick's events with its states, and the wreck's states at rest come ticks later; a
        replay jumping speed x world rate / network rate ticks per update (12 at 8x) would
        otherwise publish the wreck's states with the event, and a receiver reading the
        events on their own stream (``sortie dis``) could see the wreck at rest, undamaged,
        before the crash."""
        self._read_wrecks()
        i = bisect.bisect_right(self._stop_ticks, after)
        return self._stop_ticks[i] if i < len(self._stop_ticks) and self._stop_ticks[i] < before else None

    def _damaged(self, k: int, exc: DataFormatError) -> None:
        if k not in self.damaged:
            self.damaged[k] = str(exc)
            logger.warning("replay passes over a damaged chunk: %s", exc)

    def show(self, tick: int, events: bool) -> None:
        """Display recorded ``tick``; with ``events``, emit those recorded after the tick
        shown before it, up to it (a damaged chunk's events are lost, with a warning).
        DataFormatError naming the chunk when ``tick``'s own chunk is damaged: nothing changes."""
        rec = self.rec
        f = rec.frame(tick)
        unknown = set(f.ids.tolist()) - self.infos.keys()
        if unknown:  # described by no chunk that reads (Recording.undescribed); new dicts: others read these
            self.infos = {**self.infos, **{i: _described(i, None) for i in unknown}}
            self.entities = {**self.entities, **{i: Entity(*self.infos[i][:5]) for i in unknown}}
        if events and f.tick > self.tick_count:
            # Events after tick k are kept with tick k + 1's chunk (server/recording.py).
            last_chunk = min(rec.chunk_of_tick(f.tick + 1) + 1, rec.chunk_count)
            for k in range(rec.chunk_of_tick(self.tick_count + 1), last_chunk):
                try:
                    chunk = rec.chunk(k)
                except DataFormatError as exc:
                    self._damaged(k, exc)
                    continue
                for r in chunk.events:
                    if self.tick_count < r.tick <= f.tick:
                        e = r.event
                        self._append_event(WorldEvent(e.time_s, e.kind, e.entity_id, e.lat_deg, e.lon_deg, e.alt_msl_m,
                                              _detail(e.detail_json)))
        s = f.states
        lat, lon, h = ecef_to_geodetic(s[:, 0:3]) if f.ids.size else (np.zeros(0),) * 3
        self.snapshot = Snapshot(f.time_s, f.tick, f.ids, s[:, 0:3], s[:, 3:6], s[:, 6:9], s[:, 9:13], s[:, 13:16],
                                 np.asarray(lat), np.asarray(lon), np.asarray(h) - self.geoid_undulation_m)
        self.tick_count, self.time_s = f.tick, f.time_s

    # -- the World interface of server.sim_service ------------------------------------------------

    @property
    def terrain(self):
        """The recorded terrain, waited for while it opens; None where there is none (an
        observer's centre is then at mean sea level: sim_service.Sessions._ground_point)."""
        return None if self.recorded_terrain is None else self.recorded_terrain.get()

    def claim(self, entity_id: int, owner: str, client: str = ""):
        raise InvalidArgument("role", "a replay has no agents to control: join as an observer")

    def release(self, entity_id: int, vanished: bool = False) -> None:
        pass

    def command(self, entity_id: int, kind: str, values: dict) -> None:
        raise PermissionDenied("a replay takes no commands")

    def external_owner(self, external_id: str) -> None:
        return None

    def publish_external(self, external_id: str, owner: str, state=None, *args, **kwargs) -> int:
        raise PermissionDenied("a replay takes no external entities")

    def remove_owned_external(self, owner: str) -> None:
        pass

    def emit(self, kind: str, entity_id: int = 0, **detail) -> None:
        self._append_event(WorldEvent(self.time_s, kind, entity_id, detail=detail))


def _described(i: int, e) -> tuple:
    """The info tuple (server.world.World.infos) of entity ``i`` as recorded (``e``: its
    EntityInfo, or None). One the recording does not describe (first held by a lost chunk,
    server/recording.py) shows as a static object named after its id."""
    if e is None or e.kind not in KIND_NAMES:
        return (i, e.name if e is not None and e.name else f"entity {i}", STATIC, "undescribed", "neutral")
    return (i, e.name, e.kind, e.type, e.coalition) + ((e.external_id,) if e.external_id else ())


def _detail(text: str) -> dict:
    import json

    try:
        d = json.loads(text) if text else {}
        return d if isinstance(d, dict) else {"detail": d}
    except ValueError:
        return {"detail": text}


class ReplaySessions(Sessions):
    def join(self, name: str, role: int, agent_name: str = "", observer=None):
        if role not in (pb.ROLE_OBSERVER, pb.ROLE_GATEWAY):
            raise InvalidArgument("role", "a replay serves observers and gateways only (take over an agent with "
                                          "sortie resim --take-over)",
                                  value=pb.Role.Name(role) if role in pb.Role.values() else role)
        return super().join(name, role, agent_name, observer)


class ReplayServer:
    """A recording + its replay clock + SimulationService and ReplayService. ``start()``, ``stop()``."""

    def __init__(self, path, address: str = "127.0.0.1:0", speed: float = 1.0, playing: bool = True,
                 start_s: float | None = None, dem=None, terrain_service: str | None = None):
        """``dem`` files or a ``terrain_service`` address stand in for the recorded terrain
        (NotFound for a DEM file that is not there); without them, the recording's own."""
        from server.dead_reckoning import DeadReckoner
        from server.resim import recorded_scenario
        from server.sim_server import ServerConfig, server_config

        if start_s is not None and math.isnan(start_s):
            raise InvalidArgument("start_s", "must be a number of seconds", value=start_s)
        self.rec = Recording(path)
        scenario = None
        try:
            scenario = recorded_scenario(self.rec)
            self.config = server_config(scenario, self.rec.header.terrain.description)
        except Exception as exc:  # noqa: BLE001 - a scenario this build cannot read: default parameters
            logger.warning("replay of %s with default parameters: %s", path, exc)
            self.config = ServerConfig(exercise_name=self.rec.header.exercise_name,
                                       start_time=self.rec.header.start_time)
        try:
            self.terrain = replay_terrain(self.rec, scenario, dem, terrain_service)
        except BaseException:
            self.rec.close()
            raise
        self.world = ReplayWorld(self.rec, self.terrain)
        self._check_speed(speed)
        self.speed = float(speed)
        self.playing = bool(playing)
        self._lock = threading.Lock()
        self._position_s = self.rec.first_time_s if start_s is None else self._clamp(start_s)
        self._last_wall = time.monotonic()  # when the position was last advanced
        self._seeked = True
        self._step_events = False  # with _seeked: a forward step, whose events go out as played
        self.sessions = ReplaySessions(self.world, self.params_of, self.config.vanished_timeout_s)
        self.publisher = Publisher(DeadReckoner(), lambda i: self.params_of(i).thresholds)
        self._stop = threading.Event()
        self._kick = threading.Event()  # wakes the clock thread after a control
        self.finished = threading.Event()
        self.error: BaseException | None = None  # what stopped the clock thread, if anything did
        self._thread = threading.Thread(target=self._run, name="replay-clock", daemon=True)
        servicer = functools.partial(SimulationServicer, self.sessions, self.world_info)
        self.servicer = None  # made by the gRPC server's start, with its thread pool

        def handlers(pool):
            self.servicer = servicer(pool)
            return method_handlers(self.servicer)

        self.grpc = AioManagedServer(SERVICE_NAME, handlers, address, max_rpcs=MAX_CONCURRENT_RPCS,
                                     extra_services=[(REPLAY_SERVICE, lambda pool: self._handlers())])
        self.port = self.grpc.port
        self.address = f"{address.rsplit(':', 1)[0]}:{self.port}"

    def params_of(self, entity_id, kind: str | None = None):
        from server.sim_server import type_params

        return type_params(self.config.params, self.world.entities, entity_id, kind)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        self.terrain.start()  # on its own thread: only an observer's Join waits for it
        self._show()
        self.grpc.start()
        self._thread.start()

    def stop(self, grace_s: float = 2.0) -> None:
        self._stop.set()
        self._thread.join(timeout=10.0)
        for s in self.sessions.watching():
            s.queue.close()
        if self.servicer is not None:  # events and client streams end OK too, now
            self.servicer.close()
        self.grpc.stop(grace_s).wait()
        self.terrain.close()
        self.rec.close()

    # -- controls -------------------------------------------------------------------------------

    @staticmethod
    def _check_speed(speed) -> None:
        if not (isinstance(speed, (int, float)) and math.isfinite(speed) and MIN_SPEED <= speed <= MAX_SPEED):
            raise InvalidArgument("speed", f"must be in [{MIN_SPEED:g}, {MAX_SPEED:g}]", value=speed)

    def _clamp(self, t: float) -> float:
        return min(max(float(t), self.rec.first_time_s), self.rec.last_time_s)

    def control(self, msg: rpb.ReplayControl) -> rpb.ReplayStatus:
        which = msg.WhichOneof("action")
        with self._lock:
            if which is None:
                raise InvalidArgument("action", "set one of play, pause, speed, seek_time_s, step_ticks")
            if which in ("play", "pause") and not getattr(msg, which):
                # A oneof bool names its action by being set; false would read as its opposite
                # (pause: false as play) or as nothing, and was taken as true: refused instead.
                other = "pause" if which == "play" else "play"
                raise InvalidArgument(which, f"must be true (false is not an action; set {other}: true to {other})",
                                      value=False)
            if which == "play":
                if self._position_s >= self.rec.last_time_s:  # at the end: play from the start
                    self._position_s, self._seeked = self.rec.first_time_s, True
                self.playing = True
            elif which == "pause":
                self.playing = False
            elif which == "speed":
                self._check_speed(msg.speed)
                self.speed = msg.speed
            elif which == "seek_time_s":
                if not math.isfinite(msg.seek_time_s):
                    raise InvalidArgument("seek_time_s", "must be a finite number", value=msg.seek_time_s)
                position_s = self._clamp(msg.seek_time_s)
                self._check_readable(self.rec.tick_at(position_s))
                self._position_s, self._seeked, self._step_events = position_s, True, False
            else:
                n = msg.step_ticks
                if not 0 < abs(n) <= MAX_STEP_TICKS:
                    raise InvalidArgument("step_ticks", f"must be non-zero, at most {MAX_STEP_TICKS} either way",
                                          value=n)
                tick = min(max(self.rec.tick_at(self._position_s) + n, self.rec.first_tick), self.rec.last_tick)
                self._check_readable(tick)
                self.playing = False
                self._position_s = tick * self.rec.dt
                # Any step resnapshots, as a seek does: paused, a client's picture does not
                # extrapolate (time scale 0) and dead reckoning sends only what passes its
                # threshold, so after a forward step a renderer or debrief tool would keep
                # the old time and positions. A full picture at the new tick is what a
                # Tacview-like frame step shows; a forward step still emits the events it
                # passes (as playing does), a backward one none.
                self._seeked, self._step_events = True, n > 0
            self._wake_clock()
        return self.status()

    def _check_readable(self, tick: int) -> None:
        """DataFormatError (FAILED_PRECONDITION, naming the chunk) when ``tick``'s chunk is damaged:
        a seek or step there is refused and the replay stays where it was."""
        try:
            self.rec.chunk(self.rec.chunk_of_tick(tick))
        except DataFormatError as exc:
            raise DataFormatError(f"cannot show tick {tick} (t = {tick * self.rec.dt:.3f} s): {exc}") from None

    def _wake_clock(self) -> None:
        self._last_wall = time.monotonic()
        self._kick.set()

    def status(self) -> rpb.ReplayStatus:
        """Where the replay is (the position a control just set, shown at the next update)."""
        tick = self.rec.tick_at(self._position_s)
        return rpb.ReplayStatus(time_s=tick * self.rec.dt, tick=tick,
                                first_time_s=self.rec.first_time_s, last_time_s=self.rec.last_time_s,
                                playing=self.playing, speed=self.speed, recording=self.rec.path.name)

    def world_info(self) -> pb.WorldInfo:
        from server.sim_server import world_info

        clock = "paused" if not self.playing else "realtime" if self.speed == 1.0 else "fast"
        return world_info(self.config, self.world.time_s, clock, self.speed if self.playing else 0.0,
                          self.rec.rate_hz, self.world.geoid_undulation_m, self.world.snapshot)

    def _handlers(self) -> dict:
        async def control(request, context):
            try:
                return self.control(request)
            except Exception as exc:  # noqa: BLE001 - every error becomes a status
                await context.abort(status_of(exc), str(exc))

        async def get_status(request, context):
            return self.status()

        def unary(fn, req):
            return grpc.unary_unary_rpc_method_handler(fn, request_deserializer=req.FromString,
                                                       response_serializer=lambda m: m.SerializeToString())

        return {"Control": unary(control, rpb.ReplayControl),
                "GetStatus": unary(get_status, rpb.GetReplayStatusRequest)}

    # -- the replay clock -----------------------------------------------------------------------

    def _show(self) -> None:
        """Advance the position, show its tick, publish (on the clock thread)."""
        with self._lock:
            now = time.monotonic()
            if self.playing:
                self._position_s += (now - self._last_wall) * self.speed
                if self._position_s >= self.rec.last_time_s:
                    self._position_s, self.playing = self.rec.last_time_s, False
            self._last_wall = now
            tick, seeked, step_events = self.rec.tick_at(self._position_s), self._seeked, self._step_events
            self._seeked = self._step_events = False
        if seeked:  # every watcher starts over from a full snapshot at the new time
            self.publisher.reset()
            for session in self.sessions.watching():
                with session.view_lock:  # not half-way through a new Watch's take-over
                    session.reset_visible()
                    session.queue.resnapshot()
        if not seeked and tick > self.world.tick_count:  # playing on: a tick with a crash or collision first
            stop = self.world.next_stop(self.world.tick_count, tick)
            tick = tick if stop is None else stop
        if tick != self.world.tick_count or seeked:
            try:
                self.world.show(tick, events=not seeked or step_events)
            except DataFormatError as exc:
                self._pass_damaged(tick, exc)
        self.publisher.publish(self.world.snapshot, self.world.infos, self.sessions.watching(),
                               self.speed if self.playing else 0.0, self.world.wrecks)

    def _pass_damaged(self, tick: int, exc: DataFormatError) -> None:
        """Playback reached ``tick`` in a damaged chunk: go on from the next chunk (the clients'
        picture starts over there, as after a seek); paused, or with no chunk after it, stay on
        the picture shown."""
        k = self.rec.chunk_of_tick(tick)
        self.world._damaged(k, exc)
        with self._lock:
            if self.playing and k + 1 < self.rec.chunk_count:
                self._position_s = max(self._position_s, self.rec.index.chunk_first_tick[k + 1] * self.rec.dt)
                self._seeked = True
                self._kick.set()
            elif self.playing:
                self.playing = False

    def _run(self) -> None:
        period = 1.0 / self.config.network_rate_hz
        next_show = time.monotonic()
        next_expire = time.monotonic() + 1.0
        try:
            while not self._stop.is_set():
                now = time.monotonic()
                # At the network rate, on a control (kick), and as soon as a Watch awaits its
                # snapshot: a recording's network rate may be as low as its scenario allowed.
                if (now >= next_show or self._kick.is_set()
                        or any(s.queue.needs_snapshot for s in self.sessions.watching())):
                    self._kick.clear()
                    self._show()
                    next_show = now + period
                if time.monotonic() >= next_expire:
                    self.sessions.expire()
                    next_expire = time.monotonic() + 1.0
                # Bounded: a newcomer's snapshot waits at most REPLAY_POLL_S (and Event.wait
                # overflows on a 1e300 s period).
                self._kick.wait(min(max(next_show - time.monotonic(), 0.0), REPLAY_POLL_S))
        except Exception as exc:  # noqa: BLE001 - the clock thread must say why it died
            self.error = exc
            logger.exception("replay clock stopped by an error")
        finally:
            self.finished.set()


def replay_terrain(rec: Recording, scenario=None, dem=None, service: str | None = None) -> RecordedTerrain:
    """The terrain a replay's observers stand on, found as ``sortie resim`` finds it
    (server.resim.recorded_terrain_spec: ``dem`` files or a ``service`` given, else the
    header's DEM files or those its terrain service read; ``scenario``'s insets with DEM
    files, as the world answered from them); not opened yet. Given files that are not there
    are NotFound; where the recording's own cannot be found, a warning now and observers at
    mean sea level."""
    from server.resim import recorded_terrain_spec, with_insets

    try:
        spec, notes = recorded_terrain_spec(rec, dem, service)
    except (NotFound, DataFormatError) as exc:
        if dem or service:
            raise
        logger.warning("replay of %s: observers stand at mean sea level: %s (give --dem FILE... or --terrain "
                       "HOST:PORT for the recorded terrain)", rec.path.name, exc)
        return RecordedTerrain(None)
    for note in notes:
        logger.info("replay: %s", note)
    if scenario is not None:
        with_insets(spec, scenario)
    if "service" in spec:
        what = f"the terrain service {spec['service']}"
    else:
        parts = [str(p) for p in (*spec.get("dem", ()), *spec.get("store", ()))]
        parts += [f"procedural seed {spec['procedural']}"] if "procedural" in spec else []
        what = "the terrain of " + ", ".join(parts)
    return RecordedTerrain(spec, what)


# -- CLI ------------------------------------------------------------------------------------------

def add_parser(sub) -> None:
    p = sub.add_parser("replay", help="serve a recording through the live streaming API, with replay controls",
                       description="Serve a sortie recording through sortie.v1.SimulationService (observers join "
                                   "and watch as live: interest management, dead reckoning, events; an "
                                   "observer stands on the recorded terrain, or --dem / --terrain, at mean sea "
                                   "level where none opens) and sortie.v1.ReplayService (play, pause, speed "
                                   "0.1x-64x, seek, step).")
    p.add_argument("file", help="a .sortie recording")
    p.add_argument("--port", type=int, required=True, help="TCP port; 0 picks a free one")
    terrain = p.add_mutually_exclusive_group()
    terrain.add_argument("--dem", nargs="+", metavar="FILE",
                         help="the DEM files observers stand on (default: the recorded ones)")
    terrain.add_argument("--terrain", metavar="HOST:PORT[,HOST:PORT...]",
                         help="a terrain service (or replicas of one) serving the recorded terrain")
    p.add_argument("--host", default="127.0.0.1", help=f"{HOST_HELP} (default %(default)s)")
    p.add_argument("--speed", type=float, default=1.0, help="times real time, 0.1-64 (default %(default)s)")
    p.add_argument("--paused", action="store_true", help="start paused")
    p.add_argument("--start", type=float, metavar="S", help="start at world time S")
    p.add_argument("--grace-s", type=grace_seconds, default=DEFAULT_GRACE_S,
                   help=f"seconds in-flight calls get on shutdown, 0-{MAX_GRACE_S:g} (default %(default)s)")
    p.set_defaults(func=replay_command)


def replay_command(args) -> int:
    """Serve until SIGTERM/SIGINT (exit 0), or until the replay clock dies (exit 1: a dead
    replay is not served)."""
    if args.start is not None and math.isnan(args.start):
        raise InvalidArgument("--start", "must be a number of seconds", value=args.start)
    server = ReplayServer(args.file, listen_address(args.host, args.port), args.speed, not args.paused, args.start,
                          dem=args.dem, terrain_service=args.terrain)
    with stop_signals() as stop:  # before the line that says it listens (grpc_common.stop_signals)
        server.start()
        r = server.rec
        line(f"sortie replay of {r.path.name} ({r.first_time_s:.1f} .. {r.last_time_s:.1f} s, {len(r.entities)} "
             f"entities) listening on {server.address}", logger=__name__)
        wait_for_signal(server.finished, stop=stop)
    server.stop(args.grace_s)
    if server.error is not None:
        line(f"sortie replay: error: the replay clock stopped: {server.error}", stream=sys.stderr,
             level=logging.ERROR, logger=__name__)
        return 1
    return 0
