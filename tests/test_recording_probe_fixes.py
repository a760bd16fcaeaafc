"""The recording acceptance probe's findings (/tmp/probe_rec): a target area across the antimeridian in
the glTF scene, damage to a recording's header, a directory given as a recording, and the size the
server prints of its recording.

Real parts: recordings are written by the real writer (synthetic entities, or the alps world) and read
back from real files; the command line runs as real processes (`sortie server` records a real
exercise). The header's damage is made byte by byte, as the probe made it.
"""

from __future__ import annotations

import json
import math
import re
import struct
import subprocess

import numpy as np
import pytest

from server import recording as recording_mod
from server.recording import Recording, RecordingWriter, quantization_of
from server import recording_codec as codec
from sortie.errors import DataFormatError
from sortie.v1 import recording_pb2 as rpb
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic
from test_acmi import info, write_synthetic


def sortie(*args, timeout=120) -> subprocess.CompletedProcess:
    from server.process import sortie_command

    return subprocess.run([*sortie_command(), *map(str, args)], capture_output=True, text=True, timeout=timeout)


# -- 1: a target area across the antimeridian in the glTF scene ---------------------------------------

ANTIMERIDIAN_SCENARIO = """
[exercise]
name = "am"
start_time = 2026-03-01T12:00:00Z
[terrain]
dem = ["N10E179.hgt", "N10W180.hgt"]
[[agents]]
name = "sam"
kind = "static"
type = "sam_site"
coalition = "red"
lat_deg = 10.5
lon_deg = 179.995
[[target_areas]]
name = "box"
polygon = [[10.45, 179.99], [10.45, -179.99], [10.55, -179.99], [10.55, 179.99]]
detail_m = 20.0
"""


def test_outline_of_an_area_across_the_antimeridian_goes_the_short_way():
    from server.gltf import _outline

    polygon = [[10.45, 179.99], [10.45, -179.99], [10.55, -179.99], [10.55, 179.99]]
    out = _outline(polygon, 50.0)
    assert len(out) < 700  # 26.6 km in 50-m pieces, not 78,835 km
    lat, lon = out[:, 0], out[:, 1]
    assert np.all((-180.0 <= lon) & (lon < 180.0))
    assert np.all(np.abs(lon - np.where(lon > 0, 180.0, -180.0)) <= 0.01 + 1e-12)  # never away from 180
    assert np.all((10.45 <= lat) & (lat <= 10.55))
    for v in polygon:  # through every vertex, closed
        assert np.hypot(lat - v[0], lon - v[1]).min() == 0.0
    assert tuple(out[0]) == tuple(out[-1])
    # An area away from the antimeridian is drawn as before: through its vertices, within the box.
    alps = [[47.30, 9.50], [47.30, 9.60], [47.40, 9.60]]
    out = _outline(alps, 50.0)
    assert out[:, 1].min() == 9.50 and out[:, 1].max() == 9.60 and len(out) < 1000


def test_gltf_draws_a_target_area_across_the_antimeridian_short(tmp_path):
    """The probe's area (0.02 deg of longitude either side of 180 by 0.1 deg of latitude): an
    outline of ~26.6 km (2 x (2.19 + 11.06)) with a few hundred vertices, not 78,835 km and 3 M
    vertices in a 67 MB file."""
    from server.gltf import export_gltf
    from terrain.mesh import LocalFrame, gltf_to_enu

    rec = tmp_path / "am.sortie"
    write_synthetic(rec, {1: (info(1, "sam", pb.ENTITY_KIND_STATIC, "sam_site", "red"),
                              lambda t: (10.5, 179.999, 100.0, 0.0, 0.0, 0.0)),
                          2: (info(2, "tank", pb.ENTITY_KIND_GROUND, "m1", "blue"),
                              lambda t: (10.5, -179.98, 100.0, 0.0, 0.0, 90.0))}, ticks=30,
                    scenario=(ANTIMERIDIAN_SCENARIO, str(tmp_path / "am.toml")))
    out = tmp_path / "am.gltf"
    with Recording(rec) as r:
        stats = export_gltf(r, out, None)
    assert stats.target_areas == 1
    assert out.stat().st_size < 1_000_000
    import base64

    j = json.loads(out.read_text())
    buf = base64.b64decode(j["buffers"][0]["uri"].split(",", 1)[1])
    mesh = next(m for m in j["meshes"] if m["name"].startswith("target area"))
    a = j["accessors"][mesh["primitives"][0]["attributes"]["POSITION"]]
    bv = j["bufferViews"][a["bufferView"]]
    v = np.frombuffer(buf, np.float32, a["count"] * 3, bv.get("byteOffset", 0) + a.get("byteOffset", 0))
    v = v.reshape(-1, 3).astype(np.float64)
    assert a["count"] < 2000
    seg = v.reshape(-1, 2, 3)
    length = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1).sum()
    assert length == pytest.approx(2 * (2186.0 + 11061.0), rel=0.01)
    f = j["scenes"][0]["extras"]["sortie"]["frame"]
    assert -180.0 <= f["lon_deg"] < 180.0  # the tracks' box centre (180.0095 unwrapped), as a longitude
    assert f["lon_deg"] == pytest.approx(-179.9905, abs=1e-3)
    lat, lon, _ = ecef_to_geodetic(LocalFrame.at(f["lat_deg"], f["lon_deg"], f["h_m"]).to_ecef(gltf_to_enu(v)))
    assert np.all(np.abs(np.mod(lon, 360.0) - 180.0) <= 0.0101) and np.all(np.abs(lat - 10.5) <= 0.0501)


# -- 2: the header's CRC and ranges -----------------------------------------------------------------

def _synthetic(path, scenario=None) -> None:
    write_synthetic(path, {1: (info(1, "viper", pb.ENTITY_KIND_AIRCRAFT, "f16"),
                               lambda t: (47.3, 9.3 + t * 1e-4, 2000.0, 0.0, 0.0, 90.0))}, ticks=45,
                    scenario=scenario)


SMALL_SCENARIO = ('[exercise]\nname = "x"\nstart_time = 2026-03-01T12:00:00Z\n[terrain]\ndem = ["x.hgt"]\n',
                  "/nowhere/x.toml")


def _header_span(path) -> tuple[int, int]:
    data = path.read_bytes()
    (n,) = struct.unpack("<I", data[8:12])
    return 12, 12 + n


def _flipped(path, out, offset: int, bit: int):
    data = bytearray(path.read_bytes())
    data[offset] ^= 1 << bit
    out.write_bytes(bytes(data))
    return out


def test_a_new_recording_has_a_header_crc_and_check_says_so(tmp_path):
    from server.recording import HEADER_CRC

    rec = tmp_path / "new.sortie"
    _synthetic(rec, SMALL_SCENARIO)
    start, end = _header_span(rec)
    assert rec.read_bytes()[start:start + 2] == b"\x8d\x01"  # field 17, fixed32, first
    with Recording(rec) as r:
        report = r.check()
        assert report.ok and report.header_checked and not report.notes and r.header_checked
        assert r.header.SerializeToString() == rec.read_bytes()[start + HEADER_CRC.size:end]  # the CRC read off
    out = sortie("recording", "check", rec)
    assert out.returncode == 0 and "header CRC checked" in out.stdout and "OK" in out.stdout, out.stdout
    out = sortie("recording", "info", rec, "--json")
    assert out.returncode == 0 and json.loads(out.stdout)["header_crc"] is True


def test_the_probes_header_damage_is_refused_by_every_reader(tmp_path):
    """The probe's hdr_corrupt.py: the start time's year 2026 -> 2826 and an exponent bit of the
    geoid undulation (10 m -> 10 x 2^32 m): check said OK, the ACMI said ReferenceTime 2826.
    Now each is a DataFormatError naming the file and the header, and every command exits 2."""
    rec = tmp_path / "whole.sortie"
    _synthetic(rec, SMALL_SCENARIO)
    data = rec.read_bytes()
    year = bytearray(data)
    i = year.index(b"2026-01-02T03:04:05.250Z")
    year[i + 1] = ord("8")
    geoid = bytearray(data)
    j = geoid.index(struct.pack("<d", 10.0))
    geoid[j + 7] ^= 0x01
    for name, damaged in (("year", year), ("geoid", geoid)):
        p = tmp_path / f"{name}.sortie"
        p.write_bytes(bytes(damaged))
        with pytest.raises(DataFormatError, match=rf"{re.escape(str(p))}: damaged header .*CRC-32 mismatch"):
            Recording(p)
        for args in (("recording", "check", p), ("recording", "info", p), ("export", "acmi", p, "-o",
                     tmp_path / "x.acmi"), ("export", "gltf", p, "-o", tmp_path / "x.glb", "--no-terrain"),
                     ("resim", p), ("replay", p, "--port", "0")):
            out = sortie(*args)
            assert out.returncode == 2 and "damaged header" in out.stderr and p.name in out.stderr, (args, out)
        assert not (tmp_path / "x.acmi").exists()


def test_every_bit_of_the_header_is_checked(tmp_path):
    """Each bit flip in the header (its length included) is refused as a damaged header, but in
    the scenario text, which its SHA-256 checks: a problem, as before (the probe's silent.py found
    quantisation steps changed silently)."""
    rec = tmp_path / "whole.sortie"
    _synthetic(rec, SMALL_SCENARIO)
    with Recording(rec) as r:
        ref = r.header.SerializeToString()
    start, end = _header_span(rec)
    text = rec.read_bytes().index(SMALL_SCENARIO[0].encode())
    text_span = range(text, text + len(SMALL_SCENARIO[0]))
    out = tmp_path / "flip.sortie"
    refused = problems = 0
    for offset in range(8, end):
        for bit in range(8):
            _flipped(rec, out, offset, bit)
            try:
                with Recording(out) as r:
                    report = r.check()
                    assert offset in text_span, (offset, bit)
                    assert not report.ok and any("scenario SHA-256 mismatch" in p for p in report.problems)
                    assert r.header.SerializeToString() != ref
                    problems += 1
            except DataFormatError as exc:
                assert "header" in str(exc) and out.name in str(exc), str(exc)
                refused += 1
    assert problems == 8 * len(text_span) and refused == 8 * (end - 8 - len(text_span))


def test_a_scenario_text_that_is_no_longer_utf8_is_a_sha256_problem(tmp_path):
    rec = tmp_path / "whole.sortie"
    _synthetic(rec, SMALL_SCENARIO)
    i = rec.read_bytes().index(b'name = "x"')
    out = _flipped(rec, tmp_path / "utf8.sortie", i, 7)  # 'n' | 0x80: not UTF-8
    with Recording(out) as r:
        report = r.check()
        assert not report.ok and any("scenario SHA-256 mismatch" in p for p in report.problems)
        assert "\ufffd" in r.header.scenario_toml and r.frame(5).ids.tolist() == [1]


def _unsealed(monkeypatch):
    """Write headers as before header CRCs."""
    monkeypatch.setattr(recording_mod, "sealed_header", lambda h: h.SerializeToString())


def test_a_recording_from_before_header_crcs_reads_as_before_with_a_note(tmp_path, monkeypatch):
    rec = tmp_path / "old.sortie"
    with monkeypatch.context() as m:
        _unsealed(m)
        _synthetic(rec, SMALL_SCENARIO)
    with Recording(rec) as r:
        report = r.check()
        assert report.ok and not report.header_checked and not r.header_checked
        assert any("no CRC" in n for n in report.notes)
        assert r.header.geoid_undulation_m == 10.0 and r.frame(5).ids.tolist() == [1]
    out = sortie("recording", "check", rec)
    assert out.returncode == 0 and "header unchecked" in out.stdout and "note: the header has no CRC" in out.stdout
    out = sortie("recording", "info", rec, "--json")
    assert out.returncode == 0 and json.loads(out.stdout)["header_crc"] is False
    start, _ = _header_span(rec)
    assert rec.read_bytes()[start:start + 2] == b"\x08\x01"  # format_version = 1, first
    with pytest.raises(DataFormatError, match=r"old-first.sortie: damaged header .*starts with neither its CRC"):
        Recording(_flipped(rec, tmp_path / "old-first.sortie", start, 0))  # 0x08 -> 0x09
    # Its fields are still range-checked: the probe's geoid flip (10 m -> 4.3e10 m) is refused.
    j = rec.read_bytes().index(struct.pack("<d", 10.0))
    bad = _flipped(rec, tmp_path / "old-geoid.sortie", j + 7, 0)
    with pytest.raises(DataFormatError, match=r"old-geoid.sortie: damaged header: geoid_undulation_m .* must be "
                                              r"within \[-120, 120\] m"):
        Recording(bad)


@pytest.mark.parametrize("field, value, says", [
    ("geoid_undulation_m", 500.0, r"geoid_undulation_m 500.0: must be within \[-120, 120\] m"),
    ("world_rate_hz", 5000.0, r"world_rate_hz 5000.0: must be within \(0, 1000\] Hz"),
    ("world_rate_hz", math.nan, r"world_rate_hz nan"),
    ("fdm_rate_hz", 10.0, r"fdm_rate_hz 10.0: must be within \[world_rate_hz, 1000\] Hz"),
    ("chunk_s", -1.0, r"chunk_s -1.0"),
    ("start_time", "2026-13-01T00:00:00Z", r"start_time '2026-13-01T00:00:00Z'"),
    ("start_time", "2026-01-01T00:00:00", r"must be an ISO 8601 date-time with an offset"),
    ("exercise_name", "a\x00b", r"exercise_name 'a\\x00b'"),
    ("quantization.position_m", 0.0, r"quantization.position_m 0.0: must be within \[1e-08, 1\]"),
    ("quantization.quaternion", 2.0 ** 20, r"quantization.quaternion 1048576.0"),
])
def test_header_fields_beyond_a_recordings_ranges_are_refused(tmp_path, field, value, says):
    """A header whose CRC checks but whose fields no recorder writes (the scenario's limits)."""
    header = rpb.RecordingHeader(format_version=1, exercise_name="ranges", world_rate_hz=30.0, fdm_rate_hz=120.0,
                                 start_time="2026-01-02T03:04:05Z", quantization=quantization_of(codec.DEFAULT_STEPS),
                                 chunk_s=1.0, geoid_undulation_m=10.0)
    target, _, name = field.rpartition(".")
    setattr(getattr(header, target) if target else header, name, value)
    path = tmp_path / "ranges.sortie"
    RecordingWriter(path, header).close()
    with pytest.raises(DataFormatError, match=rf"ranges.sortie: damaged header: .*{says}"):
        Recording(path)


def test_the_header_crc_covers_its_length_and_its_tag(tmp_path):
    rec = tmp_path / "whole.sortie"
    _synthetic(rec)
    start, _ = _header_span(rec)
    for bit in range(3):  # the length's low bits: the header ends elsewhere
        with pytest.raises(DataFormatError, match="damaged header"):
            Recording(_flipped(rec, tmp_path / f"n{bit}.sortie", 8, bit))
    for offset, bit in ((start + 1, 1), (start, 7), (start, 0)):  # field 17 -> 49, 0x8d -> 0x0d, wire type 4
        with pytest.raises(DataFormatError, match="its CRC field's tag is damaged"):  # the CRC still matches
            Recording(_flipped(rec, tmp_path / "tag.sortie", offset, bit))


# -- 4: a directory is no recording -----------------------------------------------------------------

def test_a_directory_given_as_a_recording_is_said_to_be_one(tmp_path):
    with pytest.raises(DataFormatError, match="is a directory, not a recording file"):
        Recording(tmp_path)
    for args in (("recording", "check", tmp_path), ("recording", "info", tmp_path),
                 ("export", "acmi", tmp_path, "-o", tmp_path / "x.acmi")):
        out = sortie(*args)
        assert out.returncode == 2 and "is a directory" in out.stderr and "does not exist" not in out.stderr, out
    out = sortie("recording", "check", tmp_path / "nope.sortie")
    assert out.returncode == 2 and "does not exist" in out.stderr


# -- 5: the size the server prints of its recording ----------------------------------------------------

def test_the_writer_counts_the_footer_in_its_bytes(tmp_path):
    header = rpb.RecordingHeader(format_version=1, world_rate_hz=30.0,
                                 quantization=quantization_of(codec.DEFAULT_STEPS))
    path = tmp_path / "w.sortie"
    writer = RecordingWriter(path, header)
    before = writer.bytes_written
    writer.close()
    assert writer.bytes_written == path.stat().st_size > before


def test_the_server_prints_its_recordings_real_size(tmp_path, hgt_alps):
    scenario = tmp_path / "s.toml"
    scenario.write_text(f"""
[exercise]
name = "size"
start_time = 2026-03-01T12:00:00Z
clock = "fast"
time_scale = 20.0
duration_s = 1.0
[terrain]
dem = ["{hgt_alps}"]
[[agents]]
name = "sam"
kind = "static"
type = "sam_site"
coalition = "red"
lat_deg = 47.3
lon_deg = 9.3
""")
    path = tmp_path / "size.sortie"
    out = sortie("server", "--scenario", scenario, "--port", "0", "--aircraft-workers", "0", "--record", path)
    assert out.returncode == 0, out.stdout + out.stderr
    said = re.search(r"recording .*size\.sortie: ([\d,]+) bytes", out.stdout)
    assert said, out.stdout
    assert int(said.group(1).replace(",", "")) == path.stat().st_size
    with Recording(path) as r:
        assert not r.recovered and r.check().ok
