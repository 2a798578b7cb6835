"""docker/compose.scale.yaml brought up once: frames through it, and a map worker lost.

The stack (PostgreSQL, a Ray head, one Ray worker node, the API as a Ray node without
CPUs) comes up with ``docker compose up``; four maps (MRCLAM robots 1-4, the first F
frames each), one client per map posting in order with the admin key and retrying on 503
and transport errors. Once map 0 has K frames, the worker's container is killed
(``docker kill``: every process of that node at once); the maps it held move to the head.
Afterwards, per map: where it ran before and after, the seconds until it answered again
from another node, lost and duplicated frames (as in bench.scale_out). Then
``docker compose down -v``. Writes ``<out>/compose_scale.json``.

Needs a Docker daemon (DOCKER_HOST), docker compose (the v2 plugin or v1), the image
covslam:scale and postgres:15-bookworm (without a registry: docker/postgres-image.sh)::

    docker build --network host --build-arg EXTRAS=ray,postgres -f docker/Dockerfile \\
        -t covslam:scale .
    python -m bench.compose_scale [--frames 150] [--kill-after 50]
"""

from __future__ import annotations

import argparse
import json
import os
import secrets
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

import httpx

from bench.scale_out import MAP_CONFIG
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames
from service.offline.http_client import check_log, post_until_answered
from tests.support.clusters import free_port, until_ready

REPO = Path(__file__).resolve().parent.parent
NODE_ID = "import ray; ray.init(address='auto', logging_level='ERROR'); "
NODE_ID += "print(ray.get_runtime_context().get_node_id())"


def _compose_command() -> list[str]:
    plugin = subprocess.run(["docker", "compose", "version"], capture_output=True, check=False)
    if plugin.returncode == 0:
        return ["docker", "compose"]
    if shutil.which("docker-compose"):
        return ["docker-compose"]
    raise SystemExit("no docker compose (the v2 plugin, or docker-compose)")


class Stack:
    """One compose project of docker/compose.scale.yaml."""

    def __init__(self, workers: int, overrides: list[Path] | None = None) -> None:
        self.project = f"covslam-bench-{secrets.token_hex(4)}"
        self.port = free_port()
        self.key = secrets.token_urlsafe(24)
        self.workers = workers
        self.env = {
            **os.environ,
            "COVSLAM_AUTH__ADMIN_KEY": self.key,
            "POSTGRES_PASSWORD": secrets.token_urlsafe(16),
            "COVSLAM_PUBLISH": f"127.0.0.1:{self.port}",
        }
        files = [REPO / "docker/compose.scale.yaml", *(overrides or [])]
        self.cmd = [*_compose_command(), "-p", self.project]
        self.cmd += [a for f in files for a in ("-f", str(f))]
        self.url = f"http://127.0.0.1:{self.port}"
        self.headers = {"Authorization": f"Bearer {self.key}"}

    def run(self, *args: str, timeout: float = 600) -> str:
        done = subprocess.run([*self.cmd, *args], env=self.env, capture_output=True, text=True,
                              timeout=timeout, check=False)  # fmt: skip
        if done.returncode != 0:
            raise RuntimeError(f"compose {' '.join(args)}: {done.stderr[-3000:]}")
        return done.stdout.strip()

    def up(self) -> float:
        """Seconds from ``up`` until /readyz answers 200."""
        t0 = time.monotonic()
        self.run("up", "-d", "--no-build", "--scale", f"ray-worker={self.workers}")
        if until_ready(self.url, 600, every_s=0.5) is None:
            raise TimeoutError(f"the stack did not answer: {self.run('logs', '--tail', '50')}")
        return time.monotonic() - t0

    def container(self, service: str) -> str:
        return self.run("ps", "-q", service).splitlines()[0]

    def node_of(self, service: str) -> str:
        """The Ray node id of a service's container."""
        done = subprocess.run(
            ["docker", "exec", self.container(service), "python", "-c", NODE_ID],
            capture_output=True, text=True, timeout=120, check=True, env=self.env,
        )  # fmt: skip
        return done.stdout.strip().splitlines()[-1]

    def down(self) -> None:
        self.run("down", "-v", "--timeout", "20")


def _nodes(c: httpx.Client) -> dict[str, str | None]:
    return {w["map"]: w["node"] for w in c.get("/v1/workers").json()["workers"]}


def run(
    data: Path, *, frames: int, kill_after: int, overrides: list[Path] | None = None
) -> dict[str, Any]:
    stack = Stack(workers=1, overrides=overrides)
    report: dict[str, Any] = {"compose": "docker/compose.scale.yaml", "ray_workers": 1}
    if overrides:
        report["overrides"] = {str(f): f.read_text() for f in overrides}
    try:
        report["seconds_until_ready"] = round(stack.up(), 1)
        nodes = {s: stack.node_of(s) for s in ("ray-head", "ray-worker", "covslam")}
        runs = [
            [frame_to_dict(f) for f in mrclam_frames(load_mrclam(data, robot))[0][:frames]]
            for robot in range(1, 5)
        ]
        c = httpx.Client(base_url=stack.url, headers=stack.headers, timeout=120)
        ids = []
        for i in range(len(runs)):
            r = c.post("/v1/maps", json={"name": f"robot{i + 1}", "config": MAP_CONFIG})
            r.raise_for_status()
            ids.append(r.json()["id"])
        acked: list[list[dict]] = [[] for _ in ids]

        def client(i: int) -> None:
            with httpx.Client(base_url=stack.url, headers=stack.headers, timeout=300) as mine:
                for frame in runs[i]:
                    acked[i].append(post_until_answered(mine, ids[i], frame))

        threads = [threading.Thread(target=client, args=(i,)) for i in range(len(ids))]
        for t in threads:
            t.start()
        while len(acked[0]) < kill_after:
            time.sleep(0.05)
        before = _nodes(c)
        hit = [m for m in ids if before[m] == nodes["ray-worker"]]
        t_kill = time.monotonic()
        subprocess.run(["docker", "kill", stack.container("ray-worker")], env=stack.env,
                       capture_output=True, check=True, timeout=60)  # fmt: skip
        answered: dict[str, float] = {}
        while len(answered) < len(hit) and time.monotonic() - t_kill < 300:
            for m in hit:
                if m not in answered and c.get(f"/v1/maps/{m}/pose").status_code == 200:
                    where = _nodes(c).get(m)
                    if where is not None and where != nodes["ray-worker"]:
                        answered[m] = round(time.monotonic() - t_kill, 2)
            time.sleep(0.05)
        for t in threads:
            t.join()
        after = _nodes(c)
        name = {v: k for k, v in nodes.items()}
        report["per_map"] = [
            {
                "map": m,
                "node_before": name.get(before[m] or "", before[m]),
                "node_after": name.get(after[m] or "", after[m]),
                "seconds_until_answers_again": answered.get(m),
                **check_log(stack.url, m, runs[i], acked[i], stack.headers),
            }
            for i, m in enumerate(ids)
        ]
        report["frames_per_map"] = frames
        report["killed_after_frames_of_map_0"] = kill_after
        report["maps_hit"] = len(hit)
        report["lost_total"] = sum(m["lost"] for m in report["per_map"])
        report["duplicated_total"] = sum(m["duplicated"] for m in report["per_map"])
        c.close()
    finally:
        stack.down()
    return report


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--data", type=Path, default=None, help="MRCLAM-6 folder")
    ap.add_argument("--frames", type=int, default=150, help="frames per map")
    ap.add_argument("--kill-after", type=int, default=50, help="map 0's frames before the kill")
    ap.add_argument(
        "--override", type=Path, action="append", default=[],
        help="a further compose file laid over it (e.g. the head's RAY_health_check_*)",
    )  # fmt: skip
    ap.add_argument("--out", type=Path, default=Path("bench/results"))
    args = ap.parse_args(argv)
    report = run(args.data or default_mrclam_dir(), frames=args.frames,
                 kill_after=args.kill_after, overrides=args.override)  # fmt: skip
    args.out.mkdir(parents=True, exist_ok=True)
    name = "compose_scale.json" if not args.override else "compose_scale_override.json"
    (args.out / name).write_text(json.dumps(report, indent=1) + "\n")
    print(json.dumps({k: v for k, v in report.items() if k != "per_map"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
