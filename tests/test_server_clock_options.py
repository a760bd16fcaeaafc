"""sortie server's --clock and --time-scale against the scenario's clock (acceptance probe: a
fast x10 scenario run with --clock realtime ran ten times real time, labelled "realtime";
--clock fast on a real-time scenario ran at x1; --time-scale 5 alone ran "realtime" x5)."""

import pytest

from server.scenario import DEFAULT_FAST_TIME_SCALE
from server.sim_cli import run_clock
from sortie.errors import InvalidArgument


@pytest.mark.parametrize("scenario, clock_opt, scale_opt, expected", [
    (("fast", 10.0), "realtime", None, ("realtime", 1.0)),
    (("fast", 10.0), "paused", None, ("paused", 1.0)),  # resumes in real time, as a paused scenario does
    (("realtime", 1.0), "fast", None, ("fast", DEFAULT_FAST_TIME_SCALE)),
    (("realtime", 1.0), "fast", 4.0, ("fast", 4.0)),
    (("fast", 10.0), None, 3.0, ("fast", 3.0)),
    (("fast", 25.0), "fast", None, ("fast", 25.0)),  # the same clock keeps the scenario's rate
    (("paused", 1.0), None, None, ("paused", 1.0)),
    (("realtime", 1.0), None, None, ("realtime", 1.0)),
])
def test_the_clock_options_bring_their_own_rate(scenario, clock_opt, scale_opt, expected):
    assert run_clock(*scenario, clock_opt, scale_opt) == expected


@pytest.mark.parametrize("scenario, clock_opt, scale_opt", [
    (("realtime", 1.0), None, 5.0),
    (("fast", 10.0), "realtime", 2.0),
    (("fast", 10.0), "paused", 10.0),
])
def test_a_time_scale_other_than_1_needs_the_fast_clock(scenario, clock_opt, scale_opt):
    with pytest.raises(InvalidArgument, match=r"time_scale: must be 1\.0 with the (realtime|paused) clock "
                                              r"\(use --clock fast\)"):
        run_clock(*scenario, clock_opt, scale_opt)
