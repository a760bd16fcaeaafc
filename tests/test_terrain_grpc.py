"""The terrain query service over real gRPC on loopback: answers equal the
in-process Terrain bit for bit, hostile requests get clear statuses without
disturbing anyone else, health and reflection work for stock clients, the
numpy wire codec is byte-compatible with the generated classes, and
`sortie terrain serve` stops cleanly on SIGTERM.
"""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
import threading
from pathlib import Path

import grpc
import numpy as np
import pytest
from google.protobuf import descriptor_pb2
from google.protobuf.message import DecodeError
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc
from hypothesis import given, settings
from hypothesis import strategies as st

from client.terrain_client import ServiceError, TerrainClient
from server import terrain_service
from server.grpc_common import PackedCodec
from server.terrain_service import SERVICE_NAME, create_server
from sortie import cli
from sortie.errors import InvalidArgument, LimitExceeded
from sortie.v1 import terrain_pb2 as pb
from sortie.v1 import terrain_pb2_grpc
from terrain.raster import CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, Georef, Raster
from terrain.terrain import Terrain

SORTIE = Path(sys.executable).parent / "sortie"  # the console script of this environment
SUBPROCESS_TIMEOUT_S = 30.0

# Inside N47E009 (47..48 N, 9..10 E) with a margin outside it on every side.
LAT_RANGE = (46.9, 48.1)
LON_RANGE = (8.9, 10.1)


@pytest.fixture(scope="module")
def alps(hgt_alps) -> Terrain:
    """The SRTM3 tile read independently of terrain.dem: row 0 = 48 N in the file."""
    h = np.fromfile(hgt_alps, ">i2").reshape(1201, 1201)[::-1].astype(np.float32)
    return Terrain([Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1 / 1200, 1 / 1200), name="N47E009")])


@pytest.fixture(scope="module")
def address(alps):
    server, port = create_server(alps, "127.0.0.1:0", max_workers=8)
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(0).wait()


@pytest.fixture
def client(address):
    with TerrainClient(address, timeout_s=20.0) as c:
        yield c


@pytest.fixture
def unsplit_client(address):
    """A client that never splits batches, to reach the server's own limits."""
    with TerrainClient(address, timeout_s=20.0, chunk_points=1 << 40, chunk_rays=1 << 40) as c:
        yield c


@pytest.fixture
def stub(address):
    """The generated stub with the generated message classes: what grpcurl-like clients send."""
    with grpc.insecure_channel(address) as channel:
        yield terrain_pb2_grpc.TerrainServiceStub(channel)


def _points(n: int, seed: int):
    rng = np.random.default_rng(seed)
    return rng.uniform(*LAT_RANGE, n), rng.uniform(*LON_RANGE, n)


def _rays(n: int, seed: int):
    rng = np.random.default_rng(seed)
    a_lat, b_lat = rng.uniform(47.05, 47.95, (2, n))
    a_lon, b_lon = rng.uniform(9.05, 9.95, (2, n))
    a_h, b_h = rng.uniform(500.0, 4000.0, (2, n))
    return a_lat, a_lon, a_h, b_lat, b_lon, b_h


def _same(a, b) -> bool:
    """Equal bit for bit, NaN included, and of the same dtype."""
    a, b = np.asarray(a), np.asarray(b)
    return a.dtype == b.dtype and a.shape == b.shape and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


# --- answers ---------------------------------------------------------------------------------

def test_heights_equal_in_process_bit_for_bit(alps, client):
    lat, lon = _points(50_000, seed=1)
    posts_lat = 47.0 + np.arange(0, 1201, 37) / 1200  # exactly on posts, tile edges included
    lat = np.concatenate([lat, posts_lat, [47.0, 48.0, -89.9, 89.9]])
    lon = np.concatenate([lon, 9.0 + np.arange(0, 1201, 37) / 1200, [9.0, 10.0, 9.5, 369.5]])
    got, ref = client.heights(lat, lon), alps.heights(lat, lon)
    assert _same(got.height_msl_m, ref.height_msl_m)
    assert _same(got.status, ref.status)
    assert (ref.status == STATUS_OUTSIDE).any() and (ref.status == STATUS_OK).any()


def test_generated_stub_gets_the_same_heights(alps, stub):
    lat, lon = _points(1000, seed=2)
    resp = stub.GetHeights(pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon))
    ref = alps.heights(lat, lon)
    assert _same(np.array(resp.height_msl_m), ref.height_msl_m)
    assert list(resp.status) == ref.status.tolist()


def test_scalar_point(alps, client):
    got = client.heights(47.25, 9.25)
    assert _same(got.height_msl_m, alps.heights([47.25], [9.25]).height_msl_m)


def test_normals_equal_in_process(alps, client):
    lat, lon = _points(20_000, seed=3)
    got, ref = client.normals(lat, lon), alps.normals(lat, lon)
    assert _same(got.normal_enu, ref.normal_enu)
    assert _same(got.slope_deg, ref.slope_deg)
    assert _same(got.status, ref.status)


def test_profile_equals_in_process(alps, client):
    got = client.profile(47.1, 9.1, 47.9, 9.8, 2001)
    ref = alps.profile(47.1, 9.1, 47.9, 9.8, 2001)
    for name in ("lat_deg", "lon_deg", "distance_m", "height_msl_m", "status"):
        assert _same(getattr(got, name), getattr(ref, name)), name


def test_line_of_sight_equals_in_process(alps, client):
    rays = _rays(2000, seed=4)
    got, ref = client.line_of_sight(*rays), alps.line_of_sight(*rays)
    assert _same(got.visible, ref.visible)
    assert _same(got.status, ref.status)
    assert got.visible.any() and not got.visible.all()


def test_intersect_equals_in_process(alps, client):
    rays = _rays(2000, seed=5)
    got, ref = client.intersect(*rays), alps.intersect(*rays)
    for name in ("hit", "distance_m", "lat_deg", "lon_deg", "height_msl_m", "normal_enu", "status"):
        assert _same(getattr(got, name), getattr(ref, name)), name


def test_metadata(client, alps):
    meta = client.metadata()
    (source,) = meta["sources"]
    (local,) = alps.describe()
    assert source == local  # the same keys and values as the in-process Terrain
    assert (source["lat_min"], source["lon_min"], source["lat_max"], source["lon_max"]) == (47.0, 9.0, 48.0, 10.0)
    assert client.describe() == meta["sources"]
    assert meta["dem_files"] == []  # this service was given a Terrain, not files
    assert "mean sea level" in meta["height_reference"]
    assert meta["limits"] == {
        "max_height_points": terrain_service.MAX_HEIGHT_POINTS,
        "max_normal_points": terrain_service.MAX_NORMAL_POINTS,
        "max_profile_samples": terrain_service.MAX_PROFILE_SAMPLES,
        "max_line_of_sight_rays": terrain_service.MAX_LOS_RAYS,
        "max_segments": terrain_service.MAX_SEGMENTS,
        "max_message_bytes": 64 * 1024 * 1024,
        "max_region_posts": terrain_service.MAX_REGION_POSTS,
    }


# --- the all-OK status convention --------------------------------------------------------------

def _inside_points(n: int, seed: int):
    rng = np.random.default_rng(seed)
    return rng.uniform(47.05, 47.95, n), rng.uniform(9.05, 9.95, n)


def test_all_ok_status_is_sent_empty_and_the_client_expands_it(alps, client, stub):
    """Every batched response leaves out a status of all POINT_STATUS_OK (a byte a
    point less on the wire); the client library gives callers the full array."""
    lat, lon = _inside_points(5000, seed=21)
    rays = _rays(300, seed=22)
    checks = [
        (stub.GetHeights(pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon)),
         client.heights(lat, lon), alps.heights(lat, lon)),
        (stub.GetNormals(pb.GetNormalsRequest(lat_deg=lat, lon_deg=lon)),
         client.normals(lat, lon), alps.normals(lat, lon)),
        (stub.GetProfile(pb.GetProfileRequest(start_lat_deg=47.1, start_lon_deg=9.1, end_lat_deg=47.9,
                                              end_lon_deg=9.8, n_samples=501)),
         client.profile(47.1, 9.1, 47.9, 9.8, 501), alps.profile(47.1, 9.1, 47.9, 9.8, 501)),
        (stub.LineOfSight(pb.LineOfSightRequest(**dict(zip(terrain_service._RAY_NAMES, rays)))),
         client.line_of_sight(*rays), alps.line_of_sight(*rays)),
        (stub.IntersectSegments(pb.IntersectSegmentsRequest(**dict(zip(terrain_service._RAY_NAMES, rays)))),
         client.intersect(*rays), alps.intersect(*rays)),
    ]
    for wire, got, ref in checks:
        name = type(wire).__name__
        assert (ref.status == STATUS_OK).all(), name
        assert len(wire.status) == 0, name
        assert _same(got.status, ref.status), name
        assert got.status.flags.writeable, name
    heights = checks[0][1].height_msl_m
    assert heights.flags.writeable and heights.flags.owndata  # the caller's own array, not a view of the message


def test_other_statuses_are_sent_per_point(alps, client, stub):
    lat, lon = _inside_points(2000, seed=23)
    lat[[5, 1500]] = 46.5  # OUTSIDE
    ref = alps.heights(lat, lon)
    wire = stub.GetHeights(pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon))
    assert list(wire.status) == ref.status.tolist()
    assert _same(client.heights(lat, lon).status, ref.status)
    assert np.count_nonzero(ref.status == STATUS_OUTSIDE) == 2


def test_statuses_stay_aligned_across_chunks_sent_with_and_without_them():
    """A chunked batch whose chunks are answered all OK (status sent empty),
    with filled voids and with points outside: statuses as in-process, in order."""
    h = np.random.default_rng(24).normal(800.0, 100.0, (121, 121)).astype(np.float32)
    filled = np.zeros(h.shape, bool)
    filled[60:63, 60:63] = True
    terrain = Terrain([Raster(h, Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1 / 1200, 1 / 1200), filled=filled)])
    rng = np.random.default_rng(25)
    lat = 47.0 + rng.uniform(0, 40, 3000) / 1200  # chunks 0 and 1: clear of the voids
    lon = 9.0 + rng.uniform(0, 40, 3000) / 1200
    lat[2000:2100], lon[2000:2100] = 47.0 + 61 / 1200, 9.0 + 61.5 / 1200  # chunk 2: FILLED
    lat[2900], lon[2900] = 48.5, 9.01  # ... and one OUTSIDE
    server, port = create_server(terrain)
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}", chunk_points=1000) as c:
            got, ref = c.heights(lat, lon), terrain.heights(lat, lon)
            assert _same(got.status, ref.status)
            assert _same(got.height_msl_m, ref.height_msl_m)
            assert (ref.status[:2000] == STATUS_OK).all()
            assert set(ref.status[2000:].tolist()) == {STATUS_OK, STATUS_FILLED, STATUS_OUTSIDE}
            normals = c.normals(lat, lon)
            assert _same(normals.status, terrain.normals(lat, lon).status)
    finally:
        server.stop(0).wait()


def test_status_expansion_needs_points():
    _, _, encode, decode = terrain_service.serializers("GetHeights")
    assert terrain_service.sent_status(np.full(3, STATUS_OK, np.uint8)).size == 0
    assert decode(encode({"height_msl_m": np.zeros(3), "status": np.zeros(0, np.uint8)}))["status"].tolist() \
        == [STATUS_OK] * 3
    empty = decode(b"")  # no points at all: nothing to expand
    assert empty["height_msl_m"].size == 0 and empty["status"].size == 0


# --- stock clients: health and reflection ----------------------------------------------------

@pytest.mark.parametrize("service", ["", SERVICE_NAME])
def test_health_serving(address, service):
    with grpc.insecure_channel(address) as channel:
        resp = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=service))
    assert resp.status == health_pb2.HealthCheckResponse.SERVING


def test_reflection_lists_and_describes_the_service(address):
    with grpc.insecure_channel(address) as channel:
        reflect = reflection_pb2_grpc.ServerReflectionStub(channel)
        requests = [reflection_pb2.ServerReflectionRequest(list_services=""),
                    reflection_pb2.ServerReflectionRequest(file_containing_symbol=SERVICE_NAME)]
        listed, described = list(reflect.ServerReflectionInfo(iter(requests)))
    names = {s.name for s in listed.list_services_response.service}
    assert {SERVICE_NAME, "grpc.health.v1.Health"} <= names
    files = [descriptor_pb2.FileDescriptorProto.FromString(raw)
             for raw in described.file_descriptor_response.file_descriptor_proto]
    (service,) = [s for f in files for s in f.service if s.name == "TerrainService"]
    assert {m.name for m in service.method} == {
        "GetMetadata", "GetHeights", "GetNormals", "GetProfile", "LineOfSight", "IntersectSegments",
        "GetTile", "GetRegion"}


# --- hostile input ---------------------------------------------------------------------------

def _lat_with(index: int, value: float, n: int = 10) -> list[float]:
    lat = [47.5] * n
    lat[index] = value
    return lat


BAD_HEIGHT_REQUESTS = [
    # (lat, lon, status code, message start)
    (_lat_with(7, 91.0), [9.5] * 10, grpc.StatusCode.INVALID_ARGUMENT, "lat_deg[7]: must be within [-90, 90]"),
    (_lat_with(3, math.nan), [9.5] * 10, grpc.StatusCode.INVALID_ARGUMENT, "lat_deg[3]: must be finite"),
    ([47.5] * 4, [9.5, 9.5, math.inf, 9.5], grpc.StatusCode.INVALID_ARGUMENT, "lon_deg[2]: must be finite"),
    ([47.5] * 5, [9.5] * 4, grpc.StatusCode.INVALID_ARGUMENT, "lon_deg: must have as many values as lat_deg"),
    ([], [], grpc.StatusCode.INVALID_ARGUMENT, "lat_deg: must hold at least one value"),
]


@pytest.mark.parametrize("lat, lon, code, message", BAD_HEIGHT_REQUESTS)
def test_bad_heights_status_names_field_and_index(stub, lat, lon, code, message):
    with pytest.raises(grpc.RpcError) as info:
        stub.GetHeights(pb.GetHeightsRequest(lat_deg=lat, lon_deg=lon))
    assert info.value.code() == code
    assert info.value.details().startswith(message)


@pytest.mark.parametrize("lat, lon, code, message", BAD_HEIGHT_REQUESTS[:-1])  # empty: answered empty
def test_client_raises_sortie_errors_with_server_message(client, lat, lon, code, message):
    with pytest.raises(InvalidArgument) as info:
        client.heights(lat, lon)
    assert str(info.value).startswith(message)


def test_oversized_batch_is_resource_exhausted(unsplit_client):
    n = terrain_service.MAX_HEIGHT_POINTS + 1
    with pytest.raises(LimitExceeded) as info:
        unsplit_client.heights(np.full(n, 47.5), np.full(n, 9.5))
    assert str(info.value) == f"lat_deg: {n} exceeds the limit of {terrain_service.MAX_HEIGHT_POINTS}"
    assert (info.value.field, info.value.size) == ("lat_deg", n)


def test_profile_limits(stub):
    too_many = terrain_service.MAX_PROFILE_SAMPLES + 1
    with pytest.raises(grpc.RpcError) as info:
        stub.GetProfile(pb.GetProfileRequest(start_lat_deg=47.1, start_lon_deg=9.1, end_lat_deg=47.2,
                                             end_lon_deg=9.2, n_samples=too_many))
    assert info.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert info.value.details().startswith("n_samples:")
    with pytest.raises(grpc.RpcError) as info:
        stub.GetProfile(pb.GetProfileRequest(start_lat_deg=47.1, start_lon_deg=9.1))
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert info.value.details().startswith("n_samples: must be at least 2")


def test_ray_batches_are_checked(client, unsplit_client):
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = _rays(6, seed=6)
    with pytest.raises(InvalidArgument, match=r"^b_lon_deg: must have as many values as a_lat_deg"):
        client.line_of_sight(a_lat, a_lon, a_h, b_lat, b_lon[:5], b_h)
    n = terrain_service.MAX_SEGMENTS + 1
    with pytest.raises(LimitExceeded, match=r"^a_lat_deg: "):
        unsplit_client.intersect(*(np.full(n, v) for v in (47.5, 9.5, 3000.0, 47.6, 9.6, 3000.0)))


def test_bad_ray_values_name_the_request_field(client):
    a_lat, a_lon, a_h, b_lat, b_lon, b_h = _rays(6, seed=6)
    b_lat[4] = -90.5
    with pytest.raises(InvalidArgument, match=r"^b_lat_deg\[4\]: "):
        client.line_of_sight(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    b_lat[4] = 47.5
    a_h[2] = math.nan
    with pytest.raises(InvalidArgument, match=r"^a_height_msl_m\[2\]: "):
        client.intersect(a_lat, a_lon, a_h, b_lat, b_lon, b_h)


def test_hostile_clients_do_not_disturb_a_concurrent_one(alps, address, unsplit_client, stub):
    lat, lon = _points(10_000, seed=7)
    expected = alps.heights(lat, lon).height_msl_m
    stop = threading.Event()
    answers, failures = [], []

    def well_behaved():
        with TerrainClient(address, timeout_s=20.0) as good:
            while not stop.is_set():
                try:
                    answers.append(_same(good.heights(lat, lon).height_msl_m, expected))
                except Exception as exc:  # the test reports any failure below
                    failures.append(exc)

    thread = threading.Thread(target=well_behaved)
    thread.start()
    try:
        big = np.full(terrain_service.MAX_HEIGHT_POINTS + 1, 47.5)
        for _ in range(3):
            for bad_lat, bad_lon, _, _ in BAD_HEIGHT_REQUESTS:
                with pytest.raises(grpc.RpcError):
                    stub.GetHeights(pb.GetHeightsRequest(lat_deg=bad_lat, lon_deg=bad_lon))
            with pytest.raises(LimitExceeded):
                unsplit_client.heights(big, big)
    finally:
        stop.set()
        thread.join(timeout=30)
    assert not failures
    assert answers and all(answers)


def test_concurrent_clients_are_served_in_parallel(alps, address):
    n_clients = 6
    barrier = threading.Barrier(n_clients)
    results = [None] * n_clients

    def run(i):
        lat, lon = _points(20_000, seed=100 + i)
        expected = alps.heights(lat, lon)
        with TerrainClient(address, timeout_s=20.0) as c:
            barrier.wait(timeout=20)
            got = [c.heights(lat, lon) for _ in range(3)]
        results[i] = all(_same(g.height_msl_m, expected.height_msl_m) and _same(g.status, expected.status)
                         for g in got)

    threads = [threading.Thread(target=run, args=(i,)) for i in range(n_clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert results == [True] * n_clients


class _FailingSource(Raster):
    """A real raster whose height kernel fails: an unexpected server-side bug."""

    def heights_into(self, lat, lon, out_h, out_status):
        raise RuntimeError("kernel exploded")


def test_unexpected_error_is_internal_and_server_keeps_serving():
    raster = _FailingSource(np.zeros((2, 2), np.float32), Georef(CRS_GEOGRAPHIC, 9.0, 47.0, 1.0, 1.0))
    server, port = create_server(Terrain([raster]))
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as c:
            with pytest.raises(ServiceError) as info:
                c.heights([47.5], [9.5])
            assert info.value.code == grpc.StatusCode.INTERNAL
            assert "RuntimeError: kernel exploded" in str(info.value)
            assert c.normals([47.5], [9.5]).status.tolist() == [STATUS_OK]
    finally:
        server.stop(0).wait()


def test_stop_marks_not_serving_first(alps):
    server, port = create_server(alps)
    server.start()
    request = health_pb2.HealthCheckRequest(service=SERVICE_NAME)
    assert server.health.Check(request, None).status == health_pb2.HealthCheckResponse.SERVING
    server.stop(0).wait()
    assert server.health.Check(request, None).status == health_pb2.HealthCheckResponse.NOT_SERVING


# --- the wire codec --------------------------------------------------------------------------

PACKED_MESSAGES = [getattr(pb, name) for name in (
    "GetHeightsRequest", "GetHeightsResponse", "GetNormalsRequest", "GetNormalsResponse",
    "GetProfileRequest", "GetProfileResponse", "LineOfSightRequest", "LineOfSightResponse",
    "IntersectSegmentsRequest", "IntersectSegmentsResponse")]

_HARD_DOUBLES = [0.0, -0.0, math.nan, math.inf, -math.inf, 5e-324, 1.7976931348623157e308, 47.123456789]


def _random_values(message_class, n: int, rng) -> dict:
    """Values for every field: hard doubles, all enum values, both bools; n = 0 for empty."""
    values = {}
    for fd in message_class.DESCRIPTOR.fields:
        if fd.is_repeated and fd.type == fd.TYPE_DOUBLE:
            values[fd.name] = np.concatenate([_HARD_DOUBLES, rng.normal(0, 1e3, n)])[:n] if n else np.zeros(0)
        elif fd.is_repeated and fd.type == fd.TYPE_ENUM:
            values[fd.name] = rng.integers(0, 4, n).astype(np.uint8)
        elif fd.is_repeated:
            values[fd.name] = rng.integers(0, 2, n).astype(bool)
        elif fd.type == fd.TYPE_DOUBLE:
            values[fd.name] = float(rng.choice(_HARD_DOUBLES)) if n else 0.0
        else:
            values[fd.name] = int(rng.integers(0, 2**32)) if n else 0
    return values


def _generated(message_class, values: dict):
    return message_class(**{k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in values.items()})


def _assert_same_values(got: dict, want: dict):
    assert got.keys() == want.keys()
    for name, value in want.items():
        if isinstance(value, np.ndarray):
            assert _same(got[name], value), name
        else:
            assert _bits(got[name]) == _bits(value), name


def _bits(v):
    return np.float64(v).tobytes() if isinstance(v, float) else v


@pytest.mark.parametrize("message_class", PACKED_MESSAGES, ids=lambda c: c.__name__)
@pytest.mark.parametrize("n", [0, 1, 9, 1000])
def test_codec_bytes_equal_generated_bytes(message_class, n):
    codec = PackedCodec(message_class)
    values = _random_values(message_class, n, np.random.default_rng(n))
    ours = codec.encode(values)
    theirs = _generated(message_class, values).SerializeToString()
    assert ours == theirs
    _assert_same_values(codec.decode(theirs), values)
    assert message_class.FromString(ours) == _generated(message_class, values)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.floats(allow_nan=True, allow_infinity=True), max_size=50),
       st.lists(st.sampled_from([0, 1, 2, 3]), max_size=50))
def test_codec_round_trip_property(heights, statuses):
    values = {"height_msl_m": np.array(heights, np.float64), "status": np.array(statuses, np.uint8)}
    codec = PackedCodec(pb.GetHeightsResponse)
    data = codec.encode(values)
    assert data == _generated(pb.GetHeightsResponse, values).SerializeToString()
    _assert_same_values(codec.decode(data), values)


def test_codec_reads_every_legal_encoding():
    codec = PackedCodec(pb.GetHeightsResponse)
    lat = np.array([1.5, -2.25, math.nan])
    # Unpacked doubles (wire type 1 per value) must be accepted by any parser.
    unpacked = b"".join(b"\x09" + np.float64(v).tobytes() for v in lat)
    assert _same(codec.decode(unpacked)["height_msl_m"], lat)
    # A packed field split over two chunks is concatenated.
    two_chunks = codec.encode({"height_msl_m": lat[:1]}) + codec.encode({"height_msl_m": lat[1:]})
    assert _same(codec.decode(two_chunks)["height_msl_m"], lat)
    # An unknown field is skipped; an enum value of two varint bytes still reads.
    unknown = codec.encode({"height_msl_m": lat}) + b"\xf8\x01\x05"
    assert _same(codec.decode(unknown)["height_msl_m"], lat)
    wide_enum = pb.GetHeightsResponse(status=[1, 200, 3]).SerializeToString()
    assert codec.decode(wide_enum)["status"].tolist() == [1, 200, 3]


@pytest.mark.parametrize("data", [b"\x0a\x10" + bytes(8), b"\x0a\x07" + bytes(7), b"\x0a"])
def test_codec_rejects_malformed_bytes(data):
    with pytest.raises(DecodeError):
        PackedCodec(pb.GetHeightsResponse).decode(data)


@pytest.mark.parametrize("data, reason", [
    (b"\x0a\x07" + bytes(7) + b"\x12\x08" + bytes(8), "lat_deg: packed double length 7 is not a multiple of 8"),
    (b"\x0a\x10" + bytes(8), "lat_deg: truncated packed field"),
    (b"\x0a", "truncated varint"),
])
def test_undecodable_request_bytes_are_invalid_argument_with_the_reason(address, client, data, reason):
    """gRPC maps an exception in a request deserializer to INTERNAL and drops its message; the
    service hands the decoder's reason to the caller as INVALID_ARGUMENT, and keeps serving."""
    with grpc.insecure_channel(address) as channel:
        raw = channel.unary_unary("/sortie.v1.TerrainService/GetHeights", request_serializer=lambda b: b,
                                  response_deserializer=lambda b: b)
        with pytest.raises(grpc.RpcError) as info:
            raw(data, timeout=10)
    assert info.value.code() == grpc.StatusCode.INVALID_ARGUMENT
    assert info.value.details() == f"request: does not decode as a GetHeights request: {reason}"
    assert client.heights([47.5], [9.5]).status[0] == STATUS_OK


def test_the_client_answers_like_the_in_process_terrain_on_edge_inputs(alps, client):
    """Empty batches get empty results of the same dtypes without a call (the service refuses
    them), and n_samples is checked as Terrain.profile checks it, before anything is sent."""
    for name, args in (("heights", ([], [])), ("normals", ([], [])), ("line_of_sight", ([],) * 6),
                       ("intersect", ([],) * 6)):
        remote, local = getattr(client, name)(*args), getattr(alps, name)(*args)
        for f in dataclasses.fields(local):
            assert _same(getattr(remote, f.name), getattr(local, f.name)), (name, f.name)
    for bad, message in ((2.7, "must be an integer"), (-1, "must be at least 2"), (True, "must be an integer")):
        for terrain in (client, alps):
            with pytest.raises(InvalidArgument, match=f"n_samples: {message}"):
                terrain.profile(47.1, 9.1, 47.2, 9.2, bad)


def test_codec_without_copy_decodes_read_only_views():
    """The server's request decoder: arrays are views of the message, not copies;
    decoding with copies (the client's responses) gives arrays of their own."""
    lat, lon = _points(100, seed=31)
    data = PackedCodec(pb.GetHeightsRequest).encode({"lat_deg": lat, "lon_deg": lon})
    viewed = PackedCodec(pb.GetHeightsRequest, copy=False).decode(data)
    copied = PackedCodec(pb.GetHeightsRequest).decode(data)
    for name, want in (("lat_deg", lat), ("lon_deg", lon)):
        assert _same(viewed[name], want) and _same(copied[name], want)
        assert not viewed[name].flags.writeable and not viewed[name].flags.owndata
        assert copied[name].flags.writeable and copied[name].flags.owndata
    status = np.array([1, 2, 3], np.uint8)
    resp = PackedCodec(pb.GetHeightsResponse).encode({"height_msl_m": np.zeros(3), "status": status})
    assert _same(PackedCodec(pb.GetHeightsResponse, copy=False).decode(resp)["status"], status)
    request_decoder = terrain_service.serializers("GetHeights")[1]
    assert not request_decoder(data)["lat_deg"].flags.writeable


# --- the command line ------------------------------------------------------------------------

@pytest.mark.parametrize("argv", [["terrain"], ["terrain", "serve"], ["terrain", "info"], ["terrain", "query"]])
def test_cli_help(argv, capsys):
    with pytest.raises(SystemExit) as info:
        cli.main([*argv, "--help"])
    assert info.value.code == 0
    assert "usage: sortie terrain" in capsys.readouterr().out


def test_cli_query_and_info(address, alps, hgt_alps, capsys):
    assert cli.main(["terrain", "query", "--address", address, "47.25", "9.25", "-47", "9"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert lines[1].split() == ["47.250000", "9.250000", f"{alps.heights([47.25], [9.25]).height_msl_m[0]:.2f}",
                                "OK"]
    assert lines[2].split()[-2:] == ["nan", "OUTSIDE"]
    assert cli.main(["terrain", "info", "--dem", str(hgt_alps)]) == 0
    local = capsys.readouterr().out
    assert "lat 47.000000 .. 48.000000 deg" in local and "1201 rows x 1201 cols" in local
    assert f"file: {hgt_alps.resolve()} (2,884,802 bytes, sha256 " in local
    assert cli.main(["terrain", "info", "--address", address]) == 0
    assert "lat 47.000000 .. 48.000000 deg" in capsys.readouterr().out


@pytest.mark.parametrize("port, message", [("70000", "a port is 0 ..= 65535, got 70000"),
                                           ("-5", "a port is 0 ..= 65535, got -5"),
                                           ("http", "a port is an integer 0 ..= 65535, got 'http'")])
def test_ports_out_of_range_are_refused_by_every_command(port, message, capsys):
    """Sockets keep a port's low 16 bits: 70000 would serve quietly on 4464. Every --port and
    --metrics-port of every command takes 0 ..= 65535."""
    for argv in (["terrain", "serve", "--procedural", "1", f"--port={port}"],
                 ["terrain", "serve", "--procedural", "1", "--port", "0", f"--metrics-port={port}"],
                 ["server", "--scenario", "x.toml", f"--port={port}"], ["replay", "x.sortie", f"--port={port}"],
                 ["dis", "--server", "127.0.0.1:1", f"--port={port}"]):
        with pytest.raises(SystemExit) as info:
            cli.main(argv)
        assert info.value.code == 2
        assert message in capsys.readouterr().err, argv


def test_cli_serve_needs_a_terrain(capsys):
    assert cli.main(["terrain", "serve", "--port", "0"]) == 2
    assert "give at least one DEM file, --store PATH or --procedural SEED" in capsys.readouterr().err


def test_cli_serve_subprocess_stops_cleanly_on_sigterm(alps, hgt_alps):
    assert SORTIE.exists(), f"console script {SORTIE} missing: run `make bootstrap`"
    proc = subprocess.Popen([str(SORTIE), "terrain", "serve", "--dem", str(hgt_alps), "--port", "0"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        line = _readline(proc, SUBPROCESS_TIMEOUT_S)
        if not line.startswith("sortie terrain service listening on 127.0.0.1:"):
            proc.kill()
            pytest.fail(f"unexpected first line {line!r}; stderr: {proc.communicate()[1]}")
        address = line.split()[-1]
        lat, lon = _points(5000, seed=9)
        with TerrainClient(address) as c:
            got = c.heights(lat, lon)
        assert _same(got.height_msl_m, alps.heights(lat, lon).height_msl_m)
        with grpc.insecure_channel(address) as channel:
            health = health_pb2_grpc.HealthStub(channel).Check(health_pb2.HealthCheckRequest(service=SERVICE_NAME))
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        proc.terminate()  # SIGTERM
        out, err = proc.communicate(timeout=SUBPROCESS_TIMEOUT_S)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 0, err
    assert "sortie terrain service stopped" in out


def _readline(proc: subprocess.Popen, timeout_s: float) -> str:
    """First stdout line of proc, failing (not hanging) if none comes within timeout_s."""
    lines = []
    reader = threading.Thread(target=lambda: lines.append(proc.stdout.readline()), daemon=True)
    reader.start()
    reader.join(timeout_s)
    if not lines:
        pytest.fail(f"no output from {proc.args} within {timeout_s} s")
    return lines[0].strip()


def test_client_splits_large_batches_and_keeps_error_indices(address, alps):
    """Batches beyond a chunk go as pipelined chunks: same answers, in order; an error
    in a later chunk names the caller's index, not the chunk's."""
    with TerrainClient(address, chunk_points=1000, chunk_rays=7, max_in_flight=3) as small:
        lat, lon = _points(3500, seed=11)
        assert _same(small.heights(lat, lon).height_msl_m, alps.heights(lat, lon).height_msl_m)
        normals = small.normals(lat, lon)
        assert _same(normals.normal_enu, alps.normals(lat, lon).normal_enu)
        rays = _rays(30, seed=12)
        assert _same(small.line_of_sight(*rays).visible, alps.line_of_sight(*rays).visible)
        assert _same(small.intersect(*rays).distance_m, alps.intersect(*rays).distance_m)
        lat[2500] = math.inf
        with pytest.raises(InvalidArgument, match=r"^lat_deg\[2500\]: must be finite") as info:
            small.heights(lat, lon)
        assert info.value.index == 2500
        a_lat, a_lon, a_h, b_lat, b_lon, b_h = rays
        b_h[23] = math.nan
        with pytest.raises(InvalidArgument, match=r"^b_height_msl_m\[23\]: "):
            small.line_of_sight(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    with pytest.raises(InvalidArgument, match="^max_in_flight: "):
        TerrainClient(address, max_in_flight=0)
