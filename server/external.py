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

COALITIONS = ("blue", "red", "neutral")
MAX_TEXT_CHARS = 64  # external ids, names and types


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


def external_state(t0_s: float, ecef_m, vel_ecef_mps, acc_ecef_mps2, quat_ecef2body, body_rates_rps,
                   algorithm: int) -> ExternalState:
    """A validated :class:`ExternalState` (InvalidArgument naming the field): finite values,
    a position within 100 km of the WGS84 surface band (|r| in [6.25e6, 6.5e6] m), a
    quaternion of norm 0.5-2 (normalised here), a DIS world-coordinate algorithm (1-5)."""
    pos = _finite_vector("state.ecef_m", ecef_m, 3)
    r = math.sqrt(sum(x * x for x in pos))
    if not 6.25e6 <= r <= 6.5e6:
        raise InvalidArgument("state.ecef_m", "must be within 100 km of the Earth's surface (|r| in "
                                              "[6250, 6500] km)", value=[round(x, 3) for x in pos])
    q = np.array(_finite_vector("state.orientation_wxyz", quat_ecef2body, 4))
    norm = float(np.linalg.norm(q))
    if not 0.5 <= norm <= 2.0:
        raise InvalidArgument("state.orientation_wxyz", "must be a unit quaternion", value=q.tolist())
    code = int(check_algorithms(int(algorithm), 1)[0])
    return ExternalState(float(t0_s), pos, _finite_vector("state.velocity_ecef_mps", vel_ecef_mps, 3),
                         _finite_vector("state.acceleration_ecef_mps2", acc_ecef_mps2, 3),
                         tuple((q / norm).tolist()), _finite_vector("state.angular_velocity_body_rps",
                                                                    body_rates_rps, 3), code)
