"""A recording without its footer (the server was killed) with a damaged chunk in its middle:
the walk goes on past it, the chunk's ticks are lost and said so, everything else reads as
in the whole file (acceptance report h3, bug 6).

Real parts: the alps world records 6 s (1-s chunks; one closes early when a tick is slow in
wall time, so the chunks are found by what they hold: "quiet", a chunk in the middle with
no input, and "new", the one that first holds an external entity, the "newcomer", published
after tick 100) with a pilot's and a driver's inputs; its footer is cut off and one byte of a
chunk's body, head or frame lengths is changed. Expected, against the whole file: the same first and last
ticks, chunk count and entity descriptions; bit-identical frames outside the damaged chunk;
a DataFormatError naming the chunk and its offset inside it; the events of every other chunk;
re-simulation refused when the chunk's inputs are lost, bit-exact on the rest when it held
none. Recordings in the layout written before chunk heads had a CRC of their own (converted
here from the whole file) still read; there a lost chunk loses the descriptions of the entities
it introduced, which are then reported, and read without them."""

from __future__ import annotations

import json
import subprocess
import time
import types
import zlib

import numpy as np
import pytest

from server.recording import FRAME, NO_FOOTER, Recording
from sortie.errors import DataFormatError
from sortie.v1 import recording_pb2 as rpb
from test_recording import SCENARIO, _world

TICKS = 180
NEWCOMER_TICK = 100  # the external entity's first update: after tick 100


def record(path):
    """The alps world for TICKS ticks with a pilot, a driver, a removal and an external
    entity published after NEWCOMER_TICK; the newcomer's id."""
    from server.external import external_state
    from server.recorder import Recorder, recording_header
    from server.sim_server import terrain_spec
    from server.world import AIRCRAFT
    from terrain.geodesy import geodetic_to_ecef

    world, scenario, terrain, desc = _world()
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    by_name = {e.name: e.id for e in world.entities.values()}
    viper, tank = by_name["viper1"], by_name["tank1"]
    newcomer = None
    try:
        for k in range(TICKS):
            if k == 20:
                world.claim(viper, "token", "pilot-1")
                world.command(viper, "stick", {"pitch": 0.25, "roll": -0.1, "throttle": 1.0})
            if k == 50:
                world.claim(tank, "tank-token", "driver-1")
                world.command(tank, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 3.0})
            if k == 90:
                world.release(viper, vanished=True)
            if k == NEWCOMER_TICK:
                pos = np.asarray(geodetic_to_ecef(47.3, 9.4, 3000.0), float).reshape(3)
                state = external_state(0.0, pos, (0.0, 150.0, 0.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0),
                                       (0.0, 0.0, 0.0), 4)
                newcomer = world.publish_external("dis:1.2.3", "gw", state, "newcomer", AIRCRAFT, "f16", "red")
            if k == 120:
                world.remove(by_name["radar1"], "destroyed by the test")
            world.tick()
    finally:
        rec.close()
        world.close()
    return newcomer


class Whole:
    """The whole recording: its path, the newcomer's id, and the chunks "quiet" and "new"."""

    def __init__(self, path, newcomer: int):
        self.path, self.newcomer = path, newcomer
        with Recording(path) as rec:
            assert rec.check().ok and (rec.first_tick, rec.last_tick) == (1, TICKS)
            assert rec.entities[newcomer].name == "newcomer"
            heads = [rec.chunk_head(k) for k in range(rec.chunk_count)]
            self.chunks = rec.chunk_count
            firsts = list(rec.index.chunk_first_tick)
            self.ticks = [(a, b - 1) for a, b in zip(firsts, firsts[1:] + [rec.last_tick + 1])]
        self.new = next(k for k, h in enumerate(heads) if newcomer in [e.entity_id for e in h.new_entities])
        self.quiet = next(k for k, h in enumerate(heads[1:-1], 1) if h.input_count == 0)
        assert 0 < self.new < self.chunks - 1 and heads[self.new].input_count > 0

    def k(self, which: str) -> int:
        return {"quiet": self.quiet, "new": self.new}[which]


@pytest.fixture(scope="module")
def whole(tmp_path_factory):
    path = tmp_path_factory.mktemp("walk") / "whole.sortie"
    return Whole(path, record(path))


def footerless(path, out, k: int = -1, where: str = "", chunks=None) -> int:
    """``path`` without its footer into ``out``, with chunk k damaged ``where``: "body" (a byte of
    the compressed body), "head" (a byte of the head), "length" (the body length 1000 bytes too
    long), "huge" (a body length past the end of the file); chunk k's offset. ``chunks``:
    the chunks' bytes to write instead of the file's (a converted file)."""
    with Recording(path) as rec:
        data = path.read_bytes()
        offsets, ends = list(rec.index.chunk_offset), list(rec.index.chunk_offset[1:]) + [rec._index_end]
    parts = chunks if chunks is not None else [data[a:b] for a, b in zip(offsets, ends)]
    out_bytes = bytearray(data[:offsets[0]])
    starts = []
    for part in parts:
        starts.append(len(out_bytes))
        out_bytes += part
    if k >= 0:
        o = starts[k]
        _, nh, nb, _ = FRAME.unpack(out_bytes[o:o + FRAME.size])
        if where == "body":
            out_bytes[o + FRAME.size + nh + 20] ^= 0x10
        elif where == "head":
            out_bytes[o + FRAME.size + 1] ^= 0x04  # first_tick's value: a head that parses, and lies
        elif where == "length":
            out_bytes[o + 8:o + 12] = (nb + 1000).to_bytes(4, "little")
        elif where == "huge":
            out_bytes[o + 8:o + 12] = (len(out_bytes) * 4).to_bytes(4, "little")
        else:
            raise ValueError(where)
    out.write_bytes(bytes(out_bytes))
    return starts[k] if k >= 0 else -1


def old_format_chunks(path) -> list[bytes]:
    """The chunks of ``path`` as a writer before head CRCs wrote them: heads without head_crc32
    and recent_entities, each frame's CRC over its head and body."""
    with Recording(path) as rec:
        data = path.read_bytes()
        out = []
        for o in rec.index.chunk_offset:
            _, nh, nb, _ = FRAME.unpack(data[o:o + FRAME.size])
            head = rpb.ChunkHead.FromString(data[o + FRAME.size:o + FRAME.size + nh])
            body = data[o + FRAME.size + nh:o + FRAME.size + nh + nb]
            for name in ("recent_entities", "head_crc32"):
                if name in head.DESCRIPTOR.fields_by_name:
                    head.ClearField(name)
            hb = head.SerializeToString()
            out.append(FRAME.pack(b"CHNK", len(hb), len(body), zlib.crc32(body, zlib.crc32(hb))) + hb + body)
    return out


def events_by_chunk(rec) -> list:
    out = []
    for k in range(rec.chunk_count):
        try:
            out.append([e.SerializeToString() for e in rec.chunk_body(k)[1].events])
        except DataFormatError:
            out.append(None)
    return out


def sortie(*args, timeout=300) -> subprocess.CompletedProcess:
    from server.process import sortie_command

    return subprocess.run([*sortie_command(), *map(str, args)], capture_output=True, text=True, timeout=timeout)


def assert_reads_as_whole_but(rec, whole_rec, k: int, offset: int, ticks: list) -> None:
    """``rec`` holds what ``whole_rec`` does but chunk k's ticks (``ticks[k]``), inputs and events."""
    lo, hi = ticks[k]
    assert hi - lo >= 20 and rec.recovered and rec.chunk_count == whole_rec.chunk_count
    assert (rec.first_tick, rec.last_tick) == (whole_rec.first_tick, whole_rec.last_tick) == (1, TICKS)
    assert (rec.first_time_s, rec.last_time_s) == (whole_rec.first_time_s, whole_rec.last_time_s)
    assert list(rec.index.chunk_first_tick) == list(whole_rec.index.chunk_first_tick)
    for tick in range(1, TICKS + 1):
        if lo <= tick <= hi:
            with pytest.raises(DataFormatError, match=f"chunk {k} at offset {offset}"):
                rec.frame(tick)
            continue
        f, g = rec.frame(tick), whole_rec.frame(tick)
        assert np.array_equal(f.ids, g.ids) and np.array_equal(f.q, g.q) and f.digest == g.digest
    got, want = events_by_chunk(rec), events_by_chunk(whole_rec)
    assert got[k] is None and got[:k] + got[k + 1:] == want[:k] + want[k + 1:]
    report = rec.check()
    assert report.damaged_chunks == 1 and report.lost_ticks == hi - lo + 1
    assert np.allclose(report.replays, [(1 / 30, (lo - 1) / 30), ((hi + 1) / 30, TICKS / 30)], rtol=0, atol=1e-12)
    assert report.problems[0] == NO_FOOTER
    damage = [p for p in report.problems if f"offset {offset}" in p and "first to hold" not in p]
    assert len(damage) == 1 and f"chunk {k} at offset {offset}" in damage[0]


@pytest.mark.parametrize("which, where", [("quiet", "body"), ("quiet", "head"), ("new", "head"),
                                         ("quiet", "length"), ("new", "huge")])
def test_the_walk_goes_on_past_a_damaged_chunk(whole, tmp_path, which, where):
    k, newcomer = whole.k(which), whole.newcomer
    damaged = tmp_path / f"{where}-{which}.sortie"
    offset = footerless(whole.path, damaged, k, where)
    with Recording(damaged) as rec, Recording(whole.path) as w:
        assert_reads_as_whole_but(rec, w, k, offset, whole.ticks)
        # Every entity keeps its description, the newcomer too when its own chunk's head is
        # lost: the next heads repeat it (recent_entities).
        assert {i: e.SerializeToString() for i, e in rec.entities.items()} == \
            {i: e.SerializeToString() for i, e in w.entities.items()}
        assert rec.undescribed == {} and rec.entities[newcomer].name == "newcomer"
        lo, hi = whole.ticks[k]
        if where == "body":  # its head checks: the tick span, inputs and events it loses are known
            assert rec.lost == {} and rec.trusted_head(k).first_tick == lo
            with pytest.raises(DataFormatError, match=f"its head checks: ticks {lo}\\.\\.{hi} .* 0 inputs"):
                rec.chunk(k)
        else:
            assert list(rec.lost) == [k] and rec.trusted_head(k) is None
            assert f"ticks {lo}..{hi}" in rec.lost[k]
            assert f"next whole chunk, at offset {rec.index.chunk_offset[k + 1]}" in rec.lost[k]


def test_check_and_info_list_the_damaged_chunk_and_what_replays(whole, tmp_path):
    k, n = whole.quiet, whole.chunks
    (lo, hi) = whole.ticks[k]
    damaged = tmp_path / "head.sortie"
    offset = footerless(whole.path, damaged, k, "head")
    out = sortie("recording", "check", damaged)
    assert out.returncode == 1 and "Traceback" not in out.stderr, out.stdout + out.stderr
    assert f"{n - 1} of {n} chunks replay" in out.stdout and f"chunk {k} at offset {offset}" in out.stdout
    assert (f"replays 0.03 .. {(lo - 1) / 30:.2f} s, {(hi + 1) / 30:.2f} .. 6.00 s; {hi - lo + 1} ticks lost"
            in out.stdout)
    out = sortie("recording", "info", damaged, "--json")
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["ticks"] == TICKS and info["chunks"] == n and info["entities"] == 13
    assert info["damaged_chunks"] == [{"chunk": k, "offset": offset}]
    assert np.allclose(info["replays_s"], [[1 / 30, (lo - 1) / 30], [(hi + 1) / 30, 6.0]], rtol=0, atol=1e-12)
    assert sum(f"offset {offset}" in p for p in info["problems"]) == 1  # listed once
    out = sortie("recording", "info", damaged)
    assert out.returncode == 0 and f"damaged: chunk {k} at offset {offset}" in out.stdout


def test_a_recording_in_the_older_layout_reads_and_reports_entities_a_lost_chunk_described(whole, tmp_path):
    path, newcomer, k = whole.path, whole.newcomer, whole.new
    chunks = old_format_chunks(path)
    old = tmp_path / "old.sortie"
    footerless(path, old, chunks=chunks)
    with Recording(old) as rec, Recording(path) as w:  # whole: it reads as the new layout does
        assert rec.check().problems == [NO_FOOTER] and rec.chunk_count == whole.chunks and rec.last_tick == TICKS
        assert {i: e.name for i, e in rec.entities.items()} == {i: e.name for i, e in w.entities.items()}
        assert np.array_equal(rec.frame(150).q, w.frame(150).q)
    # Chunk k introduced the newcomer: with its head lost nothing else describes it.
    damaged = tmp_path / "old-new.sortie"
    offset = footerless(path, damaged, k, "body", chunks=chunks)  # the older layout's CRC covers the head too
    with Recording(damaged) as rec, Recording(path) as w:
        assert_reads_as_whole_but(rec, w, k, offset, whole.ticks)
        assert list(rec.undescribed) == [newcomer] and f"chunk {k} at offset" in rec.undescribed[newcomer]
        assert rec.entities[newcomer] == type(rec.entities[newcomer])(entity_id=newcomer)
        assert {i: e.name for i, e in rec.entities.items() if i != newcomer} == \
            {i: e.name for i, e in w.entities.items() if i != newcomer}
        assert any(f"chunk {k} at offset {offset} was the first to hold 1 entity" in p and str(newcomer) in p
                   for p in rec.problems)
        from server.replay import ReplayWorld

        world = ReplayWorld(rec)  # a replay shows it, named after its id
        world.show(150, events=False)
        assert newcomer in world.snapshot.ids and world.infos[newcomer][1] == f"entity {newcomer}"
    # Its first chunk lost: the recording starts at the next one, every scenario entity undescribed.
    damaged = tmp_path / "old0.sortie"
    offset = footerless(path, damaged, 0, "head", chunks=chunks)
    start = whole.ticks[1][0]
    with Recording(damaged) as rec, Recording(path) as w:
        assert (rec.first_tick, rec.last_tick) == (start, TICKS) and rec.index.ticks == TICKS - start + 1
        assert np.array_equal(rec.frame(start).q, w.frame(start).q)
        assert f"chunk 0 at offset {offset} fails its CRC: the ticks before tick {start}" in rec.lost[0]
        assert sorted(rec.undescribed) == sorted(i for i in w.entities if i != newcomer)
        assert rec.entities[newcomer].name == "newcomer"  # its own chunk's head describes it
    out = sortie("export", "acmi", damaged, "-o", tmp_path / "old0.acmi")
    assert out.returncode == 0 and "Traceback" not in out.stderr  # written from the chunks that read
    assert f"left out: old0.sortie: chunk 0 at offset {offset}" in out.stderr, out.stderr


def test_resim_compares_around_a_chunk_that_held_no_inputs(whole, tmp_path):
    from server.resim import resimulate

    lo, hi = whole.ticks[whole.quiet]
    damaged = tmp_path / "body.sortie"
    footerless(whole.path, damaged, whole.quiet, "body")  # its head checks, and counts no input
    report = resimulate(damaged)
    lost = hi - lo + 1
    assert report.bit_exact and report.ticks == TICKS - lost and report.ticks_not_compared == lost, report.as_dict()
    assert any(n.startswith(f"ticks {lo}..{hi} not compared") for n in report.notes)


def test_resim_refuses_past_a_chunk_whose_inputs_are_lost(whole, tmp_path):
    from server.resim import resimulate

    k = whole.new
    last = whole.ticks[k][0] - 1  # its inputs were done after this tick or later
    damaged = tmp_path / "head.sortie"
    offset = footerless(whole.path, damaged, k, "head")  # it held the newcomer's first update
    with pytest.raises(DataFormatError, match=rf"cannot re-simulate past t = {last / 30:.3f} s \(tick {last}\)"):
        resimulate(damaged)
    report = resimulate(damaged, until_s=last / 30)  # up to the lost inputs: bit-exact
    assert report.bit_exact and report.ticks == last and report.ticks_not_compared == 0
    out = sortie("resim", damaged)
    assert out.returncode == 2 and "Traceback" not in out.stderr
    assert f"chunk {k} at offset {offset}" in out.stderr and f"--until {last / 30:.3f}" in out.stderr


def test_replay_seeks_around_and_plays_across_a_lost_chunk(whole, tmp_path):
    from client.sim_client import SimClient
    from server.replay import ReplayServer

    k, newcomer = whole.new, whole.newcomer
    lo, hi = whole.ticks[k]
    damaged = tmp_path / "head.sortie"
    offset = footerless(whole.path, damaged, k, "head")
    server = ReplayServer(damaged, speed=1.0, playing=False)
    server.start()
    try:
        with SimClient(server.address) as c:
            c.join("debrief", "observer", observer=(47.4, 9.5, 150_000.0))
            pic = c.watch()
            assert pic.snapshot_received.wait(15.0)
            with pytest.raises(DataFormatError, match=f"chunk {k} at offset {offset}"):
                c.replay(seek_time_s=(lo + hi) / 60)
            st = c.replay(seek_time_s=(hi + 10) / 30)  # after it: shown, the newcomer named as recorded
            assert pic.wait_for(lambda p: abs(p.time_s - st.tick / 30.0) < 1e-9, 15.0)
            assert pic.wait_for(lambda p: newcomer in p.infos, 15.0) and pic.infos[newcomer].name == "newcomer"
            c.replay(seek_time_s=(lo - 15) / 30)
            c.replay(speed=4.0)
            c.replay(play=True)  # across the lost chunk and on
            assert pic.wait_for(lambda p: p.time_s >= (hi + 10) / 30, 20.0)
            # The picture's clock runs on between updates (dead reckoning of world time), so it
            # can pass a tick before the replay's clock does: wait for the replay's own.
            deadline = time.monotonic() + 15.0
            while server.world.tick_count <= hi and time.monotonic() < deadline:
                time.sleep(0.05)
            assert server.error is None and list(server.world.damaged) == [k]
    finally:
        server.stop()


def test_exports_leave_out_a_damaged_chunk_and_say_so(whole, tmp_path):
    """Tacview and glTF exports of a file with a damaged chunk are written from every other
    chunk (exit status 0): the damaged chunk is named with its offset on stderr, and the
    ACMI holds the objects and frames of the chunks around it."""
    k = whole.quiet
    damaged = tmp_path / "body.sortie"
    offset = footerless(whole.path, damaged, k, "body")
    for out_name in ("d.acmi", "d.gltf"):
        out = sortie("export", "acmi" if out_name.endswith("acmi") else "gltf", damaged, "-o",
                     tmp_path / out_name, *([] if out_name.endswith("acmi") else ["--no-terrain"]))
        assert out.returncode == 0, out.stderr
        assert "left out: " in out.stderr and f"chunk {k} at offset {offset}" in out.stderr, out.stderr
        assert (tmp_path / out_name).stat().st_size > 0
    text = (tmp_path / "d.acmi").read_text(encoding="utf-8-sig")
    frames = [float(line[1:]) for line in text.splitlines() if line.startswith("#")]
    lo, hi = whole.ticks[k]
    assert frames and not any(lo / 30 + 1e-6 < t < hi / 30 - 1e-6 for t in frames)  # none inside the lost ticks
    assert any(t < lo / 30 for t in frames) and any(t > hi / 30 for t in frames)  # both sides of it


# -- chunks out of order, written twice or missing; bytes between chunks; the ticks before the
# first chunk (acceptance report "collisions", bugs 3, 4 and 5) ------------------------------------

def rearranged(path, out, order, between=None) -> list[int]:
    """The chunks of ``path`` (a whole recording) in ``order`` (their indices, repeats allowed)
    without the footer into ``out``; ``between``: {position in order: bytes written before that
    chunk}. The offsets the chunks are written at, in ``order``."""
    with Recording(path) as rec:
        data = path.read_bytes()
        offsets, ends = list(rec.index.chunk_offset), list(rec.index.chunk_offset[1:]) + [rec._index_end]
    parts = [data[a:b] for a, b in zip(offsets, ends)]
    out_bytes, starts = bytearray(data[:offsets[0]]), []
    for n, k in enumerate(order):
        out_bytes += (between or {}).get(n, b"")
        starts.append(len(out_bytes))
        out_bytes += parts[k]
    out.write_bytes(bytes(out_bytes))
    return starts


def assert_frames_as_whole(rec, whole_rec, but=(0, -1)) -> None:
    """Every tick's frame of ``rec`` is bit-identical to ``whole_rec``'s, but those of ticks
    ``but`` (first, last), which are a DataFormatError."""
    for tick in range(1, TICKS + 1):
        if but[0] <= tick <= but[1]:
            with pytest.raises(DataFormatError):
                rec.frame(tick)
            continue
        f, g = rec.frame(tick), whole_rec.frame(tick)
        assert f.tick == tick and np.array_equal(f.ids, g.ids) and np.array_equal(f.q, g.q) and f.digest == g.digest


def span_text(lo: int, hi: int) -> str:
    return f"ticks {lo}..{hi} (t = {lo / 30:.2f} .. {hi / 30:.2f} s)"


def test_chunks_out_of_order_in_the_file_read_in_tick_order(whole, tmp_path):
    """Bug 3: chunks k and k + 1 swapped. Each reads alone and its head says its ticks: both are
    indexed in tick order, the later one reported out of place; every tick, input and event reads
    as in the whole file, the ACMI export's time marks go forward, re-simulation is bit-exact."""
    from server.acmi import export_acmi
    from server.resim import resimulate

    k, n = whole.quiet, whole.chunks
    order = list(range(n))
    order[k], order[k + 1] = k + 1, k
    path = tmp_path / "swap.sortie"
    starts = rearranged(whole.path, path, order)
    with Recording(path) as rec, Recording(whole.path) as w:
        assert rec.chunk_count == n and rec.lost == {}
        assert (rec.first_tick, rec.last_tick, rec.index.ticks) == (1, TICKS, TICKS)
        assert list(rec.index.chunk_first_tick) == list(w.index.chunk_first_tick)
        assert list(rec.index.chunk_offset) == starts[:k] + [starts[k + 1], starts[k]] + starts[k + 2:]
        assert_frames_as_whole(rec, w)
        assert events_by_chunk(rec) == events_by_chunk(w)
        assert [r.SerializeToString() for r in rec.inputs()] == [r.SerializeToString() for r in w.inputs()]
        report = rec.check()
        assert report.problems == [
            NO_FOOTER, f"chunk at offset {starts[k + 1]} holds {span_text(*whole.ticks[k])}, before those of the "
            f"chunk at offset {starts[k]} (ticks {whole.ticks[k + 1][0]}..{whole.ticks[k + 1][1]}), which comes "
            "first in the file: a chunk out of place, read in its place"]
        assert report.lost_ticks == 0 and report.damaged_chunks == 0 and report.ticks == TICKS
        assert np.allclose(report.replays, [(1 / 30, TICKS / 30)], rtol=0, atol=1e-12)
        export_acmi(rec, tmp_path / "swap.acmi")
    marks = [float(line[1:]) for line in (tmp_path / "swap.acmi").read_text(encoding="utf-8-sig").splitlines()
             if line.startswith("#")]
    assert len(marks) == TICKS and marks == sorted(marks)
    report = resimulate(path)
    assert report.bit_exact and report.ticks == TICKS and report.ticks_not_compared == 0, report.as_dict()


def test_a_chunk_written_twice_is_read_once(whole, tmp_path):
    """Bug 3: chunk k twice in a row. The copy is reported and left out: the ticks, inputs and
    events are those of the whole file (no tick counted twice)."""
    k, n = whole.new, whole.chunks
    path = tmp_path / "dup.sortie"
    starts = rearranged(whole.path, path, list(range(k + 1)) + list(range(k, n)))
    lo, hi = whole.ticks[k]
    with Recording(path) as rec, Recording(whole.path) as w:
        assert rec.chunk_count == n and rec.lost == {}
        assert (rec.first_tick, rec.last_tick, rec.index.ticks) == (1, TICKS, TICKS)
        assert list(rec.index.chunk_offset) == starts[:k + 1] + starts[k + 2:]
        assert (rec.index.input_count, rec.index.event_count) == (w.index.input_count, w.index.event_count)
        assert_frames_as_whole(rec, w)
        assert events_by_chunk(rec) == events_by_chunk(w)
        assert rec.problems == [
            NO_FOOTER, f"chunk at offset {starts[k + 1]} holds {span_text(lo, hi)}, and the chunk at offset "
            f"{starts[k]}, before it in the file, holds ticks {lo}..{hi}: a copy or a chunk out of place, left out "
            "with its inputs and events"]
    out = sortie("recording", "check", path)
    assert out.returncode == 1 and f"{n} of {n} chunks replay: {TICKS} ticks" in out.stdout, out.stdout


def test_a_missing_chunk_is_lost_ticks(whole, tmp_path):
    """Bug 3: chunk k (it held inputs) not in the file. The gap its ticks leave is indexed as a
    lost chunk named by the chunk after it: its frames are a DataFormatError, its ticks counted
    lost, and re-simulation refused past the tick before it."""
    from server.resim import resimulate

    k, n = whole.new, whole.chunks
    path = tmp_path / "drop.sortie"
    starts = rearranged(whole.path, path, [j for j in range(n) if j != k])
    lo, hi = whole.ticks[k]
    text = (f"chunk {k} at offset {starts[k]} is missing: no chunk in the file holds {span_text(lo, hi)}, so they "
            f"are lost, and the inputs and events recorded with them (the chunk at offset {starts[k]} goes on from "
            f"tick {hi + 1})")
    with Recording(path) as rec, Recording(whole.path) as w:
        assert rec.chunk_count == n and rec.lost == {k: text} and rec.problems == [NO_FOOTER, text]
        assert (rec.first_tick, rec.last_tick, rec.index.ticks) == (1, TICKS, TICKS)
        assert list(rec.index.chunk_first_tick) == list(w.index.chunk_first_tick)
        assert list(rec.index.chunk_offset) == starts[:k] + [starts[k]] + starts[k:]
        assert_frames_as_whole(rec, w, but=(lo, hi))
        with pytest.raises(DataFormatError, match=f"chunk {k} at offset {starts[k]} is missing"):
            rec.frame((lo + hi) // 2)
        report = rec.check()
        assert report.lost_ticks == hi - lo + 1 and report.damaged_chunks == 1
        assert np.allclose(report.replays, [(1 / 30, (lo - 1) / 30), ((hi + 1) / 30, TICKS / 30)], rtol=0, atol=1e-12)
    with pytest.raises(DataFormatError, match=rf"cannot re-simulate past t = {(lo - 1) / 30:.3f} s \(tick {lo - 1}\)"):
        resimulate(path)
    out = sortie("recording", "check", path)
    assert out.returncode == 1 and f"{n - 1} of {n} chunks replay: {TICKS} ticks" in out.stdout, out.stdout
    assert f"; {hi - lo + 1} ticks lost" in out.stdout


def test_a_footer_whose_index_is_out_of_tick_order_is_not_trusted(whole, tmp_path):
    """Bug 3, with a footer: an index whose chunks' first ticks go back (its CRC checks) is a
    damaged footer; the file is walked and reads as the whole one."""
    data = whole.path.read_bytes()
    with Recording(whole.path) as rec:
        index, at = rpb.RecordingIndex(), rec._index_end
        index.CopyFrom(rec.index)

    def with_index(path, index):
        blob = index.SerializeToString()
        path.write_bytes(data[:at] + FRAME.pack(b"INDX", len(blob), 0, zlib.crc32(blob)) + blob
                         + at.to_bytes(8, "little") + b"SORTEND1")

    swapped = rpb.RecordingIndex()
    swapped.CopyFrom(index)
    swapped.chunk_first_tick[1], swapped.chunk_first_tick[2] = index.chunk_first_tick[2], index.chunk_first_tick[1]
    with_index(tmp_path / "index.sortie", swapped)
    with Recording(tmp_path / "index.sortie") as rec, Recording(whole.path) as w:
        assert rec.recovered and rec.problems == [f"damaged footer at offset {at}: its index is not in tick order; "
                                                  "chunks found by walking the file"]
        assert list(rec.index.chunk_first_tick) == list(w.index.chunk_first_tick)
        assert_frames_as_whole(rec, w)
    # In tick order, but chunk 2 said to start 5 ticks late: the index does not match chunk 1's
    # head (it holds fewer ticks than the index gives it), so the footer is not trusted either;
    # the walk reads the file as the whole one.
    late = whole.ticks[2][0] + 5
    index.chunk_first_tick[2] = late
    with_index(tmp_path / "late.sortie", index)
    with Recording(tmp_path / "late.sortie") as rec, Recording(whole.path) as w:
        lo, hi = whole.ticks[1]
        assert rec.recovered and rec.problems == [
            f"the footer's index does not match the file: its chunk 1 at offset {w.index.chunk_offset[1]} "
            f"(ticks {lo}..{late - 1}) holds ticks {lo}..{hi} there; chunks found by walking the file"]
        assert_frames_as_whole(rec, w)


@pytest.mark.parametrize("where", ["middle", "start"])
def test_bytes_between_chunks_of_consecutive_ticks_lose_nothing(whole, tmp_path, where):
    """Bug 4: 17 bytes before chunk k (one that holds inputs, or the first): the chunks either
    side hold consecutive ticks, so no chunk was there (a chunk holds a tick, but the writer's
    last). The bytes are a problem; nothing is indexed lost, and re-simulation runs through."""
    from server.resim import resimulate

    k, n = (whole.new if where == "middle" else 0), whole.chunks
    path = tmp_path / f"garbage-{where}.sortie"
    starts = rearranged(whole.path, path, range(n), {k: b"\0" * 17})
    lo = whole.ticks[k][0]
    sides = (f"the chunks either side hold consecutive ticks ({lo - 1} then {lo})" if k else
             "the chunk after it holds the recording's first tick (1)")
    with Recording(path) as rec, Recording(whole.path) as w:
        assert rec.chunk_count == n and rec.lost == {} and (rec.first_tick, rec.last_tick) == (1, TICKS)
        assert rec.index.input_count == w.index.input_count > 0
        assert rec.problems == [NO_FOOTER, f"chunk at offset {starts[k] - 17} is no chunk frame (no CHNK magic): "
                                           f"17 bytes skipped to the next whole chunk, at offset {starts[k]}; {sides}, "
                                           "so no chunk is lost there (no tick, input or event)"]
        report = rec.check()
        assert report.damaged_chunks == 0 and report.lost_ticks == 0
    report = resimulate(path)
    assert report.bit_exact and report.ticks == TICKS and report.ticks_not_compared == 0, report.as_dict()


def test_the_writers_last_chunk_without_ticks_is_kept_by_the_walk(tmp_path):
    """The writer writes a chunk with no tick last when inputs or events came after the last tick
    (Recorder.close). Footer-less, the walk keeps it after the last tick; with the chunk before
    it lost, its first tick says what that one held."""
    from server.recorder import encode_chunk
    from server.recording import RecordingWriter, quantization_of
    from server.recording_codec import DEFAULT_STEPS
    from server.world import Snapshot

    header = rpb.RecordingHeader(format_version=1, exercise_name="empty last", world_rate_hz=30.0,
                                 quantization=quantization_of(DEFAULT_STEPS))
    path = tmp_path / "whole.sortie"
    writer = RecordingWriter(path, header)
    remove = rpb.InputRecord(tick=6, kind="remove", entity_id=1, reason="after the last tick")
    z3, q = np.zeros((1, 3)), np.array([[1.0, 0.0, 0.0, 0.0]])
    for first in (1, 3, 5, 7):
        snaps = [Snapshot(t / 30, t, np.array([1]), np.array([[4e6 + t, 0.0, 0.0]]), z3, z3, q, z3, *np.zeros((3, 1)))
                 for t in range(first, min(first + 2, 7))]
        c = types.SimpleNamespace(snapshots=snaps, inputs=[remove] if first == 7 else [], events=[],
                                  new_entities=[])
        writer.write_chunk(*encode_chunk(c, DEFAULT_STEPS, 30.0))
    writer.close()
    for damaged in (-1, 2):
        out = tmp_path / f"cut{damaged}.sortie"
        offset = footerless(path, out, damaged, "head") if damaged >= 0 else footerless(path, out)
        with Recording(out) as rec:
            assert rec.chunk_count == 4 and list(rec.index.chunk_first_tick) == [1, 3, 5, 7]
            assert (rec.first_tick, rec.last_tick, rec.index.ticks, rec.index.input_count) == (1, 6, 6, 1)
            assert rec.chunk_head(3).ticks == 0 and [r.reason for r in rec.chunk_body(3)[1].inputs] == [remove.reason]
            assert rec.frame(4).states[0, 0] == 4e6 + 4
            if damaged < 0:
                assert rec.problems == [NO_FOOTER]
            else:
                assert list(rec.lost) == [2] and rec.lost[2].startswith(f"chunk 2 at offset {offset} fails its CRC: "
                                                                        f"{span_text(5, 6)} are lost")


@pytest.mark.parametrize("how", ["head", "missing"])
def test_the_ticks_before_the_first_whole_chunk_are_counted_lost(whole, tmp_path, how):
    """Bug 5: chunk 0 damaged (its head) or not in the file. A recording starts at tick 1: the
    ticks before the first whole chunk stay out of the index's ticks (the recording reads from
    that chunk) and are counted lost, by check and info alike; re-simulation is refused."""
    from server.resim import resimulate

    n, start = whole.chunks, whole.ticks[1][0]
    path = tmp_path / f"first-{how}.sortie"
    if how == "head":
        offset = footerless(whole.path, path, 0, "head")
        text = (f"chunk 0 at offset {offset} fails its CRC: the ticks before tick {start} (t = {start / 30:.2f} s) "
                "are lost, and the inputs and events recorded with them; ")
    else:
        offset = rearranged(whole.path, path, range(1, n))[0]
        text = (f"chunk 0 at offset {offset} is missing: no chunk in the file holds the ticks before tick {start} "
                f"(t = {start / 30:.2f} s), so they are lost, and the inputs and events recorded with them (the "
                f"chunk at offset {offset} goes on from tick {start}; a recording starts at tick 1)")
    with Recording(path) as rec:
        assert rec.chunk_count == n and list(rec.lost) == [0] and rec.lost[0].startswith(text)
        assert (rec.first_tick, rec.last_tick, rec.index.ticks) == (start, TICKS, TICKS - start + 1)
        report = rec.check()
        assert report.lost_ticks == start - 1 and report.damaged_chunks == 1
    out = sortie("recording", "check", path)
    assert out.returncode == 1 and f"replays {start / 30:.2f} .. 6.00 s; {start - 1} ticks lost" in out.stdout, \
        out.stdout
    out = sortie("recording", "info", path, "--json")
    info = json.loads(out.stdout)
    assert out.returncode == 0 and info["lost_ticks"] == start - 1 and info["ticks"] == TICKS - start + 1
    with pytest.raises(DataFormatError, match="cannot re-simulate: .* inputs from the recording's start are lost"):
        resimulate(path)
