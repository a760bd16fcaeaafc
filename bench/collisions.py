"""Collisions between agents for ``sortie bench server``: the world's per-tick test
(server/collisions.py) against an all-pairs numpy reference on the same scene.

The scene is one world tick of a battlefield: 2000 ground vehicles (boxes of the catalog's
types, any heading, up to 20 m/s, moved as over a second so the scene holds contacts) of
which a quarter crowd a 240 m vehicle park and the rest spread over 20 km x 20 km; 300
aircraft (spheres of 5-30 m, 100-300 m/s in any direction, half milling in an 800 m cube, the
rest 0.5-3.5 km up over the area) and 50 static sites (10 m spheres); quick: a quarter of each.
The reference tests every pair with the same rules (spheres: least distance over the tick,
touching at its start excluded; boxes: separating axes at the start and at the kernel's
instants), vectorised over blocks of rows, so the two must find the same contacts.

Metrics: ``collision_entities``, ``collision_new_contacts`` (in the scene),
``collision_ms`` (one tick's test, best of 7), ``collision_us_per_entity``,
``collision_vs_all_pairs`` (the reference's time over ours), ``collision_disagreements``
(pairs one finds and the other not; 0 expected).
"""

from __future__ import annotations

import math
import time

import numpy as np

from bench.harness import Report

LAT0, LON0 = 47.3, 9.5
M_PER_DEG = 111_200.0  # near enough for placing a scene
TICK_S = 1.0 / 30.0
BLOCK_ROWS = 128
PARK_M = 120.0  # half side of the vehicle park (a quarter of the vehicles)
FURBALL_M = 400.0  # half side of the cube where half the aircraft mill about


def scene(quick: bool, seed: int = 7) -> dict:
    """Start and end positions (ECEF) and shapes of one tick's entities (module docstring)."""
    from fdm.vehicle_types import VEHICLE_TYPES
    from terrain.geodesy import enu_basis, geodetic_to_ecef

    rng = np.random.default_rng(seed)
    scale = 4 if quick else 1
    n_gnd, n_air, n_static = 2000 // scale, 300 // scale, 50 // scale
    n = n_gnd + n_air + n_static
    m_lon = M_PER_DEG * math.cos(math.radians(LAT0))
    parked, furball = n_gnd // 4, n_air // 2
    spread = n - parked - furball
    east = np.r_[rng.uniform(-PARK_M, PARK_M, parked), rng.uniform(-10_000, 10_000, n_gnd - parked),
                 rng.uniform(-FURBALL_M, FURBALL_M, furball), rng.uniform(-10_000, 10_000, spread - n_gnd + parked)]
    north = np.r_[rng.uniform(-PARK_M, PARK_M, parked), rng.uniform(-10_000, 10_000, n_gnd - parked),
                  rng.uniform(-FURBALL_M, FURBALL_M, furball), rng.uniform(-10_000, 10_000, spread - n_gnd + parked)]
    up = np.r_[np.full(n_gnd, 500.0), 2000.0 + rng.uniform(-FURBALL_M, FURBALL_M, furball),
               rng.uniform(500, 3500, n_air - furball), np.full(n_static, 500.0)]
    lat, lon = LAT0 + north / M_PER_DEG, LON0 + east / m_lon
    p1 = geodetic_to_ecef(lat, lon, up)
    e, nn, u = enu_basis(LAT0, LON0)
    heading = rng.uniform(0, 360, n)
    speed = np.r_[rng.uniform(0, 20, n_gnd), rng.uniform(100, 300, n_air), np.zeros(n_static)]
    h = np.radians(heading)
    climb = np.r_[np.zeros(n_gnd), rng.uniform(-0.3, 0.3, n_air), np.zeros(n_static)]
    v = speed[:, None] * (np.sin(h)[:, None] * e + np.cos(h)[:, None] * nn + climb[:, None] * u)
    # The ground moves as over a second (20 m at most: boxes are tested at the start and the end
    # only, which the reference does too), so that the park holds new contacts to compare.
    p0 = p1 - v * np.r_[np.full(n_gnd, 1.0), np.full(n_air + n_static, TICK_S)][:, None]
    types = list(VEHICLE_TYPES.values())
    kind = rng.integers(0, len(types), n_gnd)
    half_l = np.r_[[types[k].length_m / 2 for k in kind], np.zeros(n_air + n_static)]
    half_w = np.r_[[types[k].width_m / 2 for k in kind], np.zeros(n_air + n_static)]
    radius = np.r_[np.hypot(half_l[:n_gnd], half_w[:n_gnd]), rng.uniform(5, 30, n_air), np.full(n_static, 10.0)]
    moves = np.r_[np.ones(n_gnd + n_air, bool), np.zeros(n_static, bool)]
    return dict(p0=p0, p1=p1, radius=radius, heading_deg=heading, half_length_m=half_l, half_width_m=half_w,
                moves=moves, lat_deg=lat, lon_deg=lon)


def _sat(dx, dy, hi, hj, li, wi, lj, wj):
    """Separating-axis overlap of rectangles (numpy over pairs): centres (dx, dy) apart, headings
    hi, hj (radians from north), half lengths l and widths w."""
    ci, si, cj, sj = np.sin(hi), np.cos(hi), np.sin(hj), np.cos(hj)
    overlap = np.ones(dx.shape, bool)
    for ax, ay in ((ci, si), (si, -ci), (cj, sj), (sj, -cj)):
        ri = li * np.abs(ci * ax + si * ay) + wi * np.abs(si * ax - ci * ay)
        rj = lj * np.abs(cj * ax + sj * ay) + wj * np.abs(sj * ax - cj * ay)
        overlap &= np.abs(dx * ax + dy * ay) <= ri + rj
    return overlap


def all_pairs(s: dict) -> set:
    """New contacts by testing every pair (numpy, BLOCK_ROWS rows at a time)."""
    from terrain.geodesy import enu_basis

    p0, p1, r = s["p0"], s["p1"], s["radius"]
    hl, hw, moves = s["half_length_m"], s["half_width_m"], s["moves"]
    hd = np.radians(s["heading_deg"])
    n = r.size
    e, nn, u = enu_basis(s["lat_deg"], s["lon_deg"])
    found = set()
    for a in range(0, n, BLOCK_ROWS):
        i = np.arange(a, min(a + BLOCK_ROWS, n))[:, None]
        j = np.arange(n)[None, :]
        i, j = np.broadcast_arrays(i, j)
        keep = (j > i) & (moves[i] | moves[j])
        i, j = i[keep], j[keep]
        rs = r[i] + r[j]
        r0, r1 = p0[j] - p0[i], p1[j] - p1[i]
        d0 = np.linalg.norm(r0, axis=1)
        boxes = (hl[i] > 0) & (hl[j] > 0)
        dr = r1 - r0
        dd = (dr * dr).sum(1)
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.clip(np.where(dd > 0, -(r0 * dr).sum(1) / dd, 0.0), 0.0, 1.0)
        dmin = np.linalg.norm(r0 + t[:, None] * dr, axis=1)
        sphere_hit = ~boxes & (d0 >= rs) & (dmin < rs)
        box_hit = np.zeros(i.size, bool)
        b = np.flatnonzero(boxes & (dmin < rs))
        if b.size:
            ib, jb = i[b], j[b]

            def touching(rr):
                return (np.abs((rr * u[ib]).sum(1)) < rs[b]) & _sat(
                    (rr * e[ib]).sum(1), (rr * nn[ib]).sum(1), hd[ib], hd[jb], hl[ib], hw[ib], hl[jb], hw[jb])
            # The same instants as the kernel: the start, then every half of the narrower width.
            samples = np.maximum(1, np.ceil(np.sqrt(dd[b]) / np.minimum(hw[ib], hw[jb]))).astype(np.int64)
            hit_b = np.zeros(b.size, bool)
            for k in range(1, int(samples.max()) + 1):
                live = k <= samples
                tk = np.where(live, k / samples, 1.0)
                hit_b |= live & touching(r0[b] + tk[:, None] * dr[b])
            box_hit[b] = hit_b & ~touching(r0[b])
        hit = sphere_hit | box_hit
        found |= set(zip(i[hit].tolist(), j[hit].tolist()))
    return found


def run_collisions(report: Report, quick: bool) -> None:
    from server.collisions import new_contacts

    s = scene(quick)
    new_contacts(**s)  # compile
    t_ours = math.inf
    for _ in range(7):
        t0 = time.perf_counter()
        ci, cj, _, _ = new_contacts(**s)
        t_ours = min(t_ours, time.perf_counter() - t0)
    t0 = time.perf_counter()
    reference = all_pairs(s)
    t_ref = time.perf_counter() - t0
    ours = set(zip(ci.tolist(), cj.tolist()))
    n = s["radius"].size
    report.metrics["collision_entities"] = n
    report.metrics["collision_new_contacts"] = len(ours)
    report.metrics["collision_ms"] = t_ours * 1e3
    report.metrics["collision_us_per_entity"] = t_ours * 1e6 / n
    report.metrics["collision_vs_all_pairs"] = t_ref / t_ours
    report.metrics["collision_disagreements"] = len(ours ^ reference)
    report.params.update(collision_scene="2000 vehicles (a quarter in a 240 m park), 300 aircraft (half in an "
                                         "800 m cube), 50 sites"
                         + (" / 4" if quick else ""), collision_reference="all pairs, numpy, same rules")
