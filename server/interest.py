"""Interest management: which entities each receiver needs to hear about.

A receiver (a session) has an area of interest: a sphere of radius r_i around
a centre c_i in ECEF (its own agent's position, or the point an observer
chose), with the radius of its agent type from the scenario. Entity j is
relevant to receiver i when |p_j - c_i| <= r_i, or when it is always relevant
to i (its own agent). Straight-line ECEF distance, not ground distance: the
two differ by d^3 / (24 R^2), under 0.1 % for 200 km.

Hysteresis keeps an entity hovering at the edge from flickering in and out:
once in, it leaves only beyond r_i (1 + HYSTERESIS).
"""

from __future__ import annotations

import numpy as np

HYSTERESIS = 0.05


def _squared_distances(c: np.ndarray, p: np.ndarray) -> np.ndarray:
    """(m, n) |c_i - p_j|^2 as |c|^2 + |p|^2 - 2 c.p (one matrix product instead of an
    (m, n, 3) temporary), about the entities' mean so that the squares stay small:
    for an exercise 1000 km across the rounding error is under 1e-3 m^2."""
    o = p.mean(axis=0) if p.size else np.zeros(3)
    c, p = c - o, p - o
    d2 = (c * c).sum(axis=1)[:, None] + (p * p).sum(axis=1)[None, :] - 2.0 * (c @ p.T)
    return np.maximum(d2, 0.0, out=d2)


def relevant(centres_ecef, radii_m, positions_ecef, was_relevant=None) -> np.ndarray:
    """(m, n) bool: entity j relevant to receiver i.

    centres_ecef (m, 3), radii_m (m,), positions_ecef (n, 3), metres;
    ``was_relevant`` (m, n) bool, the previous answer, for the hysteresis.
    """
    c = np.asarray(centres_ecef, dtype=np.float64).reshape(-1, 3)
    p = np.asarray(positions_ecef, dtype=np.float64).reshape(-1, 3)
    r = np.asarray(radii_m, dtype=np.float64).reshape(-1, 1)
    d2 = _squared_distances(c, p)
    inside = d2 <= r * r
    if was_relevant is not None:
        keep = d2 <= (r * (1.0 + HYSTERESIS)) ** 2
        inside |= np.asarray(was_relevant, bool) & keep
    return inside
