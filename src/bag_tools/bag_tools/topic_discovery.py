"""The graph's topics as ``ros2 bag record -a`` takes them, found while running: shared by
the recorder and live_view, which both subscribe to whatever is published, raw.

A topic is taken once it has a publisher (one only subscribed has nothing to give), is
wanted (``topics`` / ``exclude`` / ``include_hidden_topics``: every topic but hidden ones by
default, exactly as ``ros2 bag record -a``), has one type, and that type's Python class and
definition are installed. One that fails a check is skipped for good, with a warning."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Container, Iterable
from typing import Any, NamedTuple

from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rclpy.topic_endpoint_info import TopicEndpointInfo

from bag_tools.message_definitions import DefinitionNotFoundError, definition
from vgm_common.parameters import NodeParameters, Param

SUBSCRIPTION_DEPTH = 1000  # keep-last depth of every subscription: 5 s of 200 Hz joint
# states, so a recorder stalled by a loaded machine catches up without loss


def import_message_type(type_name: str) -> Any:
    """The Python class of ``pkg/msg/Type``. Raises ImportError/AttributeError if absent."""
    package, interface, name = type_name.split('/')
    return getattr(importlib.import_module(f'{package}.{interface}'), name)


def topic_is_hidden(name: str) -> bool:
    """rclpy's rule (and rosbag2's): any name token starting with ``_``."""
    return any(token.startswith('_') for token in name.split('/'))


def _absolute_names(names: Iterable[str]) -> str | None:
    """A reason if a topic list holds a name that is not absolute, else None."""
    relative = [name for name in names if not name.startswith('/')]
    return f'must hold absolute topic names, got {relative}' if relative else None


def topic_selection_params(
    verb: str, done: str, discovery_period: float, exclude_example: str = ''
) -> list[Param]:
    """The parameters of a TopicDiscovery: ``topics``, ``exclude``,
    ``include_hidden_topics``, ``discovery_period`` [s]; ``verb`` / ``done`` say what is
    done with a topic ('record' / 'recorded')."""
    return [
        Param(
            'topics',
            [],
            f'Topics to {verb} (exact names); empty = every published topic.',
            check=_absolute_names,
            read_only=True,
        ),
        Param(
            'exclude',
            [],
            f'Topics never {done} (exact names){exclude_example}.',
            check=_absolute_names,
            read_only=True,
        ),
        Param(
            'include_hidden_topics',
            False,
            f'Also {verb} hidden topics (a name token starting with _).',
            read_only=True,
        ),
        Param(
            'discovery_period',
            discovery_period,
            '[s] How often the graph is polled for new topics.',
            range=(0.01, 60.0),
            read_only=True,
        ),
    ]


def subscription_qos(publisher_qos_profiles: Iterable[QoSProfile]) -> QoSProfile:
    """The QoS that receives from all the given publishers (rosbag2's adapt_request_to_offers):
    reliable if every publisher is, else best effort; transient local if every publisher is
    (a transient local subscription does not match a volatile publisher), else volatile;
    keep last SUBSCRIPTION_DEPTH."""
    profiles = list(publisher_qos_profiles)
    reliable = bool(profiles) and all(
        p.reliability == ReliabilityPolicy.RELIABLE for p in profiles
    )
    transient_local = bool(profiles) and all(
        p.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in profiles
    )
    return QoSProfile(
        history=HistoryPolicy.KEEP_LAST,
        depth=SUBSCRIPTION_DEPTH,
        reliability=ReliabilityPolicy.RELIABLE if reliable else ReliabilityPolicy.BEST_EFFORT,
        durability=(
            DurabilityPolicy.TRANSIENT_LOCAL if transient_local else DurabilityPolicy.VOLATILE
        ),
    )


class DiscoveredTopic(NamedTuple):
    """A topic found to take: its name, its one type ``pkg/msg/Type``, that type's class and
    definition, and its publishers."""

    name: str
    type_name: str
    message_type: Any  # the message class
    definition: tuple[str, str]  # (encoding, text) of message_definitions.definition
    publishers: list[TopicEndpointInfo]  # its publishers when found


class TopicDiscovery:
    """Polls ``node``'s graph for topics to take, by the rules above; ``params`` holds the
    values of ``topic_selection_params``; ``doing`` names what is done in the warnings
    ('recording': 'not recording /x: ...'). ``skipped``: the topics skipped for good."""

    def __init__(self, node: Node, params: NodeParameters, doing: str) -> None:
        self._node = node
        self.wanted_topics: set[str] = set(params.topics)
        self.excluded: set[str] = set(params.exclude)
        self._include_hidden: bool = params.include_hidden_topics
        self._doing = doing
        self.skipped: set[str] = set()

    def wanted(self, name: str) -> bool:
        """True if ``name`` is to be taken by the selection parameters: not excluded, listed
        in ``topics`` if that is set, else not hidden unless ``include_hidden_topics``."""
        if name in self.excluded:
            return False
        if self.wanted_topics:
            return name in self.wanted_topics
        return self._include_hidden or not topic_is_hidden(name)

    def skip(self, name: str, reason: str) -> None:
        """Skip ``name`` for good and log a warning with ``reason``."""
        self.skipped.add(name)
        self._node.get_logger().warning(f'not {self._doing} {name}: {reason}')

    def poll(
        self,
        taken: Container[str],
        on_types_of_taken: Callable[[str, list[str]], None] | None = None,
    ) -> list[DiscoveredTopic]:
        """The DiscoveredTopics new since the last poll: not in ``taken`` (the caller's)
        nor skipped. ``on_types_of_taken(name, types)`` sees each taken topic's types."""
        found = []
        for name, types in self._node.get_topic_names_and_types():
            if name in taken:
                if on_types_of_taken is not None:
                    on_types_of_taken(name, types)
                continue
            if name in self.skipped or not self.wanted(name):
                continue
            if len(types) != 1:
                self.skip(name, f'published with several types {types}')
                continue
            publishers = self._node.get_publishers_info_by_topic(name)
            if not publishers:
                continue  # only subscribed so far: nothing to take (as rosbag2)
            try:
                message_type = import_message_type(types[0])
                text = definition(types[0])
            except (ImportError, AttributeError, ValueError, DefinitionNotFoundError) as error:
                self.skip(name, f'type {types[0]} is not installed ({error})')
                continue
            found.append(DiscoveredTopic(name, types[0], message_type, text, publishers))
        return found
