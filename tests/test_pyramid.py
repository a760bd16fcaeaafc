"""Min/max pyramid: exact bounds of the bilinear surface at every level, holes, layout."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from terrain.pyramid import build_pyramid, cell_bounds, to_float32_outward
from terrain.raster import CRS_GEOGRAPHIC, STATUS_OUTSIDE, Georef, Raster

D = 1.0 / 1200.0


def _heights(seed, ny, nx, dtype=np.float32, holes=0):
    rng = np.random.default_rng(seed)
    h = rng.normal(800.0, 300.0, (ny, nx))
    h[rng.integers(0, ny, holes), rng.integers(0, nx, holes)] = np.nan
    return h.astype(dtype)


def _bilinear(raster, rows, cols):
    lat = raster.georef.y0 + rows * raster.georef.dy
    lon = raster.georef.x0 + cols * raster.georef.dx
    h = np.full(rows.size, np.nan)
    status = np.full(rows.size, STATUS_OUTSIDE, np.uint8)
    raster.heights_into(lat, lon, h, status)
    return h


def _brute_block(heights, k, bi, bj):
    """Min and max over the posts of the cells a level-k block covers (NaN aware)."""
    ny, nx = heights.shape
    r0, r1 = bi << k, min((bi + 1) << k, ny - 1)
    c0, c1 = bj << k, min((bj + 1) << k, nx - 1)
    posts = heights[r0:r1 + 1, c0:c1 + 1].astype(np.float64)
    if np.isnan(posts).any():  # conservative where a hole touches the block
        cells = posts[:-1, :-1] + posts[:-1, 1:] + posts[1:, :-1] + posts[1:, 1:]
        if np.isnan(cells).any():
            return -np.inf, np.inf
    return np.nanmin(posts), np.nanmax(posts)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**31), ny=st.integers(2, 40), nx=st.integers(2, 40),
       dtype=st.sampled_from([np.float32, np.float64]), holes=st.integers(0, 3),
       level_frac=st.floats(0, 1), block_frac=st.tuples(st.floats(0, 1), st.floats(0, 1)))
def test_bilinear_within_block_bounds(seed, ny, nx, dtype, holes, level_frac, block_frac):
    heights = _heights(seed, ny, nx, dtype, holes)
    raster = Raster(heights, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    pyr = raster.pyramid
    k = min(int(level_frac * pyr.n_levels), pyr.n_levels - 1)
    lo, hi = pyr.mins[k], pyr.maxs[k]
    bi = min(int(block_frac[0] * lo.shape[0]), lo.shape[0] - 1)
    bj = min(int(block_frac[1] * lo.shape[1]), lo.shape[1] - 1)
    # Points anywhere in the block's (clipped) cell range, edges included.
    r0, r1 = bi << k, min((bi + 1) << k, ny - 1)
    c0, c1 = bj << k, min((bj + 1) << k, nx - 1)
    rng = np.random.default_rng(seed)
    rows = np.concatenate([rng.uniform(r0, r1, 200), [r0, r1, r0, r1]])
    cols = np.concatenate([rng.uniform(c0, c1, 200), [c0, c1, c1, c0]])
    h = _bilinear(raster, rows, cols)
    ok = ~np.isnan(h)
    # The lerp form can round a float64 result one ulp past its posts: 1e-12 relative.
    slack = 1e-12 * np.abs(h[ok])
    assert (lo[bi, bj] <= h[ok] + slack).all()
    assert (h[ok] - slack <= hi[bi, bj]).all()
    if not ok[:200].all():  # an interior point on a hole makes the block unskippable
        assert lo[bi, bj] == -np.inf and hi[bi, bj] == np.inf
    # And the bounds are tight: exactly the posts' extremes (float32 rounded outward).
    want_lo, want_hi = _brute_block(heights, k, bi, bj)
    assert lo[bi, bj] == to_float32_outward(np.array([want_lo]), -np.inf)[0]
    assert hi[bi, bj] == to_float32_outward(np.array([want_hi]), np.inf)[0]


@pytest.mark.parametrize("shape", [(2, 2), (3, 2), (2, 9), (1201, 1201), (17, 1000)])
def test_level_shapes_halve_up_to_one_block(shape):
    pyr = build_pyramid(np.zeros(shape, np.float32))
    shapes = [tuple(s) for s in pyr.shapes]
    assert shapes[0] == (shape[0] - 1, shape[1] - 1)
    for (a0, a1), (b0, b1) in zip(shapes, shapes[1:]):
        assert (b0, b1) == (-(-a0 // 2), -(-a1 // 2))
    assert shapes[-1] == (1, 1)
    assert pyr.offsets[-1] == pyr.min_flat.size == pyr.max_flat.size


def test_float64_heights_round_outward_by_at_most_one_ulp():
    h = _heights(5, 30, 31, np.float64)
    lo, hi = cell_bounds(h)
    c = np.stack([h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:]])
    exact_lo, exact_hi = c.min(axis=0), c.max(axis=0)
    assert (lo <= exact_lo).all() and (hi >= exact_hi).all()
    assert (np.nextafter(lo, np.float32(np.inf)) > exact_lo).all()
    assert (np.nextafter(hi, np.float32(-np.inf)) < exact_hi).all()


def test_holes_are_never_skippable_and_do_not_leak():
    h = np.full((9, 9), 100.0, np.float32)
    h[4, 4] = np.nan
    pyr = build_pyramid(h)
    lo0, hi0 = pyr.mins[0], pyr.maxs[0]
    around = np.zeros((8, 8), bool)
    around[3:5, 3:5] = True  # the four cells sharing the NaN post
    assert (lo0[around] == -np.inf).all() and (hi0[around] == np.inf).all()
    assert (lo0[~around] == 100.0).all() and (hi0[~around] == 100.0).all()
    assert pyr.maxs[-1][0, 0] == np.inf


def test_filled_levels_or_reduce():
    h = np.zeros((10, 10), np.float32)
    filled = np.zeros((10, 10), bool)
    filled[9, 9] = True
    pyr = build_pyramid(h, filled)
    assert pyr.filled[0][8, 8] == 1 and pyr.filled[0].sum() == 1
    assert all(level[-1, -1] == 1 and level.sum() == 1 for level in pyr.filled)
    assert build_pyramid(h).filled == ()


def test_raster_caches_a_read_only_pyramid():
    raster = Raster(_heights(1, 12, 7), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, D, D))
    assert raster.pyramid is raster.pyramid
    with pytest.raises(ValueError):
        raster.pyramid.maxs[0][0, 0] = 0.0
