"""Flight dynamics: JSBSim aircraft on Sortie terrain (see ARCHITECTURE.md).

- :mod:`fdm.aircraft` — :class:`~fdm.aircraft.Aircraft` (one ``FGFDMExec``: initial
  conditions, validated normalised controls, terrain coupling, events, state out);
- :mod:`fdm.state` — the SI state and its vectorised conversion from JSBSim's raw snapshot;
- :mod:`fdm.events` — touchdown, take-off, crash and out-of-fuel detection;
- :mod:`fdm.autopilot` — heading/altitude/speed hold and waypoint following;
- :mod:`fdm.catalog` — the aircraft and scripts of the ``jsbsim`` wheel, script replay;
- :mod:`fdm.cli` — ``sortie fdm list`` and ``sortie fdm fly``.

JSBSim's imperial property names never leave this package.
"""
