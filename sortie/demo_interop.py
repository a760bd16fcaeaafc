"""The demo's interoperability part: the live exercise as other simulators see it.

``sortie dis`` and ``sortie tacview`` run against the demo's simulation server
as their own processes, as deployed. This process plays the other side:

- :class:`DisPeer`, a DIS simulator on the loopback broadcast port: it keeps
  every Entity State PDU the gateway sends (``dis-capture.pcap``, which
  Wireshark opens; checked here with tshark's DIS dissector when tshark is
  installed) and sends one entity of its own, a red tank driving east along
  the Rhine valley road, which the gateway publishes into the exercise as an
  external entity ("dis:42.4.1");
- :class:`TacviewCapture`, a client of the real-time telemetry protocol (the
  handshake Tacview sends, then the live ACMI it receives, saved as
  ``tacview-live.acmi``, a file Tacview opens).
"""

from __future__ import annotations

import math
import re
import shutil
import socket
import subprocess
import threading
import time
from pathlib import Path

import numpy as np

from server import dis
from server.pcap import write_pcap

DIS_EXERCISE = 1
PEER_ENTITY = (42, 4, 1)  # site, application, entity of the demo's "other simulator"
PEER_START = (47.2405, 9.5220)  # on the Rhine valley floor near Buchs SG (lat, lon)
PEER_SPEED_MPS = 12.0
PEER_SEND_EVERY_S = 1.0  # well inside the 5 s heartbeat, so the remote entity never times out


def _tank_state(t_s: float, terrain_height_m: float):
    """ECEF position, ECEF velocity and quaternion ECEF -> body of the peer's tank, driving
    east at PEER_SPEED_MPS since t = 0 (a straight line on the local tangent plane)."""
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat
    from terrain.geodesy import enu_basis, geodetic_to_ecef

    lat, lon = PEER_START
    east = np.asarray(enu_basis(lat, lon)[0]).reshape(3)
    start = np.asarray(geodetic_to_ecef(lat, lon, terrain_height_m), float).reshape(3)
    quat = ned_to_ecef_quat(euler_to_quaternion(0.0, 0.0, math.pi / 2), lat, lon)
    return start + PEER_SPEED_MPS * t_s * east, PEER_SPEED_MPS * east, np.asarray(quat, float).reshape(4)


class DisPeer:
    """Another DIS simulator on (host, port): receives what the exercise sends, sends a tank."""

    def __init__(self, port: int, host: str = "127.255.255.255", terrain_height_m: float = 450.0):
        self.address = (host, port)
        self.terrain_height_m = terrain_height_m
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        self.sock.settimeout(0.2)
        self.sock.bind(self.address)
        self.received: list = []  # (unix time, datagram) from the exercise's gateway
        self.entities: dict = {}  # DIS entity id -> marking, of what the gateway sent
        self.deactivated: set = set()
        self.sent = 0
        self._stop = threading.Event()
        self._t0 = time.monotonic()
        self._threads = [threading.Thread(target=self._receive, daemon=True, name="dis-peer-rx"),
                         threading.Thread(target=self._send, daemon=True, name="dis-peer-tx")]

    def start(self) -> DisPeer:
        for t in self._threads:
            t.start()
        return self

    def _receive(self) -> None:
        while not self._stop.is_set():
            try:
                data = self.sock.recv(65536)
            except socket.timeout:
                continue
            except OSError:
                return
            try:
                pdus = [dis.decode_pdu(d) for d in dis.split_datagram(data)]
            except Exception:  # noqa: BLE001 - the demo counts only what it can read
                continue
            ours = [p for p in pdus if isinstance(p, dis.EntityStatePdu) and tuple(p.entity_id[:2]) != PEER_ENTITY[:2]]
            if ours:
                self.received.append((time.time(), data))
            for p in ours:
                self.entities[tuple(p.entity_id)] = p.marking_text
                if p.appearance & dis.APPEARANCE_DEACTIVATED:
                    self.deactivated.add(tuple(p.entity_id))

    def _send(self) -> None:
        while not self._stop.wait(0.0 if self.sent == 0 else PEER_SEND_EVERY_S):
            self.send_tank(deactivated=False)

    def send_tank(self, deactivated: bool) -> None:
        pos, vel, quat = _tank_state(time.monotonic() - self._t0, self.terrain_height_m)
        pdu = dis.entity_state_pdu(
            exercise_id=DIS_EXERCISE, entity_id=PEER_ENTITY, kind="ground", type_name="t72", coalition="red",
            name="T72 PEER", ecef_m=pos, vel_ecef_mps=vel, acc_ecef_mps2=(0.0, 0.0, 0.0), quat_wxyz=quat,
            body_rates_rps=(0.0, 0.0, 0.0), algorithm=dis.DR_FPW, timestamp=0,
            appearance=dis.APPEARANCE_DEACTIVATED if deactivated else 0)
        self.sock.sendto(dis.encode_pdu(pdu), self.address)
        self.sent += 1

    def close(self, pcap_path: Path) -> dict:
        """Stop (the tank says deactivated), write the capture; figures."""
        self._stop.set()
        for t in self._threads:
            t.join(5.0)
        self.send_tank(deactivated=True)
        self.sock.close()
        write_pcap(pcap_path, [d for _, d in self.received], self.address[1], [t for t, _ in self.received])
        return {"pdus_from_exercise": len(self.received), "entities_from_exercise": len(self.entities),
                "deactivated_on_stop": len(self.deactivated), "peer_pdus_sent": self.sent, "pcap": str(pcap_path),
                "wireshark": tshark_check(pcap_path, self.address[1])}


def tshark_check(pcap: Path, port: int) -> dict:
    """Run the capture through Wireshark's DIS dissector (tshark), when installed."""
    exe = shutil.which("tshark")
    if exe is None:
        return {"checked": False, "why": "tshark is not installed (make bootstrap installs it)"}
    r = subprocess.run([exe, "-r", str(pcap), "-d", f"udp.port=={port},dis", "-V"], capture_output=True, text=True,
                       timeout=120)
    text = r.stdout
    return {"checked": r.returncode == 0, "entity_state_pdus": len(re.findall(r"PDU type: Entity State", text, re.I)),
            "malformed": text.count("Malformed"), "expert_errors": text.count("[Severity level: Error]")}


class TacviewCapture:
    """A Tacview real-time telemetry client: handshake, then save the live ACMI it gets."""

    def __init__(self, port: int, path: Path, host: str = "127.0.0.1"):
        from server.tacview_live import client_handshake

        self.path = path
        self.sock = socket.create_connection((host, port), timeout=10.0)
        self.sock.settimeout(0.2)
        self.sock.sendall(client_handshake("sortie-demo"))
        self.bytes = 0
        self._stop = threading.Event()
        self._file = open(path, "wb")
        self._thread = threading.Thread(target=self._run, daemon=True, name="tacview-capture")

    def start(self) -> TacviewCapture:
        self._thread.start()
        return self

    def _run(self) -> None:
        handshake_done = False
        pending = b""
        while not self._stop.is_set():
            try:
                chunk = self.sock.recv(1 << 16)
            except socket.timeout:
                continue
            except OSError:
                return
            if not chunk:
                return
            if not handshake_done:  # the host's handshake ends with a NUL; the ACMI text follows
                pending += chunk
                if b"\0" not in pending:
                    continue
                chunk = pending.split(b"\0", 1)[1]
                handshake_done = True
            self._file.write(chunk)
            self.bytes += len(chunk)

    def close(self) -> dict:
        self._stop.set()
        self._thread.join(5.0)
        self.sock.close()
        self._file.close()
        text = self.path.read_text(encoding="utf-8", errors="replace")
        objects = {line.split(",", 1)[0] for line in text.splitlines()
                   if line and line[0] not in "#-/" and not line.startswith(("0,", "FileType", "FileVersion"))}
        return {"acmi": str(self.path), "bytes": self.bytes,
                "frames": sum(1 for line in text.splitlines() if line.startswith("#")),
                "objects": len(objects), "header_ok": text.startswith("FileType=text/acmi/tacview")}
