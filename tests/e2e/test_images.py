"""Image frames over HTTP against a real `covslam serve`: a rendered run posted as
multipart (meta + image) builds a map; every bad image is a precise 422/413 that
leaves the map unchanged; an acknowledged image frame survives kill -9."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import numpy as np
import pytest

from frontend.cameras import PanoramaCamera
from service.offline.datasets.render_run import RenderedRun, write_rendered_run
from service.offline.evaluation import ate_rmse, dead_reckoning, read_tum
from service.offline.http_client import fetch_tum, image_frame_parts, replay_http
from service.offline.replay import ImageFrame, read_replay_frames
from service.pipeline.camera_config import CAMERA_GRAPH_FRAME_DISTANCE_M
from tests.e2e.conftest import Server, create_map
from tests.frontend import _synthetic as synthetic

CAMERA = PanoramaCamera(1024, 256)
MAX_IMAGE_BYTES = 1_000_000
FRAMES = 40


@pytest.fixture(scope="module")
def rendered(tmp_path_factory: pytest.TempPathFactory) -> RenderedRun:
    return write_rendered_run(
        tmp_path_factory.mktemp("rendered"),
        frames=FRAMES,
        rng=np.random.default_rng(3),
        camera=CAMERA,
        rooms=(1, 2),
    )


@pytest.fixture(scope="module")
def frames(rendered: RenderedRun) -> list[ImageFrame]:
    items = read_replay_frames(rendered.frames_path)
    assert all(isinstance(it, ImageFrame) for it in items)
    return [it for it in items if isinstance(it, ImageFrame)]


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(
        tmp_path_factory.mktemp("svc-images") / "data",
        workers=1,
        env={"COVSLAM_API__MAX_IMAGE_BYTES": str(MAX_IMAGE_BYTES)},
    )
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def client(server: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=server.url, timeout=60) as c:
        yield c


def _camera_map(client: httpx.Client, name: str) -> str:
    return create_map(client, name, config={"landmark_cap": None, "camera": CAMERA.as_config()})


def _problem(r: httpx.Response, status: int, slug: str) -> dict[str, Any]:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = r.json()
    assert body["type"] == f"urn:covslam:problem:{slug}", body
    assert body["status"] == status and body["detail"]
    return body


def _frames_in(client: httpx.Client, map_id: str) -> int:
    return int(client.get(f"/v1/maps/{map_id}").json()["counts"]["frames"])


def test_rendered_run_over_http_builds_a_map_near_the_truth(
    server: Server, client: httpx.Client, rendered: RenderedRun, frames: list[ImageFrame]
) -> None:
    map_id = _camera_map(client, "rendered")
    run = replay_http(frames, url=server.url, map_id=map_id, progress=False)
    assert len(run.results) == FRAMES
    assert run.results[-1]["timing_ms"]["features"] > 0
    # A camera map is created with tracked frames between its graph frames; every frame
    # is still in the trajectory.
    summary = client.get(f"/v1/maps/{map_id}").json()
    assert summary["config"]["graph_frame_distance_m"] == CAMERA_GRAPH_FRAME_DISTANCE_M
    assert 0 < summary["counts"]["graph_frames"] < summary["counts"]["frames"] == FRAMES
    traj = client.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
    assert [p["seq"] for p in traj] == [f.frame.seq for f in frames]
    landmarks = client.get(f"/v1/maps/{map_id}/landmarks").json()
    assert len(landmarks) > 10, "candidate tracks became landmarks"
    observed = sum(len(r["landmarks"]["observed"]) for r in run.results)
    assert observed > 5 * FRAMES, "later frames matched landmarks by descriptor"
    tum = rendered.frames_path.parent / "est.tum"
    tum.write_text(fetch_tum(server.url, map_id, "r1"))
    truth = read_tum(rendered.ground_truth_path)
    ate = ate_rmse(read_tum(tum), truth)
    drift = ate_rmse(dead_reckoning([f.frame for f in frames]), truth)
    assert ate < 0.03, (ate, drift)  # measured 0.0099 m (dead reckoning 0.015 m)
    # Landmarks lie where the rendered world's posters are: inside the two rooms.
    xy = np.array([[lm["x"], lm["y"]] for lm in landmarks])
    assert np.all(np.isfinite(xy))


def test_bad_image_frames_are_refused_precisely_and_change_nothing(
    client: httpx.Client, frames: list[ImageFrame]
) -> None:
    map_id = _camera_map(client, "bad-images")
    first = image_frame_parts(frames[0])
    assert client.post(f"/v1/maps/{map_id}/frames", **first).status_code == 200
    url = f"/v1/maps/{map_id}/frames"
    nxt = image_frame_parts(frames[1])
    meta = nxt["data"]
    png = nxt["files"]["image"][1]

    def post_image(data: bytes, name: str = "x.png") -> httpx.Response:
        return client.post(url, data=meta, files={"image": (name, data, "image/png")})

    cases: list[tuple[httpx.Response, int, str, str]] = [
        (post_image(b"GIF89a not a png"), 422, "invalid-image", "neither PNG nor JPEG"),
        (post_image(b""), 422, "invalid-image", "empty"),
        (post_image(png[: len(png) // 2]), 422, "invalid-image", "could not be decoded"),
        (
            post_image(synthetic.png(np.zeros((100, 400), np.uint8))),
            422,
            "invalid-image",
            "1024x256",
        ),
        (post_image(synthetic.png_header_only(100_000, 100_000)), 413, "image-too-large", "pixels"),
        (post_image(png + b"\0" * MAX_IMAGE_BYTES), 413, "image-too-large", "exceed"),
        (
            client.post(url, files={"image": ("x.png", b"\0" * (MAX_IMAGE_BYTES + 2**21))}),
            413,
            "body-too-large",
            "exceeds the limit",
        ),
        (
            client.post(url, files={"meta": (None, meta["meta"].encode())}),
            422,
            "invalid-image-frame",
            "image: part is required",
        ),
        # A urlencoded form (what a cross-site HTML form sends) is not a frame.
        (client.post(url, data=meta), 415, "unsupported-media-type", "multipart/form-data"),
        (
            client.post(url, files={"image": ("x.png", png, "image/png")}),
            422,
            "invalid-image-frame",
            "meta: part is required",
        ),
        (
            client.post(url, data={"meta": "{not json"}, files={"image": ("x.png", png)}),
            422,
            "invalid-image-frame",
            "meta: malformed JSON",
        ),
        (
            client.post(url, data={"meta": "[1, 2]"}, files={"image": ("x.png", png)}),
            422,
            "invalid-image-frame",
            "meta: must be a JSON object",
        ),
        (
            client.post(url, data=meta, files={"image": (None, b"not a file")}),
            422,
            "invalid-image-frame",
            "must be a file part",
        ),
        (
            client.post(
                url,
                data={"meta": _meta_with(meta, observations=[{"bearing": 0.1, "label": "a"}])},
                files={"image": ("x.png", png)},
            ),
            422,
            "invalid-frame",
            "meta.observations",
        ),
        (
            client.post(
                url, data={"meta": _meta_with(meta, seq=-1)}, files={"image": ("x.png", png)}
            ),
            422,
            "invalid-frame",
            "seq",
        ),
        (
            client.post(
                url, data={"meta": _meta_with(meta, odometer=1.0)}, files={"image": ("x.png", png)}
            ),
            422,
            "invalid-frame",
            "odometer: is not a field of a frame",
        ),
        (
            client.post(
                url, data={"meta": _meta_with(meta, stamp=1e300)}, files={"image": ("x.png", png)}
            ),
            422,
            "invalid-frame",
            "stamp: must lie within",
        ),
        (
            client.post(
                url,
                content=b"--xyz\r\nContent-Disposition: form-data; name=meta\r\n\r\n{}",
                headers={"content-type": "multipart/form-data; boundary=xyz"},
            ),
            422,
            "invalid-image-frame",
            "",
        ),
    ]
    for response, status, slug, words in cases:
        body = _problem(response, status, slug)
        assert words in body["detail"], body
    assert _frames_in(client, map_id) == 1, "no refused frame reached the map"
    # The map takes the same frame, with its real image, as if nothing happened; a meta
    # that names its image (a line of a frame file) is the same frame.
    named = {"meta": _meta_with(meta, image="images/000001.png")}
    r = client.post(url, data=named, files=nxt["files"])
    assert r.status_code == 200, r.text
    assert r.json()["seq"] == frames[1].frame.seq
    # A retry with the same image is answered from the log; another image is a 409.
    again = client.post(url, **nxt)
    assert again.headers.get("idempotent-replayed") == "true"
    assert again.json() == r.json()
    _problem(post_image(image_frame_parts(frames[2])["files"]["image"][1]), 409, "duplicate-seq")
    plain = create_map(client, "no-camera")
    _problem(client.post(f"/v1/maps/{plain}/frames", **first), 422, "no-camera")


def test_acknowledged_image_frames_survive_kill9(tmp_path: Path, frames: list[ImageFrame]) -> None:
    server = Server(tmp_path / "data", workers=1)
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            map_id = _camera_map(c, "durable")
            acked = [
                c.post(f"/v1/maps/{map_id}/frames", **image_frame_parts(f)) for f in frames[:12]
            ]
            assert all(r.status_code == 200 for r in acked)
            before = c.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
            landmarks = {lm["id"] for lm in c.get(f"/v1/maps/{map_id}/landmarks").json()}
        server.kill9()
        server.start()
        with httpx.Client(base_url=server.url, timeout=60) as c:
            after = c.get(f"/v1/maps/{map_id}/trajectory").json()["robots"]["r1"]
            assert [p["seq"] for p in after] == [p["seq"] for p in before]
            assert max(abs(a["x"] - b["x"]) for a, b in zip(after, before, strict=True)) < 1e-6
            assert {lm["id"] for lm in c.get(f"/v1/maps/{map_id}/landmarks").json()} == landmarks
            r = c.post(f"/v1/maps/{map_id}/frames", **image_frame_parts(frames[12]))
            assert r.status_code == 200, r.text
            assert len(r.json()["landmarks"]["observed"]) > 3, "the reloaded map still matches"
    finally:
        server.stop()


def _meta_with(meta: dict[str, str], **changes: Any) -> str:
    return json.dumps({**json.loads(meta["meta"]), **changes})


def test_replay_cli_posts_image_frames_with_the_camera_config(
    server: Server, client: httpx.Client, rendered: RenderedRun, capsys: pytest.CaptureFixture
) -> None:
    from api.cli import main

    short = rendered.frames_path.parent / "short.jsonl"
    short.write_text("".join(rendered.frames_path.read_text().splitlines(True)[:8]))
    stats = rendered.frames_path.parent / "http-stats.json"
    code = main(["replay", str(short), "--url", server.url, "--stats", str(stats)])
    assert code == 0
    map_id = json.loads(stats.read_text())["map_id"]
    summary = client.get(f"/v1/maps/{map_id}").json()
    assert summary["config"]["camera"] == {**CAMERA.as_config(), "model": "panorama"}
    # No --huber: the map gets the camera's robust loss, as in an in-process replay.
    assert summary["config"]["noise"]["bearing_loss"] == "geman_mcclure"
    assert summary["counts"]["frames"] == 8
    assert "8 frames over HTTP" in capsys.readouterr().out


def test_export_import_of_an_image_map_over_http(
    client: httpx.Client, frames: list[ImageFrame]
) -> None:
    """An exported camera map imports as a map that labels new images as the original."""
    source = _camera_map(client, "to-export")
    for f in frames[:24]:
        assert client.post(f"/v1/maps/{source}/frames", **image_frame_parts(f)).status_code == 200
    r = client.get(f"/v1/maps/{source}/export")
    assert r.status_code == 200, r.text
    doc = r.json()
    assert doc["map"]["config"]["camera"]["width"] == CAMERA.width
    assert doc["frontend"]["associator"]["landmarks"] and doc["frontend"]["last"]["r1"]
    assert all("image" in f["frame"] for f in doc["frames"])
    # The frames carry the image's digest, not its bytes: the whole document is smaller
    # than the PNGs it was built from, which embedded (base64) would take 4/3 of alone.
    png_bytes = sum(f.image_path.stat().st_size for f in frames[:24])
    assert len(r.content) < png_bytes, (len(r.content), png_bytes)

    r = client.post("/v1/maps/import", json=doc)
    assert r.status_code == 201, r.text
    copy = r.json()["id"]
    assert r.json()["counts"]["frames"] == 24

    def labels(map_id: str, result: dict[str, Any]) -> list[str]:
        live = {lm["id"]: lm["label"] for lm in client.get(f"/v1/maps/{map_id}/landmarks").json()}
        return sorted(live[i] for i in result["landmarks"]["observed"] if i in live)

    matched = 0
    for f in frames[24:32]:
        a = client.post(f"/v1/maps/{source}/frames", **image_frame_parts(f))
        b = client.post(f"/v1/maps/{copy}/frames", **image_frame_parts(f))
        assert a.status_code == b.status_code == 200, (a.text, b.text)
        assert a.json()["landmarks"]["observed"] == b.json()["landmarks"]["observed"]
        assert labels(source, a.json()) == labels(copy, b.json())
        assert abs(a.json()["pose"]["x"] - b.json()["pose"]["x"]) < 1e-6
        matched += len(a.json()["landmarks"]["observed"])
    assert matched > 30, "the imported map matched its landmarks in new images"
    # A retry of an imported image frame (same meta, same image) is answered from the log.
    again = client.post(f"/v1/maps/{copy}/frames", **image_frame_parts(frames[5]))
    assert again.headers.get("idempotent-replayed") == "true", again.text
    # A document with a broken front-end state is refused and creates no map.
    maps_before = len(client.get("/v1/maps").json())
    doc["frontend"]["associator"]["landmarks"][0]["descriptors"] = ["!!"]
    _problem(client.post("/v1/maps/import", json=doc), 422, "invalid-import")
    assert len(client.get("/v1/maps").json()) == maps_before
