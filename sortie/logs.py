"""Logging of the ``sortie`` entry points: plain text for people, JSON lines for machines.

``--log-format json`` (or ``SORTIE_LOG_FORMAT=json``) writes one JSON object per
record to stderr: ``time`` (ISO 8601 UTC, ms), ``level``, ``logger``,
``message``, ``process`` (pid), ``thread`` (name), any ``extra={...}`` fields
the call passed, and ``exception`` (the formatted traceback) when there is one
— what log shippers (Loki, Elasticsearch, CloudWatch) ingest without parsing
rules. Libraries only call ``logging.getLogger(__name__)``; this module is
used by :mod:`sortie.cli` alone, and by the commands for their status lines
(:func:`line`: "listening on ...", "stopped", the error that ends a command),
which are JSON records too in json mode, so that every line a service writes, on
stdout or stderr, is one JSON object.
"""

from __future__ import annotations

import json
import logging
import sys
import time

FORMATS = ("text", "json")
TEXT_FORMAT = "%(asctime)s %(levelname)s %(name)s: %(message)s"
# Attributes every LogRecord has: whatever else a record carries came from `extra`.
_STANDARD = set(vars(logging.LogRecord("", 0, "", 0, "", (), None))) | {"message", "asctime"}


class JsonFormatter(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        out = {"time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
               "level": record.levelname, "logger": record.name, "message": record.getMessage(),
               "process": record.process, "thread": record.threadName}
        out.update({k: v for k, v in vars(record).items() if k not in _STANDARD})
        if record.exc_info:
            out["exception"] = self.formatException(record.exc_info)
        return json.dumps(out, default=str)


_format = "text"  # of the command being run (configure)


def configure(level: int, fmt: str = "text") -> None:
    """Root logging to stderr at ``level`` in ``fmt`` ("text" or "json"); :func:`line` writes in
    ``fmt`` too, and in json Python's warnings are log records."""
    global _format
    _format = fmt
    handler = logging.StreamHandler()
    handler.setFormatter(JsonFormatter() if fmt == "json" else logging.Formatter(TEXT_FORMAT))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(level)
    logging.captureWarnings(fmt == "json")


def line(text: str, stream=None, level: int = logging.INFO, logger: str = "sortie", fmt: str | None = None) -> None:
    """A command's status line (stdout by default) or error line (stderr): ``text`` as is in text
    logging; in json logging one JSON record (``message`` = ``text``, at ``level``, from
    ``logger``), whatever the log level, as the text line is printed whatever it is. ``fmt``:
    the format when :func:`configure` has not been called yet (an error in the options)."""
    stream = sys.stdout if stream is None else stream
    if (fmt or _format) == "json":
        text = JsonFormatter().format(logging.LogRecord(logger, level, "", 0, text, None, None))
    print(text, file=stream, flush=True)
