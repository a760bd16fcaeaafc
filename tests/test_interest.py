"""Interest management (server/interest.py) against a brute-force reading of its rule:
|p_j - c_i| <= r_i, kept out to r_i (1 + HYSTERESIS) while already relevant, the
receiver's own agent always, nothing for a negative radius; and the per-receiver
entered / left / updated columns the publisher fans out."""

import numpy as np
import pytest

from server.interest import HYSTERESIS, changes, relevant
from sortie.errors import InvalidArgument


def _reference(c, r, p, prev, own, due):
    d = np.linalg.norm(p[None, :, :] - c[:, None, :], axis=2)
    now = (d <= r[:, None]) | (prev & (d <= r[:, None] * (1.0 + HYSTERESIS)))
    now &= (r >= 0.0)[:, None]
    for i, k in enumerate(own):
        if k >= 0:
            now[i, k] = True
    return now, now & ~prev, prev & ~now, now & prev & due[None, :]


@pytest.mark.parametrize("seed", range(5))
def test_changes_match_the_rule_for_every_receiver(seed):
    rng = np.random.default_rng(seed)
    m, n = 7, 300
    base = np.array([4.3e6, 0.7e6, 4.6e6])  # ECEF metres, about the Alps
    p = base + rng.uniform(-60e3, 60e3, (n, 3))
    c = base + rng.uniform(-60e3, 60e3, (m, 3))
    r = rng.uniform(10e3, 50e3, m)
    r[2] = -1.0  # no centre: its own agent only
    prev = rng.random((m, n)) < 0.3
    own = rng.integers(-1, n, m)
    due = rng.random(n) < 0.2
    now, counts, ptr, idx = changes(c, r, p, prev, own, due)
    ref_now, entered, left, updated = _reference(c, r, p, prev, own, due)
    assert np.array_equal(now, ref_now)
    for i in range(m):
        for q, ref in enumerate((entered, left, updated)):
            got = idx[ptr[i, q]:ptr[i, q] + counts[i, q]]
            assert np.array_equal(got, np.flatnonzero(ref[i])), (i, q)
    assert np.array_equal(relevant(c, r, p, prev), _reference(c, r, p, prev, np.full(m, -1), due)[0])


def test_an_entity_at_the_edge_does_not_flicker():
    c = np.zeros((1, 3))
    r = np.array([1000.0])
    ring = np.array([[990.0, 0, 0], [1020.0, 0, 0], [1049.0, 0, 0], [1051.0, 0, 0]])
    fresh = relevant(c, r, ring)
    assert fresh.tolist() == [[True, False, False, False]]
    held = relevant(c, r, ring, was_relevant=np.ones((1, 4), bool))
    assert held.tolist() == [[True, True, True, False]]  # kept out to 1050 m


def test_a_previous_answer_of_the_wrong_shape_is_named():
    with pytest.raises(InvalidArgument, match="was_relevant"):
        relevant(np.zeros((2, 3)), [1.0, 1.0], np.zeros((3, 3)), was_relevant=np.zeros((3, 2), bool))
