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
