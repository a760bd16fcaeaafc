"""Aircraft state in SI units: the raw JSBSim snapshot and its conversion.

The hot loop copies a fixed list of JSBSim properties (imperial, JSBSim's own
names: they never leave ``fdm/``) into a float64 row; :func:`state_arrays`
turns any number of such rows (many aircraft, or many instants of one) into SI
arrays in one vectorised pass, and :class:`AircraftState` is one row of that
with named fields. Converting lazily keeps the per-step cost to the copy.

Frames and conventions (argument order is always (lat, lon)):

- geodetic WGS84 latitude/longitude in degrees; ``alt_msl_m`` is JSBSim's
  geodetic altitude. JSBSim's "sea level" *is* the WGS84 ellipsoid (it has no
  geoid), and the terrain heights we feed it are MSL (EGM96 for SRTM), so
  inside the simulation MSL and ellipsoid coincide. ECEF is built from
  ``alt_msl_m + geoid_undulation_m`` (the host passes the undulation N of its
  region; default 0), so ECEF is exact to the host's geoid model.
- NED velocity (north, east, down), ECEF velocity rotated from it.
- attitude: Euler (roll phi, pitch theta, yaw psi; aerospace z-y-x sequence)
  and the unit quaternion (w, x, y, z) of the same rotation local NED -> body
  (Stevens & Lewis, *Aircraft Control and Simulation*, 3rd ed., eq. 1.8-17),
  with w >= 0.
- body rates p, q, r (rad/s); body accelerations udot, vdot, wdot of the
  body-axis velocity (m/s^2) and the pilot's load factor n_z (g, positive
  up as the pilot feels it, JSBSim ``accelerations/Nz``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from terrain.geodesy import enu_basis, geodetic_to_ecef

# International foot, exact by definition (NIST SP 811, appendix B.8).
FT_M = 0.3048
# International knot: 1852 m per hour, exact (NIST SP 811, appendix B.8).
KT_MPS = 1852.0 / 3600.0

# The raw snapshot: (column name, JSBSim property). Order is the row layout.
RAW_PROPERTIES = (
    ("time_s", "simulation/sim-time-sec"),
    ("lat_rad", "position/lat-geod-rad"),
    ("lon_rad", "position/long-gc-rad"),
    ("alt_ft", "position/geod-alt-ft"),
    ("v_north_fps", "velocities/v-north-fps"),
    ("v_east_fps", "velocities/v-east-fps"),
    ("v_down_fps", "velocities/v-down-fps"),
    ("phi_rad", "attitude/phi-rad"),
    ("theta_rad", "attitude/theta-rad"),
    ("psi_rad", "attitude/psi-rad"),
    ("p_rps", "velocities/p-rad_sec"),
    ("q_rps", "velocities/q-rad_sec"),
    ("r_rps", "velocities/r-rad_sec"),
    ("udot_fps2", "accelerations/udot-ft_sec2"),
    ("vdot_fps2", "accelerations/vdot-ft_sec2"),
    ("wdot_fps2", "accelerations/wdot-ft_sec2"),
    ("nz_g", "accelerations/Nz"),
    ("vt_fps", "velocities/vt-fps"),
    ("vc_kts", "velocities/vc-kts"),
    ("alpha_rad", "aero/alpha-rad"),
    ("beta_rad", "aero/beta-rad"),
    ("wow", "gear/wow"),
    # Last: filled by the host with the terrain under the CG it fed JSBSim (not read back).
    ("terrain_ft", "position/terrain-elevation-asl-ft"),
)
RAW_COLUMNS = {name: k for k, (name, _) in enumerate(RAW_PROPERTIES)}
RAW_WIDTH = len(RAW_PROPERTIES)


def euler_to_quaternion(phi, theta, psi):
    """(..., 4) unit quaternions (w, x, y, z), NED -> body, from z-y-x Euler angles (rad).

    Stevens & Lewis, 3rd ed., eq. 1.8-17; the sign is fixed so that w >= 0.
    """
    cr, sr = np.cos(np.multiply(phi, 0.5)), np.sin(np.multiply(phi, 0.5))
    cp, sp = np.cos(np.multiply(theta, 0.5)), np.sin(np.multiply(theta, 0.5))
    cy, sy = np.cos(np.multiply(psi, 0.5)), np.sin(np.multiply(psi, 0.5))
    q = np.stack(np.broadcast_arrays(cr * cp * cy + sr * sp * sy,
                                     sr * cp * cy - cr * sp * sy,
                                     cr * sp * cy + sr * cp * sy,
                                     cr * cp * sy - sr * sp * cy), axis=-1)
    return np.where(q[..., :1] < 0.0, -q, q)


def ned_to_ecef_vectors(v_ned, lat_deg, lon_deg):
    """Rotate (..., 3) local (north, east, down) vectors at (lat, lon) degrees into ECEF."""
    east, north, up = enu_basis(lat_deg, lon_deg)
    v = np.asarray(v_ned, dtype=np.float64)
    return v[..., :1] * north + v[..., 1:2] * east - v[..., 2:3] * up


def state_arrays(raw, geoid_undulation_m=0.0) -> dict:
    """SI arrays from raw snapshot rows (..., RAW_WIDTH); one vectorised pass.

    Returns a dict of arrays whose leading shape is the rows' leading shape;
    vector quantities gain a last axis of 3 (or 4 for the quaternion).
    """
    raw = np.asarray(raw, dtype=np.float64)
    c = RAW_COLUMNS

    def col(name):
        return raw[..., c[name]]

    lat = np.degrees(col("lat_rad"))
    lon = np.degrees(col("lon_rad"))
    alt = col("alt_ft") * FT_M
    terrain = col("terrain_ft") * FT_M
    v_ned = np.stack([col("v_north_fps"), col("v_east_fps"), col("v_down_fps")], axis=-1) * FT_M
    euler = np.stack([col("phi_rad"), col("theta_rad"), col("psi_rad")], axis=-1)
    return {
        "time_s": col("time_s").copy(),
        "lat_deg": lat,
        "lon_deg": lon,
        "alt_msl_m": alt,
        "ecef_m": geodetic_to_ecef(lat, lon, alt + geoid_undulation_m),
        "vel_ned_mps": v_ned,
        "vel_ecef_mps": ned_to_ecef_vectors(v_ned, lat, lon),
        "euler_rad": euler,
        "quat_wxyz": euler_to_quaternion(euler[..., 0], euler[..., 1], euler[..., 2]),
        "body_rates_rps": np.stack([col("p_rps"), col("q_rps"), col("r_rps")], axis=-1),
        "accel_body_mps2": np.stack([col("udot_fps2"), col("vdot_fps2"), col("wdot_fps2")], axis=-1) * FT_M,
        "load_factor_g": col("nz_g").copy(),
        "airspeed_true_mps": col("vt_fps") * FT_M,
        "airspeed_cal_mps": col("vc_kts") * KT_MPS,
        "alpha_rad": col("alpha_rad").copy(),
        "beta_rad": col("beta_rad").copy(),
        "terrain_msl_m": terrain,
        "agl_m": alt - terrain,
        "on_ground": col("wow") > 0.5,
    }


@dataclass(frozen=True)
class AircraftState:
    """One aircraft at one instant, SI units (see the module docstring for frames).

    Scalars are Python floats; vectors are float64 numpy arrays.
    """

    time_s: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    ecef_m: np.ndarray  # (3,) float64
    vel_ned_mps: np.ndarray  # (3,) north, east, down
    vel_ecef_mps: np.ndarray  # (3,)
    euler_rad: np.ndarray  # (3,) roll, pitch, yaw (true heading)
    quat_wxyz: np.ndarray  # (4,) NED -> body
    body_rates_rps: np.ndarray  # (3,) p, q, r
    accel_body_mps2: np.ndarray  # (3,) udot, vdot, wdot
    load_factor_g: float
    airspeed_true_mps: float
    airspeed_cal_mps: float
    alpha_rad: float
    beta_rad: float
    terrain_msl_m: float
    agl_m: float
    on_ground: bool

    @classmethod
    def from_raw(cls, row, geoid_undulation_m: float = 0.0) -> "AircraftState":
        a = state_arrays(np.asarray(row, dtype=np.float64).reshape(RAW_WIDTH), geoid_undulation_m)
        return cls(**{k: (v if np.ndim(v) else v.item()) for k, v in a.items()})

    @property
    def heading_deg(self) -> float:
        """True heading in [0, 360)."""
        return float(np.degrees(self.euler_rad[2]) % 360.0)

    @property
    def ground_speed_mps(self) -> float:
        return float(np.hypot(self.vel_ned_mps[0], self.vel_ned_mps[1]))

    def is_finite(self) -> bool:
        """Every number finite (the hard-case tests' invariant)."""
        scalars = [self.time_s, self.lat_deg, self.lon_deg, self.alt_msl_m, self.load_factor_g,
                   self.airspeed_true_mps, self.airspeed_cal_mps, self.alpha_rad, self.beta_rad, self.agl_m]
        arrays = [self.ecef_m, self.vel_ned_mps, self.vel_ecef_mps, self.euler_rad, self.quat_wxyz,
                  self.body_rates_rps, self.accel_body_mps2]
        return bool(np.isfinite(scalars).all() and all(np.isfinite(a).all() for a in arrays))
