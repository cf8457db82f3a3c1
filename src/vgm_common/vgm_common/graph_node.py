"""The base class of the project's nodes: parameters, diagnostics and the check that every
topic it uses carries the type it expects."""

from __future__ import annotations

from collections.abc import (
    Callable,
    Mapping,
    Sequence,
)
from typing import TYPE_CHECKING, Any, ClassVar

from rclpy.node import Node

from vgm_common.diagnostics import Diagnostics
from vgm_common.errors import VgmError
from vgm_common.parameters import NodeParameters, Param

if TYPE_CHECKING:
    pass


class TopicTypeError(VgmError):
    """A topic the node would publish or subscribe already carries another type."""


def message_type_name(msg_type: Any) -> str:
    """'sensor_msgs/msg/Image' for the Python class of a ROS message."""
    package, interface = msg_type.__module__.split('.')[:2]
    return f'{package}/{interface}/{msg_type.__name__}'


TYPE_CHECK_PERIOD = 2.0  # [s] how often a node looks for other types on its topics


class GraphNode(Node):
    """What every node of the graph starts with: a Node named by the class's
    ``node_name``, its ``diagnostics`` (on /diagnostics) and its ``params``
    (NodeParameters of ``parameters``, a refused change reported to the diagnostics;
    ``on_change`` as there, ``renamed_parameters`` its ``renamed``).

    A publisher or subscription on a topic that already carries another type (a remap
    such as ``-r /tool/pressure:=/joint_states``) is a TopicTypeError naming both types
    (a start-up error); a typed subscription whose topic gets a publisher of another
    type later is one error line and diagnostic naming both, every TYPE_CHECK_PERIOD."""

    node_name: ClassVar[str]
    renamed_parameters: ClassVar[Mapping[str, str]] = {}

    def __init__(
        self,
        parameters: Sequence[Param],
        on_change: Mapping[str, Callable[[Any], None]] | None = None,
        **kwargs: Any,
    ) -> None:
        # Node.__init__ already creates publishers through create_publisher.
        self._own_types: dict[str, str] = {}  # resolved topic -> its type in this node
        self._typed_subscriptions: dict[str, tuple[str, str]] = {}  # -> (type, name given)
        self._reported_types: set[tuple[str, str]] = set()  # (topic, other type) logged
        super().__init__(self.node_name, **kwargs)
        self.diagnostics = Diagnostics(self)
        self.params = NodeParameters(
            self, parameters, self.diagnostics, on_change, self.renamed_parameters
        )
        self.create_timer(TYPE_CHECK_PERIOD, self._check_topic_types)

    def create_publisher(self, msg_type: Any, topic: str, *args: Any, **kwargs: Any) -> Any:
        """Node.create_publisher, refusing a topic that carries another type in this node
        (rcl would fail with 'invalid allocator')."""
        self._claim_topic(msg_type, topic, foreign_too=False)
        return super().create_publisher(msg_type, topic, *args, **kwargs)

    def create_subscription(
        self,
        msg_type: Any,
        topic: str,
        callback: Callable[[Any], None],  # as rclpy annotates it
        *args: Any,
        **kwargs: Any,
    ) -> Any:
        """Node.create_subscription, refusing a topic known to carry another type (DDS
        would deliver nothing, or rcl fail with 'invalid allocator'); a raw subscription
        (of whatever type a topic has: recorder, live_view) is not checked later."""
        resolved = self._claim_topic(msg_type, topic, foreign_too=not kwargs.get('raw'))
        if not kwargs.get('raw'):
            self._typed_subscriptions[resolved] = (message_type_name(msg_type), topic)
        return super().create_subscription(msg_type, topic, callback, *args, **kwargs)

    def _claim_topic(self, msg_type: Any, topic: str, foreign_too: bool) -> str:
        resolved = self.resolve_topic_name(topic)
        ours = message_type_name(msg_type)
        others = {self._own_types.get(resolved, ours)} - {ours}
        if foreign_too:
            others |= set(dict(self.get_topic_names_and_types()).get(resolved, ())) - {ours}
        if others:
            raise TopicTypeError(
                f'{self._topic_as_given(topic)} carries {", ".join(sorted(others))}; '
                f'this node needs {ours} there',
                key=resolved,
                value=sorted(others),
            )
        self._own_types.setdefault(resolved, ours)
        return resolved

    def _topic_as_given(self, topic: str) -> str:
        """'/tool/pressure (remapped to /joint_states)', or the topic if not remapped."""
        expanded = self.resolve_topic_name(topic, only_expand=True)
        resolved = self.resolve_topic_name(topic)
        return resolved if expanded == resolved else f'{expanded} (remapped to {resolved})'

    def _check_topic_types(self) -> None:
        """One error line and diagnostic per other type seen on a typed subscription's
        topic: its messages never arrive, and without a word the node would just wait."""
        types = dict(self.get_topic_names_and_types())
        for resolved, (ours, given) in self._typed_subscriptions.items():
            for other in sorted(set(types.get(resolved, ())) - {ours}):
                if (resolved, other) in self._reported_types:
                    continue
                self._reported_types.add((resolved, other))
                message = (
                    f'{self._topic_as_given(given)} carries {other}; this node '
                    f'subscribes it as {ours} and receives none of those'
                )
                self.get_logger().error(message)
                self.diagnostics.publish(
                    'topic type', 'error', message, {'topic': resolved, 'type': other}
                )
