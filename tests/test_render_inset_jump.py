"""The clipmap never shows through a target area's inset inside its polygon, whatever level is
drawn there: after a camera jump (finer levels lag, coarse ones cover the area) and far away
(client/render/clipmap_layer.py "Insets"; docs/RENDERING.md "Geomipmap insets").

Real parts: the Alps SRTM tile (N47E009), the alps scenario's "altenrhein-airfield" target area
(1.6 x 2.6 km) at detail_m = 4 (troughs up to detail_bound_m = 10.9 m below the DEM), the
observer and ground_vehicle profiles' clipmaps as ``sortie view`` builds them, and an EGL
context (Mesa llvmpipe without a GPU), 240 x 180 frames.

Oracles:
- jump (the tester's reproduction): 2500 m over the Rhine crossing, then straight down on the
  airfield from 1500 m MSL (1100 m above it; the whole view inside the polygon). Each of the 4
  frames after the jump against a fresh renderer's frame of that pose: pixels inside the polygon
  differing by more than 6 levels in a channel. Before: 1231 (observer) and 15220
  (ground_vehicle) pixels in frame 0.
- depth: the inset drawn alone (the same layer, the same triangles) gives each pixel the inset's
  depth; where the full frame's visible point lies inside the polygon and nearer than that, the
  clipmap shows through. Counted beyond 20 m from the border, where the clipmap's fragments are
  surely pushed behind (terrain/inset.py CoverageMask: e + texel sqrt(2), 17 m here; nearer the
  border both are the DEM). Before: 152 pixels at a grazing view from 4.7 km east.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap_layer import clipmap_factory
from client.render.geomipmap import GeomipmapInset
from client.render.profiles import profile
from client.render.renderer import Renderer
from terrain.geodesy import ecef_to_geodetic
from terrain.inset import INSET_SEED, insets_of, with_insets

W, H = 240, 180
N = 48.0
MAGENTA = (255, 0, 255)
AIRFIELD = [(47.478, 9.543), (47.478, 9.577), (47.492, 9.577), (47.492, 9.543)]
BEFORE = (47.282, 9.565, 2500.0, 0.0, -90.0)
AFTER = (47.485, 9.560, 1500.0, 0.0, -90.0)
GRAZING = (47.485, 9.62, 700.0, 270.0, -4.0)  # 4.7 km east of the area, looking west along it
# Beyond this distance inside the polygon the clipmap's fragments are surely pushed behind (the
# coverage mask's e + texel sqrt(2), 17 m here; tested below); nearer the border both are the DEM
# (the inset's detail starts at a0 = 131 m), where either may win the depth test.
SURELY_INSIDE_M = 20.0


@pytest.fixture(scope="module")
def area(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = with_insets(Terrain([read_dem(hgt_alps)]), [("altenrhein-airfield", AIRFIELD, 4.0)], INSET_SEED)
    return terrain, insets_of(terrain)


def camera(lat, lon, alt, heading, pitch) -> Camera:
    return Camera.from_geodetic(lat, lon, alt, heading, pitch, 0.0, geoid_undulation_m=N, fov_x_deg=60.0)


def view_renderer(terrain, insets, profile_name: str) -> Renderer:
    """As ``sortie view`` builds it (client/render_cli.py _renderer), test sky (no fog)."""
    return Renderer(terrain, W, H, geoid_undulation_m=N, insets=insets, flat_sky_rgb=MAGENTA,
                    terrain_layer_factory=clipmap_factory(terrain, geoid_undulation_m=N, insets=insets,
                                                          **profile(profile_name).layer_args()))


def inset_depth_m(inset, cam: Camera) -> np.ndarray:
    """(H, W) view depth of the inset drawn alone; inf where it does not cover the pixel."""
    with Renderer(None, W, H, geoid_undulation_m=N, sea=False, flat_sky_rgb=MAGENTA,
                  terrain_layer_factory=lambda ctx, origin: GeomipmapInset(ctx, inset, origin,
                                                                           geoid_undulation_m=N)) as r:
        r.render(cam)
        return r.depth_m()


def visible_points(renderer: Renderer, cam: Camera, inset) -> tuple[np.ndarray, np.ndarray]:
    """((H, W) view depth, (H, W) signed distance (m, positive inside) of each pixel's visible
    point from the polygon's border; -inf where only sky was drawn)."""
    d = renderer.depth_m()
    rays = cam.pixel_rays(W, H)
    seen = np.isfinite(d)
    p = cam.position_ecef + rays * np.where(seen, d / (rays @ cam.r_ecef_body[:, 0]), 0.0)[..., None]
    lat, lon, _ = ecef_to_geodetic(p.reshape(-1, 3))
    s = inset.plane.signed_distance_m(lat, lon).reshape(H, W)
    return d, np.where(seen, s, -np.inf)


@pytest.mark.parametrize("profile_name", ["observer", "ground_vehicle"])
def test_after_a_camera_jump_no_clipmap_shows_inside_the_polygon(area, profile_name):
    terrain, insets = area
    cam = camera(*AFTER)
    alone = inset_depth_m(insets[0], cam)
    with view_renderer(terrain, insets, profile_name) as fresh:
        ref = fresh.render(cam).astype(int)
    with view_renderer(terrain, insets, profile_name) as r:
        r.render(camera(*BEFORE))
        for k in range(4):
            img = r.render(cam).astype(int)
            d, s = visible_points(r, cam, insets[0])
            assert (s > 0).all()  # the whole view lies inside the polygon
            differ = np.any(np.abs(img - ref) > 6, axis=-1)
            assert differ.sum() == 0, (profile_name, k, int(differ.sum()))
            assert np.all(d >= alone * (1.0 - 1e-6)), (profile_name, k)  # the inset is what is seen


def test_the_coverage_mask_says_inside_only_inside(area):
    """A bilinear sample of InsetSource.coverage_mask is > 0 only where the point is inside the
    polygon, and is > 0 wherever it is more than e + texel sqrt(2) inside (terrain/inset.py)."""
    inset = area[1][0]
    m = inset.coverage_mask()
    ny, nx = m.values.shape
    rng = np.random.default_rng(5)
    x = rng.uniform(m.x0, m.x0 + (nx - 1) * m.texel_m, 200_000)
    y = rng.uniform(m.y0, m.y0 + (ny - 1) * m.texel_m, 200_000)
    fx, fy = (x - m.x0) / m.texel_m, (y - m.y0) / m.texel_m
    c, r = np.minimum(fx.astype(int), nx - 2), np.minimum(fy.astype(int), ny - 2)
    tx, ty = fx - c, fy - r
    v = m.values.astype(np.float64)
    sample = ((1 - ty) * ((1 - tx) * v[r, c] + tx * v[r, c + 1])
              + ty * ((1 - tx) * v[r + 1, c] + tx * v[r + 1, c + 1]))
    p = inset.plane
    s = inset.plane.signed_distance_m(p.lat_ref + y / p.k_y, p.lon_ref + x / p.k_x)
    assert (s > 0).any() and (s < 0).any()
    assert np.all(s[sample > 0] > 0)
    surely = m.margin_m + math.sqrt(2.0) * m.texel_m
    assert np.all(sample[s > surely] > 0)
    assert SURELY_INSIDE_M >= surely and SURELY_INSIDE_M < inset.detail_offset_m


def test_coarse_levels_far_away_do_not_show_through(area):
    terrain, insets = area
    cam = camera(*GRAZING)
    alone = inset_depth_m(insets[0], cam)
    with view_renderer(terrain, insets, "observer") as r:
        r.render(cam)
        d, s = visible_points(r, cam, insets[0])
        assert [x.k for x in r.terrain_layer.draws][0] >= 4  # coarse levels are drawn over the area
    inside = s > SURELY_INSIDE_M
    assert inside.sum() > 500
    through = inside & (d < alone * (1.0 - 1e-6))
    assert through.sum() == 0, int(through.sum())
