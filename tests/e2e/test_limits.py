"""Limits of the HTTP front against a real `covslam serve`: content types, camera configs
the camera refuses, deep JSON, names, the number of maps, import size; each a clear 4xx
(or 507) problem+json that leaves the service's maps as they were."""

from __future__ import annotations

import json
from collections.abc import Iterator

import httpx
import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from service.settings import Settings
from tests.e2e.conftest import Server, create_map, frame_dicts, post_all, sim_frames

MAX_MAPS = 4
MAX_IMPORT_BYTES = 64 << 10
FRAMES = frame_dicts(sim_frames(4))


@pytest.fixture(scope="module")
def limited(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(
        tmp_path_factory.mktemp("limits") / "data",
        workers=1,
        env={
            "COVSLAM_MAX_MAPS": str(MAX_MAPS),
            "COVSLAM_API__MAX_IMPORT_BYTES": str(MAX_IMPORT_BYTES),
        },
    )
    srv.start()
    yield srv
    srv.stop()


@pytest.fixture(scope="module")
def c(limited: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=limited.url, timeout=60) as client:
        yield client


@pytest.fixture(scope="module")
def mapped(c: httpx.Client) -> str:
    map_id = create_map(c, "kept")
    post_all(c, map_id, FRAMES)
    return map_id


def _problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    body = dict(r.json())
    assert body["status"] == status and body["detail"]
    return body


def _state(c: httpx.Client, limited: Server) -> tuple[list[str], list[str]]:
    """The maps the service lists, and the map files on its disk."""
    files = sorted(p.name for p in (limited.data_dir / "maps").glob("*.sqlite"))
    return sorted(m["id"] for m in c.get("/v1/maps").json()), files


def test_json_endpoints_refuse_other_content_types(
    c: httpx.Client, limited: Server, mapped: str
) -> None:
    before = _state(c, limited)
    frames_before = c.get(f"/v1/maps/{mapped}").json()["counts"]["frames"]
    body = json.dumps({"name": "csrf"}).encode()
    for ctype in ("text/plain", "application/x-www-form-urlencoded", None):
        headers = {} if ctype is None else {"content-type": ctype}
        detail = _problem(c.post("/v1/maps", content=body, headers=headers), 415)["detail"]
        assert "application/json" in detail
        _problem(c.post("/v1/maps/import", content=body, headers=headers), 415)
        _problem(
            c.patch(f"/v1/maps/{mapped}", content=b'{"mode": "localisation"}', headers=headers), 415
        )
        frame = json.dumps(FRAMES[0]).encode()
        _problem(c.post(f"/v1/maps/{mapped}/frames", content=frame, headers=headers), 415)
        _problem(c.post(f"/v1/maps/{mapped}/places", content=b"{}", headers=headers), 415)
    assert _state(c, limited) == before
    summary = c.get(f"/v1/maps/{mapped}").json()
    assert summary["counts"]["frames"] == frames_before and summary["mode"] == "mapping"
    # application/json with parameters is still JSON; a body-less POST needs no type.
    r = c.post(
        f"/v1/maps/{mapped}/frames",
        content=json.dumps(FRAMES[-1]).encode(),
        headers={"content-type": "application/json; charset=utf-8"},
    )
    assert r.status_code == 200, r.text


@pytest.mark.parametrize(
    "camera",
    [
        {"model": "panorama", "width": 8, "height": 4},
        {"model": "panorama", "width": 9, "height": 4},
        {"model": "panorama", "width": 64, "height": 16, "vfov_deg": 5e-324},
    ],
)
def test_camera_the_camera_refuses_is_a_422_and_leaves_no_file(
    c: httpx.Client, limited: Server, camera: dict
) -> None:
    before = _state(c, limited)
    body = _problem(c.post("/v1/maps", json={"name": "cam", "config": {"camera": camera}}), 422)
    assert body["detail"].startswith("config.camera")
    assert _state(c, limited) == before


def test_deeply_nested_json_is_a_400(c: httpx.Client, limited: Server, mapped: str) -> None:
    before = _state(c, limited)
    deep = b'{"name": ' + b"[" * 20_000 + b"]" * 20_000 + b"}"
    headers = {"content-type": "application/json"}
    for path in ("/v1/maps", "/v1/maps/import", f"/v1/maps/{mapped}/frames"):
        r = c.post(path, content=deep, headers=headers)
        body = _problem(r, 400)
        assert "Error" not in body["detail"], body
    assert _state(c, limited) == before


def _export(c: httpx.Client, map_id: str) -> dict:
    r = c.get(f"/v1/maps/{map_id}/export")
    assert r.status_code == 200
    return dict(r.json())


def test_import_checks_the_name_like_create(c: httpx.Client, limited: Server, mapped: str) -> None:
    doc = _export(c, mapped)
    before = _state(c, limited)
    for name, why in (("x" * 201, "at most 200"), ("a\ud800b", "surrogate"), ("", "non-empty")):
        doc["map"]["name"] = name
        raw = json.dumps(doc).encode()  # ensure_ascii: the lone surrogate as \ud800
        r = c.post("/v1/maps/import", content=raw, headers={"content-type": "application/json"})
        body = _problem(r, 422)
        assert body["field"] == "map.name" and why in body["detail"], body
    _problem(c.post("/v1/maps", json={"name": "x" * 201}), 422)
    r = c.post(
        "/v1/maps", content=b'{"name": "a\\ud800"}', headers={"content-type": "application/json"}
    )
    _problem(r, 422)
    assert _state(c, limited) == before


def test_import_over_its_size_limit_is_a_413(c: httpx.Client, limited: Server) -> None:
    before = _state(c, limited)
    raw = b'{"pad": "' + b"x" * MAX_IMPORT_BYTES + b'"}'
    _problem(
        c.post("/v1/maps/import", content=raw, headers={"content-type": "application/json"}), 413
    )
    assert _state(c, limited) == before


def test_unknown_robot_404_does_not_list_the_robots(c: httpx.Client, mapped: str) -> None:
    body = _problem(c.get(f"/v1/maps/{mapped}/trajectory", params={"robot": "nobody"}), 404)
    assert "nobody" in body["detail"] and "r1" not in body["detail"]


def test_readyz_tells_no_process_ids(c: httpx.Client) -> None:
    body = c.get("/readyz").json()
    assert body["ready"] is True and body["workers"] == 1
    assert "pid" not in json.dumps(body)


def test_max_maps_is_a_507_for_create_and_import(
    c: httpx.Client, limited: Server, mapped: str
) -> None:
    doc = _export(c, mapped)
    created = []
    while len(c.get("/v1/maps").json()) < MAX_MAPS:
        created.append(create_map(c, "filler"))
    before = _state(c, limited)
    body = _problem(c.post("/v1/maps", json={"name": "one too many"}), 507)
    assert str(MAX_MAPS) in body["detail"]
    _problem(c.post("/v1/maps/import", json=doc), 507)
    assert _state(c, limited) == before
    for map_id in created:
        assert c.delete(f"/v1/maps/{map_id}").status_code == 204
    assert c.post("/v1/maps", json={"name": "room again"}).status_code == 201


def test_a_500_tells_no_exception_text_and_closes_the_connection(tmp_path) -> None:
    app = create_app(Settings(data_dir=tmp_path))

    @app.get("/boom")
    async def boom() -> None:
        raise RuntimeError("IndeterminantLinearSystemException near variable x3 in /secret/path")

    with TestClient(app, raise_server_exceptions=False) as client:
        r = client.get("/boom")
    body = _problem(r, 500)
    assert r.headers["connection"] == "close"
    text = r.text
    for leak in ("RuntimeError", "Indeterminant", "x3", "/secret"):
        assert leak not in text
    assert body["type"] == "urn:covslam:problem:internal"
