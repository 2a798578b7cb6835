"""API keys against a real `covslam serve` with an admin key: who may do what (401/403
per scope and map), keys hashed at rest, surviving a restart, dying with their map."""

from __future__ import annotations

import hashlib
import sqlite3
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.offline.http_client import API_KEY_VARIABLE, ReplayHTTPError, fetch_tum, replay_http
from tests.e2e.conftest import Server, frame_dicts, sim_frames
from tests.e2e.test_dashboard import _wait_for

ADMIN_KEY = "test-admin-key-0123456789abcdef"
FRAMES = frame_dicts(sim_frames(6))

# (method, path under /v1/maps/{A}, JSON body or None, scope it needs). Bodies are chosen
# so that an allowed request fails *after* authorisation (422/404) or changes nothing.
MAP_REQUESTS: list[tuple[str, str, object, str]] = [
    ("GET", "", None, "read"),
    ("GET", "/pose", None, "read"),
    ("GET", "/trajectory", None, "read"),
    ("GET", "/landmarks", None, "read"),
    ("GET", "/coverage", None, "read"),
    ("GET", "/places", None, "read"),
    ("GET", "/export", None, "read"),
    ("POST", "/frames", {"robot": "r1"}, "write"),
    ("POST", "/places", {"robot": "nobody"}, "write"),
    ("PATCH", "", {"mode": "mapping"}, "admin"),
    ("GET", "/keys", None, "admin"),
    ("POST", "/keys", {"scope": "everything"}, "admin"),
    ("DELETE", "/keys/unknown", None, "admin"),
]
SERVICE_REQUESTS: list[tuple[str, str, object]] = [
    ("POST", "/v1/maps", {"name": ""}),
    ("GET", "/v1/maps", None),
    ("POST", "/v1/maps/import", {"format": "nope"}),
    ("GET", "/metrics", None),
    ("GET", "/v1/workers", None),
]
RANK = {"read": 0, "write": 1, "admin": 2}


@pytest.fixture(scope="module")
def secured(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Server]:
    srv = Server(
        tmp_path_factory.mktemp("auth") / "data",
        workers=1,
        env={"COVSLAM_AUTH__ADMIN_KEY": ADMIN_KEY},
    )
    srv.start()
    yield srv
    srv.stop()


def _bearer(key: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {key}"}


@pytest.fixture(scope="module")
def admin(secured: Server) -> Iterator[httpx.Client]:
    with httpx.Client(base_url=secured.url, timeout=60, headers=_bearer(ADMIN_KEY)) as c:
        yield c


@pytest.fixture(scope="module")
def maps(admin: httpx.Client) -> dict[str, str]:
    """Two maps, A with frames; keys of each scope for A, a read key for B."""
    ids = {}
    for name in ("A", "B"):
        r = admin.post("/v1/maps", json={"name": name})
        assert r.status_code == 201, r.text
        ids[name] = r.json()["id"]
    for frame in FRAMES:
        assert admin.post(f"/v1/maps/{ids['A']}/frames", json=frame).status_code == 200
    return ids


def _key(admin: httpx.Client, map_id: str, scope: str) -> str:
    r = admin.post(f"/v1/maps/{map_id}/keys", json={"scope": scope})
    assert r.status_code == 201, r.text
    body = r.json()
    assert body["scope"] == scope and body["id"] and body["key"]
    return str(body["key"])


@pytest.fixture(scope="module")
def keys(admin: httpx.Client, maps: dict[str, str]) -> dict[str, str]:
    out = {scope: _key(admin, maps["A"], scope) for scope in RANK}
    out["other"] = _key(admin, maps["B"], "admin")
    return out


def _send(c: httpx.Client, method: str, path: str, body: object, key: str | None) -> int:
    headers = {} if key is None else _bearer(key)
    if body is None:
        return c.request(method, path, headers=headers).status_code
    return c.request(method, path, json=body, headers=headers).status_code


def _assert_problem(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/problem+json")
    return dict(r.json())


def test_scope_matrix_on_a_map(secured: Server, maps: dict[str, str], keys: dict[str, str]) -> None:
    """Every map endpoint: 401 without a valid key, 403 for another map's key or too
    weak a scope, past authorisation otherwise (admin key and strong enough keys)."""
    bogus = "csk_" + "x" * 43
    with httpx.Client(base_url=secured.url, timeout=60) as c:
        for method, sub, body, needs in MAP_REQUESTS:
            path = f"/v1/maps/{maps['A']}{sub}"
            assert _send(c, method, path, body, None) == 401, (method, path)
            assert _send(c, method, path, body, bogus) == 401, (method, path)
            assert _send(c, method, path, body, keys["other"]) == 403, (method, path)
            for scope in RANK:
                status = _send(c, method, path, body, keys[scope])
                if RANK[scope] >= RANK[needs]:
                    assert status not in (401, 403), (method, path, scope, status)
                else:
                    assert status == 403, (method, path, scope, status)
            assert _send(c, method, path, body, ADMIN_KEY) not in (401, 403), (method, path)


def test_only_the_admin_key_manages_the_service(secured: Server, keys: dict[str, str]) -> None:
    with httpx.Client(base_url=secured.url, timeout=60) as c:
        for method, path, body in SERVICE_REQUESTS:
            assert _send(c, method, path, body, None) == 401, path
            for scope in RANK:
                assert _send(c, method, path, body, keys[scope]) == 403, (path, scope)
            assert _send(c, method, path, body, ADMIN_KEY) not in (401, 403), path


def test_401_challenges_and_403_tells_nothing_about_other_maps(
    secured: Server, maps: dict[str, str], keys: dict[str, str]
) -> None:
    with httpx.Client(base_url=secured.url, timeout=60) as c:
        r = c.get(f"/v1/maps/{maps['A']}")
        _assert_problem(r, 401)
        assert r.headers["www-authenticate"].startswith("Bearer")
        r = c.get(f"/v1/maps/{maps['A']}", headers={"Authorization": "Basic dXNlcjpwYXNz"})
        assert r.status_code == 401 and "www-authenticate" in r.headers
        existing = _assert_problem(
            c.get(f"/v1/maps/{maps['B']}", headers=_bearer(keys["read"])), 403
        )
        missing = _assert_problem(
            c.get("/v1/maps/000000000000", headers=_bearer(keys["read"])), 403
        )
        assert existing["detail"] == missing["detail"]
        assert maps["B"] not in existing["detail"]


def test_probes_are_open_docs_declare_bearer(secured: Server) -> None:
    with httpx.Client(base_url=secured.url, timeout=60) as c:
        assert c.get("/healthz").status_code == 200
        assert c.get("/readyz").status_code == 200
        schema = c.get("/openapi.json").json()
    schemes = schema["components"]["securitySchemes"]
    assert any(s == {**s, "type": "http", "scheme": "bearer"} for s in schemes.values())
    assert schema["paths"]["/v1/maps/{map_id}/pose"]["get"]["security"]
    assert "security" not in schema["paths"]["/healthz"]["get"]
    refusals = schema["paths"]["/v1/maps"]["post"]["responses"]
    for code in ("401", "403", "415", "422", "507"):
        assert list(refusals[code]["content"]) == ["application/problem+json"], code


def test_event_stream_takes_the_key_as_access_token(
    secured: Server, maps: dict[str, str], keys: dict[str, str]
) -> None:
    path = f"/v1/maps/{maps['A']}/events"
    with httpx.Client(base_url=secured.url, timeout=10) as c:
        with c.stream("GET", path, params={"since": 0, "access_token": keys["read"]}) as r:
            assert r.status_code == 200
            assert r.headers["content-type"].startswith("text/event-stream")
        with c.stream("GET", path, params={"access_token": keys["other"]}) as r:
            assert r.status_code == 403
        with c.stream("GET", path, params={"access_token": "wrong"}) as r:
            assert r.status_code == 401
        # Only the event stream reads a key from the address.
        r = c.get(f"/v1/maps/{maps['A']}/pose", params={"access_token": keys["read"]})
        assert r.status_code == 401


def test_keys_listed_without_secret_hashed_at_rest_and_revocable(
    secured: Server, admin: httpx.Client, maps: dict[str, str]
) -> None:
    map_id = maps["A"]
    created = admin.post(f"/v1/maps/{map_id}/keys", json={"scope": "read"}).json()
    listed = admin.get(f"/v1/maps/{map_id}/keys").json()
    assert {"id": created["id"], "scope": "read"}.items() <= next(
        k for k in listed if k["id"] == created["id"]
    ).items()
    assert all("key" not in k for k in listed)
    assert created["key"] not in admin.get(f"/v1/maps/{map_id}/keys").text

    catalog = secured.data_dir / "catalog.sqlite"
    raw = b"".join(p.read_bytes() for p in catalog.parent.glob("catalog.sqlite*"))
    assert created["key"].encode() not in raw
    with sqlite3.connect(f"file:{catalog}?mode=ro", uri=True) as db:
        stored = db.execute("SELECT hash FROM keys WHERE id = ?", (created["id"],)).fetchone()
    assert stored[0] == hashlib.sha256(created["key"].encode()).hexdigest()

    reader = _bearer(created["key"])
    assert admin.get(f"/v1/maps/{map_id}", headers=reader).status_code == 200
    assert admin.delete(f"/v1/maps/{map_id}/keys/{created['id']}").status_code == 204
    assert admin.get(f"/v1/maps/{map_id}", headers=reader).status_code == 401
    _assert_problem(admin.delete(f"/v1/maps/{map_id}/keys/{created['id']}"), 404)


def test_a_map_admin_key_makes_keys_and_deletes_its_map_whose_keys_die(
    secured: Server, admin: httpx.Client
) -> None:
    map_id = admin.post("/v1/maps", json={"name": "doomed"}).json()["id"]
    owner = _bearer(_key(admin, map_id, "admin"))
    r = admin.post(f"/v1/maps/{map_id}/keys", json={"scope": "write"}, headers=owner)
    assert r.status_code == 201
    writer = _bearer(r.json()["key"])
    assert (
        admin.post(f"/v1/maps/{map_id}/frames", json=FRAMES[0], headers=writer).status_code == 200
    )
    assert admin.delete(f"/v1/maps/{map_id}", headers=writer).status_code == 403
    assert admin.delete(f"/v1/maps/{map_id}", headers=owner).status_code == 204
    assert admin.get(f"/v1/maps/{map_id}", headers=owner).status_code == 401
    with sqlite3.connect(f"file:{secured.data_dir / 'catalog.sqlite'}?mode=ro", uri=True) as db:
        assert (
            db.execute("SELECT COUNT(*) FROM keys WHERE map_id = ?", (map_id,)).fetchone()[0] == 0
        )


def test_keys_survive_a_restart(tmp_path: Path) -> None:
    srv = Server(tmp_path / "data", workers=1, env={"COVSLAM_AUTH__ADMIN_KEY": ADMIN_KEY})
    srv.start()
    try:
        with httpx.Client(base_url=srv.url, timeout=60, headers=_bearer(ADMIN_KEY)) as c:
            map_id = c.post("/v1/maps", json={"name": "kept"}).json()["id"]
            key = _key(c, map_id, "read")
        srv.stop()
        srv.start()
        with httpx.Client(base_url=srv.url, timeout=60) as c:
            assert c.get(f"/v1/maps/{map_id}", headers=_bearer(key)).status_code == 200
            assert c.get(f"/v1/maps/{map_id}", headers=_bearer(key + "x")).status_code == 401
    finally:
        srv.stop()


def test_dashboard_asks_for_a_key_once_and_follows_the_map_live(
    browser: Any, secured: Server, admin: httpx.Client, maps: dict[str, str]
) -> None:
    """A map's read key, entered once in the dashboard: REST calls carry it as a header,
    the event stream as access_token; it stays in this tab's sessionStorage."""
    map_id = maps["A"]
    key = _key(admin, map_id, "read")
    frames = admin.get(f"/v1/maps/{map_id}").json()["counts"]["frames"]
    page = browser.new_page(viewport={"width": 1280, "height": 800})
    page.goto(f"{secured.url}/dashboard/?map={map_id}")
    _wait_for(page, "app", "state", "key")
    assert page.locator("#key-form").is_visible()
    page.fill("#key-input", key)
    page.click("#key-form button")
    _wait_for(page, "app", "state", "live")
    _wait_for(page, "app", "frame", frames)
    assert not page.locator("#key-form").is_visible()
    assert page.evaluate("() => sessionStorage.getItem('covslam.apiKey')") == key
    more = frame_dicts(sim_frames(len(FRAMES) + 2))[len(FRAMES) :]
    for frame in more:
        assert admin.post(f"/v1/maps/{map_id}/frames", json=frame).status_code == 200
    _wait_for(page, "app", "frame", frames + len(more))  # through the authenticated stream
    page.reload()  # the key is remembered in this tab
    _wait_for(page, "app", "state", "live")
    page.close()


def test_replay_client_sends_the_key_from_the_environment(
    secured: Server, admin: httpx.Client, monkeypatch: pytest.MonkeyPatch
) -> None:
    map_id = admin.post("/v1/maps", json={"name": "replayed"}).json()["id"]
    frames = sim_frames(5)
    with pytest.raises(ReplayHTTPError, match="401"):
        replay_http(frames, url=secured.url, map_id=map_id, progress=False, attempts=1)
    monkeypatch.setenv(API_KEY_VARIABLE, _key(admin, map_id, "write"))
    run = replay_http(frames, url=secured.url, map_id=map_id, progress=False)
    assert len(run.results) == len(frames)
    tum = fetch_tum(secured.url, map_id, "r1")
    assert len([ln for ln in tum.splitlines() if not ln.startswith("#")]) == len(frames)


def test_revoking_a_key_ends_its_open_event_stream(
    secured: Server, admin: httpx.Client, maps: dict[str, str]
) -> None:
    map_id = maps["A"]
    created = admin.post(f"/v1/maps/{map_id}/keys", json={"scope": "read"}).json()
    path = f"/v1/maps/{map_id}/events"
    with httpx.Client(base_url=secured.url, timeout=10) as c:
        params = {"since": 0, "access_token": created["key"]}
        with c.stream("GET", path, params=params) as r:
            assert r.status_code == 200
            lines = r.iter_lines()
            assert next(lines).startswith(": covslam events")
            assert admin.delete(f"/v1/maps/{map_id}/keys/{created['id']}").status_code == 204
            t0 = time.monotonic()
            for _ in lines:  # the backlog, if not sent yet; then the server ends the stream
                pass  # (a stream left open would raise httpx's 10 s read timeout here)
            assert time.monotonic() - t0 < 5
