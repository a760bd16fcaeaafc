"""Command-line fixes found by acceptance probing, on real ``sortie`` runs (sortie.cli.main):

1. ``sortie render`` / ``sortie view``: a bad --fov-deg, --camera field, --size or
   --geoid-undulation-m is an error naming the option as typed (and the --camera field), exit 2,
   before anything is rendered, not the renderer's parameter (fov_x_deg, pitch_deg, lat_deg,
   lon[0], width, geoid_undulation_m); the CLI's geoid bound is the renderer's;
2. two alternatives of one group of exclusive options (required or not: --dem | --terrain,
   --record | --no-record) from the same environment or config file are an error naming both and
   where each came from, as the command line's usage error; a higher layer still overrides.
"""

from __future__ import annotations

import pytest

from sortie.cli import main
from sortie.errors import InvalidArgument
from test_operations import parse

DEM = "data/dem/N47E009.hgt"
POSE = "47.2,9.3,3000,0,0"


# --- 1. render / view option errors name the option ----------------------------------------------

def _render(tmp_path, *extra, camera=POSE):
    return main(["render", "--dem", DEM, "--camera", camera, "--out", str(tmp_path / "x.png"), "--size", "64x48",
                 *extra])


@pytest.mark.parametrize("extra, camera, expected", [
    (["--fov-deg", "0"], POSE, "--fov-deg: must be within [1, 170] degrees (got 0.0)"),
    (["--fov-deg", "nan"], POSE, "--fov-deg: must be within [1, 170] degrees (got nan)"),
    (["--fov-deg", "171"], POSE, "--fov-deg: must be within [1, 170] degrees"),
    ([], "47.2,9.3,3000,0,-100", "--camera: PITCH_DEG -100 must be within [-90, 90] degrees"),
    ([], "91,9.3,3000,0,0", "--camera: LAT 91 must be within [-90, 90] degrees"),
    ([], "47.2,1e20,3000,0,0", "--camera: LON 1e+20 must be within [-540, 540] degrees"),
    (["--size", "100000x10"], POSE, "--size: width and height must be in [1, 8192] pixels (got '100000x10')"),
    (["--size", "10x8193"], POSE, "--size: width and height must be in [1, 8192] pixels"),
    (["--geoid-undulation-m", "150"], POSE, "--geoid-undulation-m: must be finite and within [-120, 120] m"),
    (["--geoid-undulation-m", "-120.5"], POSE, "--geoid-undulation-m: must be finite and within [-120, 120] m"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_render_option_errors_name_the_option(tmp_path, capsys, extra, camera, expected):
    assert _render(tmp_path, *extra, camera=camera) == 2
    err = capsys.readouterr().err
    assert f"sortie render: error: {expected}" in err, err
    for internal in ("fov_x_deg", "pitch_deg", "lat_deg", "lon[0]", "width:", "geoid_undulation_m"):
        assert internal not in err, err
    assert "Traceback" not in err and not (tmp_path / "x.png").exists()


def test_the_render_clis_geoid_bound_is_the_renderers(tmp_path, capsys):
    """The bound is the renderer's (server.scenario.GEOID_UNDULATION_ABS_MAX_M, which a scenario
    also takes): its edge renders, just past it is refused by the CLI, naming the option."""
    import argparse

    from client.render_cli import add_parser, check_render_options
    from server.scenario import GEOID_UNDULATION_ABS_MAX_M

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    base = ["render", "--dem", DEM, "--camera", POSE, "--out", "x.png"]
    check_render_options(parser.parse_args([*base, "--geoid-undulation-m", str(GEOID_UNDULATION_ABS_MAX_M)]))
    assert _render(tmp_path, "--geoid-undulation-m", str(-GEOID_UNDULATION_ABS_MAX_M)) == 0, capsys.readouterr().err
    assert (tmp_path / "x.png").exists()
    assert _render(tmp_path, "--geoid-undulation-m", str(GEOID_UNDULATION_ABS_MAX_M + 0.5)) == 2
    assert "--geoid-undulation-m:" in capsys.readouterr().err


@pytest.mark.parametrize("extra, expected", [
    (["--fov-deg", "nan"], "--fov-deg: must be within [1, 170] degrees"),
    (["--size", "100000x10"], "--size: width and height must be in [1, 8192] pixels"),
    (["--geoid-undulation-m", "150"], "--geoid-undulation-m: must be finite and within [-120, 120] m"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_view_option_errors_name_the_option_before_joining(tmp_path, capsys, extra, expected):
    """Checked before joining a server (none listens at the address)."""
    argv = ["view", "--server", "127.0.0.1:1", "--follow", "viper1", "--frames", "1", "--fps", "1",
            "--out", str(tmp_path / "v"), *extra]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert f"sortie view: error: {expected}" in err, err
    assert "no simulation server" not in err and not (tmp_path / "v").exists()


# --- 2. two alternatives of one group from one source --------------------------------------------

SERVER = ["server", "--scenario", "data/scenarios/alps.toml", "--port", "0", "--aircraft-workers", "0",
          "--duration", "1", "--clock", "fast"]


def test_dem_and_terrain_from_the_environment_are_an_error_naming_both(monkeypatch, capsys, tmp_path):
    monkeypatch.setenv("SORTIE_SERVER_DEM", DEM)
    monkeypatch.setenv("SORTIE_SERVER_TERRAIN", "127.0.0.1:1")
    assert main([*SERVER, "--no-record"]) == 2
    err = capsys.readouterr().err
    assert ("--dem (set by SORTIE_SERVER_DEM): not allowed with --terrain (set by SORTIE_SERVER_TERRAIN)"
            in err), err
    assert "UNAVAILABLE" not in err and "Traceback" not in err
    # one from a higher layer still overrides one from a lower: command line > environment > file
    base = ["server", "--scenario", "s.toml", "--port", "0"]
    args = parse([*base, "--dem", "a.hgt"], {"SORTIE_SERVER_TERRAIN": "127.0.0.1:1"})
    assert (args.dem, args.terrain) == (["a.hgt"], None)
    args = parse(base, {"SORTIE_SERVER_DEM": "a.hgt"}, '[server]\nterrain = "127.0.0.1:1"\n', tmp_path)
    assert (args.dem, args.terrain) == (["a.hgt"], None)


def test_record_and_no_record_in_one_config_table_are_an_error_naming_both(tmp_path, capsys):
    conf = tmp_path / "both.toml"
    conf.write_text(f'[server]\nrecord = "{tmp_path / "r.sortie"}"\nno-record = true\n')
    assert main(["--config", str(conf), *SERVER, "--dem", DEM]) == 2
    err = capsys.readouterr().err
    assert (f"--record (set by {conf}: server.record): not allowed with --no-record "
            f"(set by {conf}: server.no-record)" in err), err
    assert not (tmp_path / "r.sortie").exists()
    # the same pair from the environment too; a flag set to its default (NO_RECORD=0) is no
    # alternative; a higher layer overrides a lower one's
    base = ["server", "--scenario", "s.toml", "--port", "0"]
    with pytest.raises(InvalidArgument, match=r"--record \(set by SORTIE_SERVER_RECORD\): not allowed with "
                                              r"--no-record \(set by SORTIE_SERVER_NO_RECORD\)"):
        parse(base, {"SORTIE_SERVER_NO_RECORD": "1", "SORTIE_SERVER_RECORD": "r.sortie"})
    args = parse(base, {"SORTIE_SERVER_NO_RECORD": "0", "SORTIE_SERVER_RECORD": "r.sortie"})
    assert (args.no_record, args.record) == (False, "r.sortie")
    args = parse(base, {"SORTIE_SERVER_NO_RECORD": "1"}, '[server]\nrecord = "r.sortie"\n', tmp_path)
    assert (args.no_record, args.record) == (True, None)
    args = parse([*base, "--record", "r.sortie"], {"SORTIE_SERVER_NO_RECORD": "1", "SORTIE_SERVER_RECORD_DIR": "d"})
    assert (args.no_record, args.record, args.record_dir) == (False, "r.sortie", "recordings")
