"""A target area's inset over a coast keeps land and water apart (terrain/inset.py
keep_sea_level_sign): an acceptance tester's case, an area of open sea beside the Kattegat's
skerries (N57E011, SRTM3: the sea is stored as 0 m), where the fractal detail raised land
blotches on 437 of 900 sea posts (0-8.5 cm high), which the renderer then coloured as land."""

from __future__ import annotations

import numpy as np
import pytest

from terrain.inset import INSET_SEED, LAND_FLOOR_M, insets_of, keep_sea_level_sign, with_insets

SEA = [(57.48, 11.66), (57.48, 11.70), (57.50, 11.70), (57.50, 11.66)]
COAST = [(57.70, 11.65), (57.70, 11.69), (57.72, 11.69), (57.72, 11.65)]  # skerries and sea (half land)


@pytest.fixture(scope="module")
def kattegat(hgt_kattegat):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_kattegat)])


@pytest.mark.parametrize("polygon", [SEA, COAST], ids=["sea", "coast"])
def test_detail_keeps_the_sign_of_the_ground_beneath(kattegat, polygon):
    """At every inset post: where the DEM beneath is water (<= 0 m) the inset is exactly it;
    where it is land the inset stays land (> 0). Detail still shapes the land (the coast case
    holds posts it moves by metres)."""
    inset = insets_of(with_insets(kattegat, [("area", polygon, 2.0)], INSET_SEED))[0]
    g = inset.georef
    rows, cols = inset.heights.shape
    lat = g.y0 + np.arange(rows) * g.dy
    lon = g.x0 + np.arange(cols) * g.dx
    below = kattegat.height_grid(lat, lon).height_msl_m
    h = inset.heights.astype(np.float64)
    ok = np.isfinite(below) & np.isfinite(h)
    water, land = ok & (below <= 0.0), ok & (below > 0.0)
    assert water.sum() > 1000
    assert np.array_equal(h[water], below[water].astype(np.float32).astype(np.float64))
    assert np.all(h[land] > 0.0)
    if polygon is COAST:
        assert land.sum() > 1000 and np.abs(h[land] - below[land]).max() > 1.0


def test_keep_sea_level_sign_bounds():
    """Water keeps its height; land keeps the detailed height unless it would sink to 1 cm or
    below, where it is held at 1 cm (or its own height, if lower)."""
    below = np.array([-3.0, 0.0, 0.005, 0.5, 20.0])
    detailed = np.array([2.0, 0.3, -1.0, -4.0, 17.5])
    assert keep_sea_level_sign(below, detailed).tolist() == [-3.0, 0.0, 0.005, LAND_FLOOR_M, 17.5]
