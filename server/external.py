"""External entities: states another simulation publishes through a gateway.

Pure validation of what a gateway sends (server/sim_service.py PublishExternal,
server/dis_gateway.py), kept apart from the world so a gateway can check a
state before sending it without loading the flight model. The world
(server/world.py) holds the validated states and dead-reckons them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from server.dead_reckoning import check_algorithms
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


@dataclass(frozen=True)
class ExternalState:
    """An external entity's last published state (ECEF, SI; orientation ECEF -> body),
    valid at world time ``t0_s``; extrapolated by DIS ``algorithm``."""

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
    quaternion of norm 0.5-2 (normalised here), a DIS world-coordinate algorithm (1-5), and
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
    if not 0.5 <= norm <= 2.0:
        raise InvalidArgument("state.orientation_wxyz", "must be a unit quaternion", value=q.tolist())
    try:
        code = int(check_algorithms(int(algorithm), 1)[0])
    except InvalidArgument as exc:  # the request's field, not the library's parameter
        raise exc.with_field("state.dead_reckoning") from None
    return ExternalState(float(t0_s), pos,
                         _bounded_vector("state.velocity_ecef_mps", vel_ecef_mps, MAX_SPEED_MPS, "m/s"),
                         _bounded_vector("state.acceleration_ecef_mps2", acc_ecef_mps2, MAX_ACCELERATION_MPS2,
                                         "m/s^2"),
                         tuple((q / norm).tolist()),
                         _bounded_vector("state.angular_velocity_body_rps", body_rates_rps, MAX_BODY_RATE_RPS,
                                         "rad/s"), code)
