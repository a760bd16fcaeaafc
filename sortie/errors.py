"""The one error root of Sortie and its mapping to gRPC status codes.

Library code raises these; servicers catch :class:`SortieError` and call
:func:`grpc_code` once, so every service reports the same failure the same way.
"""

from __future__ import annotations

# How much of a bad value an error message shows (a longer repr keeps its head and its last
# SHOWN_TAIL_CHARS, a file's name, with its length between), and the longest message a status
# carries: gRPC sends the message as trailing metadata, which a receiver refuses beyond 16 KiB
# (the call then fails RESOURCE_EXHAUSTED instead of saying why).
SHOWN_VALUE_CHARS = 256
SHOWN_TAIL_CHARS = 48
MAX_MESSAGE_CHARS = 1024


def shown(value) -> str:
    """``repr(value)`` for an error message, cut to about SHOWN_VALUE_CHARS (its head and its
    tail, with the value's length) when longer: a 5 MB name is not echoed back, a long path
    keeps its file name."""
    text = repr(value)
    if len(text) <= SHOWN_VALUE_CHARS:
        return text
    try:
        size = f"{len(value):,} {'characters' if isinstance(value, str) else 'items'}"
    except TypeError:
        size = f"{len(text):,} characters"
    head = SHOWN_VALUE_CHARS - SHOWN_TAIL_CHARS
    return f"{text[:head]}...({size})...{text[-SHOWN_TAIL_CHARS:]}"


def message_of(error) -> str:
    """An error's (or a text's) text for a status or a log line, at most MAX_MESSAGE_CHARS (cut with its length)."""
    text = str(error)
    if len(text) <= MAX_MESSAGE_CHARS:
        return text
    return f"{text[:MAX_MESSAGE_CHARS]}... (message of {len(text):,} characters cut)"


class SortieError(Exception):
    """Root of every error Sortie raises on purpose."""


class InvalidArgument(SortieError, ValueError):
    """An input value is malformed: NaN, out of range, wrong shape.

    The message always names the field, and the index when the field is an array; the value
    shown is cut short (:func:`shown`).
    """

    def __init__(self, field: str, message: str, index: int | None = None, value=None):
        where = f"{field}[{index}]" if index is not None else field
        got = "" if value is None else f" (got {shown(value)})"
        super().__init__(f"{where}: {message}{got}")
        self.field = field
        self.message = message
        self.index = index
        self.value = value

    def __reduce__(self):  # picklable (an aircraft worker's errors reach the server's caller)
        return type(self), (self.field, self.message, self.index, self.value)

    def with_field(self, field: str) -> "InvalidArgument":
        """The same error naming ``field`` instead (a request's own field path for a library
        function's parameter: ``stick.pitch`` for ``pitch``)."""
        return InvalidArgument(field, self.message, self.index, self.value)


class LimitExceeded(SortieError):
    """A request is larger than a documented limit (batch size, rate, queue length)."""

    def __init__(self, field: str, size: int, limit: int, why: str = ""):
        super().__init__(f"{field}: {size} exceeds the limit of {limit}" + (f" ({why})" if why else ""))
        self.field = field
        self.size = size
        self.limit = limit
        self.why = why

    def __reduce__(self):
        return type(self), (self.field, self.size, self.limit, self.why)


class DataFormatError(SortieError):
    """A data file (DEM, recording) cannot be read as the format it claims to be."""


class NotFound(SortieError):
    """A named thing (file, agent, recording) does not exist."""


class Unauthenticated(SortieError):
    """An unknown, expired or forged session token."""


class PermissionDenied(SortieError):
    """The caller may not do this (e.g. command an agent its session does not hold)."""


def grpc_code(error: BaseException):
    """Map an exception to a ``grpc.StatusCode``; anything unexpected is INTERNAL."""
    import grpc

    if isinstance(error, InvalidArgument):
        return grpc.StatusCode.INVALID_ARGUMENT
    if isinstance(error, LimitExceeded):
        return grpc.StatusCode.RESOURCE_EXHAUSTED
    if isinstance(error, NotFound):
        return grpc.StatusCode.NOT_FOUND
    if isinstance(error, DataFormatError):
        return grpc.StatusCode.FAILED_PRECONDITION
    if isinstance(error, Unauthenticated):
        return grpc.StatusCode.UNAUTHENTICATED
    if isinstance(error, PermissionDenied):
        return grpc.StatusCode.PERMISSION_DENIED
    return grpc.StatusCode.INTERNAL


def bound_text(bound: float, refused: float) -> str:
    """A limit as a refusal of ``refused`` shows it: 6 significant digits (as the scenario's
    errors), or all its digits (the shortest text that reads back as it) where 6 would put
    the limit on or past the refused value, so that the message never contradicts itself
    (an m1a2's 18.77568 m/s top speed read "18.8" refusing 18.8, "18.7757" refusing 18.7757)."""
    text = f"{bound:.6g}"
    shown_bound = float(text)
    # The refused value strictly on one side of both (compared, not multiplied: the product of
    # two differences near 1e308 overflowed, a numpy scalar's with a RuntimeWarning; NaN: neither).
    if (refused > shown_bound and refused > bound) or (refused < shown_bound and refused < bound):
        return text
    return repr(float(bound))
