"""The scenario file: the shipped example loads, every kind of error names its key path and value,
agent parameters resolve per type then per kind, and polygon checks hold as properties."""

from __future__ import annotations

import copy
import math
import re
from datetime import datetime, timezone
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server.scenario import (
    KIND_DEFAULTS, MAX_AGENTS, MAX_ROUTE_POINTS, AgentTypeParams, GroundRoute, Hold, ScenarioError, WaypointRoute,
    check_simple_polygon, load_scenario, parse_scenario,
)
from sortie.errors import InvalidArgument, NotFound, grpc_code

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "data" / "scenarios" / "alps.toml"
DEM = REPO / "data" / "dem" / "N47E009.hgt"
RHINE = [[47.24, 9.522], [47.26, 9.537], [47.28, 9.552], [47.28, 9.58]]
LAKE_CONSTANCE_M = 392.0


def base() -> dict:
    """A small valid scenario, as tomllib would return it."""
    return {
        "exercise": {"name": "test", "start_time": "2026-06-15T07:00:00Z"},
        "terrain": {"dem": [str(DEM)]},
        "agents": [
            {"name": "viper1", "kind": "aircraft", "type": "f16", "coalition": "blue", "lat_deg": 47.3,
             "lon_deg": 9.3, "alt_m": 4500.0, "heading_deg": 90.0, "speed_mps": 220.0,
             "autopilot": {"route": [[47.3, 9.55, 4500.0], [47.45, 9.7, 4000.0]], "speed_mps": 220.0}},
            {"name": "lead", "kind": "ground", "type": "hmmwv", "coalition": "red", "lat_deg": 47.2405,
             "lon_deg": 9.5224, "autopilot": {"route": copy.deepcopy(RHINE), "cruise_mps": 12.0, "convoy": "rhine"}},
            {"name": "second", "kind": "ground", "type": "m2a3", "coalition": "red", "lat_deg": 47.2401,
             "lon_deg": 9.5221, "autopilot": {"route": copy.deepcopy(RHINE), "cruise_mps": 12.0, "convoy": "rhine"}},
            {"name": "sam1", "kind": "static", "type": "sam_site", "coalition": "red", "lat_deg": 47.35,
             "lon_deg": 9.45},
        ],
        "target_areas": [{"name": "box", "polygon": [[47.47, 9.54], [47.47, 9.58], [47.49, 9.58], [47.49, 9.54]]}],
    }


def _walk(doc: dict, path: str):
    """(container, last key) of a key path like ``agents[2].autopilot.route``."""
    keys = []
    for part in path.split("."):
        m = re.fullmatch(r"([^\[]+)((?:\[\d+\])*)", part)
        keys.append(m.group(1))
        keys.extend(int(i) for i in re.findall(r"\[(\d+)\]", m.group(2)))
    node = doc
    for k in keys[:-1]:
        node = node[k]
    return node, keys[-1]


def mutated(path: str, value) -> dict:
    doc = base()
    node, key = _walk(doc, path)
    if value is DELETE:
        del node[key]
    else:
        node[key] = value
    return doc


DELETE = object()
BOW_TIE = [[47.0, 9.0], [47.0, 9.1], [47.1, 9.0], [47.1, 9.1]]

# (key path to change, new value, field the error names, text its message holds)
ERROR_CASES = [
    # wrong type
    ("agents[0].lat_deg", "47.3", "agents[0].lat_deg", "must be a number (got '47.3')"),
    ("exercise.fdm_rate_hz", True, "exercise.fdm_rate_hz", "must be a whole number (got True)"),
    ("agents[0].on_ground", 1, "agents[0].on_ground", "must be true or false (got 1)"),
    ("agents[0].coalition", "green", "agents[0].coalition", "must be one of 'blue', 'red', 'neutral' (got 'green')"),
    ("agents", {"name": "x"}, "agents", "must be an array of tables"),
    ("agents[1].autopilot.route[1]", [47.26], "agents[1].autopilot.route[1]", "must be [lat, lon] (got [47.26])"),
    # out of range
    ("agents[0].lat_deg", 123.0, "agents[0].lat_deg", "must be within [-90, 90] (got 123.0)"),
    ("agents[0].lon_deg", math.nan, "agents[0].lon_deg", "must be a finite number (got nan)"),
    ("agents[0].heading_deg", 360.0, "agents[0].heading_deg", "must be within [0, 360) (got 360.0)"),
    ("agents[0].autopilot.route[1]", [47.45, 9.7, 200000.0], "agents[0].autopilot.route[1]",
     "alt_msl_m must be within [-500, 100000] (got 200000.0)"),
    ("agents[1].autopilot.route[2]", [95.0, 9.552], "agents[1].autopilot.route[2]", "lat must be within [-90, 90]"),
    ("agents[1].autopilot.cruise_mps", 50.0, "agents[1].autopilot.cruise_mps",
     "must be within (0, 29.1667] (got 50.0)"),
    ("exercise.network_rate_hz", 60, "exercise.network_rate_hz", "must be within (0, 30] (got 60.0)"),
    ("exercise.world_rate_hz", 240, "exercise.world_rate_hz", "must be within [1, 120] (got 240)"),
    ("terrain.geoid_undulation_m", 400.0, "terrain.geoid_undulation_m", "(got 400.0)"),
    # required
    ("exercise.name", DELETE, "exercise.name", "is required"),
    ("agents[0].speed_mps", DELETE, "agents[0].speed_mps", "is required"),
    # unknown keys, anywhere
    ("agents[0].lat_dge", 47.0, "agents[0].lat_dge", "unknown key; did you mean 'lat_deg'?"),
    ("agent", [], "agent", "unknown key; did you mean 'agents'?"),
    ("exercise.fdm_rate", 120, "exercise.fdm_rate", "did you mean 'fdm_rate_hz'?"),
    ("agents[0].autopilot.sped_mps", 220.0, "agents[0].autopilot.sped_mps", "unknown key"),
    ("target_areas[0].detail", 2.0, "target_areas[0].detail", "did you mean 'detail_m'?"),
    ("agents[3].speed_mps", 3.0, "agents[3].speed_mps", "only for aircraft and ground agents, not static"),
    ("agents[1].alt_m", 400.0, "agents[1].alt_m", "only for aircraft agents, not ground"),
    # names and types
    ("agents[2].name", "lead", "agents[2].name", "duplicates agents[1].name (got 'lead')"),
    ("agents[0].name", "has space", "agents[0].name", "(got 'has space')"),
    ("agents[0].type", "f61", "agents[0].type", "did you mean f16"),
    ("agents[1].type", "t72", "agents[1].type", "must be a vehicle type (hmmwv, m1083, m1a2, m2a3) (got 't72')"),
    ("agents[0].kind", "observer", "agents[0].kind", "(got 'observer')"),
    # polygons
    ("target_areas[0].polygon", [[47.0, 9.0], [47.1, 9.0]], "target_areas[0].polygon",
     "closing vertex not counted (got 2)"),
    ("target_areas[0].polygon", BOW_TIE, "target_areas[0].polygon", "is not a simple polygon: edge 1 (vertices 1-2) "
     "and edge 3 (vertices 3-0) cross or touch (got [[47.0, 9.1], [47.1, 9.0], [47.1, 9.1], [47.0, 9.0]])"),
    ("target_areas[0].polygon", [[47.0, 9.0], [47.0, 9.1], [47.0, 9.05]], "target_areas[0].polygon",
     "is not a simple polygon"),
    ("target_areas[0].polygon", [[47.0, 9.0], [47.0, 9.1], [47.1, 9.1], [47.0, 9.1], [47.1, 9.0]],
     "target_areas[0].polygon", "is not a simple polygon"),
    ("target_areas[0].detail_m", 0.25, "target_areas[0].detail_m", "inset posts"),
    # timing
    ("exercise.fdm_rate_hz", 100, "exercise.fdm_rate_hz", "must be a whole multiple of world_rate_hz (30) (got 100)"),
    ("exercise.time_scale", 4.0, "exercise.time_scale", 'must be 1.0 with clock = "realtime"'),
    ("exercise.start_time", "2026-06-15T07:00:00", "exercise.start_time", "needs a UTC offset"),
    ("exercise.start_time", "tomorrow", "exercise.start_time", "(got 'tomorrow')"),
    # convoys
    ("agents[2].autopilot.route", RHINE[:2] + [[47.28, 9.553]] + RHINE[3:], "agents[2].autopilot.route[2]",
     "members of convoy 'rhine' share it with its leader agents[1]; the leader's point 2 is [47.28, 9.552] "
     "(got [47.28, 9.553])"),
    ("agents[2].autopilot.route", RHINE[:3], "agents[2].autopilot.route", "the leader's has 4 points (got 3)"),
    ("agents[2].autopilot.spacing_m", 80.0, "agents[2].autopilot.spacing_m", "the leader's is 50.0 (got 80.0)"),
    ("agents[2].autopilot.convoy", "rhien", "agents[1].autopilot.convoy", "has no other member"),
    ("agents[1].autopilot.route[1]", [47.24, 9.522], "agents[1].autopilot.route[1]", "repeats the point before it"),
    ("agents[1].autopilot.route[1]", [-47.0, -170.0], "agents[1].autopilot.route[1]",
     "degrees of arc from the point before it (a leg must span less than 90)"),
    # aircraft specifics
    ("agents[0].on_ground", True, "agents[0].alt_m", "must be left out when on_ground = true"),
    ("agents[0].autopilot.hold", {"heading_deg": 90.0}, "agents[0].autopilot", "exactly one of route"),
    # terrain
    ("terrain.dem", ["missing.hgt"], "terrain.dem[0]", "(got 'missing.hgt')"),
    ("terrain.dem", [str(DEM), "../dem/nowhere.hgt"], "terrain.dem[1]", "no such file"),
    ("terrain.dem", ["notes.txt"], "terrain.dem[0]", "must be a DEM file"),
    ("terrain.service", "localhost:50051", "terrain", "exactly one of dem = [files] or service = \"host:port\" "
     "(got ['dem', 'service'])"),
    # agent types
    ("agent_types", {"f61": {"aoi_radius_m": 1.0}}, "agent_types.f61", "(got 'f61')"),
    ("agent_types", {"ground": {"aoi_radius_km": 1.0}}, "agent_types.ground.aoi_radius_km", "did you mean"),
    ("agent_types", {"aircraft": {"dr_algorithm": "DRM4"}}, "agent_types.aircraft.dr_algorithm", "(got 'DRM4')"),
    ("agent_types", {"f16": {"heartbeat_s": 0.0}}, "agent_types.f16.heartbeat_s", "must be within (0, 3600]"),
    ("agent_types", {"F16": {}, "f16": {}}, "agent_types.f16", "names the same type (f16) as agent_types.F16"),
]


@pytest.mark.parametrize("path, value, field, text", ERROR_CASES,
                         ids=lambda v: v if isinstance(v, str) and "." in v else None)
def test_errors_name_the_key_path_and_value(path, value, field, text):
    with pytest.raises(ScenarioError) as info:
        parse_scenario(mutated(path, value), EXAMPLE.parent)
    assert info.value.field == field
    assert str(info.value).startswith(f"{field}: ")
    assert text in str(info.value)


def test_duplicate_target_area_names():
    doc = base()
    doc["target_areas"].append(copy.deepcopy(doc["target_areas"][0]))
    with pytest.raises(ScenarioError, match=r"^target_areas\[1\]\.name: duplicates target_areas\[0\]\.name "
                                            r"\(got 'box'\)$"):
        parse_scenario(doc, EXAMPLE.parent)


def test_the_base_scenario_is_valid():
    s = parse_scenario(base(), EXAMPLE.parent)
    assert [a.name for a in s.agents] == ["viper1", "lead", "second", "sam1"]
    assert s.convoys[0].members == ("lead", "second") and s.convoys[0].spacing_m == 50.0


def test_limits_are_errors_too():
    doc = base()
    doc["agents"] = [doc["agents"][3]] * (MAX_AGENTS + 1)
    with pytest.raises(ScenarioError, match=rf"^agents: at most {MAX_AGENTS} entries \(got {MAX_AGENTS + 1}\)"):
        parse_scenario(doc, EXAMPLE.parent)
    route = [[47.0 + 1e-3 * k, 9.5, 1000.0] for k in range(MAX_ROUTE_POINTS + 1)]
    with pytest.raises(ScenarioError, match=r"^agents\[0\]\.autopilot\.route: must have 1\.\.1000 waypoints"):
        parse_scenario(mutated("agents[0].autopilot.route", route), EXAMPLE.parent)


# --- the example and files -------------------------------------------------------------------------

def test_example_scenario_loads():
    s = load_scenario(EXAMPLE)
    assert s.exercise.start_time == datetime(2026, 6, 15, 7, 0, tzinfo=timezone.utc)
    assert s.exercise.fdm_steps_per_tick == 4
    assert s.terrain.dem == (DEM.resolve(),) and s.terrain.service is None
    kinds = {a.kind for a in s.agents}
    assert kinds == {"aircraft", "ground", "static"}
    assert {type(a.autopilot) for a in s.agents} == {WaypointRoute, Hold, GroundRoute, type(None)}
    assert [c.name for c in s.convoys] == ["rhine"] and len(s.convoys[0].members) == 4
    assert [t.name for t in s.target_areas] == ["altenrhein-airfield", "rhine-crossing"]
    assert len(s.target_areas[1].polygon) == 5  # the closing vertex is dropped


def test_scenario_is_plain_data():
    """A loaded scenario pickles and converts with dataclasses.asdict (recordings, worker processes)."""
    import dataclasses
    import pickle

    s = load_scenario(EXAMPLE)
    assert pickle.loads(pickle.dumps(s)) == s
    assert dataclasses.asdict(s)["agents"][0]["name"] == "viper1"
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.agents[0].lat_deg = 0.0


def test_example_fits_the_shipped_dem_and_the_fdm():
    """Every agent is inside N47E009, airborne aircraft clear the terrain under their start and
    waypoints by 300 m, ground agents are on land, and the fdm accepts routes and initial conditions."""
    from fdm.convoy import Route
    from terrain.dem import read_dem
    from terrain.raster import STATUS_OUTSIDE
    from terrain.terrain import Terrain

    s = load_scenario(EXAMPLE)
    terrain = Terrain([read_dem(p) for p in s.terrain.dem])
    for a in s.agents:
        h = terrain.heights([a.lat_deg], [a.lon_deg])
        assert h.status[0] != STATUS_OUTSIDE, a.name
        if a.kind == "aircraft":
            a.initial_conditions().validated()
            if not a.on_ground:
                assert a.alt_m - h.height_msl_m[0] > 300.0, a.name
            if isinstance(a.autopilot, WaypointRoute):
                lat, lon, alt = np.array(a.autopilot.waypoints).T
                assert (alt - terrain.heights(lat, lon).height_msl_m > 300.0).all(), a.name
        elif a.kind == "ground":
            assert h.height_msl_m[0] > LAKE_CONSTANCE_M + 2.0, a.name
            if a.autopilot is not None:
                lat, lon = np.array(a.autopilot.points).T
                Route(lat, lon)
                assert (terrain.heights(lat, lon).height_msl_m > LAKE_CONSTANCE_M + 2.0).all(), a.name


def test_dem_paths_are_relative_to_the_scenario_file(tmp_path):
    (tmp_path / "dem").mkdir()
    (tmp_path / "dem" / "N47E009.hgt").write_bytes(b"")  # existence is all the loader checks
    doc = base()
    doc["terrain"] = {"dem": ["dem/N47E009.hgt", str(DEM)]}
    s = parse_scenario(doc, tmp_path)
    assert s.terrain.dem == ((tmp_path / "dem" / "N47E009.hgt").resolve(), DEM.resolve())


def test_terrain_service_address():
    for address in ("localhost:50051", "10.0.0.7:1", "[::1]:50051", "terrain:50061,terrain2:50061"):
        doc = mutated("terrain", {"service": address, "geoid_undulation_m": 48.0})
        assert parse_scenario(doc, EXAMPLE.parent).terrain.service == address
    for address in ("localhost", ":50051", "host:0", "host:port", "::1:50051", "a:1,", "a:1,b"):
        with pytest.raises(ScenarioError, match=r"^terrain\.service: must be \"host:port\""):
            parse_scenario(mutated("terrain", {"service": address}), EXAMPLE.parent)


def test_toml_syntax_error_names_file_line_and_column(tmp_path):
    path = tmp_path / "broken.toml"
    path.write_text('[exercise]\nname = "x"\nstart_time = \n')
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    e = info.value
    assert (e.line, e.column) == (3, 14)
    assert str(e).startswith(f"{path}: line 3, column 14: TOML syntax error: ")


def test_errors_inside_a_file_name_the_file(tmp_path):
    text = EXAMPLE.read_text().replace('dem = ["../dem/N47E009.hgt"]', f'dem = ["{DEM}"]')
    bad = tmp_path / "typo.toml"
    bad.write_text(text.replace("heading_deg = 90.0\nspeed_mps = 220.0", "heading_deg = 90.0\nspeed_mps = 'fast'"))
    with pytest.raises(ScenarioError) as info:
        load_scenario(bad)
    assert str(info.value) == f"{bad}: agents[0].speed_mps: must be a number (got 'fast')"
    assert info.value.field == "agents[0].speed_mps"
    assert isinstance(info.value, InvalidArgument) and grpc_code(info.value).name == "INVALID_ARGUMENT"


def test_missing_scenario_file(tmp_path):
    with pytest.raises(NotFound, match="does not exist"):
        load_scenario(tmp_path / "nope.toml")


# --- values and defaults ---------------------------------------------------------------------------

def test_exercise_defaults_and_clock():
    e = parse_scenario(base(), EXAMPLE.parent).exercise
    assert (e.fdm_rate_hz, e.world_rate_hz, e.network_rate_hz) == (120, 30, 20.0)
    assert (e.clock, e.time_scale, e.duration_s) == ("realtime", 1.0, None)
    assert (e.vanished_client_timeout_s, e.on_vanish) == (10.0, "autopilot")
    fast = parse_scenario(mutated("exercise.clock", "fast"), EXAMPLE.parent).exercise
    assert fast.time_scale == 10.0
    doc = mutated("exercise.clock", "fast")
    doc["exercise"]["time_scale"] = 1.0
    with pytest.raises(ScenarioError, match=r"^exercise\.time_scale: must be within \(1, 1000\]"):
        parse_scenario(doc, EXAMPLE.parent)



def test_network_rate_defaults_to_the_world_rate_below_20_hz():
    """A scenario that slows the world below 20 Hz and says nothing of network_rate_hz is valid: the
    default is no faster than the world (it was 20, refused under a key the user never wrote)."""
    for world, expected in ((10, 10.0), (1, 1.0), (20, 20.0), (30, 20.0)):
        e = parse_scenario(mutated("exercise.world_rate_hz", world), EXAMPLE.parent).exercise
        assert (e.world_rate_hz, e.network_rate_hz) == (world, expected)
    doc = mutated("exercise.world_rate_hz", 10)
    doc["exercise"]["network_rate_hz"] = 20.0  # written by the user: still refused
    with pytest.raises(ScenarioError, match=r"^exercise\.network_rate_hz: must be within \(0, 10\] \(got 20\.0\)"):
        parse_scenario(doc, EXAMPLE.parent)

def test_start_time_is_utc_from_any_offset():
    doc = mutated("exercise.start_time", datetime.fromisoformat("2026-06-15T09:00:00+02:00"))
    assert parse_scenario(doc, EXAMPLE.parent).exercise.start_time == datetime(2026, 6, 15, 7, tzinfo=timezone.utc)


def test_aircraft_values():
    s = parse_scenario(mutated("agents[0].type", "F16"), EXAMPLE.parent)
    a = s.agents[0]
    assert a.type == "f16"  # the catalog's spelling
    assert (a.alt_ref, a.on_ground, a.controllable) == ("msl", False, False)
    assert a.autopilot == WaypointRoute(((47.3, 9.55, 4500.0), (47.45, 9.7, 4000.0)), 220.0)
    doc = base()
    doc["agents"][0] = {"name": "parked", "kind": "aircraft", "type": "c172p", "coalition": "blue",
                        "lat_deg": 47.485, "lon_deg": 9.56, "heading_deg": 100.0, "on_ground": True,
                        "autopilot": {"hold": {"heading_deg": 100.0}}}
    a = parse_scenario(doc, EXAMPLE.parent).agents[0]
    assert (a.alt_m, a.speed_mps) == (None, 0.0) and a.autopilot == Hold(heading_deg=100.0)
    assert a.initial_conditions().on_ground


def test_agent_type_resolves_type_then_kind_then_default():
    doc = base()
    doc["agents"].append({"name": "cessna", "kind": "aircraft", "type": "c172p", "coalition": "neutral",
                          "lat_deg": 47.4, "lon_deg": 9.6, "alt_m": 1500.0, "speed_mps": 50.0})
    doc["agent_types"] = {"aircraft": {"aoi_radius_m": 60_000.0, "heartbeat_s": 2.0},
                          "F16": {"aoi_radius_m": 150_000.0},  # case-insensitive catalog name
                          "sam_site": {"dr_algorithm": "FPW"},
                          "m1a2": {"aoi_radius_m": 5_000.0}}  # a vehicle type no agent uses yet
    s = parse_scenario(doc, EXAMPLE.parent)
    viper, lead, _, sam, cessna = s.agents
    assert s.agent_type(viper) == AgentTypeParams(150_000.0, 1.0, 3.0, 2.0, "RVW")  # type, then kind
    assert s.agent_type(cessna) == AgentTypeParams(60_000.0, 1.0, 3.0, 2.0, "RVW")  # kind table
    assert s.agent_type(lead) == KIND_DEFAULTS["ground"]  # built-in default
    assert s.agent_type(sam) == AgentTypeParams(50_000.0, 1.0, 3.0, 5.0, "FPW")
    assert s.type_params("ground", "m1a2").aoi_radius_m == 5_000.0
    assert s.type_params("observer") == AgentTypeParams(200_000.0, 1.0, 3.0, 5.0, "FPW")
    with pytest.raises(InvalidArgument, match="^kind: "):
        s.type_params("submarine")


def test_built_in_kind_defaults():
    assert {k: p.aoi_radius_m for k, p in KIND_DEFAULTS.items()} == {
        "aircraft": 80_000.0, "ground": 10_000.0, "static": 50_000.0, "observer": 200_000.0}
    assert {p.dr_position_m for p in KIND_DEFAULTS.values()} == {1.0}
    assert {p.dr_orientation_deg for p in KIND_DEFAULTS.values()} == {3.0}
    assert {p.heartbeat_s for p in KIND_DEFAULTS.values()} == {5.0}


# --- polygons (properties) -------------------------------------------------------------------------

def _star(draw_angles, radii, lat0=47.5, lon0=9.5):
    """A star-shaped polygon around (lat0, lon0): sorted angles, radii in metres -> [[lat, lon], ...]."""
    m_per_deg_lat = 111_200.0
    m_per_deg_lon = m_per_deg_lat * math.cos(math.radians(lat0))
    return [[lat0 + r * math.cos(a) / m_per_deg_lat, lon0 + r * math.sin(a) / m_per_deg_lon]
            for a, r in zip(draw_angles, radii)]


@st.composite
def star_polygons(draw, min_n=3, max_n=40):
    n = draw(st.integers(min_n, max_n))
    gaps = draw(st.lists(st.floats(0.2, 1.0), min_size=n, max_size=n))
    total = sum(gaps)
    angles = np.cumsum([2 * math.pi * g / total for g in gaps]) - 1e-3
    radii = draw(st.lists(st.floats(200.0, 2_000.0), min_size=n, max_size=n))
    return _star(angles, radii)


def _area_doc(polygon) -> dict:
    doc = base()
    doc["target_areas"] = [{"name": "area", "polygon": polygon, "detail_m": 5.0}]
    return doc


@settings(max_examples=60, deadline=None)
@given(star_polygons(), st.integers(0, 39), st.booleans(), st.booleans())
def test_star_shaped_polygons_are_simple_in_any_order(polygon, shift, reverse, close):
    """A star-shaped polygon is accepted whatever its first vertex, direction or closing vertex."""
    k = shift % len(polygon)
    ring = polygon[k:] + polygon[:k]
    ring = ring[::-1] if reverse else ring
    area = parse_scenario(_area_doc(ring + ([ring[0]] if close else [])), EXAMPLE.parent).target_areas[0]
    assert area.polygon == tuple(tuple(v) for v in ring)


@settings(max_examples=60, deadline=None)
@given(st.integers(4, 30), st.integers(0, 29), st.floats(500.0, 3_000.0))
def test_swapping_two_vertices_of_a_convex_polygon_is_rejected(n, k, radius):
    """Vertices k, k+1 of a convex polygon swapped: chords (k-1, k+1) and (k, k+2) interleave, so cross."""
    polygon = _star(np.linspace(0.0, 2 * math.pi, n, endpoint=False), [radius] * n)
    k %= n
    polygon[k], polygon[(k + 1) % n] = polygon[(k + 1) % n], polygon[k]
    with pytest.raises(ScenarioError, match=r"^target_areas\[0\]\.polygon: is not a simple polygon"):
        parse_scenario(_area_doc(polygon), EXAMPLE.parent)


def _meet_brute_force(north, east):
    """The first pair of edges that meet where they must not, one pair at a time (the oracle)."""
    pts = np.stack([east, north], axis=1)
    n = len(pts)

    def dist(x, a, b):
        ab = b - a
        length2 = np.dot(ab, ab)
        t = 0.0 if length2 == 0.0 else min(max(np.dot(x - a, ab) / length2, 0.0), 1.0)
        return float(np.hypot(*(a + t * ab - x)))

    def orient(a, b, c):
        return (b[0] - a[0]) * (c[1] - a[1]) - (b[1] - a[1]) * (c[0] - a[0])

    for i in range(n):
        for j in range(i + 1, n):
            pi, qi, pj, qj = pts[i], pts[(i + 1) % n], pts[j], pts[(j + 1) % n]
            if j == i + 1:
                meet = min(dist(pi, pj, qj), dist(qj, pi, qi)) < 1e-3
            elif i == 0 and j == n - 1:
                meet = min(dist(qi, pj, qj), dist(pj, pi, qi)) < 1e-3
            else:
                meet = (orient(pi, qi, pj) * orient(pi, qi, qj) < 0 and orient(pj, qj, pi) * orient(pj, qj, qi) < 0) \
                    or min(dist(pi, pj, qj), dist(qi, pj, qj), dist(pj, pi, qi), dist(qj, pi, qi)) < 1e-3
            if meet:
                return i, j
    return None


@settings(max_examples=300, deadline=None)
@given(st.integers(3, 8).flatmap(lambda n: st.lists(
    st.tuples(st.integers(0, 4), st.integers(0, 4)) | st.tuples(st.floats(0, 100), st.floats(0, 100)),
    min_size=n, max_size=n)))
def test_simple_polygon_check_agrees_with_brute_force(points):
    """Random polygons (east, north in units of 10 m), many degenerate: integer vertices on a 5 x 5
    lattice repeat and line up."""
    pts = 10.0 * np.array(points, dtype=np.float64)
    got = check_simple_polygon(pts[:, 1], pts[:, 0])
    want = _meet_brute_force(pts[:, 1], pts[:, 0])
    if want is None and got == (0, 0):
        return  # no edges meet, but no area either (the oracle does not look at area)
    assert got == want


def test_polygon_touching_and_antimeridian():
    # A vertex touching a non-neighbouring edge (an hourglass pinched at one point) is not simple.
    east = np.array([0.0, 100.0, 50.0, 100.0, 0.0, 50.0])
    north = np.array([0.0, 0.0, 50.0, 100.0, 100.0, 50.0])
    assert check_simple_polygon(north, east) == (1, 4)
    north[5] -= 0.01  # 1 cm apart: simple
    assert check_simple_polygon(north, east) is None
    # Across the antimeridian, longitudes wrap: a 2 x 2 km square at 179.99 .. -179.99 is simple.
    square = [[60.0, 179.99], [60.0, -179.99], [60.02, -179.99], [60.02, 179.99]]
    assert parse_scenario(_area_doc(square), EXAMPLE.parent).target_areas[0].polygon[1] == (60.0, -179.99)


@settings(max_examples=80, deadline=None)
@given(st.floats(allow_nan=True, allow_infinity=True))
def test_any_latitude_is_accepted_in_range_or_named_with_its_value(lat):
    doc = mutated("agents[3].lat_deg", lat)
    if math.isfinite(lat) and abs(lat) <= 90.0:
        assert parse_scenario(doc, EXAMPLE.parent).agents[3].lat_deg == lat
    else:
        with pytest.raises(ScenarioError) as info:
            parse_scenario(doc, EXAMPLE.parent)
        assert str(info.value).startswith("agents[3].lat_deg: must be ") and f"(got {lat!r})" in str(info.value)


def test_an_agent_that_cannot_start_is_named(tmp_path):
    """Valid values a model cannot start at (a J3 Cub trimmed at 220 m/s): building the
    world fails with the agent's key path, name and type, and JSBSim's reason."""
    from server.sim_server import build_world, open_terrain

    doc = base()
    doc["agents"][0]["type"] = "J3Cub"
    scenario = parse_scenario(doc, tmp_path)
    terrain, _, _ = open_terrain(scenario)
    with pytest.raises(ScenarioError, match=r"agents\[0\].*'viper1' \(J3Cub\) cannot start.*trim"):
        build_world(scenario, terrain)


def test_engines_running_false_starts_an_aircraft_gliding_and_holds_only_its_heading(tmp_path):
    """An engine-out exercise: ``engines_running = false`` parses (a non-boolean is named), and
    in the world the c172x starts trimmed in its steady glide and, with no autopilot table, only
    its heading is held: over 10 s it sinks at least 1 m/s and keeps its speed within 1.5 m/s,
    where the same aircraft with its engine running holds its height within 10 m."""
    from server.sim_server import _aircraft_spec, build_world, open_terrain

    doc = base()
    doc["agents"] = [{"name": "glider", "kind": "aircraft", "type": "c172x", "coalition": "blue", "lat_deg": 47.3,
                      "lon_deg": 9.3, "alt_m": 2500.0, "heading_deg": 90.0, "speed_mps": 35.0,
                      "engines_running": False}]
    doc["target_areas"] = []
    scenario = parse_scenario(doc, tmp_path)
    agent = scenario.agents[0]
    assert agent.engines_running is False and agent.initial_conditions().engines_running is False
    assert _aircraft_spec(agent, "autopilot")["hold"] == {"heading_deg": 90.0}
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.engines_running: must be true or false"):
        parse_scenario({**doc, "agents": [{**doc["agents"][0], "engines_running": "no"}]}, tmp_path)

    def fly(document) -> tuple[float, float]:
        """(height change m, speed change m/s) over 10 s of world time."""
        s = parse_scenario(document, tmp_path)
        terrain, _, _ = open_terrain(s)
        world = build_world(s, terrain)
        try:
            world.tick()
            h0, v0 = world.snapshot.alt_msl_m[0], np.linalg.norm(world.snapshot.vel_ecef_mps[0])
            while world.snapshot.time_s < 10.0:
                world.tick()
            return (world.snapshot.alt_msl_m[0] - h0, np.linalg.norm(world.snapshot.vel_ecef_mps[0]) - v0)
        finally:
            world.close()

    dh, dv = fly(doc)
    print(f"\ngliding: {dh:.1f} m, {dv:+.2f} m/s in 10 s")
    assert dh < -10.0 and abs(dv) < 1.5
    powered = copy.deepcopy(doc)
    del powered["agents"][0]["engines_running"]
    dh, _ = fly(powered)
    print(f"powered: {dh:.1f} m in 10 s")
    assert abs(dh) < 10.0
