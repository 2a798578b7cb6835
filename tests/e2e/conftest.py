"""A real `covslam serve` on loopback, with its SQLite store in a temporary directory."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from graph.types import FrameInput
from service.frames_io import frame_to_dict
from service.offline.datasets.indoor_sim import make_world, simulate
from tests.e2e.chromium import CHROMIUM_ARGS

REPO = Path(__file__).resolve().parents[2]
CHROMIUM = Path(os.environ.get("COVSLAM_CHROMIUM", "/usr/bin/chromium"))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Server:
    """One `covslam serve` process group (uvicorn + its workers)."""

    def __init__(
        self,
        data_dir: Path,
        *,
        workers: int = 2,
        env: dict[str, str] | None = None,
        args: list[str] | None = None,
    ):
        self.data_dir = data_dir
        admin_key = (env or {}).get("COVSLAM_AUTH__ADMIN_KEY")
        self.auth = {"Authorization": f"Bearer {admin_key}"} if admin_key else {}
        """Headers that carry the admin key, if the server has one."""
        self.args = args or []
        self.workers = workers
        self.port = free_port()
        self.url = f"http://127.0.0.1:{self.port}"
        self.env = {**os.environ, "COVSLAM_LOG_LEVEL": "warning", **(env or {})}
        self.proc: subprocess.Popen[bytes] | None = None
        self.log = data_dir.parent / f"{data_dir.name}-server.log"

    def start(self, *, wait_ready: bool = True, timeout_s: float = 60.0) -> float:
        """Start the service; seconds until /readyz answered 200."""
        t0 = time.monotonic()
        with self.log.open("ab") as log:
            self.proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "api.cli",
                    "serve",
                    "--port",
                    str(self.port),
                    "--data-dir",
                    str(self.data_dir),
                    "--workers",
                    str(self.workers),
                    *self.args,
                ],
                cwd=REPO,
                env=self.env,
                stdout=log,
                stderr=subprocess.STDOUT,
                start_new_session=True,
            )
        if wait_ready:
            self.wait_ready(timeout_s)
        return time.monotonic() - t0

    def wait_ready(self, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            assert self.proc is not None
            if self.proc.poll() is not None:
                raise RuntimeError(f"server exited: {self.log.read_text()[-3000:]}")
            try:
                if httpx.get(self.url + "/readyz", timeout=1.0).status_code == 200:
                    return
            except httpx.TransportError:
                pass
            time.sleep(0.05)
        raise TimeoutError(f"server not ready in {timeout_s} s: {self.log.read_text()[-3000:]}")

    def kill9(self) -> None:
        """SIGKILL the whole process group (API process and workers), like a container kill."""
        assert self.proc is not None
        os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait(timeout=10)

    def stop(self) -> None:
        if self.proc is None or self.proc.poll() is not None:
            return
        self.proc.send_signal(signal.SIGTERM)  # uvicorn shuts down, closing its workers
        try:
            self.proc.wait(timeout=15)
        except subprocess.TimeoutExpired:
            self.kill9()

    def worker_pids(self) -> list[int]:
        body = httpx.get(self.url + "/v1/workers", timeout=5, headers=self.auth).json()
        return [w["pid"] for w in body["workers"] if w["pid"] is not None]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(tmp_path_factory.mktemp("svc") / "data")
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c


def sim_frames(n: int, *, seed: int = 1, robot: str = "r1") -> list[FrameInput]:
    """A small deterministic indoor run: two rooms, 30 landmarks, ~10 bearings per frame."""
    rng = np.random.default_rng(seed)
    world = make_world(rooms=(1, 2), landmarks=30, rng=rng)
    return simulate(world, frames=n, rng=rng, robot=robot).frames


def frame_dicts(frames: list[FrameInput]) -> list[dict[str, Any]]:
    return [frame_to_dict(f) for f in frames]


def create_map(client: httpx.Client, name: str = "m", **body: Any) -> str:
    r = client.post("/v1/maps", json={"name": name, **body})
    assert r.status_code == 201, r.text
    return str(r.json()["id"])


def post_all(client: httpx.Client, map_id: str, frames: list[dict[str, Any]]) -> list[dict]:
    out = []
    for f in frames:
        r = client.post(f"/v1/maps/{map_id}/frames", json=f)
        assert r.status_code == 200, r.text
        out.append(r.json())
    return out


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Headless Debian Chromium through Playwright (never a downloaded browser)."""
    if not CHROMIUM.exists():
        pytest.skip(f"no Chromium at {CHROMIUM} (apt-get install chromium; .ci/run does)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright not installed")
    with sync_api.sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), args=CHROMIUM_ARGS)
        yield b
        b.close()
