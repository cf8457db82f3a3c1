"""Exact-time synchronisation of several topics (what message_filters'
TimeSynchronizer does), without rclpy: the node feeds messages in, complete sets
come out.

A set is complete when every key has a message with the same stamp. Incomplete sets
are dropped once they are older than ``max_wait`` [s] (by the caller's clock) or when
more than ``queue_size`` stamps are pending, and counted in ``dropped``.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable, Iterable
from typing import Any

# A complete set: ``callback(stamp_ns, {key: msg})``; messages of any type.
SetCallback = Callable[[int, dict[str, Any]], None]


class ExactTimeSync:
    """Pair messages of ``keys`` by identical stamp (int nanoseconds)."""

    def __init__(
        self,
        keys: Iterable[str],
        callback: SetCallback,
        queue_size: int = 10,
        max_wait: float = 1.0,
    ) -> None:
        self.keys = tuple(keys)
        self._callback = callback
        self._queue_size = queue_size
        self._max_wait = max_wait
        # stamp_ns -> (arrival time [s], {key: msg})
        self._pending: OrderedDict[int, tuple[float, dict[str, Any]]] = OrderedDict()
        self.matched = 0
        self.dropped = 0  # messages discarded without a complete set
        self._first_arrival: float | None = None  # [s] of any key's first message
        self._last_arrival: dict[str, float] = {}  # key -> [s] of its latest message

    def add(self, key: str, stamp_ns: int, msg: Any, now: float) -> None:
        """Offer one message; calls ``callback(stamp_ns, {key: msg})`` when its set
        completes. ``now`` [s] is the caller's monotonic clock."""
        if key not in self.keys:
            raise KeyError(f'unknown sync key {key!r}; expected one of {self.keys}')
        if self._first_arrival is None:
            self._first_arrival = now
        self._last_arrival[key] = now
        arrived, messages = self._pending.setdefault(stamp_ns, (now, {}))
        if key in messages:
            self.dropped += 1  # a duplicate stamp on one topic: keep the newest
        messages[key] = msg
        if len(messages) == len(self.keys):
            del self._pending[stamp_ns]
            self._drop_older_than(stamp_ns)
            self.matched += 1
            self._callback(stamp_ns, messages)
        self._expire(now)

    def _drop_older_than(self, stamp_ns: int) -> None:
        # Stamps are monotonic per topic, so an older incomplete set can never complete.
        for stale in [s for s in self._pending if s < stamp_ns]:
            self.dropped += len(self._pending.pop(stale)[1])

    def _expire(self, now: float) -> None:
        while self._pending:
            stamp, (arrived, messages) = next(iter(self._pending.items()))
            if now - arrived <= self._max_wait and len(self._pending) <= self._queue_size:
                break
            del self._pending[stamp]
            self.dropped += len(messages)

    def silent(self, now: float, after: float) -> list[str]:
        """The keys without a message for ``after`` [s] while another key had one within
        that time: the topic that keeps every set from completing (a camera that does not
        publish, or publishes under another name). [] while nothing arrives at all."""
        if self._first_arrival is None or not any(
            now - t <= after for t in self._last_arrival.values()
        ):
            return []
        return [
            key
            for key in self.keys
            if now - self._last_arrival.get(key, self._first_arrival) > after
        ]

    @property
    def pending(self) -> int:
        """The number of stamps waiting for their set to complete."""
        return len(self._pending)
