"""The FSX geographic quad tree (terrain/quadtree.py) against geometric references.

Oracles share no formulas with the module:
- cell edges are computed here with exact rationals (``fractions.Fraction``)
  from the definition (paper section 4; cell (d, r, c) spans latitude
  [90 - (r+1) 90/2^d, 90 - r 90/2^d], longitude [-180 + c 120/2^d, ...]);
- ``cell_at`` is checked by brute force: the one cell of the whole grid whose
  edges contain the point under the half-open rule (own northern and western
  edges; the South Pole in the last row; longitude reduced mod 360 exactly);
- edge neighbours by stepping a small epsilon outside each edge at many points
  along it and asking which cell holds each point, reflecting points that
  pass a pole back over it (lat -> +-180 - lat, lon -> lon + 180);
- ``neighbours`` by two references: the same sampling around the whole
  boundary ring, corners included; and, over every cell of the grid, the
  cells whose closed rectangles meet the cell's at a point other than a pole,
  plus the polar-row cells whose closed longitude span meets the cell's span
  turned 180 degrees (the reflection across the pole). Cells that meet a
  polar cell only at the pole point are not neighbours: that is the rule.
- ``cells_within`` by brute force over every cell of depths 3 to 5, with the
  great-circle angle from unit vectors (atan2 of cross and dot products), not
  the module's haversine; cells whose centre is within 1e-9 rad of the radius
  are not compared (the two formulas may round differently there).
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from sortie.errors import InvalidArgument
from terrain import quadtree as qt

SETTINGS = settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])


# --- references --------------------------------------------------------------


def ref_bounds(d: int, r: int, c: int):
    """Exact (lat_min, lon_min, lat_max, lon_max) as Fractions, from the definition."""
    h = Fraction(90, 2**d)
    w = Fraction(120, 2**d)
    return (90 - (r + 1) * h, -180 + c * w, 90 - r * h, -180 + (c + 1) * w)


def ref_wrap(lon: float) -> Fraction:
    """Longitude reduced exactly into [-180, 180)."""
    return (Fraction(lon) + 180) % 360 - 180


_GRIDS: dict[int, tuple] = {}


def grid(d: int):
    """All cells of depth d: (rows, cols) index arrays and their exact edges as float arrays."""
    if d not in _GRIDS:
        rows, cols = 2 * 2**d, 3 * 2**d
        r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
        r, c = r.ravel(), c.ravel()
        # Edges as Fractions converted to float; they are dyadic rationals with short
        # numerators, which the asserts show float64 holds exactly.
        lat_edges = [Fraction(90) - k * Fraction(90, 2**d) for k in range(rows + 1)]
        lon_edges = [Fraction(-180) + k * Fraction(120, 2**d) for k in range(cols + 1)]
        assert all(Fraction(float(e)) == e for e in lat_edges + lon_edges)
        lat_e = np.array([float(e) for e in lat_edges])
        lon_e = np.array([float(e) for e in lon_edges])
        _GRIDS[d] = (r, c, lat_e[r + 1], lon_e[c], lat_e[r], lon_e[c + 1], rows, cols)
    return _GRIDS[d]


def brute_cell_at(lat: float, lon: float, d: int) -> tuple[int, int, int]:
    """The one (d, r, c) of the whole grid holding the point under the half-open rule."""
    r, c, s, w, n, e, rows, _ = grid(d)
    lon_w = ref_wrap(lon)
    assert Fraction(float(lon_w)) == lon_w
    lon_w = float(lon_w)
    in_lat = ((s < lat) & (lat <= n)) | ((lat == -90.0) & (r == rows - 1))
    in_lon = (w <= lon_w) & (lon_w < e)
    hit = np.flatnonzero(in_lat & in_lon)
    assert hit.size == 1, (lat, lon, d, hit)
    return d, int(r[hit[0]]), int(c[hit[0]])


def deep_ref_cell_at(lat: float, lon: float, d: int) -> tuple[int, int, int]:
    """As brute_cell_at for any depth, searching only rows/cols next to the exact quotient."""
    h, w = Fraction(90, 2**d), Fraction(120, 2**d)
    lat_f, lon_w = Fraction(lat), ref_wrap(lon)
    r0 = math.floor((90 - lat_f) / h)
    c0 = math.floor((lon_w + 180) / w)
    rows_ok = [
        r
        for r in (r0 - 1, r0, r0 + 1)
        if 0 <= r < 2 * 2**d
        and ((90 - (r + 1) * h < lat_f <= 90 - r * h) or (lat_f == -90 and r == 2 * 2**d - 1))
    ]
    cols_ok = [c for c in (c0 - 1, c0, c0 + 1) if 0 <= c < 3 * 2**d and -180 + c * w <= lon_w < -180 + (c + 1) * w]
    assert len(rows_ok) == 1 and len(cols_ok) == 1
    return d, rows_ok[0], cols_ok[0]


def reflect(lat: float, lon: float) -> tuple[float, float]:
    """A point stepped past a pole, brought back over it onto the opposite meridian."""
    if lat > 90.0:
        return 180.0 - lat, lon + 180.0
    if lat < -90.0:
        return -180.0 - lat, lon + 180.0
    return lat, lon


def cells_holding(points, d: int) -> set[int]:
    lat, lon = zip(*(reflect(a, b) for a, b in points))
    return set(qt.cell_at(np.array(lat), np.array(lon), d).tolist())


def lon_spans_meet(a0, a1, b0, b1) -> np.ndarray:
    """Closed longitude intervals [a0, a1] and [b0, b1] meet on the circle."""
    return np.any([(a0 <= b1 + k) & (b0 + k <= a1) for k in (-360.0, 0.0, 360.0)], axis=0)


def closed_touch_neighbours(d: int, row: int, col: int) -> set[int]:
    """Reference neighbours from closed rectangles over the whole grid (see module docstring)."""
    r, c, s, w, n, e, rows, _ = grid(d)
    s0, w0, n0, e0 = (float(v) for v in ref_bounds(d, row, col))
    lat_lo, lat_hi = np.maximum(s, s0), np.minimum(n, n0)
    meet_lat = lat_lo <= lat_hi
    only_pole = (lat_lo == lat_hi) & (np.abs(lat_lo) == 90.0)
    touching = meet_lat & ~only_pole & lon_spans_meet(w, e, w0, e0)
    if row in (0, rows - 1):
        touching |= (r == row) & lon_spans_meet(w, e, w0 + 180.0, e0 + 180.0)
    touching &= ~((r == row) & (c == col))
    return set(qt.cell_id(d, r[touching], c[touching]).tolist())


def unit(lat_deg, lon_deg):
    la, lo = np.radians(lat_deg), np.radians(lon_deg)
    return np.stack([np.cos(la) * np.cos(lo), np.cos(la) * np.sin(lo), np.sin(la)], axis=-1)


def angle_between(u, v):
    return np.arctan2(np.linalg.norm(np.cross(u, v), axis=-1), np.sum(u * v, axis=-1))


# --- strategies --------------------------------------------------------------

depths = st.integers(0, qt.MAX_DEPTH)


@st.composite
def cells(draw, max_depth=qt.MAX_DEPTH, min_depth=0):
    d = draw(st.integers(min_depth, max_depth))
    rows, cols = 2 * 2**d, 3 * 2**d
    r = draw(st.one_of(st.sampled_from([0, rows - 1]), st.integers(0, rows - 1)))
    c = draw(st.one_of(st.sampled_from([0, cols - 1]), st.integers(0, cols - 1)))
    return d, r, c


@st.composite
def edge_lats(draw):
    """A latitude on, or one ulp beside, a cell edge of some depth."""
    d = draw(st.integers(0, qt.MAX_DEPTH))
    k = draw(st.integers(0, 2 * 2**d))
    x = float(Fraction(90) - k * Fraction(90, 2**d))
    x = draw(st.sampled_from([x, np.nextafter(x, 100.0), np.nextafter(x, -100.0)]))
    return float(min(90.0, max(-90.0, x)))


@st.composite
def edge_lons(draw):
    """A longitude on, or one ulp beside, a cell edge of some depth, possibly a turn off."""
    d = draw(st.integers(0, qt.MAX_DEPTH))
    k = draw(st.integers(0, 3 * 2**d))
    x = float(Fraction(-180) + k * Fraction(120, 2**d))
    x = draw(st.sampled_from([x, np.nextafter(x, 1000.0), np.nextafter(x, -1000.0)]))
    return x + draw(st.sampled_from([0.0, 0.0, 360.0, -360.0]))


lats = st.one_of(
    st.floats(-90.0, 90.0),
    st.sampled_from([90.0, -90.0, 0.0, -0.0, 45.0, -45.0, 89.99999999, -89.99999999]),
    edge_lats(),
)
lons = st.one_of(
    st.floats(-720.0, 720.0),
    st.sampled_from([180.0, -180.0, 0.0, -0.0, 179.99999999, -179.99999999, 540.0, -540.0, 1e6]),
    edge_lons(),
)


# --- ids ---------------------------------------------------------------------


@SETTINGS
@given(cells())
def test_cell_id_round_trip(cell):
    i = qt.cell_id(*cell)
    assert isinstance(i, int) and 0 <= i < 2**63
    assert qt.unpack(i) == cell
    assert qt.unpack(np.int64(i)) == cell
    assert qt.rows_at(cell[0]) == 2 * 2 ** cell[0] and qt.cols_at(cell[0]) == 3 * 2 ** cell[0]


@SETTINGS
@given(cells(), cells())
def test_ids_order_like_depth_row_col(a, b):
    assert (qt.cell_id(*a) < qt.cell_id(*b)) == (a < b)


def test_cell_id_vectorised():
    rng = np.random.default_rng(1)
    d = rng.integers(0, qt.MAX_DEPTH + 1, 500)
    r = rng.integers(0, 2 * 2**d)
    c = rng.integers(0, 3 * 2**d)
    ids = qt.cell_id(d, r, c)
    assert ids.dtype == np.int64 and ids.shape == (500,)
    assert ids.tolist() == [qt.cell_id(int(a), int(b), int(e)) for a, b, e in zip(d, r, c)]
    assert len(set(ids.tolist())) == len({(a, b, e) for a, b, e in zip(d, r, c)})
    back = qt.unpack(ids)
    assert [x.tolist() for x in back] == [d.tolist(), r.tolist(), c.tolist()]
    # Broadcasting one depth over arrays of rows and cols.
    assert qt.cell_id(3, np.arange(4), 0).tolist() == [qt.cell_id(3, k, 0) for k in range(4)]


@pytest.mark.parametrize(
    "args, field",
    [
        ((-1, 0, 0), "depth"),
        ((qt.MAX_DEPTH + 1, 0, 0), "depth"),
        ((0, 2, 0), "row"),
        ((0, -1, 0), "row"),
        ((0, 0, 3), "col"),
        ((5, 0, 3 * 32), "col"),
        ((1.0, 0, 0), "depth"),
        ((True, 0, 0), "depth"),
        ((0, 0.5, 0), "row"),
        ((0, 0, 2**70), "col"),
        ((0, 0, "1"), "col"),
    ],
)
def test_cell_id_invalid(args, field):
    with pytest.raises(InvalidArgument) as e:
        qt.cell_id(*args)
    assert e.value.field == field
    assert field in str(e.value)


def test_cell_id_invalid_names_index_and_value():
    with pytest.raises(InvalidArgument) as e:
        qt.cell_id(np.array([1, 1, 1]), np.array([0, 3, 4]), 0)
    assert (e.value.field, e.value.index, e.value.value) == ("row", 2, 4)
    assert "row[2]" in str(e.value) and "4" in str(e.value)


@pytest.mark.parametrize(
    "bad",
    [
        -1,
        2**62,
        2**63 - 1,
        (qt.MAX_DEPTH + 1) << 56,
        (0 << 56) | (2 << 28),  # row 2 at depth 0
        3,  # col 3 at depth 0
        (1 << 56) | 6,  # col 6 at depth 1
    ],
)
def test_unpack_invalid(bad):
    with pytest.raises(InvalidArgument) as e:
        qt.unpack(bad)
    assert e.value.field == "cell_id" and e.value.value == bad
    with pytest.raises(InvalidArgument) as e:
        qt.unpack(np.array([0, bad], dtype=np.int64))
    assert (e.value.field, e.value.index) == ("cell_id", 1)
    with pytest.raises(InvalidArgument) as e:
        qt.bounds(bad)
    assert e.value.field == "cell"


def test_other_invalid_arguments():
    root = qt.cell_id(0, 0, 0)
    deepest = qt.cell_id(qt.MAX_DEPTH, 0, 0)
    cases = [
        (lambda: qt.parent(root), "cell"),
        (lambda: qt.siblings(root), "cell"),
        (lambda: qt.children(deepest), "cell"),
        (lambda: qt.ancestor(qt.cell_id(2, 0, 0), 3), "depth"),
        (lambda: qt.ancestor(qt.cell_id(2, 0, 0), -1), "depth"),
        (lambda: qt.neighbour(root, "up"), "direction"),
        (lambda: qt.neighbours(np.array([root])), "cell"),
        (lambda: qt.cell_at(float("nan"), 0.0, 3), "lat"),
        (lambda: qt.cell_at(90.5, 0.0, 3), "lat"),
        (lambda: qt.cell_at(-91.0, 0.0, 3), "lat"),
        (lambda: qt.cell_at(0.0, float("inf"), 3), "lon"),
        (lambda: qt.cell_at(0.0, 0.0, qt.MAX_DEPTH + 1), "depth"),
        (lambda: qt.cells_within(float("nan"), 0.0, 3, 2.5), "lat"),
        (lambda: qt.cells_within(0.0, 0.0, 3, -1.0), "radius_cells"),
        (lambda: qt.cells_within(0.0, 0.0, -2, 2.5), "depth"),
        (lambda: qt.rows_at(99), "depth"),
    ]
    for call, field in cases:
        with pytest.raises(InvalidArgument) as e:
            call()
        assert e.value.field == field, (e.value, field)
    with pytest.raises(InvalidArgument) as e:
        qt.cell_at(np.array([0.0, 10.0, np.nan]), 0.0, 3)
    assert (e.value.field, e.value.index) == ("lat", 2)


# --- geometry of cells -------------------------------------------------------


@SETTINGS
@given(cells())
def test_bounds_are_the_exact_definition(cell):
    got = qt.bounds(qt.cell_id(*cell))
    assert all(type(v) is float for v in got)
    assert [Fraction(v) for v in got] == list(ref_bounds(*cell))
    dlat, dlon = qt.cell_size_deg(cell[0])
    assert (Fraction(dlat), Fraction(dlon)) == (Fraction(90, 2 ** cell[0]), Fraction(120, 2 ** cell[0]))
    assert qt.cell_height_m(cell[0]) == pytest.approx(qt.EARTH_RADIUS_M * math.pi / 2 / 2 ** cell[0], rel=1e-15)


def spherical_area(s, w, n, e):
    """Area of a lat/lon rectangle on the unit sphere."""
    return (math.sin(math.radians(n)) - math.sin(math.radians(s))) * math.radians(e - w)


@SETTINGS
@given(cells(max_depth=qt.MAX_DEPTH - 1))
def test_children_tile_their_parent(cell):
    i = qt.cell_id(*cell)
    kids = qt.children(i)
    assert len(kids) == 4 and len(set(kids)) == 4
    ps, pw, pn, pe = ref_bounds(*cell)
    mid_lat, mid_lon = (ps + pn) / 2, (pw + pe) / 2
    expected = [  # NW, NE, SW, SE
        (mid_lat, pw, pn, mid_lon),
        (mid_lat, mid_lon, pn, pe),
        (ps, pw, mid_lat, mid_lon),
        (ps, mid_lon, mid_lat, pe),
    ]
    for k, want in zip(kids, expected):
        assert qt.unpack(k)[0] == cell[0] + 1
        assert qt.parent(k) == i
        assert qt.is_ancestor(i, k) and not qt.is_ancestor(k, i)
        b = [Fraction(v) for v in qt.bounds(k)]
        assert b == list(want)
        assert ps <= b[0] < b[2] <= pn and pw <= b[1] < b[3] <= pe
    # The four children's areas add up to the parent's (exactly, as rationals, in
    # the latitude-longitude plane; and on the sphere to rounding).
    plane = sum((b[2] - b[0]) * (b[3] - b[1]) for b in ([Fraction(v) for v in qt.bounds(k)] for k in kids))
    assert plane == (pn - ps) * (pe - pw)
    sphere = sum(spherical_area(*qt.bounds(k)) for k in kids)
    assert sphere == pytest.approx(spherical_area(*qt.bounds(i)), rel=1e-9, abs=1e-300)
    if cell[0] > 0:
        sibs = qt.siblings(i)
        assert len(sibs) == 3 and i not in sibs
        assert set(sibs) | {i} == set(qt.children(qt.parent(i)))
        assert list(sibs) == sorted(sibs)  # NW, NE, SW, SE order is ascending id order


@SETTINGS
@given(cells(), st.data())
def test_ancestor(cell, data):
    i = qt.cell_id(*cell)
    target = data.draw(st.integers(0, cell[0]))
    a = qt.ancestor(i, target)
    # Walking up one parent at a time reaches the same cell.
    walk = i
    for _ in range(cell[0] - target):
        walk = qt.parent(walk)
    assert a == walk
    assert qt.is_ancestor(a, i) == (target < cell[0])
    assert not qt.is_ancestor(i, i)
    # Geometric containment of the ancestor.
    s, w, n, e = ref_bounds(*qt.unpack(a))
    cs, cw, cn, ce = ref_bounds(*cell)
    assert s <= cs and cn <= n and w <= cw and ce <= e


def test_hierarchy_vectorised():
    rng = np.random.default_rng(2)
    d = rng.integers(1, qt.MAX_DEPTH, 300)
    ids = qt.cell_id(d, rng.integers(0, 2 * 2**d), rng.integers(0, 3 * 2**d))
    assert qt.parent(ids).tolist() == [qt.parent(int(i)) for i in ids]
    assert qt.children(ids).tolist() == [list(qt.children(int(i))) for i in ids]
    assert qt.siblings(ids).tolist() == [list(qt.siblings(int(i))) for i in ids]
    assert qt.ancestor(ids, 1).tolist() == [qt.ancestor(int(i), 1) for i in ids]
    assert qt.is_ancestor(qt.parent(ids), ids).all()
    assert not qt.is_ancestor(ids, qt.parent(ids)).any()
    b = qt.bounds(ids)
    assert np.array(b).T.tolist() == [list(qt.bounds(int(i))) for i in ids]


# --- cell_at -----------------------------------------------------------------


@SETTINGS
@given(lats, lons, st.integers(0, 5))
def test_cell_at_matches_brute_force(lat, lon, d):
    got = qt.cell_at(lat, lon, d)
    assert isinstance(got, int)
    assert qt.unpack(got) == brute_cell_at(lat, lon, d)
    if d > 0:
        assert qt.cell_at(lat, lon, d - 1) == qt.parent(got)


@SETTINGS
@given(lats, lons, st.integers(6, qt.MAX_DEPTH))
def test_cell_at_deep_matches_exact_reference(lat, lon, d):
    got = qt.cell_at(lat, lon, d)
    assert qt.unpack(got) == deep_ref_cell_at(lat, lon, d)
    assert qt.cell_at(lat, lon, d - 1) == qt.parent(got)
    # The returned cell's bounds hold the point under the half-open rule.
    s, w, n, e = qt.bounds(got)
    lon_w = float(ref_wrap(lon))
    assert (s < lat <= n or lat == s == -90.0) and w <= lon_w < e


def test_cell_at_special_points():
    for d in (0, 1, 7, qt.MAX_DEPTH):
        rows, cols = qt.rows_at(d), qt.cols_at(d)
        assert qt.unpack(qt.cell_at(90.0, 0.0, d))[1] == 0
        assert qt.unpack(qt.cell_at(-90.0, 0.0, d))[1] == rows - 1
        assert qt.unpack(qt.cell_at(0.0, 180.0, d))[2] == 0
        assert qt.unpack(qt.cell_at(0.0, -180.0, d))[2] == 0
        assert qt.unpack(qt.cell_at(0.0, np.nextafter(180.0, 0.0), d))[2] == cols - 1
        assert qt.unpack(qt.cell_at(-90.0, 180.0, d)) == (d, rows - 1, 0)
    # Root cells: the equator is the northern edge of the southern row, so it
    # belongs there; lon -60 is the western edge of column 1.
    assert qt.unpack(qt.cell_at(0.0, -60.0, 0)) == (0, 1, 1)
    assert qt.unpack(qt.cell_at(1e-300, np.nextafter(-60.0, -100.0), 0)) == (0, 0, 0)


def test_cell_at_vectorised():
    rng = np.random.default_rng(3)
    lat = rng.uniform(-90, 90, 400)
    lon = rng.uniform(-400, 400, 400)
    lat[:4] = [90.0, -90.0, 0.0, 45.0]
    lon[:4] = [180.0, -180.0, 540.0, 60.0]
    d = rng.integers(0, qt.MAX_DEPTH + 1, 400)
    got = qt.cell_at(lat, lon, d)
    assert got.dtype == np.int64 and got.shape == (400,)
    assert got.tolist() == [qt.cell_at(float(a), float(b), int(k)) for a, b, k in zip(lat, lon, d)]
    assert qt.cell_at(lat.reshape(20, 20), lon.reshape(20, 20), 9).shape == (20, 20)


# --- neighbours --------------------------------------------------------------


def edge_points(d, r, c, direction, n=41):
    """Points a small step outside the named edge, spread along it (corners excluded)."""
    s, w, no, e = (float(v) for v in ref_bounds(d, r, c))
    eps = 1e-6 * (no - s)
    t = np.linspace(0.01, 0.99, n)
    if direction == "n":
        return [(no + eps, w + k * (e - w)) for k in t]
    if direction == "s":
        return [(s - eps, w + k * (e - w)) for k in t]
    if direction == "e":
        return [(s + k * (no - s), e + eps) for k in t]
    return [(s + k * (no - s), w - eps) for k in t]


def ring_points(d, r, c, n=41):
    """Points a small step outside the cell all round its boundary, the four corners included."""
    s, w, no, e = (float(v) for v in ref_bounds(d, r, c))
    eps = 1e-6 * (no - s)
    s, w, no, e = s - eps, w - eps, no + eps, e + eps
    t = np.linspace(0.0, 1.0, n)
    return (
        [(no, w + k * (e - w)) for k in t]
        + [(s, w + k * (e - w)) for k in t]
        + [(s + k * (no - s), w) for k in t]
        + [(s + k * (no - s), e) for k in t]
    )


@SETTINGS
@given(cells(max_depth=8))
def test_neighbour_matches_stepping_outside_each_edge(cell):
    i = qt.cell_id(*cell)
    for direction in "nsew":
        got = qt.neighbour(i, direction)
        assert isinstance(got, tuple)
        assert set(got) == cells_holding(edge_points(*cell, direction), cell[0]), direction
        assert len(set(got)) == len(got) and i not in got
    # Two across-pole cells only at depth 0; one cell everywhere else.
    polar = cell[1] in (0, qt.rows_at(cell[0]) - 1)
    assert len(qt.neighbour(i, "n" if cell[1] == 0 else "s")) == (2 if polar and cell[0] == 0 else 1)


@SETTINGS
@given(cells(max_depth=8))
def test_neighbours_match_the_boundary_ring(cell):
    i = qt.cell_id(*cell)
    got = qt.neighbours(i)
    assert isinstance(got, tuple) and list(got) == sorted(set(got))
    ring = cells_holding(ring_points(*cell), cell[0]) - {i}
    assert set(got) == ring
    # Every edge neighbour is among them.
    for direction in "nsew":
        assert set(qt.neighbour(i, direction)) <= set(got)


@SETTINGS
@given(cells(max_depth=5))
def test_neighbours_match_closed_rectangles(cell):
    assert set(qt.neighbours(qt.cell_id(*cell))) == closed_touch_neighbours(*cell)


def test_neighbours_counts():
    # Away from the poles: the 8 cells around.
    assert len(qt.neighbours(qt.cell_id(4, 10, 0))) == 8
    # Depth 0: every other root is a neighbour (5).
    for c in range(3):
        assert len(qt.neighbours(qt.cell_id(0, 0, c))) == 5
        assert qt.neighbour(qt.cell_id(0, 0, c), "n") == (qt.cell_id(0, 0, (c + 1) % 3), qt.cell_id(0, 0, (c + 2) % 3))
    # Polar row at depth 3: E, W, three across the pole, three to the south.
    assert len(qt.neighbours(qt.cell_id(3, 0, 5))) == 8
    assert qt.neighbour(qt.cell_id(3, 15, 2), "s") == (qt.cell_id(3, 15, 14),)


# --- cells_within ------------------------------------------------------------


def brute_cells_within(lat, lon, d, radius_cells):
    """(sure, unsure): cells of the whole grid whose centre is within the radius, and the
    cells too close to the radius to judge (left out of the comparison)."""
    r, c, s, w, n, e, _, _ = grid(d)
    angle = angle_between(unit((s + n) / 2, (w + e) / 2), unit(lat, lon))
    alpha = radius_cells * math.radians(90.0 / 2**d)
    ids = qt.cell_id(d, r, c)
    return set(ids[angle < alpha - 1e-9].tolist()), set(ids[np.abs(angle - alpha) <= 1e-9].tolist())


within_lats = st.one_of(
    st.floats(-90.0, 90.0),
    st.floats(85.0, 90.0),
    st.floats(-90.0, -85.0),
    st.sampled_from([90.0, -90.0, 0.0]),
)
within_lons = st.one_of(
    st.floats(-180.0, 180.0),
    st.floats(170.0, 190.0),
    st.floats(-190.0, -170.0),
    st.sampled_from([180.0, -180.0]),
)


@SETTINGS
@given(within_lats, within_lons, st.integers(3, 5), st.one_of(st.floats(0.0, 6.0), st.sampled_from([2.5, 4.5])))
def test_cells_within_matches_brute_force(lat, lon, d, radius):
    got = qt.cells_within(lat, lon, d, radius)
    assert got.dtype == np.int64 and list(got) == sorted(set(got.tolist()))
    sure, unsure = brute_cells_within(lat, lon, d, radius)
    assert set(got.tolist()) - unsure == sure


def test_cells_within_small_depths_and_huge_radius():
    # A radius past the antipode holds every cell; at depth 0 the roots.
    everything = qt.cells_within(10.0, 20.0, 2, 100.0)
    assert len(everything) == qt.rows_at(2) * qt.cols_at(2)
    for lat, lon, radius in [(45.0, -150.0, 1.0), (-89.0, 179.0, 2.5), (90.0, 0.0, 0.99)]:
        sure, unsure = brute_cells_within(lat, lon, 0, radius)
        assert set(qt.cells_within(lat, lon, 0, radius).tolist()) - unsure == sure
    assert qt.cells_within(0.0, 0.0, 4, 0.0).size == 0


@pytest.mark.parametrize(
    "lat, lon, d, radius",
    [
        (47.3, 8.5, 20, 4.5),  # mid latitudes, deep
        (0.0, 180.0, 18, 3.0),  # on the antimeridian
        (89.999, -179.99, 12, 2.5),  # next to the North Pole: cap holds the pole
        (-90.0, 0.0, 12, 4.5),  # on the South Pole: whole polar rows
    ],
)
def test_cells_within_deep_against_local_brute_force(lat, lon, d, radius):
    """Deep levels: brute force over a window of rows (all columns near a pole)."""
    got = qt.cells_within(lat, lon, d, radius)
    dlat = 90.0 / 2**d
    rows, cols = qt.rows_at(d), qt.cols_at(d)
    _, r0, c0 = qt.unpack(qt.cell_at(lat, lon, d))
    span = int(radius) + 2
    rr = np.arange(max(0, r0 - span), min(rows, r0 + span + 1))
    near_pole = rr.min() == 0 or rr.max() == rows - 1
    cc = np.arange(cols) if near_pole else np.arange(c0 - 4 * span, c0 + 4 * span + 1) % cols
    r, c = (a.ravel() for a in np.meshgrid(rr, cc, indexing="ij"))
    centre_lat = 90.0 - (r + 0.5) * dlat
    centre_lon = -180.0 + (c + 0.5) * (120.0 / 2**d)
    angle = angle_between(unit(centre_lat, centre_lon), unit(lat, lon))
    alpha = radius * math.radians(dlat)
    ids = qt.cell_id(d, r, c)
    tol = 1e-9 * alpha
    sure = set(ids[angle < alpha - tol].tolist())
    unsure = set(ids[np.abs(angle - alpha) <= tol].tolist())
    assert set(got.tolist()) - unsure == sure
    assert len(sure) > 0
