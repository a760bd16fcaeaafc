"""Ground-vehicle types: the figures the vectorised model in :mod:`fdm.ground` needs.

Each :class:`VehicleType` holds SI figures for one class of vehicle. Figures
marked *spec* are the published ones for the named vehicle (rounded), as the
public fact sheets and the secondary sources listed per type tabulate them
(not re-checked against the vehicles' technical manuals); figures marked
*model* are modelling choices where no public figure fixes them (braking,
lateral acceleration, pivot rate, drivetrain efficiency), chosen to be
conservative and stated so they can be changed in one place.

Sources:

- [A] M1A2 Abrams: weight 63.0 t, 1500 hp AGT1500, top speed 42 mph
  (67.6 km/h), hull 7.92 m x 3.66 m; "gradient 60 %, side slope 40 %,
  vertical obstacle 1.07 m" -- US Army / FAS Military Analysis Network "M1
  Abrams" fact file; strategic-bureau.com "M1 Abrams" (67 km/h, 63.1 t, 1500 hp).
  0-32 km/h in 7.2 s gives 1.2 m/s^2 and the track ground contact is 4.6 m,
  both as commonly quoted from the FAS fact file.
- [B] M2 Bradley: 600 hp Cummins VTA-903T, 16.2 kW/t, top speed 40 mph
  (64 km/h), hull 6.55 m x 3.60 m (BAE Systems / FAS "M2A3 and M3A3 Bradley
  Fighting Vehicle Systems"); gradient 60 %, side slope 40 % (FAS).
- [C] HMMWV M998: curb 2.34 t, 6.2 l diesel 150 hp, max road speed 105 km/h,
  gradient 60 %, side slope 40 %, vertical step 0.6 m, length 4.7 m, width
  2.12 m (military-today.com "HMMWV"; TM 9-2320-280-10 gives 150 hp, 65 mph).
  Wheelbase 3.30 m (130 in), track 1.82 m, turning radius 7.6 m (25 ft) per
  TM 9-2320-280-10.
- [D] FMTV M1083A1P2 5-ton 6x6: curb 11.3 t (24,870 lb), payload 4.5 t, CAT C7
  330 hp, 94 km/h, length 7.27 m, width 2.44 m (US Army / Oshkosh fact sheet
  as tabulated by piglix.com "Family of Medium Tactical Vehicles"); gradient
  60 %, side slope 30 % (US Army FMTV fact file). Wheelbase (front axle to
  rear bogie centre) 4.5 m and turning radius 11 m are *model* figures
  consistent with the published 7.27 m length.

Gradient limits are tan(slope): "60 % gradient" is a rise of 0.6 m per metre,
31 degrees. Rolling resistance f_r: 0.04 tracked, 0.03 wheeled on firm
soil (Wong, *Theory of Ground Vehicles*, 4th ed. 2008, table 1.2 and sec. 2.x:
0.02-0.05 on medium soils). Drivetrain efficiency 0.6 tracked, 0.75 wheeled
(Wong, sec. 3.1: tracked transmissions lose more in steering gear and tracks).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

from sortie.errors import InvalidArgument, NotFound

WHEELED = 0
TRACKED = 1
KIND_NAMES = {WHEELED: "wheeled", TRACKED: "tracked"}

G_MPS2 = 9.80665  # standard gravity (CGPM 1901)
HP_W = 745.69987  # mechanical horsepower in watts


@dataclass(frozen=True)
class VehicleType:
    """One class of ground vehicle; every figure SI (m, s, kg, W, tan of slope).

    contact_length_m is the front-to-rear distance between the terrain
    contact points the model samples (wheelbase; track ground-contact length),
    contact_width_m the left-to-right one (track width / tread).
    min_turn_radius_m is 0 for vehicles that pivot (tracked).
    """

    name: str
    kind: int
    max_speed_mps: float
    max_reverse_mps: float
    accel_mps2: float
    brake_mps2: float
    min_turn_radius_m: float
    pivot_rate_dps: float
    max_lat_accel_mps2: float
    max_gradient: float
    max_side_slope: float
    mass_kg: float
    power_w: float
    rolling_resistance: float
    drivetrain_efficiency: float
    contact_length_m: float
    contact_width_m: float
    length_m: float
    width_m: float

    def __post_init__(self):
        if self.kind not in KIND_NAMES:
            raise InvalidArgument("kind", f"must be one of {sorted(KIND_NAMES)}", value=self.kind)
        for f in fields(self):
            if f.name in ("name", "kind"):
                continue
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0.0):
                raise InvalidArgument(f.name, "must be a finite number >= 0", value=v)
        for name in ("max_speed_mps", "accel_mps2", "brake_mps2", "max_lat_accel_mps2", "max_gradient",
                     "max_side_slope", "mass_kg", "power_w", "drivetrain_efficiency", "contact_length_m",
                     "contact_width_m"):
            if getattr(self, name) <= 0.0:
                raise InvalidArgument(name, "must be > 0", value=getattr(self, name))
        if self.kind == WHEELED and self.min_turn_radius_m <= 0.0:
            raise InvalidArgument("min_turn_radius_m", "must be > 0 for a wheeled vehicle",
                                  value=self.min_turn_radius_m)
        if self.kind == TRACKED and self.pivot_rate_dps <= 0.0:
            raise InvalidArgument("pivot_rate_dps", "must be > 0 for a tracked vehicle", value=self.pivot_rate_dps)

    @property
    def max_yaw_rate_dps(self) -> float:
        """Largest heading rate the type can reach at any speed (deg/s).

        Wheeled: the yaw rate v / R_min grows with speed until the lateral
        acceleration limit a / v caps it; the two meet at v = sqrt(a R), where
        the rate is sqrt(a / R). Tracked: the pivot rate, or that bound if larger.
        """
        r_lat = math.sqrt(self.max_lat_accel_mps2 / max(self.min_turn_radius_m, 1e-9))
        if self.kind == TRACKED:
            return max(self.pivot_rate_dps, math.degrees(r_lat) if self.min_turn_radius_m > 0 else 0.0)
        return math.degrees(r_lat)


KMH = 1.0 / 3.6
MPH = 0.44704

M1A2_ABRAMS = VehicleType(
    name="m1a2", kind=TRACKED,
    max_speed_mps=42.0 * MPH,  # spec [A]
    max_reverse_mps=30.0 * KMH,  # model
    accel_mps2=(32.0 * KMH) / 7.2,  # spec [A]: 0-32 km/h in 7.2 s
    brake_mps2=4.0,  # model (~0.4 g)
    min_turn_radius_m=0.0, pivot_rate_dps=30.0,  # pivot: model rate
    max_lat_accel_mps2=0.3 * G_MPS2,  # model
    max_gradient=0.60, max_side_slope=0.40,  # spec [A]
    mass_kg=63_000.0, power_w=1500.0 * HP_W,  # spec [A]
    rolling_resistance=0.04, drivetrain_efficiency=0.6,  # Wong
    contact_length_m=4.6, contact_width_m=3.66 - 0.64,  # spec [A]; width less one 0.64 m track
    length_m=7.92, width_m=3.66,  # spec [A]
)

M2_BRADLEY = VehicleType(
    name="m2a3", kind=TRACKED,
    max_speed_mps=40.0 * MPH,  # spec [B]
    max_reverse_mps=25.0 * KMH,  # model
    accel_mps2=1.0,  # model
    brake_mps2=4.0,  # model
    min_turn_radius_m=0.0, pivot_rate_dps=35.0,  # model
    max_lat_accel_mps2=0.3 * G_MPS2,  # model
    max_gradient=0.60, max_side_slope=0.40,  # spec [B]
    mass_kg=30_000.0, power_w=600.0 * HP_W,  # spec [B]
    rolling_resistance=0.04, drivetrain_efficiency=0.6,  # Wong
    contact_length_m=3.9, contact_width_m=3.60 - 0.53,  # model: ~60 % of hull length; width less one track
    length_m=6.55, width_m=3.60,  # spec [B]
)

HMMWV = VehicleType(
    name="hmmwv", kind=WHEELED,
    max_speed_mps=105.0 * KMH,  # spec [C]
    max_reverse_mps=20.0 * KMH,  # model
    accel_mps2=1.8,  # model (~0-50 km/h in 8 s)
    brake_mps2=6.0,  # model (~0.6 g on dry road)
    min_turn_radius_m=7.6, pivot_rate_dps=0.0,  # spec [C]
    max_lat_accel_mps2=0.45 * G_MPS2,  # model (rollover margin)
    max_gradient=0.60, max_side_slope=0.40,  # spec [C]
    mass_kg=2_340.0 + 1_000.0, power_w=150.0 * HP_W,  # spec [C] curb + a model load
    rolling_resistance=0.03, drivetrain_efficiency=0.75,  # Wong
    contact_length_m=3.30, contact_width_m=1.82,  # spec [C]
    length_m=4.7, width_m=2.12,  # spec [C]
)

FMTV_M1083 = VehicleType(
    name="m1083", kind=WHEELED,
    max_speed_mps=94.0 * KMH,  # spec [D]
    max_reverse_mps=15.0 * KMH,  # model
    accel_mps2=1.0,  # model
    brake_mps2=5.0,  # model
    min_turn_radius_m=11.0, pivot_rate_dps=0.0,  # model
    max_lat_accel_mps2=0.35 * G_MPS2,  # model (high centre of gravity)
    max_gradient=0.60, max_side_slope=0.30,  # spec [D]
    mass_kg=11_300.0 + 4_540.0, power_w=330.0 * HP_W,  # spec [D] curb + payload
    rolling_resistance=0.03, drivetrain_efficiency=0.75,  # Wong
    contact_length_m=4.5, contact_width_m=2.0,  # model
    length_m=7.27, width_m=2.44,  # spec [D]
)

VEHICLE_TYPES: dict[str, VehicleType] = {t.name: t for t in (M1A2_ABRAMS, M2_BRADLEY, HMMWV, FMTV_M1083)}

# Columns of the parameter table the kernels read, one row per type.
P_KIND = 0
P_VMAX = 1
P_VREV = 2
P_ACCEL = 3
P_BRAKE = 4
P_RMIN = 5
P_PIVOT = 6  # rad/s
P_ALAT = 7
P_GRAD = 8
P_SIDE = 9
P_POWER_PER_KG = 10  # efficiency * power / mass, W/kg
P_FR = 11
P_LEN = 12
P_WID = 13
P_YAWMAX = 14  # rad/s
N_PARAMS = 15


def type_table(types) -> np.ndarray:
    """(n_types, N_PARAMS) float64 table of the figures the kernels read."""
    table = np.zeros((len(types), N_PARAMS))
    for k, t in enumerate(types):
        table[k] = [t.kind, t.max_speed_mps, t.max_reverse_mps, t.accel_mps2, t.brake_mps2,
                    t.min_turn_radius_m, math.radians(t.pivot_rate_dps), t.max_lat_accel_mps2, t.max_gradient,
                    t.max_side_slope, t.drivetrain_efficiency * t.power_w / t.mass_kg, t.rolling_resistance,
                    t.contact_length_m, t.contact_width_m, math.radians(t.max_yaw_rate_dps)]
    table.flags.writeable = False
    return table


def get_type(name: str) -> VehicleType:
    """The catalogued type called ``name`` (see VEHICLE_TYPES)."""
    try:
        return VEHICLE_TYPES[name]
    except KeyError:
        raise NotFound(f"vehicle type {name!r}: known types are {sorted(VEHICLE_TYPES)}") from None
