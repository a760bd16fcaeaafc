"""A SIGTERM that comes while a command's modules import and its parser is built (before a
service takes its own signals) ends the process cleanly: 0 for a service, as its SIGTERM later
would, 143 (128 + SIGTERM) for any other command; never a kill by the signal (-15)."""

from __future__ import annotations

import subprocess
import sys
import textwrap

import pytest

# Sends itself SIGTERM while the parser is being built (the command modules importing), the
# window before any command's own handlers.
_SCRIPT = textwrap.dedent("""
    import os, signal, sys
    from sortie import cli
    build = cli.build_parser
    def build_parser(modules):
        os.kill(os.getpid(), signal.SIGTERM)
        return build(modules)
    cli.build_parser = build_parser
    sys.exit(cli.main(sys.argv[1:]))
""")


@pytest.mark.parametrize("argv, status", [
    (["server", "--scenario", "data/scenarios/alps.toml", "--port", "0"], 0),
    (["terrain", "serve", "--port", "0"], 0),
    (["bot", "--server", "127.0.0.1:1", "--count", "1"], 0),
    (["terrain", "info"], 143),
    (["bench", "terrain", "--quick", "--json", "/dev/null"], 143),
])
def test_a_sigterm_while_the_command_loads_ends_it_cleanly(argv, status):
    proc = subprocess.run([sys.executable, "-c", _SCRIPT, *argv], capture_output=True, text=True, timeout=60)
    assert proc.returncode == status, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr


def test_main_leaves_the_sigterm_handler_as_it_found_it(capsys):
    """In process (tests, embedding), main's handler is gone when it returns or raises."""
    import signal

    from sortie import cli

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(SystemExit):
        cli.main(["--version"])
    assert signal.getsignal(signal.SIGTERM) is before
    assert cli.main(["terrain", "info", "--dem", "/no/such/dem.hgt"]) != 0
    assert signal.getsignal(signal.SIGTERM) is before
