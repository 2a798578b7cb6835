"""Under load, over HTTP: event streams that do not read hold no frame up and still get
every event; a SIGTERM snapshots every map, so the next start replays no log."""

from __future__ import annotations

import json
import socket
from pathlib import Path

import httpx

from tests.e2e.conftest import Server, create_map, frame_dicts, post_all, sim_frames
from tests.support.snapshots import unsnapshotted

FRAMES = frame_dicts(sim_frames(30))


def _subscribe(port: int, map_id: str) -> socket.socket:
    """An SSE stream of the map's events, opened and then not read."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=30)
    sock.sendall(
        f"GET /v1/maps/{map_id}/events?since=0 HTTP/1.1\r\nHost: x\r\n"
        "Accept: text/event-stream\r\n\r\n".encode()
    )
    return sock


def _frame_events(sock: socket.socket, count: int) -> list[dict]:
    """Read the stream until `count` frame events arrived; their data."""
    buf = b""
    while buf.count(b"event: frame\n") < count:
        chunk = sock.recv(1 << 16)
        assert chunk, "stream ended early"
        buf += chunk
    out = []
    for block in buf.split(b"\n\n"):
        lines = block.decode().split("\n")
        if "event: frame" in lines:
            data = next(line for line in lines if line.startswith("data: "))
            out.append(json.loads(data.removeprefix("data: ")))
    return out


def test_streams_that_do_not_read_hold_no_frame_up(server: Server, client: httpx.Client) -> None:
    map_id = create_map(client, "streams")
    streams = [_subscribe(server.port, map_id) for _ in range(50)]
    try:
        results = post_all(client, map_id, FRAMES)  # while no stream reads
        for sock in streams:
            got = _frame_events(sock, len(FRAMES))
            assert [e["seq"] for e in got] == [r["seq"] for r in results]
            assert got == results
    finally:
        for sock in streams:
            sock.close()


def test_sigterm_snapshots_every_map_and_a_start_replays_nothing(tmp_path: Path) -> None:
    server = Server(tmp_path / "data")
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            ids = [create_map(c, f"m{i}") for i in range(3)]
            for k, map_id in enumerate(ids):
                post_all(c, map_id, FRAMES[: 10 + 5 * k])  # far below snapshot_every
            poses = [c.get(f"/v1/maps/{m}/pose").json() for m in ids]
    finally:
        server.stop()  # SIGTERM
    for map_id in ids:
        assert unsnapshotted(tmp_path / "data" / "maps" / f"{map_id}.sqlite") == 0
    server.start()
    try:
        with httpx.Client(base_url=server.url, timeout=60) as c:
            assert [c.get(f"/v1/maps/{m}/pose").json() for m in ids] == poses
            more = post_all(c, ids[0], FRAMES[10:12])
            assert [r["seq"] for r in more] == [10, 11]
    finally:
        server.stop()
