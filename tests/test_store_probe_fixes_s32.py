"""Fixes to the terrain store found by the s32 acceptance probe (docs/STORE.md).

1. A manifest whose ``unit_m`` is not 1 cm (one flipped bit, 0.01 -> 0.03, tripled every height
   with status OK), whose ``lossless`` does not say whether the step is 1 unit (GetMetadata then
   claimed 0.005 m for a 1 m step), or whose ``vertical_datum`` no import writes, is refused naming
   store.json, the key and the value; an import of another unit is refused before it writes.
2. Class blobs are zstd frames with a content checksum: a flipped bit inside one that still
   decodes is refused naming the level file and the tile (it was read silently).
3. A store opened before a re-import reads its own files at every level (levels opened lazily
   after the re-import mixed the two pyramids: damage errors or wrong heights); a level file opened
   after a re-import is refused, saying the store was re-imported and naming it; ``open_store``
   opens the re-imported store anew.
4. A write that fails while importing (a full disk, a file past the process's size limit) is
   InvalidArgument naming output and the file, and leaves no partial file (it was a bare
   ``[Errno 28] No space left on device``, the partial band left in .import/).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import zstandard

from sortie.cli import main
from sortie.errors import DataFormatError, InvalidArgument, shown
from terrain import store as st
from terrain.store import MANIFEST, StoreSource, TerrainStore, open_store
from terrain.store_import import import_dems
from terrain.terrain import Terrain

REPO = Path(__file__).resolve().parents[1]
CS = 1.0 / 1200.0  # 3 arc-seconds
N = 300  # posts a side of the test DEM: at the default depth (1.236" x 1.648"), a region of 3 x 2 tiles, 3 levels


def _write_asc(path: Path, h: np.ndarray, x0: float = 9.5, y0: float = 47.0) -> Path:
    """An ESRI ASCII grid (corner registration) of h (rows north to south), NODATA -9999."""
    head = [f"ncols {h.shape[1]}", f"nrows {h.shape[0]}", f"xllcorner {x0!r}", f"yllcorner {y0!r}",
            f"cellsize {CS!r}", "NODATA_value -9999"]
    path.write_text("\n".join(head + [" ".join(f"{v:.2f}" for v in row) for row in h]) + "\n")
    return path


def _terrain_heights(seed: int = 0) -> np.ndarray:
    """Hills of a few hundred metres with centimetre noise, and an enclosed void (a filled class)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:N, 0:N] / N
    h = 800 + 300 * np.sin(7 * x) * np.cos(5 * y) + 80 * np.sin(23 * x + 11 * y) + rng.normal(0, 2, (N, N))
    h[140:150, 160:172] = -9999
    return h


@pytest.fixture(scope="module")
def dems(tmp_path_factory):
    """(the DEM, the same DEM with a 3 m bump): the second is what a re-import brings."""
    d = tmp_path_factory.mktemp("dems")
    h = _terrain_heights()
    bumped = h.copy()
    bumped[100:200, 100:200] = np.where(bumped[100:200, 100:200] > -9999, bumped[100:200, 100:200] + 3.0, -9999)
    return _write_asc(d / "hills.asc", h), _write_asc(d / "hills_bump.asc", bumped)


@pytest.fixture(scope="module")
def reference(tmp_path_factory, dems):
    """A store of the DEM at a 1 m step (read-only: tests copy it)."""
    out = tmp_path_factory.mktemp("ref") / "st"
    import_dems([dems[0]], out, step_m=1.0)
    return out


def _points(store: TerrainStore, n: int = 4000):
    b = store.regions[0].bounds
    rng = np.random.default_rng(1)
    return rng.uniform(b[0], b[2], n), rng.uniform(b[1], b[3], n)


def _heights(store: TerrainStore, level: int, lat, lon) -> np.ndarray:
    return Terrain([StoreSource(store, level)]).heights(lat, lon).height_msl_m


# --------------------------------------------------------------------------- 1: the manifest's unit, step, datum


def _set(key, value):
    return lambda m: m.__setitem__(key, value)


MANIFEST_DAMAGE = {  # case: (key, damage, the value the message shows)
    "unit_m 0.03 (one bit)": ("unit_m", _set("unit_m", 0.03), 0.03),
    "unit_m 0.02": ("unit_m", _set("unit_m", 0.02), 0.02),
    "unit_m 1": ("unit_m", _set("unit_m", 1), 1),
    "lossless true at a 1 m step": ("lossless", _set("lossless", True), True),
    "lossless 'no'": ("lossless", _set("lossless", "no"), "no"),
    "lossless missing": ("lossless", lambda m: m.pop("lossless"), None),
    "vertical_datum ellipsoid": ("vertical_datum", _set("vertical_datum", "WGS84 ellipsoid"), "WGS84 ellipsoid"),
}


@pytest.mark.parametrize("case", sorted(MANIFEST_DAMAGE))
def test_a_manifest_of_another_unit_step_flag_or_datum_is_refused_naming_the_file_key_and_value(reference, tmp_path,
                                                                                               case):
    """Bound: DataFormatError naming store.json, the key and its value (old code opened each: unit_m
    0.03 answered 3x every height with status OK; lossless true made max_error_m 0.005 m, not 0.505)."""
    key, damage, value = MANIFEST_DAMAGE[case]
    out = tmp_path / "st"
    shutil.copytree(reference, out)
    m = json.loads((out / MANIFEST).read_text())
    damage(m)
    (out / MANIFEST).write_text(json.dumps(m))
    with pytest.raises(DataFormatError) as e:
        TerrainStore(out)
    msg = str(e.value)
    assert str(out / MANIFEST) in msg and f"{key} " in msg, msg
    if value is not None:
        assert shown(value) in msg, msg


def test_a_lossless_store_saying_it_is_not_is_refused_and_every_datum_an_import_writes_opens(reference, tmp_path,
                                                                                            dems):
    """lossless false with step_units 1 is refused; the readers' datums (SRTM's, "as supplied", each
    EPSG one) all open, and the unchanged store answers within its max_error_m of the DEM."""
    out = tmp_path / "st"
    import_dems([dems[0]], out, lossless=True)
    m = json.loads((out / MANIFEST).read_text())
    assert m["lossless"] is True and m["step_units"] == 1
    (out / MANIFEST).write_text(json.dumps({**m, "lossless": False}))
    with pytest.raises(DataFormatError, match=r"lossless False does not go with step_units 1"):
        TerrainStore(out)
    from terrain import dem

    for datum in (dem.VERTICAL_DATUM_SRTM, dem.VERTICAL_DATUM_DEFAULT, *dem.VERTICAL_DATUMS_EPSG.values()):
        (out / MANIFEST).write_text(json.dumps({**m, "vertical_datum": datum}))
        assert Terrain([StoreSource(TerrainStore(out))]).describe()[0]["vertical_datum"] == datum


def test_an_import_in_another_unit_is_refused_before_it_writes(dems, tmp_path):
    """Bound: InvalidArgument naming unit_m and the value, nothing written (old code wrote a store of
    3 cm units, which readers now refuse)."""
    with pytest.raises(InvalidArgument) as e:
        import_dems([dems[0]], tmp_path / "st", unit_m=0.03)
    assert e.value.field == "unit_m" and e.value.value == 0.03
    assert not (tmp_path / "st").exists()


# --------------------------------------------------------------------------- 2: class blob checksums


def _class_tile(store: TerrainStore):
    """(level file, tile row, tile col, offset of its class blob, the blob) of the first tile of
    level 0 whose classes are not all one (the DEM's edges and its void)."""
    path = st.level_file(store.path, 0, 0)
    entries, _, _ = store._level_index(0, 0)
    data = path.read_bytes()
    for e in entries:
        if e["clen"] > 1:
            start = int(e["offset"]) + int(e["hlen"])
            return path, int(e["row"]), int(e["col"]), start, data[start:start + int(e["clen"])]
    raise AssertionError("no tile of mixed classes")


def test_class_blobs_carry_a_checksum_and_a_flip_inside_one_is_refused(reference, tmp_path):
    """Every non-uniform class blob has a content checksum; 160 single-bit flips spread over one
    (frame header, compressed classes, checksum) each raise DataFormatError naming the level file and
    the tile, or decode to the same classes. Bound: no flip reads different classes (old code: no
    checksum, and flips in the literals read other classes silently)."""
    out = tmp_path / "st"
    shutil.copytree(reference, out)
    store = TerrainStore(out)
    path, ti, tj, start, blob = _class_tile(store)
    assert zstandard.get_frame_parameters(blob).has_checksum
    T = store.tile
    region = store.regions[0]
    rows, cols = (ti * T, ti * T + T), (tj * T, tj * T + T)
    want = store.decode(region, 0, *rows, *cols)[1].copy()
    store.close()
    original = path.read_bytes()
    rng = np.random.default_rng(2)
    refused = 0
    for bit in rng.choice(8 * len(blob), size=min(160, 8 * len(blob)), replace=False):
        damaged = bytearray(original)
        damaged[start + bit // 8] ^= 1 << (bit % 8)
        path.write_bytes(bytes(damaged))
        try:
            got = TerrainStore(out).decode(region, 0, *rows, *cols)[1]
        except DataFormatError as e:
            assert f"{path}: tile ({ti}, {tj})" in str(e), str(e)
            refused += 1
            continue
        np.testing.assert_array_equal(got, want, err_msg=f"bit {bit} of the class blob flipped: read silently")
    assert refused > 0


# --------------------------------------------------------------------------- 3: re-import while reading


def test_a_store_opened_before_a_reimport_reads_its_own_files_at_every_level(reference, dems, tmp_path):
    """The probe's sequence: a store read at level 2 only, then re-imported (the bumped DEM, lossless,
    over the 1 m store). Bound: at levels 0 and 1 the open store answers exactly what a copy of the
    old store does (old code opened those levels after the re-import: a mix of both pyramids raised
    damage errors or answered wrong heights); a fresh open reads the new store."""
    out = tmp_path / "st"
    shutil.copytree(reference, out)
    old = TerrainStore(reference)
    store = TerrainStore(out)
    lat, lon = _points(store)
    assert store.levels >= 3
    np.testing.assert_array_equal(_heights(store, 2, lat, lon), _heights(old, 2, lat, lon))
    import_dems([dems[1]], out, lossless=True)
    for level in (0, 1, 2):
        np.testing.assert_array_equal(_heights(store, level, lat, lon), _heights(old, level, lat, lon),
                                      err_msg=f"level {level}")
    new = TerrainStore(out)
    assert new.step_units == 1
    assert np.nanmax(np.abs(_heights(new, 0, lat, lon) - _heights(old, 0, lat, lon))) > 2.0  # the bump


def test_open_store_opens_a_reimported_store_anew(reference, dems, tmp_path):
    """open_store gives one instance per store until it is re-imported, then a new one reading the new
    files (old code kept the first instance: its levels not yet opened read the new files)."""
    out = tmp_path / "st"
    shutil.copytree(reference, out)
    first = open_store(out)
    assert open_store(out) is first
    import_dems([dems[1]], out, lossless=True)
    second = open_store(out)
    assert second is not first and second.step_units == 1 and first.step_units == 100
    assert open_store(out) is second
    lat, lon = _points(second)
    np.testing.assert_array_equal(_heights(second, 0, lat, lon), _heights(TerrainStore(out), 0, lat, lon))


@pytest.mark.parametrize("how", ["closed", "beyond the files opened with the manifest"])
def test_a_level_file_opened_after_a_reimport_is_refused_naming_the_store(reference, dems, tmp_path, monkeypatch,
                                                                          how):
    """A level file the store had not opened when it was re-imported (after close(), or past
    EAGER_LEVEL_FILES) is refused: DataFormatError saying the store was re-imported and to reopen
    it, naming the store and the file (old code read the new file silently into the old store)."""
    out = tmp_path / "st"
    shutil.copytree(reference, out)
    monkeypatch.setattr(st, "EAGER_LEVEL_FILES", 256 if how == "closed" else 1)
    store = TerrainStore(out)
    if how == "closed":
        store.close()
    import_dems([dems[1]], out, lossless=True)
    lat, lon = _points(store)
    with pytest.raises(DataFormatError) as e:
        _heights(store, 0, lat, lon)
    msg = str(e.value)
    assert f"terrain store {out}: re-imported since it was opened" in msg and "reopen it" in msg, msg
    assert "level-0" in msg, msg


# --------------------------------------------------------------------------- 4: a write that fails while importing


def _no_partial_files(out: Path) -> list[Path]:
    return sorted(p for p in out.rglob("*") if ".tmp" in p.name)


def test_an_import_past_the_file_size_limit_names_output_and_the_file_and_leaves_no_partial_file(dems, tmp_path):
    """`sortie terrain import` in a process whose files may not grow past 64 KiB (RLIMIT_FSIZE: the
    band file fails as on a full disk, with EFBIG). Bound: exit 2, the error names output and the
    band file under .import/, and no temporary file is left (old code: a bare '[Errno 27] File too
    large' and the partial band left). A first import without the limit loads (or writes) numba's
    cache, whose files the limit would refuse too."""
    out = tmp_path / "st"
    script = ("import resource, signal, sys\n"
              "from sortie.cli import main\n"
              "from terrain.store_import import import_dems\n"
              f"import_dems([{str(dems[0])!r}], {str(tmp_path / 'warm')!r})\n"
              "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
              "resource.setrlimit(resource.RLIMIT_FSIZE, (65536, resource.RLIM_INFINITY))\n"
              f"sys.exit(main(['terrain', 'import', {str(dems[0])!r}, '-o', {str(out)!r}, '--no-progress']))\n")
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r.stderr
    assert "output: cannot write" in r.stderr and f"{out / '.import'}/" in r.stderr and "File too large" in r.stderr, \
        r.stderr
    assert "Traceback" not in r.stderr
    assert _no_partial_files(out) == []
    assert not (out / MANIFEST).exists()


def test_a_level_file_write_that_fails_leaves_no_temporary_file(tmp_path):
    """write_level_file under a 4 KiB file size limit: the OSError propagates (the importer names the
    file) and neither level-00.tmp nor level-00.tiles is left (old code left the partial .tmp)."""
    path = tmp_path / "level-00.tiles"
    script = ("import resource, signal\n"
              "signal.signal(signal.SIGXFSZ, signal.SIG_IGN)\n"
              "resource.setrlimit(resource.RLIMIT_FSIZE, (4096, resource.RLIM_INFINITY))\n"
              "from pathlib import Path\n"
              "from terrain import store as st\n"
              "try:\n"
              f"    st.write_level_file(Path({str(path)!r}), 0, {{(0, 0): (bytes(20000), b'')}})\n"
              "except OSError as e:\n"
              "    print('OSError', e.errno)\n")
    r = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert "OSError 27" in r.stdout, r.stdout + r.stderr
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.mark.skipif(os.geteuid() != 0 or shutil.which("mount") is None, reason="mounts a tmpfs: needs root")
def test_an_import_onto_a_full_disk_names_output_and_the_file(dems, tmp_path, capsys):
    """The probe's case: a 1 MiB tmpfs. Bound: exit 2 naming output, the file and 'No space left on
    device'; no partial file left (old code: '[Errno 28] No space left on device' alone)."""
    disk = tmp_path / "full"
    disk.mkdir()
    if subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(disk)]).returncode != 0:
        pytest.skip("cannot mount a tmpfs here")
    try:
        out = disk / "st"
        rc = main(["terrain", "import", str(dems[0]), "-o", str(out), "--lossless", "--no-progress"])
        err = capsys.readouterr().err
        assert rc == 2, err
        assert "output: cannot write" in err and f"{out}/" in err and "No space left on device" in err, err
        assert _no_partial_files(out) == []
    finally:
        subprocess.run(["umount", str(disk)], check=True)

