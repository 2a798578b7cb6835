"""The measure the worker pool balances maps by, and its choice of a move.

A map's load is the work it keeps in flight: the time-averaged number of its requests
waiting or being computed (by Little's law its clients' rate times the time each
request spends) times the worker time one of its requests takes (`MapLoad`). A worker
serves its requests in turn, so equal loads give the maps of all workers the same rate.
`choose_move` picks the map whose move from the busiest to the least busy worker evens
them out best, if the gap is clear and the move narrows it enough; the pool
(service.pool.WorkerPool) measures, asks and moves.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

MOVE_COOLDOWN_S = 10.0
"""A map that moved stays where it is for at least this long (no ping-pong)."""
SETTLE_INTERVALS = 4
"""After a move, the balancer waits this many intervals (the loads it measures settle)."""
MIN_LOAD_GAP = 0.005
"""Loads (seconds of work in flight, time-averaged) two workers may differ by without a
move..."""
MIN_RELATIVE_GAP = 0.25
"""...or by this fraction of the busiest worker's load."""
ACTIVE_S = 1.0
"""A map whose last request ended this recently counts as busy when a map is dealt at
its first frame (a client between two frames)."""
MOVE_GAIN = 0.6
"""A move must leave at most this fraction of the gap it closes (6:2 equal maps -> 5:3
leaves 1/2; a move that mostly swaps the roles of the two workers is no gain)."""


@dataclass
class MapLoad:
    """A map's requests in flight integrated over time, and the worker time each takes:
    the balancer's measure."""

    inflight: int = 0
    area: float = 0.0
    """Integral of `inflight` over time since the last `sample`, request-seconds."""
    since: float = field(default_factory=time.monotonic)
    waiting: float = 0.0
    """Smoothed time-averaged requests in flight."""
    service_s: float = 0.0
    """Smoothed worker time of one request, seconds."""
    load: float = 0.0
    """`waiting` x `service_s`: the work the map keeps in flight, seconds."""
    moved: float = -MOVE_COOLDOWN_S
    ended: float = -ACTIVE_S
    """When its last request ended (time.monotonic)."""

    def change(self, delta: int, now: float) -> None:
        self.area += self.inflight * (now - self.since)
        self.since = now
        self.inflight += delta
        if delta < 0:
            self.ended = now

    def active(self, now: float) -> bool:
        """A request in flight, or one that ended within ACTIVE_S."""
        return self.inflight > 0 or now - self.ended < ACTIVE_S

    def served(self, seconds: float) -> None:
        """A request of the map took the worker `seconds`."""
        self.service_s = seconds if not self.service_s else 0.9 * self.service_s + 0.1 * seconds

    def sample(self, now: float, interval_s: float) -> float:
        """Fold the time since the last sample into `load` (half old, half new)."""
        self.change(0, now)
        self.waiting = 0.5 * self.waiting + 0.5 * self.area / max(interval_s, 1e-9)
        self.area = 0.0
        self.load = self.waiting * self.service_s
        return self.load


def choose_move(
    totals: dict[int, float], movable: dict[int, dict[str, float]], *, min_gap: float = MIN_LOAD_GAP
) -> tuple[str, int, int] | None:
    """(map, from worker, to worker) that best evens out the busiest and the least busy
    worker, or None. `totals`: each worker's load; `movable`: per worker, the loads of
    the maps that may move. Only a gap g of at least `min_gap` and MIN_RELATIVE_GAP of
    the busiest's load counts (measured loads are noisy), and only a move that narrows
    it to MOVE_GAIN of itself or less: a map of load l leaves a gap |g - 2l|; the
    smallest wins."""
    if len(totals) < 2:
        return None
    busiest = max(totals, key=lambda w: totals[w])
    idlest = min(totals, key=lambda w: totals[w])
    gap = totals[busiest] - totals[idlest]
    if gap < max(min_gap, MIN_RELATIVE_GAP * totals[busiest]):
        return None
    maps = movable.get(busiest, {})
    candidates = [(abs(gap - 2 * load), m) for m, load in maps.items() if load > 0]
    best = min(candidates, default=None)
    if best is None or best[0] > MOVE_GAIN * gap:
        return None
    return best[1], busiest, idlest
