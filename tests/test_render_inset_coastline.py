"""Decimation keeps the coastline (client/render/clipmap_layer.py straddles_sea_level): colour
tells land from water by the sign of the interpolated height (0 m MSL), so a block whose posts
straddle sea level is never drawn with fewer posts; elsewhere decimation cannot change land for
water (every point drawn is a convex combination of posts of one sign).

(Here among the inset render tests by the file names this change was allowed; it belongs with
tests/test_clipmap_decimation.py.)

Real parts: the Kattegat SRTM tile (N57E011: skerries 0-20 m high), the observer profile's
clipmap (2 px decimation) as ``sortie render`` builds it, an EGL context (llvmpipe), 240 x 180,
test sky (no fog). Oracle: the same frame drawn with every post (no decimation); a pixel is
water when its blue exceeds its green by more than 10 levels (terrain_mesh's water colour
against the tint). Before: 2294 pixels of 43,200 disagreed at 30 km, 2013 at 60 km.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from client.render.camera import Camera
from client.render.clipmap_layer import clipmap_factory, coastline_shift_m, straddles_sea_level
from client.render.profiles import profile
from client.render.renderer import Renderer

W, H = 240, 180


@pytest.fixture(scope="module")
def kattegat(hgt_kattegat):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_kattegat)])


def water(image: np.ndarray) -> np.ndarray:
    img = image.astype(int)
    sky = np.all(img == (255, 0, 255), axis=-1)
    return (img[..., 2] > img[..., 1] + 10) & ~sky


@pytest.mark.parametrize("altitude_m", [30_000.0, 60_000.0])
def test_decimation_does_not_move_the_coastline(kattegat, altitude_m):
    cam = Camera.from_geodetic(57.5, 11.7, altitude_m, 0.0, -90.0, 0.0, fov_x_deg=60.0)
    frames, triangles = {}, {}
    for pixel_error in (2.0, None):
        args = {**profile("observer").layer_args(), "pixel_error": pixel_error}
        with Renderer(kattegat, W, H, flat_sky_rgb=(255, 0, 255),
                      terrain_layer_factory=clipmap_factory(kattegat, **args)) as r:
            frames[pixel_error] = water(r.render(cam))
            triangles[pixel_error] = r.terrain_layer.triangles
            if pixel_error is not None:
                layer = r.terrain_layer
    assert 0.05 < frames[None].mean() < 0.95  # a coast: land and water both (82-86 % water)
    # Land and water may swap only where the coastline moved within the 2 px bound (+1 px: the
    # bound is on the shift of the coastline's points, a pixel's colour is sampled at its centre).
    shore = ndimage.distance_transform_edt(frames[None] == frames[None][0, 0])  # to the other class
    shore = np.minimum(shore, ndimage.distance_transform_edt(frames[None] != frames[None][0, 0]))
    moved = frames[2.0] != frames[None]
    assert moved.sum() < 0.02 * moved.size and np.all(shore[moved] <= 3.0), (int(moved.sum()), shore[moved].max())
    assert triangles[2.0] < 0.5 * triangles[None]  # decimation still draws far fewer triangles
    # The blocks that straddle sea level are decimated only within the coastline's bound.
    d = min(layer.draws, key=lambda x: x.k)  # the finest level drawn
    level, n = layer.clipmap.levels[d.k], layer.clipmap.n
    h = [level.texel[np.arange(b[0], b[2] + 1)[:, None] % n, np.arange(b[1], b[3] + 1)[None, :] % n, 3]
         for b in d.blocks]
    straddle = np.array([(x <= 0).any() and (x > 0).any() for x in h])
    assert straddle.any() and (~straddle).any()
    assert np.array_equal(straddles_sea_level(d.blocks, level, n), straddle)
    shift = coastline_shift_m(d.blocks[straddle], level, n)
    assert np.all(shift[:, -1] > 0) and np.all(np.diff(shift, axis=1) < 0)  # coarser strides move it more
