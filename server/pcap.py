"""Classic pcap files of UDP datagrams (what Wireshark and tshark read).

A capture of what a gateway sent, for people to open in Wireshark and for the
tests to run through tshark's DIS dissector. Format: the libpcap file format
(https://wiki.wireshark.org/Development/LibpcapFileFormat): a 24-byte global
header (magic 0xA1B2C3D4, version 2.4, LINKTYPE_ETHERNET = 1), then per frame
a 16-byte record header and an Ethernet II + IPv4 (RFC 791) + UDP (RFC 768)
frame with its lengths and checksums right.
"""

from __future__ import annotations

import socket
import struct
from pathlib import Path

LINKTYPE_ETHERNET = 1
SNAPLEN = 65535


def _checksum(data: bytes) -> int:
    """The Internet checksum (RFC 1071): ones' complement of the ones' complement sum."""
    if len(data) % 2:
        data += b"\0"
    total = sum(struct.unpack(f">{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def udp_frame(payload: bytes, port: int, src: str = "10.0.0.1", dst: str = "10.0.0.255") -> bytes:
    """Ethernet II + IPv4 + UDP around ``payload`` from ``src`` to ``dst``, both UDP ports ``port``."""
    s, d = socket.inet_aton(src), socket.inet_aton(dst)
    length = 8 + len(payload)
    udp_sum = _checksum(s + d + struct.pack(">BBH", 0, 17, length) + struct.pack(">HHHH", port, port, length, 0)
                        + payload) or 0xFFFF
    udp = struct.pack(">HHHH", port, port, length, udp_sum)
    ip = struct.pack(">BBHHHBBH4s4s", 0x45, 0, 20 + length, 0, 0x4000, 64, 17, 0, s, d)
    ip = ip[:10] + struct.pack(">H", _checksum(ip)) + ip[12:]
    return b"\xff" * 6 + b"\x02\x00\x00\x00\x00\x01" + b"\x08\x00" + ip + udp + payload


def write_pcap(path: str | Path, payloads, port: int, times_s=None) -> None:
    """A pcap file of one UDP frame per payload (to ``port``); ``times_s``: each frame's
    Unix time (default one second apart from 2023-11-14)."""
    out = [struct.pack("<IHHiIII", 0xA1B2C3D4, 2, 4, 0, 0, SNAPLEN, LINKTYPE_ETHERNET)]
    for k, p in enumerate(payloads):
        t = 1_700_000_000.0 + k if times_s is None else float(times_s[k])
        frame = udp_frame(p, port)
        sec = int(t)
        out.append(struct.pack("<IIII", sec, int(round((t - sec) * 1e6)) % 1_000_000, len(frame), len(frame)) + frame)
    Path(path).write_bytes(b"".join(out))
