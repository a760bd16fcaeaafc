"""Frame times of the reference renderer (client/render/) at 960x540, by terrain window size.

    sortie bench render [--quick] [--json PATH] [--plots DIR]

For each window configuration (full-resolution half-width, horizon-ring half-width)
and each camera pose over the Alps SRTM tile: the time to build and upload the
mesh (the first frame's update), then the median and best of the following frames
(same pose: draw + read back, no rebuild), with the triangles and vertices drawn.
Figures are from whatever OpenGL the machine has (Mesa llvmpipe without a GPU);
the report's params say which.
"""

from __future__ import annotations

import statistics
from pathlib import Path

from bench.harness import Report

REPO = Path(__file__).resolve().parents[1]
WIDTH, HEIGHT = 960, 540
# (name, half-width of the full-resolution window in km, of the horizon ring in km: 0 = none)
WINDOWS = (("w10", 10.0, 0.0), ("w20", 20.0, 0.0), ("w20_h80", 20.0, 80.0), ("w40_h120", 40.0, 120.0))
# (name, lat, lon, alt MSL m, heading deg, pitch deg): low over the Alpstein, and higher looking down.
POSES = (("low", 47.15, 9.25, 2600.0, 45.0, -8.0), ("high", 47.5, 9.5, 6000.0, 180.0, -20.0))


def _dem() -> Path:
    for base in (REPO.parent / "shared" / "data" / "dem", REPO / "data" / "dem"):
        if (base / "N47E009.hgt").exists():
            return base / "N47E009.hgt"
    raise FileNotFoundError("N47E009.hgt is in neither ../shared/data/dem nor data/dem")


def run(quick: bool = False) -> Report:
    from client.render.camera import Camera
    from client.render.renderer import Renderer
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    terrain = Terrain([read_dem(_dem())])
    frames = 4 if quick else 12
    windows = WINDOWS[1:3] if quick else WINDOWS
    report = Report("render", quick, params={"size": [WIDTH, HEIGHT], "frames_per_pose": frames,
                                             "dem": "N47E009.hgt", "poses": [p[0] for p in POSES]})
    for name, window_km, horizon_km in windows:
        with Renderer(terrain, WIDTH, HEIGHT, window_m=window_km * 1e3, horizon_m=horizon_km * 1e3) as r:
            report.params.setdefault("gl_renderer", r.ctx.info.get("GL_RENDERER"))
            for pose, lat, lon, alt, hdg, pitch in POSES:
                cam = Camera.from_geodetic(lat, lon, alt, hdg, pitch)
                r.render(cam)
                build_ms = r.stats.update_ms
                times = []
                for _ in range(frames):
                    r.render(cam)
                    times.append(r.stats.frame_ms)
                key = f"{name}_{pose}"
                report.metrics[f"{key}_frame_ms_median"] = statistics.median(times)
                report.metrics[f"{key}_frame_ms_best"] = min(times)
                report.metrics[f"{key}_mesh_build_ms"] = build_ms
                report.metrics[f"{key}_triangles"] = r.stats.triangles
                report.metrics[f"{key}_vertices"] = r.stats.vertices
    return report
