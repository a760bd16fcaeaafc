"""Docs probe of round s31: a start-up error is one line in text logging too (ARCHITECTURE.md,
"Start-up errors"): gRPC's C-core log line about a port in use came first."""

from __future__ import annotations

import os
import socket
import subprocess
import sys


def test_a_port_in_use_is_one_line_in_text_logging():
    with socket.socket() as held:
        held.bind(("127.0.0.1", 0))
        held.listen()
        port = held.getsockname()[1]
        env = {k: v for k, v in os.environ.items() if k != "GRPC_VERBOSITY"}
        proc = subprocess.run([sys.executable, "-m", "sortie.cli", "terrain", "serve", "--dem", "data/dem/N47E009.hgt",
                               "--port", str(port)], capture_output=True, text=True, timeout=60, env=env)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and "Address already in use" in lines[0] and str(port) in lines[0], proc.stderr
