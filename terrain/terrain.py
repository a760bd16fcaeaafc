"""The Terrain: an ordered stack of height sources answering batched queries.

Sources are tried in order; each point is answered by the first source that
covers it (real DEMs first, procedural terrain last, so a procedural world
fills everything the DEMs leave). A point a source covers only with a filled
void (STATUS_FILLED) is answered by the first later source that has it
measured (STATUS_OK), if any; synthetic sources (procedural) do not count.
Normals and slopes follow the same rule, from the source the height comes from.
Segments (intersect, line of sight) meet, at every point, the surface the
same rule gives (:func:`terrain.los.stack_trace`): that of the first source
covering it, or over its filled void the first later source measuring the
ground there. A source is
anything with the methods of :class:`terrain.raster.Raster` used here:
``heights_into``, ``gradient_into``, ``raster_for`` and ``describe`` (and
optionally ``warm_cache``, and ``ray_raster_for``: ``raster_for`` for a group of
rays that raises LimitExceeded where ``raster_for`` would answer with less).

All heights are metres above mean sea level (the sources' vertical datum,
EGM96 for SRTM); argument order is always (lat, lon) in degrees.
"""

from __future__ import annotations

import math
import threading
import time
from dataclasses import dataclass

import numpy as np

from sortie.errors import LimitExceeded, SortieError
from terrain.geodesy import WGS84_A_M, WGS84_B_M, WGS84_E2, ecef_to_geodetic, geodetic_to_ecef
from terrain.raster import STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Raster, metres_per_index, normals_from_gradients
from terrain.validate import LON_ABS_MAX_DEG, check_latlon, latlon_all_valid


# Margin (m) around a segment's ground track in the box a source builds a raster for: far above the
# track model's error (terrain.los.MODEL_ERROR_M, 1 micrometre; 1 mm within 1 cm of the polar axis)
# and rounding, far below any source's post spacing (a detail raster's finest lattice: about 0.5 m).
RAY_BOX_PAD_M = 0.1
# Least metres per radian of latitude on WGS84: the meridian radius of curvature at the equator,
# a (1 - e^2) (Torge & Mueller, Geodesy, 4th ed., eq. 4.32), so metres of pad are at least that
# many degrees. Also the least radius of curvature, bounding a chord's sag below its ends.
MERIDIAN_RADIUS_MIN_M = WGS84_A_M * (1.0 - WGS84_E2)
# A single segment whose box a source cannot serve is traced in halves (each with its own box)
# down to this length (m); a shorter one gets the source's own answer (raster_for).
RAY_PART_MIN_M = 1.0
# Where a stretch is cut (fraction of it): the golden section, not the middle, so that a segment
# symmetric about a pole (ends at one latitude, 180 degrees apart) has the pole inside one part,
# which alone needs every longitude, not at the end of two (each a full turn of the ring).
RAY_PART_CUT = (3.0 - math.sqrt(5.0)) / 2.0
# Source kinds (describe()["kind"]) whose heights are made up, not measured: a
# filled void of a DEM is not handed to them.
SYNTHETIC_KINDS = ("procedural",)
# heights / gradients (threads=k) split a raster's share of a batch into k contiguous parts, each at least
# this many points (smaller batches: one thread; a hand-off costs ~20-50 us, a point ~13 ns).
PARALLEL_MIN_POINTS_PER_THREAD = 16_384
# The shell every surface of a stack lies in (Terrain._shell): what a segment does above it or
# below it is known without tracing. Metres of margin on either radius, far above rounding.
SHELL_MARGIN_M = 1.0
# Most posts of synthetic-source rasters (the procedural world's, terrain.procedural.ProceduralTerrain.raster_for)
# one segment call (intersect, line_of_sight) may assemble for its segments, over every raster it
# makes (groups, stack partitions, parts of long segments): a raster and its min/max pyramid cost
# about 100 ns a post (measured), so 2^25 posts is 3-4 s of work. One raster holds at most
# terrain.procedural.RASTER_FOR_MAX_POSTS (2^23) posts, so a batch over one area stays far below; a
# long segment is traced in parts of about that many posts each (about 10 M posts for a 3-degree
# diagonal at the default spacing). Its new blocks are held to terrain.procedural.MAX_NEW_BLOCKS_PER_CALL,
# as a heights query's are. See RayBudget.
RAY_MAX_POSTS_PER_CALL = 1 << 25
# The fixed cost of one ray raster of a synthetic source, in posts of raster (the ~100 ns a post of
# RAY_MAX_POSTS_PER_CALL's measure): about 0.4 ms whatever its size (measured for a 1 km segment's
# raster over the procedural world, its blocks cached: ray_box 0.14 ms, box_cost 0.06 ms,
# raster_for 0.05 ms, pyramid and trace 0.1 ms). A group of segments is split where its raster
# would hold more posts than its segments' own boxes plus this for each further raster
# (terrain.terrain._sparse), and RayBudget counts it for every raster made, so splitting cannot
# hide work from the budget.
RAY_RASTER_OVERHEAD_POSTS = 4096
# Segments traced on one raster between two checks of a RayBudget's ``check`` (the caller's deadline):
# 4096 rays of 10 km over a DEM take a few milliseconds.
RAY_CHUNK = 4096


def shell_stretch(a: np.ndarray, b: np.ndarray, r_out: float, r_in: float):
    """Where each ECEF segment a + s (b - a), s in [0, 1], meets the shell between two spheres
    about the Earth's centre: (s_lo, s_hi, dives). [s_lo, s_hi] is the stretch inside the
    outer sphere (s_lo > s_hi: none), cut short where the segment enters the inner sphere from
    outside it, and ``dives`` marks those that do enter it within the segment, or start inside
    it (their stretch is s = 0 alone: a is below every surface, so it is the first contact).
    Roots of |a + s d|^2 = r^2, a quadratic in s."""
    d = b - a
    qa = np.einsum("ij,ij->i", d, d)
    qb = 2.0 * np.einsum("ij,ij->i", a, d)
    aa = np.einsum("ij,ij->i", a, a)
    safe = np.where(qa > 0.0, qa, 1.0)

    def roots(r):
        disc = qb * qb - 4.0 * qa * (aa - r * r)
        root = np.sqrt(np.maximum(disc, 0.0))
        return (-qb - root) / (2.0 * safe), (-qb + root) / (2.0 * safe), (disc >= 0.0) & (qa > 0.0)

    o1, o2, o_hit = roots(r_out)
    inside_out = aa <= r_out * r_out
    s_lo = np.where(inside_out, 0.0, np.where(o_hit, np.maximum(o1, 0.0), 2.0))
    s_hi = np.where(o_hit, np.minimum(o2, 1.0), np.where(inside_out, 1.0, -1.0))
    i1, _, i_hit = roots(r_in)
    dives = i_hit & (aa > r_in * r_in) & (i1 > 0.0) & (i1 < 1.0)
    s_hi = np.where(dives, np.minimum(s_hi, i1), s_hi)
    # Not traced past a: from near the Earth's centre (a valid end: lat 0, h = -a) the rest of
    # the track spans every latitude and longitude, a box no synthetic source serves.
    below = aa < r_in * r_in
    return s_lo, np.where(below, 0.0, s_hi), dives | below


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


class RayBudget:
    """What one segment call (:meth:`Terrain.intersect`, :meth:`Terrain.line_of_sight`) may spend on
    the rasters synthetic sources make for its segments, and how it learns that its caller is gone.

    Checked twice. Before any work (:meth:`estimate`): the posts and new blocks under the boxes of
    the segments' stretches that are traced (each segment's box, or a long one's pieces' boxes,
    about the parts it is traced in; shared posts counted once) over every source with
    ``boxes_cost`` (the procedural world); a call over ``max_posts`` or ``max_new_blocks`` there is
    refused at once. While tracing (:meth:`charge`): every raster such a source makes for the call
    (``box_cost``, before it is made) adds its posts (plus RAY_RASTER_OVERHEAD_POSTS, its fixed
    cost, so many small rasters count as the work they are) and new blocks, and the call is refused
    (LimitExceeded) at the raster that would pass either limit, however it was split (groups,
    parts): the new-block limit is per call, not per raster. ``check``: None, or a callable called
    between chunks of work (before each raster a source makes, between chunks of RAY_CHUNK
    segments traced on one raster) that raises to end the call (the terrain service's does when
    the caller's deadline passes or it cancels). Not thread-safe: one per call.
    """

    def __init__(self, max_posts: int = RAY_MAX_POSTS_PER_CALL, max_new_blocks: int | None = None, check=None):
        from terrain.procedural import MAX_NEW_BLOCKS_PER_CALL

        self.max_posts = int(max_posts)
        self.max_new_blocks = MAX_NEW_BLOCKS_PER_CALL if max_new_blocks is None else int(max_new_blocks)
        self.check = check
        self.posts = 0
        self.new_blocks = 0
        self._ring = False  # a raster of every longitude was made: a ring of blocks is allowed

    def tick(self) -> None:
        """Call ``check`` (it raises to end the call)."""
        if self.check is not None:
            self.check()

    def chunks(self, idx: np.ndarray):
        """idx in chunks of RAY_CHUNK, ``check`` called before each; idx whole without a check."""
        if self.check is None or idx.size <= RAY_CHUNK:
            self.tick()
            yield idx
            return
        for start in range(0, idx.size, RAY_CHUNK):
            self.tick()
            yield idx[start:start + RAY_CHUNK]

    def estimate(self, sources, a_ecef: np.ndarray, b_ecef: np.ndarray) -> None:
        """Refuse (LimitExceeded), before any work, segments a -> b ((n, 3) ECEF: the stretches
        to be traced) whose boxes hold more posts or new blocks of a source with ``boxes_cost``
        than the limits. A segment whose box would hold more than RASTER_FOR_MAX_POSTS posts is
        cut into pieces of about that many (m pieces for m^2 times too many: its parts), and a piece
        still over it (one over a pole) in halves as the trace cuts it (:func:`_halved_pieces`)."""
        from terrain.procedural import RASTER_FOR_MAX_POSTS

        costly = [i for i, src in enumerate(sources) if hasattr(src, "boxes_cost")]
        if not costly or a_ecef.shape[0] == 0:
            return
        self.tick()
        lat_a, lon_a, _ = ecef_to_geodetic(a_ecef)
        lat_b, lon_b, _ = ecef_to_geodetic(b_ecef)
        d_lon = np.abs((lon_b - lon_a + 180.0) % 360.0 - 180.0)
        for i in costly:
            src = sources[i]
            sp = src.spacing_deg
            posts = (np.abs(lat_b - lat_a) / sp + 2.0) * (d_lon / sp + 2.0)
            m = np.clip(np.ceil(np.sqrt(posts / RASTER_FOR_MAX_POSTS)), 1, RAY_ESTIMATE_MAX_PIECES).astype(np.int64)
            seg = np.repeat(np.arange(m.size), m)
            k = np.arange(seg.size) - np.repeat(np.cumsum(m) - m, m)
            d = b_ecef - a_ecef
            p0 = a_ecef[seg] + (k / m[seg])[:, None] * d[seg]
            p1 = a_ecef[seg] + ((k + 1) / m[seg])[:, None] * d[seg]
            la0, lo0, la1, lo1 = _halved_pieces(p0, p1, sp)
            # Pieces a DEM before the source holds end to end are left to it (it answers them; should
            # one leave it after all, through a hole, the rasters made are counted as they are).
            left = np.ones(la0.size, bool)
            for dem in (s_ for s_ in sources[:i] if isinstance(s_, Raster)):
                left &= ~(_inside(dem.bounds, la0, lo0) & _inside(dem.bounds, la1, lo1))
            la0, lo0, la1, lo1 = la0[left], lo0[left], la1[left], lo1[left]
            if la0.size == 0:
                continue
            lo1 = lo0 + (lo1 - lo0 + 180.0) % 360.0 - 180.0
            west = np.minimum(lo0, lo1)
            turns = 360.0 * np.floor((west + 180.0) / 360.0)
            posts, new = src.boxes_cost(np.minimum(la0, la1), west - turns, np.maximum(la0, la1),
                                        np.maximum(lo0, lo1) - turns)
            self._over(posts, new, src, "under the boxes of the segments' stretches traced, before any work")

    def charge(self, source, box) -> None:
        """Count the raster ``source`` is about to make for ``box`` (lat_min, lon_min, lat_max,
        lon_max), if it says what one costs (``box_cost``; None: it will refuse the box, and the
        caller splits it); LimitExceeded when the call would pass a limit. Calls ``check`` first."""
        self.tick()
        cost = getattr(source, "box_cost", None)
        got = None if cost is None else cost(*box)
        if got is None:
            return
        self._ring = self._ring or (box[3] - box[1]) % 360.0 == 0.0 and box[3] > box[1]
        self.posts += got[0] + RAY_RASTER_OVERHEAD_POSTS  # a raster's fixed cost counted too
        self.new_blocks += got[1]
        self._over(self.posts, self.new_blocks, source, "made for the call's segments so far")

    def _over(self, posts: int, new: int, source, what: str) -> None:
        # As raster_for: a full ring of block columns (a segment over a pole) is always allowed.
        new_limit = max(self.max_new_blocks, getattr(source, "block_cols", 0)) if self._ring else self.max_new_blocks
        why = (f"{what}; ask about fewer or shorter segments per call, each long segment over "
               f"{getattr(source, 'name', 'a synthetic source')} costs posts along its length")
        if posts > self.max_posts:
            raise LimitExceeded("segments (procedural raster posts)", int(posts), self.max_posts, why)
        if new > new_limit:
            raise LimitExceeded("segments (new procedural blocks)", int(new), new_limit, why)


def source_boxes(descriptions) -> list[tuple[float, float, float, float]]:
    """(lat_min, lon_min, lat_max, lon_max) degrees of each source of a terrain's describe()
    (``descriptions``, in order; a service's values may be text) that has a finite box; lon_max
    may pass 180."""
    out = []
    for d in descriptions:
        try:
            box = tuple(float(d.get(k)) for k in ("lat_min", "lon_min", "lat_max", "lon_max"))
        except (TypeError, ValueError):
            continue
        if all(math.isfinite(v) for v in box):
            out.append(box)
    return out


def _inside(bounds, lat, lon) -> np.ndarray:
    """(n,) bool: points (degrees) inside a raster's bounds (lat_min, lon_min, lat_max, lon_max; lon_max
    may pass 180)."""
    lat0, lon0, lat1, lon1 = bounds
    return (lat >= lat0) & (lat <= lat1) & ((lon - lon0) % 360.0 <= lon1 - lon0)


# Most pieces RayBudget.estimate cuts one segment into (a stretch 10^4 pieces long would be
# over the posts limit on its own).
RAY_ESTIMATE_MAX_PIECES = 4096
# Most times RayBudget.estimate halves a piece whose own box is still over RASTER_FOR_MAX_POSTS
# (a piece over a pole spans half a turn of longitude until it is about 30 rows tall: 7 halvings
# of a 3-degree piece; 2^-16 of a turn-wide piece is under a block).
RAY_ESTIMATE_MAX_HALVINGS = 16


def _halved_pieces(p0: np.ndarray, p1: np.ndarray, spacing_deg: float):
    """(lat0, lon0, lat1, lon1) degrees of the ends of ECEF pieces p0 -> p1 ((k, 3) metres each),
    each piece whose box of its ends holds more than RASTER_FOR_MAX_POSTS posts of spacing_deg cut
    in halves at its ECEF midpoint, again while so (at most RAY_ESTIMATE_MAX_HALVINGS times), as
    Terrain._trace_in_halves traces a stretch whose box a source refuses. Equal cuts alone leave a
    piece over a pole spanning half a turn of longitude over most of its rows: a 330 km segment
    over the south pole, 6 M posts to trace, was refused before any work at 191 M."""
    from terrain.procedural import RASTER_FOR_MAX_POSTS

    k0 = p0.shape[0]
    for halving in range(RAY_ESTIMATE_MAX_HALVINGS + 1):
        la0, lo0, _ = ecef_to_geodetic(p0)
        la1, lo1, _ = ecef_to_geodetic(p1)
        d_lon = np.abs((lo1 - lo0 + 180.0) % 360.0 - 180.0)
        big = (np.abs(la1 - la0) / spacing_deg + 2.0) * (d_lon / spacing_deg + 2.0) > RASTER_FOR_MAX_POSTS
        # (more big pieces than there were pieces: not a pole's few, leave the estimate as it is)
        if not big.any() or halving == RAY_ESTIMATE_MAX_HALVINGS or big.sum() > k0:
            return la0, lo0, la1, lo1
        mid = 0.5 * (p0[big] + p1[big])
        p0, p1 = np.concatenate([p0[~big], p0[big], mid]), np.concatenate([p1[~big], mid, p1[big]])


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

    def heights(self, lat, lon, *, warm: bool = False, threads: int = 1) -> HeightResult:
        """Bilinear heights (m, MSL) at (lat, lon) degrees, float64 (n,).

        warm: let each source reached stream its posts into the CPU caches
        first when the batch is large enough to gain from it (see
        :meth:`terrain.raster.Raster.warm_cache`); for callers whose caches are
        cold, like the gRPC service. threads: answer a DEM raster's share of a
        large batch on up to this many threads (:func:`_answer_into`; the
        service's query threads). Results are the same either way, bit for bit.
        """
        lat, lon = check_latlon(lat, lon)
        out_h = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for idx, source in self._unanswered(status):
            if warm:
                _warm_cache(source, lat.size if idx is None else idx.size)
            if idx is None:
                _answer_into(source, "heights_into", threads, lat, lon, out_h, status)
            else:
                sub_h = np.full(idx.size, np.nan)
                sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
                _answer_into(source, "heights_into", threads, lat[idx], lon[idx], sub_h, sub_status)
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
        asked. This is the one place the rule lives for points, so heights, slopes and their
        lattice forms take a point from the same source (segments apply it cell by cell:
        terrain.los._top_at). A terrain of one measured source pays nothing; others
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

    def _left_to_stack(self, status):
        """(n,) bool over a first source's statuses for segments: those the stack of every
        source answers instead, the segments that leave it (OUTSIDE) and, where a later source
        measures ground, those that passed over its filled voids (FILLED)."""
        if len(self._measured_sources()) < 2:
            return status == STATUS_OUTSIDE
        return (status == STATUS_OUTSIDE) | (status == STATUS_FILLED)

    def _measured_flags(self) -> list[bool]:
        """Per source, whether it holds measured data (:func:`terrain.los.stack_trace`'s ``measured``)."""
        measured = self._measured_sources()
        return [any(source is m for m in measured) for source in self.sources]

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

    def normals(self, lat, lon, *, warm: bool = False, threads: int = 1) -> NormalResult:
        """Surface normals (ENU) and slope of the bilinear surface at (lat, lon).

        warm, threads: as for :meth:`heights`.
        """
        de, dn, status = self.gradients(lat, lon, warm=warm, threads=threads)
        normal, slope = np.empty((de.size, 3)), np.empty(de.size)
        normals_from_gradients(de, dn, normal, slope)
        return NormalResult(normal, slope, status)

    def gradients(self, lat, lon, *, warm: bool = False, threads: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(dh/d east metre, dh/d north metre, status) of the bilinear surface at (lat, lon),
        float64 (n,) each, NaN where outside: what :meth:`normals` is made from, for callers
        that build their own (the clipmap's normal maps). warm, threads: as for :meth:`heights`."""
        lat, lon = check_latlon(lat, lon)
        de = np.full(lat.shape, np.nan)
        dn = np.full(lat.shape, np.nan)
        status = np.full(lat.shape, STATUS_OUTSIDE, dtype=np.uint8)
        for idx, source in self._unanswered(status):
            if warm:
                _warm_cache(source, lat.size if idx is None else idx.size)
            if idx is None:
                _answer_into(source, "gradient_into", threads, lat, lon, de, dn, status)
            else:
                sub_de, sub_dn = np.full(idx.size, np.nan), np.full(idx.size, np.nan)
                sub_status = np.full(idx.size, STATUS_OUTSIDE, dtype=np.uint8)
                _answer_into(source, "gradient_into", threads, lat[idx], lon[idx], sub_de, sub_dn, sub_status)
                de[idx], dn[idx], status[idx] = sub_de, sub_dn, sub_status
        # A filled point's slope comes from the source its height comes from (heights' rule,
        # decided on heights). A source has a slope wherever it has a height
        # (terrain.raster._rim_gradient), so its answer replaces the fill's.
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

    def intersect(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl, *, budget: RayBudget | None = None) -> SegmentResult:
        """First contact of each straight (ECEF) segment a -> b with the surface.

        Arrays (n,) float64: (lat, lon) degrees, heights metres MSL. The surface is, at every
        point, that of the first source covering it (see :func:`terrain.los.stack_trace`), so
        a -> b and b -> a meet the same surface wherever the segment crosses from one source into
        another. Over a filled void of one DEM that a later DEM measured it is the later DEM's
        surface, as :meth:`heights` answers (see ARCHITECTURE.md, "Line of sight and
        collision"). A segment that reaches a stretch no
        source covers before any hit is OUTSIDE. Each segment is answered as it is alone: a batch
        too wide for one raster of a procedural or store source is split into groups whose boxes
        it serves; LimitExceeded only for a single segment whose box it cannot serve, or for a call
        over its :class:`RayBudget` (``budget``; None: the default limits, no check).
        """
        from terrain.los import check_segments

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        a = geodetic_to_ecef(rays[0], rays[1], rays[2])
        b = geodetic_to_ecef(rays[3], rays[4], rays[5])
        n = rays[0].size
        budget = RayBudget() if budget is None else budget
        shell = self._shell_cut(rays, a, b)
        if shell is None:
            budget.estimate(self.sources, a, b)
            s, de, dn, status = self._trace(rays, a, b, np.zeros(n), np.ones(n), budget=budget)
        else:  # only the stretches inside the shell, up to where a segment dives below it
            cut, s_lo, s_hi, dives, above = shell
            s, de, dn = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
            status = np.full(n, STATUS_OK, np.uint8)
            go = np.flatnonzero(~above)
            budget.estimate(self.sources, cut[1][go], cut[2][go])
            got = self._trace(tuple(x[go] for x in cut[0]), a[go], b[go], s_lo[go], s_hi[go],
                              chord=(cut[1][go], cut[2][go]), budget=budget)
            s[go], de[go], dn[go], status[go] = got
            # A segment that dives below every surface meets one before; should rounding put
            # that contact past the cut, its whole length is traced.
            again = np.flatnonzero(dives & np.isnan(s))
            if again.size:
                got = self._trace(tuple(x[again] for x in rays), a[again], b[again], np.zeros(again.size),
                                  np.ones(again.size), budget=budget)
                s[again], de[again], dn[again], status[again] = got
        lat, lon, h = ecef_to_geodetic(a + s[:, None] * (b - a))
        normal = np.stack([-de, -dn, np.ones(n)], axis=-1)
        normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
        return SegmentResult(~np.isnan(s), s * np.linalg.norm(b - a, axis=1), lat, lon, h, normal, status)

    def line_of_sight(self, a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl, *,
                      budget: RayBudget | None = None) -> LosResult:
        """Whether each straight (ECEF) segment a -> b clears the surface.

        Arrays as :meth:`intersect`, and the same surface. Contacts within 1 mm of an endpoint
        do not block (a point on the ground can see); symmetric in a and b: each segment is
        traced from the endpoint whose ECEF (x, y, z) sorts first, and one that reaches a
        stretch no source covers before any contact from the other as well (blocked when
        either meets the surface first, else OUTSIDE). ``budget`` as :meth:`intersect` takes it.
        """
        from terrain.los import _both_ways, check_segments, line_of_sight, stack_line_of_sight

        rays = check_segments(a_lat, a_lon, a_h_msl, b_lat, b_lon, b_h_msl)
        n = rays[0].size
        a = geodetic_to_ecef(rays[0], rays[1], rays[2])
        b = geodetic_to_ecef(rays[3], rays[4], rays[5])
        visible, status = np.zeros(n, bool), np.full(n, STATUS_OUTSIDE, np.uint8)
        todo_all = np.arange(n)
        shell = self._shell_cut(rays, a, b)
        if shell is not None:
            # Below every surface somewhere: blocked; above every one all along: clear. The rest
            # are traced between the ends of their stretch inside the shell (nothing outside it
            # can block, and contacts at those ends, far from any surface, do not arise).
            (rays, a, b), _, _, dives, above = shell
            status[dives | above] = STATUS_OK
            visible[above] = True
            todo_all = np.flatnonzero(~(dives | above))
        budget = RayBudget() if budget is None else budget
        budget.estimate(self.sources, a[todo_all], b[todo_all])
        parted = []
        for first, idx in self._groups(0, rays, a, b, todo_all, parted=parted, budget=budget):
            if first is not None:
                for part in budget.chunks(idx):
                    visible[part], status[part] = line_of_sight(first, *(x[part] for x in rays))
            todo = idx[self._left_to_stack(status[idx])]
            if len(self.sources) == 1 or todo.size == 0:
                continue
            # Off the first source: the stack of every source's surface, as line_of_sight does on one.
            visible[todo], status[todo] = stack_line_of_sight(self._stack(first, rays, a, b, todo, parted, budget),
                                                              a[todo], b[todo], self._measured_flags())
        if parted:
            # Segments whose box a source cannot serve: line_of_sight's rule over their traces in parts.
            idx = np.unique(np.concatenate(parted))

            def trace(a_, b_, lo, hi):
                got = self._trace_in_halves(a_, b_, lo, hi, budget)
                return got[0], got[3]

            visible[idx], status[idx] = _both_ways(trace, a[idx], b[idx])
        return LosResult(visible, status)

    def _shell(self):
        """(r_out, r_in): radii (m, about the Earth's centre) between which every surface of the
        stack lies, for a stack that covers the globe (a procedural world: nothing is OUTSIDE, so
        cutting a segment short changes no status) and whose every source knows its heights'
        range; else None. A point at height h (the terrain's ECEF heights are these metres on the
        ellipsoid) is within a + h of the centre, and at least b + min(h, 0) from it."""
        if not any(getattr(src, "covers_globe", False) for src in self.sources):
            return None
        ranges = [getattr(src, "height_range_m", False) for src in self.sources]
        if any(r is False for r in ranges):
            return None
        lo = min(r[0] for r in ranges if r is not None)
        hi = max(r[1] for r in ranges if r is not None)
        return (WGS84_A_M + max(hi, 0.0) + SHELL_MARGIN_M, WGS84_B_M + min(lo, 0.0) - SHELL_MARGIN_M)

    def _shell_cut(self, rays, a, b):
        """Segments against :meth:`_shell`, or None (no shell, or no segment reaches out of it):
        ((rays, a, b) of the stretches' ends: a cut segment's moved to its stretch's, the others'
        as given; s_lo, s_hi: the stretches on the whole segments, 0 and 1 where not cut; dives;
        above: the segments with no stretch inside the shell, clear of every surface)."""
        shell = self._shell()
        if shell is None:
            return None
        s_lo, s_hi, dives = shell_stretch(a, b, *shell)
        cut = (s_lo > 0.0) | (s_hi < 1.0)
        if not cut.any():
            return None
        above = ~dives & (s_lo > s_hi)
        s_lo, s_hi = np.where(cut & ~above, s_lo, 0.0), np.where(cut & ~above, s_hi, 1.0)
        move = cut & ~above
        pa = np.where(move[:, None], a + s_lo[:, None] * (b - a), a)
        pb = np.where(move[:, None], a + s_hi[:, None] * (b - a), b)
        ends = list(rays)
        if move.any():
            ga, gb = ecef_to_geodetic(pa[move]), ecef_to_geodetic(pb[move])
            for k, v in enumerate(ga + gb):
                ends[k] = np.array(ends[k], dtype=np.float64, copy=True)
                ends[k][move] = v
        return (tuple(ends), pa, pb), s_lo, s_hi, dives, above

    def _trace(self, rays, a, b, s_lo, s_hi, chord=None, budget: RayBudget | None = None):
        """First contact s in [s_lo, s_hi] of each segment a + s (b - a) with the stack's surface:
        (s (NaN: none), d h / d east metre and d h / d north metre there, status). The first
        source traces every segment on its own (its kernel marks those that leave it); only those
        go through :func:`terrain.los.stack_trace` (and those over its filled voids, where a later
        source may measure the ground), so a terrain whose segments stay on its first source
        pays nothing more. Sources' boxes are made for the stretches [s_lo, s_hi]: ``rays``
        holds their ends' (lat, lon, h) and ``chord`` their ECEF ends (None: a and b, the
        stretches being the whole segments). A segment whose box a source cannot serve is traced
        in halves (:meth:`_trace_in_halves`). ``budget`` (:class:`RayBudget`) counts the rasters made."""
        from terrain.los import stack_partitions, stack_trace, trace_segments

        n = a.shape[0]
        ca, cb = (a, b) if chord is None else chord
        s, de, dn = np.full(n, np.nan), np.full(n, np.nan), np.full(n, np.nan)
        status = np.full(n, STATUS_OUTSIDE, np.uint8)
        parted = []
        budget = RayBudget() if budget is None else budget
        for first, idx in self._groups(0, rays, ca, cb, np.arange(n), parted=parted, budget=budget):
            if first is not None:
                for part in budget.chunks(idx):
                    got = trace_segments(first, a[part], b[part], s_lo[part], s_hi[part])
                    s[part], status[part] = got[0], got[3]
                    _slopes_into(first, a, b, s, part, got[1], got[2], de, dn)
            todo = idx[self._left_to_stack(status[idx])]
            if len(self.sources) == 1 or todo.size == 0:
                continue
            a_t, b_t, lo_t, hi_t = a[todo], b[todo], s_lo[todo], s_hi[todo]
            measured = self._measured_flags()
            for part, rasters, cov in stack_partitions(self._stack(first, rays, ca, cb, todo, parted, budget), a_t, b_t,
                                                       lo_t, hi_t, measured):
                got_s, dcol, drow, got_st, which = stack_trace(rasters, a_t[part], b_t[part], lo_t[part], hi_t[part],
                                                               cov, measured)
                where = todo[part]
                s[where], status[where] = got_s, got_st
                for k in np.unique(which[which >= 0]):
                    sel = np.flatnonzero(which == k)
                    _slopes_into(rasters[k], a, b, s, where[sel], dcol[sel], drow[sel], de, dn)
        if parted:
            idx = np.unique(np.concatenate(parted))
            s[idx], de[idx], dn[idx], status[idx] = self._trace_in_halves(a[idx], b[idx], s_lo[idx], s_hi[idx],
                                                                          budget)
        return s, de, dn, status

    def _trace_in_halves(self, a, b, s_lo, s_hi, budget: RayBudget | None = None):
        """:meth:`_trace` of segments a + s (b - a), s in [s_lo, s_hi] ((n, 3) ECEF, (n,)), each cut at
        RAY_PART_CUT of [s_lo, s_hi] into two stretches traced with boxes of their own (a stretch
        still too big for a source is halved again): near a pole a short stretch spans every
        longitude but a few rows, a long one over fine detail few posts a side. The segment's
        answer is its first half's when that meets the surface or leaves every source (OUTSIDE),
        else its second half's, FILLED if either half's is."""
        n = a.shape[0]
        mid = s_lo + RAY_PART_CUT * (s_hi - s_lo)
        lo, hi = np.concatenate([s_lo, mid]), np.concatenate([mid, s_hi])
        a2, b2 = np.concatenate([a, a]), np.concatenate([b, b])
        pa, pb = a2 + lo[:, None] * (b2 - a2), a2 + hi[:, None] * (b2 - a2)
        rays = ecef_to_geodetic(pa) + ecef_to_geodetic(pb)
        s, de, dn, status = self._trace(rays, a2, b2, lo, hi, chord=(pa, pb), budget=budget)
        second = np.flatnonzero(np.isnan(s[:n]) & (status[:n] != STATUS_OUTSIDE))
        filled = second[(status[second] == STATUS_FILLED) & (status[n + second] != STATUS_OUTSIDE)]
        got = s[:n].copy(), de[:n].copy(), dn[:n].copy(), status[:n].copy()
        for out, both in zip(got, (s, de, dn, status)):
            out[second] = both[n + second]
        got[3][filled] = STATUS_FILLED
        return got

    def _stack(self, first, rays, a, b, todo, parted=None, budget: RayBudget | None = None) -> list:
        """The sources as :func:`terrain.los.stack_partitions` takes them, for the segments todo
        (indices local to them): the first source's raster ``first`` (None: it has none here),
        then each source's groups (lone segments whose box a source cannot serve go to
        ``parted``, as :meth:`_groups` says)."""
        def first_groups(idx):
            return [(first, idx)]

        def later(k):
            return lambda idx: self._groups(k, rays, a, b, todo[idx], base=todo, parted=parted, budget=budget)

        return [first_groups] + [later(k) for k in range(1, len(self.sources))]

    def _groups(self, k: int, rays, a, b, idx, base=None, parted=None, budget: RayBudget | None = None):
        """Yield (raster or None, indices) for source k and the segments idx: a Raster source is
        its own raster for them all; any other hands out a raster for the segments' box
        (:func:`ray_box`; None where it has none), and when it cannot serve that box (it raises
        LimitExceeded: more posts than its limit) the segments are split in two (at the widest gap
        between their middles along the box's longer side when that holds most of the box, else
        at the median) until each group's box is served; a source on a lattice of known spacing
        (``spacing_deg``: the procedural world) also has a group split where its box holds more
        posts than its segments' own boxes and a raster's fixed cost for each would
        (:func:`_sparse`: segments scattered far apart get rasters of about the posts they need,
        not one over the whole expanse between them); a lone segment's box that is not served is the
        source's own answer (``raster_for``: a store's region holding most of it, a procedural
        world's LimitExceeded). Groups are yielded one at a time (their rasters freed once
        traced). Indices come out relative to ``base`` (None: as given). With ``parted`` (a list),
        a lone segment whose box is not served, longer than RAY_PART_MIN_M, is not yielded but its
        (global) index appended there, for the caller to trace in parts
        (:meth:`_trace_in_halves`); rays, a and b are then the ends of the stretches boxes are
        made for. ``budget`` (:class:`RayBudget`) is charged for each raster before it is made (a
        call over it raises LimitExceeded, which no split answers)."""
        source = self.sources[k]
        if isinstance(source, Raster) or idx.size == 0:
            yield (source if isinstance(source, Raster) else None), _relative(idx, base)
            return
        strict = getattr(source, "ray_raster_for", source.raster_for)
        spacing = _lattice_spacing_deg(source)
        own = None if spacing is None else _own_posts(rays, idx, spacing)  # over rays, at idx
        pending = [idx]
        while pending:
            grp = pending.pop()
            box = ray_box(rays, a, b, grp)
            if own is not None and grp.size > 1 and _sparse(box, own[grp], spacing):
                pending.extend(_split(rays, grp)[::-1])
                continue
            if budget is not None:
                budget.charge(source, box)
            try:
                raster = strict(*box)
            except LimitExceeded:
                if grp.size > 1:
                    pending.extend(_split(rays, grp)[::-1])
                    continue
                if parted is not None and np.linalg.norm(b[grp[0]] - a[grp[0]]) > RAY_PART_MIN_M:
                    parted.append(grp)
                    continue
                raster = source.raster_for(*box)
            yield raster, _relative(grp, base)

    def describe(self) -> list[dict]:
        """One dict per source: name, kind, bounds, resolution, vertical datum."""
        return [source.describe() for source in self.sources]

    def warm_up(self, near: tuple[float, float] = (0.0, 0.0)) -> float:
        """Run every query once over each source, and across each source's edges, so that the
        compiled kernels a query reaches are ready before a real-time caller needs them;
        returns the seconds it took.

        numba compiles a kernel on its first call in a process and keeps it in its on-disk cache,
        so in a fresh install the first query down a new path (a segment crossing from a target
        area's inset onto the DEM under it: ``stack_partitions``, ``segment_coverage``,
        ``stack_trace``) waits for the compiler, 10-25 s on a busy 2-core machine. In a world
        tick that stalls the clock and every stream (a view joining then saw nothing for 15 s:
        tests/test_insets_integration.py). ``near`` (lat, lon), degrees: where to warm a source
        that covers the globe (the procedural world), e.g. the exercise's centre.

        Per source: a vertical segment through the ground at its centre, and two slanted ones
        from inside it across its east and north edges (onto the next source, or out of the
        data), each as an intersection, a line of sight, heights and normals, in one batch."""
        t0 = time.perf_counter()
        lat, lon, h0, lat_b, lon_b, h1 = [], [], [], [], [], []
        for la0, lo0, la1, lo1 in source_boxes(self.describe()):
            if la1 - la0 >= 90.0 or lo1 - lo0 >= 180.0:  # (nearly) global: a small box at near
                la0, la1 = max(-89.9, near[0] - 0.05), min(89.9, near[0] + 0.05)
                lo0, lo1 = near[1] - 0.05, near[1] + 0.05
            cl, co = 0.5 * (la0 + la1), 0.5 * (lo0 + lo1)
            dla, dlo = min(0.2 * (la1 - la0), 0.02), min(0.2 * (lo1 - lo0), 0.02)
            ground = float(self.heights(np.array([cl]), np.array([co])).height_msl_m[0])
            ground = ground if math.isfinite(ground) else 0.0
            ends = [((cl, co, ground + 200.0), (cl, co, ground - 200.0)),
                    ((cl, lo1 - dlo, ground + 30.0), (cl, lo1 + dlo, ground - 30.0)),
                    ((la1 - dla, co, ground + 30.0), (min(89.9, la1 + dla), co, ground - 30.0))]
            for (a_la, a_lo, a_h), (b_la, b_lo, b_h) in ends:
                lat.append(a_la), lon.append((a_lo + 180.0) % 360.0 - 180.0), h0.append(a_h)
                lat_b.append(b_la), lon_b.append((b_lo + 180.0) % 360.0 - 180.0), h1.append(b_h)
        if not lat:
            return time.perf_counter() - t0
        seg = [np.array(x, np.float64) for x in (lat, lon, h0, lat_b, lon_b, h1)]
        try:
            self.intersect(*seg)
            self.line_of_sight(*seg)
            both_lat, both_lon = np.concatenate([seg[0], seg[3]]), np.concatenate([seg[1], seg[4]])
            self.heights(both_lat, both_lon)
            self.normals(both_lat, both_lon)
            self.height_at(float(seg[0][0]), float(seg[1][0]))
        except SortieError:  # a limit of this terrain's (e.g. a ray budget): the queries warm what they reached
            pass
        return time.perf_counter() - t0


def _answer_into(source, method: str, threads: int, lat, lon, *outs) -> None:
    """``source.<method>(lat, lon, *outs)`` (heights_into or gradient_into) over (n,) float64
    C-contiguous arrays; a DEM raster's (its kernels, terrain.raster.bilinear_into and
    gradient_into, release the GIL, and each writes only the points it is given) in up to
    ``threads`` contiguous parts of at least PARALLEL_MIN_POINTS_PER_THREAD points, on
    terrain.threads' shared pool with the caller working too. Other sources (stores, the
    procedural world, insets: caches of their own) take the batch whole."""
    answer = getattr(source, method)
    parts = min(int(threads), lat.size // PARALLEL_MIN_POINTS_PER_THREAD)
    if parts < 2 or type(source) is not Raster:
        answer(lat, lon, *outs)
        return
    from terrain.threads import map_shared

    cuts = np.linspace(0, lat.size, parts + 1).astype(np.int64).tolist()
    map_shared(lambda k: answer(*(a[cuts[k]:cuts[k + 1]] for a in (lat, lon, *outs))), list(range(parts)), parts)


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


def _relative(idx, base):
    """idx as positions in base (sorted indices holding idx); idx itself when base is None."""
    return idx if base is None else np.searchsorted(base, idx)


def _slopes_into(raster, a, b, s, idx, dcol, drow, out_de, out_dn) -> None:
    """out_*[idx] = the raster's slopes d h / d col, d h / d row at the contacts a + s (b - a) of
    segments idx (NaN where none), per metre east and north at the contact's latitude."""
    hit = ~np.isnan(s[idx])
    sel = idx[hit]
    if sel.size == 0:
        return
    lat, _, _ = ecef_to_geodetic(a[sel] + s[sel][:, None] * (b[sel] - a[sel]))
    g = raster.georef
    m_col, m_row = metres_per_index(g.crs, g.dx, g.dy, lat)
    out_de[sel] = dcol[hit] / m_col
    out_dn[sel] = drow[hit] / m_row


def _lattice_spacing_deg(source) -> float | None:
    """The spacing (degrees, both ways) of the lattice a source makes ray rasters on, where it
    says (``spacing_deg``: the procedural world); None for others (their groups are split only
    when a box is refused)."""
    sp = getattr(source, "spacing_deg", None)
    return float(sp) if isinstance(sp, (int, float)) and not isinstance(sp, bool) and sp > 0.0 else None


def _box_posts(d_lat, d_lon, spacing_deg: float):
    """Posts of a lattice of ``spacing_deg`` in a box d_lat x d_lon degrees (arrays or numbers): the
    rows and columns it spans, plus one each way for the cells it cuts at either end."""
    return (d_lat / spacing_deg + 2.0) * (d_lon / spacing_deg + 2.0)


def _own_posts(rays, idx, spacing_deg: float) -> np.ndarray:
    """(n,) float64 over the n segments of ``rays``, set at idx (0 elsewhere): about how many lattice
    posts each segment's own box holds (its ends' span of latitude and, the short way, of
    longitude; without the pads and a chord's poleward reach, which only make a group look
    sparser than it is)."""
    a_lat, a_lon, _, b_lat, b_lon, _ = rays
    out = np.zeros(a_lat.size)
    d_lon = np.abs((b_lon[idx] - a_lon[idx] + 180.0) % 360.0 - 180.0)
    out[idx] = _box_posts(np.abs(b_lat[idx] - a_lat[idx]), d_lon, spacing_deg)
    return out


def _sparse(box, own_posts: np.ndarray, spacing_deg: float) -> bool:
    """Whether a group of segments is better split than given one raster for ``box`` (ray_box):
    when its box holds more posts than its segments' own boxes together plus the fixed cost of a
    raster for each but one (RAY_RASTER_OVERHEAD_POSTS): what one raster each would cost at most.
    Segments scattered far apart (200 under 1 km over 6 degrees: a box of 76 M posts, 6,500 posts
    of their own) come apart, each group's raster holding about the posts its rays need; a batch
    over one area (a fan of rays from one observer, a convoy's sight lines) keeps its one raster."""
    lat_min, lon_min, lat_max, lon_max = box
    posts = _box_posts(lat_max - lat_min, lon_max - lon_min, spacing_deg)
    return posts > float(own_posts.sum()) + (own_posts.size - 1) * RAY_RASTER_OVERHEAD_POSTS


def _split(rays, idx) -> tuple[np.ndarray, np.ndarray]:
    """Two groups of the segments idx, apart along the longer side of their box (degrees of
    latitude or of longitude, unrolled as :func:`ray_box` does): at the widest gap between the
    segments' middles when it holds a quarter of their spread or more (batches over far-apart
    places come apart as they are), else (and where the middles are all alike) at the median."""
    a_lat, a_lon, _, b_lat, b_lon, _ = rays
    a_near = a_lon[idx[0]] + (a_lon[idx] - a_lon[idx[0]] + 180.0) % 360.0 - 180.0
    mid_lon = a_near + 0.5 * ((b_lon[idx] - a_lon[idx] + 180.0) % 360.0 - 180.0)
    mid_lat = 0.5 * (a_lat[idx] + b_lat[idx])
    key = mid_lon if np.ptp(mid_lon) >= np.ptp(mid_lat) else mid_lat
    order = np.argsort(key, kind="stable")
    gaps = np.diff(key[order])
    cut = int(np.argmax(gaps)) + 1
    if not gaps[cut - 1] > 0.0 or not gaps[cut - 1] >= 0.25 * np.ptp(key):
        cut = idx.size // 2  # (middles all alike: halves, not one segment peeled off at a time)
    return np.sort(idx[order[:cut]]), np.sort(idx[order[cut:]])


def ray_box(rays, a_ecef, b_ecef, idx) -> tuple[float, float, float, float]:
    """(lat_min, lon_min, lat_max, lon_max) degrees holding the ground tracks of the segments idx,
    with RAY_BOX_PAD_M around them; lon_min in [-180, 180), lon_max may pass 180 (east across the
    antimeridian); (-180, 180) when the tracks need every longitude.

    Longitude: along a chord the longitude atan2(y, x) is monotone between its endpoints' and
    turns the way the sign of (a x b)_z says (east when positive: the chord's projection on the
    equatorial plane is a straight line, which subtends less than 180 degrees at the axis), so
    the endpoints' span that way holds it, also where the short way is ambiguous (ends 180 degrees
    apart, passing beside a pole). A track passing through the axis (sign 0, ends 180 degrees
    apart) or within about the pad of it needs every longitude. Every a is unrolled next to the
    first one's and b next to its a, so a box never spans the long way round. The pad in degrees
    of longitude is RAY_BOX_PAD_M over the track's least distance from the axis (its closest
    point when inside the segment, else an end's).

    Latitude: the chord's largest and smallest z / rho (rho = hypot(x, y)) are at its ends or
    where d/ds (z / rho) = 0; with rho^2 = A s^2 + B s + C and z = z0 + z1 s that is
    z1 rho^2 = z rho rho' = z (2 A s + B) / 2, which is linear in s: s* = (z0 B / 2 - z1 C) /
    (z1 B / 2 - z0 A). The geodetic latitude there (and at the ends) bounds the track's to within
    e^2 dh / R radians, dh the chord's height range (geodetic latitude depends on the height at a
    given z / rho only through the e^2 term): at most |h_a - h_b| plus the chord's sag d^2 / (8 R)
    below its ends. The pad is twice that (in metres: e^2 dh) plus RAY_BOX_PAD_M, over the least
    metres per radian of latitude. Near a pole this is the chord's real poleward reach, not
    degrees of longitude.
    """
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = rays
    a, b = a_ecef[idx], b_ecef[idx]
    d = b - a
    A = d[:, 0] ** 2 + d[:, 1] ** 2
    B = 2.0 * (a[:, 0] * d[:, 0] + a[:, 1] * d[:, 1])
    C = a[:, 0] ** 2 + a[:, 1] ** 2
    with np.errstate(divide="ignore", invalid="ignore"):
        s_star = (0.5 * a[:, 2] * B - d[:, 2] * C) / (0.5 * d[:, 2] * B - a[:, 2] * A)
    inner = np.flatnonzero((s_star > 0.0) & (s_star < 1.0))
    lats = [a_lat[idx], b_lat[idx]]
    if inner.size:
        lats.append(ecef_to_geodetic(a[inner] + s_star[inner, None] * d[inner])[0])
    lats = np.concatenate(lats)
    length2 = A + d[:, 2] ** 2
    dh = np.abs(a_h[idx] - b_h[idx]) + length2 / (8.0 * MERIDIAN_RADIUS_MIN_M)
    pad_lat = np.degrees((RAY_BOX_PAD_M + 2.0 * WGS84_E2 * dh.max()) / MERIDIAN_RADIUS_MIN_M)
    cross = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]  # (a x b)_z: the way the longitude turns
    delta = (b_lon[idx] - a_lon[idx] + 180.0) % 360.0 - 180.0
    delta = np.where((cross > 0.0) & (delta < 0.0), delta + 360.0, delta)
    delta = np.where((cross < 0.0) & (delta > 0.0), delta - 360.0, delta)
    with np.errstate(divide="ignore", invalid="ignore"):
        s_axis = -B / (2.0 * A)  # nearest the axis: the distance of the line x, y from the origin
        rho_min = np.where((s_axis > 0.0) & (s_axis < 1.0), np.abs(a[:, 0] * d[:, 1] - a[:, 1] * d[:, 0])
                           / np.sqrt(A), np.sqrt(np.minimum(C, C + B + A)))
        # A track with no horizontal extent (A = 0: one point, as a stretch that starts below every
        # surface is) has the one longitude atan2(y, x): the pad as at the equator is ample for
        # rounding, also on the axis (rho 0), where the pad over rho would be every longitude.
        pad_lon = np.degrees(RAY_BOX_PAD_M / np.where(A > 0.0, rho_min, WGS84_A_M))
    lat_lo = max(lats.min() - pad_lat, -90.0)
    lat_hi = min(lats.max() + pad_lat, 90.0)
    a_lon_near = a_lon[idx[0]] + (a_lon[idx] - a_lon[idx[0]] + 180.0) % 360.0 - 180.0
    west = np.minimum(a_lon_near, a_lon_near + delta) - pad_lon
    east = np.maximum(a_lon_near, a_lon_near + delta) + pad_lon
    if not (np.all(np.abs(delta) < 180.0) and east.max() - west.min() < 360.0):
        return lat_lo, -180.0, lat_hi, 180.0  # every longitude (a track through or beside the axis)
    west, east = west.min(), east.max()
    turns = 360.0 * math.floor((west + 180.0) / 360.0)  # west in [-180, 180); east may pass 180
    return lat_lo, west - turns, lat_hi, east - turns
