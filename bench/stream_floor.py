"""The latency floor of the streaming path: gRPC Python with nothing else to do.

``sortie bench server`` measures publish -> client receipt with a whole world
behind the streams. This measures the same path with no world at all, on
the same machine and with the same clients, so the server's figure can be
read against what the transport alone allows here:

- a ``grpc.aio`` server whose only work is to write one message of the
  server run's mean size to every open stream, 20 times a second, all at
  once (as a publish wakes every Watch), the message's first 8 bytes being
  the wall time of the write's trigger;
- the clients: plain gRPC channels, one per client, 8 to a process (as
  bench/server_clients.py runs them), each recording trigger -> receipt;
- optionally the aircraft workers' CPU load, as stand-ins: one busy process
  per core at the workers' priority (server.aircraft_host.WORKER_NICE),
  busy ``duty`` of every 30 Hz tick.

    python -m bench.stream_floor serve BYTES          (prints "ready PORT")
    python -m bench.stream_floor clients ADDRESS N SECONDS   (prints JSON)
    python -m bench.stream_floor burn NICE DUTY
"""

from __future__ import annotations

import asyncio
import json
import os
import struct
import subprocess
import sys
import threading
import time

import numpy as np

RATE_HZ = 20.0  # the network rate of the server bench's clients
TICK_S = 1.0 / 30.0  # the world tick the burners' duty is a fraction of
METHOD = "/sortie.bench.Floor/Watch"
WARM_MESSAGES = 20  # left out of each client's log: channel start-up


def _serve(msg_bytes: int) -> None:
    import grpc

    async def main():
        server = grpc.aio.server()
        events: list[asyncio.Event] = []
        payload = bytearray(max(8, msg_bytes))

        async def watch(request, context):
            ready = asyncio.Event()
            events.append(ready)
            try:
                while not context.done():
                    await ready.wait()
                    ready.clear()
                    await context.write(bytes(payload))
            finally:
                events.remove(ready)

        handler = grpc.method_handlers_generic_handler("sortie.bench.Floor", {"Watch": grpc.unary_stream_rpc_method_handler(
            watch, request_deserializer=bytes, response_serializer=bytes)})
        server.add_generic_rpc_handlers((handler,))
        port = server.add_insecure_port("127.0.0.1:0")
        await server.start()
        print(f"ready {port}", flush=True)
        period = 1.0 / RATE_HZ
        next_t = time.monotonic()
        while True:
            next_t += period
            await asyncio.sleep(max(0.0, next_t - time.monotonic()))
            payload[:8] = struct.pack("<d", time.time())
            for ready in events:
                ready.set()

    asyncio.run(main())


def _clients(address: str, n: int, seconds: float) -> None:
    import grpc

    logs: list[list[float]] = [[] for _ in range(n)]

    def run(log: list) -> None:
        with grpc.insecure_channel(address) as channel:
            call = channel.unary_stream(METHOD, request_serializer=bytes, response_deserializer=bytes)(b"")
            t_end = time.time() + seconds
            for message in call:
                now = time.time()
                log.append((now - struct.unpack("<d", message[:8])[0]) * 1e3)
                if now > t_end:
                    break
            call.cancel()

    threads = [threading.Thread(target=run, args=(log,)) for log in logs]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    json.dump([x for log in logs for x in log[WARM_MESSAGES:]], sys.stdout)


def _burn(nice: int, duty: float) -> None:
    os.nice(nice)
    while True:
        t0 = time.perf_counter()
        while time.perf_counter() - t0 < TICK_S * duty:
            pass
        time.sleep(TICK_S * (1.0 - duty))


def _python(*args) -> list[str]:
    return [sys.executable, "-m", "bench.stream_floor", *map(str, args)]


def measure_floor(clients: int, per_process: int, seconds: float, msg_bytes: int, duty: float = 0.0,
                  nice: int | None = None) -> np.ndarray:
    """Trigger -> receipt latencies (ms) of every client's messages after its first
    WARM_MESSAGES; ``duty`` > 0 adds one busy process per core at priority ``nice``
    (default: the aircraft workers')."""
    from server.aircraft_host import WORKER_NICE

    server = subprocess.Popen(_python("serve", msg_bytes), stdout=subprocess.PIPE, text=True)
    procs: list[subprocess.Popen] = []
    try:
        line = server.stdout.readline()
        if not line.startswith("ready "):
            raise RuntimeError(f"stream floor server failed: {line!r}")
        address = f"127.0.0.1:{int(line.split()[1])}"
        if duty > 0:
            procs += [subprocess.Popen(_python("burn", WORKER_NICE if nice is None else nice, duty))
                      for _ in range(os.cpu_count() or 1)]
        loads = [subprocess.Popen(_python("clients", address, min(per_process, clients - first), seconds),
                                  stdout=subprocess.PIPE, text=True)
                 for first in range(0, clients, per_process)]
        procs += loads
        out = []
        for p in loads:
            text, _ = p.communicate(timeout=seconds + 60.0)
            out += json.loads(text)
        return np.array(out)
    finally:
        for p in [server, *procs]:
            if p.poll() is None:
                p.kill()
                p.wait()


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["serve"]:
        _serve(int(argv[1]))
    elif argv[:1] == ["clients"]:
        _clients(argv[1], int(argv[2]), float(argv[3]))
    elif argv[:1] == ["burn"]:
        _burn(int(argv[1]), float(argv[2]))
    else:
        print(__doc__, file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
