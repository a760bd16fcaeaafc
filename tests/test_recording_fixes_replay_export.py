"""Recording, replay and export fixes (acceptance probe /tmp/probe/rec.md, bugs 1-6).

Real parts: the alps world (JSBSim aircraft, ground vehicles on the embedded SRTM tile)
records 6 s into a real file while a pilot pulls viper1 into a negative-g crash (load
factor, about tick 85, in chunk 2); copies of it are damaged byte by byte; replay is
served over gRPC on loopback to a real SimClient, and to the Tacview telemetry host on a
real TCP socket read by the protocol reader of tests/test_tacview_live.py; the command line
runs as real processes.

Error bounds: a replayed paused picture is the recorded state within half the position
quantisation step (0.5 mm); a Tacview ``T=`` longitude or latitude is written to 1e-7
degrees (rounding 0.5e-7 plus the quantisation, under 1e-8); a ground vehicle on a DEM
raised 5 m is 5 m from its recorded position at tick 1 (the ground under it moves straight
up; seen: 5.000 m), its ECEF z part 5 sin(lat) m (3.685 m).
"""

from __future__ import annotations

import json
import math
import time

import numpy as np
import pytest

from server import recording_codec as codec
from server.recording import Recording
from sortie.errors import InvalidArgument
from terrain.geodesy import ecef_to_geodetic
from test_recording import SCENARIO, TICKS, _world
from test_recording_damage import flipped_chunk, sortie
from test_tacview_live import TacviewReader, client_hello

HALF_POSITION_STEP_M = codec.DEFAULT_STEPS.position_m / 2 * (1 + 1e-9)


def record_crash(path):
    """Record the alps world for TICKS, a pilot holding viper1's stick full forward from tick 10
    until it crashes; the tick of its crash event."""
    from server.recorder import Recorder, recording_header
    from server.sim_server import terrain_spec

    world, scenario, terrain, desc = _world()
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    viper = next(e for e in world.entities.values() if e.name == "viper1")
    crash = None
    try:
        for k in range(TICKS):
            if k == 10:
                world.claim(viper.id, "pilot-token", "pilot-1")
            if 10 <= k and k % 6 == 4 and not world.is_wreck(viper):
                world.command(viper.id, "stick", {"pitch": -1.0, "roll": 0.3, "throttle": 1.0})
            for ev in world.tick() or ():
                if ev.kind == "crash" and ev.entity_id == viper.id and crash is None:
                    crash = world.tick_count
    finally:
        rec.close()
        world.close()
    return crash


@pytest.fixture(scope="module")
def crashed(tmp_path_factory):
    path = tmp_path_factory.mktemp("crash") / "alps-crash.sortie"
    crash = record_crash(path)
    assert crash is not None and 61 <= crash <= 90, crash  # in chunk 2 (ticks 61-90)
    return path, crash


# -- bug 1: a step while paused moves every client's picture -------------------------------------------

def _picture_error_m(pic, rec, tick) -> float:
    ids, pos, _ = pic.state(tick * rec.dt)
    f = rec.frame(tick)
    k = np.searchsorted(f.ids, ids)
    assert len(ids) == len(f.ids) and np.array_equal(f.ids[k], ids)
    return float(np.linalg.norm(pos - f.states[k, 0:3], axis=1).max())


def test_a_forward_step_while_paused_shows_the_new_tick_to_every_watcher(crashed):
    from client.sim_client import SimClient
    from server.replay import ReplayServer

    path, crash = crashed
    server = ReplayServer(path, playing=False)
    server.start()
    try:
        with SimClient(server.address) as c, Recording(path) as rec:
            c.join("debrief", "observer", observer=(47.4, 9.5, 150_000.0))
            pic = c.watch()
            assert pic.snapshot_received.wait(10.0)
            st = c.replay(seek_time_s=1.0)
            assert pic.wait_for(lambda p: abs(p.time_s - st.tick * rec.dt) < 1e-9, 5.0)
            for n in (30, 1, 45, -20, 60):  # 45 crosses the crash
                before = server.world.events_total
                st = c.replay(step_ticks=n)
                assert pic.wait_for(lambda p: abs(p.time_s - st.tick * rec.dt) < 1e-9, 5.0), (n, pic.time_s)
                time.sleep(0.1)
                assert _picture_error_m(pic, rec, st.tick) <= HALF_POSITION_STEP_M * math.sqrt(3), n
                kinds = [e.kind for e in server.world.events_since(before)[0]]
                if n == 45:  # a forward step plays the events it passes
                    assert "crash" in kinds and st.tick >= crash
                if n < 0:
                    assert kinds == []
    finally:
        server.stop()


# -- bug 2: the ACMI export of a recording whose first chunk is damaged -------------------------------

def test_acmi_export_leaves_out_a_damaged_first_chunk_and_exits_0(crashed, tmp_path):
    path, _ = crashed
    from server.acmi import export_acmi

    flipped, offset = flipped_chunk(path, tmp_path, 0, "c0.sortie")
    with Recording(flipped) as rec:  # in process, then as the command runs it
        stats = export_acmi(rec, tmp_path / "in-process.acmi")
    assert len(stats.skipped) == 1 and f"chunk 0 at offset {offset}" in stats.skipped[0]
    out_path = tmp_path / "c0.acmi"
    out = sortie("export", "acmi", flipped, "-o", out_path)
    assert out.returncode == 0, out.stdout + out.stderr
    assert f"chunk 0 at offset {offset}" in out.stderr
    text = out_path.read_text(encoding="utf-8-sig")
    with Recording(path) as rec:  # the reference: the median position at the first tick that reads
        first = rec.chunk_ticks(1)[0]
        lat, lon, _ = ecef_to_geodetic(rec.frame(first).states[:, codec.POS])
    assert f"0,ReferenceLongitude={int(np.rint(np.median(lon)))}\n" in text
    assert f"0,ReferenceLatitude={int(np.rint(np.median(lat)))}\n" in text
    times = [float(line[1:]) for line in text.split("\n") if line.startswith("#")]
    assert times and times[0] == pytest.approx(first / 30.0, abs=1e-3)
    assert (tmp_path / "in-process.acmi").read_text(encoding="utf-8-sig") == text


# -- bug 3: Tacview telemetry of a replay follows its seeks -------------------------------------------

def test_tacview_telemetry_of_a_replay_follows_a_seek_and_ends_the_stream_on_a_backward_one(crashed):
    from server import tacview_live as tl
    from server.replay import ReplayServer

    path, _ = crashed
    server = ReplayServer(path, playing=False)
    server.start()
    telemetry = readers = None
    try:
        from client.sim_client import SimClient

        ctl = SimClient(server.address)
        ctl.replay(seek_time_s=4.0)
        telemetry = tl.TacviewTelemetry(server.address, port=0, rate_hz=20, name="replay")
        telemetry.start()
        readers = [TacviewReader(telemetry.port, client_hello("pytest"))]
        assert readers[0].until(lambda r: r.frames and r.frames[-1] == pytest.approx(4.0, abs=1e-3))
        ctl.replay(seek_time_s=5.0)  # forward: one more frame, at the new time
        assert readers[0].until(lambda r: r.frames[-1] == pytest.approx(5.0, abs=1e-3), 5.0), readers[0].frames[-5:]
        ctl.replay(seek_time_s=1.0)  # backward: the stream ends
        assert readers[0].until(lambda r: r.closed, 5.0), readers[0].frames[-5:]
        assert all(t <= 5.0 + 1e-3 for t in readers[0].frames)
        readers.append(TacviewReader(telemetry.port, client_hello("pytest-again")))
        r = readers[1]
        assert r.until(lambda r: len(r.frames) >= 1)  # the key frame (paused: nothing more changes)
        r.pump(0.3)
        assert r.frames[0] == pytest.approx(1.0, abs=1e-3) and r.frames[-1] == pytest.approx(1.0, abs=1e-3)
        with Recording(path) as rec:
            f = rec.frame(30)
            lat, lon, _ = ecef_to_geodetic(f.states[:, codec.POS])
            for i, la, lo in zip(f.ids.tolist(), lat, lon):
                got = r.objects[f"{i:x}"]["T"]
                assert abs(got[0] - lo) < 1e-7 and abs(got[1] - la) < 1e-7, (i, got, lo, la)
        ctl.replay(speed=4.0)
        ctl.replay(play=True)  # and on: frame times follow the replay's from 1 s
        assert r.until(lambda r: r.frames[-1] > 2.0, 5.0)
        assert not r.closed and np.all(np.diff(r.frames) > 0) and r.frames[-1] < 4.0
        ctl.close()
    finally:
        for r in readers or ():
            r.close()
        if telemetry is not None:
            telemetry.stop()
        server.stop()


# -- bug 4: a take-over of an agent that crashed before it -------------------------------------------

def test_take_over_refuses_an_agent_that_crashed_before_the_instant(crashed, tmp_path):
    from server.resim import take_over

    path, crash = crashed
    with pytest.raises(InvalidArgument, match=rf"has crashed by t = 4.0 s \(at t = {crash / 30:.2f} s\)"):
        take_over(path, 4.0, "viper1")
    out = sortie("resim", path, "--take-over", "4", "--agent", "viper1", "--port", "0", "--no-record")
    assert out.returncode == 2, out.stdout + out.stderr
    assert f"--agent: has crashed by t = 4.0 s (at t = {crash / 30:.2f} s)" in out.stderr
    assert "listening" not in out.stdout


# -- bug 5: resim's position difference is a distance --------------------------------------------------

def test_resim_reports_the_position_difference_as_a_distance(crashed, tmp_path, hgt_alps):
    from server.resim import resimulate

    path, _ = crashed
    raised = np.fromfile(hgt_alps, ">i2")
    raised = np.where(raised > -32768, raised + 5, raised).astype(">i2")  # the whole tile 5 m higher
    other = tmp_path / "N47E009.hgt"
    raised.tofile(other)
    report = resimulate(path, dem=[other], until_s=1 / 30)
    assert report.ticks == 1 and not report.bit_exact
    assert report.max_position_diff_m == pytest.approx(5.0, abs=0.01)  # the ground vehicles, straight up
    # The per-axis figure: the ECEF z part alone, 5 sin(lat) m for vehicles at 47.2-47.5 degrees north.
    assert 5.0 * math.sin(math.radians(47.2)) - 0.01 < report.max_abs_diff_m < 5.0 * math.sin(math.radians(47.5))
    d = report.as_dict()
    assert d["max_position_diff_m"] == report.max_position_diff_m and d["max_abs_diff_m"] == report.max_abs_diff_m
    json.dumps(d)


# -- bug 6: info and check leave a damaged chunk out of the event and input totals -------------------

def test_info_and_check_totals_leave_out_a_damaged_chunk(crashed, tmp_path):
    from server.recording_cli import summary

    path, _ = crashed
    with Recording(path) as rec:
        whole = rec.check()
        lost = rec.chunk(2)
        assert any(e.event.kind == "crash" for e in lost.events) and lost.inputs  # what the damage loses
    flipped, _ = flipped_chunk(path, tmp_path, 2)
    with Recording(flipped) as rec:
        s = summary(rec)
        report = rec.check()
    assert s["events"] == sum(s["events_by_kind"].values()) == whole.events - len(lost.events)
    assert "crash" not in s["events_by_kind"]
    assert s["inputs"] == whole.inputs - len(lost.inputs)
    assert (report.events, report.inputs) == (s["events"], s["inputs"])
    out = sortie("recording", "check", flipped)
    assert out.returncode == 1 and f"{s['events']} events, {s['inputs']} inputs" in out.stdout, out.stdout
