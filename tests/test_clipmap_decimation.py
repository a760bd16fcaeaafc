"""Blocks of a clipmap level drawn with fewer posts where the screen allows
(client/render/clipmap_layer.py: decimated_grid, clamped_triangles, grid_weights,
decimation_errors, edge_deviations, block_neighbours, block_strides, edge_strides).

The meshes are checked combinatorially (they tile the block, wind counter-clockwise, draw each
edge with exactly its edge stride's posts and leave no T-junction inside, so neighbouring blocks
that give their shared edge one stride meet watertight; so do blocks cut short, as the clamp
draws them), the error of a decimated block against analytic surfaces (zero on a plane, the
bump's height on a bump) and against dense sampling of real Alps posts (the exact overlay error;
with stitched edges, within the full-edge error plus the edge's deviation), and on the GPU, a
frame of the Alps drawn with decimation against the same frame without: fewer triangles, no
holes, and a screen error against the full-resolution surface no more than the pixel bound above
the undecimated frame's (bench/render.py's measure).
"""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

import numpy as np
import pytest

from client.render.clipmap_layer import (BLOCK, DECIMATION_STRIDES, SHAPE_TRIANGLES, VARIANTS, block_grid,
                                         block_strides, clamped_triangles, decimated_grid, decimation_errors,
                                         grid_weights)
from sortie.errors import InvalidArgument

STRIDES = (1, *DECIMATION_STRIDES)


def _xy(tris: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    verts = block_grid()[0][:, ::-1].astype(np.float64)  # (x, y) = (column, row)
    return verts[tris[:, 0]], verts[tris[:, 1]], verts[tris[:, 2]]


@pytest.mark.parametrize("stride", STRIDES)
def test_decimated_grid_tiles_the_block_counter_clockwise(stride):
    tris = decimated_grid(stride)
    a, b, c = _xy(tris)
    area = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
    assert area.min() > 0  # counter-clockwise seen from above, none degenerate
    assert area.sum() == pytest.approx(BLOCK * BLOCK, abs=1e-9)


@pytest.mark.parametrize("stride", STRIDES)
def test_decimated_grid_keeps_every_edge_post_and_has_no_t_junction(stride):
    """Each directed edge appears once; an edge used once (undirected) is on the block's outline and one
    cell long; the others are used twice, in opposite directions; no vertex lies inside another's edge."""
    tris = decimated_grid(stride)
    directed = Counter()
    for t in tris:
        for i in range(3):
            directed[(int(t[i]), int(t[(i + 1) % 3]))] += 1
    assert max(directed.values()) == 1
    verts = block_grid()[0]  # (row, column)
    outline = 0
    for (p, q) in directed:
        if (q, p) in directed:
            continue
        (r0, c0), (r1, c1) = verts[p], verts[q]
        assert (r0 == r1 and r0 in (0, BLOCK)) or (c0 == c1 and c0 in (0, BLOCK)), (verts[p], verts[q])
        assert abs(int(r1) - int(r0)) + abs(int(c1) - int(c0)) == 1  # every post of the edge is a vertex
        outline += 1
    assert outline == 4 * BLOCK
    used = np.unique(tris)
    rc = verts[used]
    on_edge = (rc[:, 0] % BLOCK == 0) | (rc[:, 1] % BLOCK == 0)
    assert np.all(on_edge | ((rc[:, 0] % stride == 0) & (rc[:, 1] % stride == 0)))
    # No T-junction: no used vertex strictly inside any triangle edge.
    xy = rc[:, ::-1].astype(np.float64)
    for p, q in directed:
        a, b = verts[p][::-1].astype(np.float64), verts[q][::-1].astype(np.float64)
        d = b - a
        cross = d[0] * (xy[:, 1] - a[1]) - d[1] * (xy[:, 0] - a[0])
        along = ((xy - a) @ d) / (d @ d)
        assert not np.any((np.abs(cross) < 1e-12) & (along > 1e-12) & (along < 1 - 1e-12)), (verts[p], verts[q])


@pytest.mark.parametrize("stride", STRIDES)
def test_clamped_meshes_tile_a_cut_short_block_watertight(stride):
    """A block a ring's edge cuts to h x w cells draws the clamped mesh (clamped_triangles): for every
    shape, its triangles wind counter-clockwise or stand upright (no area in plan, none folded over),
    their areas sum to the block's, and its outline is every post of the h x w block's four edges,
    each directed edge inside used once each way: it meets any neighbour watertight."""
    verts = block_grid()[0]  # (row, column)
    for h in range(1, BLOCK + 1):
        for w in range(1, BLOCK + 1):
            tris = clamped_triangles(stride, h, w)
            a, b, c = _xy(tris)
            area = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
            assert area.min() >= -1e-12 and area.sum() == pytest.approx(h * w), (h, w)
            rc = verts[np.unique(tris)]
            assert rc[:, 0].max() <= h and rc[:, 1].max() <= w
            directed = Counter((int(t[i]), int(t[(i + 1) % 3])) for t in tris for i in range(3))
            assert max(directed.values()) == 1, (h, w)
            outline = []
            for p, q in directed:
                if (q, p) in directed:
                    continue
                (r0, c0), (r1, c1) = verts[p], verts[q]
                assert (r0 == r1 and r0 in (0, h)) or (c0 == c1 and c0 in (0, w)), (h, w, verts[p], verts[q])
                assert abs(int(r1) - int(r0)) + abs(int(c1) - int(c0)) == 1
                outline.append((p, q))
            assert len(outline) == 2 * (h + w), (h, w)
            assert SHAPE_TRIANGLES[h, w, STRIDES.index(stride)] == len(tris)


def test_cut_short_blocks_errors_are_the_largest_distance_between_the_clamped_surfaces(hgt_alps):
    """decimation_errors of blocks cut short, against dense sampling of both clamped surfaces (their
    triangles with area in plan: the upright ones lie between the two) over real Alps posts."""
    from terrain.dem import read_dem

    h_m = np.asarray(read_dem(hgt_alps).heights, np.float64)
    n = BLOCK + 1
    rng = np.random.default_rng(11)
    verts = block_grid()[0][:, ::-1].astype(np.float64)
    for h, w in ((BLOCK, 5), (3, BLOCK), (6, 6), (1, BLOCK), (BLOCK, 2), (7, 3)):
        gi, gj = np.linspace(0.0, h, 32 * h + 1), np.linspace(0.0, w, 32 * w + 1)
        pts = np.stack(np.meshgrid(gj, gi), -1).reshape(-1, 2)
        for _ in range(3):
            i0, j0 = rng.integers(0, h_m.shape[0] - n, 2)
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            pos = np.stack([90.0 * j, 90.0 * i, h_m[i0:i0 + n, j0:j0 + n]], -1)
            err = decimation_errors(np.array([[0, 0, h, w]], np.int32), SimpleNamespace(pos_ecef=pos), n)[0]
            zf = pos.reshape(-1, 3)

            def flat(t):
                a, b, c = verts[t[:, 0]], verts[t[:, 1]], verts[t[:, 2]]
                return t[np.abs((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0]) > 1e-12]

            full = _surface_at(flat(clamped_triangles(1, h, w)), zf, pts)
            for s_i, s in enumerate(DECIMATION_STRIDES):
                dense = np.linalg.norm(full - _surface_at(flat(clamped_triangles(s, h, w)), zf, pts), axis=1).max()
                assert dense <= err[s_i] + 1e-9 and err[s_i] <= 1.02 * dense + 1e-9, (h, w, s, dense, err[s_i])


def test_cut_short_blocks_take_the_fewest_triangles_within_the_bound():
    """A cut-short block does not take a coarser stride that draws more triangles than a finer one
    within the bound (a 1-cell-wide block draws 16 triangles at every stride: it keeps stride 1 on a
    tie only if the coarser are out of bounds), and never morphs."""
    coarse, fine = DECIMATION_STRIDES
    blk = np.array([[0, 0, BLOCK, BLOCK], [0, 0, BLOCK, 1], [0, 0, 3, 3], [0, 0, BLOCK, 6]], np.int32)
    tri = SHAPE_TRIANGLES[blk[:, 2] - blk[:, 0], blk[:, 3] - blk[:, 1]]
    lo = np.tile([[0.0, 1000.0, 0.0]], (4, 1))
    err = np.array([[0.0, 0.0]] * 4)
    strides, morph = block_strides(err, lo, lo + 10.0, np.zeros(3), 1000.0, 1.0, tri)
    want = [coarse]
    for t in tri[1:]:
        col = min(range(3), key=lambda c: (t[c], -STRIDES[c]))
        want.append(STRIDES[col])
    assert strides.tolist() == want and strides[1] == coarse  # the tie goes to the coarser
    assert np.all(morph == 0.0)
    err_fine_only = np.array([[5.0, 0.5]] * 4)  # the coarse stride out of bounds at 1 km (5 px)
    strides, morph = block_strides(err_fine_only, lo, lo + 10.0, np.zeros(3), 1000.0, 1.0, tri)
    assert strides[0] == fine and all(s in (1, fine) for s in strides)
    assert np.all(morph[1:] == 0.0)


def test_decimated_grid_counts_and_bad_stride():
    assert len(decimated_grid(1)) == 2 * BLOCK * BLOCK
    counts = [len(decimated_grid(s)) for s in sorted(STRIDES)]
    assert counts == sorted(counts, reverse=True) and counts[-1] <= counts[0] / 4
    with pytest.raises(ValueError):
        decimated_grid(3)
    with pytest.raises(ValueError):
        decimated_grid(BLOCK)  # one cell: its four sides would all carry every post


@pytest.mark.parametrize("stride", STRIDES)
def test_grid_weights_reproduce_every_post(stride):
    """The weights are barycentric (non-negative, summing to 1) over a triangle's corners and put every
    grid vertex back where it is: an affine function is reproduced exactly; a drawn vertex takes itself."""
    tris = decimated_grid(stride)
    idx, w = grid_weights(tris)
    assert np.all(w >= -1e-12) and np.allclose(w.sum(1), 1.0)
    verts = block_grid()[0].astype(np.float64)
    assert np.allclose((verts[idx] * w[..., None]).sum(1), verts, atol=1e-12)
    for v in np.unique(tris):
        assert np.isclose(w[v][idx[v] == v].sum(), 1.0)


def _level(heights: np.ndarray):
    """A level's storage stand-in: (n, n) posts 90 m apart in a local plane, z = heights (ECEF-like
    metres; decimation_errors only reads pos_ecef)."""
    n = heights.shape[0]
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pos = np.stack([90.0 * j, 90.0 * i, heights], -1).astype(np.float64)
    return SimpleNamespace(pos_ecef=pos)


def test_decimation_errors_on_a_plane_a_bump_and_a_partial_block():
    n = 4 * BLOCK + 1
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    plane = _level(1000.0 + 3.0 * i - 7.5 * j)
    blk = np.array([[0, 0, BLOCK, BLOCK], [BLOCK, 2 * BLOCK, 2 * BLOCK, 3 * BLOCK],
                    [0, 3 * BLOCK, BLOCK, 3 * BLOCK + 5]], np.int32)  # the last: 5 cells wide (a ring's edge)
    err = decimation_errors(blk, plane, n)
    assert err.shape == (3, len(DECIMATION_STRIDES))
    assert np.all(err < 1e-9)  # the cut-short block too: clamped, its meshes lie on the plane
    # A bump of 40 m at an odd post inside the first block: every stride skips that post.
    bumped = 1000.0 + np.zeros((n, n))
    bumped[BLOCK // 2 + 1, BLOCK // 2 + 1] += 40.0
    err = decimation_errors(blk[:1], _level(bumped), n)
    assert err[0] == pytest.approx(40.0, abs=1e-9)
    # A bump at a post every stride draws: the post is kept, and the drawn triangles around it pull its
    # flat neighbours up, the nearest (one cell along a triangle's edge) by 40 (s - 1) / s; between
    # posts the two surfaces can be farther apart, never more than the bump.
    kept = 1000.0 + np.zeros((n, n))
    s = max(DECIMATION_STRIDES)
    kept[s, s] += 40.0
    err = decimation_errors(blk[:1], _level(kept), n)[0]
    assert np.all(err >= [40.0 * (st - 1) / st - 1e-9 for st in DECIMATION_STRIDES]) and np.all(err <= 40.0 + 1e-9)


def _surface_at(tris: np.ndarray, z: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """(P, 3) values at points (P, 2) (x = column, y = row) of the piecewise-linear surface through
    the grid values z (V, 3) on triangles ``tris``: a plain loop over triangles, for reference."""
    verts = block_grid()[0][:, ::-1].astype(np.float64)
    out = np.full((len(pts), 3), np.nan)
    for t in tris:
        a, b, c = verts[t]
        m = np.array([[b[0] - a[0], c[0] - a[0]], [b[1] - a[1], c[1] - a[1]]])
        uv = np.linalg.solve(m, (pts - a).T).T
        inside = (uv >= -1e-12).all(1) & (uv.sum(1) <= 1 + 1e-12)
        out[inside] = ((1 - uv[inside].sum(1))[:, None] * z[t[0]] + uv[inside, :1] * z[t[1]]
                       + uv[inside, 1:] * z[t[2]])
    return out


def test_decimation_errors_are_the_largest_distance_between_the_surfaces(hgt_alps):
    """Against dense sampling (1/32 of a cell) of both piecewise-linear surfaces over real Alps posts:
    never less than any sample's distance (the overlay's vertices hold the maximum), and within 2 %
    of the densest sample's. At posts alone the error is smaller on some blocks: the largest distance
    lies where a decimated edge crosses a fine one."""
    from terrain.dem import read_dem

    h = np.asarray(read_dem(hgt_alps).heights, np.float64)
    n = BLOCK + 1
    g = np.linspace(0.0, BLOCK, 32 * BLOCK + 1)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    rng = np.random.default_rng(5)
    beyond_posts = 0
    for _ in range(12):
        i0, j0 = rng.integers(0, h.shape[0] - n, 2)
        z = h[i0:i0 + n, j0:j0 + n]
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        pos = np.stack([90.0 * j, 90.0 * i, z], -1)
        err = decimation_errors(np.array([[0, 0, BLOCK, BLOCK]], np.int32), SimpleNamespace(pos_ecef=pos), n)[0]
        zf = pos.reshape(-1, 3)
        full = _surface_at(decimated_grid(1), zf, pts)
        for s_i, s in enumerate(DECIMATION_STRIDES):
            dense = np.linalg.norm(full - _surface_at(decimated_grid(s), zf, pts), axis=1).max()
            assert dense <= err[s_i] + 1e-9 and err[s_i] <= 1.02 * dense + 1e-9, (s, dense, err[s_i])
            idx, w = grid_weights(decimated_grid(s))
            at_posts = np.linalg.norm(zf - (zf[idx] * w[..., None]).sum(1), axis=1).max()
            beyond_posts += at_posts < 0.999 * err[s_i]
    assert beyond_posts > 0


def test_block_strides_take_the_coarsest_within_the_pixel_bound():
    coarse, fine = DECIMATION_STRIDES
    # Errors (m) for strides (coarse, fine); boxes at 1, 10, 100 and 15 km straight ahead, and one
    # holding the camera.
    err = np.tile(np.array([[10.0, 1.0]]), (5, 1))
    lo = np.array([[0.0, 1_000.0, 0.0], [0.0, 10_000.0, 0.0], [0.0, 100_000.0, 0.0], [0.0, 15_000.0, 0.0],
                   [-5.0, -5.0, -5.0]])
    hi = lo + 10.0
    strides, morph = block_strides(err, lo, hi, np.zeros(3), focal_px=1000.0, pixel_error=1.0)
    # 1 km: 10 px and 1 px; 10 km: 1 px and 0.1 px; 100 km: 0.1 px; 15 km: 0.67 and 0.067 px.
    assert strides.tolist() == [fine, coarse, coarse, coarse, 1]
    # Morph towards the next stride: at 1 km the coarse stride's 10 px is past 2 px (0); the
    # coarsest stride has none; the camera's block (both errors infinite in pixels) none.
    assert morph.tolist() == [0.0, 0.0, 0.0, 0.0, 0.0]
    strides, morph = block_strides(err, lo, hi, np.zeros(3), focal_px=1000.0, pixel_error=6.0)
    # 1 km: the coarse stride's 10 px is within 2 x 6: morph 2 - 10 / 6.
    assert strides[0] == fine and morph[0] == pytest.approx(2.0 - 10.0 / 6.0, rel=1e-6)
    # A finer stride out of bounds keeps a block off the coarser one, whatever the coarser's error.
    odd = np.array([[0.5, 50.0]])
    strides, morph = block_strides(odd, lo[:1], hi[:1], np.zeros(3), 1000.0, 1.0)
    assert strides.tolist() == [1] and morph.tolist() == [0.0]
    assert block_strides(np.full((5, 2), np.inf), lo, hi, np.zeros(3), 1000.0, 100.0)[0].tolist() == [1] * 5


def test_the_morph_moves_a_post_by_at_most_the_pixel_bound():
    """morph x r <= pixel_error for every error r (px) of the next stride: the bound holds while morphing."""
    r = np.linspace(0.0, 10.0, 10_001)
    lo = np.zeros((len(r), 3)) + [0.0, 1000.0, 0.0]
    err = np.stack([r, r / 10.0], -1)  # metres = pixels at 1 km with a 1000 px focal length; the fine stride always holds
    strides, morph = block_strides(err, lo, lo + 1e-9, np.zeros(3), 1000.0, 2.0)
    at_fine = strides == DECIMATION_STRIDES[1]
    assert np.all(morph[at_fine] * r[at_fine] <= 2.0 + 1e-6)
    assert np.all(np.diff(morph[at_fine]) <= 0)  # rises as the error falls
    assert morph[at_fine][0] == pytest.approx(1.0, abs=1e-3) and morph[at_fine][-1] == 0.0


@pytest.mark.parametrize("stride", [1, *DECIMATION_STRIDES[1:]])
def test_morph_targets_are_the_next_stride_mesh(stride):
    from client.render.clipmap_layer import morph_targets

    order = sorted(STRIDES)
    nxt = order[order.index(stride) + 1]
    t = morph_targets(stride)
    idx, w = grid_weights(decimated_grid(nxt))
    kept = np.zeros(len(idx), bool)
    kept[np.unique(decimated_grid(nxt))] = True
    got = t["m"][..., 0] * (BLOCK + 1) + t["m"][..., 1]
    assert np.array_equal(got[~kept], idx[~kept]) and np.allclose(t["w"][~kept], w[~kept], atol=1e-7)
    assert np.all(t["w"][kept] == [1.0, 0.0, 0.0]) and np.all(got[kept] == np.arange(len(idx))[kept, None])
    assert np.all(t["w"][~kept].max(axis=1) < 1.0)  # every dropped post lies inside or on an edge, not at a corner


def test_layer_rejects_a_bad_pixel_error(hgt_alps):
    from client.render.clipmap_layer import clipmap_factory
    from client.render.renderer import Renderer
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(hgt_alps)])
    for bad in (0.0, -1.0, float("nan"), 1e9, "1", True):
        with pytest.raises(InvalidArgument, match="pixel_error"):
            with Renderer(terrain, 32, 18, terrain_layer_factory=clipmap_factory(terrain, pixel_error=bad)):
                pass


def test_decimated_frame_has_no_holes_and_stays_within_the_pixel_bound(hgt_alps):
    """One Alps frame (960 x 540, 60 degrees, 2000 m above the ground, test mode) without and with
    decimation at 1 px: fewer triangles, some blocks decimated, no holes, and the screen error against
    the full-resolution surface (bench/render.py's per-pixel measure) at p99 within 1 px of the
    undecimated frame's, the median within 0.1 px."""
    from bench.render import FLAT_SKY_RGB, error_summary, measure_frame
    from client.render.camera import Camera
    from client.render.clipmap_layer import clipmap_factory
    from client.render.renderer import Renderer
    from client.render.terrain_mesh import lattice_for
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(hgt_alps)])
    lat, lon = 47.15, 9.25
    ground = float(terrain.heights(np.array([lat]), np.array([lon])).height_msl_m[0])
    camera = Camera.from_geodetic(lat, lon, ground + 2000.0, 45.0, -10.0, fov_x_deg=60.0)
    lattice = lattice_for(terrain.describe(), lat, lon)
    got = {}
    for pixel_error in (None, 1.0):
        factory = clipmap_factory(terrain, levels=6, n=127, budget=10**7, pixel_error=pixel_error)
        with Renderer(terrain, 960, 540, terrain_layer_factory=factory, flat_sky_rgb=FLAT_SKY_RGB) as r:
            r.render(camera)
            image = r.render(camera)
            layer = r.terrain_layer
            strides = [d.strides for d in layer.draws if d.strides is not None]
            stitched = sum(int((np.array([VARIANTS[v][1] for v in d.variants]) > 1).any(1).sum())
                           for d in layer.draws if d.variants is not None)
            got[pixel_error] = (layer.triangles, strides, measure_frame(r, camera, image, terrain, lattice), stitched)
    tris0, _, frame0, _ = got[None]
    tris1, strides, frame1, stitched = got[1.0]
    decimated = int(sum((s > 1).sum() for s in strides))
    print(f"\ntriangles {tris0} -> {tris1}, {decimated} blocks decimated, {stitched} with stitched edges")
    assert decimated > 0 and stitched > 0 and tris1 < 0.9 * tris0
    assert frame0.holes_px == 0 and frame1.holes_px == 0
    e0, e1 = error_summary([frame0]), error_summary([frame1])
    print(f"screen error p50/p99 px: {e0['median']:.3f}/{e0['p99']:.2f} -> {e1['median']:.3f}/{e1['p99']:.2f}")
    assert e1["p99"] <= e0["p99"] + 1.0
    assert e1["median"] <= e0["median"] + 0.1


def test_the_vertex_shader_morphs_dropped_posts_onto_the_next_stride_mesh(hgt_alps):
    """Transform feedback of the layer's vertex shader over whole blocks of a drawn Alps frame: with
    morph 0 every vertex is the level's own surface; with morph 1 each vertex is the barycentric
    combination (morph_targets) of the morph-0 vertices of its triangle in the next stride's mesh,
    to float32 rounding; posts that mesh keeps do not move."""
    import moderngl

    from client.render.camera import Camera
    from client.render.clipmap_layer import VERTEX_SHADER, clipmap_factory, morph_targets, shader_variant
    from client.render.renderer import Renderer
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(hgt_alps)])
    camera = Camera.from_geodetic(47.15, 9.25, 4000.0, 45.0, -10.0, fov_x_deg=60.0)
    with Renderer(terrain, 96, 54, terrain_layer_factory=clipmap_factory(terrain, levels=5, n=63, budget=10**7,
                                                                          pixel_error=1.0)) as r:
        r.render(camera)
        layer, ctx = r.terrain_layer, r.ctx
        with ctx:
            prog = ctx.program(vertex_shader=shader_variant(VERTEX_SHADER, False), varyings=["v_world"])
            grid = ctx.buffer(block_grid()[0].tobytes())
            checked = 0
            drawn = {d.k for d in layer.draws}
            for d in layer.draws:
                full = d.blocks[((d.blocks[:, 2] - d.blocks[:, 0]) == BLOCK) & ((d.blocks[:, 3] - d.blocks[:, 1]) == BLOCK)]
                if len(full) == 0:
                    continue
                layer.set_uniforms(prog, {"u_view": camera.view_matrix(layer.origin).T.astype("f4").tobytes(),
                                          "u_projection": camera.projection(96, 54).T.astype("f4").tobytes(),
                                          **layer.level_uniforms(d, d.k + 1 in drawn)})
                layer._tex[d.k][0].use(0)
                if d.k + 1 in drawn:
                    layer._tex[d.k + 1][0].use(1)
                rel = full[:3] - np.array([d.region.i0, d.region.j0, d.region.i0, d.region.j0], np.int32)
                for stride in (1, *DECIMATION_STRIDES[1:]):
                    targets = morph_targets(stride)
                    tbuf = ctx.buffer(targets.tobytes())
                    out = {}
                    for morph in (0.0, 1.0):
                        rec = np.zeros(len(rel), dtype=[("b", "<i4", 4), ("m", "<f4")])
                        rec["b"], rec["m"] = rel, morph
                        ibuf = ctx.buffer(rec.tobytes())
                        obuf = ctx.buffer(reserve=len(rel) * len(targets) * 12)
                        vao = ctx.vertex_array(prog, [(grid, "2i", "in_cell"), (ibuf, "4i 1f/i", "in_block", "in_morph"),
                                                      (tbuf, "2i 2i 2i 3f", "in_m0", "in_m1", "in_m2", "in_mw")])
                        vao.transform(obuf, mode=moderngl.POINTS, vertices=len(targets), instances=len(rel))
                        out[morph] = np.frombuffer(obuf.read(), np.float32).reshape(len(rel), len(targets), 3).astype(np.float64)
                        for obj in (vao, ibuf, obuf):
                            obj.release()
                    tbuf.release()
                    idx = targets["m"][..., 0] * (BLOCK + 1) + targets["m"][..., 1]
                    want = (out[0.0][:, idx] * targets["w"][None, :, :, None].astype(np.float64)).sum(2)
                    scale = np.abs(out[0.0]).max()
                    assert np.abs(out[1.0] - want).max() <= 16 * 2.0 ** -24 * scale + 1e-4, (d.k, stride)
                    kept = targets["w"].max(axis=1) == 1.0
                    assert np.array_equal(out[1.0][:, kept], out[0.0][:, kept])
                    assert np.abs(out[1.0][:, ~kept] - out[0.0][:, ~kept]).max() > 0.0  # relief: they do move
                    checked += 1
            grid.release()
            prog.release()
    assert checked >= 4


# -- stitched edges -------------------------------------------------------------------------------

def _outline_and_pairs(tris: np.ndarray):
    directed = Counter((int(t[i]), int(t[(i + 1) % 3])) for t in tris for i in range(3))
    return directed, [(p, q) for p, q in directed if (q, p) not in directed]


@pytest.mark.parametrize("stride", DECIMATION_STRIDES)
def test_stitched_meshes_tile_the_block_with_each_edge_at_its_stride(stride):
    """Every (stride, edges) mesh the layer draws (VARIANTS): counter-clockwise, tiling the block,
    each inner directed edge used once each way, and its outline on side X made of segments of
    exactly edges[X] cells between the posts at the multiples of edges[X]: two blocks that give their
    shared edge one stride meet watertight. Its triangle count is VARIANT_TRIANGLES'."""
    from client.render.clipmap_layer import VARIANT_TRIANGLES

    verts = block_grid()[0]
    for v, (s, edges) in enumerate(VARIANTS):
        if s != stride:
            continue
        tris = decimated_grid(s, BLOCK, edges)
        a, b, c = _xy(tris)
        area = 0.5 * ((b - a)[:, 0] * (c - a)[:, 1] - (b - a)[:, 1] * (c - a)[:, 0])
        assert area.min() > 0 and area.sum() == pytest.approx(BLOCK * BLOCK)
        directed, outline = _outline_and_pairs(tris)
        assert max(directed.values()) == 1
        seen = Counter()
        for p, q in outline:
            (r0, c0), (r1, c1) = verts[p], verts[q]
            side = (0 if r0 == r1 == 0 else 2 if r0 == r1 == BLOCK else 1 if c0 == c1 == BLOCK
                    else 3 if c0 == c1 == 0 else None)
            assert side is not None, (edges, verts[p], verts[q])
            e = edges[side]
            assert abs(int(r1) - int(r0)) + abs(int(c1) - int(c0)) == e
            assert (r0 % e, c0 % e, r1 % e, c1 % e) == (0, 0, 0, 0)
            seen[side] += 1
        assert [seen[x] for x in range(4)] == [BLOCK // e for e in edges]
        assert VARIANT_TRIANGLES[v] == len(tris)
    with pytest.raises(ValueError):
        decimated_grid(stride, BLOCK, (3, 1, 1, 1))
    with pytest.raises(ValueError):
        decimated_grid(stride, BLOCK, (1, 1, 2 * BLOCK, 1))
    with pytest.raises(ValueError):
        decimated_grid(1, BLOCK, (2, 1, 1, 1))


def test_stitched_mesh_error_is_within_the_stride_error_plus_the_edge_deviation(hgt_alps):
    """The bound edge_strides relies on: a mesh with coarser edges parts from the full surface by at
    most the full-edge mesh's error (decimation_errors) plus the largest deviation of its coarsened
    edges (edge_deviations), against dense sampling of both surfaces over real Alps posts. The
    deviations equal a brute-force line fit."""
    from client.render.clipmap_layer import EDGE_STRIDES, edge_deviations
    from terrain.dem import read_dem

    h_m = np.asarray(read_dem(hgt_alps).heights, np.float64)
    n = BLOCK + 1
    g = np.linspace(0.0, BLOCK, 16 * BLOCK + 1)
    pts = np.stack(np.meshgrid(g, g), -1).reshape(-1, 2)
    rng = np.random.default_rng(17)
    blk = np.array([[0, 0, BLOCK, BLOCK]], np.int32)
    for _ in range(6):
        i0, j0 = rng.integers(0, h_m.shape[0] - n, 2)
        i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
        pos = np.stack([90.0 * j, 90.0 * i, h_m[i0:i0 + n, j0:j0 + n]], -1)
        level = SimpleNamespace(pos_ecef=pos)
        err = decimation_errors(blk, level, n)[0]
        dev = edge_deviations(blk, level, n)[0]  # (north, east) x strides
        def brute(line, e):  # the largest distance of the posts from their edge at every e-th post
            t = np.arange(BLOCK + 1)
            t0 = t - t % e
            f = (t % e / e)[:, None]
            return np.linalg.norm(line - ((1 - f) * line[t0] + f * line[np.minimum(t0 + e, BLOCK)]), axis=1).max()

        sides = (pos[0, :, :], pos[:, BLOCK, :], pos[BLOCK, :, :], pos[:, 0, :])  # south, east, north, west
        for s_i, e in enumerate(EDGE_STRIDES):
            assert dev[0, s_i] == pytest.approx(brute(sides[2], e), abs=1e-9)
            assert dev[1, s_i] == pytest.approx(brute(sides[1], e), abs=1e-9)
        zf = pos.reshape(-1, 3)
        full = _surface_at(decimated_grid(1), zf, pts)
        for s_i, s in enumerate(DECIMATION_STRIDES):
            combos = [(s, s, s, s), (s, 1, s, 1), (1, s, 1, s), (max(s // 2, 1), s, 1, s)]
            if 2 * s == BLOCK:  # a two-cell block's edges can run corner to corner
                combos += [(BLOCK,) * 4, (BLOCK, 1, s, BLOCK)]
            for edges in combos:
                tris = decimated_grid(s, BLOCK, edges)
                dense = np.linalg.norm(full - _surface_at(tris, zf, pts), axis=1).max()
                side_dev = [brute(line, e) if e > 1 else 0.0 for line, e in zip(sides, edges)]
                assert dense <= err[s_i] + max(side_dev) + 1e-9, (s, edges, dense, err[s_i], side_dev)


def test_neighbours_and_edge_strides_are_shared_and_within_the_bound():
    """block_neighbours against a brute-force search over a real ring's blocks; edge_strides gives a
    shared edge one stride on both sides, dividing both blocks' strides, with each block's own error
    plus the edge's deviation within the bound; 1 on every edge without a whole neighbour."""
    from client.render.clipmap import Rect, blocks, ring_rects
    from client.render.clipmap_layer import EDGE_STRIDES, block_neighbours, edge_choices, edge_strides

    blk = blocks(ring_rects(Rect(-7, 1001, 247, 1255), Rect(57, 1065, 183, 1191)), BLOCK)
    nb = block_neighbours(blk)
    whole = ((blk[:, 2] - blk[:, 0]) == BLOCK) & ((blk[:, 3] - blk[:, 1]) == BLOCK)
    for a in range(len(blk)):
        for side, (di, dj) in enumerate(((BLOCK, 0), (0, BLOCK))):
            want = [b for b in range(len(blk)) if whole[a] and whole[b]
                    and blk[b, 0] == blk[a, 0] + di and blk[b, 1] == blk[a, 1] + dj]
            assert nb[a, side] == (want[0] if want else -1)
    assert (nb >= 0).sum() > len(blk)  # most whole blocks have neighbours
    rng = np.random.default_rng(3)
    m = len(blk)
    strides = rng.choice([1, *DECIMATION_STRIDES], m).astype(np.int32)
    err = rng.uniform(0.0, 2.0, (m, len(DECIMATION_STRIDES)))
    dev = rng.uniform(0.0, 2.0, (m, 2, len(EDGE_STRIDES)))
    dist = np.full(m, 1000.0)
    edges = edge_strides(strides, err, dev, nb, dist, 1000.0, 3.0)  # px = metres at 1 km
    cols = {s: i for i, s in enumerate(DECIMATION_STRIDES)}
    own = np.array([err[i, cols[s]] if s > 1 else 0.0 for i, s in enumerate(strides)])
    cols = {s: i for i, s in enumerate(EDGE_STRIDES)}
    for a in range(m):
        for side, (mine, theirs) in enumerate(((2, 0), (1, 3))):
            b = nb[a, side]
            if b < 0:
                continue
            e = edges[a, mine]
            assert edges[b, theirs] == e
            assert e in edge_choices(strides[a]) and e in edge_choices(strides[b])
            if e > 1:
                d = dev[a, side, cols[e]]
                assert own[a] + d <= 3.0 and own[b] + d <= 3.0
    has = np.zeros((m, 4), bool)
    has[:, 2], has[:, 1] = nb[:, 0] >= 0, nb[:, 1] >= 0
    has[nb[nb[:, 0] >= 0, 0], 0] = True
    has[nb[nb[:, 1] >= 0, 1], 3] = True
    assert np.all(edges[~has] == 1) and (edges > 1).any() and (edges == BLOCK).any()
    # Where a corner-to-corner edge would sag too far (MAX_CORNER_EDGE_SAG_M), the next stride down.
    capped = edge_strides(strides, err, dev, nb, dist, 1000.0, 3.0, corner_to_corner=False)
    assert not (capped == BLOCK).any() and np.array_equal(capped[edges < BLOCK], edges[edges < BLOCK])


def test_border_edges_take_the_coarser_levels_posts_and_spare_their_border_triangles():
    """On the drawn border of a level (with the coarser level drawn), a whole decimated block that
    starts on an even post draws its border side with the even posts alone (edge stride 2): the
    morph puts the odd ones halfway between them. Only on even border rows and columns; the border
    triangles (border_segments) are left out exactly where every cell of a segment is so drawn."""
    from client.render.clipmap import Rect, blocks, ring_rects
    from client.render.clipmap_layer import border_edges, border_segments, border_segments_left

    rng = np.random.default_rng(23)
    for region in (Rect(-8, 1000, 246, 1254), Rect(-7, 1001, 247, 1255), Rect(2, 4, 256, 258)):
        hole = Rect(region.i0 + 63, region.j0 + 63, region.i0 + 190, region.j0 + 190)
        blk = blocks(ring_rects(region, hole), BLOCK)
        strides = rng.choice([1, *DECIMATION_STRIDES], len(blk)).astype(np.int32)
        inner = np.where(rng.random((len(blk), 4)) < 0.5, 2, 1).astype(np.int32)  # stitched inside
        for side, (c, at) in enumerate(((0, region.i0), (3, region.j1), (2, region.i1), (1, region.j0))):
            inner[blk[:, c] == at, side] = 1  # nothing beyond the border to stitch with
        edges, spared = border_edges(blk, region, strides, inner)
        whole = ((blk[:, 2] - blk[:, 0]) == BLOCK) & ((blk[:, 3] - blk[:, 1]) == BLOCK)
        for b in range(len(blk)):
            i0, j0, i1, j1 = blk[b]
            ok = whole[b] and strides[b] >= 2
            want = [ok and i0 == region.i0 and i0 % 2 == 0 and j0 % 2 == 0,
                    ok and j1 == region.j1 and j1 % 2 == 0 and i0 % 2 == 0,
                    ok and i1 == region.i1 and i1 % 2 == 0 and j0 % 2 == 0,
                    ok and j0 == region.j0 and j0 % 2 == 0 and i0 % 2 == 0]
            assert np.all(edges[b][np.array(want)] == 2) and np.array_equal(edges[b][~np.array(want)],
                                                                             inner[b][~np.array(want)])
        if region.i0 % 2 == 0:
            assert (edges == 2).any()
        rows, cols = border_segments(region)
        left = border_segments_left(region, blk, spared)
        for segments, kept, along in ((rows, left[0], "row"), (cols, left[1], "col")):
            for seg in segments:
                i0, j0, i1, j1 = seg + np.array([region.i0, region.j0, region.i0, region.j0])
                if along == "row":
                    side = 0 if i0 == region.i0 else 2
                    cells = range(j0, j1)
                    spans = [(blk[b, 1], blk[b, 3]) for b in range(len(blk))
                             if edges[b, side] == 2 and blk[b, side] == (region.i0 if side == 0 else region.i1)]
                else:
                    side = 3 if j0 == region.j0 else 1
                    cells = range(i0, i1)
                    spans = [(blk[b, 0], blk[b, 2]) for b in range(len(blk))
                             if edges[b, side] == 2 and blk[b, 4 - side] == (region.j0 if side == 3 else region.j1)]
                spared = all(any(a <= c < z for a, z in spans) for c in cells)
                assert spared != any(np.array_equal(seg, k) for k in kept), (region, seg)


def test_compiled_frame_passes_equal_their_vectorised_definitions():
    """block_strides, edge_strides and visible_blocks run every frame for every level as compiled
    passes (20 ms -> 2 ms a frame's plan at L 6, n 255); the numpy compositions they replaced,
    kept here, give the same answers on a real ring's blocks with random errors, cameras and
    cut-short blocks."""
    from client.render.clipmap import Rect, blocks, ring_rects
    from client.render.clipmap_layer import (EDGE_STRIDES, block_neighbours, block_triangles, edge_choices,
                                             edge_strides, visible_blocks)

    def strides_np(err_m, lo, hi, cam, focal_px, pixel_error, triangles):
        gap = np.maximum(np.maximum(lo - cam, cam - hi), 0.0)
        px = err_m * focal_px / np.maximum(np.sqrt((gap ** 2).sum(-1)), 1e-9)[:, None]
        strides, morph = np.ones(len(err_m), np.int32), np.zeros(len(err_m), np.float32)
        ok = np.ones(len(err_m), bool)
        oks = np.ones((len(err_m), 1 + len(DECIMATION_STRIDES)), bool)
        for s_i in reversed(range(len(DECIMATION_STRIDES))):
            r = px[:, s_i]
            morph = np.where(ok, np.clip(2.0 - r / pixel_error, 0.0, 1.0), morph)
            ok &= r <= pixel_error
            oks[:, 1 + s_i] = ok
            strides = np.where(ok, DECIMATION_STRIDES[s_i], strides)
        morph = np.where(strides == DECIMATION_STRIDES[0], 0.0, morph).astype(np.float32)
        cut = triangles[:, 0] != 2 * BLOCK * BLOCK
        order = np.array([*range(1, 1 + len(DECIMATION_STRIDES)), 0])
        cost = np.where(oks[cut], triangles[cut], np.iinfo(np.int64).max)[:, order]
        strides[cut] = np.array([1, *DECIMATION_STRIDES], np.int32)[order[np.argmin(cost, axis=1)]]
        morph[cut] = 0.0
        return strides, morph

    def edges_np(strides, err_m, dev_m, neighbours, dist, focal_px, pixel_error, corner_to_corner):
        edges = np.ones((len(strides), 4), np.int32)
        px_scale = focal_px / np.maximum(dist, 1e-9)
        own = np.zeros(len(strides))
        for i, s in enumerate(DECIMATION_STRIDES):
            own[strides == s] = err_m[strides == s, i] * px_scale[strides == s]
        allowed = {e: np.isin(strides, [s for s in DECIMATION_STRIDES if e in edge_choices(s)])
                   & (corner_to_corner or e < BLOCK) for e in EDGE_STRIDES}
        for side, (mine, theirs) in enumerate(((2, 0), (1, 3))):
            a = np.flatnonzero(neighbours[:, side] >= 0)
            b = neighbours[a, side]
            e = np.ones(len(a), np.int32)
            for s_i, s in enumerate(EDGE_STRIDES):
                d = dev_m[a, side, s_i]
                ok = ((e == 1) & allowed[s][a] & allowed[s][b] & (own[a] + d * px_scale[a] <= pixel_error)
                      & (own[b] + d * px_scale[b] <= pixel_error))
                e = np.where(ok, s, e)
            edges[a, mine], edges[b, theirs] = e, e
        return edges

    def visible_np(lo, hi, view_proj):
        box = np.stack([np.stack([np.where(k & 1, hi[:, 0], lo[:, 0]), np.where(k & 2, hi[:, 1], lo[:, 1]),
                                  np.where(k & 4, hi[:, 2], lo[:, 2])], -1) for k in range(8)], 1)
        clip = np.einsum("mcj,ij->mci", np.concatenate([box, np.ones((*box.shape[:2], 1))], -1), view_proj)
        x, y, w = clip[..., 0], clip[..., 1], clip[..., 3]
        return ~((x > w).all(1) | (x < -w).all(1) | (y > w).all(1) | (y < -w).all(1) | (w <= 0).all(1))

    rng = np.random.default_rng(41)
    blk = blocks(ring_rects(Rect(-7, 1001, 247, 1255), Rect(57, 1065, 183, 1191)), BLOCK)
    m = len(blk)
    nb, tri = block_neighbours(blk), block_triangles(blk)
    assert (tri[:, 0] != 2 * BLOCK * BLOCK).any()  # cut-short blocks among them
    n_vis = 0
    for trial in range(40):
        lo = rng.uniform(-5e3, 5e3, (m, 3))
        hi = lo + rng.uniform(0.0, 500.0, (m, 3))
        cam = rng.uniform(-6e3, 6e3, 3)
        err = rng.uniform(0.0, 3.0, (m, len(DECIMATION_STRIDES))) * rng.choice([0.1, 1.0, 10.0])
        pixel_error = float(rng.choice([0.5, 2.0]))
        got = block_strides(err, lo, hi, cam, 1000.0, pixel_error, tri)
        want = strides_np(err, lo, hi, cam, 1000.0, pixel_error, tri)
        assert np.array_equal(got[0], want[0]) and np.array_equal(got[1], want[1])
        gap = np.maximum(np.maximum(lo - cam, cam - hi), 0.0)
        dist = np.sqrt((gap ** 2).sum(-1))
        dev = rng.uniform(0.0, 3.0, (m, 2, len(EDGE_STRIDES)))
        for c2c in (True, False):
            assert np.array_equal(edge_strides(got[0], err, dev, nb, dist, 1000.0, pixel_error, c2c),
                                  edges_np(got[0], err, dev, nb, dist, 1000.0, pixel_error, c2c))
        # A camera looking from cam towards a random point, 60 degrees wide.
        f = 1.0 / np.tan(np.radians(30.0))
        fwd = rng.normal(size=3)
        fwd /= np.linalg.norm(fwd)
        right = np.cross(fwd, [0.0, 0.0, 1.0])
        right /= np.linalg.norm(right)
        up = np.cross(right, fwd)
        view = np.eye(4)
        view[:3, :3] = np.stack([right, up, -fwd])
        view[:3, 3] = -view[:3, :3] @ cam
        proj = np.array([[f, 0, 0, 0], [0, f * 16 / 9, 0, 0], [0, 0, 0, 1.0], [0, 0, -1.0, 0]])
        vis = visible_blocks(lo, hi, proj @ view)
        assert np.array_equal(vis, visible_np(lo, hi, proj @ view))
        n_vis += int(vis.sum())
    assert 0 < n_vis < 40 * m  # some blocks in view and some out


def test_pruned_overlay_rows_give_the_errors_of_the_whole_rows():
    """decimation_errors evaluates the overlay rows without their zero-weight terms and without
    the rows that are a post minus itself: bit for bit the errors of every row in full, on the
    blocks of a ring over rough terrain (whole blocks and blocks cut short)."""
    from client.render.clipmap import Rect, blocks, ring_rects
    from client.render.clipmap_layer import _overlay_errors, overlay_rows

    n = 256
    rng = np.random.default_rng(8)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pos = np.stack([90.0 * j + 6.4e6, 90.0 * i, np.cumsum(rng.normal(0, 30.0, (n, n)), 1)], -1)
    blk = blocks(ring_rects(Rect(-7, 1001, 247, 1255), Rect(57, 1065, 183, 1191)), BLOCK)
    got = decimation_errors(blk, SimpleNamespace(pos_ecef=pos), n)
    want = np.empty_like(got)
    for b in range(len(blk)):
        h, w = int(blk[b, 2] - blk[b, 0]), int(blk[b, 3] - blk[b, 1])
        for s_i, s in enumerate(DECIMATION_STRIDES):
            idx, wt = overlay_rows(s, BLOCK, h, w)
            _overlay_errors(pos, blk[b:b + 1].astype(np.int64), n, BLOCK, idx, wt,
                            np.full(len(idx), idx.shape[1], np.int64), want[b:b + 1], s_i)
    assert len({(int(b[2] - b[0]), int(b[3] - b[1])) for b in blk}) > 1 and (got > 0).all()
    assert np.array_equal(got, want)


def test_a_moved_levels_blocks_measured_in_parts_give_the_whole_rings_answers():
    """The plan measures a moved level's blocks in parts on helper threads (by_parts): the
    decimation errors, edge deviations and culling boxes are those of one call over the ring,
    bit for bit, whatever the number of parts (cut-short blocks included)."""
    from client.render.camera import LocalOrigin
    from client.render.clipmap import Rect, blocks, ring_rects
    from client.render.clipmap_layer import PLAN_PART_MIN_BLOCKS, block_bounds, by_parts, edge_deviations

    n = 255
    rng = np.random.default_rng(5)
    i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
    pos = np.stack([90.0 * j + 6.4e6, 90.0 * i, np.cumsum(rng.normal(0, 30.0, (n, n)), 1)], -1)
    level, coarse = SimpleNamespace(pos_ecef=pos), SimpleNamespace(pos_ecef=pos[::-1].copy())
    blk = blocks(ring_rects(Rect(1001, 2003, 1255, 2257), Rect(1065, 2067, 1191, 2193)), BLOCK)
    origin = LocalOrigin(np.array([6.4e6 + 1e4, 1e4, 0.0]))
    assert len(blk) > 4 * PLAN_PART_MIN_BLOCKS and len({(int(b[2] - b[0]), int(b[3] - b[1])) for b in blk}) > 1

    def measure(b):
        return (decimation_errors(b, level, n), edge_deviations(b, level, n),
                *block_bounds(b, level, coarse, n, origin))

    whole = measure(blk)
    for threads in (2, 3, 4):
        parts = by_parts(measure, blk, threads)
        assert len(parts) == len(whole)
        for got, want in zip(parts, whole):
            assert np.array_equal(got, want)
    assert np.array_equal(by_parts(lambda b: decimation_errors(b, level, n), blk, 2), whole[0])  # one array
    small = blk[:PLAN_PART_MIN_BLOCKS]  # too few blocks to split: one call
    assert np.array_equal(by_parts(lambda b: edge_deviations(b, level, n), small, 4), whole[1][:len(small)])


def test_a_moving_clipmaps_measures_reused_for_unchanged_blocks_equal_measuring_all(hgt_alps, monkeypatch):
    """Flying over the Alps, every level's decimation errors, edge deviations and culling boxes,
    as the plan keeps them (blocks whose posts did not change since they were measured reused,
    the others measured anew: remeasure), equal measuring the whole ring afresh at every step, bit
    for bit; and the reuse happens (a finer level's move leaves most of the coarser ring)."""
    from bench.render import update_only
    from client.render import clipmap_layer as cl
    from client.render.camera import Camera
    from client.render.renderer import Renderer
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    measured = []
    whole = cl.by_parts

    def counting(fn, blk, threads=None):
        measured.append(len(blk))
        return whole(fn, blk, threads)

    monkeypatch.setattr(cl, "by_parts", counting)
    terrain = Terrain([read_dem(hgt_alps)])
    factory = cl.clipmap_factory(terrain, levels=5, n=63, budget=10**7, pixel_error=1.0)
    lat, lon, alt = 47.30, 9.30, 2600.0
    with Renderer(terrain, 64, 36, terrain_layer_factory=factory) as r:
        layer = r.terrain_layer
        rings_measured = 0
        for step in range(40):
            # North-east, then a turn east and a climb: moves of every level, some together.
            lat += 0.0012 if step < 25 else 0.0002
            lon += 0.0009 + (0.0015 if step >= 25 else 0.0)
            alt += 0.0 if step < 25 else 60.0
            camera = Camera.from_geodetic(lat, lon, alt, 45.0 if step < 25 else 80.0, -15.0, fov_x_deg=60.0)
            update_only(r, camera)
            before = len(measured)
            with r.ctx:
                drawn = [d.k for d in layer.plan(r._frame(camera))]
            rings_measured += len(measured) - before
            c = layer.clipmap
            for k in drawn:  # (a level not drawn keeps what it had when it was)
                _, errors, deviations, blk = layer._errors[k]
                level = c.levels[k]
                assert np.array_equal(errors, decimation_errors(blk, level, c.n)), (step, k)
                assert np.array_equal(deviations, cl.edge_deviations(blk, level, c.n)), (step, k)
                bkey, lo, hi, bblk = layer._bounds[k]
                coarse = c.levels[k + 1] if bkey[2] is not None else None
                want_lo, want_hi = cl.block_bounds(bblk, level, coarse, c.n, r.origin)
                assert np.array_equal(lo, want_lo) and np.array_equal(hi, want_hi), (step, k)
    rings = [len(b) for b in (ring[1] for ring in layer._rings.values())]
    print(f"\n{rings_measured} measures of rings of {sorted(rings)} blocks; blocks measured: {sorted(measured)}")
    assert rings_measured > 10
    assert min(measured) < min(rings), "no ring was measured in part: nothing was reused"


def test_a_levels_write_log_and_the_blocks_it_leaves_unchanged():
    """LevelStore.written_since lists the posts written after a version (None once the log no
    longer reaches back); same_blocks pairs equal blocks; posts_unchanged keeps the blocks
    inside the region and clear of every write."""
    from client.render.clipmap import WRITE_LOG_MOVES, LevelStore, Rect
    from client.render.clipmap_layer import posts_unchanged, same_blocks

    level = LevelStore(0, 31, region=Rect(0, 0, 30, 30))
    for v in range(1, WRITE_LOG_MOVES + 3):  # move v writes row v
        level.version = v
        level._log_writes([Rect(v, 0, v, 30)])
    last = level.version
    assert last == 18
    assert level.written_since(last) == []
    assert level.written_since(16) == [Rect(17, 0, 17, 30), Rect(18, 0, 18, 30)]
    assert level.written_since(1) is None  # older than the log
    blk = np.array([[0, 0, 8, 8], [8, 0, 16, 8], [16, 8, 24, 16], [24, 0, 32, 8]], np.int32)
    # Since version 16 rows 17 and 18 were written: the third block holds them; the last
    # reaches row 32, outside the region.
    assert posts_unchanged(blk, level, 16).tolist() == [True, True, False, False]
    assert posts_unchanged(blk, level, 1).tolist() == [False] * 4  # unknown: none kept
    rows, other = same_blocks(blk, blk[[3, 1, 0]])
    assert sorted(zip(rows.tolist(), other.tolist())) == [(0, 2), (1, 1), (3, 0)]
    assert len(same_blocks(blk, np.array([[1 << 30, 0, (1 << 30) + 8, 8]]))[0]) == 0


def test_plan_threads_from_the_environment(monkeypatch):
    from client.render.clipmap_layer import PLAN_THREADS_DEFAULT_MAX, _plan_threads
    from sortie.errors import InvalidArgument
    from terrain.threads import cpu_count

    monkeypatch.delenv("SORTIE_PLAN_THREADS", raising=False)
    assert _plan_threads() == min(cpu_count(), PLAN_THREADS_DEFAULT_MAX)
    monkeypatch.setenv("SORTIE_PLAN_THREADS", " 3 ")
    assert _plan_threads() == 3
    for bad in ("0", "-2", "two", "1.5"):
        monkeypatch.setenv("SORTIE_PLAN_THREADS", bad)
        with pytest.raises(InvalidArgument, match="SORTIE_PLAN_THREADS"):
            _plan_threads()
