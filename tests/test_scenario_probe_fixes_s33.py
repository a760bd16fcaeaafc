"""Scenario fixes found by acceptance probing (round 33), on real files, terrains and services:

1. a YAML value shaped like a date or date-time that is none (2026-02-29, second 60, hour 24,
   month 13, an offset of 25 hours, an agent named 2024-13-01) is a ScenarioError with its line,
   column and text, `sortie server` exit 2 with one line (a bare ValueError and exit 1 before);
2. a TOML value nested deeper than tomllib recurses is a ScenarioError (RecursionError before);
3. a terrain service's port is ASCII digits: "h:²" is a ScenarioError (int() raised before) and
   "127.0.0.1:１２３" is refused by the scenario and by TerrainClient (accepted before);
4. WorldInfo's entity centre cuts the circle of longitudes at its widest gap: the same for any
   order of the entities, among the group across the antimeridian (the first entity's side
   before: a lone aircraft listed first pulled it to 0 E);
5. a target area's inset size: refused by the validator (naming target_areas[i].detail_m) where
   no DEM can give it at most terrain/inset.py's INSET_MAX_POSTS, by the server (naming the same
   key) where the scenario's DEM does not (an unnamed LimitExceeded before);
6. [terrain] service with insets = true: the server refuses a service that does not serve the
   target areas' insets, naming terrain.insets (it started and said terrain_insets before);
7. a static agent over water stands on the sea surface, not the DEM's bathymetry;
10. a TOML scenario starting with a UTF-8 byte order mark loads (a syntax error before), as its
    YAML twin does, from a file and from a recording's text;
AOI 2. [agent_types.observer] aoi_radius_m = 0 is refused naming the key (no observer could join).
"""

from __future__ import annotations

import itertools
import json
import tomllib
from pathlib import Path

import numpy as np
import pytest

from server.scenario import ScenarioError, load_scenario, scenario_data
from sortie.cli import main
from sortie.errors import InvalidArgument

REPO = Path(__file__).resolve().parents[1]
DEM = REPO / "data" / "dem" / "N47E009.hgt"
PORT = 53630  # this file's terrain services: 53630-53639

HEAD = f"""[exercise]
name = "s33"
start_time = 2026-06-15T07:00:00Z
[terrain]
dem = ["{DEM}"]
"""


def _toml(tmp_path, body: str = "", name: str = "s.toml", head: str = HEAD) -> Path:
    path = tmp_path / name
    path.write_text(head + body, encoding="utf-8")
    return path


def _refused(path) -> ScenarioError:
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    return info.value


def _server_exit(path, capsys) -> tuple[int, str]:
    code = main(["server", "--scenario", str(path), "--port", "0", "--no-record", "--aircraft-workers", "0",
                 "--clock", "fast", "--duration", "0.1"])
    return code, capsys.readouterr().err


# --- 1. YAML date-times that are none -------------------------------------------------------------

YAML_HEAD = f"""exercise:
  name: s33
  start_time: {{start}}
terrain:
  dem: ["{DEM}"]
"""


@pytest.mark.parametrize("start, why", [
    ("2026-02-29T12:00:00Z", "day is out of range for month"),
    ("2026-06-30T23:59:60Z", "second must be in 0..59"),
    ("2026-13-01T00:00:00Z", "month must be in 1..12"),
    ("2026-01-01T24:00:00Z", "hour must be in 0..23"),
    ("2026-01-01T00:00:00+25:00", "a UTC offset's hours must be in 0..23"),
    ("2026-01-01T00:00:00+01:75", "a UTC offset's minutes must be in 0..59"),  # PyYAML read it as +02:15
    ("0000-01-01T00:00:00Z", "year 0 is out of range"),
])
def test_a_yaml_date_time_that_is_none_is_an_error_at_its_line_and_column(tmp_path, start, why):
    path = tmp_path / "s.yaml"
    path.write_text(YAML_HEAD.format(start=start))
    e = _refused(path)
    assert (e.line, e.column, e.field) == (3, 15, "line 3, column 15")
    assert f"found {start!r}, which has the shape of a date or date-time but is none ({why};" in str(e), str(e)
    # a valid one still reads as TOML reads it, lower-case "t" and "z" too
    path.write_text(YAML_HEAD.format(start="2026-06-15t08:00:00+02:00"))
    assert load_scenario(path).exercise.start_time.isoformat() == "2026-06-15T06:00:00+00:00"


def test_an_unquoted_name_shaped_like_a_date_that_is_none(tmp_path, capsys):
    path = tmp_path / "s.yaml"
    path.write_text(YAML_HEAD.format(start="2026-06-15T07:00:00Z") + """agents:
  - name: 2024-13-01
    kind: static
    type: radar
    coalition: red
    lat_deg: 47.3
    lon_deg: 9.5
""")
    e = _refused(path)
    assert (e.line, e.column) == (7, 11) and "found '2024-13-01'" in str(e) and "quote it if it is text" in str(e)
    code, err = _server_exit(path, capsys)
    assert code == 2 and err.count("\n") == 1 and "Traceback" not in err, err
    assert "line 7, column 11: YAML syntax error: found '2024-13-01'" in err


# --- 2. TOML nested too deeply ----------------------------------------------------------------------

@pytest.mark.parametrize("value", ["[" * 1000 + "]" * 1000, "{a=" * 1000 + "1" + "}" * 1000])
def test_a_toml_value_nested_too_deeply_is_a_scenario_error(tmp_path, capsys, value):
    path = tmp_path / "deep.toml"
    path.write_text(f"[exercise]\nname = {value}\n")
    e = _refused(path)
    assert e.field == "file" and "TOML syntax error: nested too deeply" in str(e)
    code, err = _server_exit(path, capsys)
    assert code == 2 and err.count("\n") == 1 and "nested too deeply" in err, err


# --- 3. a service's port in ASCII digits --------------------------------------------------------------

@pytest.mark.parametrize("service", ["h:\u00b2", "127.0.0.1:\uff11\uff12\uff13", "127.0.0.1:1,127.0.0.2:\u0663"])
def test_a_service_port_of_other_digits_is_refused(tmp_path, service):
    from client.terrain_client import replica_target

    head = HEAD.replace(f'dem = ["{DEM}"]', f'service = "{service}"')
    e = _refused(_toml(tmp_path, head=head))
    assert e.field == "terrain.service" and f"(got {service!r})" in str(e)
    # a client of replicas (the scenario's and --terrain's comma lists) checks each entry so
    with pytest.raises(InvalidArgument, match="each replica must be"):
        replica_target(f"127.0.0.1:50051,{service}")


# --- 4. the entities' centre across the antimeridian ------------------------------------------------

def test_the_entities_centre_is_the_same_in_any_order_and_lies_among_the_group():
    from server.sim_server import entities_centre

    # The probe's case: a lone aircraft at 0 E and four statics either side of 180. The centre is
    # the largest group's (since the thirty-sixth session): the four statics', halfway between
    # the two middle ones across 180 (before, the median of all five: 179.9).
    lat = [-16.5, -16.5, -16.5, -16.6, -16.6]
    lon = [0.0, 179.9, -179.9, 179.8, -179.8]
    centres = {entities_centre([lat[k] for k in p], [lon[k] for k in p]) for p in itertools.permutations(range(5))}
    assert centres == {(5, -16.55, -180.0)}
    # an even count: halfway between the two middle ones, across 180 where they lie either side
    for p in itertools.permutations([179.9, -179.7, 179.5, -179.3]):
        assert entities_centre([0.0] * 4, list(p))[2] == pytest.approx(-179.9, abs=1e-9)
    # an ordinary group keeps its plain median; longitudes given past 180 wrap
    assert entities_centre([47.3, 47.4, 47.5], [9.3, 9.5, 9.6]) == (3, 47.4, 9.5)
    assert entities_centre([0.0, 0.0], [190.0, -171.0])[2] == pytest.approx(-170.5, abs=1e-9)


# --- 5. the inset's size ----------------------------------------------------------------------------

def _area(polygon, detail_m: float, name: str = "big") -> str:
    return f'[[target_areas]]\nname = "{name}"\npolygon = {json.dumps(polygon)}\ndetail_m = {detail_m}\n'


def test_the_validator_refuses_an_inset_no_dem_can_fit(tmp_path):
    # 0.23 x 0.33 deg (25.6 x 24.9 km) at 5 m: at least 5185 x 5057 posts at any DEM (the old
    # bounding-box rule took it: 5100 x 4990 < 8192^2), far past 4096^2.
    polygon = [[47.25, 9.3], [47.25, 9.63], [47.48, 9.63], [47.48, 9.3]]
    e = _refused(_toml(tmp_path, _area(polygon, 5.0)))
    assert e.field == "target_areas[0].detail_m" and "(got 5.0)" in str(e)
    assert "more than the 16777216 (4096 x 4096) an inset may have" in str(e)
    # the same area at 10 m may fit: left to the server, which knows the DEM
    assert load_scenario(_toml(tmp_path, _area(polygon, 10.0))).target_areas[0].detail_m == 10.0


@pytest.mark.parametrize("polygon, detail_m", [
    ([[47.30, 9.50], [47.30, 9.53], [47.32, 9.53]], 20.0),
    ([[47.40, 9.60], [47.41, 9.64], [47.43, 9.61], [47.42, 9.59]], 7.0),
    ([[47.05, 9.95], [47.06, 9.99], [47.08, 9.97]], 100.0),
])
def test_the_validators_bound_is_at_most_the_insets_posts(alps_terrain, polygon, detail_m):
    """inset_posts_least is a lower bound of InsetSource's lattice (the Alps tile's 3" posts
    refine to 0.5..1 x detail_m, so the bound is within 2^2 of it)."""
    from server.scenario import inset_posts_least
    from terrain.inset import INSET_SEED, InsetSource

    inset = InsetSource(alps_terrain, polygon, detail_m, INSET_SEED)
    rows, cols = inset.shape
    least = inset_posts_least(*np.array(polygon).T, detail_m)
    assert least[0] <= rows <= 2 * least[0] + 64 and least[1] <= cols <= 2 * least[1] + 64, (least, inset.shape)


@pytest.fixture(scope="module")
def alps_terrain():
    from terrain.mosaic import load_sources
    from terrain.terrain import Terrain

    return Terrain(load_sources([DEM]))


def test_the_server_refuses_an_inset_the_dem_cannot_fit_naming_its_detail_m(tmp_path, capsys):
    """The probe's Alps box (0.18 x 0.26 deg at 5 m): at least 4033 x 3969 posts, so possible,
    but the tile's 3" posts refine to 2.9 x 3.9 m: 6977 x 5057. Refused before any inset is
    built, naming the key and the count."""
    from server.sim_server import open_terrain

    polygon = [[47.30, 9.30], [47.30, 9.56], [47.48, 9.56], [47.48, 9.30]]
    path = _toml(tmp_path, _area([[47.0, 9.9], [47.0, 9.91], [47.01, 9.9]], 50.0, "small") + _area(polygon, 5.0),
                 head=HEAD + "insets = true\n")
    scenario = load_scenario(path)  # the validator cannot know the DEM's lattice
    with pytest.raises(ScenarioError) as info:
        open_terrain(scenario)
    e = info.value
    assert e.field == "target_areas[1].detail_m" and e.value == 5.0 and str(e).startswith(f"{path}: ")
    assert "target area 'big' inset posts (6977 x 5057 at 5.0 m): 35282689 exceeds the limit of 16777216" in str(e)
    code, err = _server_exit(path, capsys)
    assert code == 2 and err.count("\n") == 1 and "target_areas[1].detail_m" in err, err
    # without insets the area is only an outline: the server starts
    path.write_text(path.read_text().replace("insets = true\n", ""))
    assert open_terrain(load_scenario(path))[1] == f"dem:{DEM}"


# --- 6. a service that must serve the insets ----------------------------------------------------------

SMALL = [[47.300, 9.500], [47.300, 9.520], [47.312, 9.515]]


@pytest.fixture(scope="module")
def services(alps_terrain):
    """(address of a service without insets, address of one serving SMALL's inset "a" at 20 m)."""
    from server.terrain_service import create_server
    from terrain.inset import INSET_SEED, with_insets

    plain, plain_port = create_server(alps_terrain, f"127.0.0.1:{PORT}")
    inset, inset_port = create_server(with_insets(alps_terrain, [("a", SMALL, 20.0)], INSET_SEED),
                                      f"127.0.0.1:{PORT + 1}")
    plain.start()
    inset.start()
    yield f"127.0.0.1:{plain_port}", f"127.0.0.1:{inset_port}"
    plain.stop(0)
    inset.stop(0)


def _service_scenario(tmp_path, address: str, detail_m: float = 20.0, insets: bool = True):
    head = HEAD.replace(f'dem = ["{DEM}"]', f'service = "{address}"\ninsets = {str(insets).lower()}')
    return load_scenario(_toml(tmp_path, _area(SMALL, detail_m, "a"), head=head))


def test_a_service_without_the_insets_is_refused_naming_terrain_insets(tmp_path, services):
    from server.sim_server import open_terrain, server_config

    plain, inset = services
    with pytest.raises(ScenarioError) as info:
        open_terrain(_service_scenario(tmp_path, plain))
    e = info.value
    assert e.field == "terrain.insets" and e.value is True
    assert f"the terrain service at {plain} serves no inset of target_areas[0] 'a'" in str(e)
    # an inset of that name at another detail_m is not the area's
    with pytest.raises(ScenarioError, match=r"serves an inset named 'a' that is not target_areas\[0\]'s"):
        open_terrain(_service_scenario(tmp_path, inset, detail_m=25.0))
    # the service serving it, or insets = false: the server opens it and says so
    scenario = _service_scenario(tmp_path, inset)
    terrain, desc, _ = open_terrain(scenario)
    terrain.close()
    assert desc == f"service:{inset}" and server_config(scenario, desc).insets is True
    scenario = _service_scenario(tmp_path, plain, insets=False)
    terrain, _, _ = open_terrain(scenario)
    terrain.close()
    assert server_config(scenario).insets is False
    # --terrain over a DEM scenario with insets: the same check
    dem_scenario = load_scenario(_toml(tmp_path, _area(SMALL, 20.0, "a"), head=HEAD + "insets = true\n"))
    with pytest.raises(ScenarioError, match="terrain.insets: the terrain service"):
        open_terrain(dem_scenario, service=plain)


# --- 7. a static over water ---------------------------------------------------------------------------

def test_a_static_over_water_stands_on_the_sea_surface(tmp_path):
    from server.sim_server import build_world
    from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
    from terrain.terrain import Terrain

    # a coast: sea 20 m deep (bathymetry, as a DEM may carry it) west of 30.02 E, land at 10 m east
    h = np.where(np.arange(400)[None, :] < 200, -20.0, 10.0) * np.ones((400, 1))
    terrain = Terrain([Raster(h, Georef(CRS_GEOGRAPHIC, 30.0, 20.0, 1e-4, 1e-4), name="coast")])
    body = "".join(f'[[agents]]\nname = "{n}"\nkind = "static"\ntype = "ship"\ncoalition = "red"\n'
                   f"lat_deg = 20.02\nlon_deg = {lon}\n" for n, lon in (("at_sea", 30.01), ("ashore", 30.03)))
    world = build_world(load_scenario(_toml(tmp_path, body)), terrain)
    world.tick()
    alt = dict(zip((world.entities[int(i)].name for i in world.snapshot.ids), world.snapshot.alt_msl_m))
    assert alt == {"at_sea": 0.0, "ashore": 10.0}  # -20.0 at sea before
    spawns = {e.detail["name"]: e.alt_msl_m for e in world.events_since(0)[0] if e.kind == "spawn"}
    assert spawns == {"at_sea": 0.0, "ashore": 10.0}
    world.close()


# --- 10. a byte order mark ---------------------------------------------------------------------------

def test_a_toml_scenario_with_a_byte_order_mark_loads_as_without(tmp_path):
    plain = load_scenario(_toml(tmp_path, name="plain.toml"))
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + HEAD.encode("utf-8"))
    assert load_scenario(path).exercise == plain.exercise
    # a recording keeps the text as read (server/recorder.py), the mark included
    text = path.read_text(encoding="utf-8")
    assert text.startswith("\ufeff") and scenario_data(text, path) == tomllib.loads(HEAD)
    # an error's line and column are the text's, after the mark, as without it
    broken = HEAD.replace("s33", "s33\n")
    path.write_bytes(b"\xef\xbb\xbf" + broken.encode("utf-8"))
    e, twin = _refused(path), _refused(_toml(tmp_path, head=broken))
    assert (e.line, e.column) == (twin.line, twin.column) == (2, 12)


# --- AOI 2. an observer's area of interest of 0 ------------------------------------------------------

def test_an_observer_area_of_interest_of_zero_is_refused(tmp_path):
    e = _refused(_toml(tmp_path, "[agent_types.observer]\naoi_radius_m = 0\n"))
    assert e.field == "agent_types.observer.aoi_radius_m" and "(got 0.0)" in str(e)
    assert "must be within (0, 1000000] for observers" in str(e)
    e = _refused(_toml(tmp_path, "[agent_types.observer]\naoi_radius_m = -0.0\n"))
    assert e.field == "agent_types.observer.aoi_radius_m"
    # another kind may see only itself; an observer's tiny but positive area stays
    s = load_scenario(_toml(tmp_path, "[agent_types.ground]\naoi_radius_m = 0\n[agent_types.aircraft]\n"
                                      "aoi_radius_m = 0.0\n[agent_types.observer]\naoi_radius_m = 1e-3\n"))
    assert (s.kind_params["ground"].aoi_radius_m, s.kind_params["aircraft"].aoi_radius_m,
            s.kind_params["observer"].aoi_radius_m) == (0.0, 0.0, 1e-3)
