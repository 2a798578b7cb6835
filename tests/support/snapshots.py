"""What a map's SQLite file says about its snapshots (tests and benchmarks)."""

from __future__ import annotations

import sqlite3
from pathlib import Path


def unsnapshotted(path: Path) -> int:
    """Frames of the map's log after its latest snapshot: what opening it replays."""
    conn = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
    try:
        last = conn.execute("SELECT coalesce(max(id), 0) FROM frames").fetchone()[0]
        upto = conn.execute("SELECT coalesce(max(upto), 0) FROM snapshots").fetchone()[0]
    finally:
        conn.close()
    return int(last - upto)
