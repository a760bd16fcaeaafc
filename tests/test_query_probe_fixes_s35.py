"""Probe pass s35 on the terrain queries (issue #2): segments over a pole of the procedural world.

RayBudget.estimate cut a segment into equal pieces by its whole box; over a pole the piece
holding the pole kept half a turn of longitude over most of its rows, so a 330 km segment
12 km above the south pole, which the trace answers with about 6 M posts of rasters, was
refused before any work at 191 M (and a 1100 km one from the north pole at 171 M), while a
segment between the same latitudes each side of the pole at equal heights passed. The reference
here is independent of terrain.los: the chord sampled densely in ECEF, converted by PROJ
(EPSG:4978 -> EPSG:4979), its heights compared with the terrain's heights there.
"""

from __future__ import annotations

import numpy as np
import pyproj
import pytest

from sortie.errors import LimitExceeded
from terrain.geodesy import geodetic_to_ecef
from terrain.procedural import ProceduralTerrain
from terrain.raster import STATUS_OK
from terrain.terrain import RayBudget, Terrain

REF_SAMPLES = 100_001
_TO_GEODETIC = pyproj.Transformer.from_crs("EPSG:4978", "EPSG:4979", always_xy=True)


def _ends(*values):
    return tuple(np.array([v], dtype=np.float64) for v in values)


def _dense(terrain: Terrain, rays):
    """(s of the first sample under the surface or None, least clearance m, step as a fraction of
    the segment): the chord a -> b in REF_SAMPLES samples, PROJ's geodetic heights against the
    terrain's heights at the same points."""
    a, b = geodetic_to_ecef(*rays[:3])[0], geodetic_to_ecef(*rays[3:])[0]
    s = np.linspace(0.0, 1.0, REF_SAMPLES)
    p = a[None] + s[:, None] * (b - a)[None]
    lon, lat, h = _TO_GEODETIC.transform(p[:, 0], p[:, 1], p[:, 2])
    clearance = h - terrain.heights(lat, lon).height_msl_m
    below = np.flatnonzero(clearance < 0.0)
    return (s[below[0]] if below.size else None), float(clearance.min()), 1.0 / (REF_SAMPLES - 1)


def test_a_segment_over_the_south_pole_is_estimated_as_traced_and_answered():
    """330 km at 12 km over the south pole: the estimate is within a factor 2 of the posts the trace
    makes (LimitExceeded 'before any work' at 191 M posts before), and the answer is the dense
    reference's: clear (its least clearance is kilometres), status OK."""
    t = Terrain([ProceduralTerrain(seed=3)])
    rays = _ends(-87.0, 45.0, 12000.0, -87.5, -135.0, 12000.0)
    a, b = geodetic_to_ecef(*rays[:3]), geodetic_to_ecef(*rays[3:])
    with pytest.raises(LimitExceeded, match="before any work") as info:  # its size: the estimate's posts
        RayBudget(max_posts=0).estimate(t.sources, a, b)
    traced = RayBudget()
    seg = t.intersect(*rays, budget=traced)
    assert 0.5 * traced.posts < info.value.size < 2.0 * traced.posts
    los = t.line_of_sight(*rays)
    first, least, _ = _dense(t, rays)
    assert first is None and least > 1000.0
    assert not seg.hit[0] and seg.status[0] == STATUS_OK
    assert los.visible[0] and los.status[0] == STATUS_OK


def test_a_long_segment_from_the_north_pole_hits_where_dense_samples_go_under():
    """1100 km from 8 km over the north pole down the chord to 80 N, 170 E: refused before any
    work at 171 M posts before; now it hits where the dense reference first goes under the
    surface, to within one sampling step (11 m) plus 1 m, and is not visible."""
    t = Terrain([ProceduralTerrain(seed=3)])
    rays = _ends(90.0, 0.0, 8000.0, 80.0, 170.0, 8000.0)
    seg, los = t.intersect(*rays), t.line_of_sight(*rays)
    first, _, step = _dense(t, rays)
    length = np.linalg.norm(geodetic_to_ecef(*rays[3:])[0] - geodetic_to_ecef(*rays[:3])[0])
    assert first is not None and seg.hit[0] and seg.status[0] == STATUS_OK
    assert (first - step) * length - 1.0 <= seg.distance_m[0] <= first * length + 1.0
    assert not los.visible[0] and los.status[0] == STATUS_OK
