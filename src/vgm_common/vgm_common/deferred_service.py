"""A std_srvs/Trigger service answered later: ``on_call(reply)`` receives each call and
calls ``reply(success, message)`` when the work it waits for is done, from any thread.

Under ``DeferredServiceExecutor`` no executor thread waits for the answer; under another
executor the call waits on its own thread, up to ``max_wait()`` seconds.

The replies to waiting calls come in bursts (one result answers them all). Every client of
a service receives every reply (rmw_fastrtps: each client's reader keeps them and drops
those not its own when its caller takes them), in the caller's history (rclpy's default:
keep-last 10); twenty replies at once reached 10 to 13 of twenty callers in one process,
nothing said. So replies go out paced, one each REPLY_PERIOD (ten take 0.2 s: a caller
that spins gets its own), and the service's own history holds ``max_calls`` requests and
replies. A caller that does not spin while more than its history of other replies goes
out can still miss its own; only its QoS can help it (a deeper response history).
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from rclpy.callback_groups import MutuallyExclusiveCallbackGroup, ReentrantCallbackGroup
from rclpy.qos import QoSProfile, qos_profile_services_default
from std_srvs.srv import Trigger

from vgm_common.diagnostics import guarded
from vgm_common.node_main import DeferredCallback

if TYPE_CHECKING:
    from rclpy.node import Node

    from vgm_common.diagnostics import Diagnostics

REPLIES_PER_PERIOD = 1
REPLY_PERIOD = 0.02  # [s]

Reply = Callable[[bool, str], None]


class DeferredTriggerService:
    """The service ``name`` of ``node``; ``diagnostics`` hears of replies that fail."""

    def __init__(
        self,
        node: Node,
        name: str,
        on_call: Callable[[Reply], None],
        max_wait: Callable[[], float],
        max_calls: int,
        diagnostics: Diagnostics,
    ) -> None:
        self.diagnostics = diagnostics  # for @guarded
        self._on_call = on_call
        self._max_wait = max_wait
        self._lock = threading.Lock()
        self._outgoing: deque[tuple[Trigger.Response, Any]] = deque()  # (response, header)
        qos = QoSProfile(
            history=qos_profile_services_default.history,
            depth=max_calls,
            reliability=qos_profile_services_default.reliability,
            durability=qos_profile_services_default.durability,
        )
        self._service = node.create_service(
            Trigger,
            name,
            DeferredCallback(self._on_request, self._on_blocking_request),
            qos_profile=qos,
            callback_group=ReentrantCallbackGroup(),
        )
        self._name = name
        node.create_timer(
            REPLY_PERIOD, self._send_replies, callback_group=MutuallyExclusiveCallbackGroup()
        )

    @guarded('service request')
    def _on_request(self, request: Trigger.Request, header: Any) -> None:
        def reply(success: bool, message: str) -> None:
            with self._lock:
                self._outgoing.append((Trigger.Response(success=success, message=message), header))

        self._on_call(reply)

    def _on_blocking_request(
        self, request: Trigger.Request, response: Trigger.Response
    ) -> Trigger.Response:
        done = threading.Event()
        result: dict[str, Any] = {}

        def reply(success: bool, message: str) -> None:
            result.update(success=success, message=message)
            done.set()

        self._on_call(reply)
        done.wait(self._max_wait())
        response.success = result.get('success', False)
        response.message = result.get('message', 'no answer')
        return response

    @guarded('service reply')
    def _send_replies(self, limit: int | None = REPLIES_PER_PERIOD) -> None:
        """Send up to ``limit`` queued replies (None: all)."""
        with self._lock:
            count = len(self._outgoing) if limit is None else min(limit, len(self._outgoing))
            batch = [self._outgoing.popleft() for _ in range(count)]
        for response, header in batch:
            try:
                self._service.send_response(response, header)
            except Exception as error:  # noqa: BLE001 - the caller may be gone
                self.diagnostics.reject(f'{self._name} reply', error)

    def flush(self) -> None:
        """Send every queued reply now (at shutdown)."""
        self._send_replies(None)
