"""Fixes to `sortie terrain texture` (terrain/texture_cli.py, terrain/texture.py):

M4: each pixel is lit by its own sun (terrain/sun.py at the pixel), so a box
spanning day and night is lit on its day side and dark on its night side, and
a polar cap box has one azimuth per longitude; cast shadows follow each
post's own sun (cast_shadow with arrays). L2: a box with no terrain data is
refused naming --bbox (as `sortie terrain mesh` does, same exit status).
L3: -o on a file (or through one) is an error naming -o and the value, for
the texture's folder and the mesh's file alike.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pytest

from sortie.cli import main
from sortie.errors import InvalidArgument
from terrain.sun import sun_position
from terrain.texture import (LightParams, cast_shadow, fractal_noise, grid_latlon, light_map, metre_spacing,
                             row_spacing)
from terrain.texture_cli import add_texture_parser, make_texture, texture_request


# --------------------------------------------------------------------------- M4: the sun at every pixel

def _tilted(req, east_slope: float):
    """A plane rising ``east_slope`` metres a metre eastward over the request's grid: (heights, lat, lon)."""
    lat, lon = grid_latlon(req.lat_min, req.lon_min, req.lat_max, req.lon_max, req.rows, req.cols)
    dx, _ = metre_spacing(req.lat_min, req.lat_max, (req.lat_max - req.lat_min) / req.rows,
                          (req.lon_max - req.lon_min) / req.cols)
    heights = 500.0 + east_slope * dx * np.arange(req.cols)[None, :] * np.ones((req.rows, 1))
    return heights, lat, lon


@pytest.mark.parametrize("bbox, when", [
    ([-60.0, -170.0, 60.0, 170.0], "2026-03-20T12:00:00Z"),  # day in the middle, midnight at the sides
    ([70.0, -180.0, 90.0, 180.0], "2026-06-21T12:00:00Z"),  # a polar cap: every azimuth at once
])
def test_each_pixel_has_its_own_sun(bbox, when):
    """N.L on a plane tilted east is (-a Le + Lu) / sqrt(1 + a^2) with L the sun at that very pixel
    (azimuth and elevation, from terrain/sun.py), and day and night fall where that sun says."""
    req = texture_request(bbox, "64x32", None, when)
    a = 0.2
    heights, lat, lon = _tilted(req, a)
    tex, summary = make_texture(None, req, sampled=(heights, lat, lon))
    sun = sun_position(req.when, lat[:, None], lon[None, :], refraction=True)
    az, el = np.radians(sun.azimuth_deg), np.radians(sun.elevation_deg)
    # The fixture rises a * (the centre's east-west spacing) a column; slopes take each row's own spacing.
    dlat, dlon = (req.lat_max - req.lat_min) / req.rows, (req.lon_max - req.lon_min) / req.cols
    a = (a * metre_spacing(req.lat_min, req.lat_max, dlat, dlon)[0] / row_spacing(lat, dlat, dlon)[0])[:, None]
    expected = (-a * np.cos(el) * np.sin(az) + np.sin(el)) / np.sqrt(1.0 + a * a)
    np.testing.assert_allclose(tex.light.n_dot_l, expected, atol=1e-5)
    day, night = sun.elevation_deg > 5.0, sun.elevation_deg < -LightParams().twilight_deg
    lit = tex.light.light
    assert day.any()
    assert (lit[day & (expected > 0.2)] > LightParams().ambient).all()
    assert not tex.light.shadow[day].all()
    assert summary["sun"]["elevation_deg_min"] == pytest.approx(float(sun.elevation_deg.min()))
    if bbox[0] < 0.0:  # the equatorial box: day in the middle, night at both sides
        assert night[:, 0].all() and night[:, -1].all()
        assert (lit[night] <= LightParams().night_ambient + 1e-6).all()
        assert tex.light.shadow[night].all()
        assert summary["sun"]["elevation_deg_min"] < 0.0 < summary["sun"]["elevation_deg_max"]
        assert 0.0 < summary["sun"]["daylit_fraction"] < 1.0
    else:  # the polar cap under the midnight sun: the sun stands in every direction
        assert np.ptp(sun.azimuth_deg) > 300.0


def test_cli_box_spanning_day_and_night(tmp_path, capsys):
    """The acceptance tester's box: at 12:00 UTC the sides (+-170 deg) are at local midnight."""
    from PIL import Image

    out = tmp_path / "tp"
    rc = main(["terrain", "texture", "--procedural", "3", "--bbox", "-60", "-170", "60", "170",
               "--time", "2026-03-20T12:00:00Z", "--size", "48x24", "-o", str(out)])
    assert rc == 0
    assert "daylight" in capsys.readouterr().out
    light = np.asarray(Image.open(out / "lightmap.png"))
    shadow = np.asarray(Image.open(out / "shadow.png"))
    night_level = round(LightParams().night_ambient * 255)
    assert light[:, :3].max() <= night_level and (shadow[:, :3] == 255).all()  # the west edge: night
    assert light[:, -3:].max() <= night_level and (shadow[:, -3:] == 255).all()  # the east edge: night
    assert light[6:18, 22:26].min() > 0.5 * 255  # the middle: the sun near the zenith
    summary = json.loads((out / "texture.json").read_text())
    assert 0.3 < summary["shadow_fraction"] < 0.7


def _terrain(rows=48, cols=64, seed=5):
    y, x = np.mgrid[0:rows, 0:cols]
    return 2500.0 * fractal_noise(x / 11.0, y / 11.0, seed)


@pytest.mark.parametrize("az", [0.0, 20.0, 45.0, 90.0, 150.0, 200.0, 260.0, 315.0, 333.3])
@pytest.mark.parametrize("reach", [None, 700.0])
def test_one_sun_as_arrays_is_the_one_sun_sweep(az, reach):
    z = _terrain()
    z[10:13, 30:34] = np.nan
    for el in (4.0, 15.0):
        one = cast_shadow(z, 30.0, 45.0, az, el, max_distance_m=reach)
        field = cast_shadow(z, 30.0, 45.0, np.full(z.shape, az), np.full(z.shape, el), max_distance_m=reach)
        assert one.any() and np.array_equal(one, field)


def _marched(z, d_m, az_deg, el_deg):
    """Brute-force shadows on a square grid: each post marches its own straight ray in quarter-post
    steps, bilinear heights (the reference the sweeps approximate)."""
    rows, cols = z.shape
    out = np.zeros(z.shape, dtype=bool)
    s = np.arange(0.25, rows + cols, 0.25)
    for i in range(rows):
        for j in range(cols):
            a = np.radians(az_deg[i, j])
            c, r = j + s * np.sin(a), i - s * np.cos(a)
            ok = (c >= 0) & (c <= cols - 1) & (r >= 0) & (r <= rows - 1)
            c, r, d = c[ok], r[ok], s[ok] * d_m
            i0, j0 = np.minimum(r.astype(int), rows - 2), np.minimum(c.astype(int), cols - 2)
            fy, fx = r - i0, c - j0
            h = ((z[i0, j0] * (1 - fx) + z[i0, j0 + 1] * fx) * (1 - fy)
                 + (z[i0 + 1, j0] * (1 - fx) + z[i0 + 1, j0 + 1] * fx) * fy)
            out[i, j] = np.any(h > z[i, j] + d * np.tan(np.radians(el_deg[i, j])))
    return out


@pytest.mark.parametrize("az0, az1", [(150.0, 155.0), (42.0, 47.0), (87.0, 92.0), (265.0, 270.0), (357.5, 362.5)])
def test_shadows_follow_each_posts_own_sun(az0, az1):
    """The sun's azimuth turns 5 degrees across 64 columns (across a sweep's axis, or north, too):
    the per-post sweep's shadows agree with rays marched along each post's own sun about as well
    as one-sun sweeps along each post's own sun do."""
    z = _terrain()
    az = np.broadcast_to(np.linspace(az0, az1, z.shape[1])[None, :], z.shape)
    el = np.full(z.shape, 8.0)
    field = cast_shadow(z, 30.0, 30.0, az, el)
    own = np.empty(z.shape, dtype=bool)
    for j in range(z.shape[1]):
        own[:, j] = cast_shadow(z, 30.0, 30.0, float(az[0, j]), 8.0)[:, j]
    marched = _marched(z, 30.0, az, el)
    assert 0.3 < marched.mean() < 0.95
    assert np.mean(field == marched) > 0.95
    assert np.mean(field == marched) > np.mean(own == marched) - 0.025
    # Night posts are in shadow whatever the terrain.
    el[:, :10] = -1.0
    assert cast_shadow(z, 30.0, 30.0, az, el)[:, :10].all()


def test_no_cast_shadow_on_a_plane_under_a_turning_sun():
    """A plane rising more gently than the sun stands casts no shadow, however fast the sun turns."""
    rows, cols = 32, 64
    z = 500.0 + 0.2 * 1000.0 * np.arange(cols)[None, :] * np.ones((rows, 1))  # 0.2 m/m eastward
    az = np.broadcast_to(np.linspace(0.0, 360.0, cols)[None, :], z.shape)
    el = np.full(z.shape, 15.0)  # tan 15 deg = 0.27 > 0.2
    assert not cast_shadow(z, 1000.0, 700.0, az, el).any()
    assert not cast_shadow(z, 1000.0, 700.0, az, el, max_distance_m=5000.0).any()


def test_light_map_of_one_sun_is_unchanged():
    """Scalars keep the one-sun light map; arrays of the same sun give the same light."""
    z = _terrain()
    one = light_map(z, 30.0, 30.0, 200.0, 12.0)
    field = light_map(z, 30.0, 30.0, np.full(z.shape, 200.0), np.full(z.shape, 12.0))
    assert np.array_equal(one.shadow, field.shadow)
    np.testing.assert_allclose(field.light, one.light, atol=1e-6)
    np.testing.assert_allclose(field.n_dot_l, one.n_dot_l, atol=1e-6)


# --------------------------------------------------------------------------- L2: no terrain data

def test_box_without_data_is_refused_like_the_mesh(tmp_path, hgt_alps, capsys):
    common = ["--dem", str(hgt_alps), "--bbox", "10", "10", "11", "11", "--size", "32x32",
              "--time", "2026-06-21T12:00:00Z"]
    rc_texture = main(["terrain", "texture", *common, "-o", str(tmp_path / "e2")])
    texture_err = capsys.readouterr().err
    rc_mesh = main(["terrain", "mesh", *common, "-o", str(tmp_path / "e2.glb")])
    mesh_err = capsys.readouterr().err
    assert rc_texture == rc_mesh == 2
    for err in (texture_err, mesh_err):
        assert "--bbox: holds no terrain data" in err
    assert not (tmp_path / "e2").exists()


def test_cell_without_data_names_cell(tmp_path, hgt_alps):
    from terrain import quadtree

    parser = argparse.ArgumentParser()
    add_texture_parser(parser.add_subparsers(dest="c", required=True))
    cell = int(quadtree.cell_at(10.5, 10.5, 9))
    args = parser.parse_args(["texture", "--dem", str(hgt_alps), "--cell", str(cell), "--size", "16x16",
                              "--time", "2026-06-21T12:00:00Z", "-o", str(tmp_path / "c")])
    with pytest.raises(InvalidArgument) as err:
        args.func(args)
    assert err.value.field == "--cell" and "no terrain data" in str(err.value)


# --------------------------------------------------------------------------- L3: -o

def _texture_argv(hgt, out):
    return ["terrain", "texture", "--dem", str(hgt), "--bbox", "47.1", "9.1", "47.2", "9.2", "--size", "16x16",
            "--time", "2026-06-21T12:00:00Z", "-o", str(out)]


def test_texture_output_on_a_file_names_o(tmp_path, hgt_alps, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)  # short paths: the error shows the value whole
    f = Path("taken")
    f.write_text("keep me")
    for out in (f, f / "sub"):
        assert main(_texture_argv(hgt_alps, out)) == 2
        err = capsys.readouterr().err
        assert "-o" in err and str(out) in err and "Errno" not in err
    assert f.read_text() == "keep me"


def test_mesh_output_on_a_folder_names_o(tmp_path, hgt_alps, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    folder = Path("m.glb")
    folder.mkdir()
    f = Path("taken")
    f.write_text("keep me")
    for out in (folder, f / "m.glb"):
        assert main(["terrain", "mesh", "--dem", str(hgt_alps), "--bbox", "47.1", "9.1", "47.2", "9.2",
                     "--size", "16x16", "-o", str(out)]) == 2
        err = capsys.readouterr().err
        assert "-o" in err and str(out) in err and "cannot be written" in err
    assert folder.is_dir() and not any(folder.iterdir())


def test_unwritable_output_names_o(hgt_alps, capsys):
    """A folder nobody may create (procfs refuses root too, so this runs wherever CI does)."""
    out = Path("/proc/sortie-texture-test/t")
    assert main(_texture_argv(hgt_alps, out)) == 2
    err = capsys.readouterr().err
    assert "-o" in err and str(out) in err and "cannot be written" in err
    assert not out.exists()
