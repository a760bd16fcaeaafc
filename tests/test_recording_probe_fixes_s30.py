"""The recordings acceptance probe's findings, round 30 (/tmp/probes/recordings): the DIS gateway over
a fast replay (Collision PDUs with velocity 0, a wreck's Entity State PDU without the destroyed bit),
and a footer index that points at the wrong chunk.

Real parts: three pairs of JSBSim f16s fly head-on over the embedded SRTM tile (a scenario file, the
server's world, its recorder) and collide at about 2, 2.8 and 3.6 s; the recording is replayed by
`ReplayServer` over gRPC on loopback (ports 52810-52811) and turned into DIS PDUs by a real
`DisGateway`, read from a real UDP socket on the loopback broadcast address; the damaged copy of the
recording has its first two chunks swapped byte for byte, its footer kept.

Bounds: a Collision PDU's velocity is the issuer's recorded velocity at the collision's tick within
0.5 m/s (float32 on the wire; the gateway's estimate from the last state sent before the collision,
dead-reckoned to it; seen: 0.04-0.07 m/s), where the probe saw 0 against 250 m/s; every Entity
State PDU of a wreck at rest (speed under 1 m/s: these aircraft fly at 250 m/s until they collide)
carries the destroyed appearance.
"""

from __future__ import annotations

import json
import math
import socket
import time

import numpy as np
import pytest

from server import dis
from server.recording import Recording
from conftest import EMBEDDED_DEM
from test_dis import dis_socket

REPLAY_PORT, DIS_PORT = 52810, 52811
PAIR_HALF_GAPS_M = (500.0, 700.0, 900.0)  # each pair's aircraft this far either side of its centre
SPEED_MPS = 250.0
TICKS = 150  # 5 s at 30 Hz: five 1-s chunks; the last pair collides at about 3.6 s
REPLAY_SPEED = 8.0  # the probe's: 12 ticks a network update
COLLISION_VELOCITY_TOLERANCE_MPS = 0.5
AT_REST_MPS = 1.0


def _scenario_text() -> str:
    lines = [f"""[exercise]
name = "Head-on pairs"
start_time = 2026-06-15T07:00:00Z
world_rate_hz = 30
network_rate_hz = 20
clock = "fast"
duration_s = 60.0
[terrain]
dem = ["{EMBEDDED_DEM / 'N47E009.hgt'}"]
geoid_undulation_m = 48.0
"""]
    for p, half in enumerate(PAIR_HALF_GAPS_M):
        lat = 47.30 + 0.05 * p  # 5.6 km between pairs
        d_lon = half / (111_200.0 * math.cos(math.radians(lat)))
        for side, lon, heading in (("w", 9.30 - d_lon, 90.0), ("e", 9.30 + d_lon, 270.0)):
            lines.append(f"""[[agents]]
name = "p{p}{side}"
kind = "aircraft"
type = "f16"
coalition = "{'blue' if side == 'w' else 'red'}"
lat_deg = {lat}
lon_deg = {lon}
alt_m = 4000.0
alt_ref = "msl"
heading_deg = {heading}
speed_mps = {SPEED_MPS}
[agents.autopilot]
hold = {{heading_deg = {heading}, alt_msl_m = 4000.0, speed_mps = {SPEED_MPS}}}
""")
    return "\n".join(lines)


def _record(path, scenario_path, text: str, ticks: int):
    """A recording (``path``) of ``ticks`` world ticks of the scenario ``text``, made in process."""
    from server.recorder import Recorder, recording_header
    from server.scenario import load_scenario
    from server.sim_server import build_world, open_terrain, terrain_spec

    scenario_path.write_text(text)
    scenario = load_scenario(scenario_path)
    terrain, desc, _ = open_terrain(scenario)
    world = build_world(scenario, terrain)
    rec = Recorder(path, recording_header(scenario_path, scenario, world, desc, terrain_spec(scenario), terrain), 1.0)
    world.attach_recorder(rec)
    try:
        for _ in range(ticks):
            world.tick()
    finally:
        rec.close()
        world.close()
    return path


@pytest.fixture(scope="module")
def head_on(tmp_path_factory):
    """The recording of the three pairs (path), and its collision events (tick, entity, other)."""
    d = tmp_path_factory.mktemp("head_on")
    path = _record(d / "head-on.sortie", d / "head-on.toml", _scenario_text(), TICKS)
    with Recording(path) as r:
        collisions = [(int(e.tick), int(e.event.entity_id), int(json.loads(e.event.detail_json)["other_id"]))
                      for e in r.events() if e.event.kind == "collision"]
    assert len(collisions) == 6 and len({t for t, _, _ in collisions}) == 3, collisions  # each pair, its own tick
    return path, collisions


def _receive(sock, seconds: float, until=None) -> list:
    """The PDUs (decoded: Entity State and Collision) that arrive within ``seconds``, in order."""
    out, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline and not (until and until(out)):
        try:
            data = sock.recv(65536)
        except socket.timeout:
            continue
        for d in dis.split_datagram(data):
            if d[2] == dis.PDU_TYPE_COLLISION:
                out.append(dis.decode_collision_pdu(d))
            elif d[2] == dis.PDU_TYPE_ENTITY_STATE:
                out.append(dis.decode_pdu(d))
    return out


# -- 1: the DIS gateway over a fast replay ----------------------------------------------------------

def test_dis_over_a_fast_replay_sends_collision_velocities_and_wrecks_as_live(head_on):
    """The probe's case at 8x (12 ticks a network update): each Collision PDU carries its issuer's
    velocity at the collision (the recorded one at the collision's tick, within 0.5 m/s; the probe
    saw (0, 0, 0) in 2 runs of 3), and no Entity State PDU shows a wreck at rest without the
    destroyed appearance (the probe saw appearance 0 with velocity 0 before the Collision PDU)."""
    from client.sim_client import SimClient
    from server.dis_gateway import DisGateway
    from server.replay import ReplayServer

    path, collisions = head_on
    with Recording(path) as r:
        truth = {}
        for tick, issuer, _ in collisions:
            f = r.frame(tick)
            truth[issuer] = f.states[int(np.searchsorted(f.ids, issuer)), 3:6]
        ids = sorted(r.entities)
    replay = ReplayServer(path, f"127.0.0.1:{REPLAY_PORT}", speed=REPLAY_SPEED, playing=False)
    peer = dis_socket(DIS_PORT)
    replay.start()
    try:
        with DisGateway(replay.address, port=DIS_PORT, exercise=7, site=5, application=30):
            seen = _receive(peer, 10.0, until=lambda ps: {p.entity_id[2] for p in ps
                                                          if isinstance(p, dis.EntityStatePdu)} >= set(ids))
            assert {p.entity_id[2] for p in seen if isinstance(p, dis.EntityStatePdu)} >= set(ids)
            with SimClient(replay.address) as ctl:
                ctl.join("ctl", "observer", observer=(47.3, 9.3, 1.0))
                ctl.replay(play=True)
                pdus = _receive(peer, TICKS / 30.0 / REPLAY_SPEED + 3.0,
                                until=lambda ps: sum(isinstance(p, dis.CollisionPdu) for p in ps) >= 6
                                and not replay.playing and replay.world.tick_count == replay.rec.last_tick)
                pdus += _receive(peer, 0.5)
    finally:
        peer.close()
        replay.stop(0.5)
    hits = [p for p in pdus if isinstance(p, dis.CollisionPdu)]
    assert sorted((p.issuing_entity_id[2], p.colliding_entity_id[2]) for p in hits) == \
        sorted((issuer, other) for _, issuer, other in collisions)
    for p in hits:
        v = np.array(p.velocity)
        error = float(np.linalg.norm(v - truth[p.issuing_entity_id[2]]))
        assert error <= COLLISION_VELOCITY_TOLERANCE_MPS, (p.issuing_entity_id, p.velocity,
                                                           truth[p.issuing_entity_id[2]])
    states = [p for p in pdus if isinstance(p, dis.EntityStatePdu)]
    wrecks = [p for p in states if math.hypot(*p.linear_velocity) < AT_REST_MPS]
    assert {p.entity_id[2] for p in wrecks} == set(ids)  # every wreck came to rest in the replay
    undamaged = [(p.entity_id[2], hex(p.appearance)) for p in wrecks
                 if p.appearance & dis.APPEARANCE_DESTROYED != dis.APPEARANCE_DESTROYED]
    assert not undamaged, f"wrecks at rest sent without the destroyed appearance: {undamaged}"


def test_fast_replay_publishes_each_collision_tick_with_its_events_before_any_later_tick(head_on):
    """The replay's half, deterministic: playing at 8x, every tick with a collision or a crash is
    published (its states, its events already in the log) and no later tick is published in the same
    network update, so a receiver of both streams is never handed the wreck at rest with the event
    (before: the update jumped 12 ticks, past the collision, events and later states together)."""
    from server.replay import ReplayServer

    path, collisions = head_on
    replay = ReplayServer(path, f"127.0.0.1:{REPLAY_PORT}", speed=REPLAY_SPEED, playing=True)
    published, original = [], replay.publisher.publish

    def publish(snap, *args):
        published.append((snap.tick, time.monotonic(), replay.world.events_total))
        return original(snap, *args)

    replay.publisher.publish = publish
    replay.start()
    try:
        deadline = time.monotonic() + TICKS / 30.0 / REPLAY_SPEED + 5.0
        while time.monotonic() < deadline and (replay.playing or replay.world.tick_count != replay.rec.last_tick):
            time.sleep(0.05)
    finally:
        replay.stop(0.5)
    ticks = [t for t, _, _ in published]
    assert ticks[-1] == TICKS
    events_by_tick = {}
    with Recording(path) as r:
        for e in r.events():
            events_by_tick[int(e.tick)] = events_by_tick.get(int(e.tick), 0) + 1
    for k in sorted({t for t, _, _ in collisions}):
        assert k in ticks, f"collision tick {k} never published (published {ticks})"
        i = ticks.index(k)
        # Its events (and every one since the first tick shown) were in the log when it was published.
        assert published[i][2] >= sum(n for t, n in events_by_tick.items() if ticks[0] < t <= k)
        # The next tick published came a network update later, not in the same one.
        if i + 1 < len(published):
            assert published[i + 1][1] - published[i][1] >= 0.5 / replay.config.network_rate_hz


# -- 2: a footer index that points at the wrong chunk -----------------------------------------------

def _swapped(src: bytes, offsets: list) -> bytes:
    """The recording's bytes with its first two chunks swapped, the footer kept (it still ends the
    file at the same offset: the two chunks' bytes add up to the same length)."""
    a, b, c = offsets[0], offsets[1], offsets[2]
    return src[:a] + src[b:c] + src[a:b] + src[c:]


def test_check_walks_a_recording_whose_footer_points_at_the_wrong_chunk(head_on, tmp_path):
    """Chunks 0 and 1 swapped, the footer kept: the index's offsets now point at each other's
    chunk. The footer is not trusted (a problem naming chunk 0, its offset and the ticks it holds);
    the walk reads every chunk in its place: no tick lost, every frame the original's (before:
    "frame(1)" raised "holds ticks 31..60, not tick 1" while check said the chunk replayed)."""
    from server.recording_cli import check_command

    path, _ = head_on
    with Recording(path) as r:
        assert not r.recovered and r.check().ok
        offsets = list(r.index.chunk_offset)
        original = {t: r.frame(t).q for t in range(r.first_tick, r.last_tick + 1)}
        events = [e.SerializeToString() for e in r.events()]
    damaged = tmp_path / "swapped.sortie"
    damaged.write_bytes(_swapped(path.read_bytes(), offsets))
    with Recording(damaged) as r:
        assert r.recovered
        report = r.check()
        assert not report.ok and report.lost_ticks == 0 and report.damaged_chunks == 0
        assert report.replays == [(1 / 30.0, TICKS / 30.0)]
        assert any("footer's index does not match the file" in p and f"chunk 0 at offset {offsets[0]}" in p
                   and "holds ticks 30..58" in p for p in report.problems), report.problems
        assert any("out of place, read in its place" in p for p in report.problems), report.problems
        for t, q in original.items():
            assert np.array_equal(r.frame(t).q, q), t
        assert [e.SerializeToString() for e in r.events()] == events

    class Args:
        file = str(damaged)

    assert check_command(Args()) == 1  # damaged, but every tick replays


def test_a_footer_that_matches_the_chunks_is_still_trusted(head_on, tmp_path):
    """A chunk whose body is damaged, at its place: the footer's index is used (no walk), and the
    chunk is reported damaged with its offset, as before."""
    path, _ = head_on
    src = bytearray(path.read_bytes())
    with Recording(path) as r:
        offsets = list(r.index.chunk_offset)
    src[offsets[2] + (offsets[3] - offsets[2]) // 2 + 40] ^= 0x10  # inside chunk 2's compressed body
    damaged = tmp_path / "flipped.sortie"
    damaged.write_bytes(bytes(src))
    with Recording(damaged) as r:
        assert not r.recovered
        assert not any("footer" in p for p in r.problems), r.problems
        report = r.check()
        assert report.damaged_chunks == 1 and report.lost_ticks == 29
        assert any(f"chunk 2 at offset {offsets[2]}" in p for p in report.problems), report.problems


# -- a recording of a very low network rate, replayed ----------------------------------------------

@pytest.mark.parametrize("rate", [1e-300, 0.001])
def test_a_replay_of_a_low_network_rate_gives_a_joiner_its_snapshot(tmp_path, rate):
    """A scenario may set any network rate above 0. Old: the replay clock waited a whole network
    period between updates (Event.wait(1e300) raised OverflowError and stopped the clock; at
    0.001 Hz a joiner got no snapshot in 3 s). Bound: the snapshot within 3 wall s."""
    from client.sim_client import SimClient
    from server.replay import ReplayServer

    text = _scenario_text().replace("network_rate_hz = 20", f"network_rate_hz = {rate!r}")
    path = _record(tmp_path / "low.sortie", tmp_path / "low.toml", text, 30)
    replay = ReplayServer(path, "127.0.0.1:0", speed=1.0, playing=True)
    replay.start()
    try:
        with SimClient(replay.address) as obs:
            obs.join("obs", "observer", observer=(47.35, 9.3, 50_000.0))
            pic = obs.watch()
            assert pic.snapshot_received.wait(3.0), "no snapshot within 3 wall s"
            assert len(pic.infos) == 2 * len(PAIR_HALF_GAPS_M)
        assert replay.error is None, replay.error
    finally:
        replay.stop(0.5)
