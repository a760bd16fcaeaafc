"""Acceptance-probe fixes of the geometry clipmap (session 31, seeds conformance).

1. A level's lattice column was wrapped at lon0 + 180 of its lattice (lon 0 for the procedural
   world and terrain stores, whose lattices start at -180; the antimeridian for a DEM lattice
   from lon 0): crossing it, every level's region jumped a whole turn and was refilled whole
   instead of by strips, the finer levels fell behind the budget and were not drawn (1 level of 7
   and 80,645 samples in the frame after lon 0, one level back a frame). Columns are now taken on
   the turn nearest the last focus (Clipmap.unwrapped_dlon): every meridian is an ordinary
   toroidal update (thesis §3.1.3, §3.1.4).
2. The finest level's alpha_h is the thesis' n = n_max case, h / (0.4 edge(n)) (§3.2.2), not the
   0.2-0.4 extent ramp of the other levels; edge(n) = max(edge_x, edge_y).

Real parts: the procedural world (terrain/procedural.py), EGL (llvmpipe), small frames.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from client.render.camera import Camera
from client.render.clipmap import NORMALS_PER_POST, Clipmap, drawn_regions
from client.render.clipmap_layer import clipmap_factory, height_alpha
from client.render.renderer import Renderer
from client.render.terrain_mesh import Lattice, lattice_for
from terrain.procedural import ProceduralTerrain
from terrain.terrain import Terrain

MAGENTA = (255, 0, 255)
LEVELS, N = 4, 31
# Posts of 360 / 2^16 degrees (about 610 m), a dyadic spacing: level k's turn is 2^(16 - k) columns
# and every post's longitude is exact in float64, on any turn.
POSTS_PER_TURN = 2 ** 16
STEP_DEG = 0.005  # a focus step: under one finest column (0.0055 degrees)
# Per update, each level moves by at most one 2-column strip (the finest column is wider than a
# step): the samples a crossing elsewhere takes, heights and normals.
STRIP_SAMPLES = LEVELS * 2 * N * (1 + NORMALS_PER_POST)
MARGIN_CELLS = math.ceil(0.1 * N) + 2  # as the layer crops a lagging level (morph width + 2)


@pytest.fixture(scope="module")
def world():
    return Terrain([ProceduralTerrain(3, block_cells=64, posts_per_turn=POSTS_PER_TURN)])


def _lattice(world, lon0: float) -> Lattice:
    """The procedural world's lattice (from lon -180), or the same posts counted from ``lon0``
    (a DEM lattice's first column)."""
    base = lattice_for(world.describe(), -12.0, 0.0)
    assert base.lon0 == -180.0 and base.dlon == 360.0 / POSTS_PER_TURN
    return Lattice(base.lat0, lon0, base.dlat, base.dlon, base.exact)


def _fly(clipmap: Clipmap, lat: float, lons) -> list[tuple]:
    """(lon, samples, levels behind, levels drawn) of each update along ``lons``."""
    out = []
    for lon in lons:
        clipmap.update(lat, lon)
        d = drawn_regions(clipmap, [lv.k for lv in clipmap.levels if lv.valid], margin_cells=MARGIN_CELLS)
        out.append((lon, clipmap.stats.samples, clipmap.stats.levels_behind, len(d)))
    return out


# --------------------------------------------------------------------------- 1: any meridian

# (lattice lon0, meridian crossed): lon0 + 180 of the procedural/store lattice (the probe's lon 0),
# the antimeridian of a lattice from lon 0 (a DEM's), and for comparison a meridian that never
# wrapped (the antimeridian of the -180 lattice, lon 0.3).
CROSSINGS = [(-180.0, 0.0), (0.0, 180.0), (-180.0, 180.0), (-180.0, 0.3)]


@pytest.mark.parametrize("lon0, meridian", CROSSINGS)
@pytest.mark.parametrize("east", [True, False])
def test_crossing_any_meridian_is_an_ordinary_strip_update(world, lon0, meridian, east):
    """Before: at lon 0 (lattice from -180) and at 180 (lattice from 0), 4805 samples a frame
    (a level refilled whole: 31 x 31 x 5) for 4 frames, 3 levels behind and 1 drawn. Now every
    update of the flight takes at most one strip a level, none falls behind, all 4 are drawn."""
    c = Clipmap(world, _lattice(world, lon0), LEVELS, N, budget=2000)
    sign = 1.0 if east else -1.0
    lons = [(meridian + sign * (k * STEP_DEG - 0.05) + 180.0) % 360.0 - 180.0 for k in range(21)]  # as a camera gives
    c.update(-12.0, lons[0], unlimited=True)
    for lon, samples, behind, drawn in _fly(c, -12.0, lons[1:]):
        assert behind == 0 and drawn == LEVELS, (lon, samples, behind, drawn)
        assert samples <= STRIP_SAMPLES, (lon, samples)


@pytest.mark.parametrize("lon0, meridian", CROSSINGS[:2])
def test_strips_across_the_wrap_equal_a_rebuild_bit_for_bit(world, lon0, meridian):
    """The levels' posts, heights and normals after crossing are a fresh clipmap's at the same
    focus, bit for bit, their regions a whole turn apart (the columns run on past the turn)."""
    lattice = _lattice(world, lon0)
    moving = Clipmap(world, lattice, LEVELS, N, budget=10 ** 9)
    lons = [(meridian + d + 180.0) % 360.0 - 180.0 for d in (-0.05, -0.01, 0.002, 0.04)]
    for lon in lons:
        moving.update(-12.0, lon)
    fresh = Clipmap(world, lattice, LEVELS, N, budget=10 ** 9)
    fresh.update(-12.0, lons[-1])
    for a, b in zip(moving.levels, fresh.levels):
        turn = POSTS_PER_TURN >> a.k
        assert a.region.i0 == b.region.i0 and (a.region.j0 - b.region.j0) % turn == 0
        ta, pa, na = a.unrolled()
        tb, pb, nb = b.unrolled()
        assert np.array_equal(pa, pb) and np.array_equal(ta[..., 3], tb[..., 3]) and np.array_equal(na, nb)


def test_a_whole_turn_of_the_globe_moves_every_level_by_strips():
    """Round the equator in 80 steps of 4.5 degrees over a procedural world of 360/1024-degree
    posts, on its lattice (level 0 spans 10.5 degrees, level 3 84): every level moves east by
    strips each step, across lon0 + 180 and the antimeridian alike, and after the turn each
    region is one turn of columns on from where it started, holding the same posts bit for bit."""
    coarse_world = Terrain([ProceduralTerrain(3, block_cells=64, posts_per_turn=1024)])
    lattice = lattice_for(coarse_world.describe(), 0.0, 0.0)
    assert (lattice.lon0, lattice.dlon) == (-180.0, 360.0 / 1024)
    c = Clipmap(coarse_world, lattice, LEVELS, N, budget=10 ** 9)
    c.update(0.0, -170.0, unlimited=True)
    start = [(lv.region, lv.unrolled()) for lv in c.levels]
    for k in range(1, 81):
        before = [lv.region for lv in c.levels]
        c.update(0.0, -170.0 + 4.5 * k)
        for lv, old in zip(c.levels, before):
            assert 0 <= lv.region.j0 - old.j0 < N - 1 and lv.region.i0 == old.i0, (k, lv.k, old, lv.region)
    for lv, (region, (t0, p0, n0)) in zip(c.levels, start):
        assert lv.region.j0 - region.j0 == 1024 >> lv.k
        t, p, nm = lv.unrolled()
        assert np.array_equal(p, p0) and np.array_equal(t[..., 3], t0[..., 3]) and np.array_equal(nm, n0)


def _sky_below(image: np.ndarray) -> int:
    """Flat-sky pixels in the lower half of a frame pitched 10 degrees down: all below the horizon."""
    return int(np.all(image[image.shape[0] // 2:] == MAGENTA, axis=-1).sum())


def test_a_flight_across_lon_0_draws_every_level_and_no_hole():
    """The probe's flight (default procedural world, east at lat -5, 1500 m): before, the frame
    after lon 0 drew 1 level of 6 with 80k samples (a whole level, 127 x 127 x 5), then one more
    level a frame. Now all 6 levels every frame, at most a strip a level (6 x 2 x 127 x 5), and
    no flat-sky pixel below the horizon."""
    terrain = Terrain([ProceduralTerrain(3)])
    levels, n = 6, 127
    factory = clipmap_factory(terrain, levels=levels, n=n)
    with Renderer(terrain, 160, 90, flat_sky_rgb=MAGENTA, sea=False, terrain_layer_factory=factory) as r:
        for k in range(-2, 4):
            lon = k * 0.0015 + 0.0007
            image = r.render(Camera.from_geodetic(-5.0, lon, 1500.0, 90.0, -10.0))
            assert _sky_below(image) == 0, lon
            if k > -2:  # after the first load
                s = r.stats
                assert s.levels_active == levels and r.terrain_layer.clipmap.stats.levels_behind == 0, lon
                assert s.terrain_samples <= levels * 2 * n * (1 + NORMALS_PER_POST), (lon, s.terrain_samples)


# --------------------------------------------------------------------------- 2: alpha_h of the finest


def _thesis_alpha_h(h_m: float, edge_m: float) -> float:
    """Thesis §3.2.2, n = n_max: alpha_h = h / (0.4 edge(n)), clamped to [0, 1] as alpha is."""
    return min(max(h_m / (0.4 * edge_m), 0.0), 1.0)


def test_the_finest_levels_alpha_h_is_the_thesis_n_max_case():
    """Before: 0.000 at 0.1 edge (the other levels' 0.2-0.4 ramp), where the thesis gives 0.250."""
    edge = 126 * 30.0
    for frac in (0.0, 0.05, 0.1, 0.2, 0.3, 0.39, 0.4, 0.6):
        assert height_alpha(frac * edge, edge, finest=True) == pytest.approx(_thesis_alpha_h(frac * edge, edge),
                                                                             abs=1e-12)
    assert height_alpha(0.1 * edge, edge) == 0.0  # the other levels keep their ramp


def test_the_layer_fades_the_finest_level_from_the_ground_up():
    """Through the renderer over the procedural world: the finest level's alpha_h (what its
    draw gives the shader) is h / (0.4 edge) with h the camera's height above the ground and edge
    the longer side of its region (computed here from the lattice), the finest is dropped where
    it reaches 1, and the next level stays unmorphed (alpha_h 0) while the finest is drawn, so
    their border keeps the next level's posts (no crack)."""
    terrain = Terrain([ProceduralTerrain(3)])
    lat, lon = -5.0, 20.0
    ground = float(terrain.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
    assert ground > 0.0  # land: the layer's ground is this height (sea posts are stored at 0 m)
    with Renderer(terrain, 96, 54, terrain_layer_factory=clipmap_factory(terrain, levels=5, n=63)) as r:
        r.render(Camera.from_geodetic(lat, lon, ground + 100.0, 0.0, -30.0))
        layer = r.terrain_layer
        lattice = layer.clipmap.lattice
        ns_m = math.radians(lattice.dlat) * 6_371_000.0
        ew_m = math.radians(lattice.dlon) * 6_371_000.0 * math.cos(math.radians(lat))
        edge = 62 * max(ns_m, ew_m)
        post_relief = 60.0  # the layer's ground is its nearest finest post's: within this of the query's
        seen_fading = False
        for frac in (0.02, 0.1, 0.25, 0.35, 0.45):
            h = frac * edge
            r.render(Camera.from_geodetic(lat, lon, ground + h, 0.0, -30.0))
            want = _thesis_alpha_h(h, edge)
            assert layer.level_alpha_h(0) == pytest.approx(want, abs=post_relief / (0.4 * edge)), frac
            draws = {d.k: d for d in layer.draws}
            if want < 0.95:
                assert 0 in draws and draws[0].alpha_h == layer.level_alpha_h(0), frac
                assert layer.level_alpha_h(1) == 0.0, frac
                seen_fading |= want > 0.2
            elif want >= 1.0:
                assert 0 not in draws, frac
        assert seen_fading
