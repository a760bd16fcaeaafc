"""Slopes follow the measured-over-filled rule of heights: a point one DEM gives as a filled void
(STATUS_FILLED) and a second DEM has measured takes its normal, slope and gradient from the second
DEM, the source its height comes from; per point and in lattice form, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from terrain.procedural import ProceduralTerrain
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef, Raster
from terrain.terrain import Terrain

D1 = 1.0 / 1200.0  # 3" posts
D2 = 1.0 / 900.0  # 4" posts: not aligned with the first DEM's


@pytest.fixture(scope="module")
def dems():
    """A 3" DEM with a filled void (posts 20..29 x 20..29), and a 4" DEM over all of it but its
    western columns (from 24), whose surface tilts another way, so every slope says which of the
    two answered."""
    rng = np.random.default_rng(5)
    n = 61
    rr, cc = np.mgrid[0:n, 0:n]
    h1 = 500.0 + 3.0 * rr + 1.0 * cc + rng.normal(0.0, 2.0, (n, n))
    filled = np.zeros((n, n), bool)
    filled[20:30, 20:30] = True
    h1[filled] = 530.0 + 0.5 * cc[filled]  # what a fill would leave: smooth, a guess
    first = Raster(h1.astype(np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D1, D1), name="first", filled=filled)
    m = 31
    rr, cc = np.mgrid[0:m, 0:m]
    h2 = 800.0 - 2.0 * rr + 5.0 * cc + rng.normal(0.0, 2.0, (m, m))
    second = Raster(h2.astype(np.float32), Georef(CRS_GEOGRAPHIC, 9.0 + 24 * D1, 47.0 + 10 * D1, D2, D2),
                    name="second")
    return first, second


def _points(rng, n, lo, hi, lon_lo=None):
    """n random points of the first DEM's index box [lo, hi]^2 (its columns from lon_lo)."""
    return 47.0 + rng.uniform(lo, hi, n) * D1, 9.0 + rng.uniform(lo if lon_lo is None else lon_lo, hi, n) * D1


def test_normals_of_a_filled_void_come_from_the_measured_source(dems):
    first, second = dems
    t = Terrain([first, second])
    rng = np.random.default_rng(1)
    lat, lon = _points(rng, 400, 20.05, 28.95, 24.05)  # inside the void's cells the second DEM has
    assert (Terrain([first]).heights(lat, lon).status == STATUS_FILLED).all()
    h = t.heights(lat, lon)
    assert (h.status == STATUS_OK).all()
    np.testing.assert_array_equal(h.height_msl_m, Terrain([second]).heights(lat, lon).height_msl_m)
    want = Terrain([second]).gradients(lat, lon)
    got = t.gradients(lat, lon)
    for g, w in zip(got[:2], want[:2]):
        np.testing.assert_array_equal(g, w)  # bit for bit: the same kernel on the same source
    assert (got[2] == STATUS_OK).all()
    n_got, n_want = t.normals(lat, lon), Terrain([second]).normals(lat, lon)
    np.testing.assert_array_equal(n_got.normal_enu, n_want.normal_enu)
    np.testing.assert_array_equal(n_got.slope_deg, n_want.slope_deg)
    assert (n_got.status == STATUS_OK).all()


def test_slopes_and_heights_take_every_point_from_the_same_source(dems):
    """Over the whole first DEM and beyond it: the void (second DEM's), its rim cells (filled
    corners of non-zero weight), measured cells, and points outside both. Each point's status
    is the same for heights and slopes, and its slope is the one of the source whose height it
    got (one of the two single-source terrains agrees on the height, bit for bit)."""
    first, second = dems
    t = Terrain([first, second])
    rng = np.random.default_rng(2)
    lat, lon = _points(rng, 4000, -5.0, 65.0)
    # Posts and cell edges of the first DEM exactly, where zero-weight corners do not count.
    k = np.arange(15, 35)
    lat = np.concatenate([lat, 47.0 + np.repeat(k, k.size) * D1, 47.0 + np.repeat(k + 0.5, k.size) * D1])
    lon = np.concatenate([lon, 9.0 + np.tile(k, k.size) * D1, 9.0 + np.tile(k, k.size) * D1])
    h = t.heights(lat, lon)
    de, dn, st = t.gradients(lat, lon)
    np.testing.assert_array_equal(st, h.status)
    assert {STATUS_OK, STATUS_FILLED, STATUS_OUTSIDE} <= set(st.tolist())
    from_first = Terrain([first]).heights(lat, lon).height_msl_m == h.height_msl_m
    from_second = ~from_first & (Terrain([second]).heights(lat, lon).height_msl_m == h.height_msl_m)
    assert from_second.sum() > 200 and from_first.sum() > 1000
    for single, sel in ((first, from_first), (second, from_second)):
        w_de, w_dn, w_st = Terrain([single]).gradients(lat[sel], lon[sel])
        np.testing.assert_array_equal(de[sel], w_de)
        np.testing.assert_array_equal(dn[sel], w_dn)
        np.testing.assert_array_equal(st[sel], w_st)
    # A filled point no measured source has keeps the fill's slope, FILLED, as its height does.
    rim = (st == STATUS_FILLED)
    assert rim.any() and not from_second[rim].any()


def test_gradient_grid_follows_the_rule_as_gradients_do(dems):
    """The lattice form (a clipmap's normal maps), first source's lattice kernel then the
    per-point stack for what it leaves: the same answers as gradients() at every point."""
    first, second = dems
    t = Terrain([first, second, ProceduralTerrain(seed=4)])
    lat_rows = 47.0 + np.arange(-3, 64, 0.75) * D1
    lon_cols = 9.0 + np.arange(-3, 64, 0.5) * D1
    de, dn, st = t.gradient_grid(lat_rows, lon_cols)
    lat, lon = np.repeat(lat_rows, lon_cols.size), np.tile(lon_cols, lat_rows.size)
    w_de, w_dn, w_st = t.gradients(lat, lon)
    np.testing.assert_array_equal(de.ravel(), w_de)
    np.testing.assert_array_equal(dn.ravel(), w_dn)
    np.testing.assert_array_equal(st.ravel(), w_st)
    hg = t.height_grid(lat_rows, lon_cols)
    np.testing.assert_array_equal(hg.status, st)
    in_void = ((lat - 47.0) / D1 > 20.01) & ((lat - 47.0) / D1 < 28.99) & ((lon - 9.0) / D1 > 24.01) & \
        ((lon - 9.0) / D1 < 28.99)
    assert in_void.sum() > 100
    s_de, s_dn, _ = Terrain([second]).gradients(lat[in_void], lon[in_void])
    np.testing.assert_array_equal(de.ravel()[in_void], s_de)
    np.testing.assert_array_equal(dn.ravel()[in_void], s_dn)
    assert (st.ravel()[in_void] == STATUS_OK).all()


def test_one_measured_source_pays_no_extra_pass(dems, monkeypatch):
    """A DEM over the procedural world (one measured source): a filled void stays the DEM's,
    FILLED (the procedural world measures nothing), and no source is asked for heights while
    slopes are answered, per point or in lattice form."""
    first, _ = dems
    proc = ProceduralTerrain(seed=4)
    t = Terrain([first, proc])
    calls = []
    for src in (first, proc):
        monkeypatch.setattr(src, "heights_into", lambda *a, _s=src: calls.append(_s.describe()["kind"]))
    rng = np.random.default_rng(3)
    lat, lon = _points(rng, 300, 20.05, 28.95)
    de, dn, st = t.gradients(lat, lon)
    assert (st == STATUS_FILLED).all() and not calls
    w = Terrain([first]).gradients(lat, lon)
    np.testing.assert_array_equal(de, w[0])
    np.testing.assert_array_equal(dn, w[1])
    t.gradient_grid(47.0 + np.arange(18, 32) * D1, 9.0 + np.arange(18, 32) * D1)
    assert not calls
