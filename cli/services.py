"""The platform's background services: the Prefect server, the served deployments and the MLflow UI.

    m3t up       start them (127.0.0.1 unless ``--host`` says otherwise), each in its own process group, logs and
                 ``services.json`` (name, pid, pgid, port, url, log, command) in the run directory (``.m3t/run``)
    m3t status   their URLs and health; non-zero exit when one is down
    m3t down     stop exactly the processes ``up`` started: every process of each group and the leader's
                 descendants, SIGTERM then SIGKILL after a timeout, and check that none is left

This module composes them (commands, ports, the state file, health checks, start order and rollback); starting
and stopping one process group is :mod:`cli.processes`.
"""
from __future__ import annotations

import dataclasses
import ipaddress
import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path

from cli.processes import Running, Service, ServiceError, is_running, start, stop
from m3t.atomic import run_lock, write_json
from m3t.experiment import TELEMETRY_OFF, absolute_uri

ORDER = ("prefect", "mlflow", "deployments")  # start order; ``down`` stops in reverse (the runner needs the API)
STATE_FILE = "services.json"
LOG_TAIL_LINES = 40


@dataclass(frozen=True)
class ServicesConfig:
    run_dir: Path = Path(".m3t/run")  # services.json, the logs and (unless PREFECT_HOME is set) Prefect's home
    params: Path = Path("params.yaml")  # MLflow store (``experiment`` section); the deployments' params_path
    host: str = "127.0.0.1"  # anything else makes both servers reachable from other machines, unauthenticated
    prefect_port: int = 4200
    mlflow_port: int = 5000
    serve: bool = True  # also serve the deployments (python -m flows.deploy) against the Prefect server
    start_timeout_s: float = 120.0  # per service, until its health check answers
    root: Path = Path(".")  # working directory of the services; relative store paths resolve against it


@dataclass(frozen=True)
class Health:
    name: str
    pid: int
    alive: bool
    healthy: bool
    url: str
    log: str
    detail: str = ""


# --- state ---------------------------------------------------------------------------------------------------
def read_state(run_dir: Path) -> list[Running]:
    path = Path(run_dir) / STATE_FILE
    if not path.exists():
        return []
    try:
        rows = json.loads(path.read_text())["services"]
        return [Running(**{**row, "command": tuple(row["command"])}) for row in rows]
    except (ValueError, KeyError, TypeError) as err:
        raise ServiceError(f"{path}: not a services record ({err}); stop the processes it names by hand, "
                           "then delete it") from err


def write_state(run_dir: Path, records: list[Running]) -> None:
    records = sorted(records, key=lambda r: ORDER.index(r.name) if r.name in ORDER else len(ORDER))
    write_json(Path(run_dir) / STATE_FILE, {"services": [dataclasses.asdict(r) for r in records]})


# --- health --------------------------------------------------------------------------------------------------
def _http(url: str, body: dict | None = None, timeout: float = 2.0) -> bytes | None:
    """The response body of a 200 answer, else None."""
    if not url.startswith(("http://", "https://")):  # services.json is a file on disk: never follow file:// there
        return None
    data = None if body is None else json.dumps(body).encode()
    request = urllib.request.Request(url, data=data, headers={"Content-Type": "application/json"})  # noqa: S310
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:  # noqa: S310 - our own servers
            return response.read() if response.status == 200 else None
    except (OSError, ValueError):
        return None


def _served(record: Running) -> tuple[bool, str]:
    """The runner is healthy once the Prefect API shows deployments it has polled since it started."""
    answer = _http(record.health_url, {"limit": 200})
    if answer is None:
        return False, "the Prefect API does not answer"
    polled = [d for d in json.loads(answer) if d.get("status") == "READY" and d.get("last_polled")
              and datetime.fromisoformat(d["last_polled"]).timestamp() >= record.started_at - 1.0]
    return bool(polled), f"{len(polled)} deployments polled by this runner"


def check(record: Running) -> Health:
    alive = is_running(record)
    healthy, detail = False, "not running"
    if alive and record.name == "deployments":
        healthy, detail = _served(record)
    elif alive:
        healthy = _http(record.health_url) is not None
        detail = "" if healthy else f"no HTTP 200 from {record.health_url}"
    return Health(record.name, record.pid, alive, healthy, record.url, record.log, detail)


def status(run_dir: Path) -> list[Health]:
    return [check(r) for r in read_state(run_dir)]


def log_tail(path: str | Path, lines: int = LOG_TAIL_LINES) -> str:
    try:
        return "\n".join(Path(path).read_text(errors="replace").splitlines()[-lines:])
    except OSError:
        return "(no log)"


# --- up / down -----------------------------------------------------------------------------------------------
def is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return host == "localhost"


def port_free(host: str, port: int) -> bool:
    """Whether a server could listen on ``host:port`` now (SO_REUSEADDR as servers set it, so TIME_WAIT is free)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
            return True
        except OSError:
            return False


def plan(cfg: ServicesConfig) -> list[Service]:
    """The services of ``cfg`` in start order, with their commands and environments."""
    from m3t.config import load_params

    experiment = load_params(cfg.params).experiment
    root = Path(cfg.root).resolve()
    run_dir = (root / cfg.run_dir).resolve()
    local = "127.0.0.1" if cfg.host in ("0.0.0.0", "::") else cfg.host  # noqa: S104 - where clients connect, no bind
    local = f"[{local}]" if ":" in local else local
    prefect, mlflow = f"http://{local}:{cfg.prefect_port}", f"http://{local}:{cfg.mlflow_port}"
    base = {**TELEMETRY_OFF, **os.environ, "PYTHONUNBUFFERED": "1", "PREFECT_API_URL": f"{prefect}/api",
            "PREFECT_SERVER_API_HOST": cfg.host, "PREFECT_SERVER_API_PORT": str(cfg.prefect_port)}
    base.setdefault("PREFECT_HOME", str(run_dir / "prefect"))  # keep tests and fresh clones off ~/.prefect
    artifacts = (root / experiment.artifact_dir).resolve()
    python = sys.executable
    out = [
        Service("prefect", (python, "-m", "prefect", "server", "start", "--host", cfg.host, "--port",
                            str(cfg.prefect_port)), base, prefect, f"{prefect}/api/health", cfg.prefect_port,
                "--prefect-port"),
        Service("mlflow", (python, "-m", "mlflow", "server", "--host", cfg.host, "--port", str(cfg.mlflow_port),
                           "--workers", "1", "--backend-store-uri", absolute_uri(experiment.tracking_uri, root),
                           "--default-artifact-root", artifacts.as_uri(), "--artifacts-destination",
                           artifacts.as_uri()),
                {**base, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"}, mlflow, f"{mlflow}/health",
                cfg.mlflow_port, "--mlflow-port"),
    ]
    if cfg.serve:
        params = str(Path(cfg.params).resolve())
        out.append(Service("deployments", (python, "-m", "flows.deploy", "--params", params), base,
                           f"{prefect}/deployments", f"{prefect}/api/deployments/filter", requires="prefect"))
    return out


def _suggest(host: str, port: int, taken: set[int]) -> str:
    for candidate in range(port + 1, port + 100):
        if candidate not in taken and port_free(host, candidate):
            return f" (for instance {candidate}, free now)"
    return ""


def _check_ports(cfg: ServicesConfig, services: list[Service]) -> None:
    ports = [s.port for s in services if s.port is not None]
    if len(set(ports)) < len(ports):
        raise ServiceError(f"--prefect-port and --mlflow-port are both {ports[0]}: give them different ports")
    for service in services:
        if service.port is not None and not port_free(cfg.host, service.port):
            raise ServiceError(f"port {service.port} is in use (by another program): pass {service.port_flag} N"
                               + _suggest(cfg.host, service.port, set(ports)))


def wait_healthy(record: Running, proc: subprocess.Popen | None, timeout_s: float) -> float:
    """Seconds from its start until ``record`` answered its health check; ServiceError (with its log's tail)
    if it exits or does not answer within ``timeout_s`` of this call."""
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        code = proc.poll() if proc is not None else (None if is_running(record) else "?")
        if code is not None:
            raise ServiceError(f"{record.name} exited (code {code}) before answering; the end of {record.log}:\n"
                               f"{log_tail(record.log)}")
        if check(record).healthy:
            return time.time() - record.started_at
        time.sleep(0.5)
    raise ServiceError(f"{record.name} did not answer at {record.health_url} within {timeout_s:.0f} s (raise "
                       f"--timeout if the machine is busy); the end of {record.log}:\n{log_tail(record.log)}")


@contextmanager
def _starting(run_dir: Path) -> Iterator[None]:
    """Hold ``<run_dir>.up.lock`` while services start, so that a second ``m3t up`` on the same run directory stops
    at once, naming the first, instead of starting a second set. The lock is the kernel's (``flock``): a killed
    ``up`` never leaves the next one locked out."""
    lock = run_dir.with_name(run_dir.name + ".up.lock")
    held = ExitStack()
    try:
        held.enter_context(run_lock(lock, "m3t up"))
    except RuntimeError:
        try:
            pid = lock.read_text(encoding="utf-8").strip() or "unknown"
        except OSError:
            pid = "unknown"
        raise ServiceError(f"another `m3t up` (pid {pid}) is starting the services of {run_dir}; wait for it to "
                           "finish, then `m3t status`") from None
    with held:
        yield


def up(cfg: ServicesConfig, say: Callable[[str], None] = print) -> list[Running]:
    """Start what is not running yet (ports checked before anything starts), wait until every service is
    healthy; if one fails, stop what this call started and raise ServiceError. One ``up`` at a time per run
    directory (:func:`_starting`)."""
    root = Path(cfg.root).resolve()
    run_dir = (root / cfg.run_dir).resolve()
    with _starting(run_dir):
        return _start_missing(cfg, root, run_dir, say)


def _start_missing(cfg: ServicesConfig, root: Path, run_dir: Path, say: Callable[[str], None]) -> list[Running]:
    running = {r.name: r for r in read_state(run_dir) if is_running(r)}
    wanted = {"prefect": cfg.prefect_port, "mlflow": cfg.mlflow_port}
    for name, record in running.items():
        moved = name in wanted and record.port != wanted[name]
        say(f"{name} is already running at {record.url} (pid {record.pid})"
            + ("; `m3t down` first to move it to another port" if moved else ""))
    if "prefect" in running:  # a runner started now must talk to the server that runs
        cfg = dataclasses.replace(cfg, prefect_port=running["prefect"].port)
    services = plan(cfg)
    todo = [s for s in services if s.name not in running]
    _check_ports(cfg, todo)
    if not is_loopback(cfg.host) and todo:
        say(f"warning: --host {cfg.host} makes the Prefect and MLflow servers reachable from other machines, "
            "without authentication")
    started: list[tuple[Running, subprocess.Popen]] = []
    try:
        for service in todo:
            if service.requires in running:
                wait_healthy(running[service.requires], None, cfg.start_timeout_s)
            record, proc = start(service, run_dir, root)
            started.append((record, proc))
            running[service.name] = record
            write_state(run_dir, list(running.values()))  # at once, so `down` finds it even if `up` dies
            say(f"{service.name} started (pid {record.pid}), log {record.log}")
        for record, proc in started:
            seconds = wait_healthy(record, proc, cfg.start_timeout_s)
            say(f"{record.name} healthy at {record.url} after {seconds:.1f} s")
    except BaseException:
        for record, _ in reversed(started):
            stop(record)
            running.pop(record.name)
        write_state(run_dir, list(running.values()))
        raise
    return [running[n] for n in ORDER if n in running]


def down(run_dir: Path, timeout_s: float = 20.0, say: Callable[[str], None] = print) -> list[Running]:
    """Stop every recorded service (reverse start order) and forget them; returns the records it stopped."""
    records = read_state(run_dir)
    rank = {n: i for i, n in enumerate(ORDER)}
    stopped = []
    for record in sorted(records, key=lambda r: rank.get(r.name, -1), reverse=True):
        if stop(record, timeout_s):
            stopped.append(record)
            say(f"{record.name} stopped (pid {record.pid})")
        else:
            say(f"{record.name} was not running")
    write_state(run_dir, [])
    return stopped
