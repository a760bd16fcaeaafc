"""YAML scenarios: the file's suffix picks TOML or YAML, a YAML scenario validates to exactly the
scenario its TOML twin gives (the same key-path errors too), YAML syntax errors name the line
and column, and a sortie recorded from a YAML scenario re-simulates bit-exact."""

from __future__ import annotations

import copy
import dataclasses
import tomllib
from pathlib import Path

import pytest
import yaml

from server.scenario import ScenarioError, load_scenario, parse_scenario

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "data" / "scenarios" / "alps.toml"
DEM = REPO / "data" / "dem" / "N47E009.hgt"


def _alps_data() -> dict:
    data = tomllib.loads(EXAMPLE.read_text())
    data["terrain"]["dem"] = [str(DEM)]
    return data


def _same(a, b) -> None:
    assert dataclasses.replace(a, base_dir=b.base_dir) == b


@pytest.mark.parametrize("suffix", [".yaml", ".yml", ".YAML"])
def test_alps_as_yaml_loads_equal_to_the_toml(tmp_path, suffix):
    path = tmp_path / f"alps{suffix}"
    path.write_text(yaml.safe_dump(_alps_data(), sort_keys=False))
    _same(load_scenario(path), load_scenario(EXAMPLE))


def test_hand_written_yaml_reads_scalars_as_toml_does(tmp_path):
    """Unquoted date-times, exponents without a dot or sign (YAML 1.1 reads ``1e3`` as a
    string), flow and block sequences, anchors and merge keys."""
    text = f"""
exercise:
  name: Alpine Shield (Lake Constance)
  start_time: 2026-06-15T07:00:00Z
  fdm_rate_hz: 120
  world_rate_hz: 30
  network_rate_hz: 20
  clock: realtime
  duration_s: 3.6e3
  vanished_client_timeout_s: 1e1
terrain:
  dem:
    - {DEM}
agent_types:
  ground: {{dr_position_m: .5}}
agents:
  - &viper
    name: viper1
    kind: aircraft
    type: f16
    coalition: blue
    lat_deg: 47.30
    lon_deg: 9.30
    alt_m: 4500
    heading_deg: 90
    speed_mps: 220.0
    controllable: true
    autopilot: {{route: [[47.30, 9.55, 4500.0], [47.45, 9.70, 4000.0]], speed_mps: 220.0}}
  - <<: *viper
    name: viper2
    lat_deg: 47.31
"""
    path = tmp_path / "s.yaml"
    path.write_text(text)
    twin = tmp_path / "s.toml"
    twin.write_text(f"""
[exercise]
name = "Alpine Shield (Lake Constance)"
start_time = 2026-06-15T07:00:00Z
duration_s = 3600.0
vanished_client_timeout_s = 10
[terrain]
dem = ["{DEM}"]
[agent_types.ground]
dr_position_m = 0.5
[[agents]]
name = "viper1"
kind = "aircraft"
type = "f16"
coalition = "blue"
lat_deg = 47.3
lon_deg = 9.3
alt_m = 4500
heading_deg = 90
speed_mps = 220
controllable = true
autopilot = {{route = [[47.30, 9.55, 4500.0], [47.45, 9.70, 4000.0]], speed_mps = 220.0}}
[[agents]]
name = "viper2"
kind = "aircraft"
type = "f16"
coalition = "blue"
lat_deg = 47.31
lon_deg = 9.3
alt_m = 4500
heading_deg = 90
speed_mps = 220
controllable = true
autopilot = {{route = [[47.30, 9.55, 4500.0], [47.45, 9.70, 4000.0]], speed_mps = 220.0}}
""")
    scenario = load_scenario(path)
    _same(scenario, load_scenario(twin))
    assert scenario.exercise.duration_s == 3600.0 and scenario.exercise.vanished_client_timeout_s == 10.0


def test_other_suffixes_are_refused_naming_the_option_and_the_suffixes(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    for name in ("s.json", "scenario", "s.toml.bak"):
        Path(name).write_text("exercise: {}\n")
        with pytest.raises(ScenarioError) as info:
            load_scenario(name)
        text = str(info.value)
        assert text.startswith("--scenario: ") and ".toml, .yaml, .yml" in text and repr(name) in text, text
    with pytest.raises(ScenarioError, match=r"^--insets: "):
        load_scenario(tmp_path / "s.json", option="--insets")


def test_yaml_syntax_errors_name_file_line_and_column(tmp_path):
    path = tmp_path / "broken.yaml"
    path.write_text("exercise:\n  name: x\n start_time: 2026-06-15T07:00:00Z\n")  # indented wrong
    with pytest.raises(ScenarioError) as info:
        load_scenario(path)
    e = info.value
    assert (e.line, e.column) == (3, 2)
    assert str(e).startswith(f"{path}: line 3, column 2: YAML syntax error: "), str(e)
    path.write_text("exercise:\n  name: x\n  name: y\n")
    with pytest.raises(ScenarioError, match=r": line 3, column 3: YAML syntax error: .*the key 'name' twice") as info:
        load_scenario(path)
    path.write_text("exercise:\n  name: x\n  1: y\n")
    with pytest.raises(ScenarioError, match=r": line 3, column 3: YAML syntax error: .*not a string \(1; quote it\)"):
        load_scenario(path)
    path.write_text("a: 1\n---\nb: 2\n")
    with pytest.raises(ScenarioError, match=r": line 2, column 1: YAML syntax error: .*single document"):
        load_scenario(path)
    path.write_text("a: !!python/object/apply:os.system ['true']\n")
    with pytest.raises(ScenarioError, match=r": line 1, column 4: YAML syntax error: .*constructor"):
        load_scenario(path)


ERROR_CASES = [  # (key path, value): each must fail with the message TOML's tables give
    ("agents[0].lat_deg", "47.3"),
    ("agents[0].lat_deg", 123.0),
    ("agents[1].autopilot.route", [[47.24, 9.522]]),
    ("agents[0].alt_ref", "amsl"),
    ("agents[0].speedmps", 200.0),
    ("exercise.fdm_rate_hz", 125),
    ("exercise.start_time", "2026-06-15T07:00:00"),
    ("agent_types.f16.aoi_radius_m", -1.0),
    ("target_areas[0].polygon", [[47.0, 9.0], [47.0, 9.1], [47.1, 9.0], [47.1, 9.1]]),
]


@pytest.mark.parametrize("path, value", ERROR_CASES)
def test_key_path_errors_are_those_of_toml(tmp_path, path, value):
    data = _alps_data()
    node, keys = data, path.replace("]", "").replace("[", ".").split(".")
    for k in keys[:-1]:
        node = node[int(k)] if k.isdigit() else node[k]
    node[keys[-1]] = value
    with pytest.raises(ScenarioError) as expected:
        parse_scenario(copy.deepcopy(data), tmp_path)
    file = tmp_path / "s.yaml"
    file.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ScenarioError) as got:
        load_scenario(file)
    assert str(got.value) == f"{file}: {expected.value}"
    assert got.value.field == expected.value.field


def test_yaml_1_1_words_are_strings_and_null_is_an_error(tmp_path):
    data = _alps_data()
    data["agents"][0]["coalition"] = "no"
    file = tmp_path / "s.yaml"
    file.write_text(yaml.safe_dump(data, sort_keys=False).replace("coalition: 'no'", "coalition: no"))
    assert "coalition: no\n" in file.read_text()
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.coalition: must be one of 'blue', 'red', 'neutral' "
                                            r"\(got 'no'\)"):
        load_scenario(file)
    data = _alps_data()
    data["agents"][0]["alt_m"] = None  # a required number left empty must not pass as absent
    file.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.alt_m: has no value \(YAML null\)"):
        load_scenario(file)
    data["agents"][0]["alt_m"] = 10 ** 400  # no float holds it: an error, not an OverflowError
    file.write_text(yaml.safe_dump(data, sort_keys=False))
    with pytest.raises(ScenarioError, match=r"agents\[0\]\.alt_m: must be a finite number \(got inf\)"):
        load_scenario(file)
    file.write_text("")
    with pytest.raises(ScenarioError, match=r": exercise: is required"):  # as an empty TOML file
        load_scenario(file)


def test_a_recording_of_a_yaml_scenario_resimulates(tmp_path):
    from server.recorder import Recorder, recording_header
    from server.resim import recorded_scenario, resimulate
    from server.recording import Recording
    from server.sim_server import build_world, open_terrain, terrain_spec

    path = tmp_path / "small.yaml"
    path.write_text(f"""\
exercise: {{name: yaml sortie, start_time: 2026-06-15T07:00:00Z}}
terrain: {{dem: [{DEM}]}}
agents:
  - name: lead
    kind: ground
    type: hmmwv
    coalition: red
    lat_deg: 47.2405
    lon_deg: 9.5224
    autopilot: {{route: [[47.24, 9.522], [47.26, 9.537]], cruise_mps: 12.0}}
  - {{name: sam1, kind: static, type: sam_site, coalition: red, lat_deg: 47.35, lon_deg: 9.45}}
""")
    scenario = load_scenario(path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    out = tmp_path / "small.sortie"
    rec = Recorder(out, recording_header(path, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    try:
        for _ in range(45):
            world.tick()
    finally:
        rec.close()
        world.close()
    with Recording(out) as r:
        assert r.header.scenario_toml == path.read_text()
        _same(recorded_scenario(r), scenario)
    report = resimulate(out)
    assert report.ticks == 45 and report.bit_exact, report.as_dict()
