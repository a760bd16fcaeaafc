"""Compiling the world's own kernels before its clock starts.

numba compiles a kernel on its first call in a process, or loads it from its on-disk cache
(``cache=True``). In a fresh install the cache is empty, and the world's first ticks compiled
the ground vehicles', convoys' and obstacle search's kernels inside the tick: measured on the
Alps scenario in a fresh clone (2-core VM), tick 1 took 4.1-7.4 s (fdm.convoy, fdm.ground)
and tick 2 1.8-2.1 s (server.obstacles), a stall of the clock and of every stream. The
terrain's query kernels are warmed by :meth:`terrain.terrain.Terrain.warm_up`; the publisher's
passes when it is made (server.streaming.Publisher).

:func:`warm_up_world` ticks a small scratch world on the real world's terrain instead of
calling each kernel by hand: a two-vehicle convoy on a short route, a vehicle on the same
route coming the other way (the obstacle search, the pairs' contact test, the convoy's
traffic rules), one driving off any route (the heading hold) and a static target, for
``WARM_UP_TICKS`` ticks. Whatever the tick calls, it calls with the same types the real
world's ticks pass, so a kernel added to the tick later is warmed too
(tests/test_warm_up.py counts what a real world's first ticks still compile). The scratch
world is its own: it shares only the terrain (which it reads), and is closed after.
"""

from __future__ import annotations

import logging
import math
import time

from fdm.ground import FREE
from sortie.errors import SortieError

logger = logging.getLogger(__name__)

# Fewer than server.world.TERRAIN_RETAIN_EVERY_TICKS (30): the scratch world never tells a
# procedural terrain where its vehicles are (which would let it evict blocks near the real ones).
WARM_UP_TICKS = 12
ROUTE_LEG_M = 200.0  # the scratch route: two legs of this length from the place
CONVOY_SPACING_M = 15.0
WARM_UP_TYPES = ("m1a2", "hmmwv")  # one tracked, one wheeled (fdm.vehicle_types)
METRES_PER_DEG_LAT = 111_320.0  # near enough for placing a scratch route (no accuracy rests on it)


def _offset(lat: float, lon: float, heading_deg: float, distance_m: float) -> tuple[float, float]:
    h = math.radians(heading_deg)
    dlat = distance_m * math.cos(h) / METRES_PER_DEG_LAT
    dlon = distance_m * math.sin(h) / (METRES_PER_DEG_LAT * max(math.cos(math.radians(lat)), 0.01))
    return lat + dlat, (lon + dlon + 180.0) % 360.0 - 180.0


def _populate(world, lat: float, lon: float, heading_deg: float = 45.0) -> None:
    """The scratch agents at (lat, lon): SortieError where the terrain refuses them there
    (water, a slope, outside the data)."""
    route = [(lat, lon), _offset(lat, lon, heading_deg, ROUTE_LEG_M), _offset(lat, lon, heading_deg, 2 * ROUTE_LEG_M)]
    behind = _offset(lat, lon, heading_deg, -CONVOY_SPACING_M)
    world.spawn_ground(["warm-lead", "warm-second"], list(WARM_UP_TYPES), [lat, behind[0]], [lon, behind[1]],
                       [heading_deg, heading_deg], route=route, cruise_mps=8.0, spacing_m=CONVOY_SPACING_M)
    ahead = _offset(lat, lon, heading_deg, 0.25 * ROUTE_LEG_M)
    world.spawn_ground(["warm-oncoming"], WARM_UP_TYPES[1], [ahead[0]], [ahead[1]], [heading_deg + 180.0],
                       route=route[::-1], cruise_mps=8.0)
    side = _offset(lat, lon, heading_deg + 90.0, 40.0)
    world.spawn_ground(["warm-driver"], WARM_UP_TYPES[0], [side[0]], [side[1]], [heading_deg], speed_mps=4.0)
    target = _offset(lat, lon, heading_deg - 90.0, 40.0)
    world.spawn_static("warm-target", "radar", target[0], target[1])


def warm_up_world(world, places) -> tuple[float, tuple[float, float] | None]:
    """Tick a scratch world like ``world`` (its terrain, rates and geoid undulation) at the
    first of ``places`` ((lat, lon) degrees) where the terrain takes ground vehicles (spawns
    them, and lets one of them drive: fdm.ground.FREE at the end); (the
    seconds it took, the place used, or None where no place took them: nothing was warmed,
    and the first ticks compile as before)."""
    from server.world import World

    t0 = time.perf_counter()
    for lat, lon in places:
        if not (math.isfinite(lat) and math.isfinite(lon) and abs(lat) < 89.0):
            continue
        scratch = World(world.terrain, 1.0 / world.fdm_dt, 1.0 / world.dt, world.geoid_undulation_m)
        try:
            _populate(scratch, float(lat), float(lon))
            for _ in range(WARM_UP_TICKS):
                scratch.tick()
        except SortieError as exc:
            logger.debug("warm-up world at (%.5f, %.5f) refused: %s", lat, lon, exc)
            continue
        finally:
            scratch.close()
        if not (scratch.ground.blocked == FREE).any():  # stopped at once (water, slopes): the next place
            logger.debug("warm-up world at (%.5f, %.5f): every vehicle blocked", lat, lon)
            continue
        return time.perf_counter() - t0, (float(lat), float(lon))
    return time.perf_counter() - t0, None
