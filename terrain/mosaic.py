"""Mosaic: several DEM rasters -> the fewest rasters that keep seams continuous.

This is the thesis's height-raster conversion step (several tiles in, one
terrain out). Rasters with the same CRS, post spacing and vertical datum (the
datum itself, not its label: :func:`terrain.dem.vertical_datum_identity`, so an
SRTM tile and a GeoTIFF declaring EGM96 by EPSG:5773 are one system) whose
post grids align (origins a whole number of posts apart, within
``ALIGN_TOLERANCE_POSTS``) and that touch or overlap are copied into one
raster over their bounding box, so the bilinear surface is continuous across
tile seams: SRTM neighbours share their edge row or column, and cell-centred
tiles that abut one post apart get the cell between them.

Priority is input order. Where two merged rasters both have a post the earlier
one wins, and ``meta`` records how much they disagreed. A raster joins a merge
only if that cannot hand one of its posts priority over an earlier raster
outside the merge (that is, no such raster lies between them in the input
order and overlaps the merged box); otherwise it stays a separate entry.
Aligned rasters that do not share an edge (distant tiles, or tiles meeting
only at a corner) stay separate too, so they never cost a bounding box of
NaN; so does a raster whose merge would exceed ``MOSAIC_MAX_POSTS`` (a 4 x 4
block of SRTM1 tiles loads as several merged blocks, each continuous inside).
Separate rasters that share edge posts (SRTM) stay continuous across them.

Filled voids of a member are not data here: where another member has
measured posts they win, whatever the order, and the posts no member
measured are gaps, filled afresh by the rule below from all the measured
posts around them (a hole in one SRTM tile is answered by the DEM listed
after it, the usual "fill SRTM's holes from X").

Gaps: posts of the merged box that no raster covers. A gap region enclosed by
data (not touching the box's outer edge) is filled by the harmonic rule of
:mod:`terrain.dem` and marked filled; a gap touching the outer edge stays NaN,
which the query kernel reports as STATUS_OUTSIDE so a lower-priority source
can answer there.

Different resolutions: a raster whose post spacing is a whole multiple k (2..``REFINE_MAX_FACTOR``,
each axis) of another's it touches or overlaps, on that raster's post lattice, is first
refined to the finer spacing by bilinear subdivision (:func:`refine`) and then merges as
above. Subdividing a bilinear surface by whole factors is exact: each coarse cell's bilinear
function is bilinear on every sub-cell, so the refined raster's surface is the coarse one's
(its own posts bit for bit, the new ones rounded to the raster's float type: within 2.4e-4 m
at 4000 m in float32), and the seam between the two resolutions becomes continuous. Kept
separate, an SRTM3 tile beside an SRTM1 tile stepped along their shared edge by whatever
the 1" posts depart from the 3" tile's straight line between its posts (metres in
mountains), and a lidar patch over a coarser DEM stepped along its whole outline. Rasters
at spacings that are no whole multiple of each other stay separate (each continuous inside).

Longitude wraps for geographic rasters: tiles E179 and W180 merge into one
raster with x0 = 179 that runs on to 181 (the kernel reads longitude modulo
360 east of x0). Web Mercator rasters wrap likewise every 2 pi a metres of x
when that is a whole number of posts (to ``ALIGN_TOLERANCE_POSTS``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from sortie.errors import LimitExceeded
from terrain.dem import enclosed_voids, fill_voids, read_dem, vertical_datum_identity
from terrain.raster import CRS_GEOGRAPHIC, TWO_PI_A_M, Georef, Raster, grid_bounds

log = logging.getLogger(__name__)

# Post grids align when every post of one lands within this fraction of a
# post on a post of the other (1e-6 of a 90 m post is 0.1 mm).
ALIGN_TOLERANCE_POSTS = 1e-6

# Largest merged raster: a 3 x 3 block of SRTM1 tiles (10801^2 = 116.7 M
# posts, 467 MB as float32). Anything bigger is refused rather than swapped.
MOSAIC_MAX_POSTS = 120_000_000

FULL_TURN_DEG = 360.0

# Coarser rasters are refined to a touching finer one's spacing up to this factor a side (SRTM3
# beside SRTM1 is 3; 30 m beside 1 m lidar, 30, is left separate: 900 times the posts).
REFINE_MAX_FACTOR = 8
REFINE_PASSES = 4  # passes of _refined: a chain of resolutions refines one link a pass


def load_sources(paths) -> list[Raster]:
    """Read DEM files (see :func:`terrain.dem.read_dem`) and mosaic them.

    paths: file paths in priority order (first wins where they overlap).
    Returns rasters in priority order, ready for ``Terrain(sources)``.
    """
    return mosaic([read_dem(p) for p in paths])


def mosaic(rasters) -> list[Raster]:
    """Merge aligned, touching rasters; keep the rest as they are.

    rasters: Raster objects in priority order. Returns a list in priority
    order (each entry placed where its highest-priority member was); a raster
    that merges with nothing is returned as the same object.
    """
    given = list(rasters)
    rasters = _refined(given)
    groups: list[list[int]] = []
    for i in range(len(rasters)):
        home = next((g for g in groups if _can_merge(rasters, groups, g + [i])), None)
        if home is None:
            groups.append([i])
            continue
        home.append(i)
        _absorb_bridged(rasters, groups, home)
    # a raster refined for a merge that did not happen is returned as it was given
    return [given[g[0]] if len(g) == 1 else _composite([rasters[i] for i in sorted(g)])
            for g in sorted(groups, key=min)]


def refine_factors(coarse: Raster, fine: Raster) -> tuple[int, int] | None:
    """(ky, kx): ``coarse``'s post spacing as whole multiples of ``fine``'s, each in
    2..REFINE_MAX_FACTOR on one axis at least (1 on the other allowed), with ``coarse``'s
    posts on ``fine``'s lattice and the same CRS and vertical datum; None otherwise."""
    gc, gf = coarse.georef, fine.georef
    if not _same_system(coarse, fine):
        return None
    factors = []
    for dc, df, n in ((gc.dy, gf.dy, coarse.shape[0]), (gc.dx, gf.dx, coarse.shape[1])):
        k = round(dc / df)
        # the refined raster's far posts must stay within tolerance of the fine lattice
        if not 1 <= k <= REFINE_MAX_FACTOR or abs(dc / (k * df) - 1.0) * k * (n - 1) > ALIGN_TOLERANCE_POSTS:
            return None
        factors.append(int(k))
    if factors == [1, 1] or not _on_lattice(gc, gf):
        return None
    return factors[0], factors[1]


def refine(raster: Raster, ky: int, kx: int) -> Raster:
    """``raster`` subdivided ky x kx times by bilinear interpolation: the same surface on a
    grid ky (kx) times as fine (see the module docstring). Its own posts are copied bit for
    bit; a new post between posts of which one is NaN is NaN, and one that any filled post
    weighs into is filled."""
    g = raster.georef
    h = _subdivide(_subdivide(raster.heights.astype(np.float64), ky, axis=0), kx, axis=1)
    filled = None
    if raster.filled is not None:
        f = raster.filled.astype(np.float64)
        filled = _subdivide(_subdivide(f, ky, axis=0), kx, axis=1) > 0.0
    before = raster.meta.get("refined")  # refined already (a chain of resolutions): from the file's own grid
    meta = {**raster.meta, "refined": {
        "factors": [ky * before["factors"][0], kx * before["factors"][1]] if before else [ky, kx],
        "spacing": before["spacing"] if before else [g.dy, g.dx],
        "shape": before["shape"] if before else list(raster.shape)}}
    return Raster(h.astype(raster.heights.dtype), Georef(g.crs, g.x0, g.y0, g.dx / kx, g.dy / ky),
                  name=raster.name, vertical_datum=raster.vertical_datum, filled=filled, source=raster.source,
                  meta=meta)


def _subdivide(a: np.ndarray, k: int, axis: int) -> np.ndarray:
    """Linear subdivision of ``a`` along ``axis``, k new intervals per old one: old posts at
    every k-th place, copied; between them (1 - s/k) a[i] + (s/k) a[i + 1]."""
    if k == 1:
        return a
    a = np.moveaxis(a, axis, 0)
    n = a.shape[0]
    out = np.empty(((n - 1) * k + 1,) + a.shape[1:], np.float64)
    out[::k] = a
    lo, hi = a[:-1], a[1:]
    for step in range(1, k):
        t = step / k
        out[step::k] = (1.0 - t) * lo + t * hi
    return np.moveaxis(out, 0, axis)


def _refined(rasters: list[Raster]) -> list[Raster]:
    """``rasters`` with each one that touches or overlaps a finer raster on whose lattice it
    lies (:func:`refine_factors`) refined to the finest such; in place in the priority order.
    One whose refined size would exceed MOSAIC_MAX_POSTS stays as it is. Passes repeat while
    one refines something (at most REFINE_PASSES): three resolutions in a row (9" beside 3"
    beside 1") end at the finest."""
    out = list(rasters)
    for _ in range(REFINE_PASSES):
        changed = False
        current = list(out)  # each pass decides on the rasters as the pass began
        for i, r in enumerate(current):
            best = None
            for j, f in enumerate(current):
                if j == i:
                    continue
                k = refine_factors(r, f)
                if k is None or (best is not None and k[0] * k[1] <= best[0] * best[1]):
                    continue
                if _boxes_touch(r, f):
                    best = k
            if best is None:
                continue
            posts = ((r.shape[0] - 1) * best[0] + 1) * ((r.shape[1] - 1) * best[1] + 1)
            if posts > MOSAIC_MAX_POSTS:
                log.info("mosaic: %s is not refined %d x %d to its finer neighbour's spacing (%d posts > %d)",
                         r.name, best[0], best[1], posts, MOSAIC_MAX_POSTS)
                continue
            out[i] = refine(r, *best)
            changed = True
        if not changed:
            break
    return out


def _boxes_touch(a: Raster, b: Raster) -> bool:
    """Whether the two rasters' post boxes meet, or come within one post of each's spacing
    of each other (cell-centred tiles abutting: their outer posts are half a cell of each
    from the shared edge). Compared in degrees: a Web Mercator spacing of x metres spans at
    most x / (a pi / 180) degrees of longitude or latitude."""
    def spacing_deg(g: Georef) -> float:
        d = max(abs(g.dx), abs(g.dy))
        return d if g.crs == CRS_GEOGRAPHIC else d / (TWO_PI_A_M / FULL_TURN_DEG)

    grow = spacing_deg(a.georef) + spacing_deg(b.georef)
    la0, lo0, la1, lo1 = a.bounds
    return _boxes_intersect((la0 - grow, lo0 - grow, la1 + grow, lo1 + grow), b.bounds)


def _absorb_bridged(rasters: list[Raster], groups: list[list[int]], home: list[int]) -> None:
    """Merge into ``home`` every group that its newest member now connects it to."""
    absorbed = True
    while absorbed:
        absorbed = False
        for other in groups:
            if other is not home and _can_merge(rasters, groups, home + other):
                home += other
                groups[:] = [g for g in groups if g is not other]
                absorbed = True
                break


@dataclass(frozen=True)
class Placement:
    """Where member rasters go in a merged grid.

    georef: the merged grid's posts; shape: (ny, nx); offsets: (row, col) of
    each member's post (0, 0) in the merged grid, in member order.
    """

    georef: Georef
    shape: tuple[int, int]
    offsets: tuple[tuple[int, int], ...]


def _can_merge(rasters: list[Raster], groups: list[list[int]], members: list[int]) -> bool:
    members = sorted(members)
    chosen = [rasters[i] for i in members]
    if not all(aligned(chosen[0], r) for r in chosen[1:]):
        return False
    placement = place(chosen)
    if placement.shape[0] * placement.shape[1] > MOSAIC_MAX_POSTS or not _connected(chosen, placement):
        return False
    box = grid_bounds(placement.georef, placement.shape)
    first = members[0]
    group_start = {i: min(g) for g in groups for i in g}
    # A raster ranked between the members, that would be listed after the
    # merged one, must not lie under it: the later members would override it.
    for j in range(first + 1, members[-1]):
        if j not in members and group_start[j] > first and _boxes_intersect(box, rasters[j].bounds):
            return False
    return True


def aligned(a: Raster, b: Raster) -> bool:
    """True when a and b can share one grid: same CRS, vertical datum (by identity, whatever the
    labels), spacing, post phase."""
    ga, gb = a.georef, b.georef
    if not _same_system(a, b):
        return False
    # Spacing: b's far posts must stay within tolerance of a's grid.
    for da, db, n in ((ga.dx, gb.dx, max(a.shape[1], b.shape[1])), (ga.dy, gb.dy, max(a.shape[0], b.shape[0]))):
        if abs(db / da - 1.0) * (n - 1) > ALIGN_TOLERANCE_POSTS:
            return False
    return _on_lattice(gb, ga)


def _same_system(a: Raster, b: Raster) -> bool:
    """Same CRS and vertical datum (by identity, whatever the labels)."""
    return a.georef.crs == b.georef.crs and (vertical_datum_identity(a.vertical_datum)
                                             == vertical_datum_identity(b.vertical_datum))


def _on_lattice(g: Georef, lattice: Georef) -> bool:
    """Whether ``g``'s first post lies on ``lattice``'s posts (a whole number of its spacings
    away on each axis, within ALIGN_TOLERANCE_POSTS; longitude by whole turns where it wraps)."""
    dcol = (g.x0 - lattice.x0) / lattice.dx
    if _wraps(lattice):
        dcol %= _turn(lattice) / lattice.dx
    drow = (g.y0 - lattice.y0) / lattice.dy
    return _near_whole(dcol, lattice) and abs(drow - round(drow)) <= ALIGN_TOLERANCE_POSTS


def _near_whole(dcol: float, g: Georef) -> bool:
    if abs(dcol - round(dcol)) <= ALIGN_TOLERANCE_POSTS:
        return True
    # dcol taken modulo a turn may sit just below the period: that is 0.
    return _wraps(g) and abs(dcol - _turn(g) / g.dx) <= ALIGN_TOLERANCE_POSTS


def _turn(g: Georef) -> float:
    """A full turn of longitude in the grid's x unit: 360 degrees, or Web Mercator's 2 pi a metres
    (EPSG:3857's x is a * longitude in radians, IOGP Guidance Note 7-2, method 1024)."""
    return FULL_TURN_DEG if g.crs == CRS_GEOGRAPHIC else TWO_PI_A_M


def _wraps(g: Georef) -> bool:
    """Grids whose posts repeat every turn of longitude (a whole number of posts a turn) can wrap:
    geographic ones every 360 degrees, Web Mercator ones every 2 pi a metres (tiles cut at x = +-pi a
    merged across the antimeridian as geographic ones do; the heights kernel and the ray walk read x
    modulo the same turn)."""
    period = _turn(g) / g.dx
    return abs(period - round(period)) <= ALIGN_TOLERANCE_POSTS


def place(members: list[Raster]) -> Placement:
    """Merged grid and member offsets for aligned rasters (see :func:`aligned`).

    Geographic grids that wrap are laid out from the member whose x0 gives the
    narrowest span, every other x0 moved east of it by whole turns; so E179
    then W180 gives x0 = 179 and the W180 tile at 180..181.
    """
    ref = members[0].georef
    dx, dy = ref.dx, ref.dy
    xs = [m.georef.x0 for m in members]
    if _wraps(ref):
        best = None
        for k, xk in enumerate(xs):
            east = [_east_of(x, xk, dx, _turn(ref)) for x in xs]
            span = max(e + (m.shape[1] - 1) * dx for e, m in zip(east, members))
            if best is None or span < best[0] - 0.5 * dx:
                best = (span, xk, east)
        _, x0, east = best
    else:
        x0 = min(xs)
        east = [x - x0 for x in xs]
    y0 = min(m.georef.y0 for m in members)
    offsets = tuple((round((m.georef.y0 - y0) / dy), round(e / dx)) for m, e in zip(members, east))
    ny = max(r + m.shape[0] for (r, _), m in zip(offsets, members))
    nx = max(c + m.shape[1] for (_, c), m in zip(offsets, members))
    return Placement(Georef(ref.crs, x0, y0, dx, dy), (ny, nx), offsets)


def _east_of(x: float, start: float, dx: float, turn: float) -> float:
    """From start east to x, in [0, turn) (the grid's x unit); a hair below a turn is 0."""
    d = (x - start) % turn
    return 0.0 if turn - d <= ALIGN_TOLERANCE_POSTS * dx else d


def _connected(members: list[Raster], placement: Placement) -> bool:
    """True when the members' post boxes link them all through shared edges: two boxes link
    when they overlap or abut (one post apart) along one axis and share at least one cell
    side (two posts) along the other. Boxes meeting only at a corner do not link: merging
    them would buy a bounding box of NaN for one cell of continuity."""
    boxes = [(r, c, r + m.shape[0] - 1, c + m.shape[1] - 1) for (r, c), m in zip(placement.offsets, members)]
    reached = {0}
    frontier = [0]
    while frontier:
        a = boxes[frontier.pop()]
        for k, b in enumerate(boxes):
            if k not in reached and _share_edge(a, b):
                reached.add(k)
                frontier.append(k)
    return len(reached) == len(boxes)


def _share_edge(a, b) -> bool:
    """Whether post boxes (row0, col0, row1, col1), inclusive, share an edge (see _connected)."""
    touch_rows = a[0] <= b[2] + 1 and b[0] <= a[2] + 1
    touch_cols = a[1] <= b[3] + 1 and b[1] <= a[3] + 1
    side_rows = min(a[2], b[2]) - max(a[0], b[0]) >= 1
    side_cols = min(a[3], b[3]) - max(a[1], b[1]) >= 1
    return (touch_rows and side_cols) or (touch_cols and side_rows)


def _boxes_intersect(a, b) -> bool:
    """Whether two (lat_min, lon_min, lat_max, lon_max) boxes meet; longitude wraps."""
    if a[0] > b[2] or b[0] > a[2]:
        return False
    wa, wb = a[3] - a[1], b[3] - b[1]
    if wa >= FULL_TURN_DEG or wb >= FULL_TURN_DEG:
        return True
    return (b[1] - a[1]) % FULL_TURN_DEG <= wa or (a[1] - b[1]) % FULL_TURN_DEG <= wb


def _composite(members: list[Raster]) -> Raster:
    """One raster from aligned, connected members (priority order)."""
    placement = place(members)
    ny, nx = placement.shape
    if ny * nx > MOSAIC_MAX_POSTS:
        raise LimitExceeded(f"mosaic of {', '.join(m.name for m in members)} (posts)", ny * nx, MOSAIC_MAX_POSTS)
    dtype = np.float32 if all(m.heights.dtype == np.float32 for m in members) else np.float64
    heights = np.full((ny, nx), np.nan, dtype)
    overlap_posts = 0
    disagreeing = 0
    max_diff = 0.0
    for m, (r, c) in zip(members, placement.offsets):
        window = (slice(r, r + m.shape[0]), slice(c, c + m.shape[1]))
        target = heights[window]
        src = m.heights
        # A member's filled voids are not data: measured posts of any member win over
        # them, and what no member measured is filled afresh below.
        has = ~np.isnan(src) if m.filled is None else ~np.isnan(src) & (m.filled == 0)
        both = has & ~np.isnan(target)
        if both.any():
            diff = np.abs(target[both].astype(np.float64) - src[both])
            overlap_posts += int(both.sum())
            disagreeing += int(np.count_nonzero(diff))
            max_diff = max(max_diff, float(diff.max()))
        take = has & np.isnan(target)
        target[take] = src[take]
    gaps = np.isnan(heights)
    enclosed = enclosed_voids(gaps)
    if enclosed.any():
        heights[enclosed] = fill_voids(heights, enclosed)
    filled = enclosed
    meta = {
        "format": "mosaic",
        "members": [{"name": m.name, "source": m.source, "row": r, "col": c, "shape": m.shape,
                     **({"refined": m.meta["refined"]} if "refined" in m.meta else {})}
                    for m, (r, c) in zip(members, placement.offsets)],
        "overlap_posts": overlap_posts,
        "overlap_disagreeing_posts": disagreeing,
        "overlap_max_abs_diff_m": max_diff,
        "gap_posts_filled": int(enclosed.sum()),
        "gap_posts_outside": int(gaps.sum() - enclosed.sum()),
    }
    if disagreeing:
        log.info("mosaic: %d of %d shared posts disagree, by up to %.3f m; earlier sources win",
                 disagreeing, overlap_posts, max_diff)
    return Raster(heights, placement.georef, name="+".join(m.name for m in members),
                  vertical_datum=members[0].vertical_datum, filled=filled,
                  source="; ".join(m.source for m in members), meta=meta)

