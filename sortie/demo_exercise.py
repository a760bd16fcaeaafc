"""The demo's live exercise: simulation server + bots + an observer, bounded in time.

``sortie server`` runs the example scenario (data/scenarios/alps.toml) over
the demo's terrain *service* (server and clients use the same terrain
answers), ``sortie bot`` takes two controllable agents in its own process and
flies/drives patrol boxes, and this process watches as an observer, printing
the dead-reckoned picture and writing it to ``exercise.json``. The server
records the sortie into ``sortie.sortie`` (sortie/demo_debrief.py replays,
re-simulates and exports it).
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
SCENARIO = REPO / "data" / "scenarios" / "alps.toml"
WATCH_S = 12.0


def run_exercise(terrain_address: str, out: Path, console) -> dict:
    from rich.table import Table

    from client.sim_client import SimClient
    from server.process import ServiceProcess, sortie_command
    from terrain.geodesy import ecef_to_geodetic

    recording = out / "sortie.sortie"
    recording.unlink(missing_ok=True)  # a recording is never overwritten: this demo's run replaces the last one's
    server = ServiceProcess(["server", "--scenario", str(SCENARIO), "--terrain", terrain_address,
                             "--record", str(recording)], log=out / "simulation-server.log")
    console.print(f"[bold]simulation server[/]: {' '.join(server.command)}")
    with server:
        bots_log = open(out / "bots.log", "w")
        bots = subprocess.Popen([*sortie_command(), "bot", "--server", server.address, "--count", "2",
                                 "--duration", str(WATCH_S), "--leg-s", "4"], stdout=bots_log,
                                stderr=subprocess.STDOUT)
        with SimClient(server.address) as sim:
            sim.join("demo-observer", "observer", observer=(47.40, 9.50, 100_000.0))
            picture = sim.watch()
            picture.snapshot_received.wait(10.0)
            first = {}
            t_end = time.monotonic() + WATCH_S
            while time.monotonic() < t_end:
                ids, pos, _ = picture.state()
                for i, p in zip(ids.tolist(), pos):
                    first.setdefault(i, p)
                time.sleep(0.5)
            ids, pos, _ = picture.state()
            lat, lon, h = ecef_to_geodetic(pos) if len(ids) else (np.zeros(0),) * 3
            world = sim.world()
            rows = []
            for k, i in enumerate(ids.tolist()):
                info = picture.infos.get(i)
                moved = float(np.linalg.norm(pos[k] - first.get(i, pos[k])))
                rows.append({"name": info.name if info else str(i), "type": info.type if info else "",
                             "coalition": info.coalition if info else "", "lat_deg": float(lat[k]),
                             "lon_deg": float(lon[k]), "height_m": float(h[k]), "moved_m": moved})
            summary = {"world_time_s": world.time_s, "entities": len(ids), "updates": picture.updates,
                       "states_received": picture.states_received, "bytes": picture.bytes,
                       "entities_seen": rows}
            sim.leave()
        bots.wait(timeout=60.0)
        bots_log.close()
        summary["bots"] = (out / "bots.log").read_text().strip().splitlines()
    summary["recording"] = str(recording)  # closed (footer written) when the server stopped
    table = Table(title=f"live exercise: {world.exercise_name} (observer, dead-reckoned picture at "
                        f"t = {summary['world_time_s']:.0f} s)")
    for col in ("entity", "type", "side", "lat", "lon", "height m", "moved m"):
        table.add_column(col, justify="left" if col in ("entity", "type", "side") else "right")
    for r in rows:
        table.add_row(r["name"], r["type"], r["coalition"], f"{r['lat_deg']:.4f}", f"{r['lon_deg']:.4f}",
                      f"{r['height_m']:.0f}", f"{r['moved_m']:.0f}")
    console.print(table)
    console.print(f"observer: {summary['updates']} updates, {summary['states_received']} entity states, "
                  f"{summary['bytes']:,} bytes in {WATCH_S:.0f} s; bots: {'; '.join(summary['bots'])}")
    (out / "exercise.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
