"""A node's health on /diagnostics: rejected input counted and throttled, the published-message
counts, and ``guarded`` callbacks that report instead of dying."""

from __future__ import annotations

import functools
import math
import re
import threading
import time
from collections import deque
from collections.abc import (
    Callable,
    Mapping,
)
from typing import TYPE_CHECKING, Any, TypeVar

from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.node import Node
from rclpy.publisher import Publisher

from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

if TYPE_CHECKING:
    pass


class CountingPublisher(Publisher):
    """A publisher that counts what it sent. Pass ``publisher_class=CountingPublisher`` to
    ``create_publisher``; ``run_node`` logs the counts when the node stops (``published:
    /topic=N ...``, read back by ``parse_published_counts``), so a recording can be
    checked for lost messages."""

    sent = 0

    def publish(self, msg: Any) -> None:
        """Publish ``msg`` and count it in ``sent``."""
        super().publish(msg)
        self.sent += 1


def parse_published_counts(log_text: str) -> dict[str, int]:
    """{topic: messages published} from a node's 'published: /topic=N ...' log lines (a
    node may log several; a topic counted in several lines keeps the last count)."""
    lines = re.findall(r'published: (.*)', log_text)
    if not lines:
        raise ValueError('no "published:" line in the log')
    return {topic: int(n) for line in lines for topic, n in re.findall(r'(\S+)=(\d+)', line)}


def log_published_counts(node: Node) -> None:
    """Log how many messages each counting publisher of ``node`` sent (at shutdown)."""
    counts: dict[str, int] = {}
    for publisher in node.publishers:
        if isinstance(publisher, CountingPublisher):
            counts[publisher.topic_name] = counts.get(publisher.topic_name, 0) + publisher.sent
    if counts:
        node.get_logger().info('published: ' + ' '.join(f'{t}={n}' for t, n in counts.items()))


class Diagnostics:
    """Publishes DiagnosticArray on /diagnostics and logs rejected input, throttled.

    A reliable publisher drops what it sends before discovery matched a subscriber, and
    nodes report their start-up state at once: until some subscriber (a monitor, the
    recorder) has matched, the latest ``UNSENT_LIMIT`` arrays wait and go out first."""

    UNSENT_LIMIT = 20

    LEVELS = {
        'ok': DiagnosticStatus.OK,
        'warn': DiagnosticStatus.WARN,
        'error': DiagnosticStatus.ERROR,
        'stale': DiagnosticStatus.STALE,
    }

    def __init__(self, node: Node, hardware_id: str = 'simulation') -> None:
        self._node = node
        self._hardware_id = hardware_id
        self._publisher = node.create_publisher(
            DiagnosticArray, DIAGNOSTICS_TOPIC, DEFAULT_QOS, publisher_class=CountingPublisher
        )
        self._last_log: dict[str, float] = {}  # what -> time.monotonic() of its last log
        self._unsent: deque[DiagnosticArray] = deque(maxlen=self.UNSENT_LIMIT)
        self._lock = threading.Lock()  # nodes publish from worker threads too
        self.rejected: dict[str, int] = {}  # reason key -> count

    def publish(
        self, name: str, level: str, message: str, values: Mapping[str, object] | None = None
    ) -> None:
        """Publish the status ``name`` (prefixed with the node's name) at ``level`` ('ok',
        'warn', 'error' or 'stale') with ``message`` and ``values`` (as strings). Until a
        subscriber has matched, the latest ``UNSENT_LIMIT`` arrays are held back."""
        status = DiagnosticStatus(
            level=self.LEVELS[level],
            name=f'{self._node.get_name()}: {name}',
            message=message,
            hardware_id=self._hardware_id,
            values=[KeyValue(key=str(k), value=str(v)) for k, v in (values or {}).items()],
        )
        array = DiagnosticArray(status=[status])
        array.header.stamp = self._node.get_clock().now().to_msg()
        with self._lock:
            if self._publisher.get_subscription_count() == 0:
                self._unsent.append(array)
                return
            while self._unsent:
                self._publisher.publish(self._unsent.popleft())
            self._publisher.publish(array)

    def reject(self, what: str, error: Exception | str, throttle_s: float = 2.0) -> None:
        """Count and report bad input ``what`` (e.g. a topic); log at most every
        ``throttle_s`` [s] per kind of input."""
        self.rejected[what] = self.rejected.get(what, 0) + 1
        now = time.monotonic()
        if now - self._last_log.get(what, -math.inf) >= throttle_s:
            self._last_log[what] = now
            self._node.get_logger().warning(
                f'rejected {what}: {error} ({self.rejected[what]} so far)'
            )
        self.publish(f'rejected {what}', 'warn', str(error), {'count': self.rejected[what]})


_R = TypeVar('_R')


def guarded(what: str) -> Callable[[Callable[..., _R]], Callable[..., _R | None]]:
    """Decorate a node's timer, subscription or service callback so that no exception
    escapes it to the executor (that would end the process). An unexpected one goes to
    the node's ``on_internal_error(what, error)`` if it has one (pa10_ik_node stops the
    arm there), else it is reported as rejected ``what`` (one throttled log line and a
    diagnostic); a service callback ``(request, response)`` then answers success=false
    with the error. Expected bad input is rejected inside the callbacks with a better
    reason."""

    def decorate(callback: Callable[..., _R]) -> Callable[..., _R | None]:
        @functools.wraps(callback)
        def wrapper(self: Any, *args: Any) -> _R | None:  # self: the node, duck-typed
            try:
                return callback(self, *args)
            except Exception as error:  # noqa: BLE001 - the root rule: nothing escapes
                handler = getattr(self, 'on_internal_error', None)
                if handler is not None:
                    handler(what, error)
                else:
                    self.diagnostics.reject(what, f'{type(error).__name__}: {error}')
                if len(args) == 2 and hasattr(args[1], 'success'):  # a service response
                    response = args[1]
                    response.success, response.message = False, f'{what}: {error}'
                    return response
                return None

        return wrapper

    return decorate
