"""The seam between the clipmap and a target area's geomipmap inset (client/render/geomipmap.py,
client/render/clipmap_layer.py; docs/RENDERING.md "Geomipmap insets").

Real parts: the Alps SRTM tile (N47E009), the alps scenario's "rhine-crossing" target area (a
1.8 x 3 km pentagon in the flat Rhine valley) at detail_m = 4, the fast_jet profile's clipmap
(90 m finest posts, 2 px decimation) as ``sortie view`` builds it, and an EGL context (Mesa
llvmpipe without a GPU), 320 x 240 frames.

Oracles:
- shading: within a0 - 20 m of the polygon's border the inset is the DEM exactly (no detail,
  terrain/inset.py), so the same frame drawn by the clipmap alone over the plain DEM shows the
  same ground there; the inset's pixels must have its colour (mean and mean absolute
  difference per channel, 0-255), with and without land classes. Deeper inside, where the
  inset adds its detail, its mean colour must stay near the clipmap's (before: a darker,
  untextured polygon; with land classes, the tint where the clipmap draws its classes).
- flicker: the camera moved 0.75 m east, twice; pixels within 150 m of the border (their
  visible point's signed distance, from the depth buffer) changing by more than 12 levels in a
  channel (the tester's measure) are counted.
Before the fix: mean difference in the strip -4.6 to -7.6 levels (mean |diff| 6.0-7.7), the
interior -8.5 to -17; with land classes -13 to -40 in the strip; flicker 1453 and 194 pixels at
the first pose, 73 and 447 at the second. After: |mean| <= 0.14, mean |diff| <= 1.8, interior
within 3.3; flicker 0-5 pixels.
"""

from __future__ import annotations

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap_layer import clipmap_factory
from client.render.profiles import profile
from client.render.renderer import Renderer
from terrain.geodesy import ecef_to_geodetic
from terrain.inset import INSET_SEED, insets_of, with_insets

W, H = 320, 240
N = 48.0  # the alps scenario's geoid undulation
RHINE = [(47.274, 9.545), (47.274, 9.565), (47.284, 9.585), (47.290, 9.570), (47.286, 9.545)]
POSES = [(47.282, 9.535, 750.0, 90.0, -12.0),  # from the west, across the polygon (the tester's zfight view)
         (47.270, 9.555, 700.0, 10.0, -15.0)]  # from the south, its southern edge near
STEP_DEG = 1e-5  # 0.75 m east


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.fixture(scope="module")
def area(alps):
    terrain = with_insets(alps, [("rhine-crossing", RHINE, 4.0)], INSET_SEED)
    return terrain, insets_of(terrain)


def camera(lat, lon, alt, heading, pitch) -> Camera:
    return Camera.from_geodetic(lat, lon, alt, heading, pitch, 0.0, geoid_undulation_m=N, fov_x_deg=60.0)


def view_renderer(terrain, insets, land_classes: bool = False) -> Renderer:
    """As ``sortie view`` builds it (client/render_cli.py _renderer) for the fast_jet profile."""
    layer_args = profile("fast_jet").layer_args()
    return Renderer(terrain, W, H, geoid_undulation_m=N, insets=insets,
                    terrain_layer_factory=clipmap_factory(terrain, geoid_undulation_m=N, insets=insets,
                                                          land_classes=land_classes, **layer_args))


def signed_distance_of_pixels(renderer: Renderer, cam: Camera, inset) -> np.ndarray:
    """(H, W) signed distance (m, positive inside) of each pixel's visible point from the
    polygon's border, from the depth buffer; -inf where only sky was drawn."""
    d = renderer.depth_m()
    rays = cam.pixel_rays(W, H)
    along = rays @ cam.r_ecef_body[:, 0]
    seen = np.isfinite(d)
    p = cam.position_ecef + rays * np.where(seen, d / along, 0.0)[..., None]
    lat, lon, _ = ecef_to_geodetic(p.reshape(-1, 3))
    s = inset.plane.signed_distance_m(lat, lon).reshape(H, W)
    return np.where(seen, s, -np.inf)


@pytest.mark.parametrize("land_classes", [False, True])
def test_the_inset_is_shaded_as_the_clipmap_where_both_are_the_dem(alps, area, land_classes):
    terrain, insets = area
    a0 = insets[0].detail_offset_m  # 131 m: no detail within it
    with view_renderer(terrain, insets, land_classes) as r, view_renderer(alps, [], land_classes) as plain:
        for pose in POSES:
            cam = camera(*pose)
            img = r.render(cam).astype(float)
            s = signed_distance_of_pixels(r, cam, insets[0])
            ref = plain.render(cam).astype(float)
            strip = (s > 0.0) & (s < a0 - 20.0)
            inner = s > a0 + insets[0].border_band_m + 50.0
            assert strip.sum() > 3000 and inner.sum() > 3000
            diff = img[strip] - ref[strip]
            assert np.abs(diff.mean(axis=0)).max() <= 1.0, (pose, diff.mean(axis=0))
            assert np.abs(diff).mean() <= 2.5, (pose, np.abs(diff).mean())
            # Inside, the inset's detail (its rougher normals) may darken the ground a little, not
            # make a darker (or, with land classes, a mottled) polygon of it.
            inner_diff = (img[inner] - ref[inner]).mean(axis=0)
            assert np.abs(inner_diff).max() <= 4.0, (pose, inner_diff)


def test_the_border_does_not_flicker_under_a_sub_metre_move(area):
    terrain, insets = area
    with view_renderer(terrain, insets) as r:
        for pose in POSES:
            frames, near = [], []
            for k in range(3):
                cam = camera(pose[0], pose[1] + k * STEP_DEG, *pose[2:])
                frames.append(r.render(cam).astype(int))
                near.append(np.abs(signed_distance_of_pixels(r, cam, insets[0])) < 150.0)
            for k in (0, 1):
                band = near[k] | near[k + 1]
                assert band.sum() > 10_000
                changed = np.any(np.abs(frames[k] - frames[k + 1]) > 12, axis=-1) & band
                assert changed.sum() <= 20, (pose, k, int(changed.sum()))
