"""MRCLAM-6 robot 1 through a real `covslam serve`, posted by `covslam replay --url`."""

from __future__ import annotations

import subprocess
import sys

import httpx
import numpy as np
import pytest

from service.offline.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames
from service.offline.evaluation import ate_rmse, dead_reckoning, read_tum
from tests.e2e.conftest import REPO, Server

DATA = default_mrclam_dir()
pytestmark = pytest.mark.skipif(
    not (DATA / "Robot1_Odometry.dat.gz").exists() and not (DATA / "Robot1_Odometry.dat").exists(),
    reason=f"MRCLAM-6 data not found in {DATA} (set COVSLAM_DATA)",
)


def test_mrclam_robot1_over_http(server: Server, tmp_path) -> None:
    frames, gt = mrclam_frames(load_mrclam(DATA, 1))
    tum = tmp_path / "r1.tum"
    out = subprocess.run(
        [
            sys.executable,
            "-m",
            "api.cli",
            "replay",
            "mrclam",
            str(DATA),
            "--robot",
            "1",
            "--landmark-cap",
            "8",
            "--url",
            server.url,
            "--trajectory",
            str(tum),
            "--no-progress",
        ],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert out.returncode == 0, out.stderr
    print(out.stdout.strip())
    map_id = out.stdout.split()[1].rstrip(":")
    assert f"{len(frames)} frames over HTTP" in out.stdout

    est = read_tum(tum)
    assert len(est) == len(frames)
    ate, dr = ate_rmse(est, gt), ate_rmse(dead_reckoning(frames), gt)
    assert ate < dr, (ate, dr)

    # The import replays all 1376 frames inside one request: minutes on a busy 2-core machine.
    with httpx.Client(base_url=server.url, timeout=600) as c:
        summary = c.get(f"/v1/maps/{map_id}").json()
        assert summary["counts"]["frames"] == len(frames)
        assert summary["counts"]["live_landmarks"] <= 8
        pose = c.get(f"/v1/maps/{map_id}/pose").json()["robots"]["r1"]
        np.testing.assert_allclose([pose["pose"]["x"], pose["pose"]["y"]], est.xy[-1], atol=1e-5)
        landmarks = c.get(f"/v1/maps/{map_id}/landmarks").json()
        assert 0 < len(landmarks) <= 8
        assert all(lm["label"].isdigit() and 6 <= int(lm["label"]) <= 20 for lm in landmarks)
        coverage = c.get(f"/v1/maps/{map_id}/coverage").json()
        assert coverage["removal_count"] > 0 and coverage["grid"]["explored_cells"] > 0

        doc = c.get(f"/v1/maps/{map_id}/export").json()
        r = c.post("/v1/maps/import", json=doc)
        assert r.status_code == 201, r.text
        copy = c.get(
            f"/v1/maps/{r.json()['id']}/trajectory", params={"robot": "r1", "format": "tum"}
        )
        original = c.get(f"/v1/maps/{map_id}/trajectory", params={"robot": "r1", "format": "tum"})
        assert copy.text == original.text
