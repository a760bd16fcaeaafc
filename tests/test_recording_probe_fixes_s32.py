"""Crash-safety probe findings of round s32 (/tmp/probes32/crashrec): a chunk whose CHNK magic
reads INDX ended the walk (every later chunk dropped, nothing reported); a whole footer followed
by other bytes read as "no footer" and the bytes went unnamed; a --record-chunk-s of 1e300 killed
the recorder's thread (every tick lost, the server saying the recording succeeded); chunks were
never synced to the disk (a power loss lost ~35 s); inputs made while the clock was paused stayed
in memory until it ran, so a kill -9 lost them.

Real parts: the alps scenario's world (JSBSim aircraft, ground vehicles on the embedded SRTM tile)
records into real files through the real Recorder; the fsync test runs a recorder in a real
process under strace; the CLI checks run the real `sortie` commands.

Bounds: a damaged magic loses exactly that chunk's ticks (every other tick replays as in the whole
file); bytes after a footer leave the recording read by its footer, every frame as the whole
file's; chunk_s is refused above 3600 s; one fdatasync of the recording per chunk written;
inputs made while the clock is paused are on disk within chunk_s + 0.25 s + writing (read back
from a copy of the open file), and re-simulation is bit-exact with them at their tick.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import time
import types

import numpy as np
import pytest

from server.recorder import Recorder, recording_header
from server.recording import FRAME, NO_FOOTER, Recording
from sortie.errors import InvalidArgument

from conftest import REPO
from test_recording import SCENARIO, TICKS, _world, record_alps

CHUNK_S = 0.5  # 14 ticks a chunk at 30 Hz (a tick short of chunk_s, for its write): 13 chunks in TICKS
MAX_CHUNK_S = 3600.0  # server/recorder.py MAX_CHUNK_S: the bound the docs state


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    path = tmp_path_factory.mktemp("s32") / "whole.sortie"
    record_alps(path, chunk_s=CHUNK_S)
    with Recording(path) as rec:
        assert rec.problems == [] and rec.chunk_count == -(-TICKS // 14)
        return types.SimpleNamespace(path=path, offsets=list(rec.index.chunk_offset), footer=rec._index_end,
                                     firsts=list(rec.index.chunk_first_tick))


def sortie(*args):
    return subprocess.run([str(REPO / ".venv" / "bin" / "sortie"), *map(str, args)], capture_output=True,
                          text=True, timeout=120)


def assert_frames_as(rec: Recording, other: Recording, ticks) -> None:
    for t in ticks:
        a, b = rec.frame(t), other.frame(t)
        assert a.tick == b.tick == t and a.digest == b.digest and np.array_equal(a.q, b.q)


# -- finding 1: an INDX magic in a chunk ---------------------------------------------------------------

@pytest.mark.parametrize("footer", [True, False])
def test_a_chunk_magic_damaged_into_indx_loses_that_chunk_only(whole, tmp_path, footer):
    """Chunk 3's magic changed from CHNK to INDX (3 bytes): the walk does not stop there (no whole
    footer starts there); chunk 3 is lost, with its offset, and every later chunk reads (before:
    the walk ended, 3 of 12 chunks read and nothing said so)."""
    data = whole.path.read_bytes()
    at = whole.offsets[3]
    damaged = data[:at] + b"INDX" + data[at + 4:]
    path = tmp_path / "indx.sortie"
    path.write_bytes(damaged if footer else damaged[:whole.footer])
    lo, hi = whole.firsts[3], whole.firsts[4] - 1
    with Recording(path) as rec, Recording(whole.path) as w:
        assert rec.chunk_count == w.chunk_count and list(rec.lost) == [3]
        assert rec.lost[3].startswith(f"chunk 3 at offset {at} is no chunk frame (an INDX magic, but no whole "
                                      f"footer there): ticks {lo}..{hi}")
        assert (rec.first_tick, rec.last_tick) == (1, TICKS)
        report = rec.check()
        assert report.lost_ticks == hi - lo + 1 and report.damaged_chunks == 1 and not report.ok
        assert_frames_as(rec, w, [1, lo - 1, hi + 1, TICKS])


# -- finding 2: bytes after a whole footer -------------------------------------------------------------

@pytest.mark.parametrize("extra", ["garbage", "chunk_magic", "second_recording"])
def test_bytes_after_a_whole_footer_are_named_and_the_footer_read(whole, tmp_path, extra):
    """A whole footer followed by other bytes (appended garbage, a CHNK magic and garbage, a second
    recording concatenated): the recording reads by its footer, as the whole file, and the one
    problem names the bytes after it and the footer's offset (before: "no footer (not closed)",
    the bytes never named)."""
    data = whole.path.read_bytes()
    rng = np.random.default_rng(32)
    tail = {"garbage": rng.bytes(1000), "chunk_magic": b"CHNK" + rng.bytes(300), "second_recording": data}[extra]
    path = tmp_path / f"{extra}.sortie"
    path.write_bytes(data + tail)
    with Recording(path) as rec, Recording(whole.path) as w:
        assert not rec.recovered and rec.chunk_count == w.chunk_count
        assert rec.problems == [f"{len(tail)} bytes after the footer at offset {whole.footer} (the recording ends at "
                                f"byte {len(data)}): not part of the recording, left unread"]
        assert_frames_as(rec, w, [1, TICKS // 2, TICKS])
    if extra == "garbage":
        out = sortie("recording", "check", path)
        assert out.returncode == 1 and f"{len(tail)} bytes after the footer at offset {whole.footer}" in out.stdout, \
            out.stdout


def test_a_footer_damaged_in_place_is_still_walked_past_and_named(whole, tmp_path):
    """A footer cut short (its last 5 bytes gone) is no whole footer: the walk reads every chunk and
    names the bytes where the footer was (before: the walk stopped silently at its INDX)."""
    data = whole.path.read_bytes()
    path = tmp_path / "cut.sortie"
    path.write_bytes(data[:-5])
    with Recording(path) as rec:
        assert rec.recovered and rec.chunk_count == len(whole.offsets) and rec.last_tick == TICKS
        assert rec.problems == [NO_FOOTER, f"chunk at offset {whole.footer} is no chunk frame (an INDX magic, but no "
                                           f"whole footer there); {len(data) - 5 - whole.footer} bytes skipped (no "
                                           "whole chunk after it)"]


# -- finding 3: --record-chunk-s bounded -----------------------------------------------------------------

def test_chunk_s_is_bounded_where_it_is_given(tmp_path):
    """chunk_s above MAX_CHUNK_S (3600 s; 1e300 overflowed the writer thread's clock and killed it)
    is refused by the Recorder naming chunk_s, and by `sortie server` naming --record-chunk-s
    (exit 2, no file made)."""
    from server.sim_server import terrain_spec

    world, scenario, terrain, desc = _world()
    try:
        header = recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain)
        for bad in (1e300, MAX_CHUNK_S * 1.001, float("inf"), 0.0):
            with pytest.raises(InvalidArgument, match=r"^chunk_s: must be a number of seconds in \(0, 3600\]"):
                Recorder(tmp_path / f"r{bad}.sortie", header, bad)
        rec = Recorder(tmp_path / "max.sortie", header, MAX_CHUNK_S)  # the bound itself records
        world.attach_recorder(rec)
        for _ in range(3):
            world.tick()
        rec.close()
        assert rec.error is None and rec._thread.is_alive() is False
    finally:
        world.close()
    with Recording(tmp_path / "max.sortie") as r:
        assert r.problems == [] and r.last_tick == 3
    path = tmp_path / "cs.sortie"
    out = sortie("server", "--scenario", SCENARIO, "--port", 53201, "--record", path, "--record-chunk-s", "1e300",
                 "--aircraft-workers", 0, "--duration", 1)
    assert out.returncode == 2 and "--record-chunk-s: must be a number of seconds in (0, 3600]" in out.stderr, \
        out.stderr
    assert not path.exists()


# -- finding 4: chunks synced to the disk --------------------------------------------------------------------

RECORD_UNDER_STRACE = """
import sys
sys.path.insert(0, {repo!r}); sys.path.insert(0, {tests!r})
from test_recording import record_alps
from server.recording import Recording
record_alps({path!r}, ticks=60, chunk_s=0.25, inputs=False)
with Recording({path!r}) as r:
    print("chunks", r.chunk_count)
"""


@pytest.mark.skipif(shutil.which("strace") is None, reason="needs strace")
def test_every_chunk_is_synced_to_the_disk_as_it_is_written(tmp_path):
    """Under strace: at least one fdatasync of the recording's file per chunk written (before: none;
    one fsync, of the footer, when the recording closed, so a power loss lost up to the kernel's
    ~35 s of dirty pages)."""
    path = tmp_path / "synced.sortie"
    script = RECORD_UNDER_STRACE.format(repo=str(REPO), tests=str(REPO / "tests"), path=str(path))
    trace = tmp_path / "strace.out"
    out = subprocess.run(["strace", "-f", "-y", "-e", "trace=fdatasync,fsync", "-o", str(trace), sys.executable,
                          "-c", script], capture_output=True, text=True, timeout=180, cwd=REPO)
    assert out.returncode == 0, out.stderr[-2000:]
    chunks = int(out.stdout.split("chunks")[1])
    syncs = [ln for ln in trace.read_text().splitlines() if "fdatasync(" in ln and str(path) in ln]
    # 60 ticks at 0.25 s a chunk make 10 chunks of ticks; slowed by strace, the writer may also
    # close one on the wall clock (a CI run saw 11), so at least 10.
    assert chunks >= 10 and len(syncs) >= chunks, (chunks, syncs)


# -- finding 5: inputs made while the clock is paused ----------------------------------------------------

def test_inputs_made_while_paused_are_on_disk_before_the_clock_runs_and_resimulate(tmp_path):
    """The clock stops after 40 ticks; a pilot claims viper1 and sends 6 autopilot commands 0.15 s
    apart while it is paused (chunk_s 0.2 s). A copy of the open file taken then (what a kill -9
    leaves) holds the claim and at least the commands older than chunk_s + 0.25 s + 0.1 s of
    writing, in chunks of no tick, at tick 40 (before: none: they stayed in memory until the next
    tick). The clock runs 20 more ticks; the closed recording, and the same without its footer,
    read every input at its tick with no problem, and re-simulation is bit-exact."""
    from server.resim import resimulate
    from server.sim_server import terrain_spec

    path = tmp_path / "paused.sortie"
    world, scenario, terrain, desc = _world()
    chunk_s = 0.2
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain), chunk_s)
    world.attach_recorder(rec)
    viper = next(e.id for e in world.entities.values() if e.name == "viper1")
    sent = []
    try:
        for _ in range(40):
            world.tick()
        world.claim(viper, "token", "pilot-p")
        for k in range(6):
            world.command(viper, "autopilot", {"heading_deg": 100.0 + k, "alt_msl_m": 4200.0, "speed_mps": 210.0})
            sent.append(time.monotonic())
            time.sleep(0.15)
        time.sleep(chunk_s + 0.35)
        killed = tmp_path / "killed.sortie"
        shutil.copyfile(path, killed)  # what a kill -9 now leaves on disk
        for _ in range(20):
            world.tick()
    finally:
        rec.close()
        world.close()
    assert rec.error is None
    with Recording(killed) as r:
        inputs = list(r.inputs())
        assert r.problems == [NO_FOOTER] and r.last_tick == 40
        assert [i.kind for i in inputs] == ["claim"] + ["command"] * 6 and {i.tick for i in inputs} == {40}
    data = path.read_bytes()
    with Recording(path) as whole:
        footer = whole._index_end
    (tmp_path / "walked.sortie").write_bytes(data[:footer])
    for p in (path, tmp_path / "walked.sortie"):
        with Recording(p) as r:
            assert r.problems == ([] if p == path else [NO_FOOTER])
            assert (r.first_tick, r.last_tick, r.index.ticks) == (1, 60, 60)
            tickless = [k for k in range(r.chunk_count) if r.chunk_head(k).ticks == 0]
            assert tickless and all(r.index.chunk_first_tick[k] == 41 for k in tickless)
            inputs = list(r.inputs())
            assert [i.kind for i in inputs] == ["claim"] + ["command"] * 6 and {i.tick for i in inputs} == {40}
            assert [round(json.loads(i.values_json)["heading_deg"]) for i in inputs[1:]] == \
                list(range(100, 106))
    report = resimulate(path)
    assert report.bit_exact and report.ticks == 60, report.as_dict()


def test_a_copied_chunk_of_no_tick_is_left_out_once(tmp_path):
    """The reader keeps chunks of no tick in the middle of a recording (inputs made while paused)
    but not a byte-for-byte copy of one: its inputs would be made twice."""
    from server.recorder import encode_chunk
    from server.recording import RecordingWriter, quantization_of
    from server.recording_codec import DEFAULT_STEPS
    from server.world import Snapshot
    from sortie.v1 import recording_pb2 as rpb

    header = rpb.RecordingHeader(format_version=1, exercise_name="paused", world_rate_hz=30.0,
                                 quantization=quantization_of(DEFAULT_STEPS))
    path = tmp_path / "w.sortie"
    writer = RecordingWriter(path, header)
    z3, q = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]])

    def snaps(a, b):
        return [Snapshot(t / 30, t, np.array([1]), np.array([[4e6 + t, 0.0, 0.0]]), z3, z3, q, z3, *np.zeros((3, 1)))
                for t in range(a, b)]

    cmd = [rpb.InputRecord(tick=4, kind="remove", entity_id=2, reason=f"paused {k}") for k in range(2)]
    for s, inputs in ((snaps(1, 5), []), ([], cmd[:1]), ([], cmd[1:]), (snaps(5, 9), [])):
        writer.write_chunk(*encode_chunk(types.SimpleNamespace(snapshots=s, inputs=inputs, events=[], new_entities=[]),
                                         DEFAULT_STEPS, 30.0))
    writer.close()
    data = path.read_bytes()
    with Recording(path) as r:
        offs, footer = list(r.index.chunk_offset), r._index_end
        assert r.problems == [] and list(r.index.chunk_first_tick) == [1, 5, 5, 5]
        assert [i.reason for i in r.inputs()] == ["paused 0", "paused 1"]
    copy = data[:offs[3]] + data[offs[2]:offs[3]] + data[offs[3]:footer]
    (tmp_path / "copy.sortie").write_bytes(copy)
    with Recording(tmp_path / "copy.sortie") as r:
        assert [i.reason for i in r.inputs()] == ["paused 0", "paused 1"] and r.last_tick == 8
        assert r.problems[0] == NO_FOOTER and len(r.problems) == 2
        assert r.problems[1].startswith(f"chunk at offset {offs[3]} holds no tick") and "a copy" in r.problems[1]
