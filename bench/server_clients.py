"""Load for ``sortie bench server``: N observer clients in one process.

    python -m bench.server_clients ADDRESS N SECONDS SEED [--stall K] [--stall-phases] [--radius-m R]

Each client joins as an observer with a 20 km area of interest around a
random point of the N47E009 tile (seeded), watches for SECONDS, and records
(world time, wall receive time) of every WatchUpdate; K more clients join and
open a Watch they never read (stalled). With --stall-phases the K stalled
clients come and go on command instead: a line "stall" on stdin joins them and
opens their Watches (each read up to its snapshot, then never again), "calm"
cancels those and closes them; each command is acknowledged on stderr
("stall ok", "calm ok") once done. Prints one JSON object: per-client receive
logs, bytes and states received.
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
import time

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser()
    p.add_argument("address")
    p.add_argument("n", type=int)
    p.add_argument("seconds", type=float)
    p.add_argument("seed", type=int)
    p.add_argument("--stall", type=int, default=0)
    p.add_argument("--stall-phases", action="store_true")
    p.add_argument("--radius-m", type=float, default=20_000.0)
    args = p.parse_args(argv)

    from client.sim_client import SimClient
    from sortie.v1 import simulation_pb2 as pb
    from sortie.v1 import simulation_pb2_grpc as pb_grpc

    rng = np.random.default_rng(args.seed)
    clients, pictures, stalled = [], [], []
    for k in range(args.n):
        c = SimClient(args.address)
        c.join(f"load-{k}", "observer", observer=(float(rng.uniform(47.1, 47.9)), float(rng.uniform(9.1, 9.9)),
                                                  args.radius_m))
        clients.append(c)
        pictures.append(c.watch())
    def stall(name: str) -> tuple:
        c = SimClient(args.address)
        c.join(name, "observer", observer=(47.5, 9.5, 200_000.0))
        call = pb_grpc.SimulationServiceStub(c.channel).Watch(pb.WatchRequest(session_token=c.token))
        next(call)  # the snapshot, then never read again
        return c, call

    if not args.stall_phases:
        for k in range(args.stall):
            c, call = stall(f"stalled-{k}")
            clients.append(c)
            stalled.append(call)
    print("ready", flush=True, file=sys.stderr)
    if args.stall_phases:
        _phases(args, stall, time.monotonic() + args.seconds)
    else:
        time.sleep(args.seconds)
    out = {"received": [[(t, wall) for t, wall in pic.wall_log] for pic in pictures],
           "bytes": [pic.bytes for pic in pictures], "states": [pic.states_received for pic in pictures],
           "entered": [pic.entered for pic in pictures]}
    for call in stalled:
        call.cancel()
    done = threading.Event()

    def close():
        for c in clients:
            c.close()
        done.set()

    threading.Thread(target=close, daemon=True).start()
    done.wait(10.0)
    json.dump(out, sys.stdout)
    sys.stdout.flush()
    return 0


def _phases(args, stall, until: float) -> None:
    """Follow the "stall" / "calm" lines of stdin until it closes or ``until`` (monotonic) passes."""
    present: list = []  # (client, call) of the stalled clients while a stalled phase lasts
    generation = 0

    def dismiss() -> None:
        for c, call in present:
            call.cancel()
            c.leave()
            c.close()
        present.clear()

    for line in sys.stdin:
        command = line.strip()
        if command == "stall" and not present:
            generation += 1
            present.extend(stall(f"stalled-{generation}-{k}") for k in range(args.stall))
        elif command == "calm":
            dismiss()
        print(f"{command} ok", flush=True, file=sys.stderr)
        if time.monotonic() >= until:
            break
    dismiss()
    time.sleep(max(0.0, until - time.monotonic()))


if __name__ == "__main__":
    sys.exit(main())
