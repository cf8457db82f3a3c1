"""Holding a node's output until named subscribers have joined (with a time limit), so a
recorder or viewer started alongside misses nothing."""

from __future__ import annotations

import threading
import time
from collections.abc import (
    Iterable,
)
from typing import TYPE_CHECKING

from rclpy.node import Node
from rclpy.publisher import Publisher

from vgm_common.parameters import Param

if TYPE_CHECKING:
    pass


def subscriber_gate_params(what: str) -> list[Param]:
    """The three parameters of a SubscriberGate: ``min_subscribers`` (0 = open at once),
    ``wait_for_nodes`` and ``subscriber_timeout``; ``what`` says what waits and on which
    topics the count applies, e.g. 'Publish only once every camera topic has'."""
    return [
        Param(
            'min_subscribers',
            0,
            f'{what} this many matched subscribers (e.g. a recorder), at most '
            'subscriber_timeout: a reliable publisher drops what it sends before '
            'discovery. 0 = start at once.',
            range=(0, 100),
            read_only=True,
        ),
        Param(
            'wait_for_nodes',
            [],
            'Also wait until each of these nodes (a name, or '
            '/namespace/name) has a matched subscription on every topic the node '
            'publishes, e.g. [recorder]: a count alone is met by other subscribers '
            'while the recorder is still starting. Name only nodes that subscribe '
            'every stream from their start, never one that subscribes on demand '
            '(live_view, while a viewer watches): without its viewer the wait lasts '
            'subscriber_timeout.',
            check=_node_names,
            read_only=True,
        ),
        Param(
            'subscriber_timeout',
            30.0,
            '[s] Longest wait for min_subscribers and wait_for_nodes; then publishing '
            'starts with a warning naming what is missing.',
            range=(0.0, 3600.0),
            read_only=True,
        ),
    ]


def _node_names(names: Iterable[object]) -> str | None:
    """A reason if ``names`` holds anything but non-empty strings, else None."""
    bad = [name for name in names if not isinstance(name, str) or not name]
    return f'must hold node names, got {bad}' if bad else None


def _full_node_name(namespace: str, name: str) -> str:
    return f'{namespace.rstrip("/")}/{name}'


class SubscriberGate:
    """Holds streams back until their subscribers are there, or ``timeout`` [s] passed
    since its creation: a reliable publisher drops what it sends before discovery has
    matched a reader, so a recorder started alongside would miss a stream's first
    messages. Thread-safe; ``opened`` is set once open.

    Open when each of ``counted`` (default: all ``publishers``) has ``min_subscribers``
    matched subscribers, and each node of ``wait_for_nodes`` has subscribed to every one
    of ``publishers`` with every discovered subscription matched (the graph lists a
    subscription when it is discovered, the count says when it is matched)."""

    def __init__(
        self,
        node: Node,
        publishers: Iterable[Publisher],
        min_subscribers: int,
        timeout: float,
        wait_for_nodes: Iterable[str] = (),
        counted: Iterable[Publisher] | None = None,
    ) -> None:
        self._node, self._publishers = node, tuple(publishers)
        self._counted = self._publishers if counted is None else tuple(counted)
        self._min_subscribers, self._timeout = min_subscribers, timeout
        self._wait_for_nodes = tuple(wait_for_nodes)
        self._created = time.monotonic()
        self.opened = threading.Event()

    def missing(self) -> list[str]:
        """What the gate still waits for, as 'node on topic' / 'N of M on topic' texts."""
        missing = [
            f'{p.get_subscription_count()} of {self._min_subscribers} subscribers '
            f'on {p.topic_name}'
            for p in self._counted
            if p.get_subscription_count() < self._min_subscribers
        ]
        if not self._wait_for_nodes:
            return missing
        for publisher in self._publishers:
            infos = self._node.get_subscriptions_info_by_topic(publisher.topic_name)
            names = {info.node_name for info in infos} | {
                _full_node_name(info.node_namespace, info.node_name) for info in infos
            }
            missing += [
                f'{name} on {publisher.topic_name}'
                for name in self._wait_for_nodes
                if name not in names
            ]
            if publisher.get_subscription_count() < len(infos):
                missing.append(f'matching on {publisher.topic_name}')
        return missing

    def is_open(self) -> bool:
        """True once the gate is open: the subscribers are there or the timeout passed.
        Opening logs how long it waited (a warning naming what is missing after a
        timeout) and sets ``opened``; the gate then stays open."""
        if self.opened.is_set():
            return True
        missing = self.missing()
        waited = time.monotonic() - self._created
        if missing and waited <= self._timeout:
            return False
        if missing:
            self._node.get_logger().warning(
                f'publishing after {waited:.1f} s without: {"; ".join(missing)}'
            )
        elif self._min_subscribers or self._wait_for_nodes:
            self._node.get_logger().info(f'subscribers matched after {waited:.1f} s')
        self.opened.set()
        return True
