"""Autopilots for bots: heading, altitude and speed hold, and waypoint following.

They sit on top of the aircraft's own flight control system and move only the
normalised pilot controls (:class:`fdm.aircraft.Controls`), like a pilot would:

- lateral: heading error -> bank command (proportional, limited) -> roll stick
  (PD on bank with roll-rate damping);
- longitudinal: altitude error -> flight-path-angle command (limited) ->
  pitch stick (PI on flight-path angle with pitch-rate damping); the
  integrator finds the stick that holds the trim, turns included, so the
  altitude settles without a steady error;
- speed: airspeed error -> throttle (PI, anti-windup by clamping); the error the
  throttle's range cannot correct moves the flight-path command (speed protection);
- yaw: sideslip damper on the pedals.

This is the classic successive-loop-closure structure (Beard & McLain, *Small
Unmanned Aircraft*, 2012, ch. 6: the inner attitude loops are closed first and
the outer loops are slower by a factor of 5-10). Gains are per aircraft class
(:data:`GAINS`), tuned by step responses on the c172x (light), the f16
(fighter, whose fly-by-wire FCS turns stick into g and roll-rate demands) and
the MD11, B747 and 787-8 (transport). Heavy jets add washed-out angle-of-attack
feedback to the pitch loop and a stall protection: beyond ``max_alpha_rad`` the
stick only moves forward. The f16 rolls into turns at a limited bank rate.

Every class keeps its load factor within 0.8 of its limit load (:data:`NZ_LIMIT_FRACTION`),
and an upset (beyond 60 degrees of bank, below -30 of pitch) is recovered before the hold
resumes: unload, wings level the shortest way, then pull out within the limit (:data:`UPSET_BANK_RAD`);
a nose-high one (pitch above 25 degrees, the flight path 10 above the hold's climb limit) is
unloaded to 0 g until the flight path is back within that limit (:data:`UPSET_NOSE_HIGH_PITCH_RAD`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from pyproj import Geod

from fdm.events import LIMITS
from fdm.state import FT_M, RAW_COLUMNS as _C
from sortie.errors import InvalidArgument

G = 9.80665  # standard gravity, m/s^2 (CGPM 1901)


@dataclass(frozen=True)
class Gains:
    max_bank_rad: float  # bank limit in turns
    k_heading: float  # bank (rad) per rad of heading error
    kp_bank: float  # roll stick per rad of bank error
    kd_roll_rate: float  # roll stick per rad/s of roll rate
    ki_bank: float  # roll stick per rad*s of bank error (propeller torque, asymmetry)
    k_alt: float  # flight-path angle (rad) per m of altitude error
    max_climb_rad: float
    max_descent_rad: float
    kp_pitch: float  # pitch stick per rad of flight-path-angle error
    ki_pitch: float  # pitch stick per rad*s
    kd_pitch_rate: float  # pitch stick per rad/s of pitch rate
    kp_speed: float  # throttle per m/s of speed error
    ki_speed: float  # throttle per m
    k_beta: float  # yaw pedal per rad of sideslip
    # Pitch stiffness: pitch stick per rad of angle of attack above its washed-out (low-passed)
    # value, and the low-pass time constant; 0 leaves the flight-path loop as it is.
    k_alpha: float = 0.0
    alpha_washout_s: float = 4.0
    # Stall protection: above this angle of attack the pitch stick moves no further aft.
    max_alpha_rad: float = math.inf
    # Bank command slew limit, rad/s: a heading step rolls in at this rate rather than at full
    # stick (the f16 answers a full roll stick with a load-factor dip below -1 g).
    max_bank_rate_rad_s: float = math.inf


GAINS = {
    "light": Gains(max_bank_rad=math.radians(25), k_heading=1.2, kp_bank=2.0, kd_roll_rate=0.3, ki_bank=0.3,
                   k_alt=0.003, max_climb_rad=math.radians(6),
                   max_descent_rad=math.radians(-6), kp_pitch=3.0, ki_pitch=1.0, kd_pitch_rate=0.8,
                   kp_speed=0.08, ki_speed=0.01, k_beta=1.0),
    # Re-tuned here on the f16 at 200 m/s, 3000 m by a grid over k_alt, kp/ki/kd_pitch on a
    # combined +200 m, +30 deg step (overshoot 5 m, within 5 m after 24 s, 0.4..2.4 g).
    "fighter": Gains(max_bank_rad=math.radians(45), k_heading=3.0, kp_bank=1.5, kd_roll_rate=0.2, ki_bank=0.2,
                     k_alt=0.001, max_climb_rad=math.radians(10),
                     max_descent_rad=math.radians(-10), kp_pitch=3.0, ki_pitch=0.3, kd_pitch_rate=0.8,
                     kp_speed=0.05, ki_speed=0.01, k_beta=0.5, max_bank_rate_rad_s=0.4),
    # Heavy jets without a stability augmentation system: the MD11's short period is slow, so
    # the flight-path loop needs a stiff pitch loop (high proportional and pitch-rate gains and
    # washed-out alpha feedback) and a slower altitude loop (k_alt * 150 m/s: a 6.7 s time
    # constant). Tuned here by step responses (+-300 m, +30 deg, holds of 240 s) on the MD11,
    # B747 and 787-8 at 140-150 m/s and 3000 m; the stall limit lies below the MD11's lift peak
    # (CL max at alpha 0.23 rad, 13.2 deg, in its aero tables).
    "transport": Gains(max_bank_rad=math.radians(25), k_heading=1.2, kp_bank=2.0, kd_roll_rate=0.3, ki_bank=0.3,
                       k_alt=0.001, max_climb_rad=math.radians(5),
                       max_descent_rad=math.radians(-5), kp_pitch=8.0, ki_pitch=0.3, kd_pitch_rate=8.0,
                       kp_speed=0.08, ki_speed=0.01, k_beta=1.0, k_alpha=3.0, alpha_washout_s=4.0,
                       max_alpha_rad=math.radians(10)),
}

# On the ground the heading is steered with the pedals: full pedal at this many radians of
# heading error and more (a pedal of 1 per 0.5 rad, 29 degrees: tuned here on the c172x).
G_STEER = 2.0
# With weight on wheels the heading the pedals steer to moves towards the target no faster than a
# turn of this lateral acceleration (m/s^2, about 0.1 g) allows at the ground speed v: a turn rate
# of ROLL_LATERAL_ACCEL_MPS2 / v (a level turn's a = v * turn rate). A steered nose wheel turns
# the aircraft on a path of curvature tan(delta) / wheelbase (the kinematic, "bicycle", model:
# Rajamani, Vehicle Dynamics and Control, 2nd ed., 2012, sec. 2.2), so full pedal asks for
# v^2 tan(delta) / wheelbase: on the c172p (10 degrees, 1.65 m: c172p.xml) 72 m/s^2 at 26 m/s,
# where its tyres hold 4.9 (dynamic friction 0.5), and a 90-degree heading step on the take-off
# roll ground-looped it onto a wing tip. A taxi still turns: at 2 m/s this allows 29 degrees a
# second, more than the c172p's tightest turn there (9.4 m at full pedal: 12 degrees a second), at
# 5 m/s 11 (a 90-degree turn in 8 s). And the runway's heading is held with the pedals' full
# authority (the c172x needs 0.6 pedal against its propeller at 18 m/s): limiting the pedal instead
# (by (5 m/s / v)^2) let it veer 32 degrees off the runway.
ROLL_LATERAL_ACCEL_MPS2 = 1.0

# Raw row columns read each update, looked up once.
_TIME, _LAT, _LON, _ALT = _C["time_s"], _C["lat_rad"], _C["lon_rad"], _C["alt_ft"]
_VN, _VE, _VD, _VT = _C["v_north_fps"], _C["v_east_fps"], _C["v_down_fps"], _C["vt_fps"]
_PHI, _PSI, _P, _Q, _BETA = _C["phi_rad"], _C["psi_rad"], _C["p_rps"], _C["q_rps"], _C["beta_rad"]
_ALPHA, _THETA, _TERRAIN = _C["alpha_rad"], _C["theta_rad"], _C["terrain_ft"]
_NZ = _C["nz_g"]

# Stall protection: pitch stick per second, per rad of angle of attack beyond max_alpha_rad,
# by which the stick is walked forward (tuned here: 1 deg beyond moves it 0.035 a second).
_STALL_PUSH_PER_RAD_S = 2.0


# Load-factor limiter. fdm.events.LIMITS holds each class's ultimate load, 1.5 x its limit load
# (the factor of safety of 14 CFR 23.303 / 25.303); limit loads +3.8 / -1.52 g for normal-category
# light aeroplanes (14 CFR 23.337), +2.5 / -1 g for transports (14 CFR 25.337), +9 / -3 g for
# fighters (MIL-A-8861B). The pitch stick keeps the load factor within NZ_LIMIT_FRACTION of the
# limit load, a margin for the overshoot of a limiter that acts on the measured load factor: past
# it the stick moves no further that way and walks back, faster the further past (like the stall
# protection). A c172x given full aft stick at 76 m/s reached 9.8 g in 0.27 s.
SAFETY_FACTOR = 1.5
NZ_LIMIT_FRACTION = 0.8
# Pitch stick per second per g past the limiter's load factor (tuned here on the c172x upsets).
_NZ_PUSH_PER_G_S = 1.0

# Upset recovery (FAA Airplane Flying Handbook, FAA-H-8083-3C, 2021, ch. 5, and the Airplane Upset
# Prevention and Recovery Training Aid, rev. 3, 2017, nose-low recovery: unload, roll in the
# shortest direction to wings level, then recover to level flight within the g limits). Beyond
# UPSET_BANK_RAD of bank or below UPSET_PITCH_RAD of pitch (the Training Aid's definition of an
# upset: bank beyond 45 degrees, pitch below -10; wider here, as the holds bank to 45 themselves)
# the altitude hold's flight-path loop stands down: the pitch stick holds a load factor, first
# unloaded to the 1 g the wings give at the bank, cos(bank), never below 0 g (the lift never pulls
# toward the ground) while the roll loop levels the wings, then, within PULL_BANK_RAD of level,
# pulls out at UPSET_PULL_FRACTION of the limit load until the flight path is back within the
# hold's descent limit, where the hold takes over from the stick where it is. Handed a spiral dive
# (bank 107..173 degrees, pitch -22..-64), the old hold pulled a c172x to 5.8..9.8 g in under 0.8 s.
UPSET_BANK_RAD = math.radians(60.0)
UPSET_PITCH_RAD = math.radians(-30.0)
PULL_BANK_RAD = math.radians(30.0)
UPSET_PULL_FRACTION = 0.8
# Nose-high upset (the Training Aid's nose-high recovery: unload, a nose-down pitch rate, until the
# nose is back; its upset: pitch beyond +25 degrees). Entered beyond UPSET_NOSE_HIGH_PITCH_RAD of
# pitch with the flight path UPSET_NOSE_HIGH_MARGIN_RAD above the hold's climb limit: the pitch stick
# holds NOSE_HIGH_UNLOAD_G (cos(bank) if less) until the flight path is back within that limit, where
# the hold takes over. The hold's flight-path loop alone pushed full forward at once: an f16 handed
# over in a 52-degree zoom at 7.3 g (a pilot leaving mid-manoeuvre) reached -3.9 g, past its -3 g
# limit load, before the load-factor limiter, walking the stick back, caught it.
UPSET_NOSE_HIGH_PITCH_RAD = math.radians(25.0)
UPSET_NOSE_HIGH_MARGIN_RAD = math.radians(10.0)
NOSE_HIGH_UNLOAD_G = 0.0
# Pitch stick per second per g of load-factor error in the upset's load-factor loop (integral).
_UPSET_KI_PER_G_S = 0.2


# Heading error (rad) beyond which a turn keeps the way it began (170 degrees).
REVERSAL_RAD = math.radians(170.0)

# Speed protection: the time constant (s) in which the flight path gives back a speed error the
# throttle cannot (tuned here on the c172x climb-out and the 787-8 / MD11 descents).
SPEED_PROTECTION_TAU_S = 5.0
# The fraction of a climb's angle that speed protection leaves.
CLIMB_KEPT = 0.5
# The time constant (s) of the low-pass on the speed error the throttle cannot correct.
PROTECTION_LAG_S = 2.0


def _speed_protected(gamma_cmd: float, speed_excess_mps: float) -> float:
    """The flight-path angle command (rad) that gives way to a speed error the throttle cannot
    correct (``speed_excess_mps`` > 0 too slow at full power, < 0 too fast at idle).

    Along the flight path dV/dt = g (T - D) / W - g sin(gamma) (the point-mass energy equation;
    Lambregts, "Vertical flight path and speed control autopilot design using total energy
    principles", AIAA 83-2239, 1983, the basis of TECS), so an acceleration a asks the path for
    a / g radians less. The error is given back in SPEED_PROTECTION_TAU_S. A descent is traded
    down to level flight and never further; a climb down to CLIMB_KEPT of its angle: the altitude
    loop's direction stands, and a too slow aircraft still climbs away from the terrain (from a
    lift-off well below its target speed, a level path would hold it in ground effect).
    """
    gamma = gamma_cmd - speed_excess_mps / (SPEED_PROTECTION_TAU_S * G)
    if gamma_cmd >= 0.0:
        return _clamp(gamma, CLIMB_KEPT * gamma_cmd, gamma_cmd)
    return _clamp(gamma, gamma_cmd, 0.0)


# With weight on wheels and an altitude target this far (m) above, the roll is a take-off.
TAKE_OFF_ABOVE_M = 10.0

# On the runway the pitch attitude stays this far (rad, 3 degrees) below the tail strike's.
TAIL_STRIKE_MARGIN_RAD = math.radians(3.0)


def tail_strike_pitch_rad(contacts) -> float:
    """The pitch attitude (rad) at which a structure contact aft of the aft-most wheels meets level
    ground while those wheels stay on it: the least angle up from the wheels to such a point in
    the structural frame (JSBSim: x aft, z up; ``contacts`` as fdm.aircraft.Aircraft.contacts).
    Strut compression is left out, so the true angle is a little less. Infinite where no structure
    contact lies aft of the wheels (a tail wheel is aft-most: its tail cannot strike)."""
    wheels = [c.location_in for c in contacts if c.kind != "structure"]
    if not wheels:
        return math.inf
    xb = max(w[0] for w in wheels)
    zb = min(w[2] for w in wheels if w[0] == xb)
    angles = [math.atan2(c.location_in[2] - zb, c.location_in[0] - xb) for c in contacts
              if c.kind == "structure" and c.location_in[0] > xb]
    return min(angles, default=math.inf)


# After a take-off the wings are held within LEVEL_BANK_RAD of level until the aircraft is
# LEVEL_AGL_M above the ground (ArduPlane's TAKEOFF mode: wings level below TKOFF_LVL_ALT, 20 m,
# within LEVEL_ROLL_LIMIT, 5 degrees; ArduPilot, ArduPlane/mode_takeoff.cpp and Parameters.cpp).
# A heading still to turn at lift-off banked a J3Cub 27 degrees at 3 m and 20 m/s, and it stalled;
# a 787-8 turning as it lifted off struck the runway ("structure contact") 2 s later.
LEVEL_AGL_M = 20.0
LEVEL_BANK_RAD = math.radians(5.0)
# Heading trim: the bank the heading loop's proportional term would need a standing error for
# (a constant true heading is a rhumb line, which curves against the great circle a wings-level
# aircraft flies: at 60 S an f16 held 90 with a 0.1 degree error and drifted 1.4 km north in
# 830 km; a model's own asymmetry) is integrated in near the target: within HEADING_TRIM_ZONE_RAD
# of it, at k_heading / HEADING_TRIM_TAU_S per second, at most HEADING_TRIM_MAX_BANK_RAD of bank.
# Outside the zone (a turn) it is not used and starts again from 0 (it holds no windup from a turn).
HEADING_TRIM_ZONE_RAD = math.radians(2.0)
HEADING_TRIM_TAU_S = 10.0
HEADING_TRIM_MAX_BANK_RAD = math.radians(3.0)


# What a hold may be told (Autopilot.set_targets; server/scenario.py takes the same bounds for a
# scenario's altitudes and speeds, and the world for commands): a heading within a turn either
# way (wrapped), an altitude from the Dead Sea shore's -430 m (rounded down) to the Karman line,
# a speed below orbital.
TARGET_HEADING_ABS_MAX_DEG = 360.0
TARGET_ALT_MSL_MIN_M = -500.0
TARGET_ALT_MSL_MAX_M = 100_000.0
TARGET_SPEED_MAX_MPS = 8_000.0


def _check_positive(name: str, v) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        raise InvalidArgument(name, "must be a finite number", value=v)
    if v <= 0:
        raise InvalidArgument(name, "must be positive", value=v)


def _clamp(x: float, lo: float, hi: float) -> float:
    return lo if x < lo else hi if x > hi else x


def wrap_pi(a: float) -> float:
    """Angle in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))


def _row_values(aircraft, row):
    """The raw row as Python floats: ``row`` if given (a list, or an array made a list,
    as float arithmetic is cheaper than numpy scalars' and gives the same bits), else
    read from the aircraft."""
    if row is None:
        return aircraft.raw_values()
    return row.tolist() if isinstance(row, np.ndarray) else row


@dataclass
class Targets:
    """What the autopilot holds: true heading (deg), altitude (m MSL), true airspeed (m/s).
    None leaves that axis alone (its control stays where it is)."""

    heading_deg: float | None = None
    alt_msl_m: float | None = None
    speed_mps: float | None = None


class Autopilot:
    """Heading / altitude / speed hold for one :class:`fdm.aircraft.Aircraft`.

    Call :meth:`update` once per step before ``aircraft.step()`` (or use
    :meth:`run`), or once per ``dt_s`` of several steps, passing it (a host updates its
    pilots every 1/30 s: server.aircraft_host.PILOT_HZ; the integrators, slew limits and
    low-pass filters advance by the time that passes, so the tuning holds at either rate).
    The autopilot reads the raw state and writes controls; it keeps its integrators, so
    one autopilot flies one aircraft.
    """

    def __init__(self, aircraft, targets: Targets | None = None, gains: Gains | None = None):
        self.aircraft = aircraft
        self.gains = gains or GAINS[aircraft.aircraft_class]
        self.targets = targets or Targets()
        self._i_pitch = 0.0
        self._i_bank = 0.0
        self._i_speed = aircraft.controls.throttle
        self._alpha_lp = None  # low-passed angle of attack, rad (set on the first update)
        self._bank_cmd = None  # slew-limited bank command, rad
        self._stuck_mps = 0.0  # low-passed speed error the throttle cannot correct, m/s
        self._turn_sign = 0.0  # the way a reversal turns (+1 right, -1 left), 0 outside one
        self._i_heading = 0.0  # heading trim, rad of bank (HEADING_TRIM_*)
        self._ground_ref = None  # the heading the pedals steer to on the ground, rad (None: airborne)
        # The highest pitch attitude on the runway (rad): a pull from standstill struck the
        # c172p's tail skid (10 degrees up from its main wheels) at 3 m/s.
        self._max_ground_pitch = tail_strike_pitch_rad(getattr(aircraft, "contacts", ())) - TAIL_STRIKE_MARGIN_RAD
        self._lifting_off = False  # taken off, not yet LEVEL_AGL_M up: wings (nearly) level
        limits = LIMITS[aircraft.aircraft_class]
        self._nz_hi = NZ_LIMIT_FRACTION * limits.nz_max_g / SAFETY_FACTOR  # limiter's bounds, g
        self._nz_lo = NZ_LIMIT_FRACTION * limits.nz_min_g / SAFETY_FACTOR
        self._nz_pull = UPSET_PULL_FRACTION * limits.nz_max_g / SAFETY_FACTOR  # upset pull-out, g
        self._upset = False  # recovering from an upset (UPSET_*)
        self._nose_high = False  # that upset is nose-high (UPSET_NOSE_HIGH_*)
        self._i_upset = 0.0  # the upset recovery's integral of load-factor error, pitch stick

    def set_targets(self, heading_deg=None, alt_msl_m=None, speed_mps=None) -> None:
        """Hold a heading (degrees true, within a turn either way: TARGET_HEADING_ABS_MAX_DEG),
        an altitude (m MSL, TARGET_ALT_MSL_MIN_M..TARGET_ALT_MSL_MAX_M) and a speed (m/s true,
        positive, at most TARGET_SPEED_MAX_MPS); None leaves that axis unheld. A bad value is
        refused naming its field, and the targets held before are kept."""
        for name, v in (("heading_deg", heading_deg), ("alt_msl_m", alt_msl_m), ("speed_mps", speed_mps)):
            if v is not None and not (isinstance(v, (int, float)) and math.isfinite(v)):
                raise InvalidArgument(name, "must be a finite number", value=v)
        if speed_mps is not None:
            _check_positive("speed_mps", speed_mps)
            if speed_mps > TARGET_SPEED_MAX_MPS:
                raise InvalidArgument("speed_mps", f"must be at most {TARGET_SPEED_MAX_MPS:g} m/s", value=speed_mps)
        if heading_deg is not None and abs(heading_deg) > TARGET_HEADING_ABS_MAX_DEG:
            raise InvalidArgument("heading_deg", f"must be within [-{TARGET_HEADING_ABS_MAX_DEG:g}, "
                                  f"{TARGET_HEADING_ABS_MAX_DEG:g}] degrees true", value=heading_deg)
        if alt_msl_m is not None and not TARGET_ALT_MSL_MIN_M <= alt_msl_m <= TARGET_ALT_MSL_MAX_M:
            raise InvalidArgument("alt_msl_m", f"must be within [{TARGET_ALT_MSL_MIN_M:g}, {TARGET_ALT_MSL_MAX_M:g}] m "
                                  "MSL", value=alt_msl_m)
        self.targets = Targets(heading_deg, alt_msl_m, speed_mps)

    def _ground_steer_err(self, err: float, psi: float, r, dt: float) -> float:
        """The heading error (rad) the pedals steer by on the ground: from the heading they steer
        to, which follows the target (``err`` away from ``psi``, rad) at the turn rate of
        ROLL_LATERAL_ACCEL_MPS2 at the ground speed, starting from the heading on touching down."""
        if self._ground_ref is None:
            self._ground_ref = psi
        ground = math.hypot(r[_VN], r[_VE]) * FT_M
        most = ROLL_LATERAL_ACCEL_MPS2 * dt / ground if ground > 0.0 else math.inf
        # The way to the target from the reference: the way the target's error goes from the
        # heading (a reversal keeps its side), less the reference's lead on the heading.
        to_go = err - wrap_pi(self._ground_ref - psi)
        self._ground_ref = wrap_pi(self._ground_ref + _clamp(to_go, -most, most))
        return wrap_pi(self._ground_ref - psi)

    def _in_upset(self, r, rolling: bool) -> bool:
        """Whether the aircraft is (still) in an upset (UPSET_*): entered beyond the bank or below
        the pitch of an upset, left once the wings are within PULL_BANK_RAD of level and the
        flight path is back within the hold's descent limit; or nose-high (UPSET_NOSE_HIGH_*,
        ``_nose_high``), left once the flight path is back within the hold's climb limit."""
        if rolling:
            self._nose_high = False
            return False
        phi = abs(r[_PHI])
        v = max(math.sqrt(r[_VN] ** 2 + r[_VE] ** 2 + r[_VD] ** 2), 1.0)
        climb = -r[_VD] / v  # sine of the flight path angle
        if phi > UPSET_BANK_RAD or r[_THETA] < UPSET_PITCH_RAD:
            self._nose_high = False
            return True
        if (r[_THETA] > UPSET_NOSE_HIGH_PITCH_RAD
                and climb > math.sin(self.gains.max_climb_rad + UPSET_NOSE_HIGH_MARGIN_RAD)):
            self._nose_high = True
            return True
        if not self._upset:
            return False
        if self._nose_high:
            self._nose_high = phi >= PULL_BANK_RAD or climb > math.sin(self.gains.max_climb_rad)
            return self._nose_high
        return phi >= PULL_BANK_RAD or climb < math.sin(self.gains.max_descent_rad)

    def _upset_pitch(self, r, dt: float, entering: bool) -> float:
        """The pitch stick of an upset recovery: a load-factor command, unloaded to cos(bank) (at
        least 0 g) until the wings are within PULL_BANK_RAD of level, then the class's upset pull.
        The stick is an integral of the load-factor error plus the class's pitch-rate damping
        about the pitch rate that load factor turns at, q = g (nz - cos(theta) cos(phi)) / V (the
        body-axis normal force balance in a coordinated manoeuvre, small angle of attack): the
        heavy jets' slow short period set a pure integral oscillating beyond their limits."""
        g = self.gains
        phi = abs(r[_PHI])
        if self._nose_high:  # unloaded, whatever the bank
            nz_cmd = min(NOSE_HIGH_UNLOAD_G, max(math.cos(phi), 0.0))
        else:
            nz_cmd = self._nz_pull if phi < PULL_BANK_RAD else max(math.cos(phi), 0.0)
        v = max(r[_VT] * FT_M, 1.0)
        q_cmd = G * (nz_cmd - math.cos(r[_THETA]) * math.cos(phi)) / v
        damping = g.kd_pitch_rate * (q_cmd - r[_Q])
        if entering:  # from the stick where it stands
            self._i_upset = self.aircraft.controls.pitch - damping
        self._i_upset = _clamp(self._i_upset + _UPSET_KI_PER_G_S * (nz_cmd - r[_NZ]) * dt, -1.0, 1.0)
        return _clamp(self._i_upset + damping, -1.0, 1.0)

    def update(self, row=None, dt_s: float | None = None) -> None:
        """Read the state, write the controls for the next step (or the next ``dt_s``
        seconds of steps: the time the integrators advance by; None, one step).

        ``row``: the aircraft's current raw state (``raw_values()``, a list or a
        float64 array of fdm.state.RAW_WIDTH), for a host that has already read
        it for its snapshot; None reads it here. Same controls either way.
        """
        ac = self.aircraft
        r = _row_values(ac, row)
        g = self.gains
        dt = ac.dt if dt_s is None else dt_s
        phi, psi, p, q = r[_PHI], r[_PSI], r[_P], r[_Q]
        pitch = roll = yaw = throttle = None
        tg = self.targets
        # Weight on wheels: the take-off roll (or a landing's). Banking into a turn there drops
        # a wing tip onto the runway: wings are held level and the heading is steered with the
        # pedals (rudder and nose wheel), and the pitch loop's integrator waits (it would wind up
        # to full aft stick before the elevator can act, and over-rotate into a tail strike).
        rolling = ac.on_ground
        was_upset, self._upset = self._upset, self._in_upset(r, rolling)
        if tg.heading_deg is None:
            self._ground_ref = None
        else:
            err = wrap_pi(math.radians(tg.heading_deg) - psi)
            # A reversal: near 180 degrees the shorter way round flips with every jitter of the
            # heading, and the wings rocked from one bank to the other. Beyond REVERSAL_RAD the
            # turn keeps the way it took on entering that zone until it is out of it.
            if abs(err) <= REVERSAL_RAD:
                self._turn_sign = 0.0
            elif not self._turn_sign:
                self._turn_sign = 1.0 if err > 0.0 else -1.0
            elif err * self._turn_sign < 0.0:
                err = math.copysign(2.0 * math.pi - abs(err), self._turn_sign)
            if rolling or self._upset:  # an upset: wings level first, the shortest way
                bank_cmd = self._i_heading = 0.0
            else:
                most = g.max_bank_rad
                if self._lifting_off:
                    if (r[_ALT] - r[_TERRAIN]) * FT_M < LEVEL_AGL_M:
                        most = min(most, LEVEL_BANK_RAD)
                    else:
                        self._lifting_off = False
                if abs(err) < HEADING_TRIM_ZONE_RAD:
                    self._i_heading = _clamp(self._i_heading + g.k_heading / HEADING_TRIM_TAU_S * err * dt,
                                             -HEADING_TRIM_MAX_BANK_RAD, HEADING_TRIM_MAX_BANK_RAD)
                else:
                    self._i_heading = 0.0
                bank_cmd = _clamp(g.k_heading * err + self._i_heading, -most, most)
            if self._upset:  # at full roll authority; a slew resumes from the bank it leaves
                self._bank_cmd = phi
            elif g.max_bank_rate_rad_s < math.inf:
                last = phi if self._bank_cmd is None else self._bank_cmd
                step = g.max_bank_rate_rad_s * dt
                bank_cmd = self._bank_cmd = _clamp(bank_cmd, last - step, last + step)
            e = bank_cmd - phi
            u = g.kp_bank * e + self._i_bank - g.kd_roll_rate * p
            if -1.0 < u < 1.0:
                self._i_bank = _clamp(self._i_bank + g.ki_bank * e * dt, -0.5, 0.5)
            roll = _clamp(u, -1.0, 1.0)
            if rolling:
                yaw = _clamp(G_STEER * self._ground_steer_err(err, psi, r, dt), -1.0, 1.0)
            else:
                self._ground_ref = None
                yaw = _clamp(-g.k_beta * r[_BETA], -1.0, 1.0)
        # Speed first: where the throttle cannot hold the speed (at idle too fast, at full power
        # too slow), the flight-path command below gives way to it.
        speed_excess = 0.0
        if tg.speed_mps is not None:
            e = tg.speed_mps - r[_VT] * FT_M
            u = g.kp_speed * e + self._i_speed
            if 0.0 < u < 1.0:
                self._i_speed = _clamp(self._i_speed + g.ki_speed * e * dt, 0.0, 1.0)
            throttle = _clamp(u, 0.0, 1.0)
            if rolling and tg.alt_msl_m is not None and tg.alt_msl_m > r[_ALT] * FT_M + TAKE_OFF_ABOVE_M:
                # A take-off: full power on the roll, whatever the target speed (one at or below the
                # lift-off speed held on the runway never lifted off under the attitude limit below).
                throttle = 1.0
                self._lifting_off = True
            # The speed error the throttle cannot correct from where it stands (m/s): too slow
            # at full power, too fast at idle; low-passed, so that the path command does not
            # step when the throttle reaches a stop. None on the runway: a take-off roll is slow
            # by nature, and the climb-out starts from where lift-off leaves it.
            stuck = e if not rolling and ((throttle >= 1.0 and e > 0.0) or (throttle <= 0.0 and e < 0.0)) else 0.0
            self._stuck_mps += (stuck - self._stuck_mps) * min(dt / PROTECTION_LAG_S, 1.0)
            speed_excess = self._stuck_mps
            if ac.controls.brakes and throttle > 0.0:
                # Holding a speed it has not reached, a pilot lets the brakes off (a ground
                # start sets them, fdm.aircraft): a route from the ground is a take-off.
                ac.set_controls(brakes=0.0)
        if tg.alt_msl_m is not None:
            vn, ve, vd = r[_VN], r[_VE], r[_VD]
            v = max(math.sqrt(vn * vn + ve * ve + vd * vd), 1.0)
            gamma = math.asin(_clamp(-vd / v, -1.0, 1.0))
            gamma_cmd = _clamp(g.k_alt * (tg.alt_msl_m - r[_ALT] * FT_M), g.max_descent_rad,
                               g.max_climb_rad)
            if speed_excess and not rolling:
                gamma_cmd = _speed_protected(gamma_cmd, speed_excess)
            e = gamma_cmd - gamma
            u = g.kp_pitch * e + self._i_pitch - g.kd_pitch_rate * q
            alpha = r[_ALPHA]
            if g.k_alpha:
                if self._alpha_lp is None:
                    self._alpha_lp = alpha
                self._alpha_lp += (alpha - self._alpha_lp) * min(dt / g.alpha_washout_s, 1.0)
                u -= g.k_alpha * (alpha - self._alpha_lp)
            if self._upset:
                u = self._upset_pitch(r, dt, not was_upset)
            elif was_upset:  # the hold takes over from the recovery's stick, without a jump
                self._i_pitch = _clamp(self._i_pitch + ac.controls.pitch - u, -1.0, 1.0)
                u = ac.controls.pitch
            stalling = alpha > g.max_alpha_rad
            if stalling:  # no further aft than now: forward, faster the deeper into the stall
                u = min(u, ac.controls.pitch - _STALL_PUSH_PER_RAD_S * (alpha - g.max_alpha_rad) * dt)
            nz = r[_NZ]
            # Past the limiter's load factor the integrator waits too (it would wind up against it).
            limited = not rolling and ((nz > self._nz_hi and e > 0.0) or (nz < self._nz_lo and e < 0.0))
            if -1.0 < u < 1.0 and not (stalling and e > 0.0) and not (rolling or limited or self._upset):
                # anti-windup: not while saturated
                self._i_pitch = _clamp(self._i_pitch + g.ki_pitch * e * dt, -1.0, 1.0)
            if rolling and self._max_ground_pitch < math.inf:
                # Attitude limit: the stick that holds the pitch below the limit, rate-damped.
                u = min(u, g.kp_pitch * (self._max_ground_pitch - r[_THETA]) - g.kd_pitch_rate * q)
            # Load-factor limiter: past a bound, no further that way than now, and walked back.
            if not rolling and nz > self._nz_hi:
                u = min(u, ac.controls.pitch - _NZ_PUSH_PER_G_S * (nz - self._nz_hi) * dt)
            elif not rolling and nz < self._nz_lo:
                u = max(u, ac.controls.pitch + _NZ_PUSH_PER_G_S * (self._nz_lo - nz) * dt)
            pitch = _clamp(u, -1.0, 1.0)
        if pitch != pitch or roll != roll or yaw != yaw or throttle != throttle:
            # A NaN state: set_controls rejects it, naming the control, as it always has.
            ac.set_controls(**{k: v for k, v in (("roll", roll), ("yaw", yaw), ("pitch", pitch),
                                                  ("throttle", throttle)) if v is not None})
        # Clamped to their ranges above, hence trusted.
        ac._set_controls_trusted(pitch, roll, yaw, throttle)

    def run(self, seconds: float) -> list:
        """Fly for ``seconds`` of simulated time; the events."""
        events = []
        for _ in range(int(round(seconds / self.aircraft.dt))):
            self.update()
            events.extend(self.aircraft.step())
            if self.aircraft.crashed:
                break
        return events


# Karney's geodesic inverse (C. F. F. Karney, "Algorithms for geodesics", J. Geodesy 87, 2013)
# on WGS84, through pyproj: PROJ's geodesic.c is Karney's own C implementation, the algorithm of
# GeographicLib. A route follower asks once a world tick; GeographicLib's Python Inverse took
# 41 us a call here (more than the aircraft's four JSBSim steps), this 0.7 us, with the same
# azimuths and distances (tests/test_fdm_autopilot.py).
_GEOD = Geod(ellps="WGS84")


def geodesic_inverse(lat1: float, lon1: float, lat2: float, lon2: float) -> tuple[float, float]:
    """(azimuth at the first point, degrees clockwise from north in (-180, 180]; distance, m)
    of the WGS84 geodesic between two points (lat, lon degrees)."""
    azi1, _, s12 = _GEOD.inv(lon1, lat1, lon2, lat2)
    return azi1, s12


class WaypointFollower:
    """Fly a route of (lat, lon, alt_msl_m) waypoints at a speed, holding altitude per leg.

    The heading target is the geodesic azimuth to the active waypoint
    (Karney 2013: :func:`geodesic_inverse`). A waypoint is passed, and the next
    one becomes active, when the aircraft comes within ``capture_radius_m``
    (default: three seconds of flight) or when it passes it abeam: its
    along-track distance past the waypoint turns positive, i.e. it crosses the
    geodesic through the waypoint perpendicular to the leg there. That is how a
    flight management system sequences a waypoint it does not fly over: on
    "passing abeam" it, when the along-track distance to go on the leg turns
    negative (the RNAV along-track/cross-track frame of the leg).
    The leg runs from the previous waypoint, or for the first one from where
    the aircraft was when it became active (this follower's first update).
    Without it, a waypoint inside the turning circle (an f16's 4 km at 45
    degrees of bank) was circled for good. Along-track is signed by the
    azimuths at the waypoint, from it back along the leg and from it to the
    aircraft (the geodesic's reverse azimuths): their difference beyond 90
    degrees is past. Geodesic azimuths hold across the antimeridian and at a
    waypoint on a pole (GeographicLib's limit convention for a pole's azimuth).
    A pass abeam is reported like a capture, in ``passed``, its miss distance
    beyond the capture radius. After the last waypoint the aircraft holds its
    last heading.
    """

    def __init__(self, aircraft, waypoints, speed_mps: float, capture_radius_m: float | None = None,
                 gains: Gains | None = None):
        pts = []
        for i, w in enumerate(waypoints):
            if len(w) != 3 or not all(isinstance(v, (int, float)) and math.isfinite(v) for v in w):
                raise InvalidArgument("waypoints", "must be finite (lat, lon, alt_msl_m) triples", index=i,
                                      value=w)
            if abs(w[0]) > 90:
                raise InvalidArgument("waypoints", "latitude must be within [-90, 90]", index=i, value=w)
            pts.append(tuple(float(v) for v in w))
        if not pts:
            raise InvalidArgument("waypoints", "need at least one waypoint")
        _check_positive("speed_mps", speed_mps)
        if capture_radius_m is not None:
            _check_positive("capture_radius_m", capture_radius_m)
        self.waypoints = pts
        self.active = 0
        self.capture_radius_m = capture_radius_m if capture_radius_m is not None else 3.0 * speed_mps
        self.autopilot = Autopilot(aircraft, gains=gains)
        self.speed_mps = speed_mps
        self.passed: list = []  # (index, time_s, miss distance m)
        self._leg_back_azi = None  # the active leg's azimuth at its waypoint, back to its start (deg)

    @property
    def done(self) -> bool:
        return self.active >= len(self.waypoints)

    def update(self, row=None, dt_s: float | None = None) -> None:
        """Retarget on the active waypoint, then the autopilot's update; ``row`` and ``dt_s``
        as in :meth:`Autopilot.update` (the row read once here and shared with the autopilot)."""
        if not self.done:
            r = row = _row_values(self.autopilot.aircraft, row)
            lat, lon, alt = self.waypoints[self.active]
            here = math.degrees(r[_LAT]), math.degrees(r[_LON])
            azi1, back, s12 = _GEOD.inv(here[1], here[0], lon, lat)
            if self._leg_back_azi is None:  # the first waypoint (or after a repeated one): its leg starts here
                self._leg_back_azi = back if s12 > 0.0 else None
            if s12 < self.capture_radius_m or (self._leg_back_azi is not None
                                               and math.cos(math.radians(back - self._leg_back_azi)) < 0.0):
                self.passed.append((self.active, r[_TIME], s12))
                self.active += 1
                if not self.done:
                    prev = lat, lon
                    lat, lon, alt = self.waypoints[self.active]
                    azi1, _, s12 = _GEOD.inv(here[1], here[0], lon, lat)
                    _, back, leg = _GEOD.inv(prev[1], prev[0], lon, lat)
                    # A repeated waypoint (a leg of 0 m): its leg starts at the aircraft's next update.
                    self._leg_back_azi = back if leg > 0.0 else None
            if not self.done:
                self.autopilot.set_targets(azi1 % 360.0, alt, self.speed_mps)
        self.autopilot.update(row, dt_s)

    def run(self, seconds: float) -> list:
        events = []
        ac = self.autopilot.aircraft
        for _ in range(int(round(seconds / ac.dt))):
            self.update()
            events.extend(ac.step())
            if ac.crashed:
                break
        return events
