"""Which speeds each aircraft of the catalog trims at: ``sortie fdm trims``.

For each model, an airborne trimmed start (:class:`fdm.aircraft.Aircraft`, so level flight or
a glider's glide) over flat ground at one altitude and each speed of a grid; a speed trims
when the start raises nothing. Each model runs in a child process with a time limit: JSBSim's
trim cannot be interrupted (a failing one can wander for a minute) and a few models crash the
process. The child prints a line a speed, so a model cut off keeps the speeds it got through.

``fdm.catalog.TRIM_SPEEDS_SURVEYED`` and ``TRIM_NEVER`` are this survey's answer at 1500 m
(what TrimFailed's message quotes); re-run it after a JSBSim upgrade.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# Upper bounds of the options. An altitude beyond the Karman line (server.scenario.ALT_MAX_M,
# the most any start of a scenario may be given) is no flight a trim answers; a time limit past
# an hour per model is a unit mix-up (the default is 120 s, past any trim that ends), and an
# infinite one overflowed subprocess's wait (OverflowError).
ALT_MAX_M = 100_000.0
TIMEOUT_MAX_S = 3_600.0

_CHILD = r"""
import json, sys, time
from fdm.aircraft import Aircraft, FlatTerrain, InitialConditions
from sortie.errors import SortieError
name, alt, speeds = sys.argv[1], float(sys.argv[2]), json.loads(sys.argv[3])
for v in speeds:
    t0 = time.perf_counter()
    row = {"speed_mps": v}
    try:
        ac = Aircraft(name, FlatTerrain(0.0), InitialConditions(47.0, 9.0, alt, speed_mps=float(v)))
        row["gamma_deg"] = ac.trim_gamma_deg
    except SortieError as exc:
        row["error"] = f"{type(exc).__name__}: {str(exc)[:300]}"
    row["seconds"] = round(time.perf_counter() - t0, 3)
    print("ROW " + json.dumps(row), flush=True)
"""


def survey_model(name: str, alt_m: float, speeds, timeout_s: float) -> dict:
    """{"name", "trims": [speeds that trimmed], "rows": [per speed], "timed_out", "returncode"}."""
    t0 = time.perf_counter()
    out, timed_out, code = "", False, 0
    try:
        r = subprocess.run([sys.executable, "-c", _CHILD, name, str(alt_m), json.dumps(list(speeds))],
                           cwd=REPO, capture_output=True, text=True, timeout=timeout_s)
        out, code = r.stdout, r.returncode
    except subprocess.TimeoutExpired as exc:
        out = exc.stdout.decode() if isinstance(exc.stdout, bytes) else (exc.stdout or "")
        timed_out = True
    rows = [json.loads(line[4:]) for line in out.splitlines() if line.startswith("ROW ")]
    return {"name": name, "trims": [r["speed_mps"] for r in rows if "error" not in r], "rows": rows,
            "timed_out": timed_out, "returncode": code, "seconds": round(time.perf_counter() - t0, 1)}


def survey(names, alt_m: float, speeds, timeout_s: float, progress=None) -> list[dict]:
    """:func:`survey_model` of each name, in order; ``progress(result)`` after each."""
    results = []
    for name in names:
        results.append(survey_model(name, alt_m, speeds, timeout_s))
        if progress is not None:
            progress(results[-1])
    return results


def trims_command(args) -> int:
    from fdm.catalog import TRIM_SURVEY_SPEEDS, list_aircraft, resolve
    from sortie.errors import InvalidArgument

    names = [resolve(n) for n in args.aircraft] or list(list_aircraft())
    speeds = tuple(args.speeds) if args.speeds else TRIM_SURVEY_SPEEDS
    for field, v, high, unit in (("alt_m", args.alt_m, ALT_MAX_M, "m MSL"),
                                 ("timeout_s", args.timeout_s, TIMEOUT_MAX_S, "s")):
        if not 0.0 <= v <= high:  # NaN too
            raise InvalidArgument(field, f"must be a number within [0, {high:g}] {unit}", value=v)
    if any(not (0 < s < 1000) for s in speeds):
        raise InvalidArgument("speeds", "must be within (0, 1000) m/s", value=list(speeds))

    def show(r):
        note = " (timed out)" if r["timed_out"] else (f" (exit {r['returncode']})" if r["returncode"] else "")
        print(f"{r['name']:18s} {', '.join(f'{v:g}' for v in r['trims']) or '-'}{note}", flush=True)

    results = survey(names, args.alt_m, speeds, args.timeout_s, None if args.json else show)
    if args.json:
        print(json.dumps({"alt_m": args.alt_m, "speeds_mps": list(speeds), "results": results}))
    else:
        print(f"{sum(bool(r['trims']) for r in results)}/{len(results)} models trim at some speed "
              f"at {args.alt_m:g} m MSL")
    return 0


def add_parser(commands) -> None:
    p = commands.add_parser("trims", help="which speeds each aircraft trims at",
                            description="Try an airborne trimmed start (level flight, or a glider's glide) "
                                        "of each aircraft at each speed over flat ground, each model in a "
                                        "child process with a time limit, and print the speeds that trim.")
    p.add_argument("aircraft", nargs="*", help="catalog names (default: every aircraft)")
    p.add_argument("--alt-m", type=float, default=1500.0, help="altitude, m MSL (default %(default)s)")
    p.add_argument("--speeds", type=float, nargs="+", metavar="MPS",
                   help="true airspeeds to try, m/s (default: 5 to 150 by 5, 175, 200, 250)")
    p.add_argument("--timeout-s", type=float, default=120.0, help="limit per model, s (default %(default)s)")
    p.add_argument("--json", action="store_true", help="print JSON instead of text")
    p.set_defaults(func=trims_command)
