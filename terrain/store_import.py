"""``sortie terrain import``: DEM files to a terrain store (thesis §3.3.3's
converter grown up).

Pipeline: read and mosaic the DEMs (:mod:`terrain.mosaic`); group them into
regions (sources whose boxes come within a tile of each other code together);
for each region sample the store's level-0 lattice over the region's box —
bilinear on the sources, anti-aliased by averaging a kx x ky block of bilinear
samples when the store is coarser than a source (kx and ky = the longitude and
the latitude spacing ratios, rounded up), optionally with synthetic detail
below the sources' spacing; classify posts (measured, filled void, outside);
fill the outside by nearest value (it only shapes the residuals: outside posts
answer "outside"); code the pyramid (:mod:`terrain.heightcodec`); write level
files; remove an earlier store's level files that the new manifest does not
list; write the manifest last.

Resumable: sampling is the slow step for large imports, and is done in bands
of tile rows saved under ``STORE/.import/``; an interrupted import re-run with
the same arguments and the same source files reuses the bands it finished (the
band files carry a key of the arguments and of the files' contents). The
manifest is written once, when every region is coded: an interrupted import
leaves no ``store.json`` (an earlier store's is removed before its level files
are overwritten), so nothing opens it as complete. A finished import removes
``.import``. A write that fails (a full disk) is InvalidArgument naming output
and the file; it leaves no partial file, and keeps the finished bands to resume.

Re-importing into an existing store: once every new level file is written, the
earlier store's level files and region directories that the new manifest will
not list are removed (only those names, :func:`_remove_unlisted`), and the
stored bytes count the listed files alone.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import re
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numba
import numpy as np

from sortie.errors import DataFormatError, InvalidArgument
from terrain import heightcodec, store as st
from terrain.geodesy import WGS84_A_M, WGS84_E2
from terrain.procedural import mix64
from terrain.raster import (CRS_GEOGRAPHIC, STATUS_FILLED, STATUS_OK, STATUS_OUTSIDE, TWO_PI_A_M, Raster,
                            fractional_index)
from terrain.terrain import Terrain

BAND_TILES = 4  # tile rows sampled per resumable band
MAX_REGION_POSTS = 400_000_000  # level-0 posts one region may hold, whatever the memory
# Peak memory of an import per level-0 post of its largest region, with a margin: measured
# (ru_maxrss of one SRTM tile imported at 6.4 M, 25 M and 102 M posts: 0.43, 1.07 and 3.31 GB,
# slopes of 31-33 bytes a post; docs/STORE.md): float64 heights, then int64 units, the codec's
# padded levels and decoded copies.
IMPORT_BYTES_PER_POST = 40
SAMPLE_CHUNK = 1 << 20  # points per Terrain.heights call
# In the bands' key: bands sampled by an importer of another version (2: kx x ky anti-aliasing; 3: edge
# posts also at the edges of a source's voids; 4: sources either side of the antimeridian grouped into
# one region, whose bands a band's name, by region index, does not tell apart; 5: synthetic detail fitted
# over land alone, pooled over the sources, tapered towards the poles; 6: cellular detail from a 3-D
# lattice, its mean removed, and a region round the globe one turn wide) are sampled again, not mixed
# into a store with new ones.
SAMPLING_VERSION = 6
WORK_DIR = ".import"  # resumable bands, removed when the import finishes
REGION_DIR = re.compile(r"region-[0-9]{3,}")  # the store's own names (docs/STORE.md, Files): what a
LEVEL_FILE = re.compile(r"level-[0-9]{2,}\.tiles")  # re-import may remove when its manifest does not list it


@dataclass
class ImportSummary:
    store: str
    regions: int
    depth: int
    levels: int
    spacing_arcsec: tuple[float, float]
    posts: int
    measured_posts: int
    filled_posts: int
    stored_bytes: int
    ratio_vs_int16: float
    step_m: float
    max_quantisation_error_m: float
    rms_quantisation_error_m: float
    max_error_vs_source_m: float
    rms_error_vs_source_m: float
    seconds: float
    samples_per_s: float
    bounds: list
    # Synthetic detail (--add-detail, --detail-seed): its posts between the sources' are counted
    # in measured_posts (their class: the data they are made from), not measured themselves.
    add_detail: str | None = None
    detail_seed: int | None = None

    def to_json(self) -> dict:
        return dict(self.__dict__)


def import_dems(paths, out, *, resolution_arcsec: float | None = None, step_m: float = 1.0,
                lossless: bool = False, tile: int = st.DEFAULT_TILE, unit_m: float = st.DEFAULT_UNIT_M,
                add_detail: str | None = None, detail_seed: int = 0, name: str | None = None,
                progress: bool = False) -> ImportSummary:
    """Build a store at ``out`` from DEM files; returns the summary (also in the manifest)."""
    from terrain.mosaic import load_sources

    t_start = time.perf_counter()
    if not paths:
        raise InvalidArgument("files", "give at least one DEM file")
    _check_seed(detail_seed)
    if unit_m != st.DEFAULT_UNIT_M:
        raise InvalidArgument("unit_m", f"must be {st.DEFAULT_UNIT_M} m: the store's height unit is 1 cm (readers "
                              "refuse another, docs/STORE.md)", value=unit_m)
    step_units = _step_units(step_m, lossless, unit_m)
    if add_detail not in (None, "fractal", "cellular"):
        raise InvalidArgument("add_detail", "must be 'fractal' or 'cellular'", value=add_detail)
    rasters = load_sources(paths)
    for r in rasters:
        _check_height_range(r, unit_m)
    _check_datums(rasters)
    if rasters[0].vertical_datum not in st.vertical_datums():  # readers would refuse the store
        raise DataFormatError(f"{rasters[0].source}: vertical datum {rasters[0].vertical_datum!r} is not one a "
                              "store records (" + ", ".join(sorted(st.vertical_datums())) + ")")
    # Default lattice: no coarser than any source along either axis (store posts are
    # 4/3 as wide in degrees of longitude as they are tall in latitude).
    depth = (_default_depth(rasters, tile) if resolution_arcsec is None
             else st.depth_for_spacing(resolution_arcsec / 3600.0, tile))
    dlat, dlon = st.lattice_spacing_deg(depth, tile)
    sources = _with_detail(rasters, add_detail, detail_seed, dlat) if add_detail else rasters
    terrain = Terrain(sources)
    groups = _regions(rasters, dlat, dlon, tile)
    out = _output_dir(Path(out))
    key = _import_key(paths, depth, tile, unit_m, add_detail, detail_seed)
    detail = _detail_record(add_detail, detail_seed, sources)
    _drop_stale_bands(out / WORK_DIR, key)
    progress_bar = _Progress(progress, sum(_region_posts(g) for g in groups))
    try:
        summary = _import_regions(out, key, name, terrain, sources, rasters, groups, tile, depth, unit_m,
                                  step_units, progress_bar, t_start, detail)
    finally:
        progress_bar.close()
    shutil.rmtree(out / WORK_DIR, ignore_errors=True)
    return summary


def _import_regions(out: Path, key: str, name, terrain, sources, rasters, groups, tile: int, depth: int,
                    unit_m: float, step_units: int, progress_bar, t_start: float, detail: dict) -> ImportSummary:
    """Sample, code and write every region, then the manifest (import_dems's steps 3-5); a write
    that fails is InvalidArgument naming output and the file (:func:`_writing`); ``detail``:
    :func:`_detail_record`."""
    dlat, dlon = st.lattice_spacing_deg(depth, tile)
    regions, totals = [], {"posts": 0, "measured": 0, "filled": 0, "qmax": 0.0, "qsq": 0.0, "smax": 0.0,
                           "ssq": 0.0, "sn": 0}
    for index, (row0, col0, rows, cols, members) in enumerate(groups):
        edges = [(sources[m], rasters[m]) for m in members]
        heights, classes = _sample_region(terrain, out, key, index, row0, col0, rows, cols, dlat, dlon, tile,
                                          [rasters[m] for m in members], edges, progress_bar)
        units = _to_units(heights, unit_m, [rasters[m] for m in members])
        del heights
        rects, blobs = heightcodec.encode_pyramid(units, row0, col0, tile, step_units, depth + 1)
        class_levels = _class_pyramid(classes, row0, col0, rects)
        if index == 0:
            # The level files below overwrite an earlier store's: its manifest no longer describes them.
            with _writing(out, out / st.MANIFEST):
                (out / st.MANIFEST).unlink(missing_ok=True)
        with _writing(out, out / f"region-{index:03d}"):
            (out / f"region-{index:03d}").mkdir(exist_ok=True)
        for level, rect in enumerate(rects):
            tiles = {}
            for (k, ti, tj), blob in blobs.items():
                if k != level:
                    continue
                c = class_levels[level][ti * tile - rect.row0:(ti + 1) * tile - rect.row0,
                                        tj * tile - rect.col0:(tj + 1) * tile - rect.col0]
                tiles[(ti, tj)] = (blob, st.code_classes(c))
            path = st.level_file(out, index, level)
            with _writing(out, path):
                st.write_level_file(path, level, tiles)
        del blobs, class_levels
        regions.append({"index": index, "rects": [[r.row0, r.col0, r.rows, r.cols] for r in rects],
                        "bounds": _data_bounds(classes, row0, col0, dlat, dlon),
                        "sources": [str(rasters[m].source) for m in members]})
        # Errors: the decoded store against the sampled lattice and against the source posts, read
        # through the regions written so far (the manifest itself is written once, at the end).
        store = st.TerrainStore(out, manifest=_manifest(out, name, tile, depth, unit_m, step_units, rasters,
                                                        regions, None, detail))
        qmax, qsq = _quantisation_error(store, store.regions[index], units, classes, row0, col0, unit_m)
        totals["qmax"] = max(totals["qmax"], qmax)
        totals["qsq"] += qsq
        totals["posts"] += int(np.count_nonzero(classes != st.CLASS_OUTSIDE))
        totals["measured"] += int(np.count_nonzero(classes == st.CLASS_MEASURED))
        totals["filled"] += int(np.count_nonzero(classes == st.CLASS_FILLED))
        del units, classes
        src = _error_vs_sources(st.StoreSource(store), [rasters[m] for m in sorted(members)])  # in priority order
        totals["smax"] = max(totals["smax"], src[0])
        totals["ssq"] += src[1]
        totals["sn"] += src[2]
        store.close()
    listed = st.level_files(out, regions)
    with _writing(out, out):
        _remove_unlisted(out, listed)
    stored = sum(p.stat().st_size for p in listed)
    seconds = time.perf_counter() - t_start
    summary = ImportSummary(
        store=str(out), regions=len(regions), depth=depth, levels=max(len(r["rects"]) for r in regions),
        spacing_arcsec=(dlat * 3600, dlon * 3600), posts=totals["posts"], measured_posts=totals["measured"],
        filled_posts=totals["filled"], stored_bytes=stored,
        ratio_vs_int16=2.0 * totals["posts"] / max(stored, 1), step_m=step_units * unit_m,
        max_quantisation_error_m=totals["qmax"],
        rms_quantisation_error_m=math.sqrt(totals["qsq"] / max(totals["posts"], 1)),
        max_error_vs_source_m=totals["smax"], rms_error_vs_source_m=math.sqrt(totals["ssq"] / max(totals["sn"], 1)),
        seconds=seconds, samples_per_s=sum(_region_posts(g) for g in groups) / seconds,
        bounds=[r["bounds"] for r in regions], add_detail=detail["add_detail"], detail_seed=detail["detail_seed"])
    with _writing(out, out / st.MANIFEST):
        _write_manifest(out, _manifest(out, name, tile, depth, unit_m, step_units, rasters, regions,
                                       summary.to_json(), detail))
    return summary


@contextlib.contextmanager
def _writing(out: Path, path: Path):
    """An OSError writing ``path`` in the store ``out`` (a full disk, a file grown past the process's
    limit, a directory made read-only) as InvalidArgument naming output and the path, saying what the
    import leaves: no manifest, and its finished bands under .import/ (docs/STORE.md: the same import
    run again resumes from them), which the user may delete to free their space. The writers remove
    their own partial files (st.write_level_file, :func:`_save_band`, :func:`_write_manifest`)."""
    try:
        yield
    except OSError as e:
        work = out / WORK_DIR
        kept = sum(p.stat().st_size for p in work.glob("*.npz")) if work.is_dir() else 0
        raise InvalidArgument("output", f"cannot write {path}: {e.strerror or e}; the store has no {st.MANIFEST} "
                              f"until an import finishes: free some space (or fix the directory) and run the same "
                              f"import again, which resumes from the {kept / 2**20:.1f} MiB of finished bands kept "
                              f"in {work} (delete it to free them)", value=str(path)) from None


# How far from a whole number of units a step may be and still be that number: float noise of
# the decimal value (0.07 / 0.01 = 7.000000000000001), relative.
STEP_UNITS_REL_TOL = 1e-9


def _step_units(step_m: float, lossless: bool, unit_m: float) -> int:
    """The quantisation step in units, checked against the codec's range and refused unless it
    is a whole number of units (InvalidArgument naming step and --step, with the nearest steps
    allowed). The codec quantises whole units, and the unit stays 1 cm whatever the step (the
    range of 2^29 units and GetRegion's centimetre encoding assume it), so a step of 0.015 m
    would have been 0.02 m, silently."""
    if lossless:
        return 1
    top_m = heightcodec.MAX_ABS_UNITS * unit_m
    if not (math.isfinite(step_m) and unit_m <= step_m <= top_m):
        raise InvalidArgument("step", f"must be a number of metres from the unit {unit_m} m up to {top_m:,.0f} m "
                              f"(2^29 units, the codec's range)", value=step_m)
    units = step_m / unit_m
    whole = round(units)
    if abs(units - whole) > STEP_UNITS_REL_TOL * units:
        near = sorted({max(1, math.floor(units)), math.ceil(units)})
        shown = " or ".join(f"--step {round(k * unit_m, 12):g}" for k in near)
        raise InvalidArgument("step", f"--step must be a whole number of the store's height unit, {unit_m:g} m "
                              f"(the codec quantises whole units), which {step_m!r} m is not: take {shown}",
                              value=step_m)
    return max(1, int(whole))


def _default_depth(rasters, tile: int) -> int:
    """The lattice depth without --resolution: the least whose spacing is no coarser than any
    source's along either axis (store posts are 4/3 as wide in degrees of longitude as they are
    tall in latitude). A source finer than the finest lattice (depth MAX_DEPTH, ~4 cm) is refused
    naming the file and its post spacing, the cause: not ``resolution``, which the user did not give."""
    spacing = [min(_lat_spacing_deg(r), 0.75 * _lon_spacing_deg(r)) for r in rasters]
    k = int(np.argmin(spacing))
    try:
        return st.depth_for_spacing(spacing[k], tile)
    except InvalidArgument:
        r = rasters[k]
        finest_deg = st.lattice_spacing_deg(st.MAX_DEPTH, tile)[0]
        raise InvalidArgument("files", f"{r.source}: its posts {_lat_spacing_deg(r) * 3600:.3g} x "
                                       f"{_lon_spacing_deg(r) * 3600:.3g} arc-seconds apart (latitude x longitude) "
                                       f"are finer than the store's finest lattice ({finest_deg * 3600:.3g} "
                                       f"arc-seconds of latitude, depth {st.MAX_DEPTH}): is its cell size right? "
                                       f"To import it anyway, give --resolution ARCSEC") from None


def _check_height_range(r: Raster, unit_m: float) -> None:
    """DataFormatError naming the file, the height and where it is, for a DEM post beyond
    the codec's range (2^29 units: +-5,368 km at 1 cm): a damaged or mis-scaled file."""
    h = np.asarray(r.heights)
    top_m = heightcodec.MAX_ABS_UNITS * unit_m
    with np.errstate(invalid="ignore"):
        beyond = np.abs(h) > top_m
    if not beyond.any():
        return
    i, j = (int(v) for v in np.argwhere(beyond)[0])
    lat, lon = _post_latlon(r, np.array([i]), np.array([j]))
    raise DataFormatError(f"{r.source}: height {float(h[i, j]):g} m at post ({i}, {j}) (lat {float(lat[0]):.6f}, "
                          f"lon {float(lon[0]):.6f}) is beyond the store's range of +-{top_m:,.0f} m "
                          f"({int(beyond.sum())} such posts); is the file damaged or in other units?")


def _check_datums(rasters) -> None:
    """InvalidArgument naming files, the two files and their vertical datums, when two sources are
    on different named vertical datums (by identity, terrain.dem.vertical_datum_identity: two labels
    of one datum agree): the manifest records one ``vertical_datum`` (the first source's), so the
    second's heights would be stored as if on the first's, off by the datums' separation (EGM2008
    and EGM96 differ by up to a few metres, NAVD88 and the geoids by a metre or two). Heights "as
    supplied" (terrain.dem.VERTICAL_DATUM_DEFAULT) claim no datum and go with any."""
    from terrain.dem import VERTICAL_DATUM_DEFAULT, vertical_datum_identity

    named = [r for r in rasters if r.vertical_datum != VERTICAL_DATUM_DEFAULT]
    for r in named[1:]:
        if vertical_datum_identity(r.vertical_datum) != vertical_datum_identity(named[0].vertical_datum):
            a, b = named[0], r
            raise InvalidArgument("files", f"{a.source} is on {a.vertical_datum} but {b.source} on "
                                           f"{b.vertical_datum}: a store records one vertical datum; convert one "
                                           f"file's heights to the other's datum, or import them into two stores",
                                  value=[str(a.source), str(b.source)])


def _check_seed(seed) -> None:
    """InvalidArgument naming --detail-seed and the value unless it is an integer within [0, 2^64)
    (the detail's lattice hash takes it as a uint64), before anything is read or written."""
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or not 0 <= seed < 2**64:
        raise InvalidArgument("--detail-seed", "must be an integer within [0, 2^64)", value=seed)


def _remove_unlisted(out: Path, listed) -> None:
    """Remove what an earlier store in ``out`` left that the new manifest will not list: level files
    (``level-KK.tiles``) in region directories (``region-NNN``), then such directories left empty.
    Nothing else there is touched (a user's files, other names, symbolic links). Runs once every new
    level file is written and before the manifest: an import interrupted here has no manifest yet, and
    its re-run (from its bands) removes the rest."""
    keep = {Path(p) for p in listed}
    for d in sorted(out.iterdir()):
        if not (REGION_DIR.fullmatch(d.name) and d.is_dir() and not d.is_symlink()):
            continue
        for f in sorted(d.iterdir()):
            if LEVEL_FILE.fullmatch(f.name) and f.is_file() and not f.is_symlink() and f not in keep:
                f.unlink()
        if not any(d.iterdir()):
            d.rmdir()


def _output_dir(out: Path) -> Path:
    """The store directory, created (InvalidArgument naming output and the path when it cannot be)."""
    if out.exists() and not out.is_dir():
        raise InvalidArgument("output", f"{out} exists and is not a directory", value=str(out))
    try:
        out.mkdir(parents=True, exist_ok=True)
        probe = out / ".write-test"
        probe.write_bytes(b"")
        probe.unlink()
    except OSError as e:
        raise InvalidArgument("output", f"cannot write the store directory {out}: {e.strerror or e}",
                              value=str(out)) from None
    return out


def _import_key(paths, depth, tile, unit_m, add_detail, detail_seed) -> str:
    """The key of resumable bands: the arguments and each source file's path and SHA-256
    (a file replaced or corrected at the same path invalidates its bands)."""
    files = []
    for p in paths:
        p = Path(p).resolve()
        with open(p, "rb") as f:
            files.append([str(p), hashlib.file_digest(f, "sha256").hexdigest()])
    return hashlib.sha256(json.dumps([files, depth, tile, unit_m, add_detail, detail_seed,
                                      SAMPLING_VERSION]).encode()).hexdigest()[:16]


def _drop_stale_bands(work: Path, key: str) -> None:
    """Remove the bands of other imports (other arguments, or files since changed)."""
    if work.is_dir():
        for p in work.iterdir():
            if not p.name.startswith(key + "-"):
                p.unlink(missing_ok=True)


def _to_units(heights: np.ndarray, unit_m: float, members) -> np.ndarray:
    """Heights (m) to integer units, in place; DataFormatError naming the sources when synthetic
    detail pushed a post beyond the codec's range."""
    np.divide(heights, unit_m, out=heights)
    np.round(heights, out=heights)
    top = max(float(heights.max(initial=0.0)), -float(heights.min(initial=0.0)))
    if top > heightcodec.MAX_ABS_UNITS:
        raise DataFormatError(f"{'; '.join(str(r.source) for r in members)}: a resampled height of "
                              f"{top * unit_m:g} m is beyond the store's range of "
                              f"+-{heightcodec.MAX_ABS_UNITS * unit_m:,.0f} m")
    return heights.astype(np.int64)


def _data_bounds(classes: np.ndarray, row0: int, col0: int, dlat: float, dlon: float) -> list[float]:
    """[lat_min, lon_min, lat_max, lon_max] of the region's posts that hold data (lon_max may
    pass 180 for a region across the antimeridian)."""
    rows = np.flatnonzero((classes != st.CLASS_OUTSIDE).any(axis=1))
    cols = np.flatnonzero((classes != st.CLASS_OUTSIDE).any(axis=0))
    lat_top, lon_west = 90.0 - (row0 + rows[0]) * dlat, (col0 + cols[0]) * dlon - 180.0
    return [90.0 - (row0 + rows[-1]) * dlat, lon_west, lat_top, (col0 + cols[-1]) * dlon - 180.0]


def _quantisation_error(store, region, units, classes, row0, col0, unit_m) -> tuple[float, float]:
    """(max, sum of squares) of decoded - imported heights (m) over the posts with data, band by band."""
    rows, cols = units.shape
    worst, sq = 0.0, 0.0
    step = BAND_TILES * store.tile
    for b0 in range(0, rows, step):
        b1 = min(rows, b0 + step)
        decoded, _ = store.decode(region, 0, row0 + b0, row0 + b1, col0, col0 + cols)
        err = np.abs(decoded - units[b0:b1] * unit_m)[classes[b0:b1] != st.CLASS_OUTSIDE]
        worst = max(worst, float(err.max(initial=0.0)))
        sq += float(np.sum(err ** 2))
    return worst, sq


def _lat_spacing_deg(r: Raster) -> float:
    g = r.georef
    if g.crs == CRS_GEOGRAPHIC:
        return g.dy
    # Web Mercator: metres of northing -> degrees of latitude at the raster's centre.
    lat_c = math.radians((r.bounds[0] + r.bounds[2]) / 2)
    return math.degrees(g.dy * math.cos(lat_c) / 6378137.0)


def _lon_spacing_deg(r: Raster) -> float:
    g = r.georef
    if g.crs == CRS_GEOGRAPHIC:
        return g.dx
    return math.degrees(g.dx / 6378137.0)


def _with_detail(rasters, kind: str, seed: int, dlat_deg: float):
    """The sources with synthetic detail down to the store's spacing (``dlat_deg``): one fit of
    the residuals of all sources of a spacing, over land (terrain.detail.detailed_rasters), so
    tiles kept apart meet at their seams."""
    from terrain.detail import SEA_LEVEL_M, detailed_rasters, variance_by_spacing

    finest_m = dlat_deg * math.pi / 180.0 * 6371008.8
    if kind == "fractal":
        return detailed_rasters(rasters, seed, finest_spacing_m=finest_m, sea_level_m=SEA_LEVEL_M)
    return [CellularDetail(r, seed, finest_m, amplitude_m=0.5 * math.sqrt(float(v[0])) if v.size else 0.0)
            for r, v in zip(rasters, variance_by_spacing(rasters, SEA_LEVEL_M))]


def _detail_record(add_detail: str | None, seed: int, sources) -> dict:
    """What the manifest and summary say of the synthetic detail (docs/STORE.md): its kind,
    seed and finest spacing, and per source its level stds (fractal) or amplitude (cellular);
    add_detail None without detail."""
    if not add_detail:
        return {"add_detail": None, "detail_seed": None}
    if add_detail == "fractal":
        per_source = [{"detail_level_std_m": [float(v) for v in s.level_std_m]} for s in sources]
        finest_m = sources[0].finest_spacing_m
    else:
        per_source = [{"detail_amplitude_m": float(s.amplitude_m)} for s in sources]
        finest_m = sources[0].cell_m / 4.0
    return {"add_detail": add_detail, "detail_seed": int(seed), "detail_finest_spacing_m": float(finest_m),
            "detail_sources": per_source}


class CellularDetail:
    """Cellular (Worley F1) bumps added below a raster's post spacing (thesis §3.3.3's
    "cellular noise"): F1 of a 3-D lattice of feature points, one jittered point per cube of
    side ``cell_m`` (4 store posts) in Earth-centred, Earth-fixed coordinates, evaluated on the
    WGS84 ellipsoid (:func:`_worley_f1`). Built in 3-D, the field is the same whatever the
    longitude: continuous across the antimeridian and at the poles, and isotropic on the ground
    (F1 of a plane lattice in (lat, lon cos lat) was sheared by lon sin lat, and jumped at
    +-180). Amplitude: the raster's finest pyramid residual std / 2 over land
    (terrain.detail.pyramid_residual_variance with the sea level; or ``amplitude_m``, one
    shared by an import's sources), times F1 - CELLULAR_F1_MEAN (the field's mean removed: zero
    on average). As the fractal detail (terrain.detail.sea_taper): none at or below sea level,
    ramping in over the amplitude above it (F1 - CELLULAR_F1_MEAN >= -CELLULAR_F1_MEAN, so land
    stays above sea level: h (1 - CELLULAR_F1_MEAN) at worst)."""

    def __init__(self, raster: Raster, seed: int, finest_m: float, amplitude_m: float | None = None):
        from terrain.detail import SEA_LEVEL_M, pyramid_residual_variance

        self.raster = raster
        self.seed = int(seed)
        self.cell_m = 4.0 * finest_m
        if amplitude_m is None:
            var = pyramid_residual_variance(raster.heights, sea_level_m=SEA_LEVEL_M)
            amplitude_m = 0.5 * math.sqrt(float(var[0])) if var.size else 0.0
        self.amplitude_m = float(amplitude_m)
        self.name = f"{raster.name}+cellular"

    def heights_into(self, lat, lon, out_h, out_status) -> None:
        from terrain.detail import SEA_LEVEL_M, sea_taper

        self.raster.heights_into(lat, lon, out_h, out_status)
        ok = np.flatnonzero(out_status != STATUS_OUTSIDE)
        weight, _ = sea_taper(out_h[ok], SEA_LEVEL_M, self.amplitude_m)
        keep = weight > 0.0  # at or below sea level: the source's own height
        ok, weight = ok[keep], weight[keep]
        out_h[ok] += weight * self.amplitude_m * self._f1(lat[ok], lon[ok])

    def _f1(self, lat, lon) -> np.ndarray:
        """F1 - CELLULAR_F1_MEAN (cells) at points (lat, lon degrees, (n,)) on the ellipsoid."""
        lat = np.ascontiguousarray(lat, np.float64).reshape(-1)
        lon = np.ascontiguousarray(lon, np.float64).reshape(-1)
        out = np.empty(lat.size)
        _worley_f1(lat, lon, 1.0 / self.cell_m, np.uint64(self.seed), out)
        return out - CELLULAR_F1_MEAN

    def gradient_into(self, lat, lon, out_de, out_dn, out_status) -> None:
        self.raster.gradient_into(lat, lon, out_de, out_dn, out_status)

    def raster_for(self, *box):
        return self.raster.raster_for(*box)

    def describe(self) -> dict:
        return {**self.raster.describe(), "name": self.name, "detail": "cellular"}


# The mean of F1 (:func:`_f1_cells`, cells): over a surface, whose points fall at every offset in
# their cubes alike, the mean over the unit cube of the expected distance to the nearest feature point.
# Measured once (no closed form for a jittered lattice): 2e8 points uniform in the cubes, 20 runs of
# 1e7 (numpy default_rng(run), seed = run): 0.52035, standard error 0.00001 (the runs' spread /
# sqrt(20)); the field's std is 0.172. tests/test_store2_probe_fixes_s33.py checks |mean| < 0.01 over
# the globe. (A Poisson process of the same density would give 0.554, the mean distance to the nearest
# neighbour, Gamma(4/3) (4 pi / 3)^(-1/3): Chandrasekhar 1943, Rev. Mod. Phys. 15, 1; one point a cube
# spreads them more evenly, so the nearest is nearer. The mean at a given offset in the cube ranges from
# 0.477 at its centre to 0.539 at its corners: a ripple of the cell's period, within the bumps' own scale.)
CELLULAR_F1_MEAN = 0.52035
_JITTER_MASK = np.uint64((1 << 21) - 1)  # a feature point's offset: three 21-bit fields of its cube's hash
_JITTER_SHIFT_Y, _JITTER_SHIFT_Z = np.uint64(21), np.uint64(42)
_JITTER_SCALE = 2.0 ** -21


@numba.njit(cache=True, nogil=True)
def _feature_d2(h_seed, i, j, k, ox, oy, oz) -> float:
    """Squared distance (cells) to the feature point of cube (i, j, k), whose corner lies at
    (ox, oy, oz) from the point: the cube's hash (terrain.procedural.lattice_hash(seed, i, j, k),
    h_seed being mix64(seed)) split into three 21-bit offsets in [0, 1)."""
    h = mix64(mix64(mix64(h_seed ^ np.uint64(i)) ^ np.uint64(j)) ^ np.uint64(k))
    dx = ox + float(h & _JITTER_MASK) * _JITTER_SCALE
    dy = oy + float((h >> _JITTER_SHIFT_Y) & _JITTER_MASK) * _JITTER_SCALE
    dz = oz + float((h >> _JITTER_SHIFT_Z) & _JITTER_MASK) * _JITTER_SCALE
    return dx * dx + dy * dy + dz * dz


@numba.njit(cache=True, nogil=True)
def _f1_cells(h_seed, px, py, pz) -> float:
    """Worley F1 (Worley 1996, "A cellular texture basis function", SIGGRAPH) at a point (cells):
    the distance to the nearest feature point, one per unit cube. Exact: the 27 cubes around the
    point first; a cube two away along an axis lies at least 1 + the point's least distance to its
    own cube's faces away, so the 125 cubes are searched when the nearest found is further than
    that (2.5e-4 of points), and no cube three away can hold a point nearer than the
    point's own cube's (within sqrt(3)). F1 is therefore continuous (1-Lipschitz) everywhere.
    h_seed: mix64(seed), uint64; px, py, pz: the point, cells (float64)."""
    fx, fy, fz = math.floor(px), math.floor(py), math.floor(pz)
    ix, iy, iz = np.int64(fx), np.int64(fy), np.int64(fz)
    fx, fy, fz = px - fx, py - fy, pz - fz
    best = np.inf
    for a in range(-1, 2):
        for b in range(-1, 2):
            for c in range(-1, 2):
                best = min(best, _feature_d2(h_seed, ix + a, iy + b, iz + c, a - fx, b - fy, c - fz))
    reach = 1.0 + min(min(fx, 1.0 - fx), min(fy, 1.0 - fy), min(fz, 1.0 - fz))
    if best > reach * reach:
        for a in range(-2, 3):
            for b in range(-2, 3):
                for c in range(-2, 3):
                    if max(abs(a), abs(b), abs(c)) == 2:
                        best = min(best, _feature_d2(h_seed, ix + a, iy + b, iz + c, a - fx, b - fy, c - fz))
    return math.sqrt(best)


@numba.njit(cache=True, nogil=True)
def _worley_f1(lat, lon, inv_cell_m, seed, out) -> None:
    """F1 (:func:`_f1_cells`) on the WGS84 ellipsoid: lat, lon (n,) float64 degrees; inv_cell_m:
    1 / the cube's side in metres; seed uint64; out (n,) float64, cells. A point's position is its
    ECEF one (terrain.geodesy.geodetic_to_ecef at height 0) in cells."""
    h_seed = mix64(seed)
    for n in range(lat.shape[0]):
        phi, lam = math.radians(lat[n]), math.radians(lon[n])
        sin_phi, cos_phi = math.sin(phi), math.cos(phi)
        nu = WGS84_A_M / math.sqrt(1.0 - WGS84_E2 * sin_phi * sin_phi) * inv_cell_m
        out[n] = _f1_cells(h_seed, nu * cos_phi * math.cos(lam), nu * cos_phi * math.sin(lam),
                           nu * (1.0 - WGS84_E2) * sin_phi)


@numba.njit(cache=True, nogil=True)
def _worley_f1_cells(px, py, pz, seed, out) -> None:
    """F1 (:func:`_f1_cells`) at points given in cells: px, py, pz (n,) float64; seed uint64; out
    (n,) float64 (CELLULAR_F1_MEAN's measurement, the tests)."""
    h_seed = mix64(seed)
    for n in range(px.shape[0]):
        out[n] = _f1_cells(h_seed, px[n], py[n], pz[n])


def _regions(rasters, dlat, dlon, tile):
    """Group sources whose level-0 post boxes come within one tile of each other, across the
    antimeridian too: (row0, col0, rows, cols, member indices) per group, col0 in the lattice's first
    turn (col0 + cols past a turn for a group across the antimeridian), cols at most one turn: a
    group round the globe is the turn from the antimeridian, col0 0 and cols the columns per turn.

    Rows stop at the lattice's last one, 2 2^D T - 1, one spacing north of the South Pole: the
    pole's own row (2 2^D T) is the southern edge of the last row of quad-tree cells, which no
    cell owns (a cell owns its northern and western edges), so a tile holding it could not be
    addressed, and a region's pyramid would never shrink to one tile (at every level the pole
    row starts a tile row of its own). The store therefore answers down to that last row."""
    last_row = int(round(180.0 / dlat)) - 1
    per_turn = int(round(360.0 / dlon))
    boxes = []
    for r in rasters:
        lat_min, lon_min, lat_max, lon_max = r.bounds
        lon_max = lon_min + (lon_max - lon_min) % 360.0 if lon_max < lon_min else lon_max
        row0 = min(int(math.floor((90.0 - lat_max) / dlat)), last_row)
        row1 = min(int(math.ceil((90.0 - lat_min) / dlat)) + 1, last_row + 1)
        col0 = int(math.floor((lon_min + 180.0) / dlon))
        col1 = int(math.ceil((lon_max + 180.0) / dlon)) + 1
        # col0 into the lattice's first turn [0, per_turn), col1 with it (past per_turn across the
        # antimeridian): a source west of -180 (xllcorner -180.05) or turns east (1000) would
        # otherwise give a rectangle of negative columns or columns turns away.
        shift = per_turn * (col0 // per_turn)
        boxes.append([row0, col0 - shift, row1, col1 - shift])
    groups = [[i] for i in range(len(boxes))]
    merged = True
    while merged:
        merged = False
        for a in range(len(groups)):
            for b in range(a + 1, len(groups)):
                turns = _near_turns(_group_box(boxes, groups[a]), _group_box(boxes, groups[b]), tile, per_turn)
                if turns is not None:
                    for m in groups[b]:  # b's columns beside a's: across the antimeridian, a turn away
                        boxes[m][1] += turns * per_turn
                        boxes[m][3] += turns * per_turn
                    groups[a] += groups.pop(b)
                    merged = True
                    break
            if merged:
                break
    out = []
    limit, why = region_post_limit()
    for g in groups:
        row0, col0, row1, col1 = _group_box(boxes, g)
        shift = per_turn * (col0 // per_turn)  # col0 into the first turn again, as for one source
        col0, col1 = col0 - shift, col1 - shift
        if col1 - col0 >= per_turn:
            # Round the globe (a 360-degree source, whose reader adds a wrap column; sources that
            # chain round it): one turn of columns from the antimeridian, tile-aligned (per_turn is
            # 3 2^D T), each lattice column once. Wider, the columns past the turn were stored twice
            # (coded apart, up to a step apart) and counted twice in the summary's posts.
            col0, col1 = 0, per_turn

        if (row1 - row0) * (col1 - col0) > limit:
            raise InvalidArgument("resolution", f"a region of {row1 - row0} x {col1 - col0} posts exceeds the "
                                  f"limit of {limit:,} posts ({why}); import a coarser resolution or fewer files")
        out.append((row0, col0, row1 - row0, col1 - col0, sorted(g)))
    return out


def region_post_limit() -> tuple[int, str]:
    """(the most level-0 posts one region may hold, why): MAX_REGION_POSTS, or fewer where the
    memory available now (Linux MemAvailable, else the physical memory) would not hold
    IMPORT_BYTES_PER_POST a post."""
    available = _available_memory_bytes()
    if available is None or available // IMPORT_BYTES_PER_POST >= MAX_REGION_POSTS:
        return MAX_REGION_POSTS, "the store's limit"
    return int(available // IMPORT_BYTES_PER_POST), (f"{available / 2**30:.1f} GiB of memory available at "
                                                     f"{IMPORT_BYTES_PER_POST} bytes a post while importing")


def _available_memory_bytes() -> int | None:
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return None


def _near_turns(a, b, tile: int, per_turn: int) -> int | None:
    """The whole number of turns m, nearest 0, by which box b ([row0, col0, row1, col1] of level-0
    posts) moved east comes within a tile of box a; None when no copy of b does. Boxes either side
    of the antimeridian come near a turn apart (m = +-1)."""
    if not (a[0] - tile <= b[2] and b[0] - tile <= a[2]):
        return None
    lo = -(-(a[1] - tile - b[3]) // per_turn)  # b[3] + m per_turn >= a[1] - tile
    hi = (a[3] + tile - b[1]) // per_turn  # b[1] + m per_turn <= a[3] + tile
    return min(range(lo, hi + 1), key=abs, default=None)


def _group_box(boxes, members):
    b = np.array([boxes[m] for m in members])
    return [int(b[:, 0].min()), int(b[:, 1].min()), int(b[:, 2].max()), int(b[:, 3].max())]


def _region_posts(group) -> int:
    return group[2] * group[3]


def _sample_region(terrain, out: Path, key: str, index: int, row0, col0, rows, cols, dlat, dlon, tile,
                   members, edges, progress_bar):
    """Heights (m) and classes of a region's level-0 posts, band by band (resumable).

    edges: (source, its raster) of the region's members, priority order (see _edge_samples)."""
    work = out / WORK_DIR
    with _writing(out, work):
        work.mkdir(exist_ok=True)
    heights = np.empty((rows, cols), np.float64)
    classes = np.empty((rows, cols), np.uint8)
    # Anti-aliasing: average kx x ky samples a post when the store is coarser than a source, each
    # axis by its own spacing ratio (a store post is 4/3 as wide in degrees as it is tall).
    ky = _aa_factor(dlat, [_lat_spacing_deg(r) for r in members])
    kx = _aa_factor(dlon, [_lon_spacing_deg(r) for r in members])
    band_rows = BAND_TILES * tile
    for b0 in range(0, rows, band_rows):
        b1 = min(rows, b0 + band_rows)
        path = work / f"{key}-r{index:03d}-b{b0:08d}.npz"
        if path.is_file():
            with np.load(path) as z:
                heights[b0:b1], classes[b0:b1] = z["h"], z["c"]
        else:
            h, c = _sample_band(terrain, row0 + b0, row0 + b1, col0, cols, dlat, dlon, (ky, kx), edges,
                                [r.bounds for r in members])
            heights[b0:b1], classes[b0:b1] = h, c
            with _writing(out, path):
                _save_band(path, h, c)
        progress_bar.advance((b1 - b0) * cols)
    outside = classes == st.CLASS_OUTSIDE
    if outside.all():
        raise InvalidArgument("files", "no DEM post falls on the store's lattice")
    if outside.any():
        import scipy.ndimage

        ri, ci = scipy.ndimage.distance_transform_edt(outside, return_distances=False, return_indices=True)
        heights[outside] = heights[ri[outside], ci[outside]]
    return heights, classes


def _save_band(path: Path, heights: np.ndarray, classes: np.ndarray) -> None:
    """A sampled band, written atomically (a temporary file, then a rename; the temporary file
    removed when the write fails, so that .import/ holds only whole bands)."""
    tmp = path.with_name(path.name + ".tmp.npz")
    try:
        np.savez(tmp, h=heights, c=classes)
        tmp.replace(path)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


def _aa_factor(store_spacing: float, source_spacings) -> int:
    """Samples per post along one axis: the store's spacing over the finest source's, rounded up (1
    where the store is no coarser)."""
    return max(1, math.ceil(max(store_spacing / s for s in source_spacings) - 1e-9))


def _sample_band(terrain, r_a, r_b, col0, cols, dlat, dlon, factors=(1, 1), edges=(), boxes=None):
    """Posts of rows [r_a, r_b): the mean of ky x kx bilinear samples (factors (ky, kx):
    latitude, longitude) spread over each post's cell ((1, 1): the bilinear value at
    the post). A post with no sample
    on the data but within one spacing of a point a source answers (its box's edges, its voids'
    edges) takes the source's height at the nearest such point (:func:`_edge_samples`), so that
    the store answers all the way to the sources' edges.

    boxes: the bounds (lat_min, lon_min, lat_max, lon_max) of every source that can answer
    here (None: not known): the posts and offsets whose samples cannot fall inside one of them
    are not sampled (:func:`_reaching`), as those samples would answer OUTSIDE and count for
    nothing (a 0.1" source of 60 x 60 posts at --resolution 3600 took 12,650^2 offsets a post
    over a band of 256 x 256 posts: 83 s)."""
    rows = np.arange(r_a, r_b, dtype=np.float64)
    cs = np.arange(col0, col0 + cols, dtype=np.float64)
    ky, kx = factors
    offsets_y = (np.arange(ky) - (ky - 1) / 2.0) / ky
    offsets_x = (np.arange(kx) - (kx - 1) / 2.0) / kx
    ri, ci = np.arange(rows.size), np.arange(cs.size)
    if boxes is not None:
        ri, ci, offsets_y, offsets_x = _reaching(rows, cs, offsets_y, offsets_x, dlat, dlon, boxes)
    acc, n_ok, filled = _sample_means(terrain, rows[ri], cs[ci], offsets_y, offsets_x, dlat, dlon)
    if ri.size != rows.size or ci.size != cs.size:  # the rest of the band: no sample reached a source
        grid = np.ix_(ri, ci)
        acc_all, n_all = np.zeros((rows.size, cs.size)), np.zeros((rows.size, cs.size), np.int64)
        filled_all = np.zeros((rows.size, cs.size), bool)
        acc_all[grid], n_all[grid], filled_all[grid] = acc, n_ok, filled
        acc, n_ok, filled = acc_all, n_all, filled_all
    empty = n_ok == 0
    if edges and empty.any():
        i, j = np.nonzero(empty)
        h, s = _edge_samples(edges, 90.0 - rows[i] * dlat, (cs[j] * dlon) % 360.0 - 180.0, dlat, dlon)
        ok = s != STATUS_OUTSIDE
        acc[i[ok], j[ok]] = h[ok]
        n_ok[i[ok], j[ok]] = 1
        filled[i[ok], j[ok]] = s[ok] == STATUS_FILLED
    classes = np.where(n_ok == 0, st.CLASS_OUTSIDE, np.where(filled, st.CLASS_FILLED, st.CLASS_MEASURED))
    heights = np.where(n_ok > 0, acc / np.maximum(n_ok, 1), 0.0)
    return heights, classes.astype(np.uint8)


def _sample_means(terrain, rows, cs, offsets_y, offsets_x, dlat, dlon):
    """(sums of heights m, counts of samples answered, any sample FILLED), each (m, n), over the
    samples at every (offsets_y, offsets_x) pair of the posts at lattice rows ``rows`` (m,) and
    columns ``cs`` (n,) (see :func:`_sample_band`)."""
    acc = np.zeros((rows.size, cs.size))
    n_ok = np.zeros((rows.size, cs.size), np.int64)
    filled = np.zeros((rows.size, cs.size), bool)
    # The ky x kx offsets (latitude's outer), as many together as SAMPLE_CHUNK points hold: a band
    # of few posts far coarser than its source (a 0.1" DEM at --resolution 240: 3.3 M offsets) took
    # one Terrain.heights call an offset (150 s; a day at 3600"; now 3 s and 94 s).
    ky, kx = offsets_y.size, offsets_x.size
    n_off = ky * kx
    per_call = max(1, SAMPLE_CHUNK // max(1, rows.size * cs.size))
    for o0 in range(0, n_off, per_call):
        o = np.arange(o0, min(n_off, o0 + per_call))
        lat = np.clip(90.0 - (rows[None, :] + offsets_y[o // kx, None]) * dlat, -90.0, 90.0)
        lon = ((cs[None, :] + offsets_x[o % kx, None]) * dlon) % 360.0 - 180.0
        shape = (o.size, rows.size, cs.size)
        la = np.broadcast_to(lat[:, :, None], shape).ravel()
        lo = np.broadcast_to(lon[:, None, :], shape).ravel()
        h = np.empty(la.size)
        s = np.empty(la.size, np.uint8)
        for k in range(0, la.size, SAMPLE_CHUNK):
            res = terrain.heights(la[k:k + SAMPLE_CHUNK], lo[k:k + SAMPLE_CHUNK])
            h[k:k + SAMPLE_CHUNK], s[k:k + SAMPLE_CHUNK] = res.height_msl_m, res.status
        h, s = h.reshape(shape), s.reshape(shape)
        ok = s != STATUS_OUTSIDE
        # Summed in the offsets' order onto acc, as one offset at a time did (the same bits).
        if o.size == 1:
            acc += np.where(ok[0], h[0], 0.0)
        else:
            acc = np.concatenate((acc[None], np.where(ok, h, 0.0))).sum(axis=0)
        n_ok += ok.sum(axis=0)
        filled |= (s == STATUS_FILLED).any(axis=0)
    return acc, n_ok, filled


# Degrees by which a source's box is widened when choosing the samples that can reach it:
# far more than the rounding of a sample's coordinates (1e-13 degrees), far less than a post.
REACH_MARGIN_DEG = 1e-9


def _lat_reach(lat_lo, lat_hi, boxes) -> np.ndarray:
    """(n,) bool: whether latitudes [lat_lo, lat_hi] (degrees, (n,) each) meet the latitudes of
    one of ``boxes`` (lat_min, lon_min, lat_max, lon_max degrees), widened by REACH_MARGIN_DEG."""
    m = REACH_MARGIN_DEG
    return np.logical_or.reduce([(lat_lo <= lat_max + m) & (lat_hi >= lat_min - m)
                                 for lat_min, _, lat_max, _ in boxes] + [np.zeros(np.shape(lat_lo), bool)])


def _lon_reach(lon_lo, lon_hi, boxes) -> np.ndarray:
    """(n,) bool: whether longitudes [lon_lo, lon_hi] (degrees, unwrapped, (n,) each) meet, in
    some turn, the longitudes of one of ``boxes`` (lon_max may pass 180), widened by
    REACH_MARGIN_DEG."""
    m = REACH_MARGIN_DEG
    out = np.zeros(np.shape(lon_lo), bool)
    for _, lon_min, _, lon_max in boxes:
        width = (lon_max - lon_min) % 360.0 if lon_max < lon_min else lon_max - lon_min
        # Some whole turn k puts [lon_min, lon_min + width] + 360 k over [lon_lo, lon_hi].
        out |= np.ceil((lon_lo - (lon_min + width) - m) / 360.0) <= np.floor((lon_hi - lon_min + m) / 360.0)
    return out


def _reaching(rows, cs, offsets_y, offsets_x, dlat, dlon, boxes):
    """(row indices, column indices, offsets_y, offsets_x) of :func:`_sample_band` whose samples
    can fall inside one of ``boxes`` (see :func:`_lat_reach`, :func:`_lon_reach`): the rows and
    columns (lattice indices, (m,) and (n,) ascending) whose samples over every offset reach a
    box, then the offsets whose samples over those rows and columns do. A sample is inside a
    box only if its latitude is within the box's and its longitude within the box's, so what
    either axis drops answers OUTSIDE (and counts for nothing) wherever the other lies."""
    north, south = offsets_y[0], offsets_y[-1]  # offsets ascend: the first is the northernmost
    ri = np.flatnonzero(_lat_reach(90.0 - (rows + south) * dlat, 90.0 - (rows + north) * dlat, boxes))
    ci = np.flatnonzero(_lon_reach((cs + offsets_x[0]) * dlon - 180.0, (cs + offsets_x[-1]) * dlon - 180.0, boxes))
    if ri.size == 0 or ci.size == 0:
        return ri, ci, offsets_y[:0], offsets_x[:0]
    keep_y = _lat_reach(90.0 - (rows[ri[-1]] + offsets_y) * dlat, 90.0 - (rows[ri[0]] + offsets_y) * dlat, boxes)
    keep_x = _lon_reach((cs[ci[0]] + offsets_x) * dlon - 180.0, (cs[ci[-1]] + offsets_x) * dlon - 180.0, boxes)
    return ri, ci, offsets_y[keep_y], offsets_x[keep_x]


def _edge_samples(edges, lat, lon, dlat, dlon):
    """(heights m, statuses) of points (lat, lon degrees, (n,)) that no source answers but that lie
    less than one store spacing (dlat, dlon) from a point where a source does: each takes that
    source's height at the nearest such point (the first source in priority order that has one);
    OUTSIDE for the rest.

    A source answers on its cells whose corners all hold data, on the edges between two posts
    with data, and at its posts with data (terrain.raster's bilinear rule: a corner of zero weight
    is not read), so it answers all the way to its box's edges and to the edges of its voids
    (NODATA left unfilled, reaching the file's edge). The store's lattice is not aligned with the
    sources: without this, the store posts just beyond such an edge would be outside, and so would
    every bilinear cell between the edge and the first post inside it (the source's first valid
    column of posts lost, its answers there OUTSIDE from the store)."""
    h = np.full(lat.size, np.nan)
    s = np.full(lat.size, STATUS_OUTSIDE, np.uint8)
    for source, raster in edges:
        todo = np.flatnonzero(s == STATUS_OUTSIDE)
        if todo.size == 0:
            break
        g = raster.georef
        rc = np.empty(todo.size)
        cc = np.empty(todo.size)
        _nearest_answering(np.ascontiguousarray(raster.heights), lat[todo], lon[todo], dlat, dlon, g.crs, g.x0, g.y0,
                           g.dx, g.dy, rc, cc)
        near = np.flatnonzero(np.isfinite(rc))
        if near.size == 0:
            continue
        la, lo = _post_latlon(raster, rc[near], cc[near])
        hh = np.full(near.size, np.nan)
        ss = np.full(near.size, STATUS_OUTSIDE, np.uint8)
        source.heights_into(la, lo, hh, ss)
        h[todo[near]], s[todo[near]] = hh, ss
    return h, s


@numba.njit(cache=True, nogil=True)
def _nearest_answering(heights, lat, lon, dlat, dlon, crs, x0, y0, dx, dy, out_r, out_c):
    """For each point, the fractional (row, col) of a raster (georef crs, x0, y0, dx, dy; heights
    NaN where no data) of the nearest point where the raster answers, less than dlat degrees of
    latitude and dlon of longitude away (distances in those units); NaN where there is none.

    Candidates: each cell's point nearest the query (clamped into the cell), answered when every
    corner of non-zero weight holds data (a whole cell, or the edge it lands on), and each post
    with data; between them they hold the nearest point of every part of the answered set."""
    ny, nx = heights.shape
    turn = 360.0 if crs == CRS_GEOGRAPHIC else TWO_PI_A_M
    turn_cols = turn / dx
    reach_c = dlon / 360.0 * turn_cols  # columns within dlon of the point
    for k in range(lat.shape[0]):
        out_r[k] = np.nan
        out_c[k] = np.nan
        r, c = fractional_index(lat[k], lon[k], crs, x0, y0, dx, dy)
        # Rows less than dlat away (unclamped at the poles: a pole's post reaches as far as any).
        r_lo, _ = fractional_index(lat[k] - dlat, lon[k], crs, x0, y0, dx, dy)
        r_hi, _ = fractional_index(lat[k] + dlat, lon[k], crs, x0, y0, dx, dy)
        if r != r:
            continue  # beyond a Web Mercator raster's latitudes
        if r_lo != r_lo:
            r_lo = -1.0 - 1.0 * ny  # past the raster's south: no bound inside it
        if r_hi != r_hi:
            r_hi = 2.0 * ny
        # Longitude wraps (fractional_index takes it east of x0): west of the raster's west edge
        # is the column a turn less, where that is nearer to the raster's columns.
        if c > nx - 1 and c - turn_cols < 0.0 and turn_cols - c < c - (nx - 1):
            c -= turn_cols
        reach_r = 0.5 * (r_hi - r_lo)
        best = np.inf
        i_a, i_b = max(0, int(math.floor(r_lo))), min(ny - 1, int(math.floor(r_hi)) + 1)
        j_a, j_b = max(0, int(math.floor(c - reach_c))), min(nx - 1, int(math.floor(c + reach_c)) + 1)
        for i in range(i_a, i_b + 1):
            for j in range(j_a, j_b + 1):
                for cell in range(2):
                    if cell == 0:  # the post itself
                        pr, pc = float(i), float(j)
                        ok = heights[i, j] == heights[i, j]
                    else:  # the cell whose south-west corner it is: the query clamped into it
                        if i >= ny - 1 or j >= nx - 1:
                            continue
                        pr, pc = min(max(r, float(i)), i + 1.0), min(max(c, float(j)), j + 1.0)
                        fy, fx = pr - i, pc - j
                        i0 = i + 1 if fy == 1.0 else i
                        i1 = i if fy == 0.0 else i + 1
                        j0 = j + 1 if fx == 1.0 else j
                        j1 = j if fx == 0.0 else j + 1
                        ok = (heights[i0, j0] == heights[i0, j0] and heights[i0, j1] == heights[i0, j1]
                              and heights[i1, j0] == heights[i1, j0] and heights[i1, j1] == heights[i1, j1])
                    if not ok or not (r_lo < pr < r_hi and abs(pc - c) < reach_c):
                        continue
                    d = ((pr - r) / reach_r) ** 2 + ((pc - c) / reach_c) ** 2
                    if d < best:
                        best = d
                        out_r[k] = pr
                        out_c[k] = pc


def _class_pyramid(classes, row0, col0, rects):
    """Post classes of every level: level 0 padded to its rectangle (outside), then the
    even posts of each level (as the heights)."""
    r = rects[0]
    top, left = row0 - r.row0, col0 - r.col0
    levels = [np.pad(classes, ((top, r.rows - top - classes.shape[0]), (left, r.cols - left - classes.shape[1])),
                     constant_values=st.CLASS_OUTSIDE)]
    for f, c in zip(rects, rects[1:]):
        sub = levels[-1][::2, ::2]
        t, l = f.row0 // 2 - c.row0, f.col0 // 2 - c.col0
        levels.append(np.pad(sub, ((t, c.rows - t - sub.shape[0]), (l, c.cols - l - sub.shape[1])),
                             constant_values=st.CLASS_OUTSIDE))
    return levels


def _error_vs_sources(source: st.StoreSource, rasters, max_points: int = 200_000):
    """(max, sum of squares, n) of store height - source height at the sources'
    measured posts that the source itself answers in the stack (a deterministic subsample of at most
    max_points per source). rasters: in priority order. The stack answers a point from its first
    source answering OK there, else its first answering FILLED (terrain.terrain.Terrain); a post
    answered by another source holds that source's height in the store, so counting it reported
    the sources' disagreement as the store's error (7.15 m max, 5.19 m RMS, for a store within
    0.17 m of each source where it answers)."""
    worst, sq, n = 0.0, 0.0, 0
    for k, r in enumerate(rasters):
        ny, nx = r.heights.shape
        stride = max(1, int(math.ceil(math.sqrt(ny * nx / max_points))))
        rows, cols = np.meshgrid(np.arange(0, ny, stride), np.arange(0, nx, stride), indexing="ij")
        rows, cols = rows.ravel(), cols.ravel()
        lat, lon = _post_latlon(r, rows, cols)
        want = np.asarray(r.heights, np.float64)[rows, cols]
        h = np.full(lat.size, np.nan)
        s = np.full(lat.size, STATUS_OUTSIDE, np.uint8)
        source.heights_into(lat, lon, h, s)
        ok = (s == STATUS_OK) & np.isfinite(want)
        if r.filled is not None:
            ok &= r.filled[rows, cols] == 0  # uint8 flags: 1 where a void was filled
        ok &= _answered_by(rasters, k, lat, lon)
        d = np.abs(h[ok] - want[ok])
        worst = max(worst, float(d.max(initial=0.0)))
        sq += float(np.sum(d ** 2))
        n += int(d.size)
    return worst, sq, n


def _answered_by(rasters, k: int, lat, lon) -> np.ndarray:
    """(n,) bool: where the stack of ``rasters`` (priority order) answers from rasters[k]: the
    first answering OK, else (none OK) the first answering FILLED. lat, lon: (n,) float64 degrees."""
    owner_ok = np.full(lat.size, -1)
    owner_filled = np.full(lat.size, -1)
    h, s = np.empty(lat.size), np.empty(lat.size, np.uint8)
    for j, r in enumerate(rasters):
        s.fill(STATUS_OUTSIDE)  # heights_into answers only the points still OUTSIDE
        r.heights_into(lat, lon, h, s)
        owner_ok[(owner_ok < 0) & (s == STATUS_OK)] = j
        owner_filled[(owner_filled < 0) & (s == STATUS_FILLED)] = j
    return np.where(owner_ok >= 0, owner_ok, owner_filled) == k


def _post_latlon(r: Raster, rows, cols):
    from terrain.geodesy import web_mercator_inverse

    x, y = r.georef.post_xy(rows, cols)
    if r.georef.crs == CRS_GEOGRAPHIC:
        return y, (x + 180.0) % 360.0 - 180.0
    return web_mercator_inverse(x, y)


def _manifest(out: Path, name, tile, depth, unit_m, step_units, rasters, regions, summary, detail) -> dict:
    """The manifest (docs/STORE.md); summary None while the import is running (never written so);
    ``detail``: :func:`_detail_record` (add_detail, detail_seed, and with detail its finest spacing
    and each source's level stds or amplitude)."""
    per_source = detail.get("detail_sources") or [{} for _ in rasters]
    return {
        "format": st.FORMAT_NAME, "version": st.FORMAT_VERSION, "name": name or out.name,
        "tile": tile, "depth": depth, "unit_m": unit_m, "step_units": step_units,
        "lossless": step_units == 1, "vertical_datum": rasters[0].vertical_datum,
        "quadtree": "global-terrain-flight-sim §4: 6 roots of 90 x 120 deg; tile (row, col) of level k = "
                    "cell (depth - k, row, col)",
        **{k: v for k, v in detail.items() if k != "detail_sources"},
        "regions": regions,
        "sources": [{"path": str(r.source), "name": r.name, **d} for r, d in zip(rasters, per_source)],
        "summary": summary,
    }


def _write_manifest(out: Path, manifest: dict) -> None:
    """store.json, written atomically (no partial file left when the write fails)."""
    tmp = out / (st.MANIFEST + ".tmp")
    try:
        tmp.write_text(json.dumps(manifest, indent=1) + "\n")
        tmp.replace(out / st.MANIFEST)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink(missing_ok=True)
        raise


class _Progress:
    """A rich progress bar over posts sampled (silent when not asked for)."""

    def __init__(self, enabled: bool, total: int):
        self._p = None
        if enabled:
            from rich.progress import BarColumn, Progress, TextColumn, TimeRemainingColumn

            self._p = Progress(TextColumn("importing"), BarColumn(),
                               TextColumn("{task.completed:,}/{task.total:,} posts"), TimeRemainingColumn())
            self._task = self._p.add_task("import", total=total)
            self._p.start()

    def advance(self, n: int) -> None:
        if self._p is not None:
            self._p.advance(self._task, n)

    def close(self) -> None:
        if self._p is not None:
            self._p.stop()


__all__ = ["import_dems", "ImportSummary", "STATUS_OK"]
