"""A real client of the REST API: post a frame sequence to a running service.

Retries on 503 (honouring Retry-After) and on connection errors, so a replay
survives a worker restart or a service restart: `(robot, seq)` makes every retry
safe. Used by ``covslam replay ... --url URL``; with ``COVSLAM_API_KEY`` set, every
request carries it (``Authorization: Bearer``). A frame with an image
(`service.offline.replay.ImageFrame`) is posted as multipart/form-data: ``meta`` (the
frame JSON without observations) and ``image`` (the file's bytes).

`post_until_answered` posts one frame until the service answers it (a client riding out a
failover); `check_log` re-posts a map's frames and counts what its log lost or duplicated.
"""

from __future__ import annotations

import json
import logging
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import httpx
import numpy as np
from tqdm import tqdm

from graph.types import FrameInput
from service.frames_io import frame_to_dict
from service.offline.replay import ImageFrame

log = logging.getLogger(__name__)


class ReplayHTTPError(RuntimeError):
    """The service refused a frame (4xx) or stayed unavailable past the retries."""


@dataclass
class HttpReplay:
    """What a replay over HTTP produced."""

    map_id: str
    results: list[dict[str, Any]] = field(default_factory=list)
    latency_ms: list[float] = field(default_factory=list)
    """Client-side round trip of each frame, milliseconds."""
    retries: int = 0

    def summary(self) -> str:
        ms = np.asarray(self.latency_ms)
        if ms.size == 0:
            return f"map {self.map_id}: no frames"
        return (
            f"map {self.map_id}: {len(ms)} frames over HTTP, latency p50 "
            f"{np.percentile(ms, 50):.2f} ms, p99 {np.percentile(ms, 99):.2f} ms, "
            f"{self.retries} retries"
        )


def _request(
    client: httpx.Client, method: str, path: str, *, attempts: int, **kwargs: Any
) -> tuple[httpx.Response, int]:
    """One request with retries on 503 and transport errors; (response, retries used)."""
    for attempt in range(attempts):
        try:
            response = client.request(method, path, **kwargs)
        except httpx.TransportError as exc:
            if attempt == attempts - 1:
                raise ReplayHTTPError(f"{method} {path}: {exc}") from exc
            time.sleep(min(0.2 * 2**attempt, 5.0))
            continue
        if response.status_code != 503:
            return response, attempt
        time.sleep(float(response.headers.get("retry-after", "1")))
    raise ReplayHTTPError(f"{method} {path}: still 503 after {attempts} attempts")


_IMAGE_TYPES = {".png": "image/png", ".jpg": "image/jpeg", ".jpeg": "image/jpeg"}


def image_frame_parts(item: ImageFrame) -> dict[str, Any]:
    """httpx keyword arguments (`data`, `files`) posting one image frame as multipart."""
    meta = frame_to_dict(item.frame)
    del meta["observations"]
    media = _IMAGE_TYPES.get(item.image_path.suffix.lower(), "application/octet-stream")
    return {
        "data": {"meta": json.dumps(meta, separators=(",", ":"))},
        "files": {"image": (item.image_path.name, item.image_path.read_bytes(), media)},
    }


API_KEY_VARIABLE = "COVSLAM_API_KEY"
"""The environment variable with the key a client sends (a map key of scope write, or the
admin key to create maps)."""


def _client(url: str, timeout_s: float) -> httpx.Client:
    key = os.environ.get(API_KEY_VARIABLE)
    headers = {"Authorization": f"Bearer {key}"} if key else None
    return httpx.Client(base_url=url.rstrip("/"), timeout=timeout_s, headers=headers)


def replay_http(
    frames: Sequence[FrameInput | ImageFrame],
    *,
    url: str,
    map_id: str | None = None,
    name: str = "replay",
    config: dict[str, Any] | None = None,
    progress: bool | None = None,
    attempts: int = 30,
    timeout_s: float = 60.0,
) -> HttpReplay:
    """Post `frames` in order to `url` (into `map_id`, or a new map with `config`)."""
    with _client(url, timeout_s) as client:
        if map_id is None:
            body = {"name": name, "config": config or {}}
            r, _ = _request(client, "POST", "/v1/maps", json=body, attempts=attempts)
            if r.status_code != 201:
                raise ReplayHTTPError(f"creating the map: {r.status_code} {r.text}")
            map_id = str(r.json()["id"])
        out = HttpReplay(map_id)
        bar = tqdm(frames, unit="frame", disable=None if progress is None else not progress)
        for item in bar:
            if isinstance(item, ImageFrame):
                frame, body = item.frame, image_frame_parts(item)
            else:
                frame, body = item, {"json": frame_to_dict(item)}
            t0 = time.perf_counter()
            r, retries = _request(
                client, "POST", f"/v1/maps/{map_id}/frames", attempts=attempts, **body
            )
            out.latency_ms.append(1e3 * (time.perf_counter() - t0))
            out.retries += retries
            if r.status_code != 200:
                raise ReplayHTTPError(
                    f"frame robot={frame.robot} seq={frame.seq}: {r.status_code} {r.text}"
                )
            out.results.append(r.json())
        log.info(out.summary())
        return out


def fetch_tum(url: str, map_id: str, robot: str, *, attempts: int = 30) -> str:
    """One robot's trajectory as TUM text."""
    with _client(url, 60.0) as client:
        r, _ = _request(
            client,
            "GET",
            f"/v1/maps/{map_id}/trajectory",
            params={"robot": robot, "format": "tum"},
            attempts=attempts,
        )
        if r.status_code != 200:
            raise ReplayHTTPError(f"trajectory: {r.status_code} {r.text}")
        return r.text


def post_until_answered(client: httpx.Client, map_id: str, frame: dict[str, Any]) -> dict[str, Any]:
    """Post a frame, retrying on 503 (after Retry-After) and transport errors, until the
    service answers; its result (any other status raises)."""
    while True:
        try:
            r = client.post(f"/v1/maps/{map_id}/frames", json=frame)
        except httpx.TransportError:
            time.sleep(0.2)
            continue
        if r.status_code == 503:
            time.sleep(float(r.headers.get("retry-after", "1")))
            continue
        if r.status_code != 200:
            raise ReplayHTTPError(f"map {map_id} seq {frame['seq']}: {r.status_code} {r.text}")
        result: dict[str, Any] = r.json()
        return result


def check_log(
    url: str,
    map_id: str,
    frames: list[dict[str, Any]],
    acked: list[dict[str, Any]],
    headers: dict[str, str] | None = None,
) -> dict[str, Any]:
    """Lost and duplicated frames of a map: re-post every frame (each must be answered
    from the log with its acknowledged result) and count the log's frames."""
    lost = changed = 0
    with httpx.Client(base_url=url, timeout=120, headers=headers) as c:
        for frame, result in zip(frames, acked, strict=True):
            r = c.post(f"/v1/maps/{map_id}/frames", json=frame)
            if r.headers.get("idempotent-replayed") != "true":
                lost += 1
            elif r.json() != result:
                changed += 1
        logged = c.get(f"/v1/maps/{map_id}").json()["counts"]["frames"]
    return {
        "posted": len(frames),
        "acknowledged": len(acked),
        "logged": logged,
        "lost": lost,
        "duplicated": logged - len(frames),
        "answer_changed_on_retry": changed,
    }
