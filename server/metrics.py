"""Operational metrics over HTTP, in the Prometheus text exposition format.

``sortie server --metrics-port N`` and ``sortie terrain serve --metrics-port N``
serve ``GET /metrics`` (format 0.0.4,
https://prometheus.io/docs/instrumenting/exposition_formats/) from a daemon
thread; every scrape calls the service's ``collect()`` for fresh values, so
nothing is computed between scrapes. Counters end in ``_total`` and only grow
(rates are the scraper's business: ``rate(sortie_watch_bytes_total[1m])`` is
the bytes/s the Watch streams send); gauges are values now; tick durations are
a summary whose quantiles cover the last :data:`TICK_WINDOW` ticks and whose
``_sum`` and ``_count`` every tick since the start (a summary's ``_sum`` and
``_count`` are counters to Prometheus, which reads a drop as a restart:
https://prometheus.io/docs/concepts/metric_types/#summary). Names and meanings
are listed in docs/DEPLOYMENT.md.
"""

from __future__ import annotations

import logging
import math
import socket
import threading
import time
from dataclasses import dataclass, field
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np

from sortie.errors import SortieError

logger = logging.getLogger(__name__)

CONTENT_TYPE = "text/plain; version=0.0.4; charset=utf-8"
TICK_WINDOW = 1000  # ticks in the tick-duration summary


@dataclass
class Metric:
    """One metric family: ``samples`` are (labels dict, value); type "counter", "gauge" or "summary"."""

    name: str
    type: str
    help: str
    samples: list = field(default_factory=list)

    def add(self, value: float, **labels) -> Metric:
        self.samples.append((labels, float(value)))
        return self


def _label_text(labels: dict) -> str:
    if not labels:
        return ""
    esc = {k: str(v).replace("\\", r"\\").replace("\n", r"\n").replace('"', r"\"") for k, v in labels.items()}
    return "{" + ",".join(f'{k}="{v}"' for k, v in esc.items()) + "}"


def _number(v: float) -> str:
    if math.isnan(v):
        return "NaN"
    if math.isinf(v):
        return "+Inf" if v > 0 else "-Inf"
    return repr(int(v)) if v == int(v) and abs(v) < 2 ** 53 else repr(v)


def exposition(metrics: list[Metric]) -> str:
    """The text of ``metrics`` (HELP, TYPE, one line per sample)."""
    lines = []
    for m in metrics:
        help_text = m.help.replace("\\", "\\\\").replace("\n", "\\n")
        lines.append(f"# HELP {m.name} {help_text}")
        lines.append(f"# TYPE {m.name} {m.type}")
        for labels, value in m.samples:
            labels = dict(labels)
            suffix = labels.pop("__suffix", "")
            lines.append(f"{m.name}{suffix}{_label_text(labels)} {_number(value)}")
    return "\n".join(lines) + "\n"


def summary(name: str, help_text: str, window, count: int, total: float,
            quantiles=(0.5, 0.9, 0.99)) -> Metric:
    """A summary metric: quantiles of the recent observations ``window`` (NaN when empty), and
    ``count`` observations totalling ``total`` since the start as _count and _sum (running
    totals, never a window's: Prometheus treats them as counters)."""
    a = np.asarray(window, float)
    m = Metric(name, "summary", help_text)
    for q in quantiles:
        m.add(float(np.quantile(a, q)) if a.size else math.nan, quantile=q)
    m.add(total, __suffix="_sum")
    m.add(count, __suffix="_count")
    return m


class MetricsServer:
    """``GET /metrics`` on ``host:port`` (port 0: any free one, see :attr:`port`) answered with
    ``exposition(collect())``; other paths are 404. A collect() that fails answers 500
    and is logged; the service it describes carries on. ``host`` is a name or an address
    as sockets take it (an IPv6 literal without brackets: the server binds the family
    ``host`` resolves to, IPv6 included); :attr:`address` is HOST:PORT for a URL
    (an IPv6 literal in brackets, RFC 3986 section 3.2.2)."""

    def __init__(self, collect, host: str = "127.0.0.1", port: int = 0):
        self.collect = collect
        outer = self

        class Handler(BaseHTTPRequestHandler):
            def do_GET(self):  # noqa: N802 - http.server's name
                if self.path.split("?")[0] != "/metrics":
                    self.send_error(404, "only /metrics is served")
                    return
                try:
                    body = exposition(outer.collect()).encode("utf-8")
                except Exception:  # noqa: BLE001 - a broken scrape must not take the service down
                    logger.exception("collecting metrics failed")
                    self.send_error(500, "collecting metrics failed")
                    return
                self.send_response(200)
                self.send_header("Content-Type", CONTENT_TYPE)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            def log_message(self, fmt, *args):  # scrapes are not news
                logger.debug("metrics: " + fmt, *args)

        authority = f"[{host}]" if ":" in host else host
        try:
            family = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0][0]
            server_class = type("MetricsHTTPServer", (ThreadingHTTPServer,), {"address_family": family})
            self.httpd = server_class((host, port), Handler)
        except OSError as exc:
            raise SortieError(f"cannot serve metrics on {authority}:{port}: {exc.strerror or exc}") from None
        self.httpd.daemon_threads = True
        self.port = self.httpd.server_address[1]
        self.address = f"{authority}:{self.port}"
        self._thread = threading.Thread(target=self.httpd.serve_forever, name="metrics", daemon=True)

    def start(self) -> MetricsServer:
        self._thread.start()
        return self

    def stop(self) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()


def simulation_metrics(server) -> list[Metric]:
    """A :class:`server.sim_server.SimulationServer`'s metrics now."""
    world = server.world
    kinds = {}
    for e in list(world.entities.values()):
        key = ("external" if e.external_id else "sortie", {1: "aircraft", 2: "ground", 3: "static"}[e.kind])
        kinds[key] = kinds.get(key, 0) + 1
    entities = Metric("sortie_entities", "gauge", "Entities in the world, by kind and owner (sortie or external)")
    for (owner, kind), n in sorted(kinds.items()):
        entities.add(n, kind=kind, owner=owner)
    sessions = server.sessions
    ticks, tick_ms_total = server.tick_totals
    out = [
        Metric("sortie_world_time_seconds", "gauge", "World time (s since the exercise start)").add(world.time_s),
        Metric("sortie_world_ticks_total", "counter", "World ticks run").add(world.tick_count),
        summary("sortie_tick_duration_milliseconds",
                f"Wall time of a world tick (quantiles: last {TICK_WINDOW} ticks; sum, count: all)",
                server.tick_ms[-TICK_WINDOW:], ticks, tick_ms_total),
        summary("sortie_publish_duration_milliseconds",
                f"Wall time of a publish to the Watch streams, beside the ticks (quantiles: last {TICK_WINDOW}; "
                "sum, count: all)", server.publish_ms[-TICK_WINDOW:], *server.publish_totals),
        Metric("sortie_tick_overruns_total", "counter", "Ticks that started late by more than a tick").add(
            server.overruns),
        entities,
        Metric("sortie_sessions", "gauge", "Client sessions").add(len(sessions)),
        Metric("sortie_watch_streams", "gauge", "Open Watch streams").add(len(sessions.watching())),
        Metric("sortie_updates_sent_total", "counter", "Entity state updates decided by dead reckoning").add(
            server.publisher.updates_sent),
        Metric("sortie_watch_messages_total", "counter", "WatchUpdate messages written to streams").add(
            server.stream_stats.messages),
        Metric("sortie_watch_bytes_total", "counter", "Bytes of WatchUpdate messages written to streams").add(
            server.stream_stats.bytes),
        Metric("sortie_events_total", "counter", "World events emitted").add(world.events_total),
        Metric("sortie_uptime_seconds", "gauge", "Seconds since the server started").add(
            time.monotonic() - server.started_monotonic),
    ]
    rec = server.recorder
    if rec is not None:
        out.append(Metric("sortie_recording_bytes_total", "counter", "Bytes written to the recording").add(
            rec.bytes_written))
        out.append(Metric("sortie_recording_failed", "gauge", "1 when the recorder has failed").add(
            1 if rec.error else 0))
    return out


def terrain_metrics(stats) -> list[Metric]:
    """A terrain service's call counters (:class:`server.grpc_common.CallStats`)."""
    calls = Metric("sortie_terrain_calls_total", "counter", "Terrain RPCs answered, by method")
    errors = Metric("sortie_terrain_errors_total", "counter", "Terrain RPCs that failed, by method and status code")
    seconds = Metric("sortie_terrain_call_seconds_total", "counter", "Wall time spent answering, by method")
    for method, (n, s, codes) in sorted(stats.snapshot().items()):
        calls.add(n, method=method)
        seconds.add(s, method=method)
        for code, k in sorted(codes.items()):
            errors.add(k, method=method, code=code)
    return [calls, errors, seconds]
