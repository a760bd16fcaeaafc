"""External entities: states another simulation publishes through a gateway.

Pure validation of what a gateway sends (server/sim_service.py PublishExternal,
server/dis_gateway.py), kept apart from the world so a gateway can check a
state before sending it without loading the flight model, and the dead
reckoning of those states (:func:`extrapolate_external`). The world
(server/world.py) holds the validated states and dead-reckons them each tick.

Dead reckoning. An external entity moves by the DIS algorithm its simulation
chose (IEEE 1278.1-2012 Annex E), world axes (1-5, server/dead_reckoning.py)
or body axes (6-9), natively: a body-axis sender sends a new state only when
the body-axis model drifts past its thresholds, so nothing else would keep
the world within them between its heartbeats (a world-axis stand-in for a
3 deg/s turn at 200 m/s is 130 m off after 5 s). Body axes (Annex E; R0 the
orientation sent, body -> ECEF; v_b, a_b the velocity and acceleration
sent, body axes; omega the body rates; dt = t - t0):

====== == ================================= ===================================
name   #  position P(t)                      velocity, orientation
====== == ================================= ===================================
FPB    6  P0 + R0 v_b dt                     R0 v_b, fixed
RPB    7  P0 + R0 R1 v_b                     R(t) v_b, rotating at omega
RVB    8  P0 + R0 (R1 v_b + R2 a_b)          R(t) (v_b + a_b dt), rotating
FVB    9  P0 + R0 (v_b dt + a_b dt^2 / 2)    R0 (v_b + a_b dt), fixed
====== == ================================= ===================================

R(t) = R0 DR(t), DR(t) the turn by |omega| dt about omega (the body turns
at constant body rates, server.dead_reckoning.rotate_body), and
R1 = int_0^dt DR(s) ds, R2 = int_0^dt DR(s) s ds, Annex E's closed forms:
with w = |omega|, a = w dt, [omega x] the cross-product matrix,

    R1 = (a - sin a) / w^3 omega omega^T + sin a / w I + (1 - cos a) / w^2 [omega x]
    R2 = (a^2 / 2 - cos a - a sin a + 1) / w^4 omega omega^T
         + (cos a + a sin a - 1) / w^2 I + (sin a - a cos a) / w^3 [omega x],

evaluated as dt^k times functions of a alone (:func:`_rotation_integral_terms`)
whose Taylor series stand in below SERIES_BELOW_RAD, where the closed forms
cancel (R1 -> dt I and R2 -> dt^2 / 2 I as omega -> 0, FPB's and FVB's).
The velocity is the position's derivative (dR1/dt = DR, dR2/dt = DR dt).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from server.dead_reckoning import ALGORITHM_NAMES, FVW, RVW, extrapolate, quat_conjugate, quat_multiply, rotate_body
from sortie.errors import InvalidArgument
from terrain.geodesy import WGS84_A_M, WGS84_B_M, ecef_to_geodetic

COALITIONS = ("blue", "red", "neutral")
MAX_TEXT_CHARS = 64  # external ids, names and types
# - position: within 100 km of the WGS84 ellipsoid, geodetic height (the Karman line; a
#   simulation's entities fly, drive or sail well inside it).
MAX_HEIGHT_M = 100_000.0
# Plausibility bounds, far above anything that moves within 100 km of the surface, so that
# no real entity is refused and garbage (a float32 1e30 from a DIS sender) never reaches the
# world's dead reckoning and the recording:
# - speed 20 km/s: Earth's escape velocity is 11.2 km/s; a ballistic missile re-enters at
#   about 7 km/s, the fastest air-breathing flight (X-43A, 2004) was about 3.3 km/s.
MAX_SPEED_MPS = 20_000.0
# - acceleration 1e4 m/s^2 (about 1,000 g): ten times the ~100 g of the Sprint interceptor,
#   the hardest-accelerating guided missile fielded; only a shell inside its gun barrel does more.
MAX_ACCELERATION_MPS2 = 1.0e4
# - body rate 1e5 rad/s: above a rifle bullet's spin (about 4,000 rev/s, 2.5e4 rad/s).
MAX_BODY_RATE_RPS = 1.0e5
# A published quaternion's norm within these is normalised (float32 round-off, a sender's scaling);
# outside them it is refused.
MIN_QUAT_NORM = 0.5
MAX_QUAT_NORM = 2.0
# IEEE 1278.1-2012 Annex E / SISO-REF-010 "Dead Reckoning Algorithm" (UID 44) body-axis codes:
# velocity and acceleration in the entity's own axes (the module docstring).
FPB, RPB, RVB, FVB = 6, 7, 8, 9
BODY_ALGORITHM_NAMES = {FPB: "FPB", RPB: "RPB", RVB: "RVB", FVB: "FVB"}
# Every code an external state may carry: the world-axis ones (server.dead_reckoning) and these.
EXTERNAL_ALGORITHM_NAMES = {**ALGORITHM_NAMES, **BODY_ALGORITHM_NAMES}
# Below this turn angle |omega| dt (rad) the rotation integrals' closed forms lose digits to
# cancellation (R2's omega omega^T term by eps / a^4: 2e-11 relative at 0.1); their Taylor
# series to a^6 are exact to rounding there (the next terms are below 1e-13 relative).
SERIES_BELOW_RAD = 0.1


@dataclass(frozen=True)
class ExternalState:
    """An external entity's last published state (ECEF, SI; orientation ECEF -> body),
    valid at world time ``t0_s``; extrapolated by DIS ``algorithm`` (1-9: for the body-axis
    ones, 6-9, the velocity and acceleration are in body axes, as the names of the fields
    do not say; see the module docstring)."""

    t0_s: float
    ecef_m: tuple
    vel_ecef_mps: tuple
    acc_ecef_mps2: tuple
    quat_ecef2body: tuple
    body_rates_rps: tuple
    algorithm: int


def _finite_vector(name: str, values, n: int) -> tuple:
    v = np.asarray(values, dtype=np.float64).reshape(-1)
    if v.size != n:
        raise InvalidArgument(name, f"must have {n} values, got {v.size}")
    bad = np.flatnonzero(~np.isfinite(v))
    if bad.size:
        raise InvalidArgument(name, "must be finite", index=int(bad[0]), value=float(v[bad[0]]))
    return tuple(v.tolist())


def _bounded_vector(name: str, values, limit: float, unit: str) -> tuple:
    """A finite 3-vector whose magnitude is at most ``limit`` (InvalidArgument naming it)."""
    v = _finite_vector(name, values, 3)
    magnitude = math.sqrt(sum(x * x for x in v))
    if magnitude > limit:
        raise InvalidArgument(name, f"magnitude {magnitude:.6g} {unit} is beyond the plausible {limit:g} {unit}",
                              value=list(v))
    return v


def external_state(t0_s: float, ecef_m, vel_ecef_mps, acc_ecef_mps2, quat_ecef2body, body_rates_rps,
                   algorithm: int) -> ExternalState:
    """A validated :class:`ExternalState` (InvalidArgument naming the field): finite values,
    a position within MAX_HEIGHT_M of the WGS84 ellipsoid (its geodetic height), a
    quaternion of norm 0.5-2 (normalised here), a DIS dead-reckoning algorithm (1-5 world
    axes, 6-9 body axes: then ``vel_ecef_mps`` and ``acc_ecef_mps2`` are in body axes), and
    magnitudes of velocity, acceleration and body rates within MAX_SPEED_MPS,
    MAX_ACCELERATION_MPS2 and MAX_BODY_RATE_RPS."""
    pos = _finite_vector("state.ecef_m", ecef_m, 3)
    r = math.sqrt(sum(x * x for x in pos))
    # A cheap bound first (every point within MAX_HEIGHT_M of the ellipsoid is within
    # [b - MAX_HEIGHT_M, a + MAX_HEIGHT_M] of the centre), then the geodetic height itself.
    height = math.inf
    if WGS84_B_M - MAX_HEIGHT_M <= r <= WGS84_A_M + MAX_HEIGHT_M:
        height = float(ecef_to_geodetic(np.array([pos], np.float64))[2][0])
    if not abs(height) <= MAX_HEIGHT_M:
        raise InvalidArgument("state.ecef_m", f"must be within {MAX_HEIGHT_M / 1000:g} km of the WGS84 ellipsoid "
                                              "(geodetic height)", value=[round(x, 3) for x in pos])
    q = np.array(_finite_vector("state.orientation_wxyz", quat_ecef2body, 4))
    norm = float(np.linalg.norm(q))
    if not MIN_QUAT_NORM <= norm <= MAX_QUAT_NORM:
        raise InvalidArgument("state.orientation_wxyz", f"must be a unit quaternion (a norm within "
                                                        f"{MIN_QUAT_NORM:g}-{MAX_QUAT_NORM:g} is normalised; this "
                                                        f"one's is {norm:.6g})", value=q.tolist())
    code = algorithm
    if isinstance(code, bool) or not isinstance(code, (int, np.integer)) or code not in EXTERNAL_ALGORITHM_NAMES:
        raise InvalidArgument("state.dead_reckoning", f"must be a DIS dead-reckoning code "
                                                      f"{sorted(EXTERNAL_ALGORITHM_NAMES)} "
                                                      f"({', '.join(EXTERNAL_ALGORITHM_NAMES.values())})",
                              value=algorithm)
    return ExternalState(float(t0_s), pos,
                         _bounded_vector("state.velocity_ecef_mps", vel_ecef_mps, MAX_SPEED_MPS, "m/s"),
                         _bounded_vector("state.acceleration_ecef_mps2", acc_ecef_mps2, MAX_ACCELERATION_MPS2,
                                         "m/s^2"),
                         tuple((q / norm).tolist()),
                         _bounded_vector("state.angular_velocity_body_rps", body_rates_rps, MAX_BODY_RATE_RPS,
                                         "rad/s"), int(code))


class ExternalTable:
    """The world's external entities' last states (entity id -> :class:`ExternalState`, a
    mapping in the order the entities came), kept beside that as columns for the tick's dead
    reckoning (:meth:`columns`). A state replaced or an entity added is written into its row
    (the columns grow by doubling); only a removal rebuilds them. Building the columns from the
    states each tick cost 11 ms a tick at 5,000 entities (a gateway's limit is the world's,
    10,000), most of the tick."""

    _FIELDS = (("t0", ()), ("pos", (3,)), ("vel", (3,)), ("acc", (3,)), ("quat", (4,)), ("rates", (3,)))

    def __init__(self):
        self._states: dict[int, ExternalState] = {}
        self._row: dict[int, int] = {}
        self._n = 0
        self._alloc(16)

    def _alloc(self, capacity: int) -> None:
        old = getattr(self, "_cols", None)
        cols = {name: np.zeros((capacity,) + shape, np.float64) for name, shape in self._FIELDS}
        cols["ids"] = np.zeros(capacity, np.int64)
        cols["algorithm"] = np.zeros(capacity, np.int64)
        if old is not None:
            for name, a in cols.items():
                a[:self._n] = old[name][:self._n]
        self._cols = cols

    def _write(self, r: int, entity_id: int, s: ExternalState) -> None:
        c = self._cols
        c["ids"][r], c["t0"][r], c["algorithm"][r] = entity_id, s.t0_s, s.algorithm
        c["pos"][r], c["vel"][r], c["acc"][r] = s.ecef_m, s.vel_ecef_mps, s.acc_ecef_mps2
        c["quat"][r], c["rates"][r] = s.quat_ecef2body, s.body_rates_rps

    def __setitem__(self, entity_id: int, state: ExternalState) -> None:
        r = self._row.get(entity_id)
        if r is None:
            if self._n == len(self._cols["ids"]):
                self._alloc(2 * self._n)
            r = self._row[entity_id] = self._n
            self._n += 1
        self._states[entity_id] = state
        self._write(r, entity_id, state)

    def pop(self, entity_id: int, default=None):
        state = self._states.pop(entity_id, None)
        if state is None:
            return default
        r = self._row.pop(entity_id)
        for a in self._cols.values():  # the rows after it move up one, in order
            a[r:self._n - 1] = a[r + 1:self._n]
        self._n -= 1
        for i in self._cols["ids"][r:self._n].tolist():
            self._row[i] -= 1
        return state

    def __getitem__(self, entity_id: int) -> ExternalState:
        return self._states[entity_id]

    def __contains__(self, entity_id) -> bool:
        return entity_id in self._states

    def __len__(self) -> int:
        return self._n

    def __iter__(self):
        return iter(self._states)

    def columns(self) -> tuple:
        """(ids, t0, pos, vel, acc, quat, rates, algorithm): (n,) and (n, k) arrays in the
        order the entities came, the states' values exactly (views: read, do not keep)."""
        c, n = self._cols, self._n
        return tuple(c[k][:n] for k in ("ids", "t0", "pos", "vel", "acc", "quat", "rates", "algorithm"))


# -- dead reckoning -------------------------------------------------------------------------------

def _rotation_integral_terms(a: np.ndarray) -> tuple:
    """(f1, s, g, h1, h2, h3), (n,) each, of turn angles a = |omega| dt (n,) rad, such that
    R1 = dt (f1 dt^2 omega omega^T + s I + g dt [omega x]) and
    R2 = dt^2 (h1 dt^2 omega omega^T + h2 I + h3 dt [omega x]) (module docstring):
    f1 = (a - sin a) / a^3, s = sin a / a, g = (1 - cos a) / a^2,
    h1 = (a^2 / 2 - cos a - a sin a + 1) / a^4, h2 = (cos a + a sin a - 1) / a^2,
    h3 = (sin a - a cos a) / a^3; below SERIES_BELOW_RAD their Taylor series (from those of
    sin and cos: h1's a^2n coefficient is (-1)^n (2n - 1) / (2n)!, h3's a^2k is
    (-1)^k 2 (k + 1) / (2k + 3)!)."""
    small = a < SERIES_BELOW_RAD
    big = np.where(small, 1.0, a)  # no division by 0 where the series stands in
    sin, cos = np.sin(big), np.cos(big)
    a2 = a * a
    closed = ((big - sin) / big ** 3, sin / big, (1.0 - cos) / big ** 2,
              (0.5 * big * big - cos - big * sin + 1.0) / big ** 4, (cos + big * sin - 1.0) / big ** 2,
              (sin - big * cos) / big ** 3)
    series = (1 / 6 - a2 / 120 + a2 ** 2 / 5040 - a2 ** 3 / 362880,
              1 - a2 / 6 + a2 ** 2 / 120 - a2 ** 3 / 5040,
              1 / 2 - a2 / 24 + a2 ** 2 / 720 - a2 ** 3 / 40320,
              1 / 8 - a2 / 144 + 7 * a2 ** 2 / 40320 - 9 * a2 ** 3 / 3628800,
              1 / 2 - a2 / 8 + a2 ** 2 / 144 - 7 * a2 ** 3 / 40320,
              1 / 3 - a2 / 30 + a2 ** 2 / 840 - a2 ** 3 / 45360)
    return tuple(np.where(small, s_, c_) for s_, c_ in zip(series, closed))


def _body_to_ecef(quat: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n, 3) ECEF components of body vectors v (n, 3) of orientations quat (n, 4) ECEF -> body:
    the vector part of q (0, v) q*."""
    zero = np.zeros(v.shape[:-1] + (1,))
    return quat_multiply(quat_multiply(quat, np.concatenate([zero, v], axis=-1)), quat_conjugate(quat))[..., 1:]


def extrapolate_external(algorithm, t0, pos, vel, acc, quat, omega, t) -> tuple:
    """(pos_t (n, 3) ECEF m, vel_t (n, 3) ECEF m/s, quat_t (n, 4) ECEF -> body) at world time t
    (scalar) of external states sent at t0 (n,) s: algorithm (n,) DIS codes 1-9; pos (n, 3) ECEF
    m; vel (n, 3) m/s and acc (n, 3) m/s^2, ECEF for codes 1-5 and body axes for 6-9; quat
    (n, 4) ECEF -> body; omega (n, 3) rad/s body axes. World codes go by
    server.dead_reckoning.extrapolate (velocity V0 + A0 dt for RVW and FVW, else V0), body
    codes by IEEE 1278.1-2012 Annex E (the module docstring)."""
    code = np.asarray(algorithm, np.int64)
    pos, vel, acc, quat, omega = (np.asarray(x, np.float64) for x in (pos, vel, acc, quat, omega))
    t0 = np.broadcast_to(np.asarray(t0, np.float64), code.shape)
    dt = float(t) - t0
    pos_t, vel_t, quat_t = pos.copy(), vel.copy(), quat.copy()
    world = code < FPB
    if world.any():
        pos_t[world], quat_t[world] = extrapolate(code[world], t0[world], pos[world], vel[world], acc[world],
                                                  quat[world], omega[world], t)
        accelerates = np.isin(code[world], (RVW, FVW))[:, None]
        vel_t[world] = vel[world] + np.where(accelerates, acc[world] * dt[world][:, None], 0.0)
    body = ~world
    if body.any():
        pos_t[body], vel_t[body], quat_t[body] = _extrapolate_body(code[body], dt[body], pos[body], vel[body],
                                                                   acc[body], quat[body], omega[body])
    return pos_t, vel_t, quat_t


def _extrapolate_body(code, dt, pos, v_b, a_b, quat, omega) -> tuple:
    """:func:`extrapolate_external` of body-axis rows (codes 6-9, dt (n,) s)."""
    rotating = np.isin(code, (RPB, RVB))
    a_b = np.where(np.isin(code, (RVB, FVB))[:, None], a_b, 0.0)
    w = np.where(rotating[:, None], omega, 0.0)  # FPB and FVB hold the orientation: R1 = dt I, R2 = dt^2 / 2 I
    f1, s, g, h1, h2, h3 = _rotation_integral_terms(np.linalg.norm(w, axis=-1) * np.abs(dt))
    d = dt[:, None]
    r1_v = d * ((f1[:, None] * d * d) * w * np.sum(w * v_b, -1, keepdims=True) + s[:, None] * v_b
                + (g[:, None] * d) * np.cross(w, v_b))
    r2_a = d * d * ((h1[:, None] * d * d) * w * np.sum(w * a_b, -1, keepdims=True) + h2[:, None] * a_b
                    + (h3[:, None] * d) * np.cross(w, a_b))
    quat_t = np.where(rotating[:, None], rotate_body(quat, w, dt), quat)
    return (pos + _body_to_ecef(quat, r1_v + r2_a), _body_to_ecef(quat_t, v_b + a_b * d), quat_t)
