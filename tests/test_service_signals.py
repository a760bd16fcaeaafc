"""A service stops cleanly on SIGTERM sent the moment it says where it listens (a supervisor's
or a test's reflex): the signal handlers are in place before that line (grpc_common.stop_signals).
Before, they came after it, and a SIGTERM in between killed the process (-15): seen as a flaky
`sortie replay` test on a loaded machine. Each service runs in a subprocess whose status-line
function sends the process SIGTERM right after writing a "listening on" line."""

import subprocess
import sys

import pytest

from test_recording import record_alps

SELF_SIGNAL = """
import os, signal, sys
import sortie.logs as logs
_line = logs.line
def line(message, *args, **kwargs):
    _line(message, *args, **kwargs)
    if "listening on" in message:
        os.kill(os.getpid(), signal.SIGTERM)
logs.line = line
from sortie.cli import main
sys.exit(main(sys.argv[1:]))
"""


def _run(*argv) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", SELF_SIGNAL, *map(str, argv)], capture_output=True, text=True,
                          timeout=120)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("signals") / "alps.sortie"
    record_alps(path)
    return path


def test_terrain_serve_stops_cleanly_on_a_sigterm_right_after_it_listens(hgt_alps):
    out = _run("terrain", "serve", "--dem", hgt_alps, "--port", "0")
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
    assert "stopped" in out.stdout


def test_replay_stops_cleanly_on_a_sigterm_right_after_it_listens(recorded):
    out = _run("replay", recorded, "--port", "0")
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])


def test_the_server_stops_cleanly_on_a_sigterm_right_after_it_listens(tmp_path):
    from test_sim_hardening import AGENTS, scenario_file

    out = _run("server", "--scenario", scenario_file(tmp_path, AGENTS), "--port", "0", "--aircraft-workers", "0",
               "--no-record")
    assert out.returncode == 0, (out.returncode, out.stderr[-2000:])
