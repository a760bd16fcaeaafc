"""Recording, replay with seek, re-simulation and crash safety (issue #6).

Real parts throughout: the alps scenario's world (JSBSim aircraft, ground
vehicles on the embedded SRTM tile) records into real files; replay is served
over gRPC on loopback; the kill -9 test kills a real ``sortie server`` process.

Error bounds: a replayed state is the recorded one within the quantisation
steps (server/recording_codec.py: 0.5 mm, 0.5 mm/s, 5 mm/s^2, 2^-17 per
quaternion component, 5e-5 rad/s); re-simulation is bit-exact (digests of
the exact float64 states equal at every tick); a killed server loses at most
one chunk (1 s of world time) plus the writer's latency.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from server import recording_codec as codec
from server.recorder import Recorder, recording_header
from server.recording import FRAME, Recording
from sortie.errors import DataFormatError, InvalidArgument, NotFound

from conftest import REPO

SCENARIO = REPO / "data" / "scenarios" / "alps.toml"
TICKS = 180  # 6 s at 30 Hz, six 1-s chunks
STEPS = codec.DEFAULT_STEPS
HALF_STEP = STEPS.vector() / 2 * (1 + 1e-9)


def _world():
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain

    scenario = load_scenario(SCENARIO)
    terrain, desc, _ = open_terrain(scenario)
    return build_world(scenario, terrain), scenario, terrain, desc


def record_alps(path, ticks: int = TICKS, chunk_s: float = 1.0, inputs: bool = True):
    """Record the alps world for ``ticks`` with a pilot's inputs; (snapshots' state
    matrices by tick, the world's entity names by id)."""
    from server.sim_server import terrain_spec

    world, scenario, terrain, desc = _world()
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain), chunk_s)
    world.attach_recorder(rec)
    by_name = {e.name: e.id for e in world.entities.values()}
    viper, tank = by_name["viper1"], by_name["tank1"]
    states = {}
    try:
        for k in range(ticks):
            if inputs:
                if k == 20:
                    world.claim(viper, "secret-token", "pilot-1")
                    world.command(viper, "stick", {"pitch": 0.25, "roll": -0.1, "throttle": 1.0})
                    world.command(viper, "stick", {"pitch": 0.3, "roll": -0.2, "throttle": 1.0})  # latest wins
                if k == 50:
                    world.command(viper, "autopilot", {"heading_deg": 120.0, "alt_msl_m": 5000.0})
                    world.claim(tank, "tank-token", "driver-1")
                    world.command(tank, "drive", {"speed_mps": 8.0, "yaw_rate_dps": 3.0})
                if k == 90:
                    world.release(viper, vanished=True)
                if k == 120:
                    world.remove(by_name["radar1"], "destroyed by the test")
            world.tick()
            states[world.tick_count] = codec.state_matrix(world.snapshot)
    finally:
        rec.close()
        world.close()
    return states, {e.id: e.name for e in world.entities.values()}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("rec") / "alps.sortie"
    states, names = record_alps(path)
    return path, states, names


# -- the codec ------------------------------------------------------------------------------------

@settings(max_examples=60, deadline=None)
@given(st.integers(1, 6), st.integers(1, 5), st.data())
def test_codec_round_trips_any_integers_exactly(ticks, entities, data):
    q = data.draw(hnp.arrays(np.int64, (ticks, entities, codec.FIELDS),
                             elements=st.integers(-(1 << 40), 1 << 40)))
    rate = data.draw(st.sampled_from([30.0, 60.0, 1.0, 7.0]))
    out = codec.decode(codec.encode(q, STEPS, rate), ticks, entities, STEPS, rate)
    assert np.array_equal(out, q)


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 5), st.integers(0, 4), st.data())
def test_the_compiled_coder_writes_the_reference_bytes(ticks, entities, data):
    scale = np.array([1e7] * 3 + [400.0] * 3 + [100.0] * 3 + [1.0] * 4 + [10.0] * 3)
    states = data.draw(hnp.arrays(np.float64, (ticks, entities, codec.FIELDS),
                                  elements=st.floats(-1.0, 1.0))) * scale
    want = codec.encode(codec.quantize(states), STEPS, 30.0)
    assert codec.encode_states(states, STEPS, 30.0) == want
    out = codec.decode(want, ticks, entities, STEPS, 30.0)
    assert np.array_equal(out, codec.quantize(states))


def test_gathered_states_are_the_state_matrices_bit_for_bit():
    from server.world import Snapshot

    rng = np.random.default_rng(3)
    for order in (np.arange(1, 8), np.array([5, 2, 9, 1, 7])):  # in order, and not
        snaps = []
        for t in range(3):
            n = order.size
            snaps.append(Snapshot(t / 30, t, order, rng.normal(size=(n, 3)) * 6e6, rng.normal(size=(n, 3)),
                                  rng.normal(size=(n, 3)), rng.normal(size=(n, 4)), rng.normal(size=(n, 3)),
                                  np.zeros(n), np.zeros(n), np.zeros(n)))
        ids, states = codec.gather_states(snaps)
        for t, s in enumerate(snaps):
            want_ids, want = codec.state_matrix(s)
            assert np.array_equal(ids, want_ids) and states[t].tobytes() == want.tobytes()
            assert codec.digest(ids, states[t]) == codec.digest(want_ids, want)


def test_codec_rejects_bytes_of_the_wrong_shape():
    q = np.arange(2 * 3 * codec.FIELDS, dtype=np.int64).reshape(2, 3, codec.FIELDS)
    data = codec.encode(q, STEPS, 30.0)
    with pytest.raises(DataFormatError, match="claims|left over|end before"):
        codec.decode(data, 2, 4, STEPS, 30.0)
    with pytest.raises(DataFormatError):
        codec.decode(data[:-1], 2, 3, STEPS, 30.0)
    with pytest.raises(DataFormatError, match="left over"):
        codec.decode(data + b"\x00", 2, 3, STEPS, 30.0)


def test_absent_entries_take_their_neighbours_and_present_ones_stay():
    q = np.arange(4 * 3 * codec.FIELDS, dtype=np.int64).reshape(4, 3, codec.FIELDS)
    present = np.array([[0, 1, 1], [1, 1, 0], [1, 1, 0], [0, 1, 1]], bool)
    f = codec.fill_absent(q, present)
    assert np.array_equal(f[present], q[present])
    assert np.array_equal(f[0, 0], q[1, 0]) and np.array_equal(f[3, 0], q[2, 0])  # leading gap back, trailing fwd
    assert np.array_equal(f[1, 2], q[0, 2]) and np.array_equal(f[2, 2], q[0, 2])


# -- record and read back -------------------------------------------------------------------------

def test_every_recorded_state_reads_back_within_the_quantisation_step(recorded):
    path, states, _ = recorded
    with Recording(path) as rec:
        assert not rec.recovered and rec.check().ok
        assert (rec.first_tick, rec.last_tick) == (1, TICKS)
        assert rec.last_time_s == pytest.approx(TICKS / 30.0)
        for tick, (ids, exact) in states.items():
            f = rec.frame(tick)
            assert np.array_equal(f.ids, ids), tick
            assert np.all(np.abs(f.states - exact) <= HALF_STEP), tick
            assert f.digest == codec.digest(ids, exact)  # the exact states are pinned by the digest


def test_inputs_events_and_entities_are_recorded(recorded):
    path, _, names = recorded
    with Recording(path) as rec:
        inputs = list(rec.inputs())
        kinds = [(r.tick, r.kind, r.command) for r in inputs]
        assert kinds[:3] == [(20, "claim", ""), (20, "command", "stick"), (20, "command", "stick")]
        assert (90, "release", "") in kinds and (120, "remove", "") in kinds
        claim = inputs[0]
        assert claim.client == "pilot-1" and "secret" not in str(rec.header) + str(inputs)  # no session tokens
        stick = json.loads(inputs[2].values_json)
        assert stick == {"pitch": 0.3, "roll": -0.2, "throttle": 1.0}
        events = [r.event for r in rec.events()]
        assert sum(e.kind == "spawn" for e in events) == 12  # the scenario's spawns, before the first tick
        removed = [e for e in events if e.kind == "remove"]
        assert len(removed) == 1 and json.loads(removed[0].detail_json)["reason"] == "destroyed by the test"
        assert {e.name for e in rec.entities.values()} >= set(names.values()) | {"radar1"}
        assert rec.frame(TICKS).ids.size == rec.frame(1).ids.size - 1  # radar1 gone after tick 120
        assert rec.header.scenario_toml == SCENARIO.read_text()
        assert rec.header.terrain.files[0].sha256 and rec.header.build_id


def test_seek_to_random_times_returns_the_frame_of_that_tick(recorded):
    path, states, _ = recorded
    rng = np.random.default_rng(6)
    with Recording(path) as rec:
        for t in rng.uniform(-1.0, TICKS / 30.0 + 1.0, 40):
            tick = rec.tick_at(t)
            assert tick == min(max(int(np.floor(t * 30.0 + 1e-6)), 1), TICKS)
            rec._cache.clear()  # every seek from a cold cache: one chunk decoded
            f = rec.frame(tick)
            ids, exact = states[tick]
            assert f.tick == tick and np.array_equal(f.ids, ids)
            assert np.all(np.abs(f.states - exact) <= HALF_STEP)


def test_recording_cli_info_and_check(recorded):
    from server.process import sortie_command

    path, _, _ = recorded
    out = subprocess.run([*sortie_command(), "recording", "info", str(path), "--json"], capture_output=True,
                         text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    info = json.loads(out.stdout)
    assert info["ticks"] == TICKS and info["entities"] == 12 and info["footer"]
    assert info["entities_by_kind"] == {"aircraft": 4, "ground": 6, "static": 2}
    assert info["duration_s"] == pytest.approx((TICKS - 1) / 30.0) and info["bytes_per_entity_second"] > 0
    out = subprocess.run([*sortie_command(), "recording", "check", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 0 and "OK" in out.stdout, out.stdout + out.stderr


# -- damaged files --------------------------------------------------------------------------------

def test_missing_and_foreign_files_are_clear_errors(tmp_path):
    with pytest.raises(NotFound, match="does not exist"):
        Recording(tmp_path / "nope.sortie")
    (tmp_path / "x.sortie").write_bytes(b"this is not a recording at all")
    with pytest.raises(DataFormatError, match="not a Sortie recording"):
        Recording(tmp_path / "x.sortie")


def test_truncated_files_replay_up_to_their_last_whole_chunk(recorded, tmp_path):
    path, states, _ = recorded
    data = path.read_bytes()
    with Recording(path) as whole:
        offsets = list(whole.index.chunk_offset)
    header_end = offsets[0]
    # Cut at many places: in the header (a clear error), inside chunks and frames, in the footer.
    for cut in sorted({10, header_end - 3, header_end + 5, offsets[2] + FRAME.size + 7, offsets[3] - 1,
                       offsets[-1] + 2, len(data) - 9, len(data) - 1}):
        p = tmp_path / f"cut{cut}.sortie"
        p.write_bytes(data[:cut])
        if cut < header_end:
            with pytest.raises(DataFormatError):
                Recording(p)
            continue
        with Recording(p) as rec:
            whole_chunks = sum(o + 1 <= cut for o in offsets[1:]) if cut < offsets[-1] else len(offsets) - 1
            assert rec.recovered and rec.chunk_count >= whole_chunks
            report = rec.check()
            assert report.problems and not report.footer
            if rec.chunk_count:
                f = rec.frame(rec.last_tick)
                ids, exact = states[rec.last_tick]
                assert np.all(np.abs(f.states - exact) <= HALF_STEP)


def test_a_corrupt_chunk_is_reported_with_its_offset_and_the_rest_still_reads(recorded, tmp_path):
    path, states, _ = recorded
    data = bytearray(path.read_bytes())
    with Recording(path) as rec:
        offset = rec.index.chunk_offset[2]
    data[offset + FRAME.size + 40] ^= 0xFF  # a bit flip inside chunk 2
    p = tmp_path / "flip.sortie"
    p.write_bytes(bytes(data))
    with Recording(p) as rec:
        assert not rec.recovered  # the footer is intact: the index still finds every chunk
        with pytest.raises(DataFormatError, match=f"chunk 2 at offset {offset}"):
            rec.frame(2 * 30 + 5)
        f = rec.frame(4 * 30 + 5)  # other chunks are unaffected
        assert np.all(np.abs(f.states - states[4 * 30 + 5][1]) <= HALF_STEP)
        report = rec.check()
        assert len(report.problems) == 1 and str(offset) in report.problems[0]
    from server.process import sortie_command

    out = subprocess.run([*sortie_command(), "recording", "check", str(p)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 1 and f"offset {offset}" in out.stdout


def test_a_recording_is_never_overwritten(recorded):
    path, _, _ = recorded
    from server.recording import RecordingWriter
    from sortie.v1 import recording_pb2 as rpb

    with pytest.raises(FileExistsError):
        RecordingWriter(path, rpb.RecordingHeader())


def test_a_chunk_closes_after_chunk_s_of_wall_time_when_the_clock_is_slow(tmp_path):
    from server.sim_server import terrain_spec

    world, scenario, terrain, desc = _world()
    rec = Recorder(tmp_path / "slow.sortie", recording_header(SCENARIO, scenario, world, desc,
                                                              terrain_spec(scenario), terrain), chunk_s=0.2)
    world.attach_recorder(rec)
    try:
        world.tick()  # one tick, then the clock stalls: the writer thread closes the chunk on its own
        deadline = time.monotonic() + 5.0
        while rec.chunks_written == 0 and time.monotonic() < deadline:
            time.sleep(0.02)
        assert rec.chunks_written == 1
        assert rec.chunks_coded == 1  # coded before it was synced (bench/recording.py times both)
        with Recording(tmp_path / "slow.sortie") as r:  # readable while still being written
            assert r.recovered and r.last_tick == 1
    finally:
        rec.close()
        world.close()


# -- re-simulation --------------------------------------------------------------------------------

def test_resimulation_is_bit_exact(recorded):
    from server.resim import resimulate

    path, _, _ = recorded
    report = resimulate(path)
    assert report.ticks == TICKS and report.bit_exact, report.as_dict()
    assert report.max_abs_diff_m == 0.0 and report.first_divergence is None
    assert report.same_build and report.same_terrain


def test_resimulation_on_other_terrain_reports_the_first_divergence(recorded, tmp_path, hgt_alps):
    from server.resim import resimulate

    path, _, _ = recorded
    raised = np.fromfile(hgt_alps, ">i2")
    raised = np.where(raised > -32768, raised + 5, raised).astype(">i2")  # the whole tile 5 m higher
    other = tmp_path / "N47E009.hgt"
    raised.tofile(other)
    report = resimulate(path, dem=[other], until_s=1.0)
    assert not report.same_terrain and not report.bit_exact
    d = report.first_divergence
    assert d is not None and d.tick == 1 and d.field.startswith(("ecef", "vel", "acc", "quat", "rate"))
    assert 0.5 < report.max_abs_diff_m < 20.0  # ground vehicles follow the raised terrain
    assert "DEM SHA-256 mismatch" in " ".join(report.notes)


def test_resim_cli_reports_bit_exact(recorded, tmp_path):
    from server.process import sortie_command

    path, _, _ = recorded
    out = subprocess.run([*sortie_command(), "resim", str(path), "--until", "2", "--json", str(tmp_path / "r.json")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    assert "bit-exact" in out.stdout
    assert json.loads((tmp_path / "r.json").read_text())["bit_exact"] is True


def record_over_service(path, serve_args: list, ticks: int = 45):
    """Record the alps scenario for ``ticks`` over a `sortie terrain serve` of ``serve_args``,
    then stop the service; its GetMetadata dem_files."""
    from client.terrain_client import TerrainClient
    from server.process import ServiceProcess
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, terrain_spec

    scenario = load_scenario(SCENARIO)
    with ServiceProcess(["terrain", "serve", *serve_args]) as service:
        with TerrainClient(service.address) as client:
            dem_files = client.metadata()["dem_files"]
        terrain, desc, _ = open_terrain(scenario, service=service.address)
        world = build_world(scenario, terrain)
        rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc,
                                              terrain_spec(scenario, service=service.address), terrain), 1.0)
        world.attach_recorder(rec)
        try:
            for _ in range(ticks):
                world.tick()
        finally:
            rec.close()
            world.close()
    return dem_files


def test_a_sortie_recorded_over_a_terrain_service_resimulates_from_its_files(tmp_path, hgt_alps):
    """A terrain service names the DEM files it read with their SHA-256 (GetMetadata); a
    recording over it keeps them. With the service gone, re-simulation opens those files in
    process, rebuilds the insets the service served from their recorded parameters, and is
    bit-exact. Changed bytes in a file are a SHA-256 mismatch: same_terrain is False."""
    import shutil

    from server.resim import resimulate
    from server.scenario import load_scenario
    from terrain.dem import file_identity

    dem = tmp_path / "N47E009.hgt"
    shutil.copyfile(hgt_alps, dem)
    path = tmp_path / "served.sortie"
    areas = load_scenario(SCENARIO).target_areas
    assert areas
    assert record_over_service(path, ["--dem", str(dem), "--insets", str(SCENARIO)]) == [file_identity(dem)]
    with Recording(path) as r:
        assert r.header.terrain.description.startswith("service:")
        assert [f.sha256 for f in r.header.terrain.files] == [file_identity(dem)["sha256"]]
    report = resimulate(path)
    assert report.ticks == 45 and report.bit_exact and report.same_terrain, report.as_dict()
    notes = " ".join(report.notes)
    assert "SHA-256 checked" in notes and f"{len(areas)} insets rebuilt" in notes
    heights = np.fromfile(dem, ">i2")
    heights[heights.size // 2] += 1
    heights.tofile(dem)
    report = resimulate(path, until_s=0.5)
    assert not report.same_terrain and "DEM SHA-256 mismatch" in " ".join(report.notes)
    dem.unlink()
    with pytest.raises(NotFound, match="--terrain ADDRESS"):
        resimulate(path)


def test_a_sortie_over_a_service_of_a_store_and_a_procedural_world_resimulates_without_it(tmp_path, hgt_alps):
    """The same for a service of a terrain store over a procedural world: both rebuilt in
    process from the recorded sources (the store's path, the world's seed), every recorded
    field of their descriptions checked; no insets (the scenario's are not the service's)."""
    from server.resim import resimulate
    from terrain.store_import import import_dems

    store = tmp_path / "alps-store"
    import_dems([hgt_alps], store, progress=False)
    path = tmp_path / "served.sortie"
    assert record_over_service(path, ["--store", str(store), "--procedural", "5"], ticks=30) == []
    report = resimulate(path)
    assert report.ticks == 30 and report.bit_exact and report.same_terrain, report.as_dict()
    notes = " ".join(report.notes)
    assert "1 terrain stores" in notes and "procedural world, seed 5" in notes and "insets" not in notes
    from server.resim import sources_match
    from server.terrain_cli import build_terrain

    with Recording(path) as r:  # another seed is another terrain, and says where
        same, why = sources_match(r, build_terrain([], 6, [str(store)]))
    assert not same and "differs from the recording's in seed: 6 here, 5 recorded" in why[0]


def test_take_over_starts_from_the_recorded_state_with_the_agent_free(recorded):
    from server.resim import take_over

    path, states, names = recorded
    world, inputs, _ = take_over(path, 100 / 30.0, "tank1")
    try:
        assert world.tick_count == 100
        ids, exact = codec.state_matrix(world.snapshot)
        with Recording(path) as rec:
            assert codec.digest(ids, exact) == rec.frame(100).digest  # bit for bit the recorded instant
        tank = next(e for e in world.entities.values() if e.name == "tank1")
        assert tank.owner is None and tank.controllable  # the recorded driver let go: free to claim
        world.claim(tank.id, "me", "new-driver")
        world.command(tank.id, "drive", {"speed_mps": 0.0, "yaw_rate_dps": 0.0})
        for _ in range(30):  # the others go on with their recorded inputs (radar1 removed at 120)
            inputs.apply(world)
            world.tick()
        assert "radar1" not in {e.name for e in world.entities.values()}
    finally:
        world.close()
    with pytest.raises(InvalidArgument, match="no agent of this name"):
        take_over(path, 1.0, "nobody")


# -- replay over gRPC -----------------------------------------------------------------------------

def test_replay_serves_the_recording_through_the_live_api_with_controls(recorded):
    import grpc
    from grpc_reflection.v1alpha.proto_reflection_descriptor_database import ProtoReflectionDescriptorDatabase

    from client.sim_client import SimClient
    from server.replay import ReplayServer

    path, states, _ = recorded
    server = ReplayServer(path, speed=2.0, playing=False)
    server.start()
    try:
        with SimClient(server.address) as c:
            c.join("debrief", "observer", observer=(47.4, 9.5, 150_000.0))
            pic = c.watch()
            assert pic.snapshot_received.wait(10.0)
            assert pic.time_scale == 0.0  # paused: the picture's clock stands still
            for t in (4.0, 1.5, 5.9):  # forward and backward seeks, paused
                st = c.replay(seek_time_s=t)
                tick = int(np.floor(t * 30.0 + 1e-6))
                assert st.tick == tick and not st.playing
                assert pic.wait_for(lambda p: abs(p.time_s - tick / 30.0) < 1e-9, 5.0)
                time.sleep(0.2)
                ids, pos, _ = pic.state(tick / 30.0)
                rids, exact = states[tick]
                k = np.searchsorted(rids, ids)
                assert np.array_equal(rids[k], ids) and len(ids) == len(rids)
                assert np.abs(pos - exact[k, 0:3]).max() <= 0.5e-3 + 1e-6  # the recorded position itself
            st = c.replay(step_ticks=-10)
            assert st.tick == 167 and not st.playing
            with pytest.raises(InvalidArgument, match="speed"):
                c.replay(speed=65.0)
            with pytest.raises(InvalidArgument, match="observers and gateways only"):
                SimClient(server.address).join("pilot", "pilot")
            assert c.world().clock == "paused"
            c.replay(seek_time_s=0.0)
            c.replay(speed=8.0)
            st = c.replay(play=True)
            assert st.playing and c.world().time_scale == 8.0
            assert pic.wait_for(lambda p: p.time_scale == 8.0, 5.0)  # every stream told the new rate
            assert pic.wait_for(lambda p: p.time_s >= 5.0, 10.0)  # 6 s of world time in ~0.75 s
            time.sleep(0.2)
            with Recording(path) as rec:  # dead-reckoned picture within the thresholds of the recording
                t = pic.time_s
                ids, pos, _ = pic.state(t)
                f = rec.frame(rec.tick_at(t))
                k = np.searchsorted(f.ids, ids)
                assert np.abs(pos - f.states[k, 0:3]).max() < 2.0
        channel = grpc.insecure_channel(server.address)
        services = set(ProtoReflectionDescriptorDatabase(channel).get_services())
        assert {"sortie.v1.SimulationService", "sortie.v1.ReplayService", "grpc.health.v1.Health"} <= services
        channel.close()
    finally:
        server.stop()


# -- crash safety ---------------------------------------------------------------------------------

def test_kill_9_loses_at_most_one_chunk_and_the_rest_replays(tmp_path):
    from client.sim_client import SimClient
    from server.process import free_port, sortie_command, wait_serving

    port = free_port()
    path = tmp_path / "killed.sortie"
    proc = subprocess.Popen([*sortie_command(), "server", "--scenario", str(SCENARIO), "--port", str(port),
                             "--record", str(path), "--aircraft-workers", "0"], stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)
    try:
        wait_serving(f"127.0.0.1:{port}", proc, timeout_s=60.0)
        with SimClient(f"127.0.0.1:{port}") as c:
            while c.world().time_s < 3.5:
                time.sleep(0.05)
            t_polled = c.world().time_s
            t0 = time.monotonic()
            os.killpg(proc.pid, signal.SIGKILL)
            world_time_at_kill = t_polled + (time.monotonic() - t0)
        proc.wait(10.0)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
    with Recording(path) as rec:
        assert rec.recovered and rec.chunk_count >= 2
        lost = world_time_at_kill - rec.last_time_s
        assert -0.05 < lost <= 1.0 + 0.25, lost  # one 1-s chunk, plus the poll's and writer's latency
        report = rec.check()
        assert report.ticks == rec.last_tick and all("footer" in p or "cut short" in p for p in report.problems)
        rec.frame(rec.last_tick)
    out = subprocess.run([*sortie_command(), "recording", "check", str(path)], capture_output=True, text=True,
                         timeout=60)
    assert out.returncode == 1 and "footer no" in out.stdout and "chunks replay" in out.stdout


def test_take_over_cli_serves_live_with_the_agent_free_to_drive(recorded, tmp_path):
    from client.sim_client import SimClient
    from server.process import ServiceProcess

    path, states, _ = recorded
    with ServiceProcess(["resim", str(path), "--take-over", "3", "--agent", "tank1", "--no-record"],
                        log=tmp_path / "t.log") as p, \
            SimClient(p.address) as driver:
        agent = driver.join("new-driver", "driver", agent_name="tank1")
        assert driver.world().time_s >= 3.0
        with driver.controls() as stream:
            stream.drive(speed_mps=10.0, yaw_rate_dps=0.0)
            pic = driver.watch()
            assert pic.wait_for(lambda q: agent in q.infos, 10.0)
            _, start, _ = pic.state(ids=[agent])
            time.sleep(2.0)
            _, later, _ = pic.state(ids=[agent])
        moved = float(np.linalg.norm(later - start))
        assert 5.0 < moved < 40.0, moved  # ~2 s at up to 10 m/s (the tank accelerates)
        with pytest.raises(InvalidArgument, match="not free"):
            SimClient(p.address).join("second", "driver", agent_name="tank1")


def test_events_after_the_last_whole_chunk_are_kept_in_a_chunk_without_ticks(tmp_path):
    from server.sim_server import terrain_spec

    world, scenario, terrain, desc = _world()
    path = tmp_path / "tail.sortie"
    rec = Recorder(path, recording_header(SCENARIO, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    try:
        for _ in range(30):  # exactly one chunk, closed by its last tick
            world.tick()
        world.emit("leave", 0, client="last-one")  # after it: a chunk of no ticks
    finally:
        rec.close()
        world.close()
    with Recording(path) as r:
        assert r.check().ok and r.chunk_count == 2 and (r.first_tick, r.last_tick) == (1, 30)
        assert r.frame(r.tick_at(99.0)).tick == 30
        assert [e.event.kind for e in r.events()][-1] == "leave"
