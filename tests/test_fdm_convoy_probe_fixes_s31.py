"""A convoy staged behind its route's first waypoint (acceptance probe of the bots, session 31).

The probe lined six Humvees up on the westward extension of their route's first leg (c-1 at
the first waypoint, c-6 213 m back, 42.6 m apart; spacing 40 m, cruise 12 m/s). Every one of
them projected onto the route at s = 0 (the arc length was clamped to the route), so the
column kept the order it was listed in and every gap read 0: listed back to front, c-6 led
from the back, drove into c-5 at 11.7 m/s after 6.5 s and the column stood for 140 s; listed
front to back, each follower waited until the one ahead had passed the first waypoint and
the column took 70 s to reach its spacing. Oracle for the arc lengths: GeographicLib (Karney,
"Algorithms for geodesics", J. Geodesy 87, 2013)."""

import numpy as np
import pytest
from geographiclib.geodesic import Geodesic

from fdm.aircraft import FlatTerrain
from fdm.convoy import CATCH_UP_FRAC, Route, column_order
from server.world import World

WGS84 = Geodesic.WGS84
# The probe's route (east 530 m, then south 330 m; 600 m short of the antimeridian) and column.
ROUTE = [(-17.0, 179.9940), (-17.0, 179.9990), (-17.003, 179.9990)]
COLUMN_LAT = [-17.0] * 6
COLUMN_LON = [179.9940 - 0.0004 * k for k in range(6)]  # c-1 .. c-6, front to back


def _route() -> Route:
    return Route(*np.array(ROUTE).T)


def test_arc_length_runs_on_before_the_first_and_past_the_last_waypoint():
    """Points on the first leg's geodesic extended back 1 to 500 m project to s = -d, and on
    the last leg's extended on 1 to 213 m to the route's length + d, within 1 mm, on the
    route (cross-track under 1 mm); a point off the route beside the corner still projects
    onto the corner (s at the waypoint). Before, all of them were clamped to 0 or the
    route's length."""
    route = _route()
    (a_lat, a_lon), (b_lat, b_lon), (c_lat, c_lon) = ROUTE
    back = WGS84.Inverse(a_lat, a_lon, b_lat, b_lon)["azi1"] + 180.0
    on = WGS84.Inverse(b_lat, b_lon, c_lat, c_lon)["azi2"]
    d = np.array([1.0, 42.6, 213.0, 500.0])
    for start, azimuth, want in (((a_lat, a_lon), back, -d), ((c_lat, c_lon), on, route.length_m + d[:3])):
        pts = [WGS84.Direct(*start, azimuth, float(m)) for m in np.abs(want - np.clip(want, 0, route.length_m))]
        s, x, _ = route.project([p["lat2"] for p in pts], [p["lon2"] for p in pts])
        np.testing.assert_allclose(s, want, atol=1e-3)
        np.testing.assert_allclose(x, 0.0, atol=1e-3)
    outside = WGS84.Direct(b_lat, b_lon, 45.0, 20.0)  # north-east of the corner, outside it
    s, _, _ = route.project([outside["lat2"]], [outside["lon2"]])
    assert s[0] == pytest.approx(route.cum[1], abs=1e-6)


@pytest.mark.parametrize("listed", ["front_first", "back_first"])
def test_column_order_of_a_column_staged_behind_the_start(listed):
    """The staged column listed either way: the front one (at the first waypoint) leads, the
    others follow in their order back along the road. Before, every one stood at s = 0 and
    the listed order stood, back to front."""
    order = np.arange(6) if listed == "front_first" else np.arange(6)[::-1]
    got = column_order(_route(), np.array(COLUMN_LAT)[order], np.array(COLUMN_LON)[order], np.full(6, 90.0))
    assert order[got].tolist() == list(range(6))


def _along_first_leg_m(lat, lon) -> np.ndarray:
    """Metres along the first leg from its first waypoint (negative: behind it), by the
    geodesic (the column stays on the leg in the 30 s the test drives: c-1 covers 320 m of its
    530 m); independent of Route.project."""
    a_lat, a_lon = ROUTE[0]
    return np.array([np.sign(lo - a_lon) * WGS84.Inverse(a_lat, a_lon, la, lo)["s12"] for la, lo in zip(lat, lon)])


@pytest.mark.parametrize("listed", ["front_first", "back_first"])
def test_a_convoy_staged_behind_its_start_moves_off_together_in_column(listed):
    """The probe's column in a world at 30 Hz, listed either way, for 30 s: no collision; c-1
    leads and the others follow in their order, never closer than 30 m along the road (by the
    geodesic); all
    six are rolling (over 5 m/s) by 5 s; by 30 s the gaps are 40 m to within 1 m and c-1 has
    driven over 280 m, none faster than the cruise and its 30 % catch-up. Before: back to front, c-6 led from the back
    and rammed c-5 at 6.5 s, c-1 never moved; front to back, each follower waited about 5 s
    for the one ahead to pass the first waypoint and the leader crawled at 2-4 m/s."""
    order = list(range(6)) if listed == "front_first" else list(range(6))[::-1]
    world = World(FlatTerrain(150.0))
    try:
        column = world.spawn_ground([f"c-{k + 1}" for k in order], "hmmwv", [COLUMN_LAT[k] for k in order],
                                    [COLUMN_LON[k] for k in order], [90.0] * 6, route=ROUTE, cruise_mps=12.0,
                                    spacing_m=40.0)
        by_name = {e.name: e.ground_id for e in column}
        idx = world.ground.index_of([by_name[f"c-{k + 1}"] for k in range(6)])  # front to back
        events, least_gap, rolling_at, fastest = [], np.inf, None, 0.0
        for _ in range(30 * 30):
            events += world.tick()
            s = _along_first_leg_m(world.ground.lat[idx], world.ground.lon[idx])
            least_gap = min(least_gap, float(np.min(s[:-1] - s[1:])))
            fastest = max(fastest, float(world.ground.speed_mps[idx].max()))
            if rolling_at is None and (world.ground.speed_mps[idx] > 5.0).all():
                rolling_at = world.time_s
        assert not [e for e in events if e.kind in ("collision", "blocked")]
        assert least_gap > 30.0  # in column, front first, throughout
        assert rolling_at is not None and rolling_at <= 5.0
        np.testing.assert_allclose(s[:-1] - s[1:], 40.0, atol=1.0)
        assert s[0] > 280.0
        assert fastest <= (1.0 + CATCH_UP_FRAC) * 12.0 + 0.1
    finally:
        world.close()
