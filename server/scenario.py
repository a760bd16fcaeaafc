"""The scenario file of the simulation server (``sortie server --scenario FILE``).

A scenario is a TOML file (``.toml``, read with the standard library's
``tomllib``) or the same tables in YAML (``.yaml`` / ``.yml``, read with
PyYAML's safe loader and YAML 1.2's core schema, :func:`scenario_data`); the
file's suffix picks the format. This module only *validates*: it checks every
value, resolves names and paths, and returns frozen dataclasses. It neither
loads DEMs nor builds the world (it checks that DEM files exist, nothing
more). Every failure is a :class:`ScenarioError` (an ``InvalidArgument``)
whose message names the key path and the value, e.g. ``agents[2].lat_deg:
must be within [-90, 90] (got 123.0)``; a TOML or YAML syntax error names its
line and column. Unknown keys are errors everywhere, with a suggestion for
near misses, so a typo never passes silently. Units are SI, angles in
degrees, positions in (lat, lon) order.

YAML gives exactly the scenario its TOML twin gives: a TOML table is a YAML
mapping, an array of tables (``[[agents]]``) a sequence of mappings, and
scalars read as TOML's do (YAML 1.2 core: ``1e3`` is a number; ``yes``, ``no``,
``on`` and ``off`` are strings, only ``true`` / ``false`` are booleans; ``010``
is ten). What TOML cannot say is an error with its line and column, or its key
path: a duplicate key, a key that is not a string, a null value (leave the key
out for its default). A value shaped like a date or date-time that is none
(2026-02-29, hour 24, second 60, an offset of 24 hours) is an error with its
line and column in either format. A leading byte order mark is skipped in
either format.

Schema (``*`` required; everything else has the default shown)::

    [exercise]
    name*                      free text, 1..128 printable characters
    start_time*                ISO 8601 with an offset ("2026-06-15T08:00:00Z", or a TOML
                               offset date-time; RFC 3339's lower-case "t" and "z" too, in
                               either format); stored in UTC. Required: it fixes the sun,
                               the recording's time stamps and replays, so it must never be
                               "now", and no fixed default is given because midnight UTC
                               would silently light the scene for night.
    fdm_rate_hz = 120          integer, [50, 1000]; JSBSim and ground-vehicle steps (50 Hz:
                               fdm.catalog.DT_MAX_S, the longest step the catalog's gear holds)
    world_rate_hz = 30         integer, fdm_rate_hz must be a whole multiple of it (a world
                               tick is fdm_rate_hz / world_rate_hz FDM steps)
    network_rate_hz = 20       (0, world_rate_hz]; state streamed to clients (default: 20, or
                               world_rate_hz when that is lower); a joiner's snapshot, entities
                               coming or going and heartbeats do not wait for it (they go at the
                               next world tick: server/sim_server.py)
    clock = "realtime"         "realtime" | "fast" | "paused" (starts frozen; resumes in real time
                               on SIGUSR1 to `sortie server`, SIGUSR2 pauses any clock)
    time_scale                 simulated seconds per wall second: 1.0 (and only 1.0) for
                               realtime and paused; for fast default 10.0, within (1, 1000]
    duration_s                 optional end of the exercise, (0, 7 days]; absent: until stopped
    vanished_client_timeout_s = 10   (0, 3600]: silence after which a client is gone
    on_vanish = "autopilot"    "autopilot" (its agent returns to its scenario autopilot, or
                               holds heading, altitude and speed) | "remove"

    [terrain]                  exactly one of dem / service
    dem = ["f.hgt", ...]       1..64 DEM files, highest priority first, relative to the
                               scenario file's folder or absolute; .hgt .asc .tif .tiff
                               (raw 16-bit files need a georeference a scenario cannot give)
    service = "host:port"      a running terrain service ("[::1]:50051" for IPv6; the port in
                               ASCII digits)
    geoid_undulation_m = 0.0   N (ellipsoid minus geoid height) for ECEF, |N| <= 120
    insets = false             answer inside the target areas from their high-detail inset
                               data (terrain/inset.py), which clients draw as geomipmaps;
                               with a service, the service must serve them (sortie terrain
                               serve --insets SCENARIO): the server refuses to start, naming
                               terrain.insets, when it serves no inset of a target area's
                               name, polygon and detail_m (server/sim_server.py)

    [agent_types.<name>]       <name> is a kind (aircraft, ground, static, observer) or a
                               type (a JSBSim catalog name, a vehicle type, or the type of a
                               static agent of this scenario; catalog names case-insensitive);
                               a type table overrides its kind's, for every agent of that type.
                               Resolution: built-in kind default < [agent_types.<kind>]
                               < [agent_types.<type>]. Keys, each optional:
        aoi_radius_m           area of interest, [0, 1,000 km]; for observer (0, 1,000 km]: the
                               largest radius an observer may join with (0 for another kind:
                               an agent that sees only itself)
        dr_position_m          dead-reckoning position threshold, (0, 1000]
        dr_orientation_deg     dead-reckoning orientation threshold, (0, 180]
        heartbeat_s            state sent at least this often, (0, 3600]
        dr_algorithm           "RVW" | "FVW" | "FPW" | "RPW" | "STATIC" (DIS dead-reckoning
                               models: Rotating/Fixed orientation, Velocity (with
                               acceleration)/Position (constant velocity), World frame)

                  aoi_radius_m  dr_position_m  dr_orientation_deg  heartbeat_s  dr_algorithm
      aircraft    80 km         1.0            3.0                 5.0          RVW
      ground      10 km         1.0            3.0                 5.0          RVW
      static      50 km         1.0            3.0                 5.0          STATIC
      observer    200 km        1.0            3.0                 5.0          FPW

    Aircraft see (and are seen) far: 80 km is a fighter radar's search range. A
    ground vehicle cares about 10 km (direct-fire and visual range in the
    valleys). A static agent is usually a sensor site (a SAM or radar), 50 km of
    medium-range radar. An observer watches the whole exercise area. Aircraft
    turn and accelerate (RVW); so do ground vehicles on their routes (RVW sent
    fewest bytes at the same error in bench/dr.py: a route's turns are what a
    fixed orientation misses); observer cameras glide (FPW); statics never move.

    [[agents]]                 0..10,000; the order is kept (a convoy: see convoy below)
    name*                      unique, [A-Za-z0-9][A-Za-z0-9_.-]*, at most 64 characters
    kind*                      "aircraft" | "ground" | "static" (observers join as clients)
    type*                      aircraft: JSBSim catalog name (case-insensitive, stored in
                               the catalog's spelling); ground: fdm.vehicle_types name;
                               static: free text like "sam_site" (same rule as names)
    coalition*                 "blue" | "red" | "neutral"
    lat_deg*, lon_deg*         [-90, 90], [-180, 180]
    heading_deg = 0.0          [0, 360), true
    aircraft only:
      on_ground = false        true: at rest on its wheels (no alt_m / alt_ref, speed 0)
      alt_m*                   airborne only; msl: [-500, 100,000] m; agl: (0, 100,000] m
      alt_ref = "msl"          "msl" | "agl"
      speed_mps*               airborne: (0, 8000] true airspeed; on the ground: 0 (default)
      engines_running = true   false: every engine off (an engine-out exercise); airborne, the
                               aircraft starts trimmed in its steady glide at speed_mps, and
                               without an autopilot table it holds only its heading; true
                               on the ground with an engine that does not start, even on its
                               starter, is refused
    ground only:
      speed_mps = 0.0          [0, the vehicle type's top speed]: the speed it starts at, on
                               heading_deg; without an autopilot table it holds that heading
                               and speed (a route's follower takes over its speed)
    aircraft and ground:
      controllable = false     may a pilot / driver session take the agent (opt-in, so a
                               session never takes a bot by accident)
      [agents.autopilot]       optional
        aircraft, one of:      route = [[lat, lon, alt_msl_m], ...] (1..1000) with speed_mps*
                               hold = {heading_deg, alt_msl_m, speed_mps} (at least one)
                               (none: airborne, it holds its start's heading, speed_mps and
                               altitude; alt_ref = "agl" holds the altitude above mean sea
                               level it starts at, the surface under it plus alt_m)
        ground:                route* = [[lat, lon], ...] (2..1000, consecutive points at
                               least 1 mm apart), cruise_mps* (0, type's top speed],
                               convoy = "name" and spacing_m = 50.0 (0, 1000], centre to
                               centre, at least the longest member's length plus the 4 m a
                               driver keeps behind the vehicle ahead (convoy_spacing_min_m):
                               members of a convoy (at least 2) share route, cruise_mps and
                               spacing_m, each keeping its own coalition, controllable and
                               speed_mps; the member farthest along the route leads, the
                               others follow in their order along it (listed order where
                               level); members before the first waypoint are placed along the
                               first leg extended back
    No two agents may start inside each other (their collision shapes overlapping: the world
    tests contacts as they begin, so they would pass through each other); two statics may.
    Checked when the world is built (server/sim_server.py), as is terrain under the agents.

    [[target_areas]]           0..256
    name*                      unique (same rule as agent names)
    polygon*                   [[lat, lon], ...], 3..1000 vertices, closing vertex optional
                               (dropped), a simple polygon: no repeated consecutive vertex,
                               no edge crossing or touching another (1 mm), non-zero area
    detail_m = 5.0             inset post spacing, [0.25, 100] m; the inset (terrain/inset.py:
                               the polygon's bounding box and a margin, in blocks of 64 cells,
                               posts at most detail_m apart: the DEM's, refined by a power of
                               two to between 0.5 and 1 x detail_m where they are coarser)
                               may have at most 4096 x 4096 posts (INSET_MAX_POSTS). Refused
                               here when it cannot over any DEM, by the server (which reads
                               the DEM's lattice) when it does not over the scenario's

Polygons are checked in a local plane around their first vertex (north and
east metres with WGS84 radii of curvature at that latitude, longitude
differences wrapped, so an area may straddle the antimeridian); the bounding
box limit keeps areas far below the size where that plane distorts topology. Edges run
straight in latitude and longitude (as the insets' lattice and the drawn outlines take
them), so an area cannot contain a pole: one whose longitudes wind a full turn is refused.

Limits are the module constants below (``MAX_*``, ``*_MAX_*``, ``*_MIN_*``).
"""

from __future__ import annotations

import difflib
import functools
import math
import re
import sys
import tomllib
from dataclasses import dataclass, field, fields, replace
from datetime import date, datetime, time, timezone
from pathlib import Path
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from fdm import catalog
from fdm.autopilot import TARGET_ALT_MSL_MAX_M, TARGET_ALT_MSL_MIN_M, TARGET_SPEED_MAX_MPS
from fdm.vehicle_types import VEHICLE_TYPES
from sortie.errors import InvalidArgument, NotFound
from terrain.geodesy import geodetic_to_ecef, radii_of_curvature

# --- limits ---------------------------------------------------------------------------------------
MAX_FILE_BYTES = 16 * 1024 * 1024
MAX_AGENTS = 10_000
MAX_ROUTE_POINTS = 1_000
MAX_POLYGON_VERTICES = 1_000
MAX_TARGET_AREAS = 256
MAX_DEM_FILES = 64
MAX_AGENT_TYPES = 512
MAX_NAME_CHARS = 64
MAX_EXERCISE_NAME_CHARS = 128
FDM_RATE_MAX_HZ = 1_000
FDM_RATE_MIN_HZ = math.ceil(1.0 / catalog.DT_MAX_S - 1e-9)  # the aircraft's longest step (50 Hz)
TIME_SCALE_MAX = 1_000.0
DURATION_MAX_S = 7 * 86_400.0
VANISH_TIMEOUT_MAX_S = 3_600.0
GEOID_UNDULATION_ABS_MAX_M = 120.0  # EGM96 spans -107 .. +86 m
# The Dead Sea shore is at -430 m; the Karman line; above orbital speed is a unit mix-up. The
# autopilot's own bounds on its targets (fdm.autopilot), so a scenario, a command and the
# library take the same.
ALT_MSL_MIN_M = TARGET_ALT_MSL_MIN_M
ALT_MAX_M = TARGET_ALT_MSL_MAX_M
SPEED_MAX_MPS = TARGET_SPEED_MAX_MPS
AOI_MAX_M = 1_000_000.0
DR_POSITION_MAX_M = 1_000.0
DR_ORIENTATION_MAX_DEG = 180.0
HEARTBEAT_MAX_S = 3_600.0
CONVOY_SPACING_MAX_M = 1_000.0
WAYPOINT_MIN_SEPARATION_M = 1e-3  # as fdm.convoy.Route requires
DETAIL_MIN_M = 0.25
DETAIL_MAX_M = 100.0
POLYGON_TOUCH_M = 1e-3  # edges closer than this touch

# --- defaults -------------------------------------------------------------------------------------
DEFAULT_FDM_RATE_HZ = 120
DEFAULT_WORLD_RATE_HZ = 30
DEFAULT_NETWORK_RATE_HZ = 20.0
DEFAULT_FAST_TIME_SCALE = 10.0
DEFAULT_VANISH_TIMEOUT_S = 10.0
DEFAULT_CONVOY_SPACING_M = 50.0
DEFAULT_DETAIL_M = 5.0

KINDS = ("aircraft", "ground", "static")
TYPE_KINDS = KINDS + ("observer",)
COALITIONS = ("blue", "red", "neutral")
CLOCKS = ("realtime", "fast", "paused")
ON_VANISH = ("autopilot", "remove")
ALT_REFS = ("msl", "agl")
DR_ALGORITHMS = ("RVW", "FVW", "FPW", "RPW", "STATIC")
DEM_SUFFIXES = (".hgt", ".asc", ".tif", ".tiff")
NAME_PATTERN = re.compile(r"[A-Za-z0-9][A-Za-z0-9_.\-]*")

_REQUIRED = object()


class ScenarioError(InvalidArgument):
    """A scenario value is wrong: ``field`` is its key path (``agents[2].lat_deg``).

    ``file``, ``line`` and ``column`` are set where known (the file by
    :func:`load_scenario`, line and column for TOML and YAML syntax errors).
    """

    def __init__(self, field: str, message: str, value=None, *, file: str | None = None,
                 line: int | None = None, column: int | None = None):
        super().__init__(field, message, value=value)
        self.message = message
        self.file = file
        self.line = line
        self.column = column
        if file is not None:
            self.args = (f"{file}: {self.args[0]}",)

    def __reduce__(self):
        return (functools.partial(ScenarioError, file=self.file, line=self.line, column=self.column),
                (self.field, self.message, self.value))

    def in_file(self, file) -> "ScenarioError":
        """The same error, its message prefixed with the scenario file's name."""
        return ScenarioError(self.field, self.message, self.value, file=str(file), line=self.line,
                             column=self.column)


# --- the scenario ---------------------------------------------------------------------------------

@dataclass(frozen=True)
class Exercise:
    """``[exercise]``: timing and session rules. start_time is timezone-aware UTC."""

    name: str
    start_time: datetime
    fdm_rate_hz: int = DEFAULT_FDM_RATE_HZ
    world_rate_hz: int = DEFAULT_WORLD_RATE_HZ
    network_rate_hz: float = DEFAULT_NETWORK_RATE_HZ
    clock: str = "realtime"
    time_scale: float = 1.0
    duration_s: float | None = None
    vanished_client_timeout_s: float = DEFAULT_VANISH_TIMEOUT_S
    on_vanish: str = "autopilot"

    @property
    def fdm_steps_per_tick(self) -> int:
        """FDM steps in one world tick (fdm_rate_hz is a whole multiple of world_rate_hz)."""
        return self.fdm_rate_hz // self.world_rate_hz


@dataclass(frozen=True)
class TerrainSpec:
    """``[terrain]``: absolute DEM paths (priority order) or a service address, never both."""

    dem: tuple[Path, ...] = ()
    service: str | None = None
    geoid_undulation_m: float = 0.0
    insets: bool = False


@dataclass(frozen=True)
class AgentTypeParams:
    """Network and interest parameters of an agent type (see the module docstring)."""

    aoi_radius_m: float
    dr_position_m: float
    dr_orientation_deg: float
    heartbeat_s: float
    dr_algorithm: str


KIND_DEFAULTS: Mapping[str, AgentTypeParams] = MappingProxyType({
    "aircraft": AgentTypeParams(80_000.0, 1.0, 3.0, 5.0, "RVW"),
    "ground": AgentTypeParams(10_000.0, 1.0, 3.0, 5.0, "RVW"),
    "static": AgentTypeParams(50_000.0, 1.0, 3.0, 5.0, "STATIC"),
    "observer": AgentTypeParams(200_000.0, 1.0, 3.0, 5.0, "FPW"),
})


@dataclass(frozen=True)
class WaypointRoute:
    """Aircraft autopilot: fly (lat, lon, alt_msl_m) waypoints at speed_mps
    (for :class:`fdm.autopilot.WaypointFollower`)."""

    waypoints: tuple[tuple[float, float, float], ...]
    speed_mps: float


@dataclass(frozen=True)
class Hold:
    """Aircraft autopilot: hold these (for :class:`fdm.autopilot.Targets`); None leaves an axis alone."""

    heading_deg: float | None = None
    alt_msl_m: float | None = None
    speed_mps: float | None = None


@dataclass(frozen=True)
class GroundRoute:
    """Ground autopilot: follow (lat, lon) points at cruise_mps (:class:`fdm.convoy.Route`),
    alone or as a member of ``convoy`` keeping ``spacing_m`` (None when alone)."""

    points: tuple[tuple[float, float], ...]
    cruise_mps: float
    convoy: str | None = None
    spacing_m: float | None = None


@dataclass(frozen=True)
class Agent:
    """One ``[[agents]]`` entry. alt_m/alt_ref/on_ground matter for aircraft only."""

    name: str
    kind: str
    type: str
    coalition: str
    lat_deg: float
    lon_deg: float
    heading_deg: float = 0.0
    speed_mps: float = 0.0
    alt_m: float | None = None
    alt_ref: str = "msl"
    on_ground: bool = False
    engines_running: bool = True
    controllable: bool = False
    autopilot: WaypointRoute | Hold | GroundRoute | None = None

    def initial_conditions(self):
        """The :class:`fdm.aircraft.InitialConditions` of an aircraft agent."""
        if self.kind != "aircraft":
            raise InvalidArgument("kind", "initial conditions are for aircraft", value=self.kind)
        from fdm.aircraft import InitialConditions

        return InitialConditions(self.lat_deg, self.lon_deg, self.alt_m or 0.0, self.alt_ref, self.heading_deg,
                                 self.speed_mps, on_ground=self.on_ground, engines_running=self.engines_running)


@dataclass(frozen=True)
class ConvoySpec:
    """Ground agents in column: members[0] leads (scenario order), all on one route."""

    name: str
    members: tuple[str, ...]
    points: tuple[tuple[float, float], ...]
    cruise_mps: float
    spacing_m: float


@dataclass(frozen=True)
class TargetArea:
    """A high-detail inset: a simple polygon of (lat, lon) vertices (open: no closing
    vertex), inset posts every detail_m metres."""

    name: str
    polygon: tuple[tuple[float, float], ...]
    detail_m: float = DEFAULT_DETAIL_M


@dataclass(frozen=True)
class Scenario:
    """A validated scenario; agent parameters resolve through :meth:`agent_type`."""

    exercise: Exercise
    terrain: TerrainSpec
    agents: tuple[Agent, ...]
    convoys: tuple[ConvoySpec, ...]
    target_areas: tuple[TargetArea, ...]
    kind_params: dict[str, AgentTypeParams]  # every kind of TYPE_KINDS, resolved; read-only
    type_overrides: dict[str, dict[str, Any]]  # [agent_types.<type>] as given; read-only
    base_dir: Path
    # The file it was loaded from (load_scenario): errors found later name it. Not part of its value.
    file: str | None = field(default=None, compare=False)

    def type_params(self, kind: str, type_name: str | None = None) -> AgentTypeParams:
        """Parameters of ``type_name`` of ``kind``: kind defaults < kind table < type table."""
        if kind not in self.kind_params:
            raise InvalidArgument("kind", f"must be one of {', '.join(TYPE_KINDS)}", value=kind)
        return replace(self.kind_params[kind], **self.type_overrides.get(type_name, {}))

    def in_file(self, error: ScenarioError) -> ScenarioError:
        """``error`` (found after loading: building the terrain or the world) prefixed with the
        scenario file's name, as :func:`load_scenario`'s own are; as it is without a file."""
        return error if self.file is None else error.in_file(self.file)

    def agent_type(self, agent: Agent) -> AgentTypeParams:
        """The resolved parameters of one agent (its type's table over its kind's)."""
        return self.type_params(agent.kind, agent.type)

    def agent(self, name: str) -> Agent:
        """The agent called ``name``; NotFound if there is none."""
        for a in self.agents:
            if a.name == name:
                return a
        raise NotFound(f"agent {name!r} is not in the scenario")


# --- entry points ---------------------------------------------------------------------------------

def load_scenario(path, option: str = "--scenario") -> Scenario:
    """Read and validate the scenario at ``path`` (see the module docstring): TOML for a
    ``.toml`` file, YAML for ``.yaml`` / ``.yml``.

    Raises NotFound when the file does not exist, ScenarioError naming ``option`` (the
    command-line option that gave the path) for any other suffix, and ScenarioError
    (message prefixed with the file name) for anything wrong inside it.
    """
    path = Path(path)
    scenario_format(path, option)
    if not path.is_file():
        raise NotFound(f"scenario file {str(path)!r} does not exist")
    size = path.stat().st_size
    if size > MAX_FILE_BYTES:
        raise ScenarioError("file", f"must be at most {MAX_FILE_BYTES} bytes", value=size, file=str(path))
    try:
        text = path.read_bytes().decode("utf-8")
    except UnicodeDecodeError as e:
        raise ScenarioError("file", f"is not UTF-8 text (byte {e.start})", file=str(path)) from None
    try:
        scenario = parse_scenario(scenario_data(text, path), path.resolve().parent)
    except ScenarioError as e:
        raise e.in_file(path) from None
    return replace(scenario, file=str(path))


SCENARIO_FORMATS = MappingProxyType({".toml": "TOML", ".yaml": "YAML", ".yml": "YAML"})


def scenario_format(path, option: str = "--scenario") -> str:
    """"TOML" or "YAML", by the suffix of ``path`` (case-insensitive); any other suffix is a
    ScenarioError naming ``option``."""
    fmt = SCENARIO_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise ScenarioError(option, f"must name a scenario file ending in {', '.join(SCENARIO_FORMATS)} (the "
                                    "suffix picks TOML or YAML)", value=str(path))
    return fmt


def scenario_data(text: str, path) -> dict:
    """The tables of a scenario file's ``text``, for :func:`parse_scenario`: YAML when
    ``path`` ends in .yaml / .yml, TOML otherwise (a recording keeps the text and the
    path it was read from; server/resim.py). A syntax error is a ScenarioError naming
    the line and column (no file name: :func:`load_scenario` adds it). A leading byte
    order mark is no part of the text (Unicode 15.0 section 23.8: U+FEFF at the start of
    a stream is a signature, not content; PyYAML skips it, tomllib refuses it, and editors
    on Windows write it)."""
    text = text.removeprefix("\ufeff")
    if SCENARIO_FORMATS.get(Path(path).suffix.lower()) != "YAML":
        try:
            return tomllib.loads(text)
        except tomllib.TOMLDecodeError as e:
            raise _syntax_error(e) from None
        except RecursionError:  # tomllib parses nested arrays and inline tables recursively
            raise ScenarioError("file", "TOML syntax error: nested too deeply") from None
        except ValueError:  # int() refusing an integer of more than sys.get_int_max_str_digits() digits
            raise _long_integer(text) from None
    return _yaml_data(text)


def _long_integer(text: str) -> ScenarioError:
    """The error of a TOML integer longer than Python converts (sys.get_int_max_str_digits(),
    4300 by default: tomllib raises a bare ValueError without its place): the first such run
    of digits, with its line, column and the key on that line where there is one."""
    limit = sys.get_int_max_str_digits()
    for m in re.finditer(r"\d(?:_?\d)*", text):
        digits = len(m.group()) - m.group().count("_")
        if digits > limit:
            line = text.count("\n", 0, m.start()) + 1
            column = m.start() - text.rfind("\n", 0, m.start())
            key = re.match(r"\s*([A-Za-z0-9_.\-\"']+)\s*=", text[m.start() - column + 1:m.start()])
            what = f"{key.group(1)} is an integer" if key else "an integer"
            return ScenarioError(f"line {line}, column {column}", f"TOML value error: {what} of {digits} digits "
                                 f"(at most {limit})", line=line, column=column)
    return ScenarioError("file", f"TOML value error: an integer of more than {limit} digits")


def _syntax_error(error: tomllib.TOMLDecodeError) -> ScenarioError:
    text = str(error)
    m = re.search(r"\(at line (\d+), column (\d+)\)$", text)
    if m:
        line, column = int(m.group(1)), int(m.group(2))
        where, reason = f"line {line}, column {column}", text[:m.start()].strip()
    else:
        line = column = None
        where, reason = "end of file", re.sub(r"\s*\(at end of document\)$", "", text)
    return ScenarioError(where, f"TOML syntax error: {reason}", line=line, column=column)


@functools.cache
def _yaml_loader():
    """PyYAML's safe loader (its C parser where built) with YAML 1.2's core schema, so a
    scalar reads as TOML reads it, refusing duplicate and non-string keys."""
    import yaml
    from yaml.constructor import ConstructorError

    base = getattr(yaml, "CSafeLoader", yaml.SafeLoader)

    class Loader(base):
        yaml_implicit_resolvers: dict = {}

        def construct_mapping(self, node, deep=False):
            if isinstance(node, yaml.MappingNode):
                seen = set()
                for key_node, _ in node.value:
                    if key_node.tag == "tag:yaml.org,2002:merge":
                        continue
                    key = self.construct_object(key_node, deep=True)
                    if not isinstance(key, str):
                        raise ConstructorError("while reading a mapping", node.start_mark,
                                               f"found a key that is not a string ({key!r}; quote it)",
                                               key_node.start_mark)
                    if key in seen:
                        raise ConstructorError("while reading a mapping", node.start_mark,
                                               f"found the key {key!r} twice", key_node.start_mark)
                    seen.add(key)
            return super().construct_mapping(node, deep)

        def construct_core_int(self, node):
            text = self.construct_scalar(node)
            if text.startswith(("0o", "0x")):
                return int(text[2:], 8 if text[1] == "o" else 16)
            try:
                return int(text, 10)
            except ValueError:  # more digits than sys.get_int_max_str_digits() (4300 by default)
                raise ConstructorError(None, None, f"found an integer of {len(text.lstrip('+-'))} digits (at most "
                                                   f"{sys.get_int_max_str_digits()})", node.start_mark) from None

        def construct_checked_timestamp(self, node):
            """PyYAML's timestamp, or a YAML error at its place where the text has a date's or a
            date-time's shape but is none (2026-02-29, hour 24, second 60, an offset beyond
            RFC 3339's: PyYAML lets the datetime module's bare ValueError out, or reads offset
            minutes past 59 as hours); TOML refuses each of them."""
            parts = _YAML_TIMESTAMP_PARTS.match(node.value)
            why = _offset_problem(parts["tz_hour"], parts["tz_minute"]) if parts else None
            if why is None:
                try:
                    return self.construct_yaml_timestamp(node)
                except (ValueError, OverflowError) as e:
                    why = str(e)
            raise ConstructorError(None, None, f"found {node.value!r}, which has the shape of a date or date-time "
                                               f"but is none ({why}; quote it if it is text)", node.start_mark)

    resolvers = (
        ("null", r"~|null|Null|NULL|", "~nN"),
        ("bool", r"true|True|TRUE|false|False|FALSE", "tTfF"),
        ("int", r"[-+]?[0-9]+|0o[0-7]+|0x[0-9a-fA-F]+", "-+0123456789"),
        ("float", r"[-+]?(?:\.[0-9]+|[0-9]+(?:\.[0-9]*)?)(?:[eE][-+]?[0-9]+)?|[-+]?\.(?:inf|Inf|INF)"
                  r"|\.(?:nan|NaN|NAN)", "-+0123456789."),
        ("merge", r"<<", "<"),
    )
    for tag, pattern, first in resolvers:
        Loader.add_implicit_resolver(f"tag:yaml.org,2002:{tag}", re.compile(f"^(?:{pattern})$"), list(first))
    Loader.add_implicit_resolver("tag:yaml.org,2002:null", re.compile("^$"), [""])
    Loader.add_implicit_resolver("tag:yaml.org,2002:timestamp", _YAML_TIMESTAMP, list("0123456789"))
    Loader.timestamp_regexp = _YAML_TIMESTAMP_PARTS  # what PyYAML's timestamp constructor reads
    Loader.add_constructor("tag:yaml.org,2002:int", Loader.construct_core_int)
    Loader.add_constructor("tag:yaml.org,2002:timestamp", Loader.construct_checked_timestamp)
    return Loader


# YAML's timestamps (https://yaml.org/type/timestamp.html, as PyYAML resolves and reads them), so
# date-times read as TOML's do, with RFC 3339's lower-case "z" for UTC too (section 5.6; TOML
# reads 2026-03-01t00:00:00z as a date-time, PyYAML's pattern only an upper-case Z).
_YAML_TIMESTAMP = re.compile(r"""^(?:[0-9]{4}-[0-9]{2}-[0-9]{2}
    |[0-9]{4}-[0-9]{1,2}-[0-9]{1,2}(?:[Tt]|[ \t]+)[0-9]{1,2}:[0-9]{2}:[0-9]{2}(?:\.[0-9]*)?
     (?:[ \t]*(?:[Zz]|[-+][0-9]{1,2}(?::[0-9]{2})?))?)$""", re.X)
_YAML_TIMESTAMP_PARTS = re.compile(r"""^(?P<year>[0-9]{4})-(?P<month>[0-9]{1,2})-(?P<day>[0-9]{1,2})
    (?:(?:[Tt]|[ \t]+)(?P<hour>[0-9]{1,2}):(?P<minute>[0-9]{2}):(?P<second>[0-9]{2})(?:\.(?P<fraction>[0-9]*))?
     (?:[ \t]*(?P<tz>[Zz]|(?P<tz_sign>[-+])(?P<tz_hour>[0-9]{1,2})(?::(?P<tz_minute>[0-9]{2}))?))?)?$""", re.X)


def _offset_problem(hour: str | None, minute: str | None) -> str | None:
    """What is wrong with a UTC offset's hours and minutes (text, None where absent), or None:
    RFC 3339 section 5.6's time-numoffset has hours 00-23 and minutes 00-59."""
    if hour is not None and int(hour) > 23:
        return "a UTC offset's hours must be in 0..23"
    if minute is not None and int(minute) > 59:
        return "a UTC offset's minutes must be in 0..59"
    return None


def _yaml_data(text: str) -> dict:
    """A YAML scenario's tables (an empty document is an empty table, as in TOML); a
    syntax error, a duplicate or non-string key a ScenarioError with line and column,
    a null value one with its key path."""
    import yaml

    try:
        data = yaml.load(text, Loader=_yaml_loader())  # noqa: S506 - a safe loader
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark or e.context_mark
        reason = "; ".join(str(x) for x in (e.context, e.problem) if x)
        if mark is None:
            raise ScenarioError("end of file", f"YAML syntax error: {reason}") from None
        line, column = mark.line + 1, mark.column + 1
        raise ScenarioError(f"line {line}, column {column}", f"YAML syntax error: {reason}", line=line,
                            column=column) from None
    except yaml.YAMLError as e:
        raise ScenarioError("file", f"YAML syntax error: {e}") from None
    except RecursionError:
        raise ScenarioError("file", "YAML syntax error: nested too deeply") from None
    if data is None:
        return {}
    _check_no_nulls(data)
    return data


def _check_no_nulls(data) -> None:
    """TOML has no null: a YAML null anywhere is an error at its key path."""
    stack, seen = [("", data)], set()
    while stack:
        path, value = stack.pop()
        if value is None:
            raise ScenarioError(path or "scenario", "has no value (YAML null): give one, or leave the key out for "
                                                    "its default")
        if isinstance(value, dict) and id(value) not in seen:  # aliases: one visit each
            seen.add(id(value))
            stack.extend(reversed([(f"{path}.{k}" if path else k, v) for k, v in value.items()]))
        elif isinstance(value, list) and id(value) not in seen:
            seen.add(id(value))
            stack.extend(reversed([(f"{path}[{i}]", v) for i, v in enumerate(value)]))


def parse_scenario(data: Mapping, base_dir) -> Scenario:
    """Validate a scenario already parsed (:func:`scenario_data`); DEM paths are relative to ``base_dir``."""
    top = _Table(data, "", ("exercise", "terrain", "agent_types", "agents", "target_areas"))
    base_dir = Path(base_dir)
    exercise = _exercise(top.table("exercise"))
    terrain = _terrain(top.table("terrain"), base_dir)
    agents = tuple(_agent(t) for t in top.tables("agents", MAX_AGENTS))
    _unique([a.name for a in agents], "agents")
    convoys = _convoys(agents)
    kind_params, overrides = _agent_types(top.table("agent_types", {}), agents)
    areas = tuple(_target_area(t) for t in top.tables("target_areas", MAX_TARGET_AREAS))
    _unique([a.name for a in areas], "target_areas")
    return Scenario(exercise, terrain, agents, convoys, areas, kind_params, overrides, base_dir)


# --- reading tables -------------------------------------------------------------------------------

class _Table:
    """One TOML table at a key path, with typed getters; unknown keys fail at construction."""

    def __init__(self, value, path: str, allowed, elsewhere: Mapping[str, str] | None = None):
        if not isinstance(value, dict):
            raise ScenarioError(path or "scenario", "must be a table", value=_shown(value))
        self.data = value
        self.path = path
        for key in value:
            if key not in allowed:
                raise ScenarioError(self.key(key), _unknown_key(key, allowed, (elsewhere or {}).get(key)))

    def key(self, key: str) -> str:
        return f"{self.path}.{key}" if self.path else key

    def raw(self, key: str, default=_REQUIRED):
        if key in self.data:
            return self.data[key]
        if default is _REQUIRED:
            raise ScenarioError(self.key(key), "is required")
        return default

    def table(self, key: str, default=_REQUIRED) -> dict:
        value = self.raw(key, default)
        if not isinstance(value, dict):
            raise ScenarioError(self.key(key), "must be a table", value=_shown(value))
        return value

    def tables(self, key: str, limit: int):
        """(key path, table) of each entry of an array of tables."""
        value = self.raw(key, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise ScenarioError(self.key(key), f"must be an array of tables ([[{key}]])", value=_shown(value))
        if len(value) > limit:
            raise ScenarioError(self.key(key), f"at most {limit} entries", value=len(value))
        return [(f"{self.key(key)}[{i}]", v) for i, v in enumerate(value)]

    def number(self, key: str, default=_REQUIRED, **bounds) -> float:
        value = self.raw(key, default)
        return value if value is None else _number(value, self.key(key), **bounds)

    def integer(self, key: str, default=_REQUIRED, lo=None, hi=None) -> int:
        path = self.key(key)
        value = self.raw(key, default)
        if isinstance(value, float) and value.is_integer():
            value = int(value)
        if isinstance(value, bool) or not isinstance(value, int):
            raise ScenarioError(path, "must be a whole number", value=_shown(value))
        _check_range(value, path, lo, hi)
        return value

    def boolean(self, key: str, default=_REQUIRED) -> bool:
        value = self.raw(key, default)
        if not isinstance(value, bool):
            raise ScenarioError(self.key(key), "must be true or false", value=_shown(value))
        return value

    def string(self, key: str, default=_REQUIRED, choices=None, name: bool = False) -> str | None:
        value = self.raw(key, default)
        if value is None:
            return None
        path = self.key(key)
        if not isinstance(value, str):
            raise ScenarioError(path, "must be a string", value=_shown(value))
        if choices is not None and value not in choices:
            raise ScenarioError(path, f"must be one of {', '.join(map(repr, choices))}", value=value)
        if name:
            _check_name(value, path)
        return value


def _unknown_key(key: str, allowed, elsewhere: str | None) -> str:
    if elsewhere:
        return f"unknown key here ({elsewhere})"
    close = difflib.get_close_matches(key, list(allowed), n=1)
    hint = f"; did you mean {close[0]!r}?" if close else f"; expected one of {', '.join(sorted(allowed))}"
    return "unknown key" + hint


def _shown(value):
    """A value as an error message shows it (dates as ISO text, long lists shortened)."""
    if isinstance(value, (datetime, date, time)):
        return value.isoformat()
    if isinstance(value, (list, dict)) and len(value) > 8:
        return f"{type(value).__name__} of {len(value)} entries"
    return value


def _fmt(x: float) -> str:
    return str(int(x)) if float(x).is_integer() and abs(x) < 1e15 else f"{x:.6g}"


def _number(value, path: str, lo=None, hi=None, lo_open=False, hi_open=False) -> float:
    """A finite float within the bounds (either may be open); ints are accepted, bools not."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ScenarioError(path, "must be a number", value=_shown(value))
    try:
        value = float(value)
    except OverflowError:  # a whole number beyond float's range (TOML and YAML integers have none)
        value = math.inf if value > 0 else -math.inf
    if not math.isfinite(value):
        raise ScenarioError(path, "must be a finite number", value=value)
    _check_range(value, path, lo, hi, lo_open, hi_open)
    return value


def _check_range(value, path, lo=None, hi=None, lo_open=False, hi_open=False) -> None:
    below = lo is not None and (value <= lo if lo_open else value < lo)
    above = hi is not None and (value >= hi if hi_open else value > hi)
    if not (below or above):
        return
    if hi is None:
        raise ScenarioError(path, f"must be {'>' if lo_open else '>='} {_fmt(lo)}", value=value)
    if lo is None:
        raise ScenarioError(path, f"must be {'<' if hi_open else '<='} {_fmt(hi)}", value=value)
    span = f"{'(' if lo_open else '['}{_fmt(lo)}, {_fmt(hi)}{')' if hi_open else ']'}"
    raise ScenarioError(path, f"must be within {span}", value=value)


def _check_name(value: str, path: str) -> None:
    if len(value) > MAX_NAME_CHARS or not NAME_PATTERN.fullmatch(value):
        raise ScenarioError(path, f"must be 1..{MAX_NAME_CHARS} characters: a letter or digit, then letters, "
                                  "digits, '_', '.' or '-'", value=value)


def _unique(names, path: str) -> None:
    first: dict[str, int] = {}
    for i, n in enumerate(names):
        if n in first:
            raise ScenarioError(f"{path}[{i}].name", f"duplicates {path}[{first[n]}].name", value=n)
        first[n] = i


_POINT_PARTS = (("lat", -90.0, 90.0), ("lon", -180.0, 180.0), ("alt_msl_m", ALT_MSL_MIN_M, ALT_MAX_M))


def _latlon(point, path: str, width: int = 2) -> tuple:
    """A [lat, lon] or [lat, lon, alt_msl_m] array, checked; returns floats."""
    if not isinstance(point, list) or len(point) != width:
        raise ScenarioError(path, f"must be [{', '.join(n for n, _, _ in _POINT_PARTS[:width])}]",
                            value=_shown(point))
    out = []
    for value, (label, lo, hi) in zip(point, _POINT_PARTS):
        try:
            out.append(_number(value, path, lo, hi))
        except ScenarioError as e:
            raise ScenarioError(path, f"{label} {e.message}", value=e.value) from None
    return tuple(out)


def _points(value, path: str, width: int, least: int, limit: int, what: str) -> list[tuple]:
    if not isinstance(value, list):
        raise ScenarioError(path, f"must be an array of {what}", value=_shown(value))
    if not least <= len(value) <= limit:
        raise ScenarioError(path, f"must have {least}..{limit} {what}", value=len(value))
    return [_latlon(p, f"{path}[{i}]", width) for i, p in enumerate(value)]


# --- [exercise] and [terrain] ---------------------------------------------------------------------

_EXERCISE_KEYS = ("name", "start_time", "fdm_rate_hz", "world_rate_hz", "network_rate_hz", "clock", "time_scale",
                  "duration_s", "vanished_client_timeout_s", "on_vanish")


def _exercise(value) -> Exercise:
    t = _Table(value, "exercise", _EXERCISE_KEYS)
    name = t.string("name")
    if not 1 <= len(name) <= MAX_EXERCISE_NAME_CHARS or not name.isprintable():
        raise ScenarioError(t.key("name"), f"must be 1..{MAX_EXERCISE_NAME_CHARS} printable characters", value=name)
    fdm = t.integer("fdm_rate_hz", DEFAULT_FDM_RATE_HZ, FDM_RATE_MIN_HZ, FDM_RATE_MAX_HZ)
    world = t.integer("world_rate_hz", DEFAULT_WORLD_RATE_HZ, 1, fdm)
    if fdm % world:
        raise ScenarioError(t.key("fdm_rate_hz"), f"must be a whole multiple of world_rate_hz ({world})", value=fdm)
    clock = t.string("clock", "realtime", CLOCKS)
    if clock == "fast":
        scale = t.number("time_scale", DEFAULT_FAST_TIME_SCALE, lo=1.0, hi=TIME_SCALE_MAX, lo_open=True)
    else:
        scale = t.number("time_scale", 1.0)
        if scale != 1.0:
            raise ScenarioError(t.key("time_scale"), f'must be 1.0 with clock = "{clock}" (use clock = "fast")',
                                value=scale)
    return Exercise(
        name=name, start_time=_start_time(t.raw("start_time"), t.key("start_time")), fdm_rate_hz=fdm,
        world_rate_hz=world,
        network_rate_hz=t.number("network_rate_hz", min(DEFAULT_NETWORK_RATE_HZ, float(world)), lo=0.0,
                                 hi=float(world), lo_open=True),  # the default no faster than the world
        clock=clock, time_scale=scale,
        duration_s=t.number("duration_s", None, lo=0.0, hi=DURATION_MAX_S, lo_open=True),
        vanished_client_timeout_s=t.number("vanished_client_timeout_s", DEFAULT_VANISH_TIMEOUT_S, lo=0.0,
                                           hi=VANISH_TIMEOUT_MAX_S, lo_open=True),
        on_vanish=t.string("on_vanish", "autopilot", ON_VANISH))


def _start_time(value, path: str) -> datetime:
    """An aware datetime in UTC from a TOML offset date-time or an ISO 8601 / RFC 3339
    string (its "T" and "Z" in either case)."""
    if isinstance(value, str):
        try:
            parsed = datetime.fromisoformat(_upper_t_z(value))
        except ValueError:
            raise ScenarioError(path, 'must be an ISO 8601 date-time like "2026-06-15T08:00:00Z"',
                                value=value) from None
    elif isinstance(value, datetime):
        parsed = value
    else:
        raise ScenarioError(path, 'must be an ISO 8601 date-time like "2026-06-15T08:00:00Z"', value=_shown(value))
    if parsed.tzinfo is None or parsed.utcoffset() is None:
        raise ScenarioError(path, "needs a UTC offset (end it with Z for UTC)", value=_shown(value))
    try:
        return parsed.astimezone(timezone.utc)
    except OverflowError:  # 9999-12-31T23:59:59-05:00 is in year 10000 UTC
        raise ScenarioError(path, "must be within years 1..9999 in UTC (its offset takes it past them)",
                            value=_shown(value)) from None


_RFC3339_DATE_TIME = re.compile(r"(?P<date>\d{4}-\d\d-\d\d)(?P<sep>[Tt ])(?P<time>\d\d:\d\d:\d\d(?:\.\d+)?)"
                                r"(?P<offset>[Zz]|[+-]\d\d:\d\d)", re.ASCII)


def _upper_t_z(text: str) -> str:
    """An RFC 3339 date-time's text with its date-time separator and UTC designator in upper
    case (section 5.6: "T" and "Z" "may alternatively be lower case"; TOML's offset date-times
    are RFC 3339's, and tomllib reads them so, but datetime.fromisoformat takes only upper
    case); any other text as it is."""
    m = _RFC3339_DATE_TIME.fullmatch(text)
    return text if m is None else f"{m['date']}{m['sep'].upper()}{m['time']}{m['offset'].upper()}"


def _terrain(value, base_dir: Path) -> TerrainSpec:
    t = _Table(value, "terrain", ("dem", "service", "geoid_undulation_m", "insets"))
    if ("dem" in value) == ("service" in value):
        raise ScenarioError("terrain", "give exactly one of dem = [files] or service = \"host:port\"",
                            value=sorted(value))
    undulation = t.number("geoid_undulation_m", 0.0, lo=-GEOID_UNDULATION_ABS_MAX_M, hi=GEOID_UNDULATION_ABS_MAX_M)
    insets = t.boolean("insets", False)
    if "service" in value:
        return TerrainSpec(service=service_address(t.string("service"), t.key("service")),
                           geoid_undulation_m=undulation, insets=insets)
    files = t.raw("dem")
    if not isinstance(files, list) or not files:
        raise ScenarioError(t.key("dem"), "must be a non-empty array of file paths", value=_shown(files))
    if len(files) > MAX_DEM_FILES:
        raise ScenarioError(t.key("dem"), f"at most {MAX_DEM_FILES} files", value=len(files))
    return TerrainSpec(dem=tuple(_dem_path(f, f"terrain.dem[{i}]", base_dir) for i, f in enumerate(files)),
                       geoid_undulation_m=undulation, insets=insets)


def _dem_path(value, path: str, base_dir: Path) -> Path:
    if not isinstance(value, str) or not value:
        raise ScenarioError(path, "must be a file path", value=_shown(value))
    if Path(value).suffix.lower() not in DEM_SUFFIXES:
        raise ScenarioError(path, f"must be a DEM file ({', '.join(DEM_SUFFIXES)})", value=value)
    full = (base_dir / value).resolve()
    if not full.is_file():
        raise ScenarioError(path, f"no such file ({full})", value=value)
    return full


def service_address(value: str, path: str) -> str:
    """ "host:port", or a comma list of them (replicas of one terrain service:
    client/terrain_client.py); a ScenarioError at ``path`` otherwise. Also `sortie server
    --terrain`'s check (server/sim_cli.py): gRPC keeps a port's low 16 bits, so port 99999
    would reach whatever serves 34463."""
    for entry in value.split(","):
        host, sep, port = entry.strip().rpartition(":")
        bare = host[1:-1] if host.startswith("[") and host.endswith("]") else host
        unbracketed_ipv6 = ":" in host and bare == host
        # ASCII digits only: str.isdigit() takes "²" and "１２３" too, which int() refuses or a
        # socket never sees (as server/health_cli.py checks a port).
        if (not sep or not bare or unbracketed_ipv6 or not (port.isascii() and port.isdigit())
                or not 1 <= int(port) <= 65535):
            raise ScenarioError(path, 'must be "host:port" with a port in [1, 65535] ("[::1]:50051" for IPv6), '
                                      'or a comma list of them (replicas)', value=value)
    return value


# --- [agent_types] ----------------------------------------------------------------------------------

_PARAM_KEYS = tuple(f.name for f in fields(AgentTypeParams))


def _agent_types(value: dict, agents) -> tuple[dict, dict]:
    t = _Table(value, "agent_types", value.keys())
    if len(t.data) > MAX_AGENT_TYPES:
        raise ScenarioError("agent_types", f"at most {MAX_AGENT_TYPES} tables", value=len(t.data))
    static_types = {a.type for a in agents if a.kind == "static"}
    kind_params = dict(KIND_DEFAULTS)
    overrides: dict[str, dict] = {}
    spelled: dict[str, str] = {}
    for key, table in t.data.items():
        path = t.key(key)
        given = _type_params(table, path)
        if key == "observer" and given.get("aoi_radius_m") == 0.0:
            # An observer's area is the largest radius it may join with (Sessions.join takes
            # (0, this]): 0 would shut every observer out. Other kinds may see only themselves.
            raise ScenarioError(f"{path}.aoi_radius_m", f"must be within (0, {_fmt(AOI_MAX_M)}] for observers (it "
                                                        "is the largest radius an observer may join with, so 0 "
                                                        "would let none join)", value=given["aoi_radius_m"])
        if key in TYPE_KINDS:
            kind_params[key] = replace(kind_params[key], **given)
            continue
        name = _type_name(key, path, static_types)
        if name in overrides:
            raise ScenarioError(path, f"names the same type ({name}) as agent_types.{spelled[name]}", value=key)
        overrides[name] = given
        spelled[name] = key
    return kind_params, overrides


def _type_params(value, path: str) -> dict:
    t = _Table(value, path, _PARAM_KEYS)
    bounds = {"aoi_radius_m": (0.0, AOI_MAX_M, False), "dr_position_m": (0.0, DR_POSITION_MAX_M, True),
              "dr_orientation_deg": (0.0, DR_ORIENTATION_MAX_DEG, True), "heartbeat_s": (0.0, HEARTBEAT_MAX_S, True)}
    given = {k: t.number(k, lo=lo, hi=hi, lo_open=lo_open) for k, (lo, hi, lo_open) in bounds.items() if k in value}
    if "dr_algorithm" in value:
        given["dr_algorithm"] = t.string("dr_algorithm", choices=DR_ALGORITHMS)
    return given


def _type_name(key: str, path: str, static_types) -> str:
    """The canonical spelling of a type table's name; it must name a type that can exist."""
    if key in VEHICLE_TYPES or key in static_types:
        return key
    try:
        return catalog.resolve(key)
    except NotFound as e:
        raise ScenarioError(path, f"is neither a kind ({', '.join(TYPE_KINDS)}), a vehicle type "
                                  f"({', '.join(sorted(VEHICLE_TYPES))}), a static agent's type, nor an aircraft: "
                                  f"{e}", value=key) from None


# --- [[agents]] -------------------------------------------------------------------------------------

_COMMON_KEYS = ("name", "kind", "type", "coalition", "lat_deg", "lon_deg", "heading_deg")
_AGENT_KEYS = {
    "aircraft": _COMMON_KEYS + ("alt_m", "alt_ref", "speed_mps", "on_ground", "engines_running", "controllable",
                              "autopilot"),
    "ground": _COMMON_KEYS + ("speed_mps", "controllable", "autopilot"),
    "static": _COMMON_KEYS,
}


def _agent(entry) -> Agent:
    path, value = entry
    kind = _Table(value, path, value.keys()).string("kind", choices=KINDS)
    elsewhere = {k: f"only for {' and '.join(n for n in KINDS if k in _AGENT_KEYS[n])} agents, not {kind}"
                 for k in set().union(*_AGENT_KEYS.values()) - set(_AGENT_KEYS[kind])}
    t = _Table(value, path, _AGENT_KEYS[kind], elsewhere)
    common = dict(name=t.string("name", name=True), kind=kind, coalition=t.string("coalition", choices=COALITIONS),
                  lat_deg=t.number("lat_deg", lo=-90.0, hi=90.0), lon_deg=t.number("lon_deg", lo=-180.0, hi=180.0),
                  heading_deg=t.number("heading_deg", 0.0, lo=0.0, hi=360.0, hi_open=True))
    if kind == "aircraft":
        return _aircraft(t, common)
    if kind == "ground":
        return _ground(t, common)
    type_name = t.string("type", name=True)
    if type_name in TYPE_KINDS:
        raise ScenarioError(t.key("type"), "a static type must not be a kind's name", value=type_name)
    return Agent(type=type_name, **common)


def _aircraft(t: _Table, common: dict) -> Agent:
    type_path = t.key("type")
    try:
        type_name = catalog.resolve(t.string("type"))
    except NotFound as e:
        raise ScenarioError(type_path, str(e), value=t.data["type"]) from None
    on_ground = t.boolean("on_ground", False)
    if on_ground:
        for key in ("alt_m", "alt_ref"):
            if key in t.data:
                raise ScenarioError(t.key(key), "must be left out when on_ground = true (the aircraft rests on "
                                                "its wheels)", value=t.data[key])
        speed = t.number("speed_mps", 0.0)
        if speed != 0.0:
            raise ScenarioError(t.key("speed_mps"), "must be 0 when on_ground = true (it starts at rest)",
                                value=speed)
        alt, alt_ref = None, "msl"
    else:
        alt_ref = t.string("alt_ref", "msl", ALT_REFS)
        lo = (0.0, True) if alt_ref == "agl" else (ALT_MSL_MIN_M, False)
        alt = t.number("alt_m", lo=lo[0], lo_open=lo[1], hi=ALT_MAX_M)
        speed = t.number("speed_mps", lo=0.0, lo_open=True, hi=SPEED_MAX_MPS)
    autopilot = _aircraft_autopilot(t.table("autopilot"), t.key("autopilot")) if "autopilot" in t.data else None
    return Agent(type=type_name, speed_mps=speed, alt_m=alt, alt_ref=alt_ref, on_ground=on_ground,
                 engines_running=t.boolean("engines_running", True), controllable=t.boolean("controllable", False),
                 autopilot=autopilot, **common)


def _aircraft_autopilot(value, path: str) -> WaypointRoute | Hold:
    t = _Table(value, path, ("route", "speed_mps", "hold"))
    if ("route" in value) == ("hold" in value):
        raise ScenarioError(path, "give exactly one of route = [[lat, lon, alt_msl_m], ...] or hold = {...}",
                            value=sorted(value))
    if "hold" in value:
        if "speed_mps" in value:
            raise ScenarioError(t.key("speed_mps"), "goes inside hold = {...} when holding", value=value["speed_mps"])
        h = _Table(t.table("hold"), t.key("hold"), tuple(f.name for f in fields(Hold)))
        if not h.data:
            raise ScenarioError(h.path, "must hold at least one of heading_deg, alt_msl_m, speed_mps")
        return Hold(heading_deg=h.number("heading_deg", None, lo=0.0, hi=360.0, hi_open=True),
                    alt_msl_m=h.number("alt_msl_m", None, lo=ALT_MSL_MIN_M, hi=ALT_MAX_M),
                    speed_mps=h.number("speed_mps", None, lo=0.0, lo_open=True, hi=SPEED_MAX_MPS))
    points = _points(t.raw("route"), t.key("route"), 3, 1, MAX_ROUTE_POINTS, "waypoints")
    return WaypointRoute(tuple(points), t.number("speed_mps", lo=0.0, lo_open=True, hi=SPEED_MAX_MPS))


def _ground(t: _Table, common: dict) -> Agent:
    type_name = t.string("type")
    if type_name not in VEHICLE_TYPES:
        raise ScenarioError(t.key("type"), f"must be a vehicle type ({', '.join(sorted(VEHICLE_TYPES))})",
                            value=type_name)
    top = VEHICLE_TYPES[type_name].max_speed_mps
    speed = t.number("speed_mps", 0.0, lo=0.0, hi=top)
    autopilot = _ground_autopilot(t.table("autopilot"), t.key("autopilot"), top) if "autopilot" in t.data else None
    return Agent(type=type_name, speed_mps=speed, controllable=t.boolean("controllable", False), autopilot=autopilot,
                 **common)


def _ground_autopilot(value, path: str, top_speed_mps: float) -> GroundRoute:
    t = _Table(value, path, ("route", "cruise_mps", "convoy", "spacing_m"))
    points = _points(t.raw("route"), t.key("route"), 2, 2, MAX_ROUTE_POINTS, "points")
    _check_separation(points, t.key("route"))
    convoy = t.string("convoy", None, name=True)
    if "spacing_m" in value and convoy is None:
        raise ScenarioError(t.key("spacing_m"), "only for a convoy member (set convoy = \"name\")",
                            value=value["spacing_m"])
    spacing = t.number("spacing_m", DEFAULT_CONVOY_SPACING_M, lo=0.0, lo_open=True, hi=CONVOY_SPACING_MAX_M)
    return GroundRoute(tuple(points), t.number("cruise_mps", lo=0.0, lo_open=True, hi=top_speed_mps), convoy,
                       spacing if convoy is not None else None)


def _local_m(lat, lon, lat0: float, lon0: float):
    """North and east metres from (lat0, lon0) in the plane tangent there (longitude wrapped)."""
    m, n = radii_of_curvature(lat0)
    dlon = (np.asarray(lon) - lon0 + 180.0) % 360.0 - 180.0
    return np.radians(np.asarray(lat) - lat0) * m, np.radians(dlon) * n * math.cos(math.radians(lat0))


def _check_separation(points, path: str) -> None:
    """Each route point apart from the one before it (their ECEF chord, valid at the poles and
    across the antimeridian) and less than a leg's arc limit from it (fdm.convoy.LEG_MAX_ARC_DEG:
    the angle between the points' ellipsoid normals, as fdm.convoy measures a leg)."""
    from fdm.convoy import LEG_MAX_ARC_DEG

    lat_deg, lon_deg = np.array(points, dtype=np.float64).T
    chord = np.linalg.norm(np.diff(geodetic_to_ecef(lat_deg, lon_deg, 0.0), axis=0), axis=1)
    lat, lon = np.radians(lat_deg), np.radians(lon_deg)
    close = chord < WAYPOINT_MIN_SEPARATION_M
    if close.any():
        i = int(np.flatnonzero(close)[0]) + 1
        raise ScenarioError(f"{path}[{i}]", f"repeats the point before it (closer than {WAYPOINT_MIN_SEPARATION_M} m)",
                            value=list(points[i]))
    normals = np.stack([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)], -1)
    a, b = normals[:-1], normals[1:]
    arc = np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.sum(a * b, axis=1)))
    far = arc >= LEG_MAX_ARC_DEG
    if far.any():
        i = int(np.flatnonzero(far)[0]) + 1
        raise ScenarioError(f"{path}[{i}]", f"is {arc[i - 1]:.6g} degrees of arc from the point before it (a leg "
                            f"must span less than {LEG_MAX_ARC_DEG:g})", value=list(points[i]))


def _convoys(agents) -> tuple[ConvoySpec, ...]:
    members: dict[str, list[int]] = {}
    for i, a in enumerate(agents):
        if isinstance(a.autopilot, GroundRoute) and a.autopilot.convoy is not None:
            members.setdefault(a.autopilot.convoy, []).append(i)
    out = []
    for name, idx in members.items():
        lead = agents[idx[0]].autopilot
        if len(idx) < 2:
            raise ScenarioError(f"agents[{idx[0]}].autopilot.convoy", "has no other member (a convoy needs two "
                                                                      "agents; check the name's spelling)", value=name)
        for i in idx[1:]:
            _same_as_leader(agents[i].autopilot, lead, f"agents[{i}].autopilot", idx[0], name)
        _check_spacing(agents, idx, name)
        out.append(ConvoySpec(name, tuple(agents[i].name for i in idx), lead.points, lead.cruise_mps, lead.spacing_m))
    return tuple(out)


def convoy_spacing_min_m(type_names) -> float:
    """The least spacing (m, centre to centre along the route, as fdm.convoy keeps it) of a
    convoy of vehicles of ``type_names``: its longest vehicle's length plus the standoff a
    driver keeps behind what is ahead of it (fdm.convoy.OBSTACLE_STANDOFF_M, bumper to
    bumper). Whichever two follow each other, their bumpers are then at least the standoff
    apart at the convoy's spacing (half of each length lies between their centres); closer,
    the column's spacing law drives each into the one ahead (3 m with 7.9 m M1A2s: a
    collision every 14 s)."""
    from fdm.convoy import OBSTACLE_STANDOFF_M

    return max(VEHICLE_TYPES[t].length_m for t in type_names) + OBSTACLE_STANDOFF_M


def _check_spacing(agents, idx: list[int], convoy: str) -> None:
    from fdm.convoy import OBSTACLE_STANDOFF_M

    spacing = agents[idx[0]].autopilot.spacing_m
    least = convoy_spacing_min_m([agents[i].type for i in idx])
    if spacing < least:
        k = max(idx, key=lambda i: VEHICLE_TYPES[agents[i].type].length_m)
        length = VEHICLE_TYPES[agents[k].type].length_m
        raise ScenarioError(f"agents[{idx[0]}].autopilot.spacing_m",
                            f"must be at least {least:g} m for convoy {convoy!r}: its longest member, agents[{k}] "
                            f"{agents[k].name!r} ({agents[k].type}), is {length:g} m long, and a driver keeps "
                            f"{OBSTACLE_STANDOFF_M:g} m (bumper to bumper) behind the vehicle ahead; the spacing is "
                            "centre to centre along the route", value=spacing)


def _same_as_leader(member: GroundRoute, lead: GroundRoute, path: str, lead_index: int, convoy: str) -> None:
    why = f"members of convoy {convoy!r} share it with its leader agents[{lead_index}]"
    if member.points != lead.points:
        common = min(len(member.points), len(lead.points))
        k = next((k for k in range(common) if member.points[k] != lead.points[k]), None)
        if k is None:
            raise ScenarioError(f"{path}.route", f"{why}; the leader's has {len(lead.points)} points",
                                value=len(member.points))
        raise ScenarioError(f"{path}.route[{k}]", f"{why}; the leader's point {k} is {list(lead.points[k])}",
                            value=list(member.points[k]))
    for key in ("cruise_mps", "spacing_m"):
        if getattr(member, key) != getattr(lead, key):
            raise ScenarioError(f"{path}.{key}", f"{why}; the leader's is {getattr(lead, key)}",
                                value=getattr(member, key))


# --- [[target_areas]] -------------------------------------------------------------------------------

def _target_area(entry) -> TargetArea:
    path, value = entry
    t = _Table(value, path, ("name", "polygon", "detail_m"))
    name = t.string("name", name=True)
    detail = t.number("detail_m", DEFAULT_DETAIL_M, lo=DETAIL_MIN_M, hi=DETAIL_MAX_M)
    poly_path = t.key("polygon")
    raw = t.raw("polygon")
    vertices = _points(raw, poly_path, 2, 0, len(raw) if isinstance(raw, list) else 0, "vertices")
    if len(vertices) > 1 and vertices[-1] == vertices[0]:
        vertices = vertices[:-1]  # the closing vertex
    if not 3 <= len(vertices) <= MAX_POLYGON_VERTICES:
        raise ScenarioError(poly_path, f"must have 3..{MAX_POLYGON_VERTICES} vertices, a closing vertex not "
                                       "counted", value=len(vertices))
    lat, lon = np.array(vertices).T
    # Edges run straight in (lat, lon), the short way in longitude (the inset's lattice, its
    # PolygonPlane, the drawn outlines): longitudes winding a full turn circle a pole, which
    # such a polygon cannot contain (it would be a band along the parallels, not an area).
    winding = float(np.sum((np.roll(lon, -1) - lon + 180.0) % 360.0 - 180.0))
    if abs(winding) > 180.0:
        raise ScenarioError(poly_path, "circles a pole: a target area's edges run straight in latitude and "
                                       "longitude (as its inset's lattice does), so it cannot contain a pole; "
                                       "keep the area off the pole", value=_shown(vertices))
    north, east = _local_m(lat, lon, float(lat[0]), float(lon[0]))
    _check_simple_polygon(north, east, poly_path, vertices)
    _check_inset_size(lat, lon, detail, t.key("detail_m"))
    return TargetArea(name, tuple(vertices), detail)


def inset_posts_least(lat, lon, detail_m: float) -> tuple[int, int]:
    """(rows, cols): the fewest posts the inset of a target area (terrain/inset.py) can have,
    whatever the DEM beneath. Its lattice spans the polygon's bounding box plus
    INSET_MARGIN_CELLS cells each side, rounded up to whole INSET_BLOCK_CELLS blocks plus one
    post, with posts at most detail_m apart along each axis (the DEM's own spacing where that
    is finer, else the DEM's refined by the least power of two that reaches detail_m: between
    0.5 and 1 x detail_m); the box's extents in metres are the inset's, at its middle latitude.

    lat, lon: (n,) float64 degrees, the polygon's vertices; longitudes taken the short way
    from the first (an area may straddle the antimeridian)."""
    from terrain.inset import INSET_BLOCK_CELLS, INSET_MARGIN_CELLS

    lat, lon = np.asarray(lat, np.float64), np.asarray(lon, np.float64)
    lat_c = 0.5 * (float(lat.min()) + float(lat.max()))
    m, n = radii_of_curvature(lat_c)
    dlon = (lon - lon[0] + 180.0) % 360.0 - 180.0
    extent_m = (math.radians(float(np.ptp(lat))) * float(m),
                math.radians(float(np.ptp(dlon))) * float(n) * math.cos(math.radians(lat_c)))
    rows, cols = (math.ceil((e / detail_m + 2 * INSET_MARGIN_CELLS) / INSET_BLOCK_CELLS) * INSET_BLOCK_CELLS + 1
                  for e in extent_m)
    return rows, cols


def _check_inset_size(lat, lon, detail_m: float, path: str) -> None:
    """A target area whose inset cannot fit terrain/inset.py's INSET_MAX_POSTS over any DEM is
    a ScenarioError at ``path`` (its detail_m). Whether it fits over the scenario's DEM is
    known only with the DEM: the server checks that (server/sim_server.py), before it builds
    an inset; `sortie terrain serve --insets` builds them from any scenario's areas."""
    from terrain.inset import INSET_MAX_POSTS

    rows, cols = inset_posts_least(lat, lon, detail_m)
    if rows * cols > INSET_MAX_POSTS:
        side = math.isqrt(INSET_MAX_POSTS)
        raise ScenarioError(path, f"gives at least {rows} x {cols} inset posts over the polygon's bounding box "
                                  f"(posts at most detail_m apart, terrain/inset.py), more than the "
                                  f"{INSET_MAX_POSTS} ({side} x {side}) an inset may have: coarsen it or shrink the "
                                  "area", value=detail_m)


def check_simple_polygon(north, east) -> tuple[int, int] | None:
    """The first pair (i, j) of edges of a closed polygon that meet where they must not,
    or None for a simple polygon.

    north, east: (n,) float64 metres in a local plane, n >= 3 (no closing
    vertex); edge k runs from vertex k to vertex k + 1 (mod n). Edges
    that are not neighbours must stay POLYGON_TOUCH_M apart and must not
    cross; neighbours may share only their common vertex (a vertex of one
    within POLYGON_TOUCH_M of the other is a spike or a repeated vertex).
    (0, 0) is returned for a zero-area polygon.
    """
    p = np.stack([east, north], axis=1).astype(np.float64)
    q = np.roll(p, -1, axis=0)
    n = len(p)
    i, j = np.triu_indices(n, k=1)
    adjacent = (j == i + 1) | ((i == 0) & (j == n - 1))
    # Neighbours: the far end of either within touching distance of the other edge.
    a = np.where(j == i + 1, i, j)[adjacent]  # the edge that ends at the shared vertex
    b = np.where(j == i + 1, j, i)[adjacent]  # the edge that starts there
    spike = ((_point_segment_m(p[a], p[b], q[b]) < POLYGON_TOUCH_M)
             | (_point_segment_m(q[b], p[a], q[a]) < POLYGON_TOUCH_M))
    # Others: only pairs whose bounding boxes (grown by the tolerance) overlap can meet.
    lo, hi = np.minimum(p, q) - POLYGON_TOUCH_M, np.maximum(p, q) + POLYGON_TOUCH_M
    i, j = i[~adjacent], j[~adjacent]
    keep = np.all((lo[i] <= hi[j]) & (lo[j] <= hi[i]), axis=1)
    i, j = i[keep], j[keep]
    cross = ((_orient(p[i], q[i], p[j]) * _orient(p[i], q[i], q[j]) < 0)
             & (_orient(p[j], q[j], p[i]) * _orient(p[j], q[j], q[i]) < 0))
    near = np.minimum.reduce([_point_segment_m(p[i], p[j], q[j]), _point_segment_m(q[i], p[j], q[j]),
                              _point_segment_m(p[j], p[i], q[i]), _point_segment_m(q[j], p[i], q[i])])
    bad = cross | (near < POLYGON_TOUCH_M)
    hits = [(int(min(x, y)), int(max(x, y))) for x, y in zip(a[spike], b[spike])]
    hits += [(int(x), int(y)) for x, y in zip(i[bad], j[bad])]
    if hits:
        return min(hits)
    area2 = float(np.sum(p[:, 0] * q[:, 1] - q[:, 0] * p[:, 1]))
    return (0, 0) if abs(area2) < POLYGON_TOUCH_M ** 2 else None


def _orient(a, b, c) -> np.ndarray:
    """Twice the signed area of triangles (a, b, c), each (m, 2)."""
    return (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0])


def _point_segment_m(x, a, b) -> np.ndarray:
    """Distance of points x to segments a-b, each (m, 2) metres."""
    ab = b - a
    length2 = np.einsum("ij,ij->i", ab, ab)
    t = np.clip(np.einsum("ij,ij->i", x - a, ab) / np.where(length2 > 0, length2, 1.0), 0.0, 1.0)
    return np.hypot(*(a + t[:, None] * ab - x).T)


def _check_simple_polygon(north, east, path: str, vertices) -> None:
    hit = check_simple_polygon(north, east)
    if hit is None:
        return
    n = len(vertices)
    i, j = hit
    if hit == (0, 0):
        raise ScenarioError(path, "encloses no area (its vertices are collinear)", value=_shown(vertices))
    raise ScenarioError(path, f"is not a simple polygon: edge {i} (vertices {i}-{(i + 1) % n}) and edge {j} "
                              f"(vertices {j}-{(j + 1) % n}) cross or touch",
                        value=[list(vertices[i]), list(vertices[(i + 1) % n]), list(vertices[j]),
                               list(vertices[(j + 1) % n])])
