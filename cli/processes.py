"""Process groups of the background services: start a command as the leader of a new group, find every live
process of a recorded one, stop them all.

A service is one process group because both servers fork workers (MLflow's uvicorn, the runner's flow runs): the
recorded pid alone would leave them behind. A record also keeps the leader's start time, so a pid reused by some
other program after a reboot is never signalled. POSIX only (process groups, ``/proc`` where there is one).
"""
from __future__ import annotations

import os
import signal
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path


class ServiceError(RuntimeError):
    """A service could not be started or stopped; the message says which and what to do."""


@dataclass(frozen=True)
class Service:
    """What to start: one command, run as the leader of a new process group."""

    name: str
    command: tuple[str, ...]
    env: dict[str, str]
    url: str  # what a user opens
    health_url: str
    port: int | None = None  # checked free before anything starts
    port_flag: str = ""  # the ``m3t up`` option that moves it
    requires: str | None = None  # a service that must be healthy before this one starts


@dataclass(frozen=True)
class Running:
    """A started service, as recorded in services.json."""

    name: str
    pid: int
    pgid: int
    port: int | None
    url: str
    health_url: str
    log: str
    command: tuple[str, ...]
    started_at: float  # epoch seconds
    proc_start: int | None  # the leader's start time in clock ticks (/proc), to tell a reused pid


def _proc_table() -> dict[int, tuple[int, int, str, int]] | None:
    """pid -> (ppid, pgid, state, start ticks) of every process, or None without /proc."""
    if not os.path.isdir("/proc/self"):
        return None
    table = {}
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/stat") as fh:
                    fields = fh.read().rsplit(")", 1)[1].split()  # the name in (...) may hold spaces
            except (OSError, IndexError):
                continue  # exited while we looked
            table[int(entry)] = (int(fields[1]), int(fields[2]), fields[0], int(fields[19]))
    return table


def _start_ticks(pid: int) -> int | None:
    table = _proc_table()
    return table[pid][3] if table and pid in table else None


def processes(record: Running, table: dict[int, tuple[int, int, str, int]] | None = None) -> set[int]:
    """Live (non-zombie) processes of a record: its process group and the leader's descendants."""
    table = _proc_table() if table is None else table
    if table is None:  # no /proc: the group as a whole
        try:
            os.killpg(record.pgid, 0)
            return {record.pgid}
        except (ProcessLookupError, PermissionError):
            return set()
    leader = table.get(record.pid)
    if leader and record.proc_start is not None and leader[3] != record.proc_start:
        return set()  # the pid now belongs to another program (our group cannot exist while it holds the number)
    live = {pid for pid, (_, _, state, _) in table.items() if state not in "ZX"}
    found = {pid for pid in live if table[pid][1] == record.pgid}
    frontier = [record.pid]
    while frontier:  # descendants that left the group (a child calling setsid) are still ours
        parent = frontier.pop()
        for pid in live:
            if table[pid][0] == parent and pid not in found:
                found.add(pid)
                frontier.append(pid)
    return found & live


def _signal(record: Running, pids: set[int], sig: signal.Signals) -> None:
    try:
        os.killpg(record.pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass
    for pid in pids:
        try:
            os.kill(pid, sig)
        except (ProcessLookupError, PermissionError):
            pass


def _reap(pid: int) -> None:
    """Collect the exit status when the caller started the leader itself (else it stays a zombie)."""
    try:
        os.waitpid(pid, os.WNOHANG)
    except ChildProcessError:
        pass


def stop(record: Running, timeout_s: float = 20.0) -> bool:
    """SIGTERM every process of ``record``, SIGKILL what is left after ``timeout_s``; False if none was running."""
    left = processes(record)
    if not left:
        return False
    for sig, wait in ((signal.SIGTERM, timeout_s), (signal.SIGKILL, 10.0)):
        _signal(record, left, sig)
        deadline = time.monotonic() + wait
        while left and time.monotonic() < deadline:
            time.sleep(0.1)
            _reap(record.pid)
            table = _proc_table()
            # a member reparented out of sight is still watched by its pid
            left = processes(record, table) | {pid for pid in left if _alive(pid, table)}
        if not left:
            return True
    raise ServiceError(f"{record.name}: processes {sorted(left)} survived SIGKILL; see `ps -o pid,cmd -g "
                       f"{record.pgid}`")


def _alive(pid: int, table: dict[int, tuple[int, int, str, int]] | None) -> bool:
    if table is not None:
        return pid in table and table[pid][2] not in "ZX"
    try:
        os.kill(pid, 0)
        return True
    except (ProcessLookupError, PermissionError):
        return False


def is_running(record: Running) -> bool:
    return bool(processes(record))


def start(service: Service, run_dir: Path, root: Path = Path(".")) -> tuple[Running, subprocess.Popen]:
    """Start ``service`` as the leader of a new process group, its output in ``<run_dir>/<name>.log``."""
    run_dir = Path(run_dir).resolve()
    run_dir.mkdir(parents=True, exist_ok=True)
    log = run_dir / f"{service.name}.log"
    with open(log, "wb") as fh:
        proc = subprocess.Popen(service.command, stdin=subprocess.DEVNULL, stdout=fh,  # noqa: S603 - plan()'s argv
                                stderr=subprocess.STDOUT,
                                env=service.env, cwd=root, start_new_session=True)
    record = Running(service.name, proc.pid, os.getpgid(proc.pid), service.port, service.url, service.health_url,
                     str(log), service.command, time.time(), _start_ticks(proc.pid))
    return record, proc
