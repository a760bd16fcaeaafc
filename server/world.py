"""The simulated world: every agent on one terrain, advanced in fixed world ticks.

One world tick (``1 / world_rate_hz`` s, 30 Hz by default) does, in order:

1. apply the latest command of each agent (latest wins; commands arrive from
   RPC threads at any time and wait in ``_pending``);
2. update the autopilots (aircraft: heading/altitude/speed hold or waypoint
   following; ground vehicles: route following and convoys) at the world rate;
3. advance every aircraft by ``fdm_rate_hz / world_rate_hz`` JSBSim steps
   through its aircraft host (server.aircraft_host: one
   :class:`fdm.fleet.Fleet` in process, or one in each worker process, which
   then run while this process steps the ground vehicles) and every ground
   vehicle by one tick through one :class:`fdm.ground.GroundVehicles` (one
   batched query per sub-step);
4. test the airborne aircraft's paths over the tick against the terrain
   (one batched segment intersection), and every moving entity's path against
   every other entity's (server/collisions.py: a "collision" event for each of
   the two; an aircraft in one crashes, a ground vehicle stops where it met the
   other, or is put back where it began the tick, and the snapshot shows it there);
5. publish an immutable :class:`Snapshot` of every live entity's kinematic
   state (ECEF position, velocity and acceleration, orientation ECEF -> body,
   body rates) for the network side to read without locks.

The aircraft host's tick runs one tick ahead: as soon as a tick's aircraft
are back (3.), the commands received so far are applied and the next tick's
aircraft start, so worker processes fly them while this process builds the
snapshot, tests collisions and publishes (measured at 71 f16s, 2000 ground
vehicles and 32 clients: mean tick 37 -> 30 ms). Commands therefore take
effect at the first tick begun after they arrive, as before; a crash the
segment test finds reaches the aircraft one tick later (it has flown one
more tick, ~8 m at 250 m/s, when it stops), and the aircraft then puts its
wreck back where the path met the terrain; until its rows show that, the
world's snapshots show the wreck there already (``_placed``), so the crash
event and every state streamed or recorded agree from the crash's tick on.

Physics never waits on the network: readers take the latest snapshot, writers
only drop commands into a dict. Acceleration is the ECEF velocity's change
over the last tick (what a receiver's second-order dead reckoning needs: the
inertial acceleration of the CG, not JSBSim's body-axis velocity rates).

Entities have stable integer ids (1, 2, ...). A crashed aircraft stays where
it stopped (JSBSim stops stepping it), or where its path met the terrain when
the segment test found that, until removed; one crashed clear of the surface
falls there first (fdm/wreck.py).

External entities are owned by another simulation and published through a
gateway (DIS, server/dis_gateway.py): the world keeps each one's last state,
stamped with the world time it arrived at, and every snapshot dead-reckons it
to the tick's time with its own DIS algorithm, world or body axes
(server.external), so the rest of the server (interest, streaming, recording)
treats it like any entity. Its simulation may say it is destroyed: it is then a
wreck like one of ours (EntityInfo.destroyed, one "destroyed" event), for good.
Its arrivals are inputs like commands: journaled with the tick they came
after, so re-simulation repeats them.
"""

from __future__ import annotations

import dataclasses
import json
import math
import threading
from dataclasses import dataclass, field

import numpy as np

from fdm.aircraft import SEGMENT_CRASH_REASON, InitialConditions, rest_row, terrain_msl_m, validate_controls
from fdm.convoy import (BACK_OFF_AFTER_S, BACK_OFF_MPS, BACK_OFF_S, OBSTACLE_STANDOFF_M, PASS_AFTER_M,
                        PASS_CRAWL_CLEAR_M, PASS_CRAWL_MPS, Convoy, FollowerSet, Route, RouteFollower,
                        column_order, obstacle_reach_m, obstacle_speed_ceiling, pass_offset_m, swing_room_m)
from fdm.ground import BLOCKED_COLLISION, BLOCKED_NAMES, FREE, GroundVehicles
from fdm.state import FT_M, RAW_COLUMNS, euler_to_quaternion, state_arrays
from fdm.vehicle_types import P_BRAKE, P_RMIN
from server.aircraft_host import LocalAircraftHost
from server.collisions import forward_ecef, new_contacts, overlap_depth
from server.obstacles import MOVING_MPS, clearance_ahead
from server.dead_reckoning import ned_to_ecef_quat
from server.external import COALITIONS, MAX_TEXT_CHARS, ExternalTable, extrapolate_external
from sortie.errors import InvalidArgument, LimitExceeded, NotFound, PermissionDenied, bound_text
from terrain.geodesy import ecef_to_geodetic, enu_basis, geodetic_to_ecef

AIRCRAFT, GROUND, STATIC = 1, 2, 3  # = sortie.v1.EntityKind values
KIND_NAMES = {AIRCRAFT: "aircraft", GROUND: "ground", STATIC: "static"}
# Commands that set only the fields they give (the others keep their values): see World.command.
PARTIAL_COMMANDS = frozenset({"stick", "autopilot"})
KIND_OF_NAME = {v: k for k, v in KIND_NAMES.items()}
MAX_ENTITIES = 10_000
# How often (ticks) the world tells its in-process procedural terrain where its entities are
# (ProceduralTerrain.retain_near: blocks no entity is near are dropped, the others evicted last),
# and how far around an entity its blocks are kept: the paper's blocks "dropped when they leave"
# the view (Ammeter & Mikhailyuk), for a simulation that reads its entities' contacts and one
# tick's path; 10 km is far beyond what a Mach 3 aircraft covers between two calls (1 s at 30 Hz).
TERRAIN_RETAIN_EVERY_TICKS = 30
TERRAIN_RETAIN_RADIUS_M = 10_000.0
# Events kept for late readers of the events stream (a ring; readers that fall
# further behind lose the oldest).
EVENT_BACKLOG = 10_000
# Bounding radii (m) of what the world knows no size of: static entities (a scenario's
# "sam_site", "radar": a vehicle-sized site) and external entities, by kind (a fighter's
# half length; a main battle tank's half diagonal). Aircraft take their model's
# (fdm.catalog.body_radius_m), ground vehicles their type's box.
STATIC_RADIUS_M = 10.0
EXTERNAL_RADIUS_M = {1: 8.0, 2: 4.5, 3: STATIC_RADIUS_M}
# An aircraft that touches another entity at this relative speed or more crashes; on the
# ground below it (a taxiing wing tip brushing a parked vehicle) it is reported, not crashed.
AIRCRAFT_CRASH_SPEED_MPS = 2.0
# A ground vehicle or static entity in a collision at this relative speed or more is
# destroyed (72 km/h: an aircraft flying into it, two vehicles meeting head-on at speed);
# below it a ground vehicle stops and drives on, a static one is unharmed.
DESTROY_SPEED_MPS = 20.0
# A ground vehicle touching another entity may not move deeper into it by more than this over
# the contact (metres, its own moves summed, backing out counting against them; rounding of
# positions through geodetic coordinates is far below it): it is put back where it began the
# tick, so a driver pushing on does not pass through. Summed, not per tick: a tank starting from
# rest moves 0.7 mm in its first tick at 30 Hz, under the bound, and crept through the other
# that way, 0.7 mm every other tick (World._held_back).
HOLD_DEPTH_M = 1.0e-3
# A ground vehicle the terrain stops (a slope, water, the terrain's edge) is reported once
# ("blocked", with the reason) and again only after it has driven free for this long (s): a
# driver pushing against a slope is stopped, accelerates and is stopped again tick after tick.
BLOCKED_REPORT_AFTER_FREE_S = 1.0
# An autopilot driver held at a standstill by traffic (what is in its path, server/obstacles.py)
# for this long (s) is reported too ("blocked", reason "traffic"): a jam is not silent.
TRAFFIC_REPORT_S = 10.0
TRAFFIC = -1  # the "blocked" code of a traffic stop (fdm.ground's codes are its own)
BACK_OFF_RUN_M = BACK_OFF_MPS * BACK_OFF_S  # how far a driver backs off (fdm.convoy)
# A driver backs off again only this long (s) after it last did: one whose way round stays
# blocked waits (and is reported as traffic) instead of shuttling back and forth.
BACK_OFF_RETRY_S = 30.0
# A driver swings out to pass a parked obstacle only when the lane it would take is clear for the
# pass and for what oncoming traffic at this speed (m/s) covers meanwhile, at most this far (m).
PASS_LANE_ONCOMING_MPS = 20.0
PASS_LANE_MAX_M = 300.0


# The fields an autopilot or a drive command takes (sortie.v1 AutopilotTargets, DriveControls; a
# stick command's are fdm.aircraft.CONTROL_RANGES').
COMMAND_FIELDS = {"autopilot": ("heading_deg", "alt_msl_m", "speed_mps"), "drive": ("speed_mps", "yaw_rate_dps")}


def command_values(kind: str, values: dict) -> dict:
    """The ``values`` of an autopilot or drive command (``kind``) as floats; InvalidArgument
    naming the field ("drive.speed_mps") for one the command does not take (a drive command
    with a misspelt field stopped the vehicle: what it does not give is 0) or a value that is
    not a finite number (numpy's numbers are numbers, a bool is not, an integer beyond any
    float is not finite)."""
    out = {}
    for k, v in values.items():
        name = f"{kind}.{k}"
        if k not in COMMAND_FIELDS[kind]:
            raise InvalidArgument(name, f"unknown field; known: {', '.join(COMMAND_FIELDS[kind])}", value=v)
        if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise InvalidArgument(name, "must be a finite number", value=v)
        try:
            f = float(v)
        except OverflowError:  # an int beyond any float
            raise InvalidArgument(name, "must be a finite number (an integer beyond any float)") from None
        if not math.isfinite(f):
            raise InvalidArgument(name, "must be a finite number", value=f)
        out[k] = f
    return out


@dataclass(frozen=True)
class WorldEvent:
    time_s: float
    kind: str
    entity_id: int
    lat_deg: float = math.nan
    lon_deg: float = math.nan
    alt_msl_m: float = math.nan
    detail: dict = field(default_factory=dict)

    def detail_json(self) -> str:
        return json.dumps(self.detail, sort_keys=True, default=float)


@dataclass
class Entity:
    """One agent. Aircraft live on the world's aircraft host under the entity's id
    (``crashed`` and ``on_ground`` mirror it as of the last tick), ``ground_id``
    for a ground vehicle (its id in the world's GroundVehicles), ``static_*`` for
    static ones."""

    id: int
    name: str
    kind: int
    type: str
    coalition: str = "neutral"
    controllable: bool = False
    owner: str | None = None  # session token of the client in control
    crashed: bool = False
    destroyed: bool = False  # a ground vehicle or static entity destroyed in a collision
    on_ground: bool = False
    ground_id: int | None = None
    static_lat_lon_alt: tuple = ()
    static_heading_deg: float = 0.0
    on_vanish: str = "autopilot"
    external_id: str = ""  # set for an entity another simulation owns (its gateway's id for it)


@dataclass(frozen=True)
class Snapshot:
    """Every live entity at one world time; arrays are aligned with ``ids``."""

    time_s: float
    tick: int
    ids: np.ndarray  # (n,) int64
    ecef_m: np.ndarray  # (n, 3)
    vel_ecef_mps: np.ndarray  # (n, 3)
    acc_ecef_mps2: np.ndarray  # (n, 3)
    quat_ecef2body: np.ndarray  # (n, 4) w, x, y, z
    body_rates_rps: np.ndarray  # (n, 3)
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    alt_msl_m: np.ndarray

    def index(self) -> dict:
        return {int(i): k for k, i in enumerate(self.ids)}


def rows_of(all_ids: np.ndarray, ids: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(rows of ids in all_ids, an unsorted array of distinct ids; found mask); rows of
    the missing ones are 0."""
    ids = np.asarray(ids, np.int64)
    if not all_ids.size:
        return np.zeros(ids.size, np.int64), np.zeros(ids.size, bool)
    order = np.argsort(all_ids, kind="stable")
    k = order[np.minimum(np.searchsorted(all_ids, ids, sorter=order), all_ids.size - 1)]
    found = all_ids[k] == ids
    return np.where(found, k, 0), found


def _empty_snapshot(t: float, tick: int) -> Snapshot:
    z3 = np.zeros((0, 3))
    return Snapshot(t, tick, np.zeros(0, np.int64), z3, z3, z3, np.zeros((0, 4)), z3, np.zeros(0), np.zeros(0),
                    np.zeros(0))


class EventLog:
    """The events kept for late readers (the newest EVENT_BACKLOG), with a condition
    that readers wait on; what the events stream reads (server/sim_service.py)."""

    def __init__(self):
        self.events: list[WorldEvent] = []  # newest last
        self.events_total = 0  # events ever emitted (readers keep their own count)
        self.event_cond = threading.Condition()

    def _append_event(self, ev: WorldEvent) -> None:
        with self.event_cond:
            self.events.append(ev)
            self.events_total += 1
            if len(self.events) > EVENT_BACKLOG:
                del self.events[:len(self.events) - EVENT_BACKLOG]
            self.event_cond.notify_all()

    def events_since(self, count: int) -> tuple[list[WorldEvent], int]:
        """Events after the first ``count`` ever emitted (those still kept), and the new count."""
        with self.event_cond:
            first = self.events_total - len(self.events)
            return self.events[max(count - first, 0):], self.events_total


class World(EventLog):
    """Agents on one terrain, a fixed-step clock, commands in, snapshots out.

    ``terrain``: anything with ``heights(lat, lon)`` (in-process Terrain or a
    TerrainClient). ``aircraft_host``: where the aircraft fly
    (server.aircraft_host; a LocalAircraftHost on ``terrain`` by default); the
    world closes it in :meth:`close`. Thread-safety: :meth:`tick` runs on one thread (the
    clock's); :meth:`command`, :meth:`claim`, :meth:`release` and spawning may
    be called from any thread; :attr:`snapshot` is replaced atomically.
    """

    def __init__(self, terrain, fdm_rate_hz: float = 120.0, world_rate_hz: float = 30.0,
                 geoid_undulation_m: float = 0.0, aircraft_host=None):
        steps = fdm_rate_hz / world_rate_hz
        if not (world_rate_hz > 0 and abs(steps - round(steps)) < 1e-9 and round(steps) >= 1):
            raise InvalidArgument("fdm_rate_hz", f"must be a whole multiple of world_rate_hz ({world_rate_hz})",
                                  value=fdm_rate_hz)
        self.terrain = terrain
        self.fdm_dt = 1.0 / fdm_rate_hz
        self.dt = 1.0 / world_rate_hz
        self.steps_per_tick = int(round(steps))
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.air = aircraft_host if aircraft_host is not None else LocalAircraftHost(terrain, self.fdm_dt,
                                                                                    self.geoid_undulation_m)
        self._air_tick = None  # the aircraft host's last AirTick
        self._air_in_flight = False  # a tick of the aircraft host begun and not yet ended
        self._layout_version = 0  # bumped when an entity comes or goes
        self._layout_cache = None
        self._shape_cache = None  # (layout version, ids sorted, radius, half length, half width, fixed)
        self._shapes_of = None  # (ids, _shapes(ids)) of the last call
        self.ground: GroundVehicles | None = None
        self.routes: list = []  # (route spec, [entity ids]) of ground agents on routes
        self._scenario_routes: dict[int, dict] = {}  # the route spec each ground agent spawned on
        self._followers = FollowerSet([])  # a RouteFollower/Convoy per route, rebuilt when vehicles go
        self._blocked_reported: dict = {}  # entity id -> (blocked reason reported, last time seen blocked)
        self._waiting: dict = {}  # entity id -> world time since which traffic has held it at a standstill
        self._backing: dict = {}  # entity id -> world time until which it backs off (fdm.convoy BACK_OFF_S)
        self._backed: dict = {}  # entity id -> world time it last began to back off
        self._followed: set = set()  # entity ids on a route
        self._followers_stale = False  # routes changed since _followers was made (_current_followers)
        self._ground_heading_hold: dict = {}  # entity id -> {heading_deg, speed_mps} autopilot targets
        self._hold_version = 0  # bumped when a hold changes (its arrays are cached against it)
        self._hold_cache = None
        self._external = ExternalTable()  # external entities' last states (and their columns)
        self._external_ids: dict[str, int] = {}  # external id -> entity id
        self.entities: dict[int, Entity] = {}
        self._names: set[str] = set()  # the entities' names (unique)
        # id -> (id, name, kind, type, coalition); replaced, never mutated, so readers on
        # other threads always see a whole dict.
        self.infos: dict[int, tuple] = {}
        # Ids of the entities crashed (aircraft) or destroyed (ground, static); replaced, never
        # mutated, like infos (what the streams tell a view an entity entering it is).
        self.wrecks: frozenset = frozenset()
        self.time_s = 0.0
        self.tick_count = 0
        EventLog.__init__(self)
        self._lock = threading.RLock()
        self._pending: dict[int, tuple] = {}
        self._next_id = 1
        self._prev_vel = (np.zeros(0, np.int64), np.zeros((0, 3)))  # (ids, ECEF velocities) of the last snapshot
        # Wrecks the segment test put where their path met the terrain: entity id -> (lat, lon,
        # alt m MSL, surface m MSL), shown there until the aircraft host's rows have them there.
        self._placed: dict[int, tuple] = {}
        # The ongoing contacts of this world's ground vehicles (key: vehicle id << 32 | other id)
        # and how much deeper the vehicle's own moves have taken each so far (m): World._held_back.
        self._contact_creep = (np.zeros(0, np.int64), np.zeros(0))
        # The pairs touching as the last tick left them, with a ground vehicle of this world in
        # each (key: lower id << 32 | higher id, sorted): World._touching_before.
        self._touching = np.zeros(0, np.int64)
        self.snapshot = _empty_snapshot(0.0, 0)
        self.recorder = None  # server.recorder.Recorder: every tick, input and event

    @property
    def layout_version(self) -> int:
        """A number that changes whenever an entity comes or goes (the next snapshot's ids
        differ): the clock publishes such a change without waiting for a network tick."""
        return self._layout_version

    def attach_recorder(self, recorder) -> None:
        """Record from now on (server/recorder.py): the snapshot of every tick, every
        input (:meth:`command`, :meth:`claim`, :meth:`release`, :meth:`remove`, with the
        tick count it was done at) and every event; the events so far (the scenario's
        spawns) are handed over first."""
        with self._lock, self.event_cond:
            for ev in self.events:
                recorder.on_event(self.tick_count, ev)
            self.recorder = recorder

    def _journal(self, input_kind: str, entity_id: int, **fields) -> None:
        """An input to the world, for the recording (called under the lock, so inputs
        and ticks are in one order). Re-simulation repeats the same call after the same
        tick (server/resim.py)."""
        if self.recorder is not None:
            self.recorder.on_input(self.tick_count, input_kind, entity_id, fields)

    # -- spawning -------------------------------------------------------------------------------

    def _check_new_names(self, names: list, what: str) -> None:
        """LimitExceeded unless ``names`` fit in the world (MAX_ENTITIES), InvalidArgument naming
        ``name`` for one given twice or taken: what refuses a batch before any of it is made."""
        if len(self.entities) + len(names) > MAX_ENTITIES:
            raise LimitExceeded("entities", len(self.entities) + len(names), MAX_ENTITIES)
        seen = set()
        for name in names:
            if name in seen:
                raise InvalidArgument("name", f"appears twice among the {what} spawned", value=name)
            if name in self._names:
                raise InvalidArgument("name", "an entity of this name exists", value=name)
            seen.add(name)

    def _new_entity(self, name: str, kind: int, type_: str, **kw) -> Entity:
        if len(self.entities) >= MAX_ENTITIES:
            raise LimitExceeded("entities", len(self.entities) + 1, MAX_ENTITIES)
        if name in self._names:  # (a scan of every entity: 3 s over 5,000 gateway adds)
            raise InvalidArgument("name", "an entity of this name exists", value=name)
        e = Entity(self._next_id, name, kind, type_, **kw)
        self._next_id += 1
        return e

    def _register(self, e: Entity) -> None:
        self.entities[e.id] = e
        self._names.add(e.name)
        self._layout_version += 1
        info = (e.id, e.name, e.kind, e.type, e.coalition) + ((e.external_id,) if e.external_id else ())
        self.infos = {**self.infos, e.id: info}

    def spawn_aircraft(self, name: str, type_: str, ic: InitialConditions, *, coalition: str = "neutral",
                       controllable: bool = False, route=None, hold=None, speed_mps: float | None = None,
                       on_vanish: str = "autopilot") -> Entity:
        """An aircraft; ``route`` [(lat, lon, alt_msl_m), ...] flown at ``speed_mps``, or
        ``hold`` {heading_deg, alt_msl_m, speed_mps} held, or neither (stick, trimmed)."""
        e = self.spawn_aircraft_many([dict(name=name, type_=type_, ic=ic, coalition=coalition,
                                           controllable=controllable, route=route, hold=hold,
                                           speed_mps=speed_mps, on_vanish=on_vanish)])[0]
        if isinstance(e, BaseException):
            raise e
        return e

    def spawn_aircraft_many(self, specs: list[dict]) -> list:
        """Aircraft, each spec the keywords of :meth:`spawn_aircraft` (name, type_, ic
        required), loaded and trimmed by every aircraft worker at once. Per spec its Entity,
        or the error that refused it (a model that cannot trim there: the others are
        spawned regardless). A bad name or too many entities refuses the whole batch."""
        with self._lock:
            names = [s["name"] for s in specs]
            if len(set(names)) != len(names):
                dup = next(n for n in names if names.count(n) > 1)
                raise InvalidArgument("name", "appears twice among the aircraft spawned", value=dup)
            if len(self.entities) + len(specs) > MAX_ENTITIES:
                raise LimitExceeded("entities", len(self.entities) + len(specs), MAX_ENTITIES)
            ents = [self._new_entity(s["name"], AIRCRAFT, s["type_"], coalition=s.get("coalition", "neutral"),
                                     controllable=s.get("controllable", False),
                                     on_vanish=s.get("on_vanish", "autopilot")) for s in specs]
            results = self.air.spawn_many([(e.id, s["type_"], s["ic"], {k: s.get(k) for k in ("route", "hold",
                                                                                              "speed_mps")})
                                           for e, s in zip(ents, specs)])
            out = []
            for e, s, r in zip(ents, specs, results):
                if isinstance(r, BaseException):
                    out.append(r)
                    continue
                e.type = r
                self._register(e)
                self._emit(WorldEvent(self.time_s, "spawn", e.id, s["ic"].lat_deg, s["ic"].lon_deg, math.nan,
                                      {"name": e.name, "kind": "aircraft", "type": e.type}))
                out.append(e)
            return out

    def spawn_ground(self, names, type_, lat, lon, heading_deg, *, coalition="neutral", controllable=False,
                     route=None, cruise_mps: float | None = None, spacing_m: float | None = None,
                     on_vanish: str = "autopilot", speed_mps=0.0) -> list[Entity]:
        """Ground vehicles (one per name); with ``route`` [(lat, lon), ...] they follow it
        at ``cruise_mps`` (a convoy ``spacing_m`` apart when given: the one farthest along the
        route leads, the others follow in their order along it, names given first going first
        where two stand level). ``type_``, ``coalition``, ``controllable`` and ``speed_mps``
        are one value for all or a sequence of one per name: each vehicle keeps its own (a
        convoy of a blue and a red vehicle, one controllable, is one route, not one side).
        ``speed_mps`` (m/s, [0, its type's top speed]) is the speed each starts at; off a
        route, one started moving holds it on its heading (as a scenario aircraft holds its
        spawn speed), until a driver or an autopilot command takes it."""
        names = list(names)
        n = len(names)

        def each(value, field_name: str) -> list:
            if isinstance(value, (list, tuple, np.ndarray)):
                if len(value) != n:
                    raise InvalidArgument(field_name, f"must have {n} values (one per name), got {len(value)}")
                return list(value)
            return [value] * n

        types = each(type_, "type_")
        coalitions, controllables = each(coalition, "coalition"), each(controllable, "controllable")
        speeds = np.array(each(speed_mps, "speed_mps"), np.float64)
        bad = ~(speeds >= 0.0)  # NaN too; the top speed is the vehicle model's check below
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InvalidArgument("speed_mps", f"must be >= 0 m/s (a vehicle starts forward or at rest) for "
                                               f"{names[k]}", index=k, value=float(speeds[k]))
        # The route's geometry, made once here (a bad route refused before anything changes) and
        # kept with its spec for every rebuild of the followers (_route_of).
        spec = None
        if route is not None:
            spec = {"route": [tuple(p) for p in route], "cruise_mps": cruise_mps, "spacing_m": spacing_m}
            spec["geometry"] = Route(*np.array(spec["route"], float).T)
        with self._lock:
            # Every check that can refuse the batch before the vehicles are added: a refusal
            # after it left vehicles in self.ground without an entity (stepped and queried, unseen).
            self._check_new_names(names, "vehicles")
            first = self.ground is None
            if first:
                self.ground = GroundVehicles(self.terrain, lat, lon, heading_deg, types)
                gids = self.ground.ids.copy()
            else:
                gids = self.ground.add(lat, lon, heading_deg, types)
            rows = self.ground.index_of(gids)
            try:
                self.ground.check_controls(speeds, None, index=rows, names=names)
                if spec is not None:  # its cruise speed and spacing, checked as its follower is made
                    self._follower(spec, rows)
            except InvalidArgument:
                if first:
                    self.ground = None
                else:
                    self.ground.remove(gids)
                raise
            self.ground.speed_mps[rows] = speeds
            self.ground.speed_cmd_mps[rows] = speeds
            out = []
            for k, name in enumerate(names):
                e = self._new_entity(name, GROUND, str(types[k]), coalition=coalitions[k],
                                     controllable=bool(controllables[k]), ground_id=int(gids[k]),
                                     on_vanish=on_vanish)
                self._register(e)
                out.append(e)
            if spec is not None:
                ids = [e.id for e in out]
                if spacing_m and n > 1:
                    ids = [ids[k] for k in column_order(spec["geometry"], lat, lon, heading_deg)]
                self.routes.append((spec, ids))
                self._scenario_routes.update((e.id, spec) for e in out)
                self._followed.update(ids)  # (not _rebuild_followers' scan of every route: n spawns, n^2)
                self._followers_stale = True
            elif (speeds > 0.0).any():
                for e, v in zip(out, speeds.tolist()):
                    if v > 0.0:
                        self._ground_heading_hold[e.id] = self._present_hold(e)
                self._hold_version += 1
            for e, la, lo in zip(out, np.atleast_1d(lat), np.atleast_1d(lon)):
                self._emit(WorldEvent(self.time_s, "spawn", e.id, float(la), float(lo), math.nan,
                                      {"name": e.name, "kind": "ground", "type": e.type}))
            return out

    def spawn_static(self, name: str, type_: str, lat: float, lon: float, alt_msl_m: float | None = None,
                     heading_deg: float = 0.0, *, coalition: str = "neutral") -> Entity:
        """A static entity; on the surface when ``alt_msl_m`` is None: the surface an aircraft,
        a ground vehicle and the scenario's overlap check meet there (fdm.aircraft.terrain_msl_m:
        the sea surface over water, where a DEM's bathymetry lies below it; no data as sea
        level)."""
        with self._lock:
            if alt_msl_m is None:
                alt_msl_m = float(terrain_msl_m(self.terrain, np.array([lat], float), np.array([lon], float))[0])
            e = self._new_entity(name, STATIC, type_, coalition=coalition, static_lat_lon_alt=(lat, lon, alt_msl_m),
                                 static_heading_deg=heading_deg)
            self._register(e)
            self._emit(WorldEvent(self.time_s, "spawn", e.id, lat, lon, alt_msl_m,
                                  {"name": name, "kind": "static", "type": type_}))
            return e

    def publish_external(self, external_id: str, owner: str, state: ExternalState | None = None,
                         name: str = "", kind: int = AIRCRAFT, type_: str = "", coalition: str = "neutral",
                         remove: bool = False, destroyed: bool = False) -> int:
        """An external entity's update from the gateway session ``owner``: the first one of
        ``external_id`` adds the entity (``name``, ``kind``, ``type_``, ``coalition``), later
        ones replace its state (``state.t0_s`` is set to the world time now), ``remove``
        takes it out. ``destroyed``: its simulation says it is destroyed (a DIS appearance's
        damage "destroyed"): from this update on it is a wreck (:meth:`is_wreck`, in
        :attr:`wrecks`, so EntityInfo.destroyed), with one "destroyed" event; a later update
        without it does not mend it. Its entity id. Another owner's external id is
        PERMISSION_DENIED's business (the caller checks :meth:`external_owner`)."""
        with self._lock:
            entity_id = self._external_ids.get(external_id)
            if remove:
                if entity_id is None:
                    raise NotFound(f"external entity {external_id!r} does not exist")
                self.remove(entity_id, "external entity removed by its gateway")
                return entity_id
            if state is None:
                raise InvalidArgument("state", "is required unless remove is set")
            state = dataclasses.replace(state, t0_s=self.time_s)
            fields = {"external_id": external_id, "state": [state.ecef_m, state.vel_ecef_mps, state.acc_ecef_mps2,
                                                           state.quat_ecef2body, state.body_rates_rps,
                                                           state.algorithm]}
            if entity_id is None:
                if kind not in KIND_NAMES:
                    raise InvalidArgument("kind", "must be aircraft, ground or static", value=kind)
                if coalition not in COALITIONS:
                    raise InvalidArgument("coalition", f"must be one of {', '.join(COALITIONS)}", value=coalition)
                for field_name, text, least in (("external_id", external_id, 1), ("name", name, 1),
                                                ("type", type_, 0)):
                    if not (least <= len(text) <= MAX_TEXT_CHARS and text.isprintable()):
                        raise InvalidArgument(field_name, f"must be {least}-{MAX_TEXT_CHARS} printable characters",
                                              value=text)
                e = self._new_entity(name, kind, type_, coalition=coalition, owner=owner, external_id=external_id,
                                     on_vanish="remove")
                self._register(e)
                self._external_ids[external_id] = e.id
                fields.update(name=name, kind=kind, type=type_, coalition=coalition)
                entity_id = e.id
                lat, lon, h = (float(x) for x in ecef_to_geodetic(np.array(state.ecef_m)))
                self._emit(WorldEvent(self.time_s, "spawn", e.id, lat, lon, h - self.geoid_undulation_m,
                                      {"name": name, "kind": KIND_NAMES[kind], "type": type_,
                                       "external_id": external_id}))
            self._external[entity_id] = state
            e = self.entities[entity_id]
            if destroyed:
                fields["destroyed"] = True
            self._journal("external", entity_id, **fields)
            if destroyed and not e.destroyed:
                self._destroy_external(e, state)
            return entity_id

    def _destroy_external(self, e: Entity, state: ExternalState) -> None:
        """An external entity its simulation says is destroyed: a wreck from now on, said once."""
        e.destroyed = True
        self.wrecks = self.wrecks | {e.id}
        lat, lon, h = (float(x) for x in ecef_to_geodetic(np.array(state.ecef_m)))
        self._emit(WorldEvent(self.time_s, "destroyed", e.id, lat, lon, h - self.geoid_undulation_m,
                              {"reason": f"its simulation says so ({e.external_id})"}))

    def external_owner(self, external_id: str) -> str | None:
        """The session that publishes ``external_id`` (None: not in the world)."""
        entity_id = self._external_ids.get(external_id)
        e = self.entities.get(entity_id) if entity_id is not None else None
        return None if e is None else e.owner

    def remove_owned_external(self, owner: str) -> None:
        """Remove every external entity published by the session ``owner`` (its gateway left)."""
        with self._lock:
            for e in [e for e in self.entities.values() if e.external_id and e.owner == owner]:
                self.remove(e.id, "its gateway left")

    def remove(self, entity_id: int, reason: str = "removed") -> None:
        with self._lock:
            if entity_id in self.entities:
                self._journal("remove", entity_id, reason=reason)
            self._remove(entity_id, reason)

    def _remove(self, entity_id: int, reason: str) -> None:
        with self._lock:
            e = self.entities.pop(entity_id, None)
            if e is None:
                raise NotFound(f"entity {entity_id} does not exist")
            self._names.discard(e.name)
            self._layout_version += 1
            self.infos = {k: v for k, v in self.infos.items() if k != entity_id}
            self.wrecks = self.wrecks - {entity_id}
            self._pending.pop(entity_id, None)
            self._ground_heading_hold.pop(entity_id, None)
            self._hold_version += 1
            self._placed.pop(entity_id, None)
            if e.external_id:
                self._external.pop(entity_id, None)
                self._external_ids.pop(e.external_id, None)
            elif e.kind == AIRCRAFT:
                self.air.remove(entity_id)
            elif e.kind == GROUND:
                self.ground.remove([e.ground_id])
                self._scenario_routes.pop(entity_id, None)
                self._off_route(entity_id)
            self._emit(WorldEvent(self.time_s, "remove", entity_id, detail={"name": e.name, "reason": reason}))

    def _off_route(self, entity_id: int) -> None:
        """Take a ground vehicle off its route (its convoy goes on without it)."""
        self.routes = [(spec, [i for i in ids if i != entity_id]) for spec, ids in self.routes]
        self.routes = [(spec, ids) for spec, ids in self.routes if ids]
        self._rebuild_followers()

    def _rebuild_followers(self) -> None:
        """Route followers index vehicles by position in the arrays, which removals shift: after
        :attr:`routes` changed, the followers are made again, once, when the next tick needs them
        (:meth:`_current_followers`), however many vehicles came or went meanwhile. Made again at
        every change, a scenario of 10,000 vehicles each on its own route took hours to spawn
        (each spawn remade every route before it, 0.4 ms each), and a driver taking one vehicle
        off its route stalled the tick for seconds."""
        self._followed = {i for _, ids in self.routes for i in ids}
        self._followers_stale = True

    @staticmethod
    def _route_of(spec: dict) -> Route:
        """The Route of a route spec, made once and kept in it (spawn_ground makes it)."""
        route = spec.get("geometry")
        if route is None:
            route = spec["geometry"] = Route(*np.array(spec["route"], float).T)
        return route

    def _follower(self, spec: dict, idx: np.ndarray, top_mps: np.ndarray | None = None) -> RouteFollower:
        """The follower (a Convoy when spaced) of the vehicles at rows ``idx`` on route ``spec``;
        ``top_mps``: every vehicle's top speed (m/s), when the caller has it."""
        top = self.ground.top_speed_mps(idx) if top_mps is None else top_mps[idx]
        cruise = spec["cruise_mps"] or float(top.min()) * 0.5
        if spec["spacing_m"] and len(idx) > 1:
            return Convoy(self.ground, self._route_of(spec), idx, cruise, spec["spacing_m"])
        return RouteFollower(self.ground, self._route_of(spec), idx, cruise)

    def _current_followers(self) -> FollowerSet:
        """The followers of :attr:`routes` as they are now (made again if they changed)."""
        if self._followers_stale:
            self._followers_stale = False
            rows = self.ground.index_of([self.entities[i].ground_id for _, ids in self.routes for i in ids]) \
                if self.routes else np.zeros(0, np.int64)
            ends = np.cumsum([len(ids) for _, ids in self.routes])
            top = self.ground.speed_limits_mps[1]
            self._followers = FollowerSet([self._follower(spec, idx, top) for (spec, _), idx
                                           in zip(self.routes, np.split(rows, ends[:-1]))])
        return self._followers

    # -- control --------------------------------------------------------------------------------

    def is_wreck(self, e: Entity) -> bool:
        """Whether ``e`` has crashed (an aircraft) or been destroyed (a ground vehicle or a
        static): it takes no owner and no commands (a crash found this tick included)."""
        return e.destroyed or e.crashed or e.id in self.wrecks

    def wreck_state(self, e: Entity) -> str | None:
        """How a refusal says ``e`` is a wreck ("is destroyed", "has crashed"), None if it is not."""
        return None if not self.is_wreck(e) else "is destroyed" if e.destroyed else "has crashed"

    def claim(self, entity_id: int, owner: str, client: str = "") -> Entity:
        """Give control of a controllable entity to ``owner`` (a session token; the
        recording keeps the ``client`` name instead); NotFound/InvalidArgument otherwise."""
        with self._lock:
            e = self.entities.get(entity_id)
            if e is None:
                raise NotFound(f"entity {entity_id} does not exist")
            if not e.controllable or e.owner is not None:
                raise InvalidArgument("agent", "is not free to control", value=e.name)
            if self.is_wreck(e):  # nothing to fly or drive
                raise InvalidArgument("agent", self.wreck_state(e), value=e.name)
            e.owner = owner
            self._journal("claim", entity_id, client=client)
            return e

    def release(self, entity_id: int, vanished: bool = False) -> None:
        """The owner lets go: the agent keeps flying/driving on its autopilot
        (holding its present heading, altitude and speed) or is removed, per its
        ``on_vanish``."""
        with self._lock:
            e = self.entities.get(entity_id)
            if e is None:
                return
            self._journal("release", entity_id, vanished=vanished)
            e.owner = None
            self._pending.pop(entity_id, None)  # the leaver's last command is not applied after it left
            if e.on_vanish == "remove":
                self._remove(entity_id, "vanished" if vanished else "left")
                return
            if e.kind == AIRCRAFT:
                self.air.hand_to_autopilot(entity_id)
            elif e.kind == GROUND and not e.external_id and not e.destroyed:
                self._resume_ground(e)

    def _present_hold(self, e: Entity) -> dict:
        """A ground vehicle's heading-and-speed hold of what it does now: its heading, and its
        forward speed within its type's limits."""
        i = self.ground.index_of([e.ground_id])[0]
        speed = min(max(float(self.ground.speed_mps[i]), 0.0), float(self.ground.top_speed_mps([i])[0]))
        heading = float(self.ground.heading_deg[i]) % 360.0
        return {"heading_deg": 0.0 if heading >= 360.0 else heading,  # (-1e-15 % 360 is 360.0)
                "speed_mps": speed}

    def _resume_ground(self, e: Entity) -> None:
        """A ground vehicle left by its driver returns to its scenario route (alone: a convoy
        does not wait for it), or holds its present heading at its present forward speed."""
        if e.id in self._followed:  # its driver never took it off its route
            return
        self._ground_heading_hold.pop(e.id, None)
        self._hold_version += 1
        spec = self._scenario_routes.get(e.id)
        if spec is not None:
            self.routes.append((spec, [e.id]))
            self._rebuild_followers()
            return
        self._ground_heading_hold[e.id] = self._present_hold(e)

    def command(self, entity_id: int, kind: str, values: dict, owner: str | None = None) -> None:
        """Validate a command now (InvalidArgument naming the field; nothing kept) and
        keep it for the next tick, replacing any earlier one (latest wins); but stick and
        autopilot commands set only the fields they give, so two of the same kind in one
        tick add up, the later one's value winning field by field (a heading and then an
        altitude both hold, as they do a tick apart).

        kind "stick": aircraft controls (fdm.aircraft.CONTROL_RANGES names);
        "autopilot": heading_deg / alt_msl_m / speed_mps targets; "drive":
        speed_mps and yaw_rate_dps of a ground vehicle.

        ``owner``: the session that sends it (its token), which must own the entity when the
        command is kept (PERMISSION_DENIED otherwise), checked under the world's lock: a session
        validated before its Leave released the agent on another thread had its command kept
        after the release, the released aircraft flew on the departed pilot's stick and
        crashed (an acceptance probe: 3 of 160 leaves made mid-stream). None: the caller's
        check stands (re-simulation, in-process use).
        """
        e = self.entities.get(entity_id)
        if e is None:
            raise NotFound(f"entity {entity_id} does not exist")
        if self.is_wreck(e):
            raise InvalidArgument("command", f"{e.name} {self.wreck_state(e)}", value=kind)
        if kind == "stick":
            if e.kind != AIRCRAFT:
                raise InvalidArgument("stick", f"only aircraft take stick controls; {e.name} is "
                                               f"{KIND_NAMES[e.kind]}")
            try:
                values = validate_controls(values)
            except InvalidArgument as exc:
                raise exc.with_field(f"stick.{exc.field}") from None
        elif kind == "autopilot":
            if e.kind == STATIC:
                raise InvalidArgument("autopilot", f"{e.name} is static")
            values = command_values(kind, values)
            self._check_autopilot(e, values)
        elif kind == "drive":
            if e.kind != GROUND:
                raise InvalidArgument("drive", f"only ground vehicles take drive commands; {e.name} is "
                                               f"{KIND_NAMES[e.kind]}")
            values = command_values(kind, values)
            self._check_ground_command(e, "drive", values.get("speed_mps", 0.0), values.get("yaw_rate_dps", 0.0))
        else:
            raise InvalidArgument("command", 'must be "stick", "autopilot" or "drive"', value=kind)
        with self._lock:
            if owner is not None and e.owner != owner:
                raise PermissionDenied(f"{e.name} is no longer controlled by this session")
            was = self._pending.get(entity_id)
            merged = {**was[1], **values} if was is not None and was[0] == kind and kind in PARTIAL_COMMANDS else values
            self._pending[entity_id] = (kind, merged)
            self._journal("command", entity_id, command=kind, values=values)

    def _check_autopilot(self, e: Entity, values: dict) -> None:
        """An autopilot command's targets (floats, :func:`command_values`), within the scenario's own bounds for them
        (server.scenario: heading [0, 360), altitude [ALT_MSL_MIN_M, ALT_MAX_M], speed
        (0, SPEED_MAX_MPS]); a ground vehicle's speed within its type's (a value the
        vehicle model refuses would otherwise stop the world at the next tick)."""
        from server.scenario import ALT_MAX_M, ALT_MSL_MIN_M, SPEED_MAX_MPS

        heading, alt, speed = values.get("heading_deg"), values.get("alt_msl_m"), values.get("speed_mps")
        if heading is not None and not 0.0 <= heading < 360.0:
            raise InvalidArgument("autopilot.heading_deg", "must be within [0, 360) degrees true", value=heading)
        if e.kind == GROUND:
            if alt is not None:
                raise InvalidArgument("autopilot.alt_msl_m", "ground vehicles have no altitude to hold")
            if speed is not None:  # forward only, up to its type's top speed (a drive command may reverse)
                top, type_name = self._ground_top_speed(e)
                if not 0.0 <= speed <= top:
                    raise InvalidArgument("autopilot.speed_mps", f"must be within [0, {bound_text(top, speed)}] m/s "
                                          f"for {e.name} ({type_name}: its top speed)", value=speed)
        elif speed is not None and not 0.0 < speed <= SPEED_MAX_MPS:
            raise InvalidArgument("autopilot.speed_mps", f"must be within (0, {SPEED_MAX_MPS:g}] m/s for aircraft",
                                  value=speed)
        elif alt is not None and not ALT_MSL_MIN_M <= alt <= ALT_MAX_M:
            raise InvalidArgument("autopilot.alt_msl_m", f"must be within [{ALT_MSL_MIN_M:g}, {ALT_MAX_M:g}] m MSL",
                                  value=alt)

    def _ground_top_speed(self, e: Entity) -> tuple[float, str]:
        """(top speed m/s, type name) of a ground vehicle, as its model has them."""
        with self._lock:
            t = self.ground.types[int(self.ground.type_id[self.ground.index_of([e.ground_id])[0]])]
        return float(t.max_speed_mps), t.name

    def _check_ground_command(self, e: Entity, command: str, speed_mps, yaw_rate_dps) -> None:
        """The vehicle model's own checks of a speed/heading-rate command (its type's limits),
        made now, with the command's field named; nothing is applied."""
        with self._lock:
            idx = self.ground.index_of([e.ground_id])
            try:
                self.ground.check_controls(speed_mps, yaw_rate_dps, index=idx, names=[e.name])
            except InvalidArgument as exc:
                raise InvalidArgument(f"{command}.{exc.field}", exc.message, value=exc.value) from None

    def aircraft_controls(self, entity_id: int):
        """An aircraft's present controls (fdm.aircraft.Controls)."""
        with self._lock:
            return self.air.controls(entity_id)

    def pilot_kind(self, entity_id: int) -> str:
        """Who flies an aircraft: "autopilot", "route" or "stick" (a client)."""
        with self._lock:
            return self.air.pilot_kind(entity_id)

    def _apply_commands(self) -> None:
        pending, self._pending = self._pending, {}
        for entity_id, (kind, values) in pending.items():
            e = self.entities.get(entity_id)
            if e is None:
                continue
            if kind == "stick":
                self.air.stick(entity_id, values)  # the pilot has the stick
            elif kind == "autopilot" and e.kind == AIRCRAFT:
                self.air.autopilot(entity_id, values)
            elif e.kind == GROUND:
                self._drive(e, kind, values)

    def _drive(self, e: Entity, kind: str, values: dict) -> None:
        if e.id in self._followed:  # a commanded vehicle leaves its route
            self._off_route(e.id)
        idx = self.ground.index_of([e.ground_id])
        if kind == "drive":
            self.ground.set_controls(values.get("speed_mps", 0.0), values.get("yaw_rate_dps", 0.0), index=idx)
            self._ground_heading_hold.pop(e.id, None)
        else:  # autopilot: hold a heading (proportional heading-rate command) and a speed;
            # a target not given keeps the hold's, or what the vehicle does now (a heading
            # alone stopped it: a missing speed read as 0, and a wheeled vehicle cannot turn
            # standing)
            hold = self._ground_heading_hold.get(e.id)
            if hold is None:
                hold = self._ground_heading_hold[e.id] = self._present_hold(e)
            hold.update({k: v for k, v in values.items() if v is not None})
        self._hold_version += 1

    # -- ticking --------------------------------------------------------------------------------

    def tick(self) -> list[WorldEvent]:
        """One world tick (see the module docstring); the events it produced."""
        with self._lock:
            if not self._air_in_flight:  # the first tick (later ones were started by the tick before)
                self._apply_commands()
                self.air.begin_tick(self.steps_per_tick)
            if self.ground is not None and self.ground.n:
                fs = self._current_followers()
                if fs.followers:
                    fs.update(*self._obstacles_ahead(fs.index, fs.convoy_of, place=fs.place, remaining_m=fs.remaining_m(),
                                                     cross_track_m=fs.cross_track_m()),
                              step_s=self.dt * self.ground.divisor[fs.index])
                self._hold_ground_headings()
                self._heading_before = self.ground.heading_deg.copy()  # turning into another is held too
                self.ground.step(self.dt)
            air = self._air_tick = self.air.end_tick()
            # The next tick's aircraft start now, with the commands in so far: in worker
            # processes they fly while this one builds and publishes this tick's snapshot.
            self._apply_commands()
            self.air.begin_tick(self.steps_per_tick)
            self._air_in_flight = True
            self.tick_count += 1
            self.time_s = self.tick_count * self.dt
            events, fdm_crashes = self._air_events(air)
            for entity_id, crashed, on_ground in zip(air.ids.tolist(), air.crashed.tolist(), air.on_ground.tolist()):
                e = self.entities.get(entity_id)
                if e is not None:  # a crash the world found stays, though its command is still on its way
                    e.crashed, e.on_ground = e.crashed or crashed, on_ground
            for entity_id in air.lost:
                events.append(self._lose(entity_id))
            prev_vel = self._prev_vel
            snapshot = self._take_snapshot()
            if self._terrain_collisions(self.snapshot, snapshot, events, fdm_crashes):
                self._prev_vel = prev_vel  # taken again: this tick's wrecks where their paths met the terrain
                snapshot = self._take_snapshot()
            self._note_wrecks(events)  # what crashed so far this tick moves no more
            collided, moved = self._agent_collisions(self.snapshot, snapshot)
            events += collided
            if moved.size:  # stopped where they met, or put back: this snapshot shows where they are
                self._restate_ground(snapshot, self.snapshot, moved)
            self._note_wrecks(events)
            events += self._terrain_blocks()
            for ev in events:
                self._emit(ev)
            self.snapshot = snapshot
            if self.tick_count % TERRAIN_RETAIN_EVERY_TICKS == 0:
                self._retain_terrain(snapshot)
            if self.recorder is not None:
                self.recorder.on_tick(snapshot, self.infos)
            return events

    def _retain_terrain(self, snapshot: Snapshot) -> None:
        """Tell the in-process procedural sources where the entities are
        (ProceduralTerrain.retain_near); a remote terrain service, or an aircraft worker's own
        copy of the terrain, keeps its own cache."""
        from terrain.procedural import ProceduralTerrain

        for src in getattr(self.terrain, "sources", ()):
            if isinstance(src, ProceduralTerrain) and snapshot.ids.size:
                src.retain_near(snapshot.lat_deg, snapshot.lon_deg, TERRAIN_RETAIN_RADIUS_M)

    def _terrain_blocks(self) -> list[WorldEvent]:
        """A "blocked" event for each ground vehicle of this world that the terrain stopped
        this tick (fdm.ground: ``reason`` side_slope, slope, water or outside), or that traffic
        has held at a standstill for TRAFFIC_REPORT_S (``reason`` traffic), and that was not
        already reported for that reason (see BLOCKED_REPORT_AFTER_FREE_S), where it stands;
        so a vehicle stuck on its route, or in a jam, says so once, not silently and not every
        tick."""
        g = self.ground
        if g is None or g.n == 0:
            return []
        gnd_ids, idx, _ = self._layout()
        code = g.blocked[idx].astype(np.int64)
        if self._waiting:  # held by traffic long enough (and not stopped by the terrain)
            rows_w, found = rows_of(gnd_ids, np.fromiter(self._waiting, np.int64, len(self._waiting)))
            since = np.fromiter(self._waiting.values(), np.float64, len(self._waiting))
            late = rows_w[found & (self.time_s - since >= TRAFFIC_REPORT_S)]
            code[late[code[late] == FREE]] = TRAFFIC
        rows = np.flatnonzero((code != FREE) & (code != BLOCKED_COLLISION))
        reported, events = self._blocked_reported, []
        for k in rows.tolist():
            eid, c = int(gnd_ids[k]), int(code[k])
            if reported.get(eid, (FREE,))[0] != c and eid not in self.wrecks:
                j = idx[k]
                events.append(WorldEvent(self.time_s, "blocked", eid, float(g.lat[j]), float(g.lon[j]),
                                         float(g.height_msl_m[j]),
                                         {"reason": "traffic" if c == TRAFFIC else BLOCKED_NAMES[c]}))
            reported[eid] = (c, self.time_s)
        if len(reported) > rows.size:  # forget those free (or gone) for long enough
            for eid in [i for i, (_, t) in reported.items() if self.time_s - t >= BLOCKED_REPORT_AFTER_FREE_S]:
                del reported[eid]
        return events

    def _note_wrecks(self, events: list) -> None:
        """Add the entities that crashed or were destroyed in ``events`` to :attr:`wrecks`."""
        down = {ev.entity_id for ev in events if ev.kind in ("crash", "destroyed")}
        if not down <= self.wrecks:
            self.wrecks = self.wrecks | down

    def _lose(self, entity_id: int) -> WorldEvent:
        """An aircraft whose worker process died: gone from the world (the host has forgotten it)."""
        e = self.entities.pop(entity_id)
        self._names.discard(e.name)
        self._layout_version += 1
        self.infos = {k: v for k, v in self.infos.items() if k != entity_id}
        self._pending.pop(entity_id, None)
        self._placed.pop(entity_id, None)
        return WorldEvent(self.time_s, "remove", entity_id, detail={"name": e.name, "reason": "fdm worker exited"})

    def close(self) -> None:
        """Release the aircraft host (its worker processes, if any)."""
        self.air.close()

    def _air_events(self, air) -> tuple[list[WorldEvent], dict[int, int]]:
        """The aircraft host's events of this tick as world events, and which of them are
        crashes the fdm found this tick of aircraft airborne at the tick's start (entity id ->
        index in the list: :meth:`_terrain_collisions` tests their paths). Left out: a crash
        of an aircraft the world already had down (its own finding, on its way to the aircraft
        while this tick ran: one crash per entity), and anything of a wreck the world put where
        its path met the terrain (what the aircraft did past that place did not happen)."""
        events, fdm_crashes = [], {}
        for entity_id, ev in air.events:
            e = self.entities.get(entity_id)
            if entity_id in self._placed or (e is not None and e.crashed and ev.kind == "crash"):
                continue
            if ev.kind == "crash" and e is not None and not e.on_ground and entity_id not in fdm_crashes:
                fdm_crashes[entity_id] = len(events)
            events.append(WorldEvent(self.time_s, ev.kind, entity_id, ev.lat_deg, ev.lon_deg, ev.alt_msl_m,
                                     dict(ev.detail)))
        return events, fdm_crashes

    def _terrain_collisions(self, before: Snapshot, after: Snapshot, events: list, fdm_crashes: dict) -> bool:
        """Aircraft whose path over the last tick cut the terrain: one batched
        segment-intersection query (the terrain service's IntersectSegments when the
        terrain is remote), so a fast mover cannot tunnel through a ridge between the
        fdm's contact checks. The paths: the straight ECEF segment from the previous
        snapshot's position to this one's for the airborne aircraft; and for those the fdm
        crashed this tick (``fdm_crashes``: entity id -> index of the crash in ``events``),
        to where it stopped them, since far from the ground the fdm finds a cliff face only
        at its next terrain refresh, up to a tick past it (at 1 Hz and 250 m/s, 39 m inside a
        wall, reported as the load factor of JSBSim's gear pushed out of the rock).

        Where a path meets the terrain the crash is there ("terrain collision (segment)": a new
        event, or the fdm's moved there), and so is the wreck, at rest on the surface (the
        aircraft host puts it there, :meth:`fdm.aircraft.Aircraft.crash`; this snapshot and
        the next, taken before it has, show it there through ``_placed``). A crash the fdm
        found whose path does not meet the terrain keeps its place and reason. Events are
        added to (or changed in) ``events``; True if a wreck was placed."""
        if not hasattr(self.terrain, "intersect") or before.ids.size == 0:
            return False
        air = self._air_tick
        ids = air.ids[~air.crashed & ~air.on_ground]
        kb, in_before = rows_of(before.ids, ids)
        ka, in_after = rows_of(after.ids, ids)
        keep = in_before & in_after
        entities = [self.entities.get(i) for i in ids.tolist()]
        keep &= np.array([e is not None and not e.crashed for e in entities], bool)  # not down this tick
        movers = [e for e, k in zip(entities, keep) if k]
        kb, ka = kb[keep], ka[keep]
        end = (after.lat_deg[ka], after.lon_deg[ka], after.alt_msl_m[ka])
        crashed = [self.entities[i] for i in fdm_crashes if i in self.entities]
        if crashed:  # from the previous snapshot to where the fdm stopped them (its crash event's place)
            kc, had = rows_of(before.ids, np.array([e.id for e in crashed], np.int64))
            crashed = [e for e, k in zip(crashed, had) if k]
            stops = [events[fdm_crashes[e.id]] for e in crashed]
            kb = np.concatenate([kb, kc[had]])
            end = tuple(np.concatenate([a, np.array([getattr(ev, f) for ev in stops], np.float64)])
                        for a, f in zip(end, ("lat_deg", "lon_deg", "alt_msl_m")))
        if not movers and not crashed:
            return False
        res = self.terrain.intersect(before.lat_deg[kb], before.lon_deg[kb], before.alt_msl_m[kb], *end)
        hits = np.flatnonzero(np.asarray(res.hit, bool))
        if hits.size == 0:
            return False
        lat, lon = np.asarray(res.lat_deg, np.float64)[hits], np.asarray(res.lon_deg, np.float64)[hits]
        surface = terrain_msl_m(self.terrain, lat, lon)  # the sea's surface over water, as the fdm's
        alt = np.maximum(np.asarray(res.height_msl_m, np.float64)[hits], surface)  # not inside, by rounding
        for j, la, lo, h, s in zip(hits.tolist(), lat.tolist(), lon.tolist(), alt.tolist(), surface.tolist()):
            e = movers[j] if j < len(movers) else crashed[j - len(movers)]
            crash = WorldEvent(self.time_s, "crash", e.id, la, lo, h, {"reason": SEGMENT_CRASH_REASON})
            if j < len(movers):
                events.append(crash)
            else:
                events[fdm_crashes[e.id]] = crash
            self.air.crash(e.id, self.time_s, la, lo, h, SEGMENT_CRASH_REASON)  # it puts the wreck there
            e.crashed = True
            self._placed[e.id] = (la, lo, h, s)
        return True

    def _place_wrecks(self, ids: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """The aircraft host's raw ``rows`` (of entities ``ids``) with the wrecks of ``_placed``
        at rest where they were put (fdm.aircraft.rest_row, the aircraft's own formula), a
        copy; a wreck whose row already has it there is forgotten (the host has caught up)."""
        placed = list(self._placed)
        k, found = rows_of(ids, np.array(placed, np.int64))
        rows = rows.copy()
        c = RAW_COLUMNS
        for entity_id, r, here in zip(placed, k.tolist(), found.tolist()):
            if not here:
                continue
            lat, lon, alt, surface = self._placed[entity_id]
            if (rows[r, c["lat_rad"]], rows[r, c["lon_rad"]], rows[r, c["alt_ft"]]) == \
                    (math.radians(lat), math.radians(lon), alt / FT_M):
                del self._placed[entity_id]
            else:
                rest_row(rows[r], lat, lon, alt, surface)
        return rows

    def _shapes(self, ids: np.ndarray) -> tuple:
        """(bounding radius, half length, half width, fixed) of each entity in ``ids`` --
        metres, half length 0 for a sphere (everything but a ground vehicle of this
        world's), fixed for this world's static entities -- then the rows of ``ids`` that
        are this world's ground vehicles and their rows in ``self.ground``; cached until
        an entity comes or goes or ``ids`` change."""
        if self._shape_cache is None or self._shape_cache[0] != self._layout_version:
            from fdm.catalog import body_radius_m
            from fdm.vehicle_types import VEHICLE_TYPES

            order = sorted(self.entities)
            radius, half_l, half_w = np.zeros(len(order)), np.zeros(len(order)), np.zeros(len(order))
            fixed = np.zeros(len(order), bool)
            for k, i in enumerate(order):
                e = self.entities[i]
                if e.external_id:
                    radius[k] = EXTERNAL_RADIUS_M.get(e.kind, STATIC_RADIUS_M)
                elif e.kind == AIRCRAFT:
                    radius[k] = body_radius_m(e.type)
                elif e.kind == GROUND and e.type in VEHICLE_TYPES:
                    t = VEHICLE_TYPES[e.type]
                    half_l[k], half_w[k] = 0.5 * t.length_m, 0.5 * t.width_m
                    radius[k] = math.hypot(half_l[k], half_w[k])
                else:
                    radius[k] = STATIC_RADIUS_M
                    fixed[k] = e.kind == STATIC
            self._shape_cache = (self._layout_version, np.array(order, np.int64), radius, half_l, half_w, fixed)
            self._shapes_of = None
        if self._shapes_of is not None and np.array_equal(self._shapes_of[0], ids):
            return self._shapes_of[1]
        _, known, radius, half_l, half_w, fixed = self._shape_cache
        k, found = rows_of(known, ids)
        gnd_ids, gnd_idx, _ = self._layout()
        rows, is_gnd = rows_of(ids, gnd_ids)
        shapes = (np.where(found, radius[k], STATIC_RADIUS_M), np.where(found, half_l[k], 0.0),
                  np.where(found, half_w[k], 0.0), found & fixed[k], rows[is_gnd], gnd_idx[is_gnd])
        self._shapes_of = (ids.copy(), shapes)
        return shapes

    def _agent_collisions(self, before: Snapshot, after: Snapshot) -> tuple[list[WorldEvent], np.ndarray]:
        """Entities that came into contact with each other over the last tick
        (server/collisions.py): a "collision" event for each of the two, where it was at
        the moment they touched, naming the other and their relative speed. An aircraft
        in one crashes (on the ground, only at AIRCRAFT_CRASH_SPEED_MPS or more); a ground
        vehicle or static entity at DESTROY_SPEED_MPS or more is destroyed; below it a ground
        vehicle of this world's stops where it met the other (moved back along its path this
        tick, not left past it). A ground vehicle of this world's that drives deeper into
        what it already touches is put back where it began the tick and stopped
        (:meth:`_held_back`): it can back off, turn or slide along, not drive through.
        Entities new this tick are not tested (they have no path yet). Returns the events
        and the rows in ``self.ground`` of the vehicles it stopped or moved (``after`` still
        has them where the fdm left them: :meth:`_restate_ground`)."""
        none = np.zeros(0, np.int64)
        contact_creep, self._contact_creep = self._contact_creep, (none, np.zeros(0))  # kept for those still on
        touching, self._touching = self._touching, none
        if before.ids.size == 0 or after.ids.size < 2:
            return [], none
        if np.array_equal(before.ids, after.ids):  # the usual tick: the same entities in the same order
            ka = kb = np.arange(after.ids.size)
        else:
            kb, here = rows_of(before.ids, after.ids)
            if np.count_nonzero(here) < 2:
                return [], none
            ka = np.flatnonzero(here)
            kb = kb[here]
        ids = after.ids[ka]
        radius, half_l, half_w, fixed, gnd_rows, gnd_idx = self._shapes(ids)
        heading = np.zeros(ids.size)
        heading0 = heading.copy()  # at the tick's start
        if gnd_rows.size:
            heading[gnd_rows] = self.ground.heading_deg[gnd_idx]
            start = getattr(self, "_heading_before", None)
            heading0[gnd_rows] = start[gnd_idx] if start is not None and start.size == self.ground.n else \
                heading[gnd_rows]
        moving = ~fixed
        if self.wrecks:  # wrecks (crashed aircraft, falling ones too, destroyed vehicles) never meet each other
            rows, found = rows_of(ids, np.fromiter(self.wrecks, np.int64, len(self.wrecks)))
            moving[rows[found]] = False
        ci, cj, t, dist = new_contacts(before.ecef_m[kb], after.ecef_m[ka], radius, heading_deg=heading,
                                       half_length_m=half_l, half_width_m=half_w, moves=moving,
                                       lat_deg=after.lat_deg[ka], lon_deg=after.lon_deg[ka], ongoing=gnd_rows.size > 0)
        key = (np.minimum(ids[ci], ids[cj]) << 32) | np.maximum(ids[ci], ids[cj])  # entity ids are below 2**31
        if touching.size and ci.size:
            keep = self._touching_before(after, ka, ci, cj, t, key, touching, heading, radius, half_l, half_w)
            ci, cj, t, dist, key = ci[keep], cj[keep], t[keep], dist[keep], key[keep]
        if gnd_rows.size:
            gnd = np.zeros(ids.size, bool)
            gnd[gnd_rows] = True
            self._touching = np.unique(key[gnd[ci] | gnd[cj]])
        held = t < 0.0  # touching at both ends of the tick: an ongoing contact
        if held.any():
            back = self._held_back(before, after, ka, kb, ci[held], cj[held], (heading0, heading), radius, half_l,
                                   half_w, gnd_rows, gnd_idx, moving, contact_creep)
            ci, cj, t, dist = ci[~held], cj[~held], t[~held], dist[~held]
        else:
            back = None
        events, crashes, stops = [], [], []
        for i, j, frac, d in zip(ci.tolist(), cj.tolist(), t.tolist(), dist.tolist()):
            a, b = self.entities.get(int(ids[i])), self.entities.get(int(ids[j]))
            if a is None or b is None:
                continue
            rel = float(np.linalg.norm(after.vel_ecef_mps[ka[j]] - after.vel_ecef_mps[ka[i]]))
            for me, other, row in ((a, b, i), (b, a, j)):
                p = before.ecef_m[kb[row]] + frac * (after.ecef_m[ka[row]] - before.ecef_m[kb[row]])
                lat, lon, h = (float(x) for x in ecef_to_geodetic(p))
                events.append(WorldEvent(self.time_s, "collision", me.id, lat, lon, h - self.geoid_undulation_m,
                                         {"other_id": other.id, "other_name": other.name,
                                          "other_kind": KIND_NAMES.get(other.kind, "unknown"),
                                          "relative_speed_mps": round(rel, 3), "distance_m": round(d, 3)}))
                if me.external_id:
                    continue  # its own simulation decides what happens to it
                if me.kind == AIRCRAFT and not me.crashed and (not me.on_ground or rel >= AIRCRAFT_CRASH_SPEED_MPS):
                    crashes.append((me, other, (lat, lon, h - self.geoid_undulation_m)))
                elif me.kind in (GROUND, STATIC) and not me.destroyed and rel >= DESTROY_SPEED_MPS:
                    crashes.append((me, other, (lat, lon, h - self.geoid_undulation_m)))
                elif me.kind == GROUND:
                    stops.append((me.ground_id, lat, lon))
        moved = []
        for me, other, hit in crashes:
            reason = f"collision with {other.name}"
            if me.kind == AIRCRAFT and not me.crashed:
                self.air.crash(me.id, self.time_s, *hit, reason)
                me.crashed = True
                events.append(WorldEvent(self.time_s, "crash", me.id, *hit, {"reason": reason}))
            elif me.kind != AIRCRAFT and not me.destroyed:
                self._destroy(me, hit[:2])
                events.append(WorldEvent(self.time_s, "destroyed", me.id, *hit, {"reason": reason}))
                if me.kind == GROUND and not me.external_id:
                    moved.append(self.ground.index_of([me.ground_id]))
        if stops:
            gid, lat, lon = zip(*stops)
            # Where each was when it met the other (on its path this tick), not past it.
            moved.append(self.ground.index_of(list(gid)))
            self.ground.stop(moved[-1], lat=lat, lon=lon)
        if back is not None and back[0].size:  # after the stops: the tick's start is before any contact point
            alive = np.array([not self.entities[int(i)].destroyed for i in ids[back[1]]], bool)
            rows = back[0][alive]
            self.ground.heading_deg[rows] = heading0[back[1][alive]]  # and as it was turned then
            self.ground.stop(rows, lat=before.lat_deg[kb[back[1][alive]]], lon=before.lon_deg[kb[back[1][alive]]])
            moved.append(rows)
        return events, np.unique(np.concatenate(moved)) if moved else none

    def _touching_before(self, after: Snapshot, ka, ci, cj, t, key, touching, heading, radius, half_l,
                         half_w) -> np.ndarray:
        """Of the contacts ``new_contacts`` found this tick (rows ``ci``, ``cj`` of ``ids`` in
        :meth:`_agent_collisions`, ``t`` the fraction at which they touch, -1 ongoing; ``key``:
        each pair's key), those new ones of a pair that touched as the last tick left it
        (``touching``: the last tick's :attr:`_touching`) made ongoing (``t`` set to -1 in
        place) where they still touch at the tick's end, and a mask of the contacts to keep,
        False for those that no longer touch then. A vehicle stopped where it met a sphere (a
        site, an aircraft: the smaller root of |r(t)| = r_i + r_j) stands on the sphere's
        surface, and read back from the snapshot it may be a rounding outside it: pushing on, it
        was a new collision every tick (1569 in 60 s at 30 Hz), not an ongoing contact held
        from going deeper (server/collisions.py counts a pair touching at the tick's start as
        one). Those touching at neither end passed each other, as a pair touching at the start
        that does not at the end is no contact to the kernel."""
        keep = np.ones(t.size, bool)
        again = np.flatnonzero((t >= 0.0) & np.isin(key, touching, assume_unique=True))
        if again.size:
            i, j = ci[again], cj[again]
            r = after.ecef_m[ka[j]] - after.ecef_m[ka[i]]
            on = overlap_depth(r, after.lat_deg[ka[i]], after.lon_deg[ka[i]], heading[i], heading[j], half_l[i],
                               half_w[i], half_l[j], half_w[j], radius[i], radius[j], after.lat_deg[ka[j]],
                               after.lon_deg[ka[j]]) > 0.0
            t[again[on]] = -1.0
            keep[again[~on]] = False
        return keep

    def _restate_ground(self, snapshot: Snapshot, before: Snapshot, moved: np.ndarray) -> None:
        """Rewrite, in this tick's ``snapshot`` (not yet published), the rows of the ground
        vehicles ``moved`` (rows in ``self.ground``) that the collision pass stopped or put back
        after it was taken, from their state now, so what is published and recorded, and the next
        tick's paths and overlap depths (:meth:`_held_back`), start where they are: measured
        from the un-stopped pose, a vehicle pushing on was never "deeper" every other tick and
        crept through what it pushed. Accelerations as :meth:`_take_snapshot`'s, from
        ``before``'s velocities (the arrays are this snapshot's own; ``_prev_vel`` holds the
        same velocity array, so it follows)."""
        gnd_ids, idx, _ = self._layout()
        k, found = rows_of(idx, moved)
        rows, here = rows_of(snapshot.ids, gnd_ids[k[found]])
        rows, moved = rows[here], moved[found][here]
        if rows.size == 0:
            return
        ecef, vel, quat, rates, lat, lon, h = self.ground.snapshot_rows(moved, self.geoid_undulation_m)
        snapshot.ecef_m[rows], snapshot.vel_ecef_mps[rows], snapshot.quat_ecef2body[rows] = ecef, vel, quat
        snapshot.body_rates_rps[rows], snapshot.lat_deg[rows], snapshot.lon_deg[rows] = rates, lat, lon
        snapshot.alt_msl_m[rows] = h
        kb, had = rows_of(before.ids, snapshot.ids[rows])
        snapshot.acc_ecef_mps2[rows] = np.where(had[:, None], (vel - before.vel_ecef_mps[kb]) / self.dt, 0.0)

    def _held_back(self, before: Snapshot, after: Snapshot, ka, kb, ci, cj, headings, radius, half_l, half_w,
                   gnd_rows, gnd_idx, moving, contact_creep) -> tuple[np.ndarray, np.ndarray]:
        """Of the pairs (ci, cj) touching at both ends of the tick (rows of ``ids`` in
        :meth:`_agent_collisions`, with its shapes; ``headings``: at the tick's start and end),
        the ground vehicles of this world that moved deeper into the other: its overlap with the
        other as that began the tick is deeper from where and as the vehicle ended it than from
        where and as it began (so a tank pivoting into its neighbour is held as one driving into
        it), by more than HOLD_DEPTH_M less what its own moves over the contact's earlier ticks
        took it deeper (``contact_creep``: the last tick's :attr:`_contact_creep`; this tick's
        are kept there; a move out of the overlap takes off, down to 0). Summed, moves each under
        the bound do not add up: a tank pushing on from rest crept 0.7 mm every other tick through
        the other. Only its own moves count: the other's (an aircraft taxiing into it, an external
        entity) never hold it. Returns their rows in ``self.ground`` and in ``ids``, each once."""
        heading0, heading = headings
        gidx = np.full(heading.size, -1, np.int64)
        gidx[gnd_rows] = gnd_idx
        mine, others = np.concatenate([ci, cj]), np.concatenate([cj, ci])
        sel = (gidx[mine] >= 0) & moving[mine]
        mine, others = mine[sel], others[sel]
        if mine.size == 0:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        q = before.ecef_m[kb[others]]
        # Each heading is from the north where it was (near a pole the norths of two places metres
        # apart differ: server/collisions.overlap_depth carries the other's onto the vehicle's).
        sizes = (half_l[mine], half_w[mine], half_l[others], half_w[others], radius[mine], radius[others],
                 before.lat_deg[kb[others]], before.lon_deg[kb[others]])
        deeper_m = (overlap_depth(q - after.ecef_m[ka[mine]], after.lat_deg[ka[mine]], after.lon_deg[ka[mine]],
                                  heading[mine], heading0[others], *sizes)
                    - overlap_depth(q - before.ecef_m[kb[mine]], before.lat_deg[kb[mine]], before.lon_deg[kb[mine]],
                                    heading0[mine], heading0[others], *sizes))
        keys = (after.ids[ka[mine]] << 32) | after.ids[ka[others]]  # entity ids are below 2**31
        creep = np.zeros(mine.size)
        if contact_creep[0].size:
            k, known = rows_of(contact_creep[0], keys)
            creep[known] = contact_creep[1][k[known]]
        rows = np.unique(mine[creep + deeper_m > HOLD_DEPTH_M])
        back = np.isin(mine, rows)  # put back, for all its contacts: its move did not happen
        self._contact_creep = (keys, np.where(back, creep, np.maximum(creep + deeper_m, 0.0)))
        return gidx[rows], rows

    def _destroy(self, e: Entity, where: tuple) -> None:
        """A ground vehicle or static entity destroyed: it stays as a wreck; a vehicle where it
        was hit (``where``: lat, lon on its path this tick) leaves its route or hold and stops
        for good (its commands are refused)."""
        e.destroyed = True
        if e.kind != GROUND:
            return
        if e.id in self._followed:
            self._off_route(e.id)
        self._scenario_routes.pop(e.id, None)
        if self._ground_heading_hold.pop(e.id, None) is not None:
            self._hold_version += 1
        self._pending.pop(e.id, None)
        idx = self.ground.index_of([e.ground_id])
        self.ground.set_controls(0.0, 0.0, index=idx)
        self.ground.stop(idx, lat=[where[0]], lon=[where[1]])

    def _hold_ground_headings(self) -> None:
        if not self._ground_heading_hold:
            return
        # The holds' rows, speeds and headings (NaN: hold the current one), cached until a
        # hold changes or an entity comes or goes (rebuilding them cost 0.4 ms a tick for
        # 1800 held vehicles).
        key = (self._layout_version, self._hold_version)
        if self._hold_cache is None or self._hold_cache[0] != key:
            holds = self._ground_heading_hold
            ids = list(holds)
            idx = self.ground.index_of([self.entities[i].ground_id for i in ids])
            self._hold_cache = (key, idx, np.array([holds[i].get("speed_mps", 0.0) for i in ids]),
                                np.array([holds[i].get("heading_deg", np.nan) for i in ids], np.float64))
        _, idx, speed, target = self._hold_cache
        heading = self.ground.heading_deg[idx]
        target = np.where(np.isnan(target), heading, target)
        err = (target - heading + 180.0) % 360.0 - 180.0
        rate = np.clip(0.5 * err, -self.ground.yaw_rate_limit_dps[idx], self.ground.yaw_rate_limit_dps[idx])
        ceiling = self._obstacles_ahead(idx, passing=False)[0]  # heading holds brake, never pass
        self.ground.set_controls(speed if ceiling is None else np.minimum(speed, ceiling), rate, index=idx)

    def _obstacles_ahead(self, idx: np.ndarray, convoy: np.ndarray | None = None, passing: bool = True,
                         remaining_m: np.ndarray | None = None, cross_track_m: np.ndarray | None = None,
                         place: np.ndarray | None = None) -> tuple:
        """What the autopilot-driven ground vehicles ``idx`` (rows of self.ground) do about the
        nearest entity in their path (server/obstacles.py: vehicles, wrecks, static sites,
        aircraft on the ground, as the last snapshot has them): (speed ceilings (m/s), so each
        stops OBSTACLE_STANDOFF_M short of it; with ``passing``, the sideways shift of the path
        that passes it (m, to the right; NaN: none) and over how much route, for one stopped or
        coming the other way (one going its way is followed, not passed), while the ceiling
        lets it roll out at PASS_CRAWL_MPS), as :meth:`FollowerSet.update` takes them; Nones
        when there is nothing to look at. ``convoy``: per vehicle its convoy's number (-1:
        none), whose members do not brake for those ahead of them in the column (``place``: per
        vehicle its place in it, 0 the leader; one behind it in the column that stands in its
        path it brakes for); ``remaining_m``: per vehicle the
        route still ahead of it (m): one whose route ends before it would be past the obstacle
        does not pass it (it queues: vehicles bound for one place do not jostle round each
        other there); ``cross_track_m``: per vehicle how far right of its route it is (m), for
        the shift is of its route's path, not of where it stands (one that cut a corner is off
        its route). A human driver's commands are not capped: braking is his."""
        snap = self.snapshot
        if snap.ids.size < 2 or idx.size == 0:
            return None, None, None, None
        radius, half_l, half_w, _, gnd_rows, gnd_idx = self._shapes(snap.ids)
        heading = np.zeros(snap.ids.size)
        heading[gnd_rows] = self.ground.heading_deg[gnd_idx]
        row_of = np.full(self.ground.n, -1, np.int64)
        row_of[gnd_idx] = gnd_rows
        rows = row_of[idx]
        group = np.full(snap.ids.size, -1, np.int64)
        column_place = np.zeros(snap.ids.size, np.int64)
        if convoy is not None:
            group[rows[rows >= 0]] = convoy[rows >= 0]
        if place is not None:
            column_place[rows[rows >= 0]] = place[rows >= 0]
        brake = self.ground.table[self.ground.type_id[idx], P_BRAKE]
        step = self.dt * self.ground.divisor[idx]  # what each one's next integration covers
        own_speed = self.ground.speed_mps[idx]

        def search(asking, reach, headings=heading, **options):
            """server/obstacles.clearance_ahead over this tick's scene, for the snapshot rows asking."""
            return clearance_ahead(snap.ecef_m, snap.lat_deg, snap.lon_deg, headings, radius, half_l, half_w, group,
                                   asking, reach, snap.vel_ecef_mps, place=column_place, **options)

        clear, other, across, need, yield_m = search(rows, obstacle_reach_m(own_speed, brake))
        ceiling = obstacle_speed_ceiling(clear, brake, step, own_speed)
        # What it would not touch driving straight on (beside its path, within the margin) it
        # passes slowly: two vehicles side by side each in the other's margin do not hold each
        # other for good.
        grazing = (other >= 0) & (np.abs(across) > need)
        ceiling = np.where(grazing, np.maximum(ceiling, PASS_CRAWL_MPS), ceiling)
        # Crossing traffic on its right goes first (server/obstacles.py): it stops short.
        ceiling = np.minimum(ceiling, obstacle_speed_ceiling(yield_m, brake, step, own_speed))
        seen = np.flatnonzero(other >= 0)
        if not passing or seen.size == 0:
            self._note_waiting(idx, ceiling)
            return ceiling, None, None, None
        j = other[seen]
        east, north, _ = enu_basis(snap.lat_deg[rows[seen]], snap.lon_deg[rows[seen]])
        h = np.radians(heading[rows[seen]])
        forward = np.sin(h)[:, None] * east + np.cos(h)[:, None] * north
        vel = snap.vel_ecef_mps[j]
        along = np.einsum("ij,ij->i", vel, forward)
        stopped = np.linalg.norm(vel, axis=1) < 0.5
        oncoming = along < -0.5
        if remaining_m is not None:  # a follower stopped on its way going our way (queued) is not passed
            en_route = np.zeros(snap.ids.size, bool)
            en_route[rows] = remaining_m > 1.0
            # Nose to nose (not a queue), the headings compared in ECEF: each is from its own north,
            # and near a pole two neighbours' norths differ by tens of degrees.
            facing = np.einsum("ij,ij->i", forward_ecef(snap.lat_deg[j], snap.lon_deg[j], heading[j]), forward) < 0.0
            stopped &= ~en_route[j] | facing
        # The shift moves the route's path (fdm.convoy.FollowerSet._shift_goals): the obstacle's
        # place across the route is its place across the vehicle plus the vehicle's off the route.
        off = np.zeros(idx.size) if cross_track_m is None else np.asarray(cross_track_m, np.float64)
        shift = np.full(idx.size, np.nan)
        place = across[seen] + np.where(stopped & ~oncoming, off[seen], 0.0)
        shift[seen] = np.where(stopped | oncoming, pass_offset_m(place, need[seen], oncoming), np.nan)
        # Route to get past: its own length, the obstacle's reach along and PASS_AFTER_M.
        length = clear + 2.0 * (half_l[rows] + radius[np.maximum(other, 0)]) + PASS_AFTER_M
        if remaining_m is not None:
            shift = np.where(remaining_m < length, np.nan, shift)
        wanted = shift
        shift = self._lane_clear(shift, length, idx, rows, oncoming, seen, search, off)
        # One waiting for the lane to clear stops where it has room to swing out from a standstill.
        waits = ~np.isnan(wanted) & np.isnan(shift)
        if waits.any():
            room = swing_room_m(wanted[waits] - off[waits], self.ground.table[self.ground.type_id[idx[waits]], P_RMIN])
            ceiling[waits] = np.minimum(ceiling[waits], obstacle_speed_ceiling(
                clear[waits] - np.maximum(room - OBSTACLE_STANDOFF_M, 0.0), brake[waits], step[waits],
                own_speed[waits]))
        # It rolls out to pass at up to PASS_CRAWL_MPS, slower where it could not stop short of
        # touching the obstacle (half its braking, as every ceiling here).
        rolls = ~np.isnan(shift) & (clear > PASS_CRAWL_CLEAR_M)
        crawl = np.minimum(PASS_CRAWL_MPS, obstacle_speed_ceiling(clear + OBSTACLE_STANDOFF_M - PASS_CRAWL_CLEAR_M,
                                                                  brake, step, own_speed))
        ceiling = np.where(rolls & (yield_m == np.inf), np.maximum(ceiling, crawl), ceiling)
        self._note_waiting(idx, ceiling)
        backing = self._backing_off(idx, ceiling <= 0.0, ~np.isnan(shift), rows, heading, search)
        return ceiling, shift, length, backing

    def _lane_clear(self, shift, length, idx, rows, oncoming, seen, search, off):
        """``shift`` with the passes of parked obstacles whose lane is not clear withdrawn (NaN):
        one whose lane (the path ``shift`` to the side, server/obstacles.py) holds a mover
        within the pass and the way oncoming traffic at PASS_LANE_ONCOMING_MPS covers meanwhile
        waits behind the obstacle instead of swinging into it (what stands in the lane it brakes
        for as for anything in its path; two each waiting for the other's lane would wait for
        good). Passes of oncoming vehicles (each keeping right) are left as they are. ``search``:
        :meth:`_obstacles_ahead`'s path search over this tick's scene; ``off``: each vehicle's
        place right of its route (the shifts are of the route's path, the lane is searched from
        where the vehicle is)."""
        cand = np.flatnonzero(~np.isnan(shift))
        if cand.size == 0:
            return shift
        on = np.zeros(idx.size, bool)
        on[seen] = oncoming
        cand = cand[~on[cand]]
        if cand.size == 0:
            return shift
        v = np.maximum(np.abs(self.ground.speed_mps[idx[cand]]), PASS_CRAWL_MPS)
        reach = np.minimum(length[cand] * (1.0 + PASS_LANE_ONCOMING_MPS / v), PASS_LANE_MAX_M)
        busy = search(rows[cand], reach, offset_m=shift[cand] - off[cand], min_speed_mps=MOVING_MPS)[1] >= 0
        shift = shift.copy()
        shift[cand[busy]] = np.nan
        return shift

    def _backing_off(self, idx: np.ndarray, held: np.ndarray, passable: np.ndarray, rows, heading,
                     search) -> np.ndarray | None:
        """(per vehicle of ``idx``) which back off now (fdm.convoy BACK_OFF_*): those held at a
        standstill by something they would pass (``held & passable``) for BACK_OFF_AFTER_S
        start to, for BACK_OFF_S, where nothing is behind them within that run and the
        standoff (the path search of server/obstacles.py, looking back), and not within
        BACK_OFF_RETRY_S of its last; one that finds something behind it as it goes stops
        backing. None when none backs off. ``rows``, ``heading``, ``search``: the snapshot
        rows of ``idx``, every entity's heading and the path search of :meth:`_obstacles_ahead`."""
        if not (held & passable).any() and not self._backing:
            return None

        def clear_behind(sel):
            back = heading.copy()
            back[rows[sel]] = (heading[rows[sel]] + 180.0) % 360.0
            return search(rows[sel], BACK_OFF_RUN_M + OBSTACLE_STANDOFF_M, headings=back)[0]
        eids = self._entity_ids_of(idx)
        now = self.time_s
        due = [k for k in np.flatnonzero(held & passable).tolist()
               if int(eids[k]) not in self._backing and now - self._waiting.get(int(eids[k]), now) >= BACK_OFF_AFTER_S
               and now - self._backed.get(int(eids[k]), -math.inf) >= BACK_OFF_RETRY_S]
        if due:
            free = clear_behind(np.array(due)) > BACK_OFF_RUN_M + OBSTACLE_STANDOFF_M
            for k in np.array(due)[free].tolist():
                self._backing[int(eids[k])] = now + BACK_OFF_S
                self._backed[int(eids[k])] = now
        going = np.flatnonzero(np.isin(eids, np.fromiter(self._backing, np.int64, len(self._backing))))
        if going.size:  # something came up behind: stop backing
            for k in going[clear_behind(going) <= OBSTACLE_STANDOFF_M / 2].tolist():
                self._backing[int(eids[k])] = now
        for eid in [e for e, until in self._backing.items() if until <= now]:
            del self._backing[eid]
        if not self._backing:
            return None
        return np.isin(eids, np.fromiter(self._backing, np.int64, len(self._backing)))

    def _entity_ids_of(self, idx: np.ndarray) -> np.ndarray:
        """The entity ids of the ground vehicles in rows ``idx`` of self.ground (-1: none)."""
        gnd_ids, lay_idx, _ = self._layout()
        eid_of = np.full(self.ground.n, -1, np.int64)
        eid_of[lay_idx] = gnd_ids
        return eid_of[idx]

    def _note_waiting(self, idx: np.ndarray, ceiling: np.ndarray) -> None:
        """Keep :attr:`_waiting` (for :meth:`_terrain_blocks`): the vehicles ``idx`` whose
        obstacle ceiling is 0 (something in their path within the standoff) are waiting, since
        when they first were; the others of ``idx`` are not."""
        held = ceiling <= 0.0
        if not held.any() and not self._waiting:
            return
        asked = self._entity_ids_of(idx)
        now_held = set(asked[held].tolist())
        if self._waiting:
            keys = np.fromiter(self._waiting, np.int64, len(self._waiting))
            for eid in keys[np.isin(keys, asked)].tolist():
                if eid not in now_held:
                    del self._waiting[eid]
        for eid in now_held:
            self._waiting.setdefault(eid, self.time_s)

    def _layout(self):
        """(ground entity ids, their rows in self.ground, (static ids, static snapshot
        columns) or None), cached until an entity comes or goes."""
        if self._layout_cache is not None and self._layout_cache[0] == self._layout_version:
            return self._layout_cache[1]
        gnd = [e for e in self.entities.values() if e.kind == GROUND and not e.external_id]
        gnd_ids = np.array([e.id for e in gnd], np.int64)
        idx = self.ground.index_of([e.ground_id for e in gnd]) if gnd else np.zeros(0, np.int64)
        st = [e for e in self.entities.values() if e.kind == STATIC and not e.external_id]
        static_part = None
        if st:
            lat = np.array([e.static_lat_lon_alt[0] for e in st])
            lon = np.array([e.static_lat_lon_alt[1] for e in st])
            h = np.array([e.static_lat_lon_alt[2] for e in st])
            q_ned = euler_to_quaternion(np.zeros(len(st)), np.zeros(len(st)),
                                        np.radians([e.static_heading_deg for e in st]))
            z = np.zeros((len(st), 3))
            static_part = ([e.id for e in st], (geodetic_to_ecef(lat, lon, h + self.geoid_undulation_m), z,
                                                ned_to_ecef_quat(q_ned, lat, lon), z, lat, lon, h))
        self._layout_cache = (self._layout_version, (gnd_ids, idx, static_part))
        return self._layout_cache[1]

    def _take_snapshot(self) -> Snapshot:
        ids, parts = [], []
        air = self._air_tick
        if air is not None and air.ids.size:
            rows, air_ids = air.rows, air.ids
            here = np.array([i in self.entities for i in air_ids.tolist()], bool)
            if not here.all():  # removed while their tick was under way
                rows, air_ids = rows[here], air_ids[here]
            if self._placed:
                rows = self._place_wrecks(air_ids, rows)
            s = state_arrays(rows, self.geoid_undulation_m)
            ids += air_ids.tolist()
            parts.append((s["ecef_m"], s["vel_ecef_mps"],
                          ned_to_ecef_quat(s["quat_wxyz"], s["lat_deg"], s["lon_deg"]), s["body_rates_rps"],
                          s["lat_deg"], s["lon_deg"], s["alt_msl_m"]))
        gnd_ids, idx, static_part = self._layout()
        if gnd_ids.size:
            ids += gnd_ids.tolist()
            parts.append(self.ground.snapshot_rows(idx, self.geoid_undulation_m))
        if static_part is not None:
            ids += static_part[0]
            parts.append(static_part[1])
        if len(self._external):
            ext_ids, *ext_cols = self._external.columns()
            ids += ext_ids.tolist()
            parts.append(self._external_part(*ext_cols))
        if not ids:
            return _empty_snapshot(self.time_s, self.tick_count)
        cols = [np.concatenate([p[k] for p in parts]) for k in range(7)]
        ids = np.array(ids, np.int64)
        vel = cols[1]
        acc = np.zeros_like(vel)
        prev_ids, prev_vel = self._prev_vel
        if np.array_equal(ids, prev_ids):  # the usual tick: the same entities in the same order
            acc = (vel - prev_vel) / self.dt
        elif prev_ids.size:
            k, had = rows_of(prev_ids, ids)
            acc[had] = (vel[had] - prev_vel[k[had]]) / self.dt
        self._prev_vel = (ids, vel)
        return Snapshot(self.time_s, self.tick_count, ids, cols[0], vel, acc, cols[2], cols[3], cols[4], cols[5],
                        cols[6])

    def _external_part(self, t0, pos, vel, acc, quat, rates, algorithm) -> tuple:
        """Snapshot columns of external entities (their states' columns,
        server.external.ExternalTable.columns): each state dead-reckoned to the world time now
        with its own DIS algorithm, world or body axes (server.external.extrapolate_external)."""
        pos_t, vel_t, quat_t = extrapolate_external(algorithm, t0, pos, vel, acc, quat, rates, self.time_s)
        lat, lon, h = ecef_to_geodetic(pos_t)
        return pos_t, vel_t, quat_t, rates, lat, lon, h - self.geoid_undulation_m

    # -- events ---------------------------------------------------------------------------------

    def _emit(self, ev: WorldEvent) -> None:
        with self.event_cond:
            self._append_event(ev)
            if self.recorder is not None:
                self.recorder.on_event(self.tick_count, ev)

    def emit(self, kind: str, entity_id: int = 0, **detail) -> None:
        """An event from outside the physics (joins, leaves)."""
        self._emit(WorldEvent(self.time_s, kind, entity_id, detail=detail))


