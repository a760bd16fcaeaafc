"""The machine's own speed, measured around every suite: what its figures ran on.

The benchmark VM is shared, and its speed moves by several times from one hour to the
next: the same bare JSBSim step has read 8.7 µs and 16 µs in full runs a day apart, and
the same bilinear kernel 72 and 25 million samples/s. Ratios against a baseline in the
same run absorb most of that; absolute figures (and ratios between a compute-bound and a
memory-bound side) do not. So each suite's report carries two fixed probes, timed
before and after the suite (``sortie bench`` adds them to every report):

- ``host_python_ns``: nanoseconds per iteration of a fixed pure-Python loop (the
  interpreter's speed: what the hosting loops, gRPC handlers and publishers cost);
- ``host_random_read_ns``: nanoseconds per dependent random read in a 64 MiB table
  (a pointer chase, so each read waits on the one before: memory latency, what
  uniformly random terrain queries are bound by once a raster leaves the caches).

Each is the best of a few short rounds (tens of milliseconds in all), so a probe reads
the machine's speed at that moment rather than its worst stall. ``..._before`` and
``..._after`` both appear; their spread shows whether the machine changed speed during
the suite. Compare absolute figures of two runs only where these probes agree.
"""

from __future__ import annotations

import time

import numba
import numpy as np

PYTHON_LOOP_ITERATIONS = 200_000
CHASE_TABLE_BYTES = 64 * 1024 * 1024
CHASE_READS = 200_000
ROUNDS = 5


def python_ns(iterations: int = PYTHON_LOOP_ITERATIONS, rounds: int = ROUNDS) -> float:
    """Best ns per iteration of a fixed loop of integer and float arithmetic and a branch."""
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        acc, x = 0, 0.5
        for i in range(iterations):
            x = x * 0.999 + 1.0
            if i & 1:
                acc += i
        best = min(best, time.perf_counter() - t0)
    return best / iterations * 1e9


def _chase_table(n: int, seed: int = 7) -> np.ndarray:
    """A single random cycle through n slots: next[i] is the slot read after i."""
    order = np.random.default_rng(seed).permutation(n)
    table = np.empty(n, np.int64)
    table[order[:-1]] = order[1:]
    table[order[-1]] = order[0]
    return table


@numba.njit(cache=True, nogil=True)
def _chase(table, reads):
    i = 0
    for _ in range(reads):
        i = table[i]
    return i


_table: np.ndarray | None = None


def random_read_ns(reads: int = CHASE_READS, rounds: int = ROUNDS) -> float:
    """Best ns per read of a pointer chase through a CHASE_TABLE_BYTES random cycle."""
    global _table
    if _table is None:
        _table = _chase_table(CHASE_TABLE_BYTES // 8)
    _chase(_table, 1000)  # compiled (or loaded from the cache) before timing
    best = float("inf")
    for _ in range(rounds):
        t0 = time.perf_counter()
        _chase(_table, reads)
        best = min(best, time.perf_counter() - t0)
    return best / reads * 1e9


def probe() -> dict[str, float]:
    """{"host_python_ns": ..., "host_random_read_ns": ...} now."""
    return {"host_python_ns": python_ns(), "host_random_read_ns": random_read_ns()}


def add_to(report, before: dict[str, float], after: dict[str, float]) -> None:
    """The probes taken around a suite, into its report's metrics (``_before`` / ``_after``)."""
    for key in before:
        report.metrics[f"{key}_before"] = before[key]
        report.metrics[f"{key}_after"] = after[key]


__all__ = ["probe", "add_to", "python_ns", "random_read_ns"]
