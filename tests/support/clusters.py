"""Private servers for tests and benchmarks: a PostgreSQL cluster, a local Ray cluster
and `covslam serve` processes.

`PrivatePostgres` runs Debian's PostgreSQL (``initdb`` + ``pg_ctl``) in a temporary
directory on a free port, as the ``postgres`` user when we are root (PostgreSQL
refuses to run as root). `LocalRayCluster` starts a Ray head and further nodes with
``ray start --block`` on this machine (one CPU each, a private temp dir, free ports),
each in its own process group, and tears them down by those process ids.
Both raise `Unavailable` with the reason when they cannot start.
"""

from __future__ import annotations

import contextlib
import glob
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import uuid
from collections.abc import Callable
from pathlib import Path


class Unavailable(RuntimeError):
    """The server cannot start here (the message says why)."""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_ports(count: int) -> list[int]:
    """`count` distinct free ports (held open together while they are picked)."""
    with contextlib.ExitStack() as stack:
        socks = [stack.enter_context(socket.socket()) for _ in range(count)]
        for s in socks:
            s.bind(("127.0.0.1", 0))
        return [int(s.getsockname()[1]) for s in socks]


def _pg_bin(name: str) -> str | None:
    found = shutil.which(name)
    if found:
        return found
    candidates = sorted(glob.glob(f"/usr/lib/postgresql/*/bin/{name}"))
    return candidates[-1] if candidates else None


class PrivatePostgres:
    """A PostgreSQL server of our own; `url(db)` names one of its databases."""

    def __init__(self, *, fsync: bool = True) -> None:
        self.fsync = fsync
        self.port = free_port()
        self.base = Path(tempfile.mkdtemp(prefix="covslam-pg-"))
        self.data = self.base / "data"
        self.log = self.base / "server.log"
        self._prefix: list[str] = []
        self.started = False

    def _run(self, *args: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run(
            [*self._prefix, *args],
            capture_output=True,
            text=True,
            timeout=120,
            check=False,
            cwd=self.base,
        )

    def start(self) -> PrivatePostgres:
        initdb, pg_ctl = _pg_bin("initdb"), _pg_bin("pg_ctl")
        if initdb is None or pg_ctl is None:
            raise Unavailable("no initdb/pg_ctl (apt-get install postgresql; .ci/run does)")
        if os.geteuid() == 0:
            if shutil.which("runuser") is None:
                raise Unavailable("running as root without runuser to drop to 'postgres'")
            try:
                import pwd

                user = pwd.getpwnam("postgres")
            except KeyError as exc:
                raise Unavailable("running as root and there is no 'postgres' user") from exc
            os.chown(self.base, user.pw_uid, user.pw_gid)
            self._prefix = ["runuser", "-u", "postgres", "--"]
        init = self._run(
            initdb, "-D", str(self.data), "-A", "trust", "-U", "covslam", "-E", "UTF8",
            "--locale=C", "--no-sync",
        )  # fmt: skip
        if init.returncode != 0:
            raise Unavailable(f"initdb failed: {init.stderr.strip()[-500:]}")
        options = (
            f"-p {self.port} -k {self.base} -c listen_addresses=127.0.0.1 "
            f"-c fsync={'on' if self.fsync else 'off'} -c max_connections=200"
        )
        started = self._run(pg_ctl, "-D", str(self.data), "-l", str(self.log), "-o", options,
                            "-w", "-t", "60", "start")  # fmt: skip
        if started.returncode != 0:
            log = self.log.read_text() if self.log.exists() else ""
            raise Unavailable(f"pg_ctl start failed: {started.stderr.strip()} {log[-500:]}")
        self.started = True
        return self

    def restart(self) -> None:
        """Restart the server (``pg_ctl restart -m fast``): every connection is cut."""
        pg_ctl = _pg_bin("pg_ctl")
        assert pg_ctl is not None and self.started
        done = self._run(
            pg_ctl, "-D", str(self.data), "-l", str(self.log), "-m", "fast", "-w", "restart"
        )
        if done.returncode != 0:
            raise RuntimeError(f"pg_ctl restart failed: {done.stderr.strip()}")

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://covslam@127.0.0.1:{self.port}/{database}"

    def new_database(self) -> str:
        """A fresh, empty database; its URL."""
        import psycopg

        name = f"t_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(self.url(), autocommit=True) as conn:
            conn.execute(f"CREATE DATABASE {name}")
        return self.url(name)

    def stop(self) -> None:
        pg_ctl = _pg_bin("pg_ctl")
        if self.started and pg_ctl is not None:
            self._run(pg_ctl, "-D", str(self.data), "-m", "immediate", "-w", "stop")
            self.started = False
        shutil.rmtree(self.base, ignore_errors=True)


def _stat_fields(pid: str) -> list[str] | None:
    """/proc/<pid>/stat after the command name (state, ppid, ...; start time at [19])."""
    try:
        return (Path("/proc") / pid / "stat").read_text().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return None


def _signal_live(pids: dict[int, str], sig: int) -> None:
    """`sig` to each process of `pids` (process id -> start time) that is still that one."""
    for pid, start in pids.items():
        fields = _stat_fields(str(pid))
        if fields is not None and fields[19] == start:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, sig)


def _end(pids: dict[int, str], sig: int, grace_s: float) -> None:
    """`sig` to each process of `pids`; SIGKILL to those still running after `grace_s`."""
    _signal_live(pids, sig)
    deadline = time.monotonic() + grace_s
    while time.monotonic() < deadline and any(
        (f := _stat_fields(str(pid))) is not None and f[19] == start and f[0] != "Z"
        for pid, start in pids.items()
    ):
        time.sleep(0.2)
    _signal_live(pids, signal.SIGKILL)


class LocalRayCluster:
    """A Ray head plus `nodes - 1` more nodes on this machine, `cpus` CPUs each; `env`
    adds to the nodes' environment (e.g. Ray's ``RAY_health_check_*`` settings)."""

    def __init__(self, *, nodes: int = 2, cpus: int = 1, env: dict[str, str] | None = None) -> None:
        self.nodes = nodes
        self.cpus = cpus
        self.env = env or {}
        self.base = Path(tempfile.mkdtemp(prefix="covslam-ray-"))
        self.port = free_port()
        self.address = f"127.0.0.1:{self.port}"
        self.procs: list[subprocess.Popen[bytes]] = []

    def _ray(self) -> str:
        exe = Path(sys.executable).with_name("ray")
        if not exe.exists():
            raise Unavailable("Ray is not installed (pip install -e '.[ray]')")
        return str(exe)

    def _node(self, head: bool, index: int) -> subprocess.Popen[bytes]:
        names = ["--node-manager-port", "--object-manager-port", "--dashboard-agent-listen-port",
                 "--dashboard-agent-grpc-port", "--metrics-export-port",
                 "--runtime-env-agent-port"]  # fmt: skip
        picked = [p for p in free_ports(len(names) + 1) if p != self.port][: len(names)]
        ports = [a for name, port in zip(names, picked, strict=True) for a in (name, str(port))]
        ports += ["--min-worker-port", "0", "--max-worker-port", "0"]
        if head:
            where = ["--head", "--port", str(self.port), "--include-dashboard", "false",
                     "--temp-dir", str(self.base / "tmp")]  # fmt: skip
        else:
            where = ["--address", self.address]
        log = (self.base / f"node{index}.log").open("ab")
        env = {**os.environ, "RAY_USAGE_STATS_ENABLED": "0", **self.env}
        return subprocess.Popen(
            [self._ray(), "start", "--block", "--node-ip-address", "127.0.0.1",
             "--num-cpus", str(self.cpus), "--disable-usage-stats", *where, *ports],
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=env,
        )  # fmt: skip

    def start(self, timeout_s: float = 120.0) -> LocalRayCluster:
        """Start the nodes (stopping what started if they do not come up)."""
        try:
            self.procs.append(self._node(True, 0))
            time.sleep(3.0)
            self._wait_nodes(1, timeout_s)
            for i in range(1, self.nodes):
                self.procs.append(self._node(False, i))
            self._wait_nodes(self.nodes, timeout_s)
        except BaseException:
            self.stop(keep_logs=True)
            raise
        return self

    def _wait_nodes(self, count: int, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            for p in self.procs:
                if p.poll() is not None:
                    raise Unavailable(f"ray start exited: {self.logs()[-2000:]}")
            if self.alive_nodes() >= count:
                return
            time.sleep(1.0)
        raise Unavailable(f"{count} Ray nodes not up in {timeout_s} s: {self.logs()[-2000:]}")

    def alive_nodes(self) -> int:
        """Nodes the head's GCS lists as alive (0 while it does not answer)."""
        try:
            probe = subprocess.run(
                [sys.executable, "-c",
                 "import ray, sys; ray.init(address=sys.argv[1], logging_level='ERROR');"
                 "print(sum(n['Alive'] for n in ray.nodes()))", self.address],
                capture_output=True, text=True, timeout=60, check=False,
            )  # fmt: skip
        except subprocess.TimeoutExpired:
            return 0
        lines = probe.stdout.strip().splitlines()
        return int(lines[-1]) if probe.returncode == 0 and lines else 0

    def node_pids(self, index: int) -> dict[int, str]:
        """Every process of node `index`: its ``ray start``, what that started, and the
        workers its raylet started (each of those in a session of its own); process id
        -> its start time (which tells a reused process id apart)."""
        children: dict[int, list[int]] = {}
        started: dict[int, str] = {}
        for stat in Path("/proc").glob("[0-9]*/stat"):
            fields = _stat_fields(stat.parent.name)
            if fields is None:
                continue  # the process ended meanwhile
            pid = int(stat.parent.name)
            children.setdefault(int(fields[1]), []).append(pid)
            started[pid] = fields[19]
        found: dict[int, str] = {}
        todo = [self.procs[index].pid]
        while todo:
            pid = todo.pop()
            found[pid] = started.get(pid, "")
            todo.extend(children.get(pid, []))
        return found

    def stop_node(self, index: int, *, hard: bool) -> list[int]:
        """Stop node `index` (not the head) while the others go on; the process ids it had.

        ``hard``: SIGKILL to every process of the node at once, as when its machine fails
        (the head learns of it from its health checks). Otherwise SIGTERM to each, as
        ``ray stop`` sends on that machine (the raylet leaves the cluster in order), and
        SIGKILL to what is left of them after 30 s."""
        assert index > 0, "the head stays"
        pids = self.node_pids(index)
        _end(pids, signal.SIGKILL if hard else signal.SIGTERM, grace_s=30)
        self.procs[index].wait(timeout=30)
        return sorted(pids)

    def logs(self) -> str:
        return "".join(p.read_text(errors="replace") for p in sorted(self.base.glob("node*.log")))

    def stop(self, *, keep_logs: bool = False, grace_s: float = 5.0) -> None:
        """SIGTERM to every process of every node (``ray start``, what it started, the
        workers of its raylet), SIGKILL to what still runs after `grace_s` (Ray's own
        orderly shutdown of a node takes some 20 s)."""
        pids: dict[int, str] = {}
        for index, p in enumerate(self.procs):
            if p.poll() is None:
                pids.update(self.node_pids(index))
        _end(pids, signal.SIGTERM, grace_s)
        for p in self.procs:
            with contextlib.suppress(subprocess.TimeoutExpired):
                p.wait(timeout=10)
        self.procs.clear()
        if not keep_logs:
            shutil.rmtree(self.base, ignore_errors=True)


def until_ready(
    url: str, timeout_s: float, check: Callable[[], None] | None = None, every_s: float = 0.1
) -> float | None:
    """Seconds until GET `url`/readyz answered 200, None if not within `timeout_s`;
    `check` runs before each try (it raises to give up)."""
    import httpx

    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout_s:
        if check is not None:
            check()
        try:
            if httpx.get(url + "/readyz", timeout=5.0).status_code == 200:
                return time.monotonic() - t0
        except httpx.TransportError:
            pass
        time.sleep(every_s)
    return None


class Service:
    """One `covslam serve` process group on a free loopback port (stopped by its PID)."""

    def __init__(self, log: Path, *args: str, env: dict[str, str] | None = None) -> None:
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.log = log
        full_env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning", **(env or {})}
        with log.open("ab") as out:
            self.proc = subprocess.Popen(
                [sys.executable, "-m", "api.cli", "serve", "--port", str(self.port), *args],
                env=full_env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True,
            )  # fmt: skip

    def wait_ready(self, timeout_s: float = 180.0) -> float:
        """Seconds until /readyz answered 200."""

        def alive() -> None:
            if self.proc.poll() is not None:
                raise RuntimeError(f"service exited: {self.log.read_text()[-2000:]}")

        ready = until_ready(self.url, timeout_s, alive)
        if ready is None:
            raise TimeoutError(
                f"service not ready in {timeout_s} s: {self.log.read_text()[-2000:]}"
            )
        return ready

    def stop(self) -> None:
        if self.proc.poll() is None:
            os.killpg(self.proc.pid, signal.SIGTERM)
            try:
                self.proc.wait(timeout=20)
            except subprocess.TimeoutExpired:
                os.killpg(self.proc.pid, signal.SIGKILL)
                self.proc.wait(timeout=10)
