"""The demo's debrief: the live exercise's recording replayed at 8x with a seek,
re-simulated bit for bit, and exported to Tacview and as a glTF scene.

The simulation server of sortie/demo_exercise.py records its sortie into
``out/sortie.sortie``; this step serves it with ``sortie replay`` (a real
process on loopback), watches it as an observer at 8x, seeks back to the
middle and checks the dead-reckoned picture against the recorded states,
re-simulates it from the scenario with its recorded inputs (in process, on the
DEM files and insets the terrain service it was recorded over named, their
SHA-256 checked: no service needed), and exports
it as ``.acmi`` and ``.zip.acmi``, and as ``sortie.glb`` (tracks, events and the
terrain under them: server/gltf.py).
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEM = REPO / "data" / "dem" / "N47E009.hgt"


def run_debrief(recording: Path, out: Path, console) -> dict:
    from rich.table import Table

    from client.sim_client import SimClient
    from server.acmi import export_acmi
    from server.gltf import export_gltf
    from server.process import ServiceProcess
    from server.recording import Recording
    from server.recording_cli import summary
    from server.resim import resimulate
    from server.sim_server import open_terrain_source

    with Recording(recording) as rec:
        info = summary(rec)
    console.print(f"[bold]recording[/]: {recording} ({info['duration_s']:.1f} s, {info['entities']} entities, "
                  f"{info['events']} events, {info['inputs']} inputs, {info['size_bytes']:,} bytes = "
                  f"{info['bytes_per_entity_second']:.0f} bytes per entity second)")

    replay = ServiceProcess(["replay", str(recording), "--speed", "8"], log=out / "replay.log")
    console.print(f"[bold]replay[/]: {' '.join(replay.command)}")
    with replay, SimClient(replay.address) as sim, Recording(recording) as rec:
        sim.join("debrief", "observer", observer=(47.40, 9.50, 150_000.0))
        picture = sim.watch()
        picture.snapshot_received.wait(10.0)
        time.sleep(1.0)  # 8 s of the sortie in 1 s
        played_to = sim.replay_status().time_s
        middle = round(0.5 * (rec.first_time_s + rec.last_time_s), 1)
        sim.replay(seek_time_s=middle)
        sim.replay(pause=True)
        tick = sim.replay_status().tick
        picture.wait_for(lambda p: abs(p.time_s - tick * rec.dt) < 1e-9, 5.0)
        time.sleep(0.3)
        ids, pos, _ = picture.state(tick * rec.dt)
        frame = rec.frame(tick)
        k = np.searchsorted(frame.ids, ids)
        seek_error = float(np.abs(pos - frame.states[k, 0:3]).max()) if ids.size else float("nan")
        sim.leave()
    console.print(f"replayed at 8x to t = {played_to:.1f} s, sought to t = {tick * rec.dt:.2f} s: the observer's "
                  f"picture of {ids.size} entities is within {seek_error * 1e3:.2f} mm of the recorded states")

    # The terrain service is gone: re-simulation opens the DEM files it named (SHA-256 checked)
    # and rebuilds its insets, in process.
    report = resimulate(recording)
    console.print(f"re-simulation: {report.ticks} ticks in {report.wall_s:.1f} s, "
                  f"{'[green]bit-exact[/]' if report.bit_exact else '[red]diverged[/]'} "
                  f"(max position difference {report.max_abs_diff_m:.4f} m; "
                  f"{'the same' if report.same_terrain else '[red]other[/]'} terrain: "
                  f"{'; '.join(n.removeprefix('terrain: ') for n in report.notes)})"
                  + (f"; first divergence {report.first_divergence}" if report.first_divergence else ""))

    table = Table(title="Tacview export")
    for col in ("file", "bytes", "vs recording"):
        table.add_column(col, justify="left" if col == "file" else "right")
    exports = {}
    for name in ("sortie.acmi", "sortie.zip.acmi"):
        path = out / name
        with Recording(recording) as rec:
            export_acmi(rec, path)
        exports[name] = str(path)
        table.add_row(str(path), f"{path.stat().st_size:,}", f"{path.stat().st_size / info['size_bytes']:.2f}x")
    console.print(table)
    # The 3-D debrief scene: tracks, events and the terrain under them (server/gltf.py).
    path = out / "sortie.glb"
    with Recording(recording) as rec:
        scene = export_gltf(rec, path, open_terrain_source(dem=[DEM]))
    exports["sortie.glb"] = str(path)
    console.print(f"[bold]glTF debrief scene[/]: {path} ({scene.tracks} tracks, {scene.markers} animated markers, "
                  f"{scene.events} events, terrain {scene.terrain_vertices:,} vertices, {scene.bytes_written:,} bytes)")
    result = {"recording": info, "replay": {"played_to_s": played_to, "seek_tick": tick,
                                            "seek_max_error_m": seek_error, "entities": int(ids.size)},
              "resim": report.as_dict(), "exports": exports}
    (out / "debrief.json").write_text(json.dumps(result, indent=2, default=str) + "\n")
    return result
