"""Re-simulation: run a recorded sortie again from its scenario with its recorded
inputs, and compare every state; and "take over" from any instant.

The world is deterministic: the same scenario on the same terrain, with the
same calls (command, claim, release, remove) made after the same ticks, gives
bit-identical states, in process or with the aircraft in worker processes
(tests/test_aircraft_host.py). The recording keeps each of those calls with
the tick count it was made at (server/world.py journals them under the
world's lock), so re-simulation repeats them after the same tick and then
ticks. Each tick's snapshot is compared with the recorded one by the digest
of its exact float64 states (bit-exact or not) and, where they differ, by
the quantised states, which locate the first divergence (tick, entity,
field, size). A different build (the header's build id) or terrain (the DEM
files' SHA-256) is reported: bit-exactness is promised for the same build on
the same terrain only.

Take-over ("My Controls!" in FlightGear): re-simulate to tick k, then run the
world live (server.sim_server.SimulationServer) with the chosen agent free
for a client to claim (on its autopilot until one does) while every other
agent keeps receiving its recorded inputs after the same ticks
(:class:`RecordedInputs` as the server's ``before_tick``). The take-over is
a sortie like any other and is recorded from its world's start (the
re-simulated ticks, then the live ones); making the agent claimable is an
input of its own ("take_over"), so its recording re-simulates too. It runs
live for ``--duration`` world seconds or to the exercise's end: the later of
the scenario's duration_s and the recording's end (a server run with
``--duration`` past its scenario's end recorded past it), so an instant of
the recording always has a live phase; only its last instant, with no
--duration, has none, and is refused. Only aircraft and ground vehicles can
be taken over (no client role takes a static site).

A damaged chunk (server/recording.py) loses its ticks' states, which are not
compared, and its inputs: a re-simulation that would need them is refused
(it could not be bit-exact), naming the chunk and how far one can go.
"""

from __future__ import annotations

import functools
import json
import time
from collections import defaultdict
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from server import recording_codec as codec
from server.external import ExternalState
from server.recorder import build_id
from server.recording import Recording
from server.world import AIRCRAFT, GROUND, KIND_NAMES
from sortie.errors import DataFormatError, InvalidArgument, NotFound
from terrain.dem import file_identity

FIELD_NAMES = (["ecef_x_m", "ecef_y_m", "ecef_z_m", "vel_x_mps", "vel_y_mps", "vel_z_mps", "acc_x_mps2",
                "acc_y_mps2", "acc_z_mps2", "quat_w", "quat_x", "quat_y", "quat_z", "rate_p_rps", "rate_q_rps",
                "rate_r_rps"])


@dataclass
class Divergence:
    tick: int
    time_s: float
    entity_id: int
    name: str
    field: str
    recorded: float
    resimulated: float

    def __str__(self) -> str:
        if self.field == "entities":
            return f"tick {self.tick} (t = {self.time_s:.3f} s): {self.name}"
        return (f"tick {self.tick} (t = {self.time_s:.3f} s): {self.name} (id {self.entity_id}) {self.field} "
                f"recorded {self.recorded:.6f}, re-simulated {self.resimulated:.6f} "
                f"(diff {self.resimulated - self.recorded:+.6g})")


@dataclass
class ResimReport:
    recording: str
    ticks: int = 0
    bit_exact_ticks: int = 0
    max_position_diff_m: float = 0.0  # largest position difference (a distance), on the recording's grid
    max_abs_diff_m: float = 0.0  # largest difference along one ECEF axis (kept for older readers of the JSON)
    first_divergence: Divergence | None = None
    same_build: bool = True
    same_terrain: bool = True
    notes: list = field(default_factory=list)
    wall_s: float = 0.0
    ticks_not_compared: int = 0  # in chunks that do not read (damaged): their states are lost

    @property
    def bit_exact(self) -> bool:
        return self.ticks > 0 and self.bit_exact_ticks == self.ticks

    def as_dict(self) -> dict:
        d = {k: getattr(self, k) for k in ("recording", "ticks", "bit_exact_ticks", "max_position_diff_m",
                                           "max_abs_diff_m", "same_build",
                                           "same_terrain", "notes", "wall_s", "ticks_not_compared")}
        d["bit_exact"] = self.bit_exact
        d["first_divergence"] = str(self.first_divergence) if self.first_divergence else None
        return d


# -- the recorded scenario, terrain and inputs -----------------------------------------------------

def recorded_scenario(rec: Recording):
    """The scenario as recorded (its text from the header; relative DEM paths against the
    scenario file's folder at record time)."""
    from server.scenario import ScenarioError, parse_scenario, scenario_data

    h = rec.header
    try:  # TOML or YAML, by the recorded path's suffix
        data = scenario_data(h.scenario_toml, h.scenario_path)
    except ScenarioError as exc:
        raise DataFormatError(f"{rec.path.name}: the recorded scenario does not parse: {exc}") from None
    try:
        return parse_scenario(data, Path(h.scenario_path).parent)
    except ScenarioError as exc:
        if not exc.field.startswith("terrain.dem"):
            raise DataFormatError(f"{rec.path.name}: the recorded scenario is not valid here: {exc}") from None
    # Its DEMs are not where they were: the scenario still gives the agents and parameters
    # (the terrain comes from the header's files or an override, recorded_terrain_spec).
    terrain = data.get("terrain", {})
    data["terrain"] = {"service": "127.0.0.1:1", "geoid_undulation_m": terrain.get("geoid_undulation_m", 0.0)}
    return parse_scenario(data, Path(h.scenario_path).parent)


def recorded_terrain_spec(rec: Recording, dem=None, service: str | None = None) -> tuple[dict, list]:
    """(arguments of server.sim_server.open_terrain_source, notes): ``dem`` files or a
    ``service`` override the recording's terrain. DEM files are checked against the
    recorded SHA-256 (a mismatch is a note and clears same_terrain).

    A recording made over a terrain service is re-opened in process from the DEM files the
    service said it read (their SHA-256 recorded since the service names them), with the
    insets it served rebuilt from their recorded parameters: the service answers from that
    same Terrain, so the answers are the same bits (see :func:`sources_match`)."""
    t = rec.header.terrain
    if service:
        return {"service": service}, [f"terrain: service {service} (recorded: {t.description})"]
    if dem:
        paths, spec, notes = [str(p) for p in dem], {}, []
    elif t.description.startswith("service:"):
        paths, spec, notes = served_terrain(rec)
    elif t.files:
        paths, spec, notes = [f.path for f in t.files], {}, []
    else:
        raise DataFormatError(f"{rec.path.name}: the header names no terrain")
    for p in paths:
        if not Path(p).is_file():
            raise NotFound(f"terrain file {p!r} does not exist (give --dem FILE... with the recorded DEMs)")
    return {"dem": paths, **spec}, notes


def recorded_sources(rec: Recording) -> list[dict]:
    """The terrain's sources as recorded (Terrain.describe(), or the service's GetMetadata
    sources, whose details are text); [] if none or the record does not parse."""
    try:
        sources = json.loads(rec.header.terrain.sources_json or "[]")
    except json.JSONDecodeError:
        return []
    return [s for s in sources if isinstance(s, dict)] if isinstance(sources, list) else []


def service_dem_files(rec: Recording) -> list[str]:
    """The DEM files the recording's terrain service said it served (its recorded sources),
    as it named them; [] if it named none or the record does not parse."""
    return [str(x["source"]) for x in recorded_sources(rec) if x.get("kind") == "dem" and x.get("source")]


def served_terrain(rec: Recording) -> tuple[list, dict, list]:
    """(DEM paths, further open_terrain_source arguments, notes) rebuilding in process the
    terrain a recording's service served: its DEM files, terrain stores and procedural world
    (in the order `sortie terrain serve` stacks them) and its insets."""
    t = rec.header.terrain
    address = t.description.removeprefix("service:")
    sources = recorded_sources(rec)
    kinds = [str(s.get("kind")) for s in sources]
    other = sorted(set(kinds) - {"dem", "inset", "store", "procedural"})
    if other:
        raise NotFound(f"the recording's terrain was the service {address}, with {', '.join(other)} sources "
                       "not rebuilt in process; give --terrain ADDRESS of one serving the same terrain")
    if t.files:
        paths = [f.path for f in t.files]
        notes = [f"terrain: the {len(paths)} DEM files the recording's service {address} read "
                 "(SHA-256 checked)"]
    else:  # recorded before services named their files' hashes: the paths its sources gave
        paths = service_dem_files(rec)
        notes = [f"terrain: the {len(paths)} DEM files the recording's service {address} named "
                 "(its recording keeps no hashes: not checked)"] if paths else []
    stores = [str(s.get("source")) for s in sources if s.get("kind") == "store"]
    missing = [p for p in paths if not Path(p).is_file()] + [p for p in stores if not Path(p).is_dir()]
    if missing or ("dem" in kinds and not paths):
        raise NotFound(f"the recording's terrain was the service {address}; its files are not here "
                       f"({', '.join(missing) or 'it named no DEM file'}): give --terrain ADDRESS of one "
                       "serving the same terrain or --dem FILE...")
    spec: dict = {}
    if stores:
        spec["store"] = stores
        notes.append(f"terrain: the service's {len(stores)} terrain stores, checked by their description")
    procedural = [s for s in sources if s.get("kind") == "procedural"]
    if procedural:
        try:
            spec["procedural"] = int(procedural[0]["seed"])
        except (KeyError, TypeError, ValueError):
            raise DataFormatError(f"{rec.path.name}: the recorded procedural source names no seed") from None
        params = {k: float(procedural[0][k]) for k in ("max_height_m", "level_exponent", "water")
                  if k in procedural[0]}
        if params:  # the world the service made (M, E, W: sortie terrain serve --procedural-*)
            spec["procedural_params"] = params
        notes.append(f"terrain: the service's procedural world, seed {spec['procedural']}")
    areas = tuple(_inset_area(s) for s in sources if s.get("kind") == "inset")
    if areas:
        notes.append(f"terrain: the service's {len(areas)} insets rebuilt ({', '.join(a[0] for a in areas)})")
    spec["target_areas"] = areas  # the service's, none included: not the scenario's (with_insets)
    return paths, spec, notes


def _inset_area(source: dict) -> tuple:
    """(name, polygon, detail_m) of a recorded inset source, as terrain.inset.with_insets takes."""
    polygon = source.get("polygon")
    try:
        polygon = json.loads(polygon) if isinstance(polygon, str) else polygon
        return (str(source["area"]), tuple((float(a), float(b)) for a, b in polygon), float(source["detail_m"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise DataFormatError(f"the recorded inset {source.get('name')!r} does not parse: {exc}") from None


def with_insets(spec: dict, scenario) -> dict:
    """``spec`` (open_terrain_source's arguments) answering from the scenario's target-area
    insets where the world did: DEM files, and a scenario with ``insets`` and target areas
    (unless ``spec`` already has the insets a recorded service served)."""
    if "dem" in spec and "target_areas" not in spec and scenario.terrain.insets and scenario.target_areas:
        from server.sim_server import inset_areas

        spec["target_areas"] = inset_areas(scenario)
    return spec


def terrain_matches(rec: Recording, spec: dict) -> tuple[bool, list]:
    """Whether the DEM files of ``spec`` are the recorded ones (by SHA-256)."""
    recorded = {f.sha256 for f in rec.header.terrain.files}
    if "dem" not in spec:
        return True, ["terrain service: files not checked"]
    if not recorded:
        return True, ["recorded on a terrain service: files not checked against it"]
    got = {file_identity(p)["sha256"] for p in spec["dem"]}
    if got == recorded:
        return True, []
    return False, ["terrain differs from the recording's (DEM SHA-256 mismatch)"]


def sources_match(rec: Recording, terrain) -> tuple[bool, list]:
    """Whether ``terrain`` describes itself as the recorded terrain did: every field both
    descriptions have but the path (name, bounds, posts, datum, a store's levels and step, a
    procedural world's parameters, an inset's whole parameters), compared as text since a
    service sends its sources' details as text."""
    recorded = recorded_sources(rec)
    if not recorded:
        return True, []
    try:
        now = terrain.describe()
    except Exception as exc:  # noqa: BLE001 - a terrain that cannot describe itself is checked no further
        return True, [f"terrain sources not compared: {exc}"]
    if len(now) != len(recorded):
        return False, [f"terrain has {len(now)} sources, the recording's had {len(recorded)}"]
    for i, (a, b) in enumerate(zip(recorded, now)):
        for key, value in a.items():  # keys both have (a service's sources carry every proto field)
            if key != "source" and key in b and str(value) != str(b[key]):
                return False, [f"terrain source {i} ({a.get('name')}) differs from the recording's in {key}: "
                               f"{b.get(key)} here, {value} recorded"]
    return True, []


class RecordedInputs:
    """The recording's inputs by tick; :meth:`apply` makes those done after a tick.

    ``skip`` ids get none from tick ``skip_from_tick`` on (a taken-over agent). The inputs
    of a chunk that does not read are lost: a DataFormatError when a run to tick ``until``
    (None: the recording's end) needs them, else listed in :attr:`lost`. A damaged chunk
    whose head checks and counts no input loses none."""

    def __init__(self, rec: Recording, skip=(), skip_from_tick: int = 0, until: int | None = None):
        self.by_tick: dict[int, list] = defaultdict(list)
        self.skip = set(skip)
        self.lost: list[str] = []
        for k in range(rec.chunk_count):
            try:
                records = rec.chunk_body(k)[1].inputs
            except DataFormatError as exc:
                self._lost(rec, k, exc, until)
                continue
            for r in records:
                if r.entity_id not in self.skip or r.tick < skip_from_tick:
                    self.by_tick[r.tick].append(r)

    def _lost(self, rec: Recording, k: int, exc: DataFormatError, until: int | None) -> None:
        head = rec.trusted_head(k)
        if head is not None and head.input_count == 0:
            return
        count = "an unknown number of" if head is None else str(head.input_count)
        after = rec.inputs_after_tick(k)
        if until is None or after < until:
            if after < 0:
                raise DataFormatError(f"cannot re-simulate: {exc}; {count} inputs from the recording's start are "
                                      "lost with it, so no re-simulation can be bit-exact")
            raise DataFormatError(f"cannot re-simulate past t = {after * rec.dt:.3f} s (tick {after}): {exc}; "
                                  f"{count} inputs done after that tick are lost with it, so a re-simulation past "
                                  f"it cannot be bit-exact (--until {after * rec.dt:.3f} stops there)")
        self.lost.append(f"{count} inputs after tick {after} lost: {exc}")

    def apply(self, world, tick: int | None = None) -> int:
        """Make the inputs recorded after tick ``tick`` (default: the world's tick count); how many."""
        records = self.by_tick.get(world.tick_count if tick is None else tick, ())
        for r in records:
            apply_input(world, r)
        return len(records)


def apply_input(world, r) -> None:
    if r.kind == "command":
        world.command(r.entity_id, r.command, json.loads(r.values_json))
    elif r.kind == "claim":
        world.claim(r.entity_id, f"resim:{r.client}", r.client)
    elif r.kind == "release":
        world.release(r.entity_id, vanished=r.vanished)
    elif r.kind == "remove":
        world.remove(r.entity_id, r.reason)
    elif r.kind == "take_over":
        v = json.loads(r.values_json)
        e = world.entities.get(r.entity_id)
        if e is not None:
            e.controllable, e.on_vanish = bool(v["controllable"]), str(v["on_vanish"])
    elif r.kind == "external":
        v = json.loads(r.values_json)
        # The journal holds the state as validated (quaternion normalised): taken as is, since
        # normalising again could change its last bits.
        pos, vel, acc, quat, rates, algorithm = v["state"]
        state = ExternalState(0.0, tuple(pos), tuple(vel), tuple(acc), tuple(quat), tuple(rates), int(algorithm))
        destroyed = bool(v.get("destroyed", False))
        if "name" in v:  # the first update of an external entity: it enters the world
            world.publish_external(v["external_id"], "resim:external", state, v["name"], v["kind"], v["type"],
                                   v["coalition"], destroyed=destroyed)
        else:
            world.publish_external(v["external_id"], "resim:external", state, destroyed=destroyed)
    else:
        raise DataFormatError(f"input of unknown kind {r.kind!r} at tick {r.tick}")


# -- re-simulation ---------------------------------------------------------------------------------

def build_recorded_world(rec: Recording, dem=None, service: str | None = None, workers: int = 0):
    """(world as the recording started, its scenario, terrain spec, notes). The recorded
    scenario started on the recorded terrain; where it cannot start on a ``dem`` or ``service``
    given instead (an agent off it or in its water), InvalidArgument names that option and the
    recorded terrain, not the scenario's agent alone (whose scenario the user cannot change)."""
    from server.sim_server import aircraft_host, build_world, open_terrain_source

    scenario = recorded_scenario(rec)
    spec, notes = recorded_terrain_spec(rec, dem, service)
    with_insets(spec, scenario)
    terrain = open_terrain_source(**spec)
    try:
        world = build_world(scenario, terrain, aircraft_host(scenario, terrain,
                                                             functools.partial(open_terrain_source, **spec), workers))
    except InvalidArgument as exc:
        if dem is None and service is None:
            raise
        option, value = ("--dem", [str(p) for p in dem]) if dem else ("--terrain", service)
        raise InvalidArgument(option, f"the recorded scenario cannot start on this terrain (recorded: "
                                      f"{rec.header.terrain.description}): {exc}", value=value) from None
    if abs(1.0 / world.dt - rec.rate_hz) > 1e-9:
        raise DataFormatError(f"{rec.path.name}: recorded at {rec.rate_hz} Hz, the scenario ticks at "
                              f"{1.0 / world.dt} Hz")
    return world, scenario, spec, notes


def _compare(rec: Recording, report: ResimReport, tick: int, ids: np.ndarray, states: np.ndarray) -> None:
    frame = rec.frame(tick)
    report.ticks += 1
    if frame.ids.size == ids.size and np.array_equal(frame.ids, ids) and codec.digest(ids, states) == frame.digest:
        report.bit_exact_ticks += 1
        return
    if not np.array_equal(frame.ids, ids):
        if report.first_divergence is None:
            extra = sorted(set(ids.tolist()) - set(frame.ids.tolist()))
            missing = sorted(set(frame.ids.tolist()) - set(ids.tolist()))
            report.first_divergence = Divergence(tick, tick * rec.dt, 0, f"entities differ (re-simulation has "
                                                 f"extra {extra[:5]}, lacks {missing[:5]})", "entities", 0, 0)
        common, ka, kb = np.intersect1d(ids, frame.ids, return_indices=True)
        ids, states, rq = common, states[ka], frame.q[kb]
    else:
        rq = frame.q
    q = codec.quantize(states, rec.steps)
    diff = q - rq
    d_pos = diff[:, codec.POS] * rec.steps.position_m
    report.max_position_diff_m = max(report.max_position_diff_m,
                                     float(np.linalg.norm(d_pos, axis=1).max(initial=0)))
    report.max_abs_diff_m = max(report.max_abs_diff_m, float(np.abs(d_pos).max(initial=0)))
    if report.first_divergence is None:
        rows, cols = np.nonzero(diff)
        if rows.size:
            k, f = int(rows[0]), int(cols[0])
            step = rec.steps.vector()[f]
            e = rec.entities.get(int(ids[k]))
            report.first_divergence = Divergence(tick, tick * rec.dt, int(ids[k]), e.name if e else "?",
                                                 FIELD_NAMES[f], float(rq[k, f] * step), float(states[k, f]))
        else:
            report.first_divergence = Divergence(tick, tick * rec.dt, 0, "states differ below the recording's "
                                                 "quantisation step (digest mismatch)", "entities", 0, 0)


def _compare_readable(rec: Recording, report: ResimReport, tick: int, state, unreadable: dict) -> None:
    """:func:`_compare` where the recording has the tick's states; a tick of a chunk that does
    not read is counted in ``ticks_not_compared`` (and its chunk noted once)."""
    k = rec.chunk_of_tick(tick)
    if k not in unreadable:
        try:
            _compare(rec, report, tick, *state)
            return
        except DataFormatError as exc:
            unreadable[k] = str(exc)
            first, last = rec.chunk_ticks(k)
            report.notes.append(f"ticks {first}..{last} not compared (their states are lost): {exc}")
    report.ticks_not_compared += 1


def resimulate(path, dem=None, service: str | None = None, workers: int = 0, until_s: float | None = None,
               progress=None) -> ResimReport:
    """Re-run the recording at ``path`` and compare every tick (see the module docstring)."""
    t0 = time.perf_counter()
    with Recording(path) as rec:
        report = ResimReport(str(path))
        report.notes += list(rec.problems)
        if rec.header.build_id != build_id():
            report.same_build = False
            report.notes.append(f"recorded by build {rec.header.build_id}, this is {build_id()}: states may "
                                "differ in the last bits")
        world, _, spec, notes = build_recorded_world(rec, dem, service, workers)
        report.notes += notes
        same_files, notes = terrain_matches(rec, spec)
        report.notes += notes
        same_sources, notes = sources_match(rec, world.terrain)
        report.notes += notes
        report.same_terrain = same_files and same_sources
        last = rec.last_tick if until_s is None else rec.tick_at(until_s)
        unreadable: dict[int, str] = {}
        try:
            inputs = RecordedInputs(rec, until=last)
            while world.tick_count < last:
                inputs.apply(world)
                world.tick()
                if world.tick_count >= rec.first_tick:
                    _compare_readable(rec, report, world.tick_count, codec.state_matrix(world.snapshot), unreadable)
                if progress is not None:
                    progress(world.tick_count, last)
        finally:
            world.close()
    report.wall_s = time.perf_counter() - t0
    return report


def take_over(path, at_s: float, agent: str, dem=None, service: str | None = None, workers: int = 0,
              recorder=None, duration_s: float | None = None):
    """(world re-simulated to ``at_s`` with ``agent`` free to claim, RecordedInputs for the
    others, scenario as the take-over runs it): what ``sortie resim --take-over`` serves live.

    The live phase lasts ``duration_s`` world seconds, by default until the exercise's end
    (:func:`take_over_end`): the returned scenario's ``exercise.duration_s`` is the world time
    it ends at (None: until stopped). ``recorder(rec, world, scenario, terrain_spec)``: a
    server.recorder.Recorder (or None) to record the sortie with, attached to the world
    before it is re-simulated (so its recording holds the whole sortie); closed here if the
    take-over fails."""
    rec = Recording(path)
    world = attached = None
    try:
        world, scenario, spec, _ = build_recorded_world(rec, dem, service, workers)
        target = next((e for e in world.entities.values() if e.name == agent), None)
        if target is None:
            names = sorted(e.name for e in world.entities.values())
            raise InvalidArgument("agent", f"no agent of this name in the recording (agents: {', '.join(names)})",
                                  value=agent)
        if target.kind not in (AIRCRAFT, GROUND):  # no role flies or drives a static site (World.claim's roles)
            raise InvalidArgument("agent", f"is a {KIND_NAMES.get(target.kind, 'static')} agent: no client can take it "
                                           "over (aircraft and ground vehicles only)", value=agent)
        last = rec.tick_at(at_s)
        end_s = take_over_end(rec, scenario, last, at_s, duration_s)
        inputs = RecordedInputs(rec, skip=[target.id], skip_from_tick=last, until=last)
        try:  # known before re-simulating (and recording) when the recorded instant reads
            gone = target.id not in rec.frame(last).ids
        except DataFormatError:
            gone = False
        if gone:
            raise InvalidArgument("agent", f"is gone by t = {at_s} s", value=agent)
        _refuse_wreck(rec, target.id, last, at_s, agent)  # a wreck takes no owner (World.claim)
        if recorder is not None:
            attached = recorder(rec, world, scenario, spec)
            if attached is not None:
                world.attach_recorder(attached)
        while world.tick_count < last:
            inputs.apply(world)
            world.tick()
        if target.id not in world.entities:
            raise InvalidArgument("agent", f"is gone by t = {at_s} s", value=agent)
        if world.is_wreck(target):  # its crash event in a chunk that does not read
            raise InvalidArgument("agent", f"{world.wreck_state(target)} by t = {at_s} s", value=agent)
        if world.recorder is not None:  # an input: a re-simulation of this sortie makes it too
            world.recorder.on_input(world.tick_count, "take_over", target.id,
                                    {"controllable": True, "on_vanish": "autopilot"})
        target.controllable = True
        target.on_vanish = "autopilot"
        if target.owner is not None:  # the recorded client lets go; the agent flies on its autopilot
            world.release(target.id)
        return world, inputs, replace(scenario, exercise=replace(scenario.exercise, duration_s=end_s))
    except BaseException:
        if world is not None:
            world.close()
        if attached is not None:
            attached.close()
        raise
    finally:
        rec.close()


def take_over_end(rec: Recording, scenario, tick: int, at_s: float, duration_s: float | None) -> float | None:
    """World time a take-over at ``tick`` (asked for at ``at_s``) runs to: ``duration_s`` world
    seconds after it when given, else the exercise's end, the later of the scenario's
    duration_s and the recording's last instant (a server run with --duration past the
    scenario's end recorded past it); None: until stopped. InvalidArgument naming
    "take_over" when that leaves no live phase."""
    start = tick * rec.dt
    if duration_s is not None:
        return start + duration_s
    end = scenario.exercise.duration_s
    if end is None:
        return None
    end = max(end, rec.last_time_s)
    if end <= start + 1e-9:
        raise InvalidArgument("take_over", f"leaves no live phase: the exercise ends at t = {end:g} s (the later of "
                                           "the scenario's duration_s and the recording's end); give --duration S "
                                           "to run S world seconds live", value=at_s)
    return end


def _refuse_wreck(rec: Recording, entity_id: int, last: int, at_s: float, agent: str) -> None:
    """InvalidArgument when the recording has ``entity_id`` crashed or destroyed by tick
    ``last``, saying when (the events of chunks that do not read are passed over)."""
    for r in rec.events(skipped=[]):
        if r.tick > last:
            return
        if r.event.entity_id == entity_id and r.event.kind in ("crash", "destroyed"):
            what = "has crashed" if r.event.kind == "crash" else "is destroyed"
            raise InvalidArgument("agent", f"{what} by t = {at_s} s (at t = {r.event.time_s:.2f} s)", value=agent)


def take_over_header(rec: Recording, scenario, world, spec: dict, terrain_given: bool):
    """The RecordingHeader of a take-over of ``rec``: the recorded scenario text and, unless
    the terrain was given (--dem, --terrain), the recorded terrain's identity (the take-over's
    world re-opened that terrain, so a re-simulation of it does as that of ``rec`` does)."""
    from server.recorder import recording_header

    h = rec.header
    desc = f"service:{spec['service']}" if "service" in spec else "dem:" + ",".join(spec.get("dem", ()))
    return recording_header(h.scenario_path, scenario, world, desc, spec, world.terrain, scenario_text=h.scenario_toml,
                            terrain_id=None if terrain_given else h.terrain)
