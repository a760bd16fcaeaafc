"""docker-compose.yml, checked without a Docker engine.

1. ``docker-compose config`` (Debian's docker-compose v1, which ``make bootstrap``
   installs) validates the file and lists the expected services.
2. ``sortie health``, the health check of every service, says SERVING only when so.
3. The same topology runs as local processes: docker-compose itself interpolates
   the file with the compose hostnames replaced by 127.0.0.1 and free ports; each
   service's entrypoint (the Dockerfile's ``sortie`` unless it has its own),
   command and environment run as a subprocess, with the container paths of its
   volumes (/dem, /deploy, /recordings) mapped to the host paths they mount;
   services start in dependency order, each waited for with its own compose
   health check command. The server must serve, the bots join, both terrain
   replicas answer the server, the recording grow; then SIGTERM in reverse order:
   each exits 0 within its stop_grace_period and the recording is whole. Last,
   the replay service serves that recording from the "volume".
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.request
from pathlib import Path

import pytest
import yaml

from server.process import ServiceProcess, free_port, sortie_command

REPO = Path(__file__).resolve().parents[1]
COMPOSE_FILE = REPO / "docker-compose.yml"
SERVICES = {"terrain", "terrain2", "server", "bots", "dis", "tacview", "render", "replay"}
CLIENTS = {"bots", "dis", "tacview", "render"}  # no health check: they serve no gRPC
RENDER_FRAMES = 3
EXERCISE_S = 4.0  # wall seconds the exercise runs with every service up
BOTS = 2
HEALTH_POLL_S = 1.0


def _compose() -> str:
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.fail("docker-compose is not installed: `make bootstrap` installs it (Debian package docker-compose; "
                    "no Docker engine is needed to validate docker-compose.yml)")
    return exe


def _clean_environ() -> dict:
    """This process's environment without Sortie's configuration (SORTIE_*) or the compose
    file's variables, so neither the developer's shell nor a .env changes the result."""
    names = set(re.findall(r"\$\{(\w+)", COMPOSE_FILE.read_text()))
    return {k: v for k, v in os.environ.items() if not k.startswith("SORTIE_") and k not in names}


def _config(variables: dict | None = None, *args: str) -> subprocess.CompletedProcess:
    env = {**_clean_environ(), **(variables or {})}
    return subprocess.run([_compose(), "--project-directory", str(REPO), "-f", str(COMPOSE_FILE),
                           "--profile", "replay", "config", *args],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=120)


def _seconds(duration: str) -> float:
    """A compose duration ("30s", "1m30s", "500ms") in seconds."""
    units = {"h": 3600.0, "m": 60.0, "s": 1.0, "ms": 1e-3, "us": 1e-6}
    parts = re.findall(r"(\d+(?:\.\d+)?)(ms|us|h|m|s)", duration)
    assert parts and "".join(n + u for n, u in parts) == duration, f"not a compose duration: {duration!r}"
    return sum(float(n) * units[u] for n, u in parts)


def test_compose_file_is_valid_and_complete():
    r = _config()
    assert r.returncode == 0, r.stderr
    assert "WARNING" not in r.stderr, r.stderr  # e.g. a variable without a default
    services = _config(None, "--services")
    assert set(services.stdout.split()) == SERVICES, services.stdout
    spec = yaml.safe_load(r.stdout)
    assert "recordings" in spec["volumes"]
    for name, s in spec["services"].items():
        assert s["stop_signal"] == "SIGTERM" and _seconds(s["stop_grace_period"]) >= 10, name
        assert s.get("init") is True, name
        test = s["healthcheck"]["test"]
        if name in CLIENTS:
            assert test == ["NONE"], name
        else:
            assert test[:3] == ["CMD", "sortie", "health"], name
        for dep, how in s.get("depends_on", {}).items():
            assert how == {"condition": "service_healthy"}, (name, dep)
    assert spec["services"]["server"]["depends_on"].keys() == {"terrain", "terrain2"}
    assert {"source": "recordings", "target": "/recordings", "type": "volume"} in spec["services"]["server"]["volumes"]


def test_sortie_health_exits_0_only_when_serving(hgt_alps):
    def health(*argv):
        r = subprocess.run([*sortie_command(), "health", *argv], capture_output=True, text=True, timeout=60)
        return r.returncode, r.stdout.strip()

    with ServiceProcess(["terrain", "serve", "--dem", str(hgt_alps)]) as terrain:
        code, out = health(terrain.address, "--service", "sortie.v1.TerrainService")
        assert code == 0 and out.endswith("sortie.v1.TerrainService: SERVING"), out
        code, out = health(terrain.address, "--service", "sortie.v1.NoSuchService")
        assert code == 1 and "NOT_FOUND" in out, out
    code, out = health(terrain.address, "--timeout-s", "2")  # stopped: nothing listens there
    assert code == 1 and "UNAVAILABLE" in out, out


# --- the topology as local processes ----------------------------------------------------------------

def _dockerfile_entrypoint() -> list[str]:
    m = re.search(r"^ENTRYPOINT\s+(\[.*\])\s*$", (REPO / "Dockerfile").read_text(), re.M)
    assert m, "the Dockerfile has no exec-form ENTRYPOINT"
    return json.loads(m[1])


def _local_argv(argv: list[str]) -> list[str]:
    """The image's ``sortie`` is this checkout's."""
    return [*sortie_command(), *argv[1:]] if argv and argv[0] == "sortie" else list(argv)


class Mounts:
    """Container paths of a service's volumes -> the host paths they mount (a named
    volume -> a folder of its own under ``volume_root``)."""

    def __init__(self, volumes: list, volume_root: Path):
        self.paths = {}
        for v in volumes:
            source = v["source"]
            if v["type"] == "volume":
                source = volume_root / source
                source.mkdir(parents=True, exist_ok=True)
            self.paths[v["target"]] = str(source)

    def map(self, text: str) -> str:
        for target in sorted(self.paths, key=len, reverse=True):
            text = re.sub(r"(?<!\S)" + re.escape(target) + r"(?=/|\s|$)", lambda _: self.paths[target], text)
        return text


class LocalService:
    """One compose service run as a process of this machine."""

    def __init__(self, name: str, spec: dict, entrypoint: list[str], base_env: dict, tmp: Path):
        self.name = name
        self.spec = spec
        mounts = Mounts(spec.get("volumes", []), tmp / "volumes")
        self.argv = _local_argv([mounts.map(a) for a in [*spec.get("entrypoint", entrypoint), *spec["command"]]])
        self.env = {**base_env, **{k: mounts.map(str(v)) for k, v in spec.get("environment", {}).items()}}
        test = spec.get("healthcheck", {}).get("test", ["NONE"])
        self.health = None if test == ["NONE"] else _local_argv(test[1:])
        self.grace_s = _seconds(spec["stop_grace_period"])
        self.log = tmp / f"{name}.log"
        self.proc: subprocess.Popen | None = None

    def start(self) -> LocalService:
        with open(self.log, "w") as log:
            self.proc = subprocess.Popen(self.argv, env=self.env, stdout=log, stderr=subprocess.STDOUT)
        return self

    def output(self) -> str:
        return self.log.read_text(errors="replace")

    def wait_healthy(self, timeout_s: float = 120.0) -> float:
        """Run the service's health check command until it exits 0; seconds it took."""
        t0 = time.monotonic()
        while True:
            assert self.proc.poll() is None, f"{self.name} exited ({self.proc.returncode}):\n{self.output()}"
            r = subprocess.run(self.health, env=self.env, capture_output=True, text=True, timeout=60)
            if r.returncode == 0:
                return time.monotonic() - t0
            assert time.monotonic() - t0 < timeout_s, f"{self.name} not healthy: {r.stdout}{r.stderr}"
            time.sleep(HEALTH_POLL_S)

    def stop(self) -> tuple[int | None, float]:
        """SIGTERM, as `docker-compose stop` sends it; (exit code or None if it outlived its
        grace period and was killed, seconds it took)."""
        if self.proc.poll() is not None:
            return self.proc.returncode, 0.0
        t0 = time.monotonic()
        self.proc.send_signal(signal.SIGTERM)
        try:
            return self.proc.wait(self.grace_s), time.monotonic() - t0
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait()
            return None, time.monotonic() - t0


def _start_order(services: dict) -> list[str]:
    """Service names, each after what it depends on."""
    order: list[str] = []

    def visit(name, path=()):
        assert name not in path, f"dependency cycle {path + (name,)}"
        for dep in services[name].get("depends_on", {}):
            visit(dep, (*path, name))
        if name not in order:
            order.append(name)

    for name in sorted(services):
        visit(name)
    return order


def _metric(port: int, pattern: str) -> float:
    """Sum of the samples of a Prometheus page whose line matches ``pattern``."""
    text = urllib.request.urlopen(f"http://127.0.0.1:{port}/metrics", timeout=10).read().decode()
    return sum(float(line.rsplit(" ", 1)[1]) for line in text.splitlines()
               if not line.startswith("#") and re.match(pattern, line))


class EventLog:
    """World events seen by a gateway session of the server, collected in a thread."""

    def __init__(self, address: str):
        from client.sim_client import SimClient

        self.client = SimClient(address)
        self.client.join("deployment-test", "gateway")
        self.events: list = []
        stream = self.client.events()
        self._thread = threading.Thread(target=self._collect, args=(stream,), daemon=True)
        self._thread.start()

    def _collect(self, stream) -> None:
        from client.sim_client import StreamAborted

        try:
            self.events.extend(stream)
        except StreamAborted:  # this session left (the server may end the stream before the channel closes)
            pass

    def wait_for(self, predicate, timeout_s: float) -> bool:
        deadline = time.monotonic() + timeout_s
        while not predicate(self.events) and time.monotonic() < deadline:
            time.sleep(0.1)
        return predicate(self.events)

    def close(self) -> None:
        self.client.leave()
        self.client.close()
        self._thread.join(10.0)


def _bot_joins(events) -> int:
    return sum(1 for e in events if e.kind == "join" and json.loads(e.detail_json or "{}").get("role") == "ROLE_BOT")


def test_compose_topology_runs_as_local_processes(tmp_path, dem_dir):
    t_test = time.monotonic()
    ports = {k: free_port() for k in ("terrain", "terrain2", "terrain_metrics", "terrain2_metrics", "server",
                                      "server_metrics", "replay", "tacview", "dis")}
    server = f"127.0.0.1:{ports['server']}"
    variables = {
        "SORTIE_LISTEN_HOST": "127.0.0.1",
        "SORTIE_DEM_DIR": str(dem_dir),
        "TERRAIN_PORT": str(ports["terrain"]), "TERRAIN_METRICS_PORT": str(ports["terrain_metrics"]),
        "TERRAIN2_PORT": str(ports["terrain2"]), "TERRAIN2_METRICS_PORT": str(ports["terrain2_metrics"]),
        "SORTIE_TERRAIN": f"127.0.0.1:{ports['terrain']},127.0.0.1:{ports['terrain2']}",
        "SERVER_PORT": str(ports["server"]), "SERVER_METRICS_PORT": str(ports["server_metrics"]),
        "SERVER_AIRCRAFT_WORKERS": "1",  # the worker process opens the replicas too
        "SORTIE_SERVER": server, "DIS_SERVER": server, "DIS_PORT": str(ports["dis"]),
        "TACVIEW_PORT": str(ports["tacview"]), "REPLAY_PORT": str(ports["replay"]),
        "BOT_COUNT": str(BOTS), "RENDER_FRAMES": str(RENDER_FRAMES), "RENDER_SIZE": "320x180",
        "RENDER_FPS": "4",
    }
    r = _config(variables)
    assert r.returncode == 0, r.stderr
    specs = yaml.safe_load(r.stdout)["services"]
    base_env = {**_clean_environ(), "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}"}
    entrypoint = _dockerfile_entrypoint()
    assert entrypoint == ["sortie"]
    exercise = [n for n in _start_order(specs) if "profiles" not in specs[n]]
    services = {n: LocalService(n, specs[n], entrypoint, base_env, tmp_path) for n in (*exercise, "replay")}
    recordings = tmp_path / "volumes" / "recordings"
    started: list[LocalService] = []
    timings = {}
    events = None
    try:
        for name in exercise:
            svc = services[name].start()
            started.append(svc)
            if svc.health:
                timings[f"{name} healthy"] = round(svc.wait_healthy(), 1)
            if name == "server":  # watch the joins from before the bots start
                events = EventLog(server)
        assert events.wait_for(lambda ev: _bot_joins(ev) >= BOTS, 60.0), \
            f"bots did not join: {[e.kind for e in events.events]}\n{services['bots'].output()}"
        time.sleep(EXERCISE_S)
        assert _metric(ports["server_metrics"], r"sortie_sessions ") >= BOTS + 1
        replica_calls = [_metric(ports[m], r"sortie_terrain_calls_total") for m in ("terrain_metrics",
                                                                                       "terrain2_metrics")]
        assert min(replica_calls) > 0, f"terrain calls per replica {replica_calls}: both must serve the server"
        files = sorted(recordings.glob("*.sortie"))
        assert len(files) == 1 and files[0].stat().st_size > 0, files
        events.close()
        events = None

        services["render"].proc.wait(timeout=120)  # it exits by itself after its frames
        stops = {}
        for svc in reversed(started):
            stops[svc.name] = svc.stop()
        timings.update({f"{n} stopped": round(s, 2) for n, (_, s) in stops.items()})
        for svc in started:
            code, seconds = stops[svc.name]
            assert code == 0, f"{svc.name}: exit {code} after SIGTERM ({seconds:.1f} s, grace {svc.grace_s} s):\n" \
                              f"{svc.output()}"
        out = services["bots"].output()
        assert out.count("commands accepted") == BOTS, out
        frames = sorted((tmp_path / "volumes" / "frames").glob("frame_*.png"))
        assert len(frames) == RENDER_FRAMES, services["render"].output()
        check = subprocess.run([*sortie_command(), "recording", "check", str(files[0])],
                               capture_output=True, text=True, timeout=120)
        assert check.returncode == 0 and "footer yes" in check.stdout, check.stdout + check.stderr

        # Debrief: the replay service serves the newest recording of the volume.
        replay = services["replay"].start()
        started.append(replay)
        timings["replay healthy"] = round(replay.wait_healthy(), 1)
        from client.sim_client import SimClient

        with SimClient(f"127.0.0.1:{ports['replay']}") as obs:
            obs.join("debrief", "gateway")
            picture = obs.watch()
            assert picture.wait_for(lambda p: len(p) >= 5, 30.0), f"replay shows {len(picture)} entities"
            obs.leave()
        assert files[0].name in replay.output()
        code, seconds = replay.stop()
        assert code == 0, f"replay: exit {code} after SIGTERM ({seconds:.1f} s):\n{replay.output()}"
    finally:
        if events is not None:
            events.close()
        for svc in reversed(started):
            if svc.proc.poll() is None:
                svc.proc.kill()
                svc.proc.wait()
    print(f"\ncompose topology as processes in {time.monotonic() - t_test:.1f} s: {timings}")
