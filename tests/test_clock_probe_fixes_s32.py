"""The world clock's operator controls and dates (acceptance probe, session 32, "clock"):

1. ``sortie resim --take-over`` of a recording made with clock = "fast", time_scale = 50 said
   "realtime" but ran x50 (a 100 s take-over over in under 6 wall seconds): the take-over runs
   in real time x1 whatever clock the recording ran, or the --clock/--time-scale given.
2. SIGUSR1/SIGUSR2 sent while ``sortie server`` starts killed it (exit 138; its aircraft
   workers orphaned): they are taken from the first step, and the clock starts as they asked.
3. ``sortie resim --take-over`` took no clock signals (SIGUSR2 killed it, exit 140, its
   recording left without a footer): it takes sortie server's, from its first step too.
4. ACMI's ReferenceTime of a start before year 1000 read "800-03-01T..." (strftime's "%Y" is
   not zero-padded by glibc): four digits, as ISO 8601 writes a year.

Real parts: a recording made in process of a real world (one JSBSim-free ground vehicle and a
static site over the embedded DEM, in year 800, fast x50), real ``sortie`` processes and a real
gRPC client. The signals of 2 and 3 are sent by the process itself from inside a start-up step
(the world being built, the take-over being re-simulated): the window the probe hit by timing.
"""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from server.acmi import iso_utc
from server.recording import Recording

REPO = Path(__file__).resolve().parents[1]
DEM = REPO / "data" / "dem" / "N47E009.hgt"
RECORDED_TICKS = 90  # 3 s at 30 Hz
START_S = 30.0  # how long a process may take to say it listens (imports, world, re-simulation)
# A clock at x1 advances at most this many world seconds per wall second as GetWorld sees it
# (two calls' own latency and one tick of 1/30 s in the margin); the probe's take-over ran x50.
REALTIME_RATE_MAX = 1.5


def _scenario(folder: Path, clock: str = "fast", extra: str = "time_scale = 50") -> Path:
    path = folder / f"clock-{clock}.toml"
    path.write_text(textwrap.dedent(f"""\
        [exercise]
        name = "clock probe"
        start_time = "0800-02-29T23:59:30.25-03:30"
        world_rate_hz = 30
        clock = "{clock}"
        {extra}
        duration_s = 3600

        [terrain]
        dem = ["{DEM}"]

        [[agents]]
        name = "patrol1"
        kind = "ground"
        type = "hmmwv"
        coalition = "red"
        lat_deg = 47.38
        lon_deg = 9.64
        heading_deg = 30.0
        [agents.autopilot]
        route = [[47.38, 9.64], [47.40, 9.655]]
        cruise_mps = 15.0

        [[agents]]
        name = "sam1"
        kind = "static"
        type = "sam_site"
        coalition = "red"
        lat_deg = 47.35
        lon_deg = 9.45
        heading_deg = 0.0
        """))
    return path


@pytest.fixture(scope="module")
def recorded(tmp_path_factory) -> Path:
    """A recording of RECORDED_TICKS of the fast x50, year-800 scenario."""
    from server.recorder import Recorder, recording_header
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, terrain_spec

    folder = tmp_path_factory.mktemp("clock")
    scenario_path = _scenario(folder)
    scenario = load_scenario(scenario_path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    path = folder / "fast50.sortie"
    rec = Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    try:
        for _ in range(RECORDED_TICKS):
            world.tick()
    finally:
        rec.close()
        world.close()
    return path


# Runs `sortie ARGS` from this tree (the working directory first on sys.path), sending the
# process SIGNAL from inside the module attribute HOOK ("module.step.SIGNAME", or "-": none) just
# before that start-up step runs (the step looked up when the command calls it).
_SORTIE = textwrap.dedent("""
    import importlib, os, signal, sys
    if sys.argv[1] != "-":
        module, name, sig = sys.argv[1].rsplit(".", 2)
        mod = importlib.import_module(module)
        step = getattr(mod, name)
        def hooked(*args, **kwargs):
            os.kill(os.getpid(), getattr(signal, sig))
            return step(*args, **kwargs)
        setattr(mod, name, hooked)
    from sortie.cli import main
    sys.exit(main(sys.argv[2:]))
""")


def _spawn(args, signal_in: str = "-") -> subprocess.Popen:
    """``sortie ARGS`` as a process (stdout piped, stderr into it); with ``signal_in``
    ("module.step.SIGNAME") the process signals itself as that step starts."""
    return subprocess.Popen([sys.executable, "-c", _SORTIE, signal_in, *map(str, args)], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, cwd=REPO)


def _listening(proc: subprocess.Popen) -> tuple[str, str]:
    """(address, the line) once ``proc`` says where it listens; AssertionError with what it
    wrote (and its exit status) when it ends or takes longer than START_S."""
    deadline, seen = time.monotonic() + START_S, []
    while time.monotonic() < deadline:
        text = proc.stdout.readline()
        if not text:
            break
        seen.append(text)
        m = re.search(r"listening on (\S+)", text)
        if m:
            return m[1], text
    proc.kill()
    proc.wait(10)
    raise AssertionError(f"no listening line (exit {proc.returncode}): {''.join(seen)[-3000:]}")


def _stop(proc: subprocess.Popen) -> tuple[int, str]:
    """SIGTERM, then (exit status, the rest of what it wrote)."""
    proc.send_signal(signal.SIGTERM)
    rest, _ = proc.communicate(timeout=60)
    return proc.returncode, rest


def _rate(address: str, wall_s: float = 1.0):
    """(GetWorld's clock, its time_scale, world seconds per wall second measured over wall_s)."""
    from client.sim_client import SimClient

    with SimClient(address) as sim:
        a, t0 = sim.world(), time.monotonic()
        time.sleep(wall_s)
        b, t1 = sim.world(), time.monotonic()
    return b.clock, b.time_scale, (b.time_s - a.time_s) / (t1 - t0)


# -- 1. a take-over runs in real time x1 unless told otherwise --------------------------------------

def test_a_take_over_of_a_fast_recording_runs_in_real_time(recorded):
    proc = _spawn(["resim", recorded, "--take-over", "1", "--agent", "patrol1", "--duration", "100", "--port", "0",
                   "--no-record"])
    try:
        address, said = _listening(proc)
        clock, scale, rate = _rate(address)
    finally:
        code, rest = _stop(proc)
    assert 0.5 < rate < REALTIME_RATE_MAX, rate  # the probe: 50 world s per wall s
    assert (clock, scale) == ("realtime", 1.0), (clock, scale)  # the probe: realtime, time_scale 50
    assert "(clock realtime x1)" in said, said
    assert code == 0, rest


def test_a_take_over_runs_the_clock_its_options_give(recorded):
    proc = _spawn(["resim", recorded, "--take-over", "1", "--agent", "patrol1", "--duration", "1000", "--port", "0",
                   "--no-record", "--clock", "fast", "--time-scale", "4"])
    try:
        address, said = _listening(proc)
        clock, scale, rate = _rate(address)
    finally:
        code, rest = _stop(proc)
    assert "(clock fast x4)" in said and (clock, scale) == ("fast", 4.0), (said, clock, scale)
    assert 3.0 < rate < 4.0 * REALTIME_RATE_MAX, rate
    assert code == 0, rest


@pytest.mark.parametrize("options, message", [
    (["--take-over", "1", "--agent", "patrol1", "--time-scale", "5"],
     "time_scale: must be 1.0 with the realtime clock (use --clock fast)"),
    (["--take-over", "1", "--agent", "patrol1", "--clock", "fast", "--time-scale", "1"],
     "time_scale: must be within (1, "),
    (["--clock", "fast"], "clock: only with --take-over"),
    (["--time-scale", "4"], "time_scale: only with --take-over"),
])
def test_the_take_over_clock_options_are_checked(recorded, capsys, options, message):
    from sortie.cli import main

    capsys.readouterr()
    code = main(["resim", str(recorded), "--port", "0", "--no-record", *options])
    err = capsys.readouterr().err
    assert code == 2 and message in err and "Traceback" not in err, err


def test_the_take_over_help_says_its_clock(capsys):
    from sortie.cli import main

    with pytest.raises(SystemExit):
        main(["resim", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "--clock {realtime,fast,paused}" in text and "default realtime, x1" in text and "--time-scale X" in text


# -- 2. SIGUSR1/SIGUSR2 while sortie server starts ---------------------------------------------------

@pytest.mark.parametrize("clock, sig, expected", [
    ("paused", "SIGUSR1", "realtime"),  # a paused exercise runs from its start, in real time
    ("realtime", "SIGUSR2", "paused"),  # a real-time one starts paused
])
def test_a_clock_signal_while_the_server_starts_sets_the_clock_it_starts_with(tmp_path, clock, sig, expected):
    scenario = _scenario(tmp_path, clock, extra="")
    proc = _spawn(["server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", "--no-record"],
                  signal_in=f"server.sim_server.build_world.{sig}")
    try:
        address, said = _listening(proc)  # before: killed by the signal (exit -10 / -12)
        now, _, rate = _rate(address, 0.6)
    finally:
        code, rest = _stop(proc)
    assert f"clock {expected})" in said, said
    assert now == expected
    assert (rate > 0.5) == (expected == "realtime"), rate
    assert code == 0 and "Traceback" not in rest, rest


def test_a_clock_signal_before_the_command_takes_its_signals_is_applied_when_it_does(tmp_path):
    """A SIGUSR2 that comes after the process started but before the server command installed
    its clock signals (while the modules import: sortie.cli takes them from its start and hands
    the request on) pauses the server from its first tick, as one during its start-up does."""
    scenario = _scenario(tmp_path, "realtime", extra="")
    proc = _spawn(["server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", "--no-record"],
                  signal_in="server.sim_cli.server_command.SIGUSR2")
    try:
        address, said = _listening(proc)  # before: killed by the signal (exit -12)
        now, _, rate = _rate(address, 0.6)
    finally:
        code, rest = _stop(proc)
    assert "clock paused)" in said, said
    assert now == "paused" and rate < 0.5, (now, rate)  # (a paused start may show its first tick)
    assert code == 0 and "Traceback" not in rest, rest


# -- 3. the take-over's clock signals -----------------------------------------------------------------

def test_a_take_over_takes_the_clock_signals_from_its_first_step(recorded, tmp_path):
    out = tmp_path / "take-over.sortie"
    proc = _spawn(["resim", recorded, "--take-over", "1", "--agent", "patrol1", "--duration", "100", "--port", "0",
                   "--record", out], signal_in="server.resim.take_over.SIGUSR2")
    try:
        address, said = _listening(proc)  # before: killed by SIGUSR2 while re-simulating (exit -12)
        paused = _rate(address, 0.6)
        proc.send_signal(signal.SIGUSR1)  # before: killed too, serving
        running = _rate(address, 1.0)
        proc.send_signal(signal.SIGUSR2)
        paused_again = _rate(address, 0.6)
    finally:
        code, rest = _stop(proc)
    assert "(clock paused x1)" in said, said
    assert paused[0] == "paused" and paused[2] == 0.0, paused
    assert running[0] == "realtime" and 0.5 < running[2] < REALTIME_RATE_MAX, running
    assert paused_again[0] == "paused" and paused_again[2] == 0.0, paused_again
    assert code == 0 and "Traceback" not in rest, rest
    with Recording(out) as rec:
        assert not rec.recovered and not rec.problems  # its footer written


# -- 4. ISO 8601 years before 1000 --------------------------------------------------------------------

@pytest.mark.parametrize("value, expected", [
    ("0001-01-01T00:00:00Z", "0001-01-01T00:00:00Z"),
    ("0999-12-31T23:59:59Z", "0999-12-31T23:59:59Z"),
    ("0800-02-29T23:59:30.25-03:30", "0800-03-01T03:29:30.250Z"),  # a leap day (800 = 2 x 400); UTC: the next
    ("0800-03-01T03:29:30.250000Z", "0800-03-01T03:29:30.250Z"),  # as server_config writes a start_time
    ("2026-06-15T07:00:00Z", "2026-06-15T07:00:00Z"),
    ("9999-12-31T23:59:59.999+00:00", "9999-12-31T23:59:59.999Z"),
])
def test_iso_utc_writes_four_digit_years(value, expected):
    assert iso_utc(value, "start_time") == expected


def test_iso_utc_refuses_a_time_outside_years_1_to_9999_in_utc():
    from sortie.errors import DataFormatError

    with pytest.raises(DataFormatError, match=r"start_time is not within years 1\.\.9999 in UTC "
                                              r"\(got '9999-12-31T23:59:59-05:00'\)"):
        iso_utc("9999-12-31T23:59:59-05:00", "start_time")


def test_the_acmi_reference_time_of_a_year_800_sortie(recorded, tmp_path, capsys):
    from sortie.cli import main

    out = tmp_path / "old.acmi"
    assert main(["export", "acmi", str(recorded), "-o", str(out)]) == 0, capsys.readouterr().err
    lines = out.read_text(encoding="utf-8-sig").splitlines()
    assert "0,ReferenceTime=0800-03-01T03:29:30.250Z" in lines, [t for t in lines if "ReferenceTime" in t]
