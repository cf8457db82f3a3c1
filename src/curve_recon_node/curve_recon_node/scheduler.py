"""Which synchronized captures curve_recon_node reconstructs, without ROS: one after the
calibration becomes ready or changes (retried at most once a second until one succeeds),
one for each wait of ~/reconstruct calls, none of the calibration chart. The calls wait
here, with their deadlines, until a capture answers them or they time out. Thread-safe:
the node's callbacks, its timers and its worker call it. Unit-tested with an injected
clock in tests/unit/test_curve_scheduler.py.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from collections.abc import Callable, Collection
from dataclasses import dataclass, field

from vgm_common.settings import setting
from vgm_common.topics import CAMERA_NAMES

# ~/reconstruct calls waiting at once; more are refused at once (a caller that loops on
# the service must not grow the node without bound).
MAX_WAITING_CALLS = 100
AUTO_RETRY_S = 1.0  # [s] between automatic attempts until one succeeds
CHART_STAMPS_KEPT = 200  # stamps of chart poses remembered

Reply = Callable[[bool, str], None]  # answers one ~/reconstruct call: (success, message)


@dataclass(frozen=True)
class CaptureSettings:
    """When and from which views curve_recon_node reconstructs: the one source of its
    parameters of these names."""

    views: int = setting(
        3,
        'Views to use: 3 (left, right, aux) or 2 (left, right). With 3 but no aux '
        'calibration after aux_wait, two views are used.',
        range=(2, 3),
    )
    use_depth_normals: bool = setting(
        True, 'Approach axis from /depth/fused surface normals when available (else base -z).'
    )
    normal_window_px: int = setting(
        15, "Depth window for each normal's plane fit.", unit='px', range=(3, 101)
    )
    sync_max_wait: float = setting(
        1.0, 'An incomplete capture is dropped after this.', unit='s', range=(0.01, 60.0)
    )
    aux_wait: float = setting(
        2.0,
        "With views 3, how long to wait for the aux camera's calibration before "
        'reconstructing from two views.',
        unit='s',
        range=(0.0, 600.0),
    )
    service_timeout: float = setting(
        20.0,
        'Longest a reconstruct call waits for its capture and result.',
        unit='s',
        range=(0.1, 600.0),
    )


def paired_cameras(views: int) -> tuple[str, ...]:
    """The cameras whose images make a capture for ``views`` (3: all, 2: left and right)."""
    return CAMERA_NAMES if views == 3 else CAMERA_NAMES[:2]


@dataclass
class WaitingCall:
    """A ~/reconstruct call and when it times out."""

    reply: Reply
    deadline: float  # clock() [s]


@dataclass
class CaptureJob:
    """A capture to reconstruct, with the calls it answers."""

    stamp_ns: int
    calls: list[WaitingCall] = field(default_factory=list)


class CaptureScheduler:
    """Args:
    clock: monotonic seconds (``time.monotonic``; a test's own clock).
    """

    def __init__(self, clock: Callable[[], float] = time.monotonic) -> None:
        self.clock = clock
        self._lock = threading.Lock()
        self._auto_pending = False  # set when the calibration becomes ready or changes
        self._last_auto_attempt = -float('inf')
        self._chart_stamps: deque[int] = deque(maxlen=CHART_STAMPS_KEPT)  # [ns]
        self._calls: list[WaitingCall] = []
        self.skipped_chart = 0  # captures not reconstructed: the chart was on show
        self._left_right_since: float | None = None  # clock() when both became calibrated

    def cameras_to_use(
        self, calibrated: Collection[str], views: int, aux_wait: float
    ) -> tuple[str, ...] | None:
        """The cameras to reconstruct from now, given those ``calibrated``, or None while
        there are too few: left and right, and aux with ``views`` 3 (two views once aux
        has not come ``aux_wait`` [s] after the other two)."""
        if not {'left', 'right'} <= set(calibrated):
            self._left_right_since = None
            return None
        if self._left_right_since is None:
            self._left_right_since = self.clock()
        if views == 3:
            if 'aux' in calibrated:
                return ('left', 'right', 'aux')
            if self.clock() - self._left_right_since < aux_wait:
                return None
        return ('left', 'right')

    @property
    def waiting(self) -> int:
        """~/reconstruct calls waiting for a capture."""
        return len(self._calls)

    def calibration_changed(self) -> None:
        """The rig is (newly) calibrated: reconstruct the next capture."""
        with self._lock:
            self._auto_pending = True
            self._last_auto_attempt = -float('inf')

    def chart_shown(self, stamp_ns: int) -> None:
        """A target pose: the captures of this stamp show the chart, not the curve."""
        with self._lock:
            self._chart_stamps.append(stamp_ns)

    def add_call(self, reply: Reply, timeout: float) -> str | None:
        """A ~/reconstruct call waits for the next capture, at most ``timeout`` [s]; or
        why it is refused (when MAX_WAITING_CALLS wait already: the caller answers it)."""
        with self._lock:
            waiting = len(self._calls)
            if waiting < MAX_WAITING_CALLS:
                self._calls.append(WaitingCall(reply, self.clock() + timeout))
                return None
        return f'{waiting} reconstruct calls are waiting already'

    def take(self, stamp_ns: int) -> CaptureJob | None:
        """A synchronized capture of a calibrated rig: the job to reconstruct (with the
        calls it answers), or None if no reconstruction is wanted now."""
        with self._lock:
            now = self.clock()
            wanted_auto = self._auto_pending and now - self._last_auto_attempt >= AUTO_RETRY_S
            if not (wanted_auto or self._calls):
                return None
            if stamp_ns in self._chart_stamps:
                self.skipped_chart += 1
                return None
            if wanted_auto:
                self._last_auto_attempt = now
            calls, self._calls = self._calls, []
        return CaptureJob(stamp_ns, calls)

    def is_chart(self, job: CaptureJob) -> bool:
        """Whether the job's capture turned out to show the chart (its pose came after
        the images); its calls then wait for the next capture."""
        with self._lock:
            if job.stamp_ns not in self._chart_stamps:
                return False
            self.skipped_chart += 1
            self._calls = job.calls + self._calls
            job.calls = []
            return True

    def put_back(self, job: CaptureJob) -> None:
        """A job dropped before it ran: its calls wait for the next capture."""
        with self._lock:
            self._calls = job.calls + self._calls

    def succeeded(self) -> None:
        """A capture was reconstructed: no more automatic attempts until the next
        calibration change."""
        with self._lock:
            self._auto_pending = False

    def expired(self) -> list[WaitingCall]:
        """The calls past their deadline, no longer waiting (the caller answers them)."""
        now = self.clock()
        with self._lock:
            expired = [call for call in self._calls if call.deadline <= now]
            self._calls = [call for call in self._calls if call.deadline > now]
        return expired

    def close(self) -> list[WaitingCall]:
        """Every waiting call, no longer waiting (the caller answers them)."""
        with self._lock:
            calls, self._calls = self._calls, []
        return calls
