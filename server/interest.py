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

import numba
import numpy as np

from sortie.errors import InvalidArgument

HYSTERESIS = 0.05


@numba.njit(cache=True, nogil=True)
def _relevant_kernel(c, r, p, prev, own, due, now, counts):
    """now[i, j] = entity j relevant to receiver i: |p_j - c_i| <= r_i, or <= r_i (1 +
    HYSTERESIS) while prev[i, j], or j == own[i] (a negative r_i: only its own).
    counts[i] = (entered, left, updated) of receiver i against prev, ``updated`` being
    relevant, due and not entered. prev (m, n), or (0, 0) for none; own (m,) columns, -1
    for none; due (n,) bool."""
    m, n = now.shape
    has_prev = prev.shape[0] > 0
    grow = (1.0 + HYSTERESIS) * (1.0 + HYSTERESIS)
    for i in range(m):
        r2 = r[i] * r[i] if r[i] >= 0.0 else -1.0
        r2_keep = r2 * grow
        cx, cy, cz = c[i, 0], c[i, 1], c[i, 2]
        ne = nl = nu = 0
        for j in range(n):
            dx, dy, dz = p[j, 0] - cx, p[j, 1] - cy, p[j, 2] - cz
            d2 = dx * dx + dy * dy + dz * dz
            was = has_prev and prev[i, j]
            inside = d2 <= r2 or (was and d2 <= r2_keep) or j == own[i]
            now[i, j] = inside
            if inside and not was:
                ne += 1
            elif was and not inside:
                nl += 1
            elif inside and due[j]:
                nu += 1
        counts[i, 0] = ne
        counts[i, 1] = nl
        counts[i, 2] = nu


@numba.njit(cache=True, nogil=True)
def _changes_kernel(now, prev, due, counts, ptr, idx):
    """Entity columns of each receiver's changes, as CSR: receiver i's entered ones are
    idx[ptr[i, 0]:ptr[i, 0] + counts[i, 0]], then its left and updated ones likewise."""
    m, n = now.shape
    has_prev = prev.shape[0] > 0
    for i in range(m):
        a, b, u = ptr[i, 0], ptr[i, 1], ptr[i, 2]
        for j in range(n):
            inside = now[i, j]
            was = has_prev and prev[i, j]
            if inside and not was:
                idx[a] = j
                a += 1
            elif was and not inside:
                idx[b] = j
                b += 1
            elif inside and due[j]:
                idx[u] = j
                u += 1


def _rows(values, width: int) -> np.ndarray:
    return np.ascontiguousarray(np.asarray(values, dtype=np.float64).reshape(-1, width))


def relevant(centres_ecef, radii_m, positions_ecef, was_relevant=None) -> np.ndarray:
    """(m, n) bool: entity j relevant to receiver i.

    centres_ecef (m, 3), radii_m (m,), positions_ecef (n, 3), metres (a negative radius:
    nothing); ``was_relevant`` (m, n) bool, the previous answer, for the hysteresis.
    """
    return changes(centres_ecef, radii_m, positions_ecef, was_relevant)[0]


def changes(centres_ecef, radii_m, positions_ecef, was_relevant=None, own=None, due=None):
    """What each receiver's view does: (now, counts, ptr, idx).

    now (m, n) bool as :func:`relevant`, with ``own`` (m,) the column of each receiver's
    own agent (always relevant; -1: none); counts (m, 3) how many entities it sees
    enter, leave, and (relevant, ``due`` (n,) bool, not entering) update; their columns
    are idx[ptr[i, q]:ptr[i, q] + counts[i, q]] for q = 0, 1, 2, each ascending.
    """
    c, p = _rows(centres_ecef, 3), _rows(positions_ecef, 3)
    m, n = c.shape[0], p.shape[0]
    r = np.ascontiguousarray(np.asarray(radii_m, dtype=np.float64).reshape(m))
    prev = np.zeros((0, 0), bool) if was_relevant is None else np.ascontiguousarray(was_relevant, bool)
    if prev.size and prev.shape != (m, n):
        raise InvalidArgument("was_relevant", f"must have shape ({m}, {n}), got {prev.shape}")
    own = np.full(m, -1, np.int64) if own is None else np.ascontiguousarray(own, np.int64)
    due = np.zeros(n, bool) if due is None else np.ascontiguousarray(due, bool)
    now = np.empty((m, n), bool)
    counts = np.zeros((m, 3), np.int64)
    _relevant_kernel(c, r, p, prev, own, due, now, counts)
    ptr = np.zeros((m, 3), np.int64)
    ptr.ravel()[1:] = np.cumsum(counts.ravel())[:-1]
    idx = np.empty(int(counts.sum()), np.int64)
    _changes_kernel(now, prev, due, counts, ptr, idx)
    return now, counts, ptr, idx
