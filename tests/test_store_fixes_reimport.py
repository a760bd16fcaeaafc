"""Fixes to the terrain store and its texture found by an acceptance probe (docs/STORE.md).

1. Re-importing into an existing store removes the level files and region directories of the
   earlier store that the new manifest does not list (nothing else), and the stored bytes count
   only the files the manifest lists.
2. An out-of-range --detail-seed is refused naming --detail-seed and the value, for both kinds of
   detail, before anything is written (it was a traceback for cellular detail).
3. No forest or farmland where the tree line is at or below the ground (near the poles).
4. The import's anti-aliasing averages kx x ky samples a post, each axis by its own spacing ratio.
5. texture.json's sun.per_pixel and the printed line agree.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import shared_or_embedded
from sortie.cli import main
from terrain import store as st
from terrain.store_import import import_dems

# ../shared/data/dem, or the project's embedded copies (data/dem); a test fails when neither has them.
ALPS = shared_or_embedded("N47E009.hgt")
BOULDER = shared_or_embedded("landlab_SRTMGL3_BoulderCO_553x553.asc")


def _tiles(store: Path) -> list[Path]:
    return sorted(store.rglob("*.tiles"))


# --------------------------------------------------------------------------- 1: re-import


def test_a_reimport_leaves_only_what_its_manifest_lists(tmp_path):
    """The Alps and Boulder (2 regions, 7 levels), then Boulder alone (1 region, 5 levels) into the
    same directory: the old region-001 and region-000's levels 5 and 6 go, a user's files stay,
    and the sizes are a fresh import's."""
    out = tmp_path / "store"
    import_dems([ALPS, BOULDER], out)
    assert (out / "region-001").is_dir() and (out / "region-000" / "level-06.tiles").is_file()
    (out / "notes.txt").write_text("mine")
    (out / "region-backup").mkdir()
    (out / "region-backup" / "level-00.tiles").write_bytes(b"mine")
    (out / "region-002").mkdir()
    (out / "region-002" / "readme.txt").write_text("mine")  # not a level file: kept, and its directory

    summary = import_dems([BOULDER], out)
    fresh = import_dems([BOULDER], tmp_path / "fresh")

    store = st.TerrainStore(out)
    listed = [out / f"region-{r['index']:03d}" / f"level-{k:02d}.tiles" for r in store.manifest["regions"]
              for k in range(len(r["rects"]))]  # docs/STORE.md, Files
    assert [p for p in _tiles(out) if p.parent.name != "region-backup"] == sorted(listed)
    assert not (out / "region-001").exists()
    assert not (out / "region-000" / "level-05.tiles").exists()
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "region-backup" / "level-00.tiles").read_bytes() == b"mine"
    assert (out / "region-002" / "readme.txt").read_text() == "mine"
    assert summary.levels == fresh.levels == 5 and summary.regions == 1
    assert summary.stored_bytes == fresh.stored_bytes == st.TerrainStore(tmp_path / "fresh").stored_bytes()
    assert summary.ratio_vs_int16 == fresh.ratio_vs_int16
    assert store.stored_bytes() == fresh.stored_bytes == sum(p.stat().st_size for p in listed)
    # The heights are the fresh store's: every level file is byte-identical.
    for p in listed:
        assert p.read_bytes() == (tmp_path / "fresh" / p.relative_to(out)).read_bytes()


# --------------------------------------------------------------------------- 2: --detail-seed


@pytest.mark.parametrize("kind", ["fractal", "cellular"])
@pytest.mark.parametrize("seed", ["-5", str(2**64)])
def test_an_out_of_range_detail_seed_is_refused_naming_the_option(tmp_path, capsys, kind, seed):
    out = tmp_path / "store"
    rc = main(["terrain", "import", str(BOULDER), "-o", str(out), "--add-detail", kind, "--detail-seed", seed,
               "--no-progress"])
    err = capsys.readouterr().err
    assert rc == 2
    assert "--detail-seed" in err and seed in err and "Traceback" not in err
    assert not out.exists()  # refused before the store directory (or its .import/) was made


# --------------------------------------------------------------------------- 3: arctic classes


def test_no_forest_or_farmland_where_the_tree_line_is_at_or_below_the_ground():
    """Flat lowland and the Alps' relief moved north of 78 N (tree line 0 m) are tundra, rock or snow;
    at mid latitudes the classes are unchanged (the histogram recorded before the fix)."""
    from terrain.dem import read_dem
    from terrain.texture import FARMLAND, FOREST, GRASS, class_histogram, class_map, slope_deg

    treed = [FARMLAND, GRASS, FOREST]
    for lat, h in [(78.0, 30.0), (80.0, 50.0), (85.0, 10.0), (89.9, 1.0), (-85.0, 10.0)]:
        z = np.full((256, 256), h)
        assert not np.isin(class_map(z, np.zeros_like(z), 30.0, 30.0, lat), treed).any(), lat
    z = np.asarray(read_dem(ALPS).heights, np.float64)[::3, ::3]
    slope = slope_deg(z, 90.0, 90.0)
    for lat in (78.0, 82.0, 88.0):
        assert not np.isin(class_map(z, slope, 90.0, 90.0, lat), treed).any(), lat
    assert class_histogram(class_map(z, slope, 90.0, 90.0, 47.5)) == {
        "nodata": 0, "water": 0, "beach": 0, "farmland": 61524, "grass_shrub": 14022, "forest": 50393,
        "alpine_meadow": 626, "rock": 34226, "snow": 10}
    assert class_histogram(class_map(z, slope, 90.0, 90.0, 70.0)) == {
        "nodata": 0, "water": 0, "beach": 0, "farmland": 7182, "grass_shrub": 148, "forest": 1746,
        "alpine_meadow": 93157, "rock": 46234, "snow": 12334}


# --------------------------------------------------------------------------- 4: anisotropic anti-aliasing


def _write_sine_asc(path: Path, dx: float, cols: int, period_cols: float, dy: float = 0.001,
                    rows: int = 201) -> Path:
    """1000 m plus a 100 m sine along longitude of period_cols source columns, south-west post at 46 N 7 E."""
    h = 1000.0 + 100.0 * np.sin(2.0 * np.pi * np.arange(cols) / period_cols)
    lines = [f"ncols {cols}", f"nrows {rows}", "xllcenter 7.0", "yllcenter 46.0", f"dx {dx!r}", f"dy {dy!r}"]
    row = " ".join(f"{v:.3f}" for v in h)
    path.write_text("\n".join(lines + [row] * rows) + "\n")
    return path


@pytest.mark.parametrize("dx, cols, worst_std_m", [(0.0002, 1501, 3.0), (0.001, 301, 7.5)])
def test_anti_aliasing_averages_each_axis_by_its_own_ratio(tmp_path, dx, cols, worst_std_m):
    """A 100 m sine of 3 source columns under store posts 36.6 source columns wide: averaged away
    (1.0 m of std left), not aliased (46 m with one factor from the latitude ratio, 5.5). Posts 7.3
    columns wide (a square source): 7.0 m, a box filter of the post's width (8.2 m before)."""
    asc = _write_sine_asc(tmp_path / "sine.asc", dx, cols, 3.0)
    import_dems([asc], tmp_path / "s", lossless=True, resolution_arcsec=20)
    store = st.TerrainStore(tmp_path / "s")
    region = store.regions[0]
    rect = region.rects[0]
    h, _ = store.decode(region, 0, rect.row0, rect.row1, rect.col0, rect.col1)
    rr, cc = np.meshgrid(np.arange(rect.row0, rect.row1), np.arange(rect.col0, rect.col1), indexing="ij")
    lat, lon = store.post_latlon(0, rr, cc)
    inner = ((lat >= 46.0 + store.dlat) & (lat <= 46.2 - store.dlat) & (lon >= 7.0 + store.dlon)
             & (lon <= 7.0 + dx * (cols - 1) - store.dlon))
    assert inner.sum() > 50
    assert abs(float(h[inner].mean()) - 1000.0) < 1.0
    assert float(h[inner].std()) < worst_std_m


# --------------------------------------------------------------------------- 5: texture.json's sun


@pytest.mark.parametrize("bbox, per_pixel", [(["47.0", "9.0", "47.05", "9.05"], False),
                                             (["-60", "-170", "60", "170"], True)])
def test_texture_json_and_the_printed_line_agree_on_the_sun(tmp_path, capsys, bbox, per_pixel):
    out = tmp_path / "tx"
    rc = main(["terrain", "texture", "--procedural", "3", "--bbox", *bbox, "--time", "2026-03-20T12:00:00Z",
               "--size", "48x24", "-o", str(out)])
    assert rc == 0
    line = capsys.readouterr().out
    summary = json.loads((out / "texture.json").read_text())
    assert summary["sun"]["per_pixel"] is per_pixel
    assert ("each pixel its own" in line) is per_pixel
    if not per_pixel:
        assert "the centre's sun for the whole box" in line
