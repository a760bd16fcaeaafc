"""Mosaics of different resolutions: a coarser raster refined to a finer neighbour's spacing.

Real posts: the Alps tile (3") is the fine raster, and every third post of another part of
it (9", on the same lattice, as SRTM3 was sub-sampled from SRTM1) the coarse one. Oracles:
each raster queried alone, and the unmerged pair, whose seam steps.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrain import mosaic as mosaic_mod
from terrain.dem import read_hgt
from terrain.mosaic import mosaic, refine, refine_factors
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OK, Georef, Raster
from terrain.terrain import Terrain

# Float32 posts between posts are rounded: 2^-24 of the heights (< 4000 m here) and some.
FLOAT32_SURFACE_TOL_M = 1e-3
# The same posts placed in a larger grid: the kernel's fractional index differs in the last bits.
SAME_M = 1e-6


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Raster:
    return read_hgt(hgt_alps)


def _part(r: Raster, r0: int, r1: int, c0: int, c1: int, step: int = 1, name: str = "") -> Raster:
    """Posts rows r0..r1, cols c0..c1 (inclusive, row 0 south) of r, every step-th."""
    g = r.georef
    return Raster(np.ascontiguousarray(r.heights[r0:r1 + 1:step, c0:c1 + 1:step]),
                  Georef(g.crs, g.x0 + c0 * g.dx, g.y0 + r0 * g.dy, g.dx * step, g.dy * step),
                  name=name or f"{r.name}[{r0}:{r1}:{step},{c0}:{c1}:{step}]", vertical_datum=r.vertical_datum)


def _heights(sources, lat, lon):
    got = Terrain(sources if isinstance(sources, list) else [sources]).heights(np.asarray(lat, float),
                                                                              np.asarray(lon, float))
    return got.height_msl_m, got.status


def _seam_step(sources, lat, seam_lon, eps=1e-9):
    """Largest height difference straddling the meridian seam_lon at latitudes lat."""
    west, _ = _heights(sources, lat, np.full(lat.size, seam_lon - eps))
    east, _ = _heights(sources, lat, np.full(lat.size, seam_lon + eps))
    return float(np.max(np.abs(east - west)))


def test_a_coarser_tile_beside_a_finer_one_is_refined_and_merged_continuous(alps):
    """3" west of a 9" tile sharing its east edge: one raster; the fine posts bit for bit; the
    coarse tile's surface beyond the seam's first fine cell as it is alone; no step at the
    seam (kept apart, the pair steps by metres there)."""
    fine = _part(alps, 0, 240, 0, 120, name="fine")
    coarse = _part(alps, 0, 240, 120, 480, step=3, name="coarse")
    g = fine.georef
    seam = g.x0 + 120 * g.dx
    rng = np.random.default_rng(1)
    lat = rng.uniform(g.y0, g.y0 + 240 * g.dy, 2000)

    apart = _seam_step([fine, coarse], lat, seam)
    assert apart > 1.0  # what the merge removes: the 3" posts' departures from the 9" lines

    out = mosaic([fine, coarse])
    assert len(out) == 1
    merged = out[0]
    assert merged.georef.dx == pytest.approx(g.dx) and merged.shape == (241, 481)
    assert merged.meta["members"][1]["refined"]["factors"] == [3, 3]
    assert _seam_step(merged, lat, seam) < 0.01  # continuous: a slope of < 1e7 m/m over 2e-9 degrees
    np.testing.assert_array_equal(merged.heights[:, :121], fine.heights)  # fine posts bit for bit
    np.testing.assert_array_equal(merged.heights[::3, 120::3], coarse.heights[:, :])  # coarse posts too

    lon = rng.uniform(seam + g.dx, seam + 360 * g.dx, 2000)  # beyond the first fine cell east of the seam
    h_m, s_m = _heights(merged, lat, lon)
    h_c, s_c = _heights(coarse, lat, lon)
    assert np.all(s_m == STATUS_OK) and np.all(s_c == STATUS_OK)
    np.testing.assert_allclose(h_m, h_c, rtol=0, atol=FLOAT32_SURFACE_TOL_M)
    lon_w = rng.uniform(g.x0, seam, 2000)
    np.testing.assert_allclose(_heights(merged, lat, lon_w)[0], _heights(fine, lat, lon_w)[0], rtol=0, atol=SAME_M)


def test_coarse_first_keeps_its_seam_posts_and_the_fine_tile_beyond(alps):
    """Priority holds: listed first, the coarse tile's posts win on the shared edge; west of
    the seam's first fine cell the fine tile answers as it does alone."""
    fine = _part(alps, 0, 240, 0, 120, name="fine")
    coarse = _part(alps, 0, 240, 120, 480, step=3, name="coarse")
    out = mosaic([coarse, fine])
    assert len(out) == 1
    merged, g = out[0], fine.georef
    np.testing.assert_array_equal(merged.heights[::3, 120], coarse.heights[:, 0])
    seam = g.x0 + 120 * g.dx
    rng = np.random.default_rng(2)
    lat = rng.uniform(g.y0, g.y0 + 240 * g.dy, 2000)
    lon = rng.uniform(g.x0, seam - g.dx, 2000)
    np.testing.assert_allclose(_heights(merged, lat, lon)[0], _heights(fine, lat, lon)[0], rtol=0, atol=SAME_M)
    assert _seam_step(merged, lat, seam) < 0.01


def test_a_fine_patch_over_a_coarse_tile_joins_it_without_a_step_along_its_outline(alps):
    """A 3" patch listed before the 9" tile it lies in (a survey over a national DEM): inside,
    the patch's surface; outside, beyond one fine cell, the tile's; continuous across the
    outline (kept apart, the outline steps)."""
    coarse = _part(alps, 0, 480, 0, 480, step=3, name="coarse")
    patch = _part(alps, 150, 300, 210, 330, name="patch")
    g = patch.georef
    west, east = g.x0, g.x0 + 120 * g.dx
    rng = np.random.default_rng(3)
    lat = rng.uniform(g.y0 + g.dy, g.y0 + 149 * g.dy, 1500)
    assert _seam_step([patch, coarse], lat, west) > 1.0
    out = mosaic([patch, coarse])
    assert len(out) == 1
    assert _seam_step(out[0], lat, west) < 0.01 and _seam_step(out[0], lat, east) < 0.01
    lon_in = rng.uniform(west, east, 1500)
    np.testing.assert_allclose(_heights(out[0], lat, lon_in)[0], _heights(patch, lat, lon_in)[0], rtol=0,
                               atol=SAME_M)
    lon_out = rng.uniform(coarse.georef.x0, west - g.dx, 1500)
    np.testing.assert_allclose(_heights(out[0], lat, lon_out)[0], _heights(coarse, lat, lon_out)[0],
                               rtol=0, atol=FLOAT32_SURFACE_TOL_M)


def test_what_is_not_refined_stays_separate(alps, monkeypatch):
    """Off the fine lattice (half a fine post), a factor over REFINE_MAX_FACTOR, or a refined
    size over MOSAIC_MAX_POSTS: the rasters stay as they were, in priority order."""
    fine = _part(alps, 0, 240, 0, 120, name="fine")
    g = fine.georef
    off = Raster(np.zeros((40, 40), np.float32), Georef(g.crs, g.x0 + 120.5 * g.dx, g.y0, 3 * g.dx, 3 * g.dy),
                 name="off", vertical_datum=fine.vertical_datum)
    k = mosaic_mod.REFINE_MAX_FACTOR + 1
    far = Raster(np.zeros((10, 10), np.float32), Georef(g.crs, g.x0 + 120 * g.dx, g.y0, k * g.dx, k * g.dy),
                 name="far", vertical_datum=fine.vertical_datum)
    for other in (off, far):
        assert refine_factors(other, fine) is None
        out = mosaic([fine, other])
        assert [r.name for r in out] == ["fine", other.name] and out[1] is other
    coarse = _part(alps, 0, 240, 120, 480, step=3, name="coarse")
    monkeypatch.setattr(mosaic_mod, "MOSAIC_MAX_POSTS", 100_000)  # the refined coarse tile: 241 x 361
    out = mosaic([fine, coarse])
    assert [r.name for r in out] == ["fine", "coarse"] and out[1] is coarse


@settings(max_examples=40, deadline=None)
@given(ky=st.integers(1, 5), kx=st.integers(1, 5), seed=st.integers(0, 2**31))
def test_refining_keeps_the_bilinear_surface(ky, kx, seed):
    """refine(r, ky, kx) over float64 posts: the same heights everywhere (to rounding), the
    same posts bit for bit; a NaN post makes NaN only the new posts between it and its
    neighbours; a filled post marks those filled."""
    rng = np.random.default_rng(seed)
    h = rng.normal(500.0, 200.0, (7, 9))
    h[3, 4] = np.nan
    filled = np.zeros(h.shape, bool)
    filled[1, 1] = True
    r = Raster(h, Georef(CRS_GEOGRAPHIC, 8.0, 46.0, 0.01, 0.02), name="r", filled=filled)
    f = refine(r, ky, kx)
    assert f.shape == ((7 - 1) * ky + 1, (9 - 1) * kx + 1)
    np.testing.assert_array_equal(f.heights[::ky, ::kx], h)
    lat = rng.uniform(46.0, 46.12, 3000)
    lon = rng.uniform(8.0, 8.08, 3000)
    a, sa = _heights(r, lat, lon)
    b, sb = _heights(f, lat, lon)
    np.testing.assert_array_equal(sa, sb)
    np.testing.assert_allclose(b, a, rtol=0, atol=1e-9)
    nan_rows, nan_cols = np.nonzero(np.isnan(f.heights))
    assert np.all(np.abs(nan_rows - 3 * ky) < ky) and np.all(np.abs(nan_cols - 4 * kx) < kx)
    if (ky, kx) != (1, 1):
        assert f.filled is not None and f.filled[ky, kx] and f.filled.sum() == (2 * ky - 1) * (2 * kx - 1)


def test_web_mercator_tiles_of_two_resolutions_merge_continuous(tif_grand_canyon):
    """The same in EPSG:3857 (metres on the lattice, degrees for the boxes): the Grand Canyon
    posts west of a tile of every second post east of them."""
    from terrain.dem import read_dem

    r = read_dem(tif_grand_canyon)
    fine = _part(r, 0, 300, 0, 200, name="fine")
    coarse = _part(r, 0, 300, 200, 500, step=2, name="coarse")
    seam = coarse.bounds[1]
    lat = np.linspace(fine.bounds[0] + 0.001, fine.bounds[2] - 0.001, 500)
    assert _seam_step([fine, coarse], lat, seam) > 1.0
    out = mosaic([fine, coarse])
    assert [o.name for o in out] == ["fine+coarse"] and out[0].shape == (301, 501)
    assert out[0].meta["members"][1]["refined"]["factors"] == [2, 2]
    assert _seam_step(out[0], lat, seam) < 0.01


def test_three_resolutions_in_a_row_end_at_the_finest(alps):
    """3" | 9" | 27" side by side (each sharing its edge column with the next): the 27" tile
    touches only the 9" one, which touches the 3" one; all three end as one raster at 3",
    continuous at both seams, the 27" tile refined 9 x 9 from its own posts."""
    fine = _part(alps, 0, 243, 0, 81, name="fine")
    mid = _part(alps, 0, 243, 81, 324, step=3, name="mid")
    coarse = _part(alps, 0, 243, 324, 648, step=9, name="coarse")
    out = mosaic([fine, mid, coarse])
    assert len(out) == 1 and out[0].shape == (244, 649)
    assert [m.get("refined", {}).get("factors") for m in out[0].meta["members"]] == [None, [3, 3], [9, 9]]
    assert out[0].meta["members"][2]["refined"]["shape"] == list(coarse.shape)
    g = fine.georef
    lat = np.random.default_rng(4).uniform(g.y0, g.y0 + 243 * g.dy, 1000)
    for seam in (g.x0 + 81 * g.dx, g.x0 + 324 * g.dx):
        assert _seam_step([fine, mid, coarse], lat, seam) > 1.0
        assert _seam_step(out[0], lat, seam) < 0.01
    np.testing.assert_array_equal(out[0].heights[::9, 324::9], coarse.heights)
