"""Helpers shared by the server tests (tests/test_sim_server.py, tests/test_dis.py, the fuzz tests)."""

import grpc
from hypothesis import event

# What a service may answer a bad request with; INTERNAL or UNKNOWN would be a bug.
CLIENT_ERRORS = frozenset({grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.OUT_OF_RANGE,
                           grpc.StatusCode.NOT_FOUND, grpc.StatusCode.RESOURCE_EXHAUSTED,
                           grpc.StatusCode.FAILED_PRECONDITION, grpc.StatusCode.UNAUTHENTICATED,
                           grpc.StatusCode.PERMISSION_DENIED})


def rpc_outcome(call, what=""):
    """call()'s result, or the status code it failed with, which must be a client error
    with a message (the test fails here otherwise). Each outcome is a hypothesis event
    (``--hypothesis-show-statistics`` shows how often each came)."""
    try:
        result = call()
    except grpc.RpcError as exc:
        code, details = exc.code(), exc.details() or ""
        event(code.name)
        assert code in CLIENT_ERRORS, f"{code}: {details} for {what:.300}"
        assert details.strip(), f"{code} without a message"
        return code, details
    event("answered")
    return result


class PublishTap:
    """Keeps every snapshot the server's publisher publishes (the server-side truth)."""

    def __init__(self, publisher):
        self.snaps = []
        original = publisher.publish

        def publish(snap, *args):
            self.snaps.append(snap)
            return original(snap, *args)

        publisher.publish = publish
