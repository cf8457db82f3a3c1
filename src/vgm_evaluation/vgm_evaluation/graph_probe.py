"""The running graph as a test, a bench or the demo sees it, through one rclpy node in
its own context: topics recorded, /diagnostics kept by status name, services called, and
bounded waits on conditions that, on timeout, say what the nodes reported last (a node
that stopped for a reason has said it on /diagnostics)."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import rclpy
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.executors import SingleThreadedExecutor
from rclpy.qos import QoSProfile
from std_srvs.srv import Trigger

from vgm_common.conversions import stamp_to_ns
from vgm_common.node_main import use_fastdds_profile
from vgm_common.qos import DEFAULT_QOS
from vgm_common.topics import DIAGNOSTICS_TOPIC

SPIN_STEP = 0.05  # [s] longest a wait blocks between checks of its condition
LAST_STATUSES_TOLD = 5  # statuses a timeout names


def status_values(status: DiagnosticStatus) -> dict[str, str]:
    """A diagnostic status's key/value pairs as a dict."""
    return {kv.key: kv.value for kv in status.values}


class GraphProbe:
    """One node named ``name`` on the environment's ROS domain, spun only inside
    ``wait``/``spin_once``. Subscribes /diagnostics from the start unless
    ``watch_diagnostics`` is False (then ``watch_diagnostics()`` later)."""

    def __init__(self, name: str = 'graph_probe', watch_diagnostics: bool = True) -> None:
        use_fastdds_profile()  # the graph's profile, as the nodes use
        self.context = rclpy.Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.statuses: list[DiagnosticStatus] = []  # every status, in arrival order
        # the header stamp [ns] of the array each of ``statuses`` came in (its publisher's
        # clock: when the node reported it, not when it arrived)
        self.status_stamps_ns: list[int] = []
        self._diagnostics_subscription: Any = None
        self._clients: dict[str, Any] = {}  # service name -> its client, kept
        if watch_diagnostics:
            self.watch_diagnostics()

    def watch_diagnostics(self) -> None:
        """Keep every status published on /diagnostics from now on."""
        if self._diagnostics_subscription is None:
            self._diagnostics_subscription = self.node.create_subscription(
                DiagnosticArray,
                DIAGNOSTICS_TOPIC,
                self._on_diagnostics,
                DEFAULT_QOS,
            )

    def _on_diagnostics(self, msg: DiagnosticArray) -> None:
        self.statuses.extend(msg.status)
        self.status_stamps_ns.extend([stamp_to_ns(msg.header.stamp)] * len(msg.status))

    def record(self, topic: str, kind: type, qos: QoSProfile = DEFAULT_QOS) -> list[Any]:
        """A list the messages of ``topic`` are appended to as they arrive."""
        received: list[Any] = []
        self.node.create_subscription(kind, topic, received.append, qos)
        return received

    def status(self, name: str, containing: str = '') -> DiagnosticStatus | None:
        """The newest status whose name ends with ``name`` and whose message contains
        ``containing``, or None."""
        for status in reversed(self.statuses):
            if status.name.endswith(name) and containing in status.message:
                return status
        return None

    def spin_once(self, timeout: float = SPIN_STEP) -> None:
        """Serve what has arrived, waiting up to ``timeout`` [s] for something."""
        self.executor.spin_once(timeout_sec=timeout)

    def wait(self, condition: Callable[[], Any], timeout: float, what: str = 'condition') -> Any:
        """Spin until ``condition()`` is truthy (returned) or ``timeout`` [s] passed: then
        TimeoutError naming ``what`` and the last statuses the nodes published."""
        deadline = time.monotonic() + timeout
        while not (result := condition()):
            if time.monotonic() > deadline:
                raise TimeoutError(
                    f'timed out after {timeout:.0f} s waiting for {what}; '
                    f'last statuses: {self.last_statuses()}'
                )
            self.spin_once()
        return result

    def last_statuses(self, count: int = LAST_STATUSES_TOLD) -> list[str]:
        """'name: message {values}' of the newest ``count`` statuses."""
        return [
            f'{s.name}: {s.message} {status_values(s)}' if s.values else f'{s.name}: {s.message}'
            for s in self.statuses[-count:]
        ]

    def call(
        self,
        service: str,
        timeout: float = 20.0,
        *,
        srv_type: Any = Trigger,
        request: Any = None,
        give_up: Callable[[], bool] | None = None,
    ) -> Any:
        """The response of ``service`` (a Trigger service unless ``srv_type``; an empty
        request unless ``request``) once it is there, or None if ``give_up()`` turned true
        first (e.g. the process serving it died). The client is kept for the next call: a
        new one would wait for discovery again, and the first answer to a client whose
        response reader is not yet discovered can be lost."""
        client = self._clients.get(service)
        if client is None:
            client = self._clients[service] = self.node.create_client(srv_type, service)
        stopped = give_up or (lambda: False)
        self.wait(lambda: client.service_is_ready() or stopped(), timeout, f'service {service}')
        if stopped():
            return None
        future = client.call_async(srv_type.Request() if request is None else request)
        self.wait(lambda: future.done() or stopped(), timeout, f'the response of {service}')
        return future.result() if future.done() else None

    def close(self) -> None:
        """Destroy the node and shut its context down."""
        self.executor.shutdown()
        self.node.destroy_node()
        rclpy.shutdown(context=self.context)
