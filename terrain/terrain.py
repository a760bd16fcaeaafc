"""The Terrain: an ordered stack of height sources answering batched queries.

Sources are tried in order; each point is answered by the first source that
covers it (real DEMs first, procedural terrain last, so a procedural world
fills everything the DEMs leave). A source is anything with the methods of
:class:`terrain.raster.Raster` used here: ``heights_into``, ``gradient_into``,
``raster_for`` and ``describe``.

All heights are metres above mean sea level (the sources' vertical datum,
EGM96 for SRTM); argument order is always (lat, lon) in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from terrain.raster import STATUS_OUTSIDE
from terrain.validate import check_latlon


@dataclass(frozen=True)
class HeightResult:
    """height_msl_m: (n,) float64, NaN where outside; status: (n,) uint8 STATUS_*."""

    height_msl_m: np.ndarray
    status: np.ndarray


@dataclass(frozen=True)
class NormalResult:
    """normal_enu: (n, 3) float64 unit vectors (east, north, up) of the bilinear
    surface; slope_deg: (n,) angle from horizontal; NaN where outside."""

    normal_enu: np.ndarray
    slope_deg: np.ndarray
    status: np.ndarray


class Terrain:
    """Holds the sources and answers vectorised queries over them."""

    def __init__(self, sources):
        self.sources = list(sources)
        if not self.sources:
            raise ValueError("a Terrain needs at least one source")

    def heights(self, lat, lon) -> HeightResult:
        """Bilinear heights (m, MSL) at (lat, lon) degrees, float64 (n,)."""
        lat, lon = check_latlon(lat, lon)
        out_h = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for source in self.sources:
            source.heights_into(lat, lon, out_h, status)
        return HeightResult(out_h, status)

    def normals(self, lat, lon) -> NormalResult:
        """Surface normals (ENU) and slope of the bilinear surface at (lat, lon)."""
        lat, lon = check_latlon(lat, lon)
        de = np.full(lat.shape, np.nan)
        dn = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for source in self.sources:
            source.gradient_into(lat, lon, de, dn, status)
        normal = np.stack([-de, -dn, np.ones_like(de)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        slope = np.degrees(np.arctan(np.hypot(de, dn)))
        return NormalResult(normal, slope, status)

    def describe(self) -> list[dict]:
        """One dict per source: name, kind, bounds, resolution, vertical datum."""
        return [source.describe() for source in self.sources]


@dataclass(frozen=True)
class ProfileResult:
    """Heights along one geodesic: every array (n_samples,) float64 except status."""

    lat_deg: np.ndarray
    lon_deg: np.ndarray
    distance_m: np.ndarray  # along the geodesic from the start point
    height_msl_m: np.ndarray
    status: np.ndarray


@dataclass(frozen=True)
class SegmentResult:
    """First intersection of each straight (ECEF) segment a -> b with the surface.

    hit: (n,) bool; distance_m: (n,) straight-line metres from a to the hit
    (NaN if none); lat_deg, lon_deg, height_msl_m: (n,) the hit point;
    normal_enu: (n, 3) surface normal at the hit; status: (n,) uint8, OUTSIDE
    when the segment leaves the terrain before any hit.
    """

    hit: np.ndarray
    distance_m: np.ndarray
    lat_deg: np.ndarray
    lon_deg: np.ndarray
    height_msl_m: np.ndarray
    normal_enu: np.ndarray
    status: np.ndarray


@dataclass(frozen=True)
class LosResult:
    """visible: (n,) bool, True when no terrain lies strictly between a and b;
    status: (n,) uint8 (OUTSIDE when the ray leaves the terrain: visible False)."""

    visible: np.ndarray
    status: np.ndarray
