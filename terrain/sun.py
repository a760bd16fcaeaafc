"""Where the sun is: azimuth and elevation for a UTC instant and (lat, lon) arrays.

The NOAA solar calculator equations (NOAA Global Monitoring Laboratory,
"General Solar Position Calculations" and its spreadsheet NOAA_Solar_Calculations_day.xls),
which are the low-precision solar coordinates of J. Meeus, *Astronomical
Algorithms*, 2nd ed., Willmann-Bell 1998, ch. 25 ("Solar coordinates", the
"lower accuracy" method, eqs. 25.2-25.8 and the apparent-longitude and
obliquity corrections), with the equation of time of ch. 28 (eq. 28.3, after
Smart) and the refraction fit of the NOAA spreadsheet.

Meeus states about 0.01 degree for the sun's apparent longitude by this
method; NOAA states its calculator is good to about one minute of time for
sunrise and sunset between +-72 degrees latitude. The tests compare against
independent values: Meeus' worked examples 25.a and 28.b, published equinox
and solstice instants (declination 0 and +23.44 degrees), the geometry of noon
and sunrise at those instants, and nothing derived from this module itself.

Conventions: azimuth degrees clockwise from true north, in [0, 360);
elevation degrees above the astronomical horizon; times are UTC, used both
for the hour angle (where UT belongs; UTC is within 0.9 s of UT1) and for the
solar coordinates, where Meeus uses TT: NOAA's calculator does the same, and
the difference, Delta T of about 69 s in 2025, moves the sun's longitude by
69 s x 0.9856 deg/day = 0.0008 degree.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import datetime, timezone

import numpy as np

# Julian day of the Unix epoch 1970-01-01T00:00:00 UTC, and of J2000.0
# (2000-01-01T12:00 TT) (Meeus ch. 7).
JD_UNIX_EPOCH = 2440587.5
JD_J2000 = 2451545.0
DAYS_PER_JULIAN_CENTURY = 36525.0

# The NOAA spreadsheet's refraction fit switches formulas at these elevations (degrees).
_REFRACTION_NONE_ABOVE_DEG = 85.0
_REFRACTION_LOW_BELOW_DEG = 5.0
_REFRACTION_HORIZON_DEG = -0.575


@dataclass(frozen=True)
class SolarCoordinates:
    """Geocentric solar coordinates at one or more Julian days (arrays of the days' shape).

    mean_longitude_deg: L0 (Meeus 25.2), mean_anomaly_deg: M (25.3),
    eccentricity: e of the Earth's orbit (25.4), apparent_longitude_deg:
    lambda (true longitude corrected for nutation and aberration),
    obliquity_deg: epsilon corrected (22.2 + the ch. 25 correction),
    declination_deg: delta (25.7), right_ascension_deg: alpha (25.6) in
    [0, 360), equation_of_time_min: apparent minus mean solar time, minutes (28.3).
    """

    mean_longitude_deg: np.ndarray
    mean_anomaly_deg: np.ndarray
    eccentricity: np.ndarray
    apparent_longitude_deg: np.ndarray
    obliquity_deg: np.ndarray
    declination_deg: np.ndarray
    right_ascension_deg: np.ndarray
    equation_of_time_min: np.ndarray


@dataclass(frozen=True)
class SunPosition:
    """Topocentric sun direction, arrays of the broadcast (time, lat, lon) shape.

    azimuth_deg: clockwise from true north, [0, 360); elevation_deg: above the
    horizon, refraction included when asked for; hour_angle_deg: local hour
    angle, negative before solar noon, (-180, 180]; declination_deg: as in
    :class:`SolarCoordinates`.
    """

    azimuth_deg: np.ndarray
    elevation_deg: np.ndarray
    hour_angle_deg: np.ndarray
    declination_deg: np.ndarray


def julian_day(when) -> np.ndarray:
    """Julian day (UTC) of a datetime or of numpy datetime64 values.

    when: a timezone-aware ``datetime`` (naive ones are rejected: a clock
    time without a zone is ambiguous), or a ``numpy.datetime64`` array, taken
    as UTC. Returns float64 of the input's shape (a 0-d array for a datetime).
    """
    if isinstance(when, datetime):
        if when.tzinfo is None or when.utcoffset() is None:
            raise ValueError(f"when must be timezone-aware (UTC), got naive {when.isoformat()}")
        seconds = (when - datetime(1970, 1, 1, tzinfo=timezone.utc)).total_seconds()
        return np.asarray(JD_UNIX_EPOCH + seconds / 86400.0, dtype=np.float64)
    stamps = np.asarray(when)
    if stamps.dtype.kind != "M":
        raise TypeError(f"when must be a datetime or datetime64 array, got {stamps.dtype}")
    micro = (stamps - np.datetime64("1970-01-01T00:00:00", "us")).astype("timedelta64[us]").astype(np.float64)
    return JD_UNIX_EPOCH + micro / 86.4e9


def solar_coordinates(jd) -> SolarCoordinates:
    """Meeus ch. 25 low-precision coordinates of the sun at Julian day(s) jd.

    Every coefficient below is the NOAA spreadsheet's, which are Meeus'.
    """
    jd = np.asarray(jd, dtype=np.float64)
    t = (jd - JD_J2000) / DAYS_PER_JULIAN_CENTURY  # Julian centuries since J2000.0 (25.1)
    l0 = np.mod(280.46646 + t * (36000.76983 + t * 0.0003032), 360.0)  # 25.2
    m = 357.52911 + t * (35999.05029 - 0.0001537 * t)  # 25.3
    e = 0.016708634 - t * (0.000042037 + 0.0000001267 * t)  # 25.4
    m_rad = np.radians(m)
    centre = (np.sin(m_rad) * (1.914602 - t * (0.004817 + 0.000014 * t))
              + np.sin(2.0 * m_rad) * (0.019993 - 0.000101 * t)
              + np.sin(3.0 * m_rad) * 0.000289)  # equation of the centre C
    true_longitude = l0 + centre
    omega = np.radians(125.04 - 1934.136 * t)  # longitude of the Moon's ascending node
    apparent = true_longitude - 0.00569 - 0.00478 * np.sin(omega)  # nutation and aberration
    # Mean obliquity, Meeus 22.2 (seconds of arc), then the ch. 25 correction for apparent positions.
    eps0 = 23.0 + (26.0 + (21.448 - t * (46.815 + t * (0.00059 - t * 0.001813))) / 60.0) / 60.0
    eps = eps0 + 0.00256 * np.cos(omega)
    eps_rad, lam_rad = np.radians(eps), np.radians(apparent)
    declination = np.degrees(np.arcsin(np.sin(eps_rad) * np.sin(lam_rad)))  # 25.7
    right_ascension = np.mod(np.degrees(np.arctan2(np.cos(eps_rad) * np.sin(lam_rad), np.cos(lam_rad))), 360.0)
    # Equation of time, Meeus 28.3 (Smart): y = tan^2(eps / 2); E in radians, 4 minutes per degree.
    y = np.tan(eps_rad / 2.0) ** 2
    l0_rad = np.radians(l0)
    eot_rad = (y * np.sin(2.0 * l0_rad) - 2.0 * e * np.sin(m_rad)
               + 4.0 * e * y * np.sin(m_rad) * np.cos(2.0 * l0_rad)
               - 0.5 * y * y * np.sin(4.0 * l0_rad) - 1.25 * e * e * np.sin(2.0 * m_rad))
    return SolarCoordinates(l0, np.mod(m, 360.0), e, np.mod(apparent, 360.0), eps, declination,
                            right_ascension, 4.0 * np.degrees(eot_rad))


def refraction_deg(elevation_deg) -> np.ndarray:
    """Atmospheric refraction (degrees, to add) at a true elevation, NOAA spreadsheet fit.

    Above 85 degrees: 0; 5..85: 58.1/tan e - 0.07/tan^3 e + 0.000086/tan^5 e
    arcseconds (Saemundsson-like series); -0.575..5: a polynomial in e
    (1735 - 518.2 e + 103.4 e^2 - 12.79 e^3 + 0.711 e^4 arcseconds); below:
    -20.772/tan e arcseconds. About 0.57 degree at the horizon, for a
    standard atmosphere (1010 hPa, 10 C).
    """
    e = np.asarray(elevation_deg, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        tan_e = np.tan(np.radians(e))
        mid = 58.1 / tan_e - 0.07 / tan_e**3 + 0.000086 / tan_e**5
        low = 1735.0 + e * (-518.2 + e * (103.4 + e * (-12.79 + e * 0.711)))
        below = -20.772 / tan_e
    arcsec = np.where(e > _REFRACTION_NONE_ABOVE_DEG, 0.0,
                      np.where(e > _REFRACTION_LOW_BELOW_DEG, mid,
                               np.where(e > _REFRACTION_HORIZON_DEG, low, below)))
    return arcsec / 3600.0


def sun_position(when, lat_deg, lon_deg, *, refraction: bool = False) -> SunPosition:
    """Azimuth and elevation of the sun's centre at UTC instant(s) from (lat, lon) degrees.

    when: a timezone-aware datetime or datetime64 array; lat_deg, lon_deg:
    scalars or arrays, broadcast against each other and the times. The hour
    angle is the NOAA spreadsheet's: true solar time = UTC minutes of the day
    + equation of time + 4 min per degree of east longitude. Azimuth and
    elevation follow from the hour angle H, declination delta and latitude
    phi by the rotation to the local frame (Meeus 13.5/13.6, written as an
    east/north/up vector so the azimuth comes from atan2 with no quadrant rule):
    east = -cos(delta) sin(H), north = sin(delta) cos(phi) - cos(delta) sin(phi) cos(H),
    up = sin(delta) sin(phi) + cos(delta) cos(phi) cos(H).

    refraction: add :func:`refraction_deg` to the elevation (the apparent
    sun); False gives the geometric elevation. The sun's semi-diameter
    (about 0.27 degree) is never added: this is the centre of the disc.
    """
    jd = julian_day(when)
    coords = solar_coordinates(jd)
    lat = np.radians(np.asarray(lat_deg, dtype=np.float64))
    lon = np.asarray(lon_deg, dtype=np.float64)
    minutes_utc = np.mod(jd - 0.5, 1.0) * 1440.0  # Julian days start at noon
    true_solar_min = np.mod(minutes_utc + coords.equation_of_time_min + 4.0 * lon, 1440.0)
    hour_angle = true_solar_min / 4.0 - 180.0  # degrees, 0 at local solar noon
    hour_angle = np.where(hour_angle <= -180.0, hour_angle + 360.0, hour_angle)
    h = np.radians(hour_angle)
    dec = np.radians(coords.declination_deg)
    east = -np.cos(dec) * np.sin(h)
    north = np.sin(dec) * np.cos(lat) - np.cos(dec) * np.sin(lat) * np.cos(h)
    up = np.sin(dec) * np.sin(lat) + np.cos(dec) * np.cos(lat) * np.cos(h)
    elevation = np.degrees(np.arctan2(up, np.hypot(east, north)))
    azimuth = np.mod(np.degrees(np.arctan2(east, north)), 360.0)
    if refraction:
        elevation = elevation + refraction_deg(elevation)
    declination = np.broadcast_to(coords.declination_deg, elevation.shape)
    return SunPosition(azimuth, elevation, np.broadcast_to(hour_angle, elevation.shape), declination)


def sun_direction_enu(azimuth_deg, elevation_deg) -> np.ndarray:
    """Unit vector(s) (east, north, up) toward the sun, shape (..., 3) float64."""
    az = np.radians(np.asarray(azimuth_deg, dtype=np.float64))
    el = np.radians(np.asarray(elevation_deg, dtype=np.float64))
    az, el = np.broadcast_arrays(az, el)
    return np.stack([np.cos(el) * np.sin(az), np.cos(el) * np.cos(az), np.sin(el)], axis=-1)
