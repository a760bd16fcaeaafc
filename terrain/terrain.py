"""The Terrain: an ordered stack of height sources answering batched queries.

Sources are tried in order; each point is answered by the first source that
covers it (real DEMs first, procedural terrain last, so a procedural world
fills everything the DEMs leave). A point a source covers only with a filled
void (STATUS_FILLED) is answered by the first later source that has it
measured (STATUS_OK), if any; synthetic sources (procedural) do not count.
Normals and slopes follow the same rule, from the source the height comes from.
Segments (intersect, line of sight) meet the same surface: at every point that
of the first source covering it (:func:`terrain.los.stack_trace`). A source is
anything with the methods of :class:`terrain.raster.Raster` used here:
``heights_into``, ``gradient_into``, ``raster_for`` and ``describe`` (and
optionally ``warm_cache``).

All heights are metres above mean sea level (the sources' vertical datum,
EGM96 for SRTM); argument order is always (lat, lon) in degrees.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass

import numpy as np

from terrain.geodesy import ecef_to_geodetic, geodetic_to_ecef
from terrain.raster import STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Raster, metres_per_index
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
        for _, idx, sub_h in self._measured_instead(lat, lon, status):
            out_h[idx] = sub_h
            status[idx] = STATUS_OK
        return HeightResult(out_h, status)

    def _measured_instead(self, lat, lon, status):
        """Yield (source, indices, their heights there) for the points answered FILLED (a filled
        void: a guess) that a measured source has with status OK: each point by the first such
        source, in priority order; synthetic sources (procedural) measure nothing and are not
        asked. This is the one place the rule lives, so heights, slopes and their lattice forms
        take a point from the same source. A terrain of one measured source pays nothing; others
        one pass over the statuses, and the filled points their height queries."""
        if len(self.sources) == 1 or len(self._measured_sources()) < 2:
            return
        idx = np.flatnonzero(status == STATUS_FILLED)
        for source in self._measured_sources():
            if idx.size == 0:
                return
            sub_h = np.full(idx.size, np.nan)
            sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
            source.heights_into(lat[idx], lon[idx], sub_h, sub_status)
            ok = sub_status == STATUS_OK
            if ok.any():
                yield source, idx[ok], sub_h[ok]
            idx = idx[~ok]

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
        # A filled point's slope comes from the source its height comes from (heights' rule,
        # decided on heights). That source's slope is missing only on a post at the rim of one
        # of its holes (the slope's cell has a NaN corner, the height reads the post alone):
        # there the filled answer stays.
        for source, idx, _ in self._measured_instead(lat, lon, status):
            sub_de, sub_dn = np.full(idx.size, np.nan), np.full(idx.size, np.nan)
            sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
            source.gradient_into(lat[idx], lon[idx], sub_de, sub_dn, sub_status)
            got = sub_status != STATUS_OUTSIDE
            de[idx[got]], dn[idx[got]], status[idx[got]] = sub_de[got], sub_dn[got], sub_status[got]
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
            if len(self.sources) == 1:
                return outs, status
            # FILLED points too, where a second measured source may have them: the per-point
            # query lets it answer them (heights and slopes alike, see _measured_instead).
            left = status.ravel() == STATUS_OUTSIDE
            if len(self._measured_sources()) >= 2:
                left |= status.ravel() == STATUS_FILLED
            left = np.flatnonzero(left)
            if left.size == 0:
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

        Arrays (n,) float64: (lat, lon) degrees, heights metres MSL. The surface is, at every
        point, that of the first source covering it (as :meth:`heights` answers; see
        :func:`terrain.los.stack_trace`), so a -> b and b -> a meet the same surface wherever the
        segment crosses from one source into another. A segment that reaches a stretch no source
        covers before any hit is OUTSIDE.
        """
        from terrain.los import check_segments

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        a = geodetic_to_ecef(rays[0], rays[1], rays[2])
        b = geodetic_to_ecef(rays[3], rays[4], rays[5])
        n = rays[0].size
        s, dcol, drow, status, which, rasters = self._trace(rays, a, b, np.zeros(n), np.ones(n))
        hit = ~np.isnan(s)
        lat, lon, h = ecef_to_geodetic(a + s[:, None] * (b - a))
        normal = np.full((n, 3), np.nan)
        for k in np.unique(which[hit]):
            sel = np.flatnonzero(hit & (which == k))
            g = rasters[k].georef
            m_col, m_row = metres_per_index(g.crs, g.dx, g.dy, lat[sel])
            nk = np.stack([-dcol[sel] / m_col, -drow[sel] / m_row, np.ones(sel.size)], axis=-1)
            normal[sel] = nk / np.linalg.norm(nk, axis=-1, keepdims=True)
        return SegmentResult(hit, s * np.linalg.norm(b - a, axis=1), lat, lon, h, normal, status)

    def line_of_sight(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl) -> LosResult:
        """Whether each straight (ECEF) segment a -> b clears the surface.

        Arrays as :meth:`intersect`, and the same surface. Contacts within 1 mm of an endpoint
        do not block (a point on the ground can see); symmetric in a and b: each segment is
        traced from the endpoint whose ECEF (x, y, z) sorts first, and one that reaches a
        stretch no source covers before any contact from the other as well (blocked when
        either meets the surface first, else OUTSIDE).
        """
        from terrain.los import check_segments, line_of_sight, stack_line_of_sight

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        n = rays[0].size
        first = self._first_raster(rays, np.arange(n))
        if first is not None:
            visible, status = line_of_sight(first, *rays)
        else:
            visible, status = np.zeros(n, bool), np.full(n, STATUS_OUTSIDE, np.uint8)
        todo = np.flatnonzero(status == STATUS_OUTSIDE)
        if len(self.sources) == 1 or todo.size == 0:
            return LosResult(visible, status)
        # Off the first source: the stack of every source's surface, as line_of_sight does on one.
        a = geodetic_to_ecef(rays[0][todo], rays[1][todo], rays[2][todo])
        b = geodetic_to_ecef(rays[3][todo], rays[4][todo], rays[5][todo])
        rasters = [first] + self._ray_rasters(rays, todo, from_source=1)
        visible[todo], status[todo] = stack_line_of_sight(rasters, a, b)
        return LosResult(visible, status)

    def _trace(self, rays, a, b, s_lo, s_hi):
        """First contact s in [s_lo, s_hi] of each segment a + s (b - a) with the stack's surface:
        (s (NaN: none), d h / d col and d h / d row there, status, the hitting raster's index in
        ``rasters``, rasters). The first source traces every segment on its own (its kernel
        marks those that leave it); only those go through :func:`terrain.los.stack_trace`, so a
        terrain whose segments stay on its first source pays nothing more."""
        from terrain.los import stack_trace, trace_segments

        n = a.shape[0]
        first = self._first_raster(rays, np.arange(n))
        which = np.zeros(n, np.int64)
        if first is not None:
            s, dcol, drow, status = trace_segments(first, a, b, s_lo, s_hi)
        else:
            s, dcol, drow = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
            status = np.full(n, STATUS_OUTSIDE, np.uint8)
        todo = np.flatnonzero(status == STATUS_OUTSIDE)
        if len(self.sources) == 1 or todo.size == 0:
            return s, dcol, drow, status, which, [first]
        rasters = [first] + self._ray_rasters(rays, todo, from_source=1)
        s[todo], dcol[todo], drow[todo], status[todo], which[todo] = stack_trace(
            rasters, a[todo], b[todo], s_lo[todo], s_hi[todo])
        return s, dcol, drow, status, which, rasters

    def _first_raster(self, rays, idx):
        """The first source's raster for the segments idx: the source itself if it is a Raster."""
        if isinstance(self.sources[0], Raster):
            return self.sources[0]
        return self._ray_rasters(rays, idx, from_source=0, upto=1)[0]

    def _ray_rasters(self, rays, idx, from_source: int, upto: int | None = None) -> list:
        """One raster per source (from_source up to ``upto``) for the segments idx: a Raster
        source itself, any other the raster it hands out for the segments' bounding box (None
        where it has none)."""
        a_lat, a_lon, _, b_lat, b_lon, _ = rays
        out = []
        for source in self.sources[from_source:upto]:
            if isinstance(source, Raster) or idx.size == 0:
                out.append(source if isinstance(source, Raster) else None)
                continue
            lats = np.concatenate([a_lat[idx], b_lat[idx]])
            # Unroll every a's longitude next to the first one's, and b's next to its a's, so that
            # a box never spans the long way round (segments on both sides of the antimeridian).
            a_lon_near = a_lon[idx[0]] + (a_lon[idx] - a_lon[idx[0]] + 180.0) % 360.0 - 180.0
            b_lon_near = a_lon_near + (b_lon[idx] - a_lon[idx] + 180.0) % 360.0 - 180.0
            lons = np.concatenate([a_lon_near, b_lon_near])
            pad = RAY_BOX_PAD_DEG + ray_bulge_deg(np.abs(lats).max(), a_lat[idx], a_lon_near, b_lat[idx],
                                                  b_lon_near)
            west = lons.min() - pad
            turns = 360.0 * math.floor((west + 180.0) / 360.0)  # west in [-180, 180); east may pass 180
            out.append(source.raster_for(max(lats.min() - pad, -90.0), west - turns, min(lats.max() + pad, 90.0),
                                         lons.max() + pad - turns))
        return out

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
