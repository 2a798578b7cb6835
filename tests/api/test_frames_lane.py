"""The frames lane answers every request exactly as the route does: each request below
goes to an app with the lane and to one without it (the same service, a stand-in that
answers or refuses as a worker would), and the two answers must be the same bytes."""

from __future__ import annotations

import asyncio
import json
from typing import Any

import httpx
import pytest

from api.app import create_app
from api.routes.frames import FramesLane
from service.errors import ServiceError, WorkerUnavailable, invalid_frame, unknown_map
from service.frame_results import FrameReply
from service.keys import key_hash
from service.settings import Settings
from service.store import KeyRecord

ADMIN = "a" * 40
WRITER = "w" * 40
READER = "r" * 40
FRAME = {"robot": "r1", "seq": 3, "stamp": 1.0, "observations": []}
RESULT = json.dumps({"frame_id": 7, "robot": "r1", "seq": 3})


class Service:
    """Map "m" exists; a frame's robot says what the worker answers."""

    pool = type("Pool", (), {"shared": False})()

    def __init__(self) -> None:
        self.submitted: list[dict[str, Any]] = []
        self.keys = {
            key_hash(WRITER): KeyRecord("k1", "m", "write", key_hash(WRITER), 0.0),
            key_hash(READER): KeyRecord("k2", "m", "read", key_hash(READER), 0.0),
        }

    def record(self, map_id: str) -> None:
        if map_id != "m":
            raise unknown_map(map_id)

    def find_key(self, secret: str) -> KeyRecord | None:
        return self.keys.get(key_hash(secret))

    async def submit(self, map_id: str, frame: dict[str, Any], image: Any = None) -> FrameReply:
        self.submitted.append(frame)
        robot = frame.get("robot")
        if robot == "invalid":
            raise invalid_frame("observations[0].bearing", "must be a number, got string")
        if robot == "conflict":
            raise ServiceError(409, "duplicate-seq", "Duplicate frame", "seq: used", field="seq")
        if robot == "broken":
            raise ServiceError(500, "internal-error", "Internal error", "a bug")
        if robot == "restarting":
            raise WorkerUnavailable("the worker is restarting", retry_after_s=2)
        timing = {"total": 3.0}
        return FrameReply(RESULT, replayed=robot == "retry", timing_ms=timing, live=4)


def _app(settings: Settings, *, lane: bool) -> Any:
    app = create_app(settings)
    if not lane:
        app.user_middleware = [m for m in app.user_middleware if m.cls is not FramesLane]
    app.state.service = Service()
    return app


def _requests() -> list[tuple[str, str, dict[str, str], bytes]]:
    """(method, path, headers, body) of every kind of frame request."""
    json_type = {"content-type": "application/json"}
    body = json.dumps(FRAME).encode()
    out = [
        ("POST", "/v1/maps/m/frames", json_type, body),
        ("POST", "/v1/maps/m/frames", {"content-type": "application/json; charset=utf-8"}, body),
        ("POST", "/v1/maps/nothere/frames", json_type, body),
        ("POST", "/v1/maps/" + "x" * 65 + "/frames", json_type, body),
        ("POST", "/v1/maps/m/frames/", json_type, body),
        ("POST", "/v1/maps/m/frames", {"content-type": "text/plain"}, body),
        ("POST", "/v1/maps/m/frames", {}, body),
        ("POST", "/v1/maps/m/frames", json_type, b'{"robot": "r1", "seq": '),
        ("POST", "/v1/maps/m/frames", json_type, b'{"stamp": NaN}'),
        ("POST", "/v1/maps/m/frames", json_type, b'{"stamp": 1e999}'),
        ("POST", "/v1/maps/m/frames", json_type, b"[1, 2]"),
        ("POST", "/v1/maps/m/frames", json_type, b"[" * 100_000 + b"]" * 100_000),
        ("POST", "/v1/maps/m/frames", json_type, b"{}" + b" " * (2 << 20)),  # over the limit
        ("GET", "/v1/maps/m/frames", {}, b""),
    ]
    for robot in ("invalid", "conflict", "broken", "restarting", "retry"):
        out.append(("POST", "/v1/maps/m/frames", json_type, json.dumps({"robot": robot}).encode()))
    return out


def _answers(settings: Settings, keys: list[str | None]) -> tuple[list[Any], list[Any]]:
    async def run(lane: bool) -> list[Any]:
        app = _app(settings, lane=lane)
        transport = httpx.ASGITransport(app=app)
        out = []
        async with httpx.AsyncClient(transport=transport, base_url="http://t") as client:
            for key in keys:
                auth = {} if key is None else {"authorization": f"Bearer {key}"}
                for method, path, headers, body in _requests():
                    sent = {**headers, **auth}
                    r = await client.request(method, path, headers=sent, content=body)
                    answer = (r.status_code, sorted(r.headers.items()), r.content)
                    out.append((method, path, key, *answer))
        registry = app.state.metrics.registry
        out.append(("submitted", len(app.state.service.submitted)))
        for name in ("covslam_frames_total", "covslam_frames_replayed_total"):
            out.append((name, registry.get_sample_value(name, {"map": "m"})))
        for status in ("400", "401", "404", "409", "422", "500"):
            labels = {"status": status}
            out.append((status, registry.get_sample_value("covslam_frames_rejected_total", labels)))
        return out

    return asyncio.run(run(True)), asyncio.run(run(False))


@pytest.mark.parametrize(
    ("admin_key", "keys"),
    [(None, [None]), (ADMIN, [None, ADMIN, WRITER, READER, "nonsense" * 5, ""])],
)
def test_the_lane_answers_as_the_route(admin_key: str | None, keys: list[str | None]) -> None:
    settings = Settings(auth={"admin_key": admin_key}, api={"max_body_bytes": 1 << 20})
    with_lane, without = _answers(settings, keys)
    assert len(with_lane) == len(without)
    for got, want in zip(with_lane, without, strict=True):
        assert got == want
    statuses = {a[3] for a in with_lane if len(a) > 3}
    expected = {200, 400, 404, 405, 409, 413, 415, 422, 500, 503}
    assert expected | ({401, 403} if admin_key else set()) <= statuses | {307}


def test_a_plain_frame_takes_the_lane(monkeypatch: pytest.MonkeyPatch) -> None:
    from api.routes import frames

    taken: list[str] = []
    admitted = frames._admitted

    async def counting(request: Any, map_id: str, raw: bytes) -> Any:
        frame = await admitted(request, map_id, raw)
        taken.append("lane" if frame is not None else "route")
        return frame

    monkeypatch.setattr(frames, "_admitted", counting)
    _answers(Settings(), [None])
    assert taken.count("lane") == 7  # the frame (two content types), the five a worker answers
    assert taken.count("route") == 6  # unknown map, malformed, NaN, 1e999, array, too deep


def test_the_lane_passes_the_lifespan_and_other_requests_through() -> None:
    seen: list[str] = []

    async def inner(scope: Any, receive: Any, send: Any) -> None:
        seen.append(scope["type"])

    async def nothing() -> Any:
        return {"type": "lifespan.startup"}

    async def ignore(message: Any) -> None:
        return None

    lane = FramesLane(inner)
    asyncio.run(lane({"type": "lifespan"}, nothing, ignore))
    get = {"type": "http", "method": "GET", "path": "/v1/maps/m/frames", "headers": []}
    asyncio.run(lane(get, nothing, ignore))
    assert seen == ["lifespan", "http"]
