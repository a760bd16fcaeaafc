"""The demo's terrain store: import the DEMs once, serve the store, stream it to a
thin client, synthesise textures from it.

* ``sortie terrain import`` builds ``OUT/store`` (``out/demo/store``) from the demo's DEMs with a
  progress bar on the first run (later runs find it finished and reuse it;
  an interrupted one resumes).
* ``sortie terrain serve --store`` serves it as its own process; a thin
  client that holds no DEM streams the quad-tree cells around a viewer over
  the Alps at every level (GetTile, the per-level radius of 3.5 cells of
  global-terrain-flight-sim §5), and its heights are compared with the
  DEM-backed service's at random points.
* ``sortie terrain texture --store`` writes the land classes, light map and
  composite of a box of the Alps for a summer morning.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

VIEWER_LAT_LON = (47.25, 9.55)  # over the Alpine Rhine valley near Vaduz
CACHE_RADIUS_CELLS = 3.5
TEXTURE_BOX = ("47.05", "9.35", "47.30", "9.75")
TEXTURE_TIME = "2026-06-21T07:30:00Z"


def build_store(dems: list[Path], store: Path, console) -> dict:
    """The store of the demo's DEMs, imported unless a finished one of the same files is there."""
    manifest = store / "store.json"
    wanted = sorted(str(p.resolve()) for p in dems)
    if manifest.is_file():
        m = json.loads(manifest.read_text())
        from terrain.store import FORMAT_VERSION

        if (m.get("summary") and m.get("version") == FORMAT_VERSION
                and sorted(s["path"] for s in m["sources"]) == wanted):
            console.print(f"[bold]terrain store[/]: reusing {store} (built earlier from the same DEMs)")
            return m["summary"]
    command = [sys.executable, "-m", "sortie.cli", "terrain", "import", *wanted, "-o", str(store)]
    console.print(f"[bold]terrain store[/]: {' '.join(command[2:])}")
    subprocess.run(command, check=True)
    return json.loads(manifest.read_text())["summary"]


def stream_to_thin_client(store_address: str, dem_address: str, console) -> dict:
    """Tiles around a viewer at every level, over gRPC; heights checked against the DEMs."""
    from client.terrain_client import TerrainClient
    from sortie.errors import NotFound
    from terrain import quadtree

    lat, lon = VIEWER_LAT_LON
    out = {"viewer": [lat, lon], "radius_cells": CACHE_RADIUS_CELLS, "levels": []}
    with TerrainClient(store_address) as thin, TerrainClient(dem_address) as full:
        meta = thin.metadata()["sources"][0]
        details = meta.get("details", {})
        depth = int(details.get("store_depth", meta.get("store_depth", 0)))
        levels = int(details.get("store_levels", meta.get("store_levels", 0)))
        t0 = time.perf_counter()
        wire = 0
        tiles = 0
        for level in range(levels):
            cells = quadtree.cells_within(lat, lon, depth - level, CACHE_RADIUS_CELLS)
            got = 0
            for cid in cells:
                try:
                    grid = thin.get_tile(int(cid))
                except NotFound:  # a cell of the radius beyond the store's data: nothing to stream
                    continue
                got += 1
                wire += grid.wire_bytes
            tiles += got
            out["levels"].append({"level": level, "depth": depth - level, "cells": int(cells.size), "tiles": got})
        out["stream_s"] = time.perf_counter() - t0
        out["tiles"] = tiles
        out["wire_bytes"] = wire
        rng = np.random.default_rng(3)
        qlat = rng.uniform(47.02, 47.98, 20_000)
        qlon = rng.uniform(9.02, 9.98, 20_000)
        a = thin.heights(qlat, qlon)
        b = full.heights(qlat, qlon)
        ok = (a.status == 1) & (b.status == 1)
        d = a.height_msl_m[ok] - b.height_msl_m[ok]
        out["heights_vs_dem"] = {"points": int(ok.sum()), "rms_m": float(np.sqrt(np.mean(d ** 2))),
                                 "max_m": float(np.abs(d).max())}
    console.print(f"thin client: {tiles} tiles at {levels} levels around {lat}, {lon} "
                  f"({wire / 1e6:.1f} MB on the wire, zstd of centimetres) in {out['stream_s']:.1f} s; heights against the "
                  f"DEM service: RMS {out['heights_vs_dem']['rms_m']:.2f} m, max {out['heights_vs_dem']['max_m']:.1f} m "
                  f"at {out['heights_vs_dem']['points']:,} points")
    return out


def run_store(dems: list[Path], dem_address: str, out: Path, console) -> dict:
    from server.process import ServiceProcess

    store = out / "store"  # inside --out, reused by the next demo into the same folder
    summary = build_store(dems, store, console)
    console.print(f"store: {summary['regions']} regions, {summary['levels']} levels, {summary['posts']:,} posts in "
                  f"{summary['stored_bytes'] / 1e6:.1f} MB ({summary['ratio_vs_int16']:.1f}:1 against int16), "
                  f"quantisation error max {summary['max_quantisation_error_m']:.2f} m, against the source posts "
                  f"RMS {summary['rms_error_vs_source_m']:.2f} m")
    result = {"store": str(store), "import": summary}
    service = ServiceProcess(["terrain", "serve", "--store", str(store)], log=out / "terrain-store-service.log")
    console.print(f"[bold]terrain service over the store[/]: {' '.join(service.command)}")
    with service:
        result["thin_client"] = stream_to_thin_client(service.address, dem_address, console)
    texture_dir = out / "texture"
    command = [sys.executable, "-m", "sortie.cli", "terrain", "texture", "--store", str(store),
               "--bbox", *TEXTURE_BOX, "--time", TEXTURE_TIME, "-o", str(texture_dir)]
    console.print(f"[bold]texture[/]: {' '.join(command[2:])}")
    subprocess.run(command, check=True)
    result["texture"] = json.loads((texture_dir / "texture.json").read_text())
    (out / "store.json").write_text(json.dumps(result, indent=2) + "\n")
    return result
