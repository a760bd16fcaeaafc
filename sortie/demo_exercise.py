"""The demo's live exercise: simulation server + bots + gateways + an observer, bounded in time.

``sortie server`` runs the example scenario (data/scenarios/alps.toml) over
the demo's terrain *service* (server and clients use the same terrain
answers), ``sortie bot`` takes two controllable agents in its own process and
flies/drives patrol boxes, ``sortie dis`` and ``sortie tacview`` bridge the
exercise to DIS and to Tacview (sortie/demo_interop.py plays their peers: a
DIS simulator whose tank joins the exercise, and a Tacview client), and this
process watches as an observer, printing the dead-reckoned picture and
writing it to ``exercise.json``. The server records the sortie into
``sortie.sortie`` (sortie/demo_debrief.py replays, re-simulates and exports
it).
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
FOLLOW = "viper1"  # the render client's chase camera follows this aircraft
VIEW_FRAMES, VIEW_FPS, VIEW_SIZE = 24, 3.0, "640x360"


def _process(args: list[str], log: Path) -> tuple[subprocess.Popen, object]:
    from server.process import sortie_command

    f = open(log, "w")
    return subprocess.Popen([*sortie_command(), *args], stdout=f, stderr=subprocess.STDOUT), f


def _stop(proc: subprocess.Popen, log_file) -> int:
    """SIGTERM, wait (the services stop within their grace period), the exit code."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=30.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    log_file.close()
    return proc.returncode


def _connect_tacview(port: int, path: Path, proc: subprocess.Popen):
    from sortie.demo_interop import TacviewCapture

    deadline = time.monotonic() + 30.0
    while True:
        try:
            return TacviewCapture(port, path).start()
        except OSError:
            if proc.poll() is not None or time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _render_summary(frames_dir: Path, exit_code: int) -> dict:
    """The render client's figures, and its frames as an animated GIF (Pillow) for a quick look."""
    from PIL import Image

    frames = sorted(frames_dir.glob("frame_*.png"))
    summary = {"exit_code": exit_code, "frames": len(frames), "dir": str(frames_dir)}
    info = frames_dir / "summary.json"
    if info.exists():
        summary["client"] = json.loads(info.read_text())
    if frames:
        images = [Image.open(f).convert("RGB") for f in frames]
        gif = frames_dir / "flight.gif"
        images[0].save(gif, save_all=True, append_images=images[1:], duration=int(1000 / VIEW_FPS), loop=0)
        summary["gif"] = str(gif)
    return summary


def run_exercise(terrain_address: str, out: Path, console) -> dict:
    from rich.table import Table

    from client.sim_client import SimClient
    from client.terrain_client import TerrainClient
    from server.process import ServiceProcess, free_port, sortie_command
    from sortie.demo_interop import DIS_EXERCISE, PEER_START, DisPeer
    from terrain.geodesy import ecef_to_geodetic

    recording = out / "sortie.sortie"
    recording.unlink(missing_ok=True)  # a recording is never overwritten: this demo's run replaces the last one's
    server = ServiceProcess(["server", "--scenario", str(SCENARIO), "--terrain", terrain_address,
                             "--record", str(recording)], log=out / "simulation-server.log")
    console.print(f"[bold]simulation server[/]: {' '.join(server.command)}")
    with server:
        dis_port, tacview_port = free_port(), free_port()
        dis_args = ["dis", "--server", server.address, "--port", str(dis_port), "--exercise", str(DIS_EXERCISE)]
        tacview_args = ["tacview", "--server", server.address, "--port", str(tacview_port)]
        console.print(f"[bold]DIS gateway[/]: sortie {' '.join(dis_args)}")
        console.print(f"[bold]Tacview telemetry[/]: sortie {' '.join(tacview_args)}")
        dis_proc, dis_log = _process(dis_args, out / "dis-gateway.log")
        tacview_proc, tacview_log = _process(tacview_args, out / "tacview.log")
        with TerrainClient(terrain_address) as tc:
            ground = float(tc.heights(np.array([PEER_START[0]]), np.array([PEER_START[1]])).height_msl_m[0])
        peer = DisPeer(dis_port, terrain_height_m=ground).start()
        capture = _connect_tacview(tacview_port, out / "tacview-live.acmi", tacview_proc)
        frames_dir = out / "frames"
        view_args = ["view", "--server", server.address, "--follow", FOLLOW, "--chase", "--terrain", terrain_address,
                     "--frames", str(VIEW_FRAMES), "--fps", str(VIEW_FPS), "--size", VIEW_SIZE, "--out",
                     str(frames_dir)]
        console.print(f"[bold]render client[/]: sortie {' '.join(view_args)}")
        view_proc, view_log = _process(view_args, out / "render-client.log")
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
                             "lon_deg": float(lon[k]), "height_m": float(h[k]), "moved_m": moved,
                             "external_id": info.external_id if info else ""})
            summary = {"world_time_s": world.time_s, "entities": len(ids), "updates": picture.updates,
                       "states_received": picture.states_received, "bytes": picture.bytes,
                       "entities_seen": rows}
            sim.leave()
        bots.wait(timeout=60.0)
        bots_log.close()
        summary["bots"] = (out / "bots.log").read_text().strip().splitlines()
        try:
            view_proc.wait(timeout=120.0)
        except subprocess.TimeoutExpired:
            pass
        summary["render"] = _render_summary(frames_dir, _stop(view_proc, view_log))
        summary["tacview"] = capture.close()
        summary["tacview"]["telemetry_exit_code"] = _stop(tacview_proc, tacview_log)
        gateway_exit = _stop(dis_proc, dis_log)  # its last PDUs deactivate every entity it sent
        time.sleep(0.3)
        summary["dis"] = peer.close(out / "dis-capture.pcap")
        summary["dis"]["gateway_exit_code"] = gateway_exit
        summary["dis"]["gateway_log"] = (out / "dis-gateway.log").read_text().strip().splitlines()[-1:]
    summary["recording"] = str(recording)  # closed (footer written) when the server stopped
    table = Table(title=f"live exercise: {world.exercise_name} (observer, dead-reckoned picture at "
                        f"t = {summary['world_time_s']:.0f} s)")
    for col in ("entity", "type", "side", "from", "lat", "lon", "height m", "moved m"):
        table.add_column(col, justify="left" if col in ("entity", "type", "side", "from") else "right")
    for r in rows:
        table.add_row(r["name"], r["type"], r["coalition"], r["external_id"] or "sortie", f"{r['lat_deg']:.4f}",
                      f"{r['lon_deg']:.4f}", f"{r['height_m']:.0f}", f"{r['moved_m']:.0f}")
    console.print(table)
    console.print(f"observer: {summary['updates']} updates, {summary['states_received']} entity states, "
                  f"{summary['bytes']:,} bytes in {WATCH_S:.0f} s; bots: {'; '.join(summary['bots'])}")
    d, tv = summary["dis"], summary["tacview"]
    ws = d["wireshark"]
    checked = (f"Wireshark's dissector: {ws['entity_state_pdus']} Entity State PDUs, {ws['malformed']} malformed"
               if ws["checked"] else ws.get("why", "tshark failed"))
    console.print(f"DIS: the peer received {d['pdus_from_exercise']} PDUs about {d['entities_from_exercise']} "
                  f"entities ({d['deactivated_on_stop']} deactivated at stop), sent {d['peer_pdus_sent']} about its "
                  f"tank; {checked}; capture {d['pcap']}")
    rs = summary["render"]
    console.print(f"render client: {rs['frames']} frames following {FOLLOW} (chase camera) in {rs['dir']}"
                  + (f", animation {rs['gif']}" if "gif" in rs else ""))
    console.print(f"Tacview: {tv['frames']} live frames, {tv['objects']} objects, {tv['bytes']:,} bytes of ACMI "
                  f"-> {tv['acmi']}")
    (out / "exercise.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary
