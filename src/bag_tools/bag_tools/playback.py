"""When a player publishes each message, without ROS: bag time ``t`` is played at
``start + (t - t_0) / rate`` on a monotonic clock, so no drift accumulates however long
the bag; a rate change re-anchors at the bag time reached, so playback neither jumps nor
stalls; a message already due is published at once (a late player catches up)."""

from __future__ import annotations

import threading
import time
from collections.abc import Callable


class PlaybackClock:
    """The schedule of a playback at ``rate`` (1 = recorded pace), on ``clock`` [s]."""

    def __init__(self, rate: float, clock: Callable[[], float] = time.monotonic) -> None:
        self._lock = threading.Lock()
        self._clock = clock
        self.rate = rate
        # Bag time _anchor_bag [ns] is played at clock time _anchor_wall [s].
        self._anchor_wall: float | None = None
        self._anchor_bag: int | None = None

    def start(self, bag_time_ns: int) -> None:
        """Play ``bag_time_ns`` now (the first message of a pass)."""
        with self._lock:
            self._anchor_wall, self._anchor_bag = self._clock(), bag_time_ns

    def set_rate(self, rate: float) -> None:
        """Play at ``rate`` from the bag time reached now."""
        with self._lock:
            if self._anchor_wall is not None and self._anchor_bag is not None:
                now = self._clock()
                self._anchor_bag += int((now - self._anchor_wall) * self.rate * 1e9)
                self._anchor_wall = now
            self.rate = rate

    def due_in(self, log_time_ns: int) -> float:
        """[s] until the message of ``log_time_ns`` is due (<= 0: publish it now)."""
        with self._lock:
            if self._anchor_wall is None or self._anchor_bag is None:
                raise RuntimeError('PlaybackClock.start() first')
            due = self._anchor_wall + (log_time_ns - self._anchor_bag) / 1e9 / self.rate
            return due - self._clock()
