"""Property-based fuzzing of the whole API from its OpenAPI document (schemathesis):
at least 1000 generated requests, with the admin key, against a map with frames; no
answer may be a 5xx.

Bounded: a fixed seed and a fixed number of examples per operation. The event stream
(an endless response) and DELETE of the map under test are left out.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from tests.e2e.conftest import Server, frame_dicts, post_all, sim_frames

ADMIN_KEY = "schemathesis-admin-key-0123456789"
EXAMPLES_PER_OPERATION = 120
MIN_CASES = 1000


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(
        tmp_path_factory.mktemp("fuzz") / "data",
        workers=1,
        env={"COVSLAM_AUTH__ADMIN_KEY": ADMIN_KEY, "COVSLAM_MAX_MAPS": "100000"},
    )
    srv.start()
    yield srv
    srv.stop()


def _cases(report_dir: Path) -> list[int]:
    """Status codes of every request schemathesis sent (from its NDJSON report)."""
    codes = []
    for path in report_dir.glob("*.ndjson"):
        for line in path.read_text().splitlines():
            codes.extend(int(c) for c in _status_codes(json.loads(line)))
    return codes


def _status_codes(node: object) -> Iterator[int]:
    if isinstance(node, dict):
        if "status_code" in node and "elapsed" in node:
            yield node["status_code"]
        for value in node.values():
            yield from _status_codes(value)
    elif isinstance(node, list):
        for value in node:
            yield from _status_codes(value)


def test_no_generated_request_gets_a_5xx(fuzzed: Server, tmp_path: Path) -> None:
    st = shutil.which("st") or shutil.which("schemathesis")
    if st is None:
        pytest.skip("schemathesis not installed (pip install -e '.[dev]')")
    headers = {"Authorization": f"Bearer {ADMIN_KEY}"}
    with httpx.Client(base_url=fuzzed.url, timeout=60, headers=headers) as c:
        map_id = c.post("/v1/maps", json={"name": "fuzzed"}).json()["id"]
        post_all(c, map_id, frame_dicts(sim_frames(20)))
    config = tmp_path / "schemathesis.toml"
    config.write_text(f'[parameters]\nmap_id = "{map_id}"\n')
    report = tmp_path / "report"
    run = subprocess.run(
        [
            st,
            "--config-file",
            str(config),
            "run",
            f"{fuzzed.url}/openapi.json",
            "-H",
            f"Authorization: Bearer {ADMIN_KEY}",
            "--checks",
            "not_a_server_error",
            "--phases",
            "examples,coverage,fuzzing",
            "--max-examples",
            str(EXAMPLES_PER_OPERATION),
            "--seed",
            "20261204",
            "--exclude-name",
            "GET /v1/maps/{map_id}/events",
            "--exclude-name",
            "DELETE /v1/maps/{map_id}",
            "--request-timeout",
            "30",
            "--report",
            "ndjson",
            "--report-dir",
            str(report),
            "--no-color",
        ],
        capture_output=True,
        text=True,
        timeout=1200,
        env={**os.environ, "SCHEMATHESIS_HOOKS": ""},
        cwd=tmp_path,
    )
    codes = _cases(report)
    server_errors = [code for code in codes if code >= 500]
    print(f"schemathesis: {len(codes)} requests, statuses {sorted(set(codes))}")
    assert run.returncode == 0, run.stdout[-6000:]
    assert not server_errors
    assert len(codes) >= MIN_CASES, run.stdout[-3000:]
