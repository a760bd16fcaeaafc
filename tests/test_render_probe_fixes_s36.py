"""Acceptance-probe fixes of the render client (session 36: terrain the team rarely draws).

1. The reference mesh (``--terrain-renderer mesh``, and the clipmap's mesh near a pole) dropped
   every cell touching a no-data post, so from beside a DEM's edge (Boulder's ESRI grid from the
   plains east of it, the Grand Canyon GeoTIFF from the south) the view went under the terrain's
   last row and showed the sea shell at 0 m beneath land 1600-2000 m high: the terrain floated
   over the sea. The clipmap stores no-data posts at MSL 0 and drew a wall there. The mesh now
   draws the no-data posts next to data at MSL 0 too (terrain_mesh.shore_posts).

Real parts: the Boulder ESRI ASCII grid and the Grand Canyon Web Mercator GeoTIFF, EGL
(llvmpipe), small frames.
"""

from __future__ import annotations

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.renderer import Renderer
from client.render.terrain_mesh import build_mesh, grid_triangles, lattice_for, shore_posts
from terrain.geodesy import ecef_to_geodetic

MAGENTA = (255, 0, 255)
W, H = 160, 90
WINDOW_M = 10_000.0  # the mesh's window, no coarser ring: every pixel drawn at full resolution


def _terrain(path):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(path)])


def _drawn_points(terrain, camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat, lon, h ellipsoid) of what each non-sky pixel of a reference-mesh frame shows, from
    its view depth."""
    with Renderer(terrain, W, H, window_m=WINDOW_M, horizon_m=0.0, flat_sky_rgb=MAGENTA) as r:
        image = r.render(camera)
        depth = r.depth_m()
    rays = camera.pixel_rays(W, H)
    drawn = ~np.all(image == np.array(MAGENTA, np.uint8), axis=-1)
    dist = depth / (rays @ camera.r_ecef_body[:, 0])
    p = camera.position_ecef + dist[..., None] * rays
    lat, lon, h = ecef_to_geodetic(p[drawn])
    return lat, lon, h


@pytest.mark.parametrize("which, pose", [
    ("asc_boulder", (40.15, -105.20, 2500.0, 270.0, -5.0)),  # from the plains east of the grid
    ("tif_grand_canyon", (36.00, -113.00, 2500.0, 0.0, -8.0)),  # from south of the GeoTIFF
])
def test_the_mesh_draws_no_sea_under_a_dems_edge(request, which, pose):
    """Before: 2,880 (Boulder) and 4,320 (Grand Canyon) of 14,400 pixels showed the sea at 0 m at
    points under the DEM's data, 1600-2000 m below its surface. Now every pixel showing a point
    inside the DEM (one post clear of its edge) shows it within 15 m of the terrain's height there
    (the cells' triangles against the bilinear surface, and the depth buffer's read back)."""
    terrain = _terrain(request.getfixturevalue(which))
    lat, lon, h = _drawn_points(terrain, Camera.from_geodetic(*pose, fov_x_deg=60.0))
    s = terrain.describe()[0]
    pad_lat = (s["lat_max"] - s["lat_min"]) / (s["rows"] - 1)
    pad_lon = (s["lon_max"] - s["lon_min"]) / (s["cols"] - 1)
    in_window = ((np.abs(lat - pose[0]) * 111_000.0 < 0.9 * WINDOW_M)  # (the sea shows past its end)
                 & (np.abs(lon - pose[1]) * 111_000.0 * np.cos(np.radians(pose[0])) < 0.9 * WINDOW_M))
    inside = ((lat > s["lat_min"] + pad_lat) & (lat < s["lat_max"] - pad_lat)
              & (lon > s["lon_min"] + pad_lon) & (lon < s["lon_max"] - pad_lon) & in_window)
    assert inside.sum() > 0.1 * W * H
    ground = terrain.heights(lat[inside], lon[inside]).height_msl_m
    err = np.abs(h[inside] - ground)
    assert np.count_nonzero(err > 15.0) == 0, (int(np.count_nonzero(err > 15.0)), float(err.max()))


def test_shore_posts_are_the_no_data_posts_beside_data():
    h = np.full((5, 6), np.nan)
    h[1:3, 1:3] = 100.0
    shore = shore_posts(h)
    expected = np.zeros((5, 6), bool)
    expected[0:4, 0:4] = True
    expected[1:3, 1:3] = False
    assert np.array_equal(shore, expected)
    h[shore] = 0.0
    # Every cell touching data is drawn (3 x 3 cells), no cell beyond the shore.
    assert len(grid_triangles(np.isfinite(h))) == 2 * 9


def test_the_mesh_keeps_its_sea_shell_bounds_where_data_ends(asc_boulder):
    """Shore posts are drawn at MSL 0 but are no data: the sea shell is still drawn around them
    (the mesh's solid bounds exclude them), and the posts of data keep their heights."""
    terrain = _terrain(asc_boulder)
    lat, lon = 40.15, -105.26  # just east of the grid (its last column: -105.27); the window spans both
    mesh = build_mesh(terrain, lattice_for(terrain.describe(), lat, lon), lat, lon, window_m=3000.0,
                      horizon_m=0.0)
    s = terrain.describe()[0]
    assert mesh.solid_bounds is None or mesh.solid_bounds[3] < s["lon_max"]
    placed = np.isfinite(mesh.height_msl_m)  # no-data posts beyond the shore stay NaN, undrawn
    glat, glon, _ = ecef_to_geodetic(mesh.positions_ecef[placed])
    outside = glon > s["lon_max"] + 1e-9
    assert outside.any() and np.all(mesh.height_msl_m[placed][outside] == 0.0)
    assert (~placed).any()
    inside = ~outside
    ref = terrain.heights(glat[inside], glon[inside]).height_msl_m
    assert np.allclose(mesh.height_msl_m[placed][inside], ref, atol=1e-3)
