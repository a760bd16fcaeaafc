"""Aircraft events: touchdown, take-off, crash, out of fuel.

A detector sees a few numbers per step (gear weight-on-wheels, structure
contact, sink rate, load factor, fuel) and emits an :class:`Event` on each
transition; it holds no JSBSim object, so its logic is tested on plain numbers.

Crash limits come per aircraft class (:data:`LIMITS`):

- Sink rate at touchdown: the limit descent velocity of the landing-gear
  drop tests, 10 ft/s (3.05 m/s) for light aeroplanes (14 CFR 23.473(d)),
  and the 10 ft/s land-based design value for military jets
  (MIL-A-8863C, table I: 10 ft/s land-based) raised to 13 ft/s (3.96 m/s)
  for the stiffer fighter gear; beyond the limit the gear is taken as failed.
- Load factor: ultimate load = 1.5 x limit load (14 CFR 23.303 / 25.303).
  Limit loads: normal-category light aeroplanes +3.8 / -1.52 g (14 CFR
  23.337), fighters +9 / -3 g (MIL-A-8861B), transports +2.5 / -1 g
  (14 CFR 25.337). A crash is an excursion beyond the ultimate load sustained
  for ``g_hold_s`` (a one-step spike of the numerical acceleration is not a
  structural failure).
- Wheels touching water (a landplane: not a flying boat of the catalog) are a
  crash, "ditched": the host tells water by the ground vehicles' rule
  (fdm.ground.WATER_LEVEL_MSL_M) and calls :meth:`EventDetector.ditched`.
- A STRUCTURE contact (wing tip, tail skid, radome touching the ground) is a
  crash when it comes at more than STRUCTURE_REST_SPEED_MPS over the ground or
  sinking faster than the class's touchdown limit: those points are not meant
  to carry load at speed. Below both it is the aircraft coming to rest on them,
  as a glider settles on a wing tip once it stops (JSBSim's gliders declare
  wing-tip contacts for that), or a tail skid at walking pace.
"""

from __future__ import annotations

from dataclasses import dataclass, field

TOUCHDOWN = "touchdown"
TAKEOFF = "takeoff"
CRASH = "crash"
OUT_OF_FUEL = "out_of_fuel"
# A wreck that fell from where it crashed in the air meeting the surface (fdm.wreck).
WRECK_IMPACT = "wreck_impact"
EVENT_KINDS = (TOUCHDOWN, TAKEOFF, CRASH, OUT_OF_FUEL, WRECK_IMPACT)

FT_S = 0.3048
# The crash reason of a landplane's wheels touching water.
DITCHED = "ditched"
# Ground speed (m/s) up to which a structure contact is coming to rest, not a crash: a
# walking pace, below a glider's end of ground run, where a wing drops onto its tip.
STRUCTURE_REST_SPEED_MPS = 3.0
# The crash reason of a host's segment test (server.world: the aircraft's path over a world tick
# met the terrain there). Given to fdm.aircraft.Aircraft.crash, its place is where the wreck rests.
SEGMENT_CRASH_REASON = "terrain collision (segment)"
# The crash reasons of an aircraft meeting the surface (or whose state went non-finite): its
# wreck stays where it crashed. Any other crash (the load factor; a host's, such as a mid-air
# collision) well clear of the surface leaves a wreck that falls (fdm.wreck).
SURFACE_CRASH_REASONS = frozenset({"sink rate at touchdown", "structure contact", "terrain penetration",
                                   DITCHED, "state diverged", SEGMENT_CRASH_REASON})


@dataclass(frozen=True)
class CrashLimits:
    """Per-class structural limits (see the module docstring for the sources)."""

    sink_rate_mps: float
    nz_max_g: float
    nz_min_g: float
    g_hold_s: float = 0.1


LIMITS = {
    "light": CrashLimits(sink_rate_mps=10.0 * FT_S, nz_max_g=1.5 * 3.8, nz_min_g=1.5 * -1.52),
    "fighter": CrashLimits(sink_rate_mps=13.0 * FT_S, nz_max_g=1.5 * 9.0, nz_min_g=1.5 * -3.0),
    "transport": CrashLimits(sink_rate_mps=10.0 * FT_S, nz_max_g=1.5 * 2.5, nz_min_g=1.5 * -1.0),
}


@dataclass(frozen=True)
class Event:
    """Something that happened at ``time_s``; ``detail`` says why (SI numbers)."""

    kind: str
    time_s: float
    lat_deg: float
    lon_deg: float
    alt_msl_m: float
    detail: dict = field(default_factory=dict)


class EventDetector:
    """Transitions of gear contact, crash conditions and fuel, step by step.

    Take-off is reported once the gear has been clear of the ground for
    ``takeoff_clear_s`` (a bounce is not a take-off), with the time and place
    the wheels left; touchdown on the first step with weight on any wheel
    after being airborne.
    """

    def __init__(self, limits: CrashLimits, on_ground: bool, takeoff_clear_s: float = 0.5):
        self.limits = limits
        self.airborne = not on_ground
        self.on_ground = on_ground
        self.takeoff_clear_s = takeoff_clear_s
        self.crashed = False
        self.out_of_fuel = False
        self._clear_since = None
        self._clear_where = None  # (lat, lon, alt) when the gear left the ground
        self._g_since = None

    def update(self, t, lat, lon, alt, wow, structure_contact, sink_rate_mps, nz_g,
               ground_speed_mps: float = float("inf")) -> list:
        """Events of this step (a list, usually empty). Units: s, deg, m, m/s (down +), g;
        ``ground_speed_mps`` tells a structure contact at rest from a crash (unknown: a crash)."""
        events = []
        if self.crashed:
            return events
        if wow:
            self._clear_since = None
            if not self.on_ground:
                self.on_ground = True
                if self.airborne:
                    self.airborne = False
                    events.append(Event(TOUCHDOWN, t, lat, lon, alt, {"sink_rate_mps": sink_rate_mps}))
                    if sink_rate_mps > self.limits.sink_rate_mps:
                        events.append(self._crash(t, lat, lon, alt, "sink rate at touchdown",
                                                  sink_rate_mps=sink_rate_mps,
                                                  limit_mps=self.limits.sink_rate_mps))
        else:
            self.on_ground = False
            if not self.airborne:
                if self._clear_since is None:
                    self._clear_since = t
                    self._clear_where = (lat, lon, alt)
                elif t - self._clear_since >= self.takeoff_clear_s:
                    # Reported takeoff_clear_s late, as of when and where the wheels left.
                    self.airborne = True
                    events.append(Event(TAKEOFF, self._clear_since, *self._clear_where))
        if structure_contact and not self.crashed and (ground_speed_mps > STRUCTURE_REST_SPEED_MPS
                                                       or sink_rate_mps > self.limits.sink_rate_mps):
            events.append(self._crash(t, lat, lon, alt, "structure contact", ground_speed_mps=ground_speed_mps,
                                      sink_rate_mps=sink_rate_mps))
        if not self.crashed:
            if nz_g > self.limits.nz_max_g or nz_g < self.limits.nz_min_g:
                if self._g_since is None:
                    self._g_since = t
                if t - self._g_since >= self.limits.g_hold_s:
                    events.append(self._crash(t, lat, lon, alt, "load factor", nz_g=nz_g))
            else:
                self._g_since = None
        return events

    def fuel(self, t, lat, lon, alt, fuel_kg) -> list:
        """The out-of-fuel event, once, when the contents reach zero."""
        if self.out_of_fuel or fuel_kg > 0.0:
            return []
        self.out_of_fuel = True
        return [Event(OUT_OF_FUEL, t, lat, lon, alt)]

    def terrain_crash(self, t, lat, lon, alt, penetration_m) -> list:
        """A crash found by the host's own terrain check (e.g. a cliff face)."""
        if self.crashed:
            return []
        return [self._crash(t, lat, lon, alt, "terrain penetration", penetration_m=penetration_m)]

    def ditched(self, t, lat, lon, alt, **detail) -> list:
        """A landplane's wheels on water (the host's test, fdm.aircraft): a crash."""
        if self.crashed:
            return []
        return [self._crash(t, lat, lon, alt, DITCHED, **detail)]

    def _crash(self, t, lat, lon, alt, reason, **detail) -> Event:
        self.crashed = True
        return Event(CRASH, t, lat, lon, alt, {"reason": reason, **detail})
