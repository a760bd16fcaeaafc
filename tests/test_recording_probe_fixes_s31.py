"""Debrief probe findings of round s31: a Recording read from several threads at once (the
replay's clock and its control calls) decompresses each chunk with its own thread's zstd
decompressor (one shared one read intact chunks as corrupt and crashed the process); ACMI
frame times are written to the microsecond (rounded to 1 ms at 30 Hz they made a steady
200 m/s read 196-202 m/s and 18 g)."""

from __future__ import annotations

import random
import threading

import numpy as np

from server import acmi
from server.recording import Recording
from test_recording import record_alps


def test_threads_reading_chunks_at_once_read_them_intact(tmp_path):
    """Four threads read random chunks 1500 times each: every body equals the one read alone,
    none raises; each thread has its own decompressor."""
    path = tmp_path / "alps.sortie"
    record_alps(path, ticks=240, chunk_s=0.2)
    with Recording(path) as rec:
        n = rec.chunk_count
        assert n >= 20
        alone = [rec.chunk_body(k)[1].SerializeToString() for k in range(n)]
        errors, seen = [], set()

        def read(seed):
            r = random.Random(seed)
            try:
                seen.add(id(rec._decompressor()))
                for _ in range(1500):
                    k = r.randrange(n)
                    if rec.chunk_body(k)[1].SerializeToString() != alone[k]:
                        errors.append(f"chunk {k} read differently")
            except Exception as exc:  # noqa: BLE001 - any failure is the finding
                errors.append(repr(exc))

        threads = [threading.Thread(target=read, args=(s,)) for s in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert errors == []
        assert len(seen) == 4


def test_acmi_frame_times_keep_30_hz_kinematics():
    """At 30 Hz every frame time written is within 0.5 us of tick / 30, so a speed derived from
    a 200 m/s track over one frame is within 0.01 m/s of it (1 ms rounding: up to 4 m/s)."""
    dt = 1.0 / 30.0
    d = acmi.time_decimals(dt)
    ticks = np.arange(1, 3001)
    written = np.array([float(f"{k * dt:.{d}f}") for k in ticks])
    assert np.abs(written - ticks * dt).max() <= 0.5e-6 + 1e-12
    speed = 200.0 * dt / np.diff(written)
    assert np.abs(speed - 200.0).max() < 0.01
    assert acmi.time_decimals(1e-7) >= 7  # frames closer than a microsecond stay distinct
