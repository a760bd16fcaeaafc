"""Ticks and fleets: Aircraft.advance and fdm.fleet.Fleet give the trajectories of
single steps bit for bit, with fewer terrain queries; the contact kernel
against a plain numpy reference."""

import math

import numpy as np
import pytest

from fdm.aircraft import Aircraft, InitialConditions
from fdm.contacts import contact_points, ground_clearance
from fdm.fleet import Fleet
from sortie.errors import InvalidArgument
from terrain.geodesy import radii_of_curvature, wrap_lon_deg

LAKE = (47.60, 9.40)  # Lake Constance in N47E009: flat at 392 m
FT_M = 0.3048


class CountingTerrain:
    """Any terrain, counting the calls and points asked of it."""

    def __init__(self, inner):
        self.inner = inner
        self.calls = 0
        self.points = 0

    def heights(self, lat, lon):
        self.calls += 1
        self.points += np.asarray(lat).size
        return self.inner.heights(lat, lon)


@pytest.fixture(scope="module")
def alps(hgt_alps):
    from terrain.dem import read_dem
    from terrain.terrain import Terrain

    return Terrain([read_dem(hgt_alps)])


# -- the contact kernel ---------------------------------------------------------------------------

def reference_contacts(lat, lon, alt, cg_in, phi, theta, psi, ahead, locations_in):
    """Plain numpy: structural -> body (FGMassBalance::StructuralToBody), body -> NED
    with the transpose of C_n2b (Stevens & Lewis eq. 1.3-20), tangent-plane offsets."""
    d = np.asarray(locations_in, float) - np.asarray(cg_in, float)
    body = np.stack([-d[:, 0], d[:, 1], -d[:, 2]], axis=-1) / 12.0 * FT_M
    cf, sf, ct, st, cp, sp = math.cos(phi), math.sin(phi), math.cos(theta), math.sin(theta), math.cos(psi), \
        math.sin(psi)
    c_n2b = np.array([[ct * cp, ct * sp, -st],
                      [sf * st * cp - cf * sp, sf * st * sp + cf * cp, sf * ct],
                      [cf * st * cp + sf * sp, cf * st * sp - sf * cp, cf * ct]])
    ned = body @ c_n2b
    m, n = radii_of_curvature(lat)
    p_lat = np.clip(lat + np.degrees((ned[:, 0] + ahead[0]) / (m + alt)), -90, 90)
    p_lon = wrap_lon_deg(lon + np.degrees((ned[:, 1] + ahead[1]) / ((n + alt) * math.cos(math.radians(lat)))))
    return np.r_[lat, p_lat], np.r_[lon, p_lon], alt - ned[:, 2]


def test_contact_kernel_matches_the_numpy_reference():
    rng = np.random.default_rng(7)
    for _ in range(200):
        lat, lon = rng.uniform(-89, 89), rng.uniform(-180, 180)
        alt = rng.uniform(-100, 12000)
        cg = rng.uniform(-50, 400, 3)
        locs = rng.uniform(-400, 600, (rng.integers(1, 14), 3))
        angles = rng.uniform(-math.pi, math.pi, 3)
        ahead = rng.uniform(-3, 3, 2)
        ours = contact_points(lat, lon, alt, cg, *angles, ahead, locs)
        ref = reference_contacts(lat, lon, alt, cg, *angles, ahead, locs)
        np.testing.assert_allclose(ours[0], ref[0], rtol=0, atol=1e-12)
        lon_diff = (ours[1] - ref[1] + 180.0) % 360.0 - 180.0
        np.testing.assert_allclose(lon_diff, 0.0, atol=1e-10)
        np.testing.assert_allclose(ours[2], ref[2], rtol=0, atol=1e-9)


def test_ground_clearance_is_the_deepest_contact():
    alt = np.array([10.0, 9.0, 12.0])
    terr = np.array([0.0, 9.5, 8.0, 12.5])  # CG first; contact clearances 0.5, 1.0, -0.5
    c_min, elevation, hit = ground_clearance(alt, terr, np.array([False, False, True]))
    assert c_min == -0.5 and elevation == 9.0 + 0.5 and hit
    assert not ground_clearance(alt, terr, np.array([True, True, False]))[2]


# -- advance == step, fleet == alone ----------------------------------------------------------------

def flights(terrain):
    """Three aircraft: on the ground with the brakes off, low over the lake, cruising."""
    return [
        Aircraft("c172x", terrain, InitialConditions(*LAKE, heading_deg=250.0, on_ground=True)),
        Aircraft("f16", terrain, InitialConditions(*LAKE, 40.0, "agl", heading_deg=70.0, speed_mps=150.0)),
        Aircraft("f16", terrain, InitialConditions(47.1, 9.5, 3500.0, heading_deg=0.0, speed_mps=200.0)),
    ]


def controls_at(k, i):
    """Deterministic stick inputs of aircraft i at tick k (the ground one runs up and rolls)."""
    if i == 0:
        return dict(brakes=0.0, throttle=1.0, pitch=0.2 if k > 150 else 0.0)
    return dict(pitch=0.05 * math.sin(k / 9.0 + i), roll=0.2 * math.sin(k / 13.0 + i))


def fly(aircraft, ticks, tick_steps, mode, fleet=None):
    rows, events = [], []
    for k in range(ticks):
        for i, a in enumerate(aircraft):
            a.set_controls(**controls_at(k, i))
        if mode == "step":
            for a in aircraft:
                for _ in range(tick_steps):
                    events += [(aircraft.index(a), e) for e in a.step()]
        elif mode == "advance":
            for a in aircraft:
                events += [(aircraft.index(a), e) for e in a.advance(tick_steps)]
        else:
            events += [(aircraft.index(a), e) for a, ev in fleet.advance(tick_steps) for e in ev]
        rows.append([a.raw_values() for a in aircraft])
    return np.array(rows), sorted(events, key=lambda x: (x[1].time_s, x[0]))


def test_advance_and_fleet_give_the_step_by_step_trajectories_bit_for_bit(alps):
    ticks, tick_steps = 240, 4  # 8 s at 120 Hz in 30 Hz ticks
    ref, ref_events = fly(flights(alps), ticks, tick_steps, "step")
    adv, adv_events = fly(flights(alps), ticks, tick_steps, "advance")
    counting = CountingTerrain(alps)
    fleet = Fleet(counting)
    members = [fleet.add(a) for a in flights(counting)]
    counting.calls = 0  # the starts' own queries
    flt, flt_events = fly(members, ticks, tick_steps, "fleet", fleet)
    assert np.isfinite(ref).all()
    assert np.array_equal(ref, adv)
    assert np.array_equal(ref, flt)
    assert ref_events == adv_events == flt_events
    # The low f16 needs a query every step; the fleet adds the others to those
    # batches instead of making calls of their own.
    assert counting.calls == fleet.queries <= ticks * (tick_steps + 1)
    assert counting.calls <= ticks * tick_steps + 5


def test_a_far_fleet_shares_one_query_per_refresh(alps):
    counting = CountingTerrain(alps)
    fleet = Fleet(counting)
    for i in range(8):
        fleet.add(Aircraft("f16", counting, InitialConditions(47.1 + 0.05 * i, 9.5, 4000.0, heading_deg=0.0,
                                                              speed_mps=200.0)))
    counting.calls = 0
    for _ in range(90):  # 3 s
        fleet.advance(4)
    # Eight aircraft refreshing about once a second each, in shared batches.
    assert 0 < counting.calls <= 8
    assert counting.points >= 8 * 2


def test_fleet_membership_errors_name_the_field(alps):
    fleet = Fleet(alps)
    a = fleet.add(Aircraft("c172x", alps, InitialConditions(47.3, 9.5, 1500.0, heading_deg=90.0,
                                                            speed_mps=50.0)))
    with pytest.raises(InvalidArgument, match="already"):
        fleet.add(a)
    with pytest.raises(InvalidArgument, match="terrain"):
        fleet.add(Aircraft("c172x", CountingTerrain(alps), InitialConditions(47.3, 9.5, 1500.0, speed_mps=50.0)))
    with pytest.raises(InvalidArgument, match="dt"):
        fleet.add(Aircraft("c172x", alps, InitialConditions(47.3, 9.5, 1500.0, speed_mps=50.0), dt=1 / 60))
    fleet.remove(a)
    assert len(fleet) == 0
    with pytest.raises(InvalidArgument, match="not in the fleet"):
        fleet.remove(a)
