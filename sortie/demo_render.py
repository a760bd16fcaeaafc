"""The demo's render part (issue #5): a headless client follows a bot aircraft over the
Grand Canyon with the geometry clipmap, and a ground vehicle's view of its target area.

``sortie server`` runs data/scenarios/grand_canyon.toml over the demo's terrain service;
``sortie view`` (the render client, client/render_cli.py) follows viper1 with a chase
camera (the fast-jet LOD profile) and writes PNG frames, an animated GIF of them and its
per-frame HUD log; a second ``sortie view`` renders the tank's cockpit view over the
scenario's target area.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "data" / "scenarios" / "grand_canyon.toml"
FRAMES, FPS, SIZE = 24, 4.0, "640x360"


def _view(server: str, terrain: str, out: Path, log: Path, *args: str) -> dict:
    from server.process import sortie_command

    with open(log, "w") as f:
        code = subprocess.run([*sortie_command(), "view", "--server", server, "--terrain", terrain, "--out", str(out),
                               *args], stdout=f, stderr=subprocess.STDOUT, timeout=600).returncode
    summary = json.loads((out / "summary.json").read_text()) if (out / "summary.json").exists() else {}
    return {"exit_code": code, "dir": str(out), "log": str(log), "frames": len(summary.get("pngs", [])),
            "profile": summary.get("profile"), "frame_ms_median": summary.get("frame_ms", {}).get("median"),
            "triangles_median": summary.get("triangles", {}).get("median"),
            "update_ms_median": summary.get("update_ms", {}).get("median"),
            "samples_max": summary.get("terrain_samples", {}).get("max"), "pngs": summary.get("pngs", [])}


def _gif(pngs: list[str], path: Path, fps: float) -> str | None:
    from PIL import Image

    if not pngs:
        return None
    images = [Image.open(p).convert("RGB") for p in pngs]
    images[0].save(path, save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return str(path)


def run_render(terrain_address: str, out: Path, console) -> dict:
    from server.process import ServiceProcess

    out = out / "canyon"
    out.mkdir(parents=True, exist_ok=True)
    server = ServiceProcess(["server", "--scenario", str(SCENARIO), "--terrain", terrain_address, "--no-record"],
                            log=out / "simulation-server.log")
    console.print(f"[bold]simulation server (Grand Canyon)[/]: {' '.join(server.command)}")
    with server:
        flight = _view(server.address, terrain_address, out / "flight", out / "render-flight.log", "--follow",
                       "viper1", "--chase", "--frames", str(FRAMES), "--fps", str(FPS), "--size", SIZE)
        flight["gif"] = _gif(flight["pngs"], out / "flight.gif", FPS)
        ground = _view(server.address, terrain_address, out / "tank", out / "render-tank.log", "--follow", "tank1",
                       "--frames", "1", "--fps", "1", "--size", SIZE)
    summary = {"flight": flight, "ground": ground}
    console.print(f"render client over the Grand Canyon: {flight['frames']} frames following viper1 "
                  f"(profile {flight['profile']}, median {flight['frame_ms_median'] or 0:.0f} ms a frame, "
                  f"{flight['triangles_median'] or 0:,.0f} triangles) in {flight['dir']}, animation {flight['gif']}; "
                  f"the tank's view ({ground['profile']}) in {ground['dir']}")
    (out / "render.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
