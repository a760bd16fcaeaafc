"""Probe pass s35 on recordings and their exports (issues #6 and #8): the fixes it made.

- ``sortie export acmi`` named its bad options by the Python parameter (``rate: ...``,
  ``output: ...``) where ``sortie export gltf`` names the option the user typed (``--rate``).
- ``sortie export gltf -o scene.txt`` answered "must end in one of .glb, .gltf, .obj, .ply,
  .stl" (terrain/mesh.py's list for ``sortie terrain mesh``), and ``-o scene.obj``, which
  that list offers, was refused only after the recording and its terrain were opened.
"""

from __future__ import annotations

import subprocess

import pytest

from server.gltf import check_output
from sortie.errors import InvalidArgument
from server.process import sortie_command


def _export(tmp_path, *args):
    # The options are checked before the recording is opened: a missing recording shows it.
    return subprocess.run([*sortie_command(), "export", *args, str(tmp_path / "none.sortie")],
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, says", [
    (("acmi", "-o", "x.acmi", "--rate", "0"), "--rate: must be a finite number of frames per second > 0 (got 0.0)"),
    (("acmi", "-o", "x.acmi", "--rate", "nan"), "--rate: must be a finite number of frames per second > 0 (got nan)"),
    (("acmi", "-o", "x.txt"), "--output: must end in .acmi or .zip.acmi (got 'x.txt')"),
])
def test_sortie_export_acmi_names_its_options(tmp_path, args, says):
    done = _export(tmp_path, *args)
    assert done.returncode == 2 and says in done.stderr, done.stderr


@pytest.mark.parametrize("name", ["scene.txt", "scene.obj", "scene.ply", "scene.STL", "scene"])
def test_sortie_export_gltf_offers_only_the_forms_it_writes(tmp_path, name):
    done = _export(tmp_path, "gltf", "--no-terrain", "-o", str(tmp_path / name))
    assert done.returncode == 2, done.stderr
    assert "--output: a debrief scene is written as .glb or .gltf" in done.stderr and name in done.stderr, done.stderr
    assert ".obj" not in done.stderr.replace(name, "") and "not found" not in done.stderr.lower(), done.stderr


def test_check_output_takes_glb_and_gltf_only():
    assert check_output("a/b.GLB") == "glb" and check_output("b.gltf") == "gltf"
    for bad in ("b.obj", "b.glb.txt", "b"):
        with pytest.raises(InvalidArgument) as err:
            check_output(bad)
        assert err.value.field == "output" and err.value.value == bad
