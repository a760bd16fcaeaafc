"""Many aircraft on one terrain, stepped together with one terrain query per round.

An :class:`fdm.aircraft.Aircraft` stepped alone asks its terrain for heights
at each of its check steps: a dozen contact points every step near the
ground, one point now and then far from it. Through the terrain service that
is a round trip each time. A :class:`Fleet` steps all its aircraft through a
world tick in *rounds*: in each round every aircraft runs JSBSim up to its
next check (or the tick's end), the points all the due aircraft need go to the
terrain in one batched query, and each aircraft applies its share. Aircraft far
from the ground finish the tick in one round; one near the ground needs a
round per step, so a tick of n steps costs at most n + 1 queries whatever the
fleet size.

Each aircraft's trajectory is bit-identical to stepping it alone (the
terrain answers each point the same whichever batch it arrives in).
"""

from __future__ import annotations

import numpy as np

from fdm.aircraft import Aircraft, terrain_msl_m
from sortie.errors import InvalidArgument


class Fleet:
    """Aircraft sharing one terrain source and one step size."""

    def __init__(self, terrain):
        self.terrain = terrain
        self.aircraft: list[Aircraft] = []
        self.queries = 0  # batched terrain queries made (benchmarks, tests)

    def add(self, aircraft: Aircraft) -> Aircraft:
        if aircraft.terrain is not self.terrain:
            raise InvalidArgument("aircraft", "must use the fleet's terrain source", value=aircraft.name)
        if self.aircraft and aircraft.dt != self.aircraft[0].dt:
            raise InvalidArgument("aircraft", f"dt {aircraft.dt} differs from the fleet's {self.aircraft[0].dt}",
                                  value=aircraft.name)
        if any(a is aircraft for a in self.aircraft):
            raise InvalidArgument("aircraft", "is already in the fleet", value=aircraft.name)
        self.aircraft.append(aircraft)
        return aircraft

    def remove(self, aircraft: Aircraft) -> None:
        for k, a in enumerate(self.aircraft):
            if a is aircraft:
                del self.aircraft[k]
                return
        raise InvalidArgument("aircraft", "is not in the fleet", value=aircraft.name)

    def __len__(self) -> int:
        return len(self.aircraft)

    def advance(self, steps: int) -> list[tuple[Aircraft, list]]:
        """``steps`` JSBSim steps of every aircraft; (aircraft, events) for those with events."""
        out = []
        active = []
        for a in self.aircraft:
            if a.crashed:  # a wreck: falling (its own terrain point per tick: few fall at once) or at rest
                events = a._fall_advance(steps)
                if events:
                    out.append((a, events))
                continue
            end = a._steps + steps
            if a._quiet_tick(steps):
                continue
            active.append((a, end))
        while active:
            due = []  # (aircraft, number of points)
            for a, end in active:
                target = min(a._next_check, end)
                run = a._run
                for _ in range(target - a._steps):
                    run()
                if target > a._steps:
                    a._steps = target
                if a._steps >= a._next_check and not a._quiet_check():
                    due.append((a, a._plan()))
            points = [(a._q_lat[:n], a._q_lon[:n]) for a, n in due if n]
            terr = None
            if points:
                self.queries += 1
                terr = terrain_msl_m(self.terrain, np.concatenate([p[0] for p in points]),
                                     np.concatenate([p[1] for p in points]))
            k = 0
            for a, n in due:
                events = a._finish(terr[k:k + n] if n else None)
                k += n
                if events:
                    out.append((a, events))
            active = [(a, end) for a, end in active if a._steps < end and not a.crashed]
        return out

    def raw_values(self) -> list[list]:
        """Every aircraft's raw snapshot (fdm.state.RAW_PROPERTIES rows)."""
        return [a.raw_values() for a in self.aircraft]
