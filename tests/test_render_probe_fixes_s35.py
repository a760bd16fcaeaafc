"""Acceptance-probe fixes of the render client (session 35).

1. ``sortie view`` checked ``--pixel-error``, ``--views`` and ``--name`` only after joining the server and
   finding the agent (with no server there: "UNAVAILABLE ... within 10 s", the bad option never
   named); now they are refused first, as the other render options are.
2. ``sortie view --fps 1e-12 --frames 2`` rendered a frame, then the wait for the next one
   (1e12 s) raised OverflowError from threading (timeouts are limited to threading.TIMEOUT_MAX,
   about 9.2e9 s): a traceback. ``--fps`` is now refused under a frame a day.

Real parts: the sortie CLI's parser and checks; no server listens on the port named (52798), so
an error that comes first shows the option was checked before any connection.
"""

from __future__ import annotations

import threading
import time

import pytest

from sortie.cli import main

NO_SERVER = "127.0.0.1:52798"


def _view(tmp_path, *extra) -> list[str]:
    return ["view", "--server", NO_SERVER, "--follow", "x", "--frames", "2", "--fps", "1", "--out",
            str(tmp_path / "v"), *extra]


@pytest.mark.parametrize("extra, named", [
    (("--pixel-error", "nan"), "--pixel-error"),
    (("--pixel-error", "-1"), "--pixel-error"),
    (("--pixel-error", "1000"), "--pixel-error"),
    (("--views", "cockpit,bogus"), "--views"),
    (("--views", "chase,chase"), "--views"),
])
def test_view_refuses_bad_render_options_before_joining(tmp_path, capsys, extra, named):
    """Before: 10 s waiting for the server, then its UNAVAILABLE error (with a server: the error came
    after joining and waiting for the agent)."""
    t0 = time.monotonic()
    rc = main(_view(tmp_path, *extra))
    err = capsys.readouterr().err
    assert rc == 2 and named in err and extra[1] in err and "UNAVAILABLE" not in err, err
    assert time.monotonic() - t0 < 5.0  # before any connection


@pytest.mark.parametrize("fps", ["1e-12", "1e-6", "0", "-1", "nan"])
def test_view_refuses_a_frame_rate_too_low_to_wait_for(tmp_path, capsys, fps):
    """Before: 1e-12 and 1e-6 were taken (1e-12 then raised OverflowError between frames)."""
    t0 = time.monotonic()
    rc = main(["view", "--server", NO_SERVER, "--follow", "x", "--frames", "2", "--fps", fps, "--out",
               str(tmp_path / "v")])
    err = capsys.readouterr().err
    assert rc == 2 and "--fps" in err and "UNAVAILABLE" not in err, err
    assert time.monotonic() - t0 < 5.0


def test_the_slowest_frame_rate_waits_within_threadings_bound():
    from client.render_cli import FPS_MIN

    assert 1.0 / FPS_MIN == pytest.approx(86_400.0) and 1.0 / FPS_MIN < threading.TIMEOUT_MAX / 1e3


@pytest.mark.parametrize("name", ["", "x" * 65, "a\nb"])
def test_view_refuses_a_session_name_the_server_would_refuse(tmp_path, capsys, name):
    """Before: "client_name: must be 1-64 printable characters" from the server after joining (with
    no server: UNAVAILABLE after 10 s). Now --name, before any connection."""
    t0 = time.monotonic()
    rc = main(_view(tmp_path, f"--name={name}"))
    err = capsys.readouterr().err
    assert rc == 2 and "--name" in err and "1-64 printable" in err and "UNAVAILABLE" not in err, err
    assert time.monotonic() - t0 < 5.0


def test_a_session_name_the_server_takes_is_taken():
    from client.render_cli import check_session_name

    for name in ("render-client", "x" * 64, "Viper 1 (chase)"):
        check_session_name(name)
