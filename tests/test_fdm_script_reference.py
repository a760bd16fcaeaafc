"""Against a trajectory nobody here wrote: a JSBSim script shipped in the wheel.

``c172_elevator_doublet.xml`` (c172x at 2000 ft, trims at 1 s and 20 s,
elevator and aileron events) runs under JSBSim's own script runner; the same
aircraft is then driven through Sortie's wrapper with the same initial state,
the same pilot inputs at each step and the same trims. Not bit-exact, and why
(traced step by step):

- The wrapper takes its initial conditions in SI and geodetic latitude, the
  script in feet and geocentric latitude: the start differs by one rounding,
  3e-9 m. The wrapper feeds flat terrain at exactly 0 ft; JSBSim's own run
  keeps the -3e-9..-7e-9 ft its IC geometry gives.
- From those inputs JSBSim's full trim (at 1 s, again at 20 s) lands on
  trimmed controls that differ in the last bits (elevator position, aileron,
  throttle: 1e-14 relative).
- Until the doublets the difference stays at the start offset (< 1e-8 m:
  stepping, controls and terrain coupling add nothing); the elevator doublet
  (5-7 s) and the aileron doublet (after the re-trim) excite the trim
  difference to 1e-6 m and 1.6e-5 m at 40 s. For scale, JSBSim against itself
  with the IC latitude nudged by one ulp stays within 7e-9 m: the growth comes
  through the trims, not from chaotic flight.

Not every process sees the difference: in some (long benchmark processes)
the two runs agree bit for bit, in every fresh process so far they differ by
1.6e-5 m, with the same code and inputs. Something in JSBSim's IC or trim
path depends on state outside its inputs (uninitialised memory is the usual
suspect); it matters for bit-exact re-simulation across processes and is
left to trace with a memory checker.

Stated bounds: 1e-8 m until the first doublet, 1e-3 m over the whole run.
"""

import numpy as np

from fdm.catalog import replay_script, script_trim_times, root_dir


def test_trim_times_are_read_from_the_script():
    assert script_trim_times(root_dir() / "scripts" / "c172_elevator_doublet.xml") == [1.0, 20.0]


def test_wrapper_matches_jsbsims_own_script_run():
    ours, ref = replay_script("c172_elevator_doublet.xml")
    assert ours.shape == ref.shape and len(ref) > 4700
    diff = np.linalg.norm(ours - ref, axis=1)
    assert diff[0] < 1e-8
    assert diff[:int(5.0 * 120)].max() < 1e-8  # before the elevator doublet (dt = 1/120 s)
    assert diff.max() < 1e-3, diff.max()
    # The aircraft really flew: 20 s at 96 kt since the re-trim restarted it from
    # the initial conditions.
    assert np.linalg.norm(ref[-1] - ref[0]) > 900.0
