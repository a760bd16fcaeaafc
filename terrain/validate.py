"""Input checks shared by the library and the services.

Every failure is an :class:`sortie.errors.InvalidArgument` that names the field
and the first offending index, so a gRPC client can find its bad point.
"""

from __future__ import annotations

import numba
import numpy as np

from sortie.errors import InvalidArgument, LimitExceeded

# Longitudes wrap, but a value beyond one extra turn is almost surely a unit or
# field mix-up (radians, E7 integers), so it is rejected rather than wrapped.
LON_ABS_MAX_DEG = 540.0


def as_1d_f64(name: str, values) -> np.ndarray:
    """A (n,) float64 view or copy of values; raises naming ``name`` otherwise."""
    arr = np.asarray(values, dtype=np.float64)
    if arr.ndim == 0:
        arr = arr.reshape(1)
    if arr.ndim != 1:
        raise InvalidArgument(name, f"must be a 1-D array, got shape {arr.shape}")
    return np.ascontiguousarray(arr)


@numba.njit(cache=True, nogil=True)
def latlon_all_valid(lat, lon, lon_abs_max):
    """One pass over both arrays: True when every point is finite and in range."""
    ok = True
    for k in range(lat.shape[0]):
        a = lat[k]
        b = lon[k]
        # NaN fails every comparison, and +-inf fails the bound: one test each.
        ok &= (abs(a) <= 90.0) & (abs(b) <= lon_abs_max)
    return ok


def first_bad(mask: np.ndarray) -> int:
    return int(np.flatnonzero(mask)[0])


def check_finite(name: str, arr: np.ndarray) -> None:
    bad = ~np.isfinite(arr)
    if bad.any():
        i = first_bad(bad)
        raise InvalidArgument(name, "must be finite", index=i, value=float(arr[i]))


def raise_first_bad(checks) -> None:
    """Raise InvalidArgument at the lowest index any check fails, naming the first check (in the
    order given) that fails there; checks: (name, values, bad mask, message) each, masks alike.
    One index across all the checks, so an error names the first bad point, not the first bad
    point of whichever check runs first."""
    bad = np.logical_or.reduce([mask for _, _, mask, _ in checks])
    if bad.any():
        i = first_bad(bad)
        name, values, _, message = next(c for c in checks if c[2][i])
        raise InvalidArgument(name, message, index=i, value=float(values[i]))


def check_latlon(lat, lon, prefix: str = "", max_points: int | None = None):
    """Validated (lat, lon) float64 (n,) arrays in degrees; argument order (lat, lon)."""
    lat_name, lon_name = f"{prefix}lat", f"{prefix}lon"
    lat = as_1d_f64(lat_name, lat)
    lon = as_1d_f64(lon_name, lon)
    if lat.shape != lon.shape:
        raise InvalidArgument(lon_name, f"must have as many values as {lat_name} ({lat.size}), got {lon.size}")
    if max_points is not None and lat.size > max_points:
        raise LimitExceeded(lat_name, lat.size, max_points)
    if latlon_all_valid(lat, lon, LON_ABS_MAX_DEG):
        return lat, lon
    # Something is wrong: find the first culprit, and name it.
    raise_first_bad([(lat_name, lat, ~np.isfinite(lat), "must be finite"),
                     (lon_name, lon, ~np.isfinite(lon), "must be finite"),
                     (lat_name, lat, np.abs(lat) > 90.0, "must be within [-90, 90] degrees"),
                     (lon_name, lon, np.abs(lon) > LON_ABS_MAX_DEG,
                      f"must be within [-{LON_ABS_MAX_DEG:g}, {LON_ABS_MAX_DEG:g}] degrees")])
    return lat, lon


def check_heights(name: str, h, n: int) -> np.ndarray:
    """Validated (n,) float64 heights in metres."""
    h = as_1d_f64(name, h)
    if h.size != n:
        raise InvalidArgument(name, f"must have {n} values, got {h.size}")
    if not (np.abs(h) <= 1.0e8).all():  # one pass when all is well (NaN compares false too)
        raise_first_bad([(name, h, ~np.isfinite(h), "must be finite"),
                         (name, h, np.abs(h) > 1.0e8, "must be within +-1e8 m")])
    return h
