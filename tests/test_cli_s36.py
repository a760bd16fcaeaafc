"""Command-line fixes from the thirty-sixth session's documentation probe: `sortie terrain info`
refuses --address beside terrain files (it described the service alone), and a reader that
leaves the pipe early is no error of the command's."""

import subprocess
import sys

from conftest import shared_or_embedded


def _sortie(*args, **kwargs):
    return subprocess.run([sys.executable, "-m", "sortie.cli", *args], capture_output=True, text=True, timeout=120,
                          **kwargs)


def test_terrain_info_refuses_an_address_beside_terrain_files():
    """As `terrain texture` and `terrain mesh` do: no service is asked, so none need be there."""
    dem = str(shared_or_embedded("N47E009.hgt"))
    for extra in (["--dem", dem], ["--procedural", "7"]):
        done = _sortie("terrain", "info", *extra, "--address", "127.0.0.1:1")
        assert done.returncode == 2, done
        assert "--address: give a service address or terrain files, not both (got '127.0.0.1:1')" in done.stderr


def test_a_reader_leaving_the_pipe_is_no_error():
    """`sortie terrain info --json | head -1`: the reader gone before the command writes. Before:
    'sortie terrain: error: [Errno 32] Broken pipe', exit 2; now nothing on stderr, exit 1 (as
    Python's own advice on SIGPIPE has it)."""
    dem = str(shared_or_embedded("N47E009.hgt"))
    proc = subprocess.Popen([sys.executable, "-m", "sortie.cli", "terrain", "info", "--dem", dem, "--json"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    proc.stdout.close()  # the reader leaves before anything is written
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 1, (proc.returncode, err)
    assert "Broken pipe" not in err and "Traceback" not in err, err


def test_terrain_import_errors_name_the_options(tmp_path):
    """The importer's parameters as the command line spells them (before: 'step: ...', 'output:
    ...', which are its Python names)."""
    dem = str(shared_or_embedded("N47E009.hgt"))
    a_file = tmp_path / "afile"
    a_file.write_text("not a directory")
    done = _sortie("terrain", "import", dem, "-o", str(a_file), "--no-progress")
    assert done.returncode == 2 and f"sortie terrain: error: --output: {a_file} exists and is not a directory" \
        in done.stderr, done.stderr
    done = _sortie("terrain", "import", dem, "-o", str(tmp_path / "st"), "--step", "0.015", "--no-progress")
    assert done.returncode == 2 and "sortie terrain: error: --step: " in done.stderr, done.stderr
    assert not (tmp_path / "st" / "store.json").exists()
