"""Helpers shared by the server tests (tests/test_sim_server.py, tests/test_dis.py)."""


class PublishTap:
    """Keeps every snapshot the server's publisher publishes (the server-side truth)."""

    def __init__(self, publisher):
        self.snaps = []
        original = publisher.publish

        def publish(snap, *args):
            self.snaps.append(snap)
            return original(snap, *args)

        publisher.publish = publish
