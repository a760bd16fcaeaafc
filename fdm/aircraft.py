"""A JSBSim aircraft on Sortie terrain: initial conditions, controls, one step, state out.

This is the thesis's AirplaneObject (clipmaps-jsbsim-thesis §4.3): it owns one
``FGFDMExec``; inputs go to the flight control system, JSBSim runs one
discrete step, and the state comes back. Everything imperial stays here: the
caller speaks SI, geodetic WGS84 (lat, lon in that order, degrees) and the
normalised controls of :class:`Controls`.

Terrain coupling
----------------
JSBSim's default ground callback knows one number, the terrain elevation
(``position/terrain-elevation-asl-ft``), and treats the ground as the ellipsoid
raised by it: a horizontal plane. Every gear and structure contact measures
its clearance against that one elevation, so a slope cannot tilt the ground
under the wheels. What we do with the one number, each step while the aircraft
is near the ground:

1. place every contact point (wheels *and* structure points: wing tips, tail
   skid, radome) from the CG, the attitude and the model's contact locations,
   one step ahead along the current ground velocity (the step that will use
   the elevation);
2. ask the terrain for the height under each contact and under the CG (one
   batched query);
3. feed the elevation that gives the most-penetrating contact its true
   clearance: ``E = min_i h_i - min_i (h_i - T_i)`` (h contact altitude, T
   terrain under it). On flat ground this is exactly T; on a slope or a cliff
   edge the first contact touches at the right instant and depth.

Limitation: the ground JSBSim sees is still level, so on a slope the other
wheels meet it at the height of the first contact, not the slope's; an
aircraft at rest on a 10 % cross-slope sits level. And JSBSim's strut damping
takes the wheel's vertical speed against a ground that never moves (FGLGear
subtracts a terrain velocity its default callback leaves at 0): rolling up a
5 % slope at 20 m/s the aircraft climbs 1 m/s, which the struts read as
extending; a c172x's nose strut's rebound damping then cancels its spring, and
landing or taxiing fast up a slope of 5 % or more can nose it over (an
acceptance probe's touchdown at 0.87 m/s sink crashed 16 s later; 3 % and
flat roll out). The Python API offers no callback with a ground velocity or
normal to fix it with. A contact deeper below its own terrain than its limit
(flying into a cliff face: ``max_penetration_m`` for a structure point, for a
wheel also what its strut compresses at the ultimate load factor,
:meth:`Aircraft._set_penetration_limits`), or any structure point below its
terrain at speed, is a crash; the aircraft then freezes where it hit
(``crashed`` is set, JSBSim is stepped no more). A crash clear of the surface (a
mid-air collision, the load factor) leaves a wreck that falls to the surface and
rests there (fdm.wreck; :attr:`Aircraft.falling`, event ``wreck_impact``).

Water: terrain at or below sea level is water by the ground vehicles' rule
(fdm.ground: ``WATER_LEVEL_MSL_M``; no data counts as sea level). A landplane
cannot start on it (``on_ground``: InvalidArgument), and its wheels touching it
are a crash, "ditched": a wheel with weight on it (JSBSim's per-unit WOW) whose
terrain is water. The catalog's flying boats (fdm.catalog.lands_on_water) are
exempt, and so is a terrain source without water (``has_water`` False:
:class:`FlatTerrain`, land at any height). Over water the surface an aircraft
meets is the sea's, not a DEM's sea floor (:func:`terrain_msl_m`): the
elevation fed to JSBSim, the clearances, AGL and an airborne start's floor; a
dive into the sea ends at its surface (ditched, or the structure's crash) and a
flying boat floats on it.

Far from the ground (CG more than ``near_ground_m`` plus twice the distance
flown between refreshes above the last terrain height) nothing touches the
terrain and ground effect is nil, so the elevation under the CG is refreshed
at ``terrain_refresh_hz``, and less often the higher the aircraft is: after
the time it needs to use half its spare height flying at its airspeed over
slopes of at most 45 degrees, capped at ``MAX_REFRESH_S`` ("model only what a
scene needs"). Between refreshes the height band and the load factor are
checked at ``CHECK_HZ`` (30 Hz: every 4th step at 120 Hz; the band's margin
covers the distance flown between checks); once a load-factor exceedance
starts, or near the ground, every step is checked, so an exceedance is seen
at most 1/30 s late and its ``g_hold_s`` timed step by step. The state's AGL
is as old as the last refresh there. ``near_ground_m=math.inf`` couples every
step. Where the terrain has no data (NaN) the ground is sea level, 0 m.

A check step has two halves, ``_plan`` (which terrain points are needed) and
``_finish`` (apply their heights), so that :class:`fdm.fleet.Fleet` can
answer a whole fleet's terrain points in one batched query per step: one
call instead of one per aircraft, which matters most through the terrain
service (one round trip per step for the fleet).
"""

from __future__ import annotations

import logging
import math
import operator
import os
import re
import threading
import warnings
from contextlib import contextmanager
from dataclasses import dataclass, fields, replace

import numpy as np

from fdm import catalog
from fdm.contacts import contact_points, ground_clearance, place_contacts
from fdm.events import LIMITS, SEGMENT_CRASH_REASON, SURFACE_CRASH_REASONS, WRECK_IMPACT, Event, EventDetector
from fdm.ground import WATER_LEVEL_MSL_M
from fdm.state import FT_M, RAW_COLUMNS, RAW_PROPERTIES, RAW_WIDTH, AircraftState
from fdm.wreck import FALL_MIN_AGL_M, G0_MPS2, fall, impact_fraction, ned_to_body_matrix
from sortie.errors import InvalidArgument, SortieError
from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef, wrap_lon_deg

LB_KG = 0.45359237  # international avoirdupois pound, exact (NIST SP 811, B.8)
DT_MIN_S = catalog.DT_MIN_S
DT_MAX_S = catalog.DT_MAX_S  # where the catalog's gear is stable (see fdm.catalog)
DEFAULT_DT_S = 1.0 / 120.0
# Deeper than this below its own terrain a structure contact is inside the ground, not on it;
# a wheel may sink deeper where its strut is that soft (see _penetration_limits_m).
MAX_PENETRATION_M = 1.0
# Far above the terrain its height is refreshed at least this often (AGL in the state stays fresh).
MAX_REFRESH_S = 1.0
# Far above the terrain, height band and load factor are checked at this rate (Hz) between refreshes.
CHECK_HZ = 30.0

# Some catalog models read properties that nothing in JSBSim defines: FlightGear's own (its
# /controls tree, /sim/model/pushback/*) or a name misspelt in the model (L17's
# fcs/flaps-pos-deg). JSBSim resolves a property when first evaluated and raises there. The
# host creates each such property (at 0, as FlightGear's tree starts), once per model and
# process, up to this many per model.
MAX_UNDEFINED_PROPERTIES = 16
_UNDEFINED_RE = re.compile(r"The property (\S+) does not exist")
_undefined: dict[str, tuple[str, ...]] = {}  # model -> the properties its runs found undefined
# FlightGear's pilot inputs (its property tree, Docs/README.properties): a model that reads
# one instead of JSBSim's fcs/*-cmd-norm gets the same control value, in the same convention
# (FlightGear copies them to fcs/*-cmd-norm unchanged); the fokker50's throttles are read so.
FG_CONTROL_INPUTS = (
    (re.compile(r"/?controls/engines/engine(\[\d+\])?/throttle"), "throttle"),
    (re.compile(r"/?controls/engines/engine(\[\d+\])?/mixture"), "mixture"),
    (re.compile(r"/?controls/flight/elevator"), "pitch"),
    (re.compile(r"/?controls/flight/aileron"), "roll"),
    (re.compile(r"/?controls/flight/rudder"), "yaw"),
    (re.compile(r"/?controls/flight/flaps(-cond)?"), "flaps"),
    (re.compile(r"/?controls/gear/brake-(left|right)"), "brakes"),
    (re.compile(r"/?controls/gear/wheel(\[[01]\])?/brake-cmd-cond"), "brakes"),
    (re.compile(r"/?controls/gear/gear-down(-cond)?"), "gear_down"),
)
# The "-cond" inputs are FlightGear's conditioned pilot inputs (the L410's: its Nasal copies
# the pilot's gear, flaps and wheel-brake commands there while its systems allow): the host's
# systems always do. Left undriven, the L410's gear read 0, retracted, on the ground.


def _fg_input_paths(engines: int) -> tuple[str, ...]:
    """The FlightGear pilot inputs (FG_CONTROL_INPUTS) a model of ``engines`` engines may
    declare, spelt as JSBSim's tree holds them (absolute paths). An engine's node without an
    index is the node [0]; only one spelling of each is listed, so none is driven twice."""
    engine = [f"/controls/engines/engine[{i}]/{x}" for x in ("throttle", "mixture") for i in range(engines)]
    return (*engine, "/controls/flight/elevator", "/controls/flight/aileron", "/controls/flight/rudder",
            "/controls/flight/flaps", "/controls/gear/brake-left", "/controls/gear/brake-right",
            "/controls/gear/gear-down", "/controls/flight/flaps-cond", "/controls/gear/wheel[0]/brake-cmd-cond",
            "/controls/gear/wheel[1]/brake-cmd-cond", "/controls/gear/gear-down-cond")


# An airborne start whose trim fails at full rich is tried again leaned (Aircraft._start)
# where the air's density ratio is below this (about 500 m and higher); a ground start there
# with a piston engine starts leaned.
LEAN_BELOW_SIGMA = 0.95

# Engine kinds (fdm.catalog.EngineSpec.kind) whose JSBSim model makes power only while it runs
# (FGEngine's Running: a piston engine stopped, a turbine or turboprop in its off phase). An
# electric engine (FGElectric: the Pterosaur's dummy, whose thrust is an external force) turns
# whatever its flag reads; rockets and other kinds are left as set-running leaves them.
RUNNING_KINDS = frozenset({"piston_engine", "turbine_engine", "turboprop_engine"})
# JSBSim's set-running can leave an engine dead: it searches the engine's steady state in 0.5 s
# time steps (FGPropulsion::GetSteadyState), in which a propeller at rest on the ground stops
# and a stopped piston engine is not running (FGPiston::doEngineStartup): the c310, c182 and
# Boeing314 on the ground, the p51d anywhere. Such an engine is started as a pilot does
# (Aircraft._crank): both magnetos on, fuel on, on the starter, the throttle cracked open, then
# wide open, for at most CRANK_S each. FGPiston fires once the starter has turned it for 175
# frames and past 0.8 x its idle rpm; at a closed throttle the c182's starter turns it at
# 690 rpm, short of its 720 (its pumping losses), wide open it fires. It has started when it
# still runs CRANK_SETTLE_S off the starter (the p51d at 3000 m and 60 m/s fires cracked open,
# at 400 rpm, and stops at once; wide open it runs).
CRANK_THROTTLES = (0.1, 1.0)
CRANK_S = 8.0
CRANK_SETTLE_S = 1.0
# A ground start's running engines are run to the steady state of its throttle before time 0
# (Aircraft._settle_engines): SETTLE_CHUNK_S at a time until no engine's thrust moves by more
# than SETTLE_THRUST_LBF or SETTLE_THRUST_RATIO of it in a chunk, at most SETTLE_MAX_S (the
# catalog's slowest, the DHC6's propellers, settle in 25 s; a c172p in 2 s).
SETTLE_CHUNK_S = 0.5
SETTLE_MAX_S = 30.0
SETTLE_THRUST_LBF = 1.0
SETTLE_THRUST_RATIO = 0.01

# Glide trim (Aircraft._trim_glide). Steeper than this is a dive, not a glide (L/D below 1).
GLIDE_GAMMA_MIN_DEG = -45.0
GLIDE_ITERATIONS = 12
# Newton's target for (udot, wdot ft/s², qdot rad/s²): a tenth of JSBSim's trim tolerances
# (FGTrimAxis.cpp: 1e-3, 1e-3, 1e-4), so its full trim at the gamma found passes udot unaided.
GLIDE_TOLERANCE = np.array([1e-4, 1e-4, 1e-5])

_quiet = False

# JSBSim's messages ("Sorry, udot doesn't appear to be trimmable", file errors) go through its
# logger (FGLogger, JSBSim 1.3.3), whose default prints them on stdout: into a host's logs, a
# CLI's JSON. They are routed to this Python logger instead, at their JSBSim severity.
log = logging.getLogger("jsbsim")
_log = logging.getLogger(__name__)
_LOG_LEVELS = {0: logging.DEBUG, 1: logging.DEBUG, 2: logging.INFO, 3: logging.WARNING, 4: logging.ERROR,
               5: logging.CRITICAL, 6: logging.INFO}  # jsbsim.LogLevel: BULK .. FATAL, STDOUT
_log_thread = threading.local()  # JSBSim's logger is per thread: whether this one's is routed
_log_routers: list = []  # every router handed to JSBSim (it keeps a pointer: they must stay alive)
_Router = None


def _jsbsim():
    """The jsbsim module, its start-up banner and debug output silenced once, and its
    messages routed to the ``jsbsim`` Python logger in this thread."""
    global _quiet
    import jsbsim

    if not _quiet:
        jsbsim.FGJSBBase().debug_lvl = 0
        _quiet = True
    if not getattr(_log_thread, "routed", False):
        router = _log_router(jsbsim)()
        jsbsim.set_logger(router)
        _log_routers.append(router)
        _log_thread.routed = True
    return jsbsim


def _log_router(jsbsim):
    """The FGLogger subclass that hands each JSBSim log record to :data:`log`."""
    global _Router
    if _Router is None:
        class Router(jsbsim.FGLogger):
            # One record: set_level, message fragments, flush (jsbsim.FGLogger's documentation).
            def __init__(self):
                super().__init__()
                self._level = logging.INFO
                self._parts = []

            def set_level(self, level):
                self._level = _LOG_LEVELS.get(int(level), logging.INFO)
                self._parts = []

            def file_location(self, filename, line):
                self._parts.append(f"{filename}:{line}: ")

            def message(self, message):
                self._parts.append(message)

            def format(self, format):
                pass

            def flush(self):
                text = "".join(self._parts).strip()
                self._parts = []
                if not text:
                    return
                level = self._level
                if os.devnull in text:  # a model's output file reopened on the null device (_discard_outputs)
                    level = logging.DEBUG
                log.log(level, "%s", text)

        _Router = Router
    return _Router


def _discard_outputs(fdm) -> None:
    """Point every output a model declares (c172x: its CSV file JSBout172B.csv) at the null
    device. ``disable_output`` stops the writing but not the opening: each run_ic (start, trim,
    retries) opens the files again (FGOutput::InitModel), by default in the jsbsim package's
    own directory, truncating them. The host records the flight itself."""
    n = 0
    while fdm.get_output_filename(n):
        n += 1
    if n:
        directory, name = os.path.split(os.devnull)
        fdm.set_output_path(directory)  # output names are resolved against it (FGOutputFile::SetOutputName)
        for i in range(n):
            fdm.set_output_filename(i, name)


def _spans_a_plane(points_in: np.ndarray) -> bool:
    """Whether (n, 3) contact locations (inches) hold three points not on one line."""
    d = points_in - points_in[:1]
    return len(points_in) >= 3 and np.linalg.matrix_rank(d, tol=1e-3) >= 2


def _no_fuel() -> float:
    """The fuel check's reading for a model without tanks: never runs out."""
    return math.inf


class TrimFailed(SortieError):
    """JSBSim's trim found no steady state for the requested conditions."""


# The last advice of a TrimFailed message (what the API can do; server.sim_server says what a scenario can).
TRIM_OFF_HINT = ", or start with trim=False"


@dataclass(frozen=True)
class InitialConditions:
    """Where and how an aircraft starts. Degrees, metres, m/s; (lat, lon) order.

    ``alt_ref`` is "msl" (alt_m above mean sea level) or "agl" (above the
    terrain under the aircraft). ``on_ground`` places the aircraft at rest on
    its wheels (alt_m is ignored) and settles it with JSBSim's ground trim;
    airborne starts are trimmed (full trim) unless ``trim`` is False: in
    level flight, or a model without engines (a glider) or started with
    ``engines_running`` False in its steady glide at ``speed_mps``,
    descending (:meth:`Aircraft.trim`, ``trim_gamma_deg``).
    ``gear_down`` None means down on the ground, up in the air.
    ``engines_running`` starts every engine (JSBSim's set-running; an engine that leaves stopped
    is started on its starter, :meth:`Aircraft._crank`): a ground start whose engine still does
    not run is refused (InvalidArgument ``engines_running``). A ground start at a high field
    leans its piston engines (:meth:`Aircraft._field_mixture`).
    """

    lat_deg: float
    lon_deg: float
    alt_m: float = 0.0
    alt_ref: str = "msl"
    heading_deg: float = 0.0
    speed_mps: float = 0.0
    on_ground: bool = False
    trim: bool = True
    engines_running: bool = True
    gear_down: bool | None = None

    def validated(self) -> "InitialConditions":
        for f in ("lat_deg", "lon_deg", "alt_m", "heading_deg", "speed_mps"):
            v = getattr(self, f)
            if not isinstance(v, (int, float)) or not math.isfinite(v):
                raise InvalidArgument(f, "must be a finite number", value=v)
        if abs(self.lat_deg) > 90.0:
            raise InvalidArgument("lat_deg", "must be within [-90, 90]", value=self.lat_deg)
        if abs(self.lon_deg) > 540.0:
            raise InvalidArgument("lon_deg", "must be within [-540, 540]", value=self.lon_deg)
        if self.alt_ref not in ("msl", "agl"):
            raise InvalidArgument("alt_ref", 'must be "msl" or "agl"', value=self.alt_ref)
        if self.speed_mps < 0.0:
            raise InvalidArgument("speed_mps", "must be >= 0", value=self.speed_mps)
        return self


# name: (low, high). gear_down is a bool and checked apart.
CONTROL_RANGES = {
    "pitch": (-1.0, 1.0),  # stick: +1 full aft (nose up); JSBSim elevator-cmd-norm = -pitch
    "roll": (-1.0, 1.0),  # stick: +1 full right (right wing down)
    "yaw": (-1.0, 1.0),  # pedals: +1 full right (nose right), JSBSim rudder-cmd-norm = -yaw
    "throttle": (0.0, 1.0),  # every engine
    "mixture": (0.0, 1.0),  # every engine (piston engines; others ignore it)
    "flaps": (0.0, 1.0),
    "brakes": (0.0, 1.0),  # left and right wheel brakes
}


@dataclass(frozen=True)
class Controls:
    """Normalised pilot inputs (see CONTROL_RANGES for signs and ranges)."""

    pitch: float = 0.0
    roll: float = 0.0
    yaw: float = 0.0
    throttle: float = 0.0
    mixture: float = 1.0
    flaps: float = 0.0
    brakes: float = 0.0
    gear_down: bool = True


CONTROL_NAMES = tuple(f.name for f in fields(Controls))


def validate_controls(values: dict) -> dict:
    """The same mapping with floats; InvalidArgument naming the first bad field and value."""
    out = {}
    for name, v in values.items():
        if name == "gear_down":
            if not isinstance(v, (bool, int, float, np.bool_, np.integer, np.floating)) or v not in (0, 1):
                raise InvalidArgument(name, "must be a bool", value=v)
            out[name] = bool(v)
            continue
        if name not in CONTROL_RANGES:
            raise InvalidArgument(name, f"unknown control; known: {', '.join(CONTROL_NAMES)}", value=v)
        if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
            raise InvalidArgument(name, "must be a number", value=v)
        try:
            v = float(v)
        except OverflowError:  # an int beyond any float
            raise InvalidArgument(name, "must be finite (an integer beyond any float)") from None
        lo, hi = CONTROL_RANGES[name]
        if not math.isfinite(v):
            raise InvalidArgument(name, "must be finite", value=v)
        if not lo <= v <= hi:
            raise InvalidArgument(name, f"must be within [{lo:g}, {hi:g}]", value=v)
        out[name] = v
    return out


@dataclass(frozen=True)
class Contact:
    """One JSBSim contact point: 'gear' (a wheel) or 'structure'; location in structural inches."""

    index: int
    kind: str
    location_in: tuple


class FlatTerrain:
    """A world of constant height (m MSL) with the terrain API (``heights(lat, lon)``).
    It is land at any height, sea level included: it holds no water (``has_water``)."""

    has_water = False

    def __init__(self, height_msl_m: float = 0.0):
        self.height_msl_m = float(height_msl_m)

    def heights(self, lat, lon):
        from terrain.terrain import HeightResult

        lat = np.asarray(lat, dtype=np.float64)
        return HeightResult(np.full(lat.shape, self.height_msl_m), np.ones(lat.shape, np.uint8))


def _wet(heights_m: np.ndarray) -> np.ndarray:
    """Which terrain heights are water: the ground vehicles' rule (fdm.ground.GroundVehicles stands
    a vehicle only where every contact has ``h > WATER_LEVEL_MSL_M``)."""
    return ~(heights_m > WATER_LEVEL_MSL_M)


def terrain_msl_m(terrain, lat_deg, lon_deg) -> np.ndarray:
    """The surface an aircraft meets (m MSL) from any terrain source: the terrain, and the sea
    surface where that is water (at or below WATER_LEVEL_MSL_M: a DEM's bathymetry lies under
    the sea); no data (NaN) is sea level, 0 m. A source without water (``has_water`` False:
    FlatTerrain) is land at any height."""
    h = np.asarray(terrain.heights(np.asarray(lat_deg, np.float64), np.asarray(lon_deg, np.float64)).height_msl_m,
                   np.float64)
    h = np.where(np.isnan(h), 0.0, h)
    return np.maximum(h, WATER_LEVEL_MSL_M) if getattr(terrain, "has_water", True) else h


# The state-out columns of motion: a wreck keeps its place and attitude, and these read 0
# (1 g for the load factor) from its crash on, so that receivers dead-reckoning it see it
# stay, and its sender's dead reckoning sends one last update, then heartbeats.
WRECK_MOTION_COLUMNS = tuple(RAW_COLUMNS[name] for name in (
    "v_north_fps", "v_east_fps", "v_down_fps", "p_rps", "q_rps", "r_rps", "udot_fps2", "vdot_fps2",
    "wdot_fps2", "vt_fps", "vc_kts", "alpha_rad", "beta_rad"))


def rest_row(row, lat_deg: float, lon_deg: float, alt_msl_m: float, surface_msl_m: float):
    """A wreck's raw state row (fdm.state.RAW_PROPERTIES) at rest at a place: ``row`` (a list
    or a (RAW_WIDTH,) float64 array, changed in place and returned) put at (lat, lon) degrees,
    ``alt_msl_m`` metres MSL over the surface ``surface_msl_m``, its attitude kept, no motion
    (WRECK_MOTION_COLUMNS) and 1 g. The one formula for the aircraft (:meth:`Aircraft.crash`)
    and a host showing the same wreck before the aircraft has it (server.world), bit for bit."""
    c = RAW_COLUMNS
    row[c["lat_rad"]], row[c["lon_rad"]] = math.radians(lat_deg), math.radians(lon_deg)
    row[c["alt_ft"]], row[c["terrain_ft"]] = alt_msl_m / FT_M, surface_msl_m / FT_M
    for k in WRECK_MOTION_COLUMNS:
        row[k] = 0.0
    row[c["nz_g"]] = 1.0
    return row


def static_compressions_m(locations_in: np.ndarray, springs_lbs_ft, cg_in, weight_lbs: float) -> np.ndarray:
    """Each contact's strut compression (m) at rest on level ground: the contacts with a
    spring (``springs_lbs_ft[i]``, None or 0 for none) carry ``weight_lbs`` at the CG.

    JSBSim's strut force is k * compression (FGLGear). With small pitch a and roll b the
    compressions are d_i = h + a dx_i + b dy_i - dz_i (dx, dy from the CG, dz above the
    lowest contact), and rest is vertical force and pitch and roll moments in balance:
    sum k_i d_i (1, dx_i, dy_i) = (W, 0, 0), three linear equations; a contact the solution
    lifts off (d_i < 0) carries nothing and the rest are solved again. Contacts on one line
    or one point (minisgs) take the least-squares solution. Each is at most W / k_i (that
    contact alone carrying the aircraft): the bound where the balance needs a structure
    point (a tail skid) that has no spring."""
    loc = np.asarray(locations_in, np.float64).reshape(-1, 3) / 12.0  # ft
    k = np.array([0.0 if v is None else float(v) for v in springs_lbs_ft], np.float64)
    d = np.zeros(len(k))
    if len(k) != len(loc) or not (weight_lbs > 0.0) or not (k > 0).any():
        return d
    g = np.column_stack([np.ones(len(k)), loc[:, 0] - cg_in[0] / 12.0, loc[:, 1] - cg_in[1] / 12.0])
    dz = loc[:, 2] - loc[:, 2].min()
    active = k > 0
    for _ in range(len(k)):
        ka = k[active][:, None]
        a_mat = g[active].T @ (ka * g[active])
        rhs = np.array([weight_lbs, 0.0, 0.0]) + g[active].T @ (k[active] * dz[active])
        u = np.linalg.lstsq(a_mat, rhs, rcond=None)[0]
        d = np.where(active, g @ u - dz, 0.0)
        if (d[active] >= 0.0).all() or active.sum() == 1:
            break
        active &= d > d[active].min()  # the contact lifted most leaves the set
    with np.errstate(divide="ignore"):
        cap = np.where(k > 0, weight_lbs / np.where(k > 0, k, 1.0), 0.0)
    return np.clip(d, 0.0, cap) * FT_M


class Aircraft:
    """One JSBSim aircraft of the catalog, stepped on a terrain source.

    ``terrain`` is anything with ``heights(lat, lon) -> .height_msl_m``: a
    :class:`terrain.terrain.Terrain` in process, a
    :class:`client.terrain_client.TerrainClient`, or :class:`FlatTerrain`.
    """

    def __init__(self, name: str, terrain, ic: InitialConditions, *, dt: float = DEFAULT_DT_S,
                 terrain_refresh_hz: float = 10.0, near_ground_m: float = 150.0,
                 max_penetration_m: float = MAX_PENETRATION_M, geoid_undulation_m: float = 0.0):
        if not (isinstance(dt, (int, float)) and math.isfinite(dt) and DT_MIN_S <= dt <= DT_MAX_S):
            raise InvalidArgument("dt", f"must be within [{DT_MIN_S:g}, {DT_MAX_S:g}] s", value=dt)
        if not (terrain_refresh_hz > 0 and math.isfinite(terrain_refresh_hz)):
            raise InvalidArgument("terrain_refresh_hz", "must be positive and finite", value=terrain_refresh_hz)
        if not near_ground_m >= 0:
            raise InvalidArgument("near_ground_m", "must be >= 0 (inf couples every step)", value=near_ground_m)
        ic = ic.validated()
        self.name = catalog.resolve(name)
        self.aircraft_class = catalog.aircraft_class(self.name)
        self.terrain = terrain
        # Queries without the batch path's arrays (Terrain.heights_of), where offered.
        self._heights_of = getattr(terrain, "heights_of", None)
        # The refresh far from the ground asks one point: the terrain's scalar path, where offered.
        self._point_height = terrain.point_height() if hasattr(terrain, "point_height") else None
        self.dt = float(dt)
        self.geoid_undulation_m = float(geoid_undulation_m)
        self.max_penetration_m = float(max_penetration_m)
        self.events: list = []
        self.crashed = False
        # A wreck falling (fdm.wreck): [its state row, its height above the surface (m), the
        # height it fell from (m MSL)]
        self._fall = None

        self._refresh_steps = max(1, round(1.0 / (terrain_refresh_hz * self.dt)))
        self._max_refresh_steps = max(self._refresh_steps, round(MAX_REFRESH_S / self.dt))
        self._check_steps = max(1, min(round(1.0 / (CHECK_HZ * self.dt)), self._refresh_steps))
        self._near_ground_base_ft = near_ground_m / FT_M
        self._near_ground_ft = self._near_ground_base_ft
        self._load_and_start(_jsbsim(), ic)

    # -- set-up ---------------------------------------------------------------------------------

    def _load_and_start(self, jsbsim, ic: InitialConditions) -> None:
        """Load the model and start it at ``ic``. Where JSBSim finds a property the model
        reads undefined (see MAX_UNDEFINED_PROPERTIES), it is remembered for the model and
        the load starts over with it created; a FlightGear pilot input among them is
        driven by the matching control (FG_CONTROL_INPUTS)."""
        self._trim_error = jsbsim.TrimFailureError
        while True:
            fdm = jsbsim.FGFDMExec(catalog.root_dir().as_posix())
            fdm.set_debug_level(0)
            # A model's <input port="..."/> (the catalog's 737 declares 5137) would open JSBSim's
            # telnet property server on every interface at the first run: anyone reaching the
            # port could set any property of a hosted aircraft, past sessions, tokens and the
            # recording. The host drives its aircraft through this API alone.
            fdm.disable_input()
            with catalog.model_paths(self.name) as paths:  # a propeller's diameter in inches (fdm.catalog)
                loaded = fdm.load_model_with_paths(self.name, *paths) if paths else fdm.load_model(self.name)
            if not loaded:
                raise SortieError(f"JSBSim could not load aircraft {self.name!r}")
            fdm.disable_output()  # models may declare CSV outputs (c172x: JSBout172B.csv); the host records
            _discard_outputs(fdm)
            fdm.set_dt(self.dt)
            pm = fdm.get_property_manager()
            for name in _undefined.get(self.name, ()):
                pm.get_node(name, True)
            self.fdm = fdm
            self._bind()
            self._controls = Controls()
            try:
                self._start(ic)
                return
            except jsbsim.BaseError as exc:
                if isinstance(exc, self._trim_error):
                    raise
                m = _UNDEFINED_RE.search(str(exc))
                known = _undefined.get(self.name, ())
                if m is None or m.group(1) in known:
                    raise SortieError(f"JSBSim failed to start aircraft {self.name!r}: {str(exc).strip()}") from exc
                if len(known) >= MAX_UNDEFINED_PROPERTIES:
                    raise SortieError(f"aircraft {self.name!r} reads more than {MAX_UNDEFINED_PROPERTIES} "
                                      f"properties that nothing defines ({', '.join(known)}, ...)") from exc
                _undefined[self.name] = known + (m.group(1),)

    @property
    def undefined_properties(self) -> tuple[str, ...]:
        """Properties this model reads that nothing defines, created by the host at 0 (or
        driven by a control: FG_CONTROL_INPUTS)."""
        return _undefined.get(self.name, ())

    def _node(self, name: str):
        node = self._pm.get_node(name)
        if node is None:
            raise SortieError(f"aircraft {self.name!r} has no JSBSim property {name!r}")
        return node

    def _bind(self) -> None:
        """Look every property up once; the hot loop calls bound C methods only."""
        self._pm = self.fdm.get_property_manager()
        n = self._node
        self._run = self.fdm.run
        self._get_alt_ft = n("position/geod-alt-ft").get_double_value
        self._get_lat_rad = n("position/lat-geod-rad").get_double_value
        self._get_lon_rad = n("position/long-gc-rad").get_double_value
        self._get_nz = n("accelerations/Nz").get_double_value
        self._get_wow = n("gear/wow").get_double_value
        self._get_vt_fps = n("velocities/vt-fps").get_double_value
        self._get_vn = n("velocities/v-north-fps").get_double_value
        self._get_ve = n("velocities/v-east-fps").get_double_value
        self._get_vd = n("velocities/v-down-fps").get_double_value
        self._get_euler = [n(f"attitude/{a}-rad").get_double_value for a in ("phi", "theta", "psi")]
        self._get_cg_in = [n(f"inertia/cg-{a}-in").get_double_value for a in "xyz"]
        # A model without tanks (a glider, a bomb, a balloon) has no fuel to run out of.
        self.has_fuel = self._pm.hasNode("propulsion/total-fuel-lbs")
        self._get_fuel_lbs = n("propulsion/total-fuel-lbs").get_double_value if self.has_fuel else _no_fuel
        self._get_time = n("simulation/sim-time-sec").get_double_value
        self._set_terrain_ft = n("position/terrain-elevation-asl-ft").set_double_value
        # The terrain column is the host's own value (JSBSim's getter recomputes it, ~10x
        # the cost of the others), appended last.
        assert RAW_PROPERTIES[-1][0] == "terrain_ft"
        self._raw_getters = [n(p).get_double_value for _, p in RAW_PROPERTIES[:-1]]

        engines = 0
        while self._pm.hasNode(f"fcs/throttle-cmd-norm[{engines}]"):
            engines += 1
        self.n_engines = engines
        self._bind_propulsion(engines)
        self._set = {
            "pitch": [n("fcs/elevator-cmd-norm").set_double_value],
            "roll": [n("fcs/aileron-cmd-norm").set_double_value],
            "yaw": [n("fcs/rudder-cmd-norm").set_double_value],
            "throttle": [n(f"fcs/throttle-cmd-norm[{i}]").set_double_value for i in range(engines)],
            "mixture": [n(f"fcs/mixture-cmd-norm[{i}]").set_double_value for i in range(engines)],
            "flaps": [n("fcs/flap-cmd-norm").set_double_value],
            "brakes": [n("fcs/left-brake-cmd-norm").set_double_value,
                       n("fcs/right-brake-cmd-norm").set_double_value],
            "gear_down": [n("gear/gear-cmd-norm").set_double_value],
        }
        # FlightGear inputs the model reads: those it left undefined (created by the host) and
        # those it declares itself (the p51d's <property> /controls/engines/engine/throttle).
        # One setter a node: "/a/engine/x" and "a/engine[0]/x" name the same one.
        fg = {}
        for name in (*_undefined.get(self.name, ()), *(p for p in _fg_input_paths(engines) if self._pm.hasNode(p))):
            fg.setdefault(name.lstrip("/").replace("/engine/", "/engine[0]/"), name)
        for name in fg.values():
            control = next((c for pattern, c in FG_CONTROL_INPUTS if pattern.fullmatch(name)), None)
            if control is not None:
                self._set[control].append(n(name).set_double_value)
        self._sign = {"pitch": -1.0, "yaw": -1.0}
        self._set_elevator = self._set["pitch"][0]
        self._set_aileron = self._set["roll"][0]
        self._set_rudder = self._set["yaw"][0]
        # The pedals also steer the nose (or tail) wheel, as FlightGear's JSBSim interface does
        # (fcs/steer-cmd-norm = the pedals, +1 right, unnegated): without it a model rolls where
        # its propeller's torque takes it, the rudder alone being weak below flying speed.
        self._set_steer = n("fcs/steer-cmd-norm").set_double_value if self._pm.hasNode("fcs/steer-cmd-norm") \
            else (lambda v: None)
        self._set_throttles = tuple(self._set["throttle"])

        gr = self.fdm.get_ground_reactions()
        contacts = []
        for i in range(gr.get_num_gear_units()):
            kind = "gear" if self._pm.hasNode(f"gear/unit[{i}]/WOW") else "structure"
            with warnings.catch_warnings():  # the binding returns a numpy.matrix
                warnings.simplefilter("ignore", PendingDeprecationWarning)
                loc = tuple(float(v) for v in np.asarray(gr.get_gear_unit(i).get_location()).flat)
            contacts.append(Contact(i, kind, loc))
        self.contacts = tuple(contacts)
        self._contact_locations_in = np.array([c.location_in for c in contacts], dtype=np.float64).reshape(-1, 3)
        self._q_lat = np.empty(len(contacts) + 1)  # terrain query points of a check step
        self._q_lon = np.empty(len(contacts) + 1)
        self._q_alt = np.empty(len(contacts))  # contact altitudes, m
        self._terr = np.empty(len(contacts) + 1)  # their terrain heights (see _terrain_msl_m)
        self._structure = np.array([c.kind == "structure" for c in contacts], dtype=bool)
        # Water under the wheels ends a landplane's roll (see the module docstring): the gear
        # contacts (their indices among the contacts, their weight-on-wheels readings).
        self._has_water = getattr(self.terrain, "has_water", True)
        self._ditches = self._has_water and not catalog.lands_on_water(self.name)
        self._gear_at = np.flatnonzero(~self._structure)
        self._gear_wow = [n(f"gear/unit[{contacts[i].index}]/WOW").get_double_value for i in self._gear_at]
        self._detector_limits = LIMITS[self.aircraft_class]
        self._nz_min = self._detector_limits.nz_min_g
        self._nz_max = self._detector_limits.nz_max_g

    def _bind_propulsion(self, engines: int) -> None:
        """The engines that must run when started running (RUNNING_KINDS) and the fuel the host
        moves between tanks (:meth:`_transfer_fuel`), from the model's files (fdm.catalog.propulsion)."""
        spec = catalog.propulsion(self.name)
        known = len(spec.engines) == engines
        self.engine_kinds = tuple(e.kind for e in spec.engines) if known else ("",) * engines
        self._must_run = tuple(i for i, k in enumerate(self.engine_kinds) if k in RUNNING_KINDS)
        self._get_running = [self._node(f"propulsion/engine[{i}]/set-running").get_double_value
                             for i in self._must_run]
        self._get_thrust = [self._node(f"propulsion/engine[{i}]/thrust-lbs").get_double_value
                            for i in self._must_run]
        # JSBSim burns fuel only from the tanks an engine's <feed> names. The aircraft's fuel system
        # empties the other fuel tanks into them, and the catalog's models leave that system to
        # FlightGear: the Concorde's engines feed from four 46 lb collector tanks that its Nasal
        # refills every second; without it they starve in 5 s at full reheat. Unless a model moves
        # fuel itself (a system driving a tank's external flow: the Short_S23), the host keeps each
        # feed tank at what it held at the start from the tanks no engine feeds from.
        fuel = [i for i, t in enumerate(spec.tank_types) if t == "FUEL"
                and self._pm.hasNode(f"propulsion/tank[{i}]/contents-lbs")]
        fed = {t for e in spec.engines for t in e.feeds} if known else set()
        feed = [i for i in fuel if i in fed]
        reserve = [i for i in fuel if i not in fed]
        if not (feed and reserve) or spec.moves_fuel:
            feed = reserve = []
        self._feed_tanks = [self._node(f"propulsion/tank[{i}]/contents-lbs") for i in feed]
        self._reserve_tanks = [self._node(f"propulsion/tank[{i}]/contents-lbs") for i in reserve]
        self._feed_target_lbs = [0.0] * len(feed)

    def _field_mixture(self) -> float:
        """The mixture command a ground start takes (JSBSim's initial conditions run at the field).

        A pilot leans a piston engine before taking off from a high field (FAA-H-8083-25, Pilot's
        Handbook of Aeronautical Knowledge, ch. 7 "Mixture Control": the mixture is leaned as the
        air thins); full rich, a c172p made 81 of its 204 hp at a 2500 m field and none at 3000 m.
        Leaned to the air's density ratio sigma, as an airborne start's retry (LEAN_BELOW_SIGMA):
        the fuel-air ratio of full rich at sea level. A model whose own systems lean (the c310's
        automatic mixture control sets the mixture's position to about sigma at full rich) is
        leaned only what they leave: the command is sigma over the position full rich gives.
        1.0 below about 500 m and for a model without piston engines."""
        fdm = self.fdm
        sigma = fdm["atmosphere/sigma"]
        pistons = [i for i, kind in enumerate(self.engine_kinds) if kind == "piston_engine"]
        if not (pistons and math.isfinite(sigma) and 0.0 < sigma < LEAN_BELOW_SIGMA):
            return 1.0
        self._apply({"mixture": 1.0})
        if not fdm.run_ic():
            raise SortieError(f"JSBSim refused the initial conditions of {self.name!r}")
        full_rich = min(fdm[f"fcs/mixture-pos-norm[{i}]"] for i in pistons)
        return sigma / full_rich if math.isfinite(full_rich) and full_rich > sigma else 1.0

    def _engines_run(self) -> list:
        """The engines of RUNNING_KINDS that are not running (engine indices)."""
        return [i for i, running in zip(self._must_run, self._get_running) if not running() > 0.5]

    @contextmanager
    def _before_time_0(self):
        """Run the model before its start (to start or settle its engines), then put the start
        back: time 0 and the initial conditions (JSBSim's run_ic leaves the engines as they are).
        No fuel is burnt meanwhile (propulsion/fuel_freeze: FGPropulsion::ConsumeFuel then draws
        from no tank and counts nothing in an engine's fuel-used-lbs), and the tanks' contents
        are put back (a model's own fuel system may move fuel between them regardless)."""
        fdm, pm = self.fdm, self._pm
        tanks = []
        while pm.hasNode(f"propulsion/tank[{len(tanks)}]/contents-lbs"):
            tanks.append(f"propulsion/tank[{len(tanks)}]/contents-lbs")
        fuel_lbs = [fdm[t] for t in tanks]
        freeze = fdm["propulsion/fuel_freeze"] if pm.hasNode("propulsion/fuel_freeze") else None
        if freeze is not None:
            fdm["propulsion/fuel_freeze"] = 1
        try:
            yield
        finally:
            if freeze is not None:
                fdm["propulsion/fuel_freeze"] = freeze
        for t, lbs in zip(tanks, fuel_lbs):
            fdm[t] = lbs
        fdm.set_sim_time(0.0)
        if not fdm.run_ic():
            raise SortieError(f"JSBSim refused the initial conditions of {self.name!r}")

    def _crank(self, throttle: float, on_ground: bool) -> None:
        """Start the engines JSBSim's set-running left dead, as a pilot does (see CRANK_THROTTLES),
        before time 0 (:meth:`_before_time_0`). An engine that still does not run refuses a ground
        start (InvalidArgument ``engines_running`` naming the aircraft and the engine: it would sit
        there for good); in the air the aircraft glides, as with its engines off, and a warning says
        so (the p51d at 3000 m and 60 m/s: its throttle is a manifold-pressure loop that holds the
        throttle shut while the engine does not run, and its starter cannot turn it fast enough
        in that thin air)."""
        fdm, pm = self.fdm, self._pm
        with self._before_time_0():
            if pm.hasNode("propulsion/magneto_cmd"):
                fdm["propulsion/magneto_cmd"] = 3  # both (FGPiston: 0 off, 1 left, 2 right, 3 both)
            if pm.hasNode("propulsion/cutoff_cmd"):
                fdm["propulsion/cutoff_cmd"] = 0  # fuel on (FGTurbine, FGTurboProp)
            dead = self._engines_run()
            for opening in CRANK_THROTTLES:
                self._apply({"throttle": opening})
                fdm["propulsion/starter_cmd"] = 1
                for _ in range(max(1, round(CRANK_S / self.dt))):
                    fdm.run()
                    if not self._engines_run():
                        break
                fdm["propulsion/starter_cmd"] = 0
                for _ in range(round(CRANK_SETTLE_S / self.dt)):  # it runs once it runs off the starter
                    fdm.run()
                dead = self._engines_run()
                if not dead:
                    break
            if dead:
                spec = catalog.propulsion(self.name).engines
                which = ", ".join(f"engine {i} ({spec[i].kind} {spec[i].file})" for i in dead)
                why = (f"{self.name}'s {which} does not run: JSBSim's set-running leaves it stopped, and "
                       f"{CRANK_S:g} s on its starter at each of throttle "
                       f"{', '.join(f'{t:g}' for t in CRANK_THROTTLES)} does not start it")
                if on_ground:
                    raise InvalidArgument("engines_running", f"{why}; start {self.name} airborne or with its "
                                                             "engines off (engines_running false), or fly another "
                                                             "aircraft", value=True)
                _log.warning("%s; it starts airborne with it stopped, gliding", why)
            # The start's throttle from here on, its engine as it ran (as set-running leaves one: at
            # the steady state of full throttle): a ground start settles it (_settle_engines), an
            # airborne one in its first seconds.
            self._apply({"throttle": throttle})

    def _settle_engines(self) -> None:
        """Bring a ground start's running engines to the steady state of its throttle before
        time 0 (:meth:`_before_time_0`). JSBSim's set-running leaves them at the steady state of
        full throttle (FGPropulsion::InitRunning sets every throttle to 1, then runs
        GetSteadyState), and a ground start spent its first seconds spooling down from there
        against its brakes: a Boeing314 at a 1000 m field, leaned, 4 x 3600 lbf for a second on a
        hull without brakes, still sliding at 0.9 m/s after 5 s; the dr1, which has none either,
        rolling off at 6 m/s. The whole model runs (its flight controls may drive its engines:
        the p51d's manifold-pressure throttle, the c310's mixture), SETTLE_CHUNK_S at a time, put
        back at rest at its start after each, until no engine's thrust moves by more than
        SETTLE_THRUST_LBF or SETTLE_THRUST_RATIO of it in a chunk, for at most SETTLE_MAX_S."""
        fdm = self.fdm
        steps = max(1, round(SETTLE_CHUNK_S / self.dt))
        with self._before_time_0():
            last = [g() for g in self._get_thrust]
            for _ in range(math.ceil(SETTLE_MAX_S / SETTLE_CHUNK_S)):
                for _ in range(steps):
                    fdm.run()
                now = [g() for g in self._get_thrust]
                if not fdm.run_ic():
                    raise SortieError(f"JSBSim refused the initial conditions of {self.name!r}")
                steady = all(abs(t - t0) <= max(SETTLE_THRUST_LBF, SETTLE_THRUST_RATIO * abs(t))
                             for t, t0 in zip(now, last))
                if steady or not all(math.isfinite(t) for t in now):
                    break
                last = now

    def _transfer_fuel(self) -> None:
        """Keep the feed tanks at their start's fuel from the other fuel tanks (see
        _bind_propulsion), each reserve tank giving in proportion to what it holds."""
        feed = [t.get_double_value() for t in self._feed_tanks]
        need = [max(target - lbs, 0.0) for target, lbs in zip(self._feed_target_lbs, feed)]
        total_need = sum(need)
        if not total_need > 0.0:
            return
        reserve = [max(t.get_double_value(), 0.0) for t in self._reserve_tanks]
        available = sum(reserve)
        if not available > 0.0:
            return
        move = min(total_need, available)
        for tank, lbs, d in zip(self._feed_tanks, feed, need):
            tank.set_double_value(lbs + d * (move / total_need))
        for tank, lbs in zip(self._reserve_tanks, reserve):
            tank.set_double_value(lbs - lbs * (move / available))

    def _terrain_msl_m(self, lat_deg, lon_deg) -> np.ndarray:
        """The surface (m MSL: the terrain, the sea surface over water, no data is sea level;
        :func:`terrain_msl_m`) at the query points; the result may be this aircraft's own
        buffer, valid until the next query."""
        if self._heights_of is not None and isinstance(lat_deg, np.ndarray) and lat_deg.size <= self._terr.size:
            out = self._terr[:lat_deg.size]  # the CG alone far from the ground; every contact near it
            np.copyto(out, 0.0, where=np.isnan(self._heights_of(lat_deg, lon_deg, out)))
            if self._has_water:
                np.maximum(out, WATER_LEVEL_MSL_M, out=out)
            return out
        return terrain_msl_m(self.terrain, lat_deg, lon_deg)

    def _contact_terrain(self, lat, lon, alt_m, cg_in, phi, theta, psi, ahead_ned):
        """(terrain under the CG now then under each contact, contact altitudes), metres MSL.

        Contacts are placed from the CG with the attitude, shifted by ``ahead_ned``
        (metres), on the local tangent plane (fdm.contacts.place_contacts).
        """
        p_lat, p_lon, h = contact_points(lat, lon, alt_m, cg_in, phi, theta, psi, ahead_ned,
                                         self._contact_locations_in)
        return self._terrain_msl_m(p_lat, p_lon), h

    def _check_wheels_on_terrain(self, ic: InitialConditions, lon: float, alt_m: float, cg_in) -> None:
        """A ground start whose wheel (placed level at heading, as :meth:`_start` places them)
        stands where the terrain has no data: InvalidArgument naming lat_deg and the wheel's
        place. No data reads as sea level (:func:`terrain_msl_m`), so a landplane parked within
        a wheel base of a DEM's edge was refused as standing on water, on dry ground."""
        p_lat, p_lon, _ = contact_points(ic.lat_deg, lon, alt_m, cg_in, 0.0, 0.0, math.radians(ic.heading_deg),
                                         np.zeros(3), self._contact_locations_in)
        gear = np.flatnonzero(~self._structure) + 1  # the CG comes first
        raw = np.asarray(self.terrain.heights(p_lat[gear], p_lon[gear]).height_msl_m, np.float64)
        off = np.flatnonzero(np.isnan(raw))
        if off.size:
            k = gear[off[0]]
            raise InvalidArgument("lat_deg", f"a wheel of {self.name} at ({ic.lat_deg}, {ic.lon_deg}) stands outside "
                                             f"the terrain: no terrain data at ({float(p_lat[k]):.6f}, "
                                             f"{float(p_lon[k]):.6f}), {off.size} of its {gear.size} wheels off it; "
                                             "move it onto the terrain, a wheel base from its edge", value=ic.lat_deg)

    def _rest_height_ft(self) -> float:
        """CG height above level ground when the lowest wheel just touches (attitude level)."""
        gear = [c.location_in[2] for c in self.contacts if c.kind == "gear"]
        if not gear:
            raise InvalidArgument("on_ground", f"aircraft {self.name!r} has no landing gear")
        return (self._get_cg_in[2]() - min(gear)) / 12.0

    def _set_ic(self, ic: InitialConditions, lon: float, terrain_m: float, agl_ft: float) -> None:
        """JSBSim's initial conditions of ``ic`` at ``agl_ft`` above ``terrain_m`` (m MSL)."""
        fdm = self.fdm
        fdm["ic/lat-geod-deg"] = ic.lat_deg
        fdm["ic/long-gc-deg"] = lon
        fdm["ic/terrain-elevation-ft"] = terrain_m / FT_M
        fdm["ic/h-agl-ft"] = agl_ft
        fdm["ic/psi-true-deg"] = ic.heading_deg
        fdm["ic/vt-fps"] = ic.speed_mps / FT_M

    def _start(self, ic: InitialConditions) -> None:
        fdm = self.fdm
        lon = float(wrap_lon_deg(ic.lon_deg))
        t_m = float(self._terrain_msl_m([ic.lat_deg], [lon])[0])
        mixture = 1.0
        if ic.on_ground:
            # JSBSim computes the CG (inertia/cg-*-in) only when its models run (FGMassBalance::Run,
            # first called by run_ic): after load_model it reads 0, which would shift every contact
            # by the CG's structural offset (a 737's 15.5 m). One run_ic where the aircraft starts
            # sets it; the CG does not depend on position or attitude, so the placement below holds.
            self._set_ic(ic, lon, t_m, 0.0)
            if not fdm.run_ic():
                raise SortieError(f"JSBSim refused the initial conditions of {self.name!r}")
            mixture = self._field_mixture() if ic.engines_running else 1.0
            # Level, on the highest terrain under any wheel; no structure point may be below its terrain.
            agl_ft = self._rest_height_ft()
            cg_in = [g() for g in self._get_cg_in]
            alt_m = t_m + agl_ft * FT_M
            terr, h = self._contact_terrain(ic.lat_deg, lon, alt_m, cg_in, 0.0, 0.0,
                                            math.radians(ic.heading_deg), np.zeros(3))
            gear = ~self._structure
            t_m = float((terr[1:][gear] - (h[gear] - h[gear].min())).max())
            clearance = h - h[gear].min() + t_m - terr[1:]
            if (clearance[self._structure] < 0).any():
                raise InvalidArgument("lat_deg", f"the ground at ({ic.lat_deg}, {ic.lon_deg}) is too steep for "
                                                 f"{self.name} to stand on (a wing tip or the tail is below "
                                                 "the terrain)", value=ic.lat_deg)
            if self._ditches and _wet(terr[1:][gear]).any():
                self._check_wheels_on_terrain(ic, lon, alt_m, cg_in)
                raise InvalidArgument("lat_deg", f"the ground at ({ic.lat_deg}, {ic.lon_deg}) is water (height <= "
                                                 f"sea level, {WATER_LEVEL_MSL_M:g} m): {self.name} is a "
                                                 "landplane and cannot stand on it", value=ic.lat_deg)
        else:
            alt_msl = ic.alt_m if ic.alt_ref == "msl" else t_m + ic.alt_m
            if alt_msl <= t_m:
                surface = "the sea surface" if self._has_water and _wet(np.array([t_m]))[0] else "the terrain"
                raise InvalidArgument("alt_m", f"an airborne start must be above {surface} ({t_m:.1f} m MSL "
                                               "here); use on_ground=True to start on the ground", value=ic.alt_m)
            agl_ft = (alt_msl - t_m) / FT_M
        self._set_ic(ic, lon, t_m, agl_ft)
        gear_down = ic.on_ground if ic.gear_down is None else ic.gear_down
        throttle = 0.0 if ic.on_ground else self._controls.throttle

        def initialise(mixture: float) -> None:
            if not fdm.run_ic():
                raise SortieError(f"JSBSim refused the initial conditions of {self.name!r}")
            if ic.engines_running:
                fdm["propulsion/set-running"] = -1
            self._apply(validate_controls({"gear_down": gear_down, "mixture": mixture, "throttle": throttle,
                                           "brakes": 1.0 if ic.on_ground and ic.speed_mps == 0 else 0.0}))
            # Not where a failed trim left an engine's state non-finite (the c182 at 80 m/s): the
            # trim after a lean retry fails as it did, TrimFailed.
            if ic.engines_running and self._engines_run() and all(math.isfinite(g()) for g in self._get_thrust):
                self._crank(throttle, ic.on_ground)
            if ic.engines_running and ic.on_ground and self._must_run:
                self._settle_engines()

        initialise(mixture)
        self._terrain_ft = t_m / FT_M
        self._terrain_cg_ft = self._terrain_ft
        self._steps = 0
        self._next_refresh = 0
        self._next_check = 1  # the first step is checked (and refreshes the terrain)
        self._quiet_until = -1
        self._band_floor_ft = math.inf
        self._near = False
        self._alt_ft = agl_ft + t_m / FT_M
        self._diverged = False
        self._last_good = (ic.lat_deg, lon, self._alt_ft * FT_M)  # lat, lon, alt m: the last finite check
        self._trim_gamma_deg = 0.0
        self._engines_running = ic.engines_running
        # JSBSim's ground trim settles height, pitch and roll on the contacts; it needs
        # them to span a plane (JSBSim 1.3.3 crashes the process on SGS and minisgs, whose
        # six contacts all sit at the origin). Otherwise, or when it fails, the placement
        # at rest height stands and the gear settles in the first steps.
        if ic.on_ground:
            if _spans_a_plane(self._contact_locations_in):
                try:
                    fdm.do_trim(2)
                except self._trim_error:
                    pass
        elif ic.trim:
            try:
                self.trim()
            except TrimFailed:
                # Full rich high up starves a piston engine of the power to hold level flight
                # (a c172p or c182 at 3000 m fails at every speed). A pilot leans: to the air's
                # density ratio sigma, which keeps the fuel-air ratio of full rich at sea level
                # (fuel flow goes with the mixture, air flow with the density). Tried only when
                # full rich fails: a model tuned otherwise (the c310) keeps its full-rich trim.
                sigma = fdm["atmosphere/sigma"]
                if not (self.n_engines and ic.engines_running and math.isfinite(sigma)
                        and 0.0 < sigma < LEAN_BELOW_SIGMA):
                    raise
                initialise(sigma)
                self.trim()
        self._detector = EventDetector(self._detector_limits, on_ground=ic.on_ground)
        self._set_penetration_limits()
        self._feed_target_lbs = [t.get_double_value() for t in self._feed_tanks]

    def _set_penetration_limits(self, weight_lbs: float | None = None) -> None:
        """How deep below its terrain each contact may be before it is inside the ground (a
        crash): ``max_penetration_m`` for a structure point; for a wheel also its strut's
        compression at rest (static_compressions_m) times the class's ultimate load factor, the
        most its strut compresses short of failing (ultimate load, 14 CFR 23.303 / 25.303,
        on the wheel's share of the weight). The catalog's B747 nose strut (22000 lbs/ft under
        some 100000 lbs) rests 1.56 m compressed; a c172's wheels stay under the 1 m floor."""
        springs = catalog.contact_springs_lbs_ft(self.name)
        if len(springs) != len(self.contacts):
            springs = (None,) * len(self.contacts)
        springs = [None if c.kind == "structure" else v for c, v in zip(self.contacts, springs)]
        rest = static_compressions_m(self._contact_locations_in, springs, [g() for g in self._get_cg_in],
                                     self.fdm["inertia/weight-lbs"] if weight_lbs is None else weight_lbs)
        self.penetration_limits_m = np.maximum(self.max_penetration_m, self._nz_max * rest)

    # -- controls -------------------------------------------------------------------------------

    @property
    def controls(self) -> Controls:
        return self._controls

    def set_controls(self, controls: Controls | None = None, **values) -> None:
        """Set some or all controls. Every value is checked first; if any is bad
        (NaN, infinite, out of range, unknown name) InvalidArgument names it and
        nothing at all is applied."""
        if controls is not None:
            values = {**{f: getattr(controls, f) for f in CONTROL_NAMES}, **values}
        self._apply(validate_controls(values))

    def _apply(self, values: dict) -> None:
        for name, v in values.items():
            x = (1.0 if v else 0.0) if name == "gear_down" else v * self._sign.get(name, 1.0)
            for setter in self._set[name]:
                setter(x)
            if name == "yaw":
                self._set_steer(v)
        self._controls = replace(self._controls, **values)

    def _set_controls_trusted(self, pitch=None, roll=None, yaw=None, throttle=None) -> None:
        """Autopilot use only: values already in range, finite floats; None leaves one alone.

        The autopilot sets these every tick; skipping validation and ``replace``
        saves most of :meth:`set_controls`' cost. It writes the same JSBSim
        values (negation is exact, so -x is x * -1.0 bit for bit).
        """
        c = self._controls
        if pitch is not None:
            self._set_elevator(-pitch)
        if roll is not None:
            self._set_aileron(roll)
        if yaw is not None:
            self._set_rudder(-yaw)
            self._set_steer(yaw)
        if throttle is not None:
            for setter in self._set_throttles:
                setter(throttle)
        self._controls = Controls(c.pitch if pitch is None else pitch, c.roll if roll is None else roll,
                                  c.yaw if yaw is None else yaw, c.throttle if throttle is None else throttle,
                                  c.mixture, c.flaps, c.brakes, c.gear_down)

    def trim(self) -> None:
        """JSBSim's full trim at the initial conditions; TrimFailed when it finds none.

        JSBSim trims at the *initial conditions* and restarts from them (as a
        script's ``do_simple_trim`` does), so call it at the start. The trim
        sets throttle and the trim tabs, so afterwards a centred stick
        (pitch = roll = yaw = 0) holds the trimmed flight.

        Level flight (``trim_gamma_deg`` 0) for an aircraft with engines running.
        One without (a glider), or started with its engines off (an engine-out
        exercise), cannot hold level flight: JSBSim's trim zeroes udot with the
        throttle. It is trimmed instead in the steady
        glide at the requested speed (:meth:`_trim_glide`): ``trim_gamma_deg``
        is then the glide's flight-path angle (negative, descending): what
        JSBSim's own trim does with its "gamma fallback" (FGTrim.cpp: "Can't
        trim udot with throttle, trying flight path angle"), which its Python
        binding does not expose.
        """
        self._trim_gamma_deg = 0.0
        if self.n_engines == 0 or not self._engines_running:
            self._trim_glide()
        else:
            self._do_trim("level flight")
        throttle = min(1.0, max(0.0, self.fdm["fcs/throttle-cmd-norm[0]"] if self.n_engines else 0.0))
        self._controls = replace(self._controls, pitch=0.0, roll=0.0, yaw=0.0, throttle=throttle)
        for setter in self._set["throttle"][self.n_engines:]:  # a FlightGear input the model reads
            setter(throttle)

    @property
    def trim_gamma_deg(self) -> float:
        """The flight-path angle of the last trim (degrees, negative descending): 0 for level
        flight (and for a start without trim), a glider's glide angle (:meth:`trim`)."""
        return self._trim_gamma_deg

    def _do_trim(self, what: str) -> None:
        """JSBSim's full trim of the current initial conditions; TrimFailed saying what to try."""
        try:
            self.fdm.do_trim(1)
        except self._trim_error as exc:
            raise TrimFailed(self._trim_failed_message(what, str(exc))) from None

    def _trim_failed_message(self, what: str, why: str) -> str:
        fdm = self.fdm
        speed = fdm["ic/vt-fps"] * FT_M
        alt = (fdm["ic/h-agl-ft"] + fdm["ic/terrain-elevation-ft"]) * FT_M
        return (f"{self.name}: JSBSim trim failed for {what} at {speed:.1f} m/s, {alt:.0f} m MSL ({why}); "
                f"{catalog.trim_hint(self.name, alt)}{TRIM_OFF_HINT}")

    def _glide_residual(self, alpha_deg: float, pitch_trim: float, gamma_deg: float) -> np.ndarray:
        """(udot, wdot ft/s², qdot rad/s²) at the initial conditions with this angle of attack,
        pitch trim and flight-path angle: the accelerations JSBSim's trim zeroes, evaluated
        as its trim does (the state initialised, the models run once, trim status set so the
        flight controls' filters pass their input through)."""
        fdm = self.fdm
        fdm["ic/gamma-deg"] = gamma_deg
        fdm["ic/alpha-deg"] = alpha_deg  # JSBSim keeps gamma and moves theta
        fdm["fcs/pitch-trim-cmd-norm"] = pitch_trim
        fdm.set_trim_status(True)
        try:
            fdm.run_ic()
        finally:
            fdm.set_trim_status(False)
        return np.array([fdm["accelerations/udot-ft_sec2"], fdm["accelerations/wdot-ft_sec2"],
                         fdm["accelerations/qdot-rad_sec2"]])

    def _trim_glide(self) -> None:
        """Trim an aircraft without engines, or with them off, in its steady glide at the
        requested speed.

        JSBSim's full trim zeroes udot with the throttle; with no thrust only the
        flight-path angle gamma can: drag is balanced by the weight's component
        along the path, so gamma = -atan(D/L) (equilibrium glide, Anderson,
        *Introduction to Flight*, "Gliding flight": tan(theta) = 1/(L/D)). udot
        must be within JSBSim's 1e-3 ft/s² (FGTrimAxis.cpp), i.e. gamma within
        about 0.002 degrees, so gamma is not guessed: a Newton iteration on
        (alpha, pitch trim, gamma) zeroes (udot, wdot, qdot), started from the
        L/D estimate; JSBSim's full trim at that gamma then settles every axis
        (its throttle axis already in tolerance). A model with no glide at that
        speed (no lift: a ball, a bomb, a balloon; too slow or too fast) is
        TrimFailed. A few ms for a glider (about 20 evaluations of the models).
        """
        fdm = self.fdm
        lo, hi = fdm["aero/alpha-min-rad"], fdm["aero/alpha-max-rad"]
        # JSBSim's trim searches alpha over the model's CL-max range, or -5..20 degrees if it has none.
        lo, hi = (math.degrees(lo), math.degrees(hi)) if hi > lo else (-5.0, 20.0)
        x = np.array([min(max(2.0, lo), hi), 0.0, 0.0])
        self._glide_residual(*x)  # level at 2 degrees alpha: L/D for the first estimate of gamma
        lod = fdm["forces/lod-norm"]
        x[2] = -math.degrees(math.atan(1.0 / lod)) if lod > 1.0 else -10.0
        lower = np.array([lo, -1.0, GLIDE_GAMMA_MIN_DEG])
        upper = np.array([hi, 1.0, 0.0])
        steps = np.array([1e-3, 1e-4, 1e-3])  # finite-difference steps: deg, norm, deg
        for _ in range(GLIDE_ITERATIONS):
            r = self._glide_residual(*x)
            if not np.isfinite(r).all():
                break
            if (np.abs(r) < GLIDE_TOLERANCE).all():
                fdm["ic/gamma-deg"] = x[2]
                self._do_trim(f"a steady glide at gamma {x[2]:.2f} deg")
                self._trim_gamma_deg = float(x[2])
                return
            jac = np.empty((3, 3))
            for j in range(3):
                xj = x.copy()
                xj[j] += steps[j]
                jac[:, j] = (self._glide_residual(*xj) - r) / steps[j]
            try:
                dx = np.linalg.solve(jac, -r)
            except np.linalg.LinAlgError:
                break
            # At most 5 degrees of alpha or gamma a step: Newton from a poor start can leap past stall.
            dx *= min(1.0, 5.0 / max(abs(dx[0]), abs(dx[2]), 1e-12))
            x = np.clip(x + dx, lower, upper)
        fdm["ic/gamma-deg"] = 0.0
        raise TrimFailed(self._trim_failed_message(
            "a steady glide", f"{'its engines are off' if self.n_engines else 'it has no engines'}, and no glide "
            f"at {GLIDE_GAMMA_MIN_DEG:g} to 0 degrees holds "
            "this speed with the pitch trim's authority"))

    # -- stepping -------------------------------------------------------------------------------

    @property
    def time_s(self) -> float:
        return self._get_time()

    @property
    def on_ground(self) -> bool:
        """Weight on wheels, as of the last check (every step near the ground)."""
        return self._detector.on_ground

    def crash(self, t: float, lat: float, lon: float, alt_m: float, reason: str, **detail) -> list:
        """A crash found by the host (e.g. its terrain collision check): recorded as an
        event, and the aircraft stops where it is. The event (or nothing if already down).

        A host's segment test (``reason`` SEGMENT_CRASH_REASON) gives the place where the
        aircraft's path met the terrain: the wreck rests there, not below the surface (not
        where it is, up to a world tick further on, inside the terrain), also when its own
        checks had already crashed it further along: far from the ground they run at the
        terrain refresh, which assumes slopes of at most 45 degrees, so a cliff face is found
        late (an acceptance probe's wall at 250 m/s: 13-39 m inside it)."""
        events = [] if self.crashed else self._record([self._detector._crash(t, lat, lon, alt_m, reason,
                                                                             **detail)])
        if reason == SEGMENT_CRASH_REASON:
            self._rest_at(lat, lon, alt_m)
        return events

    def _rest_at(self, lat: float, lon: float, alt_m: float) -> None:
        """The wreck (crashed: a falling one stops falling) at rest at (lat, lon) degrees,
        ``alt_m`` metres MSL or the surface there if that is higher (:func:`rest_row`)."""
        surface = self._surface_m(lat, lon)
        row = rest_row(self.raw_values(), lat, lon, max(alt_m, surface), surface)
        self._fall = None
        self.raw_values = row.copy  # shadows the method: the frozen row, a fresh list each call

    def step(self) -> list:
        """One JSBSim step with terrain coupling and event detection; the events of this step."""
        if self.crashed:
            return self._fall_advance(1)
        self._run()
        self._steps += 1
        if self._steps < self._next_check or self._quiet_check():
            return []
        return self._check()

    def advance(self, steps: int) -> list:
        """``steps`` JSBSim steps (stopping early at a crash); all their events.

        The same trajectory as calling :meth:`step` that many times, bit for
        bit, but between checks JSBSim runs in a tight loop. Far from the
        ground checks fall on multiples of the check interval, so a host that
        ticks the world at that interval (a 30 Hz world tick of 4 steps of
        1/120 s) runs each aircraft's tick as one loop and one quiet check.
        """
        if self.crashed:
            return self._fall_advance(steps)
        end = self._steps + steps
        if self._quiet_tick(steps):
            return []
        run = self._run
        events = []
        while not self.crashed:
            target = min(self._next_check, end)
            for _ in range(target - self._steps):
                run()
            if target > self._steps:
                self._steps = target
            if self._steps < self._next_check:
                break
            if not self._quiet_check():
                events += self._check()
        return events

    def run(self, seconds: float) -> list:
        """Step for ``seconds`` of simulated time (whole steps); all events."""
        return self.advance(int(round(seconds / self.dt)))

    def _quiet_tick(self, steps: int) -> bool:
        """The common tick, done here when it applies: no check due before the tick's
        end and a quiet one (:meth:`_quiet_check`) there. False, with nothing or only
        the JSBSim steps done, when the tick needs the general loop of :meth:`advance`."""
        end = self._steps + steps
        if end > self._next_check or self.crashed:
            return False
        run = self._run
        for _ in range(steps):
            run()
        self._steps = end
        if end < self._next_check:
            return True
        # _quiet_check inlined: this is the hot path of a hosted tick
        if end < self._quiet_until and self._get_alt_ft() > self._band_floor_ft \
                and self._nz_min < self._get_nz() < self._nz_max:
            self._next_check = end + self._check_steps
            return True
        return False

    def _quiet_check(self) -> bool:
        """The common check step, done here: far from the ground, no refresh due, load
        factor within limits; then the next one is scheduled. False when the full check
        (:meth:`_check`) is needed."""
        if self._steps < self._quiet_until and self._get_alt_ft() > self._band_floor_ft \
                and self._nz_min < self._get_nz() < self._nz_max:
            self._next_check = self._steps + self._check_steps
            return True
        return False

    def _check(self) -> list:
        """The full check of this step: plan, terrain heights, finish."""
        n = self._plan()
        if n == 1 and self._point_height is not None:  # far from the ground: the CG alone
            lat, lon = self._cg_lat, self._cg_lon
            # Finite here (_plan ends a diverged flight); point_height does not validate, so
            # anything out of range still goes the validated way below.
            if -90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0:
                # Floats throughout, no array: numpy's code is as cold as ours here.
                h = self._point_height(lat, lon)
                if h != h:
                    h = 0.0  # no data is sea level, as _terrain_msl_m
                if self._has_water and h < WATER_LEVEL_MSL_M:
                    h = WATER_LEVEL_MSL_M  # the sea's surface over its floor
                return self._finish([h])
        return self._finish(None if n == 0 else self._terrain_msl_m(self._q_lat[:n], self._q_lon[:n]))

    def _where(self, alt_ft):
        return math.degrees(self._get_lat_rad()), math.degrees(self._get_lon_rad()), alt_ft * FT_M

    def _record(self, events: list) -> list:
        if events:
            self.events.extend(events)
            if self._detector.crashed and not self.crashed:
                self.crashed = True
                crash = next(e for e in events if e.kind == "crash")
                if not self._start_fall(crash):
                    self._come_to_rest()
        return events

    _MOTION_COLUMNS = WRECK_MOTION_COLUMNS

    @property
    def falling(self) -> bool:
        """Whether this aircraft is a wreck falling from where it crashed (fdm.wreck)."""
        return self._fall is not None

    def _start_fall(self, crash: Event) -> bool:
        """A crash clear of the surface (not one of SURFACE_CRASH_REASONS, more than
        FALL_MIN_AGL_M above the surface where it happened) leaves a wreck that falls from
        here with the velocity it has (:meth:`_fall_advance`); True if so. Its state out is
        then the wreck's: its attitude kept, no rotation, no air data."""
        if "raw_values" in self.__dict__ or crash.detail.get("reason") in SURFACE_CRASH_REASONS:
            return False
        agl = crash.alt_msl_m - self._surface_m(crash.lat_deg, crash.lon_deg)
        if not agl > FALL_MIN_AGL_M:
            return False
        row = self.raw_values()
        for k in self._MOTION_COLUMNS:
            if k not in self._VELOCITY_COLUMNS:
                row[k] = 0.0
        row[RAW_COLUMNS["wow"]] = 0.0
        alt_m = row[RAW_COLUMNS["alt_ft"]] * FT_M
        self._fall = [row, alt_m - self._surface_m(math.degrees(row[RAW_COLUMNS["lat_rad"]]),
                                                   math.degrees(row[RAW_COLUMNS["lon_rad"]])), alt_m]
        self.raw_values = row.copy  # shadows the method; the row changes as the wreck falls
        return True

    def _surface_m(self, lat: float, lon: float) -> float:
        """The surface (m MSL, :meth:`_terrain_msl_m`) at one point."""
        return float(self._terrain_msl_m(np.array([lat], np.float64), np.array([lon], np.float64))[0])

    _VELOCITY_COLUMNS = tuple(RAW_COLUMNS[name] for name in ("v_north_fps", "v_east_fps", "v_down_fps"))

    def _fall_advance(self, steps: int) -> list:
        """``steps`` steps of a falling wreck (fdm.wreck.fall); nothing for a wreck at rest.
        Where its path meets the surface (checked once per call, between the call's start and
        end; a wreck falls a few metres a tick) it comes to rest on it, where the path crossed
        it: the WRECK_IMPACT event (its speed, and how far it fell), and from then on the
        state of a wreck at rest (:meth:`_come_to_rest`)."""
        if self._fall is None or steps <= 0:
            return []
        row, agl0, _ = self._fall
        c = RAW_COLUMNS
        lat0, lon0 = math.degrees(row[c["lat_rad"]]), math.degrees(row[c["lon_rad"]])
        h0 = row[c["alt_ft"]] * FT_M
        v0 = [row[k] * FT_M for k in self._VELOCITY_COLUMNS]
        lat, lon, h, v, a = fall(lat0, lon0, h0, v0, self.dt, steps)
        t0 = row[c["time_s"]]
        surface = self._surface_m(lat, lon)
        if h - surface > 0.0:
            self._fall[1] = h - surface
            self._fall_row(row, lat, lon, h, v, a, t0 + steps * self.dt, surface)
            return []
        # Where the step's straight path meets the surface (ECEF, so across the antimeridian too).
        f = float(impact_fraction(agl0, h - surface))
        p0, p1 = geodetic_to_ecef([lat0, lat], [lon0, lon], [h0, h])
        lat_i, lon_i, _ = (float(x) for x in ecef_to_geodetic(p0 + f * (p1 - p0)))
        surface = self._surface_m(lat_i, lon_i)
        t = t0 + f * steps * self.dt
        speed = math.sqrt(sum(x * x for x in v))
        self._fall_row(row, lat_i, lon_i, surface, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), t, surface)
        for k in self._MOTION_COLUMNS:  # at rest (the row is raw_values' own, as _come_to_rest's)
            row[k] = 0.0
        row[c["nz_g"]] = 1.0
        event = Event(WRECK_IMPACT, t, lat_i, lon_i, surface,
                      {"speed_mps": round(speed, 3), "fell_m": round(self._fall[2] - surface, 3)})
        self._fall = None
        self.events.append(event)
        return [event]

    def _fall_row(self, row: list, lat: float, lon: float, h: float, v_ned, a_ned, t: float,
                  surface: float) -> None:
        """Write a falling wreck's place, velocity and acceleration into its state ``row``:
        the acceleration as JSBSim's body-axis udot/vdot/wdot (the attitude is fixed, so the
        body rates are 0 and the body acceleration is the local one rotated into the body),
        the load factor Nz as the body-z specific force over g (JSBSim's accelerations/Nz)."""
        c = RAW_COLUMNS
        row[c["time_s"]] = t
        row[c["lat_rad"]], row[c["lon_rad"]], row[c["alt_ft"]] = math.radians(lat), math.radians(lon), h / FT_M
        for k, x in zip(self._VELOCITY_COLUMNS, v_ned):
            row[k] = x / FT_M
        row[c["terrain_ft"]] = surface / FT_M
        body = ned_to_body_matrix(row[c["phi_rad"]], row[c["theta_rad"]], row[c["psi_rad"]])
        acc = [sum(body[i][j] * a_ned[j] for j in range(3)) for i in range(3)]
        row[c["udot_fps2"]], row[c["vdot_fps2"]], row[c["wdot_fps2"]] = (x / FT_M for x in acc)
        # Specific force = acceleration - gravity (gravity is +g down in NED).
        f_z = acc[2] - body[2][2] * G0_MPS2
        row[c["nz_g"]] = -f_z / G0_MPS2

    def _come_to_rest(self) -> None:
        """From a crash on, the state out is the wreck at rest where it came down (see
        _MOTION_COLUMNS); a diverged state has its own frozen row (_end_diverged)."""
        if "raw_values" in self.__dict__:  # already frozen
            return
        row = self.raw_values()
        for k in self._MOTION_COLUMNS:
            row[k] = 0.0
        row[RAW_COLUMNS["nz_g"]] = 1.0
        self.raw_values = row.copy  # shadows the method: the frozen row, a fresh list each call

    # A check step has two halves so that a host stepping many aircraft
    # (fdm.fleet.Fleet) can answer all their terrain queries in one batch:
    # _plan writes the points this step needs into _q_lat/_q_lon, the host
    # looks their heights up, _finish applies them.

    def _plan(self) -> int:
        """How many terrain points this check step needs (written to _q_lat/_q_lon[:n]):
        0 (none due), 1 (under the CG, far from the ground) or 1 + contacts (near it)."""
        alt_ft = self._get_alt_ft()
        self._alt_ft = alt_ft
        self._near = near = alt_ft - self._terrain_ft < self._near_ground_ft
        # The CG's position as floats for _couple (also _q_lat/_q_lon[0], for a batch query).
        self._cg_lat = lat = math.degrees(self._get_lat_rad())
        self._cg_lon = lon = math.degrees(self._get_lon_rad())
        if not (lat - lat == 0.0 and lon - lon == 0.0 and alt_ft - alt_ft == 0.0):
            self._diverged = True  # JSBSim's state is NaN or infinite: _finish ends the flight
            return 0
        if near:
            cg = self._get_cg_in
            dt_ft = FT_M * self.dt
            place_contacts(lat, lon, alt_ft * FT_M,
                           cg[0](), cg[1](), cg[2](), *(g() for g in self._get_euler),
                           self._get_vn() * dt_ft, self._get_ve() * dt_ft,
                           self._contact_locations_in, self._q_lat, self._q_lon, self._q_alt)
            return self._q_lat.size
        if self._steps >= self._next_refresh:
            self._q_lat[0] = lat
            self._q_lon[0] = lon
            return 1
        return 0

    def _finish(self, terr) -> list:
        """Events of this check step, given the terrain (m MSL, no NaN) at the planned points or None."""
        if self._diverged:
            return self._end_diverged()
        events = self._check_g() if terr is None else self._couple(terr)
        if self._near or self._detector._g_since is not None or self._detector.on_ground:
            self._next_check = self._steps + 1
            self._quiet_until = -1
        else:
            # Far from the ground checks fall on multiples of _check_steps (refreshes too).
            cs = self._check_steps
            self._next_check = min((self._steps // cs + 1) * cs, self._next_refresh)
            self._quiet_until = self._next_refresh
            self._band_floor_ft = self._terrain_ft + self._near_ground_ft
        return events

    def _end_diverged(self) -> list:
        """JSBSim's state went NaN or infinite (a model flown far outside its envelope): a
        crash where the aircraft last was finite (its last check of the terrain, at most
        MAX_REFRESH_S ago), and from then on its state out is that place at rest, heading
        north, never the non-finite numbers (hosts, streams and recordings stay finite)."""
        lat, lon, alt_m = self._last_good
        t = self._get_time()
        row = [0.0] * RAW_WIDTH
        row[RAW_COLUMNS["time_s"]] = t
        row[RAW_COLUMNS["lat_rad"]] = math.radians(lat)
        row[RAW_COLUMNS["lon_rad"]] = math.radians(lon)
        row[RAW_COLUMNS["alt_ft"]] = alt_m / FT_M
        row[RAW_COLUMNS["nz_g"]] = 1.0
        row[RAW_COLUMNS["terrain_ft"]] = self._terrain_cg_ft
        self.raw_values = row.copy  # shadows the method: the frozen row, a fresh list each call
        return self._record([self._detector._crash(t, lat, lon, alt_m, "state diverged")])

    def _ditch(self, t, lat, lon, alt_m, terr) -> list:
        """The ditching crash when a wheel with weight on it has water under it (else nothing)."""
        under = terr[1:][self._gear_at]
        wet = _wet(under)
        if not wet.any():
            return []
        wheels = [k for k in np.flatnonzero(wet) if self._gear_wow[k]() > 0.5]
        if not wheels:
            return []
        return self._detector.ditched(t, lat, lon, alt_m, gear_units=[self.contacts[self._gear_at[k]].index
                                                                      for k in wheels],
                                      terrain_msl_m=float(under[wheels].max()), sink_rate_mps=self._get_vd() * FT_M)

    def _check_g(self) -> list:
        """Far from the ground between refreshes only the load factor can end the flight."""
        nz = self._get_nz()
        if self._nz_min < nz < self._nz_max and self._detector._g_since is None:
            return []
        return self._record(self._detector.update(self._get_time(), *self._where(self._alt_ft), False, False,
                                                  self._get_vd() * FT_M, nz))

    def _couple(self, terr) -> list:
        """Apply the terrain under the aircraft (and its contacts when near); see the module docstring."""
        t = self._get_time()
        alt_ft = self._alt_ft
        lat, lon = self._cg_lat, self._cg_lon
        alt_m = alt_ft * FT_M
        self._last_good = (lat, lon, alt_m)
        events = []
        self._terrain_cg_ft = terr[0] / FT_M
        if self._near:
            if terr.size > 1:
                c_min, elevation_m, struct_hit = ground_clearance(self._q_alt, terr, self._structure)
            else:
                c_min, elevation_m, struct_hit = alt_m - terr[0], float(terr[0]), False
            self._terrain_ft = elevation_m / FT_M
            self._set_terrain_ft(self._terrain_ft)
            if c_min < -self.max_penetration_m:  # every contact's limit is at least that
                if terr.size > 1:
                    depth = terr[1:] - self._q_alt
                    k = int(np.argmax(depth - self.penetration_limits_m))
                    if depth[k] > self.penetration_limits_m[k]:
                        events += self._detector.terrain_crash(t, lat, lon, alt_m, float(depth[k]))
                else:
                    events += self._detector.terrain_crash(t, lat, lon, alt_m, -c_min)
            wow = self._get_wow() > 0.5
            events += self._detector.update(t, lat, lon, alt_m, wow, struct_hit,
                                            self._get_vd() * FT_M, self._get_nz(),
                                            math.hypot(self._get_vn(), self._get_ve()) * FT_M if struct_hit
                                            else math.inf)
            if wow and self._ditches:
                events += self._ditch(t, lat, lon, alt_m, terr)
        elif terr[0] - alt_m > self.max_penetration_m:
            # Far from the ground as of the last refresh, and the terrain now above the CG: the
            # terrain rose faster than the refresh assumes (a cliff face: slopes of at most 45
            # degrees), and the aircraft is inside it. A crash where it is (a host's segment test
            # moves it to where the path met the terrain, server.world), not the terrain handed
            # to JSBSim, whose gear forces threw an aircraft 950 m inside a wall to -4.6 g first.
            events += self._detector.terrain_crash(t, lat, lon, alt_m, terr[0] - alt_m)
        else:
            self._terrain_ft = self._terrain_cg_ft
            self._set_terrain_ft(self._terrain_ft)
            # Far from the ground: only the load factor can end the flight; and the
            # detector hears of leaving the near band without the take-off debounce.
            # Airborne with the load factor within limits it has nothing to do: not called
            # (each call costs, its code cold after the JSBSim steps between refreshes).
            d, nz = self._detector, self._get_nz()
            if not d.airborne or d.on_ground or d._g_since is not None or not self._nz_min < nz < self._nz_max:
                events += d.update(t, lat, lon, alt_m, False, False, self._get_vd() * FT_M, nz)
        if self._steps >= self._next_refresh:
            if self._feed_tanks:  # at least every MAX_REFRESH_S: the Concorde's collectors last 5 s
                self._transfer_fuel()
            fuel_lbs = self._get_fuel_lbs()
            if fuel_lbs <= 0.0 and not self._detector.out_of_fuel:
                events += self._detector.fuel(t, lat, lon, alt_m, fuel_lbs * LB_KG)
            # Near-ground band: the set distance plus twice what can be flown before the next refresh.
            vt_ft = self._get_vt_fps()
            step_ft = max(vt_ft, 1.0) * self.dt
            self._near_ground_ft = self._near_ground_base_ft + 2.0 * step_ft * self._refresh_steps
            interval = self._refresh_steps
            if not self._near:
                # Above the band the refresh may wait until the aircraft could have used half the
                # spare height: flown (horizontally or down) at most vt per second, over slopes of
                # at most 45 degrees (higher cliffs than near_ground_m are the band's job).
                spare_ft = alt_ft - self._terrain_ft - self._near_ground_ft
                interval = min(max(int(spare_ft / (4.0 * step_ft)), self._refresh_steps), self._max_refresh_steps)
            cs = self._check_steps
            self._next_refresh = -(-(self._steps + interval) // cs) * cs  # on a check step
        return self._record(events)

    # -- state out ------------------------------------------------------------------------------

    def raw_state(self, out: np.ndarray | None = None) -> np.ndarray:
        """The raw snapshot row (see fdm.state.RAW_PROPERTIES), into ``out`` if given."""
        row = np.empty(RAW_WIDTH) if out is None else out
        row[:] = self.raw_values()
        return row

    def raw_values(self) -> list:
        """The raw snapshot as a list of floats: the cheapest state out for a host that
        stacks many (``fdm.state.state_arrays(np.array(rows))`` converts them at once)."""
        values = list(map(operator.call, self._raw_getters))
        values.append(self._terrain_cg_ft)
        return values

    def state(self) -> AircraftState:
        """The current state in SI (fdm.state.AircraftState)."""
        return AircraftState.from_raw(self.raw_state(), self.geoid_undulation_m)

    def fuel_kg(self) -> float:
        """Fuel on board (kg); 0 for a model without tanks."""
        return self._get_fuel_lbs() * LB_KG if self.has_fuel else 0.0

    def set_fuel_kg(self, kg: float) -> None:
        """Spread ``kg`` of fuel evenly over the tanks (tests, scenario set-up)."""
        if not (math.isfinite(kg) and kg >= 0):
            raise InvalidArgument("fuel_kg", "must be finite and >= 0", value=kg)
        tanks = 0
        while self._pm.hasNode(f"propulsion/tank[{tanks}]/contents-lbs"):
            tanks += 1
        if tanks == 0 and kg > 0:
            raise InvalidArgument("fuel_kg", f"aircraft {self.name!r} has no fuel tanks", value=kg)
        before_lbs = self._get_fuel_lbs() if self.has_fuel else 0.0
        for i in range(tanks):
            self.fdm[f"propulsion/tank[{i}]/contents-lbs"] = kg / LB_KG / tanks
        self._feed_target_lbs = [t.get_double_value() for t in self._feed_tanks]  # what JSBSim's tanks took
        # JSBSim's weight follows at its next step; the struts' limits follow the fuel now.
        self._set_penetration_limits(self.fdm["inertia/weight-lbs"] - before_lbs + kg / LB_KG)


# Speeds tried by trim_speeds (m/s): the catalog survey's grid, from a paraglider's to a jet's.
TRIM_SCAN_SPEEDS = catalog.TRIM_SURVEY_SPEEDS
_trim_speeds: dict = {}  # (model, altitude to 100 m, speeds) -> the speeds that trimmed


def trim_speeds(name: str, alt_m: float = 1500.0, speeds=TRIM_SCAN_SPEEDS) -> tuple:
    """The speeds (m/s) of ``speeds`` at which ``name`` trims at ``alt_m`` MSL over flat
    ground: level, or a glider's glide. What TrimFailed's message suggests.

    Opt-in, not part of a failing start: each speed is a whole start and trim, a few ms
    where JSBSim's trim converges but up to tens of seconds where it wanders (the B17, the
    ah1s) and JSBSim cannot be interrupted. Cached per (model, altitude to 100 m).
    """
    name = catalog.resolve(name)
    key = (name, round(alt_m, -2), tuple(speeds))
    if key not in _trim_speeds:
        ok = []
        for v in speeds:
            try:
                Aircraft(name, FlatTerrain(0.0), InitialConditions(0.0, 0.0, key[1], speed_mps=float(v)))
            except TrimFailed:
                continue
            ok.append(v)
        _trim_speeds[key] = tuple(ok)
    return _trim_speeds[key]
