"""Each map's event feed in the API process: the events its frames stored, kept in
memory and encoded once as server-sent events, and the waiters woken when new ones
arrive. An event stream that starts or falls behind the feed reads the store instead.
"""

from __future__ import annotations

import asyncio
import itertools
from collections import deque

EventRows = list[tuple[int, str, str]]
"""Stored events: (id, kind, data JSON), oldest first."""


class Notifier:
    """Wakes the waiters of a map when new events were stored for it, and keeps each
    map's latest events in memory (a feed), so that any number of event streams read
    them without a store query each."""

    def __init__(self, feed_size: int = 1000) -> None:
        self._events: dict[str, asyncio.Event] = {}
        self._feeds: dict[str, deque[tuple[int, str, str, bytes]]] = {}
        """Per map: (id, kind, data, the event as SSE bytes), ids consecutive."""
        self._feed_size = feed_size

    def handle(self, map_id: str) -> asyncio.Event:
        """An event set at the next `notify(map_id)`; take it *before* reading the events."""
        return self._events.setdefault(map_id, asyncio.Event())

    def notify(self, map_id: str) -> None:
        event = self._events.pop(map_id, None)
        if event is not None:
            event.set()

    def publish(self, map_id: str, rows: EventRows) -> None:
        """Events a frame stored (ids consecutive and after those fed before, else the
        feed restarts with them), then wake the map's waiters."""
        if rows:
            feed = self._feeds.get(map_id)
            if feed is None or not feed or feed[-1][0] + 1 != rows[0][0]:
                feed = self._feeds[map_id] = deque(maxlen=self._feed_size)
            feed.extend((*row, sse_bytes([row])) for row in rows)  # encoded once for all
        self.notify(map_id)

    def forget(self, map_id: str) -> None:
        self._feeds.pop(map_id, None)
        self.notify(map_id)

    def _fed(self, map_id: str, after: int) -> list[tuple[int, str, str, bytes]] | None:
        feed = self._feeds.get(map_id)
        if not feed or feed[0][0] > after + 1:
            return None
        return list(itertools.islice(feed, max(0, after + 1 - feed[0][0]), None))

    def fed_sse(self, map_id: str, after: int) -> tuple[int, bytes] | None:
        """(the last id, the SSE bytes) of the fed events with id > `after` ((`after`,
        b"") if none), or None when the feed does not reach back to `after`."""
        fed = self._fed(map_id, after)
        if fed is None:
            return None
        return (fed[-1][0], b"".join(row[3] for row in fed)) if fed else (after, b"")


def sse_bytes(rows: EventRows) -> bytes:
    """Events as server-sent events (`id`, `event`, `data` lines each)."""
    return "".join(f"id: {i}\nevent: {kind}\ndata: {data}\n\n" for i, kind, data in rows).encode()
