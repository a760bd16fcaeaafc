"""The simulation server process: a world, its clock thread, and the gRPC service.

The clock thread owns the world: it ticks it at the world rate, hands each
snapshot due at the network rate to the publisher thread, which publishes it
to the watching sessions (dead reckoning and interest management,
server/streaming.py), and expires vanished sessions once a second. Clock modes: "realtime" (world time follows the wall clock),
"fast" (``time_scale`` times the wall clock, or as fast as the machine goes
if it cannot keep up: bots and tests), and "paused" (no ticks until
resumed). When ticks fall more than MAX_LAG_S behind the clock does not try
to catch up in a burst: it slips, and the slip is counted (``overruns``);
physics never waits on the network.

Publishing runs beside the ticks, one snapshot at a time and in order: the
clock hands over a tick's snapshot (with the world's entity infos and wrecks
as they were at that tick) and goes on to the next tick, and waits only when
the snapshot before is still waiting for the publisher (a "fast" clock ticking
faster than publishes take), so every snapshot handed over is published. On
the clock thread, the publish (a few milliseconds of dead reckoning, interest,
encoding and queueing for 2,000 entities and 32 sessions, and its waits for
the interpreter beside the streams) lengthened every network tick: measured on
2 cores (150 f16s, 2000 ground vehicles, 32 clients, real time, two
interleaved pairs of runs), tick p50 / p99 11.4-38.8 / 62 ms against
7.6-8.1 / 23-45 ms beside the ticks, and the world tick -> client receipt p99
31-33 ms against 14-25 ms.

The rate advertised to clients (WorldInfo.time_scale, WatchUpdate.time_scale,
which receivers advance their world time by) is the rate the clock achieves:
the set one while it keeps up, else the one measured over the last
RATE_WINDOW_S of wall time (e.g. "fast" x100 that reaches x28 says 28), so a
receiver's estimate of world time does not run ahead of the world.

At the exercise's end (``duration_s``) and at the server's stop the last tick's snapshot is
published, at rate 0 (the clock stopped), whether or not a network tick falls on it: every watcher's picture ends at the
world's last time, each entity within its thresholds (the streams send what was pushed before
the server's end closes them). While paused, the last tick's snapshot is published without the
entities removed since (a gateway or a session's agent gone), and vanished sessions still
time out.

A server started paused runs the world's first tick before it stops (world
time 1 / world rate): until a world has ticked it has no snapshot (its
aircraft's states come from their first tick), and clients joining the paused
exercise get the whole picture, as when a running clock is paused.

What cannot wait for the next network tick is published at the next world
tick (:meth:`SimulationServer._publish_due`): a Watch's first update (its
full snapshot), an entity that came or went, a change of the advertised
clock rate, and a dead-reckoning heartbeat falling due. So a network rate as
low as a scenario allows (anything above 0) still gives a joiner its picture
within a world tick and every entity's state at least every heartbeat. The
heartbeats are tracked (one pass over the entities per publish) only where
the network period is longer than HEARTBEAT_LATE_FRACTION of the shortest
heartbeat in use; otherwise the network ticks themselves send every heartbeat
within that fraction of it, and a tick at the usual rates costs what it did.
"""

from __future__ import annotations

import collections
import functools
import gc
import logging
import math
import threading
import time
from dataclasses import dataclass, field, replace

import numpy as np

from fdm.aircraft import TRIM_OFF_HINT
from server.dead_reckoning import ALGORITHM_NAMES, TIME_SLACK_S, THRESHOLDS_BY_KIND, DeadReckoner, Thresholds
from server.grpc_common import AioManagedServer
from server.scenario import ScenarioError
from server.sim_service import (MAX_CONCURRENT_RPCS, SERVICE_NAME, Sessions, SimulationServicer, StreamStats,
                                method_handlers)
from server.streaming import Publisher
from server.warm_up import warm_up_world
from server.world import KIND_NAMES, World
from sortie.errors import InvalidArgument, LimitExceeded, SortieError
from sortie.v1 import simulation_pb2 as pb

logger = logging.getLogger(__name__)

CLOCKS = ("realtime", "fast", "paused")
DEFAULT_MAX_WORKERS = MAX_CONCURRENT_RPCS  # concurrent RPCs (server.sim_service: sessions x their calls)
EXPIRE_EVERY_S = 1.0
# A realtime clock more than this far behind resynchronises instead of bursting.
MAX_LAG_S = 0.25
# The achieved clock rate is measured over this much wall time (sampled every RATE_SAMPLE_S);
# it is advertised instead of the set rate when it falls short of it by more than
# RATE_TOLERANCE, and changed only by more than that (each change goes to every stream).
RATE_WINDOW_S = 2.0
RATE_SAMPLE_S = 0.1
RATE_TOLERANCE = 0.03
# A heartbeat may go out this fraction of itself late (at the first network tick after it falls
# due); where the network period is longer than that, the clock publishes at the world tick it
# falls due instead (see the module docstring).
HEARTBEAT_LATE_FRACTION = 0.1


@dataclass(frozen=True)
class TypeParams:
    """What the server needs per agent type: area of interest and dead reckoning."""

    aoi_radius_m: float
    thresholds: Thresholds


DEFAULT_PARAMS = {
    "aircraft": TypeParams(80_000.0, THRESHOLDS_BY_KIND["aircraft"]),
    "ground": TypeParams(10_000.0, THRESHOLDS_BY_KIND["ground"]),
    "static": TypeParams(10_000.0, THRESHOLDS_BY_KIND["static"]),
    "observer": TypeParams(200_000.0, THRESHOLDS_BY_KIND["static"]),
}


# Durations a server keeps for its benchmarks and metrics (tick_ms, publish_ms): the newest
# half of them is kept when there are more.
DURATIONS_KEPT = 100_000


def _noted(samples: list, totals: tuple[int, float], ms: float) -> tuple[int, float]:
    """``ms`` appended to ``samples`` (at most DURATIONS_KEPT), and ``totals`` (count, sum of
    milliseconds since the start) with it."""
    samples.append(ms)
    if len(samples) > DURATIONS_KEPT:
        del samples[:DURATIONS_KEPT // 2]
    count, total = totals
    return count + 1, total + ms


def live_rows(snapshot, infos: dict):
    """``snapshot`` (server.world.Snapshot) without the entities no longer in the world (not
    keys of ``infos``, World.infos): a paused world's snapshot stays its last tick's while
    entities are removed (a gateway leaves, a session's agent goes with it), and watchers kept
    them in their pictures until the clock ran again. The snapshot itself where all are live."""
    keep = np.fromiter((i in infos for i in snapshot.ids.tolist()), bool, snapshot.ids.size)
    if keep.all():
        return snapshot
    return replace(snapshot, **{f: getattr(snapshot, f)[keep] for f in (
        "ids", "ecef_m", "vel_ecef_mps", "acc_ecef_mps2", "quat_ecef2body", "body_rates_rps", "lat_deg", "lon_deg",
        "alt_msl_m")})


def type_params(params: dict, entities: dict, entity_id, kind: str | None = None) -> TypeParams:
    """The parameters of entity ``entity_id`` of ``entities`` (by its kind and type name, else
    its kind), or of ``kind`` when entity_id is None; ``params``: ServerConfig.params. A type
    table is looked up with the entity's own kind: a static decoy of type "f16" takes the
    static kind's parameters under the f16 table, not the aircraft's."""
    if entity_id is None:
        return params.get(kind, DEFAULT_PARAMS[kind])
    e = entities.get(entity_id)
    if e is None:
        return params.get("static", DEFAULT_PARAMS["static"])
    k = KIND_NAMES[e.kind]
    return params.get((k, e.type), params.get(k, DEFAULT_PARAMS[k]))


# Entities in cubes of this edge (ECEF) that touch, chained, are one group (every two entities
# this close are; groups a cube apart may join); entities_centre is the largest group's: an
# exercise over two DEMs 7,000 km apart, with no target area, had `sortie client` watch
# mid-Atlantic, between them. Three times client.cli's default observer radius (100 km).
GROUP_CELL_M = 300_000.0


def largest_group(lat_deg, lon_deg) -> np.ndarray:
    """(n,) bool: the entities (lat, lon degrees, finite, (n,) each) of the largest group (see
    GROUP_CELL_M: connected cubes, each touching its 26 neighbours); where groups tie, the one
    holding the least cube (ECEF cell indices compared in order), so that the entities' order
    does not matter."""
    from terrain.geodesy import geodetic_to_ecef

    cells = np.floor(geodetic_to_ecef(lat_deg, lon_deg, np.zeros(np.size(lat_deg))) / GROUP_CELL_M).astype(np.int64)
    uniq, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    index = {c: k for k, c in enumerate(map(tuple, uniq.tolist()))}
    parent = list(range(len(uniq)))

    def root(k: int) -> int:
        while parent[k] != k:
            parent[k] = parent[parent[k]]
            k = parent[k]
        return k

    steps = [(a, b, c) for a in (-1, 0, 1) for b in (-1, 0, 1) for c in (-1, 0, 1) if (a, b, c) > (0, 0, 0)]
    for k, (x, y, z) in enumerate(uniq.tolist()):
        for a, b, c in steps:
            j = index.get((x + a, y + b, z + c))
            if j is not None:
                parent[root(j)] = root(k)
    roots = np.array([root(k) for k in range(len(uniq))])
    sizes = np.bincount(roots, weights=counts, minlength=len(uniq))
    first = np.full(len(uniq), len(uniq))  # each group's least cube (uniq is sorted)
    np.minimum.at(first, roots, np.arange(len(uniq)))
    best = min(np.flatnonzero(sizes == sizes.max()).tolist(), key=lambda r: first[r])
    return (roots == best)[np.asarray(inverse).ravel()]


def entities_centre(lat_deg, lon_deg) -> tuple[int, float, float]:
    """(count, median latitude, median longitude) of the entities with a position (degrees),
    the medians those of the largest group of them (:func:`largest_group`); (0, 0, 0) for
    none. The longitudes are a circle, cut at the widest gap between neighbours (the arc no
    entity is on) and read as one run from there, so a group across the antimeridian has its
    median among them, whatever order the entities come in (where gaps tie, the cut is the one
    east of the westernmost entity of them, counting from -180)."""
    lat, lon = np.asarray(lat_deg, np.float64), np.asarray(lon_deg, np.float64)
    ok = np.isfinite(lat) & np.isfinite(lon)
    if not ok.any():
        return 0, 0.0, 0.0
    count = int(ok.sum())
    lat, lon = lat[ok], lon[ok]
    group = largest_group(lat, lon)
    lat, lon = lat[group], lon[group]
    outside = (lon < -180.0) | (lon >= 180.0)
    east = np.sort(np.where(outside, (lon + 180.0) % 360.0 - 180.0, lon))  # [-180, 180), in range kept exact
    gaps = np.append(np.diff(east), east[0] + 360.0 - east[-1])  # gaps[i]: from east[i] east to the next
    n = east.size
    first = int(np.argmax(gaps)) + 1  # the run starts east of the widest gap
    # The median of the run east[first], ..., east[first - 1] (indices mod n): its middle
    # entity's longitude itself, or halfway east from one middle entity to the other.
    a, b = float(east[(first + (n - 1) // 2) % n]), float(east[(first + n // 2) % n])
    centre_lon = a + 0.5 * ((b - a) % 360.0)
    if centre_lon >= 180.0:
        centre_lon -= 360.0
    return count, float(np.median(lat)), centre_lon


def world_info(config, time_s: float, clock: str, time_scale: float, world_rate_hz: float,
               geoid_undulation_m: float = 0.0, snapshot=None, terrain_centre=None) -> pb.WorldInfo:
    """GetWorld's answer: the exercise of ``config`` (a ServerConfig) at world time ``time_s``
    (live server and replay alike); ``snapshot`` (the world's last, or None) says where its
    entities are (:func:`entities_centre`); with none, ``terrain_centre`` ((lat, lon) degrees
    of the terrain's first bounded source, :func:`terrain_centre`, or None) is the centre."""
    areas = [pb.TargetArea(name=name, lat_deg=[p[0] for p in poly], lon_deg=[p[1] for p in poly], detail_m=d)
             for name, poly, d in config.target_areas]
    return pb.WorldInfo(exercise_name=config.exercise_name, start_time=config.start_time, time_s=time_s,
                        server_unix_time_s=time.time(), clock=clock, time_scale=time_scale,
                        world_rate_hz=world_rate_hz, network_rate_hz=config.network_rate_hz, target_areas=areas,
                        terrain=config.terrain, geoid_undulation_m=geoid_undulation_m,
                        terrain_insets=config.insets,
                        observer_radius_max_m=type_params(config.params, {}, None, "observer").aoi_radius_m,
                        **_centre_fields(snapshot, terrain_centre))


def _centre_fields(snapshot, terrain_centre=None) -> dict:
    count = 0
    if snapshot is not None and snapshot.ids.size:
        count, lat, lon = entities_centre(snapshot.lat_deg, snapshot.lon_deg)
    if count:
        return {"entity_count": count, "centre_lat_deg": lat, "centre_lon_deg": lon}
    if terrain_centre is None:
        return {}
    return {"entity_count": 0, "centre_lat_deg": terrain_centre[0], "centre_lon_deg": terrain_centre[1]}


def terrain_centre(terrain) -> tuple[float, float] | None:
    """(lat, lon) degrees of the middle of the first of ``terrain``'s sources with a finite box
    (its describe()), where a client with nothing else to look at watches; None without one.
    A box across the antimeridian (lon_max past 180) has its middle wrapped into [-180, 180)."""
    from terrain.terrain import source_boxes

    for lat0, lon0, lat1, lon1 in source_boxes(getattr(terrain, "describe", lambda: [])())[:1]:
        return 0.5 * (lat0 + lat1), (0.5 * (lon0 + lon1) + 180.0) % 360.0 - 180.0
    return None


@dataclass
class ServerConfig:
    exercise_name: str = "sortie"
    start_time: str = "2026-01-01T00:00:00Z"
    network_rate_hz: float = 20.0
    clock: str = "realtime"
    time_scale: float = 1.0
    duration_s: float | None = None
    vanished_timeout_s: float = 10.0
    target_areas: list = field(default_factory=list)  # (name, [(lat, lon)], detail_m)
    insets: bool = False  # the terrain answers inside the target areas from their insets
    terrain: str = ""
    # kind name -> TypeParams, and (kind name, type name) -> TypeParams of [agent_types.<type>] over that kind
    params: dict = field(default_factory=lambda: dict(DEFAULT_PARAMS))


class SimulationServer:
    """World + clock thread + gRPC service. ``start()``, then ``stop()``."""

    def __init__(self, world: World, config: ServerConfig, address: str = "127.0.0.1:0",
                 max_workers: int = DEFAULT_MAX_WORKERS, recorder=None, before_tick=None):
        if config.clock not in CLOCKS:
            raise InvalidArgument("clock", f"must be one of {', '.join(CLOCKS)}", value=config.clock)
        if not (config.time_scale > 0):
            raise InvalidArgument("time_scale", "must be > 0", value=config.time_scale)
        if not (0 < config.network_rate_hz <= 1.0 / world.dt + 1e-9):
            raise InvalidArgument("network_rate_hz", f"must be in (0, {1.0 / world.dt:g}] (the world rate)",
                                  value=config.network_rate_hz)
        self.world = world
        self.config = config
        # server.recorder.Recorder (attached to the world now, closed by stop()); before_tick(world)
        # runs on the clock thread before each tick (re-simulated inputs of a take-over).
        self.recorder = recorder
        if recorder is not None:
            world.attach_recorder(recorder)
        self.before_tick = before_tick
        self.sessions = Sessions(world, self.params_of, config.vanished_timeout_s)
        self.publisher = Publisher(DeadReckoner(), lambda i: self.params_of(i).thresholds)
        self.tick_ms: list[float] = []  # wall time of each tick (the clock thread's), for benchmarks
        self.publish_ms: list[float] = []  # wall time of each publish (the publisher thread's)
        self.publish_totals: tuple[int, float] = (0, 0.0)  # (publishes, their milliseconds) since start
        # (ticks, their milliseconds) since start: the metrics summary's _count and _sum, which
        # Prometheus reads as counters; one tuple, so a scrape never sees one without the other
        self.tick_totals: tuple[int, float] = (0, 0.0)
        self.overruns = 0
        self._clock = config.clock
        self._rate_marks: collections.deque = collections.deque()  # (wall monotonic, world time) samples
        self._achieved: float | None = None  # the advertised rate when short of the set one (None: the set one)
        self._rate_reset = False  # set_clock asks the clock thread to measure anew
        # What the last publish covered (written by the publisher thread, read by the clock's
        # _publish_due; a publish behind makes a publish due at most once more): the queues it
        # served, the world's entity layout and the rate it sent, and when a heartbeat falls due.
        self._served: set = set()
        self._published_layout = -1
        self._published_rate: float | None = None
        self._tick_layout = -1  # the world's layout version just before its last tick
        self._track_heartbeats = 1.0 / config.network_rate_hz > HEARTBEAT_LATE_FRACTION * _shortest_heartbeat_s(
            config.params)
        self._next_heartbeat_s = math.inf
        self._terrain_centre = False  # terrain_centre(world.terrain), found at the first GetWorld
        self._heartbeat_ids = np.zeros(0, np.int64)  # the ids _heartbeats_s holds the heartbeats of
        self._heartbeats_s = np.zeros(0)
        self._stop = threading.Event()
        self._resume = threading.Event()
        self._thread = threading.Thread(target=self._run, name="world-clock", daemon=True)
        # The publish handed over by the clock and not yet taken by the publisher thread:
        # (rate, snapshot, infos, wrecks, layout version) or None; closed when the clock ends.
        self._handover = threading.Condition()
        self._pending: tuple | None = None
        self._publisher_closed = False
        self._publisher_thread = threading.Thread(target=self._publish_loop, name="world-publisher", daemon=True)
        self.stream_stats = StreamStats()
        self.started_monotonic = time.monotonic()
        servicer = functools.partial(SimulationServicer, self.sessions, self.world_info,
                                     stream_stats=self.stream_stats)
        self.servicer = None  # made by the gRPC server's start, with its thread pool

        def handlers(pool):
            self.servicer = servicer(pool)
            return method_handlers(self.servicer)

        # SortieError when it cannot listen
        self.grpc = AioManagedServer(SERVICE_NAME, handlers, address, max_rpcs=max_workers)
        self.port = self.grpc.port
        self.address = f"{address.rsplit(':', 1)[0]}:{self.port}"
        self.finished = threading.Event()  # set when the clock thread ends (duration reached, or an error)
        self.error: Exception | None = None  # what stopped the clock thread, if an error did

    # -- parameters -----------------------------------------------------------------------------

    def params_of(self, entity_id, kind: str | None = None) -> TypeParams:
        """An entity's parameters: by its type name, else its kind (or ``kind`` directly)."""
        return type_params(self.config.params, self.world.entities, entity_id, kind)

    # -- lifecycle ------------------------------------------------------------------------------

    def start(self) -> None:
        self._warm_up()
        # Everything built so far (terrain, world, thousands of entities, what the warm-up
        # cached) lives as long as the server: out of the cyclic collector's way, so that its
        # full collections scan only what the running server allocates (they took 70-120 ms
        # with 2000 ground vehicles; 40 ms after this), a pause of the clock thread and every
        # stream.
        gc.collect()
        gc.freeze()
        self.grpc.start()
        self._publisher_thread.start()
        self._thread.start()
        logger.info("simulation server on %s, clock %s x%g", self.address, self._clock, self.config.time_scale)

    def _warm_up(self) -> None:
        """Compile the kernels the world's ticks call before the clock starts: the terrain's
        queries (Terrain.warm_up: in a fresh install the world's first segment across a target
        area's edge compiled for 10-25 s inside a tick, stalling the clock and every stream),
        near the first target area, else the origin (where a global source such as the
        procedural world is warmed); then the ground vehicles', convoys' and obstacle search's
        (server.warm_up: 4-7 s in the first tick, 2 s in the second), on a scratch world at
        the first place that takes ground vehicles: one of this world's, the target areas,
        the terrain's sources. A remote terrain (the terrain service) warms its own at start."""
        areas = self.config.target_areas
        centres = [(float(np.mean([p[0] for p in a[1]])), float(np.mean([p[1] for p in a[1]]))) for a in areas if a[1]]
        warm = getattr(self.world.terrain, "warm_up", None)
        if warm is not None:
            logger.info("terrain kernels ready in %.2f s", warm(near=centres[0] if centres else (0.0, 0.0)))
        places = []
        g = self.world.ground
        if g is not None and g.n:
            places += list(zip(g.lat[:3].tolist(), g.lon[:3].tolist()))
        places += centres
        from terrain.terrain import source_boxes

        places += [(0.5 * (la0 + la1), 0.5 * (lo0 + lo1))
                   for la0, lo0, la1, lo1 in source_boxes(getattr(self.world.terrain, "describe", lambda: [])())]
        seconds, place = warm_up_world(self.world, places)
        if place is None:
            logger.info("world kernels not warmed: no place of %d tried takes ground vehicles (%.2f s)",
                        len(places), seconds)
        else:
            logger.info("world kernels ready in %.2f s (scratch world at %.4f, %.4f)", seconds, *place)

    def stop(self, grace_s: float = 2.0) -> None:
        self._stop.set()
        self._resume.set()
        self._thread.join(timeout=10.0)
        self._close_publisher()  # (the clock's own end closed it, if the clock ran)
        for s in self.sessions.watching():
            s.queue.close()
        if self.servicer is not None:  # events and client streams end OK too, now
            self.servicer.close()
        self.grpc.stop(grace_s).wait()
        if self.recorder is not None:
            self.recorder.close()

    def set_clock(self, clock: str, time_scale: float | None = None) -> None:
        if clock not in CLOCKS:
            raise InvalidArgument("clock", f"must be one of {', '.join(CLOCKS)}", value=clock)
        if time_scale is not None:
            self.config.time_scale = float(time_scale)
            self._achieved = None
            self._rate_reset = True  # measured anew at the new rate (by the clock thread, which owns the marks)
        self._clock = clock
        if clock != "paused":
            self._resume.set()

    @property
    def time_scale(self) -> float:
        """World seconds per wall second that the clock achieves (see the module docstring):
        the set rate, or the measured one while it cannot keep up."""
        return self.config.time_scale if self._achieved is None else self._achieved

    def world_info(self) -> pb.WorldInfo:
        rate = 0.0 if self._clock == "paused" else self.time_scale  # world s per wall s (as Watch says)
        snapshot = self.world.snapshot  # (without the entities gone since, as a paused clock publishes it)
        if self._terrain_centre is False:  # (asked once: a terrain service's describe() is a call)
            self._terrain_centre = terrain_centre(self.world.terrain)
        return world_info(self.config, self.world.time_s, self._clock, rate, 1.0 / self.world.dt,
                          self.world.geoid_undulation_m,
                          None if snapshot is None else live_rows(snapshot, self.world.infos), self._terrain_centre)

    def _measure_rate(self, wall: float) -> None:
        """Sample (wall, world time) and update the advertised rate (clock thread, running clock)."""
        marks = self._rate_marks
        if self._rate_reset:
            self._rate_reset = False
            marks.clear()
        if marks and wall - marks[-1][0] < RATE_SAMPLE_S:
            return
        marks.append((wall, self.world.time_s))
        while wall - marks[0][0] > RATE_WINDOW_S:
            marks.popleft()
        span = wall - marks[0][0]
        if span < RATE_WINDOW_S / 2:
            return
        rate = (self.world.time_s - marks[0][1]) / span
        target = self.config.time_scale
        if rate >= target * (1.0 - RATE_TOLERANCE):
            self._achieved = None
        elif self._achieved is None or abs(rate - self._achieved) > RATE_TOLERANCE * self._achieved:
            self._achieved = float(f"{rate:.3g}")

    # -- the clock thread -----------------------------------------------------------------------

    def _hand_over(self, rate: float, paused: bool = False) -> None:
        """Hand the world's snapshot to the publisher thread (clock thread), advertising
        ``rate`` (0: paused), with the world's entity infos and wrecks as they are now; waits
        while the one handed over before is still waiting to be taken. ``paused``: the
        snapshot is the last tick's, and the entities removed since are left out of it
        (:func:`live_rows`)."""
        world = self.world
        infos = world.infos  # (read before the snapshot: an entity removed in between goes at the next)
        snapshot = live_rows(world.snapshot, infos) if paused else world.snapshot
        request = (rate, snapshot, infos, world.wrecks, self._tick_layout)
        with self._handover:
            while self._pending is not None and not self._publisher_closed:
                self._handover.wait(0.1)
            self._pending = request
            self._handover.notify_all()

    def _publish_loop(self) -> None:
        """The publisher thread: publish each snapshot handed over, in order, until the clock
        closes it (what is still pending then is published first). An error stops the clock as
        one of its own would."""
        try:
            while True:
                with self._handover:
                    while self._pending is None and not self._publisher_closed:
                        self._handover.wait()
                    request, self._pending = self._pending, None
                    self._handover.notify_all()
                if request is None:
                    return
                t0 = time.perf_counter()
                self._publish(*request)
                self.publish_totals = _noted(self.publish_ms, self.publish_totals, (time.perf_counter() - t0) * 1e3)
        except Exception as exc:  # noqa: BLE001 - the clock must stop, and say why
            logger.exception("publisher stopped by an error; stopping the world clock")
            self.error = exc
            self._close_publisher(join=False)
            self._stop.set()
            self._resume.set()

    def _close_publisher(self, join: bool = True) -> None:
        """No more hand-overs; the publisher thread publishes what is pending and ends."""
        with self._handover:
            self._publisher_closed = True
            self._handover.notify_all()
        if join and self._publisher_thread.is_alive():
            self._publisher_thread.join(timeout=10.0)

    def _publish(self, rate: float, snapshot, infos: dict, wrecks: frozenset, layout: int) -> None:
        """Publish one snapshot (publisher thread), advertising ``rate``, and note what it
        covered for :meth:`_publish_due`."""
        sessions = self.sessions.watching()
        # The queues as the publisher will find them: one a new Watch puts in place meanwhile
        # is skipped by the publisher and is not among these, so it is served at the next tick.
        served = {s.queue for s in sessions}
        self.publisher.publish(snapshot, infos, sessions, rate, wrecks)
        self._served = served
        self._published_layout = layout
        self._published_rate = rate
        if self._track_heartbeats:
            self._next_heartbeat_s = self._next_heartbeat()

    def _publish_due(self, rate: float) -> bool:
        """Whether something cannot wait for the next network tick (see the module docstring):
        a heartbeat due, an entity come or gone since the last publish, the advertised rate
        changed, or a watching session's queue still waiting for its snapshot. O(sessions)."""
        return (self.world.time_s - self._next_heartbeat_s >= -TIME_SLACK_S
                or self.world.layout_version != self._published_layout
                or rate != self._published_rate
                or any(s.queue.needs_snapshot and s.queue not in self._served for s in self.sessions.watching()))

    def _next_heartbeat(self) -> float:
        """World time at which the first entity's heartbeat falls due (the dead reckoner's last
        sent time plus the entity's heartbeat), inf with no entity; O(entities)."""
        reckoner = self.publisher.reckoner
        ids = reckoner.ids
        if ids.size == 0:
            return math.inf
        if not np.array_equal(ids, self._heartbeat_ids):  # as the publisher gave them to the reckoner
            self._heartbeats_s = np.array([self.params_of(i).thresholds.heartbeat_s for i in ids.tolist()])
            self._heartbeat_ids = ids
        return float(np.min(reckoner.last_sent(ids)["t0"] + self._heartbeats_s))

    def _expire_due(self, next_expire: float) -> float:
        """Expire the vanished sessions if ``next_expire`` (monotonic s) has come (clock
        thread); when to next."""
        now = time.monotonic()
        if now < next_expire:
            return next_expire
        self.sessions.expire()
        return now + EXPIRE_EVERY_S

    def _run(self) -> None:
        world, cfg = self.world, self.config
        net_dt = 1.0 / cfg.network_rate_hz
        next_net = 0.0
        next_expire = time.monotonic() + EXPIRE_EVERY_S
        wall_next = time.monotonic()
        try:
            while not self._stop.is_set():
                # Paused: watchers learn the clock stopped; newcomers get their snapshot. A world
                # that never ticked has none: its first tick runs first (see the module docstring).
                if self._clock == "paused" and world.tick_count > 0:
                    self._hand_over(0.0, paused=True)
                    self._rate_marks.clear()  # the rate is measured anew when the clock runs again
                    self._resume.clear()
                    self._resume.wait(0.1)
                    wall_next = time.monotonic()
                    # Vanished sessions time out in a pause too: their agents were held (no other
                    # client could take them) until the clock ran again.
                    next_expire = self._expire_due(next_expire)
                    continue
                t0 = time.perf_counter()
                if self.before_tick is not None:
                    self.before_tick(world)
                self._tick_layout = world.layout_version  # an entity come after this waits for no tick
                world.tick()
                running = self._clock != "paused"
                if running:
                    self._measure_rate(time.monotonic())
                rate = self.time_scale if running else 0.0
                network_tick = world.time_s + 1e-9 >= next_net
                if network_tick or self._publish_due(rate):
                    self._hand_over(rate)
                    if network_tick:
                        next_net += net_dt
                self.tick_totals = _noted(self.tick_ms, self.tick_totals, (time.perf_counter() - t0) * 1e3)
                next_expire = self._expire_due(next_expire)
                if cfg.duration_s is not None and world.time_s >= cfg.duration_s - 1e-9:
                    break
                if self._clock in ("realtime", "fast"):  # fast: time_scale x real time, or as fast as it goes
                    wall_next += world.dt / cfg.time_scale
                    lag = time.monotonic() - wall_next
                    if lag > MAX_LAG_S:
                        self.overruns += 1
                        wall_next = time.monotonic()
                    elif lag < 0:
                        self._stop.wait(-lag)
            if world.tick_count > 0 and self.error is None:
                # The exercise's end (duration_s) or the server's stop: every watcher gets the last
                # tick's state and the stopped clock (rate 0), though no network tick may fall on it.
                self._hand_over(0.0, paused=True)
        except Exception as exc:  # noqa: BLE001 - the clock thread must say why it died
            logger.exception("world clock stopped by an error")
            self.error = exc
        finally:
            self._close_publisher()
            self.finished.set()

    def tick_stats(self) -> dict:
        a = np.array(self.tick_ms) if self.tick_ms else np.zeros(1)
        return {"ticks": len(self.tick_ms), "tick_p50_ms": float(np.percentile(a, 50)),
                "tick_p99_ms": float(np.percentile(a, 99)), "overruns": self.overruns}


def _shortest_heartbeat_s(params: dict) -> float:
    """The shortest heartbeat an entity may have under ``params`` (ServerConfig.params: its
    kinds' and types' entries, the built-in kind defaults where a kind has none)."""
    kinds = KIND_NAMES.values()
    used = [p for k, p in params.items() if k in kinds or isinstance(k, tuple)]
    used += [DEFAULT_PARAMS[k] for k in kinds if k not in params]
    return min(p.thresholds.heartbeat_s for p in used)


def algorithm_name(code: int) -> str:
    return ALGORITHM_NAMES.get(int(code), str(code))


# -- from a scenario ------------------------------------------------------------------------------

def _dr_thresholds(p) -> Thresholds:
    """scenario.AgentTypeParams -> dead_reckoning.Thresholds."""
    code = {v: k for k, v in ALGORITHM_NAMES.items()}[p.dr_algorithm]
    return Thresholds(p.dr_position_m, math.radians(p.dr_orientation_deg), p.heartbeat_s, code)


def open_terrain_source(dem=None, service: str | None = None, target_areas=(), store=(),
                        procedural: int | None = None, procedural_params: dict | None = None):
    """The terrain of DEM files (in process) or a client of a terrain service; with
    ``target_areas`` ((name, polygon, detail_m) tuples) the DEM terrain answers inside them
    from their insets (terrain/inset.py; a service serves its own). ``store`` paths and a
    ``procedural`` seed add sources under the DEMs, in the order `sortie terrain serve`
    stacks them (what re-simulating a sortie recorded over such a service rebuilds), the
    procedural world with ``procedural_params`` (max_height_m, level_exponent, water) if given.

    Module-level and picklable as ``functools.partial``, so an aircraft worker
    process opens the same terrain (server.aircraft_host)."""
    if service:
        from client.terrain_client import TerrainClient

        client = TerrainClient(service)
        client.wait_ready(10.0)
        return client
    from server.terrain_cli import build_terrain

    terrain = build_terrain([str(p) for p in dem or ()], procedural, [str(p) for p in store], procedural_params)
    if target_areas:
        _check_areas_covered(terrain, target_areas)
        terrain = _with_insets(terrain, target_areas)
    return terrain


def _with_insets(terrain, target_areas):
    """terrain.inset.with_insets(terrain, target_areas, INSET_SEED), built an area at a time, so
    that an inset beyond its post limit (INSET_MAX_POSTS: its count is known only with the
    DEM's lattice, which the scenario's validator does not read) is a ScenarioError naming
    ``target_areas[i].detail_m`` (InsetSource refuses it before it reads any height)."""
    from terrain.inset import INSET_MAX_POSTS, INSET_SEED, InsetSource
    from terrain.terrain import Terrain

    insets = []
    for i, (name, polygon, detail_m) in enumerate(target_areas):
        try:
            insets.append(InsetSource(terrain, polygon, detail_m, INSET_SEED, name=name))
        except LimitExceeded as exc:
            if exc.limit != INSET_MAX_POSTS:
                raise
            side = math.isqrt(INSET_MAX_POSTS)
            raise ScenarioError(f"target_areas[{i}].detail_m", f"{exc} ({side} x {side}, terrain/inset.py): its "
                                "posts are the DEM's beneath, refined by the least power of two that brings them "
                                "within detail_m of each other; coarsen it, shrink the area or set [terrain] "
                                "insets = false", value=detail_m) from None
    return Terrain(insets + list(terrain.sources))  # as with_insets: each over the terrain itself


def _check_areas_covered(terrain, target_areas) -> None:
    """Every target area's inset has terrain under it to refine, checked before any inset is
    built (seconds each): else a ScenarioError naming ``target_areas[i].polygon`` and the area."""
    from terrain.inset import check_covered

    sources = terrain.describe()
    for i, (name, polygon, _) in enumerate(target_areas):
        try:
            check_covered(sources, (name, polygon, 0.0))
        except InvalidArgument as exc:
            raise ScenarioError(f"target_areas[{i}].polygon", f"target area {name!r} is off the terrain, so "
                                f"its inset has nothing to refine: {exc.message} (the centre of its box); "
                                "move it onto the terrain or set [terrain] insets = false",
                                value=[list(p) for p in polygon]) from None


def terrain_spec(scenario, dem=None, service: str | None = None) -> dict:
    """The arguments of :func:`open_terrain_source` for a scenario: ``dem`` files or a
    ``service`` address override the scenario's terrain."""
    if service or (not dem and scenario.terrain.service):
        return {"service": service or scenario.terrain.service}
    spec = {"dem": [str(p) for p in (dem or scenario.terrain.dem)]}
    if scenario.terrain.insets and scenario.target_areas:
        spec["target_areas"] = inset_areas(scenario)
    return spec


def inset_areas(scenario) -> tuple:
    """The scenario's target areas as (name, polygon, detail_m) tuples (picklable: worker processes
    build the same insets)."""
    return tuple((a.name, tuple(map(tuple, a.polygon)), a.detail_m) for a in scenario.target_areas)


def open_terrain(scenario, dem=None, service: str | None = None):
    """(terrain source, description, picklable factory opening the same terrain). With
    ``[terrain] insets`` and target areas, a terrain service must serve their insets
    (:func:`check_service_insets`)."""
    spec = terrain_spec(scenario, dem, service)
    desc = f"service:{spec['service']}" if "service" in spec else "dem:" + ",".join(spec["dem"])
    try:
        terrain = open_terrain_source(**spec)
        if "service" in spec and scenario.terrain.insets and scenario.target_areas:
            try:
                check_service_insets(terrain.describe(), inset_areas(scenario), spec["service"])
            except BaseException:
                terrain.close()
                raise
    except ScenarioError as exc:
        raise scenario.in_file(exc) from None
    return terrain, desc, functools.partial(open_terrain_source, **spec)


def check_service_insets(sources, target_areas, address: str) -> None:
    """A terrain service's sources (``sources``: its describe(), details as text) hold the inset
    of each of ``target_areas`` ((name, polygon, detail_m) tuples) as the server would build it
    (terrain/inset.py: the same area name, polygon and detail_m, seed INSET_SEED), since clients
    draw the insets from WorldInfo's target areas and the world meets the service's heights;
    else a ScenarioError naming ``terrain.insets``. Insets of other areas may be served too."""
    from terrain.inset import INSET_SEED

    served = {}
    for s in sources:
        if s.get("kind") == "inset":
            served.setdefault(str(s.get("area")), s)
    for i, (name, polygon, detail_m) in enumerate(target_areas):
        s = served.get(name)
        if s is None:
            why = f"serves no inset of target_areas[{i}] {name!r}"
        elif not _same_inset(s, polygon, detail_m, INSET_SEED):
            why = (f"serves an inset named {name!r} that is not target_areas[{i}]'s (its polygon "
                   f"{s.get('polygon')}, detail_m {s.get('detail_m')}, seed {s.get('detail_seed')})")
        else:
            continue
        raise ScenarioError("terrain.insets", f"the terrain service at {address} {why}; start it with `sortie "
                            "terrain serve --insets SCENARIO` on this scenario, or set insets = false", value=True)


def _same_inset(source: dict, polygon, detail_m: float, seed: int) -> bool:
    """Whether a served inset's description (its values possibly text: a service's details)
    is of ``polygon`` (closing vertex optional) at ``detail_m`` with ``seed``."""
    import json

    try:
        served = source.get("polygon")
        served = json.loads(served) if isinstance(served, str) else served
        served = [(float(a), float(b)) for a, b in served]
        same = (float(source.get("detail_m")) == float(detail_m)
                and int(source.get("detail_seed", seed)) == seed)
    except (TypeError, ValueError):
        return False
    ours = [(float(a), float(b)) for a, b in polygon]
    if len(ours) > 1 and ours[-1] == ours[0]:
        ours = ours[:-1]
    return same and served == ours


def aircraft_host(scenario, terrain, terrain_factory, workers: int, nice: int | None = None):
    """Where a scenario's aircraft fly: this process (workers=0) or ``workers``
    processes (server.aircraft_host) at CPU priority ``nice`` below this one
    (None: server.aircraft_host.WORKER_NICE)."""
    from server.aircraft_host import WORKER_NICE, LocalAircraftHost, ProcessAircraftHost

    ex = scenario.exercise
    if workers == 0:
        return LocalAircraftHost(terrain, 1.0 / ex.fdm_rate_hz, scenario.terrain.geoid_undulation_m)
    return ProcessAircraftHost(terrain_factory, 1.0 / ex.fdm_rate_hz, scenario.terrain.geoid_undulation_m, workers,
                               nice=WORKER_NICE if nice is None else nice)


def build_world(scenario, terrain, host=None) -> World:
    """A world holding every agent of a validated scenario (server.scenario.Scenario);
    its aircraft on ``host`` (see :func:`aircraft_host`; in process by default). An agent
    that cannot start is a ScenarioError naming it (and the scenario's file)."""
    try:
        return _build_world(scenario, terrain, host)
    except ScenarioError as exc:
        raise scenario.in_file(exc) from exc.__cause__


def _build_world(scenario, terrain, host) -> World:
    ex = scenario.exercise
    _check_ground_references(scenario, terrain)
    surface = _surfaces_msl_m(scenario, terrain)
    _check_spawn_overlaps(scenario, surface)
    world = World(terrain, ex.fdm_rate_hz, ex.world_rate_hz, scenario.terrain.geoid_undulation_m, host)
    convoy_of = {m: c for c in scenario.convoys for m in c.members}
    done = set()
    agents = list(scenario.agents)
    for i, a in enumerate(agents):
        if a.name in done:
            continue
        if a.kind == "aircraft":
            # This agent and the aircraft right after it, spawned at once (every aircraft
            # worker loads and trims its share); entity ids stay in the file's order.
            run = [i]
            while run[-1] + 1 < len(agents) and agents[run[-1] + 1].kind == "aircraft":
                run.append(run[-1] + 1)
            results = world.spawn_aircraft_many([_aircraft_spec(agents[k], ex.on_vanish, float(surface[k]))
                                                 for k in run])
            for k, r in zip(run, results):
                if isinstance(r, SortieError):  # valid values the model cannot start at (its trim, the ground)
                    why = str(r)
                    for api, key in SCENARIO_HINTS.items():
                        why = why.replace(api, key)
                    raise ScenarioError(f"agents[{k}]", f"{agents[k].name!r} ({agents[k].type}) cannot start: "
                                                        f"{why}") from r
                if isinstance(r, BaseException):
                    raise r
                done.add(agents[k].name)
            continue
        try:
            _spawn(world, scenario, a, convoy_of, done)
        except ScenarioError:
            raise
        except SortieError as exc:
            raise ScenarioError(f"agents[{i}]", f"{a.name!r} ({a.type}) cannot start: {exc}") from exc
        done.add(a.name)
    return world


# The advice of an aircraft's start errors (fdm.aircraft) in the Python API's words, and what a
# scenario says instead: trim=False and on_ground=True are keywords of InitialConditions and
# Aircraft, not scenario keys. (The second is fdm.aircraft's literal text of an airborne start
# below the surface, "use on_ground=True to start on the ground".)
SCENARIO_HINTS = {
    TRIM_OFF_HINT: "; in the scenario, give it a speed_mps or alt_m it trims at, or start it on the ground "
                   "(on_ground = true)",
    "use on_ground=True to start on the ground": "in the scenario, give it an alt_m above that, or start it on "
                                                 "the ground (on_ground = true)",
}


def _surfaces_msl_m(scenario, terrain) -> np.ndarray:
    """(n agents,) float64 metres MSL: the surface under each agent that starts on it or
    relative to it (an aircraft on its wheels or at an altitude above ground, a ground
    vehicle, a static), as an aircraft meets it (fdm.aircraft.terrain_msl_m: the sea surface
    over water, no data as sea level, longitude wrapped as the aircraft wraps it); NaN for an
    airborne aircraft at an altitude above mean sea level. One batched terrain query."""
    from fdm.aircraft import terrain_msl_m
    from terrain.geodesy import wrap_lon_deg

    agents = scenario.agents
    out = np.full(len(agents), np.nan)
    need = np.array([not (a.kind == "aircraft" and not a.on_ground and a.alt_ref == "msl") for a in agents], bool)
    if need.any():
        lat = np.array([a.lat_deg for a in agents], np.float64)[need]
        lon = wrap_lon_deg(np.array([a.lon_deg for a in agents], np.float64)[need])
        out[need] = terrain_msl_m(terrain, lat, lon)
    return out


def _check_spawn_overlaps(scenario, surface_msl_m: np.ndarray) -> None:
    """No two agents start inside each other: a ScenarioError naming both (``agents[j]``, the
    later, and ``agents[i]``) and their distance, where their collision shapes overlap at their
    spawn points. The shapes and the test are the world's (World._shapes,
    server.collisions.new_contacts: a ground vehicle its type's box on its heading, an aircraft
    its model's sphere, fdm.catalog.body_radius_m, a static site a sphere of
    server.world.STATIC_RADIUS_M); two statics are never tested, as the world never tests
    them (neither moves). An overlap at the start is no collision to the world (it reports
    contacts as they begin), so such agents would pass through each other unharmed. Aircraft
    at different altitudes do not overlap. An aircraft on its wheels is placed at its
    surface (its CG is its rest height above it, 1-3 m: well inside any sphere's radius).
    One sort-and-sweep pass (compiled): 10,000 agents in well under a second."""
    from fdm.catalog import body_radius_m
    from fdm.vehicle_types import VEHICLE_TYPES
    from server.collisions import new_contacts
    from server.world import STATIC_RADIUS_M
    from terrain.geodesy import geodetic_to_ecef

    agents = scenario.agents
    n = len(agents)
    if n < 2:
        return
    radius, half_l, half_w = np.zeros(n), np.zeros(n), np.zeros(n)
    alt = np.where(np.isnan(surface_msl_m), 0.0, surface_msl_m)
    aircraft_radius: dict[str, float] = {}
    for k, a in enumerate(agents):
        if a.kind == "aircraft":
            if a.type not in aircraft_radius:
                aircraft_radius[a.type] = body_radius_m(a.type)
            radius[k] = aircraft_radius[a.type]
            if not a.on_ground:
                alt[k] = a.alt_m + (alt[k] if a.alt_ref == "agl" else 0.0)
        elif a.kind == "ground":
            t = VEHICLE_TYPES[a.type]
            half_l[k], half_w[k] = 0.5 * t.length_m, 0.5 * t.width_m
            radius[k] = math.hypot(half_l[k], half_w[k])
        else:
            radius[k] = STATIC_RADIUS_M
    lat = np.array([a.lat_deg for a in agents], np.float64)
    lon = np.array([a.lon_deg for a in agents], np.float64)
    heading = np.array([a.heading_deg for a in agents], np.float64)
    p = geodetic_to_ecef(lat, lon, alt + scenario.terrain.geoid_undulation_m)  # (n, 3) ECEF metres
    moves = np.array([a.kind != "static" for a in agents], bool)
    ci, cj, _, dist = new_contacts(p, p, radius, heading_deg=heading, half_length_m=half_l, half_width_m=half_w,
                                   moves=moves, lat_deg=lat, lon_deg=lon, ongoing=True)
    if ci.size == 0:
        return
    first = int(np.lexsort((ci, cj))[0])  # the first agent listed that starts inside an earlier one
    i, j, d = int(ci[first]), int(cj[first]), float(dist[first])

    def shape(k: int) -> str:
        a = agents[k]
        if half_l[k] > 0.0:
            return f"a {2 * half_l[k]:g} x {2 * half_w[k]:g} m footprint on heading {a.heading_deg:g}"
        return f"a sphere of radius {radius[k]:.3g} m"

    a, b = agents[i], agents[j]
    raise ScenarioError(f"agents[{j}]", f"{b.name!r} ({b.type}) starts inside agents[{i}] {a.name!r} ({a.type}): "
                                        f"{d:.2f} m apart, their collision shapes ({shape(j)}; {shape(i)}) "
                                        "overlap, and agents that start overlapping never collide (a collision is "
                                        "two coming into contact); move one of them clear of the other",
                        value=[b.lat_deg, b.lon_deg])


def _check_ground_references(scenario, terrain) -> None:
    """Agents placed by the ground under them need terrain data there: an aircraft on its
    wheels or at an altitude above ground, a static (it has no altitude; ground vehicles
    are checked by the vehicle model). ScenarioError naming the agent where there is none,
    instead of a silent sea level."""
    from terrain.raster import STATUS_OUTSIDE

    needs = [(i, a) for i, a in enumerate(scenario.agents)
             if (a.kind == "aircraft" and (a.on_ground or a.alt_ref == "agl"))
             or a.kind == "static"]
    if not needs:
        return
    status = np.asarray(terrain.heights(np.array([a.lat_deg for _, a in needs], float),
                                        np.array([a.lon_deg for _, a in needs], float)).status)
    for (i, a), st in zip(needs, status):
        if st == STATUS_OUTSIDE:
            if a.kind == "static":
                what, instead = "on the ground", " (a static stands on the ground: it takes no alt_m)"
            elif a.on_ground:
                what, instead = "on the ground", " or start it airborne (alt_m above mean sea level, no on_ground)"
            else:
                what, instead = "at an altitude above ground", ' or give alt_m above mean sea level (alt_ref = "msl")'
            raise ScenarioError(f"agents[{i}]", f"{a.name!r} is placed {what} outside the terrain: no terrain data "
                                                f"at ({a.lat_deg}, {a.lon_deg}); move it onto the terrain{instead}")


def _aircraft_spec(a, on_vanish: str, surface_msl_m: float | None = None) -> dict:
    """World.spawn_aircraft's keywords for scenario aircraft agent ``a``. Without an
    autopilot table an airborne aircraft holds its spawn heading, speed and altitude: for
    alt_ref = "agl" the height it starts at, ``surface_msl_m`` (m MSL, the surface under it
    as the aircraft meets it: :func:`_surfaces_msl_m`) plus alt_m, which it then holds
    above mean sea level (a hold is of the altitude, not of the height over the terrain
    passing below)."""
    ap = a.autopilot
    route = list(ap.waypoints) if ap is not None and hasattr(ap, "waypoints") else None
    hold = None
    if ap is not None and not hasattr(ap, "waypoints"):
        hold = {k: v for k, v in (("heading_deg", ap.heading_deg), ("alt_msl_m", ap.alt_msl_m),
                                  ("speed_mps", ap.speed_mps)) if v is not None}
    ic = a.initial_conditions()
    if route is None and hold is None and not a.on_ground:
        if not a.engines_running:  # gliding: no thrust to hold a speed or height with
            hold = {"heading_deg": a.heading_deg}
        elif ic.alt_ref == "msl":
            hold = {"heading_deg": a.heading_deg, "speed_mps": max(a.speed_mps, 1.0), "alt_msl_m": ic.alt_m}
        elif surface_msl_m is not None and math.isfinite(surface_msl_m):
            hold = {"heading_deg": a.heading_deg, "speed_mps": max(a.speed_mps, 1.0),
                    "alt_msl_m": surface_msl_m + ic.alt_m}
        else:
            raise InvalidArgument("surface_msl_m", f"the surface under {a.name!r} is needed to hold the altitude it "
                                                   "starts at above ground", value=surface_msl_m)
    return dict(name=a.name, type_=a.type, ic=ic, coalition=a.coalition, controllable=a.controllable,
                route=route, hold=hold or None, speed_mps=getattr(ap, "speed_mps", None) if route else None,
                on_vanish=on_vanish)


def _spawn(world: World, scenario, a, convoy_of: dict, done: set) -> None:
    """Spawn scenario ground or static agent ``a`` (a whole convoy for its first member;
    ``done`` gains the other members)."""
    ex = scenario.exercise
    if a.kind == "ground":
        c = convoy_of.get(a.name)
        members = [scenario.agent(m) for m in c.members] if c else [a]
        ap = a.autopilot
        # Each member its own side, controllability and start speed: a convoy shares only its
        # route, cruise speed and spacing (server.scenario._same_as_leader).
        try:
            world.spawn_ground([m.name for m in members], [m.type for m in members],
                               [m.lat_deg for m in members], [m.lon_deg for m in members],
                               [m.heading_deg for m in members], coalition=[m.coalition for m in members],
                               controllable=[m.controllable for m in members],
                               speed_mps=[m.speed_mps for m in members],
                               route=(c.points if c else (ap.points if ap is not None else None)),
                               cruise_mps=(c.cruise_mps if c else (ap.cruise_mps if ap is not None else None)),
                               spacing_m=c.spacing_m if c else None, on_vanish=ex.on_vanish)
        except InvalidArgument as exc:
            # fdm.ground's placement (a vehicle in the water or off the terrain) names the member
            # by its index in the batch: here, by its place in the scenario, as statics are.
            if exc.field != "lat" or exc.index is None or not 0 <= exc.index < len(members):
                raise
            m = members[exc.index]
            raise ScenarioError(f"agents[{scenario.agents.index(m)}]",
                                f"{m.name!r} ({m.type}) is {exc.message.removeprefix('vehicle ')}; move it onto "
                                "land within the terrain") from exc
        done.update(m.name for m in members)
    else:
        world.spawn_static(a.name, a.type, a.lat_deg, a.lon_deg, a.alt_m, a.heading_deg, coalition=a.coalition)


def server_config(scenario, terrain_desc: str = "") -> ServerConfig:
    """The server's configuration of a validated scenario. Each [agent_types.<type>] table is
    resolved over every entity kind (scenario.Scenario.type_params: kind default < kind table
    < type table), keyed (kind, type): a type name may be an aircraft's and a static agent's
    at once, and each takes its own kind's parameters under the type's table."""
    ex = scenario.exercise
    params: dict = {k: TypeParams(p.aoi_radius_m, _dr_thresholds(p)) for k, p in scenario.kind_params.items()}
    for type_name in scenario.type_overrides:
        for kind in KIND_NAMES.values():
            p = scenario.type_params(kind, type_name)
            params[(kind, type_name)] = TypeParams(p.aoi_radius_m, _dr_thresholds(p))
    return ServerConfig(exercise_name=ex.name, start_time=ex.start_time.isoformat().replace("+00:00", "Z"),
                        network_rate_hz=ex.network_rate_hz, clock=ex.clock, time_scale=ex.time_scale,
                        duration_s=ex.duration_s, vanished_timeout_s=ex.vanished_client_timeout_s,
                        target_areas=[(t.name, list(t.polygon), t.detail_m) for t in scenario.target_areas],
                        terrain=terrain_desc, params=params,
                        insets=bool(scenario.terrain.insets and scenario.target_areas))
