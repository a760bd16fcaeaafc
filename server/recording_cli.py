"""``sortie recording info|check``, ``sortie resim`` and ``sortie replay``.

    sortie recording info FILE [--json]
    sortie recording check FILE            # exit 1 when anything is wrong (what is readable is listed)
    sortie resim FILE [--dem FILE... | --terrain HOST:PORT] [--until S] [--json OUT]
    sortie resim FILE --take-over S --agent NAME --port N   # live from instant S, NAME free to claim
                 [--duration S]                      # live for S world seconds (default: to the exercise's end)
                 [--clock realtime|fast|paused] [--time-scale X]  # default: real time, x1, whatever the recording ran
                 [--record FILE | --record-dir DIR | --no-record]  # recorded as sortie server records
    sortie replay FILE --port N [--speed X] [--paused] [--dem FILE... | --terrain HOST:PORT]
"""

from __future__ import annotations

import json
import logging
import math
import sys
from collections import Counter

from server.grpc_common import DEFAULT_GRACE_S, HOST_HELP, listen_address
from server.scenario import TIME_SCALE_MAX
from server.sim_server import CLOCKS
from sortie.config import MAX_GRACE_S, grace_seconds
from sortie.logs import line


def add_parser(sub) -> None:
    p = sub.add_parser("recording", help="what a sortie recording holds, and whether it is whole",
                       description="Inspect a sortie recording (server/recording.py): what it holds (info) and "
                                   "whether it is whole (check).")
    rsub = p.add_subparsers(dest="recording_command", metavar="COMMAND", required=True)
    info = rsub.add_parser("info", help="duration, entities, events, inputs, size",
                           description="Print what a recording holds: duration, entities, events, inputs, size.")
    info.add_argument("file", help="a .sortie recording")
    info.add_argument("--json", action="store_true", help="print JSON instead of text")
    info.set_defaults(func=info_command)
    check = rsub.add_parser("check", help="decode every chunk; exit 1 when anything is wrong",
                            description="Walk and decode the whole recording: the chunks that replay, and what "
                                        "is damaged or missing (a killed server leaves no footer; everything up "
                                        "to its last flushed chunk replays). Exit 0 when whole, 1 otherwise.")
    check.add_argument("file", help="a .sortie recording")
    check.set_defaults(func=check_command)

    r = sub.add_parser("resim", help="re-simulate a recording and compare every state, or take over from it",
                       description="Re-run the recorded scenario from its initial state with the recorded inputs "
                                   "and compare every state with the recording (bit-exact for the same build and "
                                   "terrain; the first divergence otherwise). With --take-over, run the world live "
                                   "from that instant instead, the --agent free for a client to claim.")
    r.add_argument("file", help="a .sortie recording")
    terrain = r.add_mutually_exclusive_group()
    terrain.add_argument("--dem", nargs="+", metavar="FILE", help="the DEM files (default: the recorded ones)")
    terrain.add_argument("--terrain", metavar="HOST:PORT[,HOST:PORT...]",
                         help="a terrain service (or replicas of one) serving the recorded DEMs")
    r.add_argument("--until", type=float, metavar="S", help="stop at world time S")
    r.add_argument("--aircraft-workers", default="0", metavar="N|auto",
                   help="processes for the aircraft (default %(default)s: in process; results are identical)")
    r.add_argument("--json", metavar="OUT", help="write the report as JSON")
    r.add_argument("--take-over", type=float, metavar="S", help="go live from world time S")
    r.add_argument("--agent", metavar="NAME", help="with --take-over: the agent a client takes (an aircraft or a "
                                                   "ground vehicle)")
    r.add_argument("--duration", type=float, metavar="S",
                   help="with --take-over: stop after S world seconds live (default: at the exercise's end, the "
                        "later of the scenario's duration_s and the recording's end; none: until stopped)")
    r.add_argument("--clock", choices=CLOCKS,
                   help="with --take-over: the clock it runs live (default realtime, x1, whatever clock the "
                        "recording ran: a client flies the agent in real time); fast: --time-scale x real time; "
                        "paused: until SIGUSR1 (SIGUSR1 runs the clock, SIGUSR2 pauses it, as sortie server's)")
    r.add_argument("--time-scale", type=float, metavar="X",
                   help=f"with --take-over: world seconds per wall second of the fast clock, (1, {TIME_SCALE_MAX:g}] "
                        "(default: the fast clock's default)")
    r.add_argument("--port", type=int, default=0, help="with --take-over: TCP port (0: a free one)")
    r.add_argument("--host", default="127.0.0.1", help=f"with --take-over: {HOST_HELP} (default %(default)s)")
    r.add_argument("--grace-s", type=grace_seconds, default=DEFAULT_GRACE_S,
                   help=f"with --take-over: seconds in-flight calls get on shutdown, 0-{MAX_GRACE_S:g} "
                        "(default %(default)s)")
    from server.sim_cli import add_recording_options

    add_recording_options(r, only="with --take-over: ")  # a take-over is a sortie: recorded as `sortie server`'s
    r.set_defaults(func=resim_command)

    from server.replay import add_parser as add_replay

    add_replay(sub)


def _open(path):
    from server.recording import Recording

    return Recording(path)


def finite_option(option: str, value: float | None) -> float | None:
    """``value`` of a command-line ``option`` (None: not given), refused unless finite."""
    if value is not None and not math.isfinite(value):
        from sortie.errors import InvalidArgument

        raise InvalidArgument(option, "must be a finite number of seconds", value=value)
    return value


def summary(rec) -> dict:
    """What the recording holds; a chunk that does not read is left out and listed in
    ``problems`` (with its offset), the others still counted."""
    from sortie.errors import DataFormatError

    kinds = Counter({1: "aircraft", 2: "ground", 3: "static"}.get(e.kind, "?") for e in rec.entities.values())
    events, damaged, unreadable, inputs = Counter(), [], set(), 0
    # Entity seconds from the chunk heads (entities x ticks of each chunk; an entity that
    # comes or goes within a chunk counts for the whole chunk).
    entity_s = 0.0
    for k in range(rec.chunk_count):
        try:
            head, body = rec.chunk_body(k)
        except DataFormatError as exc:
            unreadable.add(k)
            if not rec.mentions(k):  # a chunk the walk lost is a problem already
                damaged.append(str(exc))
            continue
        events.update(r.event.kind for r in body.events)
        inputs += len(body.inputs)
        entity_s += head.entity_count * head.ticks * rec.dt
    h = rec.header
    return {"file": str(rec.path), "size_bytes": rec.size, "exercise": h.exercise_name, "start_time": h.start_time,
            "first_time_s": rec.first_time_s, "last_time_s": rec.last_time_s, "duration_s": rec.duration_s,
            "ticks": rec.index.ticks, "world_rate_hz": rec.rate_hz, "chunks": rec.chunk_count,
            "entities": len(rec.entities), "entities_by_kind": dict(kinds), "events": sum(events.values()),
            "events_by_kind": dict(events), "inputs": inputs,
            "bytes_per_entity_second": rec.size / entity_s if entity_s else None,
            "footer": not rec.recovered, "problems": list(rec.problems) + damaged, "build_id": h.build_id,
            "replays_s": [[a * rec.dt, b * rec.dt] for a, b in rec.spans(unreadable)],
            "lost_ticks": rec.lost_ticks(unreadable),
            "damaged_chunks": [{"chunk": k, "offset": rec.index.chunk_offset[k]} for k in sorted(unreadable)],
            "sortie_version": h.sortie_version, "jsbsim_version": h.jsbsim_version,
            "terrain": h.terrain.description, "header_crc": rec.header_checked, "notes": list(rec.notes)}


def info_command(args) -> int:
    with _open(args.file) as rec:
        s = summary(rec)
    if args.json:
        print(json.dumps(s, indent=2))
        return 0
    per = s["bytes_per_entity_second"]
    print(f"{s['file']}: {s['exercise']} (start {s['start_time']})\n"
          f"  duration {s['duration_s']:.1f} s ({s['first_time_s']:.2f} .. {s['last_time_s']:.2f} s), "
          f"{s['ticks']} ticks at {s['world_rate_hz']:g} Hz in {s['chunks']} chunks\n"
          f"  entities {s['entities']} {s['entities_by_kind']}\n"
          f"  events {s['events']} {s['events_by_kind']}, inputs {s['inputs']}\n"
          f"  size {s['size_bytes']:,} bytes" + (f" ({per:.1f} bytes per entity second)" if per else "") + "\n"
          f"  terrain {s['terrain']}; build {s['build_id']} (sortie {s['sortie_version']}, "
          f"jsbsim {s['jsbsim_version']})\n"
          f"  footer {'yes' if s['footer'] else 'no (recovered by walking the chunks)'}")
    if s["damaged_chunks"]:
        lost = f"{s['lost_ticks']} ticks lost; " if s["lost_ticks"] else ""
        print(f"  replays {_spans(s['replays_s'])}; {lost}damaged: "
              + ", ".join(f"chunk {d['chunk']} at offset {d['offset']}" for d in s["damaged_chunks"]))
    for n in s["notes"]:
        print(f"  note: {n}")
    for p in s["problems"]:
        print(f"  problem: {p}")
    return 0


def check_command(args) -> int:
    with _open(args.file) as rec:
        report = rec.check(decode=True)
    print(f"{report.path}: {report.size_bytes:,} bytes, footer {'yes' if report.footer else 'no'}\n"
          f"  {report.chunks - report.damaged_chunks} of {report.chunks} chunks replay: {report.ticks} ticks, "
          f"world time {report.first_time_s:.2f} .. {report.last_time_s:.2f} s; {report.entities} entities, "
          f"{report.events} events, "
          f"{report.inputs} inputs\n  readable up to byte {report.readable_bytes:,}; header "
          + ("CRC checked" if report.header_checked else "unchecked (no CRC: recorded before header CRCs)"))
    if report.damaged_chunks:
        lost = f"; {report.lost_ticks} ticks lost" if report.lost_ticks else ""
        print(f"  replays {_spans(report.replays)}{lost}")
    for n in report.notes:
        print(f"  note: {n}")
    for p in report.problems:
        print(f"  problem: {p}")
    print("  OK" if report.ok else f"  {len(report.problems)} problem(s)")
    return 0 if report.ok else 1


def _spans(spans) -> str:
    return ", ".join(f"{a:.2f} .. {b:.2f} s" for a, b in spans) or "nothing"


def resim_command(args) -> int:
    from server.resim import resimulate
    from server.sim_cli import aircraft_workers

    finite_option("--until", args.until)
    finite_option("--take-over", args.take_over)
    workers = aircraft_workers(args.aircraft_workers)
    if args.take_over is not None:
        return take_over_command(args, workers)
    given = [o for o in ("agent", "record", "duration", "clock", "time_scale") if getattr(args, o) not in (None, "")]
    if given:
        from sortie.errors import InvalidArgument

        raise InvalidArgument(given[0], "only with --take-over", value=getattr(args, given[0]))
    with _open(args.file) as rec:
        if not rec.index.ticks:  # a server killed before its first chunk: no DIVERGED, nothing ran
            print(f"{args.file}: nothing to compare: the recording holds no ticks")
            for p in rec.problems:
                print(f"  note: {p}")
            return 1
    from rich.progress import Progress

    with Progress(transient=True) as bar:
        task = bar.add_task("re-simulating", total=None)
        report = resimulate(args.file, args.dem, args.terrain, workers, args.until,
                            progress=lambda t, last: bar.update(task, completed=t, total=last))
    d = report.as_dict()
    print(f"{report.recording}: {report.ticks} ticks compared in {report.wall_s:.1f} s: "
          f"{'bit-exact' if report.bit_exact else 'DIVERGED'} ({report.bit_exact_ticks} bit-exact ticks), "
          f"max position difference {report.max_position_diff_m:.4f} m"
          + (f"; {report.ticks_not_compared} ticks of damaged chunks not compared" if report.ticks_not_compared
             else ""))
    if report.first_divergence:
        print(f"  first divergence: {report.first_divergence}")
    for n in report.notes:
        print(f"  note: {n}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(d, f, indent=2)
    return 0 if report.bit_exact else 1


def take_over_command(args, workers: int) -> int:
    """Live from --take-over S: the world re-simulated to S, then served until the end (or
    --duration), in real time x1 unless --clock/--time-scale say otherwise (the recording's
    clock is not the take-over's: a fast x50 recording taken over ran x50, labelled
    "realtime"). SIGUSR1/SIGUSR2 run and pause the clock from the first step, as sortie
    server's (sim_cli.ClockSignals): one that comes while the world is re-simulated is
    applied as it goes live, where it killed the process before (no recording footer)."""
    from server.sim_cli import check_run_options, clock_signals, run_clock
    from sortie.errors import InvalidArgument

    if not args.agent:
        raise InvalidArgument("agent", "--take-over needs --agent NAME")
    check_run_options(args)  # --time-scale and --duration
    live_clock = run_clock("realtime", 1.0, args.clock, args.time_scale)
    with clock_signals() as clock:
        return _take_over(args, workers, live_clock, clock)


def _take_over(args, workers: int, live_clock: tuple[str, float], clock) -> int:
    """:func:`take_over_command` once its options are checked, under ``clock``
    (sim_cli.ClockSignals) with the (clock, time_scale) it runs live."""
    from server.grpc_common import stop_signals, wait_for_signal
    from server.resim import take_over, take_over_header
    from server.sim_cli import _missing_folders, check_recording, new_recording, recording_option, remove_recording
    from server.sim_server import SimulationServer, server_config
    from sortie.errors import InvalidArgument

    recording = {}

    def record(rec, world, scenario, spec):  # recorded as `sortie server` records, from the world's start
        path = check_recording(args, f"{scenario.exercise.name} take-over")
        if path is None:
            return None
        made = _missing_folders(path)
        recorder = new_recording(path, lambda: take_over_header(rec, scenario, world, spec,
                                                                bool(args.dem or args.terrain)), args.record_chunk_s,
                                 recording_option(args))
        recording.update(recorder=recorder, path=recorder.path, made=made)  # a chosen name may take a suffix
        return recorder

    try:
        world, inputs, scenario = take_over(args.file, args.take_over, args.agent, args.dem, args.terrain, workers,
                                            recorder=record, duration_s=args.duration)
    except InvalidArgument as exc:  # an agent that is gone, crashed, static or unknown; no live phase: the option
        option = {"agent": "--agent", "take_over": "--take-over"}.get(exc.field)
        raise exc.with_field(option) if option else exc from None
    recorder = recording.get("recorder")
    config = server_config(scenario, "take-over:" + str(args.file))
    config.clock, config.time_scale = live_clock
    try:
        server = SimulationServer(world, config, listen_address(args.host, args.port), before_tick=inputs.apply)
    except BaseException:  # it cannot listen: nothing is left behind for `sortie replay` to pick
        world.close()
        if recorder is not None:
            recorder.close()
            remove_recording(recording["path"], recording["made"])
        raise
    with stop_signals() as stop:  # before the line that says it listens (grpc_common.stop_signals)
        clock.attach(server)
        server.start()
        until = "until stopped" if config.duration_s is None else f"until t = {config.duration_s:.2f} s"
        line(f"sortie take-over of {args.agent} at t = {world.time_s:.2f} s ({until}) listening on "
             f"{server.address} (clock {clock.clock(config.clock)} x{config.time_scale:g})", logger=__name__)
        if recorder is not None:
            line(f"recording to {recording['path']}", logger=__name__)
        for lost in inputs.lost:
            line(f"note: the others' recorded inputs are incomplete: {lost}", stream=sys.stderr,
                 level=logging.WARNING, logger=__name__)
        wait_for_signal(server.finished, stop=stop)
    server.stop(args.grace_s)
    if recorder is not None:
        recorder.close()
    world.close()
    line(f"take-over stopped at world time {world.time_s:.1f} s", stream=sys.stderr, logger=__name__)
    if recorder is not None:
        state = f"failed: {recorder.error}" if recorder.error else f"{recording['path'].stat().st_size:,} bytes"
        line(f"recording {recording['path']}: {state}", stream=sys.stderr, logger=__name__)
    return 0
