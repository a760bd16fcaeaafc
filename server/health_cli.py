"""``sortie health``: ask a service's grpc.health.v1 whether it is serving.

    sortie health ADDRESS [--service NAME] [--timeout-s S]

Exit status 0 when the service answers SERVING, 1 otherwise (NOT_SERVING while
it drains after SIGTERM, SERVICE_UNKNOWN, an unknown service name, no answer
within the timeout, nothing listening, and a bad option or environment value
too: Docker reserves a health check's status 2); one line saying which is printed
either way. This is the health check of the container image and of
docker-compose.yml (docs/DEPLOYMENT.md), so it makes exactly one call, within
``--timeout-s``, connection included.

Every Sortie service registers the overall health ("", the default) and one
name per gRPC service it serves: ``sortie.v1.TerrainService`` (sortie terrain
serve), ``sortie.v1.SimulationService`` (sortie server, sortie replay,
sortie resim --take-over), ``sortie.v1.ReplayService`` (sortie replay).
"""

from __future__ import annotations

import math
import re

from sortie.errors import InvalidArgument

DEFAULT_TIMEOUT_S = 3.0
# HOST:PORT, the host a name, an IPv4 address or a bracketed IPv6 one (a gRPC target with a
# scheme, such as unix:PATH or dns:///HOST:PORT, is passed on as it is).
_HOST_PORT = re.compile(r"^(\[[^\]]*\]|[^\[\]:/]*):([^:]*)$")


def add_parser(sub) -> None:
    p = sub.add_parser("health", help="exit 0 if a service's grpc.health.v1 says SERVING, 1 otherwise",
                       description="Ask the grpc.health.v1 service at ADDRESS for the status of --service "
                                   "(default: the server as a whole) and print it; exit 0 when SERVING, 1 "
                                   "otherwise (not serving, unknown service, no answer). The container and "
                                   "docker-compose health check.")
    p.add_argument("address", metavar="ADDRESS", help="HOST:PORT of the service")
    p.add_argument("--service", default="", metavar="NAME",
                   help="a service name such as sortie.v1.TerrainService (default: the whole server)")
    p.add_argument("--timeout-s", type=float, default=DEFAULT_TIMEOUT_S, metavar="S",
                   help="seconds to wait for the answer, connection included (default %(default)s)")
    p.set_defaults(func=health_command)


def check(address: str, service: str = "", timeout_s: float = DEFAULT_TIMEOUT_S) -> tuple[bool, str]:
    """(serving, status text): the health of ``service`` at ``address`` after one Check call.

    The text is the status name (SERVING, NOT_SERVING, SERVICE_UNKNOWN) or the
    gRPC error's code and details when the call failed (:func:`failure_text`)."""
    import grpc
    from grpc_health.v1 import health_pb2, health_pb2_grpc

    if not (math.isfinite(timeout_s) and timeout_s > 0):
        raise InvalidArgument("timeout_s", "must be a finite number > 0", value=timeout_s)
    check_address(address)
    with grpc.insecure_channel(address) as channel:
        try:
            # Fail fast: a refused connection is reported as UNAVAILABLE with its reason
            # at once (the orchestrator asks again at its interval).
            reply = health_pb2_grpc.HealthStub(channel).Check(
                health_pb2.HealthCheckRequest(service=service), timeout=timeout_s)
        except grpc.RpcError as exc:
            return False, failure_text(exc.code(), exc.details(), service)
    return (reply.status == health_pb2.HealthCheckResponse.SERVING,
            health_pb2.HealthCheckResponse.ServingStatus.Name(reply.status))


def failure_text(code, details: str | None, service: str) -> str:
    """"CODE: what went wrong" for a failed Check. grpc.health.v1's Check fails with NOT_FOUND for
    a service name the server has not registered (gRPC's doc/health-checking.md; grpcio's
    grpc_health.v1.health.HealthServicer.Check), and grpcio's servicer sends no details with it,
    so the text names the service; any other code without details says so."""
    import grpc

    if details:
        return f"{code.name}: {details}"
    if code == grpc.StatusCode.NOT_FOUND:
        return f"NOT_FOUND: unknown service {service!r} (the server registers no health status under that name)"
    return f"{code.name}: (the server gave no details)"


def check_address(address: str) -> None:
    """HOST:PORT with a port 1..65535 (gRPC takes any number and keeps its low 16 bits: port
    99999 would probe 34463); InvalidArgument otherwise."""
    if "://" in address or address.startswith(("unix:", "unix-abstract:", "vsock:", "ipv4:", "ipv6:")):
        return
    m = _HOST_PORT.match(address)
    port = m[2] if m else ""
    if not (port.isascii() and port.isdigit() and 1 <= int(port) <= 65535):
        raise InvalidArgument("address", "must be HOST:PORT with a port 1..65535", value=address)


def health_command(args) -> int:
    serving, status = check(args.address, args.service, args.timeout_s)
    print(f"{args.address} {args.service or '(server)'}: {status}", flush=True)
    return 0 if serving else 1
