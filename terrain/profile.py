"""Height profiles along WGS84 geodesics.

The geodesic (shortest path on the ellipsoid) comes from GeographicLib
(Karney 2013, "Algorithms for geodesics", J. Geodesy 87): one inverse problem
fixes the line, then samples are placed at equal distances along it.
GeographicLib's Python package is scalar, so positions are computed one by
one (about 8 microseconds each); the height lookup is one batched call.
"""

from __future__ import annotations

import math
import operator
from typing import Callable

import numpy as np
from geographiclib.geodesic import Geodesic

from sortie.errors import InvalidArgument, LimitExceeded
from terrain.geodesy import wrap_lon_exact_deg
from terrain.validate import LON_ABS_MAX_DEG

PROFILE_MIN_SAMPLES = 2
PROFILE_MAX_SAMPLES = 100_000

_LINE_CAPS = Geodesic.LATITUDE | Geodesic.LONGITUDE | Geodesic.DISTANCE_IN | Geodesic.LONG_UNROLL
_POSITION_MASK = Geodesic.LATITUDE | Geodesic.LONGITUDE | Geodesic.LONG_UNROLL


def check_n_samples(n_samples) -> int:
    """n_samples as an int in [PROFILE_MIN_SAMPLES, PROFILE_MAX_SAMPLES]."""
    if isinstance(n_samples, bool):
        raise InvalidArgument("n_samples", "must be an integer", value=n_samples)
    try:
        n = operator.index(n_samples)
    except TypeError:
        raise InvalidArgument("n_samples", "must be an integer", value=n_samples) from None
    if n < PROFILE_MIN_SAMPLES:
        raise InvalidArgument("n_samples", f"must be at least {PROFILE_MIN_SAMPLES}", value=n)
    if n > PROFILE_MAX_SAMPLES:
        raise LimitExceeded("n_samples", n, PROFILE_MAX_SAMPLES)
    return n


def check_point(lat_name: str, lat, lon_name: str, lon) -> tuple[float, float]:
    """One (lat, lon) pair in degrees as floats; raises InvalidArgument naming the field."""
    out = []
    for name, value, limit in ((lat_name, lat, 90.0), (lon_name, lon, LON_ABS_MAX_DEG)):
        try:
            v = float(value)
        except (TypeError, ValueError):
            raise InvalidArgument(name, "must be a number of degrees", value=value) from None
        if not (math.isfinite(v) and abs(v) <= limit):
            raise InvalidArgument(name, f"must be finite and within [-{limit:g}, {limit:g}] degrees", value=v)
        out.append(v)
    return out[0], out[1]


def geodesic_points(lat1: float, lon1: float, lat2: float, lon2: float, n_samples: int):
    """n_samples points at equal distances along the WGS84 geodesic from point 1 to point 2.

    Arguments in degrees, (lat, lon) order. Returns lat_deg, lon_deg,
    distance_m, each (n_samples,) float64; distance_m is metres along the
    geodesic from point 1. Longitudes are continuous along the line (they may
    leave [-180, 180) where it crosses the antimeridian). The end points are
    the inputs exactly (point 2's longitude unrolled).
    """
    line = Geodesic.WGS84.InverseLine(lat1, lon1, lat2, lon2, _LINE_CAPS)
    distance = np.linspace(0.0, line.s13, n_samples)
    pos = [line.Position(s, _POSITION_MASK) for s in distance[1:-1]]
    lat = np.array([lat1] + [p["lat2"] for p in pos] + [lat2], dtype=np.float64)
    lon = np.array([lon1] + [p["lon2"] for p in pos] + [0.0], dtype=np.float64)
    lon_end = line.Position(line.s13, _POSITION_MASK)["lon2"]
    lon[-1] = lon2 + 360.0 * np.round((lon_end - lon2) / 360.0)
    return lat, lon, distance


def geodesic_profile(source_heights: Callable, lat1: float, lon1: float, lat2: float, lon2: float,
                     n_samples: int):
    """Heights at n_samples equally spaced points along the WGS84 geodesic 1 -> 2.

    source_heights: callable (lat (n,) float64 deg, lon (n,) float64 deg) ->
    (height_m (n,) float64, status (n,) uint8 STATUS_*), e.g. a Terrain's
    height query. Arguments in degrees, (lat, lon) order; n_samples an int in
    [2, 100000] (InvalidArgument below, LimitExceeded above).
    Returns, in the field order of terrain.terrain.ProfileResult: lat_deg,
    lon_deg (continuous along the line, as :func:`geodesic_points` gives them),
    distance_m (metres along the geodesic from point 1), height_m, each
    (n_samples,) float64, and status (n_samples,) uint8.
    """
    n = check_n_samples(n_samples)
    lat1, lon1 = check_point("lat1", lat1, "lon1", lon1)
    lat2, lon2 = check_point("lat2", lat2, "lon2", lon2)
    lat, lon, distance = geodesic_points(lat1, lon1, lat2, lon2, n)
    # Unrolled, a line that starts near the +-540 limit runs past it (530 -> 550), which the
    # height query rejects as a unit mix-up: ask at the same longitudes wrapped into [-180, 180)
    # (exactly, so a sample already there is asked as it is returned).
    height, status = source_heights(lat, wrap_lon_exact_deg(lon))
    return lat, lon, distance, np.asarray(height, dtype=np.float64), np.asarray(status, dtype=np.uint8)
