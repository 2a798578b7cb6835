"""bench.localisation's online protocol on a map whose estimate is replaced (``--online-map
batch`` / ``surveyed``): the stored map the starts load holds the batch solution's (or the
survey's) landmarks under the batch's marginal, and robots can still enter it."""

from __future__ import annotations

import dataclasses
import json
import time
from pathlib import Path

import numpy as np
import pytest

from bench.localisation import _replaced_map, rest_config
from service.frames_io import frame_to_dict
from service.offline.datasets.mrclam import default_mrclam_dir, load_mrclam, mrclam_frames
from service.pipeline.localiser import landmark_covariances, landmark_map
from service.session import MapSession
from service.settings import StoreSettings
from service.store import MapRecord

DATA = default_mrclam_dir()
needs_data = pytest.mark.skipif(
    not (DATA / "Barcodes.dat.gz").is_file() and not (DATA / "Barcodes.dat").is_file(),
    reason=f"MRCLAM dataset 6 not found in {DATA} (set COVSLAM_DATA to the data directory)",
)
SETTINGS = StoreSettings(snapshot_every=100_000)


@needs_data
@pytest.mark.parametrize("source", ["batch", "surveyed"])
def test_a_replaced_map_holds_the_batch_marginal_at_its_centre(tmp_path: Path, source: str) -> None:
    data = load_mrclam(DATA, 1)
    assert data.landmarks is not None
    surveyed = {str(int(s)): np.array([x, y]) for s, x, y in data.landmarks}
    frames, gt = mrclam_frames(data)
    frames = frames[:400]
    where = tmp_path / "map.sqlite"
    record = MapRecord("m", "online", "mapping", rest_config(), time.time())
    session = MapSession.create(where, record, SETTINGS)
    for f in frames:
        session.submit(frame_to_dict(f))
    before = landmark_map(session.slam)
    out = _replaced_map(session, frames, source, surveyed, gt)
    session.close()

    reopened = MapSession(where, SETTINGS)
    after = landmark_map(reopened.slam)
    assert set(after) == set(before)
    centre = surveyed if source == "surveyed" else out["batch_map_landmarks"]
    # Within what LM left of the gradient (the marginal's linear term; on the whole run
    # the surveyed map's landmarks sit within 0.1 mm of the survey).
    for label, xy in after.items():
        assert np.hypot(*(xy - np.asarray(centre[label]))) < 0.02, label
    sigma = {
        k: float(np.sqrt(np.linalg.eigvalsh(c)[-1]))
        for k, c in landmark_covariances(reopened.slam).items()
    }
    for label, s in out["batch_landmark_sigma_m"].items():
        assert sigma[label] == pytest.approx(s, rel=1e-3), label
    assert out["session_minus_batch_m"].keys() == before.keys()

    # Another robot enters the replaced map at its true pose and is tracked in it.
    other, _ = mrclam_frames(load_mrclam(DATA, 2))
    stream = [dataclasses.replace(other[0], initial_pose=other[0].initial_pose), *other[1:60]]
    statuses = [
        json.loads(reopened.submit(frame_to_dict(f)).result_json)["localisation"]["status"]
        for f in stream
    ]
    reopened.close()
    assert "lost" not in statuses
