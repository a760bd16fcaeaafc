"""The whole-exercise acceptance probe, round 36 (/tmp/e2eprobe): exercises over the terrains the team
had not flown (the Sweden coast tile N57E011, Boulder's ESRI ASCII grid, the Grand Canyon GeoTIFF in
EPSG:3857, two far-apart DEMs at once) from scenario to server, bots, observer, recording, replay with
seeks, re-simulation and the exports, and what a user gets wrong on the way.

1. A recording that cannot be made because the file system refuses its name (a read-only file
   system: EROFS; a name too long: ENAMETOOLONG) failed with the raw ``[Errno 30] Read-only file
   system`` / ``[Errno 36] File name too long`` and no option named: cleaning up the file that was
   never made (``remove_recording``) unlinked it, the unlink failed the same way, and that error
   replaced the one saying why; ``check_recording`` let ``Path.exists`` raise the same way.
2. ``sortie resim --dem`` / ``--terrain`` with a terrain the recorded scenario cannot start on
   (the wrong tile) failed with the scenario's own placement error ("move it onto the terrain or
   give alt_m above mean sea level"), naming neither the option nor the recorded terrain.
3. The glTF debrief scene drew a target area's outline at MSL 0 + 5 m wherever it reached past
   the DEM's edge: a wall 1,600 m down from Boulder's terrain.

Real parts: the real file system (a name over NAME_MAX, 255 bytes on every Linux file system; a
read-only tmpfs where this process may mount one), ``sortie server`` and ``sortie resim`` run in
this process over the embedded DEMs (Boulder's .asc recorded, the Alps tile as the wrong one), the
real glTF export read back with trimesh.
"""

from __future__ import annotations

import subprocess
import uuid

import numpy as np
import pytest

from conftest import EMBEDDED_DEM
from test_server_probe_fixes_s29 import _args, _header  # the recording options and header those tests use
from sortie.errors import InvalidArgument

LONG_NAME = "a" * 300  # over NAME_MAX (255 bytes)

SCENARIO = f"""[exercise]
name = "name too long"
start_time = 2026-06-15T07:00:00Z
clock = "fast"
duration_s = 0.2
[terrain]
dem = ["{EMBEDDED_DEM / 'N47E009.hgt'}"]
[[agents]]
name = "a1"
kind = "static"
type = "radar"
coalition = "blue"
lat_deg = 47.3
lon_deg = 9.3
"""


def sortie(capsys, *args) -> subprocess.CompletedProcess:
    """A ``sortie`` command run in this process (sortie.cli.main): exit status, stdout, stderr."""
    from sortie.cli import main

    capsys.readouterr()
    code = main([str(a) for a in args])
    out = capsys.readouterr()
    return subprocess.CompletedProcess(args, code, out.out, out.err)


# -- 1. a recording the file system refuses ---------------------------------------------------------

@pytest.mark.parametrize("option", ["record", "record_dir"])
def test_a_recording_whose_name_is_too_long_is_an_error_naming_the_option(tmp_path, option):
    from server.sim_cli import check_recording, new_recording

    path = tmp_path / f"{LONG_NAME}.sortie"
    with pytest.raises(InvalidArgument, match=rf"^{option}: cannot be written: File name too long \(got '.*a{{20}}"):
        new_recording(path, _header, 1.0, option)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(InvalidArgument, match=r"^record: cannot be written: File name too long"):
        check_recording(_args(record=str(path)), "small")
    with pytest.raises(InvalidArgument, match=r"^record_dir: cannot be written: File name too long"):
        check_recording(_args(record_dir=str(tmp_path / LONG_NAME / "deeper")), "small")


def test_sortie_server_says_which_option_names_a_recording_it_cannot_make(tmp_path, capsys):
    scenario = tmp_path / "s.toml"
    scenario.write_text(SCENARIO)
    for option, value in (("--record", tmp_path / f"{LONG_NAME}.sortie"), ("--record-dir", tmp_path / LONG_NAME)):
        out = sortie(capsys, "server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", option, value)
        assert out.returncode == 2, out.stderr
        assert f"{option[2:].replace('-', '_')}: cannot be written: File name too long" in out.stderr, out.stderr
        assert "Errno" not in out.stderr, out.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s.toml"]


@pytest.fixture
def read_only_folder(tmp_path):
    """A folder on a read-only tmpfs (skipped where this process may not mount one)."""
    folder = tmp_path / f"ro-{uuid.uuid4().hex[:8]}"
    folder.mkdir()
    mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k,ro", "tmpfs", str(folder)],
                             capture_output=True, timeout=10)
    if mounted.returncode != 0:
        pytest.skip(f"cannot mount a read-only tmpfs here: {mounted.stderr.decode(errors='replace').strip()}")
    try:
        yield folder
    finally:
        subprocess.run(["umount", str(folder)], capture_output=True, timeout=10)


def test_a_recording_on_a_read_only_file_system_is_an_error_naming_the_option(read_only_folder, tmp_path, capsys):
    from server.sim_cli import new_recording

    with pytest.raises(InvalidArgument, match=r"^record_dir: cannot be written: Read-only file system"):
        new_recording(read_only_folder / "x.sortie", _header, 1.0, "record_dir")
    scenario = tmp_path / "s.toml"
    scenario.write_text(SCENARIO)
    out = sortie(capsys, "server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0",
                 "--record-dir", read_only_folder)
    assert out.returncode == 2 and "record_dir: cannot be written: Read-only file system" in out.stderr, out.stderr


# -- 2. a re-simulation on a terrain the recorded scenario cannot start on ---------------------------

BOULDER_SCENARIO = """[exercise]
name = "Flatirons"
start_time = 2026-03-10T16:00:00Z
clock = "fast"
duration_s = 0.5
[terrain]
dem = ["{dem}"]
[[agents]]
name = "cessna"
kind = "aircraft"
type = "c172x"
coalition = "blue"
lat_deg = 40.05
lon_deg = -105.30
alt_m = 600.0
alt_ref = "agl"
speed_mps = 50.0
controllable = true
[[agents]]
name = "mesa-radar"
kind = "static"
type = "radar"
coalition = "red"
lat_deg = 39.99
lon_deg = -105.28
[[target_areas]]
name = "east-edge"
polygon = [[40.00, -105.29], [40.00, -105.25], [40.02, -105.25], [40.02, -105.29]]
"""


@pytest.fixture(scope="module")
def boulder_recording(tmp_path_factory):
    """A short sortie over Boulder's ESRI ASCII grid (embedded copy), recorded by `sortie server`."""
    from sortie.cli import main

    d = tmp_path_factory.mktemp("boulder")
    scenario = d / "boulder.toml"
    scenario.write_text(BOULDER_SCENARIO.format(dem=EMBEDDED_DEM / "landlab_SRTMGL3_BoulderCO_553x553.asc"))
    path = d / "boulder.sortie"
    assert main(["server", "--scenario", str(scenario), "--port", "0", "--aircraft-workers", "0",
                 "--record", str(path)]) == 0
    return path


def test_resim_on_a_wrong_dem_names_the_option_and_the_recorded_terrain(boulder_recording, capsys):
    """Before: 'agents[0]: 'cessna' is placed at an altitude above ground outside the terrain ...;
    move it onto the terrain or give alt_m above mean sea level': a scenario the user cannot
    change, and no word of the --dem they gave."""
    from server.resim import resimulate, take_over

    alps = EMBEDDED_DEM / "N47E009.hgt"
    with pytest.raises(InvalidArgument, match=r"^--dem: the recorded scenario cannot start on this terrain "
                                              r"\(recorded: dem:.*landlab_SRTMGL3_BoulderCO_553x553\.asc\): "
                                              r"agents\[0\]: 'cessna' .* \(got \[.*N47E009\.hgt'\]\)$"):
        resimulate(boulder_recording, dem=[alps])
    with pytest.raises(InvalidArgument, match=r"^--dem: the recorded scenario cannot start on this terrain"):
        take_over(boulder_recording, 0.2, "cessna", dem=[alps])
    out = sortie(capsys, "resim", boulder_recording, "--dem", alps)
    assert out.returncode == 2 and "--dem: the recorded scenario cannot start on this terrain" in out.stderr, out.stderr
    # The recorded terrain (the default) still re-simulates bit-exact.
    assert resimulate(boulder_recording).bit_exact


# -- 3. a target area reaching past the DEM's edge in the glTF scene -------------------------------

def test_gltf_outline_of_an_area_past_the_dems_edge_stays_at_the_grounds_level(boulder_recording, tmp_path):
    """The area 'east-edge' reaches 1.7 km past the east edge of Boulder's grid (-105.27), where
    the ground is at about 1,620 m. Before, the outline's points past the edge were drawn at
    MSL 0 + 5 m: a wall of yellow lines 1,600 m down from the terrain. Now they run on at the
    level of the nearest points on the terrain (within the heights the outline has on it), and
    the points on the terrain keep the terrain's height plus the 5 m lift (within 1 cm)."""
    import trimesh

    from server.gltf import TARGET_AREA_LIFT_M, export_gltf
    from server.recording import Recording
    from terrain.dem import read_dem
    from terrain.geodesy import ecef_to_geodetic
    from terrain.mesh import LocalFrame, gltf_to_enu, read_glb
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(EMBEDDED_DEM / "landlab_SRTMGL3_BoulderCO_553x553.asc")])
    out = tmp_path / "edge.glb"
    with Recording(boulder_recording) as r:
        stats = export_gltf(r, out, terrain, size="64x64")
        undulation = r.header.geoid_undulation_m
    assert stats.target_areas == 1
    f = read_glb(out.read_bytes())[0]["scenes"][0]["extras"]["sortie"]["frame"]
    frame = LocalFrame.at(f["lat_deg"], f["lon_deg"], f["h_m"])
    outline = np.asarray(trimesh.load(out, force="scene").geometry["target area east-edge"].vertices)
    lat, lon, h = ecef_to_geodetic(frame.to_ecef(gltf_to_enu(outline)))
    ground = np.asarray(terrain.heights(lat, lon).height_msl_m)
    on = np.isfinite(ground)
    assert on.any() and (~on).sum() > 10  # the area is partly off the grid
    lifted = ground[on] + TARGET_AREA_LIFT_M + undulation
    assert np.abs(h[on] - lifted).max() < 0.01
    assert lifted.min() - 0.01 <= h[~on].min() and h[~on].max() <= lifted.max() + 0.01, (h[~on].min(), lifted.min())


def test_outline_ground_fills_the_points_off_the_terrain_round_the_ring():
    from server.gltf import outline_ground

    nan = np.nan
    # The last point is the first (a closed outline): the gap wraps round it.
    assert np.allclose(outline_ground(np.array([nan, 2.0, 3.0, nan, nan, nan])), [2.25, 2, 3, 2.75, 2.5, 2.25])
    assert np.allclose(outline_ground(np.array([1.0, 2.0, nan, nan, 5.0, 1.0])), [1, 2, 3, 4, 5, 1])
    assert np.array_equal(outline_ground(np.array([nan, nan, nan])), [0.0, 0.0, 0.0])  # no terrain: MSL 0
