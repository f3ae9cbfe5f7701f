"""``m3t up`` / ``status`` / ``down``: real servers on free loopback ports, nothing bound beyond 127.0.0.1, nothing
left behind; a busy port stops ``up`` before anything starts; a failing service rolls back what ``up`` started.

The end-to-end test starts the real Prefect server, the served deployments and the MLflow UI once (~20-30 s on
two cores) in a temporary run directory over a temporary MLflow store; the others start no server.
"""
from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import time
import urllib.request
from dataclasses import replace
from pathlib import Path

import pytest
import yaml

from cli.main import main
from cli.processes import Running, Service, ServiceError, is_running, processes, start, stop
from cli.services import ServicesConfig, down, plan, port_free, read_state, up

ROOT = Path(__file__).resolve().parents[2]
PROC = Path("/proc/self").is_dir()


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def write_params(folder: Path) -> Path:
    """The repository's params.yaml with its MLflow store moved into ``folder``."""
    data = yaml.safe_load((ROOT / "params.yaml").read_text())
    data["experiment"].update(tracking_uri=f"sqlite:///{folder / 'mlflow.db'}", artifact_dir=str(folder / "mlruns"))
    path = folder / "params.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def group_members(pgids: set[int]) -> set[int]:
    """Live processes whose process group is one of ``pgids``, read straight from /proc (not via the module)."""
    found = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                fields = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            except (OSError, IndexError):
                continue
            if int(fields[2]) in pgids and fields[0] not in "ZX":
                found.add(int(entry.name))
    return found


def listening(pids: set[int]) -> list[tuple[str, int]]:
    """(address, port) of every listening TCP socket the processes hold.

    /proc/net/tcp and tcp6 rows as the kernel documents them (Documentation/networking/proc_net_tcp.rst), e.g.
    ``0: 0100007F:10F6 00000000:0000 0A 00000000:00000000 00:00000000 00000000  0  0 1066 1 ...``: local address
    as little-endian hex ``IP:PORT``, state ``0A`` = LISTEN, the socket inode in the tenth column.
    """
    inodes = set()
    for pid in pids:
        try:
            for fd in Path(f"/proc/{pid}/fd").iterdir():
                target = os.readlink(fd)
                if target.startswith("socket:["):
                    inodes.add(target[8:-1])
        except OSError:
            continue
    out = []
    for table, v6 in (("/proc/net/tcp", False), ("/proc/net/tcp6", True)):
        for line in Path(table).read_text().splitlines()[1:] if Path(table).exists() else []:
            cols = line.split()
            if cols[3] == "0A" and cols[9] in inodes:
                address, port = cols[1].split(":")
                raw = bytes.fromhex(address)
                words = b"".join(raw[i:i + 4][::-1] for i in range(0, len(raw), 4))  # host-order 32-bit words
                out.append((socket.inet_ntop(socket.AF_INET6 if v6 else socket.AF_INET, words), int(port, 16)))
    return out


def post(url: str, body: dict) -> list:
    request = urllib.request.Request(url, json.dumps(body).encode(), {"Content-Type": "application/json"})
    with urllib.request.urlopen(request, timeout=10) as response:
        return json.loads(response.read())


def cli(*args: str) -> subprocess.CompletedProcess:
    """``m3t ...`` in its own process, as a user runs it: what ``up`` starts must outlive it."""
    env = {k: v for k, v in os.environ.items() if k not in ("PREFECT_HOME", "PREFECT_API_URL")}
    return subprocess.run([sys.executable, "-m", "cli.main", *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def services(tmp_path_factory):
    """One ``m3t up`` for the module (a run in the temporary store first, to find in the UI); ``down`` at the end
    whatever happens."""
    from m3t.config import load_params
    from m3t.experiment import start_run

    folder = tmp_path_factory.mktemp("services")
    params = write_params(folder)
    (folder / "note.txt").write_text("logged before the UI started")
    with start_run(load_params(params).experiment, "probe", root=ROOT) as run:
        run.log_artifact(folder / "note.txt")
        run_id = run.run_id
    run_dir, ports = folder / "run", (free_port(), free_port())
    args = ("--params", str(params), "up", "--run-dir", str(run_dir), "--prefect-port", str(ports[0]),
            "--mlflow-port", str(ports[1]))
    t0 = time.monotonic()
    result = cli(*args)
    seconds = time.monotonic() - t0
    try:
        yield {"result": result, "seconds": seconds, "args": args, "run_dir": run_dir, "ports": ports,
               "run_id": run_id}
    finally:
        down(run_dir, timeout_s=5, say=lambda _: None)


def test_up_status_down_leaves_nothing_behind(services):
    result, run_dir = services["result"], services["run_dir"]
    assert result.returncode == 0, result.stdout + result.stderr
    print(f"m3t up: {services['seconds']:.1f} s")
    records = {r.name: r for r in read_state(run_dir)}
    assert set(records) == {"prefect", "mlflow", "deployments"}
    assert all(is_running(r) and r.pgid == r.pid for r in records.values())  # each the leader of its own group
    assert all(Path(r.log).parent == run_dir for r in records.values())
    assert (run_dir / "prefect" / "prefect.db").exists()  # PREFECT_HOME in the run directory, not ~/.prefect

    status = cli("status", "--run-dir", str(run_dir))
    assert status.returncode == 0, status.stdout
    rows = [line.split() for line in status.stdout.splitlines()[1:]]
    assert {row[0] for row in rows} == set(records) and all(row[2:4] == ["yes", "yes"] for row in rows)
    assert all(row[4].startswith("http://127.0.0.1:") for row in rows)

    if PROC:  # nothing listens beyond loopback, the two servers listen where recorded
        sockets = listening(set().union(*(processes(r) for r in records.values())))
        assert sockets and all(address == "127.0.0.1" for address, _ in sockets), sockets
        assert set(services["ports"]) <= {port for _, port in sockets}

    prefect = records["prefect"].url
    deployments = post(f"{prefect}/api/deployments/filter", {})
    flows = {f["id"]: f["name"] for f in post(f"{prefect}/api/flows/filter", {})}
    served = {f"{flows[d['flow_id']]}/{d['name']}" for d in deployments}
    assert {"fit-corpus/embedded", "smlm/embedded"} <= served, served
    assert all(d["status"] == "READY" for d in deployments)

    mlflow = records["mlflow"].url  # the UI reads the params.yaml store, artifacts included
    with urllib.request.urlopen(f"{mlflow}/ajax-api/2.0/mlflow/artifacts/list?run_id={services['run_id']}") as r:
        assert [f["path"] for f in json.loads(r.read())["files"]] == ["note.txt"]

    again = cli(*services["args"])
    assert again.returncode == 0 and again.stdout.count("already running") == 3, again.stdout
    assert {r.name: r.pid for r in read_state(run_dir)} == {n: r.pid for n, r in records.items()}

    pids = set().union(*(processes(r) for r in records.values()))
    assert len(pids) > len(records)  # the workers too (MLflow's uvicorn), which `down` must not leave behind
    stopped = cli("down", "--run-dir", str(run_dir))
    assert stopped.returncode == 0, stopped.stderr
    assert stopped.stdout.splitlines() == ["deployments stopped (pid %d)" % records["deployments"].pid,
                                           "mlflow stopped (pid %d)" % records["mlflow"].pid,
                                           "prefect stopped (pid %d)" % records["prefect"].pid]
    if PROC:
        assert not group_members({r.pgid for r in records.values()})
        assert not [p for p in pids if Path(f"/proc/{p}").exists()
                    and Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()[0] not in "ZX"]
    assert all(port_free("127.0.0.1", port) for port in services["ports"])
    assert read_state(run_dir) == []
    assert cli("status", "--run-dir", str(run_dir)).returncode == 1


@pytest.mark.parametrize("flag", ["--prefect-port", "--mlflow-port"])
def test_busy_port_says_which_flag_and_starts_nothing(tmp_path, capsys, flag):
    params, run_dir = write_params(tmp_path), tmp_path / "run"
    with socket.socket() as other:  # another program listening on the port
        other.bind(("127.0.0.1", 0))
        other.listen()
        busy = other.getsockname()[1]
        ports = {"--prefect-port": str(free_port()), "--mlflow-port": str(free_port()), flag: str(busy)}
        code = main(["up", "--params", str(params), "--run-dir", str(run_dir),
                     *[x for kv in ports.items() for x in kv]])
    assert code == 1
    assert f"port {busy} is in use (by another program): pass {flag} N" in capsys.readouterr().err
    assert not run_dir.exists()  # no log, no record, no process


def test_plan_binds_loopback_unless_told_and_keeps_prefect_home_in_the_run_dir(tmp_path, monkeypatch):
    monkeypatch.delenv("PREFECT_HOME", raising=False)
    cfg = ServicesConfig(run_dir=tmp_path / "run", params=write_params(tmp_path))
    services = {s.name: s for s in plan(cfg)}
    assert set(services) == {"prefect", "mlflow", "deployments"}
    for name in ("prefect", "mlflow"):
        command = services[name].command
        assert command[command.index("--host") + 1] == "127.0.0.1"
    mlflow = services["mlflow"].command
    assert mlflow[mlflow.index("--backend-store-uri") + 1] == f"sqlite:///{tmp_path / 'mlflow.db'}"
    assert services["mlflow"].env["MLFLOW_SERVER_ENABLE_JOB_EXECUTION"] == "false"
    assert all(s.env["PREFECT_HOME"] == str(tmp_path / "run" / "prefect") for s in services.values())
    assert services["deployments"].env["PREFECT_API_URL"] == "http://127.0.0.1:4200/api"
    wide = {s.name: s for s in plan(replace(cfg, host="0.0.0.0", serve=False))}
    assert set(wide) == {"prefect", "mlflow"} and "0.0.0.0" in wide["prefect"].command
    assert wide["prefect"].url == "http://127.0.0.1:4200"  # where this machine reaches it
    monkeypatch.setenv("PREFECT_HOME", str(tmp_path / "mine"))
    assert plan(cfg)[0].env["PREFECT_HOME"] == str(tmp_path / "mine")  # the user's own home wins


def sleeper(name: str, script: str, port: int | None = None) -> Service:
    return Service(name, (sys.executable, "-c", script), dict(os.environ), "", "", port)


@pytest.mark.skipif(not PROC, reason="reads /proc")
def test_stop_kills_a_group_that_ignores_sigterm_and_a_child_that_left_it(tmp_path):
    """SIGKILL after the timeout, and a descendant in a session of its own (setsid) goes too."""
    script = ("import signal, subprocess, sys, time; signal.signal(signal.SIGTERM, signal.SIG_IGN); "
              "subprocess.Popen([sys.executable, '-c', 'import time; time.sleep(600)'], start_new_session=True); "
              "subprocess.Popen([sys.executable, '-c', 'import signal, time; "
              "signal.signal(signal.SIGTERM, signal.SIG_IGN); time.sleep(600)']); time.sleep(600)")
    record, _ = start(sleeper("stubborn", script), tmp_path)
    deadline = time.monotonic() + 20
    while len(processes(record)) < 3 and time.monotonic() < deadline:
        time.sleep(0.1)
    pids = processes(record)
    assert len(pids) == 3 and len(group_members({record.pgid})) == 2  # one child left the group
    t0 = time.monotonic()
    assert stop(record, timeout_s=0.5)
    assert time.monotonic() - t0 >= 0.5  # SIGTERM was ignored: it took the SIGKILL
    assert not group_members({record.pgid}) and not processes(replace(record, proc_start=None))
    assert not stop(record)  # nothing left: says so


def test_a_reused_pid_is_never_signalled():
    me = os.getpid()
    stale = Running("prefect", me, os.getpgid(me), 1, "", "", "", (), 0.0, proc_start=1)  # not our start time
    if PROC:
        assert not is_running(stale) and not stop(stale, timeout_s=0.1)
    assert os.getpid() == me  # still here


def test_a_service_that_dies_rolls_back_what_up_started(tmp_path, monkeypatch):
    """The second service exits at once: ``up`` stops the first, forgets both and shows the failing log."""
    port = free_port()
    web = Service("prefect", (sys.executable, "-m", "http.server", "--bind", "127.0.0.1", str(port)),
                  dict(os.environ), f"http://127.0.0.1:{port}", f"http://127.0.0.1:{port}/", port, "--prefect-port")
    broken = sleeper("mlflow", "import sys; print('no such store: sqlite:///nowhere.db'); sys.exit(3)")
    monkeypatch.setattr("cli.services.plan", lambda cfg: [web, broken])
    cfg = ServicesConfig(run_dir=tmp_path / "run", start_timeout_s=30)
    with pytest.raises(ServiceError, match=r"mlflow exited \(code 3\)(.|\n)*no such store"):
        up(cfg, say=lambda _: None)
    assert read_state(cfg.run_dir) == []
    assert port_free("127.0.0.1", port)  # the web server was stopped


def test_a_second_up_on_the_same_run_directory_says_the_first_is_starting(tmp_path, capsys):
    """Two ``m3t up`` at once on one run directory: the second stops at once, naming the first, and starts
    nothing; once the first is gone (even killed), ``up`` runs again."""
    params, run_dir = write_params(tmp_path), tmp_path / "run"
    lock = tmp_path / "run.up.lock"
    holder = subprocess.Popen([sys.executable, "-c", (  # noqa: S603 - fixed argv
        "import sys, time; from m3t.atomic import run_lock\n"
        f"with run_lock({str(lock)!r}, 'm3t up'):\n    print('held', flush=True); time.sleep(60)")],
        stdout=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        assert holder.stdout.readline().strip() == "held"
        ports = ["--prefect-port", str(free_port()), "--mlflow-port", str(free_port())]
        start = time.monotonic()
        assert main(["up", "--params", str(params), "--run-dir", str(run_dir), *ports]) == 1
        assert time.monotonic() - start < 5.0  # refused at once, not after a start timeout
        assert f"another `m3t up` (pid {holder.pid}) is starting the services of {run_dir}" in capsys.readouterr().err
        assert not run_dir.exists()  # no log, no record, no process
    finally:
        holder.kill()
        holder.wait()
    with socket.socket() as other:  # the lock died with its holder: the next `up` gets past it (to the port check)
        other.bind(("127.0.0.1", 0))
        other.listen()
        busy = str(other.getsockname()[1])
        assert main(["up", "--params", str(params), "--run-dir", str(run_dir), "--prefect-port", busy,
                     "--mlflow-port", str(free_port())]) == 1
    assert f"port {busy} is in use" in capsys.readouterr().err
