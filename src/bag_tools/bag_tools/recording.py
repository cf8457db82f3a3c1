"""A bag being written by a thread of its own, without ROS: the recorder's subscriptions
only enqueue serialized messages; the queue is bounded in bytes (the oldest dropped and
counted per topic when the writer falls behind), drained in batches into a ``BagWriter``
and flushed every ``flush_period``, so a crash loses at most that long of data. A write
that fails (disk full) stops the recording and keeps what reached the disk."""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

from bag_tools.bag_writer import BagError, BagWriter, TopicInfo

# (topic, serialized data, log time [ns], publish time [ns])
QueuedMessage = tuple[str, bytes, int, int]


class MessageQueue:
    """FIFO of queued messages bounded in bytes; when full, the oldest messages are dropped
    and counted per topic. Thread-safe."""

    def __init__(self, max_bytes: int) -> None:
        self._items: collections.deque[QueuedMessage] = collections.deque()
        self._bytes = 0
        self._max_bytes = max_bytes
        self._condition = threading.Condition()
        self._closed = False
        self.dropped: collections.Counter[str] = collections.Counter()

    def put(self, item: QueuedMessage) -> None:
        """Queue ``item``; drop the oldest while over ``max_bytes`` (0: unbounded)."""
        with self._condition:
            self._items.append(item)
            self._bytes += len(item[1])
            while self._max_bytes and self._bytes > self._max_bytes and len(self._items) > 1:
                old = self._items.popleft()
                self._bytes -= len(old[1])
                self.dropped[old[0]] += 1
            self._condition.notify()

    def take_all(self, timeout: float) -> list[QueuedMessage] | None:
        """All queued items (possibly none after ``timeout`` [s]); None once closed and empty."""
        with self._condition:
            if not self._items and not self._closed:
                self._condition.wait(timeout)
            if not self._items and self._closed:
                return None
            items = list(self._items)
            self._items.clear()
            self._bytes = 0
            return items

    def close(self) -> None:
        """No more items: ``take_all`` returns what is left, then None."""
        with self._condition:
            self._closed = True
            self._condition.notify_all()


class BagRecording:
    """Messages written to ``bag`` by a writer thread.

    ``on_failure(error)`` is called from the writer thread once writing failed (the
    recording has stopped by then). ``close`` writes what is queued and closes the bag.
    """

    def __init__(
        self,
        bag: BagWriter,
        max_cache_size: int,
        flush_period: float,
        on_failure: Callable[[Exception], None],
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.bag = bag
        self._lock = threading.Lock()  # the bag is used by the caller's and the writer thread
        self._queue = MessageQueue(max_cache_size)
        self._flush_period = flush_period  # [s]; 0 = only when a chunk is full
        self._on_failure = on_failure
        self._clock = clock
        self.bytes_written = 0  # serialized message bytes handed to the bag (writer thread)
        self.write_error: Exception | None = None
        self.closed = False
        self._thread = threading.Thread(target=self._write_loop, name='bag_writer', daemon=True)
        self._thread.start()

    @property
    def dropped(self) -> collections.Counter[str]:
        """Messages dropped per topic because the writer fell behind."""
        return self._queue.dropped

    @property
    def topics(self) -> Sequence[TopicInfo]:
        """The bag's topics with their message counts so far."""
        return self.bag.topics

    def add_topic(self, name: str, type_name: str, offered_qos: list[dict[str, Any]]) -> None:
        """Record topic ``name`` from now on."""
        with self._lock:
            self.bag.add_topic(name, type_name, offered_qos)

    def put(self, topic: str, data: bytes, log_time_ns: int, publish_time_ns: int) -> None:
        """Queue one serialized message (any thread; never blocks on the disk)."""
        self._queue.put((topic, data, log_time_ns, publish_time_ns))

    def _write_loop(self) -> None:
        last_flush = self._clock()
        wait = self._flush_period if self._flush_period > 0 else 1.0
        while True:
            items = self._queue.take_all(timeout=wait)
            if items is None:
                return
            try:
                with self._lock:
                    for topic, data, log_time_ns, publish_time_ns in items:
                        self.bag.write(topic, data, log_time_ns, publish_time_ns)
                        self.bytes_written += len(data)
                    if self._flush_period > 0 and self._clock() - last_flush >= self._flush_period:
                        self.bag.flush()
                        last_flush = self._clock()
            except (OSError, BagError) as error:
                # Disk full or similar: stop recording, keep what is on disk.
                self.write_error = error
                self._queue.close()
                self._on_failure(error)
                return

    def close(self) -> Exception | None:
        """Write what is queued and close the bag; the error if closing failed. Idempotent."""
        if self.closed:
            return None
        self.closed = True
        self._queue.close()
        self._thread.join()
        with self._lock:
            try:
                self.bag.close()
            except (OSError, BagError) as error:
                self.write_error = self.write_error or error
                return error
        return None
