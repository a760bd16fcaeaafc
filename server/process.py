"""A Sortie service run as its own process: how the demo, the benchmarks and
integration tests start one, the way it is deployed.

:class:`ServiceProcess` starts ``sortie <args> --port P`` on a free loopback
port, waits until grpc.health.v1 reports SERVING, and on exit terminates it
(SIGTERM: the service drains in-flight calls) and reaps it.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time
from pathlib import Path

from sortie.errors import SortieError

DEFAULT_START_TIMEOUT_S = 120.0
STOP_TIMEOUT_S = 30.0


def free_port() -> int:
    """A TCP port free on loopback now (the service binds it a moment later)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def sortie_command() -> list[str]:
    """argv prefix that runs this interpreter's ``sortie`` console script."""
    exe = Path(sys.executable).with_name("sortie")
    if exe.exists():
        return [str(exe)]
    return [sys.executable, "-m", "sortie.cli"]


def wait_serving(address: str, proc: subprocess.Popen | None = None,
                 timeout_s: float = DEFAULT_START_TIMEOUT_S) -> None:
    """Block until the service at address says SERVING; SortieError if it dies or times out."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    deadline = time.monotonic() + timeout_s
    with grpc.insecure_channel(address) as channel:
        stub = health_pb2_grpc.HealthStub(channel)
        while time.monotonic() < deadline:
            if proc is not None and proc.poll() is not None:
                raise SortieError(f"service at {address} exited with code {proc.returncode} before serving")
            try:
                reply = stub.Check(health_pb2.HealthCheckRequest(service=""), timeout=1.0)
                if reply.status == health_pb2.HealthCheckResponse.SERVING:
                    return
            except grpc.RpcError:
                pass
            time.sleep(0.1)
    raise SortieError(f"service at {address} not SERVING after {timeout_s} s")


class ServiceProcess:
    """``with ServiceProcess(["terrain", "serve", "--dem", path]) as svc: svc.address``.

    args: the sortie sub-command and its options, without ``--port``. log: a
    file for the service's output (default: discarded).
    """

    def __init__(self, args: list[str], log: Path | None = None,
                 start_timeout_s: float = DEFAULT_START_TIMEOUT_S):
        self.args = list(args)
        self.log_path = log
        self.start_timeout_s = start_timeout_s
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.command = [*sortie_command(), *self.args, "--port", str(self.port)]
        self.proc: subprocess.Popen | None = None
        self._log = None

    def __enter__(self) -> ServiceProcess:
        self._log = open(self.log_path, "w") if self.log_path else subprocess.DEVNULL
        self.proc = subprocess.Popen(self.command, stdout=self._log, stderr=subprocess.STDOUT)
        try:
            wait_serving(self.address, self.proc, self.start_timeout_s)
        except BaseException:
            self.stop()
            raise
        return self

    def __exit__(self, *exc) -> None:
        self.stop()

    def stop(self) -> int | None:
        """Terminate (SIGTERM, then SIGKILL after STOP_TIMEOUT_S) and reap; the exit code."""
        code = None
        if self.proc is not None:
            if self.proc.poll() is None:
                self.proc.terminate()
                try:
                    self.proc.wait(timeout=STOP_TIMEOUT_S)
                except subprocess.TimeoutExpired:
                    self.proc.kill()
                    self.proc.wait()
            code = self.proc.returncode
        if self._log not in (None, subprocess.DEVNULL):
            self._log.close()
        self._log = None
        return code
