"""Regenerate (or check) the Python code in ``sortie/v1`` from ``proto/sortie/v1``.

    python -m sortie.protogen            # rewrite sortie/v1/*_pb2.py, *_pb2_grpc.py, *_pb2.pyi
    python -m sortie.protogen --check    # exit 1 listing generated files that are stale

protoc runs with ``-Iproto`` and the repository root as output folder, so
``proto/sortie/v1/terrain.proto`` becomes the module ``sortie.v1.terrain_pb2``
and generated modules import each other as ``sortie.v1.x_pb2``. The generated
files are committed; the check (run by tests/test_proto_sync.py) fails when
they no longer match what the protos and the installed grpcio-tools produce.
"""

from __future__ import annotations

import argparse
import filecmp
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PROTO_ROOT = REPO / "proto"
PACKAGE_DIR = "sortie/v1"
GENERATED_SUFFIXES = ("_pb2.py", "_pb2_grpc.py", "_pb2.pyi")


def proto_files(proto_root: Path = PROTO_ROOT) -> list[str]:
    """The .proto files of the package, relative to proto_root, sorted."""
    return sorted(p.relative_to(proto_root).as_posix() for p in (proto_root / PACKAGE_DIR).glob("*.proto"))


def generate(out_root: Path, proto_root: Path = PROTO_ROOT) -> list[Path]:
    """Run protoc on every proto of the package, writing under out_root; returns the files written."""
    from importlib import resources

    from grpc_tools import protoc

    protos = proto_files(proto_root)
    if not protos:
        raise FileNotFoundError(f"no .proto files in {proto_root / PACKAGE_DIR}")
    (out_root / PACKAGE_DIR).mkdir(parents=True, exist_ok=True)
    well_known = resources.files("grpc_tools") / "_proto"
    args = [
        "grpc_tools.protoc",
        f"-I{proto_root}",
        f"-I{well_known}",
        f"--python_out={out_root}",
        f"--pyi_out={out_root}",
        f"--grpc_python_out={out_root}",
        *protos,
    ]
    if protoc.main(args) != 0:
        raise RuntimeError(f"protoc failed: {' '.join(args)}")
    return generated_files(out_root)


def generated_files(root: Path) -> list[Path]:
    """Generated modules present under root/sortie/v1."""
    folder = root / PACKAGE_DIR
    return sorted(p for p in folder.iterdir() if p.name.endswith(GENERATED_SUFFIXES))


def stale_files(repo: Path = REPO) -> list[str]:
    """Generated files under repo/sortie/v1 that differ from a fresh generation.

    Each entry is "path (why)": changed, missing, or left over from a proto
    that no longer exists.
    """
    with tempfile.TemporaryDirectory() as tmp:
        fresh = {p.name: p for p in generate(Path(tmp), repo / "proto")}
        current = {p.name: p for p in generated_files(repo)}
        stale = []
        for name in sorted(fresh.keys() | current.keys()):
            path = f"{PACKAGE_DIR}/{name}"
            if name not in current:
                stale.append(f"{path} (missing)")
            elif name not in fresh:
                stale.append(f"{path} (no proto generates it)")
            elif not filecmp.cmp(fresh[name], current[name], shallow=False):
                stale.append(f"{path} (changed)")
        return stale


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m sortie.protogen", description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true",
                        help="do not write; exit 1 and list the generated files that are stale")
    args = parser.parse_args(argv)
    if args.check:
        stale = stale_files()
        for entry in stale:
            print(f"stale: {entry}")
        if stale:
            print("run `python -m sortie.protogen` (or `make proto`) and commit the result", file=sys.stderr)
            return 1
        print(f"generated code in {PACKAGE_DIR} is up to date")
        return 0
    for leftover in generated_files(REPO):
        leftover.unlink()
    for path in generate(REPO):
        print(f"wrote {path.relative_to(REPO)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
