"""Procedural terrain fixes from the s31 seeds-conformance probe (virtual-terrain-generation.txt).

2. The paper's runtime parameters M, E, W (§3: "can be changed by the user at runtime"; a new
   square's "borders are fitted to the borders of already existing neighbor squares"):
   ProceduralTerrain.set_parameters changes them with every seam kept bit for bit (the attributes
   are read-only: assigning them tore seams by up to 1665 m), and `sortie terrain serve` /
   `terrain info` take --procedural-max-height-m, --procedural-exponent, --procedural-water, which
   reach the served heights and GetMetadata; bad values are refused naming the option and value.
4. retain_near (§2: "squares dropping out of view have to be removed"): its viewers' blocks are
   the last the LRU evicts until its next call, so one large query no longer evicts them; a
   non-finite viewer is refused naming the field and index.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from sortie.cli import main
from sortie.errors import InvalidArgument
from terrain.procedural import ProceduralTerrain, height_bounds_m
from terrain.terrain import Terrain

# A small world: 16-cell blocks (5.6 degrees a side), 64 around, 32 from pole to pole.
SMALL = dict(block_cells=16, posts_per_turn=1024)
PORT = 53400  # this file's service port (53400-53449 are this area's)


def _shared_posts(a, b):
    """The posts blocks a and b (ProceduralBlock) share, as (a's, b's) 1-D arrays; None if none."""
    rows = a.bed_msl_m.shape[0] - 1
    dr = b.row - a.row
    cols = 64  # SMALL's block columns
    dc = (b.col - a.col + cols // 2) % cols - cols // 2
    if max(abs(dr), abs(dc)) != 1:
        return None
    ia, ib = {-1: (0, rows), 0: (slice(None), slice(None)), 1: (rows, 0)}[dr]
    ja, jb = {-1: (0, rows), 0: (slice(None), slice(None)), 1: (rows, 0)}[dc]
    return np.atleast_1d(a.bed_msl_m[ia, ja]), np.atleast_1d(b.bed_msl_m[ib, jb])


def _assert_seamless(blocks):
    """Every pair of neighbours among ``blocks`` shares its edge or corner posts bit for bit, and
    every pole row is one height (bed equality, no tolerance)."""
    blocks = list(blocks)
    for k, a in enumerate(blocks):
        for b in blocks[k + 1:]:
            shared = _shared_posts(a, b)
            if shared is not None:
                assert np.array_equal(*shared), (a.row, a.col, b.row, b.col, np.abs(shared[0] - shared[1]).max())
    poles = [blk.bed_msl_m[0] for blk in blocks if blk.row == 0]
    if poles:
        assert np.unique(np.concatenate(poles)).size == 1


# --------------------------------------------------------------------------- 2: runtime parameters

def test_the_probe_case_a_parameter_change_keeps_the_seam():
    """The probe: block (40, 10) cached, then W = 0.7 and M = 3000 m, then its east neighbour:
    the shared edge was 1665 m apart; now equal bit for bit, and plain assignment is refused."""
    pt = ProceduralTerrain(9, block_cells=32, posts_per_turn=2**12)
    a = pt.block(40, 10).bed_msl_m
    with pytest.raises(AttributeError):
        pt.water = 0.7
    with pytest.raises(AttributeError):
        pt.max_height_m = 3000.0
    assert pt.set_parameters(water=0.7, max_height_m=3000.0)
    assert (pt.max_height_m, pt.level_exponent, pt.water) == (3000.0, 2.0, 0.7)
    b = pt.block(40, 11).bed_msl_m
    assert np.array_equal(a[:, -1], b[:, 0])
    # The new block is made with the new parameters: away from its old neighbour it is the
    # world of a terrain made with them from the start, wherever its own borders are its own.
    fresh = ProceduralTerrain(9, max_height_m=3000.0, water=0.7, block_cells=32, posts_per_turn=2**12)
    assert np.array_equal(pt.block(40, 13).bed_msl_m, fresh.generate_block(40, 13).bed_msl_m)


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_changes_at_runtime_keep_every_seam_in_any_order(seed):
    """Blocks over a pole and the antimeridian made in a random order, the parameters changed
    several times in between and a small cache evicting as it goes: each new block fits every
    cached neighbour bit for bit (the paper's promise), a block cached at a change comes back as
    it was after the cache dropped it, every bed lies within height_range_m, and the world at
    the end is seamless everywhere. The same operations on another terrain give the same bits."""
    rng = np.random.default_rng(seed)
    cells = [(r, c % 64) for r in range(0, 5) for c in range(-3, 3)]  # rows 0-4 (south pole), across -180
    order = rng.permutation(len(cells))
    changes = {int(k): (float(rng.uniform(100.0, 5000.0)), float(rng.uniform(1.2, 3.0)), float(rng.uniform(0, 1)))
               for k in rng.choice(np.arange(1, len(cells)), 4, replace=False)}

    def run(pt):
        kept = {}  # the blocks cached at a change, as they were then
        for step, k in enumerate(order):
            if step in changes:
                kept.update((key, pt.block(*key).bed_msl_m) for key in pt.cached_blocks() if key not in kept)
                assert pt.set_parameters(*changes[step])
            blk = pt.block(*cells[k])
            _assert_seamless([pt.block(*key) for key in pt.cached_blocks()])
            lo, hi = pt.height_range_m
            assert lo <= blk.bed_msl_m.min() and blk.bed_msl_m.max() <= hi
        return kept

    pt = ProceduralTerrain(seed, cache_blocks=6, **SMALL)
    kept = run(pt)
    assert pt.parameter_changes == 4 and pt.blocks_evicted > 0 and len(kept) >= 6
    final = {key: pt.block(*key) for key in cells}
    _assert_seamless(final.values())
    assert all(np.array_equal(pt.generate_block(*key).bed_msl_m, final[key].bed_msl_m) for key in cells)
    assert all(np.array_equal(bed, pt.block(*key).bed_msl_m) for key, bed in kept.items())
    twin = ProceduralTerrain(seed, cache_blocks=6, **SMALL)
    run(twin)
    assert all(np.array_equal(twin.block(*key).bed_msl_m, final[key].bed_msl_m) for key in cells)
    pole = Terrain([pt]).heights(np.full(8, -90.0), np.linspace(-180.0, 180.0, 8)).height_msl_m
    assert np.unique(pole).size == 1  # the pole stays one height


def test_queries_answer_one_seamless_surface_after_a_change():
    """Heights on an edge between blocks made before a change (west) and after it (east) are
    the older blocks' (bit for bit the unchanged world's at its posts), continuous across it,
    while the new blocks' own posts follow the new parameters."""
    p = ProceduralTerrain(4, water=0.1, **SMALL)
    t = Terrain([p])
    n, sp = 16, p.spacing_deg
    edge_lon = -180.0 + 20 * n * sp  # the border between block columns 19 and 20
    lat = np.linspace(10.0, 15.0, 200)  # block rows 17 and 18
    west = t.heights(lat, np.full(200, edge_lon - 1e-6)).height_msl_m  # caches column 19
    p.set_parameters(max_height_m=4000.0, level_exponent=1.4, water=0.0)
    east = t.heights(lat, np.full(200, edge_lon + 1e-6)).height_msl_m  # column 20, made now
    # 1e-6 degrees is 2.8e-6 of a cell: heights within 2.8e-6 of a cell's rise (< 0.1 m) either side.
    assert np.abs(east - west).max() < 0.1
    posts = -90.0 + (17 * n + np.arange(2 * n + 1)) * sp
    unchanged = Terrain([ProceduralTerrain(4, water=0.1, **SMALL)])
    assert np.array_equal(t.heights(posts, np.full(posts.size, edge_lon)).height_msl_m,
                          unchanged.heights(posts, np.full(posts.size, edge_lon)).height_msl_m)
    inner = t.heights(posts, np.full(posts.size, edge_lon + 8 * sp)).height_msl_m
    assert not np.array_equal(inner, unchanged.heights(posts, np.full(posts.size, edge_lon + 8 * sp)).height_msl_m)
    assert (inner > 0.0).all()  # W = 0 now: no water inside the new blocks


def test_height_range_covers_every_epoch():
    """height_range_m is the generator's bound before any change, and after one covers both
    epochs (the ray shell of terrain.Terrain relies on it)."""
    from terrain.procedural import mixed_height_bounds_m

    p = ProceduralTerrain(2, **SMALL)
    assert p.height_range_m == height_bounds_m(1000.0, 2.0, 0.3, 16)
    p.block(10, 10)
    p.set_parameters(max_height_m=8000.0, water=0.9)
    lo, hi = p.height_range_m
    assert (lo, hi) == mixed_height_bounds_m([(1000.0, 2.0, 0.3), (8000.0, 2.0, 0.9)], 16)
    assert lo <= min(height_bounds_m(8000.0, 2.0, 0.9, 16)[0], height_bounds_m(1000.0, 2.0, 0.3, 16)[0])
    assert hi >= max(height_bounds_m(8000.0, 2.0, 0.9, 16)[1], height_bounds_m(1000.0, 2.0, 0.3, 16)[1])
    assert p.describe()["parameter_changes"] == 1 and p.describe()["max_height_m"] == 8000.0


@pytest.mark.parametrize("kwargs, field", [(dict(max_height_m=0.0), "max_height_m"),
                                           (dict(level_exponent=1.0), "level_exponent"),
                                           (dict(water=float("nan")), "water")])
def test_set_parameters_checks_like_the_constructor(kwargs, field):
    p = ProceduralTerrain(2, **SMALL)
    with pytest.raises(InvalidArgument, match=f"^{field}: must be a finite number"):
        p.set_parameters(**kwargs)
    assert p.parameter_changes == 0 and not p.set_parameters(water=0.3)  # the same values: no change


def _wait_listening(proc, timeout_s=60.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            with TerrainClient(f"127.0.0.1:{PORT}") as c:
                c.wait_ready(1.0)
                return
        except Exception:  # noqa: BLE001 - not up yet
            assert proc.poll() is None, proc.communicate()
            time.sleep(0.2)
    raise AssertionError("sortie terrain serve did not come up")


def test_serve_options_reach_the_served_heights_and_metadata():
    """A real `sortie terrain serve --procedural 5 --procedural-max-height-m 3000
    --procedural-exponent 1.5 --procedural-water 0.6` on its port answers the heights of an
    in-process ProceduralTerrain with those M, E, W, bit for bit, and says them in GetMetadata."""
    argv = [sys.executable, "-m", "sortie.cli", "terrain", "serve", "--procedural", "5",
            "--procedural-max-height-m", "3000", "--procedural-exponent", "1.5", "--procedural-water", "0.6",
            "--port", str(PORT)]
    proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        _wait_listening(proc)
        rng = np.random.default_rng(5)
        lat, lon = rng.uniform(40.0, 41.0, 500), rng.uniform(7.0, 8.0, 500)
        with TerrainClient(f"127.0.0.1:{PORT}") as client:
            got = client.heights(lat, lon).height_msl_m
            meta = client.metadata()
    finally:
        proc.terminate()
        proc.communicate(timeout=30)
    want = Terrain([ProceduralTerrain(5, max_height_m=3000.0, level_exponent=1.5, water=0.6)]).heights(lat, lon)
    default = Terrain([ProceduralTerrain(5)]).heights(lat, lon).height_msl_m
    assert np.array_equal(got, want.height_msl_m) and not np.array_equal(got, default)
    src = meta["sources"][0]
    assert (src["kind"], src["max_height_m"], src["level_exponent"], src["water"]) == \
        ("procedural", "3000.0", "1.5", "0.6")


def test_info_prints_the_options_parameters(capsys):
    assert main(["terrain", "info", "--procedural", "3", "--procedural-water", "0.55", "--json"]) == 0
    src = json.loads(capsys.readouterr().out)["sources"][0]
    assert (src["max_height_m"], src["level_exponent"], src["water"]) == ("1000.0", "2.0", "0.55")


@pytest.mark.parametrize("extra, expected", [
    (["--procedural", "1", "--procedural-water", "1.5"],
     "--procedural-water: must be a finite number within [0, 1] (got 1.5)"),
    (["--procedural", "1", "--procedural-exponent", "1"],
     "--procedural-exponent: must be a finite number within (1, 64] (got 1.0)"),
    (["--procedural", "1", "--procedural-max-height-m", "nan"],
     "--procedural-max-height-m: must be a finite number within (0, 100000] (got nan)"),
    (["--procedural-max-height-m", "500"],
     "--procedural-max-height-m: shapes a procedural world: give --procedural SEED too (got 500.0)"),
], ids=lambda v: " ".join(v) if isinstance(v, list) else None)
def test_bad_options_are_refused_naming_option_and_value(capsys, extra, expected):
    assert main(["terrain", "info", *extra]) == 2
    err = capsys.readouterr().err
    assert f"sortie terrain: error: {expected}" in err, err
    assert "max_height_m" not in err and "level_exponent" not in err and "Traceback" not in err


# --------------------------------------------------------------------------- 4: retain_near

def test_a_large_query_leaves_the_viewers_blocks():
    """A viewer's 5 blocks, then one query over 200 new blocks (a coarse clipmap level's worth)
    with a 32-block cache: the viewer's blocks are still the same cached objects, and the cache
    kept its bound. Old: the query evicted all of them."""
    p = ProceduralTerrain(6, cache_blocks=32, **SMALL)
    t = Terrain([p])
    viewer = (20.0, 30.0)
    t.heights(np.linspace(14.0, 26.0, 50), np.full(50, 30.0))
    t.heights(np.full(50, 20.0), np.linspace(24.0, 36.0, 50))
    p.retain_near([viewer[0]], [viewer[1]], 500_000.0)
    near = {key: p.block(*key) for key in p.cached_blocks()}
    assert len(near) >= 5
    lat, lon = np.meshgrid(np.linspace(-60.0, -10.0, 10) + 1.0, np.linspace(-170.0, -60.0, 20) + 1.0)
    t.heights(lat.ravel(), lon.ravel())
    assert len(p.cached_blocks()) <= 32 and p.blocks_generated == len(near) + 200
    assert all(p.cached_blocks().count(key) == 1 and p.block(*key) is blk for key, blk in near.items())
    # A block near the viewer made after the call is kept too.
    extra = p.block_index(np.array([viewer[0]]), np.array([viewer[1] + 8.0]))[0]
    made = p.block(*extra)
    t.heights(lat.ravel() + 5.0, lon.ravel())
    assert p.block(*extra) is made


def test_retain_near_drops_far_blocks_and_protection_ends_with_no_viewer():
    p = ProceduralTerrain(6, cache_blocks=8, **SMALL)
    Terrain([p]).heights(np.array([20.0, -50.0]), np.array([30.0, 100.0]))
    assert p.retain_near([20.0], [30.0], 1000.0) == 1
    assert p.cached_blocks() == p.block_index(np.array([20.0]), np.array([30.0]))
    assert p.retain_near([], [], 1.0) == 1 and not p.cached_blocks()
    for c in range(12):  # no viewer: a plain LRU again
        p.block(10, c)
    assert p.cached_blocks() == [(10, c) for c in range(4, 12)]


def test_viewers_filling_the_cache_still_bound_it():
    p = ProceduralTerrain(6, cache_blocks=4, **SMALL)
    p.retain_near([0.0], [0.0], 5_000_000.0)  # every block nearby is near the viewer
    for c in range(28, 36):
        p.block(16, c)
    assert p.cached_blocks() == [(16, c) for c in range(32, 36)]


@pytest.mark.parametrize("lat, lon, expected", [([10.0, float("nan")], [1.0, 2.0], r"^lat\[1\]: must be finite"),
                                                ([10.0], [float("inf")], r"^lon\[0\]: must be finite")])
def test_retain_near_refuses_non_finite_viewers(lat, lon, expected):
    p = ProceduralTerrain(6, **SMALL)
    p.block(16, 32)
    with pytest.raises(InvalidArgument, match=expected):
        p.retain_near(lat, lon, 1000.0)
    assert p.cached_blocks() == [(16, 32)]  # nothing dropped on a refused call


def test_the_world_keeps_only_the_blocks_near_its_entities():
    """A world over a procedural terrain tells it every TERRAIN_RETAIN_EVERY_TICKS ticks where
    its entities are: a block generated far away (a query on the other side of the globe) is
    dropped, the blocks under the vehicle stay."""
    from server.world import TERRAIN_RETAIN_EVERY_TICKS, World
    from terrain.procedural import ProceduralTerrain
    from terrain.terrain import Terrain

    pt = ProceduralTerrain(seed=7)
    terrain = Terrain([pt])
    land = next((la, lo) for la in np.arange(-40.0, 40.0, 0.7) for lo in np.arange(-170.0, 170.0, 1.3)
                if terrain.heights(np.array([la]), np.array([lo])).height_msl_m[0] > 50.0)
    world = World(terrain)
    try:
        world.spawn_ground(["tank"], "m1a2", [land[0]], [land[1]], [0.0])
        terrain.heights(np.array([-land[0]]), np.array([land[1] + 180.0 if land[1] < 0 else land[1] - 180.0]))
        far = len(pt._cache)
        for _ in range(TERRAIN_RETAIN_EVERY_TICKS):
            world.tick()
        kept = list(pt._cache)
        assert len(kept) < far + 4 and kept  # the far block went, the vehicle's stayed
        half = 0.5 * pt.block_cells * pt.spacing_deg
        assert all(abs(-90.0 + (2 * row + 1) * half - land[0]) < 1.0 for row, _ in kept)
    finally:
        world.close()
