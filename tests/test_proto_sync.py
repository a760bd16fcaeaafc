"""The committed code in sortie/v1 matches the protos, and the protos follow the
house rules (STYLE.md item 5): package sortie.v1, enum zero *_UNSPECIFIED, a
comment on every RPC and field, PointStatus equal to terrain.raster STATUS_*.
"""

from __future__ import annotations

import shutil
import subprocess
import sys

import pytest
from google.protobuf import descriptor_pb2

from sortie import protogen
from terrain import raster


def test_generated_code_is_up_to_date():
    result = subprocess.run([sys.executable, "-m", "sortie.protogen", "--check"], cwd=protogen.REPO,
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr


def test_check_reports_changed_missing_and_orphaned_files(tmp_path):
    shutil.copytree(protogen.REPO / "proto", tmp_path / "proto")
    shutil.copytree(protogen.REPO / "sortie" / "v1", tmp_path / "sortie" / "v1")
    assert protogen.stale_files(tmp_path) == []
    v1 = tmp_path / "sortie" / "v1"
    with open(v1 / "terrain_pb2.py", "a") as f:
        f.write("# edited by hand\n")
    (v1 / "terrain_pb2_grpc.py").unlink()
    (v1 / "removed_pb2.py").write_text("")
    assert protogen.stale_files(tmp_path) == [
        "sortie/v1/removed_pb2.py (no proto generates it)",
        "sortie/v1/terrain_pb2.py (changed)",
        "sortie/v1/terrain_pb2_grpc.py (missing)",
    ]


@pytest.fixture(scope="module")
def proto_files(tmp_path_factory) -> list[descriptor_pb2.FileDescriptorProto]:
    """The package's protos as parsed by protoc, with their comments."""
    from grpc_tools import protoc

    out = tmp_path_factory.mktemp("descriptors") / "set.pb"
    assert protoc.main(["protoc", f"-I{protogen.PROTO_ROOT}", "--include_source_info",
                        f"--descriptor_set_out={out}", *protogen.proto_files()]) == 0
    return list(descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes()).file)


def _comments(f: descriptor_pb2.FileDescriptorProto) -> dict[tuple, str]:
    return {tuple(loc.path): loc.leading_comments + loc.trailing_comments for loc in f.source_code_info.location}


def test_protos_are_versioned_and_documented(proto_files):
    # Paths into FileDescriptorProto: message_type = 4, field = 2, enum_type = 5, value = 2,
    # service = 6, method = 2 (descriptor.proto field numbers).
    for f in proto_files:
        assert f.package == "sortie.v1", f.name
        comments = _comments(f)
        for s, service in enumerate(f.service):
            for m, method in enumerate(service.method):
                text = comments.get((6, s, 2, m), "")
                assert "Unary" in text or "stream" in text, f"{method.name}: say its streaming kind"
        for i, message in enumerate(f.message_type):
            for j, field in enumerate(message.field):
                assert comments.get((4, i, 2, j), "").strip(), f"{message.name}.{field.name} has no comment"
        for i, enum in enumerate(f.enum_type):
            assert enum.value[0].number == 0 and enum.value[0].name.endswith("_UNSPECIFIED"), enum.name
            for j, value in enumerate(enum.value):
                assert comments.get((5, i, 2, j), "").strip(), f"{enum.name}.{value.name} has no comment"


def test_point_status_equals_raster_status():
    from sortie.v1 import terrain_pb2 as pb

    assert pb.POINT_STATUS_OK == raster.STATUS_OK
    assert pb.POINT_STATUS_FILLED == raster.STATUS_FILLED
    assert pb.POINT_STATUS_OUTSIDE == raster.STATUS_OUTSIDE
