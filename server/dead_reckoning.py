"""Dead reckoning as in DIS: send an entity's state only when the receivers' guess drifts.

Every receiver extrapolates an entity from the last state it was sent; the
sender runs the same extrapolation and sends a new state when it differs from
the true one by more than a position or an orientation threshold, or when a
heartbeat is due (IEEE 1278.1-2012, the entity state PDU's dead reckoning and
Annex E). The defaults are the standard's symbolic parameters DRA_POS_THRESH
(1 m), DRA_ORIENT_THRESH (3 degrees) and HBT_PDU_ENTITY_STATE (5 s).

Algorithms (IEEE 1278.1-2012 Annex E; their DIS numbers, world coordinates):

====== == ============================================ ==============================
name   #  position P(t), dt = t - t0                    orientation
====== == ============================================ ==============================
STATIC 1  P0                                           fixed
FPW    2  P0 + V0 dt                                   fixed
RPW    3  P0 + V0 dt                                   rotating at omega (body axes)
RVW    4  P0 + V0 dt + 1/2 A0 dt^2                     rotating at omega (body axes)
FVW    5  P0 + V0 dt + 1/2 A0 dt^2                     fixed
====== == ============================================ ==============================

Frames and units: positions ECEF metres, velocities m/s and accelerations
m/s^2 in ECEF; orientation the unit quaternion (w, x, y, z) of the rotation
ECEF -> body (body x forward, y right, z down), the convention of
``proto/sortie/v1/simulation.proto``; angular velocity omega = (p, q, r) of the
body relative to ECEF, body axes, rad/s. Quaternions are Hamilton's, and the
matrix of q transforms body components to ECEF ones (v_e = R(q) v_b), as
``fdm.state.euler_to_quaternion`` builds them for NED -> body.

Rotating orientation. Annex E rotates the orientation matrix by
[DR] = (1 - cos w dt) / w^2 omega omega^T + cos(w dt) I - sin(w dt) / w [omega x],
w = |omega|: a rotation by the angle w dt about omega, in body axes. In
quaternions (Stevens & Lewis, *Aircraft Control and Simulation*, 3rd ed.,
sec. 1.8: q' = 1/2 q * (0, omega)) a constant body rate integrates exactly to
q(t) = q0 * (cos(w dt / 2), sin(w dt / 2) omega / w). The vector part is
written as omega dt / 2 * sinc(w dt / 2), which has no 0/0 as w -> 0 and is
exact to rounding at w = 0; the product is renormalised, so a heartbeat of
5 s at any rate leaves a unit quaternion.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np

from sortie.errors import InvalidArgument, NotFound

# IEEE 1278.1-2012 Annex E dead-reckoning algorithm numbers (world coordinates).
STATIC = 1
FPW = 2
RPW = 3
RVW = 4
FVW = 5
ALGORITHM_NAMES = {STATIC: "STATIC", FPW: "FPW", RPW: "RPW", RVW: "RVW", FVW: "FVW"}
# Indexed by code (0 is not one): does the algorithm move, accelerate, rotate?
_MOVES = np.array([False, False, True, True, True, True])
_ACCELERATES = np.array([False, False, False, False, True, True])
_ROTATES = np.array([False, False, False, True, True, False])

# IEEE 1278.1-2012 defaults: DRA_POS_THRESH, DRA_ORIENT_THRESH, HBT_PDU_ENTITY_STATE.
DEFAULT_POSITION_THRESHOLD_M = 1.0
DEFAULT_ORIENTATION_THRESHOLD_RAD = math.radians(3.0)
DEFAULT_HEARTBEAT_S = 5.0
# Tick times carry rounding (k * 0.05 s): a heartbeat due at 5 s fires on the tick at 5 s.
TIME_SLACK_S = 1e-9
# A quaternion off unit norm by this much is refused (float32 on the wire is good to 1e-7).
_UNIT_TOLERANCE = 1e-3


# -- quaternions (w, x, y, z), Hamilton product --------------------------------------------------

def quat_multiply(a, b):
    """Hamilton product a * b of (..., 4) quaternions (w, x, y, z); broadcasts."""
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    aw, ax, ay, az = a[..., 0], a[..., 1], a[..., 2], a[..., 3]
    bw, bx, by, bz = b[..., 0], b[..., 1], b[..., 2], b[..., 3]
    return np.stack([aw * bw - ax * bx - ay * by - az * bz,
                     aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw], axis=-1)


def quat_conjugate(q):
    """(..., 4) conjugates: the inverse rotation of a unit quaternion."""
    return np.asarray(q, dtype=np.float64) * np.array([1.0, -1.0, -1.0, -1.0])


def normalised(q):
    """(..., 4) quaternions scaled to unit norm."""
    q = np.asarray(q, dtype=np.float64)
    return q / np.linalg.norm(q, axis=-1, keepdims=True)


def rotation_angle(q1, q2):
    """(...,) angle (rad, in [0, pi]) of the rotation q1^-1 q2 between two orientations.

    2 atan2(|v|, |w|) of d = conj(q1) q2: accurate near 0 and near pi (where
    acos of w loses half the digits), the same for q and -q (double cover),
    and independent of the inputs' norms.
    """
    d = quat_multiply(quat_conjugate(q1), q2)
    return 2.0 * np.arctan2(np.linalg.norm(d[..., 1:], axis=-1), np.abs(d[..., 0]))


def rotate_body(quat, omega_body, dt):
    """(n, 4) orientations after turning at constant body rate omega for dt seconds.

    quat: (n, 4) ECEF -> body (any frame -> body); omega_body: (n, 3) rad/s,
    body axes; dt: scalar or (n,) seconds (negative runs backwards).
    q(t) = q0 * (cos(a), sinc(a) omega dt / 2), a = |omega| dt / 2 (see the module
    docstring); renormalised.
    """
    half = 0.5 * np.asarray(omega_body, dtype=np.float64) * np.asarray(dt, dtype=np.float64)[..., None]
    a = np.linalg.norm(half, axis=-1)
    step = np.concatenate([np.cos(a)[..., None], np.sinc(a / np.pi)[..., None] * half], axis=-1)
    return normalised(quat_multiply(quat, step))


def body_rates_between(q0, q1, dt):
    """(n, 3) constant body rate (rad/s, body axes) that turns q0 into q1 in dt seconds.

    The inverse of :func:`rotate_body` (shortest way round, either sign of q1):
    for a sender whose model has orientations but no rate gyros (ground
    vehicles). omega = 2 atan2(|v|, w) v / |v| / dt of d = conj(q0) q1, w >= 0,
    with atan2(s, w) / s -> 1 / w as s -> 0 (no 0/0).
    """
    d = quat_multiply(quat_conjugate(q0), q1)
    d = np.where(d[..., :1] < 0.0, -d, d)
    s = np.linalg.norm(d[..., 1:], axis=-1)
    w = d[..., 0]
    safe_s = np.where(s > 0.0, s, 1.0)
    per_s = np.where(s > 0.0, np.arctan2(s, w) / safe_s, 1.0 / w)
    return 2.0 * d[..., 1:] * (per_s / np.asarray(dt, dtype=np.float64))[..., None]


def ecef_to_ned_quat(lat_deg, lon_deg):
    """(..., 4) quaternions of the rotation ECEF -> local NED at geodetic (lat, lon), degrees.

    Turn about z by the longitude, then about the new y by -(lat + 90 deg): the
    matrix's columns are then north, east, down in ECEF (terrain.geodesy.enu_basis).
    """
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.radians(np.asarray(lon_deg, dtype=np.float64))
    zero = np.zeros(np.broadcast(lat, lon).shape)
    about_z = np.stack([np.cos(0.5 * lon) + zero, zero, zero, np.sin(0.5 * lon) + zero], axis=-1)
    tilt = -0.5 * (lat + 0.5 * np.pi)
    about_y = np.stack([np.cos(tilt) + zero, zero, np.sin(tilt) + zero, zero], axis=-1)
    return quat_multiply(about_z, about_y)


def ned_to_ecef_quat(quat_ned2body, lat_deg, lon_deg):
    """(..., 4) ECEF -> body quaternions from NED -> body ones at geodetic (lat, lon), degrees.

    q_ecef2body = q_ecef2ned * q_ned2body (rotations compose like their
    matrices, R_eb = R_en R_nb; Stevens & Lewis sec. 1.8). Argument order (lat, lon).
    """
    return quat_multiply(ecef_to_ned_quat(lat_deg, lon_deg), quat_ned2body)


# -- extrapolation (IEEE 1278.1-2012 Annex E) -----------------------------------------------------

def check_algorithms(algorithm, n: int) -> np.ndarray:
    """(n,) int64 algorithm codes from a scalar or (n,) array; InvalidArgument names a bad one."""
    arr = np.asarray(algorithm)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
        raise InvalidArgument("algorithm", f"must be a code or an array of {n} codes, got shape {arr.shape}")
    if arr.size and not (np.issubdtype(arr.dtype, np.integer) and arr.dtype != np.bool_):
        raise InvalidArgument("algorithm", "must be integer DIS codes", value=arr.tolist())
    flat = np.broadcast_to(arr, (n,))
    bad = (flat < STATIC) | (flat > FVW)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidArgument("algorithm", f"must be a DIS world-coordinate code {sorted(ALGORITHM_NAMES)} "
                                           f"({', '.join(ALGORITHM_NAMES.values())})",
                              index=i if arr.ndim else None, value=flat[i].item())
    return flat.astype(np.int64)


def extrapolate(algorithm, t0, pos, vel, acc, quat, omega, t):
    """Receivers' estimate (pos_t, quat_t) at time t of states sent at t0.

    algorithm: a DIS code or (n,) codes; t0, t: seconds, scalars or (n,);
    pos (n, 3) ECEF m; vel (n, 3) ECEF m/s; acc (n, 3) ECEF m/s^2 (None: 0);
    quat (n, 4) ECEF -> body; omega (n, 3) body axes rad/s (None: 0).
    Returns pos_t (n, 3) ECEF m and quat_t (n, 4): the sent quaternion itself
    for fixed-orientation algorithms, rotated and renormalised for RPW/RVW.
    """
    pos = np.asarray(pos, dtype=np.float64)
    if pos.ndim != 2 or pos.shape[1] != 3:
        raise InvalidArgument("pos", f"must have shape (n, 3), got {pos.shape}")
    n = pos.shape[0]
    code = check_algorithms(algorithm, n)
    dt = np.broadcast_to(np.asarray(t, dtype=np.float64) - np.asarray(t0, dtype=np.float64), (n,))
    zero = np.zeros((n, 3))
    vel, acc, omega = (zero if v is None else _shaped(name, v, (n, 3))
                       for name, v in (("vel", vel), ("acc", acc), ("omega", omega)))
    quat = _shaped("quat", quat, (n, 4))
    dt_v = np.where(_MOVES[code], dt, 0.0)[:, None]
    dt_a = np.where(_ACCELERATES[code], dt, 0.0)[:, None]
    pos_t = pos + vel * dt_v + 0.5 * acc * (dt_a * dt_a)
    rotating = _ROTATES[code]
    if rotating.all():
        return pos_t, rotate_body(quat, omega, dt)
    quat_t = quat.copy()
    if rotating.any():
        quat_t[rotating] = rotate_body(quat[rotating], omega[rotating], dt[rotating])
    return pos_t, quat_t


def _shaped(name: str, values, shape: tuple) -> np.ndarray:
    """values as a float64 array of ``shape`` (an empty list fits any empty shape)."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.size == 0 and shape[0] == 0:
        return np.zeros(shape)
    if arr.shape != shape:
        raise InvalidArgument(name, f"must have shape {shape}, got {arr.shape}")
    return arr


# -- thresholds -----------------------------------------------------------------------------------

@dataclass(frozen=True)
class Thresholds:
    """When the sender sends: position error (m), orientation error (rad), heartbeat (s),
    and the algorithm receivers extrapolate with. Validated on construction."""

    position_m: float = DEFAULT_POSITION_THRESHOLD_M
    orientation_rad: float = DEFAULT_ORIENTATION_THRESHOLD_RAD
    heartbeat_s: float = DEFAULT_HEARTBEAT_S
    algorithm: int = RVW

    def __post_init__(self):
        for name, hi in (("position_m", math.inf), ("orientation_rad", math.pi), ("heartbeat_s", math.inf)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not (0.0 < v <= hi and math.isfinite(v)):
                bound = "in (0, pi]" if hi == math.pi else "finite and > 0"
                raise InvalidArgument(name, f"must be {bound}", value=v)
        check_algorithms(self.algorithm, 1)


# Per agent kind, the DIS defaults with the algorithm that sent the fewest bytes in bench.dr
# (60 s of manoeuvring c172x/f16 and a convoy on the Alps DEM, 20 Hz): RVW for both. Ground
# vehicles under RVW sent 0.46 updates (47 B) per second against FVW's 0.71 (62 B), RPW's 0.55
# (48 B) and FPW's 0.75 (56 B), at the same position error: a route's turns are what a fixed
# orientation misses. Aircraft: RVW 0.80/s (82 B), the others 1.9-2.3/s (168-174 B).
THRESHOLDS_BY_KIND = {
    "aircraft": Thresholds(algorithm=RVW),
    "ground": Thresholds(algorithm=RVW),
    "static": Thresholds(algorithm=STATIC),
}


# -- the per-entity table both ends keep ----------------------------------------------------------

def _check_ids(ids) -> np.ndarray:
    arr = np.asarray(ids)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1 or not (arr.size == 0 or np.issubdtype(arr.dtype, np.integer)):
        raise InvalidArgument("ids", f"must be a 1-D array of integer entity ids, got {arr.dtype} {arr.shape}")
    values, counts = np.unique(arr, return_counts=True)
    if (counts > 1).any():
        raise InvalidArgument("ids", "must not repeat an entity id", value=int(values[counts > 1][0]))
    return arr.astype(np.int64)


def _unit(quat: np.ndarray) -> np.ndarray:
    """(n,) bool: which (n, 4) quaternions have unit norm (to 1e-3: float32 on the wire)."""
    return np.abs(np.linalg.norm(quat, axis=1) - 1.0) < _UNIT_TOLERANCE


def _check_rows(name: str, values, n: int, width: int) -> np.ndarray:
    """(n, width) finite float64 rows (unit ones for width 4); InvalidArgument naming the field (and row)."""
    arr = _shaped(name, values, (n, width))
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidArgument(name, "must be finite", index=i, value=arr[i].tolist())
    if width == 4:
        bad = ~_unit(arr)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise InvalidArgument(name, "must be a unit quaternion (w, x, y, z)", index=i, value=arr[i].tolist())
    return arr


def _check_times(name: str, t, n: int) -> np.ndarray:
    arr = np.asarray(t, dtype=np.float64)
    if arr.ndim > 1 or (arr.ndim == 1 and arr.shape[0] != n):
        raise InvalidArgument(name, f"must be a scalar or have shape ({n},), got {arr.shape}")
    arr = np.broadcast_to(arr, (n,))
    bad = ~np.isfinite(arr)
    if bad.any():
        i = int(np.flatnonzero(bad)[0])
        raise InvalidArgument(name, "must be finite", index=i, value=float(arr[i]))
    return arr


class _Table:
    """Per-entity rows (a struct of arrays) kept sorted by entity id."""

    def __init__(self, columns: dict):
        self.ids = np.zeros(0, np.int64)
        self.cols = {name: np.zeros((0, *tail), dtype) for name, (tail, dtype) in columns.items()}

    def _find(self, ids: np.ndarray):
        """(insertion rows, found mask) of ids."""
        k = np.searchsorted(self.ids, ids)
        if not self.ids.size:
            return k, np.zeros(ids.shape, bool)
        return k, self.ids[np.minimum(k, self.ids.size - 1)] == ids

    def known(self, ids: np.ndarray) -> np.ndarray:
        return self._find(ids)[1]

    def slots(self, ids: np.ndarray) -> np.ndarray:
        """Rows of ids; NotFound names the first unknown one."""
        k, found = self._find(ids)
        if not found.all():
            raise NotFound(f"entity id {int(ids[np.flatnonzero(~found)[0]])} is not known")
        return k

    def insert(self, ids: np.ndarray, rows: dict) -> None:
        order = np.argsort(np.concatenate([self.ids, ids]), kind="stable")
        self.ids = np.concatenate([self.ids, ids])[order]
        for name, col in self.cols.items():
            self.cols[name] = np.concatenate([col, np.broadcast_to(rows[name], (ids.size, *col.shape[1:]))])[order]

    def delete(self, ids: np.ndarray) -> None:
        keep = np.ones(self.ids.size, bool)
        keep[self.slots(ids)] = False
        self.ids = self.ids[keep]
        for name in self.cols:
            self.cols[name] = self.cols[name][keep]


_STATE_COLUMNS = {"t0": ((), np.float64), "pos": ((3,), np.float64), "vel": ((3,), np.float64),
                  "acc": ((3,), np.float64), "quat": ((4,), np.float64), "omega": ((3,), np.float64),
                  "algorithm": ((), np.int64)}
_IDENTITY = np.array([1.0, 0.0, 0.0, 0.0])


def _state_rows(n, t, pos, vel, acc, quat, omega) -> dict:
    return {"t0": _check_times("t", t, n), "pos": _check_rows("pos", pos, n, 3),
            "vel": _check_rows("vel", vel, n, 3), "acc": _check_rows("acc", acc, n, 3),
            "quat": _check_rows("quat", quat, n, 4), "omega": _check_rows("omega", omega, n, 3)}


# -- the receiver's rows: one message's states as one (n, 17) float64 array ------------------------
#
# A receiver gets ~10 states per message at 20 Hz. Checked and stored field by field, a
# message cost ~40 small numpy calls (hundreds of us, most of a client's CPU). Side by
# side in one row per state, a message of entities already held is checked and stored by
# one compiled pass; anything else (new entities, a fault to name) takes the numpy path.

# Columns of a state row: t0 (s), pos, vel, acc (ECEF), quat (ECEF -> body), omega (body).
ROW_COLUMNS = {"t0": 0, "pos": slice(1, 4), "vel": slice(4, 7), "acc": slice(7, 10), "quat": slice(10, 14),
               "omega": slice(14, 17)}
ROW_WIDTH = 17
_QUAT = ROW_COLUMNS["quat"].start
# Below this many ids a Python set beats np.unique's sort and counts.
_FEW = 64


def _distinct(ids: np.ndarray) -> bool:
    """Whether no id in (n,) ids repeats."""
    if ids.size < _FEW:
        return len(set(ids.tolist())) == ids.size
    s = np.sort(ids)
    return not (s[1:] == s[:-1]).any()


def _fast_ids(ids) -> np.ndarray:
    """:func:`_check_ids` at the cost of a set in the common case, an int64 array of distinct
    ids; anything else goes to it, to be converted or to have its fault named."""
    if isinstance(ids, np.ndarray) and ids.dtype == np.int64 and ids.ndim == 1 and _distinct(ids):
        return ids
    return _check_ids(ids)


def _checked_rows(rows, n: int) -> np.ndarray:
    """(n, 17) float64 state rows, all finite with unit quaternions, in two whole-array tests;
    when one fails, the per-field checks raise the error receive's arguments would have."""
    rows = _shaped("rows", rows, (n, ROW_WIDTH))
    if not (np.isfinite(rows).all() and _unit(rows[:, ROW_COLUMNS["quat"]]).all()):
        _state_rows(n, *(rows[:, c] for c in ROW_COLUMNS.values()))
    return rows


def _filled_rows(n: int, t0, fields) -> np.ndarray | None:
    """t0 (scalar or (n,)) and the (n, 3/3/3/4/3) fields side by side, unchecked; None
    unless every shape fits."""
    try:
        t0 = np.asarray(t0, np.float64)
        fields = [np.asarray(v, np.float64) for v in fields]
    except (TypeError, ValueError):
        return None
    columns = list(ROW_COLUMNS.values())[1:]
    if t0.shape not in ((), (n,)) or any(v.shape != (n, c.stop - c.start) for v, c in zip(fields, columns)):
        return None
    rows = np.empty((n, ROW_WIDTH))
    rows[:, 0] = t0
    for v, c in zip(fields, columns):
        rows[:, c] = v
    return rows


def _rows_of(n: int, t0, pos, vel, acc, quat, omega) -> np.ndarray:
    """receive's per-field arguments as (n, 17) rows; InvalidArgument, as from
    :func:`_state_rows`, only for a shape (values are checked later)."""
    rows = _filled_rows(n, t0, (pos, vel, acc, quat, omega))
    if rows is None:
        return np.column_stack(list(_state_rows(n, t0, pos, vel, acc, quat, omega).values()))
    return rows


@numba.njit(cache=True)
def _plainly_valid(row: np.ndarray, code: int) -> bool:
    """Whether a state row is finite, its quaternion of unit norm well inside the
    tolerance (its rounding may differ from numpy's; the edge goes to the exact check)
    and its algorithm a DIS code."""
    for x in row:
        if not np.isfinite(x):
            return False
    q = row[_QUAT:_QUAT + 4]
    norm = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    return abs(norm - 1.0) < _UNIT_TOLERANCE - 1e-12 and STATIC <= code <= FVW


@numba.njit(cache=True)
def _merge_held(held_ids, held_rows, held_codes, ids, rows, codes) -> bool:
    """Store each row and code over its entity's unless the held one is newer (by t0),
    when every row is plainly valid and every (distinct) id is held; otherwise store
    nothing and return False, for the numpy path to insert or to name the fault."""
    slots = np.empty(ids.size, np.int64)
    for i in range(ids.size):
        k = np.searchsorted(held_ids, ids[i])
        if k == held_ids.size or held_ids[k] != ids[i] or not _plainly_valid(rows[i], codes[i]):
            return False
        slots[i] = k
    for i in range(ids.size):
        k = slots[i]
        if rows[i, 0] >= held_rows[k, 0]:
            held_rows[k] = rows[i]
            held_codes[k] = codes[i]
    return True


@numba.njit(cache=True, nogil=True)
def _publish_kernel(t, k, pos, vel, acc, quat, omega, c_code, c_t0, c_pos, c_vel, c_acc, c_quat, c_omega,
                    c_sent, c_pos_th, c_ori_th, c_hb, send, codes):
    """:meth:`DeadReckoner.publish_rows` for rows k (distinct) in one pass: each row's
    receivers' extrapolation (:func:`extrapolate`), its position and orientation errors
    (norm, :func:`rotation_angle`), the send decision of :meth:`DeadReckoner.due`, and
    the sent rows stored, with each row's algorithm code in ``codes``. The same formulas
    in the same order as the numpy path, so the decisions agree with it but for rounding
    at a threshold. The rows are checked by the caller."""
    for i in range(k.shape[0]):
        r = k[i]
        code = c_code[r]
        due = not c_sent[r] or t - c_t0[r] >= c_hb[r] - TIME_SLACK_S
        if not due:
            dt = t - c_t0[r]
            dt_v = dt if (code == FPW or code == RPW or code == RVW or code == FVW) else 0.0
            dt_a = dt if (code == RVW or code == FVW) else 0.0
            e2 = 0.0
            for j in range(3):
                d = c_pos[r, j] + c_vel[r, j] * dt_v + 0.5 * c_acc[r, j] * (dt_a * dt_a) - pos[i, j]
                e2 += d * d
            due = math.sqrt(e2) > c_pos_th[r]
        if not due:
            w0, x0, y0, z0 = c_quat[r, 0], c_quat[r, 1], c_quat[r, 2], c_quat[r, 3]
            if code == RPW or code == RVW:  # rotate_body: q0 * (cos a, sinc(a) omega dt / 2), renormalised
                hx, hy, hz = 0.5 * c_omega[r, 0] * dt, 0.5 * c_omega[r, 1] * dt, 0.5 * c_omega[r, 2] * dt
                a = math.sqrt(hx * hx + hy * hy + hz * hz)
                sw = math.cos(a)
                sc = math.sin(a) / a if a != 0.0 else 1.0
                sx, sy, sz = sc * hx, sc * hy, sc * hz
                qw = w0 * sw - x0 * sx - y0 * sy - z0 * sz
                qx = w0 * sx + x0 * sw + y0 * sz - z0 * sy
                qy = w0 * sy - x0 * sz + y0 * sw + z0 * sx
                qz = w0 * sz + x0 * sy - y0 * sx + z0 * sw
                m = math.sqrt(qw * qw + qx * qx + qy * qy + qz * qz)
                w0, x0, y0, z0 = qw / m, qx / m, qy / m, qz / m
            # rotation_angle: d = conj(q_dr) q, 2 atan2(|v|, |w|)
            bw, bx, by, bz = quat[i, 0], quat[i, 1], quat[i, 2], quat[i, 3]
            aw, ax, ay, az = w0, -x0, -y0, -z0
            dw = aw * bw - ax * bx - ay * by - az * bz
            dx = aw * bx + ax * bw + ay * bz - az * by
            dy = aw * by - ax * bz + ay * bw + az * bx
            dz = aw * bz + ax * by - ay * bx + az * bw
            due = 2.0 * math.atan2(math.sqrt(dx * dx + dy * dy + dz * dz), abs(dw)) > c_ori_th[r]
        send[i] = due
        codes[i] = code
        if due:
            c_t0[r] = t
            for j in range(3):
                c_pos[r, j] = pos[i, j]
                c_vel[r, j] = vel[i, j]
                c_acc[r, j] = acc[i, j]
                c_omega[r, j] = omega[i, j]
            for j in range(4):
                c_quat[r, j] = quat[i, j]
            c_sent[r] = True


_WARM = []


def _warm_merge() -> None:
    """Load (or compile) the merge kernel once per process, when the first Extrapolator
    is made: not on a stream's first update, where numba's start-up (0.5 s loading
    from its cache, seconds compiling) would hold every stream of the process."""
    if not _WARM:
        z = np.zeros(0, np.int64)
        _merge_held(z, np.zeros((0, ROW_WIDTH)), z, z, np.zeros((0, ROW_WIDTH)), z)
        _WARM.append(True)


class DeadReckoner:
    """The sender's model of what every receiver believes, one row per entity.

    One per server, not per client: every receiver extrapolates from the same
    last-sent state (as in DIS), so one decision per entity serves them all.
    Entities are added with their :class:`Thresholds` (per agent kind, see
    THRESHOLDS_BY_KIND) and removed by id; an entity never sent is always due.
    """

    def __init__(self):
        self._t = _Table(dict(_STATE_COLUMNS, sent=((), np.bool_), position_m=((), np.float64),
                              orientation_rad=((), np.float64), heartbeat_s=((), np.float64)))

    @property
    def ids(self) -> np.ndarray:
        """(m,) int64 entity ids, ascending."""
        return self._t.ids.copy()

    def __len__(self) -> int:
        return self._t.ids.size

    def add(self, ids, thresholds: Thresholds = THRESHOLDS_BY_KIND["aircraft"]) -> None:
        """Start tracking entities (never sent yet, so due at once)."""
        ids = _check_ids(ids)
        known = self._t.known(ids)
        if known.any():
            raise InvalidArgument("ids", "entity already added", value=int(ids[np.flatnonzero(known)[0]]))
        self._t.insert(ids, {"t0": 0.0, "pos": 0.0, "vel": 0.0, "acc": 0.0, "quat": _IDENTITY, "omega": 0.0,
                             "algorithm": thresholds.algorithm, "sent": False, **self._threshold_row(thresholds)})

    def remove(self, ids) -> None:
        self._t.delete(_check_ids(ids))

    def set_thresholds(self, ids, thresholds: Thresholds) -> None:
        """New thresholds and algorithm for entities (the next update carries the algorithm)."""
        k = self._t.slots(_check_ids(ids))
        for name, v in self._threshold_row(thresholds).items():
            self._t.cols[name][k] = v
        self._t.cols["algorithm"][k] = thresholds.algorithm

    @staticmethod
    def _threshold_row(th: Thresholds) -> dict:
        return {"position_m": th.position_m, "orientation_rad": th.orientation_rad, "heartbeat_s": th.heartbeat_s}

    def errors(self, t, ids, pos, quat):
        """(position error m, orientation error rad), each (n,), of the receivers'
        extrapolation at time t (s) against the true pos (n, 3) ECEF m and quat
        (n, 4) ECEF -> body; NaN for entities never sent."""
        ids = _check_ids(ids)
        return self._errors(_check_times("t", t, ids.size), self._t.slots(ids), pos, quat)

    def _errors(self, t, k, pos, quat):
        n = k.size
        pos = _check_rows("pos", pos, n, 3)
        quat = _check_rows("quat", quat, n, 4)
        c = self._t.cols
        p_dr, q_dr = extrapolate(c["algorithm"][k], c["t0"][k], c["pos"][k], c["vel"][k], c["acc"][k],
                                 c["quat"][k], c["omega"][k], t)
        never = ~c["sent"][k]
        return (np.where(never, np.nan, np.linalg.norm(p_dr - pos, axis=1)),
                np.where(never, np.nan, rotation_angle(q_dr, quat)))

    def due(self, t, ids, pos, quat) -> np.ndarray:
        """(n,) bool: the entities to send at time t (s) given their true pos (n, 3)
        ECEF m and quat (n, 4) ECEF -> body: never sent, heartbeat due, or the
        receivers' extrapolation off by more than a threshold (NaN compares False)."""
        ids = _check_ids(ids)
        t = _check_times("t", t, ids.size)
        k = self._t.slots(ids)
        pos_err, ori_err = self._errors(t, k, pos, quat)
        c = self._t.cols
        return (~c["sent"][k] | (t - c["t0"][k] >= c["heartbeat_s"][k] - TIME_SLACK_S)
                | (pos_err > c["position_m"][k]) | (ori_err > c["orientation_rad"][k]))

    def mark_sent(self, t, ids, pos, vel, acc, quat, omega, mask=None) -> None:
        """Record that the state of ids at time t went out to every receiver.

        Rows as in :func:`extrapolate`; ``mask`` (n,) bool picks the rows sent
        (e.g. the result of :meth:`due`). Pass exactly what went on the wire (if
        it rounds velocities to float32, the rounded values) so the model and
        the receivers stay bit for bit the same.
        """
        ids = _check_ids(ids)
        n = ids.size
        rows = _state_rows(n, t, pos, vel, acc, quat, omega)
        if mask is not None:
            mask = np.asarray(mask, dtype=bool)
            if mask.shape != (n,):
                raise InvalidArgument("mask", f"must have shape ({n},), got {mask.shape}")
            ids = ids[mask]
            rows = {name: v[mask] for name, v in rows.items()}
        k = self._t.slots(ids)
        for name, v in rows.items():
            self._t.cols[name][k] = v
        self._t.cols["sent"][k] = True

    def update(self, t, ids, pos, vel, acc, quat, omega) -> np.ndarray:
        """:meth:`due` then :meth:`mark_sent` of the due rows; the (n,) bool mask to send."""
        send = self.due(t, ids, pos, quat)
        if send.any():
            self.mark_sent(t, ids, pos, vel, acc, quat, omega, mask=send)
        return send

    def slots(self, ids) -> np.ndarray:
        """Table rows of entity ids (validated; NotFound names an unknown one), valid
        until entities are added or removed: for :meth:`publish_rows`."""
        return self._t.slots(_check_ids(ids))

    def publish_rows(self, t: float, k: np.ndarray, pos, vel, acc, quat, omega) -> tuple[np.ndarray, np.ndarray]:
        """(due mask, algorithm codes) of table rows k (:meth:`slots`) at time t, with the
        due rows marked sent: :meth:`due`, :meth:`mark_sent` of the due rows and
        :meth:`algorithm` in one pass, for a publisher that holds the rows of its
        snapshot's ids. pos/quat are validated as in :meth:`due`; vel/acc/omega, which
        the publisher derives from them, are not again."""
        n = k.size
        c = self._t.cols
        t = float(t)
        if not math.isfinite(t):
            raise InvalidArgument("t", "must be finite", value=t)
        pos, quat = _check_rows("pos", pos, n, 3), _check_rows("quat", quat, n, 4)
        vel, acc, omega = (_shaped(name, v, (n, 3)) for name, v in (("vel", vel), ("acc", acc), ("omega", omega)))
        send, codes = np.empty(n, bool), np.empty(n, np.int64)
        rows = (np.ascontiguousarray(a) for a in (pos, vel, acc, quat, omega))
        _publish_kernel(t, np.ascontiguousarray(k, np.int64), *rows,
                        c["algorithm"], c["t0"], c["pos"], c["vel"], c["acc"], c["quat"], c["omega"],
                        c["sent"], c["position_m"], c["orientation_rad"], c["heartbeat_s"], send, codes)
        return send, codes

    def algorithm(self, ids) -> np.ndarray:
        """(n,) DIS codes the entities' updates carry."""
        return self._t.cols["algorithm"][self._t.slots(_check_ids(ids))].copy()

    def last_sent(self, ids) -> dict:
        """The last state sent of each entity: what every receiver extrapolates from (a
        newcomer must get exactly this). Arrays t0 (n,), pos, vel, acc, omega (n, 3),
        quat (n, 4), algorithm (n,); rows of entities never sent are zeros (t0 = 0)."""
        k = self._t.slots(_check_ids(ids))
        return {name: self._t.cols[name][k].copy() for name in _STATE_COLUMNS}


class Extrapolator:
    """The receiver's side: the last update of each entity, extrapolated on demand.

    Entities appear with their first update and stay until removed; an update
    older than the one held (out-of-order delivery) is ignored. Each entity is
    one (17,) row (:data:`ROW_COLUMNS`) and an algorithm code, so a message's
    states are checked and stored as a block.
    """

    def __init__(self):
        self._t = _Table({"rows": ((ROW_WIDTH,), np.float64), "algorithm": ((), np.int64)})
        _warm_merge()

    @property
    def ids(self) -> np.ndarray:
        """(m,) int64 entity ids, ascending: the row order of :meth:`state` without ids."""
        return self._t.ids.copy()

    def __len__(self) -> int:
        return self._t.ids.size

    def receive(self, t0, ids, pos, vel, acc, quat, omega, algorithm) -> None:
        """Updates of entities ids taken at times t0 (s, scalar or (n,)); rows as in
        :func:`extrapolate`, algorithm a DIS code or (n,) codes."""
        ids = _fast_ids(ids)
        self._merge(ids, _rows_of(ids.size, t0, pos, vel, acc, quat, omega), algorithm)

    def receive_rows(self, ids, rows, algorithm) -> None:
        """:meth:`receive` of states already side by side, as a parsed message has them:
        rows (n, 17) float64 in :data:`ROW_COLUMNS` order; the same checks and errors."""
        self._merge(_fast_ids(ids), rows, algorithm)

    def _merge(self, ids: np.ndarray, rows, algorithm) -> None:
        """The compiled pass when it takes the update (every entity held, nothing to
        name), else the checks in receive's order and the numpy merge."""
        n = ids.size
        if not (isinstance(rows, np.ndarray) and rows.dtype == np.float64 and rows.shape == (n, ROW_WIDTH)
                and isinstance(algorithm, np.ndarray) and algorithm.dtype == np.int64 and algorithm.shape == (n,)
                and _merge_held(self._t.ids, self._t.cols["rows"], self._t.cols["algorithm"], ids, rows, algorithm)):
            self._keep_newest(ids, _checked_rows(rows, n), check_algorithms(algorithm, n))

    def _keep_newest(self, ids: np.ndarray, rows: np.ndarray, algorithm: np.ndarray) -> None:
        """Insert unknown entities; overwrite known ones unless the held update is newer."""
        k, known = self._t._find(ids)
        if not known.all():
            new = ~known
            self._t.insert(ids[new], {"rows": rows[new], "algorithm": algorithm[new]})
            ids, rows, algorithm = ids[known], rows[known], algorithm[known]
            if not ids.size:
                return
            k = self._t.slots(ids)
        held = self._t.cols
        newer = rows[:, 0] >= held["rows"][k, 0]
        if not newer.all():
            k, rows, algorithm = k[newer], rows[newer], algorithm[newer]
        held["rows"][k] = rows
        held["algorithm"][k] = algorithm

    def remove(self, ids) -> None:
        self._t.delete(_fast_ids(ids))

    def state(self, t, ids=None):
        """(pos (n, 3) ECEF m, quat (n, 4) ECEF -> body) extrapolated to time t (s):
        of ids, or of every entity in :attr:`ids` order."""
        k = np.arange(self._t.ids.size) if ids is None else self._t.slots(_fast_ids(ids))
        rows = self._t.cols["rows"][k]
        return extrapolate(self._t.cols["algorithm"][k], *(rows[:, c] for c in ROW_COLUMNS.values()),
                           _check_times("t", t, k.size))
