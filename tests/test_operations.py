"""Operations: configuration from a file and the environment, JSON logs, metrics,
clear start-up errors and clean SIGTERM — on real processes and real sockets."""

import json
import re
import subprocess
import time
import urllib.request

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from server.process import ServiceProcess, free_port, sortie_command
from sortie import config
from sortie.cli import build_parser
from sortie.errors import InvalidArgument

SCENARIO = "data/scenarios/alps.toml"


def parse(argv, environ=None, config_text=None, tmp_path=None):
    parser = build_parser()
    path = None
    if config_text is not None:
        path = tmp_path / "sortie.toml"
        path.write_text(config_text)
    config.apply(parser, str(path) if path else None, environ or {})
    args = parser.parse_args(argv)
    config.settle_exclusive(parser, args, argv)
    return args


def test_the_command_line_wins_within_a_group_of_alternatives_too(tmp_path):
    """--dem on the command line over a terrain service from the environment, --record over
    no-record from the config file; the environment's choice stands where the command
    line names none of the group."""
    env = {"SORTIE_SERVER_TERRAIN": "127.0.0.1:1"}
    args = parse(["server", "--scenario", "s", "--port", "0", "--dem", "a.hgt", "--record", "r.sortie"], env,
                 "[server]\nno-record = true\n", tmp_path)
    assert (args.terrain, args.dem, args.no_record, args.record) == (None, ["a.hgt"], False, "r.sortie")
    args = parse(["server", "--scenario", "s", "--port", "0"], env, "[server]\nno-record = true\n", tmp_path)
    assert (args.terrain, args.dem, args.no_record) == ("127.0.0.1:1", None, True)


@pytest.mark.parametrize("environ, text", [({"SORTIE_VERBOSE": "2"}, None), ({}, "verbose = 2\n")])
def test_verbose_comes_from_the_environment_or_the_file_as_a_count(tmp_path, environ, text):
    assert parse(["terrain", "info", "--dem", "x.hgt"], environ, text, tmp_path).verbose == 2
    with pytest.raises(InvalidArgument, match="must be a count, 0 or more"):
        parse(["terrain", "info", "--dem", "x.hgt"], {"SORTIE_VERBOSE": "-1"})


def test_options_come_from_the_command_line_then_the_environment_then_the_file(tmp_path):
    text = '[server]\nport = 7000\nclock = "fast"\nno-record = true\n[terrain.serve]\nmax_workers = 3\n'
    args = parse(["server", "--scenario", "s.toml"], {}, text, tmp_path)
    assert (args.port, args.clock, args.no_record) == (7000, "fast", True)
    args = parse(["server", "--scenario", "s.toml"], {"SORTIE_SERVER_PORT": "7001", "SORTIE_SERVER_NO_RECORD": "no"},
                 text, tmp_path)
    assert (args.port, args.no_record) == (7001, False)
    args = parse(["server", "--scenario", "s.toml", "--port", "7002"], {"SORTIE_SERVER_PORT": "7001"}, text, tmp_path)
    assert args.port == 7002
    args = parse(["terrain", "serve"], {"SORTIE_TERRAIN_SERVE_PORT": "5", "SORTIE_TERRAIN_SERVE_DEM": "'a b.hgt' c.hgt"},
                 text, tmp_path)
    assert (args.port, args.max_workers, args.dem) == (5, 3, ["a b.hgt", "c.hgt"])
    assert parse(["terrain", "info"], {"SORTIE_LOG_FORMAT": "json"}).log_format == "json"


@pytest.mark.parametrize("environ, text, message", [
    ({"SORTIE_SERVER_PORT": "x"}, None, "SORTIE_SERVER_PORT: a port is an integer 0 ..= 65535, got 'x'"),
    ({"SORTIE_SERVER_PORT": "70000"}, None, "SORTIE_SERVER_PORT: a port is 0 ..= 65535, got 70000"),
    ({"SORTIE_SERVER_DURATION": "x"}, None, "SORTIE_SERVER_DURATION: must be a number"),
    ({"SORTIE_SERVER_CLOCK": "slow"}, None, "SORTIE_SERVER_CLOCK: must be one of"),
    ({"SORTIE_SERVER_NO_RECORD": "maybe"}, None, "SORTIE_SERVER_NO_RECORD: must be one of"),
    ({}, "[server]\nprot = 1\n", "server.prot: is not an option of sortie server"),
    ({}, "[sever]\nport = 1\n", "sever: is not an option of sortie"),
    ({}, '[server]\nport = "1"\n', None),  # a string is parsed like the command line's
    ({}, "[server]\nport = 1.5\n", "server.port: a port is an integer 0 ..= 65535, got '1.5'"),
    ({}, "[server\n", "cannot be read"),
])
def test_bad_configuration_names_where_it_came_from(tmp_path, environ, text, message):
    if message is None:
        assert parse(["server", "--scenario", "s"], environ, text, tmp_path).port == 1
        return
    with pytest.raises(InvalidArgument, match=re.escape(message)):
        parse(["server", "--scenario", "s"], environ, text, tmp_path)


def run_sortie(*argv, timeout=60):
    return subprocess.run([*sortie_command(), *argv], capture_output=True, text=True, timeout=timeout)


def test_start_up_errors_are_clear_and_exit_non_zero(hgt_alps, tmp_path):
    r = run_sortie("server", "--scenario", SCENARIO, "--port", "0", "--dem", str(tmp_path / "missing.hgt"))
    assert r.returncode == 2 and "missing.hgt does not exist" in r.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[exercise]\nname = 3\n")
    r = run_sortie("server", "--scenario", str(bad), "--port", "0")
    assert r.returncode == 2 and "exercise.name: must be a string" in r.stderr
    r = run_sortie("--config", str(tmp_path / "none.toml"), "server", "--scenario", SCENARIO, "--port", "0")
    assert r.returncode == 2 and "none.toml" in r.stderr
    r = run_sortie("server", "--scenario", SCENARIO, "--port", "0", "--dem", str(hgt_alps), "--no-record",
                   "--aircraft-workers", "1", "--aircraft-worker-nice", "25")
    assert r.returncode == 2 and "aircraft_worker_nice" in r.stderr and "25" in r.stderr
    with ServiceProcess(["terrain", "serve", "--dem", str(hgt_alps)]) as svc:
        # The port is taken: both services refuse to start (no silent SO_REUSEPORT sharing).
        r = run_sortie("terrain", "serve", "--dem", str(hgt_alps), "--port", str(svc.port))
        assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{svc.port}" in r.stderr
        r = run_sortie("server", "--scenario", SCENARIO, "--dem", str(hgt_alps), "--port", str(svc.port),
                       "--no-record", "--aircraft-workers", "0")
        assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{svc.port}" in r.stderr
        rec = tmp_path / "short.sortie"
        r = run_sortie("server", "--scenario", SCENARIO, "--dem", str(hgt_alps), "--port", "0", "--record", str(rec),
                       "--aircraft-workers", "0", "--clock", "fast", "--duration", "1", timeout=120)
        assert r.returncode == 0, r.stderr
        r = run_sortie("replay", str(rec), "--port", str(svc.port))
        assert r.returncode == 2 and f"cannot listen on 127.0.0.1:{svc.port}" in r.stderr
        assert "Traceback" not in r.stderr
    # A path that cannot be written: one line naming it, not a traceback.
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    r = run_sortie("server", "--scenario", SCENARIO, "--dem", str(hgt_alps), "--port", "0", "--aircraft-workers", "0",
                   "--record-dir", str(blocker / "recordings"), "--duration", "1")
    assert r.returncode == 2 and "a-file" in r.stderr and "Traceback" not in r.stderr, r.stderr


def test_clients_tell_an_exercise_that_ended_from_a_server_gone(hgt_alps, tmp_path):
    """sortie client stops with the stream: exit 0 and a line when the server ends the
    exercise, exit 1 and a line when the server goes away; no picture extrapolated past it."""
    args = ["server", "--scenario", SCENARIO, "--dem", str(hgt_alps), "--no-record", "--aircraft-workers", "0"]
    # 10 s of exercise: the client's own start-up (imports, connect) must fit in it on a loaded
    # machine (at 4 s a busy host had the server gone before the client connected).
    duration_s = 10.0
    with ServiceProcess([*args, "--duration", f"{duration_s:g}"]) as server:
        t0 = time.monotonic()
        r = run_sortie("client", "--server", server.address, "--duration", "60", "--every", "1", timeout=90)
        assert r.returncode == 0 and "the server ended the exercise at world time" in r.stdout, r.stdout + r.stderr
        assert time.monotonic() - t0 < 30.0 + duration_s
        times = [float(m) for m in re.findall(r"^t = +([\d.]+) s", r.stdout, re.M)]
        assert times and max(times) < duration_s + 1.5
    with ServiceProcess(args) as server:
        client = subprocess.Popen([*sortie_command(), "client", "--server", server.address, "--duration", "60",
                                   "--every", "1"], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        time.sleep(6.0)
        server.proc.kill()
        out, err = client.communicate(timeout=60)
    assert client.returncode == 1 and "the server went away at world time" in err, out + err
    assert "Traceback" not in err


def scrape(url: str) -> dict:
    """{metric line name with labels: value} of a Prometheus text page."""
    with urllib.request.urlopen(url, timeout=10) as r:
        assert r.headers["Content-Type"].startswith("text/plain; version=0.0.4")
        text = r.read().decode()
    out = {}
    for line in text.splitlines():
        if line and not line.startswith("#"):
            name, value = line.rsplit(" ", 1)
            out[name] = float(value)
    return out


def _reap(proc) -> None:
    """Kill the process if it still runs, and wait for it."""
    if proc.poll() is None:
        proc.kill()
    proc.wait()


def wait_for_line(proc, pattern: str, timeout_s: float = 60.0) -> re.Match:
    deadline = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        m = re.search(pattern, line)
        if m:
            return m
    raise AssertionError(f"no line matching {pattern!r} in {seen}")


def test_terrain_service_metrics_json_logs_and_sigterm(hgt_alps):
    port = free_port()
    proc = subprocess.Popen([*sortie_command(), "--log-format", "json", "-v", "terrain", "serve", "--dem",
                             str(hgt_alps), "--port", str(port), "--metrics-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        url = "http://" + wait_for_line(proc, r"metrics on http://(\S+)/metrics")[1] + "/metrics"
        with TerrainClient(f"127.0.0.1:{port}") as tc:
            tc.wait_ready()
            tc.heights(np.array([47.2, 47.3]), np.array([9.3, 9.4]))
            with pytest.raises(InvalidArgument):
                tc.heights(np.array([95.0]), np.array([9.3]))
        m = scrape(url)
        assert m['sortie_terrain_calls_total{method="GetHeights"}'] == 2
        assert m['sortie_terrain_errors_total{method="GetHeights",code="INVALID_ARGUMENT"}'] == 1
        assert m['sortie_terrain_call_seconds_total{method="GetHeights"}'] > 0
        with pytest.raises(urllib.error.HTTPError, match="404"):
            urllib.request.urlopen(url.replace("/metrics", "/other"), timeout=10)
        proc.terminate()
        assert proc.wait(timeout=30) == 0
        records = [json.loads(line) for line in proc.stderr.read().splitlines() if line.startswith("{")]
        assert records and all({"time", "level", "logger", "message"} <= set(r) for r in records)
        assert any(r["logger"] == "server.terrain_service" and "bound" in r["message"] for r in records)
    finally:
        _reap(proc)


def test_simulation_server_metrics_and_sigterm_flushes_the_recording(hgt_alps, tmp_path):
    rec = tmp_path / "ops.sortie"
    port = free_port()
    proc = subprocess.Popen([*sortie_command(), "server", "--scenario", SCENARIO, "--dem", str(hgt_alps),
                             "--port", str(port), "--metrics-port", "0", "--record", str(rec),
                             "--aircraft-workers", "0", "--clock", "fast", "--time-scale", "4"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        url = "http://" + wait_for_line(proc, r"metrics on http://(\S+)/metrics")[1] + "/metrics"
        from client.sim_client import SimClient

        with SimClient(f"127.0.0.1:{port}") as obs:
            obs.wait_ready()
            obs.join("ops", "gateway")
            picture = obs.watch()
            assert picture.wait_for(lambda p: len(p) > 0 and p.updates > 3, 30.0)
            m = scrape(url)
        assert m["sortie_world_ticks_total"] > 0 and m["sortie_world_time_seconds"] > 0
        assert m["sortie_sessions"] == 1
        assert sum(v for k, v in m.items() if k.startswith("sortie_entities{")) == len(picture.infos)
        assert m["sortie_watch_bytes_total"] > 0 and m["sortie_watch_messages_total"] >= 3
        assert m['sortie_tick_duration_milliseconds{quantile="0.99"}'] > 0
        # The publishes, beside the ticks: at least the three updates the picture got.
        assert m["sortie_publish_duration_milliseconds_count"] >= 3
        assert m['sortie_publish_duration_milliseconds{quantile="0.5"}'] > 0
        assert m["sortie_recording_bytes_total"] > 0 and m["sortie_recording_failed"] == 0
        proc.terminate()
        assert proc.wait(timeout=30) == 0
        out = proc.stdout.read()
        assert "stopped at world time" in out and "bytes" in out
    finally:
        _reap(proc)
    r = run_sortie("recording", "check", str(rec))
    assert r.returncode == 0, r.stdout + r.stderr


def test_bots_run_until_sigterm_then_leave_cleanly(hgt_alps):
    with ServiceProcess(["server", "--scenario", SCENARIO, "--dem", str(hgt_alps), "--no-record",
                         "--aircraft-workers", "0"]) as srv:
        from client.sim_client import SimClient

        with SimClient(srv.address) as obs:
            obs.join("ops", "gateway")
            events = obs.events()
            bots = subprocess.Popen([*sortie_command(), "bot", "--server", srv.address, "--count", "2",
                                     "--duration", "0", "--leg-s", "5"],
                                    stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            try:
                kinds = []
                for ev in events:
                    kinds.append(ev.kind)
                    if kinds.count("join") == 2:
                        break
                time.sleep(1.0)
                assert bots.poll() is None, "--duration 0 runs until signalled"
                bots.terminate()
                assert bots.wait(timeout=40) == 0
                out = bots.stdout.read()
                assert out.count("commands accepted") == 2, out
                for ev in events:  # both bots said goodbye (no "vanished" after a timeout)
                    kinds.append(ev.kind)
                    if kinds.count("leave") == 2:
                        break
                assert "vanished" not in kinds
            finally:
                _reap(bots)


def test_health_loads_alone_and_reads_its_own_configuration(tmp_path, capsys):
    import sys

    from sortie.cli import main

    path = tmp_path / "sortie.toml"
    path.write_text("[server]\nport = 1\n[health]\ntimeout-s = 0.5\n")
    port = free_port()  # nothing listens there
    before = set(sys.modules)
    assert main(["--config", str(path), "health", f"127.0.0.1:{port}"]) == 1
    assert "UNAVAILABLE" in capsys.readouterr().out
    assert not {"server.sim_cli", "server.terrain_cli"} & (set(sys.modules) - before)
    path.write_text("[health]\ntimeout_z = 0.5\n")  # its own table is still checked (exit 1: Docker reserves 2)
    assert main(["--config", str(path), "health", f"127.0.0.1:{port}"]) == 1


def test_a_bad_value_checked_after_parsing_names_where_it_came_from(tmp_path):
    """--aircraft-workers is checked by the command, not argparse: from the environment or a
    config file the error says which, as argparse's own checks do; from the command line, not."""
    import os

    env = dict(os.environ, SORTIE_SERVER_AIRCRAFT_WORKERS="many")
    r = subprocess.run([*sortie_command(), "server", "--scenario", SCENARIO, "--port", "0", "--no-record"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 2 and r.stderr.rstrip().endswith("(set by SORTIE_SERVER_AIRCRAFT_WORKERS)"), r.stderr
    conf = tmp_path / "c.toml"
    conf.write_text('[server]\naircraft-workers = "many"\n')
    r = run_sortie("--config", str(conf), "server", "--scenario", SCENARIO, "--port", "0", "--no-record")
    assert r.returncode == 2 and "(set by" in r.stderr and "c.toml: server.aircraft-workers" in r.stderr, r.stderr
    r = run_sortie("server", "--scenario", SCENARIO, "--port", "0", "--no-record", "--aircraft-workers", "many")
    assert r.returncode == 2 and "set by" not in r.stderr
