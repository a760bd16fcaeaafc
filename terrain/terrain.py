"""The Terrain: an ordered stack of height sources answering batched queries.

Sources are tried in order; each point is answered by the first source that
covers it (real DEMs first, procedural terrain last, so a procedural world
fills everything the DEMs leave). A point a source covers only with a filled
void (STATUS_FILLED) is answered by the first later source that has it
measured (STATUS_OK), if any; synthetic sources (procedural) do not count. A source is anything with the methods of
:class:`terrain.raster.Raster` used here: ``heights_into``, ``gradient_into``,
``raster_for`` and ``describe`` (and optionally ``warm_cache``).

All heights are metres above mean sea level (the sources' vertical datum,
EGM96 for SRTM); argument order is always (lat, lon) in degrees.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass

import numpy as np

from terrain.raster import STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Raster
from terrain.validate import LON_ABS_MAX_DEG, check_latlon, latlon_all_valid


# Least margin around the endpoints' box when a source builds a raster for rays.
RAY_BOX_PAD_DEG = 0.01
# Source kinds (describe()["kind"]) whose heights are made up, not measured: a
# filled void of a DEM is not handed to them.
SYNTHETIC_KINDS = ("procedural",)


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


def _warm_cache(source, n_points: int) -> None:
    """Ask a source to bring its data into the CPU caches ahead of n_points, if it can."""
    warm = getattr(source, "warm_cache", None)
    if warm is not None:
        warm(n_points)


class Terrain:
    """Holds the sources and answers vectorised queries over them."""

    def __init__(self, sources):
        self.sources = list(sources)
        if not self.sources:
            raise ValueError("a Terrain needs at least one source")
        self._one = threading.local()  # height_at's and heights_of's buffers, per thread
        self._measured = None  # _measured_sources, found on first need
        # A single source with a scalar path of its own (Raster.height_at) answers height_at.
        self._scalar = getattr(self.sources[0], "height_at", None) if len(self.sources) == 1 else None

    def point_height(self):
        """A callable (lat, lon) -> height (m MSL, NaN outside) for one point the caller
        knows is valid (finite, lat within +-90, lon within +-LON_ABS_MAX_DEG): the single
        raster's own compiled call when there is one (no validation, no wrapper between),
        else :meth:`height_at`. For a host whose caches are cold at each call, where every
        layer costs (an aircraft refreshing the terrain under it)."""
        return self._scalar if self._scalar is not None else self.height_at

    def height_at(self, lat: float, lon: float) -> float:
        """The height (m MSL) at one point, NaN outside every source: what :meth:`heights`
        answers for it, without its per-call arrays, validation pass and result object (a
        host asking one point at a time: an aircraft far from the ground refreshes the
        terrain under it once a second). An invalid point raises as :meth:`heights` does.
        A single source with a scalar path of its own (:meth:`terrain.raster.Raster.height_at`)
        answers a valid point through it: one compiled call, where the arrays of
        :meth:`heights_of` cost about four times as much when the caller's caches are cold."""
        if -90.0 <= lat <= 90.0 and -LON_ABS_MAX_DEG <= lon <= LON_ABS_MAX_DEG and self._scalar is not None:
            return self._scalar(lat, lon)
        buf = getattr(self._one, "buf", None)
        if buf is None:
            buf = self._one.buf = (np.empty(1), np.empty(1), np.empty(1))
        la, lo, h = buf
        la[0], lo[0] = lat, lon
        return float(self.heights_of(la, lo, h)[0])

    def heights_of(self, lat: np.ndarray, lon: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Heights (m MSL, NaN outside every source) of a few points held in (n,) float64
        C-contiguous arrays, written into ``out`` (n,) float64 and returned: what
        :meth:`heights` answers, without its per-call arrays and result object (a host
        asking a handful of points every step: an aircraft's contacts near the ground).
        Invalid points raise as :meth:`heights` does."""
        if len(self.sources) != 1 or not latlon_all_valid(lat, lon, LON_ABS_MAX_DEG):
            out[:] = self.heights(lat, lon).height_msl_m
            return out
        st = getattr(self._one, "status", None)
        if st is None or st.size < lat.size:
            st = self._one.status = np.empty(max(lat.size, 64), np.uint8)
        st = st[:lat.size]
        st.fill(STATUS_OUTSIDE)
        out.fill(np.nan)
        self.sources[0].heights_into(lat, lon, out, st)
        return out

    def heights(self, lat, lon, *, warm: bool = False) -> HeightResult:
        """Bilinear heights (m, MSL) at (lat, lon) degrees, float64 (n,).

        warm: let each source reached stream its posts into the CPU caches
        first when the batch is large enough to gain from it (see
        :meth:`terrain.raster.Raster.warm_cache`); for callers whose caches are
        cold, like the gRPC service. Results are the same either way.
        """
        lat, lon = check_latlon(lat, lon)
        out_h = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for idx, source in self._unanswered(status):
            if warm:
                _warm_cache(source, lat.size if idx is None else idx.size)
            if idx is None:
                source.heights_into(lat, lon, out_h, status)
            else:
                sub_h = np.full(idx.size, np.nan)
                sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
                source.heights_into(lat[idx], lon[idx], sub_h, sub_status)
                out_h[idx] = sub_h
                status[idx] = sub_status
        self._prefer_measured(lat, lon, out_h, status)
        return HeightResult(out_h, status)

    def _prefer_measured(self, lat, lon, out_h, status) -> None:
        """Answer points a source gave as FILLED (a filled void: a guess) by the first source
        that has them measured (status OK) instead, if any; synthetic sources (procedural)
        measure nothing and are not asked. A terrain of one measured source pays nothing; others
        one pass over the statuses, and the filled points their queries."""
        if len(self.sources) == 1 or len(self._measured_sources()) < 2:
            return
        idx = np.flatnonzero(status == STATUS_FILLED)
        if idx.size == 0:
            return
        for source in self._measured_sources():
            sub_h = np.full(idx.size, np.nan)
            sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
            source.heights_into(lat[idx], lon[idx], sub_h, sub_status)
            ok = sub_status == STATUS_OK
            out_h[idx[ok]] = sub_h[ok]
            status[idx[ok]] = STATUS_OK
            idx = idx[~ok]
            if idx.size == 0:
                return

    def _measured_sources(self) -> list:
        """The sources holding measured data: every one but the synthetic (procedural) ones."""
        if self._measured is None:
            self._measured = [s for s in self.sources if s.describe().get("kind") not in SYNTHETIC_KINDS]
        return self._measured

    def _unanswered(self, status):
        """(indices, source) for each source in priority order, indices being the
        points no earlier source answered (None: all of them); stops once every
        point is answered, so a point costs only the sources it reaches."""
        for k, source in enumerate(self.sources):
            if k == 0:
                yield None, source
                continue
            idx = np.flatnonzero(status == STATUS_OUTSIDE)
            if idx.size == 0:
                return
            yield (None if idx.size == status.size else idx), source

    def normals(self, lat, lon, *, warm: bool = False) -> NormalResult:
        """Surface normals (ENU) and slope of the bilinear surface at (lat, lon).

        warm: as for :meth:`heights`.
        """
        de, dn, status = self.gradients(lat, lon, warm=warm)
        normal = np.stack([-de, -dn, np.ones_like(de)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        slope = np.degrees(np.arctan(np.hypot(de, dn)))
        return NormalResult(normal, slope, status)

    def gradients(self, lat, lon, *, warm: bool = False) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dh/d east metre, dh/d north metre, status) of the bilinear surface at (lat, lon),
        float64 (n,) each, NaN where outside: what :meth:`normals` is made from, for callers
        that build their own (the clipmap's normal maps). warm: as for :meth:`heights`."""
        lat, lon = check_latlon(lat, lon)
        de = np.full(lat.shape, np.nan)
        dn = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for idx, source in self._unanswered(status):
            if warm:
                _warm_cache(source, lat.size if idx is None else idx.size)
            if idx is None:
                source.gradient_into(lat, lon, de, dn, status)
            else:
                sub_de, sub_dn = np.full(idx.size, np.nan), np.full(idx.size, np.nan)
                sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
                source.gradient_into(lat[idx], lon[idx], sub_de, sub_dn, sub_status)
                de[idx], dn[idx], status[idx] = sub_de, sub_dn, sub_status
        return de, dn, status

    def height_grid(self, lat_rows, lon_cols) -> HeightResult:
        """:meth:`heights` at every point of the lattice lat_rows x lon_cols (degrees, (rows,) and
        (cols,)): height_msl_m and status (rows, cols), the answers :meth:`heights` gives for
        those points, bit for bit. Sources that answer lattices (rasters) index each row and
        column once instead of each point (a clipmap level's strips, its normal maps)."""
        def by_points(lat, lon):
            r = self.heights(lat, lon)
            return (r.height_msl_m,), r.status

        outs, status = self._grid(lat_rows, lon_cols, "grid_heights_into", 1, by_points)
        return HeightResult(outs[0], status)

    def gradient_grid(self, lat_rows, lon_cols) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """:meth:`gradients` at every point of the lattice lat_rows x lon_cols: (de, dn, status),
        (rows, cols) each, as :meth:`height_grid`."""
        def by_points(lat, lon):
            de, dn, st = self.gradients(lat, lon)
            return (de, dn), st

        outs, status = self._grid(lat_rows, lon_cols, "grid_gradient_into", 2, by_points)
        return outs[0], outs[1], status

    def _grid(self, lat_rows, lon_cols, method: str, n_out: int, by_points):
        """(outputs, status) of a lattice query: the first source's lattice method where it has
        one, then the per-point query (``by_points``) for the points left, which tries every
        source in order as the per-point query of the whole lattice would."""
        lat_rows = check_latlon(lat_rows, np.zeros(np.size(lat_rows)), "row ")[0]
        lon_cols = check_latlon(np.zeros(np.size(lon_cols)), lon_cols, "column ")[1]
        shape = (lat_rows.size, lon_cols.size)
        outs = [np.full(shape, np.nan) for _ in range(n_out)]
        status = np.full(shape, STATUS_OUTSIDE, np.uint8)
        if lat_rows.size and lon_cols.size and hasattr(self.sources[0], method):
            getattr(self.sources[0], method)(lat_rows, lon_cols, *outs, status)
            # FILLED points too: the per-point query lets a measured lower source answer them.
            left = np.flatnonzero((status.ravel() == STATUS_OUTSIDE) | (status.ravel() == STATUS_FILLED))
            if left.size == 0 or len(self.sources) == 1:
                return outs, status
        else:
            left = np.arange(status.size)
        got, st = by_points(np.repeat(lat_rows, lon_cols.size)[left], np.tile(lon_cols, lat_rows.size)[left])
        for out, values in zip(outs, got):
            out.ravel()[left] = values
        status.ravel()[left] = st
        return outs, status

    def profile(self, lat1: float, lon1: float, lat2: float, lon2: float, n_samples: int) -> ProfileResult:
        """Heights (m, MSL) at n_samples equally spaced points along the WGS84
        geodesic from (lat1, lon1) to (lat2, lon2), degrees."""
        from terrain.profile import geodesic_profile

        def source_heights(lat, lon):
            res = self.heights(lat, lon)
            return res.height_msl_m, res.status

        return ProfileResult(*geodesic_profile(source_heights, lat1, lon1, lat2, lon2, n_samples))

    def intersect(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> SegmentResult:
        """First contact of each straight (ECEF) segment a -> b with the surface.

        Arrays (n,) float64: (lat, lon) degrees, heights metres MSL. Each
        segment is answered by the first source that holds it until its hit
        (or its whole length); a segment no source holds is OUTSIDE.
        """
        from terrain.los import check_segments, intersect_segments

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        n = rays[0].size
        out = SegmentResult(np.zeros(n, bool), *(np.full(n, np.nan) for _ in range(4)),
                            np.full((n, 3), np.nan), np.full(n, STATUS_OUTSIDE, np.uint8))
        for raster, todo in self._rasters_for(rays, out.status):
            got = SegmentResult(*intersect_segments(raster, *(r[todo] for r in rays)))
            for name in SegmentResult.__dataclass_fields__:
                getattr(out, name)[todo] = getattr(got, name)
        return out

    def line_of_sight(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> LosResult:
        """Whether each straight (ECEF) segment a -> b clears the surface.

        Arrays as :meth:`intersect`. Contacts within 1 mm of an endpoint do not
        block (a point on the ground can see); symmetric in a and b.
        """
        from terrain.los import check_segments, line_of_sight

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        n = rays[0].size
        out = LosResult(np.zeros(n, bool), np.full(n, STATUS_OUTSIDE, np.uint8))
        for raster, todo in self._rasters_for(rays, out.status):
            visible, status = line_of_sight(raster, *(r[todo] for r in rays))
            out.visible[todo] = visible
            out.status[todo] = status
        return out

    def _rasters_for(self, rays, status):
        """Yield (raster, index array) per source for the rays still OUTSIDE.

        A Raster source traces every pending ray itself (its kernel marks the
        ones that leave it); other sources hand out a raster covering the
        pending rays' bounding box. ``status`` is updated by the caller between
        yields, which is what moves unanswered rays on to the next source.
        """
        a_lat, a_lon, _, b_lat, b_lon, _ = rays
        for source in self.sources:
            todo = np.flatnonzero(status == STATUS_OUTSIDE)
            if todo.size == 0:
                return
            if isinstance(source, Raster):
                yield source, todo
                continue
            lats = np.concatenate([a_lat[todo], b_lat[todo]])
            # Unroll b's longitude next to a's so a box never spans the long way round.
            b_lon_near = a_lon[todo] + (b_lon[todo] - a_lon[todo] + 180.0) % 360.0 - 180.0
            lons = np.concatenate([a_lon[todo], b_lon_near])
            pad = RAY_BOX_PAD_DEG + ray_bulge_deg(np.abs(lats).max(), a_lat[todo], a_lon[todo],
                                                  b_lat[todo], b_lon_near)
            raster = source.raster_for(lats.min() - pad, lons.min() - pad, lats.max() + pad, lons.max() + pad)
            if raster is not None:
                yield raster, todo

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


def ray_bulge_deg(lat_abs_max_deg: float, a_lat, a_lon, b_lat, b_lon) -> float:
    """How far (degrees) a chord's ground track may stray poleward of its endpoints.

    A great circle through two points of one parallel at latitude phi, d
    apart, peaks about d^2 tan(phi) / (8 R^2) radians above it (small-angle
    expansion of the great-circle vertex latitude); d is bounded here by the
    endpoints' degree spans, generously, with R the equatorial radius.
    """
    d_rad = np.radians(np.hypot(np.abs(b_lat - a_lat), np.abs(b_lon - a_lon)).max())
    tan_phi = np.tan(np.radians(min(lat_abs_max_deg, 89.0)))
    return float(np.degrees(d_rad * d_rad * tan_phi / 8.0))
