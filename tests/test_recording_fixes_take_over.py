"""A take-over (``sortie resim FILE --take-over S --agent NAME``) is a sortie the server runs,
so it is recorded as ``sortie server`` records, with the same options (acceptance report h3,
bug 9).

Real parts: the alps world records 6 s with a pilot's and a driver's inputs; a real
``sortie resim --take-over`` process serves the take-over of the tank at 3 s (tick 90) to a
real client over gRPC, which claims the tank and drives it. Expected: a recording in
--record-dir named after the exercise, which ``sortie recording check`` passes; it holds the
whole sortie from its first tick (the re-simulated ticks bit for bit the original's), the
take-over itself as an input, and the client's claim and drive command with their values;
and it re-simulates bit for bit."""

from __future__ import annotations

import json
import subprocess
import time

import pytest

from server.recording import Recording
from test_recording import record_alps


def sortie(*args, timeout=120) -> subprocess.CompletedProcess:
    from server.process import sortie_command

    return subprocess.run([*sortie_command(), *map(str, args)], capture_output=True, text=True, timeout=timeout)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("takeover") / "alps.sortie"
    record_alps(path)
    return path


def test_a_take_over_is_recorded_with_the_taken_over_agents_inputs(recorded, tmp_path):
    from client.sim_client import SimClient
    from server.process import ServiceProcess
    from server.resim import resimulate

    recordings = tmp_path / "recordings"
    args = ["resim", str(recorded), "--take-over", "3", "--agent", "tank1", "--record-dir", str(recordings)]
    with ServiceProcess(args, log=tmp_path / "take-over.log") as p, SimClient(p.address) as driver:
        agent = driver.join("new-driver", "driver", agent_name="tank1")
        with driver.controls() as stream:
            stream.drive(speed_mps=6.0, yaw_rate_dps=2.0)
            time.sleep(1.5)
        driver.leave()
    log = (tmp_path / "take-over.log").read_text()
    (path,) = recordings.glob("*.sortie")
    assert path.name.startswith("alpine-shield-lake-constance-take-over-") and f"recording to {path}" in log
    out = sortie("recording", "check", path)
    assert out.returncode == 0 and "OK" in out.stdout, out.stdout + log
    with Recording(path) as rec, Recording(recorded) as original:
        assert not rec.recovered and rec.first_tick == 1 and rec.last_tick > 90 + 15  # the live part ran
        assert rec.frame(90).digest == original.frame(90).digest  # the re-simulated part is the original's
        assert rec.header.scenario_toml == original.header.scenario_toml
        assert rec.header.terrain == original.header.terrain
        mine = [r for r in rec.inputs() if r.entity_id == agent and r.tick >= 90]
        assert [r.kind for r in mine[:4]] == ["take_over", "release", "claim", "command"], mine
        take_over, _, claim, drive = mine[:4]
        assert take_over.tick == 90 and json.loads(take_over.values_json) == {"controllable": True,
                                                                              "on_vanish": "autopilot"}
        assert claim.client == "new-driver" and drive.command == "drive"
        values = json.loads(drive.values_json)
        assert (values["speed_mps"], values["yaw_rate_dps"]) == (6.0, 2.0)
        assert mine[-1].kind == "release"  # the client left
        last = rec.last_tick
    report = resimulate(path)  # the take-over is an input too: its recording re-simulates
    assert report.bit_exact and report.ticks == last, report.as_dict()


def test_the_recording_options_are_the_take_overs(recorded, tmp_path):
    out = sortie("resim", recorded, "--record", tmp_path / "x.sortie")
    assert out.returncode == 2 and "only with --take-over" in out.stderr and "Traceback" not in out.stderr
    assert not (tmp_path / "x.sortie").exists()
    out = sortie("resim", recorded, "--take-over", "1", "--agent", "tank1", "--record", recorded)
    assert out.returncode == 2 and "the file exists" in out.stderr, out.stderr
    out = sortie("resim", "--help")
    assert all(option in out.stdout for option in ("--record FILE", "--record-dir DIR", "--no-record",
                                                   "--record-chunk-s S"))


def test_a_take_over_that_cannot_listen_leaves_no_recording(recorded, tmp_path):
    """An acceptance probe: with its port taken, a take-over exited 2 but left its recording (the
    re-simulated history, no footer) for `sortie replay` to pick up."""
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        out = sortie("resim", recorded, "--take-over", "1", "--agent", "tank1", "--port", port,
                     "--record", tmp_path / "rec" / "x.sortie")
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert not (tmp_path / "rec").exists()


def test_sortie_replay_status_lines_are_json_records_in_json_logging(recorded):
    """The services' status lines are log records in JSON logging (docs/DEPLOYMENT.md):
    `sortie replay`'s first line is one JSON object naming where it listens."""
    import signal

    from server.process import sortie_command

    proc = subprocess.Popen([*sortie_command(), "--log-format", "json", "replay", str(recorded), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        first = proc.stdout.readline()
        record = json.loads(first)
        assert "listening on" in record["message"] and record["level"].lower() == "info", record
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(30)
    assert proc.returncode == 0
