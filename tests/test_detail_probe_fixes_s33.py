"""Fractal detail fixes from the s33 acceptance probe (thesis §3.1.9, terrain/detail.py).

1. A pole is one point: with detail on, a raster whose last row lies on 90 N gave that point
   many heights (992.6 to 1003.2 m for one post of 1000 m) and a horizontal normal (the east
   slope divided by 6e-17 m a column). The noise of a pole's row is 0 and the detail fades with
   the lattice's east-west narrowing (terrain.detail.polar_taper): one height, the source's
   normal at the pole, and normals near it within a few degrees of the source's.
2. The noise variance is the land's (the detail is added over land alone): on N57E011 (86 %
   sea) level 1's std was fitted over every post, 0.690 m, where the land's residuals give 1.816
   m. DetailedRaster, CellularDetail and InsetSource count residuals whose posts all lie above
   sea level; an all-sea raster falls back to every residual.
3. Sources of an import share one fit (pooled residuals), so the detailed surface has no step
   where two tiles meet (0.50 m before, with one fit each).
5. A store imported with --add-detail says so: store.json records add_detail, detail_seed and
   each source's level stds, the store's describe() and GetMetadata report them, the summary
   says detail was added; stores without these keys still open.
6. `sortie terrain serve --procedural -1` names --procedural in its error.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from client.terrain_client import TerrainClient
from sortie.cli import main
from sortie.errors import DataFormatError
from terrain.detail import DetailedRaster, level_residuals
from terrain.raster import CRS_GEOGRAPHIC, Georef, Raster
from terrain.terrain import Terrain

SP = 1 / 1200  # SRTM3 post spacing, degrees
PORT = 53510  # this file's service port (53500-53549 are this area's)


def _hgt(path) -> np.ndarray:
    """An SRTM3 tile's heights (1201, 1201) float64, row 0 south, read independently of terrain.dem."""
    return np.fromfile(path, ">i2").reshape(1201, 1201)[::-1].astype(np.float64)


def _land_residual_variances(z: np.ndarray, levels: int) -> list[float]:
    """Oracle: the residual variance of each of the finest ``levels`` pyramid levels over the
    residuals whose 3 or 5 stencil posts (the new post and those it is predicted from) are > 0 m."""
    out = []
    for _ in range(levels):
        z = z[: z.shape[0] - 1 + z.shape[0] % 2, : z.shape[1] - 1 + z.shape[1] % 2]  # odd: the last posts coarse
        c = z[::2, ::2]
        parts = [(z[::2, 1::2], [c[:, :-1], c[:, 1:]]), (z[1::2, ::2], [c[:-1], c[1:]]),
                 (z[1::2, 1::2], [c[:-1, :-1], c[:-1, 1:], c[1:, :-1], c[1:, 1:]])]
        res, land = [], []
        for new, coarse in parts:
            res.append((new - sum(coarse) / len(coarse)).ravel())
            land.append(np.logical_and.reduce([new > 0] + [p > 0 for p in coarse]).ravel())
        out.append(float(np.concatenate(res)[np.concatenate(land)].var()))
        z = z[::2, ::2]
    return out


# --------------------------------------------------------------------------- 1: the poles

def _polar_raster() -> Raster:
    """89..90 N at 0.05 deg posts, every longitude; the pole row one height, 1000 m."""
    dx = 0.05
    lat = 89.0 + np.arange(21) * dx
    lon = -180.0 + np.arange(7201) * dx
    rng = np.random.default_rng(2)
    z = (1000.0 + 300.0 * (90.0 - lat)[:, None] * np.sin(np.radians(3.0 * lon))[None, :]
         + rng.normal(0.0, 3.0, (21, 7201)) * (90.0 - lat)[:, None])
    z[-1, :] = 1000.0
    return Raster(z, Georef(CRS_GEOGRAPHIC, -180.0, 89.0, dx, dx), name="polar")


@pytest.fixture(scope="module")
def polar():
    r = _polar_raster()
    k = DetailedRaster(r, seed=4, finest_spacing_m=1.0).sub_levels
    # A terrain-like fit: 4 m at level 1, halving each level (the Alps' sigmas halve likewise).
    return r, DetailedRaster(r, seed=4, finest_spacing_m=1.0, level_std_m=4.0 * 0.5 ** np.arange(k))


def test_the_pole_has_one_height_and_the_sources_normal(polar):
    r, d = polar
    lon = np.array([0.0, 0.013, 45.0037, -170.0051, 123.4567, 180.0, -180.0, 89.99])
    lat = np.full(lon.size, 90.0)
    h = Terrain([d]).heights(lat, lon).height_msl_m
    # 1e-9 m: the pole's post is exact; no level adds anything there (old code: 992.6 to 1003.2 m).
    np.testing.assert_allclose(h, 1000.0, rtol=0, atol=1e-9)
    plain = Terrain([r]).normals(lat, lon).normal_enu
    detailed = Terrain([d]).normals(lat, lon).normal_enu
    # 1e-9: the detail adds no slope at the pole (old code: (+-1, 0, 0), a horizontal normal).
    np.testing.assert_allclose(detailed, plain, rtol=0, atol=1e-9)


@pytest.mark.parametrize("lat", [89.99999, 89.9999, 89.999, 89.99, 89.9, 89.5])
def test_normals_near_the_pole_stay_near_the_sources(polar, lat):
    r, d = polar
    lon = np.random.default_rng(1).uniform(-180.0, 180.0, 300)
    la = np.full(lon.size, lat)
    plain = Terrain([r]).normals(la, lon).normal_enu
    detailed = Terrain([d]).normals(la, lon).normal_enu
    angle = np.degrees(np.arccos(np.clip(np.sum(plain * detailed, axis=1), -1.0, 1.0)))
    # 15 deg: the detail tilts a normal by its own slopes, 5 deg at most here (4 m over a 2.8 km
    # level-1 cell north-south, and east-west no more than twice that: POLAR_ASPECT_MIN); without
    # the taper the lattice's 1/cos(lat) narrowing left them 74-120 deg off, near horizontal.
    assert angle.max() < 15.0, (lat, angle.max())


def test_tapered_detail_gradient_matches_finite_differences():
    # 75-76 N, square posts: cells 0.26 as wide as tall, the detail scaled by about 0.52 and that
    # scale falling northwards; the gradient carries both (the product rule).
    from terrain.detail import polar_taper
    from terrain.raster import metres_per_index

    rng = np.random.default_rng(5)
    z = 500.0 + np.cumsum(np.cumsum(rng.normal(0.0, 1.0, (121, 121)), 0), 1)
    d = DetailedRaster(Raster(z, Georef(CRS_GEOGRAPHIC, 20.0, 75.0, SP, SP)), seed=3, finest_spacing_m=20.0,
                       sea_level_m=None)
    assert 0.4 < polar_taper(np.array([75.05]), CRS_GEOGRAPHIC, SP, SP)[0][0] < 0.6
    fine = 2.0 ** -d.sub_levels
    # Points inside finest-level cells (away from their edges), where the noise is bilinear.
    r = (rng.integers(10 << d.sub_levels, 110 << d.sub_levels, 400) + rng.uniform(0.2, 0.8, 400)) * fine
    c = (rng.integers(10 << d.sub_levels, 110 << d.sub_levels, 400) + rng.uniform(0.2, 0.8, 400)) * fine
    lat, lon = 75.0 + r * SP, 20.0 + c * SP
    t = Terrain([d])
    n = t.normals(lat, lon).normal_enu
    de, dn = -n[:, 0] / n[:, 2], -n[:, 1] / n[:, 2]
    step = 1e-3 * fine * SP
    mx, my = metres_per_index(CRS_GEOGRAPHIC, step, step, lat)
    h = lambda la, lo: t.heights(la, lo).height_msl_m  # noqa: E731
    fd_e = (h(lat, lon + step) - h(lat, lon - step)) / (2 * mx)
    fd_n = (h(lat + step, lon) - h(lat - step, lon)) / (2 * my)
    # rtol 1e-4 as test_detail's: the taper is smooth (its curvature over 2 steps is below 1e-12).
    np.testing.assert_allclose(de, fd_e, rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(dn, fd_n, rtol=1e-4, atol=1e-6)


# --------------------------------------------------------------------------- 2: land variance

def test_detail_is_scaled_to_the_lands_residuals(hgt_kattegat):
    from terrain.store_import import CellularDetail

    z = _hgt(hgt_kattegat)
    assert (z <= 0).mean() > 0.8  # N57E011: the Kattegat, 86 % sea
    raster = Raster(z.astype(np.float32), Georef(CRS_GEOGRAPHIC, 11.0, 57.0, SP, SP), name="N57E011")
    d = DetailedRaster(raster, seed=1)
    land = _land_residual_variances(z, 4)
    # 1e-9 relative: the same residuals, summed in another order.
    np.testing.assert_allclose(d.residual_variance_m2[:4], land, rtol=1e-9)
    slope, icpt = np.polyfit(np.arange(4.0), np.log2(land), 1)
    want = math.sqrt(2.0 ** (icpt - max(slope, 0.0)))
    assert d.level_std_m[0] == pytest.approx(want, rel=1e-9)  # 1.816 m (old code: 0.690 m)
    # Cellular detail: half the land's finest residual std.
    c = CellularDetail(raster, 1, 4.0)
    assert c.amplitude_m == pytest.approx(0.5 * math.sqrt(land[0]), rel=1e-9)
    # Without a sea level, every residual counts, as before.
    every = DetailedRaster(raster, seed=1, sea_level_m=None).residual_variance_m2[0]
    assert every == pytest.approx(float(level_residuals(z).var()), rel=1e-9)
    assert land[0] > 5.0 * every


def test_an_all_sea_raster_falls_back_to_every_residual():
    z = np.minimum(np.random.default_rng(3).normal(-40.0, 10.0, (129, 129)), 0.0)
    d = DetailedRaster(Raster(z, Georef(CRS_GEOGRAPHIC, 5.0, 55.0, SP, SP)), seed=1)
    assert d.residual_variance_m2.size >= 4
    assert d.residual_variance_m2[0] == pytest.approx(float(level_residuals(z).var()), rel=1e-9)


def test_an_inset_is_scaled_to_the_lands_residuals(hgt_kattegat):
    from terrain.inset import STATS_MARGIN_POSTS, InsetSource

    z = _hgt(hgt_kattegat)
    raster = Raster(z.astype(np.float32), Georef(CRS_GEOGRAPHIC, 11.0, 57.0, SP, SP), name="N57E011")
    # A box on the coast at 57.63 N 11.85 E (Gothenburg's archipelago): 55 % sea with its margin.
    lat0, lat1, lon0, lon1 = 57.60, 57.66, 11.80, 11.90
    polygon = [(lat0, lon0), (lat0, lon1), (lat1, lon1), (lat1, lon0)]
    inset = InsetSource(Terrain([raster]), polygon, 20.0, seed=1)
    i0 = math.floor((lat0 - 57.0) / SP) - STATS_MARGIN_POSTS
    i1 = math.ceil((lat1 - 57.0) / SP) + STATS_MARGIN_POSTS
    j0 = math.floor((lon0 - 11.0) / SP) - STATS_MARGIN_POSTS
    j1 = math.ceil((lon1 - 11.0) / SP) + STATS_MARGIN_POSTS
    window = z[i0:i1 + 1, j0:j1 + 1]
    assert 0.2 < (window <= 0).mean() < 0.8
    land = _land_residual_variances(window, 1)[0]
    # 1e-6 relative: the window's posts come back through Terrain.heights as float32 values.
    assert inset.residual_variance_m2[0] == pytest.approx(land, rel=1e-6)
    assert land > 1.5 * float(level_residuals(window).var())  # old code: every residual


# --------------------------------------------------------------------------- 3: one fit per import

@pytest.mark.parametrize("kind", ["fractal", "cellular"])
def test_tiles_of_an_import_share_one_fit_and_meet_at_their_seam(hgt_alps, kind):
    from terrain.store_import import _with_detail

    h = _hgt(hgt_alps).astype(np.float32)
    west = Raster(h[:, :601], Georef(CRS_GEOGRAPHIC, 9.0, 47.0, SP, SP), name="west")
    east = Raster(h[:, 600:], Georef(CRS_GEOGRAPHIC, 9.5, 47.0, SP, SP), name="east")
    sources = _with_detail([west, east], kind, 0, 1.0 / 3600 / 64)
    if kind == "cellular":
        assert sources[0].amplitude_m == sources[1].amplitude_m
        return
    np.testing.assert_array_equal(sources[0].level_std_m, sources[1].level_std_m)
    # The shared fit is the pooled residuals' (here: the whole tile's but for its seam column).
    whole = _land_residual_variances(h[:, :1201].astype(np.float64), 1)[0]
    assert sources[0].residual_variance_m2[0] == pytest.approx(whole, rel=0.02)
    lat = 47.0 + np.random.default_rng(8).uniform(1, 1199, 5000) * SP
    eps = 1e-10  # degrees: 8 micrometres east of the seam
    t, plain = Terrain(sources), Terrain([west, east])
    at = lambda terrain, lon: terrain.heights(lat, np.full(lat.size, lon)).height_msl_m  # noqa: E731
    step = np.abs(at(t, 9.5) - at(t, 9.5 + eps))
    plain_step = np.abs(at(plain, 9.5) - at(plain, 9.5 + eps))
    # 1e-4 m: the sources' own step there is 7e-6 m (index rounding), the detail's slopes make it
    # at most a few times that; one fit each made it 0.50 m (p95 0.20 m).
    assert plain_step.max() < 1e-4 and step.max() < 1e-4, (plain_step.max(), step.max())


# --------------------------------------------------------------------------- 5: the store says it

def _write_asc(path, z: np.ndarray, lat0: float, lon0: float) -> None:
    """An ESRI ASCII grid of heights z (row 0 south) with its lower-left post at (lat0, lon0)."""
    rows = "\n".join(" ".join(f"{v:.0f}" for v in row) for row in z[::-1])
    path.write_text(f"ncols {z.shape[1]}\nnrows {z.shape[0]}\nxllcenter {lon0!r}\nyllcenter {lat0!r}\n"
                    f"cellsize {SP!r}\nNODATA_value -32768\n{rows}\n")


@pytest.fixture(scope="module")
def detail_store(tmp_path_factory, hgt_alps):
    from terrain.store_import import import_dems

    tmp = tmp_path_factory.mktemp("detail_store")
    z = _hgt(hgt_alps)[600:661, 600:661]
    _write_asc(tmp / "crop.asc", z, 47.5, 9.5)
    summary = import_dems([tmp / "crop.asc"], tmp / "store", resolution_arcsec=1.0, lossless=True,
                          add_detail="fractal", detail_seed=9)
    return tmp, summary


def test_the_manifest_and_summary_record_the_detail(detail_store):
    from terrain.dem import read_dem
    from terrain.store_import import _with_detail
    from terrain import store as st

    tmp, summary = detail_store
    m = json.loads((tmp / "store" / "store.json").read_text())
    assert (m["add_detail"], m["detail_seed"]) == ("fractal", 9)
    assert (summary.add_detail, summary.detail_seed) == ("fractal", 9)
    assert (m["summary"]["add_detail"], m["summary"]["detail_seed"]) == ("fractal", 9)
    want, = _with_detail([read_dem(tmp / "crop.asc")], "fractal", 9, st.open_store(tmp / "store").dlat)
    assert m["sources"][0]["detail_level_std_m"] == [float(v) for v in want.level_std_m]
    assert m["detail_finest_spacing_m"] == pytest.approx(want.finest_spacing_m, rel=1e-12)


def test_the_stores_description_and_getmetadata_say_the_detail(detail_store):
    from server.terrain_service import create_server
    from terrain.store import StoreSource, open_store

    tmp, _ = detail_store
    source = StoreSource(open_store(tmp / "store"))
    d = source.describe()
    m = json.loads((tmp / "store" / "store.json").read_text())
    stds = m["sources"][0]["detail_level_std_m"]
    assert d["kind"] == "store"
    assert (d["detail"], d["detail_seed"], d["detail_levels"]) == ("fractal", 9, len(stds))
    assert d["detail_level_std_m"] == stds and len(stds) > 0
    server, port = create_server(Terrain([source]), f"127.0.0.1:{PORT}")
    server.start()
    try:
        with TerrainClient(f"127.0.0.1:{port}") as client:
            remote = client.describe()[0]
    finally:
        server.stop(0)
    assert (remote["detail"], remote["detail_seed"], remote["detail_levels"]) == ("fractal", "9", str(len(stds)))
    assert remote["detail_level_std_m"] == str(stds)


def test_stores_without_the_detail_keys_still_open(detail_store, tmp_path):
    import shutil

    from terrain.store import StoreSource, TerrainStore

    tmp, _ = detail_store
    old = tmp_path / "old"
    shutil.copytree(tmp / "store", old)
    m = json.loads((old / "store.json").read_text())
    for key in ("add_detail", "detail_seed", "detail_finest_spacing_m"):
        m.pop(key)
    for src in m["sources"]:
        src.pop("detail_level_std_m")
    (old / "store.json").write_text(json.dumps(m))
    d = StoreSource(TerrainStore(old)).describe()
    assert "detail" not in d and "detail_seed" not in d
    m["add_detail"], m["detail_seed"] = "fractal", -3
    (old / "store.json").write_text(json.dumps(m))
    with pytest.raises(DataFormatError, match="detail_seed"):
        TerrainStore(old)
    m["add_detail"], m["detail_seed"] = "fractl", 3
    (old / "store.json").write_text(json.dumps(m))
    with pytest.raises(DataFormatError, match="add_detail"):
        TerrainStore(old)


# --------------------------------------------------------------------------- 6: --procedural

@pytest.mark.parametrize("command", [["serve", "--port", str(PORT + 1)], ["info"]])
def test_a_bad_procedural_seed_names_the_option(capsys, command):
    assert main(["terrain", *command, "--procedural", "-1"]) == 2
    err = capsys.readouterr().err
    assert "error: --procedural: must be an integer within [0, 18446744073709551615] (got -1)" in err, err
    assert "Traceback" not in err
