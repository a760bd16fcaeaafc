"""Operational fixes found by acceptance probing (docs/DEPLOYMENT.md, sortie/config.py):

1. a `sortie server` that fails to start leaves no recording behind, and closes what it opened;
2. options of a required group of alternatives (--cell | --bbox) come from the environment or a
   config file like any other, the precedence and the exclusion kept;
3. an option abbreviated on the command line (--de for --dem) still wins over the environment;
4. an error is blamed on an environment variable only when it is about that option;
5. JSON logging writes nothing but JSON lines (status lines, the error line, gRPC's own log);
6. --grace-s is range-checked;
7. `sortie health` exits 1 for every failure (Docker reserves 2) and checks its address's port.
"""

from __future__ import annotations

import json
import os
import socket
import subprocess

import pytest

from server.process import free_port, sortie_command
from sortie import config
from sortie.cli import build_parser, main
from test_operations import parse
from sortie.errors import InvalidArgument, SortieError

DEM = "data/dem/N47E009.hgt"




def scenario(tmp_path, terrain: bool = True):
    """A small scenario: one static agent (no flight model to load)."""
    path = tmp_path / "sc.toml"
    text = ('[exercise]\nname = "Probe Fixes"\nstart_time = 2026-06-15T07:00:00Z\nworld_rate_hz = 30\n'
            'clock = "realtime"\n\n[[agents]]\nname = "sam1"\nkind = "static"\ntype = "sam_site"\n'
            'coalition = "red"\nlat_deg = 47.35\nlon_deg = 9.45\n')
    if terrain:
        text += f'\n[terrain]\ndem = ["{os.path.abspath(DEM)}"]\ngeoid_undulation_m = 48.0\n'
    path.write_text(text)
    return str(path)


def run_sortie(*argv, env=None, timeout=120):
    return subprocess.run([*sortie_command(), *argv], capture_output=True, text=True, timeout=timeout,
                          env=None if env is None else {**os.environ, **env})


@pytest.fixture()
def taken_port():
    """A port something listens on."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


# --- 1. a server that fails to start leaves no recording -----------------------------------------

def test_a_server_that_cannot_bind_leaves_no_recording(tmp_path, taken_port):
    sc, rec = scenario(tmp_path), tmp_path / "rec"
    r = run_sortie("server", "--scenario", sc, "--port", str(taken_port), "--record-dir", str(rec),
                   "--aircraft-workers", "0")
    assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{taken_port}: Address already in use" in r.stderr, \
        r.stderr
    assert not rec.exists() or not list(rec.iterdir()), list(rec.iterdir())
    rec.mkdir()  # the metrics port taken, into a folder that was there: the folder stays, empty
    r = run_sortie("server", "--scenario", sc, "--port", "0", "--metrics-port", str(taken_port),
                   "--record-dir", str(rec), "--aircraft-workers", "0")
    assert r.returncode == 2 and f"cannot serve metrics on 127.0.0.1:{taken_port}" in r.stderr, r.stderr
    assert rec.is_dir() and not list(rec.iterdir()), list(rec.iterdir())


@pytest.mark.parametrize("option, value, message", [("--duration", "-1", "duration: must be within"),
                                                    ("--time-scale", "0", "time_scale: must be within")])
def test_bad_clock_options_are_refused_before_anything_is_recorded(tmp_path, option, value, message):
    rec = tmp_path / "rec"
    r = run_sortie("server", "--scenario", scenario(tmp_path), "--port", "0", "--record-dir", str(rec),
                   "--aircraft-workers", "0", f"{option}={value}")
    assert r.returncode == 2 and message in r.stderr, r.stderr
    assert not rec.exists() or not list(rec.iterdir()), list(rec.iterdir())


def test_a_start_that_fails_after_the_recording_is_made_removes_it_and_closes_the_world(tmp_path, monkeypatch,
                                                                                         capsys):
    """The last step of the start (the gRPC server's start) fails: the recording made just before
    is removed with the folder made for it, the world is closed, exit 2."""
    import server.sim_server as sim_server

    closed = []
    build_world = sim_server.build_world

    def spied_build_world(*a, **kw):
        world = build_world(*a, **kw)
        close = world.close
        world.close = lambda: (closed.append("world"), close())
        return world

    def failing_start(self):
        assert self.recorder is not None and self.recorder.path.exists()  # made before the start
        raise SortieError("the start failed")

    monkeypatch.setattr(sim_server, "build_world", spied_build_world)
    monkeypatch.setattr(sim_server.SimulationServer, "start", failing_start)
    port = free_port()
    rec = tmp_path / "a" / "rec"
    assert main(["server", "--scenario", scenario(tmp_path), "--port", str(port), "--record-dir", str(rec),
                 "--aircraft-workers", "0"]) == 2
    assert "the start failed" in capsys.readouterr().err
    assert not (tmp_path / "a").exists()
    assert closed == ["world"]  # (a gRPC server never started keeps its port until the process exits)


# --- 2. required groups of alternatives from the environment or a file ---------------------------

def _value_for(action) -> str:
    """A value the option parses (for the generic test below)."""
    if action.choices:
        return str(list(action.choices)[0])
    if isinstance(action.nargs, int):
        return " ".join(["1"] * action.nargs)
    return "1" if action.type in (int, float) else "x"


def _required_groups():
    parser = build_parser()
    return [(path, [a.dest for a in g._group_actions])  # noqa: SLF001
            for path, sub in config.command_parsers(parser) for g in sub._mutually_exclusive_groups  # noqa: SLF001
            if g.required]


def test_the_commands_have_required_groups():
    assert {path for path, _ in _required_groups()} >= {("terrain", "texture"), ("terrain", "mesh"), ("render",),
                                                        ("view",)}


@pytest.mark.parametrize("path, dests", _required_groups(), ids=lambda v: " ".join(v) if isinstance(v, tuple) else None)
def test_every_member_of_every_required_group_can_come_from_the_environment(path, dests):
    """The command path alone on the command line: each member of the group from its variable
    (and the command's other required options from theirs) satisfies the group."""
    parser = build_parser()
    sub = dict(config.command_parsers(parser))[path]
    actions = {a.dest: a for a in sub._actions}  # noqa: SLF001
    required = {a.dest: _value_for(a) for a in sub._actions if a.required and a.option_strings}  # noqa: SLF001
    for dest in dests:
        environ = {config.env_name(path, d): v for d, v in {**required, dest: _value_for(actions[dest])}.items()}
        args = parse(list(path), environ)
        assert getattr(args, dest) not in (None, []), (path, dest)
        assert all(getattr(args, other) in (None, []) for other in dests if other != dest)


BOX = "47.1 9.1 47.12 9.12"


def test_a_required_group_from_the_environment_or_a_file_keeps_the_precedence(tmp_path):
    argv = ["terrain", "texture", "--dem", DEM, "--time", "2026-06-21T12:00:00Z", "-o", "out"]
    env = {"SORTIE_TERRAIN_TEXTURE_BBOX": BOX}
    args = parse(argv, env)
    assert (args.bbox, args.cell) == ([47.1, 9.1, 47.12, 9.12], None)
    args = parse([*argv, "--cell", "5"], env)  # the command line wins
    assert (args.bbox, args.cell) == (None, 5)
    args = parse([*argv, "--ce=5"], env)  # abbreviated too
    assert (args.bbox, args.cell) == (None, 5)
    args = parse(argv, env, "[terrain.texture]\ncell = 7\n", tmp_path)  # the environment over the file
    assert (args.bbox, args.cell) == ([47.1, 9.1, 47.12, 9.12], None)
    args = parse(argv, {}, "[terrain.texture]\ncell = 7\n", tmp_path)
    assert (args.bbox, args.cell) == (None, 7)
    args = parse(["view", "--server", "h:1", "--frames", "1", "--fps", "1", "--out", "d"], {},
                 '[view]\nfollow = "viper1"\n', tmp_path)
    assert (args.follow, args.agent_type) == ("viper1", None)
    args = parse(["render", "--camera", "47.5,9.5,3000,0,-10", "--out", "r.png"], {"SORTIE_RENDER_DEM": DEM})
    assert (args.dem, args.terrain, args.store) == ([DEM], None, None)


def test_two_members_of_a_required_group_from_one_source_are_an_error_naming_both(tmp_path):
    argv = ["terrain", "texture", "--dem", DEM, "--time", "2026-06-21T12:00:00Z", "-o", "out"]
    with pytest.raises(InvalidArgument, match="--cell \\(set by SORTIE_TERRAIN_TEXTURE_CELL\\): not allowed with "
                                              "--bbox \\(set by SORTIE_TERRAIN_TEXTURE_BBOX\\)"):
        parse(argv, {"SORTIE_TERRAIN_TEXTURE_BBOX": BOX, "SORTIE_TERRAIN_TEXTURE_CELL": "5"})
    with pytest.raises(InvalidArgument, match=r"--cell \(set by \S+sortie.toml: terrain.texture.cell\): not allowed "
                                              r"with --bbox \(set by \S+sortie.toml: terrain.texture.bbox\)"):
        parse(argv, {}, "[terrain.texture]\ncell = 5\nbbox = [47.1, 9.1, 47.12, 9.12]\n", tmp_path)
    with pytest.raises(SystemExit):  # none anywhere: argparse's own error, as before
        parse(argv, {})
    with pytest.raises(SystemExit):  # both on the command line: argparse's own error, as before
        parse([*argv, "--cell", "5", "--bbox", *BOX.split()], {})


def test_a_required_group_from_the_environment_runs_the_command(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("SORTIE_TERRAIN_TEXTURE_BBOX", BOX)
    out = tmp_path / "tx"
    assert main(["terrain", "texture", "--dem", DEM, "--size", "8x8", "--time", "2026-06-21T12:00:00Z",
                 "-o", str(out)]) == 0, capsys.readouterr().err
    assert any(out.iterdir())
    monkeypatch.setenv("SORTIE_TERRAIN_TEXTURE_CELL", "5")
    assert main(["terrain", "texture", "--dem", DEM, "--size", "8x8", "--time", "2026-06-21T12:00:00Z",
                 "-o", str(tmp_path / "tx2")]) == 2
    err = capsys.readouterr().err
    assert "configuration error" in err and "SORTIE_TERRAIN_TEXTURE_CELL" in err
    assert "SORTIE_TERRAIN_TEXTURE_BBOX" in err


# --- 3. abbreviations ----------------------------------------------------------------------------

@pytest.mark.parametrize("dem", [["--de", "a.hgt"], ["--de=a.hgt"], ["--dem", "a.hgt"]])
def test_an_abbreviated_option_wins_over_the_environment(dem):
    """argparse takes --de for --dem (allow_abbrev, kept): the command line's alternative wins."""
    argv = ["server", "--scenario", "s.toml", "--port", "0", *dem]
    args = parse(argv, {"SORTIE_SERVER_TERRAIN": "127.0.0.1:1"})
    assert (args.dem, args.terrain) == (["a.hgt"], None)
    args = parse(["server", "--scenario", "s.toml", "--po", "7"], {"SORTIE_SERVER_PORT": "5"})
    assert args.port == 7


def test_an_abbreviated_option_is_not_blamed_on_the_environment():
    parser = build_parser()
    argv = ["server", "--scenario", "s.toml", "--port", "0", "--dur", "-7"]
    config.apply(parser, None, {"SORTIE_SERVER_DURATION": "5"})
    config.settle_exclusive(parser, parser.parse_args(argv), argv)
    assert config.source_of(parser, argv, "duration") is None
    argv = ["server", "--scenario", "s.toml", "--port", "0"]
    assert config.source_of(parser, argv, "duration") == "SORTIE_SERVER_DURATION"


# --- 4. an error is blamed on a variable only when it is about that option -------------------------

@pytest.mark.parametrize("dem", [True, False])
def test_a_scenario_error_is_not_blamed_on_the_environment(tmp_path, monkeypatch, capsys, dem):
    monkeypatch.setenv("SORTIE_SERVER_TERRAIN", "x:1")
    argv = ["server", "--scenario", scenario(tmp_path, terrain=False), "--port", "0", "--no-record"]
    assert main(argv + (["--dem", DEM] if dem else [])) == 2
    err = capsys.readouterr().err
    assert "sc.toml: terrain: is required" in err and "set by" not in err, err


def test_an_error_about_another_value_of_the_same_name_is_not_blamed_on_the_option():
    parser = build_parser()
    argv = ["server", "--scenario", "s.toml", "--port", "0"]
    config.apply(parser, None, {"SORTIE_SERVER_DURATION": "5", "SORTIE_SERVER_RECORD": "./r.sortie"})
    config.settle_exclusive(parser, parser.parse_args(argv), argv)
    assert config.source_of(parser, argv, "duration", 5.0) == "SORTIE_SERVER_DURATION"
    assert config.source_of(parser, argv, "duration", 7.0) is None
    assert config.source_of(parser, argv, "record", "r.sortie") == "SORTIE_SERVER_RECORD"


# --- 5. JSON logging is JSON lines only ------------------------------------------------------------

def _all_json(text: str) -> list[dict]:
    lines = text.splitlines()
    assert lines and all(line.startswith("{") for line in lines), text
    return [json.loads(line) for line in lines]


def test_json_logging_start_up_errors_are_one_json_line(tmp_path, taken_port):
    env = {"SORTIE_LOG_FORMAT": "json"}
    r = run_sortie("terrain", "serve", "--dem", DEM, "--port", str(taken_port), env=env)
    (record,) = _all_json(r.stderr)
    assert r.returncode == 2 and r.stdout == ""
    assert record["level"] == "ERROR" and record["message"] == \
        f"sortie terrain: error: cannot listen on 127.0.0.1:{taken_port}: Address already in use"
    r = run_sortie("server", "--scenario", scenario(tmp_path), "--port", str(taken_port), "--no-record",
                   "--aircraft-workers", "0", env=env)
    (record,) = _all_json(r.stderr)
    assert r.returncode == 2 and "cannot listen" in record["message"] and "Address already in use" in \
        record["message"]
    r = run_sortie("--log-format", "json", "terrain", "serve", "--port", "x")
    (record,) = _all_json(r.stderr)
    assert r.returncode == 2 and "argument --port" in record["message"]
    r = run_sortie("terrain", "serve", "--port", "0", env={**env, "SORTIE_TERRAIN_SERVE_GRACE_S": "x"})
    (record,) = _all_json(r.stderr)
    assert r.returncode == 2 and record["message"].startswith("sortie: configuration error: "
                                                              "SORTIE_TERRAIN_SERVE_GRACE_S")


def test_json_logging_status_lines_are_json_records(tmp_path):
    from server.process import wait_serving

    port = free_port()
    proc = subprocess.Popen([*sortie_command(), "--log-format", "json", "terrain", "serve", "--procedural", "1",
                             "--port", str(port), "--metrics-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        wait_serving(f"127.0.0.1:{port}", proc, timeout_s=60.0)
        proc.terminate()
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    messages = [r["message"] for r in _all_json(out)]
    assert messages[0] == f"sortie terrain service listening on 127.0.0.1:{port}"
    assert messages[1].startswith("metrics on http://") and messages[-1] == "sortie terrain service stopped"
    assert err == "" or _all_json(err)


def test_the_text_error_lines_are_unchanged(capsys):
    assert main(["terrain", "serve", "--port", "0"]) == 2
    assert capsys.readouterr().err == ("sortie terrain: error: --dem: give at least one DEM file, --store PATH "
                                       "or --procedural SEED\n")


# --- 6. --grace-s ---------------------------------------------------------------------------------

SERVE = {"server": ["server", "--scenario", "s.toml", "--port", "0"],
         "terrain serve": ["terrain", "serve", "--procedural", "1", "--port", "0"]}


@pytest.mark.parametrize("command", SERVE)
@pytest.mark.parametrize("value", ["inf", "nan", "-1", "600.5", "x"])
def test_grace_s_out_of_range_is_refused(command, value, capsys):
    with pytest.raises(SystemExit) as info:
        parse([*SERVE[command], f"--grace-s={value}"])
    assert info.value.code == 2
    assert "argument --grace-s: must be" in capsys.readouterr().err
    name = config.env_name(tuple(command.split()), "grace_s")
    with pytest.raises(InvalidArgument, match=name + ": must be"):
        parse(SERVE[command], {name: value})


@pytest.mark.parametrize("command", SERVE)
def test_grace_s_in_range_is_taken(command, tmp_path):
    assert parse([*SERVE[command], "--grace-s", "0"]).grace_s == 0.0
    assert parse([*SERVE[command], "--grace-s", "600"]).grace_s == 600.0
    assert parse(SERVE[command]).grace_s == 5.0
    table = "[terrain.serve]" if command == "terrain serve" else "[server]"
    assert parse(SERVE[command], {}, f"{table}\ngrace-s = 10\n", tmp_path).grace_s == 10.0


# --- 7. sortie health ----------------------------------------------------------------------------

@pytest.mark.parametrize("argv, environ, message", [
    (["127.0.0.1:99999"], {}, "address: must be HOST:PORT with a port 1..65535 (got '127.0.0.1:99999')"),
    (["127.0.0.1:0"], {}, "port 1..65535"),
    (["[::1]:65536"], {}, "port 1..65535"),
    (["127.0.0.1"], {}, "port 1..65535"),
    (["127.0.0.1:1", "--timeout-s", "-1"], {}, "timeout_s: must be a finite number > 0"),
    (["127.0.0.1:1", "--timeout-s", "nan"], {}, "timeout_s: must be a finite number > 0"),
    (["127.0.0.1:1"], {"SORTIE_LOG_FORMAT": "xml"}, "SORTIE_LOG_FORMAT: must be one of text, json"),
    (["127.0.0.1:1"], {"SORTIE_HEALTH_TIMEOUT_S": "soon"}, "SORTIE_HEALTH_TIMEOUT_S: must be a number"),
])
def test_health_exits_1_for_every_failure(argv, environ, message, monkeypatch, capsys):
    for name, value in environ.items():
        monkeypatch.setenv(name, value)
    assert main(["health", *argv]) == 1
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["127.0.0.1:1", "--timeout-s", "x"], ["127.0.0.1:1", "--bogus"], []])
def test_health_exits_1_for_a_bad_command_line(argv, capsys):
    with pytest.raises(SystemExit) as info:
        main(["health", *argv])
    assert info.value.code == 1 and ": error: " in capsys.readouterr().err


def test_health_takes_a_good_address(capsys):
    port = free_port()  # nothing listens there: UNAVAILABLE, exit 1 as before
    assert main(["health", f"127.0.0.1:{port}", "--timeout-s", "0.5"]) == 1
    assert f"127.0.0.1:{port} (server): UNAVAILABLE" in capsys.readouterr().out
    assert main(["health", f"[::1]:{port}", "--timeout-s", "0.5"]) == 1
    assert "UNAVAILABLE" in capsys.readouterr().out
