"""The glTF debrief scene (server/gltf.py, `sortie export gltf`).

Bounds: a track point leaves the recording as float64 ECEF and reaches the file as float32
offsets from the scene's origin, within 2^-24 of the largest offset per coordinate, twice
(the offset, then the write), so the comparison allows 2 x 2^-24 x max |offset| (under 3 mm
for the 40 km of the alps world). A ground vehicle drives on the terrain (fdm/ground.py:
terrain following from the wheel base), so its recorded ellipsoidal height minus the geoid
undulation is the terrain's height within its ride height and the difference between the
wheel-base fit and the one-point height (1.5 m here), which checks that the tracks and the
terrain mesh share one frame and one datum.
"""

from __future__ import annotations

import json
import subprocess

import numpy as np
import pytest
import trimesh

from server import recording_codec as codec
from server.gltf import export_gltf, read_tracks, track_box
from server.process import sortie_command
from server.recording import Recording
from sortie.errors import InvalidArgument
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic
from terrain.mesh import LocalFrame, enu_to_gltf, gltf_to_enu
from test_acmi import info, record_alps, write_synthetic
from test_mesh import _glb_json



def _glb(path) -> dict:
    """The JSON chunk of a GLB file (tests/test_mesh.py's reader: strict, no NaN)."""
    return _glb_json(path.read_bytes())


@pytest.fixture(scope="module")
def alps(tmp_path_factory):
    """(recording, its glb with a 96x96 terrain) of the alps world."""
    d = tmp_path_factory.mktemp("gltf")
    rec = d / "alps.sortie"
    record_alps(rec, 150)
    out = d / "alps.glb"
    from server.sim_server import open_terrain_source
    from server.resim import recorded_terrain_spec

    with Recording(rec) as r:
        terrain = open_terrain_source(**recorded_terrain_spec(r)[0])
        export_gltf(r, out, terrain, size="96x96")
    return rec, out, terrain


def _frame(gltf: dict) -> LocalFrame:
    f = gltf["scenes"][0]["extras"]["sortie"]["frame"]
    return LocalFrame.at(f["lat_deg"], f["lon_deg"], f["h_m"])


def _kept(v: np.ndarray) -> np.ndarray:
    """Rows that differ from the row before (the first always)."""
    keep = np.ones(len(v), bool)
    keep[1:] = np.any(v[1:] != v[:-1], axis=1)
    return keep


def _polyline(path) -> np.ndarray:
    """A Path3D written as line segments (p0 p1, p1 p2, ...) back to its points."""
    v = np.asarray(path.vertices)
    return v[_kept(v)]


def test_tracks_are_the_recorded_positions(alps):
    rec, out, _ = alps
    gltf = _glb(out)
    frame = _frame(gltf)
    scene = trimesh.load(out, force="scene")
    with Recording(rec) as r:
        names = {i: f"{e.name} #{i}" for i, e in r.entities.items()}
        assert {n["name"] for n in gltf["nodes"]} >= {"terrain", "events", *names.values()}
        steps = r.steps.vector()[codec.POS]
        moving = 0
        for entity_id, name in names.items():
            truth = np.stack([r.frame(t).q[np.searchsorted(r.frame(t).ids, entity_id), codec.POS] * steps
                              for t in range(r.first_tick, r.last_tick + 1)
                              if entity_id in r.frame(t).ids])
            stored = _polyline(scene.geometry[name])
            # The file holds the float32 of each offset; ticks where that did not change (a
            # parked tank) are one point of the polyline.
            offsets = enu_to_gltf(frame.to_local(truth)).astype(np.float32)
            keep = _kept(offsets)
            assert np.array_equal(stored, offsets[keep]), name
            bound = 2.0 * 2.0 ** -24 * np.abs(frame.to_local(truth)).max()
            assert np.abs(frame.to_ecef(gltf_to_enu(stored)) - truth[keep]).max() <= bound, name
            moving += int(keep.sum() > 2)
            mesh_extras = next(m for m in gltf["meshes"] if m["name"] == name)["extras"]
            e = r.entities[entity_id]
            assert mesh_extras["entity_id"] == entity_id and mesh_extras["type"] == e.type
            assert mesh_extras["coalition"] == (e.coalition or "neutral")
        assert moving >= 6


def test_ground_tracks_lie_on_the_terrain(alps):
    rec, out, terrain = alps
    frame = _frame(_glb(out))
    scene = trimesh.load(out, force="scene")
    with Recording(rec) as r:
        undulation = r.header.geoid_undulation_m
        ground = [e for e in r.entities.values() if e.kind == pb.ENTITY_KIND_GROUND]
        assert ground
        for e in ground:
            track = _polyline(scene.geometry[f"{e.name} #{e.entity_id}"])
            lat, lon, h = ecef_to_geodetic(frame.to_ecef(gltf_to_enu(track)))
            above = h - undulation - terrain.heights(lat, lon).height_msl_m
            assert np.abs(above).max() < 1.5, e.name
    # The terrain mesh: its vertices at the terrain's heights plus the undulation.
    tm = scene.geometry["terrain"]
    lat, lon, h = ecef_to_geodetic(frame.to_ecef(gltf_to_enu(tm.vertices)))
    assert np.abs(h - undulation - terrain.heights(lat, lon).height_msl_m).max() < 0.01
    assert len(tm.faces) == 2 * 95 * 95


def test_scene_extras_and_events(alps):
    rec, out, _ = alps
    extras = _glb(out)["scenes"][0]["extras"]["sortie"]
    assert extras["frame"]["datum"] == "WGS84" and extras["geoid_undulation_m"] == 48.0
    assert extras["terrain"]["grid"] == [96, 96] and extras["terrain"]["sun_time_utc"] == "2026-06-15T07:00:00Z"
    kinds = [e["kind"] for e in extras["events"]]
    assert "remove" in kinds  # joins and leaves are listed too, with no point (docs/RECORDING.md)
    assert all(not e["placed"] for e in extras["events"] if e["kind"] in ("join", "leave"))
    placed = [e for e in extras["events"] if e["placed"]]
    scene = trimesh.load(out, force="scene")
    assert len(scene.geometry["events"].vertices) == len(placed)
    box = extras["terrain_box"]
    lat, lon, _ = ecef_to_geodetic(np.concatenate([p for t in read_tracks(Recording(rec)).values()
                                                   for p in (seg.ecef for seg in t.segments)]))
    assert box[0] < lat.min() and lat.max() < box[2] and box[1] < lon.min() and lon.max() < box[3]


def test_breaks_rates_and_the_antimeridian(tmp_path):
    def jumper(tick):  # across the antimeridian eastwards, absent from tick 40 to 59
        return None if 40 <= tick < 60 else (-16.5, 179.99 + 0.0004 * tick, 1000.0, 0.0, 0.0, 90.0)

    def parked(tick):
        return (-16.4, -179.95, 0.0, 0.0, 0.0, 0.0)

    def ghost(tick):  # absent from the whole second chunk (ticks 31-60): not in it at all
        return None if 25 <= tick < 65 else (-16.45, 179.98, 500.0, 0.0, 0.0, 0.0)

    rec = tmp_path / "s.sortie"
    write_synthetic(rec, {1: (info(1, "jumper", pb.ENTITY_KIND_AIRCRAFT, "f16", "red"), jumper),
                          2: (info(2, "parked", pb.ENTITY_KIND_GROUND, "m1"), parked),
                          3: (info(3, "ghost", pb.ENTITY_KIND_AIRCRAFT, "c172x"), ghost)}, ticks=90)
    with Recording(rec) as r:
        assert 3 not in r.chunk(1).entity_ids
        tracks = read_tracks(r)
        assert [len(seg.times) for seg in tracks[1].segments] == [39, 31]  # ticks 1-39 and 60-90
        assert [len(seg.times) for seg in tracks[2].segments] == [90]
        assert [seg.times[0] * 30.0 for seg in tracks[3].segments] == pytest.approx([1.0, 65.0])
        assert [len(seg.times) for seg in tracks[3].segments] == [24, 26]
        assert [len(seg.times) for seg in read_tracks(r, 10.0)[1].segments] == [14, 11]  # tick 1, then every 3rd tick
        lat_min, lon_min, lat_max, lon_max = track_box(tracks, 1000.0)
        assert lon_min < 180.0 < lon_max and lon_max - lon_min < 0.1  # not the whole world
        stats = export_gltf(r, tmp_path / "s.gltf")
    assert stats.tracks == 3 and stats.terrain_vertices == 0
    gltf = json.loads((tmp_path / "s.gltf").read_text())
    assert gltf["asset"]["version"] == "2.0" and "terrain" not in {n["name"] for n in gltf["nodes"]}
    red = next(m for m in gltf["meshes"] if m["name"] == "jumper #1")
    colours = gltf["accessors"][red["primitives"][0]["attributes"]["COLOR_0"]]
    assert colours["min"] == [235, 40, 40, 255] == colours["max"]


def test_bad_input(alps, tmp_path):
    rec, _, _ = alps
    with Recording(rec) as r:
        with pytest.raises(InvalidArgument, match="output"):
            export_gltf(r, tmp_path / "x.obj")
        with pytest.raises(InvalidArgument, match="margin_m"):
            export_gltf(r, tmp_path / "x.glb", margin_m=-1.0)
        with pytest.raises(InvalidArgument, match="rate"):
            export_gltf(r, tmp_path / "x.glb", rate_hz=0.0)
    import server.gltf as gltf_module

    with Recording(rec) as r, pytest.MonkeyPatch.context() as mp:
        mp.setattr(gltf_module, "MAX_TRACK_POINTS", 100)
        with pytest.raises(InvalidArgument, match=r"rate.*over the limit of 100: export at"):
            export_gltf(r, tmp_path / "x.glb")
        # The rate it names fits the limit.
        mp.setattr(gltf_module, "MAX_TRACK_POINTS", 1000)
        with pytest.raises(InvalidArgument, match="export at") as err:
            export_gltf(r, tmp_path / "x.glb")
        fits = float(str(err.value).split("export at ")[1].split(" Hz")[0])
        assert 900 < export_gltf(r, tmp_path / "ok.glb", rate_hz=fits).track_points <= 1000
        assert 0.0 < fits < r.rate_hz
    empty = tmp_path / "empty.sortie"
    write_synthetic(empty, {}, ticks=3)
    with Recording(empty) as r, pytest.raises(InvalidArgument, match="recording"):
        export_gltf(r, tmp_path / "x.glb")
    assert not (tmp_path / "x.glb").exists()


def test_command_line(alps, tmp_path):
    rec, _, _ = alps
    out = tmp_path / "cli.glb"
    done = subprocess.run([*sortie_command(), "export", "gltf", str(rec), "-o", str(out), "--size", "32x32",
                           "--rate", "5"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "12 tracks" in done.stdout and "terrain 1,024 vertices" in done.stdout
    assert _glb(out)["scenes"][0]["extras"]["sortie"]["terrain"]["grid"] == [32, 32]
    done = subprocess.run([*sortie_command(), "export", "gltf", str(rec), "-o", str(tmp_path / "x.glb"),
                           "--spacing-m", "-3"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 2 and "--spacing-m" in done.stderr
    assert not (tmp_path / "x.glb").exists()


def test_header_without_terrain_files(tmp_path):
    rec = tmp_path / "s.sortie"
    write_synthetic(rec, {1: (None, lambda t: (47.3, 9.3, 2000.0, 0.0, 0.0, 0.0))}, ticks=5)
    with Recording(rec) as r:
        assert not r.header.terrain.files
    done = subprocess.run([*sortie_command(), "export", "gltf", str(rec), "-o", str(tmp_path / "x.glb")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "terrain" in done.stderr


# -- the animated markers ---------------------------------------------------------------------------

def _accessor(gltf: dict, binary: bytes, k: int) -> np.ndarray:
    """Accessor k as an array (float32 / uint16, tightly packed as server/gltf.py writes them)."""
    a = gltf["accessors"][k]
    view = gltf["bufferViews"][a["bufferView"]]
    dtype = {5126: "<f4", 5123: "<u2"}[a["componentType"]]
    width = {"SCALAR": 1, "VEC3": 3, "VEC4": 4}[a["type"]]
    start = view.get("byteOffset", 0) + a.get("byteOffset", 0)
    return np.frombuffer(binary, dtype, a["count"] * width, start).reshape(a["count"], width)


def _rotation_matrices(q_xyzw: np.ndarray) -> np.ndarray:
    x, y, z, w = (q_xyzw[:, i].astype(np.float64) for i in range(4))
    return np.stack([np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
                     np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
                     np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1)], 1)


def test_markers_follow_the_tracks_with_the_recorded_attitude(alps):
    """Each marker's keys are its track's float32 offsets at world time - t0, and its rotation
    takes body axes into the scene as the recorded attitude does: checked against Tacview's
    Euler angles (server/acmi.attitude_deg), composed independently here as
    R_ned<-body = Rz(yaw) Ry(pitch) Rx(roll), within float32 rounding (1e-5)."""
    from server.acmi import attitude_deg
    from server.gltf import read_glb

    rec, out, _ = alps
    gltf, binary = read_glb(out.read_bytes())
    frame = _frame(gltf)
    anim = gltf["animations"][0]
    t0 = anim["extras"]["time_zero_world_s"]
    by_node = {}
    for ch in anim["channels"]:
        by_node.setdefault(ch["target"]["node"], {})[ch["target"]["path"]] = anim["samplers"][ch["sampler"]]
    gltf_of_enu = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    enu_of_ned = np.array([[0, 1.0, 0], [1.0, 0, 0], [0, 0, -1.0]])
    with Recording(rec) as r:
        steps = r.steps.vector()
        checked = 0
        for node_k, node in enumerate(gltf["nodes"]):
            if node_k not in by_node:
                continue
            entity_id = node["extras"]["entity_id"]
            assert node["name"] == f"{r.entities[entity_id].name} #{entity_id} marker"
            frames = [r.frame(t) for t in range(r.first_tick, r.last_tick + 1)]
            states = np.stack([f.q[np.searchsorted(f.ids, entity_id)] * steps for f in frames if entity_id in f.ids])
            times = np.array([f.time_s for f in frames if entity_id in f.ids])
            ch = by_node[node_k]
            assert np.array_equal(_accessor(gltf, binary, ch["translation"]["input"])[:, 0],
                                  (times - t0).astype(np.float32))
            where = _accessor(gltf, binary, ch["translation"]["output"])
            assert np.array_equal(where, enu_to_gltf(frame.to_local(states[:, codec.POS])).astype(np.float32))
            turn = _accessor(gltf, binary, ch["rotation"]["output"])
            assert np.all(np.einsum("ij,ij->i", turn[1:], turn[:-1]) >= 0.0)  # the short way between keys
            lat, lon, _ = ecef_to_geodetic(states[:, codec.POS])
            roll, pitch, yaw = (np.radians(a) for a in attitude_deg(states[:, codec.QUAT], lat, lon))
            cr, sr, cp, sp, cy, sy = np.cos(roll), np.sin(roll), np.cos(pitch), np.sin(pitch), np.cos(yaw), np.sin(yaw)
            ned_body = np.stack([np.stack([cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr], -1),
                                 np.stack([sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr], -1),
                                 np.stack([-sp, cp * sr, cp * cr], -1)], 1)
            # ENU at the entity, then into the frame's ENU at the origin (the basis of each).
            from terrain.geodesy import enu_basis

            e, n, u = enu_basis(lat, lon)
            ecef_enu_here = np.stack([e, n, u], axis=-1)  # columns: the local ENU axes in ECEF
            expected = gltf_of_enu @ frame.basis @ ecef_enu_here @ enu_of_ned @ ned_body
            assert np.abs(_rotation_matrices(turn) - expected).max() < 1e-5, node["name"]
            scale = _accessor(gltf, binary, ch["scale"]["output"])
            assert ch["scale"]["interpolation"] == "STEP" and np.all(scale[0] == node["scale"])
            checked += 1
        assert checked == len(r.entities)


def test_markers_hide_while_absent(tmp_path):
    from server.gltf import MARKER_SCALE_M, read_glb

    def jumper(tick):
        return None if 40 <= tick < 60 else (47.3, 9.3 + 0.0004 * tick, 1000.0, 0.0, 0.0, 90.0)

    def late(tick):
        return None if tick < 30 else (47.31, 9.3, 1200.0, 0.0, 5.0, 0.0)

    rec = tmp_path / "s.sortie"
    write_synthetic(rec, {1: (info(1, "jumper", pb.ENTITY_KIND_AIRCRAFT, "f16", "red"), jumper),
                          2: (info(2, "late", pb.ENTITY_KIND_GROUND, "m1a2"), late)}, ticks=90)
    with Recording(rec) as r:
        export_gltf(r, tmp_path / "s.glb")
        t0, dt = r.first_time_s, r.dt
    gltf, binary = read_glb((tmp_path / "s.glb").read_bytes())
    anim = gltf["animations"][0]
    keys = {}
    for ch in anim["channels"]:
        if ch["target"]["path"] == "scale":
            s = anim["samplers"][ch["sampler"]]
            name = gltf["nodes"][ch["target"]["node"]]["name"]
            keys[name] = (_accessor(gltf, binary, s["input"])[:, 0], _accessor(gltf, binary, s["output"])[:, 0])
    air = MARKER_SCALE_M[pb.ENTITY_KIND_AIRCRAFT]
    t, s = keys["jumper #1 marker"]
    assert np.allclose(t, np.array([0.0, (39 - 1 + 0.5) * dt, (60 - 1) * dt], np.float32)) and list(s) == [air, 0, air]
    t, s = keys["late #2 marker"]
    assert np.allclose(t, [0.0, (30 - 1) * dt]) and list(s) == [0, MARKER_SCALE_M[pb.ENTITY_KIND_GROUND]]
    assert t0 == dt


def test_the_khronos_validator_finds_nothing(alps, tmp_path):
    """The files pass the Khronos glTF validator (npm gltf-validator, installed by make bootstrap
    into .tools/): no error and no warning."""
    rec, glb, terrain = alps
    with Recording(rec) as r:
        export_gltf(r, tmp_path / "scene.gltf", terrain, size="16x16")
    from terrain.mesh import build_mesh, write_mesh

    lat, lon = np.linspace(47.3, 47.2, 12), np.linspace(9.2, 9.35, 13)
    h = terrain.heights(np.repeat(lat, lon.size), np.tile(lon, lat.size)).height_msl_m.reshape(12, 13)
    image = np.zeros((12, 13, 3), np.uint8)
    write_mesh(build_mesh(h, lat, lon), tmp_path / "mesh.glb", image)
    write_mesh(build_mesh(h, lat, lon), tmp_path / "mesh.gltf")
    with Recording(rec) as r:
        export_gltf(r, tmp_path / "adaptive.glb", terrain, size="40x40", max_error_m=5.0)
    _validate([glb, tmp_path / "scene.gltf", tmp_path / "mesh.glb", tmp_path / "mesh.gltf",
               tmp_path / "adaptive.glb"])


def test_a_single_tick_and_ground_without_terrain(tmp_path, alps):
    """A recording of one tick (no track has two points) is its markers alone; a sortie flown
    where the DEM has no data gets no terrain node, and says so."""
    from server.gltf import read_glb

    one = tmp_path / "one.sortie"
    write_synthetic(one, {1: (info(1, "solo", pb.ENTITY_KIND_AIRCRAFT, "f16"), lambda t: (47.3, 9.3, 900.0, 0, 0, 0))},
                    ticks=1)
    with Recording(one) as r:
        stats = export_gltf(r, tmp_path / "one.glb")
    assert stats.tracks == 0 and stats.markers == 1
    gltf, _ = read_glb((tmp_path / "one.glb").read_bytes())
    assert [n["name"] for n in gltf["nodes"]] == ["solo #1 marker"]
    far = tmp_path / "far.sortie"  # 45 N: south of the Alps tile (47-48 N)
    write_synthetic(far, {1: (None, lambda t: (45.0, 9.3 + 1e-4 * t, 900.0, 0, 0, 90.0))}, ticks=30)
    with Recording(far) as r:
        stats = export_gltf(r, tmp_path / "far.glb", alps[2], size="16x16")
    gltf, _ = read_glb((tmp_path / "far.glb").read_bytes())
    assert stats.terrain_vertices == 0 and "terrain" not in {n["name"] for n in gltf["nodes"]}
    assert gltf["scenes"][0]["extras"]["sortie"]["terrain"]["left_out"].startswith("no grid cell")
    _validate([tmp_path / "one.glb", tmp_path / "far.glb"])


def test_a_track_round_the_pole_takes_every_longitude(tmp_path):
    def circling(tick):  # 1.1 km from the pole, round it once in 90 ticks
        return (89.99, -180.0 + 4.0 * tick, 3000.0, 0.0, 0.0, 90.0)

    rec = tmp_path / "pole.sortie"
    write_synthetic(rec, {1: (None, circling)}, ticks=90)
    with Recording(rec) as r:
        lat_min, lon_min, lat_max, lon_max = track_box(read_tracks(r), 2000.0)
    assert (lon_min, lon_max, lat_max) == (-180.0, 180.0, 90.0)
    assert lat_min == pytest.approx(89.99 - 2000.0 / 111_700.0, abs=2e-4)


def test_command_line_names_its_options(alps, tmp_path):
    rec, _, _ = alps
    for extra, option in ((["--margin-m", "-1"], "--margin-m"), (["--rate", "0"], "--rate"),
                          (["--no-terrain", "--size", "8x8"], "--no-terrain"),
                          (["--max-error-m", "nan"], "--max-error-m")):
        done = subprocess.run([*sortie_command(), "export", "gltf", str(rec), "-o", str(tmp_path / "x.glb"), *extra],
                              capture_output=True, text=True, timeout=120)
        assert done.returncode == 2 and f"error: {option}:" in done.stderr, (extra, done.stderr)
    assert not (tmp_path / "x.glb").exists()


def _validate(files) -> None:
    """The Khronos glTF validator over ``files``. make bootstrap installs it with npm, and fails
    if that install fails; only a machine without Node.js and npm has no validator, and there
    this skips."""
    import shutil
    from pathlib import Path

    script = Path(__file__).with_name("gltf_validate.js")
    if shutil.which("node") is None or shutil.which("npm") is None:
        pytest.skip("no Node.js/npm on this machine: make bootstrap cannot install the Khronos glTF validator")
    assert (script.parents[1] / ".tools" / "node_modules" / "gltf-validator").exists(), \
        "npm is here but the glTF validator is not: run make bootstrap"
    done = subprocess.run(["node", str(script), *map(str, files)], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    reports = [json.loads(line) for line in done.stdout.splitlines()]
    assert len(reports) == len(files)
    for rep in reports:
        assert rep["errors"] == 0 and rep["warnings"] == 0, rep


def test_target_areas_are_outlined_on_the_ground(alps):
    """Each of the scenario's target areas is a closed outline through its polygon's vertices,
    TARGET_AREA_LIFT_M above the terrain all along (float32 offsets: within 1 cm here)."""
    from server.gltf import TARGET_AREA_LIFT_M
    from server.resim import recorded_scenario

    rec, out, terrain = alps
    frame = _frame(_glb(out))
    scene = trimesh.load(out, force="scene")
    with Recording(rec) as r:
        areas = recorded_scenario(r).target_areas
        undulation = r.header.geoid_undulation_m
    assert areas
    for area in areas:
        points = _polyline(scene.geometry[f"target area {area.name}"])
        lat, lon, h = ecef_to_geodetic(frame.to_ecef(gltf_to_enu(points)))
        ground = terrain.heights(lat, lon).height_msl_m
        assert np.abs(h - undulation - ground - TARGET_AREA_LIFT_M).max() < 0.01
        corners = np.asarray(area.polygon)
        for c in corners:  # every vertex of the polygon is on the outline
            assert np.hypot(lat - c[0], lon - c[1]).min() < 1e-6
        assert np.hypot(lat[0] - lat[-1], lon[0] - lon[-1]) < 1e-6  # closed


def test_a_recording_made_over_a_terrain_service(tmp_path, hgt_alps):
    """The service is gone: the DEM files it said it served are used where they are found, with
    a note; where they are not, the error lists them and names the options to give."""
    from sortie.v1 import recording_pb2 as rpb

    def identity(path):
        return rpb.TerrainIdentity(description="service:127.0.0.1:1", sources_json=json.dumps(
            [{"kind": "dem", "name": "N47E009", "source": str(path)}]))

    track = {1: (None, lambda t: (47.3, 9.3 + 1e-4 * t, 900.0, 0.0, 0.0, 90.0))}
    here, gone = tmp_path / "here.sortie", tmp_path / "gone.sortie"
    write_synthetic(here, track, ticks=30, terrain=identity(hgt_alps))
    write_synthetic(gone, track, ticks=30, terrain=identity(tmp_path / "missing.hgt"))
    done = subprocess.run([*sortie_command(), "export", "gltf", str(here), "-o", str(tmp_path / "a.glb"),
                           "--size", "16x16"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    assert "keeps no hashes: not checked" in done.stdout and "terrain 256 vertices" in done.stdout
    done = subprocess.run([*sortie_command(), "export", "gltf", str(gone), "-o", str(tmp_path / "b.glb")],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "missing.hgt" in done.stderr and "--terrain ADDRESS" in done.stderr
    assert not (tmp_path / "b.glb").exists()


def test_marker_shapes_are_closed_and_face_outwards(tmp_path):
    """Each marker shape is a closed surface (every edge in two faces) whose faces wind
    counter-clockwise seen from outside: its signed volume (divergence theorem,
    sum a . (b x c) / 6) is positive. An aircraft gets the dart, a ground vehicle the box."""
    from server.gltf import MARKER_SHAPES, read_glb

    for name, (v, f) in MARKER_SHAPES.items():
        edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        _, counts = np.unique(edges, axis=0, return_counts=True)
        assert np.all(counts == 2), name
        a, b, c = (v[f[:, k]].astype(np.float64) for k in range(3))
        assert np.einsum("ij,ij->", a, np.cross(b, c)) / 6.0 > 0.0, name
    rec = tmp_path / "s.sortie"
    jet = info(1, "jet", pb.ENTITY_KIND_AIRCRAFT, "f16", "red")
    tank = info(2, "tank", pb.ENTITY_KIND_GROUND, "m1a2")
    write_synthetic(rec, {1: (jet, lambda t: (47.3, 9.3, 900.0, 0, 0, 0)),
                          2: (tank, lambda t: (47.31, 9.3, 400.0, 0, 0, 0))}, ticks=5)
    with Recording(rec) as r:
        export_gltf(r, tmp_path / "s.glb")
    gltf, _ = read_glb((tmp_path / "s.glb").read_bytes())
    mesh_of = {n["name"]: gltf["meshes"][n["mesh"]]["name"] for n in gltf["nodes"] if n["name"].endswith("marker")}
    assert mesh_of == {"jet #1 marker": "marker dart red", "tank #2 marker": "marker box blue"}
