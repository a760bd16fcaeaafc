"""The geographic quad tree of Microsoft Flight Simulator X, as integer ids.

Scheme (A. Szofran, "Global Terrain Technology for Flight Simulation",
Microsoft ACES Game Studio, 2006; section 4 "Subdividing the surface of the
Earth", copy in ../shared/seeds/global-terrain-flight-sim.txt): the globe is
cut along parallels and meridians into six root cells of 90 degrees of
latitude by 120 degrees of longitude, three north of the equator and three
south of it, so that a cell's north-south and east-west extents are nearly
1:1 at +-45 degrees of latitude. Every cell splits into four children.

Coordinates of a cell. A cell is ``(depth, row, col)``: roots have depth 0;
depth ``d`` has ``rows_at(d) = 2 * 2**d`` rows and ``cols_at(d) = 3 * 2**d``
columns. ``row`` counts cells south of the North Pole (row 0 touches the
pole) and ``col`` counts cells east of the 180th meridian (col 0 starts at
longitude -180), as the paper's identifier does ("its distance in cells south
of the North Pole and east of the 180th meridian"). Cell ``(d, r, c)`` covers

    latitude  [90 - (r + 1) * 90 / 2**d,  90 - r * 90 / 2**d]
    longitude [-180 + c * 120 / 2**d,     -180 + (c + 1) * 120 / 2**d]

Packed id. ``cell_id`` packs the triple into one non-negative int64::

    bits 56..60  depth  (5 bits, 0..MAX_DEPTH)
    bits 28..55  row    (28 bits; rows_at(26) = 2**27)
    bits  0..27  col    (28 bits; cols_at(26) = 3 * 2**26 < 2**28)

Bits 61..63 are zero. Ids sort by depth, then north to south, then west to
east. As the paper asks, parent, siblings, children, ancestors and
neighbours are found with integer operations only (shifts, masks, modulo);
floats appear only where a position is involved (``cell_at``, ``bounds``,
``cell_size_deg``, ``cells_within``).

Edges and boundaries. Every edge is a dyadic rational, (90 * 2**d - 90 r) /
2**d or (120 c - 180 * 2**d) / 2**d, whose numerator has at most 36 bits, so
``bounds`` returns it exactly in float64 and adjacent cells, and parents and
children, share bit-identical edges. ``cell_at`` decides against those exact
edges under a half-open rule: a cell owns its northern and western edges;
the South Pole belongs to the last row; longitude wraps (180 == -180, so
longitude +180 falls in column 0).

Neighbours. East and west wrap around the antimeridian. North of a row-0 cell
lies across the North Pole: the row-0 cell(s) on the opposite meridian
(column shifted by half the columns); likewise south of the last row across
the South Pole. At depth 0 half the columns is 1.5 cells, so the cell across
a pole is two cells; the edge-neighbour functions return tuples for that
reason. ``neighbours`` adds the corner (diagonal) cells under the same
reflection rule; cells that meet a polar cell only at the pole point are not
neighbours unless the reflection makes them so (see ``neighbours``).

``cells_within`` gives the cells around a point out to a radius counted in
cell heights: the scene-graph cache radius of the paper's section 5 (a user
setting of 2.5 to 4.5 cells, the same number of cells at every level).
"""

from __future__ import annotations

import math

import numpy as np

from sortie.errors import InvalidArgument
from terrain.geodesy import wrap_lon_exact_deg as _wrap_lon

# Deepest level whose packed id fits the layout above in an int64: depth 26
# needs 27 row bits and 28 column bits; cells there are 90/2**26 degrees
# (about 0.15 m) tall, well below any terrain data's resolution.
MAX_DEPTH = 26

COL_BITS = 28
ROW_BITS = 28
DEPTH_BITS = 5
ROW_SHIFT = COL_BITS
DEPTH_SHIFT = COL_BITS + ROW_BITS
COL_MASK = (1 << COL_BITS) - 1
ROW_MASK = (1 << ROW_BITS) - 1
DEPTH_MASK = (1 << DEPTH_BITS) - 1
ID_BITS = DEPTH_SHIFT + DEPTH_BITS  # 61: every valid id is below 2**61

# Root cell extent (paper section 4: 90 degrees of latitude, 120 of longitude).
ROOT_DLAT_DEG = 90
ROOT_DLON_DEG = 120

# Mean Earth radius R1 = (2a + b) / 3 of GRS80, 6371008.7714 m (Moritz,
# "Geodetic Reference System 1980", Bulletin Geodesique 54 (1980); WGS84's
# differs by under a millimetre), rounded. cells_within measures great-circle
# distance on this sphere, a spherical-Earth approximation.
EARTH_RADIUS_M = 6371008.8

# Edge-neighbour directions accepted by neighbour().
DIRECTIONS = ("n", "s", "e", "w")

_INT64_MAX = np.iinfo(np.int64).max


# --- argument handling -------------------------------------------------------


def _ints(value, field: str) -> np.ndarray:
    """``value`` as an int64 array (0-d for a scalar); non-integers are refused."""
    a = np.asarray(value)
    if a.dtype.kind == "u":
        if a.size and int(a.max()) > _INT64_MAX:
            _raise_first(a > _INT64_MAX, a, field, "does not fit an int64")
        return a.astype(np.int64)
    if a.dtype.kind != "i":
        # bool, float, object (a Python int beyond int64), strings...
        raise InvalidArgument(field, "must be an integer or an integer array that fits int64", value=value)
    return a.astype(np.int64, copy=False)


def _floats(value, field: str) -> np.ndarray:
    try:
        return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InvalidArgument(field, "must be a number or a numeric array", value=value) from None


def _raise_first(bad, values, field: str, message: str):
    """Raise InvalidArgument for the first True of ``bad``, naming its index in an array."""
    bad = np.broadcast_to(bad, np.shape(values))
    if np.ndim(values) == 0:
        raise InvalidArgument(field, message, value=np.asarray(values).item())
    i = int(np.flatnonzero(bad)[0])
    raise InvalidArgument(field, message, index=i, value=np.asarray(values).flat[i].item())


def _check_depth(depth: np.ndarray, field: str = "depth") -> None:
    bad = (depth < 0) | (depth > MAX_DEPTH)
    if np.any(bad):
        _raise_first(bad, depth, field, f"must be in [0, {MAX_DEPTH}]")


def _scalar_or_array(result: np.ndarray, scalar: bool):
    return int(result) if scalar else result


def _pow2(depth) -> np.ndarray:
    """2**depth as float64 (exact)."""
    return (np.int64(1) << np.asarray(depth, dtype=np.int64)).astype(np.float64)


def _pack(depth, row, col):
    return (depth << DEPTH_SHIFT) | (row << ROW_SHIFT) | col


def _unpack(ids: np.ndarray, field: str):
    """Validate packed ids and split them into (depth, row, col) int64 arrays."""
    bad = (ids < 0) | ((ids >> ID_BITS) != 0)
    if np.any(bad):
        _raise_first(bad, ids, field, f"is not a cell id (bits above {ID_BITS - 1} or negative)")
    depth = (ids >> DEPTH_SHIFT) & DEPTH_MASK
    row = (ids >> ROW_SHIFT) & ROW_MASK
    col = ids & COL_MASK
    if np.any(depth > MAX_DEPTH):
        _raise_first(depth > MAX_DEPTH, ids, field, f"is not a cell id (depth field above {MAX_DEPTH})")
    bad = row >= (2 << depth)
    if np.any(bad):
        _raise_first(bad, ids, field, "is not a cell id (row field beyond the rows of its depth)")
    bad = col >= (3 << depth)
    if np.any(bad):
        _raise_first(bad, ids, field, "is not a cell id (col field beyond the columns of its depth)")
    return depth, row, col


def _one_cell(cell, field: str = "cell"):
    """A single cell id as Python ints (depth, row, col)."""
    ids = _ints(cell, field)
    if ids.ndim != 0:
        raise InvalidArgument(field, "must be a single cell id, not an array", value=None)
    d, r, c = _unpack(ids, field)
    return int(d), int(r), int(c)


# --- ids ---------------------------------------------------------------------


def cell_id(depth, row, col):
    """Packed int64 id of cell (depth, row, col); scalars give an int, arrays broadcast.

    Raises InvalidArgument naming ``depth``, ``row`` or ``col`` (and the index
    within an array) when a value is outside [0, MAX_DEPTH], [0, rows_at(depth))
    or [0, cols_at(depth)).
    """
    d = _ints(depth, "depth")
    r = _ints(row, "row")
    c = _ints(col, "col")
    scalar = d.ndim == r.ndim == c.ndim == 0
    _check_depth(d)
    d, r, c = np.broadcast_arrays(d, r, c)
    bad = (r < 0) | (r >= (2 << d))
    if np.any(bad):
        _raise_first(bad, r, "row", "must be in [0, rows_at(depth)) = [0, 2 * 2**depth)")
    bad = (c < 0) | (c >= (3 << d))
    if np.any(bad):
        _raise_first(bad, c, "col", "must be in [0, cols_at(depth)) = [0, 3 * 2**depth)")
    return _scalar_or_array(_pack(d, r, c), scalar)


def unpack(cell_id):
    """(depth, row, col) of a packed id: ints for an int, int64 arrays for an array.

    Raises InvalidArgument naming ``cell_id`` for a negative id, stray high
    bits, a depth above MAX_DEPTH or a row/col beyond its depth's grid.
    """
    ids = _ints(cell_id, "cell_id")
    d, r, c = _unpack(ids, "cell_id")
    if ids.ndim == 0:
        return int(d), int(r), int(c)
    return d, r, c


def rows_at(depth):
    """Rows of cells at ``depth``: 2 * 2**depth."""
    d = _ints(depth, "depth")
    _check_depth(d)
    return _scalar_or_array(2 << d, d.ndim == 0)


def cols_at(depth):
    """Columns of cells at ``depth``: 3 * 2**depth."""
    d = _ints(depth, "depth")
    _check_depth(d)
    return _scalar_or_array(3 << d, d.ndim == 0)


def cell_size_deg(depth):
    """(dlat, dlon) of a cell at ``depth`` in degrees: (90 / 2**depth, 120 / 2**depth)."""
    d = _ints(depth, "depth")
    _check_depth(d)
    p = _pow2(d)
    dlat, dlon = ROOT_DLAT_DEG / p, ROOT_DLON_DEG / p
    if d.ndim == 0:
        return float(dlat), float(dlon)
    return dlat, dlon


def cell_height_m(depth) -> float:
    """North-south extent of a cell at ``depth`` in metres on the sphere of EARTH_RADIUS_M."""
    d = _ints(depth, "depth")
    _check_depth(d)
    if d.ndim != 0:
        raise InvalidArgument("depth", "must be a single depth", value=None)
    return EARTH_RADIUS_M * math.radians(ROOT_DLAT_DEG) / (1 << int(d))


# --- edges in degrees (each one correctly rounded float operation) -----------


def _lat_edge(row, depth):
    """Latitude of the northern edge of ``row``: 90 - row * 90 / 2**depth."""
    # 90*row < 2**35 converts exactly and the division by 2**depth is exact;
    # the difference (90 * 2**depth - 90 row) / 2**depth has a numerator below
    # 2**34, so the subtraction is exact too: the edge is the true value.
    return 90.0 - (ROOT_DLAT_DEG * np.asarray(row, dtype=np.int64)).astype(np.float64) / _pow2(depth)


def _lon_edge(col, depth):
    """Longitude of the western edge of ``col``: -180 + col * 120 / 2**depth."""
    # Exact, as for _lat_edge: (120 col - 180 * 2**depth) / 2**depth, numerator below 2**36.
    return -180.0 + (ROOT_DLON_DEG * np.asarray(col, dtype=np.int64)).astype(np.float64) / _pow2(depth)


def bounds(cell):
    """(lat_min, lon_min, lat_max, lon_max) of a cell in degrees; arrays give four arrays.

    Every edge is exact in float64 (see the module docstring), so neighbouring
    cells, and a parent and its children, share bit-identical edges.
    """
    ids = _ints(cell, "cell")
    d, r, c = _unpack(ids, "cell")
    out = (_lat_edge(r + 1, d), _lon_edge(c, d), _lat_edge(r, d), _lon_edge(c + 1, d))
    if ids.ndim == 0:
        return tuple(float(v) for v in out)
    return out


# --- hierarchy ---------------------------------------------------------------


def parent(cell):
    """Id of the parent (depth - 1, row // 2, col // 2); a root cell raises InvalidArgument."""
    ids = _ints(cell, "cell")
    d, r, c = _unpack(ids, "cell")
    if np.any(d == 0):
        _raise_first(d == 0, ids, "cell", "is a root cell and has no parent")
    return _scalar_or_array(_pack(d - 1, r >> 1, c >> 1), ids.ndim == 0)


def children(cell):
    """The 4 child ids in the order NW, NE, SW, SE.

    Rows grow southward and columns eastward, so the children are
    (2r, 2c), (2r, 2c + 1), (2r + 1, 2c), (2r + 1, 2c + 1) at depth + 1.
    A scalar gives a 4-tuple of ints, an array an int64 array of shape
    (..., 4). A cell at MAX_DEPTH raises InvalidArgument.
    """
    ids = _ints(cell, "cell")
    d, r, c = _unpack(ids, "cell")
    if np.any(d == MAX_DEPTH):
        _raise_first(d == MAX_DEPTH, ids, "cell", f"is at MAX_DEPTH = {MAX_DEPTH} and has no children")
    r2, c2 = (r << 1)[..., None], (c << 1)[..., None]
    kids = _pack((d + 1)[..., None], r2 + np.array([0, 0, 1, 1]), c2 + np.array([0, 1, 0, 1]))
    if ids.ndim == 0:
        return tuple(int(k) for k in kids)
    return kids


def siblings(cell):
    """The 3 other children of the cell's parent, in NW, NE, SW, SE order.

    A scalar gives a 3-tuple, an array shape (..., 3). Root cells have no
    parent and so no siblings: InvalidArgument.
    """
    ids = _ints(cell, "cell")
    d, r, c = _unpack(ids, "cell")
    if np.any(d == 0):
        _raise_first(d == 0, ids, "cell", "is a root cell and has no siblings")
    # The parent's four children differ only in the lowest bit of row and col.
    base_r, base_c = (r & ~1)[..., None], (c & ~1)[..., None]
    family = _pack(d[..., None], base_r + np.array([0, 0, 1, 1]), base_c + np.array([0, 1, 0, 1]))
    others = family[family != ids[..., None]].reshape(ids.shape + (3,))
    if ids.ndim == 0:
        return tuple(int(s) for s in others)
    return others


def ancestor(cell, depth):
    """Id of the cell's ancestor at ``depth`` (<= the cell's depth; its own depth gives the cell)."""
    ids = _ints(cell, "cell")
    target = _ints(depth, "depth")
    _check_depth(target)
    d, r, c = _unpack(ids, "cell")
    d, r, c, target = np.broadcast_arrays(d, r, c, target)
    bad = target > d
    if np.any(bad):
        _raise_first(bad, target, "depth", "is deeper than the cell")
    up = d - target
    return _scalar_or_array(_pack(target, r >> up, c >> up), ids.ndim == 0 and np.ndim(depth) == 0)


def is_ancestor(a, b):
    """True where ``a`` is a proper ancestor of ``b`` (strictly shallower, and contains it).

    A cell is not its own ancestor; use ``a == b or is_ancestor(a, b)`` for
    "a contains b". Arrays broadcast and give a bool array.
    """
    ia = _ints(a, "a")
    ib = _ints(b, "b")
    da, ra, ca = _unpack(ia, "a")
    db, rb, cb = _unpack(ib, "b")
    up = np.maximum(db - da, 0)
    result = (da < db) & ((rb >> up) == ra) & ((cb >> up) == ca)
    if ia.ndim == 0 and ib.ndim == 0:
        return bool(result)
    return result


# --- points ------------------------------------------------------------------


def cell_at(lat, lon, depth):
    """Id of the cell containing each (lat, lon) point at ``depth``; arrays broadcast.

    Half-open rule, against the exact edges of ``bounds``: a cell owns its
    northern and western edges (lat_min < lat <= lat_max, lon_min <= lon <
    lon_max); the South Pole belongs to the last row. Longitude wraps, so 180
    == -180 and lies in column 0. Latitude must be finite and in [-90, 90]
    (else InvalidArgument naming ``lat``), longitude finite (``lon``).
    """
    lat_a = _floats(lat, "lat")
    lon_a = _floats(lon, "lon")
    d = _ints(depth, "depth")
    _check_depth(d)
    bad = ~(np.isfinite(lat_a) & (lat_a >= -90.0) & (lat_a <= 90.0))
    if np.any(bad):
        _raise_first(bad, lat_a, "lat", "must be a finite latitude in [-90, 90] degrees")
    bad = ~np.isfinite(lon_a)
    if np.any(bad):
        _raise_first(bad, lon_a, "lon", "must be a finite longitude in degrees")
    scalar = lat_a.ndim == lon_a.ndim == d.ndim == 0
    lat_a, lon_a, d = np.broadcast_arrays(lat_a, lon_a, d)
    lon_w = _wrap_lon(lon_a)
    last_row = (2 << d) - 1
    last_col = (3 << d) - 1
    scale = _pow2(d)
    # A float estimate is within one cell of the answer (its rounding error is
    # about 1e-8 of a cell at MAX_DEPTH); comparing with the exact edges then
    # settles points on or next to an edge exactly as bounds() draws it.
    row = np.clip(np.floor((90.0 - lat_a) * scale / ROOT_DLAT_DEG), 0, last_row).astype(np.int64)
    col = np.clip(np.floor((lon_w + 180.0) * scale / ROOT_DLON_DEG), 0, last_col).astype(np.int64)
    for _ in range(2):
        row = np.where(lat_a > _lat_edge(row, d), row - 1, np.where(lat_a <= _lat_edge(row + 1, d), row + 1, row))
        row = np.clip(row, 0, last_row)  # the South Pole stays in the last row
        col = np.where(lon_w < _lon_edge(col, d), col - 1, np.where(lon_w >= _lon_edge(col + 1, d), col + 1, col))
        col = np.clip(col, 0, last_col)
    return _scalar_or_array(_pack(d, row, col), scalar)


# --- neighbours --------------------------------------------------------------


def _across_pole_cols(col: int, cols: int) -> tuple[int, ...]:
    """Columns of the polar row overlapping column ``col`` turned 180 degrees about the pole."""
    # In half-column units the column spans [2 col, 2 col + 2); turning by 180
    # degrees adds half the circle, ``cols`` half-columns. It overlaps the
    # columns holding its first and last half-column (the same one unless
    # cols is odd, i.e. depth 0, where the shift is 1.5 columns).
    first = (2 * col + cols) // 2 % cols
    last = (2 * col + cols + 1) // 2 % cols
    return (first,) if first == last else (first, last)


def neighbour(cell, direction: str) -> tuple[int, ...]:
    """Edge neighbour(s) of the same depth across the cell's 'n', 's', 'e' or 'w' edge.

    East and west wrap around the antimeridian. North of row 0 (and south of
    the last row) lies across the pole: the polar-row cell(s) on the opposite
    meridian, i.e. the column shifted by cols_at(depth) / 2. That is one cell,
    except at depth 0 where the shift is 1.5 columns and the result is the two
    cells it straddles, western first (in increasing longitude from the
    opposite meridian of the cell's western edge).
    """
    d, r, c = _one_cell(cell)
    if direction not in DIRECTIONS:
        raise InvalidArgument("direction", f"must be one of {', '.join(DIRECTIONS)}", value=direction)
    rows, cols = 2 << d, 3 << d
    if direction == "e":
        return (_pack(d, r, (c + 1) % cols),)
    if direction == "w":
        return (_pack(d, r, (c - 1) % cols),)
    step = -1 if direction == "n" else 1
    if 0 <= r + step < rows:
        return (_pack(d, r + step, c),)
    return tuple(_pack(d, r, k) for k in _across_pole_cols(c, cols))


def neighbours(cell) -> tuple[int, ...]:
    """Edge and corner neighbours of the same depth, deduplicated, in ascending id order.

    The rule is the 8-neighbourhood of the grid with the pole treated as in
    ``neighbour``: stepping north from row 0 (south from the last row) lands
    in the same polar row turned 180 degrees about the pole, so the cells
    across the pole are the column(s) opposite the cell and those opposite
    its east and west neighbours. Equivalently: the cells holding the points
    just outside the cell's boundary ring, corners included, where a point
    past a pole is reflected back over it (lat -> +-180 - lat, lon -> lon +
    180). Polar cells that meet the cell only at the pole point itself, and
    not across an edge or corner of the reflected ring, are not neighbours.
    The cell itself is never included (at depths 0 and 1 the reflection
    brings every other polar-row cell in).
    """
    d, r, c = _one_cell(cell)
    rows, cols = 2 << d, 3 << d
    found = set()
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            if dr == 0 and dc == 0:
                continue
            k = (c + dc) % cols
            if 0 <= r + dr < rows:
                found.add(_pack(d, r + dr, k))
            else:
                found.update(_pack(d, r, j) for j in _across_pole_cols(k, cols))
    found.discard(_pack(d, r, c))
    return tuple(sorted(found))


# --- cache radius ------------------------------------------------------------


def _hav(x):
    """Haversine sin^2(x / 2)."""
    return np.sin(0.5 * x) ** 2


def cells_within(lat, lon, depth: int, radius_cells) -> np.ndarray:
    """Ids (sorted int64 array) of cells at ``depth`` whose centre is within a radius of a point.

    The radius is ``radius_cells`` cell heights: radius_cells * cell_height_m(depth)
    metres of great-circle distance on a sphere of EARTH_RADIUS_M (a cell's
    north-south extent is the same at every latitude). This is the
    scene-graph cache radius of the paper's section 5 (2.5 to 4.5 cells).
    Only candidate rows whose centre latitude is within the radius, and in
    each the columns within the longitude half-width the cap has at that
    latitude, are examined; at a row the cap's pole side covers, that is all
    of its columns. Works across the antimeridian and near the poles.
    """
    lat_a = _floats(lat, "lat")
    lon_a = _floats(lon, "lon")
    if lat_a.ndim != 0 or not (np.isfinite(lat_a) and -90.0 <= lat_a <= 90.0):
        raise InvalidArgument("lat", "must be one finite latitude in [-90, 90] degrees", value=lat)
    if lon_a.ndim != 0 or not np.isfinite(lon_a):
        raise InvalidArgument("lon", "must be one finite longitude in degrees", value=lon)
    d_a = _ints(depth, "depth")
    if d_a.ndim != 0:
        raise InvalidArgument("depth", "must be a single depth", value=None)
    _check_depth(d_a)
    rad_a = _floats(radius_cells, "radius_cells")
    if rad_a.ndim != 0 or not (np.isfinite(rad_a) and rad_a >= 0.0):
        raise InvalidArgument("radius_cells", "must be one finite number >= 0", value=radius_cells)
    d = int(d_a)
    rows, cols = 2 << d, 3 << d
    dlat_deg = ROOT_DLAT_DEG / (1 << d)
    dlon_deg = ROOT_DLON_DEG / (1 << d)
    # Angular radius; the sphere's radius cancels: R * alpha <= radius_cells * R * dlat.
    alpha = float(rad_a) * math.radians(dlat_deg)
    alpha_deg = math.degrees(alpha)
    lat_p = float(lat_a)
    lon_p = float(_wrap_lon(lon_a))
    phi = math.radians(lat_p)

    # Rows whose centre latitude 90 - (r + 1/2) dlat is within alpha of lat_p,
    # widened by one row against rounding.
    r_lo = max(0, math.floor((90.0 - lat_p - alpha_deg) / dlat_deg - 0.5) - 1)
    r_hi = min(rows - 1, math.ceil((90.0 - lat_p + alpha_deg) / dlat_deg - 0.5) + 1)
    if r_lo > r_hi:
        return np.zeros(0, dtype=np.int64)
    cand_rows = np.arange(r_lo, r_hi + 1, dtype=np.int64)
    phi_r = np.radians(90.0 - (cand_rows + 0.5) * dlat_deg)
    # Half-width in longitude of the cap at each row's latitude, from the
    # haversine formula hav(theta) = hav(dphi) + cos(phi) cos(phi_r) hav(dlam)
    # (Sinnott, "Virtues of the Haversine", Sky & Telescope 68(2), 1984).
    hav_alpha = math.sin(0.5 * alpha) ** 2 if alpha < math.pi else 1.0
    cc = math.cos(phi) * np.cos(phi_r)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (hav_alpha - _hav(phi_r - phi)) / cc
    all_cols = ~(cc > 1e-15) | (s >= 1.0)
    # Rows the cap covers whole (every centre closer than the radius by more
    # than rounding) are taken without evaluating each column.
    whole_row = (cc > 1e-15) & (s > 1.0 + 1e-9)
    half_deg = np.degrees(2.0 * np.arcsin(np.sqrt(np.clip(np.nan_to_num(s), 0.0, 1.0))))

    ids = []
    for r, everything, whole, half in zip(cand_rows.tolist(), all_cols.tolist(), whole_row.tolist(), half_deg.tolist()):
        if whole:
            ids.append(_pack(np.int64(d), np.int64(r), np.arange(cols, dtype=np.int64)))
            continue
        # Columns whose centre -180 + (c + 1/2) dlon is within half of lon_p,
        # widened by one column against rounding; modulo wraps the antimeridian.
        c_lo = math.floor((lon_p - half + 180.0) / dlon_deg - 0.5) - 1
        c_hi = math.ceil((lon_p + half + 180.0) / dlon_deg - 0.5) + 1
        if everything or c_hi - c_lo + 1 >= cols:
            cand = np.arange(cols, dtype=np.int64)
        else:
            cand = np.arange(c_lo, c_hi + 1, dtype=np.int64) % cols
        lam_c = np.radians(-180.0 + (cand + 0.5) * dlon_deg)
        phi_c = math.radians(90.0 - (r + 0.5) * dlat_deg)
        h = _hav(phi_c - phi) + math.cos(phi) * math.cos(phi_c) * _hav(lam_c - math.radians(lon_p))
        theta = 2.0 * np.arcsin(np.sqrt(np.clip(h, 0.0, 1.0)))
        keep = cand[theta <= alpha]
        if keep.size:
            ids.append(_pack(np.int64(d), np.int64(r), keep))
    if not ids:
        return np.zeros(0, dtype=np.int64)
    return np.unique(np.concatenate(ids))
