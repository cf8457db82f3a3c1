"""The newest input, processed in a worker thread: callbacks stay thin, and inputs that
arrive while one is being processed replace the waiting one (counted as dropped)."""
import threading


class LatestWorker:
    """Runs ``process(item)`` in a thread for the newest ``submit``ted item;
    ``on_error(error)`` gets any exception, so the node keeps serving."""

    def __init__(self, process, on_error, name):
        self._process = process
        self._on_error = on_error
        self._pending = None
        self._closed = False
        self._wakeup = threading.Condition()
        self.dropped = 0
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)
        self._thread.start()

    def submit(self, item):
        with self._wakeup:
            if self._pending is not None:
                self.dropped += 1
            self._pending = item
            self._wakeup.notify()

    def _run(self):
        while True:
            with self._wakeup:
                while self._pending is None and not self._closed:
                    self._wakeup.wait(0.5)
                if self._closed:
                    return
                item, self._pending = self._pending, None
            try:
                self._process(item)
            except Exception as error:  # noqa: BLE001 - reported as a diagnostic, keep serving
                self._on_error(error)

    def close(self):
        with self._wakeup:
            self._closed = True
            self._wakeup.notify()
        self._thread.join(timeout=5.0)
