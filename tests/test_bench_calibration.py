"""The machine-speed probes every bench report carries (bench/calibration.py)."""

import math

import numpy as np

from bench import calibration
from bench.harness import Report


def test_the_chase_table_is_one_cycle_through_every_slot():
    n = 1000
    table = calibration._chase_table(n, seed=3)
    seen = np.zeros(n, bool)
    i = 0
    for _ in range(n):
        assert not seen[i], "the chase came back early: the table holds a shorter cycle"
        seen[i] = True
        i = table[i]
    assert i == 0 and seen.all()
    assert calibration._chase(table, n) == 0  # the compiled chase walks the same cycle


def test_probes_are_positive_and_land_in_the_report_before_and_after():
    before = {"host_python_ns": calibration.python_ns(iterations=1000, rounds=2),
              "host_random_read_ns": calibration.random_read_ns(reads=1000, rounds=2)}
    assert all(math.isfinite(v) and v > 0 for v in before.values())
    report = Report("x", quick=True)
    calibration.add_to(report, before, {k: 2 * v for k, v in before.items()})
    assert report.metrics == {"host_python_ns_before": before["host_python_ns"],
                              "host_python_ns_after": 2 * before["host_python_ns"],
                              "host_random_read_ns_before": before["host_random_read_ns"],
                              "host_random_read_ns_after": 2 * before["host_random_read_ns"]}


def test_an_unwritable_json_path_is_refused_before_the_run(tmp_path):
    """sortie bench checks --json and --plots first: a suite can run for minutes, and its
    figures were lost to a traceback at the end."""
    import subprocess
    import time

    from server.process import sortie_command

    blocker = tmp_path / "a-file"
    blocker.write_text("")
    for option, value in (("--json", blocker / "x.json"), ("--plots", blocker / "plots")):
        t0 = time.monotonic()
        r = subprocess.run([*sortie_command(), "bench", "store", option, str(value)], capture_output=True, text=True,
                           timeout=60)
        assert r.returncode == 2 and f"{option}: cannot be written" in r.stderr, r.stderr
        assert time.monotonic() - t0 < 30.0  # refused at once, not after the suite
