"""Work taken off the executor thread: callbacks stay thin, a worker thread processes what
they submit, a bounded number of items wait, and what does not fit is counted."""

from __future__ import annotations

import collections
import threading
import traceback
from typing import Any, Callable, Optional

KEEP_CHOICES = ('newest', 'oldest')


class Worker:
    """Runs ``process(item)`` in a thread for each ``submit``ted item, in order; at most
    ``capacity`` items wait. When full, ``keep='newest'`` drops the oldest waiting item (a
    stream where only the latest input matters) and ``keep='oldest'`` refuses the new one
    (every item matters and a refusal must be reported, e.g. calibration views). Dropped
    items are counted in ``dropped`` and handed to ``on_drop`` (e.g. to serve a request a
    dropped item carried). ``on_error(error)`` gets any exception of ``process``, so the
    node keeps serving."""

    def __init__(
        self,
        process: Callable[[Any], None],
        on_error: Callable[[Exception], None],
        name: str,
        capacity: int = 1,
        keep: str = 'newest',
        on_drop: Optional[Callable[[Any], None]] = None,
    ) -> None:
        if capacity < 1 or keep not in KEEP_CHOICES:
            raise ValueError(
                f'capacity {capacity} (>= 1), keep {keep!r} (one of {", ".join(KEEP_CHOICES)})'
            )
        self._process, self._on_error, self._on_drop = process, on_error, on_drop
        self._capacity, self._keep = capacity, keep
        self._waiting: collections.deque[Any] = collections.deque()
        self._closed = False
        self._wakeup = threading.Condition()
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item: Any) -> bool:
        """Queue ``item``; False if it was refused (full, ``keep='oldest'``)."""
        dropped = None
        with self._wakeup:
            if len(self._waiting) >= self._capacity:
                self.dropped += 1
                if self._keep == 'oldest':
                    return False
                dropped = self._waiting.popleft()
            self._waiting.append(item)
            self._wakeup.notify()
        if dropped is not None and self._on_drop is not None:
            self._on_drop(dropped)
        return True

    def submit_if_idle(self, item: Any) -> bool:
        """Queue ``item`` only if nothing is waiting (work that a waiting item makes
        unnecessary); False if it was not queued. Not counted as dropped."""
        with self._wakeup:
            if self._waiting:
                return False
            self._waiting.append(item)
            self._wakeup.notify()
        return True

    def _run(self) -> None:
        while True:
            with self._wakeup:
                while not self._waiting and not self._closed:
                    self._wakeup.wait(0.5)
                if self._closed:
                    return
                item = self._waiting.popleft()
            try:
                self._process(item)
            except Exception as error:  # noqa: BLE001 - reported as a diagnostic, keep serving
                try:
                    self._on_error(error)
                except Exception:  # noqa: BLE001 - a failing report must not end the worker
                    traceback.print_exc()

    def close(self) -> None:
        """Stop after the item being processed; waiting items are not processed."""
        with self._wakeup:
            self._closed = True
            self._wakeup.notify()
        self._thread.join(timeout=5.0)
