"""The aircraft catalog shipped in the ``jsbsim`` wheel.

An aircraft is a folder ``aircraft/NAME/`` holding ``NAME.xml`` whose root
element is ``<fdm_config>`` (JSBSim's model file); that is exactly what
``FGFDMExec.load_model(NAME)`` loads, but for a model whose files carry a unit error JSBSim
cannot see (a propeller's diameter: :func:`model_paths`).
"""

from __future__ import annotations

import difflib
import math
import re
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

from sortie.errors import NotFound, SortieError

# Aircraft classes select autopilot gains and crash limits. Names not listed
# are classified from the model (jet engines and a high-g FCS make a fighter).
CLASS_OF = {
    "c172p": "light", "c172r": "light", "c172x": "light", "c182": "light", "c310": "light",
    "pa28": "light", "J3Cub": "light", "dr1": "light", "Camel": "light", "p51d": "light",
    "pc7": "light", "t6texan2": "light", "DHC6": "light", "L410": "light",
    "f16": "fighter", "f15": "fighter", "f22": "fighter", "f104": "fighter", "A4": "fighter",
    "F4N": "fighter", "F80C": "fighter", "T37": "fighter", "T38": "fighter", "x24b": "fighter",
    "737": "transport", "787-8": "transport", "A320": "transport", "B747": "transport",
    "MD11": "transport", "C130": "transport", "global5000": "transport", "fokker100": "transport",
    "fokker50": "transport", "Concorde": "transport", "B17": "transport", "XB-70": "transport",
}


# The JSBSim step (s) an aircraft may run at. Up to DT_MAX_S every model of the catalog whose
# gear holds it at rest at 120 Hz stays at rest on flat ground (10 s after a ground start:
# no take-off, crash, drift or bounce). Measured on the catalog (JSBSim 1.3.3): at 1/50 s all
# stay; at 1/40 s the J3Cub creeps 1 m; at 1/30 s the Pterosaur and the t6texan2 hop off their
# gear; at 1/15 s the A4, B747, c310 and J3Cub crash, at 1/10 s most of the catalog. JSBSim's
# gear is an explicit spring and damper: too long a step for its stiffness and it pumps energy in.
# (Not at rest even at 120 Hz, whatever the bound: minisgs (stable at 1e-4 s only), SGS, paraglider,
# ball, ballx, F450; the ZLT-NT creeps, 3 cm in 10 s at 1/50 s. The dr1 and wrightFlyer1903 rolled
# off on the full-throttle burst a ground start began with; started at idle since
# (fdm.aircraft.Aircraft._settle_engines) they rest, the wrightFlyer1903 creeping 9 cm in 10 s at
# 1/50 s.)
DT_MIN_S = 1e-4
DT_MAX_S = 1.0 / 50.0


def root_dir() -> Path:
    import jsbsim

    return Path(jsbsim.get_default_root_dir())


@lru_cache(maxsize=4)
def list_aircraft(root: str | None = None) -> tuple[str, ...]:
    """Names of the loadable aircraft models, sorted case-insensitively."""
    base = Path(root) if root else root_dir()
    names = []
    for d in (base / "aircraft").iterdir():
        f = d / f"{d.name}.xml"
        if d.is_dir() and f.is_file() and _is_fdm_config(f):
            names.append(d.name)
    return tuple(sorted(names, key=str.lower))


def _is_fdm_config(path: Path) -> bool:
    head = path.read_text(errors="replace")[:4000]
    return re.search(r"<fdm_config\b", head) is not None


def resolve(name: str, root: str | None = None) -> str:
    """The catalog's spelling of ``name`` (case-insensitive); NotFound with suggestions."""
    names = list_aircraft(root)
    if name in names:
        return name
    by_lower = {n.lower(): n for n in names}
    if name.lower() in by_lower:
        return by_lower[name.lower()]
    close = difflib.get_close_matches(name.lower(), list(by_lower), n=3)
    hint = f"; did you mean {', '.join(by_lower[c] for c in close)}?" if close else ""
    raise NotFound(f"aircraft {name!r} is not in the JSBSim catalog ({len(names)} aircraft){hint}")


@lru_cache(maxsize=256)
def is_rotorcraft(name: str, root: str | None = None) -> bool:
    """Whether a catalog model flies on rotors (a JSBSim <rotor> thruster, in its own folder
    or among the engine files its thrusters name): the catalog's ah1s; False for a name the
    catalog does not hold."""
    base = Path(root) if root else root_dir()
    try:
        folder = base / "aircraft" / resolve(name, root)
    except NotFound:
        return False
    texts = [f.read_text(errors="replace") for f in folder.rglob("*.xml")]
    thrusters = {m for t in texts for m in re.findall(r'<thruster\s+file="([^"]+)"', t)}
    texts += [(base / "engine" / f"{t}.xml").read_text(errors="replace") for t in thrusters
              if (base / "engine" / f"{t}.xml").is_file()]
    return any(re.search(r"<rotor\b", t) for t in texts)


# The catalog's flying boats: water is their ground, so they are exempt from ditching (a
# landplane's wheels on water, fdm.aircraft). JSBSim has no contact type or flag for water (its
# contacts are BOGEY or STRUCTURE): a model says it only in its text, so they are listed by
# name, found in the jsbsim 1.3.3 wheel's catalog by "flying boat", "seaplane", "amphibian",
# "hull" and "float": the Boeing314 (its hull and sponsons are BOGEY contacts, "hull in water")
# and the Short_S23 ("flying boat", the hull's forces in a hydrodynamics system). No
# amphibian (wheels and hull) or floatplane is in it.
WATER_AIRCRAFT = frozenset({"Boeing314", "Short_S23"})


def lands_on_water(name: str) -> bool:
    """Whether a catalog model (its catalog spelling) alights on water: a flying boat."""
    return name in WATER_AIRCRAFT


@dataclass(frozen=True)
class EngineSpec:
    """One ``<engine>`` of a model's ``<propulsion>``, in JSBSim's engine order."""

    kind: str  # its file's root element: piston_engine, turbine_engine, turboprop_engine, electric_engine, ...
    file: str  # the engine file's name as the model gives it
    feeds: tuple  # the tanks it draws from (<feed>: JSBSim tank indices)
    thruster: str = ""  # its <thruster file="...">, the name as the model gives it


@dataclass(frozen=True)
class PropulsionSpec:
    """What a model file says of its engines and tanks (:func:`propulsion`)."""

    engines: tuple  # EngineSpec, in JSBSim's engine order
    tank_types: tuple  # each tank's type attribute ("FUEL", "OXIDIZER"), in JSBSim's tank order
    moves_fuel: bool  # a system of the model moves fuel between its tanks itself (FGTank external flow)


def _model_part(folder: Path, section, ET):
    """A section of a model file, or the file of its own it names (``<propulsion file="..."/>``:
    FGModelLoader opens it from the aircraft's folder, ``.xml`` appended when missing)."""
    ref = section.get("file") if section is not None else None
    if not ref:
        return section
    path = next((p for p in (folder / ref, folder / f"{ref}.xml") if p.is_file()), None)
    return ET.parse(path).getroot() if path is not None else None


def _engine_file(folder: Path, base: Path, ref: str) -> Path | None:
    """An engine or thruster file a model names, where JSBSim finds it (FGPropulsion::FindFullPathName,
    ``.xml`` appended when missing): the aircraft's own ``Engines/`` folder, then the catalog's
    ``engine/``; None where neither holds it."""
    for path in (folder / "Engines" / ref, folder / "Engines" / f"{ref}.xml", base / "engine" / ref,
                 base / "engine" / f"{ref}.xml"):
        if ref and path.is_file():
            return path
    return None


@lru_cache(maxsize=256)
def propulsion(name: str, root: str | None = None) -> PropulsionSpec:
    """A catalog model's engines (kind, file, feed tanks, thruster) and tanks, from its files. An
    engine file is looked up as JSBSim does (:func:`_engine_file`); a kind it cannot read is ''.
    Empty for a name or file that cannot be read."""
    import xml.etree.ElementTree as ET

    base = Path(root) if root else root_dir()
    empty = PropulsionSpec((), (), False)
    try:
        folder = base / "aircraft" / resolve(name, root)
        section = _model_part(folder, ET.parse(folder / f"{folder.name}.xml").getroot().find("propulsion"), ET)
    except (NotFound, OSError, ET.ParseError):
        return empty
    if section is None:
        return empty
    engines = []
    for el in section.findall("engine"):
        ref = el.get("file", "")
        kind = ""
        path = _engine_file(folder, base, ref)
        if path is not None:
            try:
                kind = ET.parse(path).getroot().tag
            except ET.ParseError:
                pass
        thruster = el.find("thruster")
        feeds = []
        for f in el.findall("feed"):
            try:
                feeds.append(int((f.text or "").strip()))
            except ValueError:
                pass
        engines.append(EngineSpec(kind, ref, tuple(feeds), thruster.get("file", "") if thruster is not None else ""))
    types = tuple(tank.get("type", "").upper() for tank in section.findall("tank"))
    # JSBSim moves fuel between tanks only where a model's system drives a tank's external flow
    # (FGTank: propulsion/tank[i]/external-flow-rate-pps): the Short_S23's fuel system.
    moves = any("external-flow-rate-pps" in f.read_text(errors="replace") for f in folder.rglob("*.xml"))
    return PropulsionSpec(tuple(engines), types, moves)


# A unit error in a model's files that JSBSim reads without a word. FGPropeller reads <diameter>
# in feet, and a number without a unit attribute is taken in the unit asked for
# (FGXMLElement::FindElementValueAsNumberConvertTo). The catalog writes every propeller's
# diameter with unit="IN" but the L410's (engine/vrtule2.xml, "<diameter> 99 </diameter>"), which
# JSBSim 1.3.3 reads as a 99 ft (30 m) propeller on a 4.7 t twin: at 156 rpm its tips run at
# Mach 0.73 and it absorbs 1e7 ft.lbf/s, the engines cannot turn it past a few rpm, and its
# thrust jumps between -500 and +150000 lbf from one step to the next (a parked L410 rolled away
# at 10 m/s, brakes set). Its other numbers are those of a 99 in (2.51 m) propeller: Ixx 2.84
# slug.ft2, and the M601's power table, which turns it at 1150 rpm at idle. A bare diameter
# larger than any propeller ever flown is read in the inches the rest of the catalog writes.
# The largest flown: the Linke-Hofmann R.II's, 6.90 m (22 ft 7.65 in) (G. W. Haddow,
# P. M. Grosz, "The German Giants: The Story of the R-planes 1914-1919", Putnam, 1963).
MAX_PROPELLER_DIAMETER_FT = 23.0
_BARE_DIAMETER = re.compile(r"<diameter(\s*)>")


@lru_cache(maxsize=256)
def propeller_diameter_fixes(name: str, root: str | None = None) -> tuple:
    """The propellers of a catalog model whose bare ``<diameter>`` is in inches (see
    MAX_PROPELLER_DIAMETER_FT): (thruster file as the model names it, its path, the diameter
    in inches) each, once a file; empty for most models and for a name the catalog does not hold."""
    import xml.etree.ElementTree as ET

    base = Path(root) if root else root_dir()
    try:
        folder = base / "aircraft" / resolve(name, root)
    except NotFound:
        return ()
    fixes = []
    for ref in dict.fromkeys(e.thruster for e in propulsion(name, root).engines):
        path = _engine_file(folder, base, ref)
        try:
            element = ET.parse(path).getroot() if path is not None else None
        except ET.ParseError:
            continue
        diameter = element.find("diameter") if element is not None and element.tag == "propeller" else None
        if diameter is None or "unit" in diameter.attrib:
            continue
        try:
            value = float(diameter.text)
        except (TypeError, ValueError):
            continue
        if math.isfinite(value) and value > MAX_PROPELLER_DIAMETER_FT:
            fixes.append((ref, path, value))
    return tuple(fixes)


@contextmanager
def model_paths(name: str, root: str | None = None):
    """Where ``FGFDMExec.load_model_with_paths`` loads a catalog model (its catalog spelling)
    with its propellers' diameters read right (:func:`propeller_diameter_fixes`): (aircraft,
    engine, systems) folders, the aircraft folder a temporary copy of the model's whose
    ``Engines/`` holds the corrected propeller files (JSBSim looks there first), removed on
    leaving: JSBSim reads all of a model's files while it loads it. None for a model that
    loads as shipped (``load_model``)."""
    fixes = propeller_diameter_fixes(name, root)
    if not fixes:
        yield None
        return
    base = Path(root) if root else root_dir()
    with tempfile.TemporaryDirectory(prefix="sortie-jsbsim-") as tmp:
        try:
            folder = Path(tmp) / "aircraft" / name
            shutil.copytree(base / "aircraft" / name, folder)
            for ref, path, _ in fixes:
                out = folder / "Engines" / (ref if ref.endswith(".xml") else f"{ref}.xml")
                out.parent.mkdir(exist_ok=True)
                out.write_text(_BARE_DIAMETER.sub(r'<diameter unit="IN"\1>', path.read_text(), count=1))
        except OSError as exc:
            raise SortieError(f"could not write aircraft {name!r}'s corrected propeller files: {exc}") from exc
        yield str(Path(tmp) / "aircraft"), str(base / "engine"), str(base / "systems")


def aircraft_class(name: str) -> str:
    """'light', 'fighter' or 'transport' (unknown models count as 'light')."""
    return CLASS_OF.get(name, "light")


# Pilot inputs a replayed script may set, as (our control, JSBSim property, sign).
_SCRIPT_INPUTS = (
    ("pitch", "fcs/elevator-cmd-norm", -1.0),
    ("roll", "fcs/aileron-cmd-norm", 1.0),
    ("yaw", "fcs/rudder-cmd-norm", -1.0),
    ("throttle", "fcs/throttle-cmd-norm", 1.0),
    ("mixture", "fcs/mixture-cmd-norm", 1.0),
    ("flaps", "fcs/flap-cmd-norm", 1.0),
    ("brakes", "fcs/left-brake-cmd-norm", 1.0),
)


def script_trim_times(script_path: Path) -> list[float]:
    """Times after which the script asks for a full trim (events setting
    ``simulation/do_simple_trim`` under a ``simulation/sim-time-sec gt|ge|>= T`` condition)."""
    import xml.etree.ElementTree as ET

    times = []
    for ev in ET.parse(script_path).getroot().iter("event"):
        if not any(s.get("name") == "simulation/do_simple_trim" for s in ev.iter("set")):
            continue
        cond = " ".join((ev.findtext("condition") or "").split())
        m = re.fullmatch(r"simulation/sim-time-sec\s+(gt|ge|>=|>)\s+([0-9.eE+-]+)", cond)
        if not m:
            raise NotFound(f"{script_path.name}: trim event condition {cond!r} is not a time condition")
        times.append(float(m.group(2)))
    return sorted(times)


def replay_script(script: str = "c172_elevator_doublet.xml", seconds: float | None = None):
    """Run a JSBSim script shipped in the wheel with JSBSim's own runner, then drive
    the same aircraft through :class:`fdm.aircraft.Aircraft` with the same inputs.

    Only the pilot inputs the script itself sets are replayed (a model's own
    systems may write others, e.g. the c172x's automatic mixture control).

    Inputs: the initial state the script's IC file produced (given to our wrapper
    in SI), the pilot commands the script set at each step (recorded after each
    of JSBSim's steps: a script sets them before the models run, so the value
    after the step is the value that step used), and its trims at the same
    step. Terrain: flat at the script's elevation (0 ft). Returns
    ``(ours_ecef, reference_ecef)``, (n, 3) float64 metres, one row per step.
    """
    import math

    import numpy as np

    from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions, _jsbsim
    from fdm.state import FT_M
    from terrain.geodesy import geodetic_to_ecef

    jsbsim = _jsbsim()
    base = root_dir()
    path = base / "scripts" / script
    if not path.is_file():
        raise NotFound(f"script {script!r} is not in {base / 'scripts'}")
    ref = jsbsim.FGFDMExec(base.as_posix())
    ref.set_debug_level(0)
    ref.disable_input()  # no network input a script's model may declare (fdm.aircraft: the 737's telnet port)
    ref.load_script(f"scripts/{script}")
    ref.disable_output()
    ref.run_ic()
    dt = ref.get_delta_t()
    name = ref.get_model_name()
    ic = InitialConditions(ref["position/lat-geod-deg"], ref["position/long-gc-deg"],
                           ref["position/geod-alt-ft"] * FT_M, "msl", ref["attitude/psi-deg"],
                           ref["velocities/vt-fps"] * FT_M, on_ground=ref["gear/wow"] > 0.5, trim=False,
                           engines_running=ref["propulsion/engine/set-running"] > 0.5,
                           gear_down=ref["gear/gear-cmd-norm"] > 0.5)
    import xml.etree.ElementTree as ET

    run_el = ET.parse(path).getroot().find("run")
    scripted = {el.get("name") for el in run_el.iter("set")} | \
        {(el.text or "").strip() for el in run_el.findall("property")}
    replayed = [(c, p, s) for c, p, s in _SCRIPT_INPUTS if p in scripted]
    end = seconds if seconds is not None else math.inf
    inputs, ref_pos = [], []
    while ref.get_sim_time() + dt <= end + 1e-9 and ref.run():
        inputs.append({c: ref[p] * s for c, p, s in replayed})
        ref_pos.append((ref["position/lat-geod-deg"], ref["position/long-gc-deg"], ref["position/geod-alt-ft"]))

    ours = Aircraft(name, FlatTerrain(0.0), ic, dt=dt)
    trims = script_trim_times(path)
    our_pos = []
    for k, values in enumerate(inputs):
        t_next = ours.time_s + dt  # what JSBSim's IncrTime gives the script's conditions
        while trims and t_next > trims[0]:
            trims.pop(0)
            ours.trim()
        ours.set_controls(**values)
        ours.step()
        s = ours.raw_state()
        our_pos.append((math.degrees(s[1]), math.degrees(s[2]), s[3]))
    ref_pos = np.array(ref_pos)
    our_pos = np.array(our_pos)
    return (geodetic_to_ecef(our_pos[:, 0], our_pos[:, 1], our_pos[:, 2] * FT_M),
            geodetic_to_ecef(ref_pos[:, 0], ref_pos[:, 1], ref_pos[:, 2] * FT_M))


# Where each model trims: `sortie fdm trims` (fdm/trim_survey.py: an airborne trimmed start on flat
# ground at 1500 m MSL, speeds 5 to 150 m/s in 5 m/s steps and 175, 200, 250; JSBSim 1.3.3),
# the speeds (m/s) that trimmed. Level flight for a powered model, the steady glide for one without
# engines. The trim window moves with altitude and JSBSim's trim is fragile (a speed inside a
# window can fail): fdm.aircraft.trim_speeds scans one model at one altitude on request.
TRIM_SURVEY_ALT_M = 1500.0
TRIM_SURVEY_SPEEDS = tuple(range(5, 155, 5)) + (175, 200, 250)
TRIM_SPEEDS_SURVEYED = {
    "737": (105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "787-8": (100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "A320": (100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "A4": (75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "B747": (95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "Boeing314": (45, 50, 55, 60, 65, 70, 75, 80, 85, 90, 95, 100, 105, 110, 115),
    "c172p": (30, 35, 40, 45, 50, 55, 60, 65),
    "c172r": (35, 40, 45, 50, 55, 60, 65),
    "c172x": (25, 30, 35, 40, 45, 50, 55, 60),
    "c182": (35, 40, 45, 50, 55, 60, 65),
    "c310": (55, 65, 70),
    "Concorde": (110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "DHC6": (45, 50, 55, 60, 65, 70, 75),
    "f104": (115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "f15": (80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "f16": (70, 75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "F4N": (85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "F80C": (70, 75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200),
    "fokker100": (75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150),
    "global5000": (85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "J3Cub": (20, 25, 30, 35, 40, 45),
    "L17": (40, 45, 50, 55, 60, 65, 70),
    "MD11": (100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "minisgs": (5, 10),
    "OV10": (65, 70, 75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125),
    "pogo-jsbsim": (175, 200),
    "SGS": (20, 25, 30),
    "sgs126": (15, 20, 25, 30, 35, 40, 45, 50, 55, 60, 65, 70, 75, 80, 85, 90, 95, 100),
    "sgs233": (30, 35, 40, 45, 50, 55, 60, 65, 70, 75, 80, 85, 90, 95, 100, 105, 110, 115),
    "T37": (50, 55, 60, 65, 70, 75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175),
    "T38": (85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
    "t6texan2": (50, 55, 60, 65, 70, 75, 80, 85, 90, 95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150),
    "XB-70": (95, 100, 105, 110, 115, 120, 125, 130, 135, 140, 145, 150, 175, 200, 250),
}
# Models that trim at no speed in the survey, and why (where looked into: see the survey notes).
TRIM_NEVER = {
    "ah1s": "a helicopter; JSBSim's full trim is a fixed wing's, and its tries run for seconds each",
    "B17": "at full throttle its propellers, at JSBSim's trim steady state, cannot hold level flight",
    "ball": "a sphere: no lift, so neither level flight nor a glide",
    "ballx": "a sphere: no lift, so neither level flight nor a glide",
    "C130": "its turboprops give almost no thrust here (about 30 lbf at full throttle, 70 m/s)",
    "dr1": "its pitch trim cannot balance the pitching moment (JSBSim trims pitch with the trim alone)",
    "f22": "its fly-by-wire flight controls do not settle in JSBSim's trim",
    "F450": "a quadcopter: no wing lift; JSBSim's full trim is a fixed wing's",
    "fokker50": "its flight controls compute the throttle from FlightGear's lever: JSBSim's trim cannot move it",
    "J246": "a launch vehicle",
    "L410": "its turboprops make no power here (propellers at 83 degrees, feathered)",
    "mk82": "a bomb: no engines and L/D below 1, no glide shallower than 45 degrees",
    "p51d": "its throttle is a FlightGear manifold-pressure autothrottle that JSBSim's trim cannot move "
            "(its engine, which JSBSim's set-running leaves stopped, is started on its starter)",
    "pa28": "full throttle cannot hold level flight at 1500 m in the model",
    "paraglider": "a parafoil under a suspended pilot (not investigated further)",
    "pc7": "its turboprop gives little thrust here (about 50 lbf at full throttle, 70 m/s)",
    "Pterosaur": "not investigated",
    "Short_S23": "not investigated",
    "Shuttle": "no engines, and its flight controls map the pitch trim to the elevator unevenly: no glide found",
    "Submarine_Scout": "an airship: buoyancy, not wing lift, holds it up",
    "weather-balloon": "a balloon: no lift, so neither level flight nor a glide",
    "wrightFlyer1903": "not investigated",
    "X15": "a rocket plane (not investigated further)",
    "x24b": "a rocket-powered lifting body (not investigated further)",
    "ZLT-NT": "an airship: buoyancy, not wing lift, holds it up",
}


def _ranges(speeds) -> str:
    """'55, 65-70' for (55, 65, 70): the surveyed speeds as runs of neighbours on the grid."""
    runs = []
    for v in speeds:
        k = TRIM_SURVEY_SPEEDS.index(v)
        if runs and TRIM_SURVEY_SPEEDS.index(runs[-1][1]) == k - 1:
            runs[-1][1] = v
        else:
            runs.append([v, v])
    return ", ".join(f"{a}" if a == b else f"{a}-{b}" for a, b in runs)


def trim_hint(name: str, alt_m: float) -> str:
    """What to try when ``name`` does not trim at ``alt_m`` m MSL, from the survey above."""
    scan = (f"`sortie fdm trims {name} --alt-m {alt_m:.0f}` (fdm.aircraft.trim_speeds) lists the speeds "
            "that trim there")
    where = f"at {TRIM_SURVEY_ALT_M:.0f} m MSL in the catalog survey"
    if name in TRIM_NEVER:
        return f"{name} trims at no speed {where} ({TRIM_NEVER[name]})"
    if name in TRIM_SPEEDS_SURVEYED:
        return f"{name} trims at {_ranges(TRIM_SPEEDS_SURVEYED[name])} m/s {where}; {scan}"
    return f"try another speed or altitude; {scan}"


# Length units of JSBSim's configuration files (JSBSim Reference Manual, "Units"; an
# element without a unit attribute takes the manual's default: IN for <location>, FT for
# <wingspan>, <htailarm>, <vtailarm>). Exact conversions (NIST SP 811, B.8).
_TO_M = {"IN": 0.0254, "FT": 0.3048, "M": 1.0, "CM": 0.01, "MM": 0.001}
# A body radius for a model whose file gives no size at all (no wingspan, no locations).
DEFAULT_BODY_RADIUS_M = 10.0


def _length_m(element, default_unit: str) -> float | None:
    try:
        return float(element.text) * _TO_M[element.get("unit", default_unit).upper()]
    except (TypeError, ValueError, KeyError):
        return None


def _location_m(element) -> tuple | None:
    unit = _TO_M.get(element.get("unit", "IN").upper())
    try:
        return None if unit is None else tuple(float(element.findtext(a, "0")) * unit for a in "xyz")
    except ValueError:
        return None


@lru_cache(maxsize=256)
def body_radius_m(name: str, root: str | None = None) -> float:
    """Radius of a sphere about the CG that holds the aircraft, for collisions between
    agents (server/collisions.py), from the model file: the largest of half the wingspan,
    the horizontal and vertical tail arms (CG to the tail's aerodynamic centre) and the
    distance from the CG to every point the file locates (gear and structure contacts,
    point masses, tanks, engines, thrusters, the eye point and the aerodynamic reference
    point). JSBSim files give no overall length, so this bounds the airframe from below
    where the file locates nothing near the nose or tail. DEFAULT_BODY_RADIUS_M for a name
    the catalog does not hold or a file that gives no size."""
    import xml.etree.ElementTree as ET

    base = Path(root) if root else root_dir()
    try:
        folder = base / "aircraft" / resolve(name, root)
        tree = ET.parse(folder / f"{folder.name}.xml").getroot()
    except (NotFound, OSError, ET.ParseError):
        return DEFAULT_BODY_RADIUS_M
    parts = [tree]
    for section in tree:  # sections kept in files of their own: <ground_reactions file="..."/>
        ref = section.get("file")
        for path in (folder / ref, folder / f"{ref}.xml", folder / "Systems" / f"{ref}.xml") if ref else ():
            if path.is_file():
                try:
                    parts.append(ET.parse(path).getroot())
                except ET.ParseError:
                    pass
                break
    sizes = []
    for tag, factor in (("wingspan", 0.5), ("htailarm", 1.0), ("vtailarm", 1.0)):
        el = tree.find(f"metrics/{tag}")
        value = _length_m(el, "FT") if el is not None else None
        if value is not None and math.isfinite(value):
            sizes.append(abs(value) * factor)
    cg = next((_location_m(el) for el in tree.iter("location") if el.get("name") == "CG"), None)
    if cg is not None:
        for part in parts:
            for el in part.iter("location"):
                p = _location_m(el)
                if p is not None and el.get("name") != "CG":
                    sizes.append(math.dist(p, cg))
    sizes = [s for s in sizes if math.isfinite(s)]
    return max(sizes) if sizes and max(sizes) > 0 else DEFAULT_BODY_RADIUS_M


# Spring coefficients of JSBSim's contacts (FGLGear reads <spring_coeff> in LBS/FT; the
# catalog writes LBS/FT or N/M). Exact: 1 lbf = 4.4482216152605 N, 1 ft = 0.3048 m.
_TO_LBS_FT = {"LBS/FT": 1.0, "N/M": 0.3048 / 4.4482216152605}


@lru_cache(maxsize=256)
def contact_springs_lbs_ft(name: str, root: str | None = None) -> tuple:
    """Each contact's spring coefficient (lbs/ft) in the model file's order (JSBSim's
    gear/unit[i] order), None where the file gives none in a unit it knows (a contact
    with a <strut_force> function alone). Empty for a name or file that cannot be read."""
    import xml.etree.ElementTree as ET

    base = Path(root) if root else root_dir()
    try:
        folder = base / "aircraft" / resolve(name, root)
        tree = ET.parse(folder / f"{folder.name}.xml").getroot()
        section = tree.find("ground_reactions")
        ref = section.get("file") if section is not None else None
        if ref:  # <ground_reactions file="Gear"/>: the section in a file of its own
            path = next((p for p in (folder / ref, folder / f"{ref}.xml", folder / "Systems" / f"{ref}.xml")
                         if p.is_file()), None)
            section = ET.parse(path).getroot() if path is not None else None
    except (NotFound, OSError, ET.ParseError):
        return ()
    if section is None:
        return ()
    springs = []
    for contact in section.iter("contact"):
        el = contact.find("spring_coeff")
        try:
            k = float(el.text) * _TO_LBS_FT[el.get("unit", "LBS/FT").upper()]
        except (AttributeError, TypeError, ValueError, KeyError):
            k = None
        springs.append(k if k is not None and math.isfinite(k) and k > 0 else None)
    return tuple(springs)
