"""The world's external entities held as columns (server.external.ExternalTable) and its name
index: 5,000 entities added through a gateway stream slowed the world clock to 0.68x real time,
most of each tick rebuilding the external columns from the states (11 ms a tick at 5,000) and
each add scanning every entity's name (3 s over the 5,000).

The table must be the mapping it replaced, exactly: the same states in the same order (the
order the entities came; a replaced state keeps its place, one removed and added again goes
last), its columns the states' values bit for bit. Speed is `sortie bench`'s business; these
tests hold the behaviour."""

from __future__ import annotations

import numpy as np
import pytest

from server.external import ExternalTable, external_state
from server.world import AIRCRAFT, World
from sortie.errors import InvalidArgument
from tests.test_external import alps  # noqa: F401 - the fixture


def _state(rng, t0: float):
    pos = (6378137.0 + 1000.0 * rng.random(), 1000.0 * rng.normal(), 1000.0 * rng.normal())
    q = rng.normal(size=4)
    return external_state(t0, pos, tuple(rng.normal(size=3)), tuple(rng.normal(size=3)), tuple(q / np.linalg.norm(q)),
                          tuple(0.01 * rng.normal(size=3)), int(rng.integers(1, 10)))


def test_the_table_is_the_mapping_it_replaced_with_its_states_as_columns():
    rng = np.random.default_rng(32)
    table, ref = ExternalTable(), {}
    for k in range(4000):
        eid = int(rng.integers(0, 300))
        if rng.random() < 0.7:
            s = _state(rng, float(k))
            table[eid] = s
            ref[eid] = s
        else:
            assert table.pop(eid) is ref.pop(eid, None)
        assert len(table) == len(ref) and list(table) == list(ref) and bool(len(table)) == bool(ref)
        if k % 97 == 0 or k == 3999:
            ids, t0, pos, vel, acc, quat, rates, algorithm = table.columns()
            assert ids.tolist() == list(ref)
            states = list(ref.values())
            assert t0.tolist() == [s.t0_s for s in states]
            assert algorithm.tolist() == [s.algorithm for s in states]
            for col, field in ((pos, "ecef_m"), (vel, "vel_ecef_mps"), (acc, "acc_ecef_mps2"),
                               (quat, "quat_ecef2body"), (rates, "body_rates_rps")):
                assert [tuple(r) for r in col.tolist()] == [getattr(s, field) for s in states]
    assert all(table[e] is ref[e] for e in ref) and all(e in table for e in ref)
    assert 10_000 not in table and table.pop(10_000, "none") == "none"


def test_names_stay_unique_and_come_free_when_their_entity_goes(alps):
    w = World(alps)
    w.spawn_static("sam", "sam_site", 47.35, 9.45)
    pos = (4322000.0, 700000.0, 4620000.0)
    state = external_state(0.0, pos, (0, 0, 0), (0, 0, 0), (1, 0, 0, 0), (0, 0, 0), 1)
    w.publish_external("e:1", "tok", state, "bandit", AIRCRAFT, "t", "red")
    with pytest.raises(InvalidArgument) as e:
        w.publish_external("e:2", "tok", state, "sam", AIRCRAFT, "t", "red")
    assert e.value.field == "name" and "sam" in str(e.value)
    w.publish_external("e:1", "tok", remove=True)
    w.publish_external("e:3", "tok", state, "bandit", AIRCRAFT, "t", "red")  # its name is free again
    w.tick()
    ext = [i for i in w.snapshot.ids.tolist() if w.entities[i].external_id]
    assert [w.entities[i].name for i in ext] == ["bandit"] and w.entities[ext[0]].external_id == "e:3"
