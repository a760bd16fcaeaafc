"""Large height and normal batches on several threads (Terrain.heights / normals(threads=k),
the terrain service's --query-threads): the same answers, bit for bit, whatever the split,
over one DEM, over a stack of sources (later sources answer what earlier ones left: the
indexed path), and over the service on loopback."""

from __future__ import annotations

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from server.terrain_service import create_server
from terrain import terrain as terrain_mod
from terrain.dem import read_hgt
from terrain.procedural import ProceduralTerrain
from terrain.terrain import Terrain


@pytest.fixture(scope="module")
def alps(hgt_alps):
    return read_hgt(hgt_alps)


def _points(n, seed, box=(46.9, 8.9, 48.1, 10.1)):
    """Points over the tile and around it (some outside: other sources, or none, answer)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(box[0], box[2], n), rng.uniform(box[1], box[3], n)


@pytest.mark.parametrize("threads", [2, 3, 4])
@pytest.mark.parametrize("n", [40_000, 100_003])
def test_split_batches_answer_as_one_thread_does(alps, threads, n):
    t = Terrain([alps])
    lat, lon = _points(n, n + threads)
    one = t.heights(lat, lon)
    many = t.heights(lat, lon, threads=threads, warm=True)
    assert np.array_equal(one.height_msl_m, many.height_msl_m, equal_nan=True)
    assert np.array_equal(one.status, many.status)
    assert np.isnan(one.height_msl_m).any() and np.isfinite(one.height_msl_m).any()


@pytest.mark.parametrize("threads", [2, 4])
def test_split_normal_batches_answer_as_one_thread_does(alps, threads):
    t = Terrain([alps, ProceduralTerrain(seed=4)])
    lat, lon = _points(70_001, 20 + threads)
    one = t.normals(lat, lon)
    many = t.normals(lat, lon, threads=threads, warm=True)
    assert np.array_equal(one.normal_enu, many.normal_enu) and np.array_equal(one.slope_deg, many.slope_deg)
    assert np.array_equal(one.status, many.status)


def test_a_stack_splits_each_rasters_share_and_leaves_the_rest_whole(alps, monkeypatch):
    """Over the Alps tile then the procedural world: the tile's points split in parts, the
    procedural world's share taken whole (its block cache is its own)."""
    calls = []
    real = terrain_mod.Raster.heights_into

    def spy(self, lat, lon, out_h, out_status):
        calls.append(lat.size)
        return real(self, lat, lon, out_h, out_status)

    t = Terrain([alps, ProceduralTerrain(seed=3)])
    lat, lon = _points(70_000, 5)
    one = t.heights(lat, lon)
    monkeypatch.setattr(terrain_mod.Raster, "heights_into", spy)
    many = t.heights(lat, lon, threads=2)
    assert np.array_equal(one.height_msl_m, many.height_msl_m) and np.array_equal(one.status, many.status)
    assert len(calls) == 2 and sum(calls) == lat.size  # the tile: every point, in two parts
    small = t.heights(lat[:1000], lon[:1000], threads=4)  # under 2 x 16,384 points: one part
    assert np.array_equal(small.height_msl_m, one.height_msl_m[:1000]) and len(calls) == 3


@pytest.mark.parametrize("threads", [1, 2])
def test_the_service_answers_the_same_at_any_query_threads(alps, threads):
    t = Terrain([alps])
    server, port = create_server(t, "127.0.0.1:0", query_threads=threads)
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            lat, lon = _points(60_000, 11)
            got = client.heights(lat, lon)
            want = t.heights(lat, lon)
            assert np.array_equal(got.height_msl_m, want.height_msl_m, equal_nan=True)
            assert np.array_equal(got.status, want.status)
            got_n, want_n = client.normals(lat, lon), t.normals(lat, lon)
            assert np.array_equal(got_n.normal_enu, want_n.normal_enu, equal_nan=True)
            assert np.array_equal(got_n.slope_deg, want_n.slope_deg, equal_nan=True)
    finally:
        server.stop(0).wait()
