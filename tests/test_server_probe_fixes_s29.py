"""Server and recording findings of the acceptance probe (session 29):

1. a take-over of a recording that runs past its scenario's duration_s (``sortie server
   --duration``) stopped at once: it now runs to the exercise's end, the later of the
   scenario's duration_s and the recording's end, or for ``--duration S``; one that would
   leave no live phase is refused naming --take-over;
2. two servers of one exercise started in the same second collided on the default recording
   name: a chosen name takes a -2, -3 suffix (a --record file that exists stays an error);
3. a take-over of a static agent (which no client can claim) is refused naming --agent;
4. the exercise's name keeps its letters in the recording's file name (accents dropped);
5. the glTF scene's extras list every event, joins and leaves too (not placed);
6. a start_time past year 9999 in UTC is a ScenarioError naming exercise.start_time;
7. an integer longer than Python converts (4300 digits) is a ScenarioError with its line;
8. ``--clock fast --time-scale 0.5`` is refused as the scenario refuses it;
9. a ground vehicle's autopilot speed is refused saying [0, its top speed];
10. ``--record-dir`` naming a file is an error naming the option and the value;
11. a target area around a pole is refused as circling it (the insets' lattice and every
    drawing take edges straight in latitude and longitude, so no area can contain a pole).

Real parts: scenarios are parsed from real text, worlds built on the embedded SRTM tile and
recorded with the real Recorder, the command line runs as real ``sortie`` processes.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import time

import numpy as np
import pytest

from conftest import REPO
from server.recording import Recording
from sortie.errors import InvalidArgument

DEM = REPO / "data" / "dem" / "N47E009.hgt"

SCENARIO = f"""
[exercise]
name = "Ünïcødé: Shield *?"
start_time = 2026-06-15T07:00:00Z
clock = "fast"
duration_s = 1.0

[terrain]
dem = ["{DEM}"]
geoid_undulation_m = 48.0

[[agents]]
name = "tank1"
kind = "ground"
type = "m1a2"
coalition = "blue"
lat_deg = 47.29
lon_deg = 9.59
heading_deg = 45.0
controllable = true

[[agents]]
name = "truck1"
kind = "ground"
type = "hmmwv"
coalition = "blue"
lat_deg = 47.295
lon_deg = 9.595
controllable = true

[[agents]]
name = "sam1"
kind = "static"
type = "sam_site"
coalition = "red"
lat_deg = 47.35
lon_deg = 9.45
"""

RECORDED_S = 2.0  # the recording runs past the scenario's duration_s, as `sortie server --duration 2` does


def sortie(capsys, *args) -> subprocess.CompletedProcess:
    """A ``sortie`` command run in this process (sortie.cli.main, as the entry point runs it):
    its exit status, stdout and stderr."""
    from sortie.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


def _scenario_file(folder, text: str = SCENARIO, name: str = "s29.toml"):
    path = folder / name
    path.write_text(text, encoding="utf-8")
    return path


def _world(path):
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain

    scenario = load_scenario(path)
    terrain, desc, _ = open_terrain(scenario)
    return build_world(scenario, terrain), scenario, terrain, desc


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    """A recording of 2 s of an exercise whose scenario ends at 1 s (the world recorded as a
    server run with --duration 2 records it)."""
    from server.recorder import Recorder, recording_header
    from server.sim_server import terrain_spec

    d = tmp_path_factory.mktemp("s29")
    scenario_path = _scenario_file(d)
    world, scenario, terrain, desc = _world(scenario_path)
    path = d / "long.sortie"
    rec = Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain))
    world.attach_recorder(rec)
    try:
        while world.time_s < RECORDED_S - 1e-9:
            world.tick()
    finally:
        rec.close()
        world.close()
    return path


# -- 1. a take-over runs live past the scenario's duration_s ---------------------------------------

def test_a_take_over_runs_to_the_recordings_end_past_the_scenarios_duration(recorded):
    from server.resim import take_over

    world, _, scenario = take_over(recorded, 1.5, "tank1")
    try:
        assert world.time_s == pytest.approx(1.5)
        # The exercise as the take-over runs it ends at the recording's end (2 s), not at the
        # scenario's 1 s, which the server's clock had already passed: it stopped at once.
        assert scenario.exercise.duration_s == pytest.approx(RECORDED_S)
    finally:
        world.close()
    world, _, scenario = take_over(recorded, 2.0, "tank1", duration_s=3.0)  # --duration: live seconds
    try:
        assert scenario.exercise.duration_s == pytest.approx(5.0)
    finally:
        world.close()
    with pytest.raises(InvalidArgument, match=r"take_over: leaves no live phase: the exercise ends at t = 2 s.*"
                                              r"--duration S"):
        take_over(recorded, 2.0, "tank1")


def test_sortie_resim_take_over_goes_live_to_the_exercises_end(recorded, capsys):
    """The probe's run: live from 1.5 s of a recording made to 2 s of a 1-s scenario; it stopped
    at 1.5 s (one tick) before."""
    out = sortie(capsys, "resim", recorded, "--take-over", "1.5", "--agent", "tank1", "--port", "0", "--no-record")
    assert out.returncode == 0, out.stderr
    assert "(until t = 2.00 s)" in out.stdout, out.stdout
    assert "take-over stopped at world time 2.0 s" in out.stderr, out.stderr
    out = sortie(capsys, "resim", recorded, "--take-over", "2", "--agent", "tank1", "--port", "0", "--no-record")
    assert out.returncode == 2 and "--take-over: leaves no live phase" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr
    out = sortie(capsys, "resim", recorded, "--duration", "3")
    assert out.returncode == 2 and "duration: only with --take-over" in out.stderr, out.stderr


# -- 3. a static agent is not taken over --------------------------------------------------------------

def test_a_take_over_of_a_static_agent_is_refused(recorded, capsys):
    from server.resim import take_over

    with pytest.raises(InvalidArgument, match=r"agent: is a static agent: no client can take it over"):
        take_over(recorded, 1.0, "sam1")
    out = sortie(capsys, "resim", recorded, "--take-over", "1", "--agent", "sam1", "--port", "0", "--no-record")
    assert out.returncode == 2 and "--agent: is a static agent" in out.stderr and "'sam1'" in out.stderr, out.stderr


# -- 2, 4, 10. the recording's file name and folder -----------------------------------------------

def _args(**kw):
    values = {"record": None, "record_dir": "recordings", "no_record": False, "record_chunk_s": 1.0}
    values.update(kw)
    return argparse.Namespace(**values)


def _header():
    from server import recording_codec as codec
    from server.recording import quantization_of
    from sortie.v1 import recording_pb2 as rpb

    return rpb.RecordingHeader(format_version=1, exercise_name="small", world_rate_hz=30.0,
                               quantization=quantization_of(codec.DEFAULT_STEPS))


def test_a_chosen_recording_name_taken_gets_a_suffix(tmp_path):
    from server.sim_cli import check_recording, new_recording

    args = _args(record_dir=str(tmp_path / "rd"))
    path = check_recording(args, "small")
    path.parent.mkdir()
    path.write_bytes(b"another server's")  # the other server of the exercise, in the same second
    path.with_name(f"{path.stem}-2{path.suffix}").write_bytes(b"and a third's")
    assert check_recording(args, "small").parent == path.parent  # no error: a suffix is taken
    recorder = new_recording(path, _header, 1.0, "record_dir")
    try:
        assert recorder.path == path.with_name(f"{path.stem}-3{path.suffix}")
    finally:
        recorder.close()
    assert path.read_bytes() == b"another server's"  # never overwritten
    # A --record file is the user's: one that exists is an error naming the option.
    with pytest.raises(InvalidArgument, match=r"record: the file exists"):
        check_recording(_args(record=str(path)), "small")
    with pytest.raises(InvalidArgument, match=r"record: the file exists"):
        new_recording(path, _header, 1.0, "record")


def test_sortie_server_records_under_a_suffix_when_its_name_is_taken(tmp_path, capsys):
    """Two servers of the exercise in the same second: the second's name takes -2 (before, it
    failed: 'record: the file exists', or a raw [Errno 17] File exists)."""
    scenario = _scenario_file(tmp_path, SCENARIO.replace("Ünïcødé: Shield *?", "small"))
    rd = tmp_path / "rd"
    rd.mkdir()
    now = time.time()
    for dt in range(-1, 30):  # whatever second it starts in
        stamp = time.strftime("%Y%m%dT%H%M%SZ", time.gmtime(now + dt))
        (rd / f"small-{stamp}.sortie").write_bytes(b"taken")
    out = sortie(capsys, "server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", "--duration",
                 "0.2", "--record-dir", rd)
    assert out.returncode == 0, out.stderr
    made = [p for p in rd.iterdir() if p.read_bytes() != b"taken"]
    assert len(made) == 1 and made[0].name.endswith("-2.sortie"), sorted(p.name for p in rd.iterdir())
    assert f"recording to {made[0]}" in out.stdout
    with Recording(made[0]) as r:
        assert r.last_time_s > 0


def test_the_recording_name_keeps_the_exercises_letters():
    from server.sim_cli import recording_path

    path = recording_path(_args(), "Ünïcødé: Shield *?")
    assert path.name.startswith("unicøde-shield-"), path.name  # was 'n-c-d-shield-'
    assert recording_path(_args(), "Alpine Shield (Lake Constance) take-over").name.startswith(
        "alpine-shield-lake-constance-take-over-")  # ASCII names as before
    assert recording_path(_args(), "Учения «Щит» 2026").name.startswith("учения-щит-2026-")
    assert recording_path(_args(), "*** ???").name.startswith("sortie-")
    long = recording_path(_args(), "演習" * 64)  # 128 characters of 3 UTF-8 bytes each
    assert len(long.name.encode("utf-8")) < 255


def test_a_record_dir_that_is_a_file_is_an_error_naming_the_option(tmp_path, capsys):
    from server.sim_cli import check_recording

    a_file = tmp_path / "passwd"
    a_file.write_text("x")
    with pytest.raises(InvalidArgument, match=r"record_dir: is not a folder \(got '.*passwd'\)"):
        check_recording(_args(record_dir=str(a_file)), "small")
    with pytest.raises(InvalidArgument, match=r"record_dir: is not a folder \(.*passwd is not a folder\)"):
        check_recording(_args(record_dir=str(a_file / "deeper")), "small")
    with pytest.raises(InvalidArgument, match=r"record: cannot be made: .*passwd is not a folder"):
        check_recording(_args(record=str(a_file / "x.sortie")), "small")
    scenario = _scenario_file(tmp_path)
    out = sortie(capsys, "server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", "--duration",
                 "0.2", "--record-dir", a_file)
    assert out.returncode == 2 and f"record_dir: is not a folder (got '{a_file}')" in out.stderr, out.stderr


# -- 5. the glTF scene lists joins and leaves -----------------------------------------------------

def test_gltf_extras_list_joins_and_leaves_unplaced(tmp_path):
    from server.gltf import export_gltf
    from sortie.v1 import recording_pb2 as rpb
    from sortie.v1 import simulation_pb2 as pb
    from test_acmi import info, write_synthetic

    def event(tick, kind):
        return rpb.EventRecord(tick=tick, event=pb.WorldEvent(time_s=tick / 30.0, kind=kind, entity_id=1,
                                                              lat_deg=47.3, lon_deg=9.5, alt_msl_m=1000.0,
                                                              detail_json=json.dumps({"client": "c"})))

    path = tmp_path / "ev.sortie"
    write_synthetic(path, {1: (info(1, "jet", pb.ENTITY_KIND_AIRCRAFT, "f16"), lambda t: (47.3, 9.5 + t * 1e-5,
                                                                                          1000.0, 0, 0, 90))},
                    60, events=[event(5, "join"), event(20, "crash"), event(40, "leave")])
    out = tmp_path / "ev.glb"
    with Recording(path) as r:
        export_gltf(r, out)
    from test_mesh import _glb_json

    gltf = _glb_json(out.read_bytes())
    events = gltf["scenes"][0]["extras"]["sortie"]["events"]
    assert [(e["kind"], e["placed"]) for e in events] == [("join", False), ("crash", True), ("leave", False)]
    import trimesh

    assert len(trimesh.load(out, force="scene").geometry["events"].vertices) == 1  # the crash only


# -- 6, 7, 11. scenario values --------------------------------------------------------------------

def _parse(text: str, suffix: str = ".toml"):
    from server.scenario import parse_scenario, scenario_data

    return parse_scenario(scenario_data(text, "x" + suffix), REPO)


def test_a_start_time_past_year_9999_in_utc_is_a_scenario_error(tmp_path, capsys):
    from server.scenario import ScenarioError

    text = SCENARIO.replace("2026-06-15T07:00:00Z", "9999-12-31T23:59:59-05:00")
    with pytest.raises(ScenarioError, match=r"exercise\.start_time: must be within years 1\.\.9999 in UTC"):
        _parse(text)
    with pytest.raises(ScenarioError, match=r"exercise\.start_time: must be within years 1\.\.9999 in UTC"):
        _parse(SCENARIO.replace("2026-06-15T07:00:00Z", "0001-01-01T00:00:00+05:00"))
    out = sortie(capsys, "server", "--scenario", _scenario_file(tmp_path, text), "--port", "0", "--no-record")
    assert out.returncode == 2 and "exercise.start_time" in out.stderr and "Traceback" not in out.stderr


def test_an_integer_of_more_than_4300_digits_is_a_scenario_error_with_its_line():
    from server.scenario import ScenarioError

    huge = "1" + "0" * 5000
    text = SCENARIO.replace("heading_deg = 45.0", f"heading_deg = {huge}")
    line = text[:text.index(huge)].count("\n") + 1
    with pytest.raises(ScenarioError, match=rf"line {line}, column 15: TOML value error: heading_deg is an integer "
                                            r"of 5001 digits \(at most 4300\)"):
        _parse(text)
    yaml_text = "exercise:\n  name: x\n  start_time: '2026-06-15T07:00:00Z'\n  duration_s: " + huge + "\n"
    with pytest.raises(ScenarioError, match=r"line 4, column 15: YAML syntax error: found an integer of 5001 digits"):
        _parse(yaml_text, ".yaml")


def test_a_target_area_round_a_pole_is_refused_as_circling_it():
    from server.scenario import ScenarioError

    def area(polygon):
        return SCENARIO + f'\n[[target_areas]]\nname = "a"\npolygon = {polygon}\ndetail_m = 100.0\n'

    with pytest.raises(ScenarioError, match=r"target_areas\[0\]\.polygon: circles a pole"):
        _parse(area("[[89.99, 0], [89.99, 90], [89.99, 180], [89.99, -90]]"))
    with pytest.raises(ScenarioError, match=r"circles a pole"):  # the south pole, clockwise
        _parse(area("[[-89.99, 0], [-89.99, -90], [-89.99, 180], [-89.99, 90]]"))
    # Areas near a pole that do not circle it, and across the antimeridian, pass as before.
    assert _parse(area("[[89.9, 10], [89.9, 20], [89.95, 20], [89.95, 10]]")).target_areas
    assert _parse(area("[[10.45, 179.99], [10.45, -179.99], [10.55, -179.99], [10.55, 179.99]]")).target_areas


# -- 8. the fast clock's rate --------------------------------------------------------------------

@pytest.mark.parametrize("scenario, clock_opt, scale_opt", [
    (("realtime", 1.0), "fast", 0.5),
    (("fast", 10.0), None, 1.0),
    (("paused", 1.0), "fast", 1.0),
])
def test_the_fast_clock_runs_faster_than_real_time_as_in_a_scenario(scenario, clock_opt, scale_opt):
    from server.sim_cli import run_clock

    with pytest.raises(InvalidArgument, match=r"time_scale: must be within \(1, 1000\] with the fast clock"):
        run_clock(*scenario, clock_opt, scale_opt)
    assert run_clock(*scenario, clock_opt, 1.5) == ("fast", 1.5)


def test_sortie_server_refuses_the_fast_clock_slower_than_real_time(tmp_path, capsys):
    out = sortie(capsys, "server", "--scenario", _scenario_file(tmp_path), "--port", "0", "--no-record", "--clock",
                 "fast", "--time-scale", "0.5")
    assert out.returncode == 2 and "time_scale: must be within (1, 1000] with the fast clock" in out.stderr, \
        out.stderr


# -- 9. a ground vehicle's autopilot speed ---------------------------------------------------------

def test_a_ground_autopilot_speed_is_refused_with_its_own_range(tmp_path):
    from fdm.vehicle_types import VEHICLE_TYPES

    world, *_ = _world(_scenario_file(tmp_path))
    try:
        truck = next(e.id for e in world.entities.values() if e.name == "truck1")
        top = VEHICLE_TYPES["hmmwv"].max_speed_mps
        for speed in (1000.0, -3.0, -0.001, top + 0.01):
            with pytest.raises(InvalidArgument) as exc:
                world.command(truck, "autopilot", {"speed_mps": speed})
            assert str(exc.value).startswith(f"autopilot.speed_mps: must be within [0, {top:.6g}] m/s for truck1 "
                                             "(hmmwv: its top speed)"), exc.value
        for speed in (0.0, top):  # both ends inclusive
            world.command(truck, "autopilot", {"speed_mps": speed})
        world.command(truck, "drive", {"speed_mps": -3.0, "yaw_rate_dps": 0.0})  # a driver may reverse
        assert np.isfinite(top)
    finally:
        world.close()
