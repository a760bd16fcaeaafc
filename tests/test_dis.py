"""The DIS codec and gateway (issue #8): real PDUs from other simulations, property round
trips, hostile bytes, Wireshark's dissector as an independent reader of what we encode,
and the gateway between a real simulation server and real UDP sockets on loopback."""

import dataclasses
import math
import re
import shutil
import socket
import struct
import subprocess
import time

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from server import dis, pcap
from server.dead_reckoning import ecef_to_ned_quat, extrapolate, quat_conjugate, quat_multiply, rotation_angle
from server.dis_gateway import DisGateway, seconds_past_hour
from server.process import sortie_command
from sortie.errors import DataFormatError, InvalidArgument
from sortie.v1 import simulation_pb2 as pb
from terrain.geodesy import ecef_to_geodetic, enu_basis, geodetic_to_ecef
from tests.conftest import shared_or_embedded
from server_helpers import PublishTap

PDU_26 = "EntityStatePdu-26.raw"
PDU_VBS = "EntityStatePdu-vbs-articulated-parameters.raw"
LOOPBACK_BROADCAST = "127.255.255.255"


def raw(name: str) -> bytes:
    return shared_or_embedded(name, "dis").read_bytes()


def rotate(q, v):
    """(..., 3) body vectors v in ECEF, by quaternions q (..., 4) ECEF -> body: q (0, v) q*."""
    v = np.asarray(v, dtype=np.float64)
    zero = np.zeros(v.shape[:-1] + (1,))
    return quat_multiply(quat_multiply(q, np.concatenate([zero, v], axis=-1)), quat_conjugate(q))[..., 1:]


# -- real PDUs ------------------------------------------------------------------------------------

def test_decodes_the_open_dis_entity_state_pdu_as_documented():
    data = raw(PDU_26)
    pdu = dis.decode_pdu(data)
    assert (pdu.protocol_version, pdu.exercise_id, pdu.entity_id, pdu.force_id) == (6, 7, (42, 4, 26), 1)
    assert str(pdu.entity_type) == "1.1.39.7.2.1.0" and pdu.alternative_entity_type == pdu.entity_type
    np.testing.assert_allclose(pdu.location, (4374082.80485589, 1667679.95730107, 4318284.36890269), atol=1e-6)
    lat, lon, h = ecef_to_geodetic(np.array(pdu.location))
    assert abs(lat - 42.8825) < 1e-4 and abs(lon - 20.8700) < 1e-4 and abs(h - 499.0) < 1.0
    assert pdu.marking_text == "26" and pdu.marking == b"26" + bytes(9) and pdu.marking_charset == dis.MARKING_ASCII
    assert pdu.dr_algorithm == dis.DR_FPW and pdu.linear_velocity == (0.0, 0.0, 0.0)
    assert pdu.variable_parameters == () and not pdu.deactivated
    seconds, absolute = dis.timestamp_seconds(pdu.timestamp)
    assert not absolute and 0.0 <= seconds < 3600.0
    # The kind comes from the domain (land), the type is DIS's own (not in our table).
    assert dis.sortie_kind_type(pdu.entity_type) == ("ground", "dis:1.1.39.7.2.1.0")
    assert dis.coalition_of(pdu.force_id) == "blue"


def test_decodes_the_vbs_pdu_with_articulation_records():
    data = raw(PDU_VBS)
    pdu = dis.decode_pdu(data)
    assert len(data) == 400 == dis.ESPDU_BYTES + 16 * len(pdu.variable_parameters)
    assert len(pdu.variable_parameters) == 16 and pdu.marking_text == "13"
    parts = [r.articulated for r in pdu.variable_parameters]
    assert all(p is not None for p in parts)
    # Turret #1 (class 4096): azimuth (metric 11) -1.5411 rad and its rate (metric 12).
    by_type = {p.parameter_type: p for p in parts}
    assert by_type[4107].type_class == 4096 and by_type[4107].type_metric == 11
    assert by_type[4107].value == pytest.approx(-1.54111, abs=1e-5)
    assert {p.type_metric for p in parts} == {11, 12, 13, 14}
    assert all(math.isfinite(p.value) for p in parts)


@pytest.mark.parametrize("name", [PDU_26, PDU_VBS])
def test_real_pdus_reencode_bytewise_and_as_version_7(name):
    data = raw(name)
    pdu = dis.decode_pdu(data)
    assert dis.encode_pdu(pdu) == data  # version 6, as received: every byte
    v7 = dataclasses.replace(pdu, protocol_version=7)
    wire = dis.encode_pdu(v7)
    assert wire[0] == 7 and len(wire) == len(data) and wire[12:] == data[12:]
    assert dis.decode_pdu(wire) == v7


def test_split_datagram_reads_bundled_pdus():
    a, b = raw(PDU_26), raw(PDU_VBS)
    assert dis.split_datagram(a + b) == [a, b]
    with pytest.raises(DataFormatError, match="length"):
        dis.split_datagram(a + b[:100])


# -- malformed input ------------------------------------------------------------------------------

def test_truncated_pdus_name_the_field():
    data = raw(PDU_26)
    with pytest.raises(DataFormatError, match=r"header.*truncated: 5 bytes"):
        dis.decode_pdu(data[:5])
    for n in (12, 50, 143):
        with pytest.raises(DataFormatError, match=r"length at byte 8: says 144 bytes, the data has"):
            dis.decode_pdu(data[:n])
    vbs = raw(PDU_VBS)
    with pytest.raises(DataFormatError, match="length"):
        dis.decode_pdu(vbs[:-16])


def test_inconsistent_pdus_name_the_field_and_value():
    data = bytearray(raw(PDU_26))
    bad = bytearray(data)
    bad[0] = 4
    with pytest.raises(DataFormatError, match=r"protocol_version at byte 0: version 4 is not supported"):
        dis.decode_pdu(bytes(bad))
    bad = bytearray(data)
    bad[19] = 2  # two variable parameter records announced, none there
    with pytest.raises(DataFormatError, match=r"variable_parameters at byte 19: 2 records need 176"):
        dis.decode_pdu(bytes(bad))
    bad = bytearray(data)
    struct.pack_into(">H", bad, 8, 200)
    with pytest.raises(DataFormatError, match=r"length at byte 8: says 200"):
        dis.decode_pdu(bytes(bad))
    bad = bytearray(data)
    struct.pack_into(">H", bad, 8, 4)
    with pytest.raises(DataFormatError, match=r"length at byte 8: 4 bytes is shorter"):
        dis.decode_pdu(bytes(bad))
    bad = bytearray(data)
    bad[3] = 2
    with pytest.raises(DataFormatError, match=r"protocol_family at byte 3"):
        dis.decode_pdu(bytes(bad))
    bad = bytearray(data)
    struct.pack_into(">d", bad, 48, math.nan)
    with pytest.raises(DataFormatError, match=r"location at byte 48: not finite"):
        dis.decode_pdu(bytes(bad))


def test_other_pdu_types_decode_their_header_only():
    data = bytearray(raw(PDU_26))
    data[2] = 2  # Fire PDU
    other = dis.decode_pdu(bytes(data))
    assert isinstance(other, dis.OtherPdu) and other.header.pdu_type == 2 and len(other.body) == 132


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_garbage_raises_only_data_format_errors(data):
    try:
        dis.decode_pdu(data)
    except DataFormatError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 399), st.integers(0, 255))
def test_corrupted_real_bytes_decode_or_raise_data_format_error(at, value):
    data = bytearray(raw(PDU_VBS))
    data[at] = value
    try:
        pdu = dis.decode_pdu(bytes(data))
    except DataFormatError:
        return
    if isinstance(pdu, dis.EntityStatePdu):
        assert dis.decode_pdu(dis.encode_pdu(pdu)) == pdu


def test_encoding_refuses_out_of_range_fields_naming_them():
    pdu = dis.decode_pdu(raw(PDU_26))
    with pytest.raises(InvalidArgument, match=r"entity_id.entity"):
        dis.encode_pdu(dataclasses.replace(pdu, entity_id=(1, 2, 70_000)))
    with pytest.raises(InvalidArgument, match=r"entity_type.country"):
        dis.encode_pdu(dataclasses.replace(pdu, entity_type=dis.EntityType(1, 2, 70_000)))
    with pytest.raises(InvalidArgument, match=r"location"):
        dis.encode_pdu(dataclasses.replace(pdu, location=(math.inf, 0.0, 0.0)))
    with pytest.raises(InvalidArgument, match=r"exercise_id"):
        dis.encode_pdu(dataclasses.replace(pdu, exercise_id=256))


# -- property round trips -------------------------------------------------------------------------

f32 = st.floats(width=32, allow_nan=False, allow_infinity=False)
f64 = st.floats(-1e7, 1e7, allow_nan=False)
u8, u16, u32 = st.integers(0, 255), st.integers(0, 65535), st.integers(0, 2**32 - 1)
entity_types = st.builds(dis.EntityType, u8, u8, u16, u8, u8, u8, u8)
records = st.builds(dis.VariableParameter, u8, st.binary(min_size=15, max_size=15))


@st.composite
def entity_state_pdus(draw):
    version = draw(st.sampled_from(dis.SUPPORTED_VERSIONS))
    vec32 = st.tuples(f32, f32, f32)
    return dis.EntityStatePdu(
        exercise_id=draw(u8), entity_id=draw(st.tuples(u16, u16, u16)), entity_type=draw(entity_types),
        location=draw(st.tuples(f64, f64, f64)), orientation=draw(vec32), linear_velocity=draw(vec32),
        force_id=draw(u8), alternative_entity_type=draw(entity_types), appearance=draw(u32),
        dr_algorithm=draw(u8), dr_parameters=draw(st.binary(min_size=15, max_size=15)),
        dr_linear_acceleration=draw(vec32), dr_angular_velocity=draw(vec32),
        marking=draw(st.binary(min_size=11, max_size=11)),
        marking_charset=draw(u8), capabilities=draw(u32),
        variable_parameters=tuple(draw(st.lists(records, max_size=6))), timestamp=draw(u32),
        protocol_version=version, pdu_status=draw(u8) if version == 7 else 0)


@settings(max_examples=200, deadline=None)
@given(entity_state_pdus())
def test_pdu_round_trip(pdu):
    wire = dis.encode_pdu(pdu)
    assert len(wire) == dis.ESPDU_BYTES + 16 * len(pdu.variable_parameters)
    assert dis.decode_pdu(wire) == pdu


unit_quats = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 0.1)


@settings(max_examples=300, deadline=None)
@given(unit_quats)
def test_quaternion_to_dis_euler_and_back_is_the_same_rotation(q):
    q = np.array(q) / np.linalg.norm(q)
    euler = dis.dis_euler_from_quat(q)
    psi, theta, phi = euler
    assert -math.pi <= psi <= math.pi and -math.pi / 2 <= theta <= math.pi / 2 and -math.pi <= phi <= math.pi
    assert rotation_angle(q, dis.quat_from_dis_euler(euler)) < 1e-6


@settings(max_examples=300, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-1.55, 1.55), st.floats(-math.pi, math.pi))
def test_dis_euler_to_quaternion_and_back_gives_the_angles(psi, theta, phi):
    back = dis.dis_euler_from_quat(dis.quat_from_dis_euler([psi, theta, phi]))
    wrap = lambda a: (a + math.pi) % (2 * math.pi) - math.pi  # noqa: E731
    assert abs(wrap(back[0] - psi)) < 1e-9 and abs(back[1] - theta) < 1e-9 and abs(wrap(back[2] - phi)) < 1e-9


@settings(max_examples=200, deadline=None)
@given(st.floats(-math.pi, math.pi), st.floats(-math.pi / 2, math.pi / 2), st.floats(-math.pi, math.pi))
def test_dis_euler_matches_rotation_matrices(psi, theta, phi):
    """The oracle: body axes as the columns of Rz(psi) Ry(theta) Rx(phi), built from matrices."""
    c, s = math.cos, math.sin
    rz = np.array([[c(psi), -s(psi), 0], [s(psi), c(psi), 0], [0, 0, 1]])
    ry = np.array([[c(theta), 0, s(theta)], [0, 1, 0], [-s(theta), 0, c(theta)]])
    rx = np.array([[1, 0, 0], [0, c(phi), -s(phi)], [0, s(phi), c(phi)]])
    q = dis.quat_from_dis_euler([psi, theta, phi])
    np.testing.assert_allclose(rotate(q, np.eye(3)).T, rz @ ry @ rx, atol=1e-12)


def test_gimbal_lock_gives_one_angle_for_the_pair():
    # theta = +-90 degrees: only psi -/+ phi is defined; phi comes back 0, the rotation is kept.
    for theta in (math.pi / 2, -math.pi / 2):
        q = dis.quat_from_dis_euler([0.3, theta, 0.5])
        psi, theta_back, phi = dis.dis_euler_from_quat(q)
        assert phi == 0.0 and abs(theta_back - theta) < 1e-7
        assert rotation_angle(q, dis.quat_from_dis_euler([psi, theta_back, phi])) < 1e-7
    batch = dis.quat_from_dis_euler(np.array([[0.1, 0.2, 0.3], [0.0, math.pi / 2, 1.0]]))
    assert dis.dis_euler_from_quat(batch).shape == (2, 3)


def test_level_aircraft_at_lat0_lon0_oracle():
    # Heading north, level: body x = north = ECEF +Z, body z = down = ECEF -X: theta = -90 degrees.
    q_north = ecef_to_ned_quat(0.0, 0.0)
    np.testing.assert_allclose(rotate(q_north, [[1, 0, 0], [0, 0, 1]]), [[0, 0, 1], [-1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(dis.dis_euler_from_quat(q_north), [0.0, -math.pi / 2, 0.0], atol=1e-12)
    # Heading east: body x = +Y, y = south = -Z, z = -X: psi = 90, theta = 0, phi = -90 degrees.
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat

    q_east = ned_to_ecef_quat(euler_to_quaternion(0.0, 0.0, math.pi / 2), 0.0, 0.0)
    np.testing.assert_allclose(rotate(q_east, np.eye(3)), [[0, 1, 0], [0, 0, -1], [-1, 0, 0]], atol=1e-15)
    np.testing.assert_allclose(dis.dis_euler_from_quat(q_east), [math.pi / 2, 0.0, -math.pi / 2], atol=1e-12)


@settings(max_examples=300, deadline=None)
@given(st.floats(0.0, 3599.999), st.booleans())
def test_timestamp_round_trip(seconds, absolute):
    ts = dis.dis_timestamp(seconds, absolute)
    back, flag = dis.timestamp_seconds(ts)
    assert flag == absolute and 0 <= ts < 2**32
    assert 0.0 <= seconds - back < 3600.0 / 2**31 + 1e-9


def test_timestamp_units_and_flag():
    assert dis.dis_timestamp(0.0, True) == 1 and dis.dis_timestamp(0.0, False) == 0
    assert dis.dis_timestamp(1800.0, False) == 2**31  # half the hour: the top bit
    assert dis.dis_timestamp(3600.0 + 1.0, False) == dis.dis_timestamp(1.0, False)  # past the hour


@given(st.text(max_size=30))
def test_marking_is_eleven_ascii_bytes(text):
    m = dis.encode_marking(text)
    assert len(m) == 11 and all(b == 0 or 32 <= b <= 126 for b in m)
    back = dis.decode_marking(m)
    assert len(back) == min(len(text), 11)
    assert all(a == b or (b == "?" and not " " <= a <= "~") for a, b in zip(text, back))


# -- mappings -------------------------------------------------------------------------------------

def test_entity_types_both_ways():
    assert str(dis.entity_type_of("aircraft", "f16")) == "1.2.225.1.3.3.0"
    assert str(dis.entity_type_of("ground", "m1a2")) == "1.1.225.1.1.3.0"
    assert str(dis.entity_type_of("aircraft", "paraglider")) == "1.2.0.0.0.0.0"
    assert str(dis.entity_type_of("ground", "tractor")) == "1.1.0.0.0.0.0"
    assert str(dis.entity_type_of("static", "bunker")) == "5.1.0.0.0.0.0"
    with pytest.raises(InvalidArgument, match="kind"):
        dis.entity_type_of("ship", "x")
    for (kind, name), t in dis.ENTITY_TYPES.items():
        assert dis.sortie_kind_type(t)[0] == kind
        if name not in ("c172x", "c172r"):
            assert dis.sortie_kind_type(t) == (kind, name)
    assert dis.sortie_kind_type(dis.EntityType(1, 2, 225, 85, 11, 1)) == ("aircraft", "c172p")
    assert dis.sortie_kind_type(dis.EntityType(1, 2, 222, 1, 1)) == ("aircraft", "dis:1.2.222.1.1.0.0")
    assert dis.sortie_kind_type(dis.EntityType(1, 3, 0)) == ("ground", "dis:1.3.0.0.0.0.0")
    assert dis.sortie_kind_type(dis.EntityType(5, 1, 0, 1)) == ("static", "dis:5.1.0.1.0.0.0")


def test_every_catalog_aircraft_and_vehicle_maps_to_its_domain():
    from fdm.catalog import list_aircraft
    from fdm.vehicle_types import VEHICLE_TYPES

    for name in list_aircraft():
        t = dis.entity_type_of("aircraft", name)
        assert (t.kind, t.domain) == (1, 2), name
    for name in VEHICLE_TYPES:
        t = dis.entity_type_of("ground", name)
        assert (t.kind, t.domain, t.country) == (1, 1, 225), name


def test_forces_and_coalitions():
    assert [dis.force_of(c) for c in ("blue", "red", "neutral")] == [1, 2, 3]
    assert [dis.coalition_of(f) for f in (0, 1, 2, 3, 9)] == ["neutral", "blue", "red", "neutral", "neutral"]


def test_body_dead_reckoning_is_kept_for_the_world():
    """Body-axis algorithms stay body-axis (the world dead-reckons them by Annex E: server/external.py);
    what an algorithm does not use is zeroed, and an unknown one is FPW."""
    v_b, a_b, w_b = np.array([100.0, 0, 0]), np.array([1.0, 0, 0]), np.array([0.0, 0, 0.1])
    for code in (dis.DR_FPB, dis.DR_RPB, dis.DR_RVB, dis.DR_FVB, dis.DR_RVW):
        alg, v, a, w = dis.external_dead_reckoning(code, v_b, a_b, w_b)
        assert alg == code and list(v) == list(v_b)
        assert list(a) == (list(a_b) if code in dis.DR_ACCELERATING else [0.0] * 3)
        assert list(w) == (list(w_b) if code in dis.DR_ROTATING else [0.0] * 3)
    alg, v, a, w = dis.external_dead_reckoning(dis.DR_OTHER, v_b, a_b, w_b)
    assert alg == dis.DR_FPW and list(v) == list(v_b) and not a.any() and not w.any()


def test_sortie_state_of_a_received_pdu():
    state = dis.sortie_state(dis.decode_pdu(raw(PDU_26)))
    assert (state["name"], state["kind"], state["type"], state["coalition"]) == (
        "26", "ground", "dis:1.1.39.7.2.1.0", "blue")
    assert state["algorithm"] == dis.DR_FPW and abs(np.linalg.norm(state["quat_wxyz"]) - 1.0) < 1e-12
    blank = dis.sortie_state(dataclasses.replace(dis.decode_pdu(raw(PDU_26)), marking=b"\x01" + bytes(10)))
    assert blank["name"] == "?"


# -- Wireshark ------------------------------------------------------------------------------------

def write_pcap(path, payloads) -> None:
    """A pcap of one UDP frame to the DIS port per payload (server/pcap.py)."""
    pcap.write_pcap(path, payloads, dis.DEFAULT_PORT)


TSHARK_FIELDS = ("dis.proto_ver", "dis.pdu_type", "dis.exer_id", "dis.pdu_length", "dis.entity_id_site",
                 "dis.entity_id_application", "dis.entity_id_entity", "dis.force_id", "dis.entity_location.x",
                 "dis.entity_location.y", "dis.entity_location.z", "dis.entityKind", "dis.entityDomain", "dis.country",
                 "dis.subcategory", "dis.specific", "dis.extra", "dis.entity_marking", "dis.num_articulation_params")


def tshark(pcap) -> tuple[str, list[dict]]:
    """(tshark -V text, one dict of TSHARK_FIELDS per frame); fails the test without tshark."""
    exe = shutil.which("tshark")
    if exe is None:
        pytest.fail("tshark (Wireshark's command line) is not installed: `make bootstrap` installs it")
    decode = ["-d", f"udp.port=={dis.DEFAULT_PORT},dis", "-o", "udp.check_checksum:TRUE",
              "-o", "ip.check_checksum:TRUE"]
    verbose = subprocess.run([exe, "-r", str(pcap), "-V", *decode], capture_output=True, text=True, timeout=60)
    assert verbose.returncode == 0, verbose.stderr
    fields = subprocess.run([exe, "-r", str(pcap), *decode, "-T", "fields", "-E", "separator=\t", "-E", "occurrence=f",
                             *[a for f in TSHARK_FIELDS for a in ("-e", f)]],
                            capture_output=True, text=True, timeout=60)
    assert fields.returncode == 0, fields.stderr
    rows = [dict(zip(TSHARK_FIELDS, line.split("\t"))) for line in fields.stdout.splitlines()]
    return verbose.stdout, rows


def assert_clean(text: str, frames: int) -> None:
    assert text.count("Distributed Interactive Simulation") == frames
    assert text.count("Entity State PDU") >= frames
    assert "Malformed" not in text
    assert not re.search(r"Expert Info \((Error|Warning)", text), re.findall(r".*Expert Info.*", text)
    assert "[Checksum Status: Good]" in text and "Bad" not in text


def sortie_pdus() -> list[dis.EntityStatePdu]:
    """What the gateway sends: an F-16 climbing through a turn over the Alps, a deactivated
    HMMWV, an unknown static, and one with an articulated part."""
    out = []
    for k, (kind, type_name, lat, lon, alt, heading) in enumerate(
            [("aircraft", "f16", 47.3, 9.4, 3500.0, 95.0), ("ground", "hmmwv", 47.24, 9.52, 430.0, 10.0),
             ("static", "bunker", 47.35, 9.45, 900.0, 0.0), ("aircraft", "c172p", -33.9, 151.2, 1500.0, 270.0)]):
        from fdm.state import euler_to_quaternion
        from server.dead_reckoning import ned_to_ecef_quat

        q = ned_to_ecef_quat(euler_to_quaternion(0.2, 0.1, math.radians(heading)), lat, lon)
        east, north, up = (np.asarray(b).reshape(3) for b in enu_basis(lat, lon))
        pdu = dis.entity_state_pdu(
            exercise_id=3, entity_id=(17, 4242, k + 1), kind=kind, type_name=type_name,
            coalition=("blue", "red", "neutral", "blue")[k], name=f"{type_name}-{k + 1}",
            ecef_m=np.asarray(geodetic_to_ecef(lat, lon, alt)).reshape(3), vel_ecef_mps=150.0 * east + 5.0 * up,
            acc_ecef_mps2=0.5 * north, quat_wxyz=q, body_rates_rps=(0.01, 0.02, 0.05), algorithm=dis.DR_RVW,
            timestamp=dis.dis_timestamp(12.5 * k, absolute=False), appearance=dis.APPEARANCE_DEACTIVATED * (k == 1))
        out.append(pdu)
    part = dis.VariableParameter.articulated_part(dis.ArticulatedPart(0, 0, 4096 + 11, 0.75))
    out[3] = dataclasses.replace(out[3], variable_parameters=(part,))
    return out


def test_wireshark_reads_what_we_encode(tmp_path):
    pdus = sortie_pdus()
    for p in pdus:  # what we hand Wireshark decodes back to itself
        assert dis.decode_pdu(dis.encode_pdu(p)) == p
    pcap = tmp_path / "sortie.pcap"
    write_pcap(pcap, [dis.encode_pdu(p) for p in pdus])
    text, rows = tshark(pcap)
    assert_clean(text, len(pdus))
    assert len(rows) == len(pdus)
    for p, row in zip(pdus, rows):
        assert (row["dis.proto_ver"], row["dis.pdu_type"], row["dis.exer_id"]) == ("7", "1", "3")
        assert int(row["dis.pdu_length"]) == len(dis.encode_pdu(p))
        assert tuple(int(row[f"dis.entity_id_{n}"]) for n in ("site", "application", "entity")) == p.entity_id
        assert int(row["dis.force_id"]) == p.force_id
        loc = [float(row[f"dis.entity_location.{a}"]) for a in "xyz"]
        np.testing.assert_allclose(loc, p.location, rtol=0, atol=1e-6)  # tshark prints 15 digits
        t = p.entity_type
        assert [int(row[f]) for f in ("dis.entityKind", "dis.entityDomain", "dis.country", "dis.subcategory",
                                      "dis.specific", "dis.extra")] == [t.kind, t.domain, t.country,
                                                                       t.subcategory, t.specific, t.extra]
        assert row["dis.entity_marking"] == p.marking_text
        assert int(row["dis.num_articulation_params"]) == len(p.variable_parameters)
    assert "Entity Type, (1:2:225:1:3:3:0)" in text  # the F-16C, category included
    assert "State: Deactivated" in text  # appearance bit 23 on the HMMWV


def test_wireshark_reads_the_real_pdus_like_we_do(tmp_path):
    """The harness itself: Wireshark on the two real captures agrees with our decoder."""
    data = [raw(PDU_26), raw(PDU_VBS)]
    pcap = tmp_path / "real.pcap"
    write_pcap(pcap, data)
    text, rows = tshark(pcap)
    assert_clean(text, 2)
    for d, row in zip(data, rows):
        p = dis.decode_pdu(d)
        assert row["dis.proto_ver"] == "6"
        assert tuple(int(row[f"dis.entity_id_{n}"]) for n in ("site", "application", "entity")) == p.entity_id
        np.testing.assert_allclose([float(row[f"dis.entity_location.{a}"]) for a in "xyz"], p.location, atol=1e-6)
        assert row["dis.entity_marking"] == p.marking_text
        assert int(row["dis.num_articulation_params"]) == len(p.variable_parameters)


# -- the gateway, end to end ----------------------------------------------------------------------

@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


@pytest.fixture()
def server(alps):
    from fdm.aircraft import InitialConditions
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World

    w = World(alps)
    w.spawn_aircraft("viper1", "f16", InitialConditions(47.30, 9.30, 3500.0, heading_deg=90.0, speed_mps=200.0),
                     coalition="blue")
    w.spawn_aircraft("cessna", "c172x", InitialConditions(47.45, 9.45, 1500.0, heading_deg=0.0, speed_mps=50.0),
                     route=[(47.50, 9.45, 1500.0), (47.50, 9.55, 1600.0)], coalition="red")
    w.spawn_ground(["c1", "c2"], "hmmwv", [47.2412, 47.2408], [9.5229, 9.5226], 27.0,
                   route=[(47.24, 9.522), (47.26, 9.537)], cruise_mps=10.0, spacing_m=50.0)
    w.spawn_static("sam1", "sam_site", 47.35, 9.45, coalition="red")
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    srv.tap = PublishTap(srv.publisher)
    srv.start()
    yield srv
    srv.stop(0.5)


def dis_socket(port: int = 0) -> socket.socket:
    """A UDP socket sharing the DIS port on the loopback broadcast address, as a DIS peer."""
    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
    s.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    s.settimeout(0.2)
    s.bind((LOOPBACK_BROADCAST, port))
    return s


def receive(sock, seconds: float, until=None) -> list[dis.EntityStatePdu]:
    """Entity State PDUs that arrive on ``sock`` within ``seconds`` (or until ``until(pdus)``)."""
    out, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline and not (until and until(out)):
        try:
            data = sock.recv(65536)
        except socket.timeout:
            continue
        try:
            pdus = [dis.decode_pdu(d) for d in dis.split_datagram(data)]
        except DataFormatError:  # what a test sent on purpose
            continue
        out += [p for p in pdus if isinstance(p, dis.EntityStatePdu)]
    return out


def test_gateway_sends_every_entity_within_the_dead_reckoning_threshold(server):
    peer = dis_socket()
    port = peer.getsockname()[1]
    world = server.world
    with DisGateway(server.address, port=port, exercise=9, site=5, application=77) as gw:
        pdus = receive(peer, 10.0, until=lambda ps: len({p.entity_id for p in ps}) == len(world.entities))
        assert {p.entity_id[2] for p in pdus} == set(world.entities)
        assert all(p.entity_id[:2] == (5, 77) and p.exercise_id == 9 and p.protocol_version == 7 for p in pdus)
        pdus += receive(peer, 2.0)
        server.set_clock("paused")
        pdus += receive(peer, 1.0)
        truth = server.tap.snaps[-1]
        last = {p.entity_id[2]: p for p in pdus}
        names = {i: e.name for i, e in world.entities.items()}
        assert {i: p.marking_text for i, p in last.items()} == names
        assert str(last[next(i for i, n in names.items() if n == "viper1")].entity_type) == "1.2.225.1.3.3.0"
        assert dis.coalition_of(last[next(i for i, n in names.items() if n == "cessna")].force_id) == "red"
        # Each entity's last PDU, dead-reckoned to the last published tick, is within the
        # server's 1 m threshold of the truth (positions go as float64, time by the timestamp).
        index = truth.index()
        start = seconds_past_hour(server.world_info().start_time)
        for i, p in last.items():
            t0 = (dis.timestamp_seconds(p.timestamp)[0] - start) % 3600.0
            assert t0 <= truth.time_s + 1e-5
            pos, _ = extrapolate(p.dr_algorithm, t0, np.array([p.location]), np.array([p.linear_velocity]),
                                 np.array([p.dr_linear_acceleration]), dis.quat_from_dis_euler([p.orientation]),
                                 np.array([p.dr_angular_velocity]), truth.time_s)
            assert np.linalg.norm(pos[0] - truth.ecef_m[index[i]]) < 1.0 + 0.01, names[i]
        # A removed entity's last PDU says deactivated; paused, the others heartbeat on wall time.
        server.set_clock("realtime")
        sam = next(i for i, n in names.items() if n == "sam1")
        world.remove(sam)
        gone = receive(peer, 5.0, until=lambda ps: any(p.entity_id[2] == sam and p.deactivated for p in ps))
        assert any(p.entity_id[2] == sam and p.deactivated for p in gone)
        assert gw.pdus_sent >= len(pdus) and gw.pdus_malformed == 0
    # Stopping deactivates everything still in the exercise.
    final = receive(peer, 1.0)
    assert {p.entity_id[2] for p in final if p.deactivated} >= set(world.entities)
    peer.close()


def test_gateway_heartbeats_a_paused_world(server):
    peer = dis_socket()
    with DisGateway(server.address, port=peer.getsockname()[1], site=5, application=78, heartbeat_s=0.5):
        receive(peer, 10.0, until=lambda ps: len({p.entity_id for p in ps}) == len(server.world.entities))
        server.set_clock("paused")
        receive(peer, 1.0)  # drain
        again = receive(peer, 1.6)
        counts = {i: sum(p.entity_id[2] == i for p in again) for i in server.world.entities}
        assert all(2 <= c <= 5 for c in counts.values()), counts  # every 0.5 s, with nothing from the server
    peer.close()


def remote_pdu(entity: int, lat=47.3, lon=9.4, alt=3000.0, exercise=9, deactivated=False, marking="EXT1"):
    """A DIS aircraft of site 900 heading east at 100 m/s, as another simulation sends it."""
    east = np.asarray(enu_basis(lat, lon)[0]).reshape(3)
    from fdm.state import euler_to_quaternion
    from server.dead_reckoning import ned_to_ecef_quat

    q = ned_to_ecef_quat(euler_to_quaternion(0.0, 0.0, math.pi / 2), lat, lon)
    return dis.encode_pdu(dis.entity_state_pdu(
        exercise_id=exercise, entity_id=(900, 1, entity), kind="aircraft", type_name="f15", coalition="red",
        name=marking, ecef_m=np.asarray(geodetic_to_ecef(lat, lon, alt)).reshape(3), vel_ecef_mps=100.0 * east,
        acc_ecef_mps2=(0, 0, 0), quat_wxyz=q, body_rates_rps=(0, 0, 0), algorithm=dis.DR_FPW, timestamp=0,
        appearance=dis.APPEARANCE_DEACTIVATED if deactivated else 0))


def test_gateway_publishes_dis_entities_and_times_them_out(server):
    from client.sim_client import SimClient

    peer = dis_socket()
    port = peer.getsockname()[1]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sender.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    send = lambda data: sender.sendto(data, (LOOPBACK_BROADCAST, port))  # noqa: E731
    with DisGateway(server.address, port=port, exercise=9, site=5, application=79, remote_timeout_s=1.0) as gw, \
            SimClient(server.address) as obs:
        obs.join("obs", "observer", observer=(47.3, 9.4, 50_000.0))
        seen = obs.watch()
        external = lambda p: [i for i in p.infos.values() if i.external_id]  # noqa: E731
        # Hostile and foreign traffic first: counted, never fatal.
        send(b"\x07garbage")
        send(remote_pdu(1, exercise=8))
        send(remote_pdu(1)[:100])
        sent_at = time.monotonic()
        send(remote_pdu(1))
        assert seen.wait_for(lambda p: len(external(p)) == 1, 10.0)
        info = external(seen)[0]
        assert (info.external_id, info.name, info.kind, info.type, info.coalition) == (
            "dis:900.1.1", "EXT1", pb.ENTITY_KIND_AIRCRAFT, "f15", "red")
        # Where we sent it (100 m/s east since it was sent, and the 1 m threshold).
        _, pos, _ = seen.state(ids=[info.entity_id])
        sent = np.asarray(geodetic_to_ecef(47.3, 9.4, 3000.0)).reshape(3)
        assert np.linalg.norm(pos[0] - sent) < 1.0 + 100.0 * (time.monotonic() - sent_at + 0.1)
        assert gw.remote_entities == 1 and gw.pdus_malformed == 2 and gw.pdus_ignored >= 1
        # A deactivated PDU removes it (with the timeout out of the way meanwhile).
        gw.remote_timeout_s = 60.0
        send(remote_pdu(1, deactivated=True))
        assert seen.wait_for(lambda p: not external(p), 5.0)
        assert gw.remote_entities == 0
        gw.remote_timeout_s = 1.0
        # Kept alive by its PDUs, it is never sent back out as one of ours.
        ours = []
        for _ in range(8):
            send(remote_pdu(2, marking="EXT2"))
            last_sent = time.monotonic()
            ours += receive(peer, 0.2)
        assert seen.wait_for(lambda p: [i.name for i in external(p)] == ["EXT2"], 1.0)
        from_gateway = {p.marking_text for p in ours if p.entity_id[:2] == (5, 79)}
        assert from_gateway and not any(m.startswith("EXT") for m in from_gateway), from_gateway
        # Silent, it goes after the remote timeout.
        assert seen.wait_for(lambda p: not external(p), 5.0)
        assert 1.0 <= time.monotonic() - last_sent < 3.0
        assert gw.remote_entities == 0 and gw.pdus_malformed == 2
    sender.close()
    peer.close()


def test_entities_that_are_not_ours_to_send_are_refused(caplog):
    gw = DisGateway("127.0.0.1:1")  # never started: the listener alone
    update = pb.WatchUpdate(snapshot=True, entered=[pb.EntityInfo(entity_id=70_000, name="big"),
                                                    pb.EntityInfo(entity_id=3, name="EXT", external_id="dis:1.2.3")])
    with caplog.at_level("WARNING"):
        gw._on_update(None, update)
        gw._on_update(None, update)
    assert gw.local_entities == 0 and gw.pdus_sent == 0
    refused = [r.getMessage() for r in caplog.records]
    assert len(refused) == 1 and "entity 70000 (big)" in refused[0] and "65534" in refused[0]


def test_sortie_dis_command_runs_until_sigterm(server):
    peer = dis_socket()
    proc = subprocess.Popen([*sortie_command(), "dis", "--server", server.address, "--port",
                             str(peer.getsockname()[1]), "--exercise", "9", "--site", "6"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        pdus = receive(peer, 20.0, until=lambda ps: len({p.entity_id for p in ps}) == len(server.world.entities))
        assert {p.entity_id[:2] for p in pdus} == {(6, 1)} and {p.exercise_id for p in pdus} == {9}
        proc.terminate()
        out, err = proc.communicate(timeout=20)
        assert proc.returncode == 0, err
        lines = out.splitlines()
        assert len(lines) == 2 and lines[0].startswith("sortie dis: exercise 9 on 127.255.255.255:")
        assert re.match(r"sortie dis: stopped; \d+ PDUs sent", lines[1]) and not err.strip()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        peer.close()
    bad = subprocess.run([*sortie_command(), "dis", "--server", server.address, "--exercise", "300"],
                         capture_output=True, text=True, timeout=60)
    assert bad.returncode == 2 and "exercise: must be an integer in [0, 255] (got 300)" in bad.stderr


def test_gateway_notices_the_server_going_away(server):
    peer = dis_socket()
    gw = DisGateway(server.address, port=peer.getsockname()[1], site=5, application=80).start()
    try:
        receive(peer, 10.0, until=lambda ps: len({p.entity_id for p in ps}) == len(server.world.entities))
        server.stop(0.5)
        assert gw.finished.wait(10.0), "the gateway's stop signal when the server's stream ends"
    finally:
        t = time.monotonic()
        gw.stop()  # no exception with the server gone, and no long wait
        assert time.monotonic() - t < 5.0
        peer.close()


def test_unique_name_keeps_a_free_marking_and_suffixes_a_taken_one():
    assert dis.unique_name("EXT1", "dis:900.1.2", {"viper1"}) == "EXT1"
    assert dis.unique_name("EXT1", "dis:900.1.2", {"EXT1"}) == "EXT1 900.1.2"
    assert dis.unique_name("EXT1", "dis:900.1.2", {"EXT1", "EXT1 900.1.2"}) == "dis:900.1.2"
    assert dis.unique_name("EXT1", "dis:900.1.2", {"EXT1", "EXT1 900.1.2", "dis:900.1.2"}) == "dis:900.1.2#2"


def test_one_refused_dis_entity_never_costs_the_others(server, monkeypatch):
    """Two DIS entities with one marking both join (unique names). Then the world refuses one
    (its entity limit, set low here): the server ends the gateway's stream, and still the next
    entity's update arrives, and every published entity is removed or timed out."""
    from client.sim_client import SimClient
    from server import world as world_module

    peer = dis_socket()
    port = peer.getsockname()[1]
    sender = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sender.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    send = lambda data: sender.sendto(data, (LOOPBACK_BROADCAST, port))  # noqa: E731
    with DisGateway(server.address, port=port, exercise=9, site=5, application=81, remote_timeout_s=60.0) as gw, \
            SimClient(server.address) as obs:
        obs.join("obs", "observer", observer=(47.3, 9.4, 50_000.0))
        seen = obs.watch()
        external = lambda p: {i.external_id: i.name for i in p.infos.values() if i.external_id}  # noqa: E731
        send(remote_pdu(11, marking="SAME"))
        assert seen.wait_for(lambda p: len(external(p)) == 1, 10.0)
        send(remote_pdu(12, marking="SAME"))
        assert seen.wait_for(lambda p: len(external(p)) == 2, 10.0), external(seen)
        assert external(seen) == {"dis:900.1.11": "SAME", "dis:900.1.12": "SAME 900.1.12"}
        monkeypatch.setattr(world_module, "MAX_ENTITIES", len(server.world.entities))
        send(remote_pdu(13, marking="EXT13"))  # refused: the world is full; the stream ends
        time.sleep(1.0)
        send(remote_pdu(11, deactivated=True))  # meets the ended stream: sent again on a new one
        assert seen.wait_for(lambda p: "dis:900.1.11" not in external(p), 10.0), external(seen)
        send(remote_pdu(14, marking="EXT14"))
        assert seen.wait_for(lambda p: "dis:900.1.14" in external(p), 10.0), external(seen)
        assert "dis:900.1.13" not in external(seen)
        gw.remote_timeout_s = 1.0  # silent now: every entity the gateway published goes
        assert seen.wait_for(lambda p: not external(p), 10.0), external(seen)
        assert gw.remote_entities == 0
    sender.close()
    peer.close()


def test_collision_pdu_layout_and_round_trip():
    """The Collision PDU as IEEE 1278.1-2012 §7.2.3 lays it out: 60 bytes, type 4, family 1;
    the issuing, colliding and event ids at bytes 12, 18 and 24, the type at 30, velocity
    at 32, mass at 44, location at 48; decoding gives back what was encoded (float32)."""
    pdu = dis.CollisionPdu(exercise_id=3, issuing_entity_id=(1, 2, 3), colliding_entity_id=(4, 5, 6),
                           event_id=(1, 2, 77), collision_type=dis.COLLISION_INELASTIC,
                           velocity=(250.0, -1.5, 0.25), mass_kg=12000.0, location=(1.0, 2.0, -0.5), timestamp=1234)
    wire = dis.encode_collision_pdu(pdu)
    assert len(wire) == dis.COLLISION_BYTES == 60
    assert wire[2] == dis.PDU_TYPE_COLLISION and wire[3] == 1 and int.from_bytes(wire[8:10], "big") == 60
    assert struct.unpack(">9H", wire[12:30]) == (1, 2, 3, 4, 5, 6, 1, 2, 77)
    assert wire[30] == 0 and wire[31] == 0
    assert struct.unpack(">3f", wire[32:44]) == (250.0, -1.5, 0.25)
    assert struct.unpack(">f", wire[44:48]) == (12000.0,)
    assert struct.unpack(">3f", wire[48:60]) == (1.0, 2.0, -0.5)
    assert dis.decode_collision_pdu(wire) == pdu
    assert isinstance(dis.decode_pdu(wire), dis.OtherPdu)  # the entity-state decoder leaves it alone
    with pytest.raises(InvalidArgument, match="colliding_entity_id.entity"):
        dis.encode_collision_pdu(dataclasses.replace(pdu, colliding_entity_id=(4, 5, 70000)))
    with pytest.raises(DataFormatError, match="length"):
        dis.decode_collision_pdu(wire[:-4])


def test_gateway_issues_collision_pdus_and_marks_the_wrecks_destroyed(alps):
    """Two f16s head-on 2 km apart at 250 m/s each: after the world's collision, the
    gateway sends one Collision PDU issued by each, naming the other, with the velocity of
    its last Entity State PDU, and from then on both wrecks' Entity State PDUs carry the
    appearance's damage "destroyed" (before: none); so do a gateway's that joins later."""
    from fdm.aircraft import InitialConditions
    from server.sim_server import ServerConfig, SimulationServer
    from server.world import World

    w = World(alps)
    east_deg = 1000.0 / (111_200.0 * math.cos(math.radians(47.3)))
    a = w.spawn_aircraft("a", "f16", InitialConditions(47.3, 9.3 - east_deg, 4000.0, heading_deg=90.0,
                                                         speed_mps=250.0))
    b = w.spawn_aircraft("b", "f16", InitialConditions(47.3, 9.3 + east_deg, 4000.0, heading_deg=270.0,
                                                         speed_mps=250.0))
    srv = SimulationServer(w, ServerConfig(clock="realtime"))
    peer = dis_socket()
    srv.start()
    try:
        with DisGateway(srv.address, port=peer.getsockname()[1], site=5, application=82):
            states = receive(peer, 3.0, until=lambda ps: {p.entity_id[2] for p in ps} >= {a.id, b.id})
            assert {p.entity_id[2] for p in states} >= {a.id, b.id}
            assert all(not p.appearance & dis.APPEARANCE_DESTROYED for p in states)
            collisions, after = [], []
            deadline = time.monotonic() + 15.0
            while time.monotonic() < deadline and not (len(collisions) >= 2 and after):
                try:
                    data = peer.recv(65536)
                except socket.timeout:
                    continue
                for d in dis.split_datagram(data):
                    if d[2] == dis.PDU_TYPE_COLLISION:
                        collisions.append(dis.decode_collision_pdu(d))
                    elif collisions:
                        p = dis.decode_pdu(d)
                        if isinstance(p, dis.EntityStatePdu):
                            after.append(p)
            pairs = {(c.issuing_entity_id, c.colliding_entity_id) for c in collisions}
            assert pairs == {((5, 82, a.id), (5, 82, b.id)), ((5, 82, b.id), (5, 82, a.id))}
            assert len({c.event_id for c in collisions}) == 2
            assert all(c.event_id[:2] == (5, 82) for c in collisions)
            for c in collisions:
                assert 200.0 < math.hypot(*c.velocity) < 300.0
            deadline = time.monotonic() + 5.0
            while {p.entity_id[2] for p in after} < {a.id, b.id} and time.monotonic() < deadline:
                after += receive(peer, 0.5)
            assert {p.entity_id[2] for p in after} >= {a.id, b.id}
            last = {p.entity_id[2]: p for p in after}
            for i in (a.id, b.id):
                assert last[i].appearance & dis.APPEARANCE_DESTROYED == dis.APPEARANCE_DESTROYED
        # A gateway that joins after the crash sends the wrecks destroyed from its first PDU.
        with DisGateway(srv.address, port=peer.getsockname()[1], site=6, application=83):
            late = [p for p in receive(peer, 5.0, until=lambda ps: {p.entity_id for p in ps} >= {
                (6, 83, a.id), (6, 83, b.id)}) if p.entity_id[:2] == (6, 83)]
            assert {p.entity_id[2] for p in late} >= {a.id, b.id}
            assert all(p.appearance & dis.APPEARANCE_DESTROYED == dis.APPEARANCE_DESTROYED for p in late)
    finally:
        peer.close()
        srv.stop(0.5)
